//! The service list blackboard: the broker writes it, everyone reads it in place.

#[allow(unused_imports)]
use super::*;

/// The broker's side of the service list blackboard.
///
/// Each broker run writes its own blackboard (named after its epoch) and then names it
/// in the instance's fence, where readers look: a new broker never needs the writer
/// slot of a dead one (iceoryx2 gives a blackboard one writer, and a writer killed in
/// the middle of an update leaves its entry held for good), and readers keep the old
/// list, whole, until the new one is there.
pub struct ListWriter {
    header: EntryHandleMut<Ipc, u64, ListHeader>,
    chunks: Vec<EntryHandleMut<Ipc, u64, ListChunk>>,
    /// What the chunks hold now, to write only the ones that change.
    written: Box<ServiceListSnapshot>,
    seq: u64,
    epoch: u64,
    announced: bool,
    // Dropped last: the handles above hold the writer's state.
    _writer: Writer<Ipc, u64>,
}

/// The blackboard key of the list's header; chunk `k` is key `k + 1`.
const HEADER_KEY: u64 = 0;

/// The blackboard key of chunk `k`.
fn chunk_key(k: usize) -> u64 {
    k as u64 + 1
}

/// The list's header entry and its chunks' entries, from a blackboard writer's or
/// reader's `entry` (the two sides open the same keys).
fn list_entries<H, C, E: std::fmt::Debug>(
    header: impl FnOnce(&u64) -> Result<H, E>,
    mut chunk: impl FnMut(&u64) -> Result<C, E>,
) -> Result<(H, Vec<C>), TransportError> {
    let header = header(&HEADER_KEY).map_err(|e| svc_err("service-list header", e))?;
    let chunks = (0..LIST_CHUNKS)
        .map(|k| chunk(&chunk_key(k)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| svc_err("service-list chunk", e))?;
    Ok((header, chunks))
}

/// How many chunks hold `count` entries.
fn chunks_for(count: usize) -> usize {
    count.min(MAX_LISTED_SERVICES).div_ceil(CHUNK_ENTRIES)
}

/// The entries of a `count`-entry list that chunk `k` holds.
fn chunk_range(k: usize, count: usize) -> std::ops::Range<usize> {
    k * CHUNK_ENTRIES..((k + 1) * CHUNK_ENTRIES).min(count)
}

impl ListWriter {
    /// Creates the blackboard of the broker run `epoch`.
    pub fn open(node: &Node<Ipc>, inst: &Instance, epoch: u64) -> Result<Self, TransportError> {
        let name = inst.service_list(epoch);
        let sname = service_name(&name)?;
        let mut builder = node
            .service_builder(&sname)
            .blackboard_creator::<u64>()
            .max_readers(MAX_PARTICIPANTS)
            .max_nodes(MAX_PARTICIPANTS + 4)
            .add::<ListHeader>(
                HEADER_KEY,
                ListHeader {
                    seq: 0,
                    generation: 0,
                    epoch,
                    count: 0,
                    _pad: 0,
                },
            );
        for k in 0..LIST_CHUNKS {
            builder = builder.add::<ListChunk>(chunk_key(k), ListChunk::empty());
        }
        let svc = builder.create().map_err(|e| svc_err(&name, e))?;
        let writer = svc
            .writer_builder()
            .create()
            .map_err(|e| svc_err(&name, e))?;
        let (header, chunks) = list_entries(
            |k| writer.entry::<ListHeader>(k),
            |k| writer.entry::<ListChunk>(k),
        )?;
        Ok(ListWriter {
            header,
            chunks,
            written: Box::new(ServiceListSnapshot::empty()),
            seq: 0,
            epoch,
            announced: false,
            _writer: writer,
        })
    }

    /// Publishes a new snapshot (its chunks that changed, then the header); readers see
    /// it on their next read. The first one also names this list in `fence`, so readers
    /// move to it.
    pub fn publish(
        &mut self,
        snapshot: &ServiceListSnapshot,
        fence: &crate::fence::Fence,
    ) -> Result<(), TransportError> {
        self.seq += 1;
        let count = (snapshot.count as usize).min(MAX_LISTED_SERVICES);
        let before = (self.written.count as usize).min(MAX_LISTED_SERVICES);
        let mut chunk = ListChunk::empty();
        for k in 0..chunks_for(count) {
            let range = chunk_range(k, count);
            // Unchanged, and whole in shared memory already: left as it is.
            if self.seq > 1
                && range.end <= before
                && self.written.entries[range.clone()] == snapshot.entries[range.clone()]
            {
                continue;
            }
            chunk.seq = self.seq;
            chunk.entries = [ServiceListSnapshot::EMPTY_ENTRY; CHUNK_ENTRIES];
            chunk.entries[..range.len()].copy_from_slice(&snapshot.entries[range.clone()]);
            self.chunks[k].update_with_copy(chunk);
            self.written.entries[range.clone()].copy_from_slice(&snapshot.entries[range]);
        }
        self.written.count = count as u32;
        self.header.update_with_copy(ListHeader {
            seq: self.seq,
            generation: snapshot.generation,
            epoch: snapshot.epoch,
            count: count as u32,
            _pad: 0,
        });
        if !self.announced {
            fence.set_list(self.epoch);
            self.announced = true;
        }
        Ok(())
    }
}

/// A user's side of the service list: the blackboard the fence names, followed from
/// one broker run to the next.
pub struct ListReader {
    node_inst: Instance,
    fence: crate::fence::Fence,
    current: Option<OpenList>,
}

/// One broker run's list as a reader holds it: the entries' handles, opened once, and
/// the last copy taken with the write it came from.
struct OpenList {
    epoch: u64,
    header: EntryHandle<Ipc, u64, ListHeader>,
    chunks: Vec<EntryHandle<Ipc, u64, ListChunk>>,
    copy: Option<(u64, Arc<ServiceListSnapshot>)>,
    // Dropped last: the handles above hold the reader's state.
    _reader: Reader<Ipc, u64>,
}

/// Most times a reader takes the list again because the broker wrote it meanwhile.
const LIST_READ_TRIES: usize = 1000;

impl ListReader {
    /// Opens the list of the running broker; fails if no broker ever wrote one.
    pub fn open(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let fence = crate::fence::Fence::open_existing(inst)
            .map_err(|_| TransportError::Unreachable(Address::Broker))?;
        let mut r = ListReader {
            node_inst: inst.clone(),
            fence,
            current: None,
        };
        r.follow(node)?;
        Ok(r)
    }

    /// Moves to the list the fence names, if it is another one.
    fn follow(&mut self, node: &Node<Ipc>) -> Result<(), TransportError> {
        let mut epoch = self.fence.list();
        if epoch == 0 {
            // The broker stopped on purpose and removed the fence; a new one may have
            // made another.
            if let Ok(f) = crate::fence::Fence::open_existing(&self.node_inst) {
                self.fence = f;
                epoch = self.fence.list();
            }
        }
        if epoch == 0 {
            return Err(TransportError::Unreachable(Address::Broker));
        }
        if self.current.as_ref().is_some_and(|c| c.epoch == epoch) {
            return Ok(());
        }
        let name = self.node_inst.service_list(epoch);
        let svc = node
            .service_builder(&service_name(&name)?)
            .blackboard_opener::<u64>()
            .open()
            .map_err(|_| TransportError::Unreachable(Address::Broker))?;
        let reader = svc
            .reader_builder()
            .create()
            .map_err(|e| svc_err(&name, e))?;
        let (header, chunks) = list_entries(
            |k| reader.entry::<ListHeader>(k),
            |k| reader.entry::<ListChunk>(k),
        )?;
        self.current = Some(OpenList {
            epoch,
            header,
            chunks,
            copy: None,
            _reader: reader,
        });
        Ok(())
    }

    /// The newest snapshot of the running broker's list, moving to a new broker's list
    /// first if there is one. It is copied out of shared memory only when it changed
    /// since the last read; otherwise the last copy is shared again.
    pub fn read_from(
        &mut self,
        node: &Node<Ipc>,
    ) -> Result<Arc<ServiceListSnapshot>, TransportError> {
        if let Err(e) = self.follow(node) {
            // The old list stays readable until a new one can be opened.
            if self.current.is_none() {
                return Err(e);
            }
        }
        self.read()
    }

    /// The newest snapshot of the list this reader is on: a consistent copy of one
    /// write, taking only the chunks that hold entries.
    pub fn read(&mut self) -> Result<Arc<ServiceListSnapshot>, TransportError> {
        let Some(open) = &mut self.current else {
            return Err(TransportError::Unreachable(Address::Broker));
        };
        let mut header = *open.header.get();
        if let Some((seq, copy)) = &open.copy {
            if *seq == header.seq {
                return Ok(Arc::clone(copy));
            }
        }
        // Into the last copy's memory if no one holds it any more: a fresh allocation
        // of the list's size would fault its pages in again on every change.
        let mut copy = match open.copy.take() {
            Some((_, c)) if Arc::strong_count(&c) == 1 => c,
            _ => Arc::new(ServiceListSnapshot::empty()),
        };
        let snap = Arc::get_mut(&mut copy).expect("held by no one else");
        for attempt in 0..LIST_READ_TRIES {
            if attempt >= 8 {
                // The broker writes faster than this reader reads: let it run.
                std::thread::yield_now();
            }
            let count = (header.count as usize).min(MAX_LISTED_SERVICES);
            let mut torn = false;
            for (k, chunk) in open.chunks.iter().take(chunks_for(count)).enumerate() {
                let c = chunk.get();
                if c.seq > header.seq {
                    // Written after the header we hold: a newer write is under way.
                    torn = true;
                    break;
                }
                let range = chunk_range(k, count);
                let n = range.len();
                snap.entries[range].copy_from_slice(&c.entries[..n]);
            }
            let again = *open.header.get();
            if !torn && again.seq == header.seq {
                snap.generation = header.generation;
                snap.epoch = header.epoch;
                snap.count = count as u32;
                open.copy = Some((header.seq, Arc::clone(&copy)));
                return Ok(copy);
            }
            header = again;
        }
        Err(TransportError::Service {
            name: "service list".into(),
            detail: format!("it changed under each of {LIST_READ_TRIES} reads in a row"),
        })
    }
}
