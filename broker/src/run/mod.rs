//! The broker process: drives [`crate::core::Broker`] over iceoryx2.
//!
//! It sleeps in one epoll over its bell, a signal pipe and one pidfd per registered
//! system and user, and wakes only for frames, process deaths, or the core's next
//! deadline (a ping, a ping timeout, an offer timeout).

use crate::core::{Broker, BrokerConfig, Output};
use crate::federation::{Delivery, FarGrant, FedConfig, FedError, Federation};
use crate::replica::{Follower, Leader, Step};
use crate::takeover::{self, Verdict};
use crate::udp::{FrontEvent, UdpConfig, UdpError, UdpFront};
use crate::watchdog::Phase;
use muster_shared::fence::{Fence, Holder};
use muster_shared::ipc::{
    bell, create_node, inbox_reader_pids, BellRinger, Endpoint, EventWriter, ListWriter, Presence,
    ReplicaReader, ReplicaWriter, TransportError,
};
use muster_shared::names::{Address, Instance};
use muster_shared::protocol::{decode, ToBroker, ToSystem, ToUser};
use muster_shared::reactor::{
    process_alive, process_exists, raise_fd_limit, PidFd, Reactor, SignalPipe,
};
use muster_shared::snapshot::ServiceListSnapshot;
use muster_shared::trace::Stage;
use muster_shared::types::UserId;
use muster_shared::udp::access::AccessFile;
use muster_shared::udp::wire::MAX_DATAGRAM;
use muster_shared::udp::{recv_one, send_transmit, size_recv_buffer, RECV_BATCH};
use rand::RngExt;
use std::collections::{HashMap, HashSet, VecDeque};
use std::net::UdpSocket;
use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

mod cleanup;
mod handling;
mod latched;
mod replication;
mod standby;
mod udp_driver;

pub use self::cleanup::*;
pub use self::handling::*;
use self::replication::*;
pub use self::standby::*;
use self::udp_driver::*;

/// Why the broker could not start or had to stop.
#[derive(Debug, thiserror::Error)]
pub enum BrokerError {
    /// Shared memory could not be set up; see the detail (another broker on this instance?).
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// The OS refused epoll, signals or rlimits.
    #[error("os: {0}")]
    Os(#[from] std::io::Error),
    /// Another broker already serves this instance.
    #[error("another broker already serves instance {0:?}")]
    AlreadyRunning(String),
    /// The UDP front could not start.
    #[error(transparent)]
    Udp(#[from] crate::udp::UdpError),
    /// The broker could not join its federation.
    #[error(transparent)]
    Federation(#[from] FedError),
    /// Another broker took the instance over while this one was stopped or hung.
    #[error("taken over by broker pid {pid} (term {term}) while this broker was stopped or hung; it did not act and stops")]
    Fenced {
        /// The broker that holds the instance now.
        pid: u32,
        /// Its term.
        term: u32,
    },
}

const TOKEN_BELL: usize = 0;
const TOKEN_SIGNAL: usize = 1;
const TOKEN_UDP: usize = 2;
const TOKEN_HUP: usize = 3;
const TOKEN_FED: usize = 4;
const TOKEN_EVENTS: usize = 5;
const FIRST_WATCH_TOKEN: usize = 16;

/// A watched process: a system or a user, by its address.
/// A process watched for its death, and who speaks from it: one pidfd per process,
/// however many users it hosts (16 a process would otherwise take 16 descriptors).
struct Watch {
    pid: u32,
    who: HashSet<Address>,
    pidfd: PidFd,
}

/// What a broker did during its run, returned when it stops.
#[derive(Debug)]
pub struct BrokerReport {
    /// Counters from the core.
    pub stats: crate::core::BrokerStats,
    /// Time to handle each message type, µs, and the log if one was kept.
    pub handling: Handling,
    /// Counters of the UDP front, if it ran.
    pub udp: Option<crate::udp::UdpStats>,
    /// Counters of the federation, if the broker joined one.
    pub federation: Option<crate::federation::FedStats>,
    /// Its descriptors: the limit, the most open at a count, and the peers whose
    /// idle ports it closed to stay within it.
    pub descriptors: Descriptors,
}

/// What a broker saw of its descriptors ([`BrokerReport::descriptors`]).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Descriptors {
    /// Its limit (the soft one).
    pub limit: u64,
    /// The most open at any count (every [`OPEN_PEERS_EVERY`] and more) that found a
    /// descriptor free to count with.
    pub most_open: u64,
    /// Counts taken.
    pub counts: u64,
    /// Counts that found every descriptor open: the broker at its limit (frames to
    /// peers whose ports it closed wait until some close).
    pub at_limit: u64,
    /// Held peers whose idle ports were closed ([`max_open_peers`]).
    pub idle_ports_closed: u64,
}

impl BrokerReport {
    /// The report as JSON: counters, and count/p50/p99/max µs per message type.
    pub fn to_json(&self) -> serde_json::Value {
        let handling: serde_json::Map<String, serde_json::Value> = self
            .handling
            .hist
            .iter()
            .map(|(k, h)| {
                (
                    k.to_string(),
                    serde_json::json!({"count": h.len(), "p50_us": h.value_at_quantile(0.5),
                                       "p99_us": h.value_at_quantile(0.99), "max_us": h.max(),
                                       "mean_us": h.mean(), "stdev_us": h.stdev()}),
                )
            })
            .collect();
        serde_json::json!({"stats": self.stats, "handling": handling, "udp": self.udp,
                           "federation": self.federation, "descriptors": self.descriptors})
    }
}

/// The broker process's state outside the core.
struct Shell {
    endpoint: Endpoint,
    /// The list's writer (this run's own blackboard).
    list: ListWriter,
    /// The instance's fence: who may act, and which list readers read.
    fence: Fence,
    reactor: Reactor,
    watches: HashMap<usize, Watch>,
    by_addr: HashMap<Address, usize>,
    by_pid: HashMap<u32, usize>,
    next_token: usize,
    snapshot: Box<ServiceListSnapshot>,
    handling: Handling,
    /// When list watchers were last rung, and whether a ring is owed.
    last_ring: Option<Instant>,
    ring_owed: bool,
    /// What changed in the list since watchers were last rung, to ring those watching
    /// a part of it only when that part changed.
    rings: crate::rings::Rings,
    /// The core's list shape the rows in `local_views` were taken at.
    list_shape: u64,
    /// When what waits for the peers just woken is done ([`AFTER_WAKING`]): the bells
    /// of systems sent offers, and a change of this host's list's counts.
    deferred_at: Option<Instant>,
    /// Outputs for peers whose ports are not open yet: see [`OPEN_BUDGET`].
    unopened: PeerQueue,
    udp: Option<UdpDriver>,
    replica: Replication,
    /// This host's membership in a federation, if it joined one.
    fed: Option<Federation>,
    /// The event feed, if it could be opened.
    events: Option<EventWriter>,
    /// The newest value of each latched data service, for its next grant.
    latched: latched::Latched,
    /// This host's services as listed: the core's list as last taken, with (in a
    /// federation) other hosts' users' links counted (other hosts' lists change the
    /// merged one on their own).
    local_views: Vec<muster_shared::snapshot::ServiceView>,
    /// In a federation, the core's list as last taken (`local_views` adds other hosts'
    /// users' links to it).
    core_views: Vec<muster_shared::snapshot::ServiceView>,
}

/// The broker's federation membership, if any, as the UDP front's driver gets it.
type Fed<'a> = &'a mut Option<Federation>;

/// List watchers are rung at most this often; the blackboard itself is updated at once.
const RING_EVERY: Duration = Duration::from_millis(100);
/// How long after a flush the bells of systems sent offers ring and a change of the
/// list's counts in use is written: the user told of its grant runs first (a user's
/// first frame to the system rings it at once anyway). The reactor ends so short a
/// wait on a timer of its own ([`muster_shared::reactor::PRECISE_BELOW`]): epoll's
/// whole milliseconds made it 1 ms and more.
const AFTER_WAKING: Duration = Duration::from_micros(500);
/// How long one flush spends opening ports to peers it has not written to yet (a
/// welcome to a new user, its first grant): hundreds of µs each, and when hundreds of
/// users connect at once their welcomes would hold the loop for a second while the
/// requests of users already connected wait in the inbox. Past it, outputs for such
/// peers wait, in order, for the next pass, which reads the inbox first.
const OPEN_BUDGET: Duration = Duration::from_millis(2);
/// Up to this many outputs of one flush go out before the list is written; more, and
/// the list goes first.
const LIST_AFTER_AT_MOST: usize = 16;

/// Runs a broker on `inst` until SIGINT or SIGTERM; returns what it did.
pub fn run(inst: &Instance, cfg: BrokerConfig) -> Result<BrokerReport, BrokerError> {
    run_with(inst, cfg, None, None, false)
}

/// A deliberate fault, for tests and benches (`muster broker --fault`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// After this many passes, the primary's loop stops for good while its process
    /// lives on: a deadlock, as a standby sees it.
    HangAfter(u64),
    /// Once SIGUSR1 arrives, the primary's loop stops for good at its next pass (a
    /// standby's too, once it serves): a hang at a moment a bench chooses.
    HangOnUsr1,
}

static FAULT: std::sync::OnceLock<Fault> = std::sync::OnceLock::new();
/// Set by SIGUSR1 under [`Fault::HangOnUsr1`].
static USR1: std::sync::OnceLock<std::sync::Arc<std::sync::atomic::AtomicBool>> =
    std::sync::OnceLock::new();

/// Arms `fault` in this process's primary loop.
pub fn set_fault(fault: Fault) {
    if fault == Fault::HangOnUsr1 {
        let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        match signal_hook::flag::register(signal_hook::consts::SIGUSR1, flag.clone()) {
            Ok(_) => {
                let _ = USR1.set(flag);
            }
            Err(e) => tracing::warn!("fault hang-on-usr1 not armed: {e}"),
        }
    }
    let _ = FAULT.set(fault);
}

/// Whether the armed fault says the loop stops at this pass.
fn fault_now(passes: u64) -> bool {
    match FAULT.get() {
        Some(Fault::HangAfter(n)) => passes >= *n,
        Some(Fault::HangOnUsr1) => USR1
            .get()
            .is_some_and(|f| f.load(std::sync::atomic::Ordering::Relaxed)),
        None => false,
    }
}

/// How long after taking over a new primary rings the presence event (see `serve`).
const TAKEOVER_RING_DELAY: Duration = Duration::from_millis(60);

/// How long a broker started cold waits before it cleans up after dead processes.
const COLD_CLEANUP_DELAY: Duration = Duration::from_millis(500);

/// How long remote users of an old primary have to reconnect to a new one.
const REMOTE_RETURN: Duration = Duration::from_secs(20);

/// How long a new primary lets the first interactions go before it cleans up after the
/// old one (the cleanup locks the services both used, and would delay them).
const CLEANUP_DELAY: Duration = Duration::from_millis(200);

/// How often a primary with standbys tells them it is alive when it has nothing else
/// to say.
pub const HEARTBEAT: Duration = Duration::from_millis(20);
/// How long a standby waits without a record before it takes the primary for hung.
pub const DEFAULT_TAKEOVER_DEADLINE: Duration = Duration::from_millis(100);

/// The time on the host's monotonic clock: one clock for a primary and its standbys, so
/// the deadlines in the replicated state mean the same in both.
fn host_now() -> Duration {
    Duration::from_nanos(muster_shared::protocol::monotonic_ns())
}

/// A new run's epoch: the wall clock in ns, after every earlier run's.
fn new_epoch(after: u64) -> u64 {
    let wall = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    wall.max(after.saturating_add(1))
}

fn open_fence(inst: &Instance) -> Result<Fence, BrokerError> {
    Fence::open(inst).map_err(|e| {
        BrokerError::Os(std::io::Error::new(
            e.kind(),
            format!("the instance's fence file: {e}"),
        ))
    })
}

/// Takes the next term of the fence for this process, from whoever held it (a broker
/// that died, or nobody).
fn claim_fence(fence: &Fence) -> Holder {
    let pid = std::process::id();
    loop {
        let seen = fence.holder();
        if let Some(me) = fence.claim(seen, pid) {
            return me;
        }
    }
}

/// Descriptors the broker holds for its ports to one peer's inbox and bell (measured:
/// 10): iceoryx2 keeps each service's static config, dynamic config and port tag open,
/// the publisher's data segment and connection, and the notifier's socket and event
/// management. The broker closes them for idle peers when descriptors run short
/// ([`max_open_peers`]).
pub const FDS_PER_PEER_PORTS: u64 = 10;
/// Descriptors a local user costs the broker whatever it does: the user's writer to the
/// broker's inbox (its data segment and connection), and its process's pidfd. Remote
/// users cost one connection entry and no descriptor.
pub const FDS_PER_LOCAL_USER: u64 = 3;
/// Descriptors left for everything else (systems' registrations, the lists, the event
/// feed, replication, sockets, logs): an eighth of the limit, at most this many.
const FDS_RESERVE: u64 = 1024;
/// The fewest peers whose ports stay open however many users are connected.
const MIN_OPEN_PEERS: u64 = 16;
/// How often the broker's descriptors are counted, and the most open peers worked out
/// again: this, or a hundred times as long as a count takes (about 2–3 s at 20,000
/// descriptors), whichever is longer.
const OPEN_PEERS_EVERY: Duration = Duration::from_millis(50);

/// The most peers the broker keeps ports open to, its descriptor limit `limit`, with
/// `open_fds` descriptors open when `open_peers` peers' ports were: those peers, and as
/// many more as the descriptors left (less a reserve for what opens meanwhile and
/// everything else) hold at [`FDS_PER_PEER_PORTS`]; fewer than are open when the
/// reserve is eaten into (connecting users' own costs come first), and then ports to
/// peers idle for [`LINGER`] close. Idle users then cost [`FDS_PER_LOCAL_USER`] each,
/// not 13: 5,000 local users fit a limit of 20,000.
///
/// [`LINGER`]: muster_shared::ipc::LINGER
pub fn max_open_peers(limit: u64, open_fds: u64, open_peers: usize) -> usize {
    let free = i128::from(limit) - i128::from(reserve(limit)) - i128::from(open_fds);
    let most = open_peers as i128 + free / i128::from(FDS_PER_PEER_PORTS);
    usize::try_from(most.max(i128::from(MIN_OPEN_PEERS))).unwrap_or(usize::MAX)
}

/// About the most local users a broker with a descriptor limit of `limit` takes: each
/// costs [`FDS_PER_LOCAL_USER`], and [`MIN_OPEN_PEERS`] peers keep their ports open.
pub fn max_local_users(limit: u64) -> u64 {
    limit.saturating_sub(reserve(limit) + MIN_OPEN_PEERS * FDS_PER_PEER_PORTS) / FDS_PER_LOCAL_USER
}

/// Descriptors kept back from peers' ports and users at a limit of `limit`.
fn reserve(limit: u64) -> u64 {
    (limit / 8).min(FDS_RESERVE)
}

/// Raises the descriptor limit as far as it may; returns it.
fn raise_fds() -> u64 {
    match raise_fd_limit() {
        Ok(n) if max_local_users(n) < 256 => {
            tracing::warn!(
                "file-descriptor limit is {n}: at most about {} local users (remote users need none)",
                max_local_users(n)
            );
            n
        }
        Ok(n) => {
            tracing::debug!(
                "file-descriptor limit {n}: at most about {} local users",
                max_local_users(n)
            );
            n
        }
        Err(e) => {
            tracing::warn!("cannot raise the file-descriptor limit: {e}");
            muster_shared::reactor::fd_limit()
        }
    }
}

/// Runs a broker with a UDP front for remote users if `udp` is given.
pub fn run_with(
    inst: &Instance,
    cfg: BrokerConfig,
    udp: Option<UdpConfig>,
    fed: Option<FedConfig>,
    keep_log: bool,
) -> Result<BrokerReport, BrokerError> {
    raise_fds();
    // Dead nodes (a crashed broker's above all) are cleaned up beside serving, not
    // before: the broker's inbox takes more than one reader, and each run writes its own list.
    let node = create_node(&inst.broker_node(), false)?;
    let mut endpoint = Endpoint::open(inst, Address::Broker, node).map_err(|e| match e {
        TransportError::InUse(_) => BrokerError::AlreadyRunning(inst.to_string()),
        other => BrokerError::from(other),
    })?;
    let pid = std::process::id();
    if endpoint
        .reader_pids(&Address::Broker)
        .iter()
        .any(|p| *p != pid && process_alive(*p))
    {
        return Err(BrokerError::AlreadyRunning(inst.to_string()));
    }
    let fence = open_fence(inst)?;
    // A crashed broker's ports (they keep one of the inbox's reader slots) and other
    // dead processes': after the restart's storm.
    let cleanup = cleaner(inst, None, COLD_CLEANUP_DELAY);
    let me = claim_fence(&fence);
    let core = Broker::new(cfg, new_epoch(0), pid);
    serve(
        inst,
        Primary {
            endpoint,
            fence,
            me,
            core,
            how: Start::Cold,
            seq: 0,
            standby_since: None,
            cleanup: Some(cleanup),
            presence: None,
            signals: None,
        },
        udp,
        fed,
        keep_log,
    )
}

/// How a primary came to be.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Start {
    /// From nothing: systems and users register and say hello again.
    Cold,
    /// A standby with the whole state took over: peers adopt it.
    Takeover,
}

/// A broker about to serve as the primary.
struct Primary {
    endpoint: Endpoint,
    fence: Fence,
    me: Holder,
    core: Broker,
    how: Start,
    seq: u64,
    /// When a standby began taking over (it reports when it serves).
    standby_since: Option<Instant>,
    /// Dead nodes being cleaned up beside serving.
    cleanup: Option<std::thread::JoinHandle<usize>>,
    /// The presence ringer, if a standby made it ready beforehand.
    presence: Option<Ringer>,
    /// The standby's signal pipe: a SIGTERM that came while it took over is not lost.
    signals: Option<SignalPipe>,
}

/// Serves as the primary until SIGINT or SIGTERM.
fn serve(
    inst: &Instance,
    p: Primary,
    udp: Option<UdpConfig>,
    fed: Option<FedConfig>,
    keep_log: bool,
) -> Result<BrokerReport, BrokerError> {
    let Primary {
        endpoint,
        fence,
        me,
        mut core,
        how,
        seq,
        standby_since,
        cleanup,
        presence,
        signals,
    } = p;
    let mut cleanups = Cleanups::new(inst, cleanup);
    let setup = Instant::now();
    let mut steps: Vec<(&str, u64)> = Vec::new();
    let mut step = |name| steps.push((name, setup.elapsed().as_micros() as u64));
    let presence = match presence {
        Some(p) => p,
        None => Ringer::spawn(inst)?,
    };
    step("presence");
    let list = ListWriter::open(endpoint.node(), inst, core.epoch())?;
    step("list");
    let replica = ReplicaWriter::open(endpoint.node(), inst)?;
    step("replica");
    let epoch = core.epoch();
    let mut signals = match signals {
        Some(s) => s,
        None => SignalPipe::install()?,
    };
    let mut hangup = SignalPipe::hangup()?;
    let reactor = Reactor::new()?;
    reactor.add(endpoint.bell_fd(), TOKEN_BELL)?;
    reactor.add(signals.raw(), TOKEN_SIGNAL)?;
    reactor.add(hangup.raw(), TOKEN_HUP)?;
    let udp = match udp {
        Some(c) => {
            let public = hex::encode(c.key.public);
            let driver = UdpDriver::bind(c, epoch)?;
            reactor.add(driver.sock.as_raw_fd(), TOKEN_UDP)?;
            tracing::info!(udp = %driver.front.local_addr(), broker_key = %public, "listening for remote users");
            Some(driver)
        }
        None => None,
    };
    let fed = match fed {
        Some(c) => {
            let mut f = match Federation::join(inst, &c, std::process::id(), how == Start::Cold) {
                Ok(f) => f,
                Err(e) => {
                    // Not serving after all: the instance is free for another broker.
                    if fence.holds(me) {
                        fence.remove();
                    }
                    return Err(e.into());
                }
            };
            reactor.add(f.wake_fd(), TOKEN_FED)?;
            if how == Start::Takeover {
                f.take_over(&mut core, &reactor, host_now());
            }
            Some(f)
        }
        None => None,
    };
    let mut shell = Shell {
        events: None,
        latched: latched::Latched::default(),
        fed,
        local_views: Vec::new(),
        core_views: Vec::new(),
        endpoint,
        list,
        fence,
        reactor,
        watches: HashMap::new(),
        by_addr: HashMap::new(),
        by_pid: HashMap::new(),
        next_token: FIRST_WATCH_TOKEN,
        snapshot: Box::new(ServiceListSnapshot::empty()),
        last_ring: None,
        ring_owed: false,
        rings: crate::rings::Rings::new(),
        list_shape: u64::MAX,
        deferred_at: None,
        unopened: PeerQueue::default(),
        handling: Handling::new(keep_log),
        udp,
        replica: Replication {
            writer: replica,
            leader: Leader::after(seq),
            image_owed: false,
            last_image: None,
            last_sent: Instant::now(),
        },
    };
    shell.snapshot.epoch = epoch;
    // Remote users of the old primary reconnect to our front (a stateless reset tells
    // them at once); one that does not come back within the time a silent broker
    // takes to notice is gone, and its queued requests and links with it.
    let mut remote_return: Option<(Instant, Vec<UserId>)> = (how == Start::Takeover)
        .then(|| (Instant::now() + REMOTE_RETURN, core.remote_users()))
        .filter(|(_, users)| !users.is_empty());
    if !shell.fence.holds(me) {
        return Err(fenced(&shell.fence));
    }
    step("ports");
    shell.flush(&mut core, host_now())?;
    step("flush");
    // A cold start rings at once: nobody can do anything before it. After a takeover
    // the ring waits a moment: users with requests out have found this broker through
    // the fence already, systems take its offers once they saw the old one die, and
    // waking every process at once now would only delay the first interactions.
    let mut takeover_ring = match how {
        Start::Cold => {
            presence.ring(bell::BROKER_UP);
            None
        }
        Start::Takeover => Some(Instant::now() + TAKEOVER_RING_DELAY),
    };
    step("ring");
    // The event feed serves consoles and recorders, once the instance is served; the
    // broker serves without it.
    match EventWriter::open(shell.endpoint.node(), inst, core.epoch()) {
        Ok(w) => {
            shell.reactor.add(w.fd(), TOKEN_EVENTS)?;
            core.emit_events();
            shell.events = Some(w);
        }
        Err(e) => tracing::warn!("no event feed: {e}"),
    }
    step("events");
    tracing::debug!(?steps, "broker setup, us since the start of serving");
    tracing::info!(instance = %inst, epoch = format!("{epoch:016x}"), term = me.term, "broker up");
    if let Some(t0) = standby_since {
        event(serde_json::json!({"event": "serving", "term": me.term,
                                 "ready_us": t0.elapsed().as_micros() as u64,
                                 "at_ns": muster_shared::protocol::monotonic_ns()}));
    }

    // The first turn reads the inbox whatever woke it: frames written before this
    // broker's bell existed (a takeover, a restart) rang nobody.
    let mut inbox_rang = true;
    let mut passes = 0u64;
    let fd_limit = muster_shared::reactor::fd_limit();
    let fd_gauge = muster_shared::reactor::FdGauge::start(OPEN_PEERS_EVERY)
        .map_err(|e| tracing::warn!("descriptors not counted (ports to idle users stay open): {e}"))
        .ok();
    let mut fds_seen = None;
    // Logs what the loop was doing if it makes no progress for a second outside its wait.
    let watchdog = crate::watchdog::Watchdog::start(STALL)
        .map_err(|e| tracing::warn!("no loop watchdog: {e}"))
        .ok();
    let at = |phase| {
        if let Some(w) = &watchdog {
            w.at(phase);
        }
    };
    loop {
        at(Phase::Waiting);
        if let Some(open) = fd_gauge.as_ref().and_then(|g| g.open()) {
            // Only on a new count: a most the ports lowered when they ran out of
            // descriptors stands until then.
            if fds_seen != Some(open) {
                fds_seen = Some(open);
                let peers = shell.endpoint.open_peers();
                let most = max_open_peers(fd_limit, open, peers);
                tracing::trace!(
                    open,
                    fd_limit,
                    peers,
                    most,
                    evictions = shell.endpoint.evictions(),
                    "descriptors"
                );
                shell.endpoint.set_max_open_peers(most);
            }
        }
        let now = host_now();
        let timeout = core.poll_timeout().map(|t| t.saturating_sub(now));
        let housekeeping = shell
            .udp
            .as_ref()
            .and_then(|d| d.front.poll_timeout())
            .map(|t| t.saturating_duration_since(Instant::now()));
        let timeout = [
            timeout,
            shell.ring_due(),
            shell.endpoint.sweep(),
            housekeeping,
            shell.replica.heartbeat_due(),
            shell.replica.image_due(),
            remote_return
                .as_ref()
                .map(|(t, _)| t.saturating_duration_since(Instant::now())),
            takeover_ring.map(|t| t.saturating_duration_since(Instant::now())),
            shell.fed.as_ref().and_then(Federation::next_due),
            shell
                .deferred_at
                .map(|t| t.saturating_duration_since(Instant::now())),
        ]
        .into_iter()
        .flatten()
        .min();
        let tokens = shell.reactor.wait(timeout)?;
        at(Phase::Timers);
        // Taken over while we slept (stopped, or hung past the deadline)? Then another
        // broker serves the instance: act on nothing.
        if !shell.fence.holds(me) {
            return Err(fenced(&shell.fence));
        }
        // The loop goes on: what a standby reads before it takes silence for a hang.
        shell.fence.beat();
        passes += 1;
        if fault_now(passes) {
            tracing::warn!(passes, "fault: the loop stops here for good (as asked)");
            loop {
                std::thread::sleep(Duration::from_secs(3600));
            }
        }
        if shell.deferred_at.is_some_and(|t| Instant::now() >= t) {
            at(Phase::Flush);
            shell.deferred_at = None;
            shell.endpoint.ring_pending();
            shell.publish_events(&mut core);
            shell.write_list(&mut core);
            // The list taken is an input of the core's, for the standbys too.
            shell.replica.publish(&mut core);
        }
        let now = host_now();
        let mut died: Vec<Address> = Vec::new();
        for token in tokens {
            match token {
                TOKEN_BELL => {
                    at(Phase::Inbox);
                    // Drained below, once the frame that rang it is answered.
                    inbox_rang = true;
                }
                TOKEN_SIGNAL => {
                    at(Phase::Signal);
                    if signals.drain() {
                        let standbys = shell.replica.writer.standbys();
                        if standbys > 0 {
                            // Hand over: the standbys have everything up to here, and
                            // every peer what the core had for it.
                            shell.flush(&mut core, host_now())?;
                            while !shell.unopened.is_empty() {
                                shell.flush(&mut core, host_now())?;
                            }
                            let _ = shell
                                .replica
                                .writer
                                .publish(&shell.replica.leader.stepping_down());
                            shell.replica.writer.ring();
                            tracing::info!(
                                standbys,
                                "signal received: broker stepping down to a standby"
                            );
                            // Stopped together with it (a whole run stopping, or its
                            // parent gone): with no standby left to take over, the
                            // instance ends here, as with a lone broker.
                            let until = Instant::now() + HANDOVER_WAIT;
                            while shell.fence.holds(me)
                                && shell.replica.writer.standbys() > 0
                                && Instant::now() < until
                            {
                                std::thread::sleep(Duration::from_millis(10));
                            }
                            if shell.fence.holds(me) && shell.replica.writer.standbys() == 0 {
                                tracing::info!("no standby took over: instance stopped");
                                presence.ring(bell::BROKER_DOWN);
                                shell.fence.remove();
                            }
                        } else {
                            tracing::info!("signal received: broker stopping");
                            presence.ring(bell::BROKER_DOWN);
                            if shell.fence.holds(me) {
                                shell.fence.remove();
                            }
                        }
                        // The feed's readers get what a deferral still held.
                        shell.publish_events(&mut core);
                        presence.finish();
                        return Ok(BrokerReport {
                            stats: core.stats().clone(),
                            handling: shell.handling,
                            udp: shell.udp.as_ref().map(|d| d.front.stats().clone()),
                            federation: shell.fed.as_ref().map(|f| f.stats()),
                            descriptors: {
                                let seen = fd_gauge.as_ref().map(|g| g.seen()).unwrap_or_default();
                                Descriptors {
                                    limit: fd_limit,
                                    most_open: seen.most_counted,
                                    counts: seen.counts,
                                    at_limit: seen.at_limit,
                                    idle_ports_closed: shell.endpoint.evictions(),
                                }
                            },
                        });
                    }
                }
                TOKEN_HUP => {
                    if hangup.drain() {
                        if let Some(d) = shell.udp.as_mut() {
                            d.reload(&mut shell.handling, &mut core, &mut shell.fed, now);
                        }
                    }
                }
                TOKEN_UDP => {
                    at(Phase::Udp);
                    if let Some(d) = shell.udp.as_mut() {
                        d.on_readable(&mut shell.handling, &mut core, &mut shell.fed, now);
                    }
                }
                TOKEN_EVENTS => {
                    if let Some(w) = shell.events.as_ref() {
                        w.on_bell();
                    }
                }
                TOKEN_FED => {
                    at(Phase::Federation);
                    if let Some(f) = shell.fed.as_mut() {
                        f.on_wake(&mut core, &shell.reactor, now);
                    }
                }
                t if t >= crate::federation::FIRST_PROXY_TOKEN => {
                    if let Some(f) = shell.fed.as_mut() {
                        f.on_proxy(t, &core, &shell.reactor);
                    }
                }
                t => {
                    at(Phase::Timers);
                    if shell.watches.get(&t).is_some_and(|w| w.pidfd.exited()) {
                        for who in shell.unwatch(t) {
                            died_in(&mut core, shell.fed.as_mut(), now, &who);
                            died.push(who);
                        }
                    }
                }
            }
        }
        // The inbox, when its bell rang (every frame a peer writes rings it): a read of
        // the inbox asks each of its writers, hundreds of them at 900 users, so the
        // other wakes (datagrams, timers, the deferred writes) skip it. The first frame
        // is answered before anything else: before the rest are read (the read that
        // finds the inbox empty costs as much as one that finds a frame) and before the
        // bell is drained (a read of its socket until it is empty, 7-9 µs p50 at 10
        // users). The whole inbox is read after the drain, so a ring drained here misses
        // no frame: each was written before its ring.
        at(Phase::Inbox);
        if std::mem::take(&mut inbox_rang) {
            if shell.drain_inbox(&mut core, now, Some(1))? {
                shell.flush(&mut core, host_now())?;
            }
            if shell.endpoint.drain_bell() & (1 << bell::STANDBY) != 0 {
                core.keep_journal();
                shell.replica.image_owed = true;
            }
            shell.drain_inbox(&mut core, now, None)?;
        }
        at(Phase::Timers);
        if let Some(f) = shell.fed.as_mut() {
            f.set_standby(shell.replica.writer.standbys() > 0);
            f.sweep(&mut core, &shell.reactor, now);
        }
        if let Some(d) = shell.udp.as_mut() {
            d.housekeeping(&mut shell.handling, &mut core, &mut shell.fed, now);
        }
        if core.poll_timeout().is_some_and(|t| t <= now) {
            core.handle_timeout(now);
        }
        if remote_return
            .as_ref()
            .is_some_and(|(t, _)| Instant::now() >= *t)
        {
            let users = remote_return.take().map(|(_, u)| u).unwrap_or_default();
            let mut gone = 0;
            for u in users {
                if shell.udp.as_ref().is_none_or(|d| !d.front.is_remote(&u)) {
                    core.user_died(now, &u);
                    gone += 1;
                }
            }
            if gone > 0 {
                tracing::info!(
                    gone,
                    "remote users of the old primary did not come back: forgotten"
                );
            }
        }
        at(Phase::Flush);
        shell.flush(&mut core, host_now())?;
        if takeover_ring.is_some_and(|t| Instant::now() >= t) {
            takeover_ring = None;
            presence.ring(bell::TAKEOVER);
        }
        shell.ring_watchers(&core);
        at(Phase::Replication);
        shell.replica.heartbeat();
        at(Phase::Cleanup);
        if !died.is_empty() {
            // Nobody will read a dead peer's inbox: drop our ports to it now, then remove
            // the dead process's iceoryx2 resources (its node shows as dead at once) in
            // a cleanup process.
            for addr in &died {
                shell.endpoint.forget(addr);
            }
            cleanups.request();
        } else {
            cleanups.poll();
        }
    }
}

/// Outputs waiting for their peers' ports to open, in order, with how many each peer has
/// waiting: a later output for a peer with one waiting waits behind it.
#[derive(Default)]
struct PeerQueue {
    outputs: VecDeque<(Address, Output)>,
    waiting: HashMap<Address, usize>,
}

impl PeerQueue {
    /// Whether an output for `peer` waits.
    fn holds(&self, peer: &Address) -> bool {
        self.waiting.contains_key(peer)
    }

    fn push(&mut self, peer: Address, out: Output) {
        *self.waiting.entry(peer.clone()).or_default() += 1;
        self.outputs.push_back((peer, out));
    }

    /// The oldest output.
    fn pop(&mut self) -> Option<Output> {
        let (peer, out) = self.outputs.pop_front()?;
        if let Some(n) = self.waiting.get_mut(&peer) {
            *n -= 1;
            if *n == 0 {
                self.waiting.remove(&peer);
            }
        }
        Some(out)
    }

    fn is_empty(&self) -> bool {
        self.outputs.is_empty()
    }
}

/// Whether `out` is the grant that offer `offer` goes with.
fn grant_of(offer: &Output, out: &Output) -> bool {
    matches!(
        (offer, out),
        (Output::ToSystem(_, ToSystem::Offer { user, req, .. }), Output::Granted(g))
            if g.user == *user && g.req == *req
    )
}

/// The peer an output is for (sent to, watched or forgotten), if any: its outputs keep
/// their order.
fn output_peer(out: &Output) -> Option<Address> {
    match out {
        Output::Granted(g) if !g.user.is_foreign() => Some(Address::User(g.user.clone())),
        Output::Granted(_) => None,
        Output::ToSystem(name, _) => Some(Address::System(name.clone())),
        Output::ToUser(user, _) => Some(Address::User(user.clone())),
        Output::WatchSystem { system, .. } | Output::ForgetSystem(system) => {
            Some(Address::System(system.clone()))
        }
        Output::WatchUser { user, .. } | Output::ForgetUser(user) => {
            Some(Address::User(user.clone()))
        }
    }
}

/// Whether sending the output writes to its peer (opening the ports if need be).
fn opens_ports(out: &Output) -> bool {
    matches!(
        out,
        Output::Granted(_) | Output::ToSystem(..) | Output::ToUser(..)
    )
}

fn fenced(fence: &Fence) -> BrokerError {
    let h = fence.holder();
    tracing::error!(
        by_pid = h.pid,
        term = h.term,
        "this broker was taken over while stopped or hung: stopping without acting"
    );
    BrokerError::Fenced {
        pid: h.pid,
        term: h.term,
    }
}

impl Shell {
    /// Reads and handles the inbox's frames, at most `limit` of them; whether it stopped
    /// at the limit (more may wait).
    fn drain_inbox(
        &mut self,
        core: &mut Broker,
        now: Duration,
        limit: Option<usize>,
    ) -> Result<bool, BrokerError> {
        let mut read = 0;
        while let Some((frame, pid)) = self.endpoint.recv_from() {
            read += 1;
            match decode::<ToBroker>(&frame) {
                Ok(ToBroker::Operate { user, id, .. })
                    if !pid.is_some_and(instance_owner) || user.is_foreign() =>
                {
                    let m = ToUser::Operated {
                        id,
                        result: Err(LOCAL_OPERATORS.into()),
                    };
                    self.endpoint.send_control(&Address::User(user), &m);
                }
                // A latched value: the shell's to keep, never the core's. Mostly
                // written unrung, it is not what the broker was woken to answer: it
                // does not count as the frame answered first.
                Ok(msg @ ToBroker::Latest { .. }) => {
                    read -= 1;
                    if core.sender_allowed(pid, &msg) {
                        self.latched.keep(core, pid, msg);
                    }
                }
                Ok(msg) if core.sender_allowed(pid, &msg) => {
                    if let ToBroker::Request { user, req, .. } = &msg {
                        muster_shared::trace::stamp(Stage::BrokerRecv, user, *req);
                    }
                    let passed_on = self
                        .fed
                        .as_mut()
                        .is_some_and(|f| f.intercept(&msg, |_, _| None));
                    if !passed_on {
                        timed_handle(&mut self.handling, core, now, msg)
                    }
                }
                Ok(_) => {}
                Err(e) => muster_shared::protocol::log_bad_frame(&e),
            }
            if limit.is_some_and(|l| read >= l) {
                return Ok(true);
            }
        }
        Ok(false)
    }

    fn flush(&mut self, core: &mut Broker, now: Duration) -> Result<(), BrokerError> {
        loop {
            let mut dead = Vec::new();
            // Write-ahead: the standbys hear of each input before any peer hears of
            // what it caused.
            self.replica.publish(core);
            self.flush_outputs(core, &mut dead)?;
            self.replica.publish(core);
            if dead.is_empty() {
                // The pass's frames for other hosts, a batch each.
                if let Some(f) = self.fed.as_mut() {
                    f.send_pending();
                }
                return Ok(());
            }
            // A process that registered or said hello but is already gone.
            for who in dead {
                died_in(core, self.fed.as_mut(), now, &who);
            }
        }
    }

    /// Sends one output of the core's (routed past the UDP front and the federation).
    fn send_output(&mut self, out: Output, dead: &mut Vec<Address>) {
        match out {
            // A local user hears of its grant from the broker, over a port open
            // since its hello, right after its system was sent the offer. (Remote
            // users' grants went to the UDP front; a user of another host hears
            // through its own host's broker.)
            Output::Granted(g) => {
                if g.user.is_foreign() {
                    return;
                }
                muster_shared::trace::stamp(Stage::BrokerRelay, &g.user, g.req);
                let to = Address::User(g.user.clone());
                match self.latched.update_zero(&g) {
                    // A latched service's newest value goes with the grant, as the
                    // session's update 0: both written, then one bell, so that the user
                    // woken reads them together.
                    Some(zero) => {
                        self.endpoint.send_control_quiet(&to, &g.message());
                        self.endpoint.send_control_quiet(&to, &zero);
                        self.endpoint.ring_now(&to);
                    }
                    None => self.endpoint.send_control(&to, &g.message()),
                }
            }
            // An offer is written at once and its bell rung a moment after the grant
            // that follows it: the user's wake-up does not wait behind the system's
            // (which, woken first on a busy core, would run before the broker sent
            // the grant), and a user that heard of its grant finds the offer in the
            // system's inbox before its own first frame.
            Output::ToSystem(name, msg @ ToSystem::Offer { .. }) => {
                if let ToSystem::Offer { user, req, .. } = &msg {
                    muster_shared::trace::stamp(Stage::BrokerSend, user, *req);
                }
                self.endpoint
                    .send_control_quiet(&Address::System(name), &msg)
            }
            Output::ToSystem(name, msg) => self.endpoint.send_control(&Address::System(name), &msg),
            Output::ToUser(user, msg) => self.endpoint.send_control(&Address::User(user), &msg),
            Output::WatchSystem { system, pid } => self.watch(Address::System(system), pid, dead),
            Output::WatchUser { user, pid } => self.watch(Address::User(user), pid, dead),
            Output::ForgetSystem(system) => self.forget(Address::System(system)),
            Output::ForgetUser(user) => self.forget(Address::User(user)),
        }
    }

    /// Sends an output the UDP front did not take: through the federation, or to a
    /// local peer (held while its ports wait to open).
    fn pass_on(&mut self, core: &mut Broker, out: Output, dead: &mut Vec<Address>) {
        let out = match self.fed.as_mut() {
            Some(f) => {
                // A grant of a latched service to a user of another host: its update
                // 0 follows the grant to that host.
                let zero = match &out {
                    Output::Granted(g) if g.user.is_foreign() => self
                        .latched
                        .update_zero(g)
                        .map(|z| (g.user.clone(), g.session, z)),
                    _ => None,
                };
                match f.route(core, out) {
                    Some(o) => o,
                    None => {
                        if let Some((user, session, z)) = zero {
                            f.follow_grant(&user, session, z);
                        }
                        return;
                    }
                }
            }
            None => out,
        };
        // Behind what waits for its peer, or waiting itself for ports to open.
        match output_peer(&out) {
            Some(p)
                if self.unopened.holds(&p)
                    || (opens_ports(&out) && !self.endpoint.has_ports(&p)) =>
            {
                self.unopened.push(p, out)
            }
            _ => self.send_output(out, dead),
        }
    }

    fn flush_outputs(
        &mut self,
        core: &mut Broker,
        dead: &mut Vec<Address>,
    ) -> Result<(), BrokerError> {
        // A few frames (a grant and its offer, a refusal) go before the list, which a
        // change rewrites in part and which nobody on their path waits for; a storm of
        // them after it: a broker restarting under load has hundreds of welcomes to
        // send (each opening a port), and the list must not wait behind them.
        let list_first = core.outputs_waiting() > LIST_AFTER_AT_MOST;
        if list_first {
            self.write_list(core);
        }
        self.deliver_federation(core);
        // A remote user's offer, held until its grant's datagrams are sent: the grant is
        // on the user's path, the offer is not (writing it takes 10-20 µs), and the
        // system keeps a user datagram that comes before its offer
        // (`muster_systems::remote`). Anything else that comes between goes after it.
        let mut offer_after: Option<Output> = None;
        while let Some(mut out) = core.poll_output() {
            if let Some(o) = offer_after.take() {
                if grant_of(&o, &out) {
                    offer_after = Some(o);
                } else {
                    self.pass_on(core, o, dead);
                }
            }
            // An operator's status gets the shell's own figures.
            if let Output::ToUser(
                _,
                ToUser::Operated {
                    result: Ok(Some(status)),
                    ..
                },
            ) = &mut out
            {
                status.handling = self.handling.figures();
                fit_status(status);
            }
            let routed = match self.udp.as_mut() {
                Some(d) => {
                    // A remote user's grant of a latched service: its update 0 follows
                    // the grant's datagram through the front.
                    let zero = match &out {
                        Output::Granted(g) if d.front.is_remote(&g.user) => self
                            .latched
                            .update_zero(g)
                            .map(|z| Output::ToUser(g.user.clone(), z)),
                        _ => None,
                    };
                    let routed = d.front.route(core, out);
                    if routed.is_none() {
                        if let Some(z) = zero {
                            let _ = d.front.route(core, z);
                        }
                        d.transmit();
                    }
                    routed
                }
                None => Some(out),
            };
            match routed {
                // Given the remote user's contact by the front.
                Some(
                    o @ Output::ToSystem(
                        _,
                        ToSystem::Offer {
                            remote: Some(_), ..
                        },
                    ),
                ) => offer_after = Some(o),
                Some(o) => self.pass_on(core, o, dead),
                // Sent by the front: the offer held for it (if this was its grant) now.
                None => {
                    if let Some(o) = offer_after.take() {
                        self.pass_on(core, o, dead);
                    }
                }
            }
        }
        if let Some(o) = offer_after.take() {
            self.pass_on(core, o, dead);
        }
        // Peers met for the first time, within the budget; the rest on the next pass.
        let opening = Instant::now();
        while opening.elapsed() < OPEN_BUDGET {
            let Some(out) = self.unopened.pop() else {
                break;
            };
            self.send_output(out, dead);
        }
        if !self.unopened.is_empty() {
            let now = Instant::now();
            self.deferred_at = Some(self.deferred_at.map_or(now, |t| t.min(now)));
        }
        // The systems sent offers are woken a moment later: their part is off the
        // user's path, and on a busy core their wake-up would go before the user's.
        // The list, if it did not go first; and anything routing the outputs changed.
        // A change of this host's own list alone (a grant, an end: the counts in use)
        // is written a moment later too: the broker's rewrite of its rows would keep
        // from its core the user just woken there. Its watchers are rung at most every
        // 100 ms anyway.
        // The event feed too, when the flush was a few frames: its records (serialized,
        // published, their readers rung) would otherwise hold the core tens of µs
        // after the grant, with the user queued behind the broker there.
        let defer_list = !list_first && self.fed.is_none() && core.list_changed();
        if !defer_list {
            self.write_list(core);
        }
        let defer_events = !list_first && core.events_waiting();
        if !defer_events {
            self.publish_events(core);
        }
        if defer_list || defer_events || self.endpoint.bells_pending() {
            self.deferred_at
                .get_or_insert_with(|| Instant::now() + AFTER_WAKING);
        }
        Ok(())
    }

    /// Frames the federation has for local users: through shared memory, or through
    /// the UDP front to a remote user.
    fn deliver_federation(&mut self, core: &Broker) {
        let Some(f) = self.fed.as_mut() else {
            return;
        };
        while let Some(d) = f.poll_delivery() {
            let front = self.udp.as_mut().filter(|u| match &d {
                Delivery::Msg(user, _) | Delivery::Grant(FarGrant { user, .. }) => {
                    u.front.is_remote(user)
                }
            });
            match (d, front) {
                (Delivery::Msg(user, msg), None) => {
                    self.endpoint.send_control(&Address::User(user), &msg)
                }
                (Delivery::Msg(user, msg), Some(u)) => {
                    // The front takes every frame for its users.
                    let _ = u.front.route(core, Output::ToUser(user, msg));
                    u.transmit();
                }
                (Delivery::Grant(g), front) => {
                    let given = match front {
                        Some(u) => {
                            let given = u.front.granted(g);
                            u.transmit();
                            given
                        }
                        None => Err(g),
                    };
                    if let Err(g) = given {
                        // The system ends the session when its lease runs out unheard.
                        tracing::debug!(user = %g.user, req = g.req, "a grant on another host found its remote user gone");
                    }
                }
            }
        }
    }

    /// Puts what the core did on the event feed, and wakes its readers.
    fn publish_events(&mut self, core: &mut Broker) {
        let Some(w) = self.events.as_mut() else {
            while core.poll_event().is_some() {}
            return;
        };
        let mut any = false;
        while let Some(e) = core.poll_event() {
            match w.publish(e) {
                // Remote operators get it too.
                Ok(Some(json)) => {
                    if let Some(u) = self.udp.as_mut() {
                        u.front.feed(&json);
                    }
                }
                Ok(None) => {}
                Err(e) => tracing::debug!("event feed: {e}"),
            }
            any = true;
        }
        if any {
            if let Some(u) = self.udp.as_mut() {
                u.transmit();
            }
            w.ring();
        }
    }

    /// Writes the list if it changed.
    fn write_list(&mut self, core: &mut Broker) {
        // The core's rows, updated in place: alone, they are the list; in a federation,
        // other hosts' users' links are added to them first.
        // Alone, only the rows whose counts changed are taken when no service came or
        // went (`rows`); in a federation, every row.
        let (local, rows) = match self.fed {
            None => match core.take_list_change_rows(&mut self.local_views, &mut self.list_shape) {
                Some((g, rows)) => (Some(g), rows),
                None => (None, None),
            },
            Some(_) => (core.take_list_change_into(&mut self.core_views), None),
        };
        let (far, links) = self.fed.as_mut().map_or((false, false), |f| {
            (f.take_list_change(), f.take_links_change())
        });
        if local.is_none() && !far && !links {
            return;
        }
        // Other hosts' lists change the merged one on their own: it takes a generation
        // past both the core's and the last written.
        let mut generation = self.snapshot.generation + 1;
        if let Some(g) = local {
            generation = generation.max(g);
        }
        match self.fed.as_mut() {
            None => {}
            Some(f) if local.is_some() || links => {
                // Other hosts' users' links over this host's services count here too.
                let systems: Vec<&str> = core.systems().collect();
                self.local_views = f.publish_list(&self.core_views, &systems);
            }
            Some(_) => {}
        }
        self.snapshot.generation = generation;
        // One list in id order: this host's services and the other hosts', shared
        // fairly among them when there are more than the list holds.
        let (all, host) = match self.fed.as_ref() {
            Some(f) => (
                f.merged_views(&self.local_views, core.config().max_services),
                Some(muster_shared::snapshot::FixedStr::new(f.host())),
            ),
            None => (self.local_views.iter().collect(), None),
        };
        let rows = rows.filter(|_| self.snapshot.entries().len() == all.len());
        match &rows {
            Some(rows) => {
                let slots = self.snapshot.resize(all.len());
                for &i in rows {
                    let e = all[i].to_entry();
                    self.rings.changed(&slots[i], &e);
                    slots[i] = e;
                }
            }
            None => {
                if self.snapshot.entries().len() != all.len() {
                    // Services came or went: rows moved, so every watcher is rung.
                    self.rings.everything_changed();
                }
                for (slot, v) in self.snapshot.resize(all.len()).iter_mut().zip(&all) {
                    let mut e = v.to_entry();
                    if let Some(h) = host.filter(|_| !v.remote) {
                        e.host = h;
                    }
                    if *slot != e {
                        self.rings.changed(slot, &e);
                        *slot = e;
                    }
                }
            }
        }
        let t = Instant::now();
        match self.list.publish_rows(
            self.endpoint.node(),
            &self.snapshot,
            &self.fence,
            rows.as_deref(),
        ) {
            Ok(()) => self.handling.record("list_write", t, t.elapsed()),
            // Never fatal: readers keep the last list; the next change writes again.
            Err(e) => tracing::warn!("the service list could not be written: {e}"),
        }
        if let Some(d) = self.udp.as_mut() {
            // Remote users see the same list (merged once, above).
            match host {
                Some(_) => {
                    let all: Vec<muster_shared::snapshot::ServiceView> =
                        all.into_iter().cloned().collect();
                    d.front.list_changed(self.snapshot.epoch, generation, &all);
                }
                None => d.front.list_changed_rows(
                    self.snapshot.epoch,
                    generation,
                    &self.local_views,
                    rows.as_deref(),
                ),
            }
        }
        self.ring_owed = true;
    }

    /// How long until watchers may be rung again, if a ring is owed.
    fn ring_due(&self) -> Option<Duration> {
        if !self.ring_owed {
            return None;
        }
        Some(
            self.last_ring
                .map_or(Duration::ZERO, |t| RING_EVERY.saturating_sub(t.elapsed())),
        )
    }

    /// Rings the users who watch the list, at most once per [`RING_EVERY`].
    fn ring_watchers(&mut self, core: &Broker) {
        if self.ring_due() != Some(Duration::ZERO) {
            return;
        }
        self.ring_owed = false;
        self.last_ring = Some(Instant::now());
        let mut watchers: Vec<UserId> = self.rings.take_from(core);
        if let Some(d) = self.udp.as_mut() {
            let (remote, local): (Vec<UserId>, Vec<UserId>) =
                watchers.into_iter().partition(|u| d.front.is_remote(u));
            d.front.ring(&remote);
            d.transmit();
            watchers = local;
        }
        for u in watchers {
            let _ = self.endpoint.ring(&Address::User(u), bell::LIST_CHANGED);
        }
    }

    /// Watches `who`'s process (replacing an older watch); a process already gone is
    /// reported in `dead` instead.
    fn watch(&mut self, who: Address, pid: u32, dead: &mut Vec<Address>) {
        self.stop_watching(&who);
        if !process_exists(pid) {
            dead.push(who);
            return;
        }
        if let Some(&token) = self.by_pid.get(&pid) {
            match self.watches.get_mut(&token) {
                // The process whose pid this was died, its death not yet read: a new
                // one has the pid now.
                Some(w) if w.pidfd.exited() => dead.extend(self.unwatch(token)),
                Some(w) => {
                    w.who.insert(who.clone());
                    self.by_addr.insert(who, token);
                    return;
                }
                None => {}
            }
        }
        let pidfd = match PidFd::open(pid) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!("cannot watch pid {pid}: {e}; relying on pings");
                return;
            }
        };
        let token = self.next_token;
        self.next_token += 1;
        if let Err(e) = self.reactor.add(pidfd.raw(), token) {
            tracing::warn!("cannot watch pid {pid}: {e}; relying on pings");
            return;
        }
        self.by_addr.insert(who.clone(), token);
        self.by_pid.insert(pid, token);
        self.watches.insert(
            token,
            Watch {
                pid,
                who: HashSet::from([who]),
                pidfd,
            },
        );
    }

    /// Stops watching `who`; its ports linger (a Delinquent notice may just have been sent).
    fn forget(&mut self, who: Address) {
        self.stop_watching(&who);
        self.endpoint.release(&who);
    }

    /// Stops watching for `who`'s death; its process's pidfd closes with the last of
    /// those it hosts.
    fn stop_watching(&mut self, who: &Address) {
        let Some(token) = self.by_addr.remove(who) else {
            return;
        };
        let last = self.watches.get_mut(&token).is_none_or(|w| {
            w.who.remove(who);
            w.who.is_empty()
        });
        if last {
            self.unwatch(token);
        }
    }

    /// Stops watching a process; returns who spoke from it.
    fn unwatch(&mut self, token: usize) -> Vec<Address> {
        let Some(w) = self.watches.remove(&token) else {
            return Vec::new();
        };
        self.reactor.remove(w.pidfd.raw());
        if self.by_pid.get(&w.pid) == Some(&token) {
            self.by_pid.remove(&w.pid);
        }
        let mut who: Vec<Address> = w.who.into_iter().collect();
        who.retain(|a| self.by_addr.get(a) == Some(&token));
        for a in &who {
            self.by_addr.remove(a);
        }
        who.sort();
        who
    }
}

/// Why a local user's operator action is refused.
const LOCAL_OPERATORS: &str =
    "operators only: the broker takes operators' actions from processes of the instance's owner (the user the broker runs as)";

/// Whether process `pid` runs as the user this broker runs as (the instance's owner,
/// whose processes are its operators).
fn instance_owner(pid: u32) -> bool {
    let Ok(status) = std::fs::read_to_string(format!("/proc/{pid}/status")) else {
        return false;
    };
    // `Uid:` real, effective, saved, filesystem.
    let euid = status
        .lines()
        .find_map(|l| l.strip_prefix("Uid:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|u| u.parse::<u32>().ok());
    // SAFETY: geteuid has no preconditions.
    euid == Some(unsafe { libc::geteuid() })
}

/// Tells the core (and the other hosts of a federation) that the process at `who` died.
fn died_in(core: &mut Broker, fed: Option<&mut Federation>, now: Duration, who: &Address) {
    match who {
        Address::System(s) => {
            if let Some(f) = fed {
                f.local_system_gone(s);
            }
            core.system_died(now, s)
        }
        Address::User(u) => {
            if let Some(f) = fed {
                f.local_user_gone(u);
            }
            core.user_died(now, u)
        }
        Address::Broker | Address::Relay(_) | Address::Process(_) => {}
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use muster_shared::protocol::{encode, BrokerStatus, LinkInfo, UserStatus, MAX_FRAME};
    use muster_shared::types::{ServiceId, UserId};

    #[test]
    fn outputs_waiting_for_ports_leave_in_order_and_hold_back_their_peers_later_ones() {
        let user = |n: &str| Address::User(UserId(n.into()));
        let forget = |n: &str| Output::ForgetUser(UserId(n.into()));
        let mut q = PeerQueue::default();
        assert!(q.is_empty() && q.pop().is_none());
        q.push(user("a"), forget("a1"));
        q.push(user("b"), forget("b1"));
        q.push(user("a"), forget("a2"));
        assert!(q.holds(&user("a")) && q.holds(&user("b")) && !q.holds(&user("c")));
        assert_eq!(q.pop(), Some(forget("a1")));
        assert!(q.holds(&user("a")), "a's second output still waits");
        assert_eq!(q.pop(), Some(forget("b1")));
        assert!(!q.holds(&user("b")));
        assert_eq!(q.pop(), Some(forget("a2")));
        assert!(!q.holds(&user("a")) && q.is_empty() && q.pop().is_none());
    }

    #[test]
    fn an_operators_status_is_cut_to_fit_one_frame() {
        let link = |i: usize| LinkInfo {
            link: i as u64,
            data: ServiceId(format!("tracking-system-{i}/red")),
            command: ServiceId(format!("delivery-system-{i}/goal")),
        };
        let mut status = BrokerStatus {
            users: (0..200)
                .map(|i| UserStatus {
                    user: UserId(format!("u{i}-0123456789abcdef")),
                    pid: 1000 + i,
                    links: (0..8).map(|k| link(k + i as usize)).collect(),
                })
                .collect(),
            users_total: 900,
            ..BrokerStatus::default()
        };
        let mut h = Handling::new(false);
        h.record("hello", Instant::now(), Duration::from_micros(12));
        h.record("hello", Instant::now(), Duration::from_micros(40));
        status.handling = h.figures();
        assert!(encode(&status).is_err(), "the test's status must not fit");
        fit_status(&mut status);
        let frame = encode(&status).unwrap();
        assert!(frame.len() <= MAX_FRAME - 64, "{}", frame.len());
        assert_eq!(status.users.len(), 100, "halved once");
        assert_eq!(status.users_total, 900, "the total still counts all");
        assert_eq!(status.handling[0].kind, "hello");
        assert_eq!(status.handling[0].count, 2);
        assert_eq!(status.handling[0].max_us, 40);
    }

    #[test]
    fn open_peers_take_what_descriptors_the_users_leave_and_give_back_when_they_eat_the_reserve() {
        // 5,000 idle local users (3 each) and a hundred more descriptors, at 20,000:
        // about 390 peers may keep their ports.
        assert_eq!(max_open_peers(20_000, 15_100, 0), 387);
        assert_eq!(max_open_peers(20_000, 15_100 + 10 * 300, 300), 387);
        // Connecting users ate into the reserve: fewer than are open, so idle ones close.
        assert_eq!(max_open_peers(1_500, 1_450, 100), 87);
        // Never fewer than the floor, and the whole limit free is a lot of peers.
        assert_eq!(max_open_peers(1_500, 5_000, 100), MIN_OPEN_PEERS as usize);
        assert_eq!(
            max_open_peers(1 << 20, 100, 0),
            ((1 << 20) - 1_024 - 100) / 10
        );
        // How many local users a limit takes, at 3 each past the reserve and the floor.
        assert_eq!(max_local_users(20_000), (20_000 - 1_024 - 160) / 3);
    }
}
