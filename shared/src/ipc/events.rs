//! The broker's event feed: its writer and readers.

#[allow(unused_imports)]
use super::*;

// The publisher's segment holds readers × (buffer + 2) + history records of
// `MAX_EVENT` bytes, made when a broker starts serving: 8 × 258 + 128 records of 2 KiB
// are 4.4 MB. (16 readers × 1024 of 4 KiB were 68 MB, and a standby taking over paused
// its systems' streams making them.)
/// Most readers of a broker's event feed at once (consoles, recorders).
pub const MAX_EVENT_READERS: usize = 8;
/// Largest event record on the feed, bytes (JSON).
pub const MAX_EVENT: usize = 2 * 1024;
/// Events a reader that joins late gets first (the feed's history).
pub const EVENT_HISTORY: usize = 128;
/// Events a reader holds before the oldest unread ones are overwritten.
const EVENT_BUFFER: usize = 256;

fn event_services(
    node: &Node<Ipc>,
    inst: &Instance,
) -> Result<(StreamFactory, EventFactory, EventFactory), TransportError> {
    let name = inst.events();
    let stream = node
        .service_builder(&service_name(&name)?)
        .publish_subscribe::<[u8]>()
        // Each broker in turn (a standby taking over adds its own).
        .max_publishers(8)
        .max_subscribers(MAX_EVENT_READERS)
        .max_nodes(MAX_EVENT_READERS + 8)
        .subscriber_max_buffer_size(EVENT_BUFFER)
        .history_size(EVENT_HISTORY)
        // A slow reader loses its oldest events, never holds the broker up.
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| svc_err(&name, e))?;
    let bell = |name: String, notifiers: usize, listeners: usize| {
        node.service_builder(&service_name(&name)?)
            .event()
            .max_notifiers(notifiers)
            .max_listeners(listeners)
            .max_nodes(MAX_EVENT_READERS + 8)
            .open_or_create()
            .map_err(|e| svc_err(&name, e))
    };
    // News: the brokers ring, the readers listen. Hello: the other way round.
    let news = bell(inst.events_bell(), 8, MAX_EVENT_READERS)?;
    let hello = bell(inst.events_hello(), MAX_EVENT_READERS, 8)?;
    Ok((stream, news, hello))
}

/// The id a reader rings the feed's bell with when it opens: the broker then hands it
/// the feed's history (iceoryx2 delivers it as the publisher updates its connections).
const READER_HELLO: usize = 1;

/// The broker's end of its event feed.
pub struct EventWriter {
    publisher: Publisher<Ipc, [u8], ()>,
    notifier: Notifier<Ipc>,
    listener: Listener<Ipc>,
    epoch: String,
    seq: u64,
}

impl EventWriter {
    /// Opens the feed for writing, for the broker run numbered `epoch`.
    pub fn open(node: &Node<Ipc>, inst: &Instance, epoch: u64) -> Result<Self, TransportError> {
        let (stream, news, hello) = event_services(node, inst)?;
        let publisher = stream
            .publisher_builder()
            .initial_max_slice_len(MAX_EVENT)
            .allocation_strategy(AllocationStrategy::Static)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| svc_err(&inst.events(), e))?;
        let notifier = news
            .notifier_builder()
            .create()
            .map_err(|e| svc_err(&inst.events_bell(), e))?;
        let listener = hello
            .listener_builder()
            .create()
            .map_err(|e| svc_err(&inst.events_hello(), e))?;
        Ok(EventWriter {
            publisher,
            notifier,
            listener,
            epoch: format!("{epoch:016x}"),
            seq: 0,
        })
    }

    /// The bell's file descriptor (readers ring it when they open), for the reactor.
    pub fn fd(&self) -> RawFd {
        // SAFETY: the descriptor stays owned by the listener; we only read its number.
        unsafe { self.listener.file_descriptor().native_handle() }
    }

    /// The bell rang: a reader that just opened gets the feed's history.
    pub fn on_bell(&self) {
        if drain_ids(&self.listener) & (1 << READER_HELLO) != 0 {
            use iceoryx2::port::update_connections::UpdateConnections;
            if let Err(e) = self.publisher.update_connections() {
                tracing::debug!("events: {e:?}");
            }
            self.ring();
        }
    }

    /// Publishes `event` (numbered, stamped with the Unix time) and returns its record's
    /// JSON; an event too large for the feed is dropped with a warning (`None`).
    pub fn publish(
        &mut self,
        event: crate::protocol::BrokerEvent,
    ) -> Result<Option<String>, TransportError> {
        self.seq += 1;
        let t_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
        let rec = crate::protocol::EventRecord {
            epoch: self.epoch.clone(),
            seq: self.seq,
            t_ns,
            event,
        };
        let err = |e: &dyn std::fmt::Debug| svc_err("events", e);
        let json = serde_json::to_string(&rec).map_err(|e| err(&e))?;
        let bytes = json.as_bytes();
        if bytes.len() > MAX_EVENT {
            tracing::warn!(
                len = bytes.len(),
                "an event too large for the feed: dropped"
            );
            return Ok(None);
        }
        let sample = self
            .publisher
            .loan_slice_uninit(bytes.len())
            .map_err(|e| err(&e))?;
        let sample = sample.write_from_slice(bytes);
        sample.send().map_err(|e| err(&e))?;
        Ok(Some(json))
    }

    /// Wakes the feed's readers.
    pub fn ring(&self) {
        if let Err(e) = self.notifier.notify() {
            tracing::debug!("events bell: {e:?}");
        }
    }
}

/// A reader of a broker's event feed.
pub struct EventReader {
    subscriber: Subscriber<Ipc, [u8], ()>,
    listener: Listener<Ipc>,
    _notifier: Notifier<Ipc>,
}

impl EventReader {
    /// Opens the feed for reading: the first events read are the feed's recent history.
    pub fn open(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let (stream, news, hello) = event_services(node, inst)?;
        let subscriber = stream
            .subscriber_builder()
            .buffer_size(EVENT_BUFFER)
            .create()
            .map_err(|e| svc_err(&inst.events(), e))?;
        let listener = news
            .listener_builder()
            .create()
            .map_err(|e| svc_err(&inst.events_bell(), e))?;
        let notifier = hello
            .notifier_builder()
            .create()
            .map_err(|e| svc_err(&inst.events_hello(), e))?;
        // Tell the broker we are here, for the history.
        if let Err(e) = notifier.notify_with_custom_event_id(EventId::new(READER_HELLO)) {
            tracing::debug!("events bell: {e:?}");
        }
        Ok(EventReader {
            subscriber,
            listener,
            _notifier: notifier,
        })
    }

    /// The bell's file descriptor, for a reactor.
    pub fn fd(&self) -> RawFd {
        // SAFETY: the descriptor stays owned by the listener; we only read its number.
        unsafe { self.listener.file_descriptor().native_handle() }
    }

    /// Waits up to `timeout` for the bell (returns at once if events wait).
    pub fn wait(&self, timeout: Duration) {
        let _ = self.listener.timed_wait(|_| {}, timeout);
    }

    /// The next waiting event, if any; records that do not decode are skipped (counted
    /// in the log).
    pub fn next_event(&mut self) -> Option<crate::protocol::EventRecord> {
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => match serde_json::from_slice(sample.payload()) {
                    Ok(r) => return Some(r),
                    Err(e) => tracing::debug!("a bad record on the event feed: {e}"),
                },
                Ok(None) => return None,
                Err(e) => {
                    tracing::debug!("event feed: {e:?}");
                    return None;
                }
            }
        }
    }
}
