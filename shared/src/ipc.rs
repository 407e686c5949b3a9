//! The iceoryx2 transport every process shares.
//!
//! Each process (broker, system, user) owns one **inbox** — a publish-subscribe service
//! of byte frames with many publishers and one subscriber — and one **bell** — an event
//! service it waits on. Sending to a peer means writing a frame into the peer's inbox
//! (zero-copy: the peer reads it from shared memory) and ringing its bell. Peers' ports
//! are opened lazily and cached. Nothing here polls: the bell's file descriptor goes
//! into the process's [`crate::reactor::Reactor`].

use crate::names::{Address, Instance};
use crate::snapshot::{
    ListChunk, ListHeader, ServiceListSnapshot, CHUNK_ENTRIES, LIST_CHUNKS, MAX_LISTED_SERVICES,
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
pub const MAX_PARTICIPANTS: usize = 2048;
/// Most peers that may write to one user's inbox (the broker and the systems it has
/// sessions with). iceoryx2 preallocates ~11 KiB per possible writer in each reader,
/// so these limits are what a process's memory is made of.
pub const MAX_USER_PEERS: usize = 16;
/// Most peers that may write to one system's inbox (the broker and its users at once).
pub const MAX_SYSTEM_PEERS: usize = 256;
/// Largest frame on every path but system → broker. These publishers use static
/// segments: a growable (dynamic) segment makes every reader preallocate ~290 KiB of
/// bookkeeping per writer, which at 900 users is most of the broker's memory.
pub const SMALL_FRAME: usize = 4096;
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
    /// The peer's inbox is full (it reads slower than we write): this frame was dropped.
    /// The peer is still there; session updates show the loss as a sequence gap.
    #[error("{0}'s inbox is full: frame dropped")]
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
                buffer: 32,
            },
            Address::System(_) => InboxLimits {
                max_publishers: MAX_PARTICIPANTS,
                readers: 1,
                buffer: 32,
            },
            Address::User(_) => InboxLimits {
                max_publishers: MAX_USER_PEERS,
                readers: 1,
                buffer: 128,
            },
        }
    }
}

/// Where iceoryx2 keeps node and service metadata, unless `MUSTER_IOX2_ROOT` says
/// otherwise. On tmpfs: iceoryx2 fsyncs these files, and on a disk-backed /tmp (its
/// default) that cost 4 fsyncs and ~5 ms of broker time per connecting user.
pub const DEFAULT_IOX2_ROOT: &str = "/dev/shm/muster/";

/// The iceoryx2 metadata directory in use.
pub fn iox2_root() -> String {
    let mut root =
        std::env::var("MUSTER_IOX2_ROOT").unwrap_or_else(|_| DEFAULT_IOX2_ROOT.to_string());
    if !root.ends_with('/') {
        root.push('/');
    }
    root
}

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

/// Removes what the dead process `pid` left in shared memory (its nodes' ports), and
/// nothing else: unlike a full dead-node cleanup it does not pay for other dead nodes.
/// Returns how many nodes were removed.
pub fn cleanup_dead_nodes_of(pid: u32) -> usize {
    cleanup_dead_nodes(Some(pid))
}

/// Removes what dead processes left in shared memory: first what `pid` left, once it
/// has exited (a process SIGKILLed while stopped takes a moment to go, and its nodes
/// are not dead until then), then what any other dead process left (a cleanup skipped
/// because another was under way, or never run because its broker was killed first).
/// Returns how many nodes were removed.
pub fn cleanup_after(pid: Option<u32>) -> usize {
    // A segment whose creator was killed between creating and sizing it stays empty,
    // and iceoryx2 0.10 waits forever to open an empty one (its cleanup of a dead
    // node's connections among others): such segments go first, and again while the
    // cleanup runs.
    remove_stillborn_segments();
    let running = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let watch = {
        let running = running.clone();
        std::thread::spawn(move || {
            while running.load(std::sync::atomic::Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(250));
                remove_stillborn_segments();
            }
        })
    };
    let n = cleanup_after_inner(pid);
    running.store(false, std::sync::atomic::Ordering::Relaxed);
    let _ = watch.join();
    n
}

/// How long an empty segment must have stayed empty to be taken for stillborn (its
/// creator sizes it microseconds after creating it).
const STILLBORN_AFTER: Duration = Duration::from_secs(1);

/// Removes iceoryx2 segments in /dev/shm that are empty and were made more than
/// [`STILLBORN_AFTER`] ago: their creator died before sizing them. Returns how many.
pub fn remove_stillborn_segments() -> usize {
    let Ok(dir) = std::fs::read_dir("/dev/shm") else {
        return 0;
    };
    let mut n = 0;
    for entry in dir.flatten() {
        if !entry.file_name().to_string_lossy().starts_with("iox2_") {
            continue;
        }
        let Ok(meta) = entry.metadata() else { continue };
        if meta.is_file()
            && meta.len() == 0
            && old(&meta)
            && std::fs::remove_file(entry.path()).is_ok()
        {
            tracing::info!(segment = %entry.file_name().to_string_lossy(), "removed an empty segment its dead creator never sized");
            n += 1;
        }
    }
    n
}

/// Whether a file was last written at least [`STILLBORN_AFTER`] ago: what a live
/// process makes and fills within microseconds is not taken for a dead one's leftover
/// before then.
fn old(meta: &std::fs::Metadata) -> bool {
    meta.modified()
        .ok()
        .and_then(|m| m.elapsed().ok())
        .is_some_and(|age| age >= STILLBORN_AFTER)
}

fn cleanup_after_inner(pid: Option<u32>) -> usize {
    let mut n = 0;
    if let Some(pid) = pid {
        let until = std::time::Instant::now() + Duration::from_secs(10);
        while crate::reactor::process_alive(pid) && std::time::Instant::now() < until {
            std::thread::sleep(Duration::from_millis(5));
        }
        // The old primary's first, at full speed: it holds one of the broker inbox's
        // reader slots, which the next takeover or restart needs.
        n += cleanup_dead_nodes(Some(pid));
    }
    // The rest beside whatever the host is doing, never ahead of it.
    let _ = crate::reactor::set_nice(19);
    n + cleanup_dead_nodes(None)
}

/// Removes what the dead process `pid` left, waiting up to `patience` for a cleanup
/// another process has under way (a broker's inbox cannot be opened before its dead
/// readers are gone). Returns how many of its nodes are gone.
pub fn cleanup_dead_nodes_of_waiting(pid: u32, patience: Duration) -> usize {
    use iceoryx2::node::NodeView;
    let mut dead = Vec::new();
    let _ = Node::<Ipc>::list(&config(true), |state| {
        if let NodeState::Dead(view) = state {
            if node_pid(view.id()) == Some(pid) {
                dead.push(view);
            }
        }
        CallbackProgression::Continue
    });
    dead.into_iter()
        .filter(
            |view| match view.clone().blocking_remove_stale_resources(patience) {
                Ok(()) => true,
                Err(e) => {
                    tracing::warn!(pid, "cannot remove the resources of a dead process: {e:?}");
                    false
                }
            },
        )
        .count()
}

/// Removes what dead processes left in shared memory: those of process `only`, or all.
/// Returns how many nodes were removed.
pub fn cleanup_dead_nodes(only: Option<u32>) -> usize {
    use iceoryx2::node::{NodeCleanupFailure, NodeView};
    let mut dead = Vec::new();
    let _ = Node::<Ipc>::list(&config(true), |state| {
        if let NodeState::Dead(view) = state {
            if only.is_none_or(|pid| node_pid(view.id()) == Some(pid)) {
                dead.push(view);
            }
        }
        CallbackProgression::Continue
    });
    let n = dead.len();
    if only.is_none() {
        remove_half_removed_monitors(&std::path::Path::new(&iox2_root()).join("nodes"));
    }
    for view in dead {
        if view.details().is_none() {
            // Killed while its node was being made: no details, so iceoryx2 would look
            // for the node under its default root, not ours, and never remove it.
            remove_detail_less_node(&view.id().value().to_string());
            continue;
        }
        match view.try_remove_stale_resources() {
            Ok(_) => {}
            // Someone else (another process's cleanup) got there first: nothing is lost.
            Err(
                e @ (NodeCleanupFailure::ResourcesAlreadyCleanedUp
                | NodeCleanupFailure::AnotherInstanceIsCleaningUpTheNode),
            ) => tracing::debug!("a dead process's resources: {e:?}"),
            Err(e) => tracing::warn!("cannot remove the resources of a dead process: {e:?}"),
        }
    }
    n
}

/// Removes the files of a dead node that has no details (its folder under our root's
/// `nodes/`, and its monitor's three files beside it). One made just now, whose maker
/// may not hold its monitor yet, is left alone.
fn remove_detail_less_node(id: &str) {
    let nodes = std::path::Path::new(&iox2_root()).join("nodes");
    let monitor = nodes.join(format!("iox2_{id}{MONITOR}"));
    if !std::fs::metadata(&monitor).as_ref().is_ok_and(old) {
        return;
    }
    remove_node_files(&nodes, id);
    tracing::info!(node = id, "removed a dead node that was never finished");
}

/// A node's monitor state file is `iox2_<id>` and this, in our root's `nodes/`; its
/// owner lock and context add [`MONITOR_TAILS`].
const MONITOR: &str = ".node_monitor";
const MONITOR_TAILS: [&str; 2] = ["_context", "_owner_lock"];

/// Removes whatever is left of node `id` in `nodes`: its folder and its monitor's files.
fn remove_node_files(nodes: &std::path::Path, id: &str) {
    let _ = std::fs::remove_dir_all(nodes.join(id));
    for tail in std::iter::once("").chain(MONITOR_TAILS) {
        let _ = std::fs::remove_file(nodes.join(format!("iox2_{id}{MONITOR}{tail}")));
    }
}

/// Removes the monitor files of nodes whose state file is gone, in `nodes` (our root's
/// `nodes/`). iceoryx2 lists nodes by their state file (`iox2_<id>.node_monitor`) and
/// removes it first when a node is dropped, then its owner lock and its context: a
/// process killed in between (a SIGKILL after a slow shutdown) leaves those two behind,
/// where no node listing ever finds them. A live node always has its state file but for
/// microseconds while it is made or dropped, so only files older than [`STILLBORN_AFTER`]
/// are taken. Returns how many nodes' leftovers were removed.
fn remove_half_removed_monitors(nodes: &std::path::Path) -> usize {
    let Ok(dir) = std::fs::read_dir(nodes) else {
        return 0;
    };
    let mut orphans = std::collections::BTreeSet::new();
    for entry in dir.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(id) = MONITOR_TAILS
            .iter()
            .find_map(|tail| name.strip_suffix(&format!("{MONITOR}{tail}")))
            .and_then(|stem| stem.strip_prefix("iox2_"))
        else {
            continue;
        };
        if entry.metadata().as_ref().is_ok_and(old)
            && !nodes.join(format!("iox2_{id}{MONITOR}")).exists()
        {
            orphans.insert(id.to_string());
        }
    }
    for id in &orphans {
        remove_node_files(nodes, id);
        tracing::info!(node = %id, "removed what a node killed while it was dropped left");
    }
    orphans.len()
}

/// The pid of the process that created an iceoryx2 node, if it can be told.
fn node_pid(node: &iceoryx2::identifiers::UniqueNodeId) -> Option<u32> {
    node.pid::<Ipc>()
        .ok()
        .and_then(|p| u32::try_from(p.value()).ok())
}

/// Empties a listener; returns the event ids rung as bits (bit i = id i).
fn drain_ids(listener: &Listener<Ipc>) -> u64 {
    let mut rung = 0u64;
    let _ = listener.try_wait(|a| {
        let id = a.id.as_value();
        if id < 64 {
            rung |= 1 << id;
        }
    });
    rung
}

struct Peer {
    publisher: Publisher<Ipc, [u8], ()>,
    notifier: Notifier<Ipc>,
    inbox: iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], ()>,
}

/// One process's inbox and bell, plus cached ports to its peers.
pub struct Endpoint {
    inst: Instance,
    me: Address,
    node: Node<Ipc>,
    inbox: Subscriber<Ipc, [u8], ()>,
    bell: Listener<Ipc>,
    peers: HashMap<Address, Peer>,
    lingering: HashMap<Address, Instant>,
    dropped_sends: u64,
    recv_errors: u64,
    /// Control frames a full inbox could not take yet, per peer, in order: retried by
    /// [`Endpoint::sweep`], so no control message is lost to a burst.
    backlog: HashMap<Address, VecDeque<Vec<u8>>>,
    /// This endpoint's own inbox service, to look up who is behind a publisher.
    inbox_svc: iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], ()>,
    /// The process behind each publisher writing to this inbox (iceoryx2 records the
    /// node, and the node id the pid of the process that created it).
    senders: HashMap<iceoryx2::identifiers::UniquePublisherId, Option<u32>>,
    /// Peers sent frames by [`Endpoint::send_control_quiet`] whose bells
    /// [`Endpoint::ring_pending`] rings.
    pending_bells: Vec<Address>,
}

/// Most control frames held back for one peer whose inbox is full; beyond it the peer
/// is taken as hung and the oldest are dropped, loudly.
pub const MAX_BACKLOG: usize = 4096;
/// How soon a held-back control frame is tried again.
const BACKLOG_RETRY: Duration = Duration::from_millis(2);

impl Endpoint {
    /// Creates (or takes over, after a crash) the inbox and bell of `me`.
    pub fn open(inst: &Instance, me: Address, node: Node<Ipc>) -> Result<Self, TransportError> {
        let limits = InboxLimits::for_addr(&me);
        let inbox_name = inst.inbox(&me);
        let svc = node
            .service_builder(&service_name(&inbox_name)?)
            .publish_subscribe::<[u8]>()
            .max_publishers(limits.max_publishers)
            .max_subscribers(limits.readers)
            .max_nodes(limits.max_publishers + 2)
            .subscriber_max_buffer_size(limits.buffer)
            .subscriber_max_borrowed_samples(1)
            .history_size(0)
            .enable_safe_overflow(false)
            .open_or_create()
            .map_err(|e| svc_err(&inbox_name, e))?;
        let inbox = match svc.subscriber_builder().buffer_size(limits.buffer).create() {
            Ok(s) => s,
            Err(_) => {
                // A dead process of the same name may still hold the reader slots: clean
                // up after those readers first (a dead broker has hundreds of ports, and
                // the other dead nodes can wait), then after every dead node.
                let mut dead = Vec::new();
                svc.dynamic_config().list_subscribers(|d| {
                    dead.extend(node_pid(&d.node_id));
                    CallbackProgression::Continue
                });
                tracing::info!(inbox = %inbox_name, readers = ?dead, "the inbox's reader slots are held: cleaning up after dead readers");
                remove_stillborn_segments();
                let mut made = None;
                for pid in dead
                    .into_iter()
                    .filter(|p| !crate::reactor::process_alive(*p))
                {
                    // A cleanup process may be at it already: wait for it.
                    cleanup_dead_nodes_of_waiting(pid, Duration::from_secs(3));
                    if let Ok(s) = svc.subscriber_builder().buffer_size(limits.buffer).create() {
                        made = Some(s);
                        break;
                    }
                }
                if let Some(s) = made {
                    s
                } else {
                    node.try_cleanup_dead_nodes();
                    svc.subscriber_builder()
                        .buffer_size(limits.buffer)
                        .create()
                        .map_err(|e| {
                            if format!("{e:?}").contains("ExceedsMax") {
                                TransportError::InUse(me.clone())
                            } else {
                                svc_err(&inbox_name, e)
                            }
                        })?
                }
            }
        };
        let bell_name = inst.bell(&me);
        let bell_svc = node
            .service_builder(&service_name(&bell_name)?)
            .event()
            .max_notifiers(limits.max_publishers)
            .max_listeners(limits.readers)
            .max_nodes(limits.max_publishers + 2)
            .event_id_max_value(bell::MAX)
            .open_or_create()
            .map_err(|e| svc_err(&bell_name, e))?;
        let bell = match bell_svc.listener_builder().create() {
            Ok(l) => l,
            Err(_) => {
                node.try_cleanup_dead_nodes();
                bell_svc
                    .listener_builder()
                    .create()
                    .map_err(|e| svc_err(&bell_name, e))?
            }
        };
        Ok(Endpoint {
            inst: inst.clone(),
            me,
            node,
            inbox,
            bell,
            peers: HashMap::new(),
            lingering: HashMap::new(),
            dropped_sends: 0,
            recv_errors: 0,
            backlog: HashMap::new(),
            inbox_svc: svc,
            senders: HashMap::new(),
            pending_bells: Vec::new(),
        })
    }

    /// This endpoint's address.
    pub fn me(&self) -> &Address {
        &self.me
    }

    /// The iceoryx2 node.
    pub fn node(&self) -> &Node<Ipc> {
        &self.node
    }

    /// The bell's file descriptor, for the reactor.
    pub fn bell_fd(&self) -> RawFd {
        // SAFETY: the descriptor stays owned by the listener; we only read its number.
        unsafe { self.bell.file_descriptor().native_handle() }
    }

    /// Empties the bell; returns the set of event ids rung (bit i = id i).
    pub fn drain_bell(&self) -> u64 {
        drain_ids(&self.bell)
    }

    /// Takes the next frame from the inbox, copied out (it is decoded right away).
    ///
    /// A receive error (e.g. a peer's connection broken when it died mid-write) ends
    /// this drain and is counted and logged (1st, 2nd, 4th, ... time); it never stops
    /// the process: one bad peer must not take a long-running broker or system down.
    pub fn recv(&mut self) -> Option<Vec<u8>> {
        self.recv_from().map(|(f, _)| f)
    }

    /// [`Endpoint::recv`], with the pid of the process that wrote the frame (from the
    /// iceoryx2 publisher and node behind it; `None` if it cannot be told), so that a
    /// process can be held to speak only as itself.
    pub fn recv_from(&mut self) -> Option<(Vec<u8>, Option<u32>)> {
        match self.inbox.receive() {
            Ok(Some(sample)) => {
                let publisher = sample.header().publisher_id();
                let frame = sample.payload().to_vec();
                drop(sample);
                Some((frame, self.sender_pid(publisher)))
            }
            Ok(None) => None,
            Err(e) => {
                self.recv_errors += 1;
                if self.recv_errors.is_power_of_two() {
                    let e = svc_err(&self.inst.inbox(&self.me), e);
                    tracing::warn!(errors = self.recv_errors, "inbox receive failed: {e}");
                }
                None
            }
        }
    }

    fn sender_pid(&mut self, publisher: iceoryx2::identifiers::UniquePublisherId) -> Option<u32> {
        if let Some(pid) = self.senders.get(&publisher) {
            return *pid;
        }
        if self.senders.len() > 4096 {
            self.senders.clear(); // publishers come and go; rebuild from the live ones
        }
        let senders = &mut self.senders;
        self.inbox_svc.dynamic_config().list_publishers(|d| {
            senders.insert(d.publisher_id, node_pid(&d.node_id));
            iceoryx2::prelude::CallbackProgression::Continue
        });
        self.senders.get(&publisher).copied().flatten()
    }

    /// The pid of the process that owns `of`'s inbox (its one subscriber), or `None` if
    /// nobody does or it cannot be told. A process that claims to be `of` (a broker
    /// announcing itself, a system granting a session) is believed only if it is this
    /// process: an inbox has one reader, so a running broker or system cannot be posed as.
    /// The broker's inbox may have more readers for a while (a new broker took over
    /// before old ones' ports were cleaned up): its owner is the one that holds the
    /// instance's fence.
    pub fn owner_pid(&mut self, of: &Address) -> Option<u32> {
        let readers = self.reader_pids(of);
        match readers.as_slice() {
            [] => None,
            [one] => Some(*one),
            many => {
                let holder = crate::fence::Fence::open_existing(&self.inst)
                    .ok()?
                    .holder()
                    .pid;
                many.contains(&holder).then_some(holder)
            }
        }
    }

    /// The pids of the processes reading `of`'s inbox.
    pub fn reader_pids(&mut self, of: &Address) -> Vec<u32> {
        fn pids(
            svc: &iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], ()>,
        ) -> Vec<u32> {
            let mut out = Vec::new();
            svc.dynamic_config().list_subscribers(|d| {
                out.extend(node_pid(&d.node_id));
                iceoryx2::prelude::CallbackProgression::Continue
            });
            out
        }
        if let Some(peer) = self.peers.get(of) {
            return pids(&peer.inbox);
        }
        if *of == self.me {
            return pids(&self.inbox_svc);
        }
        let Some(svc) = service_name(&self.inst.inbox(of)).ok().and_then(|name| {
            self.node
                .service_builder(&name)
                .publish_subscribe::<[u8]>()
                .open()
                .ok()
        }) else {
            return Vec::new();
        };
        pids(&svc)
    }

    /// Receive errors so far (see [`Endpoint::recv`]).
    pub fn recv_errors(&self) -> u64 {
        self.recv_errors
    }

    fn peer(&mut self, to: &Address) -> Result<&mut Peer, TransportError> {
        if !self.peers.contains_key(to) {
            let started = Instant::now();
            let opened = self.open_peer(to);
            let took = started.elapsed();
            if took > Duration::from_millis(50) {
                tracing::debug!(peer = %to, ?took, ok = opened.is_ok(), "opening a peer's ports was slow");
            }
            opened?;
        }
        Ok(self.peers.get_mut(to).expect("inserted above"))
    }

    fn open_peer(&mut self, to: &Address) -> Result<(), TransportError> {
        {
            let inbox_name = self.inst.inbox(to);
            let svc = self
                .node
                .service_builder(&service_name(&inbox_name)?)
                .publish_subscribe::<[u8]>()
                .open()
                .map_err(|_| TransportError::Unreachable(to.clone()))?;
            let (len, strategy) = match (&self.me, to) {
                (Address::System(_), Address::Broker) => {
                    (INITIAL_LARGE_FRAME, AllocationStrategy::PowerOfTwo)
                }
                _ => (SMALL_FRAME, AllocationStrategy::Static),
            };
            let publisher = svc
                .publisher_builder()
                .initial_max_slice_len(len)
                .allocation_strategy(strategy)
                .max_loaned_samples(1)
                .backpressure_strategy(BackpressureStrategy::DiscardData)
                .create()
                .map_err(|e| svc_err(&inbox_name, e))?;
            let bell_name = self.inst.bell(to);
            let notifier = self
                .node
                .service_builder(&service_name(&bell_name)?)
                .event()
                .open()
                .map_err(|_| TransportError::Unreachable(to.clone()))?
                .notifier_builder()
                .create()
                .map_err(|e| svc_err(&bell_name, e))?;
            self.peers.insert(
                to.clone(),
                Peer {
                    publisher,
                    notifier,
                    inbox: svc,
                },
            );
        }
        Ok(())
    }

    /// Encodes `msg` and sends it to `to` (see [`Endpoint::send`]).
    pub fn send_msg<T: serde::Serialize>(
        &mut self,
        to: &Address,
        msg: &T,
    ) -> Result<(), TransportError> {
        let frame = crate::protocol::encode(msg).map_err(|source| TransportError::Encode {
            peer: to.clone(),
            source,
        })?;
        self.send(to, &frame)
    }

    /// Encodes and sends `msg`; a failure is logged (an encoding error loudly, a gone or
    /// busy peer quietly: process death and gaps are handled elsewhere).
    pub fn send_or_log<T: serde::Serialize>(&mut self, to: &Address, msg: &T) {
        match self.send_msg(to, msg) {
            Ok(()) => {}
            Err(e @ TransportError::Encode { .. }) => tracing::error!("{e}"),
            Err(e) => tracing::debug!("{e}"),
        }
    }

    /// Encodes and sends a control message (anything but a data update): if `to`'s
    /// inbox is full it is held back and retried in order by [`Endpoint::sweep`], never
    /// dropped (up to [`MAX_BACKLOG`] frames per peer). Errors other than a full inbox
    /// are logged as in [`Endpoint::send_or_log`].
    pub fn send_control<T: serde::Serialize>(&mut self, to: &Address, msg: &T) {
        self.control(to, msg, true)
    }

    /// [`Endpoint::send_control`], ringing `to`'s bell now if `ring`, else leaving it
    /// for [`Endpoint::ring_pending`].
    fn control<T: serde::Serialize>(&mut self, to: &Address, msg: &T, ring: bool) {
        let frame = match crate::protocol::encode(msg) {
            Ok(f) => f,
            Err(source) => {
                let e = TransportError::Encode {
                    peer: to.clone(),
                    source,
                };
                return tracing::error!("{e}");
            }
        };
        if let Some(q) = self.backlog.get_mut(to) {
            // Behind earlier frames: keep the order.
            return Self::hold(q, to, frame, &mut self.dropped_sends);
        }
        match self.send_ringing(to, &frame, ring) {
            Ok(()) => {}
            Err(TransportError::Full(_)) => {
                self.dropped_sends -= 1; // not dropped: held back
                let q = self.backlog.entry(to.clone()).or_default();
                Self::hold(q, to, frame, &mut self.dropped_sends);
            }
            Err(e) => tracing::debug!("{e}"),
        }
    }

    /// [`Endpoint::send_control`], but the frame is only written: `to`'s bell rings at
    /// the next [`Endpoint::ring_pending`]. A frame written before another peer's frame
    /// is visible before it, so a process that reads `to`'s inbox after hearing from
    /// that peer finds it, bell or not; and the other peer's bell rings first, so its
    /// wake-up does not wait behind `to`'s.
    pub fn send_control_quiet<T: serde::Serialize>(&mut self, to: &Address, msg: &T) {
        self.control(to, msg, false)
    }

    /// Whether [`Endpoint::send_control_quiet`] left bells to ring.
    pub fn bells_pending(&self) -> bool {
        !self.pending_bells.is_empty()
    }

    /// Rings the bells [`Endpoint::send_control_quiet`] left, once per peer.
    pub fn ring_pending(&mut self) {
        for to in std::mem::take(&mut self.pending_bells) {
            if let Err(e) = self.ring(&to, bell::MESSAGE) {
                tracing::debug!("{e}");
            }
        }
    }

    fn hold(q: &mut VecDeque<Vec<u8>>, to: &Address, frame: Vec<u8>, dropped: &mut u64) {
        if q.len() >= MAX_BACKLOG {
            q.pop_front();
            *dropped += 1;
            if dropped.is_power_of_two() {
                tracing::warn!(peer = %to, "{to}'s inbox stays full: dropped a held-back control frame");
            }
        }
        q.push_back(frame);
    }

    /// Tries the held-back control frames again, in order.
    fn flush_backlog(&mut self) {
        let peers: Vec<Address> = self.backlog.keys().cloned().collect();
        for to in peers {
            let Some(mut q) = self.backlog.remove(&to) else {
                continue;
            };
            while let Some(frame) = q.front() {
                match self.try_send(&to, frame, true) {
                    Ok(()) => {
                        q.pop_front();
                    }
                    Err(TransportError::Full(_)) => break,
                    Err(e) => {
                        // Gone: whatever it restarts as re-registers or says hello.
                        tracing::debug!("{e}; dropping {} held-back frames", q.len());
                        self.dropped_sends += q.len() as u64;
                        self.peers.remove(&to);
                        q.clear();
                    }
                }
            }
            if !q.is_empty() {
                self.backlog.insert(to, q);
            }
        }
    }

    /// Control frames held back for full inboxes.
    pub fn backlog(&self) -> usize {
        self.backlog.values().map(VecDeque::len).sum()
    }

    /// Writes a frame into `to`'s inbox and rings its bell.
    /// Behind held-back control frames, it is not sent (a data update overtaking them
    /// would break their order) and counts as full.
    pub fn send(&mut self, to: &Address, frame: &[u8]) -> Result<(), TransportError> {
        self.send_ringing(to, frame, true)
    }

    /// [`Endpoint::send`]; the bell is left for [`Endpoint::ring_pending`] unless `ring`.
    fn send_ringing(
        &mut self,
        to: &Address,
        frame: &[u8],
        ring: bool,
    ) -> Result<(), TransportError> {
        self.lingering.remove(to);
        if self.backlog.contains_key(to) {
            self.dropped_sends += 1;
            return Err(TransportError::Full(to.clone()));
        }
        let result = self.try_send(to, frame, ring);
        match &result {
            Ok(()) => {}
            Err(TransportError::Full(_)) => self.dropped_sends += 1,
            Err(_) => {
                // Forget the ports: the peer may come back as a new process.
                self.peers.remove(to);
                self.dropped_sends += 1;
            }
        }
        result
    }

    fn try_send(&mut self, to: &Address, frame: &[u8], ring: bool) -> Result<(), TransportError> {
        let large = matches!((&self.me, to), (Address::System(_), Address::Broker));
        if !large && frame.len() > SMALL_FRAME {
            return Err(TransportError::Send {
                peer: to.clone(),
                detail: format!(
                    "frame of {} bytes exceeds the {SMALL_FRAME}-byte limit of this path",
                    frame.len()
                ),
            });
        }
        let peer = self.peer(to)?;
        let send_err = |e: &dyn std::fmt::Debug| TransportError::Send {
            peer: to.clone(),
            detail: format!("{e:?}"),
        };
        let sample = peer
            .publisher
            .loan_slice_uninit(frame.len())
            .map_err(|e| send_err(&e))?;
        let delivered = sample
            .write_from_slice(frame)
            .send()
            .map_err(|e| send_err(&e))?;
        if delivered == 0 {
            // Nobody read it: either nobody is there, or the reader's queue is full.
            return Err(
                if peer.inbox.dynamic_config().number_of_subscribers() == 0 {
                    TransportError::Unreachable(to.clone())
                } else {
                    TransportError::Full(to.clone())
                },
            );
        }
        if ring {
            peer.notifier
                .notify_with_custom_event_id(EventId::new(bell::MESSAGE))
                .map_err(|e| send_err(&e))?;
        } else if !self.pending_bells.contains(to) {
            self.pending_bells.push(to.clone());
        }
        Ok(())
    }

    /// Rings `to`'s bell with `id` without sending a frame.
    pub fn ring(&mut self, to: &Address, id: usize) -> Result<(), TransportError> {
        let result = self.peer(to).and_then(|p| {
            p.notifier
                .notify_with_custom_event_id(EventId::new(id))
                .map(|_| ())
                .map_err(|e| TransportError::Send {
                    peer: to.clone(),
                    detail: format!("{e:?}"),
                })
        });
        if result.is_err() {
            self.peers.remove(to);
        }
        result
    }

    /// Forgets the cached ports to `to` at once (it died), releasing their shared memory.
    pub fn forget(&mut self, to: &Address) {
        self.peers.remove(to);
        self.lingering.remove(to);
    }

    /// Forgets the ports to `to` after [`LINGER`], so frames just sent still arrive.
    /// Sending to `to` again in the meantime keeps them.
    pub fn release(&mut self, to: &Address) {
        if self.peers.contains_key(to) {
            self.lingering.insert(to.clone(), Instant::now() + LINGER);
        }
    }

    /// Retries held-back control frames and drops lingering ports whose time is up;
    /// returns how long until either is due again.
    pub fn sweep(&mut self) -> Option<Duration> {
        self.flush_backlog();
        let now = Instant::now();
        let due: Vec<Address> = self
            .lingering
            .iter()
            .filter(|(_, t)| **t <= now)
            .map(|(a, _)| a.clone())
            .collect();
        for a in due {
            self.lingering.remove(&a);
            self.peers.remove(&a);
        }
        let linger = self
            .lingering
            .values()
            .min()
            .map(|t| t.saturating_duration_since(now));
        let retry = (!self.backlog.is_empty()).then_some(BACKLOG_RETRY);
        [linger, retry].into_iter().flatten().min()
    }

    /// Opens the ports to `to` now, if they are not open, so a later send to it costs no
    /// first contact.
    pub fn open_ports(&mut self, to: &Address) -> Result<(), TransportError> {
        self.peer(to).map(|_| ())
    }

    /// Whether the ports to `to` are open (a send to it costs no first contact).
    pub fn has_ports(&self, to: &Address) -> bool {
        self.peers.contains_key(to)
    }

    /// Peers with open ports (including lingering ones).
    pub fn open_peers(&self) -> usize {
        self.peers.len()
    }

    /// Frames that could not be delivered so far.
    pub fn dropped_sends(&self) -> u64 {
        self.dropped_sends
    }
}

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

type StreamFactory = iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], ()>;
type EventFactory = iceoryx2::service::port_factory::event::PortFactory<Ipc>;

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
        let subscriber = stream
            .subscriber_builder()
            .buffer_size(REPLICA_BUFFER)
            .create()
            .map_err(|e| svc_err(&inst.replica(), e))?;
        let listener = bell
            .listener_builder()
            .create()
            .map_err(|e| svc_err(&inst.replica_bell(), e))?;
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
    fn stamped_list(generation: u64, count: usize) -> Box<ServiceListSnapshot> {
        let mut s = Box::new(ServiceListSnapshot::empty());
        s.generation = generation;
        s.epoch = 1;
        s.count = count as u32;
        for (i, e) in s.entries.iter_mut().take(count).enumerate() {
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
        w.publish(&stamped_list(1, 40), &fence).unwrap();
        let mut r = ListReader::open(&node, &inst).unwrap();
        let a = r.read().unwrap();
        assert_eq!((a.generation, a.count, a.entries[39].quota), (1, 40, 1));
        assert_eq!(a.entries[39].name.as_str(), "s39");
        let b = r.read().unwrap();
        assert!(Arc::ptr_eq(&a, &b), "unchanged: the same copy");
        // Fewer entries, then more: the chunks left over from before are not read.
        w.publish(&stamped_list(2, 3), &fence).unwrap();
        let c = r.read().unwrap();
        assert_eq!((c.generation, c.count, c.entries().len()), (2, 3, 3));
        assert!(c.entries().iter().all(|e| e.quota == 2));
        w.publish(&stamped_list(3, 250), &fence).unwrap();
        let d = r.read().unwrap();
        assert_eq!(d.count, 250);
        assert!(d.entries().iter().all(|e| e.quota == 3));
        assert_eq!(d.entries[249].name.as_str(), "s249");
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
                    assert_eq!(s.count as u64, count, "count of write {g}");
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
            w.publish(&stamped_list(g, 1 + (g % 200) as usize), &fence)
                .unwrap();
            std::thread::sleep(Duration::from_micros(200));
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        assert!(reader.join().unwrap() > 0);
        drop(r);
        drop(w);
        fence.remove();
    }
}
