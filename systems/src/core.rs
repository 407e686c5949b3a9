//! A robot system's side of the protocol as a pure state machine: registration,
//! pings, offers, sessions with sequence numbers, withdrawal. No I/O, no clock.

use muster_shared::names::Address;
use muster_shared::protocol::{
    ActiveSession, SessionDigest, SessionLimit, ToBroker, ToSystem, ToUser,
};
use muster_shared::types::{
    EndReason, Payload, ServiceId, ServiceKind, ServiceSpec, SessionId, SpecError, TaskStatus,
    UserId,
};
use std::collections::{BTreeMap, BTreeSet, HashSet, VecDeque};

/// What the system wants sent or watched.
#[derive(Clone, Debug, PartialEq)]
pub enum SystemOutput {
    /// Send to the broker.
    ToBroker(ToBroker),
    /// Send to a user (directly, not through the broker).
    ToUser(UserId, ToUser),
    /// Watch the broker's process for death.
    WatchBroker(u32),
    /// Watch a user's process for death.
    WatchUser(UserId, u32),
    /// Forget a user's ports and watch.
    ForgetUser(UserId),
}

/// What happened, for the system's own logic.
#[derive(Clone, Debug, PartialEq)]
pub enum SystemEvent {
    /// The broker listed our services.
    Registered,
    /// The broker refused our registration; fix the cause and restart.
    RegistrationRefused(String),
    /// The broker declared us delinquent; we re-register.
    Delinquent,
    /// The broker is gone; sessions go on, we re-register when it is back.
    BrokerLost,
    /// A session began.
    SessionStarted {
        /// The session.
        session: SessionId,
        /// Its user.
        user: UserId,
        /// Service name.
        service: String,
    },
    /// Task input arrived on a command session.
    Input {
        /// The session.
        session: SessionId,
        /// Service name.
        service: String,
        /// The input.
        payload: Payload,
    },
    /// A session ended.
    SessionEnded {
        /// The session.
        session: SessionId,
        /// Service name.
        service: String,
        /// Why.
        reason: EndReason,
    },
    /// An update [`SystemCore::publish`] accepted could not be handed to its user after
    /// all (the user's inbox was full, or the user is gone): it is lost, counted
    /// ([`SystemCore::undelivered`]), and the user sees a gap in the sequence numbers.
    /// A system that streams faster than a user reads hears it here.
    Undelivered {
        /// The session.
        session: SessionId,
        /// Service name.
        service: String,
        /// The update's sequence number.
        seq: u64,
        /// Why (the transport's words).
        reason: String,
    },
}

/// What a system saw of one service during its run.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct ServiceReport {
    /// Declared quota.
    pub quota: u16,
    /// Most sessions held at once.
    pub max_in_use: usize,
    /// Offers granted.
    pub grants: u64,
    /// Offers refused by the system.
    pub refusals: u64,
}

/// Where the system stands with the broker.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BrokerState {
    /// Not registered (no broker, or waiting for an answer).
    Unregistered,
    /// Registered with the broker run `epoch`.
    Registered {
        /// The broker's run.
        epoch: u64,
    },
}

/// Why an update or a status did not go to (some of) a service's users.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SendError {
    /// The frame is larger than its user's path takes: nothing of it was sent to that
    /// user; its sequence number is spent, so the user counts a gap at the next frame.
    #[error(
        "a frame of {bytes} bytes is larger than the {limit} bytes a user's {path} takes: \
         {refused} of {} users did not get it (send less at once)",
        sent + refused
    )]
    TooLarge {
        /// The frame's size on that path.
        bytes: usize,
        /// The path's limit.
        limit: usize,
        /// The path: `shared memory` or `UDP datagram`.
        path: &'static str,
        /// Users that got it.
        sent: usize,
        /// Users that did not.
        refused: usize,
    },
}

/// Whether `msg` fits its user's path (a remote user's UDP datagram, else shared
/// memory); the size, limit and path if not.
fn oversized(msg: &ToUser, remote: bool) -> Option<(usize, usize, &'static str)> {
    muster_shared::fits::to_user(msg, remote)
        .err()
        .map(|t| (t.bytes, t.limit, t.path))
}

#[derive(Clone, Debug)]
struct Session {
    user: UserId,
    service: String,
    seq: u64,
    /// The user's request it answers: a repeated offer for it re-sends this grant.
    req: u64,
    /// The user's process (0: a remote user, who speaks over UDP, never here).
    user_pid: u32,
}

impl Session {
    /// Whether its user is of another host, reached through that host's relay here.
    fn relayed(&self) -> bool {
        self.user.is_foreign() && self.user_pid != 0
    }
}

/// How many ended requests a system remembers, to refuse a repeated offer for one.
pub const SERVED_MEMORY: usize = 4096;

/// Most ends of sessions not open yet a system remembers
/// ([`SystemCore::sender_allowed`]).
pub const EARLY_ENDS: usize = 1024;

/// One system's protocol state.
#[derive(Debug)]
pub struct SystemCore {
    name: String,
    pid: u32,
    specs: Vec<ServiceSpec>,
    withdrawn: BTreeSet<String>,
    sessions: BTreeMap<SessionId, Session>,
    /// Requests whose session its user ended, most recent last (at most
    /// [`SERVED_MEMORY`]): a repeated offer for one of them (it crossed a broker
    /// takeover) is refused, not granted a second time.
    served: VecDeque<(UserId, u64, String)>,
    served_set: HashSet<(UserId, u64, String)>,
    /// Ends for sessions not open here yet, with the process that sent each, most
    /// recent last (at most [`EARLY_ENDS`]): a user may end a session the broker
    /// granted it before this system has read the broker's offer for it (frames from
    /// two writers are not read in the order they were written). The offer that comes
    /// after is confirmed and the session ended at once, rather than opened for nobody,
    /// counted in use for good.
    ended_early: VecDeque<(SessionId, UserId, u32)>,
    /// Data services whose newest update the broker keeps for new sessions
    /// ([`SystemCore::latch`]), each with its newest update (`sent_ns` and the encoded
    /// payload), sent again with every registration: a broker that restarted or took
    /// over, or one this system registered with after the update, has it too (a latched
    /// ROS topic may be sent once).
    latched: BTreeMap<String, Option<(u64, Vec<u8>)>>,
    state: BrokerState,
    /// The pid of the broker that registered us (from its `Registered`).
    broker_pid: Option<u32>,
    impersonations: u64,
    overloaded: bool,
    session_limit: Option<(usize, String)>,
    udp: Option<String>,
    report: BTreeMap<String, ServiceReport>,
    /// Frames not sent: too large for their user's path.
    too_large: u64,
    undelivered: u64,
    out: VecDeque<SystemOutput>,
    events: VecDeque<SystemEvent>,
}

impl SystemCore {
    /// A system named `name` in this process offering `specs`, checked now as the
    /// broker will check them (names, sizes, quotas, payload types, schemas): a bad spec
    /// is an error here, not a refusal later.
    pub fn create(name: &str, specs: Vec<ServiceSpec>) -> Result<Self, SpecError> {
        muster_shared::types::validate_registration(name, &specs)?;
        Ok(Self::new(name, std::process::id(), specs))
    }

    /// A system named `name` in process `pid` offering `specs` (see
    /// [`SystemCore::create`], which checks them and takes this process's pid).
    pub fn new(name: &str, pid: u32, specs: Vec<ServiceSpec>) -> Self {
        SystemCore {
            name: name.to_string(),
            pid,
            specs,
            withdrawn: BTreeSet::new(),
            sessions: BTreeMap::new(),
            served: VecDeque::new(),
            served_set: HashSet::new(),
            ended_early: VecDeque::new(),
            latched: BTreeMap::new(),
            state: BrokerState::Unregistered,
            broker_pid: None,
            impersonations: 0,
            overloaded: false,
            session_limit: None,
            udp: None,
            report: BTreeMap::new(),
            too_large: 0,
            undelivered: 0,
            out: VecDeque::new(),
            events: VecDeque::new(),
        }
    }

    /// System name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The declared services.
    pub fn specs(&self) -> &[ServiceSpec] {
        &self.specs
    }

    /// Where the system stands with the broker.
    pub fn state(&self) -> BrokerState {
        self.state
    }

    /// Next output, if any.
    pub fn poll_output(&mut self) -> Option<SystemOutput> {
        self.out.pop_front()
    }

    /// Next event, if any.
    pub fn poll_event(&mut self) -> Option<SystemEvent> {
        self.events.pop_front()
    }

    /// Sessions currently open, with their user and service.
    pub fn sessions(&self) -> impl Iterator<Item = (SessionId, &UserId, &str)> {
        self.sessions
            .iter()
            .map(|(id, s)| (*id, &s.user, s.service.as_str()))
    }

    /// Number of open sessions of `service`.
    pub fn sessions_of(&self, service: &str) -> usize {
        self.sessions
            .values()
            .filter(|s| s.service == service)
            .count()
    }

    /// Per service: quota, most sessions at once, grants and refusals so far.
    pub fn report(&self) -> BTreeMap<String, ServiceReport> {
        let mut r = self.report.clone();
        for spec in &self.specs {
            r.entry(spec.name.clone()).or_default().quota = spec.quota;
        }
        r
    }

    /// Take no new sessions ("overloaded") while `true`.
    pub fn set_overloaded(&mut self, value: bool) {
        self.limit_changes(|c| c.overloaded = value);
    }

    /// Take no new sessions, with `reason`, while the system holds `limit` sessions or
    /// more over all its services (e.g. a robot's processing budget, which may be smaller
    /// than the quotas); `None` lifts the limit. Sessions already held are never ended by
    /// it. The broker is told, and refuses requests beyond it itself.
    pub fn set_session_limit(&mut self, limit: Option<usize>, reason: &str) {
        self.limit_changes(|c| c.session_limit = limit.map(|l| (l, reason.to_string())));
    }

    /// The limit the broker holds this system to: none while overloaded, else its
    /// session limit.
    fn limit(&self) -> Option<SessionLimit> {
        if self.overloaded {
            return Some(SessionLimit {
                sessions: 0,
                reason: "overloaded".into(),
            });
        }
        self.session_limit.as_ref().map(|(l, reason)| SessionLimit {
            sessions: u32::try_from(*l).unwrap_or(u32::MAX),
            reason: reason.clone(),
        })
    }

    /// Applies `change`, and tells a broker that registered us if the limit moved.
    fn limit_changes(&mut self, change: impl FnOnce(&mut Self)) {
        let before = self.limit();
        change(self);
        let after = self.limit();
        if after != before && matches!(self.state, BrokerState::Registered { .. }) {
            self.send_broker(ToBroker::Limit {
                system: self.name.clone(),
                limit: after,
            });
        }
    }

    /// Announce a UDP endpoint for remote users (`ip:port`) in the registration.
    pub fn set_udp(&mut self, addr: Option<String>) {
        self.udp = addr;
    }

    fn active_sessions(&self) -> Vec<ActiveSession> {
        self.sessions
            .iter()
            .map(|(id, s)| ActiveSession {
                session: *id,
                service: s.service.clone(),
                user: s.user.clone(),
                relayed: s.relayed(),
            })
            .collect()
    }

    /// Sends (or re-sends) the registration, with the sessions already held.
    pub fn register(&mut self) {
        let sessions = self.active_sessions();
        self.out
            .push_back(SystemOutput::ToBroker(ToBroker::Register {
                system: self.name.clone(),
                pid: self.pid,
                services: self.specs.clone(),
                sessions,
                udp: self.udp.clone(),
            }));
    }

    /// Whether a local frame written by process `pid` may say `msg`: the broker's
    /// messages only from the broker that registered us, and a registration's answer
    /// only from the process that owns the broker's inbox (`owner` tells who owns an
    /// address's inbox: [`muster_shared::ipc::Endpoint::owner_pid`]); a session's input or end
    /// only from the process the session was granted to. `None` (the writer cannot be
    /// told) is let through. Refusals are counted ([`SystemCore::impersonations`]) and
    /// logged. An end for a session not open yet is let through and remembered with its
    /// sender, for the offer that may follow (see the offer's handling).
    pub fn sender_allowed(
        &mut self,
        pid: Option<u32>,
        msg: &ToSystem,
        mut owner: impl FnMut(&Address) -> Option<u32>,
    ) -> bool {
        let Some(pid) = pid else { return true };
        let ok = match msg {
            ToSystem::Registered { broker_pid, .. } => {
                *broker_pid == pid && owner(&Address::Broker) == Some(pid)
            }
            ToSystem::End { session, user } if !self.sessions.contains_key(session) => {
                // Not open yet: remembered, with who sent it, for its offer.
                if self.ended_early.len() >= EARLY_ENDS {
                    self.ended_early.pop_front();
                }
                self.ended_early.push_back((*session, user.clone(), pid));
                true
            }
            // Another host's user's frames come from this host's broker (its relay),
            // whichever process that is now.
            ToSystem::Input { session, .. } | ToSystem::End { session, .. } => {
                self.sessions.get(session).is_none_or(|s| {
                    s.user_pid == pid || (s.user.is_foreign() && self.broker_pid == Some(pid))
                })
            }
            _ => self.broker_pid.is_none_or(|b| b == pid),
        };
        muster_shared::protocol::note_impersonation(
            ok,
            &mut self.impersonations,
            pid,
            "the broker or another user",
        )
    }

    /// Local frames refused by [`SystemCore::sender_allowed`].
    pub fn impersonations(&self) -> u64 {
        self.impersonations
    }

    /// The broker's process died: sessions go on; re-register when a broker announces itself.
    pub fn broker_lost(&mut self) {
        self.broker_pid = None;
        if self.state != BrokerState::Unregistered {
            self.state = BrokerState::Unregistered;
            self.events.push_back(SystemEvent::BrokerLost);
        }
    }

    /// Handles one frame from the inbox.
    pub fn handle(&mut self, msg: ToSystem) {
        match msg {
            ToSystem::Registered { epoch, broker_pid } => {
                if self.state == (BrokerState::Registered { epoch }) {
                    return; // a duplicate answer (we registered twice while a broker started)
                }
                self.state = BrokerState::Registered { epoch };
                self.broker_pid = Some(broker_pid);
                self.out.push_back(SystemOutput::WatchBroker(broker_pid));
                for service in self.withdrawn.clone() {
                    self.send_broker(ToBroker::Withdraw {
                        system: self.name.clone(),
                        service,
                    });
                }
                if let Some(limit) = self.limit() {
                    self.send_broker(ToBroker::Limit {
                        system: self.name.clone(),
                        limit: Some(limit),
                    });
                }
                // The newest value of each latched service, for this broker to keep.
                for (service, newest) in &self.latched {
                    if let Some((sent_ns, payload)) = newest {
                        self.out.push_back(SystemOutput::ToBroker(ToBroker::Latest {
                            system: self.name.clone(),
                            service: service.clone(),
                            sent_ns: *sent_ns,
                            payload: payload.clone(),
                        }));
                    }
                }
                self.events.push_back(SystemEvent::Registered);
            }
            ToSystem::RegistrationRefused { reason } => {
                self.state = BrokerState::Unregistered;
                self.events
                    .push_back(SystemEvent::RegistrationRefused(reason));
            }
            ToSystem::Ping { nonce } => {
                let held = SessionDigest::of(self.sessions.keys().copied());
                self.send_broker(ToBroker::Pong {
                    system: self.name.clone(),
                    nonce,
                    held: Some(held),
                });
            }
            ToSystem::ReportSessions => {
                let sessions = self.active_sessions();
                self.send_broker(ToBroker::Sessions {
                    system: self.name.clone(),
                    sessions,
                });
            }
            ToSystem::Delinquent => {
                self.state = BrokerState::Unregistered;
                self.events.push_back(SystemEvent::Delinquent);
                self.register();
            }
            ToSystem::Offer {
                ticket,
                session,
                user,
                user_pid,
                req,
                service,
                remote: _,
            } => self.offer(ticket, session, user, user_pid, req, service),
            ToSystem::Input {
                user,
                session,
                payload,
            } => {
                let Some(s) = self.sessions.get(&session) else {
                    tracing::debug!(%session, "input for an unknown session dropped");
                    return;
                };
                if s.user != user {
                    tracing::warn!(%session, %user, "input from a user not holding the session dropped");
                    return;
                }
                let service = s.service.clone();
                self.events.push_back(SystemEvent::Input {
                    session,
                    service,
                    payload,
                });
            }
            ToSystem::End { user, session } => {
                if self.sessions.get(&session).is_some_and(|s| s.user == user) {
                    // Confirmed to the user: its termination round trip is measured.
                    self.close(session, EndReason::ByUser, true);
                }
            }
            ToSystem::Terminate { session, reason } => {
                if self.sessions.contains_key(&session) {
                    self.close(session, EndReason::BySystem(reason), true);
                }
            }
            ToSystem::Revoked { user } => {
                let ids: Vec<SessionId> = self
                    .sessions
                    .iter()
                    .filter(|(_, s)| s.user == user)
                    .map(|(id, _)| *id)
                    .collect();
                for id in ids {
                    self.close(id, EndReason::BySystem("access revoked".into()), true);
                }
            }
        }
    }

    /// The grant a user is sent for `session` of `spec`.
    fn granted(&self, req: u64, session: SessionId, spec: &ServiceSpec) -> ToUser {
        ToUser::Granted {
            req,
            session,
            service: ServiceId::new(&self.name, &spec.name),
            kind: spec.kind,
            payload: spec.payload.clone(),
            schema: spec.schema.clone(),
            system_pid: self.pid,
            relayed: false,
        }
    }

    /// Opens session `session`, which the broker granted (it told the user), or says
    /// why it cannot: the broker then ends the user's grant with that reason. The broker
    /// holds the system to its quotas and limit, so a refusal here is a race (a change
    /// on its way to the broker) or a repeat.
    fn offer(
        &mut self,
        ticket: u64,
        session: SessionId,
        user: UserId,
        user_pid: u32,
        req: u64,
        service: String,
    ) {
        let answer = |c: &mut Self, answer| {
            c.send_broker(ToBroker::OfferAnswer {
                system: c.name.clone(),
                ticket,
                answer,
            })
        };
        // Ended by its user (the process the session is granted to, or for a user of
        // another host this host's broker) before this offer was read: confirmed and
        // ended at once, as if the end had come after it (the broker counts the grant
        // until then); the user, who has let it go, hears nothing.
        let broker_pid = self.broker_pid;
        if let Some(k) = self.ended_early.iter().position(|(s, u, pid)| {
            *s == session
                && *u == user
                && (*pid == user_pid || (user.is_foreign() && broker_pid == Some(*pid)))
        }) {
            self.ended_early.remove(k);
            muster_shared::trace::stamp(muster_shared::trace::Stage::SystemSend, &user, req);
            answer(self, Ok(session));
            self.remember_served((user, req, service));
            let system = self.name.clone();
            return self.send_broker(ToBroker::SessionEnded { system, session });
        }
        // The same request offered again (a retry that crossed a broker restart or
        // takeover): confirm the session it has, never open a second.
        if self
            .served_set
            .contains(&(user.clone(), req, service.clone()))
        {
            let reason = "request already served: its session has ended".to_string();
            return answer(self, Err(reason));
        }
        let spec = self.specs.iter().find(|s| s.name == service).cloned();
        let held = self
            .sessions
            .iter()
            .find(|(_, s)| s.user == user && s.req == req && s.service == service)
            .map(|(id, _)| *id);
        if let Some(held) = held {
            if let Some(spec) = &spec {
                let granted = self.granted(req, held, spec);
                self.out
                    .push_back(SystemOutput::ToUser(user.clone(), granted));
            }
            return answer(self, Ok(held));
        }
        // The limit the broker was told (overloaded, or the budget over all services).
        let over_limit = self
            .limit()
            .filter(|l| self.sessions.len() >= l.sessions as usize)
            .map(|l| l.reason);
        let spec = match spec {
            None => Err(format!("no service {service:?} here")),
            Some(_) if self.sessions.contains_key(&session) => {
                Err(format!("session {session} is another request's"))
            }
            Some(_) if self.withdrawn.contains(&service) => Err("service withdrawn".to_string()),
            Some(_) if over_limit.is_some() => Err(over_limit.unwrap_or_default()),
            Some(spec) if self.sessions_of(&service) >= spec.quota as usize => {
                Err(format!("overloaded: all {} sessions in use", spec.quota))
            }
            Some(spec) => Ok(spec),
        };
        let spec = match spec {
            Ok(spec) => spec,
            Err(reason) => {
                self.report.entry(service.clone()).or_default().refusals += 1;
                return answer(self, Err(reason));
            }
        };
        self.sessions.insert(
            session,
            Session {
                user: user.clone(),
                service: service.clone(),
                seq: 0,
                req,
                user_pid,
            },
        );
        let in_use = self.sessions_of(&service);
        let r = self.report.entry(service.clone()).or_default();
        r.grants += 1;
        r.max_in_use = r.max_in_use.max(in_use);
        muster_shared::trace::stamp(muster_shared::trace::Stage::SystemSend, &user, req);
        answer(self, Ok(session));
        // Another host's user is reached through this host's broker, whose process
        // may change (a standby takes over) without the user going: the federation
        // says when it goes.
        if user_pid != 0 && !user.is_foreign() {
            self.out
                .push_back(SystemOutput::WatchUser(user.clone(), user_pid));
        }
        // The session opened: the shell sets up a remote user's path with it (a local
        // user heard from the broker, and hears from us with the first update).
        let granted = self.granted(req, session, &spec);
        self.out
            .push_back(SystemOutput::ToUser(user.clone(), granted));
        self.events.push_back(SystemEvent::SessionStarted {
            session,
            user,
            service,
        });
    }

    /// Latches data service `service` (ROS 2's transient-local durability): each update
    /// [`SystemCore::publish`] streams also goes to the broker, which keeps the newest
    /// and hands it to every new session of the service with its grant, as its update 0
    /// (so a user has the service's value at once, not at this system's next turn).
    /// `false` if there is no such data service.
    pub fn latch(&mut self, service: &str) -> bool {
        let data = self
            .specs
            .iter()
            .any(|s| s.name == service && s.kind == ServiceKind::Data);
        if data {
            self.latched.entry(service.to_string()).or_default();
        }
        data
    }

    /// Whether `service` is latched ([`SystemCore::latch`]).
    pub fn latched(&self, service: &str) -> bool {
        self.latched.contains_key(service)
    }

    /// Streams one data update to every session of `service`. Returns how many got it;
    /// an update too large for a user's path goes to none of those users, and says so
    /// ([`SendError::TooLarge`], counted in [`SystemCore::too_large`]): it is never
    /// dropped unseen.
    ///
    /// `sent_ns` stamps the updates (CLOCK_MONOTONIC ns, see
    /// [`muster_shared::protocol::monotonic_ns`]) so users can measure update latency.
    pub fn publish(
        &mut self,
        service: &str,
        payload: &Payload,
        sent_ns: u64,
    ) -> Result<usize, SendError> {
        if let Some(newest) = self.latched.get_mut(service) {
            match muster_shared::protocol::encode(payload) {
                Ok(payload) => {
                    *newest = Some((sent_ns, payload.clone()));
                    if matches!(self.state, BrokerState::Registered { .. }) {
                        self.out.push_back(SystemOutput::ToBroker(ToBroker::Latest {
                            system: self.name.clone(),
                            service: service.to_string(),
                            sent_ns,
                            payload,
                        }));
                    }
                }
                // Too large for a frame: its sessions' updates will say so below.
                Err(e) => tracing::debug!(system = %self.name, service, "not latched: {e}"),
            }
        }
        self.publish_where(payload, sent_ns, |_, s| s.service == service)
    }

    /// Sends a data update on one session only (a session just opened gets the current
    /// value at once, not at the next update of its service); what [`SystemCore::publish`]
    /// does for all of a service's. Nothing is sent for a session not open.
    pub fn publish_session(
        &mut self,
        session: SessionId,
        payload: &Payload,
        sent_ns: u64,
    ) -> Result<usize, SendError> {
        self.publish_where(payload, sent_ns, |id, _| *id == session)
    }

    fn publish_where(
        &mut self,
        payload: &Payload,
        sent_ns: u64,
        on: impl Fn(&SessionId, &Session) -> bool,
    ) -> Result<usize, SendError> {
        let (mut sent, mut refused, mut why) = (0, 0, None);
        // Users of other hosts first: theirs is the longer way (this host's broker,
        // Zenoh, theirs), and their relay's reader takes them on while the rest are
        // written.
        for far in [true, false] {
            let mine = self
                .sessions
                .iter_mut()
                .filter(|(id, s)| s.relayed() == far && on(id, s));
            for (id, s) in mine {
                s.seq += 1;
                let msg = ToUser::Update {
                    session: *id,
                    seq: s.seq,
                    sent_ns,
                    payload: payload.clone(),
                };
                if let Some(big) = oversized(&msg, s.user_pid == 0) {
                    refused += 1;
                    why = Some(big);
                    continue;
                }
                self.out
                    .push_back(SystemOutput::ToUser(s.user.clone(), msg));
                sent += 1;
            }
        }
        self.too_large += refused as u64;
        match why {
            None => Ok(sent),
            Some((bytes, limit, path)) => Err(SendError::TooLarge {
                bytes,
                limit,
                path,
                sent,
                refused,
            }),
        }
    }

    /// Sends task status on one session. A status too large for its user's path is not
    /// sent: it is counted ([`SystemCore::too_large`]) and logged as a warning (see
    /// [`SystemCore::try_status`] to get the error instead).
    pub fn status(&mut self, session: SessionId, status: TaskStatus) {
        if let Err(e) = self.try_status(session, status) {
            tracing::warn!(system = %self.name, %session, "status not sent: {e}");
        }
    }

    /// [`SystemCore::status`], returning why a status was not sent.
    pub fn try_status(&mut self, session: SessionId, status: TaskStatus) -> Result<(), SendError> {
        let Some(s) = self.sessions.get_mut(&session) else {
            return Ok(());
        };
        s.seq += 1;
        let msg = ToUser::Status {
            session,
            seq: s.seq,
            status,
        };
        if let Some((bytes, limit, path)) = oversized(&msg, s.user_pid == 0) {
            self.too_large += 1;
            return Err(SendError::TooLarge {
                bytes,
                limit,
                path,
                sent: 0,
                refused: 1,
            });
        }
        self.out
            .push_back(SystemOutput::ToUser(s.user.clone(), msg));
        Ok(())
    }

    /// Updates and statuses not sent because they were too large for their user's path.
    pub fn too_large(&self) -> u64 {
        self.too_large
    }

    /// Updates the runtime could not hand to their users after `publish` accepted them
    /// (see [`SystemEvent::Undelivered`]).
    pub fn undelivered(&self) -> u64 {
        self.undelivered
    }

    /// The runtime could not hand update `seq` of `session` to its user: counted, and
    /// said to the app as [`SystemEvent::Undelivered`].
    pub fn note_undelivered(&mut self, session: SessionId, seq: u64, reason: String) {
        self.undelivered += 1;
        let service = self
            .sessions
            .get(&session)
            .map(|s| s.service.clone())
            .unwrap_or_default();
        self.events.push_back(SystemEvent::Undelivered {
            session,
            service,
            seq,
            reason,
        });
    }

    /// Ends a session from the system's side; the user and the broker are told.
    pub fn end_session(&mut self, session: SessionId, reason: EndReason) {
        self.close(session, reason, true);
    }

    /// A request whose session its user ended: a repeated offer for it is refused.
    fn remember_served(&mut self, key: (UserId, u64, String)) {
        if self.served_set.insert(key.clone()) {
            self.served.push_back(key);
            if self.served.len() > SERVED_MEMORY {
                if let Some(old) = self.served.pop_front() {
                    self.served_set.remove(&old);
                }
            }
        }
    }

    fn close(&mut self, session: SessionId, reason: EndReason, tell_user: bool) {
        let Some(s) = self.sessions.remove(&session) else {
            return;
        };
        // Only a session its user ended is surely known to the user: one ended for any
        // other reason may never have reached it (a remote user who never heard of its
        // grant goes silent), and its retried request deserves a grant.
        if reason == EndReason::ByUser {
            self.remember_served((s.user.clone(), s.req, s.service.clone()));
        }
        if tell_user {
            self.out.push_back(SystemOutput::ToUser(
                s.user.clone(),
                ToUser::Ended {
                    session,
                    reason: reason.clone(),
                    last_seq: s.seq,
                },
            ));
        }
        self.send_broker(ToBroker::SessionEnded {
            system: self.name.clone(),
            session,
        });
        if !self.sessions.values().any(|o| o.user == s.user) {
            self.out.push_back(SystemOutput::ForgetUser(s.user.clone()));
        }
        self.events.push_back(SystemEvent::SessionEnded {
            session,
            service: s.service,
            reason,
        });
    }

    /// A user's process died: its sessions end.
    pub fn user_died(&mut self, user: &UserId) {
        let ids: Vec<SessionId> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.user == *user)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            self.close(id, EndReason::PeerGone, false);
        }
    }

    /// Stops offering `service` for now: its sessions end, the broker is told.
    pub fn withdraw(&mut self, service: &str) {
        if !self.specs.iter().any(|s| s.name == service) || !self.withdrawn.insert(service.into()) {
            return;
        }
        let ids: Vec<SessionId> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.service == service)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            self.close(id, EndReason::Withdrawn, true);
        }
        self.send_broker(ToBroker::Withdraw {
            system: self.name.clone(),
            service: service.into(),
        });
    }

    /// Changes the services offered, for a system whose robots come and go (a fleet
    /// bridge discovering vehicles). The new list is checked as [`SystemCore::create`]
    /// checks one; sessions of services no longer declared end (their users told), and
    /// a registered system registers again at once, keeping its other sessions and its
    /// withdrawn services withdrawn.
    pub fn set_specs(&mut self, specs: Vec<ServiceSpec>) -> Result<(), SpecError> {
        muster_shared::types::validate_registration(&self.name, &specs)?;
        let keep: BTreeSet<&str> = specs.iter().map(|s| s.name.as_str()).collect();
        let gone: Vec<SessionId> = self
            .sessions
            .iter()
            .filter(|(_, s)| !keep.contains(s.service.as_str()))
            .map(|(id, _)| *id)
            .collect();
        for id in gone {
            self.close(
                id,
                EndReason::BySystem("service no longer offered".into()),
                true,
            );
        }
        self.withdrawn.retain(|s| keep.contains(s.as_str()));
        self.specs = specs;
        if matches!(self.state, BrokerState::Registered { .. }) {
            // The broker takes a registration from the same process as a new service
            // list, and clears its withdrawn flags: withdraw them again after it.
            self.register();
            for service in self.withdrawn.clone() {
                self.send_broker(ToBroker::Withdraw {
                    system: self.name.clone(),
                    service,
                });
            }
        }
        Ok(())
    }

    /// Offers a withdrawn service again.
    pub fn restore(&mut self, service: &str) {
        if self.withdrawn.remove(service) {
            self.send_broker(ToBroker::Restore {
                system: self.name.clone(),
                service: service.into(),
            });
        }
    }

    /// Leaves: ends every session and unregisters.
    pub fn shutdown(&mut self) {
        let ids: Vec<SessionId> = self.sessions.keys().copied().collect();
        for id in ids {
            self.close(id, EndReason::BySystem("system shutting down".into()), true);
        }
        self.send_broker(ToBroker::Unregister {
            system: self.name.clone(),
        });
    }

    /// Kind of one of our services.
    pub fn kind_of(&self, service: &str) -> Option<ServiceKind> {
        self.specs
            .iter()
            .find(|s| s.name == service)
            .map(|s| s.kind)
    }

    fn send_broker(&mut self, msg: ToBroker) {
        self.out.push_back(SystemOutput::ToBroker(msg));
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn spec(name: &str, kind: ServiceKind, quota: u16) -> ServiceSpec {
        ServiceSpec {
            name: name.into(),
            description: String::new(),
            kind,
            queue: false,
            quota,
            payload: "pose2d".into(),
            schema: None,
        }
    }

    fn core() -> SystemCore {
        SystemCore::new(
            "t1",
            7,
            vec![
                spec("a", ServiceKind::Data, 1),
                spec("c", ServiceKind::Command, 2),
            ],
        )
    }

    fn outs(c: &mut SystemCore) -> Vec<SystemOutput> {
        std::iter::from_fn(|| c.poll_output()).collect()
    }

    /// The session the broker grants request `req` of `user` for service `service` of t1.
    fn sid(user: &str, req: u64, service: &str) -> SessionId {
        SessionId::for_request(&ServiceId::new("t1", service), &UserId(user.into()), req)
    }

    /// Offers `service` to `user` (process `pid`; 0 a remote user) for its request
    /// `ticket`.
    fn offer_of(c: &mut SystemCore, ticket: u64, user: &str, pid: u32, service: &str) {
        offered_to(c, ticket, user, pid, service);
    }

    /// [`offer_of`], and what the system said.
    fn offered_to(
        c: &mut SystemCore,
        ticket: u64,
        user: &str,
        pid: u32,
        service: &str,
    ) -> Vec<SystemOutput> {
        c.handle(ToSystem::Offer {
            ticket,
            session: sid(user, ticket, service),
            user: UserId(user.into()),
            user_pid: pid,
            req: ticket,
            service: service.into(),
            remote: None,
        });
        outs(c)
    }

    fn offer(c: &mut SystemCore, ticket: u64, user: &str, service: &str) -> Vec<SystemOutput> {
        c.handle(ToSystem::Offer {
            ticket,
            session: sid(user, ticket, service),
            user: UserId(user.into()),
            user_pid: 0,
            req: ticket,
            service: service.into(),
            remote: None,
        });
        outs(c)
    }

    fn answer(out: &[SystemOutput]) -> Option<Result<SessionId, String>> {
        out.iter().find_map(|o| match o {
            SystemOutput::ToBroker(ToBroker::OfferAnswer { answer, .. }) => Some(answer.clone()),
            _ => None,
        })
    }

    #[test]
    fn a_session_its_user_ended_before_the_offer_was_read_is_confirmed_and_ended_not_left_open() {
        let mut c = core();
        let alice = UserId("alice".into());
        // alice (process 40) ends the session of her request 1 before the offer is read.
        let end = ToSystem::End {
            user: alice.clone(),
            session: sid("alice", 1, "a"),
        };
        assert!(c.sender_allowed(Some(40), &end, |_| None));
        c.handle(end);
        let out = offered_to(&mut c, 1, "alice", 40, "a");
        assert_eq!(answer(&out), Some(Ok(sid("alice", 1, "a"))));
        let ended: Vec<_> = out
            .iter()
            .filter_map(|o| match o {
                SystemOutput::ToBroker(ToBroker::SessionEnded { session, .. }) => Some(*session),
                _ => None,
            })
            .collect();
        assert_eq!(ended, [sid("alice", 1, "a")]);
        assert!(!out.iter().any(|o| matches!(o, SystemOutput::ToUser(..))));
        assert_eq!(c.sessions_of("a"), 0);
        // The same request offered again (a retry across a broker takeover): refused.
        assert!(matches!(
            answer(&offered_to(&mut c, 1, "alice", 40, "a")),
            Some(Err(_))
        ));
        // Another process saying it ends her next session does not: it opens.
        let forged = ToSystem::End {
            user: alice,
            session: sid("alice", 2, "a"),
        };
        assert!(c.sender_allowed(Some(41), &forged, |_| None));
        c.handle(forged);
        assert_eq!(
            answer(&offered_to(&mut c, 2, "alice", 40, "a")),
            Some(Ok(sid("alice", 2, "a")))
        );
        assert_eq!(c.sessions_of("a"), 1);
    }

    #[test]
    fn an_update_too_large_for_its_users_path_is_refused_said_and_seen_as_a_gap() {
        let mut c = core();
        let offer_as = |c: &mut SystemCore, ticket: u64, user: &str, pid: u32| {
            offer_of(c, ticket, user, pid, "a");
        };
        offer_as(&mut c, 1, "local", 40);
        let seqs = |out: Vec<SystemOutput>| -> Vec<u64> {
            out.into_iter()
                .filter_map(|o| match o {
                    SystemOutput::ToUser(_, ToUser::Update { seq, .. }) => Some(seq),
                    _ => None,
                })
                .collect()
        };
        let text = |n: usize| Payload::Text("x".repeat(n));
        assert_eq!(c.publish("a", &text(3000), 0), Ok(1));
        // Over the 4 KiB frame a local user reads: nobody gets it, the caller is told.
        match c.publish("a", &text(5000), 0) {
            Err(SendError::TooLarge {
                path,
                limit,
                sent,
                refused,
                bytes,
            }) => {
                assert_eq!((path, limit, sent, refused), ("shared memory", 4096, 0, 1));
                assert!(bytes > 5000, "{bytes}");
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(c.too_large(), 1);
        assert_eq!(c.publish("a", &text(10), 0), Ok(1));
        // The refused update's number is spent: the user counts it as lost.
        assert_eq!(seqs(outs(&mut c)), [1, 3]);
        // A remote user's path is one datagram: the same 3000 bytes do not fit it.
        c.handle(ToSystem::End {
            user: UserId("local".into()),
            session: sid("local", 1, "a"),
        });
        offer_as(&mut c, 2, "far", 0);
        let e = c.publish("a", &text(3000), 0).unwrap_err();
        assert!(e.to_string().contains("UDP datagram"), "{e}");
        // A status too large is not sent either; `status` logs it, `try_status` says it.
        offer_as(&mut c, 3, "far2", 0);
        offer_of(&mut c, 4, "loc2", 41, "c");
        let big = TaskStatus::Working("y".repeat(5000));
        assert!(c.try_status(sid("loc2", 4, "c"), big).is_err());
        assert!(c.try_status(sid("loc2", 4, "c"), TaskStatus::Idle).is_ok());
        // The system's end names the last number it spent, refused or not: a last frame
        // that never went is still counted as lost by the user.
        assert!(c.try_status(sid("loc2", 4, "c"), big_again()).is_err());
        outs(&mut c);
        c.end_session(sid("loc2", 4, "c"), EndReason::BySystem("shut".into()));
        let last = outs(&mut c).into_iter().find_map(|o| match o {
            SystemOutput::ToUser(_, ToUser::Ended { last_seq, .. }) => Some(last_seq),
            _ => None,
        });
        assert_eq!(last, Some(3));
    }

    fn big_again() -> TaskStatus {
        TaskStatus::Working("z".repeat(5000))
    }

    #[test]
    fn new_specs_end_the_sessions_of_dropped_services_and_register_again_keeping_withdrawals() {
        let mut c = SystemCore::new(
            "t1",
            7,
            vec![
                spec("a", ServiceKind::Data, 1),
                spec("c", ServiceKind::Command, 2),
                spec("w", ServiceKind::Data, 1),
            ],
        );
        c.handle(ToSystem::Registered {
            epoch: 3,
            broker_pid: 9,
        });
        outs(&mut c);
        let on_a = answer(&offer(&mut c, 1, "u1", "a")).unwrap().unwrap();
        let on_c = answer(&offer(&mut c, 2, "u2", "c")).unwrap().unwrap();
        c.withdraw("w");
        outs(&mut c);
        // A bad list is refused whole and changes nothing.
        let bad = vec![
            spec("a", ServiceKind::Data, 1),
            spec("a", ServiceKind::Data, 1),
        ];
        assert!(c.set_specs(bad).is_err());
        assert_eq!(c.specs().len(), 3);
        // "a" goes, "c" stays with its session, "w" stays withdrawn, "n" comes.
        c.handle(ToSystem::Registered {
            epoch: 3,
            broker_pid: 9,
        });
        outs(&mut c);
        let news = vec![
            spec("c", ServiceKind::Command, 2),
            spec("w", ServiceKind::Data, 1),
            spec("n", ServiceKind::Data, 1),
        ];
        c.set_specs(news).unwrap();
        let out = outs(&mut c);
        let ended: Vec<SessionId> = out
            .iter()
            .filter_map(|o| match o {
                SystemOutput::ToUser(_, ToUser::Ended { session, .. }) => Some(*session),
                _ => None,
            })
            .collect();
        assert_eq!(ended, [on_a]);
        let order: Vec<String> = out
            .iter()
            .filter_map(|o| match o {
                SystemOutput::ToBroker(ToBroker::Register {
                    services, sessions, ..
                }) => {
                    let names: Vec<&str> = services.iter().map(|s| s.name.as_str()).collect();
                    let held: Vec<SessionId> = sessions.iter().map(|a| a.session).collect();
                    Some(format!("register {names:?} {}", held == [on_c]))
                }
                SystemOutput::ToBroker(ToBroker::Withdraw { service, .. }) => {
                    Some(format!("withdraw {service}"))
                }
                _ => None,
            })
            .collect();
        assert_eq!(order, [r#"register ["c", "w", "n"] true"#, "withdraw w"]);
        assert_eq!(c.sessions_of("a"), 0);
    }

    #[test]
    fn a_repeated_offer_gets_the_same_session_and_one_for_an_ended_session_is_refused() {
        let mut c = core();
        let first = answer(&offer(&mut c, 5, "u1", "c")).unwrap().unwrap();
        // The same request offered again (a retry that crossed a takeover): same session.
        assert_eq!(answer(&offer(&mut c, 5, "u1", "c")), Some(Ok(first)));
        c.handle(ToSystem::End {
            user: UserId("u1".into()),
            session: first,
        });
        outs(&mut c);
        // Once that session has ended, the request is served: never a second grant.
        let again = answer(&offer(&mut c, 5, "u1", "c")).unwrap();
        assert!(again.unwrap_err().contains("already served"));
        // Another request of the same user is granted as usual.
        assert!(answer(&offer(&mut c, 6, "u1", "c")).unwrap().is_ok());
    }

    #[test]
    fn only_the_broker_inbox_owner_registers_us_and_speaks_for_the_broker() {
        let mut c = core();
        c.register();
        outs(&mut c);
        // The broker is pid 3; pid 66 answers our registration first, as itself.
        let owner = |a: &Address| matches!(a, Address::Broker).then_some(3);
        let registered = |pid| ToSystem::Registered {
            epoch: 1,
            broker_pid: pid,
        };
        assert!(
            !c.sender_allowed(Some(66), &registered(66), owner),
            "not the broker"
        );
        assert!(
            !c.sender_allowed(Some(66), &registered(3), owner),
            "claims another pid"
        );
        assert!(c.sender_allowed(Some(3), &registered(3), owner));
        c.handle(registered(3));
        let offer = ToSystem::Offer {
            ticket: 1,
            session: sid("m", 1, "a"),
            user: UserId("m".into()),
            user_pid: 66,
            req: 1,
            service: "a".into(),
            remote: None,
        };
        assert!(
            !c.sender_allowed(Some(66), &offer, owner),
            "offers come from the broker"
        );
        assert!(c.sender_allowed(Some(3), &offer, owner));
        assert_eq!(c.impersonations(), 3);
    }

    #[test]
    fn a_repeated_offer_gets_the_same_session_not_a_second_grant() {
        let mut c = core();
        let first = answer(&offer(&mut c, 5, "u1", "c")).unwrap().unwrap();
        // The same request (user u1, req 5) offered again under a new ticket.
        c.handle(ToSystem::Offer {
            ticket: 99,
            session: sid("u1", 5, "c"),
            user: UserId("u1".into()),
            user_pid: 0,
            req: 5,
            service: "c".into(),
            remote: None,
        });
        let out = outs(&mut c);
        assert_eq!(answer(&out), Some(Ok(first)));
        assert_eq!(c.sessions_of("c"), 1);
        assert_eq!(c.report()["c"].grants, 1);
        // A new request of the same user is a new session.
        let second = answer(&offer(&mut c, 6, "u1", "c")).unwrap().unwrap();
        assert_ne!(first, second);
        assert_eq!(c.sessions_of("c"), 2);
    }

    #[test]
    fn a_latched_services_newest_value_goes_to_every_broker_it_registers_with() {
        let mut c = core();
        assert!(c.latch("a"));
        assert!(!c.latch("c"), "a command service is not latched");
        let latest = |out: &[SystemOutput]| -> Vec<(String, u64, Vec<u8>)> {
            out.iter()
                .filter_map(|o| match o {
                    SystemOutput::ToBroker(ToBroker::Latest {
                        service,
                        sent_ns,
                        payload,
                        ..
                    }) => Some((service.clone(), *sent_ns, payload.clone())),
                    _ => None,
                })
                .collect()
        };
        let enc = |x: f64| muster_shared::protocol::encode(&Payload::Scalar(x)).unwrap();
        // Published before any broker: kept, sent to none.
        c.publish("a", &Payload::Scalar(1.0), 10).unwrap();
        assert_eq!(latest(&outs(&mut c)), vec![]);
        c.handle(ToSystem::Registered {
            epoch: 1,
            broker_pid: 9,
        });
        assert_eq!(latest(&outs(&mut c)), vec![("a".into(), 10, enc(1.0))]);
        // Registered: each update goes at once.
        c.publish("a", &Payload::Scalar(2.0), 20).unwrap();
        c.publish("a", &Payload::Scalar(3.0), 30).unwrap();
        assert_eq!(
            latest(&outs(&mut c)),
            vec![("a".into(), 20, enc(2.0)), ("a".into(), 30, enc(3.0))]
        );
        // The broker lost, another (a restart, a standby taking over): it gets the newest
        // at once, not at the service's next update.
        c.broker_lost();
        c.publish("a", &Payload::Scalar(4.0), 40).unwrap();
        assert_eq!(latest(&outs(&mut c)), vec![]);
        c.handle(ToSystem::Registered {
            epoch: 2,
            broker_pid: 11,
        });
        assert_eq!(latest(&outs(&mut c)), vec![("a".into(), 40, enc(4.0))]);
    }

    #[test]
    fn an_offer_opens_the_brokers_session_and_confirms_it() {
        let mut c = core();
        let out = offer(&mut c, 1, "u1", "a");
        let session = answer(&out).unwrap().unwrap();
        assert_eq!(session, sid("u1", 1, "a"));
        let to_user = out
            .iter()
            .position(|o| matches!(o,
            SystemOutput::ToUser(u, ToUser::Granted { session: s, kind: ServiceKind::Data, system_pid: 7, relayed: false, .. })
                if u.0 == "u1" && *s == session))
            .expect("the session opened (a remote user's path is set up from it)");
        let to_broker = out
            .iter()
            .position(|o| matches!(o, SystemOutput::ToBroker(ToBroker::OfferAnswer { .. })))
            .unwrap();
        assert!(to_broker < to_user, "{out:?}");
        assert_eq!(c.sessions_of("a"), 1);
    }

    #[test]
    fn refuses_beyond_its_own_quota_when_overloaded_and_for_unknown_services() {
        let mut c = core();
        assert!(answer(&offer(&mut c, 1, "u1", "a")).unwrap().is_ok());
        assert!(answer(&offer(&mut c, 2, "u2", "a"))
            .unwrap()
            .unwrap_err()
            .contains("overloaded"));
        assert!(answer(&offer(&mut c, 3, "u2", "zz"))
            .unwrap()
            .unwrap_err()
            .contains("no service"));
        c.set_overloaded(true);
        assert_eq!(
            answer(&offer(&mut c, 4, "u2", "c")),
            Some(Err("overloaded".into()))
        );
    }

    #[test]
    fn a_session_limit_over_all_services_refuses_with_its_reason_and_ends_nothing() {
        let mut c = core();
        c.set_session_limit(Some(2), "overburdened: tracking 3 targets");
        assert!(answer(&offer(&mut c, 1, "u1", "c")).unwrap().is_ok());
        assert!(answer(&offer(&mut c, 2, "u2", "a")).unwrap().is_ok());
        assert_eq!(
            answer(&offer(&mut c, 3, "u3", "c")),
            Some(Err("overburdened: tracking 3 targets".into()))
        );
        // Lowering the limit below what is held ends nothing.
        c.set_session_limit(Some(1), "overburdened");
        assert_eq!(c.sessions().count(), 2);
        assert_eq!(c.report()["c"].refusals, 1);
        c.set_session_limit(None, "");
        assert!(answer(&offer(&mut c, 4, "u3", "c")).unwrap().is_ok());
    }

    #[test]
    fn sequence_numbers_count_per_session() {
        let mut c = core();
        let s1 = answer(&offer(&mut c, 1, "u1", "c")).unwrap().unwrap();
        let s2 = answer(&offer(&mut c, 2, "u2", "c")).unwrap().unwrap();
        assert_ne!(s1, s2);
        c.status(s1, TaskStatus::Idle);
        c.status(s1, TaskStatus::Idle);
        c.status(s2, TaskStatus::Idle);
        let seqs: Vec<(SessionId, u64)> = outs(&mut c)
            .into_iter()
            .filter_map(|o| match o {
                SystemOutput::ToUser(_, ToUser::Status { session, seq, .. }) => {
                    Some((session, seq))
                }
                _ => None,
            })
            .collect();
        assert_eq!(seqs, vec![(s1, 1), (s1, 2), (s2, 1)]);
    }

    #[test]
    fn a_tick_goes_to_the_users_of_other_hosts_first_then_to_this_hosts() {
        let mut c = SystemCore::new("t1", 7, vec![spec("d", ServiceKind::Data, 10)]);
        // Local users (a process each, and one over UDP) and users of host a (reached
        // through a's relay, read by this host's broker, process 3), offered in no
        // particular order; the session numbers are hashes.
        let users = [
            ("u1", 11),
            ("x@a", 3),
            ("u2", 12),
            ("u3", 13),
            ("udp", 0),
            ("y@a", 3),
            ("u4", 14),
            ("z@a", 3),
        ];
        for (t, (u, pid)) in (1..).zip(users) {
            assert!(answer(&offered_to(&mut c, t, u, pid, "d")).unwrap().is_ok());
        }
        let p = Payload::Text("tick".into());
        assert_eq!(c.publish("d", &p, 8).unwrap(), users.len());
        let order: Vec<String> = outs(&mut c)
            .into_iter()
            .filter_map(|o| match o {
                SystemOutput::ToUser(u, ToUser::Update { seq: 1, .. }) => Some(u.0),
                _ => None,
            })
            .collect();
        assert_eq!(order.len(), users.len());
        let (far, near) = order.split_at(3);
        assert!(far.iter().all(|u| u.contains('@')), "{order:?}");
        assert!(near.iter().all(|u| !u.contains('@')), "{order:?}");
    }

    #[test]
    fn one_sessions_update_goes_to_that_session_only_and_counts_in_its_sequence() {
        let mut c = core();
        let s1 = answer(&offer(&mut c, 1, "u1", "c")).unwrap().unwrap();
        let s2 = answer(&offer(&mut c, 2, "u2", "c")).unwrap().unwrap();
        let p = Payload::Pose2d {
            x: 1.0,
            y: 2.0,
            theta: 0.0,
        };
        assert_eq!(c.publish_session(s2, &p, 7).unwrap(), 1);
        assert_eq!(c.publish("c", &p, 8).unwrap(), 2);
        assert_eq!(c.publish_session(SessionId(12345), &p, 9).unwrap(), 0);
        let seqs: Vec<(SessionId, u64, u64)> = outs(&mut c)
            .into_iter()
            .filter_map(|o| match o {
                SystemOutput::ToUser(
                    _,
                    ToUser::Update {
                        session,
                        seq,
                        sent_ns,
                        ..
                    },
                ) => Some((session, seq, sent_ns)),
                _ => None,
            })
            .collect();
        let mut want = vec![(s2, 1, 7), (s1, 1, 8), (s2, 2, 8)];
        want[1..].sort();
        let mut got = seqs.clone();
        got[1..].sort();
        assert_eq!(got, want, "{seqs:?}");
    }

    #[test]
    fn input_only_from_the_session_holder() {
        let mut c = core();
        let s = answer(&offer(&mut c, 1, "u1", "c")).unwrap().unwrap();
        c.handle(ToSystem::Input {
            user: UserId("u2".into()),
            session: s,
            payload: Payload::Scalar(1.0),
        });
        c.handle(ToSystem::Input {
            user: UserId("u1".into()),
            session: SessionId(99),
            payload: Payload::Scalar(1.0),
        });
        c.handle(ToSystem::Input {
            user: UserId("u1".into()),
            session: s,
            payload: Payload::Scalar(2.0),
        });
        let inputs: Vec<SystemEvent> = std::iter::from_fn(|| c.poll_event())
            .filter(|e| matches!(e, SystemEvent::Input { .. }))
            .collect();
        assert_eq!(
            inputs,
            vec![SystemEvent::Input {
                session: s,
                service: "c".into(),
                payload: Payload::Scalar(2.0)
            }]
        );
        // Only the holder can end it, too.
        c.handle(ToSystem::End {
            user: UserId("u2".into()),
            session: s,
        });
        assert_eq!(c.sessions_of("c"), 1);
        c.handle(ToSystem::End {
            user: UserId("u1".into()),
            session: s,
        });
        assert_eq!(c.sessions_of("c"), 0);
        let out = outs(&mut c);
        assert!(
            out.contains(&SystemOutput::ToBroker(ToBroker::SessionEnded {
                system: "t1".into(),
                session: s
            }))
        );
        assert!(
            out.contains(&SystemOutput::ToUser(
                UserId("u1".into()),
                ToUser::Ended {
                    session: s,
                    reason: EndReason::ByUser,
                    last_seq: 0,
                }
            )),
            "the end is confirmed to the user: {out:?}"
        );
    }

    #[test]
    fn reregistration_reports_live_sessions_and_withdrawals() {
        let mut c = core();
        let s = answer(&offer(&mut c, 1, "u1", "c")).unwrap().unwrap();
        c.withdraw("a");
        outs(&mut c);
        c.broker_lost();
        c.register();
        let out = outs(&mut c);
        let Some(SystemOutput::ToBroker(ToBroker::Register { sessions, .. })) = out.first() else {
            panic!("{out:?}")
        };
        assert_eq!(
            sessions,
            &vec![ActiveSession {
                session: s,
                service: "c".into(),
                user: UserId("u1".into()),
                relayed: false,
            }]
        );
        c.handle(ToSystem::Registered {
            epoch: 2,
            broker_pid: 9,
        });
        let out = outs(&mut c);
        assert!(out.contains(&SystemOutput::WatchBroker(9)));
        assert!(out.contains(&SystemOutput::ToBroker(ToBroker::Withdraw {
            system: "t1".into(),
            service: "a".into()
        })));
        // A duplicate answer (we registered twice while the broker started) changes nothing.
        c.handle(ToSystem::Registered {
            epoch: 2,
            broker_pid: 9,
        });
        assert!(outs(&mut c).is_empty());
    }

    #[test]
    fn a_dead_user_loses_its_sessions_and_pings_are_answered() {
        let mut c = core();
        answer(&offer(&mut c, 1, "u1", "c")).unwrap().unwrap();
        c.user_died(&UserId("u1".into()));
        assert_eq!(c.sessions().count(), 0);
        c.handle(ToSystem::Ping { nonce: 5 });
        assert!(
            outs(&mut c).contains(&SystemOutput::ToBroker(ToBroker::Pong {
                system: "t1".into(),
                nonce: 5,
                held: Some(SessionDigest::default()),
            }))
        );
    }

    #[test]
    fn a_session_number_another_request_holds_is_refused_and_changes_nothing() {
        let mut c = core();
        let first = answer(&offer(&mut c, 1, "u1", "c")).unwrap().unwrap();
        // A request whose number collides with that session (a hostile or broken
        // broker): refused, and the session held goes on as it was.
        c.handle(ToSystem::Offer {
            ticket: 2,
            session: first,
            user: UserId("u2".into()),
            user_pid: 0,
            req: 7,
            service: "c".into(),
            remote: None,
        });
        let out = outs(&mut c);
        assert!(answer(&out)
            .unwrap()
            .unwrap_err()
            .contains("another request's"));
        let held: Vec<(SessionId, String)> =
            c.sessions().map(|(s, u, _)| (s, u.0.clone())).collect();
        assert_eq!(held, [(first, "u1".to_string())]);
        assert_eq!(c.report()["c"].refusals, 1);
    }

    #[test]
    fn the_broker_hears_the_limit_when_registered_and_whenever_it_moves() {
        let limits = |out: Vec<SystemOutput>| -> Vec<Option<(u32, String)>> {
            out.into_iter()
                .filter_map(|o| match o {
                    SystemOutput::ToBroker(ToBroker::Limit { system, limit }) => {
                        assert_eq!(system, "t1");
                        Some(limit.map(|l| (l.sessions, l.reason)))
                    }
                    _ => None,
                })
                .collect()
        };
        let mut c = core();
        // Before any broker registered us, nobody is told.
        c.set_session_limit(Some(3), "overburdened");
        c.register();
        assert_eq!(limits(outs(&mut c)), []);
        // With the registration, the broker hears it.
        c.handle(ToSystem::Registered {
            epoch: 1,
            broker_pid: 3,
        });
        assert_eq!(limits(outs(&mut c)), [Some((3, "overburdened".into()))]);
        // Overloaded takes no session at all; then back to the limit; then none.
        c.set_overloaded(true);
        assert_eq!(limits(outs(&mut c)), [Some((0, "overloaded".into()))]);
        c.set_session_limit(Some(5), "overburdened");
        assert_eq!(limits(outs(&mut c)), [], "still overloaded: no change");
        c.set_overloaded(false);
        assert_eq!(limits(outs(&mut c)), [Some((5, "overburdened".into()))]);
        c.set_session_limit(Some(5), "overburdened");
        assert_eq!(limits(outs(&mut c)), [], "the same limit again");
        c.set_session_limit(None, "");
        assert_eq!(limits(outs(&mut c)), [None]);
    }
}
