//! A system's view of its own state, for recorders and viewers.

#[allow(unused_imports)]
use super::*;

/// Largest view a system publishes of its own state, bytes (JSON).
pub const MAX_VIZ: usize = 16 * 1024;
/// Most readers of one system's view at once (recorders, viewers).
const MAX_VIZ_READERS: usize = 8;

fn viz_service(
    node: &Node<Ipc>,
    inst: &Instance,
    system: &str,
) -> Result<StreamFactory, TransportError> {
    let name = inst.viz(system);
    node.service_builder(&service_name(&name)?)
        .publish_subscribe::<[u8]>()
        .max_publishers(2)
        .max_subscribers(MAX_VIZ_READERS)
        .max_nodes(MAX_VIZ_READERS + 2)
        .subscriber_max_buffer_size(2)
        .history_size(0)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| svc_err(&name, e))
}

/// A system's end of its view ([`crate::viz::SystemView`]).
pub struct VizWriter {
    publisher: Publisher<Ipc, [u8], ()>,
    name: String,
}

impl VizWriter {
    /// Opens system `system`'s view for writing.
    pub fn open(node: &Node<Ipc>, inst: &Instance, system: &str) -> Result<Self, TransportError> {
        let publisher = viz_service(node, inst, system)?
            .publisher_builder()
            .initial_max_slice_len(MAX_VIZ)
            .allocation_strategy(AllocationStrategy::Static)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| svc_err(&inst.viz(system), e))?;
        Ok(VizWriter {
            publisher,
            name: inst.viz(system),
        })
    }

    /// Publishes `view`; a view too large is cut (its plans' paths, then its tracks)
    /// until it fits.
    pub fn publish(&mut self, view: &crate::viz::SystemView) -> Result<(), TransportError> {
        let err = |e: &dyn std::fmt::Debug| svc_err(&self.name, e);
        let mut bytes = serde_json::to_vec(view).map_err(|e| err(&e))?;
        if bytes.len() > MAX_VIZ {
            let mut v = view.clone();
            for p in &mut v.plans {
                p.path.truncate(64);
            }
            v.tracks.truncate(32);
            bytes = serde_json::to_vec(&v).map_err(|e| err(&e))?;
            if bytes.len() > MAX_VIZ {
                return Err(err(&format!("a view of {} bytes", bytes.len())));
            }
        }
        use iceoryx2::port::update_connections::UpdateConnections;
        // A reader that opened since the last view gets this one.
        let _ = self.publisher.update_connections();
        let sample = self
            .publisher
            .loan_slice_uninit(bytes.len())
            .map_err(|e| err(&e))?;
        sample
            .write_from_slice(&bytes)
            .send()
            .map_err(|e| err(&e))?;
        Ok(())
    }
}

/// A reader of one system's view.
pub struct VizReader {
    subscriber: Subscriber<Ipc, [u8], ()>,
}

impl VizReader {
    /// Opens system `system`'s view for reading (made if the system has not yet).
    pub fn open(node: &Node<Ipc>, inst: &Instance, system: &str) -> Result<Self, TransportError> {
        let subscriber = viz_service(node, inst, system)?
            .subscriber_builder()
            .buffer_size(2)
            .create()
            .map_err(|e| svc_err(&inst.viz(system), e))?;
        Ok(VizReader { subscriber })
    }

    /// The newest view published since the last call, if any (views that do not decode
    /// are skipped).
    pub fn latest(&mut self) -> Option<crate::viz::SystemView> {
        let mut newest = None;
        while let Ok(Some(sample)) = self.subscriber.receive() {
            match serde_json::from_slice(sample.payload()) {
                Ok(v) => newest = Some(v),
                Err(e) => tracing::debug!("a bad system view: {e}"),
            }
        }
        newest
    }
}
