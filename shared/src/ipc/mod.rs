//! The iceoryx2 transport every process shares.
//!
//! Each process (broker, system, user) owns one **inbox** — a publish-subscribe service
//! of byte frames with many publishers and one subscriber — and one **bell** — an event
//! service it waits on. Sending to a peer means writing a frame into the peer's inbox
//! (zero-copy: the peer reads it from shared memory) and ringing its bell. Peers' ports
//! are opened lazily and cached. Nothing here polls: the bell's file descriptor goes
//! into the process's [`crate::reactor::Reactor`].
//!
//! Some inboxes are shared, their frames in envelopes naming their user: a federated
//! broker's relay for every user of another host, and a process's inbox for all the
//! users it hosts ([`ProcessInbox`]), so that a writer holds one pair of ports for
//! many users.

use crate::names::{Address, Instance};
use crate::snapshot::{
    ListChunk, ListFilter, ListHeader, ListPage, ListSeqs, ServiceListSnapshot, CHUNK_ENTRIES,
    FIRST_LIST_CHUNKS, SEQS_PER_PAGE,
};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::reader::{EntryHandle, Reader};
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::writer::{EntryHandleMut, Writer};
use iceoryx2::prelude::*;
use std::collections::{HashMap, VecDeque};
use std::os::fd::RawFd;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long a released peer's ports stay open. iceoryx2 loses a frame whose publisher
/// is dropped before the reader has connected to it, so ports to a peer we are done
/// with (e.g. after sending the `End` of our last session with it) linger, like TCP's.
pub const LINGER: Duration = Duration::from_secs(2);

/// The iceoryx2 service type muster uses between processes.
pub type Ipc = ipc::Service;

/// Most processes (users + systems + broker) one instance supports at once.
pub const MAX_PARTICIPANTS: usize = 8192;
/// Most peers that may write to one user's inbox (the broker and the systems it has
/// sessions with). iceoryx2 preallocates ~11 KiB per possible writer in each reader,
/// so these limits are what a process's memory is made of.
pub const MAX_USER_PEERS: usize = 16;
/// Most peers that may write to one system's inbox (the broker and the users in
/// sessions with it, with the 2 s of [`LINGER`] after), and to one relay inbox (the
/// host's systems). Not [`MAX_PARTICIPANTS`]: each possible writer costs the reader
/// ~3.7 KiB (measured: 10 systems' PSS 110 MiB at 2,048, 335 MiB at 8,192).
pub const MAX_SYSTEM_PEERS: usize = 2048;
/// Largest frame on every path but system → broker. These publishers use static
/// segments: a growable (dynamic) segment makes every reader preallocate ~290 KiB of
/// bookkeeping per writer, which at 900 users is most of the broker's memory.
pub const SMALL_FRAME: usize = 4096;
/// Most bytes an envelope adds to a frame written into a relay inbox
/// ([`crate::names::Address::Relay`]): a length byte and the user's id.
pub const MAX_ENVELOPE: usize = 1 + u8::MAX as usize;
/// Frames queued per writer in a relay inbox: a system's burst to all of a host's users
/// at once (a 10 Hz service streamed to 300 of them) waits there for one read.
pub const RELAY_BUFFER: usize = 1024;
/// Most peers that may write to the inbox a process's users share
/// ([`crate::names::Address::Process`]): the broker and the systems any of them has
/// sessions with. Each costs the reader about 21 KiB at [`PROCESS_INBOX_BUFFER`].
pub const MAX_PROCESS_INBOX_PEERS: usize = 128;
/// Frames queued per writer in a process's shared inbox: a system's update to every
/// one of the process's users at once.
pub const PROCESS_INBOX_BUFFER: usize = 256;
/// Initial frame size of the system → broker path, which grows (power of two) up to
/// [`crate::protocol::MAX_FRAME`] for large registrations.
const INITIAL_LARGE_FRAME: usize = 4096;

/// Event ids rung on a bell.
pub mod bell {
    /// Frames wait in the inbox.
    pub const MESSAGE: usize = 0;
    /// The service list changed (users only).
    pub const LIST_CHANGED: usize = 1;
    /// A broker started (presence event only).
    pub const BROKER_UP: usize = 2;
    /// The broker stopped on purpose (presence event only).
    pub const BROKER_DOWN: usize = 3;
    /// A standby asks the primary for its whole state (the broker's bell only).
    pub const STANDBY: usize = 4;
    /// A standby took over the running broker's state (presence event only): systems
    /// register again, users adopt it and repeat their pending requests.
    pub const TAKEOVER: usize = 5;
    /// Highest id in use.
    pub const MAX: usize = 7;
}

/// Why the transport failed. Setup errors name the service; send errors the peer.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    /// iceoryx2 could not create the node; check /dev/shm space and permissions.
    #[error("cannot create iceoryx2 node: {0}")]
    Node(String),
    /// A service could not be created or opened (limits exceeded, incompatible settings).
    #[error("iceoryx2 service {name}: {detail}")]
    Service {
        /// The service name.
        name: String,
        /// What iceoryx2 said.
        detail: String,
    },
    /// Another live process already owns this address (e.g. a system of the same name).
    #[error("{0} is already running on this instance")]
    InUse(Address),
    /// The message could not be encoded (too large for a frame); nothing was sent.
    #[error("cannot encode a message for {peer}: {source}")]
    Encode {
        /// The peer.
        peer: Address,
        /// Why.
        source: crate::protocol::EncodeError,
    },
    /// The peer's inbox is full (it reads slower than we write), or no more ports to
    /// peers may be opened now ([`Endpoint::set_max_open_peers`]): this frame was
    /// dropped (a control frame waits instead). The peer is still there; session
    /// updates show the loss as a sequence gap.
    #[error("{0}'s inbox is full, or no more peers' ports may open now: frame dropped")]
    Full(Address),
    /// The peer's inbox does not exist or nobody reads it: the peer is gone.
    #[error("{0} is unreachable (not running?)")]
    Unreachable(Address),
    /// A frame could not be written to the peer's inbox.
    #[error("sending to {peer}: {detail}")]
    Send {
        /// The peer.
        peer: Address,
        /// What iceoryx2 said.
        detail: String,
    },
}

fn svc_err(name: &str, e: impl std::fmt::Debug) -> TransportError {
    TransportError::Service {
        name: name.to_string(),
        detail: format!("{e:?}"),
    }
}

fn service_name(name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(|e| svc_err(name, e))
}

/// Limits of one process's inbox.
#[derive(Clone, Copy, Debug)]
pub struct InboxLimits {
    /// How many peers may write to it.
    pub max_publishers: usize,
    /// How many processes may read it at once: one, but four for the broker's, so that a
    /// new broker can take over before old ones' ports are cleaned up (a cleanup under
    /// load takes hundreds of ms, and a broker killed in the middle of one can leave a
    /// dead reader behind for good); the fence says which reader is the broker.
    pub readers: usize,
    /// Reader slots of the inbox itself (the bell keeps `readers` listeners). The
    /// broker's has room for dead primaries' readers until their cleanup (a `muster
    /// cleanup` process, one at a time, slow for a broker's hundreds of ports) frees
    /// them: with 4, a takeover that came while 3 dead brokers waited for cleanup
    /// waited for one (2.2 s, one SIGKILL takeover in 100). An unused slot costs a
    /// little dynamic config.
    pub inbox_readers: usize,
    /// Frames queued per writing peer before further frames are dropped.
    pub buffer: usize,
}

impl InboxLimits {
    /// The limits for an address's role.
    pub fn for_addr(addr: &Address) -> Self {
        match addr {
            Address::Broker => InboxLimits {
                max_publishers: MAX_PARTICIPANTS,
                readers: 4,
                inbox_readers: 8,
                buffer: 32,
            },
            Address::System(_) => InboxLimits {
                max_publishers: MAX_SYSTEM_PEERS,
                readers: 1,
                inbox_readers: 1,
                buffer: 32,
            },
            Address::Relay(_) => InboxLimits {
                max_publishers: MAX_SYSTEM_PEERS,
                readers: 1,
                inbox_readers: 1,
                buffer: RELAY_BUFFER,
            },
            // The broker and the systems in sessions with any of the process's users
            // (lingering ones too); a burst to all of them from one writer waits here.
            Address::Process(_) => InboxLimits {
                max_publishers: MAX_PROCESS_INBOX_PEERS,
                readers: 1,
                inbox_readers: 1,
                buffer: PROCESS_INBOX_BUFFER,
            },
            Address::User(_) => InboxLimits {
                max_publishers: MAX_USER_PEERS,
                readers: 1,
                inbox_readers: 1,
                buffer: 128,
            },
        }
    }
}

pub use crate::names::{iox2_root, DEFAULT_IOX2_ROOT};

/// The iceoryx2 config for a process. Users skip dead-node cleanup on node creation, which
/// costs O(nodes) each time; the broker cleans instead (measured: 83 ms per client at 900).
pub fn config(cleanup_dead_nodes: bool) -> Config {
    let mut c = Config::global_config().clone();
    let root = iox2_root();
    match iceoryx2::prelude::Path::new(root.as_bytes()) {
        Ok(p) => c.global.set_root_path(&p),
        Err(e) => tracing::warn!(
            "MUSTER_IOX2_ROOT {root:?} is not a valid path ({e:?}); using iceoryx2's default"
        ),
    }
    c.global.node.cleanup_dead_nodes_on_creation = cleanup_dead_nodes;
    c.global.node.cleanup_dead_nodes_on_destruction = cleanup_dead_nodes;
    c.global.service.cleanup_dead_nodes_on_open = cleanup_dead_nodes;
    c
}

/// Creates this process's iceoryx2 node, with signal handling left to muster.
pub fn create_node(name: &str, cleanup_dead_nodes: bool) -> Result<Node<Ipc>, TransportError> {
    let node_name = NodeName::new(name).map_err(|e| TransportError::Node(format!("{e:?}")))?;
    NodeBuilder::new()
        .name(&node_name)
        .config(&config(cleanup_dead_nodes))
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(|e| TransportError::Node(format!("{e:?}")))
}

mod cleanup;
mod endpoint;
mod events;
mod list;
mod presence;
mod process_inbox;
mod replica;
mod turn;
mod viz;

pub use self::cleanup::*;
pub use self::endpoint::*;
pub use self::events::*;
pub use self::list::*;
pub use self::presence::*;
pub use self::process_inbox::*;
pub use self::replica::*;
pub use self::turn::*;
pub use self::viz::*;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_systems_view_reaches_readers_old_and_new_and_a_huge_one_is_cut() {
        use crate::viz::{PlanView, SystemView, TrackView};
        let inst = Instance::new(&format!("viz-test-{}", std::process::id())).unwrap();
        let node = create_node("viz-test", false).unwrap();
        let mut early = VizReader::open(&node, &inst, "d1").unwrap();
        let mut w = VizWriter::open(&node, &inst, "d1").unwrap();
        let view = SystemView {
            system: "d1".into(),
            t: 1.5,
            tracks: vec![TrackView {
                colour: "red".into(),
                x: 1.0,
                ..TrackView::default()
            }],
            plans: vec![PlanView {
                robot: "D1".into(),
                goal: (3.0, 4.0),
                path: vec![(1.0, 1.0), (3.0, 4.0)],
            }],
            ..SystemView::default()
        };
        w.publish(&view).unwrap();
        assert_eq!(early.latest(), Some(view.clone()));
        assert_eq!(early.latest(), None, "each view once");
        let mut late = VizReader::open(&node, &inst, "d1").unwrap();
        let mut next = view.clone();
        next.t = 2.0;
        w.publish(&next).unwrap();
        w.publish(&view).unwrap();
        assert_eq!(late.latest(), Some(view.clone()), "the newest of two");
        assert_eq!(early.latest(), Some(view.clone()));
        let mut huge = view.clone();
        huge.plans[0].path = vec![(1.25, 2.5); 5000];
        w.publish(&huge).unwrap();
        let got = late.latest().unwrap();
        assert_eq!(got.plans[0].path.len(), 64);
        assert_eq!(got.tracks, view.tracks);
    }

    /// Whether `fd` is readable now.
    fn readable(fd: RawFd) -> bool {
        let mut p = libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: one valid pollfd, no wait.
        unsafe { libc::poll(&mut p, 1, 0) == 1 }
    }

    #[test]
    fn the_feed_rings_its_readers_not_the_broker_and_a_reader_rings_the_broker() {
        use crate::protocol::BrokerEvent;
        use crate::types::UserId;
        let inst = Instance::new(&format!("feed-test-{}", std::process::id())).unwrap();
        let node = create_node("feed-test", false).unwrap();
        let mut w = EventWriter::open(&node, &inst, 0xab).unwrap();
        assert!(!readable(w.fd()));
        // A reader that opens says so: the broker's bell rings, and the history is
        // handed over.
        let mut r = EventReader::open(&node, &inst).unwrap();
        assert!(readable(w.fd()), "a reader's hello rings the broker");
        w.on_bell();
        assert!(!readable(w.fd()), "drained");
        for n in 1..=3 {
            let json = w
                .publish(BrokerEvent::UserJoined {
                    user: UserId(format!("u{n}")),
                })
                .unwrap()
                .unwrap();
            assert!(json.contains(&format!("\"seq\":{n}")), "{json}");
        }
        w.ring();
        // The news wakes the reader; the broker's own bell stays quiet (it used to
        // share the bell, and each publish woke the broker itself for nothing).
        assert!(readable(r.fd()), "the reader is rung");
        assert!(!readable(w.fd()), "the broker is not rung by its own news");
        let seqs: Vec<u64> = std::iter::from_fn(|| r.next_event())
            .map(|e| e.seq)
            .collect();
        assert_eq!(seqs, [1, 2, 3]);
        assert_eq!(r.next_event(), None);
    }

    #[test]
    fn only_old_empty_segments_are_taken_for_stillborn() {
        let name = |what: &str| format!("/dev/shm/iox2_muster_test_{}_{what}", std::process::id());
        let long_ago = std::time::SystemTime::now() - Duration::from_secs(5);
        let make = |path: &str, bytes: &[u8], modified: Option<std::time::SystemTime>| {
            let f = std::fs::File::create(path).unwrap();
            std::io::Write::write_all(&mut &f, bytes).unwrap();
            if let Some(t) = modified {
                f.set_modified(t).unwrap();
            }
        };
        let (stillborn, fresh, sized) = (name("stillborn"), name("fresh"), name("sized"));
        make(&stillborn, b"", Some(long_ago));
        make(&fresh, b"", None);
        make(&sized, b"data", Some(long_ago));
        assert!(remove_stillborn_segments() >= 1);
        let exists = |p: &str| std::path::Path::new(p).exists();
        assert!(!exists(&stillborn), "an empty segment left for 5 s goes");
        assert!(exists(&fresh), "one being made now stays");
        assert!(exists(&sized), "a sized one stays");
        std::fs::remove_file(&fresh).unwrap();
        std::fs::remove_file(&sized).unwrap();
    }

    #[test]
    fn monitor_files_left_without_their_state_file_are_removed_once_old() {
        let dir = std::env::temp_dir().join(format!("muster-monitors-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let long_ago = std::time::SystemTime::now() - Duration::from_secs(5);
        let make = |name: &str, old: bool| {
            let f = std::fs::File::create(dir.join(name)).unwrap();
            if old {
                f.set_modified(long_ago).unwrap();
            }
        };
        // Killed while dropped: state file gone, owner lock and context left, long ago.
        make("iox2_11.node_monitor_owner_lock", true);
        make("iox2_11.node_monitor_context", true);
        // Killed with only the context left.
        make("iox2_12.node_monitor_context", true);
        // Alive: all three files.
        for tail in ["", "_owner_lock", "_context"] {
            make(&format!("iox2_13.node_monitor{tail}"), true);
        }
        // Being made right now: no state file yet, but young.
        make("iox2_14.node_monitor_context", false);
        // Something else entirely.
        make("iox2_15.details", true);
        assert_eq!(remove_half_removed_monitors(&dir), 2);
        let mut left: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(
            left,
            [
                "iox2_13.node_monitor",
                "iox2_13.node_monitor_context",
                "iox2_13.node_monitor_owner_lock",
                "iox2_14.node_monitor_context",
                "iox2_15.details",
            ]
        );
        assert_eq!(
            remove_half_removed_monitors(&dir),
            0,
            "nothing more to take"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A snapshot of `count` entries that all say which write they are (`quota`).
    pub(super) fn stamped_list(generation: u64, count: usize) -> Box<ServiceListSnapshot> {
        let mut s = Box::new(ServiceListSnapshot::empty());
        s.generation = generation;
        s.epoch = 1;
        for (i, e) in s.resize(count).iter_mut().enumerate() {
            e.name = crate::snapshot::FixedStr::new(&format!("s{i}"));
            e.quota = (generation % 60_000) as u16;
        }
        s
    }

    #[test]
    fn a_list_read_is_one_whole_write_and_copied_only_when_it_changed() {
        let inst = Instance::new(&format!("list-test-{}", std::process::id())).unwrap();
        let node = create_node("list-test", false).unwrap();
        let fence = crate::fence::Fence::open(&inst).unwrap();
        let mut w = ListWriter::open(&node, &inst, 1).unwrap();
        w.publish(&node, &stamped_list(1, 40), &fence).unwrap();
        let mut r = ListReader::open(&node, &inst).unwrap();
        let a = r.read().unwrap();
        assert_eq!((a.generation, a.count(), a.entries()[39].quota), (1, 40, 1));
        assert_eq!(a.entries()[39].name.as_str(), "s39");
        let b = r.read().unwrap();
        assert!(Arc::ptr_eq(&a, &b), "unchanged: the same copy");
        // Fewer entries, then more: the chunks left over from before are not read.
        w.publish(&node, &stamped_list(2, 3), &fence).unwrap();
        let c = r.read().unwrap();
        assert_eq!((c.generation, c.count(), c.entries().len()), (2, 3, 3));
        assert!(c.entries().iter().all(|e| e.quota == 2));
        w.publish(&node, &stamped_list(3, 250), &fence).unwrap();
        let d = r.read().unwrap();
        assert_eq!(d.count(), 250);
        assert!(d.entries().iter().all(|e| e.quota == 3));
        assert_eq!(d.entries()[249].name.as_str(), "s249");
        drop((a, b, c, d));

        // A writer changing the list every 200 µs, and a reader in another thread:
        // every read is one write whole (every entry stamped alike, the count the one
        // that write had), and the reads never go back.
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let reader = {
            let (inst, stop) = (inst.clone(), Arc::clone(&stop));
            std::thread::spawn(move || {
                let node = create_node("list-test-reader", false).unwrap();
                let mut r = ListReader::open(&node, &inst).unwrap();
                let (mut reads, mut last) = (0u64, 0u64);
                while !stop.load(std::sync::atomic::Ordering::Relaxed) && reads < 2_000_000 {
                    let s = r.read().unwrap();
                    let g = s.generation;
                    assert!(g >= last, "went back from {last} to {g}");
                    // (Write 3, of 250 entries, above, if this thread read before the
                    // first write below.)
                    let count = if g == 3 { 250 } else { 1 + g % 200 };
                    assert_eq!(s.count() as u64, count, "count of write {g}");
                    let stamp = (g % 60_000) as u16;
                    assert!(
                        s.entries().iter().all(|e| e.quota == stamp),
                        "write {g} torn: {:?}",
                        s.entries().iter().map(|e| e.quota).collect::<Vec<_>>()
                    );
                    last = g;
                    reads += 1;
                }
                reads
            })
        };
        // (Paced: the broker writes on a change, a few hundred times a second at most;
        // a writer that never pauses would starve a reader of whole reads.)
        for g in 4..4_000u64 {
            w.publish(&node, &stamped_list(g, 1 + (g % 200) as usize), &fence)
                .unwrap();
            std::thread::sleep(Duration::from_micros(200));
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        assert!(reader.join().unwrap() > 0);
        drop(r);
        drop(w);
        fence.remove();
    }

    #[test]
    fn a_reader_taking_only_the_chunks_that_changed_still_reads_whole_writes() {
        // 200 entries in 13 chunks; write g (from 2) stamps chunk g % 13 with g. At
        // generation G, chunk k holds the last g <= G with g % 13 == k (1 if none).
        const CHUNKS: u64 = 13;
        let inst = Instance::new(&format!("list-incr-{}", std::process::id())).unwrap();
        let node = create_node("list-incr", false).unwrap();
        let fence = crate::fence::Fence::open(&inst).unwrap();
        let mut w = ListWriter::open(&node, &inst, 1).unwrap();
        let mut list = stamped_list(1, 200);
        w.publish(&node, &list, &fence).unwrap();
        let expect = |g: u64, k: u64| -> u64 {
            if g < 2 {
                return 1;
            }
            // The last g' <= g with g' % CHUNKS == k, if it is at least 2.
            let back = (g % CHUNKS + CHUNKS - k) % CHUNKS;
            if g >= back + 2 {
                g - back
            } else {
                1
            }
        };
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let reader = {
            let (inst, stop) = (inst.clone(), Arc::clone(&stop));
            std::thread::spawn(move || {
                let node = create_node("list-incr-reader", false).unwrap();
                let mut r = ListReader::open(&node, &inst).unwrap();
                let mut reads = 0u64;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) && reads < 2_000_000 {
                    let s = r.read_from(&node).unwrap();
                    let g = s.generation;
                    for (i, e) in s.entries().iter().enumerate() {
                        let k = (i / CHUNK_ENTRIES) as u64;
                        assert_eq!(
                            u64::from(e.quota),
                            expect(g, k) % 60_000,
                            "write {g}, entry {i}"
                        );
                    }
                    reads += 1;
                }
                reads
            })
        };
        for g in 2..6_000u64 {
            list.generation = g;
            let k = (g % CHUNKS) as usize;
            let end = ((k + 1) * CHUNK_ENTRIES).min(200);
            for e in &mut list.resize(200)[k * CHUNK_ENTRIES..end] {
                e.quota = (g % 60_000) as u16;
            }
            w.publish(&node, &list, &fence).unwrap();
            std::thread::sleep(Duration::from_micros(100));
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        assert!(reader.join().unwrap() > 100);
        drop(w);
        fence.remove();
    }

    #[test]
    fn a_write_of_the_rows_that_changed_is_read_whole() {
        let inst = Instance::new(&format!("list-rows-{}", std::process::id())).unwrap();
        let node = create_node("list-rows", false).unwrap();
        let fence = crate::fence::Fence::open(&inst).unwrap();
        let mut w = ListWriter::open(&node, &inst, 1).unwrap();
        let mut list = stamped_list(1, 1000);
        w.publish(&node, &list, &fence).unwrap();
        let mut r = ListReader::open(&node, &inst).unwrap();
        assert_eq!(r.read_from(&node).unwrap().entries(), list.entries());
        for g in 2..50u64 {
            list.generation = g;
            let rows = [(g * 37 % 1000) as usize, (g * 101 % 1000) as usize];
            for &i in &rows {
                list.resize(1000)[i].in_use = g as u16;
            }
            let mut sorted = rows.to_vec();
            sorted.sort_unstable();
            w.publish_rows(&node, &list, &fence, Some(&sorted)).unwrap();
            let got = r.read_from(&node).unwrap();
            assert_eq!(got.generation, g);
            assert_eq!(got.entries(), list.entries(), "write {g}");
        }
        drop(r);
        drop(w);
        fence.remove();
    }

    /// The CI failure of 2026-11-27: a user opening the list while the broker moved it
    /// to a bigger blackboard found the name the fence gave it gone, and said the broker
    /// was unreachable. A reader opening while lists grow, over and over, always opens.
    #[test]
    fn a_reader_opening_while_the_list_grows_always_finds_it() {
        use std::sync::atomic::{AtomicBool, Ordering};
        let inst = Instance::new(&format!("list-race-{}", std::process::id())).unwrap();
        let fence = crate::fence::Fence::open(&inst).unwrap();
        let done = Arc::new(AtomicBool::new(false));
        let read_all = Arc::new(AtomicBool::new(false));
        // The broker's side: each round a writer (a broker run) names its small list,
        // the last round's goes, and the list then grows into a bigger blackboard.
        let writer = {
            let (inst, done, read_all) = (inst.clone(), Arc::clone(&done), Arc::clone(&read_all));
            std::thread::spawn(move || {
                let (small, big) = (stamped_list(1, 40), stamped_list(2, 300));
                let node = create_node("list-race-w", false).unwrap();
                let fence = crate::fence::Fence::open_existing(&inst).unwrap();
                let mut last: Option<ListWriter> = None;
                for round in 0..150u64 {
                    let mut w = ListWriter::open(&node, &inst, 1 + round).unwrap();
                    w.publish(&node, &small, &fence).unwrap();
                    drop(last.take());
                    // Readers get a moment on each list (a broker grows its list
                    // far less often than this), at varying points of their opening.
                    std::thread::sleep(Duration::from_micros(200 * (round % 7)));
                    w.publish(&node, &big, &fence).unwrap();
                    last = Some(w);
                    std::thread::sleep(Duration::from_micros(300 * (round % 5)));
                }
                done.store(true, Ordering::SeqCst);
                // The last list stays until the reader is through with it.
                while !read_all.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(1));
                }
                drop(last);
            })
        };
        let node = create_node("list-race-r", false).unwrap();
        let (mut opened, mut failed) = (0, Vec::new());
        // From the first list on (before it, no broker: unreachable, rightly).
        while fence.list() == 0 {
            std::thread::sleep(Duration::from_micros(100));
        }
        while !done.load(Ordering::SeqCst) {
            match ListReader::open(&node, &inst).and_then(|mut r| r.read_from(&node)) {
                Ok(l) => {
                    assert!(l.count() == 40 || l.count() == 300, "{}", l.count());
                    opened += 1;
                }
                Err(e) => failed.push(e.to_string()),
            }
        }
        read_all.store(true, Ordering::SeqCst);
        writer.join().unwrap();
        assert!(opened > 0);
        assert!(
            failed.is_empty(),
            "{} of {} opens failed: {:?}",
            failed.len(),
            opened + failed.len(),
            &failed[..failed.len().min(3)]
        );
        fence.remove();
    }

    #[test]
    fn a_list_outgrowing_its_blackboard_moves_to_a_bigger_one_and_reads_in_pages() {
        use crate::snapshot::{ListFilter, FIRST_LIST_CHUNKS};
        let inst = Instance::new(&format!("list-grow-{}", std::process::id())).unwrap();
        let node = create_node("list-grow", false).unwrap();
        let fence = crate::fence::Fence::open(&inst).unwrap();
        let mut w = ListWriter::open(&node, &inst, 1).unwrap();
        w.publish(&node, &stamped_list(1, 40), &fence).unwrap();
        let first = fence.list();
        let mut r = ListReader::open(&node, &inst).unwrap();
        assert_eq!(r.read_from(&node).unwrap().count(), 40);
        // 10,000 entries: past the first blackboard's room, so a new one (named anew
        // in the fence) with room for them.
        assert!(w.capacity() == FIRST_LIST_CHUNKS * CHUNK_ENTRIES && w.capacity() < 10_000);
        w.publish(&node, &stamped_list(2, 10_000), &fence).unwrap();
        assert!(w.capacity() >= 10_000);
        assert_ne!(fence.list(), first, "the fence names the new blackboard");
        let all = r.read_from(&node).unwrap();
        assert_eq!((all.generation, all.count()), (2, 10_000));
        assert!(all.entries().iter().all(|e| e.quota == 2));
        assert_eq!(all.entries()[9_999].name.as_str(), "s9999");
        // A page in place: entries 4,990..5,090, across chunk boundaries.
        let page = r
            .page_from(&node, &ListFilter::default(), 4_990, 100)
            .unwrap();
        assert_eq!(
            (page.generation, page.matching, page.entries.len()),
            (2, 10_000, 100)
        );
        let names: Vec<&str> = page.entries.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names[0], "s4990");
        assert_eq!(names[99], "s5089");
        // The last page is short; past the end is empty.
        let tail = r
            .page_from(&node, &ListFilter::default(), 9_950, 100)
            .unwrap();
        assert_eq!(tail.entries.len(), 50);
        assert_eq!(tail.entries[49].name.as_str(), "s9999");
        let past = r
            .page_from(&node, &ListFilter::default(), 20_000, 100)
            .unwrap();
        assert!(past.entries.is_empty());
        // Filtered: names s7, s70..s79, s700..s799, s7000..s7999 (1,111 of them); the
        // second page of 100 starts at the 101st.
        let f = ListFilter {
            name: Some("s7*".into()),
            ..ListFilter::default()
        };
        let p = r.page_from(&node, &f, 100, 100).unwrap();
        assert_eq!((p.matching, p.entries.len()), (1_111, 100));
        let expect: Vec<String> = all
            .entries()
            .iter()
            .map(|e| e.name.as_str().to_string())
            .filter(|n| n.starts_with("s7"))
            .skip(100)
            .take(100)
            .collect();
        let got: Vec<String> = p
            .entries
            .iter()
            .map(|e| e.name.as_str().to_string())
            .collect();
        assert_eq!(got, expect);
        // Shrinking keeps the big blackboard; a reader sees the short list whole.
        let id = fence.list();
        w.publish(&node, &stamped_list(3, 17), &fence).unwrap();
        assert_eq!(fence.list(), id);
        let short = r.read_from(&node).unwrap();
        assert_eq!((short.generation, short.count()), (3, 17));
        drop((all, short));
        drop(r);
        drop(w);
        fence.remove();
    }
}
