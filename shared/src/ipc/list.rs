//! The service list blackboard: the broker writes it, everyone reads it in place.
//!
//! A blackboard's entries are fixed when it is made, so the list has no fixed size the
//! other way: a broker run writes its list into a blackboard of [`FIRST_LIST_CHUNKS`]
//! chunks, and when the list outgrows it, into a new one with room for twice as many
//! (and so on), named in the instance's fence like the first. Readers move to the new
//! one on their next read; the old one goes when the last of them has moved.

#[allow(unused_imports)]
use super::*;
use crate::snapshot::ServiceEntry;
use iceoryx2::service::builder::blackboard::BlackboardCreateError;

/// The broker's side of the service list blackboard.
///
/// Each broker run writes its own blackboard (named after its epoch) and then names it
/// in the instance's fence, where readers look: a new broker never needs the writer
/// slot of a dead one (iceoryx2 gives a blackboard one writer, and a writer killed in
/// the middle of an update leaves its entry held for good), and readers keep the old
/// list, whole, until the new one is there.
pub struct ListWriter {
    board: Board,
    /// What the chunks hold now, to write only the ones that change.
    written: Vec<ServiceEntry>,
    seq: u64,
    epoch: u64,
    node_inst: Instance,
    /// Whether the fence names `board`.
    announced: bool,
    /// The blackboard `board` replaced, kept until the fence names `board` (a reader
    /// that read the old name from the fence meanwhile can still open it).
    retired: Option<Board>,
}

/// One list blackboard as its writer holds it.
struct Board {
    /// Its name's number, which the fence gives readers.
    id: u64,
    header: EntryHandleMut<Ipc, u64, ListHeader>,
    chunks: Vec<EntryHandleMut<Ipc, u64, ListChunk>>,
    seq_pages: Vec<EntryHandleMut<Ipc, u64, ListSeqs>>,
    /// What the seq pages hold.
    seqs: Vec<u64>,
    // Dropped last: the handles above hold the writer's state.
    _writer: Writer<Ipc, u64>,
}

/// The blackboard key of the list's header; chunk `k` is key `k + 1`.
const HEADER_KEY: u64 = 0;

/// The blackboard key of chunk `k`.
fn chunk_key(k: usize) -> u64 {
    k as u64 + 1
}

/// The blackboard key of seq page `p` of a blackboard of `chunks` chunks.
fn seqs_key(chunks: usize, p: usize) -> u64 {
    (chunks + 1 + p) as u64
}

/// How many seq pages a blackboard of `chunks` chunks has.
fn seq_pages(chunks: usize) -> usize {
    chunks.div_ceil(SEQS_PER_PAGE)
}

/// The handles of a `chunks`-chunk blackboard's chunks and seq pages, from a writer's
/// or a reader's `entry` (the two sides open the same keys).
fn board_entries<C, S, E: std::fmt::Debug>(
    chunks: usize,
    mut chunk: impl FnMut(&u64) -> Result<C, E>,
    mut seqs: impl FnMut(&u64) -> Result<S, E>,
) -> Result<(Vec<C>, Vec<S>), TransportError> {
    let c = (0..chunks)
        .map(|k| chunk(&chunk_key(k)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| svc_err("service-list chunk", e))?;
    let s = (0..seq_pages(chunks))
        .map(|p| seqs(&seqs_key(chunks, p)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| svc_err("service-list seqs", e))?;
    Ok((c, s))
}

/// How many chunks hold `count` entries.
fn chunks_for(count: usize) -> usize {
    count.div_ceil(CHUNK_ENTRIES)
}

/// The entries of a `count`-entry list that chunk `k` holds.
fn chunk_range(k: usize, count: usize) -> std::ops::Range<usize> {
    k * CHUNK_ENTRIES..((k + 1) * CHUNK_ENTRIES).min(count)
}

/// Most blackboards a writer tries when a name it picks is taken.
const BOARD_NAME_TRIES: u64 = 64;

impl Board {
    /// Creates a list blackboard of `chunks` chunks named after `id` (or a higher
    /// number, if that name is taken).
    fn create(
        node: &Node<Ipc>,
        inst: &Instance,
        id: u64,
        epoch: u64,
        chunks: usize,
    ) -> Result<Self, TransportError> {
        let mut last = None;
        for id in id..id.saturating_add(BOARD_NAME_TRIES) {
            let name = inst.service_list(id);
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
                        chunks: chunks as u32,
                    },
                );
            for k in 0..chunks {
                builder = builder.add::<ListChunk>(chunk_key(k), ListChunk::empty());
            }
            for p in 0..seq_pages(chunks) {
                builder = builder.add::<ListSeqs>(
                    seqs_key(chunks, p),
                    ListSeqs {
                        seqs: [0; SEQS_PER_PAGE],
                    },
                );
            }
            let svc = match builder.create() {
                Ok(s) => s,
                Err(BlackboardCreateError::AlreadyExists) => {
                    last = Some(svc_err(&name, BlackboardCreateError::AlreadyExists));
                    continue;
                }
                Err(e) => return Err(svc_err(&name, e)),
            };
            let writer = svc
                .writer_builder()
                .create()
                .map_err(|e| svc_err(&name, e))?;
            let header = writer
                .entry::<ListHeader>(&HEADER_KEY)
                .map_err(|e| svc_err("service-list header", e))?;
            let (chunk_handles, seq_pages) = board_entries(
                chunks,
                |k| writer.entry::<ListChunk>(k),
                |k| writer.entry::<ListSeqs>(k),
            )?;
            return Ok(Board {
                id,
                header,
                chunks: chunk_handles,
                seq_pages,
                seqs: vec![0; chunks],
                _writer: writer,
            });
        }
        Err(last.unwrap_or_else(|| svc_err("service list", "no name left")))
    }
}

/// A new list blackboard's number: past `after`'s, and the wall clock's in ns (so
/// another broker run's epoch, which starts at the wall clock, is not taken either).
fn next_board_id(after: u64) -> u64 {
    let wall = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    wall.max(after.saturating_add(1))
}

impl ListWriter {
    /// Creates the blackboard of the broker run `epoch`.
    pub fn open(node: &Node<Ipc>, inst: &Instance, epoch: u64) -> Result<Self, TransportError> {
        Ok(ListWriter {
            board: Board::create(node, inst, epoch, epoch, FIRST_LIST_CHUNKS)?,
            written: Vec::new(),
            seq: 0,
            epoch,
            node_inst: inst.clone(),
            announced: false,
            retired: None,
        })
    }

    /// How many entries the blackboard in use holds.
    pub fn capacity(&self) -> usize {
        self.board.chunks.len() * CHUNK_ENTRIES
    }

    /// Publishes a new snapshot (its chunks that changed, then the header); readers see
    /// it on their next read. The first one also names this list in `fence`, so readers
    /// move to it; so does the first one written into a bigger blackboard, made when
    /// the list outgrows the one in use.
    pub fn publish(
        &mut self,
        node: &Node<Ipc>,
        snapshot: &ServiceListSnapshot,
        fence: &crate::fence::Fence,
    ) -> Result<(), TransportError> {
        self.publish_rows(node, snapshot, fence, None)
    }

    /// [`ListWriter::publish`] where the caller knows that only entries `rows` changed
    /// since the last one (`None`: any may have): only their chunks are looked at.
    pub fn publish_rows(
        &mut self,
        node: &Node<Ipc>,
        snapshot: &ServiceListSnapshot,
        fence: &crate::fence::Fence,
        rows: Option<&[usize]>,
    ) -> Result<(), TransportError> {
        let entries = snapshot.entries();
        let count = entries.len();
        if count > self.capacity() {
            let mut chunks = self.board.chunks.len().max(1);
            while chunks * CHUNK_ENTRIES < count {
                chunks *= 2;
            }
            let id = next_board_id(self.board.id);
            let bigger = Board::create(node, &self.node_inst, id, self.epoch, chunks)?;
            self.retired = Some(std::mem::replace(&mut self.board, bigger));
            self.written.clear();
            self.announced = false;
            tracing::info!(
                services = count,
                room = chunks * CHUNK_ENTRIES,
                "the service list moves to a bigger blackboard"
            );
        }
        self.seq += 1;
        let before = self.written.len();
        // The chunks skipped below hold what `written` does; those written are copied
        // into it as they are.
        self.written.resize(count, ServiceListSnapshot::EMPTY_ENTRY);
        let mut chunk = ListChunk::empty();
        let mut pages_changed = vec![false; self.board.seq_pages.len()];
        // The chunks to look at: those of the rows that changed, or all.
        let look: Vec<usize> = match rows.filter(|_| before == count) {
            Some(rows) => {
                let mut ks: Vec<usize> = rows
                    .iter()
                    .filter(|r| **r < count)
                    .map(|r| r / CHUNK_ENTRIES)
                    .collect();
                ks.dedup();
                ks
            }
            None => (0..chunks_for(count)).collect(),
        };
        for k in look {
            let range = chunk_range(k, count);
            // Unchanged, and whole in shared memory already: left as it is.
            if range.end <= before && self.written[range.clone()] == entries[range.clone()] {
                continue;
            }
            chunk.seq = self.seq;
            chunk.entries = [ServiceListSnapshot::EMPTY_ENTRY; CHUNK_ENTRIES];
            chunk.entries[..range.len()].copy_from_slice(&entries[range.clone()]);
            self.written[range.clone()].copy_from_slice(&entries[range]);
            self.board.chunks[k].update_with_copy(chunk);
            self.board.seqs[k] = self.seq;
            pages_changed[k / SEQS_PER_PAGE] = true;
        }
        // The chunks, then their seqs, then the header: a reader that sees the header
        // sees every seq and chunk of that write.
        for (p, _) in pages_changed.iter().enumerate().filter(|(_, c)| **c) {
            let mut page = ListSeqs {
                seqs: [0; SEQS_PER_PAGE],
            };
            let seqs = &self.board.seqs[p * SEQS_PER_PAGE..];
            let n = seqs.len().min(SEQS_PER_PAGE);
            page.seqs[..n].copy_from_slice(&seqs[..n]);
            self.board.seq_pages[p].update_with_copy(page);
        }
        self.board.header.update_with_copy(ListHeader {
            seq: self.seq,
            generation: snapshot.generation,
            epoch: snapshot.epoch,
            count: count as u32,
            chunks: self.board.chunks.len() as u32,
        });
        if !self.announced {
            fence.set_list(self.board.id);
            self.announced = true;
            // Readers now find the new one; the old one goes when its last reader does.
            self.retired = None;
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
    /// The last whole copy taken, with the write it came from (kept across blackboards:
    /// a reader moving to a bigger one reuses its memory).
    copy: Option<((u64, u64), Arc<ServiceListSnapshot>)>,
    /// The write each chunk of `copy` came from (of the blackboard in `copy`'s key).
    copy_seqs: Vec<u64>,
    /// How long a read waits for a write under way ([`LIST_READ_WAIT`]).
    read_wait: Duration,
}

/// One list blackboard as a reader holds it: the entries' handles, opened once.
struct OpenList {
    id: u64,
    header: EntryHandle<Ipc, u64, ListHeader>,
    chunks: Vec<EntryHandle<Ipc, u64, ListChunk>>,
    seq_pages: Vec<EntryHandle<Ipc, u64, ListSeqs>>,
    // Dropped last: the handles above hold the reader's state.
    _reader: Reader<Ipc, u64>,
}

/// Most times a reader follows the fence again because the list it named was replaced
/// while the reader opened it.
const FOLLOW_TRIES: usize = 16;

/// How long a reader waits for a write under way to end. On a loaded machine the
/// broker can lose its core in the middle of a write for milliseconds; a reader that
/// counted its tries instead (1,000, yielding) gave up under 900 users, and its user
/// with it. A broker that stops in the middle for good is replaced, and the reader
/// leaves as soon as the fence names its successor's list.
const LIST_READ_WAIT: Duration = Duration::from_secs(2);

/// Reads taken back to back before a reader starts to sleep between them.
const LIST_READ_SPINS: u32 = 8;

/// The first sleep between two reads of a list being written; it doubles up to
/// [`LIST_READ_NAP_MAX`].
const LIST_READ_NAP: Duration = Duration::from_micros(20);
const LIST_READ_NAP_MAX: Duration = Duration::from_millis(1);

/// Why no consistent copy was taken.
enum ReadFailed {
    /// The fence names another list now: follow it and read that one.
    Moved,
    /// A write was under way for the whole wait, or there is no list.
    Error(TransportError),
}

impl ReadFailed {
    fn into_error(self) -> TransportError {
        match self {
            ReadFailed::Moved => TransportError::Service {
                name: "service list".into(),
                detail: "it moved to another blackboard while being read".into(),
            },
            ReadFailed::Error(e) => e,
        }
    }
}

impl OpenList {
    /// Whether `fence` names a list other than this one.
    fn moved(&self, fence: &crate::fence::Fence) -> bool {
        let now = fence.list();
        now != 0 && now != self.id
    }

    /// Reads the header, then what `take` reads of the chunks, then the header again,
    /// until the two headers agree and no chunk read is newer (a consistent copy of
    /// one write). `take` gets the header and a chunk reader, and returns `None` when
    /// what it read is newer than the header (a write under way: read again). A write
    /// under way is waited for, sleeping between reads, for `wait` at most, or until
    /// `fence` names another list.
    fn consistent<T>(
        &self,
        wait: Duration,
        fence: &crate::fence::Fence,
        mut take: impl FnMut(&ListHeader, &dyn Fn(usize) -> ListChunkRef) -> Option<T>,
    ) -> Result<(ListHeader, T), ReadFailed> {
        let start = Instant::now();
        let mut nap = LIST_READ_NAP;
        let mut header = *self.header.get();
        let mut attempt = 0u32;
        loop {
            let read = |k: usize| ListChunkRef(self.chunks.get(k).map(|c| c.get()));
            let got = take(&header, &read);
            let again = *self.header.get();
            if let Some(got) = got.filter(|_| again.seq == header.seq) {
                if attempt >= LIST_READ_SPINS {
                    tracing::debug!(
                        reads = attempt + 1,
                        waited_us = start.elapsed().as_micros() as u64,
                        "the service list was being written: read after a wait"
                    );
                }
                return Ok((header, got));
            }
            header = again;
            attempt += 1;
            if attempt < LIST_READ_SPINS {
                continue;
            }
            // The broker is in the middle of a write and off its core, or writes
            // faster than this reader reads: let it run.
            if self.moved(fence) {
                return Err(ReadFailed::Moved);
            }
            let waited = start.elapsed();
            if waited >= wait {
                return Err(ReadFailed::Error(TransportError::Service {
                    name: "service list".into(),
                    detail: format!(
                        "a write of it stayed under way for {} ms ({attempt} reads)",
                        waited.as_millis()
                    ),
                }));
            }
            std::thread::sleep(nap.min(wait - waited));
            nap = (nap * 2).min(LIST_READ_NAP_MAX);
        }
    }
}

/// A chunk as read (a copy out of shared memory), or none past the blackboard's end.
struct ListChunkRef(Option<iceoryx2::port::reader::BlackboardValue<ListChunk>>);

impl ListChunkRef {
    /// The chunk, if it exists and is not newer than `header`.
    fn of(&self, header: &ListHeader) -> Option<&ListChunk> {
        self.0.as_deref().filter(|c| c.seq <= header.seq)
    }
}

impl ListReader {
    /// Opens the list of the running broker; fails if no broker ever wrote one.
    pub fn open(node: &Node<Ipc>, inst: &Instance) -> Result<Self, TransportError> {
        let fence = crate::fence::Fence::open_existing(inst)
            .map_err(|_| TransportError::Unreachable(Address::Broker))?;
        let mut r = ListReader {
            node_inst: inst.clone(),
            fence,
            current: None,
            copy: None,
            copy_seqs: Vec::new(),
            read_wait: LIST_READ_WAIT,
        };
        r.follow(node)?;
        Ok(r)
    }

    /// Moves to the list the fence names, if it is another one. A blackboard that
    /// cannot be opened because the broker moved to another meanwhile (a list grown
    /// into a bigger one, a new broker run) is followed to the one the fence names
    /// now, a bounded number of times.
    fn follow(&mut self, node: &Node<Ipc>) -> Result<(), TransportError> {
        let mut tries = 0;
        loop {
            let id = self.fence.list();
            match self.follow_once(node) {
                Err(e) if tries < FOLLOW_TRIES && id != 0 && self.fence.list() != id => {
                    tracing::debug!("the list moved while opening it ({e}); following");
                    tries += 1;
                }
                r => return r,
            }
        }
    }

    /// [`ListReader::follow`], once: opens the list the fence names now.
    fn follow_once(&mut self, node: &Node<Ipc>) -> Result<(), TransportError> {
        let mut id = self.fence.list();
        if id == 0 {
            // The broker stopped on purpose and removed the fence; a new one may have
            // made another.
            if let Ok(f) = crate::fence::Fence::open_existing(&self.node_inst) {
                self.fence = f;
                id = self.fence.list();
            }
        }
        if id == 0 {
            return Err(TransportError::Unreachable(Address::Broker));
        }
        if self.current.as_ref().is_some_and(|c| c.id == id) {
            return Ok(());
        }
        let name = self.node_inst.service_list(id);
        let svc = node
            .service_builder(&service_name(&name)?)
            .blackboard_opener::<u64>()
            .open()
            .map_err(|_| TransportError::Unreachable(Address::Broker))?;
        let reader = svc
            .reader_builder()
            .create()
            .map_err(|e| svc_err(&name, e))?;
        let header = reader
            .entry::<ListHeader>(&HEADER_KEY)
            .map_err(|e| svc_err("service-list header", e))?;
        let (chunks, seq_pages) = board_entries(
            header.get().chunks as usize,
            |k| reader.entry::<ListChunk>(k),
            |k| reader.entry::<ListSeqs>(k),
        )?;
        self.current = Some(OpenList {
            id,
            header,
            chunks,
            seq_pages,
            _reader: reader,
        });
        Ok(())
    }

    /// Moves to a new broker's (or a bigger) list first if there is one; the old list
    /// stays readable until a new one can be opened.
    fn follow_or_stay(&mut self, node: &Node<Ipc>) -> Result<(), TransportError> {
        match self.follow(node) {
            Err(e) if self.current.is_none() => Err(e),
            _ => Ok(()),
        }
    }

    /// The newest snapshot of the running broker's list, moving to a new broker's list
    /// first if there is one. It is copied out of shared memory only when it changed
    /// since the last read; otherwise the last copy is shared again.
    pub fn read_from(
        &mut self,
        node: &Node<Ipc>,
    ) -> Result<Arc<ServiceListSnapshot>, TransportError> {
        self.on_newest(node, Self::read_here)
    }

    /// One page of the running broker's list: the entries `filter` lets through, from
    /// the `offset`th of them, at most `limit`. Without a filter it reads only the
    /// chunks the page is in, where they are in shared memory; with one, it filters the
    /// whole list (copied out only when it changed since the last read).
    pub fn page_from(
        &mut self,
        node: &Node<Ipc>,
        filter: &ListFilter,
        offset: usize,
        limit: usize,
    ) -> Result<ListPage, TransportError> {
        if !filter.is_everything() {
            return Ok(self.read_from(node)?.page(filter, offset, limit));
        }
        self.on_newest(node, |r| r.page_here(offset, limit))
    }

    /// `read` on the list the fence names, moving to it first; once more if the fence
    /// named another one while `read` waited for a write under way to end.
    fn on_newest<T>(
        &mut self,
        node: &Node<Ipc>,
        mut read: impl FnMut(&mut Self) -> Result<T, ReadFailed>,
    ) -> Result<T, TransportError> {
        self.follow_or_stay(node)?;
        match read(self) {
            Err(ReadFailed::Moved) => {
                self.follow_or_stay(node)?;
                read(self).map_err(ReadFailed::into_error)
            }
            r => r.map_err(ReadFailed::into_error),
        }
    }

    /// [`ListReader::page_from`] without a filter, on the list this reader is on.
    fn page_here(&self, offset: usize, limit: usize) -> Result<ListPage, ReadFailed> {
        let Some(open) = &self.current else {
            return Err(ReadFailed::Error(TransportError::Unreachable(
                Address::Broker,
            )));
        };
        let mut entries = Vec::with_capacity(limit.min(CHUNK_ENTRIES * 64));
        let (header, ()) = open.consistent(self.read_wait, &self.fence, |header, chunk| {
            entries.clear();
            let count = header.count as usize;
            let end = offset.saturating_add(limit).min(count);
            let mut at = offset.min(end);
            while at < end {
                let k = at / CHUNK_ENTRIES;
                let c = chunk(k);
                let c = c.of(header)?;
                let range = chunk_range(k, count);
                let upto = range.end.min(end);
                entries.extend_from_slice(&c.entries[at - range.start..upto - range.start]);
                at = upto;
            }
            Some(())
        })?;
        Ok(ListPage {
            generation: header.generation,
            epoch: header.epoch,
            matching: header.count as usize,
            entries,
        })
    }

    /// The newest snapshot of the list this reader is on: a consistent copy of one
    /// write. Only the chunks that changed since the last copy are taken out of shared
    /// memory (the last copy's memory is reused if no one holds it any more, else
    /// copied first).
    pub fn read(&mut self) -> Result<Arc<ServiceListSnapshot>, TransportError> {
        self.read_here().map_err(ReadFailed::into_error)
    }

    /// [`ListReader::read`], saying when the fence moved on meanwhile.
    fn read_here(&mut self) -> Result<Arc<ServiceListSnapshot>, ReadFailed> {
        let Some(open) = &self.current else {
            return Err(ReadFailed::Error(TransportError::Unreachable(
                Address::Broker,
            )));
        };
        let key = (open.id, open.header.get().seq);
        if let Some((k, copy)) = &self.copy {
            if *k == key {
                return Ok(Arc::clone(copy));
            }
        }
        let (mut copy, same_board) = match self.copy.take() {
            Some(((id, _), c)) => (c, id == open.id),
            None => (Arc::new(ServiceListSnapshot::empty()), false),
        };
        if !same_board {
            self.copy_seqs.clear();
        }
        // Held elsewhere too: this reader's copy becomes its own (a clone of it).
        let snap = Arc::make_mut(&mut copy);
        let have = &mut self.copy_seqs;
        let (header, ()) = open.consistent(self.read_wait, &self.fence, |header, chunk| {
            let count = header.count as usize;
            let n = chunks_for(count);
            let mut seqs = Vec::with_capacity(n);
            for p in 0..n.div_ceil(SEQS_PER_PAGE) {
                let page = open.seq_pages.get(p)?.get();
                let upto = (n - p * SEQS_PER_PAGE).min(SEQS_PER_PAGE);
                seqs.extend_from_slice(&page.seqs[..upto]);
            }
            if seqs.iter().any(|s| *s > header.seq) {
                return None; // a newer write is under way
            }
            have.resize(n, 0);
            let entries = snap.resize(count);
            for k in 0..n {
                if have[k] == seqs[k] && seqs[k] != 0 {
                    continue; // the copy holds this chunk as it is
                }
                let c = chunk(k);
                let c = c.of(header)?;
                if c.seq != seqs[k] {
                    return None;
                }
                let range = chunk_range(k, count);
                let len = range.len();
                entries[range].copy_from_slice(&c.entries[..len]);
                have[k] = c.seq;
            }
            Some(())
        })?;
        snap.generation = header.generation;
        snap.epoch = header.epoch;
        self.copy = Some(((open.id, header.seq), Arc::clone(&copy)));
        Ok(copy)
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::stamped_list;
    use super::*;
    use std::sync::mpsc;

    /// Leaves a write half done, as a broker that lost its core in the middle of one
    /// does: its first chunk and the chunks' seqs say a write newer than the header's.
    fn half_write(w: &mut ListWriter) {
        let mut chunk = ListChunk::empty();
        chunk.seq = w.seq + 1;
        let n = w.written.len().min(CHUNK_ENTRIES);
        chunk.entries[..n].copy_from_slice(&w.written[..n]);
        w.board.chunks[0].update_with_copy(chunk);
        w.board.seq_pages[0].update_with_copy(ListSeqs {
            seqs: [w.seq + 1; SEQS_PER_PAGE],
        });
    }

    /// A reader in its own thread (as in another process: its own node), opened on
    /// `inst`'s list; it reads once it is sent its wait (the whole list, or with `true`
    /// the page of its first 100 entries), and sends back the generation and the count
    /// of entries it read, and how long that took.
    type Reading = (Result<(u64, usize), String>, Duration);
    type Reader = (
        mpsc::Sender<(Duration, bool)>,
        mpsc::Receiver<Reading>,
        std::thread::JoinHandle<()>,
    );
    fn reader(inst: &Instance) -> Reader {
        let (go, went) = mpsc::channel::<(Duration, bool)>();
        let (tell, told) = mpsc::channel();
        let inst = inst.clone();
        let thread = std::thread::spawn(move || {
            let node = create_node("list-wait-reader", false).unwrap();
            let mut r = ListReader::open(&node, &inst).unwrap();
            while let Ok((wait, page)) = went.recv() {
                r.read_wait = wait;
                let t = Instant::now();
                let got = if page {
                    r.page_from(&node, &ListFilter::default(), 0, 100)
                        .map(|p| (p.generation, p.entries.len()))
                } else {
                    r.read_from(&node).map(|s| (s.generation, s.count()))
                };
                if tell
                    .send((got.map_err(|e| e.to_string()), t.elapsed()))
                    .is_err()
                {
                    break;
                }
            }
        });
        (go, told, thread)
    }

    /// A test instance named after `name`, with a list of 40 entries written (write 1).
    fn written(name: &str) -> (Instance, Node<Ipc>, crate::fence::Fence, ListWriter) {
        let inst = Instance::new(&format!("{name}-{}", std::process::id())).unwrap();
        let node = create_node(name, false).unwrap();
        let fence = crate::fence::Fence::open(&inst).unwrap();
        let mut w = ListWriter::open(&node, &inst, 1).unwrap();
        w.publish(&node, &stamped_list(1, 40), &fence).unwrap();
        (inst, node, fence, w)
    }

    #[test]
    fn a_reader_waits_out_a_write_left_half_done_for_longer_than_a_thousand_reads() {
        let (inst, node, fence, mut w) = written("list-wait");
        let (go, told, first) = reader(&inst);

        // Finished 300 ms later: the read takes the finished write, not an error.
        half_write(&mut w);
        go.send((LIST_READ_WAIT, false)).unwrap();
        std::thread::sleep(Duration::from_millis(300));
        w.publish(&node, &stamped_list(2, 40), &fence).unwrap();
        let (got, took) = told.recv().unwrap();
        assert_eq!(got, Ok((2, 40)), "the write it waited for");
        assert!(took >= Duration::from_millis(250), "it waited: {took:?}");

        // Never finished: an error once the wait is over, that says why (a new reader:
        // the first one has write 2, which the header still names, and shares it).
        half_write(&mut w);
        drop(go);
        first.join().unwrap();
        let (go, told, second) = reader(&inst);
        go.send((Duration::from_millis(200), false)).unwrap();
        let (got, took) = told.recv().unwrap();
        let e = got.unwrap_err();
        assert!(e.contains("stayed under way"), "{e}");
        assert!(took >= Duration::from_millis(200), "{took:?}");

        // Finished at last: read again, whole.
        w.publish(&node, &stamped_list(3, 40), &fence).unwrap();
        go.send((LIST_READ_WAIT, false)).unwrap();
        assert_eq!(told.recv().unwrap().0, Ok((3, 40)));
        // Gone before the process ends: a thread still running then leaves its node.
        drop(go);
        second.join().unwrap();
        drop(w);
        fence.remove();
    }

    #[test]
    fn a_reader_waiting_on_a_dead_brokers_half_write_moves_to_the_new_brokers_list() {
        let (inst, node, fence, first) = written("list-moved");
        let (go, told, thread) = reader(&inst);
        // Each broker stops in the middle of a write for good; 300 ms later a new one
        // names its own list. The reader, set to wait far longer, takes the new list
        // instead of waiting for the old one: reading the whole list, then a page of it
        // in place.
        let mut brokers = vec![first];
        for (epoch, page, generation, count) in [(2, false, 7, 12), (3, true, 9, 5)] {
            half_write(brokers.last_mut().unwrap());
            go.send((Duration::from_secs(60), page)).unwrap();
            std::thread::sleep(Duration::from_millis(300));
            let mut next = ListWriter::open(&node, &inst, epoch).unwrap();
            next.publish(&node, &stamped_list(generation, count), &fence)
                .unwrap();
            brokers.push(next);
            let (got, _) = told.recv().unwrap();
            assert_eq!(got, Ok((generation, count)), "page: {page}");
        }
        drop(go);
        thread.join().unwrap();
        drop(brokers);
        fence.remove();
    }
}
