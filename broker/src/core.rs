//! The broker's registry and arbitration: a plain struct with no I/O and no clock.
//!
//! Drive it with [`Broker::handle`] (a decoded message), [`Broker::handle_timeout`]
//! (at or after [`Broker::poll_timeout`]), and [`Broker::system_died`] /
//! [`Broker::user_died`] (from process-death detection); collect what it wants sent
//! with [`Broker::poll_output`] and the new list with [`Broker::take_list_change`].
//! Time is a [`Duration`] since any fixed origin the driver chooses.

use muster_shared::protocol::{
    ActiveSession, BrokerEvent, BrokerStatus, LinkInfo, Operation, QueueStatus, SessionDigest,
    SessionLimit, SessionStatus, SystemStatus, ToBroker, ToSystem, ToUser, UserStatus,
    MAX_STATUS_ROWS,
};
use muster_shared::snapshot::{ListFilter, ServiceView, DEFAULT_MAX_SERVICES};
use muster_shared::types::{
    validate_registration, EndReason, Refusal, ServiceId, ServiceKind, ServiceSpec, SessionId,
    UserId,
};
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

/// The broker's tunables.
#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Clone, Debug, PartialEq)]
pub struct BrokerConfig {
    /// How often each system is pinged (paper: 20 s).
    pub ping_interval: Duration,
    /// How long a system has to answer a ping (paper: 10 s).
    pub ping_timeout: Duration,
    /// How long a system has to answer a forwarded request.
    pub offer_timeout: Duration,
    /// Most requests one service's task queue holds.
    pub queue_capacity: u16,
    /// Most links one user may have counted in the list.
    pub max_links_per_user: usize,
    /// Most user ids one local process may hold at once (a gateway such as `muster
    /// web`, one user per person signed in, needs more than the default).
    pub max_users_per_process: usize,
    /// Most services listed at once (a system whose services would take the list past
    /// it is refused); in a federation, the merged list is held to it too.
    pub max_services: usize,
}

impl Default for BrokerConfig {
    fn default() -> Self {
        BrokerConfig {
            ping_interval: Duration::from_secs(20),
            ping_timeout: Duration::from_secs(10),
            offer_timeout: Duration::from_secs(10),
            queue_capacity: 32,
            max_links_per_user: MAX_LINKS_PER_USER,
            max_users_per_process: MAX_USERS_PER_PROCESS,
            max_services: DEFAULT_MAX_SERVICES,
        }
    }
}

impl BrokerConfig {
    /// This configuration on a scenario clock running `scale` times faster than wall
    /// time: pings come `scale` times as often and their deadline shrinks alike (never
    /// under [`muster_shared::clock::MIN_WALL_DEADLINE`]). The offer timeout measures a
    /// system's answer, which is infrastructure, and stays wall time.
    pub fn scaled(self, scale: muster_shared::clock::TimeScale) -> Self {
        BrokerConfig {
            ping_interval: scale.wall(self.ping_interval),
            ping_timeout: scale.wall_deadline(self.ping_timeout),
            ..self
        }
    }
}

/// Default bound on the user ids one local process may hold at once (a process may run
/// a few clients; [`BrokerConfig::max_users_per_process`]).
pub const MAX_USERS_PER_PROCESS: usize = 16;

/// Default bound on the links one user may have counted ([`BrokerConfig::max_links_per_user`]).
pub const MAX_LINKS_PER_USER: usize = 16;

/// What the broker wants done.
#[derive(Clone, Debug, PartialEq)]
pub enum Output {
    /// Send to a system.
    ToSystem(String, ToSystem),
    /// Send to a user.
    ToUser(UserId, ToUser),
    /// Watch this system's process for death.
    WatchSystem {
        /// System name.
        system: String,
        /// Its pid.
        pid: u32,
    },
    /// Stop watching the system; forget its ports.
    ForgetSystem(String),
    /// Watch this user's process for death.
    WatchUser {
        /// User id.
        user: UserId,
        /// Its pid.
        pid: u32,
    },
    /// Stop watching the user; forget its ports.
    ForgetUser(UserId),
    /// The broker granted a user's request (its system was sent the offer just before):
    /// the shell tells the user, over shared memory, UDP or the federation.
    Granted(Grant),
}

/// A grant the broker made ([`Output::Granted`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Grant {
    /// The user.
    pub user: UserId,
    /// Its request number.
    pub req: u64,
    /// The session.
    pub session: SessionId,
    /// The service.
    pub service: ServiceId,
    /// Data or command.
    pub kind: ServiceKind,
    /// Payload type.
    pub payload: String,
    /// An open payload type's schema.
    pub schema: Option<muster_shared::types::Schema>,
    /// The system's pid.
    pub system_pid: u32,
}

impl Grant {
    /// The message that tells its user, from the broker.
    pub fn message(&self) -> ToUser {
        ToUser::Granted {
            req: self.req,
            session: self.session,
            service: self.service.clone(),
            kind: self.kind,
            payload: self.payload.clone(),
            schema: self.schema.clone(),
            system_pid: self.system_pid,
            relayed: true,
        }
    }

    /// The system's name.
    pub fn system(&self) -> Option<String> {
        self.service.split().map(|(s, _)| s.to_string())
    }
}

/// Why a system left the registry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Removal {
    /// It did not answer a ping in time; it is told and may re-register.
    Delinquent,
    /// Its process died.
    Died,
    /// It unregistered.
    Unregistered,
}

/// Counters of what the broker did, for status and stress reports.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct BrokerStats {
    /// Registrations accepted.
    pub registrations: u64,
    /// Times a system's session digest differed from the broker's and its set was asked.
    pub reconciliations: u64,
    /// Local frames refused because their writer spoke for another process.
    pub impersonations: u64,
    /// Answers to an offer from a system it did not go to (ignored).
    pub foreign_answers: u64,
    /// Links not counted: wrong kinds, or over the user's bound.
    pub links_refused: u64,
    /// Registrations refused.
    pub registrations_refused: u64,
    /// Requests received.
    pub requests: u64,
    /// Requests forwarded to systems (immediately or from a queue).
    pub offers: u64,
    /// Requests granted.
    pub grants: u64,
    /// Grants ended because their system could not take them (it refused, did not
    /// answer, or went) before confirming.
    pub grants_undone: u64,
    /// Refusals by reason code.
    pub refusals: BTreeMap<&'static str, u64>,
    /// Requests queued.
    pub queued: u64,
    /// Systems removed as delinquent.
    pub delinquent: u64,
    /// Systems removed because their process died.
    pub died: u64,
    /// Pings sent.
    pub pings: u64,
}

#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug)]
struct SystemRec {
    pid: u32,
    udp: Option<String>,
    services: Vec<String>,
    next_ping: Duration,
    awaiting: Option<(u64, Duration)>,
    sessions: BTreeMap<SessionId, (String, UserId)>,
    /// When it last answered a ping (or registered).
    last_answer: Duration,
    /// Its own limit over all its services, if it set one ([`ToBroker::Limit`]).
    limit: Option<SessionLimit>,
}

#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug, Clone, PartialEq, Eq)]
struct Waiting {
    user: UserId,
    req: u64,
}

#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug)]
struct ServiceRec {
    spec: ServiceSpec,
    system: String,
    withdrawn: bool,
    sessions: BTreeSet<SessionId>,
    pending: u16,
    queue: VecDeque<Waiting>,
    links: u32,
}

impl ServiceRec {
    fn used(&self) -> usize {
        self.sessions.len() + self.pending as usize
    }

    /// What of its row changes without the service being declared anew: sessions in
    /// use, requests queued, links, withdrawn.
    fn counts(&self) -> (u16, u16, u16, bool) {
        let n = |x: usize| u16::try_from(x).unwrap_or(u16::MAX);
        (
            n(self.used()),
            n(self.queue.len()),
            n(self.links as usize),
            self.withdrawn,
        )
    }
}

#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug, Default)]
struct UserRec {
    pid: u32,
    watch_list: bool,
    /// The part of the list it watches (`None`: all of it).
    watch_filter: Option<ListFilter>,
    links: BTreeMap<u64, LinkInfo>,
}

#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug)]
struct Offer {
    user: UserId,
    req: u64,
    service: ServiceId,
    /// The session granted.
    session: SessionId,
    deadline: Duration,
}

/// The broker's registry of systems, services, users and requests.
///
/// Its archived form (rkyv) is the whole state a standby needs: [`crate::replica`]
/// ships it once, then every input ([`Op`]) in order. What it wants sent, its counters
/// and its journal are not state and are not archived.
#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug)]
pub struct Broker {
    cfg: BrokerConfig,
    epoch: u64,
    pid: u32,
    systems: BTreeMap<String, SystemRec>,
    services: BTreeMap<ServiceId, ServiceRec>,
    users: BTreeMap<UserId, UserRec>,
    offers: BTreeMap<u64, Offer>,
    next_ticket: u64,
    next_nonce: u64,
    generation: u64,
    list_dirty: bool,
    /// Bumped when a service comes, goes or is declared anew: what a row says other than
    /// its counts changes only then (see [`Broker::take_list_change_rows`]).
    shape: u64,
    /// Times each system was found delinquent in this run.
    delinquencies: BTreeMap<String, u32>,
    #[rkyv(with = rkyv::with::Skip)]
    out: VecDeque<Output>,
    #[rkyv(with = rkyv::with::Skip)]
    stats: BrokerStats,
    /// Inputs since the last [`Broker::take_journal`], if journaling is on.
    #[rkyv(with = rkyv::with::Skip)]
    journal: Option<Vec<(Duration, Op)>>,
    /// What it did, for the event feed, if asked for ([`Broker::emit_events`]).
    #[rkyv(with = rkyv::with::Skip)]
    events: Option<VecDeque<BrokerEvent>>,
}

/// Most events held for the shell between two [`Broker::poll_event`] sweeps; older ones
/// go first.
const MAX_PENDING_EVENTS: usize = 64 * 1024;

/// Queues an event for the feed, if the feed is on (a field of its own, so that code
/// holding another field of the broker can call it).
fn push_event(events: &mut Option<VecDeque<BrokerEvent>>, e: impl FnOnce() -> BrokerEvent) {
    if let Some(q) = events.as_mut() {
        if q.len() >= MAX_PENDING_EVENTS {
            q.pop_front();
        }
        q.push_back(e());
    }
}

/// One input to the core, as a primary journals it for its standbys: a standby that
/// applies the same inputs in the same order ([`Broker::apply`]) holds the same state.
#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Clone, Debug, PartialEq)]
pub enum Op {
    /// [`Broker::handle`].
    Handle(ToBroker),
    /// [`Broker::handle_timeout`].
    Timeout,
    /// [`Broker::system_died`].
    SystemDied(String),
    /// [`Broker::user_died`].
    UserDied(UserId),
    /// [`Broker::revoke`].
    Revoke(UserId),
    /// [`Broker::take_list_change`] returned a new list.
    ListTaken,
    /// [`Broker::take_over`]: the new run's epoch and the new broker's pid.
    TakeOver(u64, u32),
}

impl Broker {
    /// A broker run numbered `epoch` (distinct per start) in process `pid`.
    pub fn new(cfg: BrokerConfig, epoch: u64, pid: u32) -> Self {
        Broker {
            cfg,
            epoch,
            pid,
            systems: BTreeMap::new(),
            services: BTreeMap::new(),
            users: BTreeMap::new(),
            offers: BTreeMap::new(),
            // Tickets of different broker runs never meet: a late answer crossing a
            // restart matches no offer of the new run.
            next_ticket: (epoch.rotate_left(29) ^ 0x5851_F42D_4C95_7F2D) & (u64::MAX >> 2),
            next_nonce: epoch.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1,
            generation: 0,
            list_dirty: true,
            shape: 0,
            delinquencies: BTreeMap::new(),
            out: VecDeque::new(),
            stats: BrokerStats::default(),
            journal: None,
            events: None,
        }
    }

    /// Starts keeping what it does for [`Broker::poll_event`] (a serving broker's feed).
    pub fn emit_events(&mut self) {
        self.events.get_or_insert_with(VecDeque::new);
    }

    /// The next event for the feed.
    pub fn poll_event(&mut self) -> Option<BrokerEvent> {
        self.events.as_mut()?.pop_front()
    }

    /// Whether events wait for [`Broker::poll_event`].
    pub fn events_waiting(&self) -> bool {
        self.events.as_ref().is_some_and(|e| !e.is_empty())
    }

    fn ev(&mut self, e: impl FnOnce() -> BrokerEvent) {
        push_event(&mut self.events, e);
    }

    /// Starts keeping every input for [`Broker::take_journal`] (a primary with standbys).
    pub fn keep_journal(&mut self) {
        self.journal.get_or_insert_with(Vec::new);
    }

    /// The inputs since the last call, in order (empty unless [`Broker::keep_journal`]).
    pub fn take_journal(&mut self) -> Vec<(Duration, Op)> {
        self.journal
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    }

    fn journal(&mut self, now: Duration, op: impl FnOnce() -> Op) {
        if let Some(j) = self.journal.as_mut() {
            j.push((now, op()));
        }
    }

    /// Applies one journaled input, as the primary did at `now`.
    pub fn apply(&mut self, now: Duration, op: Op) {
        match op {
            Op::Handle(msg) => self.handle(now, msg),
            Op::Timeout => self.handle_timeout(now),
            Op::SystemDied(s) => self.system_died(now, &s),
            Op::UserDied(u) => self.user_died(now, &u),
            Op::Revoke(u) => self.revoke(now, &u),
            Op::ListTaken => {
                self.take_list_change();
            }
            Op::TakeOver(epoch, pid) => self.take_over(now, epoch, pid),
        }
    }

    /// Drops whatever the core wants sent (a standby's copy sends nothing).
    pub fn discard_outputs(&mut self) {
        self.out.clear();
    }

    /// This run's epoch.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// The configuration it runs with.
    pub fn config(&self) -> &BrokerConfig {
        &self.cfg
    }

    /// The whole state in rkyv's archived form (what [`crate::replica`] ships), for
    /// comparing two brokers' states.
    pub fn archived_state(&self) -> Vec<u8> {
        rkyv::to_bytes::<rkyv::rancor::Error>(self)
            .expect("the broker's state always archives")
            .to_vec()
    }

    /// A standby takes over this state as broker run `epoch` in process `pid`.
    ///
    /// Frames the old broker held unread are lost with it, so nothing is taken for
    /// granted: every system is watched again and pinged afresh (a lost pong must not
    /// make it delinquent), every offer still out is sent again with a new deadline (a
    /// lost answer; systems answer a repeated offer with the session they already
    /// granted, never a second one), and the list is written again. Peers adopt the
    /// new broker themselves when it rings the presence event, re-sending their
    /// pending requests and session sets.
    pub fn take_over(&mut self, now: Duration, epoch: u64, pid: u32) {
        self.journal(now, || Op::TakeOver(epoch, pid));
        self.epoch = epoch;
        self.pid = pid;
        for (name, s) in self.systems.iter_mut() {
            s.awaiting = None;
            s.next_ping = now + self.cfg.ping_interval;
            self.out.push_back(Output::WatchSystem {
                system: name.clone(),
                pid: s.pid,
            });
        }
        for (user, u) in &self.users {
            if u.pid != 0 {
                self.out.push_back(Output::WatchUser {
                    user: user.clone(),
                    pid: u.pid,
                });
            }
        }
        // Grants the last primary made that their systems have not confirmed: the
        // offer and the grant again (it may have died between the two). Both sides take
        // a repeat as the same session.
        let tickets: Vec<u64> = self.offers.keys().copied().collect();
        for ticket in tickets {
            if let Some(o) = self.offers.get_mut(&ticket) {
                o.deadline = now + self.cfg.offer_timeout;
            }
            self.send_offer(ticket);
            self.send_grant(ticket);
        }
        self.list_dirty = true;
    }

    /// The next thing to send or do, if any.
    pub fn poll_output(&mut self) -> Option<Output> {
        self.out.pop_front()
    }

    /// How many outputs wait for [`Broker::poll_output`].
    pub fn outputs_waiting(&self) -> usize {
        self.out.len()
    }

    /// Counters so far.
    pub fn stats(&self) -> &BrokerStats {
        &self.stats
    }

    /// Users the broker knows.
    pub fn users(&self) -> impl Iterator<Item = &UserId> {
        self.users.keys()
    }

    /// The process id a user said hello with (0 for a remote user), if it is known.
    pub fn user_pid(&self, user: &UserId) -> Option<u32> {
        self.users.get(user).map(|u| u.pid)
    }

    /// The sessions `user` holds: each with its system and that system's pid.
    pub fn user_sessions(&self, user: &UserId) -> Vec<(SessionId, String, u32)> {
        self.systems
            .iter()
            .flat_map(|(name, s)| {
                s.sessions
                    .iter()
                    .filter(|(_, (_, u))| u == user)
                    .map(move |(id, _)| (*id, name.clone(), s.pid))
            })
            .collect()
    }

    /// Remote users (over UDP: no pid here; their front tracks their liveness).
    pub fn remote_users(&self) -> Vec<UserId> {
        self.users
            .iter()
            .filter(|(_, u)| u.pid == 0)
            .map(|(id, _)| id.clone())
            .collect()
    }

    /// Users who asked to be rung when the list changes.
    pub fn list_watchers(&self) -> impl Iterator<Item = &UserId> {
        self.users
            .iter()
            .filter(|(_, u)| u.watch_list)
            .map(|(id, _)| id)
    }

    /// The users who watch the list, each with the part it watches (`None`: all).
    pub fn list_watchers_with_filters(
        &self,
    ) -> impl Iterator<Item = (&UserId, Option<&ListFilter>)> {
        self.users
            .iter()
            .filter(|(_, u)| u.watch_list)
            .map(|(id, u)| (id, u.watch_filter.as_ref()))
    }

    /// Registered system names.
    pub fn systems(&self) -> impl Iterator<Item = &str> {
        self.systems.keys().map(String::as_str)
    }

    /// If the list changed since the last call: the new generation and rows.
    pub fn take_list_change(&mut self) -> Option<(u64, Vec<ServiceView>)> {
        let mut views = Vec::new();
        self.take_list_change_into(&mut views)
            .map(|generation| (generation, views))
    }

    /// Whether the list changed since it was last taken.
    pub fn list_changed(&self) -> bool {
        self.list_dirty
    }

    /// If the list changed since the last call: the new generation, with `views` made
    /// the new rows (written over in place, see [`Broker::fill_views`]).
    pub fn take_list_change_into(&mut self, views: &mut Vec<ServiceView>) -> Option<u64> {
        let generation = self.next_generation()?;
        self.fill_views(views);
        Some(generation)
    }

    /// If the list changed since it was last taken: a new generation (journaled).
    fn next_generation(&mut self) -> Option<u64> {
        if !self.list_dirty {
            return None;
        }
        self.list_dirty = false;
        self.generation += 1;
        if let Some(j) = self.journal.as_mut() {
            // No clock in this step: the op's time is not used.
            j.push((Duration::ZERO, Op::ListTaken));
        }
        Some(self.generation)
    }

    /// [`Broker::take_list_change_into`] for a caller that keeps `views` (and `shape`,
    /// started at `u64::MAX`) from one call to the next: when no service came, went or
    /// was declared anew since, only each row's counts are looked at, and the rows that
    /// changed are returned (`Some`); otherwise every row is written over (`None`). At
    /// 10,000 services this is the difference between every row's text compared and a
    /// walk over their counts.
    pub fn take_list_change_rows(
        &mut self,
        views: &mut Vec<ServiceView>,
        shape: &mut u64,
    ) -> Option<(u64, Option<Vec<usize>>)> {
        if *shape != self.shape || views.len() != self.services.len() {
            let generation = self.take_list_change_into(views)?;
            *shape = self.shape;
            return Some((generation, None));
        }
        let generation = self.next_generation()?;
        let mut rows = Vec::new();
        for (i, (v, s)) in views.iter_mut().zip(self.services.values()).enumerate() {
            let counts = s.counts();
            if (v.in_use, v.queued, v.links, v.withdrawn) != counts {
                (v.in_use, v.queued, v.links, v.withdrawn) = counts;
                rows.push(i);
            }
        }
        Some((generation, Some(rows)))
    }

    /// The current list, in id order.
    pub fn views(&self) -> Vec<ServiceView> {
        let mut views = Vec::new();
        self.fill_views(&mut views);
        views
    }

    /// Makes `views` the current list, in id order, writing over its rows: a row whose
    /// text is unchanged (counts change, on every grant and end) allocates nothing.
    fn fill_views(&self, views: &mut Vec<ServiceView>) {
        fn set(dst: &mut String, src: &str) {
            if dst != src {
                src.clone_into(dst);
            }
        }
        views.truncate(self.services.len());
        views.resize_with(self.services.len(), ServiceView::default);
        for (v, (id, s)) in views.iter_mut().zip(&self.services) {
            set(&mut v.id, &id.0);
            set(&mut v.system, &s.system);
            set(&mut v.name, &s.spec.name);
            set(&mut v.description, &s.spec.description);
            set(&mut v.kind, s.spec.kind.as_str());
            set(&mut v.payload, &s.spec.payload);
            set(
                &mut v.encoding,
                s.spec
                    .schema
                    .as_ref()
                    .map_or("", |sc| sc.encoding.message_encoding()),
            );
            v.queue = s.spec.queue;
            v.quota = s.spec.quota;
            (v.in_use, v.queued, v.links, v.withdrawn) = s.counts();
            v.host.clear();
            v.remote = false;
        }
    }

    /// When [`Broker::handle_timeout`] must next be called, if ever.
    pub fn poll_timeout(&self) -> Option<Duration> {
        let pings = self.systems.values().map(|s| match s.awaiting {
            Some((_, deadline)) => deadline,
            None => s.next_ping,
        });
        let offers = self.offers.values().map(|o| o.deadline);
        pings.chain(offers).min()
    }

    /// Whether a local frame written by process `pid` may say `msg`: a process speaks
    /// only as itself. It registers or says hello with its own pid (and as a user whose
    /// id names a process's shared inbox only if it is that process), and speaks for a
    /// system or user only if that system or user is its own (the registry's pid). A
    /// refused frame is counted and logged (1st, 2nd, 4th, ...); `None` (the transport
    /// could not tell the writer) is let through.
    pub fn sender_allowed(&mut self, pid: Option<u32>, msg: &ToBroker) -> bool {
        let Some(pid) = pid else { return true };
        let ok = match msg {
            ToBroker::Register { pid: claimed, .. } => *claimed == pid,
            ToBroker::Hello {
                user, pid: claimed, ..
            } => {
                let others_of_pid = self
                    .users
                    .iter()
                    .filter(|(u, r)| r.pid == pid && *u != user)
                    .count();
                // A user reached at a process's shared inbox is that process's.
                *claimed == pid
                    && user.process_inbox().is_none_or(|p| p == pid)
                    && self.users.get(user).is_none_or(|r| r.pid == pid)
                    && others_of_pid < self.cfg.max_users_per_process
            }
            ToBroker::Pong { system, .. }
            | ToBroker::OfferAnswer { system, .. }
            | ToBroker::Limit { system, .. }
            | ToBroker::SessionEnded { system, .. }
            | ToBroker::Withdraw { system, .. }
            | ToBroker::Restore { system, .. }
            | ToBroker::Unregister { system, .. }
            | ToBroker::Sessions { system, .. } => {
                self.systems.get(system).is_none_or(|s| s.pid == pid)
            }
            // A value kept for the system's new sessions: from the system registered.
            ToBroker::Latest { system, .. } => {
                self.systems.get(system).is_some_and(|s| s.pid == pid)
            }
            ToBroker::Request { user, .. }
            | ToBroker::Cancel { user, .. }
            | ToBroker::LinkOpened { user, .. }
            | ToBroker::LinkClosed { user, .. }
            | ToBroker::Operate { user, .. }
            | ToBroker::WatchList { user, .. }
            | ToBroker::Goodbye { user } => self.users.get(user).is_none_or(|u| u.pid == pid),
        };
        muster_shared::protocol::note_impersonation(
            ok,
            &mut self.stats.impersonations,
            pid,
            msg.kind(),
        )
    }

    /// Handles one message.
    pub fn handle(&mut self, now: Duration, msg: ToBroker) {
        if matches!(msg, ToBroker::Latest { .. }) {
            // A latched value is the shell's to keep (`run::latched`), not state.
            return;
        }
        self.journal(now, || Op::Handle(msg.clone()));
        match msg {
            ToBroker::Register {
                system,
                pid,
                services,
                sessions,
                udp,
            } => self.register(now, system, pid, services, sessions, udp),
            ToBroker::Pong {
                system,
                nonce,
                held,
            } => self.pong(now, &system, nonce, held),
            ToBroker::Sessions { system, sessions } => self.reconcile(now, &system, sessions),
            ToBroker::OfferAnswer {
                system,
                ticket,
                answer,
            } => self.offer_answer(now, &system, ticket, answer),
            ToBroker::SessionEnded { system, session } => self.session_ended(now, &system, session),
            ToBroker::Withdraw { system, service } => self.set_withdrawn(&system, &service, true),
            ToBroker::Restore { system, service } => {
                self.set_withdrawn(&system, &service, false);
                let id = ServiceId::new(&system, &service);
                self.dispatch_queue(now, &id);
            }
            ToBroker::Limit { system, limit } => self.set_limit(now, &system, limit),
            ToBroker::Latest { .. } => {}
            ToBroker::Unregister { system } => {
                if self.systems.contains_key(&system) {
                    self.remove_system(&system, Removal::Unregistered);
                }
            }
            ToBroker::Hello {
                user,
                pid,
                links,
                watch_list,
            } => self.hello(user, pid, links, watch_list),
            ToBroker::Request { user, req, service } => self.request(now, user, req, service),
            ToBroker::Cancel { user, req } => self.cancel(now, &user, req),
            ToBroker::LinkOpened { user, link } => self.link_opened(&user, link),
            ToBroker::LinkClosed { user, link } => {
                if let Some(old) = self
                    .users
                    .get_mut(&user)
                    .and_then(|u| u.links.remove(&link))
                {
                    self.count_link(&old, false);
                    self.ev(|| BrokerEvent::LinkClosed { user, link });
                }
            }
            ToBroker::Goodbye { user } => self.forget_user(now, &user),
            ToBroker::WatchList { user, filter } => {
                if let Some(u) = self.users.get_mut(&user) {
                    u.watch_filter = filter.filter(|f| !f.is_everything());
                }
            }
            ToBroker::Operate { user, id, op } => self.operate(now, user, id, op),
        }
    }

    /// An operator's action (the shell let through operators only).
    fn operate(&mut self, now: Duration, user: UserId, id: u64, op: Operation) {
        // A status read changes nothing: it is not told on the feed.
        let what = (!matches!(op, Operation::Status)).then(|| op.to_string());
        let result = self.try_operate(now, op);
        if let Some(what) = what {
            self.ev(|| BrokerEvent::Operated {
                user: user.clone(),
                op: what,
                error: result.as_ref().err().cloned(),
            });
        }
        self.out
            .push_back(Output::ToUser(user, ToUser::Operated { id, result }));
    }

    fn try_operate(
        &mut self,
        now: Duration,
        op: Operation,
    ) -> Result<Option<Box<BrokerStatus>>, String> {
        match op {
            Operation::Status => return Ok(Some(Box::new(self.status(now)))),
            Operation::Withdraw { service: id } | Operation::Restore { service: id }
                if !self.services.contains_key(&id) =>
            {
                return Err(format!("no service {id}"));
            }
            Operation::Withdraw { service } => {
                let (system, name) = service.split().ok_or("a service id is system/name")?;
                self.set_withdrawn(system, name, true);
            }
            Operation::Restore { service } => {
                let (system, name) = service.split().ok_or("a service id is system/name")?;
                self.set_withdrawn(system, name, false);
                self.dispatch_queue(now, &service);
            }
            Operation::EndSession { session } => {
                let system = self
                    .systems
                    .iter()
                    .find(|(_, s)| s.sessions.contains_key(&session))
                    .map(|(n, _)| n.clone())
                    .ok_or_else(|| format!("no session {:016x}", session.0))?;
                self.out.push_back(Output::ToSystem(
                    system,
                    ToSystem::Terminate {
                        session,
                        reason: "ended by an operator".into(),
                    },
                ));
            }
            Operation::DropUser { user } => {
                if !self.users.contains_key(&user) {
                    return Err(format!("no user {user}"));
                }
                self.revoke(now, &user);
            }
            Operation::MoveRequest {
                service,
                user,
                req,
                position,
            } => {
                let w = self.take_waiting(&service, &user, req)?;
                let svc = self.services.get_mut(&service).ok_or("gone")?;
                let to = usize::from(position.max(1) - 1).min(svc.queue.len());
                svc.queue.insert(to, w);
                self.announce_positions(&service);
            }
            Operation::DropRequest { service, user, req } => {
                self.take_waiting(&service, &user, req)?;
                self.refuse(&user, req, Refusal::ByOperator);
                self.announce_positions(&service);
            }
        }
        Ok(None)
    }

    /// Takes request `req` of `user` out of `service`'s task queue.
    fn take_waiting(
        &mut self,
        service: &ServiceId,
        user: &UserId,
        req: u64,
    ) -> Result<Waiting, String> {
        let svc = self
            .services
            .get_mut(service)
            .ok_or_else(|| format!("no service {service}"))?;
        let at = svc
            .queue
            .iter()
            .position(|w| w.user == *user && w.req == req)
            .ok_or_else(|| format!("no request {req} of {user} waits for {service}"))?;
        self.list_dirty = true;
        svc.queue.remove(at).ok_or_else(|| "gone".into())
    }

    /// The state an operator sees.
    pub fn status(&self, now: Duration) -> BrokerStatus {
        let systems = self
            .systems
            .iter()
            .map(|(name, s)| SystemStatus {
                name: name.clone(),
                pid: s.pid,
                services: s.services.clone(),
                sessions: s.sessions.len(),
                last_answer_ms: Some(
                    u64::try_from(now.saturating_sub(s.last_answer).as_millis())
                        .unwrap_or(u64::MAX),
                ),
                ping_outstanding: s.awaiting.is_some(),
                delinquencies: self.delinquencies.get(name).copied().unwrap_or(0),
                udp: s.udp.clone(),
            })
            .collect();
        let users = self
            .users
            .iter()
            .take(MAX_STATUS_ROWS)
            .map(|(u, r)| UserStatus {
                user: u.clone(),
                pid: r.pid,
                links: r.links.values().cloned().collect(),
            })
            .collect();
        let all_sessions = self.systems.iter().flat_map(|(system, s)| {
            s.sessions
                .iter()
                .map(move |(id, (service, user))| SessionStatus {
                    session: *id,
                    service: ServiceId::new(system, service),
                    user: user.clone(),
                })
        });
        let sessions_total = self.systems.values().map(|s| s.sessions.len()).sum();
        let queues = self
            .services
            .iter()
            .filter(|(_, s)| !s.queue.is_empty())
            .map(|(id, s)| QueueStatus {
                service: id.clone(),
                waiting: s.queue.iter().map(|w| (w.user.clone(), w.req)).collect(),
            })
            .collect();
        BrokerStatus {
            epoch: self.epoch,
            systems,
            users,
            users_total: self.users.len(),
            sessions: all_sessions.take(MAX_STATUS_ROWS).collect(),
            sessions_total,
            queues,
            handling: Vec::new(),
        }
    }

    /// Where system `system`'s UDP endpoint listens, if it registered one.
    pub fn system_udp(&self, system: &str) -> Option<&str> {
        self.systems.get(system).and_then(|s| s.udp.as_deref())
    }

    /// Runs due pings, delinquency checks and offer timeouts.
    pub fn handle_timeout(&mut self, now: Duration) {
        self.journal(now, || Op::Timeout);
        let mut delinquent = Vec::new();
        for (name, s) in self.systems.iter_mut() {
            match s.awaiting {
                Some((_, deadline)) if now >= deadline => delinquent.push(name.clone()),
                None if now >= s.next_ping => {
                    let nonce = self.next_nonce;
                    self.next_nonce = self.next_nonce.wrapping_add(2);
                    s.awaiting = Some((nonce, now + self.cfg.ping_timeout));
                    self.stats.pings += 1;
                    self.out
                        .push_back(Output::ToSystem(name.clone(), ToSystem::Ping { nonce }));
                }
                _ => {}
            }
        }
        for name in delinquent {
            tracing::warn!(system = %name, "no answer to ping: delinquent, removed");
            self.remove_system(&name, Removal::Delinquent);
        }
        let expired: Vec<u64> = self
            .offers
            .iter()
            .filter(|(_, o)| now >= o.deadline)
            .map(|(t, _)| *t)
            .collect();
        for ticket in expired {
            if let Some(offer) = self.offers.remove(&ticket) {
                self.release_pending(&offer.service);
                // It may yet open the session: it is told to end it.
                if let Some(svc) = self.services.get(&offer.service) {
                    self.out.push_back(Output::ToSystem(
                        svc.system.clone(),
                        ToSystem::Terminate {
                            session: offer.session,
                            reason: "not confirmed in time".into(),
                        },
                    ));
                }
                let reason = EndReason::BySystem("the system did not answer".into());
                self.undo_grant(&offer, reason);
                self.dispatch_queue(now, &offer.service);
            }
        }
    }

    /// A system's process died: remove it at once, without waiting for a ping.
    pub fn system_died(&mut self, now: Duration, system: &str) {
        self.journal(now, || Op::SystemDied(system.to_string()));
        if self.systems.contains_key(system) {
            tracing::warn!(%system, "system process died: removed");
            self.remove_system(system, Removal::Died);
        }
    }

    /// A user's process died: drop its queued requests and links.
    pub fn user_died(&mut self, now: Duration, user: &UserId) {
        self.journal(now, || Op::UserDied(user.clone()));
        self.forget_user(now, user);
    }

    /// A user's access was revoked: every system holding a session of it is told to end
    /// them (a remote user's sessions run straight with systems, past the broker), and
    /// the user is forgotten.
    pub fn revoke(&mut self, now: Duration, user: &UserId) {
        self.journal(now, || Op::Revoke(user.clone()));
        let systems: Vec<String> = self
            .systems
            .iter()
            .filter(|(_, s)| s.sessions.values().any(|(_, u)| u == user))
            .map(|(name, _)| name.clone())
            .collect();
        for system in systems {
            self.out.push_back(Output::ToSystem(
                system,
                ToSystem::Revoked { user: user.clone() },
            ));
        }
        self.forget_user(now, user);
    }

    fn register(
        &mut self,
        now: Duration,
        system: String,
        pid: u32,
        services: Vec<ServiceSpec>,
        sessions: Vec<ActiveSession>,
        udp: Option<String>,
    ) {
        if let Err(e) = validate_registration(&system, &services) {
            return self.refuse_registration(&system, e.to_string());
        }
        if let Some(old) = self.systems.get(&system) {
            if old.pid != pid {
                let reason = format!("system name {system:?} is held by live process {}", old.pid);
                return self.refuse_registration(&system, reason);
            }
        }
        let others: usize = self
            .systems
            .iter()
            .filter(|(n, _)| **n != system)
            .map(|(_, s)| s.services.len())
            .sum();
        let max = self.cfg.max_services;
        if others + services.len() > max {
            let reason = format!(
                "service list full: {others} services listed, {} more asked, at most {max}",
                services.len()
            );
            return self.refuse_registration(&system, reason);
        }
        // Drop services the system no longer declares.
        let new_names: BTreeSet<&str> = services.iter().map(|s| s.name.as_str()).collect();
        let dropped: Vec<ServiceId> = self
            .systems
            .get(&system)
            .map(|s| {
                s.services
                    .iter()
                    .filter(|n| !new_names.contains(n.as_str()))
                    .map(|n| ServiceId::new(&system, n))
                    .collect()
            })
            .unwrap_or_default();
        for id in dropped {
            self.drop_service(&id, Refusal::Unknown);
        }
        let mut rec = SystemRec {
            pid,
            udp,
            services: services.iter().map(|s| s.name.clone()).collect(),
            next_ping: now + self.cfg.ping_interval,
            awaiting: None,
            sessions: BTreeMap::new(),
            last_answer: now,
            limit: None,
        };
        self.shape += 1;
        for spec in services {
            let id = ServiceId::new(&system, &spec.name);
            match self.services.get_mut(&id) {
                Some(s) => {
                    s.spec = spec;
                    s.withdrawn = false;
                    s.sessions.clear();
                }
                None => {
                    self.services.insert(
                        id,
                        ServiceRec {
                            spec,
                            system: system.clone(),
                            withdrawn: false,
                            sessions: BTreeSet::new(),
                            pending: 0,
                            queue: VecDeque::new(),
                            links: 0,
                        },
                    );
                }
            }
        }
        let (sessions, orphans) = self.split_unrelayable(sessions);
        for a in sessions {
            let id = ServiceId::new(&system, &a.service);
            if let Some(s) = self.services.get_mut(&id) {
                s.sessions.insert(a.session);
                rec.sessions.insert(a.session, (a.service, a.user));
            }
        }
        self.ev(|| BrokerEvent::Registered {
            system: system.clone(),
            services: rec.services.to_vec(),
        });
        self.systems.insert(system.clone(), rec);
        self.stats.registrations += 1;
        self.recount_links();
        self.list_dirty = true;
        self.out.push_back(Output::WatchSystem {
            system: system.clone(),
            pid,
        });
        self.out.push_back(Output::ToSystem(
            system.clone(),
            ToSystem::Registered {
                epoch: self.epoch,
                broker_pid: self.pid,
            },
        ));
        // Told once it is registered.
        self.end_unrelayable(&system, orphans);
    }

    fn refuse_registration(&mut self, system: &str, reason: String) {
        tracing::warn!(%system, %reason, "registration refused");
        self.stats.registrations_refused += 1;
        self.ev(|| BrokerEvent::RegistrationRefused {
            system: system.to_string(),
            reason: reason.clone(),
        });
        self.out.push_back(Output::ToSystem(
            system.to_string(),
            ToSystem::RegistrationRefused { reason },
        ));
    }

    fn pong(&mut self, now: Duration, system: &str, nonce: u64, held: Option<SessionDigest>) {
        match self.systems.get_mut(system) {
            Some(s) => {
                if matches!(s.awaiting, Some((n, _)) if n == nonce) {
                    s.awaiting = None;
                    s.next_ping = now + self.cfg.ping_interval;
                    s.last_answer = now;
                }
                let mine = SessionDigest::of(s.sessions.keys().copied());
                if held.is_some_and(|h| h != mine) {
                    // A control frame was lost somewhere: the system's set is the truth.
                    self.stats.reconciliations += 1;
                    self.out.push_back(Output::ToSystem(
                        system.to_string(),
                        ToSystem::ReportSessions,
                    ));
                }
            }
            // Found alive after removal: tell it, so it re-registers.
            None => self
                .out
                .push_back(Output::ToSystem(system.to_string(), ToSystem::Delinquent)),
        }
    }

    fn offer_answer(
        &mut self,
        now: Duration,
        system: &str,
        ticket: u64,
        answer: Result<SessionId, String>,
    ) {
        // Only the system the offer went to may answer it.
        if self
            .offers
            .get(&ticket)
            .is_some_and(|o| o.service.split().is_none_or(|(s, _)| s != system))
        {
            self.stats.foreign_answers += 1;
            tracing::warn!(
                system,
                ticket,
                "an answer to another system's offer: ignored"
            );
            return;
        }
        let Some(o) = self.offers.remove(&ticket) else {
            // A late confirmation: the grant ended (its offer timed out, or a repeat of
            // it was refused) and its user was told. The system is told to end the
            // session, unless it is one counted (a repeat of a confirmed offer).
            if let Ok(session) = answer {
                let counted = self
                    .systems
                    .get(system)
                    .is_some_and(|s| s.sessions.contains_key(&session));
                if !counted {
                    self.out.push_back(Output::ToSystem(
                        system.to_string(),
                        ToSystem::Terminate {
                            session,
                            reason: "its grant has ended".into(),
                        },
                    ));
                }
            }
            return;
        };
        self.release_pending(&o.service);
        match answer {
            Ok(session) => {
                muster_shared::trace::stamp(
                    muster_shared::trace::Stage::BrokerAnswer,
                    &o.user,
                    o.req,
                );
                if session != o.session {
                    // It holds this request under another number (opened before this
                    // broker's rule): its set is the truth, and the user's grant is void.
                    tracing::warn!(
                        system,
                        granted = %o.session,
                        held = %session,
                        "a grant confirmed under another session"
                    );
                    self.undo_grant(
                        &o,
                        EndReason::BySystem(
                            "the system holds this request under another session".into(),
                        ),
                    );
                }
                if let (Some(svc), Some(sys)) = (
                    self.services.get_mut(&o.service),
                    self.systems.get_mut(system),
                ) {
                    svc.sessions.insert(session);
                    sys.sessions
                        .insert(session, (svc.spec.name.clone(), o.user.clone()));
                }
                self.list_dirty = true;
            }
            Err(reason) => {
                self.undo_grant(&o, EndReason::BySystem(reason));
                self.dispatch_queue(now, &o.service);
            }
        }
    }

    /// Ends a grant its system did not take: the user is told why.
    fn undo_grant(&mut self, o: &Offer, reason: EndReason) {
        self.stats.grants_undone += 1;
        self.ev(|| BrokerEvent::SessionEnded {
            service: o.service.clone(),
            session: o.session,
        });
        self.out.push_back(Output::ToUser(
            o.user.clone(),
            ToUser::Ended {
                session: o.session,
                reason,
                last_seq: 0,
            },
        ));
    }

    /// A system's own limit over all its services: requests beyond it are refused here,
    /// with its reason; sessions it holds beyond it go on.
    fn set_limit(&mut self, now: Duration, system: &str, limit: Option<SessionLimit>) {
        let Some(sys) = self.systems.get_mut(system) else {
            return;
        };
        let raised = match (&sys.limit, &limit) {
            (_, None) => true,
            (None, Some(_)) => false,
            (Some(a), Some(b)) => b.sessions > a.sessions,
        };
        sys.limit = limit;
        if raised {
            self.dispatch_system_queues(now, system);
        }
    }

    /// Moves the queues of every service of `system` (a place under its own limit
    /// serves any of them).
    fn dispatch_system_queues(&mut self, now: Duration, system: &str) {
        let ids: Vec<ServiceId> = self
            .systems
            .get(system)
            .map(|s| {
                s.services
                    .iter()
                    .map(|n| ServiceId::new(system, n))
                    .collect()
            })
            .unwrap_or_default();
        for id in ids {
            self.dispatch_queue(now, &id);
        }
    }

    /// Why `system` takes no more sessions now, if its own limit is reached (its
    /// sessions and the grants it has not confirmed yet).
    fn over_limit(&self, system: &str) -> Option<String> {
        let sys = self.systems.get(system)?;
        let limit = sys.limit.as_ref()?;
        let unconfirmed = sys
            .services
            .iter()
            .filter_map(|n| self.services.get(&ServiceId::new(system, n)))
            .map(|s| s.pending as usize)
            .sum::<usize>();
        (sys.sessions.len() + unconfirmed >= limit.sessions as usize).then(|| limit.reason.clone())
    }

    /// Makes the broker's sessions of `system` the system's own set: sessions it no
    /// longer holds free their quota (and move queues), sessions it holds that the broker
    /// missed are counted.
    fn reconcile(&mut self, now: Duration, system: &str, sessions: Vec<ActiveSession>) {
        let Some(sys) = self.systems.get(system) else {
            return;
        };
        let theirs: BTreeMap<SessionId, ActiveSession> =
            sessions.into_iter().map(|a| (a.session, a)).collect();
        let gone: Vec<SessionId> = sys
            .sessions
            .keys()
            .filter(|id| !theirs.contains_key(id))
            .copied()
            .collect();
        let missed: Vec<ActiveSession> = theirs
            .into_values()
            .filter(|a| !sys.sessions.contains_key(&a.session))
            .collect();
        if !gone.is_empty() || !missed.is_empty() {
            tracing::warn!(
                system,
                freed = gone.len(),
                counted = missed.len(),
                "sessions reconciled with the system's own set"
            );
        }
        let (missed, orphans) = self.split_unrelayable(missed);
        self.end_unrelayable(system, orphans);
        for a in missed {
            let id = ServiceId::new(system, &a.service);
            let Some(svc) = self.services.get_mut(&id) else {
                continue;
            };
            svc.sessions.insert(a.session);
            if let Some(sys) = self.systems.get_mut(system) {
                sys.sessions.insert(a.session, (a.service, a.user));
            }
            self.list_dirty = true;
        }
        for session in gone {
            self.session_ended(now, system, session);
        }
    }

    /// `sessions` split: those this broker can count, and those of other hosts' users it
    /// does not serve (it started cold, without its predecessor's state), which cannot
    /// be relayed ([`Broker::end_unrelayable`]).
    fn split_unrelayable(
        &self,
        sessions: Vec<ActiveSession>,
    ) -> (Vec<ActiveSession>, Vec<ActiveSession>) {
        sessions
            .into_iter()
            .partition(|a| !a.relayed || self.users.contains_key(&a.user))
    }

    /// Tells `system` to end the sessions of users it cannot be relayed to.
    fn end_unrelayable(&mut self, system: &str, orphans: Vec<ActiveSession>) {
        let users: BTreeSet<UserId> = orphans.into_iter().map(|a| a.user).collect();
        for user in users {
            self.out.push_back(Output::ToSystem(
                system.to_string(),
                ToSystem::Revoked { user },
            ));
        }
    }

    fn session_ended(&mut self, now: Duration, system: &str, session: SessionId) {
        let Some(sys) = self.systems.get_mut(system) else {
            return;
        };
        let Some((service, _user)) = sys.sessions.remove(&session) else {
            return;
        };
        let id = ServiceId::new(system, &service);
        if let Some(svc) = self.services.get_mut(&id) {
            svc.sessions.remove(&session);
        }
        self.ev(|| BrokerEvent::SessionEnded {
            service: id.clone(),
            session,
        });
        self.list_dirty = true;
        self.dispatch_queue(now, &id);
        // A system with a limit of its own over all its services frees a place for any.
        if self.systems.get(system).is_some_and(|s| s.limit.is_some()) {
            self.dispatch_system_queues(now, system);
        }
    }

    fn set_withdrawn(&mut self, system: &str, service: &str, withdrawn: bool) {
        let id = ServiceId::new(system, service);
        let Some(svc) = self.services.get_mut(&id) else {
            return;
        };
        if svc.withdrawn == withdrawn {
            return;
        }
        svc.withdrawn = withdrawn;
        self.list_dirty = true;
        push_event(&mut self.events, || BrokerEvent::Withdrawn {
            service: id.clone(),
            withdrawn,
        });
        if withdrawn {
            let waiting: Vec<Waiting> = svc.queue.drain(..).collect();
            for w in waiting {
                self.refuse(&w.user, w.req, Refusal::Withdrawn);
            }
        }
    }

    fn hello(&mut self, user: UserId, pid: u32, links: Vec<LinkInfo>, watch_list: bool) {
        if !self.users.contains_key(&user) {
            self.ev(|| BrokerEvent::UserJoined { user: user.clone() });
        }
        let rec = self.users.entry(user.clone()).or_default();
        rec.pid = pid;
        rec.watch_list = watch_list;
        rec.watch_filter = None;
        let old = std::mem::take(&mut rec.links);
        for l in old.values() {
            self.count_link(l, false);
        }
        for l in links {
            self.link_opened(&user, l);
        }
        // pid 0: a remote user, whose liveness its transport tracks.
        if pid != 0 {
            self.out.push_back(Output::WatchUser {
                user: user.clone(),
                pid,
            });
        }
        self.out.push_back(Output::ToUser(
            user,
            ToUser::Welcome {
                epoch: self.epoch,
                broker_pid: self.pid,
            },
        ));
    }

    fn request(&mut self, now: Duration, user: UserId, req: u64, service: ServiceId) {
        self.stats.requests += 1;
        self.ev(|| BrokerEvent::Requested {
            user: user.clone(),
            req,
            service: service.clone(),
        });
        if !self.users.contains_key(&user) {
            // Unknown (never said hello) or known dead: nobody could watch it, so a
            // session granted to it might never end.
            let reason = Refusal::BadRequest("unknown user: say hello first".into());
            return self.refuse(&user, req, reason);
        }
        let Some(svc) = self.services.get(&service) else {
            return self.refuse(&user, req, Refusal::Unknown);
        };
        if svc.withdrawn {
            return self.refuse(&user, req, Refusal::Withdrawn);
        }
        // The same request again (the user reconnected, or its retry crossed our
        // answer): the answer on its way covers it; a queued one hears its place again.
        if let Some(i) = svc
            .queue
            .iter()
            .position(|w| w.user == user && w.req == req)
        {
            let position = u16::try_from(i + 1).unwrap_or(u16::MAX);
            self.out
                .push_back(Output::ToUser(user, ToUser::Queued { req, position }));
            return;
        }
        if let Some(ticket) = self
            .offers
            .iter()
            .find(|(_, o)| o.user == user && o.req == req && o.service == service)
            .map(|(t, _)| *t)
        {
            return self.send_grant(ticket);
        }
        // (A grant its system has not confirmed yet is a session the user holds, like
        // any other: no bar to asking again.)
        let already = svc.queue.iter().any(|w| w.user == user);
        if already {
            return self.refuse(&user, req, Refusal::AlreadyPending);
        }
        let quota = svc.spec.quota;
        let room = svc.used() < quota as usize;
        let over_limit = self.over_limit(&svc.system);
        if room && svc.queue.is_empty() && over_limit.is_none() {
            return self.offer(now, user, req, service);
        }
        if !svc.spec.queue {
            let reason = match over_limit {
                Some(reason) if room => Refusal::SystemRefused(reason),
                _ => Refusal::QuotaFull { quota },
            };
            return self.refuse(&user, req, reason);
        }
        // A task queue waits out the quota and the system's own limit alike.
        let waiting = svc.queue.len();
        if waiting >= self.cfg.queue_capacity as usize {
            let waiting = u16::try_from(waiting).unwrap_or(u16::MAX);
            return self.refuse(&user, req, Refusal::QueueFull { waiting });
        }
        let svc = self.services.get_mut(&service).expect("checked above");
        svc.queue.push_back(Waiting {
            user: user.clone(),
            req,
        });
        let position = u16::try_from(svc.queue.len()).unwrap_or(u16::MAX);
        self.stats.queued += 1;
        push_event(&mut self.events, || BrokerEvent::Queued {
            user: user.clone(),
            req,
            service: service.clone(),
            position,
        });
        self.list_dirty = true;
        self.out
            .push_back(Output::ToUser(user, ToUser::Queued { req, position }));
    }

    /// Grants `req` of `user` for `service` (its quota has room and its system is within
    /// its own limit: the callers checked): the system is sent the offer first, so the
    /// user's first input or end reaches it after the offer, and then the user its
    /// grant. The system confirms or, rarely, cannot take it after all
    /// ([`Broker::undo_grant`]).
    fn offer(&mut self, now: Duration, user: UserId, req: u64, service: ServiceId) {
        let Some(svc) = self.services.get_mut(&service) else {
            return self.refuse(&user, req, Refusal::Unknown);
        };
        svc.pending += 1;
        let ticket = self.next_ticket;
        self.next_ticket += 1;
        let session = SessionId::for_request(&service, &user, req);
        push_event(&mut self.events, || BrokerEvent::Granted {
            user: user.clone(),
            req,
            service: service.clone(),
            session,
        });
        self.offers.insert(
            ticket,
            Offer {
                user,
                req,
                service,
                session,
                deadline: now + self.cfg.offer_timeout,
            },
        );
        self.stats.offers += 1;
        self.stats.grants += 1;
        self.list_dirty = true;
        self.send_offer(ticket);
        self.send_grant(ticket);
    }

    /// Sends offer `ticket` to its system.
    fn send_offer(&mut self, ticket: u64) {
        let Some(o) = self.offers.get(&ticket) else {
            return;
        };
        let Some(svc) = self.services.get(&o.service) else {
            return;
        };
        let user_pid = self.users.get(&o.user).map_or(0, |u| u.pid);
        self.out.push_back(Output::ToSystem(
            svc.system.clone(),
            ToSystem::Offer {
                ticket,
                session: o.session,
                user: o.user.clone(),
                user_pid,
                req: o.req,
                service: svc.spec.name.clone(),
                remote: None,
            },
        ));
    }

    /// Tells offer `ticket`'s user of its grant.
    fn send_grant(&mut self, ticket: u64) {
        let Some(o) = self.offers.get(&ticket) else {
            return;
        };
        let Some(svc) = self.services.get(&o.service) else {
            return;
        };
        let system_pid = self.systems.get(&svc.system).map_or(0, |s| s.pid);
        self.out.push_back(Output::Granted(Grant {
            user: o.user.clone(),
            req: o.req,
            session: o.session,
            kind: svc.spec.kind,
            payload: svc.spec.payload.clone(),
            schema: svc.spec.schema.clone(),
            service: o.service.clone(),
            system_pid,
        }));
    }

    fn cancel(&mut self, now: Duration, user: &UserId, req: u64) {
        self.remove_waiting(now, |w| w.user == *user && w.req == req);
    }

    fn forget_user(&mut self, now: Duration, user: &UserId) {
        let had = self.users.remove(user);
        self.remove_waiting(now, |w| w.user == *user);
        if let Some(rec) = had {
            self.ev(|| BrokerEvent::UserLeft { user: user.clone() });
            for l in rec.links.values() {
                self.count_link(l, false);
            }
            self.out.push_back(Output::ForgetUser(user.clone()));
        }
    }

    /// Removes matching requests from every task queue; the rest move up (and are told).
    fn remove_waiting(&mut self, now: Duration, gone: impl Fn(&Waiting) -> bool) {
        let mut touched = Vec::new();
        for (id, svc) in self.services.iter_mut() {
            let before = svc.queue.len();
            svc.queue.retain(|w| !gone(w));
            if svc.queue.len() != before {
                touched.push(id.clone());
            }
        }
        for id in touched {
            self.list_dirty = true;
            self.announce_positions(&id);
            self.dispatch_queue(now, &id);
        }
    }

    /// Grants waiting requests while the quota allows, head first.
    fn dispatch_queue(&mut self, now: Duration, id: &ServiceId) {
        let mut moved = false;
        loop {
            let Some(svc) = self.services.get(id) else {
                return;
            };
            if svc.withdrawn || svc.used() >= svc.spec.quota as usize || svc.queue.is_empty() {
                break;
            }
            // Waiting requests wait out their system's own limit too.
            if self.over_limit(&svc.system).is_some() {
                break;
            }
            let Some(svc) = self.services.get_mut(id) else {
                return;
            };
            let Some(w) = svc.queue.pop_front() else {
                break;
            };
            moved = true;
            self.offer(now, w.user, w.req, id.clone());
        }
        if moved {
            self.announce_positions(id);
        }
    }

    fn announce_positions(&mut self, id: &ServiceId) {
        let Some(svc) = self.services.get(id) else {
            return;
        };
        for (i, w) in svc.queue.iter().enumerate() {
            let position = u16::try_from(i + 1).unwrap_or(u16::MAX);
            self.out.push_back(Output::ToUser(
                w.user.clone(),
                ToUser::Queued {
                    req: w.req,
                    position,
                },
            ));
        }
    }

    fn release_pending(&mut self, id: &ServiceId) {
        if let Some(svc) = self.services.get_mut(id) {
            svc.pending = svc.pending.saturating_sub(1);
            self.list_dirty = true;
        }
    }

    fn refuse(&mut self, user: &UserId, req: u64, reason: Refusal) {
        *self.stats.refusals.entry(reason.code()).or_default() += 1;
        self.ev(|| BrokerEvent::Refused {
            user: user.clone(),
            req,
            code: reason.code().to_string(),
            reason: reason.to_string(),
        });
        self.out.push_back(Output::ToUser(
            user.clone(),
            ToUser::Refused { req, reason },
        ));
    }

    fn drop_service(&mut self, id: &ServiceId, why: Refusal) {
        if let Some(svc) = self.services.remove(id) {
            self.shape += 1;
            for w in svc.queue {
                self.refuse(&w.user, w.req, why.clone());
            }
        }
        let stale: Vec<u64> = self
            .offers
            .iter()
            .filter(|(_, o)| o.service == *id)
            .map(|(t, _)| *t)
            .collect();
        for t in stale {
            if let Some(o) = self.offers.remove(&t) {
                let reason = match &why {
                    Refusal::Withdrawn => EndReason::Withdrawn,
                    Refusal::SystemGone => EndReason::PeerGone,
                    other => EndReason::BySystem(other.to_string()),
                };
                self.undo_grant(&o, reason);
            }
        }
        self.list_dirty = true;
    }

    fn remove_system(&mut self, name: &str, why: Removal) {
        let Some(rec) = self.systems.remove(name) else {
            return;
        };
        self.ev(|| BrokerEvent::SystemRemoved {
            system: name.to_string(),
            why: match why {
                Removal::Delinquent => "delinquent",
                Removal::Died => "died",
                Removal::Unregistered => "unregistered",
            }
            .into(),
        });
        for service in &rec.services {
            self.drop_service(&ServiceId::new(name, service), Refusal::SystemGone);
        }
        match why {
            Removal::Delinquent => {
                self.stats.delinquent += 1;
                *self.delinquencies.entry(name.to_string()).or_default() += 1;
                self.out
                    .push_back(Output::ToSystem(name.to_string(), ToSystem::Delinquent));
            }
            Removal::Died => self.stats.died += 1,
            Removal::Unregistered => {}
        }
        self.out.push_back(Output::ForgetSystem(name.to_string()));
        self.recount_links();
        self.list_dirty = true;
    }

    /// Records a user's link, if it joins a data service to a command service and the
    /// user is within its bound; anything else is ignored and counted.
    fn link_opened(&mut self, user: &UserId, link: LinkInfo) {
        let Some(u) = self.users.get(user) else {
            return;
        };
        // A service not (yet) listed is fine: after a broker restart users may say hello
        // before their systems register; the link counts once they do.
        let valid = self
            .kind_of(&link.data)
            .is_none_or(|k| k == ServiceKind::Data)
            && self
                .kind_of(&link.command)
                .is_none_or(|k| k == ServiceKind::Command);
        let replaces = u.links.contains_key(&link.link);
        if !valid || (!replaces && u.links.len() >= self.cfg.max_links_per_user) {
            self.stats.links_refused += 1;
            if self.stats.links_refused.is_power_of_two() {
                tracing::warn!(%user, data = %link.data, command = %link.command,
                    "link not counted (wrong kinds or over the user's bound)");
            }
            return;
        }
        let old = self
            .users
            .get_mut(user)
            .and_then(|u| u.links.insert(link.link, link.clone()));
        if let Some(old) = old {
            self.count_link(&old, false);
        }
        self.count_link(&link, true);
        self.ev(|| BrokerEvent::LinkOpened {
            user: user.clone(),
            link,
        });
    }

    /// Adds or removes one link's share of its two services' counts.
    fn count_link(&mut self, l: &LinkInfo, add: bool) {
        for id in [&l.data, &l.command] {
            if let Some(svc) = self.services.get_mut(id) {
                svc.links = if add {
                    svc.links.saturating_add(1)
                } else {
                    svc.links.saturating_sub(1)
                };
                self.list_dirty = true;
            }
        }
    }

    /// Counts every link again (a system's services came or went: rare).
    fn recount_links(&mut self) {
        let mut counts: BTreeMap<&ServiceId, u32> = BTreeMap::new();
        for u in self.users.values() {
            for l in u.links.values() {
                *counts.entry(&l.data).or_default() += 1;
                *counts.entry(&l.command).or_default() += 1;
            }
        }
        let counts: BTreeMap<ServiceId, u32> =
            counts.into_iter().map(|(k, v)| (k.clone(), v)).collect();
        for (id, svc) in self.services.iter_mut() {
            let n = counts.get(id).copied().unwrap_or(0);
            if svc.links != n {
                svc.links = n;
                self.list_dirty = true;
            }
        }
    }

    /// Kind of a listed service, if known.
    pub fn kind_of(&self, id: &ServiceId) -> Option<ServiceKind> {
        self.services.get(id).map(|s| s.spec.kind)
    }
}

#[cfg(test)]
#[path = "core_tests.rs"]
#[allow(clippy::unwrap_used)]
mod tests;
