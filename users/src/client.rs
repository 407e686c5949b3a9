//! The user client library: a [`UserCore`] driven over iceoryx2, with a blocking API
//! that takes deadlines. Reads the service list in place from the broker's blackboard.

use crate::core::{UserCore, UserEvent, UserOutput};
use crate::remote::{RemoteLink, RemoteOptions};
use muster_shared::ipc::{
    bell, create_node, Endpoint, ListReader, PortShare, Presence, ProcessInbox, TransportError,
};
use muster_shared::names::{Address, Instance};
use muster_shared::protocol::{decode, ToUser};
use muster_shared::reactor::{process_exists, PidFd, Reactor, SignalPipe};
use muster_shared::snapshot::{ListFilter, ListPage, ListPart, ServiceListSnapshot};
use muster_shared::types::{link_compatible, Payload, ServiceId, ServiceKind, SessionId, UserId};
use std::collections::{HashMap, VecDeque};
use std::os::fd::RawFd;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Why a user operation failed.
#[derive(Debug, thiserror::Error)]
pub enum UserError {
    /// Shared memory could not be set up.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// The OS refused epoll or signals.
    #[error("os: {0}")]
    Os(#[from] std::io::Error),
    /// No broker answered before the deadline; start one with `muster broker`.
    #[error("no broker on instance {0:?} (start one with `muster broker --instance {0}`)")]
    NoBroker(String),
    /// A broker reads the instance's inbox but did not welcome this user before the
    /// longer deadline ([`BUSY_BROKER_WAIT`]): it is stopped or overloaded.
    #[error("the broker of instance {inst:?} (pid {pid}) is running but did not welcome this user within {waited:?}")]
    BrokerBusy {
        /// The instance.
        inst: String,
        /// The broker's process.
        pid: u32,
        /// How long this user waited.
        waited: Duration,
    },
    /// The service id is not in the list.
    #[error("unknown service {0:?} (see `muster user list`)")]
    UnknownService(String),
    /// The two services cannot be linked; the text says why.
    #[error("cannot link: {0}")]
    CannotLink(String),
    /// SIGINT or SIGTERM arrived.
    #[error("interrupted")]
    Interrupted,
    /// No broker answered over UDP before the deadline.
    #[error("no answer from a broker at udp {addr} (is it started with `--udp {addr}`, and is user {name:?} with this key in its --access file?)")]
    NoRemoteBroker {
        /// The address tried.
        addr: String,
        /// The user name presented.
        name: String,
    },
    /// The remote list did not arrive complete in time.
    #[error("the service list did not arrive within {0:?}")]
    ListTimeout(Duration),
    /// A list filter that cannot be used (a bad name glob, a text too long).
    #[error("list filter: {0}")]
    BadFilter(String),
}

/// What [`UserClient::wait`] woke for.
#[derive(Debug)]
pub enum Wake {
    /// A protocol event.
    Event(UserEvent),
    /// The extra file descriptor is readable.
    Extra,
    /// The deadline passed.
    Timeout,
}

/// How long after a grant a user opens the granting system's inbox even if it has not heard
/// from the system yet (see `to_warm`).
const WARM_AFTER: Duration = Duration::from_millis(20);
const TOKEN_BELL: usize = 0;
const TOKEN_PRESENCE: usize = 1;
const TOKEN_SIGNAL: usize = 2;
const TOKEN_BROKER: usize = 3;
const TOKEN_EXTRA: usize = 4;
const TOKEN_UDP: usize = 5;
/// How often a user with requests out looks for a standby's takeover after its broker
/// died, and for how long.
const SUCCESSOR_POLL: Duration = Duration::from_millis(2);
const SUCCESSOR_WAIT: Duration = Duration::from_secs(5);
/// How long a remote list request may take, retries included, at least.
const LIST_WAIT: Duration = Duration::from_secs(5);
const FIRST_SYSTEM_TOKEN: usize = 16;

/// 24 bits that differ from one start of a process to the next.
fn nonce() -> u64 {
    let nanos = Instant::now().elapsed().as_nanos() as u64
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
    nanos & 0xff_ffff
}

/// The id of a local user with an inbox of its own: `PREFIX<pid>-<nonce>`.
fn own_id(prefix: &str) -> UserId {
    UserId(format!("{prefix}{}-{:06x}", std::process::id(), nonce()))
}

/// The id of a local user reached at its process's shared inbox:
/// `PREFIX<n>-<nonce>~<pid>`, `n` counting this process's users.
fn shared_id(prefix: &str, inbox: &ProcessInbox) -> UserId {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    inbox.user_id(&format!("{prefix}{n}-{:06x}", nonce()))
}

/// The shared-memory side of a local user.
struct Local {
    inst: Instance,
    endpoint: Endpoint,
    presence: Presence,
    list: Option<ListReader>,
    broker: Option<PidFd>,
    /// The dead broker's pid, and since when a successor is looked for.
    successor: Option<(u32, Instant)>,
    fence: Option<muster_shared::fence::Fence>,
    systems: HashMap<usize, (String, PidFd)>,
    system_tokens: HashMap<String, usize>,
    next_token: usize,
    /// Systems newly granting this user a session, whose inboxes it opens once idle and
    /// once the system was heard from (or [`WARM_AFTER`] passed): its first frame to a
    /// system (an input, an end) then costs no first contact, and the system, which
    /// takes in each new writer to its inbox as it next reads it (about 0.1 ms), has
    /// read the offer before this one appears.
    to_warm: Vec<(String, Instant)>,
}

/// How this user reaches the federation.
enum Transport {
    /// iceoryx2 shared memory on this host.
    Local(Box<Local>),
    /// UDP to the broker's front and to systems' endpoints.
    Remote(Box<RemoteLink>),
}

/// A connected user.
pub struct UserClient {
    core: UserCore,
    transport: Transport,
    reactor: Reactor,
    signals: Option<SignalPipe>,
    events: VecDeque<UserEvent>,
    extra: Option<RawFd>,
    /// The extra fd was seen readable by a turn and not yet reported by `wait`.
    extra_seen: bool,
    closed: bool,
    /// How long a remote list may take: [`LIST_WAIT`], or as long as the caller would
    /// wait for a broker (a list asked for in a storm of thousands connecting at once
    /// waits its turn as the connection did).
    list_wait: Duration,
}

/// This process's turn to set a local user up, and a place in the machine's (see
/// [`setup_turn`]).
struct SetupTurn {
    _machine: muster_shared::ipc::SetupTurn,
    _process: std::sync::MutexGuard<'static, ()>,
}

/// How long a user waits for a place in the machine's turn to set up before it goes on
/// without one: a holder that was stopped keeps nobody for longer. 900 users, a process
/// each, took 3–5 s to pass (2 at a time, about 4–5 ms each under that load); a
/// process's users queue for it one at a time.
const SETUP_PATIENCE: Duration = Duration::from_secs(10);

/// Waits for the turn to set a local user up: its node, inbox, bell and ports to the
/// broker, a run of files created in `/dev/shm` and segments mapped into the process.
/// Hundreds of users doing it at once queue on the directories' locks, holding them
/// while preempted, and on their processes' own locks (the memory map; the descriptor
/// table, which grows with an RCU grace period each time in a process of many
/// threads), and a broker creating files of its own (its port into a new inbox) waits
/// behind them all: measured, 900 users 16 a process starting, the broker asleep in
/// `openat` for up to 430 ms, a first-10-s request p99 of 0.15–0.58 s. So one thread of
/// a process sets up at a time, and two users of the machine
/// ([`muster_shared::ipc::SetupTurn`]). The wait for the broker's welcome is not made
/// in turn (users waiting for a broker that is not there wait together), nor is the
/// opening of the list reader (a welcomed user would wait for the setups after it).
fn setup_turn() -> SetupTurn {
    static PROCESS: std::sync::Mutex<()> = std::sync::Mutex::new(());
    static USERS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let process = PROCESS
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    // Users of one process spread over the places when they wait.
    let prefer = (std::process::id() as usize)
        .wrapping_add(USERS.fetch_add(1, std::sync::atomic::Ordering::Relaxed));
    SetupTurn {
        _machine: muster_shared::ipc::SetupTurn::wait(prefer, SETUP_PATIENCE),
        _process: process,
    }
}

/// How long, at least, a local user waits for its welcome from a broker that is running
/// (it reads the instance's inbox) but has not answered within
/// [`ConnectOptions::wait_for_broker`]: short of descriptors a broker holds a new user's
/// welcome until some of its idle users' ports close.
pub const BUSY_BROKER_WAIT: Duration = Duration::from_secs(30);

/// How to connect.
#[derive(Clone, Debug)]
pub struct ConnectOptions {
    /// How long to wait for a broker before giving up (a running broker that has not
    /// welcomed yet: at least [`BUSY_BROKER_WAIT`]).
    pub wait_for_broker: Duration,
    /// Turn SIGINT/SIGTERM into [`UserError::Interrupted`] (for command-line programs).
    pub handle_signals: bool,
    /// Be woken (a [`UserEvent::ListChanged`]) when the service list changes.
    pub watch_list: bool,
}

impl Default for ConnectOptions {
    fn default() -> Self {
        ConnectOptions {
            wait_for_broker: Duration::from_secs(5),
            handle_signals: true,
            watch_list: false,
        }
    }
}

impl UserClient {
    /// Connects to the broker of `inst`, waiting up to `opts.wait_for_broker` for one.
    pub fn connect(inst: &Instance, opts: &ConnectOptions) -> Result<Self, UserError> {
        Self::connect_as(inst, opts, "u")
    }

    /// [`UserClient::connect`], the user's id starting with `prefix` (`u` by default;
    /// the web console's users are `web-NAME-`, so operators see whose they are).
    pub fn connect_as(
        inst: &Instance,
        opts: &ConnectOptions,
        prefix: &str,
    ) -> Result<Self, UserError> {
        let turn = setup_turn();
        let node = create_node(&format!("muster-user-{}", std::process::id()), false)?;
        let client = Self::local(inst, opts, own_id(prefix), |me| {
            Endpoint::open(inst, me, node)
        })?;
        client.greet(opts, Some(turn), || UserError::NoBroker(inst.to_string()))
    }

    /// [`UserClient::connect_as`] for a user reached at `inbox`, the inbox this
    /// process's users share (see [`ProcessInbox`]): its id is
    /// `PREFIX<n>-<nonce>~<pid>`, and the broker and the systems write to it, and to
    /// the process's other users, through one pair of ports. For a process that hosts
    /// many users (`muster user --count N`).
    pub fn connect_in(
        inst: &Instance,
        opts: &ConnectOptions,
        prefix: &str,
        inbox: &ProcessInbox,
    ) -> Result<Self, UserError> {
        let turn = setup_turn();
        let node = create_node(&format!("muster-user-{}", std::process::id()), false)?;
        let id = shared_id(prefix, inbox);
        let user = id.clone();
        let client = Self::local(inst, opts, id, |_| {
            Endpoint::open_in_process_inbox(inst, user, inbox, node)
        })?;
        client.greet(opts, Some(turn), || UserError::NoBroker(inst.to_string()))
    }

    /// Starts connecting a user that writes to the broker and to systems through
    /// `share`, the ports of this thread's other users (it keeps only its own inbox and
    /// bell), and returns at once with its hello sent: [`UserEvent::Connected`] comes
    /// through [`UserClient::poll`] when a broker welcomes it, now or when one starts.
    /// For a process hosting many users on a few threads (the web console): each
    /// user's descriptors drop from about 48 to about 22–26.
    pub fn start_shared(
        inst: &Instance,
        opts: &ConnectOptions,
        prefix: &str,
        share: &PortShare,
    ) -> Result<Self, UserError> {
        let turn = setup_turn();
        let mut client = Self::local(inst, opts, own_id(prefix), |me| {
            Endpoint::open_shared(inst, me, share)
        })?;
        client.core.hello();
        client.flush();
        drop(turn);
        Ok(client)
    }

    /// A local user `id`, its endpoint made by `open`, not yet greeted.
    fn local(
        inst: &Instance,
        opts: &ConnectOptions,
        id: UserId,
        open: impl FnOnce(Address) -> Result<Endpoint, TransportError>,
    ) -> Result<Self, UserError> {
        let pid = std::process::id();
        let endpoint = open(Address::User(id.clone()))?;
        let presence = Presence::listen(endpoint.node(), inst)?;
        let reactor = Reactor::new()?;
        reactor.add(endpoint.bell_fd(), TOKEN_BELL)?;
        if let Some(fd) = presence.fd() {
            reactor.add(fd, TOKEN_PRESENCE)?;
        }
        let signals = signals_for(&reactor, opts)?;
        Ok(UserClient {
            core: UserCore::new(id, pid, opts.watch_list),
            transport: Transport::Local(Box::new(Local {
                inst: inst.clone(),
                endpoint,
                presence,
                list: None,
                broker: None,
                successor: None,
                fence: None,
                systems: HashMap::new(),
                system_tokens: HashMap::new(),
                next_token: FIRST_SYSTEM_TOKEN,
                to_warm: Vec::new(),
            })),
            reactor,
            signals,
            events: VecDeque::new(),
            extra: None,
            extra_seen: false,
            closed: false,
            list_wait: LIST_WAIT.max(opts.wait_for_broker),
        })
    }

    /// Connects to a broker's UDP front as a remote user, waiting up to
    /// `opts.wait_for_broker` for the handshake and welcome.
    pub fn connect_remote(remote: RemoteOptions, opts: &ConnectOptions) -> Result<Self, UserError> {
        let broker = remote.broker;
        let name = remote.name.clone();
        let link = RemoteLink::new(remote)?;
        let reactor = Reactor::new()?;
        reactor.add(link.fd(), TOKEN_UDP)?;
        let signals = signals_for(&reactor, opts)?;
        let client = UserClient {
            core: UserCore::new(link.user_id(), 0, opts.watch_list),
            transport: Transport::Remote(Box::new(link)),
            reactor,
            signals,
            events: VecDeque::new(),
            extra: None,
            extra_seen: false,
            closed: false,
            list_wait: LIST_WAIT.max(opts.wait_for_broker),
        };
        client.greet(opts, None, || UserError::NoRemoteBroker {
            addr: broker.to_string(),
            name: name.clone(),
        })
    }

    /// Says hello and waits for the welcome. `turn`, this process's setup turn, is let
    /// go once the hello is sent: the ports it needed are open, and the wait is not
    /// made in turn.
    fn greet(
        mut self,
        opts: &ConnectOptions,
        turn: Option<SetupTurn>,
        no_broker: impl Fn() -> UserError,
    ) -> Result<Self, UserError> {
        self.core.hello();
        self.flush();
        drop(turn);
        let started = Instant::now();
        let mut deadline = started + opts.wait_for_broker;
        let mut busy = None;
        // What comes before the welcome (a list bell, say) is kept aside and handed
        // to the caller after it, in order. Put back into `events` at once, `wait`
        // would hand the same event back at once, for ever (seen: a user spinning at
        // 100 % CPU, never connected, its queue growing).
        let mut before = Vec::new();
        while self.core.connected().is_none() {
            match self.wait(deadline)? {
                Wake::Timeout => {
                    // A broker that reads its inbox has the hello: it is there but has
                    // not welcomed yet (short of descriptors, it holds the welcome until
                    // some close; or it is stopped and a standby may take over). Such a
                    // broker is waited for longer, as a busy server's accept would be.
                    let longer = started + opts.wait_for_broker.max(BUSY_BROKER_WAIT);
                    match (busy.take(), self.running_broker()) {
                        (None, Some((inst, pid))) if Instant::now() < longer => {
                            tracing::info!(
                                pid,
                                "the broker is running but has not welcomed this user yet; waiting"
                            );
                            busy = Some((inst, pid));
                            deadline = longer;
                            continue;
                        }
                        // Waited for as long as a running broker is: it is there, but
                        // has not answered.
                        (Some((inst, pid)), _) | (None, Some((inst, pid))) => {
                            self.closed = true;
                            return Err(UserError::BrokerBusy {
                                inst,
                                pid,
                                waited: started.elapsed(),
                            });
                        }
                        // Nobody to say goodbye to.
                        (None, None) => {
                            self.closed = true;
                            return Err(no_broker());
                        }
                    }
                }
                Wake::Event(UserEvent::Connected { .. }) => {}
                Wake::Event(other) => before.push(other),
                Wake::Extra => {}
            }
        }
        for e in before.into_iter().rev() {
            self.events.push_front(e);
        }
        Ok(self)
    }

    /// The instance and pid of the broker reading the instance's inbox (local users
    /// only).
    fn running_broker(&mut self) -> Option<(String, u32)> {
        match &mut self.transport {
            Transport::Local(l) => {
                let pid = l.endpoint.owner_pid(&Address::Broker)?;
                Some((l.inst.to_string(), pid))
            }
            Transport::Remote(_) => None,
        }
    }

    /// Counters of the UDP link (remote users only).
    pub fn link_stats(&self) -> Option<&crate::remote::LinkStats> {
        match &self.transport {
            Transport::Remote(r) => Some(r.stats()),
            Transport::Local(_) => None,
        }
    }

    /// Whether this user reaches the federation over UDP.
    pub fn is_remote(&self) -> bool {
        matches!(self.transport, Transport::Remote(_))
    }

    /// This user's id.
    pub fn id(&self) -> &UserId {
        self.core.id()
    }

    /// The protocol state (sessions, counters, links).
    pub fn core(&self) -> &UserCore {
        &self.core
    }

    /// The newest service list: read in place from shared memory (local), or fetched
    /// from the broker in datagram-sized chunks (remote, waiting up to 5 s).
    pub fn list(&mut self) -> Result<Arc<ServiceListSnapshot>, UserError> {
        match &mut self.transport {
            Transport::Local(l) => {
                let (node, list) = Self::local_list(l)?;
                Ok(list.read_from(node)?)
            }
            Transport::Remote(_) => {
                let (_, l) = self.remote_list(&ListFilter::default(), 0, usize::MAX)?;
                Ok(Arc::from(l))
            }
        }
    }

    /// One page of the list: the services `filter` lets through, from the `offset`th
    /// of them, at most `limit`, with how many it lets through in all. A local user
    /// reads it in place in shared memory (without a filter, only the part the page is
    /// in); a remote user is sent only the page.
    pub fn list_page(
        &mut self,
        filter: &ListFilter,
        offset: usize,
        limit: usize,
    ) -> Result<ListPage, UserError> {
        filter.check().map_err(UserError::BadFilter)?;
        match &mut self.transport {
            Transport::Local(l) => {
                let (node, list) = Self::local_list(l)?;
                Ok(list.page_from(node, filter, offset, limit)?)
            }
            Transport::Remote(_) => {
                let (matching, l) = self.remote_list(filter, offset, limit)?;
                Ok(ListPage {
                    generation: l.generation,
                    epoch: l.epoch,
                    matching: matching as usize,
                    entries: l.entries().to_vec(),
                })
            }
        }
    }

    /// [`UserClient::list_page`] of a [`ListPart`].
    pub fn list_part(&mut self, part: &ListPart) -> Result<ListPage, UserError> {
        self.list_page(&part.filter, part.offset, part.limit)
    }

    /// The local list's reader, opened on first use, and the node it reads with.
    fn local_list(
        l: &mut Local,
    ) -> Result<
        (
            &iceoryx2::node::Node<muster_shared::ipc::Ipc>,
            &mut ListReader,
        ),
        UserError,
    > {
        if l.list.is_none() {
            l.list = Some(ListReader::open(l.endpoint.node(), &l.inst)?);
        }
        Ok((l.endpoint.node(), l.list.as_mut().expect("opened above")))
    }

    /// Asks the broker for a (part of the) list and waits for it.
    fn remote_list(
        &mut self,
        filter: &ListFilter,
        offset: usize,
        limit: usize,
    ) -> Result<(u32, Box<ServiceListSnapshot>), UserError> {
        if let Transport::Remote(r) = &mut self.transport {
            r.ask_list(filter, offset, limit);
        }
        let deadline = Instant::now() + self.list_wait;
        loop {
            if let Transport::Remote(r) = &mut self.transport {
                if let Some(l) = r.take_list() {
                    return Ok(l);
                }
            }
            if Instant::now() >= deadline {
                return Err(UserError::ListTimeout(self.list_wait));
            }
            self.turn(deadline)?;
        }
    }

    /// Asks for a service by id; the answer comes as an event.
    pub fn request(&mut self, id: &ServiceId) -> Result<u64, UserError> {
        let req = self.core.request(id.clone());
        muster_shared::trace::stamp(muster_shared::trace::Stage::UserSend, self.core.id(), req);
        self.flush();
        Ok(req)
    }

    /// An operator's action; the answer comes as [`crate::core::UserEvent::Operated`]
    /// with the number returned.
    pub fn operate(&mut self, op: muster_shared::protocol::Operation) -> u64 {
        let id = self.core.operate(op);
        self.flush();
        id
    }

    /// Watches only the part of the list `filter` lets through (`None`: all of it):
    /// this user's list bell rings only when a service of that part changes, comes or
    /// goes. For a user connected with `watch_list`.
    pub fn watch_part(&mut self, filter: Option<ListFilter>) -> Result<(), UserError> {
        if let Some(f) = &filter {
            f.check().map_err(UserError::BadFilter)?;
        }
        self.core.watch_part(filter);
        self.flush();
        Ok(())
    }

    /// Gives up a pending or queued request.
    pub fn cancel(&mut self, req: u64) {
        self.core.cancel(req);
        self.flush();
    }

    /// Ends a session.
    pub fn end(&mut self, session: SessionId) {
        self.core.end(session);
        self.flush();
    }

    /// Sends task input on a command session.
    pub fn input(&mut self, session: SessionId, payload: Payload) -> Result<(), String> {
        let r = self.core.input(session, payload);
        self.flush();
        r
    }

    /// Links a data service into a command service, after checking kinds and payload types
    /// against the list. Returns the link number.
    pub fn link(&mut self, data: &ServiceId, command: &ServiceId) -> Result<u64, UserError> {
        let list = self.list()?;
        let d = list
            .find(data)
            .ok_or_else(|| UserError::UnknownService(data.0.clone()))?;
        let c = list
            .find(command)
            .ok_or_else(|| UserError::UnknownService(command.0.clone()))?;
        if d.kind() != ServiceKind::Data {
            return Err(UserError::CannotLink(format!(
                "{data} is not a data service"
            )));
        }
        if c.kind() != ServiceKind::Command {
            return Err(UserError::CannotLink(format!(
                "{command} is not a command service"
            )));
        }
        let open = !d.encoding.as_str().is_empty();
        if !link_compatible(d.payload.as_str(), open, c.payload.as_str()) {
            let (dp, cp) = (d.payload.as_str(), c.payload.as_str());
            return Err(UserError::CannotLink(if dp == cp {
                format!(
                    "{data} and {command} both name their payload {dp}, but it is no type \
                     muster carries (a built-in one, or an open payload with its schema): \
                     the values could not be forwarded"
                )
            } else {
                format!("{data} streams {dp} but {command} takes {cp}")
            }));
        }
        let link = self.core.link(data.clone(), command.clone());
        self.flush();
        Ok(link)
    }

    /// Ends a link and its sessions.
    pub fn unlink(&mut self, link: u64) {
        self.core.unlink(link);
        self.flush();
    }

    /// The descriptor of the client's epoll set: readable when something waits for
    /// [`UserClient::wait`] (for a host event loop, such as Python's asyncio, that
    /// watches it and calls `wait` with a deadline of now). A remote client also has
    /// timers: call `wait` by [`UserClient::next_deadline`] even if it stays quiet.
    pub fn fd(&self) -> RawFd {
        self.reactor.raw()
    }

    /// When a remote client's timers (retransmissions, keepalives) next need a turn;
    /// `None` for a local client, which has none.
    pub fn next_deadline(&self) -> Option<Instant> {
        match &self.transport {
            Transport::Remote(r) => Some(r.next_deadline()),
            Transport::Local(_) => None,
        }
    }

    /// Also wake [`UserClient::wait`] when `fd` is readable (e.g. a terminal's input).
    pub fn watch_extra(&mut self, fd: RawFd) -> Result<(), UserError> {
        if let Some(old) = self.extra.take() {
            self.reactor.remove(old);
        }
        self.reactor.add(fd, TOKEN_EXTRA)?;
        self.extra = Some(fd);
        Ok(())
    }

    /// The next event, waiting until `deadline` at most.
    pub fn next_event(&mut self, deadline: Instant) -> Result<Option<UserEvent>, UserError> {
        loop {
            match self.wait(deadline)? {
                Wake::Event(e) => return Ok(Some(e)),
                Wake::Timeout => return Ok(None),
                Wake::Extra => {}
            }
        }
    }

    /// The next event if one is here, without waiting: one look at what arrived (for a
    /// caller with a loop of its own, such as a recorder).
    pub fn try_event(&mut self) -> Result<Option<UserEvent>, UserError> {
        if let Some(e) = self.events.pop_front() {
            return Ok(Some(e));
        }
        self.turn(Instant::now())?;
        Ok(self.events.pop_front())
    }

    /// Waits for an event, the extra fd, or the deadline.
    pub fn wait(&mut self, deadline: Instant) -> Result<Wake, UserError> {
        loop {
            if let Some(e) = self.events.pop_front() {
                return Ok(Wake::Event(e));
            }
            // The extra fd's readiness, seen by a turn made for something else (a
            // remote list, a request): readiness is edge-triggered, so it is kept for
            // the caller here, not lost (a view's key would wait for the next one).
            if std::mem::take(&mut self.extra_seen) {
                return Ok(Wake::Extra);
            }
            if Instant::now() >= deadline {
                return Ok(Wake::Timeout);
            }
            self.warm();
            self.turn(deadline)?;
        }
    }

    /// [`UserClient::wait`] without waiting: what is here now, or [`Wake::Timeout`] when
    /// nothing is. For a caller that drives many clients from one loop, watching each
    /// one's [`UserClient::fd`] and calling this until it says `Timeout` (and again by
    /// [`UserClient::next_turn`]).
    pub fn poll(&mut self) -> Result<Wake, UserError> {
        for first in [true, false] {
            if let Some(e) = self.events.pop_front() {
                return Ok(Wake::Event(e));
            }
            if std::mem::take(&mut self.extra_seen) {
                return Ok(Wake::Extra);
            }
            if first {
                self.warm();
                self.turn(Instant::now())?;
            }
        }
        Ok(Wake::Timeout)
    }

    /// When this client's own timers next need a [`UserClient::poll`] even if its fd
    /// stays quiet: a remote link's retransmissions and keepalives; a local user's
    /// held-back frames, lingering ports, a standby it looks for and systems' inboxes
    /// it opens. `None`: nothing is due. A local user's held-back frames and lingering
    /// ports that are due now are dealt with here.
    pub fn next_turn(&mut self) -> Option<Instant> {
        let now = Instant::now();
        match &mut self.transport {
            Transport::Remote(r) => Some(r.next_deadline()),
            Transport::Local(l) => {
                let sweep = l.endpoint.sweep().map(|d| now + d);
                let successor = l.successor.map(|_| now + SUCCESSOR_POLL);
                let warm = l.to_warm.iter().map(|(_, since)| *since + WARM_AFTER).min();
                [sweep, successor, warm].into_iter().flatten().min()
            }
        }
    }

    /// Nothing for the caller now: open the inboxes of systems that just granted a
    /// session, off the path of the grant itself.
    fn warm(&mut self) {
        if let Transport::Local(l) = &mut self.transport {
            let core = &self.core;
            let heard = |system: &str| {
                core.sessions().any(|(id, service, _)| {
                    service.split().is_some_and(|(s, _)| s == system)
                        && core.counters(id).is_some_and(|c| c.last_seq > 0)
                })
            };
            let (ready, later): (Vec<_>, Vec<_>) = std::mem::take(&mut l.to_warm)
                .into_iter()
                .partition(|(s, since)| heard(s) || since.elapsed() >= WARM_AFTER);
            l.to_warm = later;
            for (system, _) in ready {
                if let Err(e) = l.endpoint.open_ports(&Address::System(system)) {
                    tracing::debug!("{e}");
                }
            }
        }
    }

    /// One wait on the reactor (bounded by `deadline` and the transport's own timers)
    /// and the handling of what woke it. The extra fd's readiness is kept for `wait`
    /// (`extra_seen`), whoever made the turn.
    fn turn(&mut self, deadline: Instant) -> Result<(), UserError> {
        // A remote connection's timers, and what it owes since the last turn (see
        // below), before waiting.
        let news = self.events.len();
        if let Transport::Remote(r) = &mut self.transport {
            r.tick(&mut self.core);
            self.pump()?;
        }
        let now = Instant::now();
        let mut wait = deadline.saturating_duration_since(now);
        if self.events.len() > news {
            // Only a look: the timers made news for the caller.
            wait = Duration::ZERO;
        }
        match &mut self.transport {
            Transport::Local(l) => {
                if let Some(linger) = l.endpoint.sweep() {
                    wait = wait.min(linger);
                }
                if l.successor.is_some() {
                    wait = wait.min(SUCCESSOR_POLL);
                }
            }
            Transport::Remote(r) => {
                wait = wait.min(r.next_deadline().saturating_duration_since(now))
            }
        }
        let tokens = self.reactor.wait(Some(wait))?;
        for t in tokens {
            self.on_token(t)?;
        }
        if let Transport::Local(l) = &mut self.transport {
            l.look_for_successor(&mut self.core, &self.reactor);
        }
        self.pump()?;
        // News for the application (a grant) goes to it before the datagrams the
        // connection owes for it (its acknowledgement, the session's first keepalive):
        // those wake the broker or a system, which on a busy core would run first. They
        // go at the next turn, or with the application's next send.
        if let Transport::Remote(r) = &mut self.transport {
            if self.events.is_empty() {
                r.tick(&mut self.core);
                self.pump()?;
            }
        }
        Ok(())
    }

    fn on_token(&mut self, token: usize) -> Result<(), UserError> {
        match token {
            TOKEN_SIGNAL => {
                if self.signals.as_mut().is_some_and(SignalPipe::drain) {
                    return Err(UserError::Interrupted);
                }
                return Ok(());
            }
            TOKEN_EXTRA => {
                self.extra_seen = true;
                return Ok(());
            }
            _ => {}
        }
        let l = match &mut self.transport {
            Transport::Remote(r) => {
                if token == TOKEN_UDP {
                    r.on_readable(&mut self.core);
                }
                return Ok(());
            }
            Transport::Local(l) => l,
        };
        match token {
            TOKEN_BELL => {
                if l.endpoint.drain_bell() & (1 << bell::LIST_CHANGED) != 0 {
                    self.core.list_changed();
                }
            }
            TOKEN_PRESENCE => {
                let rung = l.presence.drain();
                if rung & (1 << bell::BROKER_DOWN) != 0 {
                    l.lose_broker(&mut self.core, &self.reactor, true);
                }
                if rung & (1 << bell::BROKER_UP) != 0 {
                    // Keep the publisher: the new broker takes over the same inbox.
                    l.lose_broker(&mut self.core, &self.reactor, false);
                    self.core.hello();
                }
                if rung & (1 << bell::TAKEOVER) != 0 {
                    // A standby took over with our state: adopt it (the process that now
                    // owns the broker's inbox) without a hello, repeating what it may
                    // have missed.
                    if let Some(pid) = l.endpoint.owner_pid(&Address::Broker) {
                        l.adopt(&mut self.core, &self.reactor, pid);
                    }
                }
            }
            TOKEN_BROKER => {
                if let Some(dead) = l.broker.as_ref().filter(|p| p.exited()).map(PidFd::pid) {
                    tracing::warn!(
                        "broker died; sessions go on, new requests wait for a new broker"
                    );
                    l.lose_broker(&mut self.core, &self.reactor, true);
                    // With requests out, watch for a standby's takeover rather than wait
                    // for its ring (which reaches every process on the host, in turn).
                    if self.core.awaits_broker() {
                        l.successor = Some((dead, Instant::now()));
                    }
                }
            }
            t => {
                let dead = l
                    .systems
                    .get(&t)
                    .filter(|(_, p)| p.exited())
                    .map(|(s, _)| s.clone());
                if let Some(system) = dead {
                    self.core.system_died(&system);
                    l.unwatch_system(&self.reactor, &system);
                }
            }
        }
        Ok(())
    }

    fn pump(&mut self) -> Result<(), UserError> {
        if let Transport::Local(l) = &mut self.transport {
            while let Some((frame, pid)) = l.endpoint.recv_from() {
                match decode::<ToUser>(&frame) {
                    Ok(msg)
                        if !self
                            .core
                            .sender_allowed(pid, &msg, |a| l.endpoint.owner_pid(a)) => {}
                    Ok(msg) => self.core.handle(msg),
                    Err(e) => muster_shared::protocol::log_bad_frame(&e),
                }
            }
        }
        self.flush();
        while let Some(e) = self.core.poll_event() {
            self.events.push_back(e);
        }
        self.flush();
        Ok(())
    }

    fn flush(&mut self) {
        while let Some(out) = self.core.poll_output() {
            match &mut self.transport {
                Transport::Local(l) => {
                    if let Some(system) = l.apply(&self.reactor, out) {
                        self.core.system_died(&system);
                    }
                }
                Transport::Remote(r) => match out {
                    UserOutput::ToBroker(msg) => r.send_broker(msg),
                    UserOutput::ToSystem(_, msg) => r.send_system(msg),
                    // Liveness over UDP is keepalives and silence, not process watches.
                    UserOutput::WatchBroker(_)
                    | UserOutput::WatchSystem(..)
                    | UserOutput::ForgetSystem(_) => {}
                },
            }
        }
    }

    /// Ends everything and says goodbye (dropping the client does the same).
    pub fn close(mut self) {
        self.goodbye();
    }

    /// Ends everything and says goodbye, keeping the client (its ports and shared
    /// memory) until it is dropped: for a process that removes its files at a time of
    /// its choosing (`muster user` waits for a [`muster_shared::ipc::TeardownTurn`]).
    pub fn goodbye(&mut self) {
        if !self.closed {
            self.shutdown();
            self.closed = true;
        }
    }

    fn shutdown(&mut self) {
        self.core.shutdown();
        self.flush();
        // Over UDP, wait a little for the systems to confirm the ends (they are retried).
        let deadline = Instant::now() + Duration::from_millis(500);
        while matches!(&self.transport, Transport::Remote(r) if r.ending() > 0)
            && Instant::now() < deadline
        {
            if self.turn(deadline).is_err() {
                break;
            }
        }
        if let Transport::Remote(r) = &mut self.transport {
            r.flush_held();
        }
    }
}

/// SIGINT/SIGTERM as a reactor event, if the options ask for it.
fn signals_for(reactor: &Reactor, opts: &ConnectOptions) -> Result<Option<SignalPipe>, UserError> {
    if !opts.handle_signals {
        return Ok(None);
    }
    let s = SignalPipe::install()?;
    reactor.add(s.raw(), TOKEN_SIGNAL)?;
    Ok(Some(s))
}

impl Local {
    /// Carries out one output over shared memory; returns a system found already dead.
    fn apply(&mut self, reactor: &Reactor, out: UserOutput) -> Option<String> {
        match out {
            UserOutput::ToBroker(msg) => self.endpoint.send_control(&Address::Broker, &msg),
            UserOutput::ToSystem(system, msg) => {
                self.endpoint.send_control(&Address::System(system), &msg)
            }
            UserOutput::WatchBroker(pid) => {
                if let Some(p) = self.broker.take() {
                    reactor.remove(p.raw());
                }
                if let Ok(p) = PidFd::open(pid) {
                    if reactor.add(p.raw(), TOKEN_BROKER).is_ok() {
                        self.broker = Some(p);
                    }
                }
            }
            UserOutput::WatchSystem(system, pid) => {
                if self.system_tokens.contains_key(&system) {
                    return None;
                }
                match PidFd::open(pid) {
                    Ok(p) => {
                        let t = self.next_token;
                        self.next_token += 1;
                        if reactor.add(p.raw(), t).is_ok() {
                            self.systems.insert(t, (system.clone(), p));
                            self.system_tokens.insert(system.clone(), t);
                            self.to_warm.push((system, Instant::now()));
                        }
                    }
                    // Gone before we could watch it (but not merely unwatchable).
                    Err(_) if !process_exists(pid) => return Some(system),
                    Err(e) => tracing::warn!("cannot watch system {system} (pid {pid}): {e}"),
                }
            }
            UserOutput::ForgetSystem(system) => {
                self.unwatch_system(reactor, &system);
                self.endpoint.release(&Address::System(system));
            }
        }
        None
    }

    /// Adopts broker `pid`, a standby that took over (unless already adopted).
    fn adopt(&mut self, core: &mut UserCore, reactor: &Reactor, pid: u32) {
        self.successor = None;
        if core.broker_pid() == Some(pid) {
            return;
        }
        if let Some(p) = self.broker.take() {
            reactor.remove(p.raw());
        }
        let epoch = self.broker_epoch();
        core.adopt(epoch, pid);
    }

    /// While waiting for a successor: has a new broker taken the fence and the inbox?
    fn look_for_successor(&mut self, core: &mut UserCore, reactor: &Reactor) {
        let Some((dead, since)) = self.successor else {
            return;
        };
        if since.elapsed() > SUCCESSOR_WAIT {
            self.successor = None;
            return;
        }
        if self.fence.as_ref().is_none_or(|f| f.holder().pid == 0) {
            self.fence = muster_shared::fence::Fence::open_existing(&self.inst).ok();
        }
        let Some(holder) = self.fence.as_ref().map(|f| f.holder().pid) else {
            return;
        };
        if holder != dead && self.endpoint.owner_pid(&Address::Broker) == Some(holder) {
            tracing::info!(pid = holder, "a standby took over: adopting it");
            self.adopt(core, reactor, holder);
        }
    }

    /// The running broker's epoch, as its list says (0 if it cannot be read).
    fn broker_epoch(&mut self) -> u64 {
        if self.list.is_none() {
            self.list = ListReader::open(self.endpoint.node(), &self.inst).ok();
        }
        let node = self.endpoint.node();
        self.list
            .as_mut()
            .and_then(|l| l.read_from(node).ok())
            .map_or(0, |s| s.epoch)
    }

    fn lose_broker(&mut self, core: &mut UserCore, reactor: &Reactor, forget_ports: bool) {
        core.broker_lost();
        if let Some(p) = self.broker.take() {
            reactor.remove(p.raw());
        }
        if forget_ports {
            self.endpoint.forget(&Address::Broker);
        }
    }

    fn unwatch_system(&mut self, reactor: &Reactor, system: &str) {
        if let Some(t) = self.system_tokens.remove(system) {
            if let Some((_, p)) = self.systems.remove(&t) {
                reactor.remove(p.raw());
            }
        }
    }
}

impl Drop for UserClient {
    fn drop(&mut self) {
        self.goodbye();
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn users_of_one_process_wait_for_a_missing_broker_together_not_in_turn() {
        let inst = Instance::new(&format!("setup-turn-{}", std::process::id())).unwrap();
        let opts = ConnectOptions {
            wait_for_broker: Duration::from_millis(800),
            handle_signals: false,
            watch_list: false,
        };
        let started = Instant::now();
        let users: Vec<_> = (0..4)
            .map(|_| {
                let (inst, opts) = (inst.clone(), opts.clone());
                std::thread::spawn(move || UserClient::connect(&inst, &opts).err())
            })
            .collect();
        for u in users {
            let e = u.join().unwrap();
            assert!(
                matches!(e, Some(UserError::NoBroker(ref i)) if *i == inst.to_string()),
                "{e:?}"
            );
        }
        // Each waited its 0.8 s for a broker; made in turn, the four waits would take
        // 3.2 s at least.
        let took = started.elapsed();
        assert!(took >= Duration::from_millis(800), "{took:?}");
        assert!(took < Duration::from_millis(2400), "{took:?}");
    }
}
