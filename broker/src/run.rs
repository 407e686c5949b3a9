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
    bell, create_node, BellRinger, Endpoint, EventWriter, ListWriter, Presence, ReplicaReader,
    ReplicaWriter, TransportError,
};
use muster_shared::names::{Address, Instance};
use muster_shared::protocol::{decode, ToBroker, ToSystem, ToUser};
use muster_shared::reactor::{
    process_alive, process_exists, raise_fd_limit, PidFd, Reactor, SignalPipe,
};
use muster_shared::snapshot::{ServiceListSnapshot, MAX_LISTED_SERVICES};
use muster_shared::trace::Stage;
use muster_shared::types::UserId;
use muster_shared::udp::access::AccessFile;
use muster_shared::udp::wire::MAX_DATAGRAM;
use muster_shared::udp::{recv_one, send_transmit, size_recv_buffer, RECV_BATCH};
use rand::RngExt;
use std::collections::HashMap;
use std::net::UdpSocket;
use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

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
struct Watch {
    who: Address,
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
                           "federation": self.federation})
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
    next_token: usize,
    snapshot: Box<ServiceListSnapshot>,
    handling: Handling,
    /// When list watchers were last rung, and whether a ring is owed.
    last_ring: Option<Instant>,
    ring_owed: bool,
    /// When what waits for the peers just woken is done ([`AFTER_WAKING`]): the bells
    /// of systems sent offers, and a change of this host's list's counts.
    deferred_at: Option<Instant>,
    udp: Option<UdpDriver>,
    replica: Replication,
    /// This host's membership in a federation, if it joined one.
    fed: Option<Federation>,
    /// The event feed, if it could be opened.
    events: Option<EventWriter>,
    /// This host's services as listed: the core's list as last taken, with (in a
    /// federation) other hosts' users' links counted (other hosts' lists change the
    /// merged one on their own).
    local_views: Vec<muster_shared::snapshot::ServiceView>,
    /// In a federation, the core's list as last taken (`local_views` adds other hosts'
    /// users' links to it).
    core_views: Vec<muster_shared::snapshot::ServiceView>,
}

/// The UDP front's socket and access file around the sans-IO [`UdpFront`].
struct UdpDriver {
    sock: UdpSocket,
    front: UdpFront,
    access_path: Option<PathBuf>,
}

impl UdpDriver {
    fn bind(cfg: UdpConfig, epoch: u64) -> Result<Self, UdpError> {
        let access = match &cfg.access_path {
            Some(p) => AccessFile::load(p).map_err(UdpError::Access)?,
            None => AccessFile::default(),
        };
        let sock = UdpSocket::bind(cfg.bind).map_err(|e| UdpError::Bind(cfg.bind, e))?;
        sock.set_nonblocking(true)
            .map_err(|e| UdpError::Bind(cfg.bind, e))?;
        match size_recv_buffer(&sock) {
            Ok(n) if n < muster_shared::udp::RECV_BUFFER => tracing::info!(
                "udp receive buffer {n} bytes (asked {}): raise net.core.rmem_max for bursts of handshakes",
                muster_shared::udp::RECV_BUFFER
            ),
            Ok(_) => {}
            Err(e) => tracing::warn!("cannot size the udp receive buffer: {e}"),
        }
        let local = sock.local_addr().map_err(|e| UdpError::Bind(cfg.bind, e))?;
        let seed: [u8; 32] = rand::rng().random();
        let front = UdpFront::new(
            cfg.key,
            access,
            cfg.limits,
            local,
            epoch,
            Instant::now(),
            seed,
        );
        Ok(UdpDriver {
            sock,
            front,
            access_path: cfg.access_path,
        })
    }

    /// Reads every waiting datagram (at most a few thousand a call, so one flood cannot
    /// starve the shared-memory side), handing the front's messages to the core.
    fn on_readable(&mut self, handling: &mut Handling, core: &mut Broker, fed: Fed, now: Duration) {
        let mut buf = [0u8; MAX_DATAGRAM + 1];
        for _ in 0..RECV_BATCH {
            let Some((n, from)) = recv_one(&self.sock, &mut buf) else {
                break;
            };
            self.front.handle(Instant::now(), from, &buf[..n], core);
            self.events(handling, core, fed, now);
        }
        self.transmit();
    }

    /// Re-reads the access file (SIGHUP); a bad file keeps the old one.
    fn reload(&mut self, handling: &mut Handling, core: &mut Broker, fed: Fed, now: Duration) {
        let Some(path) = &self.access_path else {
            return;
        };
        match AccessFile::load(path) {
            Ok(a) => self.front.reload(Instant::now(), a),
            Err(e) => tracing::error!("{e}; keeping the previous access file"),
        }
        self.events(handling, core, fed, now);
        self.transmit();
    }

    fn housekeeping(
        &mut self,
        handling: &mut Handling,
        core: &mut Broker,
        fed: Fed,
        now: Duration,
    ) {
        self.front.handle_timeout(Instant::now());
        self.events(handling, core, fed, now);
        self.transmit();
    }

    /// The front's messages for the core; a federation takes requests for other
    /// hosts' services first, and hears of remote users gone.
    fn events(&mut self, handling: &mut Handling, core: &mut Broker, fed: Fed, now: Duration) {
        while let Some(ev) = self.front.poll_event() {
            match ev {
                FrontEvent::ToCore(msg) => {
                    let front = &mut self.front;
                    let passed_on = fed.as_mut().is_some_and(|f| {
                        f.intercept(&msg, |user, req| front.remote_contact(user, req))
                    });
                    if !passed_on {
                        timed_handle(handling, core, now, msg)
                    }
                }
                FrontEvent::UserGone(u) => {
                    if let Some(f) = fed.as_mut() {
                        f.local_user_gone(&u);
                    }
                    core.user_died(now, &u)
                }
                FrontEvent::Revoked(u) => {
                    if let Some(f) = fed.as_mut() {
                        f.local_user_gone(&u);
                    }
                    core.revoke(now, &u)
                }
            }
        }
    }

    fn transmit(&mut self) {
        while let Some(t) = self.front.poll_transmit() {
            send_transmit(&self.sock, &t, &mut self.front.stats_mut().drops);
        }
    }
}

/// The broker's federation membership, if any, as the UDP front's driver gets it.
type Fed<'a> = &'a mut Option<Federation>;

/// List watchers are rung at most this often; the blackboard itself is updated at once.
const RING_EVERY: Duration = Duration::from_millis(100);
/// How long after a flush the bells of systems sent offers ring and a change of the
/// list's counts in use is written: the user told of its grant runs first (a user's
/// first frame to the system rings it at once anyway). The reactor waits in whole
/// milliseconds.
const AFTER_WAKING: Duration = Duration::from_micros(500);
/// Up to this many outputs of one flush go out before the list is written; more, and
/// the list goes first.
const LIST_AFTER_AT_MOST: usize = 16;

/// Runs a broker on `inst` until SIGINT or SIGTERM; returns what it did.
pub fn run(inst: &Instance, cfg: BrokerConfig) -> Result<BrokerReport, BrokerError> {
    run_with(inst, cfg, None, None, false)
}

/// The program whose `cleanup` subcommand cleans up after dead processes (see
/// [`set_cleanup_program`]).
static CLEANUP_PROGRAM: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();

/// A deliberate fault, for tests and benches (`muster broker --fault`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// After this many passes, the primary's loop stops for good while its process
    /// lives on: a deadlock, as a standby sees it.
    HangAfter(u64),
}

static FAULT: std::sync::OnceLock<Fault> = std::sync::OnceLock::new();

/// Arms `fault` in this process's primary loop.
pub fn set_fault(fault: Fault) {
    let _ = FAULT.set(fault);
}

/// Names the program (the muster binary) whose `--instance I cleanup [--pid P] --after
/// D` a broker runs to clean up after dead processes. Without it (a broker embedded in
/// another program) cleanups run in a thread of the broker, which a kill can leave
/// half-done.
pub fn set_cleanup_program(exe: PathBuf) {
    let _ = CLEANUP_PROGRAM.set(exe);
}

/// Cleans up after dead processes (those of `pid` first, once it has exited, then all)
/// after `delay`, beside serving. In a process of its own where
/// [`set_cleanup_program`] named one: iceoryx2 never cleans a node whose cleaner died
/// mid-way, and a broker can be killed at any moment.
fn cleaner(inst: &Instance, pid: Option<u32>, delay: Duration) -> std::thread::JoinHandle<usize> {
    let mut cmd = CLEANUP_PROGRAM.get().map(|exe| {
        let mut c = std::process::Command::new(exe);
        c.args(["--instance", inst.as_str(), "cleanup", "--after"])
            .arg(format!("{}ms", delay.as_millis()))
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null());
        if let Some(pid) = pid {
            c.arg("--pid").arg(pid.to_string());
        }
        c
    });
    std::thread::spawn(move || {
        if let Some(child) = cmd.as_mut().and_then(|c| c.spawn().ok()) {
            let mut child = child;
            let _ = child.wait();
            return 0;
        }
        std::thread::sleep(delay);
        muster_shared::ipc::cleanup_after(pid)
    })
}

/// Cleanups after dead peers while serving: one `muster cleanup` at a time (never in
/// the broker's own process, which may be killed mid-way), and one more owed when
/// deaths come while it runs.
struct Cleanups {
    inst: Instance,
    running: Option<std::thread::JoinHandle<usize>>,
    owed: bool,
}

impl Cleanups {
    fn new(inst: &Instance, first: Option<std::thread::JoinHandle<usize>>) -> Self {
        Cleanups {
            inst: inst.clone(),
            running: first,
            owed: false,
        }
    }

    /// Someone died: clean up after it now, or after the cleanup under way.
    fn request(&mut self) {
        self.owed = true;
        self.poll();
    }

    /// Starts the owed cleanup once the one under way has ended.
    fn poll(&mut self) {
        if self.running.as_ref().is_some_and(|h| !h.is_finished()) || !self.owed {
            return;
        }
        self.owed = false;
        self.running = Some(cleaner(&self.inst, None, Duration::ZERO));
    }
}

impl Drop for Cleanups {
    /// A broker leaving lets its cleanups end, and does the one owed: nobody else
    /// would clean up after the peers that died last.
    fn drop(&mut self) {
        if let Some(h) = self.running.take() {
            let _ = h.join();
        }
        if self.owed {
            let _ = cleaner(&self.inst, None, Duration::ZERO).join();
        }
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

fn raise_fds() {
    match raise_fd_limit() {
        Ok(n) if n < 4096 => {
            tracing::warn!(
                "file-descriptor limit is {n}: at most about {} users",
                n / 4
            )
        }
        Ok(n) => tracing::debug!("file-descriptor limit {n}"),
        Err(e) => tracing::warn!("cannot raise the file-descriptor limit: {e}"),
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
    let node = create_node(&format!("muster-broker-{inst}"), false)?;
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

/// Runs a standby on `inst`: it follows the primary's state and takes over when the
/// primary dies (its pidfd), hangs (no record for `deadline`) or steps down; then it
/// serves as the primary until SIGINT or SIGTERM.
pub fn run_standby(
    inst: &Instance,
    cfg: BrokerConfig,
    udp: Option<UdpConfig>,
    fed: Option<FedConfig>,
    keep_log: bool,
    deadline: Duration,
) -> Result<BrokerReport, BrokerError> {
    raise_fds();
    let node = create_node(&format!("muster-standby-{inst}"), false)?;
    let fence = open_fence(inst)?;
    let Some(standby) = follow(inst, &node, &fence, deadline)? else {
        return Ok(BrokerReport {
            stats: crate::core::BrokerStats::default(),
            handling: Handling::new(false),
            udp: None,
            federation: None,
        });
    };
    let Followed {
        noticed_ns,
        follower,
        presence,
        signals,
        me,
        old,
        why,
    } = standby;
    let pid = std::process::id();
    let t0 = Instant::now();
    let old_pid = old.as_ref().map(PidFd::pid);
    if why == Why::SteppedDown {
        // It is on its way out: let it go.
        if let Some(old) = &old {
            let until = Instant::now() + Duration::from_secs(2);
            while !old.exited() && Instant::now() < until {
                std::thread::sleep(Duration::from_micros(200));
            }
        }
    }
    if let Some(old) = old.filter(|o| !o.exited()) {
        // A hung primary still holds its share of the broker's inbox and would write
        // its list when it woke: having taken its term, end it. Were it to wake first, the fence stops it before it acts. Its
        // exit (slow for a process with hundreds of mappings) is not waited for: the
        // inbox takes more than one reader, and each run writes its own list.
        tracing::warn!(pid = old.pid(), "ending the hung primary");
        // SAFETY: kill(2) on a pid we hold a pidfd of (it cannot have been reused).
        unsafe { libc::kill(old.pid() as i32, libc::SIGKILL) };
        if udp.is_some() {
            // Its UDP socket is ours to bind only once it has exited.
            let until = Instant::now() + Duration::from_secs(5);
            while !old.exited() && Instant::now() < until {
                std::thread::sleep(Duration::from_micros(500));
            }
        }
    }
    let killed_us = t0.elapsed().as_micros() as u64;
    // The old primary's ports are cleaned up beside serving: the broker's inbox takes
    // more than one reader, and each run writes its own list.
    let cleanup = old_pid.map(|pid| cleaner(inst, Some(pid), CLEANUP_DELAY));
    let endpoint = Endpoint::open(inst, Address::Broker, node).map_err(|e| match e {
        TransportError::InUse(_) => BrokerError::AlreadyRunning(inst.to_string()),
        other => BrokerError::from(other),
    })?;
    let seq = follower.seq();
    let (core, how) = match follower.into_core() {
        Some(mut core) => {
            let epoch = new_epoch(core.epoch());
            core.take_over(host_now(), epoch, pid);
            (core, Start::Takeover)
        }
        None => (Broker::new(cfg, new_epoch(0), pid), Start::Cold),
    };
    tracing::warn!(
        ?why,
        term = me.term,
        state = if how == Start::Takeover {
            "replicated"
        } else {
            "none: starting cold"
        },
        killed_us,
        inbox_us = t0.elapsed().as_micros() as u64,
        "standby taking over"
    );
    event(serde_json::json!({
        "event": "took_over", "why": format!("{why:?}").to_lowercase(), "term": me.term,
        "replicated": how == Start::Takeover, "inbox_us": t0.elapsed().as_micros() as u64,
        "noticed_ns": noticed_ns,
    }));
    serve(
        inst,
        Primary {
            endpoint,
            fence,
            me,
            core,
            how,
            seq,
            standby_since: Some(t0),
            cleanup,
            presence: Some(presence),
            signals: Some(signals),
        },
        udp,
        fed,
        keep_log,
    )
}

/// Prints one standby event as a JSON line on stdout (for `muster up`, tests and the
/// failover bench).
fn event(v: serde_json::Value) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{v}");
    let _ = out.flush();
}

/// Why a standby took over.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Why {
    /// The primary's process ended (its pidfd).
    Died,
    /// No record from the primary within the deadline, and its loop made no progress
    /// while it could have run ([`crate::takeover::judge`]).
    Hung,
    /// No record within the deadline, and the primary is stopped (SIGSTOP).
    Stopped,
    /// The primary stepped down (stopped on purpose with a standby running).
    SteppedDown,
    /// There was no primary.
    NoPrimary,
}

struct Followed {
    /// When the takeover was decided (host monotonic clock, ns).
    noticed_ns: u64,
    follower: Follower,
    presence: Ringer,
    /// Its signal pipe, carried into serving.
    signals: SignalPipe,
    me: Holder,
    old: Option<PidFd>,
    why: Why,
}

/// Rings the presence event from a thread of its own: waking every process of the
/// instance takes long on a loaded host (each wakes up in turn), and the broker serves
/// meanwhile.
struct Ringer {
    tx: Option<std::sync::mpsc::Sender<usize>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Asks the ringer to connect to every listener, without ringing.
const PREPARE: usize = usize::MAX;

impl Ringer {
    fn spawn(inst: &Instance) -> Result<Self, BrokerError> {
        let (tx, rx) = std::sync::mpsc::channel::<usize>();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<(), TransportError>>();
        let inst = inst.clone();
        let thread = std::thread::spawn(move || {
            let made = create_node(&format!("muster-ringer-{inst}"), false)
                .and_then(|node| Presence::announce(&node, &inst).map(|p| (node, p)));
            let (_node, presence) = match made {
                Ok(v) => {
                    let _ = ready_tx.send(Ok(()));
                    v
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
            };
            while let Ok(id) = rx.recv() {
                if id == PREPARE {
                    presence.prepare();
                } else {
                    presence.ring(id);
                }
            }
        });
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(Ringer {
                tx: Some(tx),
                thread: Some(thread),
            }),
            Ok(Err(e)) => Err(e.into()),
            Err(_) => Err(BrokerError::Os(std::io::Error::other(
                "the presence thread died",
            ))),
        }
    }

    fn ring(&self, id: usize) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(id);
        }
    }

    fn prepare(&self) {
        self.ring(PREPARE);
    }

    /// Waits until every ring asked for has gone out.
    fn finish(mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// How often a standby connects its presence notifier to listeners that came since.
const PREPARE_EVERY: Duration = Duration::from_secs(1);

/// How long a standby without a copy of the state waits on a silent primary.
const UNSYNCED_PATIENCE: Duration = Duration::from_secs(2);

/// How often an unsynchronized standby asks the primary for its state.
const ASK_EVERY: Duration = Duration::from_millis(100);

const STANDBY_REPLICA: usize = 0;
const STANDBY_SIGNAL: usize = 1;
const STANDBY_PRIMARY: usize = 2;

/// Follows the primary until this standby has taken its term (`Some`) or was told to
/// stop (`None`).
fn follow(
    inst: &Instance,
    node: &iceoryx2::prelude::Node<muster_shared::ipc::Ipc>,
    fence: &Fence,
    deadline: Duration,
) -> Result<Option<Followed>, BrokerError> {
    let mut reader = ReplicaReader::open(node, inst)?;
    // Made now, connected to every listener from time to time: the takeover rings at once.
    let presence = Ringer::spawn(inst)?;
    let mut prepared: Option<Instant> = None;
    let mut asker = BellRinger::open(node, inst, &Address::Broker)?;
    let mut signals = SignalPipe::install()?;
    let mut reactor = Reactor::new()?;
    reactor.add(reader.fd(), STANDBY_REPLICA)?;
    reactor.add(signals.raw(), STANDBY_SIGNAL)?;
    let mut follower = Follower::new();
    let mut watched: Option<(Holder, Option<PidFd>)> = None;
    let mut heard = Instant::now();
    let mut asked: Option<Instant> = None;
    let mut logged_sync = false;
    // What the takeover judgment needs beside the silence (see `takeover`).
    let mut own_lateness = Duration::ZERO;
    let mut queued_at_heard: Option<Duration> = None;
    let mut queued_read: Option<Instant> = None;
    let mut starved_logged = false;
    tracing::info!(instance = %inst, deadline_ms = deadline.as_millis() as u64, "standby following");
    loop {
        // The primary of record: a new one (a cold start, or another standby's
        // takeover) starts a new copy.
        let holder = fence.holder();
        if watched.as_ref().is_none_or(|(h, _)| *h != holder) {
            if let Some((_, Some(p))) = watched.take() {
                reactor.remove(p.raw());
            }
            let pidfd = (holder.pid != 0)
                .then(|| PidFd::open(holder.pid).ok())
                .flatten();
            if let Some(p) = &pidfd {
                reactor.add(p.raw(), STANDBY_PRIMARY)?;
            }
            tracing::info!(pid = holder.pid, term = holder.term, "following primary");
            queued_at_heard = pidfd
                .as_ref()
                .and_then(|p| takeover::run_queue_wait(p.pid()));
            queued_read = Some(Instant::now());
            watched = Some((holder, pidfd));
            follower = Follower::new();
            heard = Instant::now();
            asked = None;
            logged_sync = false;
        }
        let (holder, pidfd) = watched.as_ref().expect("set above");
        let holder = *holder;
        let mut why = None;
        // A primary this standby holds no copy of yet gets longer to answer before it is
        // taken for hung: on a loaded host its first image may take a while, and a
        // takeover without the state would be a cold start anyway.
        let patience = if follower.synced() {
            deadline
        } else {
            deadline.max(UNSYNCED_PATIENCE)
        };
        match pidfd {
            None => why = Some(Why::NoPrimary).filter(|_| heard.elapsed() >= deadline),
            Some(p) if p.exited() => why = Some(Why::Died),
            Some(p)
                if heard.elapsed() >= patience
                    && !follower.synced()
                    && !muster_shared::reactor::process_stopped(p.pid()) =>
            {
                // Silence toward a standby that never had a record is no proof the
                // primary hangs (it may be this standby's stream that is not connected):
                // taking over a live primary would grant twice. Without the state, only
                // a primary seen stopped (or dead) is taken over; reconnect and ask again.
                tracing::warn!(
                    pid = p.pid(),
                    "no record from the running primary: reopening the replication stream"
                );
                reactor.remove(reader.fd());
                reader = ReplicaReader::open(node, inst)?;
                reactor.add(reader.fd(), STANDBY_REPLICA)?;
                heard = Instant::now();
                asked = None;
            }
            Some(p) if heard.elapsed() >= patience => {
                let beat = fence.last_beat();
                let now_ns = muster_shared::protocol::monotonic_ns();
                let seen = takeover::Seen {
                    silent: heard.elapsed(),
                    since_beat: (beat != 0)
                        .then(|| Duration::from_nanos(now_ns.saturating_sub(beat))),
                    state: takeover::proc_state(p.pid()),
                    waited_for_cpu: takeover::run_queue_wait(p.pid())
                        .zip(queued_at_heard)
                        .map(|(now, then)| now.saturating_sub(then)),
                    own_lateness,
                };
                match takeover::judge(&seen, patience) {
                    Verdict::Follow => {}
                    Verdict::Stopped => why = Some(Why::Stopped),
                    Verdict::Hung => why = Some(Why::Hung),
                    Verdict::Starved => {
                        if !starved_logged {
                            starved_logged = true;
                            tracing::warn!(
                                pid = p.pid(),
                                silent_ms = seen.silent.as_millis() as u64,
                                waited_for_cpu_ms =
                                    seen.waited_for_cpu.map(|w| w.as_millis() as u64),
                                own_lateness_ms = own_lateness.as_millis() as u64,
                                "the primary is silent but starved, not hung: not taking over"
                            );
                        }
                    }
                }
            }
            Some(_) => {}
        }
        if why.is_none() && !follower.synced() && asked.is_none_or(|t| t.elapsed() >= ASK_EVERY) {
            asker.reconnect(node);
            let _ = asker.ring(bell::STANDBY);
            asked = Some(Instant::now());
        }
        let mut stepped_down = false;
        reader.drain_bell();
        let got = reader.drain(holder.pid, |bytes| match follower.apply(bytes) {
            Ok(Step::Gap) => {
                tracing::warn!("replication records lost: asking for the whole state again");
                asked = None;
            }
            Ok(Step::SteppingDown) => stepped_down = true,
            Ok(_) => {}
            Err(e) => tracing::warn!("{e}"),
        });
        // Any record (a heartbeat at least) means the primary is not hung.
        if got > 0 {
            heard = Instant::now();
            starved_logged = false;
            // The run-queue figure at the start of a silence, read at most every
            // quarter deadline (every record would be a /proc read per heartbeat).
            if queued_read.is_none_or(|t| t.elapsed() >= deadline / 4) {
                queued_at_heard = pidfd
                    .as_ref()
                    .and_then(|p| takeover::run_queue_wait(p.pid()));
                queued_read = Some(Instant::now());
            }
        }
        if follower.synced() && prepared.is_none_or(|t| t.elapsed() >= PREPARE_EVERY) {
            presence.prepare();
            prepared = Some(Instant::now());
        }
        if follower.synced() && !logged_sync {
            logged_sync = true;
            tracing::info!(seq = follower.seq(), "standby in sync");
            event(
                serde_json::json!({"event": "in_sync", "primary": holder.pid, "seq": follower.seq()}),
            );
        }
        if stepped_down {
            why = Some(Why::SteppedDown);
        }
        if let Some(why) = why {
            // Told to stop at the same moment: stop, do not take over (the signal would
            // be lost to the primary this standby would become).
            if signals.drain() {
                tracing::info!("signal received: standby stopping");
                return Ok(None);
            }
            if let Some(me) = fence.claim(holder, std::process::id()) {
                let old = watched.and_then(|(_, p)| p);
                return Ok(Some(Followed {
                    noticed_ns: muster_shared::protocol::monotonic_ns(),
                    follower,
                    presence,
                    signals,
                    me,
                    old,
                    why,
                }));
            }
            // Another standby was quicker: follow it.
            continue;
        }
        let wait = patience
            .saturating_sub(heard.elapsed())
            .min(if follower.synced() {
                deadline
            } else {
                ASK_EVERY
            })
            .max(Duration::from_millis(1));
        let asked_at = Instant::now();
        let tokens = reactor.wait(Some(wait))?;
        // Woken by the timeout, later than asked: this standby was kept from running.
        own_lateness = match tokens.is_empty() {
            true => asked_at.elapsed().saturating_sub(wait),
            false => Duration::ZERO,
        };
        for token in tokens {
            match token {
                STANDBY_SIGNAL if signals.drain() => {
                    tracing::info!("signal received: standby stopping");
                    return Ok(None);
                }
                _ => {}
            }
        }
    }
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
                f.forget_previous(&mut core, host_now());
            }
            Some(f)
        }
        None => None,
    };
    let mut shell = Shell {
        events: None,
        fed,
        local_views: Vec::new(),
        core_views: Vec::new(),
        endpoint,
        list,
        fence,
        reactor,
        watches: HashMap::new(),
        by_addr: HashMap::new(),
        next_token: FIRST_WATCH_TOKEN,
        snapshot: Box::new(ServiceListSnapshot::empty()),
        last_ring: None,
        ring_owed: false,
        deferred_at: None,
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
        if let Some(Fault::HangAfter(n)) = FAULT.get() {
            if passes >= *n {
                tracing::warn!(passes, "fault: the loop stops here for good (as asked)");
                loop {
                    std::thread::sleep(Duration::from_secs(3600));
                }
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
                    inbox_rang = true;
                    if shell.endpoint.drain_bell() & (1 << bell::STANDBY) != 0 {
                        core.keep_journal();
                        shell.replica.image_owed = true;
                    }
                }
                TOKEN_SIGNAL => {
                    at(Phase::Signal);
                    if signals.drain() {
                        let standbys = shell.replica.writer.standbys();
                        if standbys > 0 {
                            // Hand over: the standbys have everything up to here.
                            shell.flush(&mut core, host_now())?;
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
                            federation: shell.fed.as_ref().map(|f| f.stats().clone()),
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
                        f.on_proxy(t, &core);
                    }
                }
                t => {
                    at(Phase::Timers);
                    if let Some(w) = shell.watches.get(&t) {
                        if w.pidfd.exited() {
                            let who = w.who.clone();
                            died_in(&mut core, shell.fed.as_mut(), now, &who);
                            died.push(who);
                            shell.unwatch(t);
                        }
                    }
                }
            }
        }
        // The inbox, when its bell rang (every frame a peer writes rings it, and a bell
        // drained before the inbox is read misses no frame written before it): a read
        // of the inbox asks each of its writers, hundreds of them at 900 users, so the
        // other wakes (datagrams, timers, the deferred writes) skip it. The first frame
        // is answered before the rest are read: the read that finds the inbox empty
        // costs as much as one that finds a frame, and the first user need not wait
        // for it.
        at(Phase::Inbox);
        if std::mem::take(&mut inbox_rang) && shell.drain_inbox(&mut core, now, Some(1))? {
            shell.flush(&mut core, host_now())?;
            shell.drain_inbox(&mut core, now, None)?;
        }
        at(Phase::Timers);
        if let Some(f) = shell.fed.as_mut() {
            f.sweep();
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

/// The primary's replication stream to its standbys.
struct Replication {
    writer: ReplicaWriter,
    leader: Leader,
    /// A standby asked for the whole state.
    image_owed: bool,
    /// When the last image went: images go at most every [`IMAGE_EVERY`], however
    /// often the standby bell rings (any process of the account can ring it).
    last_image: Option<Instant>,
    last_sent: Instant,
}

/// No progress of the loop for this long, outside its wait for work, is a stall the
/// watchdog logs.
const STALL: Duration = Duration::from_secs(1);

/// How long a primary stepping down waits for a standby to take over or to leave.
const HANDOVER_WAIT: Duration = Duration::from_secs(2);

/// Least time between two state images to the standbys.
const IMAGE_EVERY: Duration = Duration::from_millis(100);

impl Replication {
    /// Publishes the core's journal, then the image if one is owed; rings if anything went.
    fn publish(&mut self, core: &mut Broker) {
        let mut sent = false;
        for record in self.leader.ops(core) {
            if let Err(e) = self.writer.publish(&record) {
                tracing::warn!("replication: {e}");
            }
            sent = true;
        }
        if self.image_due() == Some(Duration::ZERO) {
            self.image_owed = false;
            self.last_image = Some(Instant::now());
            let image = self.leader.image(core);
            match self.writer.publish(&image) {
                Ok(()) => tracing::info!(
                    bytes = image.len(),
                    seq = self.leader.seq(),
                    standbys = self.writer.standbys(),
                    "state image sent to standbys"
                ),
                Err(e) => tracing::warn!("replication image: {e}"),
            }
            sent = true;
        }
        if sent {
            self.writer.ring();
            self.last_sent = Instant::now();
        }
    }

    /// When the owed image may go, if one is owed.
    fn image_due(&self) -> Option<Duration> {
        self.image_owed.then(|| {
            self.last_image
                .map_or(Duration::ZERO, |t| IMAGE_EVERY.saturating_sub(t.elapsed()))
        })
    }

    /// When a heartbeat is due, if standbys follow.
    fn heartbeat_due(&self) -> Option<Duration> {
        (self.writer.standbys() > 0).then(|| HEARTBEAT.saturating_sub(self.last_sent.elapsed()))
    }

    fn heartbeat(&mut self) {
        if self.heartbeat_due() == Some(Duration::ZERO) {
            let _ = self.writer.publish(&self.leader.heartbeat());
            self.writer.ring();
            self.last_sent = Instant::now();
        }
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
                    if !pid.is_some_and(instance_owner) || Federation::is_foreign(&user) =>
                {
                    let m = ToUser::Operated {
                        id,
                        result: Err(LOCAL_OPERATORS.into()),
                    };
                    self.endpoint.send_control(&Address::User(user), &m);
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
                return Ok(());
            }
            // A process that registered or said hello but is already gone.
            for who in dead {
                died_in(core, self.fed.as_mut(), now, &who);
            }
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
        while let Some(mut out) = core.poll_output() {
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
            let out = match self.udp.as_mut() {
                Some(d) => match d.front.route(core, out) {
                    Some(o) => o,
                    None => {
                        d.transmit();
                        continue;
                    }
                },
                None => out,
            };
            let out = match self.fed.as_mut() {
                Some(f) => match f.route(core, out) {
                    Some(o) => o,
                    None => continue,
                },
                None => out,
            };
            match out {
                // A local user hears of its grant from the broker, over a port open
                // since its hello, right after its system was sent the offer. (Remote
                // users' grants went to the UDP front; a user of another host hears
                // through its own host's broker.)
                Output::Granted(g) => {
                    if Federation::is_foreign(&g.user) {
                        continue;
                    }
                    muster_shared::trace::stamp(Stage::BrokerRelay, &g.user, g.req);
                    self.endpoint
                        .send_control(&Address::User(g.user.clone()), &g.message());
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
                Output::ToSystem(name, msg) => {
                    self.endpoint.send_control(&Address::System(name), &msg)
                }
                Output::ToUser(user, msg) => self.endpoint.send_control(&Address::User(user), &msg),
                Output::WatchSystem { system, pid } => {
                    self.watch(Address::System(system), pid, dead)
                }
                Output::WatchUser { user, pid } => self.watch(Address::User(user), pid, dead),
                Output::ForgetSystem(system) => self.forget(Address::System(system)),
                Output::ForgetUser(user) => self.forget(Address::User(user)),
            }
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
        let mine = match self.fed {
            None => &mut self.local_views,
            Some(_) => &mut self.core_views,
        };
        let local = core.take_list_change_into(mine);
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
                let mut views = self.core_views.clone();
                let n = f.links_in();
                for v in views.iter_mut() {
                    if let Some(c) = n.get(v.id.as_str()) {
                        v.links = v.links.saturating_add(*c);
                    }
                }
                let systems: Vec<&str> = core.systems().collect();
                f.publish_list(&views, &systems);
                self.local_views = views;
            }
            Some(_) => {}
        }
        self.snapshot.generation = generation;
        // One list in id order: this host's services and the other hosts', shared
        // fairly among them when there are more than the list holds.
        let (all, host) = match self.fed.as_ref() {
            Some(f) => {
                let total = self.local_views.len() + f.remote_views().count();
                if total > MAX_LISTED_SERVICES {
                    tracing::warn!(
                        total,
                        "the global list holds more services than the {MAX_LISTED_SERVICES} the shared list can: each host gets a fair share"
                    );
                }
                (
                    f.merged_views(&self.local_views, MAX_LISTED_SERVICES),
                    Some(muster_shared::snapshot::FixedStr::new(f.host())),
                )
            }
            None => (self.local_views.iter().collect(), None),
        };
        let mut n = 0;
        for (slot, v) in self.snapshot.entries.iter_mut().zip(&all) {
            *slot = v.to_entry();
            if let Some(h) = host.filter(|_| !v.remote) {
                slot.host = h;
            }
            n += 1;
        }
        self.snapshot.count = n;
        let t = Instant::now();
        match self.list.publish(&self.snapshot, &self.fence) {
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
                None => d
                    .front
                    .list_changed(self.snapshot.epoch, generation, &self.local_views),
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
        let mut watchers: Vec<UserId> = core.list_watchers().cloned().collect();
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
        if let Some(t) = self.by_addr.remove(&who) {
            self.unwatch(t);
        }
        if !process_exists(pid) {
            dead.push(who);
            return;
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
        self.watches.insert(token, Watch { who, pidfd });
    }

    /// Stops watching `who`; its ports linger (a Delinquent notice may just have been sent).
    fn forget(&mut self, who: Address) {
        if let Some(t) = self.by_addr.remove(&who) {
            self.unwatch(t);
        }
        self.endpoint.release(&who);
    }

    fn unwatch(&mut self, token: usize) {
        if let Some(w) = self.watches.remove(&token) {
            self.reactor.remove(w.pidfd.raw());
            if self.by_addr.get(&w.who) == Some(&token) {
                self.by_addr.remove(&w.who);
            }
        }
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
        Address::Broker => {}
    }
}

/// Most handling records kept for `--handling-log` (32 bytes each); later ones are
/// counted, not kept.
pub const MAX_HANDLING_LOG: usize = 2_000_000;

/// One message handled: when (CLOCK_MONOTONIC ms, one clock for every process on the
/// host), its kind, and how long the core took, µs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HandlingRecord {
    /// CLOCK_MONOTONIC ms when handling began.
    pub at_ms: u64,
    /// The message kind (`ToBroker::kind`), or `list_write` for a list snapshot write.
    pub kind: &'static str,
    /// Handling time, µs.
    pub us: u64,
}

/// Time to handle each message type (µs histograms), and, if asked, every handling.
#[derive(Debug)]
pub struct Handling {
    /// Per kind.
    pub hist: std::collections::BTreeMap<&'static str, hdrhistogram::Histogram<u64>>,
    /// Every handling in order (only with `keep_log`), at most [`MAX_HANDLING_LOG`].
    pub log: Vec<HandlingRecord>,
    /// Handlings not logged because the log was full.
    pub log_dropped: u64,
    keep_log: bool,
}

impl Handling {
    /// Empty; `keep_log` keeps every handling for a time series.
    pub fn new(keep_log: bool) -> Self {
        Handling {
            hist: std::collections::BTreeMap::new(),
            log: Vec::new(),
            log_dropped: 0,
            keep_log,
        }
    }

    /// Records one handling of `kind` that began at `began` and took `took`.
    pub fn record(&mut self, kind: &'static str, began: Instant, took: Duration) {
        let us = (took.as_nanos() as u64).div_ceil(1000).max(1);
        let h = self.hist.entry(kind).or_insert_with(|| {
            hdrhistogram::Histogram::new(3).expect("3 significant figures is a valid precision")
        });
        let _ = h.record(us);
        if self.keep_log {
            if self.log.len() < MAX_HANDLING_LOG {
                let ago = began.elapsed().as_nanos() as u64;
                let at_ms = muster_shared::protocol::monotonic_ns().saturating_sub(ago) / 1_000_000;
                self.log.push(HandlingRecord { at_ms, kind, us });
            } else {
                self.log_dropped += 1;
            }
        }
    }

    /// Counts and percentiles per kind, for an operator's status.
    pub fn figures(&self) -> Vec<muster_shared::protocol::HandlingFigures> {
        self.hist
            .iter()
            .map(|(kind, h)| muster_shared::protocol::HandlingFigures {
                kind: (*kind).to_string(),
                count: h.len(),
                p50_us: h.value_at_quantile(0.5),
                p99_us: h.value_at_quantile(0.99),
                max_us: h.max(),
            })
            .collect()
    }

    /// Writes the log as CSV (`at_ms,kind,us`).
    pub fn write_log(&self, path: &std::path::Path) -> std::io::Result<()> {
        use std::io::Write;
        let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
        writeln!(f, "at_ms,kind,us")?;
        for r in &self.log {
            writeln!(f, "{},{},{}", r.at_ms, r.kind, r.us)?;
        }
        f.flush()
    }
}

/// Cuts an operator's status to fit one frame (with room for the message around it):
/// its lists are halved until it does. The totals still count everyone.
fn fit_status(status: &mut muster_shared::protocol::BrokerStatus) {
    use muster_shared::protocol::{encode, MAX_FRAME};
    while encode(&*status).map_or(true, |f| f.len() > MAX_FRAME - 64) {
        if status.users.is_empty()
            && status.sessions.is_empty()
            && status.queues.is_empty()
            && status.systems.is_empty()
        {
            status.handling.clear();
            return;
        }
        for q in &mut status.queues {
            q.waiting.truncate(q.waiting.len() / 2);
        }
        status.queues.truncate(status.queues.len() / 2);
        status.users.truncate(status.users.len() / 2);
        status.sessions.truncate(status.sessions.len() / 2);
        status.systems.truncate(status.systems.len() / 2);
    }
}

/// Hands `msg` to the core and records how long that took under the message's kind.
pub fn timed_handle(handling: &mut Handling, core: &mut Broker, now: Duration, msg: ToBroker) {
    let kind = msg.kind();
    let t = Instant::now();
    core.handle(now, msg);
    handling.record(kind, t, t.elapsed());
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use muster_shared::protocol::{encode, BrokerStatus, LinkInfo, UserStatus, MAX_FRAME};
    use muster_shared::types::{ServiceId, UserId};

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
}
