//! The instance's presence event (a broker announcing itself) and bell ringers that
//! ring an address without sending frames.

#[allow(unused_imports)]
use super::*;

/// The presence event: a starting broker rings it; systems and users wait on it.
pub struct Presence {
    listener: Option<Listener<Ipc>>,
    notifier: Option<Notifier<Ipc>>,
}

fn presence_service(
    node: &Node<Ipc>,
    inst: &Instance,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<Ipc>, TransportError> {
    let name = inst.presence();
    node.service_builder(&service_name(&name)?)
        .event()
        .max_listeners(MAX_PARTICIPANTS)
        // Brokers and standbys; a killed one's notifier stays until it is cleaned up.
        .max_notifiers(16)
        .max_nodes(MAX_PARTICIPANTS + 4)
        .event_id_max_value(bell::MAX)
        .open_or_create()
        .map_err(|e| svc_err(&name, e))
}

impl Presence {
    /// A listener, for systems and users.
    pub fn listen(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let svc = presence_service(node, inst)?;
        let listener = svc
            .listener_builder()
            .create()
            .map_err(|e| svc_err(&inst.presence(), e))?;
        Ok(Presence {
            listener: Some(listener),
            notifier: None,
        })
    }

    /// A notifier, for the broker.
    pub fn announce(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let svc = presence_service(node, inst)?;
        let notifier = svc
            .notifier_builder()
            .create()
            .map_err(|e| svc_err(&inst.presence(), e))?;
        Ok(Presence {
            listener: None,
            notifier: Some(notifier),
        })
    }

    /// Connects the notifier to every listener now, so that a later ring does not pay
    /// for it (a standby, ready to announce its takeover at once).
    pub fn prepare(&self) {
        use iceoryx2::port::update_connections::UpdateConnections;
        if let Some(n) = &self.notifier {
            if let Err(e) = n.update_connections() {
                tracing::debug!("presence connections: {e:?}");
            }
        }
    }

    /// Rings every listener with `id` (broker only).
    pub fn ring(&self, id: usize) {
        if let Some(n) = &self.notifier {
            if let Err(e) = n.notify_with_custom_event_id(EventId::new(id)) {
                tracing::warn!("presence notify failed: {e:?}");
            }
        }
    }

    /// The listener's file descriptor (listeners only).
    pub fn fd(&self) -> Option<RawFd> {
        // SAFETY: the descriptor stays owned by the listener; we only read its number.
        self.listener
            .as_ref()
            .map(|l| unsafe { l.file_descriptor().native_handle() })
    }

    /// Empties the listener; returns the ids rung as bits.
    pub fn drain(&self) -> u64 {
        self.listener.as_ref().map_or(0, drain_ids)
    }
}

/// A notifier on one address's bell, for ringing it without sending frames (a standby
/// asking the primary broker for its state).
pub struct BellRinger {
    inst: Instance,
    to: Address,
    bell_name: String,
    notifier: Option<Notifier<Ipc>>,
}

impl BellRinger {
    /// A ringer for `to`'s bell; the bell is opened at the first ring.
    pub fn open(node: &Node<Ipc>, inst: &Instance, to: &Address) -> Result<Self, TransportError> {
        let mut r = BellRinger {
            inst: inst.clone(),
            to: to.clone(),
            bell_name: String::new(),
            notifier: None,
        };
        r.connect(node);
        Ok(r)
    }

    fn connect(&mut self, node: &Node<Ipc>) {
        let name = self.inst.bell(&self.to);
        self.bell_name = name.clone();
        self.notifier = service_name(&name)
            .ok()
            .and_then(|n| node.service_builder(&n).event().open().ok())
            .and_then(|svc| svc.notifier_builder().create().ok());
    }

    /// Rings `id`; an error means nobody has that bell (yet).
    pub fn ring(&mut self, id: usize) -> Result<(), TransportError> {
        match &self.notifier {
            Some(n) => n
                .notify_with_custom_event_id(EventId::new(id))
                .map(|_| ())
                .map_err(|e| svc_err(&self.bell_name, e)),
            None => Err(TransportError::Unreachable(self.to.clone())),
        }
    }

    /// Tries to open the bell again (its owner was not there before).
    pub fn reconnect(&mut self, node: &Node<Ipc>) {
        if self.notifier.is_none() {
            self.connect(node);
        }
    }
}
