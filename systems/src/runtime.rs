//! The SDK's runtime: drives a [`SystemCore`] over iceoryx2 and calls the system's own
//! logic ([`SystemApp`]) on events and on its ticks.
//!
//! A new robot system implements [`SystemApp`] and calls [`run_system`]. The runtime
//! registers, answers pings, re-registers after delinquency or a broker restart, and
//! sleeps on its bell, the broker's presence event and process-death descriptors. It
//! logs to standard error (`RUST_LOG`, default `info`) unless the program set up
//! `tracing` itself.

use crate::core::{SystemCore, SystemEvent, SystemOutput};
use crate::remote::UdpSessions;
use muster_shared::ipc::{bell, create_node, Endpoint, Presence, TransportError};
use muster_shared::names::{Address, Instance};
use muster_shared::protocol::{decode, ToBroker, ToSystem};
use muster_shared::reactor::{process_exists, PidFd, Reactor, SignalPipe};
use muster_shared::trace::Stage;
use muster_shared::types::UserId;
use std::collections::HashMap;
use std::os::fd::RawFd;
use std::time::{Duration, Instant};

/// A robot system's own logic.
///
/// Every call gets `now`: the time since the runtime started (a monotonic clock), the
/// same clock [`SystemApp::next_tick`] answers on. The runtime calls from one thread,
/// in this order on each wake-up: [`SystemApp::on_ready`] for the app's descriptors
/// that are readable, then [`SystemApp::on_event`] for every protocol event (a
/// session's `SessionStarted` before anything else of it, its `SessionEnded` last),
/// then [`SystemApp::on_tick`] if its time has come (so a tick never sees a session
/// whose start the app was not told of), then the events the tick led to.
pub trait SystemApp {
    /// Called for every protocol event (session started, input, ended, ...).
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent);
    /// Called when [`SystemApp::next_tick`] has passed.
    fn on_tick(&mut self, core: &mut SystemCore, now: Duration);
    /// When to call [`SystemApp::on_tick`] next, as an absolute time on the clock of
    /// `now` (e.g. `Some(last_tick + period)`), not a delay; `None` sleeps until an
    /// event or a descriptor.
    fn next_tick(&self, core: &SystemCore) -> Option<Duration>;
    /// The system's own descriptors to sleep on beside the protocol (its robot's sensor
    /// events, a socket), asked once when the runtime starts. They must stay open while
    /// the system runs. Readiness is edge-triggered: drain a descriptor in
    /// [`SystemApp::on_ready`].
    fn descriptors(&self) -> Vec<RawFd> {
        Vec::new()
    }
    /// Called when descriptor `index` of [`SystemApp::descriptors`] became readable.
    fn on_ready(&mut self, core: &mut SystemCore, now: Duration, index: usize) {
        let _ = (core, now, index);
    }
    /// Whether the system should stop now (asked after every round of callbacks): the
    /// runtime then ends its sessions, unregisters and returns, as on SIGTERM. Wake the
    /// runtime through one of [`SystemApp::descriptors`] to have it asked at once.
    fn stop_requested(&self) -> bool {
        false
    }
}

/// A borrowed app runs too, so a caller keeps it (and what it measured) after the run.
impl<A: SystemApp + ?Sized> SystemApp for &mut A {
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent) {
        (**self).on_event(core, now, event)
    }
    fn on_tick(&mut self, core: &mut SystemCore, now: Duration) {
        (**self).on_tick(core, now)
    }
    fn next_tick(&self, core: &SystemCore) -> Option<Duration> {
        (**self).next_tick(core)
    }
    fn descriptors(&self) -> Vec<RawFd> {
        (**self).descriptors()
    }
    fn on_ready(&mut self, core: &mut SystemCore, now: Duration, index: usize) {
        (**self).on_ready(core, now, index)
    }
    fn stop_requested(&self) -> bool {
        (**self).stop_requested()
    }
}

/// Why a system stopped.
#[derive(Debug, thiserror::Error)]
pub enum SystemError {
    /// Shared memory could not be set up.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// The OS refused epoll or signals.
    #[error("os: {0}")]
    Os(#[from] std::io::Error),
    /// The broker refused the registration; the reason says what to fix.
    #[error("registration refused: {0}")]
    Refused(String),
}

const TOKEN_BELL: usize = 0;
/// How often a system with sessions open takes in new writers to its inbox.
const CONNECT_EVERY: Duration = Duration::from_millis(100);
const TOKEN_PRESENCE: usize = 1;
const TOKEN_SIGNAL: usize = 2;
const TOKEN_BROKER: usize = 3;
const TOKEN_CONTROL: usize = 4;
const TOKEN_UDP: usize = 5;
const FIRST_USER_TOKEN: usize = 16;
/// The app's descriptors are registered under `FIRST_APP_TOKEN + index`, far above the
/// users' tokens.
const FIRST_APP_TOKEN: usize = 1 << 40;

/// Operator commands read from standard input, one a line.
pub const CONTROL_HELP: &str =
    "withdraw SERVICE | restore SERVICE | overload on|off | end SESSION|all | quit";

/// Lines of standard input, delivered through a socket the reactor can wait on.
struct Control {
    wake: std::os::unix::net::UnixStream,
    lines: std::sync::mpsc::Receiver<String>,
}

impl Control {
    fn spawn() -> std::io::Result<Self> {
        use std::io::{BufRead, Write};
        let (wake, mut tx_wake) = std::os::unix::net::UnixStream::pair()?;
        wake.set_nonblocking(true)?;
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::Builder::new()
            .name("stdin-control".into())
            .spawn(move || {
                for line in std::io::stdin().lock().lines() {
                    let Ok(line) = line else { break };
                    if tx.send(line).is_err() || tx_wake.write_all(b".").is_err() {
                        break;
                    }
                }
            })?;
        Ok(Control { wake, lines })
    }

    fn take(&mut self) -> Vec<String> {
        use std::io::Read;
        let mut buf = [0u8; 64];
        while (&self.wake).read(&mut buf).is_ok_and(|n| n > 0) {}
        self.lines.try_iter().collect()
    }
}

/// Applies one operator line; `false` means quit.
pub fn apply_control(core: &mut SystemCore, line: &str) -> bool {
    let words: Vec<&str> = line.split_whitespace().collect();
    match words.as_slice() {
        [] => {}
        ["withdraw", s] => core.withdraw(s),
        ["restore", s] => core.restore(s),
        ["overload", "on"] => core.set_overloaded(true),
        ["overload", "off"] => core.set_overloaded(false),
        ["end", "all"] => {
            let ids: Vec<_> = core.sessions().map(|(id, _, _)| id).collect();
            for id in ids {
                core.end_session(
                    id,
                    muster_shared::types::EndReason::BySystem("ended by the operator".into()),
                );
            }
        }
        ["end", hex] => match u64::from_str_radix(hex, 16) {
            Ok(n) => core.end_session(
                muster_shared::types::SessionId(n),
                muster_shared::types::EndReason::BySystem("ended by the operator".into()),
            ),
            Err(_) => tracing::warn!("not a session id: {hex}"),
        },
        ["quit"] => return false,
        _ => tracing::warn!("unknown control line {line:?}: {CONTROL_HELP}"),
    }
    true
}

struct Shell {
    remote: Option<UdpSessions>,
    endpoint: Endpoint,
    reactor: Reactor,
    broker: Option<PidFd>,
    users: HashMap<usize, (UserId, PidFd)>,
    user_tokens: HashMap<UserId, usize>,
    next_token: usize,
    waiting_logged: bool,
    /// When a latched value last rang the broker's bell (see [`LATEST_RING_EVERY`]).
    latest_rung: Option<Instant>,
    /// In a pass of the loop, before its events went to the app: a session's
    /// confirmation to the broker is written as it comes but the broker's bell rings
    /// only at [`Shell::end_pass`] (or with the next frame to it that rings), so that
    /// the session's first update, which the app sends when it hears of the session,
    /// goes before the broker is woken to take a core its user needs. The grant went to
    /// the user before the offer came: nothing waits on the confirmation. (An end, which
    /// frees a place a queued user may wait for, rings at once.)
    broker_bell_late: bool,
}

/// A latched value is written into the broker's inbox unrung, for the broker to read
/// as it next reads its inbox for anything else; but it rings at most this often, so
/// that a broker whose inbox nothing else rings (its users all remote) has read a
/// value this recent at a grant.
const LATEST_RING_EVERY: Duration = Duration::from_millis(250);

/// How a system runs, beyond its core and app.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Listen here for remote users' sessions (e.g. `127.0.0.1:0`); `None`: local users only.
    pub udp: Option<std::net::SocketAddr>,
    /// Read operator lines ([`CONTROL_HELP`]) from standard input (default); off for a
    /// host program that owns its standard input (the Python package).
    pub stdin_control: bool,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            udp: None,
            stdin_control: true,
        }
    }
}

/// Runs `app` as system `core` on instance `inst` until SIGINT/SIGTERM (or a `quit`
/// control line); returns the final protocol state (its [`SystemCore::report`]).
pub fn run_system<A: SystemApp>(
    inst: &Instance,
    core: SystemCore,
    app: A,
) -> Result<SystemCore, SystemError> {
    run_system_with(inst, core, app, &RunOptions::default())
}

/// [`run_system`] with options (a UDP endpoint for remote users).
pub fn run_system_with<A: SystemApp>(
    inst: &Instance,
    mut core: SystemCore,
    mut app: A,
    opts: &RunOptions,
) -> Result<SystemCore, SystemError> {
    default_logging();
    // No dead-node cleanup when opening services: after a broker crash every system
    // would race to clean the dead broker's hundreds of ports before it could
    // re-register (measured: 180 ms with 20 systems). The broker cleans up; a system
    // cleans only when its own inbox is still held by a dead process of its name.
    let node = create_node(&format!("muster-system-{}", core.name()), false)?;
    let endpoint = Endpoint::open(inst, Address::System(core.name().to_string()), node)?;
    let presence = Presence::listen(endpoint.node(), inst)?;
    let mut signals = SignalPipe::install()?;
    let reactor = Reactor::new()?;
    reactor.add(endpoint.bell_fd(), TOKEN_BELL)?;
    if let Some(fd) = presence.fd() {
        reactor.add(fd, TOKEN_PRESENCE)?;
    }
    reactor.add(signals.raw(), TOKEN_SIGNAL)?;
    let mut control = match opts.stdin_control {
        true => Some(Control::spawn()?),
        false => None,
    };
    if let Some(c) = &control {
        reactor.add(std::os::fd::AsRawFd::as_raw_fd(&c.wake), TOKEN_CONTROL)?;
    }
    let remote = match opts.udp {
        Some(addr) => {
            let r = UdpSessions::bind(addr)?;
            reactor.add(r.fd(), TOKEN_UDP)?;
            core.set_udp(Some(r.local_addr().to_string()));
            tracing::info!(udp = %r.local_addr(), "listening for remote users' sessions");
            Some(r)
        }
        None => None,
    };
    for (i, fd) in app.descriptors().into_iter().enumerate() {
        reactor.add(fd, FIRST_APP_TOKEN + i)?;
    }
    let mut shell = Shell {
        remote,
        endpoint,
        reactor,
        broker: None,
        users: HashMap::new(),
        user_tokens: HashMap::new(),
        next_token: FIRST_USER_TOKEN,
        waiting_logged: false,
        latest_rung: None,
        broker_bell_late: false,
    };
    let start = Instant::now();
    core.register();
    shell.flush(&mut core);
    tracing::info!(
        system = core.name(),
        services = core.specs().len(),
        "system up"
    );

    loop {
        let now = start.elapsed();
        let timeout = app.next_tick(&core).map(|t| t.saturating_sub(now));
        let housekeeping = shell
            .remote
            .as_ref()
            .and_then(|r| r.logic.poll_timeout())
            .map(|t| t.saturating_duration_since(Instant::now()));
        // Users holding sessions open their ports to this inbox as they go: while any
        // session is open, the inbox takes them in every CONNECT_EVERY, so the next
        // offer is not read behind them.
        let connect = (core.sessions().next().is_some()).then_some(CONNECT_EVERY);
        let timeout = [timeout, shell.endpoint.sweep(), housekeeping, connect]
            .into_iter()
            .flatten()
            .min();
        let tokens = shell.reactor.wait(timeout)?;
        shell.broker_bell_late = true;
        let now = start.elapsed();
        let mut udp_readable = false;
        let mut control_lines = Vec::new();
        for token in tokens {
            match token {
                TOKEN_BELL => {
                    shell.endpoint.drain_bell();
                }
                TOKEN_PRESENCE => {
                    let rung = presence.drain();
                    if rung & (1 << bell::BROKER_DOWN) != 0 {
                        core.broker_lost();
                        shell.drop_broker();
                    }
                    // A standby took over: it holds our registration, but frames the old
                    // broker never read are lost, so register again all the same
                    // (services, sessions, withdrawals): one frame.
                    if rung & (1 << bell::BROKER_UP | 1 << bell::TAKEOVER) != 0 {
                        // Keep the publisher: the new broker takes over the same inbox, and
                        // dropping it could lose a frame already sent.
                        core.broker_lost();
                        shell.drop_broker_watch();
                        core.register();
                    }
                }
                TOKEN_SIGNAL => {
                    if signals.drain() {
                        tracing::info!(system = core.name(), "signal received: leaving");
                        core.shutdown();
                        shell.end_pass(&mut core);
                        return Ok(core);
                    }
                }
                // Read after the inbox, below.
                TOKEN_UDP => udp_readable = true,
                // Applied after the inbox, below.
                TOKEN_CONTROL => {
                    control_lines.extend(control.as_mut().map(Control::take).unwrap_or_default())
                }
                TOKEN_BROKER => {
                    if shell.broker.as_ref().is_some_and(PidFd::exited) {
                        tracing::warn!("broker died; sessions go on, waiting for a new broker");
                        core.broker_lost();
                        shell.drop_broker();
                    }
                }
                t if t >= FIRST_APP_TOKEN => app.on_ready(&mut core, now, t - FIRST_APP_TOKEN),
                t => {
                    let dead = shell
                        .users
                        .get(&t)
                        .filter(|(_, p)| p.exited())
                        .map(|(u, _)| u.clone());
                    if let Some(user) = dead {
                        core.user_died(&user);
                        shell.unwatch_user(&user);
                        shell.endpoint.forget(&Address::User(user));
                    }
                }
            }
        }
        // Everything waiting, the broker's offers first: the inbox is read writer by
        // writer, and a user's first input or end, sent once it heard of its grant,
        // may be read before the offer the broker sent just ahead of that grant.
        let mut batch = Vec::new();
        while let Some((frame, pid)) = shell.endpoint.recv_from() {
            match decode::<ToSystem>(&frame) {
                Ok(msg) if !core.sender_allowed(pid, &msg, |a| shell.endpoint.owner_pid(a)) => {}
                Ok(msg) => {
                    if let ToSystem::Offer { user, req, .. } = &msg {
                        muster_shared::trace::stamp(Stage::SystemRecv, user, *req);
                    }
                    batch.push(msg);
                }
                Err(e) => muster_shared::protocol::log_bad_frame(&e),
            }
        }
        batch.sort_by_key(|m| !matches!(m, ToSystem::Offer { .. }));
        for msg in batch {
            if let Some(r) = shell.remote.as_mut() {
                r.logic.note(&msg);
            }
            core.handle(msg)
        }
        // A remote user's first datagram of a session comes after its grant, which the
        // broker sent just before it wrote the offer: the offers read above open their
        // sessions (their keys known) once their outputs are routed, and a datagram
        // that came before its offer is kept until then (`RemoteSessions`).
        if udp_readable && shell.remote.is_some() {
            shell.flush(&mut core);
            if let Some(r) = shell.remote.as_mut() {
                r.on_readable(&mut core);
            }
        }
        // An operator's line comes after what the broker sent before it was typed (a
        // grant its user was told of, then withdrawn: the session opens, then ends).
        for line in control_lines {
            if !apply_control(&mut core, &line) {
                core.shutdown();
                shell.end_pass(&mut core);
                return Ok(core);
            }
        }
        if let Some(r) = shell.remote.as_mut() {
            r.logic.handle_timeout(Instant::now(), &mut core);
            r.transmit();
        }
        // Events first: a session's `SessionStarted` always comes before a tick that
        // could stream to it.
        deliver(&mut app, &mut core, &mut shell, now)?;
        // What the app sent for this pass's events went first; now the broker may wake.
        shell.end_pass(&mut core);
        if app.next_tick(&core).is_some_and(|t| t <= now) {
            app.on_tick(&mut core, now);
            deliver(&mut app, &mut core, &mut shell, now)?;
        }
        shell.endpoint.update_connections();
        if app.stop_requested() {
            tracing::info!(system = core.name(), "stopping: the program asked");
            core.shutdown();
            shell.end_pass(&mut core);
            return Ok(core);
        }
    }
}

/// Logs to standard error, filtered by `RUST_LOG` (default `info`), unless the program
/// installed a `tracing` subscriber of its own: a new system says what it does without
/// a line of set-up.
fn default_logging() {
    if !tracing::dispatcher::has_been_set() {
        let filter = tracing_subscriber::EnvFilter::try_from_default_env()
            .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
        let _ = tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_writer(std::io::stderr)
            .try_init();
    }
}

/// Hands the core's events to the app, flushing what each leads to.
fn deliver<A: SystemApp>(
    app: &mut A,
    core: &mut SystemCore,
    shell: &mut Shell,
    now: Duration,
) -> Result<(), SystemError> {
    loop {
        shell.flush(core);
        let Some(ev) = core.poll_event() else {
            return Ok(());
        };
        match &ev {
            SystemEvent::RegistrationRefused(r) => return Err(SystemError::Refused(r.clone())),
            SystemEvent::Registered => {
                shell.waiting_logged = false;
                tracing::info!(system = core.name(), "registered with the broker");
            }
            SystemEvent::Delinquent => {
                tracing::warn!("broker declared us delinquent; re-registering")
            }
            _ => {}
        }
        app.on_event(core, now, ev);
    }
}

impl Shell {
    fn flush(&mut self, core: &mut SystemCore) {
        // A burst of frames to other hosts' users (an update to each of a service's
        // sessions) rings each host's relay for its first frame and at its end.
        self.endpoint.quiet_relays();
        let mut dead_users = Vec::new();
        self.flush_outputs(core, &mut dead_users);
        while !dead_users.is_empty() {
            for user in std::mem::take(&mut dead_users) {
                core.user_died(&user);
                self.endpoint.forget(&Address::User(user));
            }
            self.flush_outputs(core, &mut dead_users);
        }
        if self.broker_bell_late {
            self.endpoint.ring_pending_but(&Address::Broker);
        } else {
            self.endpoint.ring_pending();
        }
    }

    /// Ends the part of a pass in which the broker's bell waits (see
    /// [`Shell::broker_bell_late`]): flushes and rings it if frames were written.
    fn end_pass(&mut self, core: &mut SystemCore) {
        self.broker_bell_late = false;
        self.flush(core);
    }

    fn flush_outputs(&mut self, core: &mut SystemCore, dead_users: &mut Vec<UserId>) {
        while let Some(out) = core.poll_output() {
            let out = match self.remote.as_mut() {
                Some(r) => match r.logic.route(Instant::now(), out) {
                    Some(o) => o,
                    None => {
                        r.transmit();
                        continue;
                    }
                },
                None => out,
            };
            match out {
                SystemOutput::ToBroker(msg @ ToBroker::Latest { .. }) => {
                    // The broker wants it only at a grant: written, rung at most every
                    // LATEST_RING_EVERY, and dropped like an update when its inbox is
                    // full.
                    let ring = self
                        .latest_rung
                        .is_none_or(|t| t.elapsed() >= LATEST_RING_EVERY);
                    let sent = match ring {
                        true => self.endpoint.send_msg(&Address::Broker, &msg),
                        false => self.endpoint.send_silent(&Address::Broker, &msg),
                    };
                    match sent {
                        Ok(()) if ring => self.latest_rung = Some(Instant::now()),
                        Ok(()) => {}
                        Err(e) => tracing::debug!("latched value not sent: {e}"),
                    }
                }
                SystemOutput::ToBroker(msg) => {
                    if !matches!(msg, ToBroker::Register { .. }) {
                        // Session ended, offer answers, withdraw, pong...: held back
                        // when the broker's inbox is full, never dropped.
                        if self.broker_bell_late && matches!(msg, ToBroker::OfferAnswer { .. }) {
                            self.endpoint.send_control_quiet(&Address::Broker, &msg);
                        } else {
                            self.endpoint.send_control(&Address::Broker, &msg);
                        }
                        continue;
                    }
                    match self.endpoint.send_msg(&Address::Broker, &msg) {
                        Err(TransportError::Unreachable(_)) => {
                            if !self.waiting_logged {
                                tracing::info!("no broker yet; waiting for one to announce itself");
                                self.waiting_logged = true;
                            }
                        }
                        Err(e @ TransportError::Encode { .. }) => tracing::error!("{e}"),
                        Err(e) => tracing::debug!("{e}"),
                        Ok(()) => {}
                    }
                }
                // A local user heard of its grant from the broker; the session's first
                // update or status opens our ports to it.
                SystemOutput::ToUser(_, muster_shared::protocol::ToUser::Granted { .. }) => {}
                SystemOutput::ToUser(user, msg) => {
                    // Updates are a stream (a full inbox drops one, counted as a gap);
                    // everything else is control and is held back, never dropped.
                    if let muster_shared::protocol::ToUser::Update { session, seq, .. } = &msg {
                        match self.endpoint.send_msg(&Address::User(user), &msg) {
                            Ok(()) => {}
                            Err(e @ TransportError::Encode { .. }) => tracing::error!("{e}"),
                            Err(e) => core.note_undelivered(*session, *seq, e.to_string()),
                        }
                    } else {
                        self.endpoint.send_control(&Address::User(user), &msg);
                    }
                }
                SystemOutput::WatchBroker(pid) => {
                    self.drop_broker_watch();
                    match PidFd::open(pid) {
                        Ok(p) => {
                            if self.reactor.add(p.raw(), TOKEN_BROKER).is_ok() {
                                self.broker = Some(p);
                            }
                        }
                        Err(e) => tracing::warn!("cannot watch the broker (pid {pid}): {e}"),
                    }
                }
                SystemOutput::WatchUser(user, pid) => {
                    if self.user_tokens.contains_key(&user) {
                        continue;
                    }
                    match PidFd::open(pid) {
                        Ok(p) => {
                            let t = self.next_token;
                            self.next_token += 1;
                            if self.reactor.add(p.raw(), t).is_ok() {
                                self.users.insert(t, (user.clone(), p));
                                self.user_tokens.insert(user, t);
                            }
                        }
                        // The user died between its request and our grant.
                        Err(_) if !process_exists(pid) => dead_users.push(user),
                        Err(e) => tracing::warn!("cannot watch user {user} (pid {pid}): {e}"),
                    }
                }
                SystemOutput::ForgetUser(user) => {
                    self.unwatch_user(&user);
                    self.endpoint.release(&Address::User(user));
                }
            }
        }
    }

    fn drop_broker_watch(&mut self) {
        if let Some(p) = self.broker.take() {
            self.reactor.remove(p.raw());
        }
    }

    fn drop_broker(&mut self) {
        self.drop_broker_watch();
        self.endpoint.forget(&Address::Broker);
    }

    fn unwatch_user(&mut self, user: &UserId) {
        if let Some(t) = self.user_tokens.remove(user) {
            if let Some((_, p)) = self.users.remove(&t) {
                self.reactor.remove(p.raw());
            }
        }
    }
}
