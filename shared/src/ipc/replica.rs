//! The replication stream from the primary broker to its standbys.

#[allow(unused_imports)]
use super::*;

/// Most standbys following one instance's primary.
pub const MAX_STANDBYS: usize = 4;
/// Parts a standby's queue holds; one that falls further behind loses records and asks
/// for a new image.
const REPLICA_BUFFER: usize = 256;
/// Largest part of a record on the stream: larger records (a whole state, a large
/// registration) travel in several. Samples are of this fixed size, so the stream's
/// shared memory is bounded (parts × buffer × standbys: 8 MiB).
pub const REPLICA_PART: usize = 8 * 1024;
/// Each part starts with its record's number of parts and its own index (u32 each),
/// padded to 16 bytes so that the record's bytes stay aligned for rkyv.
const PART_HEADER: usize = 16;

pub(super) type StreamFactory =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], ()>;
pub(super) type EventFactory = iceoryx2::service::port_factory::event::PortFactory<Ipc>;

fn replica_services(
    node: &Node<Ipc>,
    inst: &Instance,
) -> Result<(StreamFactory, EventFactory), TransportError> {
    let name = inst.replica();
    let stream = node
        .service_builder(&service_name(&name)?)
        .publish_subscribe::<[u8]>()
        // rkyv reads a record in place: its bytes must be aligned like an AlignedVec.
        .payload_alignment(Alignment::new(16).expect("16 is a power of two"))
        // Each primary in turn; a killed one's publisher stays until it is cleaned up.
        .max_publishers(8)
        .max_subscribers(MAX_STANDBYS)
        .max_nodes(MAX_STANDBYS + 4)
        .subscriber_max_buffer_size(REPLICA_BUFFER)
        .subscriber_max_borrowed_samples(4)
        .history_size(0)
        .enable_safe_overflow(false)
        .open_or_create()
        .map_err(|e| svc_err(&name, e))?;
    let bell_name = inst.replica_bell();
    let bell = node
        .service_builder(&service_name(&bell_name)?)
        .event()
        .max_notifiers(8)
        .max_listeners(MAX_STANDBYS)
        .max_nodes(MAX_STANDBYS + 4)
        .event_id_max_value(bell::MAX)
        .open_or_create()
        .map_err(|e| svc_err(&bell_name, e))?;
    Ok((stream, bell))
}

/// A primary broker's end of the replication stream.
pub struct ReplicaWriter {
    publisher: Publisher<Ipc, [u8], ()>,
    notifier: Notifier<Ipc>,
    stream: StreamFactory,
}

impl ReplicaWriter {
    /// Opens the stream for writing.
    pub fn open(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let (stream, bell) = replica_services(node, inst)?;
        let publisher = stream
            .publisher_builder()
            .initial_max_slice_len(PART_HEADER + REPLICA_PART)
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            // Never wait on a standby: one that falls behind resynchronizes.
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| svc_err(&inst.replica(), e))?;
        let notifier = bell
            .notifier_builder()
            .create()
            .map_err(|e| svc_err(&inst.replica_bell(), e))?;
        Ok(ReplicaWriter {
            publisher,
            notifier,
            stream,
        })
    }

    /// How many standbys follow.
    pub fn standbys(&self) -> usize {
        self.stream.dynamic_config().number_of_subscribers()
    }

    /// Publishes one record, in parts of at most [`REPLICA_PART`] bytes (no ring: see
    /// [`ReplicaWriter::ring`]).
    pub fn publish(&self, record: &[u8]) -> Result<(), TransportError> {
        let err = |e: &dyn std::fmt::Debug| svc_err("replica", e);
        let parts: Vec<&[u8]> = if record.is_empty() {
            vec![record]
        } else {
            record.chunks(REPLICA_PART).collect()
        };
        let count = u32::try_from(parts.len()).map_err(|e| err(&e))?;
        for (i, part) in parts.iter().enumerate() {
            let mut sample = self
                .publisher
                .loan_slice_uninit(PART_HEADER + part.len())
                .map_err(|e| err(&e))?;
            let buf = sample.payload_mut();
            let mut header = [0u8; PART_HEADER];
            header[..4].copy_from_slice(&count.to_le_bytes());
            header[4..8].copy_from_slice(&(i as u32).to_le_bytes());
            for (dst, src) in buf.iter_mut().zip(header.iter().chain(part.iter())) {
                dst.write(*src);
            }
            // SAFETY: every byte was written just above.
            let sample = unsafe { sample.assume_init() };
            sample.send().map_err(|e| err(&e))?;
        }
        Ok(())
    }

    /// Wakes the standbys.
    pub fn ring(&self) {
        if let Err(e) = self.notifier.notify() {
            tracing::debug!("replica bell: {e:?}");
        }
    }
}

/// Largest record a standby puts together from parts (a state image of a full broker
/// is a few MiB); a record announcing more parts is dropped.
pub const MAX_REPLICA_RECORD: usize = 64 << 20;

/// A standby's end of the replication stream.
pub struct ReplicaReader {
    subscriber: Subscriber<Ipc, [u8], ()>,
    listener: Listener<Ipc>,
    stream: StreamFactory,
    /// A record arriving in parts, 16-byte aligned for rkyv.
    assembling: AlignedBytes,
    expect: u32,
    /// Publishers of the stream and the pids behind them.
    senders: HashMap<iceoryx2::identifiers::UniquePublisherId, Option<u32>>,
    /// Parts dropped: not from the primary, or of a record too big.
    refused: u64,
}

/// A growable byte buffer whose start is 16-byte aligned.
#[derive(Default)]
struct AlignedBytes {
    words: Vec<u128>,
    len: usize,
}

impl AlignedBytes {
    fn clear(&mut self) {
        self.len = 0;
    }

    fn extend_from_slice(&mut self, b: &[u8]) {
        let need = (self.len + b.len()).div_ceil(16);
        if self.words.len() < need {
            self.words.resize(need, 0);
        }
        // SAFETY: `words` holds at least `need * 16` initialized bytes.
        let bytes = unsafe {
            std::slice::from_raw_parts_mut(self.words.as_mut_ptr().cast::<u8>(), need * 16)
        };
        bytes[self.len..self.len + b.len()].copy_from_slice(b);
        self.len += b.len();
    }
}

impl std::ops::Deref for AlignedBytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        // SAFETY: the first `len` bytes of `words` are initialized.
        unsafe { std::slice::from_raw_parts(self.words.as_ptr().cast::<u8>(), self.len) }
    }
}

impl ReplicaReader {
    /// Opens the stream for reading.
    pub fn open(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let (stream, bell) = replica_services(node, inst)?;
        // Standbys SIGKILLed before their cleanup (nothing watches a standby's death)
        // still hold slots of both: freed first when they are all held.
        let subscriber = with_dead_holders_freed(
            node,
            &inst.replica(),
            || subscriber_pids(&stream),
            || {
                stream
                    .subscriber_builder()
                    .buffer_size(REPLICA_BUFFER)
                    .create()
            },
        )
        .map_err(|e| held_err(&inst.replica(), None, e))?;
        let listener = with_dead_holders_freed(
            node,
            &inst.replica_bell(),
            || listener_pids(&bell),
            || bell.listener_builder().create(),
        )
        .map_err(|e| held_err(&inst.replica_bell(), None, e))?;
        Ok(ReplicaReader {
            subscriber,
            listener,
            stream,
            assembling: AlignedBytes::default(),
            expect: 0,
            senders: HashMap::new(),
            refused: 0,
        })
    }

    /// Parts dropped so far: from another process than the primary, or of a record
    /// announcing more than [`MAX_REPLICA_RECORD`] bytes.
    pub fn refused(&self) -> u64 {
        self.refused
    }

    fn sender_pid(&mut self, publisher: iceoryx2::identifiers::UniquePublisherId) -> Option<u32> {
        if let Some(pid) = self.senders.get(&publisher) {
            return *pid;
        }
        if self.senders.len() > 64 {
            self.senders.clear();
        }
        let senders = &mut self.senders;
        self.stream.dynamic_config().list_publishers(|d| {
            senders.insert(d.publisher_id, node_pid(&d.node_id));
            iceoryx2::prelude::CallbackProgression::Continue
        });
        self.senders.get(&publisher).copied().flatten()
    }

    /// The bell's file descriptor, for the reactor.
    pub fn fd(&self) -> RawFd {
        // SAFETY: the descriptor stays owned by the listener; we only read its number.
        unsafe { self.listener.file_descriptor().native_handle() }
    }

    /// Empties the bell.
    pub fn drain_bell(&self) {
        drain_ids(&self.listener);
    }

    /// Hands each waiting record of the primary (process `primary`) to `f`: in place in
    /// shared memory if it came in one part, else put together from its parts. Parts
    /// published by any other process are dropped (counted in
    /// [`ReplicaReader::refused`]): only the primary speaks on the stream. Returns how
    /// many of the primary's parts were read.
    pub fn drain(&mut self, primary: u32, mut f: impl FnMut(&[u8])) -> usize {
        let mut n = 0;
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => {
                    if self.sender_pid(sample.header().publisher_id()) != Some(primary) {
                        self.refused += 1;
                        if self.refused.is_power_of_two() {
                            tracing::warn!(
                                refused = self.refused,
                                "replication: a record not from the primary, dropped"
                            );
                        }
                        continue;
                    }
                    n += 1;
                    let p = sample.payload();
                    if p.len() < PART_HEADER {
                        continue;
                    }
                    let count = u32::from_le_bytes([p[0], p[1], p[2], p[3]]);
                    let index = u32::from_le_bytes([p[4], p[5], p[6], p[7]]);
                    if (count as usize).saturating_mul(REPLICA_PART) > MAX_REPLICA_RECORD {
                        self.refused += 1;
                        self.assembling.clear();
                        self.expect = 0;
                        continue;
                    }
                    let body = &p[PART_HEADER..];
                    if count == 1 {
                        f(body);
                        continue;
                    }
                    if index == 0 {
                        self.assembling.clear();
                        self.expect = 0;
                    }
                    if index != self.expect {
                        // A part was lost: drop the record (the follower sees the gap).
                        self.assembling.clear();
                        self.expect = 0;
                        continue;
                    }
                    self.assembling.extend_from_slice(body);
                    self.expect += 1;
                    if self.expect == count {
                        f(&self.assembling);
                        self.assembling.clear();
                        self.expect = 0;
                    }
                }
                Ok(None) => return n,
                Err(e) => {
                    tracing::warn!("replica receive failed: {e:?}");
                    return n;
                }
            }
        }
    }
}
