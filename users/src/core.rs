//! A user's side of the protocol as a pure state machine: requests, sessions with gap
//! counting, task input, and links (data session → command session), run in the user's
//! own client so they survive a broker crash. No I/O, no clock.

use muster_shared::names::Address;
use muster_shared::protocol::{LinkInfo, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::ListFilter;
use muster_shared::types::{
    link_compatible, EndReason, Payload, Refusal, ServiceId, ServiceKind, SessionId, TaskStatus,
    UserId,
};
use std::collections::{BTreeMap, VecDeque};

/// What the user client wants sent or watched.
#[derive(Clone, Debug, PartialEq)]
pub enum UserOutput {
    /// Send to the broker.
    ToBroker(ToBroker),
    /// Send to a system directly.
    ToSystem(String, ToSystem),
    /// Watch a system's process for death.
    WatchSystem(String, u32),
    /// Forget a system's ports and watch.
    ForgetSystem(String),
    /// Watch the broker's process for death.
    WatchBroker(u32),
}

/// What happened, for the user program.
#[derive(Clone, Debug, PartialEq)]
pub enum UserEvent {
    /// The broker welcomed us.
    Connected {
        /// Broker run.
        epoch: u64,
    },
    /// The broker is gone; sessions and links go on, new requests wait for a new broker.
    BrokerLost,
    /// The service list changed; refresh to see it.
    ListChanged,
    /// A request waits in a task queue.
    Queued {
        /// Request number.
        req: u64,
        /// Service.
        service: ServiceId,
        /// Position, 1 = next.
        position: u16,
    },
    /// A request was granted: a one-to-one session is open.
    Granted {
        /// Request number.
        req: u64,
        /// The session.
        session: SessionId,
        /// Service.
        service: ServiceId,
        /// Data or command.
        kind: ServiceKind,
        /// Payload type.
        payload: String,
        /// An open payload type's schema: how to read its [`Payload::Encoded`] updates.
        schema: Option<muster_shared::types::Schema>,
    },
    /// The system confirmed a session the user ended (its `Ended` arrived).
    EndConfirmed {
        /// The session.
        session: SessionId,
    },
    /// A request was refused.
    Refused {
        /// Request number.
        req: u64,
        /// Service.
        service: ServiceId,
        /// Why.
        reason: Refusal,
    },
    /// The broker's answer to an operator's action ([`UserCore::operate`]).
    Operated {
        /// The action's number.
        id: u64,
        /// Done (with the status, for a status read), or why not.
        result: Result<Option<Box<muster_shared::protocol::BrokerStatus>>, String>,
    },
    /// A data update.
    Update {
        /// The session.
        session: SessionId,
        /// Service.
        service: ServiceId,
        /// Sequence number.
        seq: u64,
        /// Updates lost before this one (sequence gap).
        gap: u64,
        /// When the system sent it (CLOCK_MONOTONIC ns; 0 if unknown).
        sent_ns: u64,
        /// The data.
        payload: Payload,
    },
    /// Task status on a command session.
    Status {
        /// The session.
        session: SessionId,
        /// Service.
        service: ServiceId,
        /// Sequence number.
        seq: u64,
        /// The status.
        status: TaskStatus,
    },
    /// A session ended.
    Ended {
        /// The session.
        session: SessionId,
        /// Service.
        service: ServiceId,
        /// Why.
        reason: EndReason,
        /// Frames the system sent last that never came (it said its last sequence
        /// number with the end): a gap at the end, which no later frame can show.
        lost_at_end: u64,
    },
    /// Both ends of a link are granted; data now flows into the command service.
    LinkUp {
        /// The link.
        link: u64,
    },
    /// One data update was forwarded as task input.
    LinkForwarded {
        /// The link.
        link: u64,
        /// The input sent to the command system.
        input: Payload,
    },
    /// A record of the broker's event feed, sent to a remote operator (local readers
    /// read the feed in shared memory).
    Feed(muster_shared::protocol::EventRecord),
    /// A link ended.
    LinkEnded {
        /// The link.
        link: u64,
        /// Why.
        reason: String,
    },
}

#[derive(Clone, Debug)]
struct Pending {
    service: ServiceId,
    link: Option<u64>,
}

#[derive(Clone, Debug)]
struct SessionInfo {
    service: ServiceId,
    /// The request it answers.
    req: u64,
    system: String,
    kind: ServiceKind,
    payload: String,
    /// Its values are of its declared type for sure: a built-in one, an open payload
    /// with its schema, or another host's (whose schema does not cross).
    open: bool,
    last_seq: u64,
    /// Its update 0 (a latched service's value) came.
    had_latched: bool,
    gaps: u64,
    /// Of `gaps`, those the system's `Ended` showed (its last frames never came).
    lost_at_end: u64,
    link: Option<u64>,
    /// The process that granted it: the only one whose frames about it are believed.
    system_pid: u32,
    /// Which copies of its grant came ([`DIRECT`], [`RELAYED`]).
    copies: u8,
}

/// The system's own copy of a grant.
const DIRECT: u8 = 1;
/// The broker's copy of a grant ([`ToUser::Granted`] `relayed`).
const RELAYED: u8 = 2;

#[derive(Clone, Debug)]
struct LinkState {
    info: LinkInfo,
    data: Option<SessionId>,
    command: Option<SessionId>,
    command_payload: Option<String>,
    forwarded: u64,
}

/// Per-session counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SessionCounters {
    /// Highest sequence number seen.
    pub last_seq: u64,
    /// Updates lost (gaps in sequence numbers).
    pub gaps: u64,
}

/// One user's protocol state.
#[derive(Debug)]
pub struct UserCore {
    id: UserId,
    pid: u32,
    watch_list: bool,
    /// The part of the list watched (`None`: all), said again after each hello.
    watch_filter: Option<ListFilter>,
    connected: Option<u64>,
    next_req: u64,
    next_link: u64,
    pending: BTreeMap<u64, Pending>,
    sessions: BTreeMap<SessionId, SessionInfo>,
    links: BTreeMap<u64, LinkState>,
    out: VecDeque<UserOutput>,
    events: VecDeque<UserEvent>,
    stale_frames: u64,
    /// The broker that welcomed us: the only process whose queue answers are believed.
    broker_pid: Option<u32>,
    /// Local frames refused because their writer was not who they claimed to be.
    impersonations: u64,
    /// Sessions this user ended, until the system confirms.
    ending: std::collections::BTreeSet<SessionId>,
    /// A broker welcomed this user at least once (so a standby's copy knows it).
    welcomed: bool,
    /// Grants of a session this user already held (ignored).
    regrants: u64,
    /// Grants for a request this user no longer had out (ended at once).
    unwanted_grants: u64,
    /// The sessions this user held last (at most [`RECENTLY_CLOSED`]), oldest first: a
    /// repeated offer that crossed a takeover may be answered with one of them after
    /// the user ended it, before the system heard the end.
    /// With each, the copies of its grant that came.
    closed: std::collections::VecDeque<(SessionId, u8)>,
}

/// How many closed sessions a user remembers.
const RECENTLY_CLOSED: usize = 256;

impl UserCore {
    /// A user `id` in process `pid`; `watch_list` asks the broker to ring on list changes.
    pub fn new(id: UserId, pid: u32, watch_list: bool) -> Self {
        UserCore {
            ending: std::collections::BTreeSet::new(),
            closed: std::collections::VecDeque::new(),
            id,
            pid,
            watch_list,
            watch_filter: None,
            connected: None,
            next_req: 1,
            next_link: 1,
            pending: BTreeMap::new(),
            sessions: BTreeMap::new(),
            links: BTreeMap::new(),
            out: VecDeque::new(),
            events: VecDeque::new(),
            stale_frames: 0,
            broker_pid: None,
            impersonations: 0,
            welcomed: false,
            regrants: 0,
            unwanted_grants: 0,
        }
    }

    /// This user's id.
    pub fn id(&self) -> &UserId {
        &self.id
    }

    /// The broker run we are connected to, if any.
    pub fn connected(&self) -> Option<u64> {
        self.connected
    }

    /// Next output.
    pub fn poll_output(&mut self) -> Option<UserOutput> {
        self.out.pop_front()
    }

    /// Next event.
    pub fn poll_event(&mut self) -> Option<UserEvent> {
        self.events.pop_front()
    }

    /// Open sessions.
    pub fn sessions(&self) -> impl Iterator<Item = (SessionId, &ServiceId, ServiceKind)> {
        self.sessions
            .iter()
            .map(|(id, s)| (*id, &s.service, s.kind))
    }

    /// Sequence counters of a session.
    pub fn counters(&self, session: SessionId) -> Option<SessionCounters> {
        self.sessions.get(&session).map(|s| SessionCounters {
            last_seq: s.last_seq,
            gaps: s.gaps,
        })
    }

    /// The link a session belongs to, if a link asked for it.
    pub fn session_link(&self, session: SessionId) -> Option<u64> {
        self.sessions.get(&session).and_then(|s| s.link)
    }

    /// Whether request `req` still waits for an answer (pending or queued).
    pub fn is_pending(&self, req: u64) -> bool {
        self.pending.contains_key(&req)
    }

    /// Requests not yet answered by a grant or a refusal.
    pub fn pending_requests(&self) -> usize {
        self.pending.len()
    }

    /// Links currently set up or being set up.
    pub fn links(&self) -> impl Iterator<Item = &LinkInfo> {
        self.links.values().map(|l| &l.info)
    }

    /// Whether a local frame written by process `pid` may say `msg`. The broker's
    /// answers only from the process that owns the broker's inbox; a grant only from the
    /// process that owns the granting system's inbox and names itself; a session's
    /// updates, status and end only from the process that granted it (`owner` tells who
    /// owns an address's inbox: [`muster_shared::ipc::Endpoint::owner_pid`]). `None` (the
    /// writer cannot be told) is let through. Refusals are counted
    /// ([`UserCore::impersonations`]) and logged.
    pub fn sender_allowed(
        &mut self,
        pid: Option<u32>,
        msg: &ToUser,
        mut owner: impl FnMut(&Address) -> Option<u32>,
    ) -> bool {
        let Some(pid) = pid else { return true };
        let broker_pid = self.broker_pid;
        let from_broker = |owner: &mut dyn FnMut(&Address) -> Option<u32>| {
            broker_pid == Some(pid) || owner(&Address::Broker) == Some(pid)
        };
        let ok = match msg {
            ToUser::Welcome { broker_pid, .. } => {
                *broker_pid == pid && owner(&Address::Broker) == Some(pid)
            }
            ToUser::Queued { .. } | ToUser::Refused { .. } | ToUser::Operated { .. } => {
                from_broker(&mut owner)
            }
            // The broker's copy of a grant comes from the broker.
            ToUser::Granted { relayed: true, .. } => from_broker(&mut owner),
            ToUser::Granted {
                service,
                system_pid,
                ..
            } => {
                let system = service
                    .split()
                    .map(|(s, _)| s.to_string())
                    .unwrap_or_default();
                *system_pid == pid && owner(&Address::System(system)) == Some(pid)
            }
            // Another host's system's frames come from this host's broker (its relay),
            // whichever process that is now.
            // A latched service's update 0 comes from the broker, with the grant.
            ToUser::Update {
                session, seq: 0, ..
            } => self
                .sessions
                .get(session)
                .is_none_or(|s| s.system_pid == pid || from_broker(&mut owner)),
            ToUser::Update { session, .. } | ToUser::Status { session, .. } => {
                self.sessions.get(session).is_none_or(|s| {
                    s.system_pid == pid || (s.service.remote().is_some() && from_broker(&mut owner))
                })
            }
            // The broker ends a grant its system could not take.
            ToUser::Ended { session, .. } => {
                self.sessions
                    .get(session)
                    .is_none_or(|s| s.system_pid == pid)
                    || from_broker(&mut owner)
            }
        };
        muster_shared::protocol::note_impersonation(
            ok,
            &mut self.impersonations,
            pid,
            "the broker or a system",
        )
    }

    /// Local frames refused by [`UserCore::sender_allowed`].
    pub fn impersonations(&self) -> u64 {
        self.impersonations
    }

    /// Grants of a session already held, ignored (a repeated offer's answer).
    pub fn regrants(&self) -> u64 {
        self.regrants
    }

    /// Grants for requests no longer out (given up, or granted twice), ended at once.
    pub fn unwanted_grants(&self) -> u64 {
        self.unwanted_grants
    }

    /// Frames dropped because they belonged to no session or were out of order.
    pub fn stale_frames(&self) -> u64 {
        self.stale_frames
    }

    /// Says hello (again, after a broker restart), re-sending requests still pending.
    /// A new broker that did not take over the last one's state relays none of the
    /// sessions on other hosts that went through it: they end here.
    pub fn hello(&mut self) {
        if self.pid != 0 {
            let far: Vec<SessionId> = self
                .sessions
                .iter()
                .filter(|(_, s)| s.service.remote().is_some())
                .map(|(id, _)| *id)
                .collect();
            for id in far {
                self.close(id, EndReason::PeerGone, false);
            }
        }
        let links = self.links.values().map(|l| l.info.clone()).collect();
        self.send_broker(ToBroker::Hello {
            user: self.id.clone(),
            pid: self.pid,
            links,
            watch_list: self.watch_list,
        });
        if self.watch_filter.is_some() {
            self.say_watch();
        }
        self.resend_pending();
    }

    /// Watches only the part of the list `filter` lets through (`None`: all of it): the
    /// broker rings this user only when a service of that part changes, comes or goes.
    /// A user that does not watch the list (see [`UserCore::new`]) is not rung at all.
    pub fn watch_part(&mut self, filter: Option<ListFilter>) {
        let filter = filter.filter(|f| !f.is_everything());
        if filter == self.watch_filter {
            return;
        }
        self.watch_filter = filter;
        self.say_watch();
    }

    /// Tells the broker the part of the list watched, if this user watches it.
    fn say_watch(&mut self) {
        if self.watch_list {
            self.send_broker(ToBroker::WatchList {
                user: self.id.clone(),
                filter: self.watch_filter.clone(),
            });
        }
    }

    /// Whether this user has something the broker must hear again after a takeover
    /// (requests out, or links).
    pub fn awaits_broker(&self) -> bool {
        !self.pending.is_empty() || !self.links.is_empty()
    }

    /// The broker this user follows, if any.
    pub fn broker_pid(&self) -> Option<u32> {
        self.broker_pid
    }

    /// A standby took over the broker (run `epoch`, process `pid`) with this user's
    /// state: no hello is needed, but what the old broker may not have read is repeated
    /// (pending requests and links; the broker ignores what it already has). A user the
    /// broker never welcomed says hello instead.
    pub fn adopt(&mut self, epoch: u64, pid: u32) {
        if !self.welcomed {
            return self.hello();
        }
        self.connected = Some(epoch);
        self.broker_pid = Some(pid);
        self.out.push_back(UserOutput::WatchBroker(pid));
        self.events.push_back(UserEvent::Connected { epoch });
        let links: Vec<LinkInfo> = self.links.values().map(|l| l.info.clone()).collect();
        for link in links {
            self.send_broker(ToBroker::LinkOpened {
                user: self.id.clone(),
                link,
            });
        }
        self.resend_pending();
    }

    fn resend_pending(&mut self) {
        let pending: Vec<(u64, ServiceId)> = self
            .pending
            .iter()
            .map(|(r, p)| (*r, p.service.clone()))
            .collect();
        for (req, service) in pending {
            self.send_broker(ToBroker::Request {
                user: self.id.clone(),
                req,
                service,
            });
        }
    }

    /// The broker died: existing sessions and links go on.
    pub fn broker_lost(&mut self) {
        if self.connected.take().is_some() {
            self.events.push_back(UserEvent::BrokerLost);
        }
    }

    /// The broker says the list changed.
    pub fn list_changed(&mut self) {
        self.events.push_back(UserEvent::ListChanged);
    }

    /// Asks for a service; returns the request number echoed in its answer.
    pub fn request(&mut self, service: ServiceId) -> u64 {
        self.request_for(service, None)
    }

    fn request_for(&mut self, service: ServiceId, link: Option<u64>) -> u64 {
        let req = self.next_req;
        self.next_req += 1;
        self.pending.insert(
            req,
            Pending {
                service: service.clone(),
                link,
            },
        );
        self.send_broker(ToBroker::Request {
            user: self.id.clone(),
            req,
            service,
        });
        req
    }

    /// Gives up a pending or queued request.
    pub fn cancel(&mut self, req: u64) {
        if self.pending.remove(&req).is_some() {
            self.send_broker(ToBroker::Cancel {
                user: self.id.clone(),
                req,
            });
        }
    }

    /// Ends a session from the user's side; the system is told directly.
    pub fn end(&mut self, session: SessionId) {
        if self.sessions.contains_key(&session) {
            if self.ending.len() >= 1024 {
                self.ending.pop_first();
            }
            self.ending.insert(session);
        }
        self.close(session, EndReason::ByUser, true);
    }

    fn close(&mut self, session: SessionId, reason: EndReason, tell_system: bool) {
        let Some(s) = self.sessions.remove(&session) else {
            return;
        };
        if self.closed.len() >= RECENTLY_CLOSED {
            self.closed.pop_front();
        }
        self.closed.push_back((session, s.copies));
        if tell_system {
            self.out.push_back(UserOutput::ToSystem(
                s.system.clone(),
                ToSystem::End {
                    user: self.id.clone(),
                    session,
                },
            ));
        }
        if !self.sessions.values().any(|o| o.system == s.system) {
            self.out
                .push_back(UserOutput::ForgetSystem(s.system.clone()));
        }
        self.events.push_back(UserEvent::Ended {
            session,
            service: s.service,
            reason: reason.clone(),
            lost_at_end: s.lost_at_end,
        });
        if let Some(link) = s.link {
            self.end_link(link, format!("a linked session ended: {reason}"));
        }
    }

    /// Sends task input on a command session.
    pub fn input(&mut self, session: SessionId, payload: Payload) -> Result<(), String> {
        let s = self
            .sessions
            .get(&session)
            .ok_or_else(|| format!("no session {session}"))?;
        if s.kind != ServiceKind::Command {
            return Err(format!(
                "session {session} is a data session: it takes no input"
            ));
        }
        let system = s.system.clone();
        let msg = ToSystem::Input {
            user: self.id.clone(),
            session,
            payload,
        };
        // Too large for the path to the system: refused here, said, not dropped unseen.
        muster_shared::fits::to_system(&msg, self.remote())
            .map_err(|e| format!("input not sent on session {session}: {e}"))?;
        self.out.push_back(UserOutput::ToSystem(system, msg));
        Ok(())
    }

    /// Whether this user is remote (its frames go as UDP datagrams): a remote user's
    /// core is made with pid 0.
    fn remote(&self) -> bool {
        self.pid == 0
    }

    /// Links data service `data` into command service `command`: requests both, then
    /// forwards every data update as task input. Returns the link number.
    pub fn link(&mut self, data: ServiceId, command: ServiceId) -> u64 {
        let link = self.next_link;
        self.next_link += 1;
        let info = LinkInfo {
            link,
            data: data.clone(),
            command: command.clone(),
        };
        self.links.insert(
            link,
            LinkState {
                info,
                data: None,
                command: None,
                command_payload: None,
                forwarded: 0,
            },
        );
        self.request_for(data, Some(link));
        self.request_for(command, Some(link));
        link
    }

    /// Ends a link and both its sessions.
    pub fn unlink(&mut self, link: u64) {
        self.end_link(link, "ended by the user".into());
    }

    fn end_link(&mut self, link: u64, reason: String) {
        let Some(l) = self.links.remove(&link) else {
            return;
        };
        let reqs: Vec<u64> = self
            .pending
            .iter()
            .filter(|(_, p)| p.link == Some(link))
            .map(|(r, _)| *r)
            .collect();
        for r in reqs {
            self.cancel(r);
        }
        for s in [l.data, l.command].into_iter().flatten() {
            if let Some(info) = self.sessions.get_mut(&s) {
                info.link = None;
            }
            self.close(s, EndReason::ByUser, true);
        }
        if l.data.is_some() && l.command.is_some() {
            self.send_broker(ToBroker::LinkClosed {
                user: self.id.clone(),
                link,
            });
        }
        self.events.push_back(UserEvent::LinkEnded { link, reason });
    }

    /// A system's process died: its sessions end.
    pub fn system_died(&mut self, system: &str) {
        let ids: Vec<SessionId> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.system == system)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            self.close(id, EndReason::PeerGone, false);
        }
    }

    /// Leaves: ends links and sessions, cancels requests, says goodbye.
    pub fn shutdown(&mut self) {
        let links: Vec<u64> = self.links.keys().copied().collect();
        for l in links {
            self.end_link(l, "user leaving".into());
        }
        let ids: Vec<SessionId> = self.sessions.keys().copied().collect();
        for id in ids {
            self.close(id, EndReason::ByUser, true);
        }
        let reqs: Vec<u64> = self.pending.keys().copied().collect();
        for r in reqs {
            self.cancel(r);
        }
        self.send_broker(ToBroker::Goodbye {
            user: self.id.clone(),
        });
    }

    /// An operator's action (only operators may: the broker says why not otherwise);
    /// its answer comes as [`UserEvent::Operated`] with the number returned.
    pub fn operate(&mut self, op: muster_shared::protocol::Operation) -> u64 {
        let id = self.next_req;
        self.next_req += 1;
        self.send_broker(ToBroker::Operate {
            user: self.id.clone(),
            id,
            op,
        });
        id
    }

    /// A record of the broker's event feed came (for a remote operator).
    pub fn feed(&mut self, record: muster_shared::protocol::EventRecord) {
        self.events.push_back(UserEvent::Feed(record));
    }

    /// Handles one frame from the inbox.
    pub fn handle(&mut self, msg: ToUser) {
        match msg {
            ToUser::Operated { id, result } => {
                self.events.push_back(UserEvent::Operated { id, result });
            }
            ToUser::Welcome { epoch, broker_pid } => {
                self.welcomed = true;
                self.connected = Some(epoch);
                self.broker_pid = Some(broker_pid);
                self.out.push_back(UserOutput::WatchBroker(broker_pid));
                self.events.push_back(UserEvent::Connected { epoch });
            }
            ToUser::Queued { req, position } => {
                if let Some(p) = self.pending.get(&req) {
                    muster_shared::trace::stamp(
                        muster_shared::trace::Stage::UserQueued,
                        &self.id,
                        req,
                    );
                    let service = p.service.clone();
                    self.events.push_back(UserEvent::Queued {
                        req,
                        service,
                        position,
                    });
                }
            }
            ToUser::Refused { req, reason } => {
                if let Some(p) = self.pending.remove(&req) {
                    self.events.push_back(UserEvent::Refused {
                        req,
                        service: p.service,
                        reason: reason.clone(),
                    });
                    if let Some(link) = p.link {
                        self.end_link(link, format!("a linked request was refused: {reason}"));
                    }
                }
            }
            ToUser::Granted {
                req,
                session,
                service,
                kind,
                payload,
                schema,
                system_pid,
                relayed,
            } => {
                let copy = if relayed { RELAYED } else { DIRECT };
                self.granted(
                    req,
                    session,
                    service,
                    (kind, payload, schema),
                    system_pid,
                    copy,
                )
            }
            ToUser::Update {
                session,
                seq,
                sent_ns,
                payload,
            } => self.update(session, seq, sent_ns, payload),
            ToUser::Status {
                session,
                seq,
                status,
            } => {
                let Some((service, _, _)) = self.accept_seq(session, seq) else {
                    return;
                };
                self.events.push_back(UserEvent::Status {
                    session,
                    service,
                    seq,
                    status,
                });
            }
            ToUser::Ended {
                session,
                reason,
                last_seq,
            } => {
                if self.ending.remove(&session) {
                    self.events.push_back(UserEvent::EndConfirmed { session });
                } else {
                    if let Some(s) = self.sessions.get_mut(&session) {
                        s.lost_at_end = last_seq.saturating_sub(s.last_seq);
                        s.gaps += s.lost_at_end;
                    }
                    self.close(session, reason, false);
                }
            }
        }
    }

    /// Ends a session granted that this user does not take.
    fn end_at_once(&mut self, system: String, session: SessionId) {
        self.out.push_back(UserOutput::ToSystem(
            system,
            ToSystem::End {
                user: self.id.clone(),
                session,
            },
        ));
    }

    fn granted(
        &mut self,
        req: u64,
        session: SessionId,
        service: ServiceId,
        (kind, payload, schema): (ServiceKind, String, Option<muster_shared::types::Schema>),
        system_pid: u32,
        copy: u8,
    ) {
        let system = service
            .split()
            .map(|(s, _)| s.to_string())
            .unwrap_or_default();
        if let Some(s) = self.sessions.get_mut(&session) {
            if s.copies & copy == 0 {
                // The other copy of the grant that made it (the broker's or the system's).
                s.copies |= copy;
            } else {
                // The same grant again: the system answered a repeated offer (one that
                // crossed a broker takeover) with the session we already hold.
                self.regrants += 1;
            }
            return;
        }
        if self.pending.get(&req).is_some_and(|p| p.service != service) {
            // A grant under a pending request's number for another service than the one
            // asked for (a forged or misrouted grant): not taken; the request waits on.
            self.unwanted_grants += 1;
            return self.end_at_once(system, session);
        }
        let Some(p) = self.pending.remove(&req) else {
            // Granted after we gave up (cancelled, refused on timeout), or a session we
            // held and ended granted again (a repeated offer that crossed our end on its
            // way to the system): end it at once. Only the first is a second grant.
            match self.closed.iter_mut().find(|(s, _)| *s == session) {
                // The other copy of a grant whose session we already ended.
                Some((_, c)) if *c & copy == 0 => {
                    *c |= copy;
                    return;
                }
                Some(_) => self.regrants += 1,
                None => self.unwanted_grants += 1,
            }
            return self.end_at_once(system, session);
        };
        muster_shared::trace::stamp(muster_shared::trace::Stage::UserRecv, &self.id, req);
        // Another host's system is reached through this host's broker, whose process
        // may change (a standby takes over) while the system serves on: the federation
        // says when it goes.
        if service.remote().is_none() {
            self.out
                .push_back(UserOutput::WatchSystem(system.clone(), system_pid));
        }
        self.sessions.insert(
            session,
            SessionInfo {
                service: service.clone(),
                req,
                system,
                kind,
                payload: payload.clone(),
                open: schema.is_some() || service.remote().is_some(),
                last_seq: 0,
                had_latched: false,
                gaps: 0,
                lost_at_end: 0,
                link: p.link,
                system_pid,
                copies: copy,
            },
        );
        self.events.push_back(UserEvent::Granted {
            req,
            session,
            service,
            kind,
            payload: payload.clone(),
            schema,
        });
        let Some(link) = p.link else { return };
        let Some(l) = self.links.get_mut(&link) else {
            return;
        };
        match kind {
            ServiceKind::Data => l.data = Some(session),
            ServiceKind::Command => {
                l.command = Some(session);
                l.command_payload = Some(payload);
            }
        }
        if let (Some(d), Some(_)) = (l.data, l.command) {
            let (data_payload, data_open) = self
                .sessions
                .get(&d)
                .map(|s| (s.payload.clone(), s.open))
                .unwrap_or_default();
            let cmd_payload = l.command_payload.clone().unwrap_or_default();
            if !link_compatible(&data_payload, data_open, &cmd_payload) {
                self.end_link(
                    link,
                    format!("cannot link {data_payload} into {cmd_payload}"),
                );
                return;
            }
            let info = l.info.clone();
            self.send_broker(ToBroker::LinkOpened {
                user: self.id.clone(),
                link: info,
            });
            self.events.push_back(UserEvent::LinkUp { link });
        }
    }

    /// Checks a session frame's sequence number: frames for no session, repeated or out
    /// of order are dropped (counted as stale); a jump counts the lost ones as a gap.
    /// Update 0 (a latched service's value, from the broker with the grant) is taken
    /// once, before any other. Returns the session's service, the gap and its link.
    fn accept_seq(
        &mut self,
        session: SessionId,
        seq: u64,
    ) -> Option<(ServiceId, u64, Option<u64>)> {
        let Some(s) = self
            .sessions
            .get_mut(&session)
            .filter(|s| seq > s.last_seq || (seq == 0 && s.last_seq == 0 && !s.had_latched))
        else {
            self.stale_frames += 1;
            return None;
        };
        if seq == 0 {
            s.had_latched = true;
            return Some((s.service.clone(), 0, s.link));
        }
        let gap = seq - s.last_seq - 1;
        s.gaps += gap;
        s.last_seq = seq;
        Some((s.service.clone(), gap, s.link))
    }

    fn update(&mut self, session: SessionId, seq: u64, sent_ns: u64, payload: Payload) {
        let first = self
            .sessions
            .get(&session)
            .filter(|s| s.last_seq == 0 && !s.had_latched)
            .map(|s| s.req);
        let Some((service, gap, link)) = self.accept_seq(session, seq) else {
            return;
        };
        if let Some(req) = first {
            muster_shared::trace::stamp(muster_shared::trace::Stage::FirstUpdate, &self.id, req);
        }
        self.events.push_back(UserEvent::Update {
            session,
            service,
            seq,
            gap,
            sent_ns,
            payload: payload.clone(),
        });
        let Some(link) = link else { return };
        let Some(l) = self.links.get_mut(&link) else {
            return;
        };
        let (Some(cmd), Some(target)) = (l.command, l.command_payload.clone()) else {
            return;
        };
        let Some(input) = payload.convert_to(&target) else {
            // A lost target gives no goal (the command keeps its last one); any other
            // value that cannot be given ends the link, said, not dropped unseen.
            if !matches!(payload, Payload::Track2d(_)) {
                let why = format!(
                    "an update of type {} cannot be given to {target}",
                    payload.type_name()
                );
                self.end_link(link, why);
            }
            return;
        };
        let Some(system) = self.sessions.get(&cmd).map(|c| c.system.clone()) else {
            return;
        };
        let msg = ToSystem::Input {
            user: self.id.clone(),
            session: cmd,
            payload: input.clone(),
        };
        if let Err(e) = muster_shared::fits::to_system(&msg, self.pid == 0) {
            return self.end_link(link, format!("an update cannot be forwarded: {e}"));
        }
        l.forwarded += 1;
        self.out.push_back(UserOutput::ToSystem(system, msg));
        self.events
            .push_back(UserEvent::LinkForwarded { link, input });
    }

    fn send_broker(&mut self, msg: ToBroker) {
        self.out.push_back(UserOutput::ToBroker(msg));
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn user() -> UserCore {
        UserCore::new(UserId("u1".into()), 1, false)
    }

    fn outs(u: &mut UserCore) -> Vec<UserOutput> {
        std::iter::from_fn(|| u.poll_output()).collect()
    }

    fn events(u: &mut UserCore) -> Vec<UserEvent> {
        std::iter::from_fn(|| u.poll_event()).collect()
    }

    #[test]
    fn a_repeated_grant_of_a_held_session_is_ignored_not_ended() {
        let mut u = user();
        let req = u.request(ServiceId("t1/s0".into()));
        outs(&mut u);
        grant(&mut u, req, 7, "t1/s0", ServiceKind::Data, "pose2d");
        outs(&mut u);
        // The system answers a repeated offer (it crossed a takeover) with the same grant.
        grant(&mut u, req, 7, "t1/s0", ServiceKind::Data, "pose2d");
        assert!(
            !outs(&mut u)
                .iter()
                .any(|o| matches!(o, UserOutput::ToSystem(_, ToSystem::End { .. }))),
            "the held session must not be ended"
        );
        assert_eq!((u.regrants(), u.unwanted_grants()), (1, 0));
        // A grant of another session for the same request is unwanted and ended.
        grant(&mut u, req, 8, "t1/s0", ServiceKind::Data, "pose2d");
        assert!(outs(&mut u).iter().any(|o| matches!(
            o,
            UserOutput::ToSystem(_, ToSystem::End { session, .. }) if *session == SessionId(8)
        )));
        assert_eq!(u.unwanted_grants(), 1);
        // Session 7 ended by the user, then granted again by a repeated offer that
        // crossed the end: ended again, and not a second grant.
        u.end(SessionId(7));
        outs(&mut u);
        grant(&mut u, req, 7, "t1/s0", ServiceKind::Data, "pose2d");
        assert!(outs(&mut u).iter().any(|o| matches!(
            o,
            UserOutput::ToSystem(_, ToSystem::End { session, .. }) if *session == SessionId(7)
        )));
        assert_eq!((u.regrants(), u.unwanted_grants()), (2, 1));
    }

    #[test]
    fn the_two_copies_of_a_grant_make_one_session_in_either_order() {
        for first_relayed in [true, false] {
            let mut u = user();
            let req = u.request(ServiceId("t1/s0".into()));
            outs(&mut u);
            let copy = |relayed| data_grant(req, 7, "t1/s0", 50, relayed);
            u.handle(copy(first_relayed));
            u.handle(copy(!first_relayed));
            let grants = events(&mut u)
                .into_iter()
                .filter(|e| matches!(e, UserEvent::Granted { .. }))
                .count();
            assert_eq!(grants, 1, "one session, relayed first: {first_relayed}");
            assert!(outs(&mut u)
                .iter()
                .all(|o| !matches!(o, UserOutput::ToSystem(_, ToSystem::End { .. }))));
            assert_eq!((u.regrants(), u.unwanted_grants()), (0, 0));
            // A third copy is a repeated grant (an offer repeated across a takeover).
            u.handle(copy(first_relayed));
            assert_eq!((u.regrants(), u.unwanted_grants()), (1, 0));
        }
        // The second copy of a grant whose session the user already ended is let be:
        // the session was ended once, and is not ended again.
        let mut u = user();
        let req = u.request(ServiceId("t1/s0".into()));
        let copy = |relayed| data_grant(req, 9, "t1/s0", 50, relayed);
        u.handle(copy(false));
        u.end(SessionId(9));
        outs(&mut u);
        u.handle(copy(true));
        assert!(outs(&mut u).is_empty());
        assert_eq!((u.regrants(), u.unwanted_grants()), (0, 0));
        // The broker's copy alone (the system's never came) makes the session too.
        let mut u = user();
        let req = u.request(ServiceId("t1/s0".into()));
        u.handle(data_grant(req, 11, "t1/s0", 50, true));
        assert!(u.counters(SessionId(11)).is_some());
        update(&mut u, 11, 1);
        assert_eq!(u.stale_frames(), 0);
    }

    #[test]
    fn a_grant_for_another_service_under_a_pending_number_is_not_taken() {
        let mut u = user();
        let req = u.request(ServiceId("t1/s0".into()));
        outs(&mut u);
        // Another service's grant under that number: ended at once, the request waits on.
        u.handle(data_grant(req, 5, "evil/s0", 77, false));
        assert!(u.counters(SessionId(5)).is_none());
        assert!(u.is_pending(req));
        assert_eq!(u.unwanted_grants(), 1);
        let ended: Vec<_> = outs(&mut u)
            .into_iter()
            .filter(|o| matches!(o, UserOutput::ToSystem(s, ToSystem::End { .. }) if s == "evil"))
            .collect();
        assert_eq!(ended.len(), 1);
        // The real grant then makes the session.
        u.handle(data_grant(req, 6, "t1/s0", 50, false));
        assert!(u.counters(SessionId(6)).is_some());
        assert!(!u.is_pending(req));
    }

    /// A grant of a `pose2d` data session of `service`, sent by `system_pid` (the
    /// system's own copy) or `relayed` by the broker.
    fn data_grant(req: u64, session: u64, service: &str, system_pid: u32, relayed: bool) -> ToUser {
        let (system, name) = service.split_once('/').unwrap();
        ToUser::Granted {
            req,
            session: SessionId(session),
            service: ServiceId::new(system, name),
            kind: ServiceKind::Data,
            payload: "pose2d".into(),
            schema: None,
            system_pid,
            relayed,
        }
    }

    fn grant(
        u: &mut UserCore,
        req: u64,
        session: u64,
        service: &str,
        kind: ServiceKind,
        payload: &str,
    ) {
        let (system, _) = service.split_once('/').unwrap();
        u.handle(ToUser::Granted {
            req,
            session: SessionId(session),
            service: ServiceId::new(system, &service[system.len() + 1..]),
            kind,
            payload: payload.into(),
            schema: None,
            system_pid: 50,
            relayed: false,
        });
    }

    fn update(u: &mut UserCore, session: u64, seq: u64) {
        u.handle(ToUser::Update {
            session: SessionId(session),
            seq,
            sent_ns: 0,
            payload: Payload::Pose2d {
                x: 1.0,
                y: 2.0,
                theta: 0.0,
            },
        });
    }

    #[test]
    fn only_the_broker_and_the_granting_system_are_believed() {
        let mut u = user();
        // The broker is pid 3, system `s` pid 50; pid 66 poses as each.
        let owner = |a: &Address| match a {
            Address::Broker => Some(3),
            Address::System(s) if s == "s" => Some(50),
            _ => None,
        };
        let welcome = |pid| ToUser::Welcome {
            epoch: 1,
            broker_pid: pid,
        };
        assert!(
            !u.sender_allowed(Some(66), &welcome(66), owner),
            "not the broker's inbox owner"
        );
        assert!(
            !u.sender_allowed(Some(66), &welcome(3), owner),
            "claims another pid"
        );
        assert!(u.sender_allowed(Some(3), &welcome(3), owner));
        u.handle(welcome(3));
        let req = u.request(ServiceId::new("s", "a"));
        let refused = ToUser::Refused {
            req,
            reason: Refusal::Unknown,
        };
        assert!(!u.sender_allowed(Some(66), &refused, owner));
        assert!(u.sender_allowed(Some(3), &refused, owner));
        let granted = |pid| data_grant(req, 7, "s/a", pid, false);
        assert!(
            !u.sender_allowed(Some(66), &granted(66), owner),
            "not s's inbox owner"
        );
        assert!(
            !u.sender_allowed(Some(3), &granted(50), owner),
            "the broker cannot grant"
        );
        assert!(u.sender_allowed(Some(50), &granted(50), owner));
        // The broker's copy of the grant comes from the broker only.
        let relayed = |pid| data_grant(req, 7, "s/a", pid, true);
        assert!(u.sender_allowed(Some(3), &relayed(50), owner));
        assert!(
            !u.sender_allowed(Some(50), &relayed(50), owner),
            "the system cannot pose as the broker"
        );
        assert!(!u.sender_allowed(Some(66), &relayed(50), owner));
        u.handle(granted(50));
        let ended = ToUser::Ended {
            session: SessionId(7),
            reason: EndReason::BySystem("done".into()),
            last_seq: 0,
        };
        assert!(!u.sender_allowed(Some(66), &ended, owner));
        assert!(
            u.sender_allowed(Some(3), &ended, owner),
            "the broker ends a grant its system did not take"
        );
        assert!(u.sender_allowed(Some(50), &ended, owner));
        let update = ToUser::Update {
            session: SessionId(7),
            seq: 1,
            sent_ns: 0,
            payload: Payload::Goal2d { x: 1.0, y: 2.0 },
        };
        assert!(
            !u.sender_allowed(Some(3), &update, owner),
            "only the granting system streams"
        );
        assert!(
            u.sender_allowed(None, &ended, owner),
            "an unknown writer is let through"
        );
        assert_eq!(u.impersonations(), 9);
    }

    #[test]
    fn gaps_are_counted_and_old_frames_dropped() {
        let mut u = user();
        let req = u.request(ServiceId::new("t", "a"));
        grant(&mut u, req, 9, "t/a", ServiceKind::Data, "pose2d");
        for seq in [1, 2, 5, 4, 5, 6] {
            update(&mut u, 9, seq);
        }
        let seen: Vec<(u64, u64)> = events(&mut u)
            .into_iter()
            .filter_map(|e| match e {
                UserEvent::Update { seq, gap, .. } => Some((seq, gap)),
                _ => None,
            })
            .collect();
        assert_eq!(
            seen,
            vec![(1, 0), (2, 0), (5, 2), (6, 0)],
            "never misordered"
        );
        assert_eq!(
            u.counters(SessionId(9)),
            Some(SessionCounters {
                last_seq: 6,
                gaps: 2
            })
        );
        assert_eq!(u.stale_frames(), 2);
        update(&mut u, 404, 1);
        assert_eq!(u.stale_frames(), 3, "updates for no session are dropped");
    }

    #[test]
    fn a_latched_services_update_0_is_taken_once_before_the_stream_and_never_after() {
        let mut u = user();
        let seen = |u: &mut UserCore| -> Vec<(u64, u64)> {
            events(u)
                .into_iter()
                .filter_map(|e| match e {
                    UserEvent::Update { seq, gap, .. } => Some((seq, gap)),
                    _ => None,
                })
                .collect()
        };
        // With the grant: update 0, then the system's stream from 1, no gap counted.
        let req = u.request(ServiceId::new("t", "a"));
        grant(&mut u, req, 9, "t/a", ServiceKind::Data, "pose2d");
        for seq in [0, 0, 1, 2] {
            update(&mut u, 9, seq);
        }
        assert_eq!(seen(&mut u), vec![(0, 0), (1, 0), (2, 0)], "one update 0");
        assert_eq!(
            u.counters(SessionId(9)),
            Some(SessionCounters {
                last_seq: 2,
                gaps: 0
            })
        );
        assert_eq!(u.stale_frames(), 1);
        // The system's update 1 read first (two writers): update 0, older, is dropped.
        let req = u.request(ServiceId::new("t", "b"));
        grant(&mut u, req, 10, "t/b", ServiceKind::Data, "pose2d");
        update(&mut u, 10, 1);
        update(&mut u, 10, 0);
        assert_eq!(seen(&mut u), vec![(1, 0)]);
        assert_eq!(u.stale_frames(), 2);
    }

    #[test]
    fn an_update_0_is_believed_from_the_broker_and_the_granting_system_only() {
        let mut u = user();
        let owner = |a: &Address| match a {
            Address::Broker => Some(3),
            Address::System(s) if s == "s" => Some(50),
            _ => None,
        };
        let req = u.request(ServiceId::new("s", "a"));
        u.handle(data_grant(req, 7, "s/a", 50, true));
        let zero = ToUser::Update {
            session: SessionId(7),
            seq: 0,
            sent_ns: 0,
            payload: Payload::Text("x".into()),
        };
        assert!(u.sender_allowed(Some(3), &zero, owner), "the broker's");
        assert!(u.sender_allowed(Some(50), &zero, owner), "the system's");
        assert!(!u.sender_allowed(Some(66), &zero, owner), "nobody else's");
        // Any other update of a local system's session, from the system only.
        let one = ToUser::Update {
            session: SessionId(7),
            seq: 1,
            sent_ns: 0,
            payload: Payload::Text("x".into()),
        };
        assert!(!u.sender_allowed(Some(3), &one, owner));
        assert!(u.sender_allowed(Some(50), &one, owner));
    }

    #[test]
    fn the_systems_confirmation_of_our_end_is_its_own_event() {
        let mut u = user();
        let req = u.request(ServiceId::new("t", "a"));
        grant(&mut u, req, 9, "t/a", ServiceKind::Data, "pose2d");
        let req2 = u.request(ServiceId::new("t", "b"));
        grant(&mut u, req2, 10, "t/b", ServiceKind::Data, "pose2d");
        events(&mut u);
        u.end(SessionId(9));
        let ended = |u: &mut UserCore, s: u64, reason: EndReason| {
            u.handle(ToUser::Ended {
                session: SessionId(s),
                reason,
                last_seq: 0,
            });
        };
        ended(&mut u, 9, EndReason::ByUser);
        ended(&mut u, 9, EndReason::ByUser);
        ended(&mut u, 10, EndReason::BySystem("operator".into()));
        let got = events(&mut u);
        assert!(matches!(
            got[0],
            UserEvent::Ended {
                session: SessionId(9),
                ..
            }
        ));
        assert_eq!(
            got[1],
            UserEvent::EndConfirmed {
                session: SessionId(9)
            }
        );
        // A repeat confirms nothing more; a system's own end is an ordinary end.
        assert!(matches!(
            got[2],
            UserEvent::Ended {
                session: SessionId(10),
                ..
            }
        ));
        assert_eq!(got.len(), 3, "{got:?}");
    }

    #[test]
    fn frames_the_system_sent_last_that_never_came_are_counted_at_its_end() {
        let mut u = user();
        let req = u.request(ServiceId("t1/s0".into()));
        grant(&mut u, req, 7, "t1/s0", ServiceKind::Data, "pose2d");
        let update = |session, seq| ToUser::Update {
            session: SessionId(session),
            seq,
            sent_ns: 0,
            payload: Payload::Scalar(1.0),
        };
        u.handle(update(7, 1));
        u.handle(update(7, 3));
        events(&mut u);
        // The system sent up to 6: 4, 5 and 6 never came (one gap before, three at the end).
        u.handle(ToUser::Ended {
            session: SessionId(7),
            reason: EndReason::BySystem("done".into()),
            last_seq: 6,
        });
        let got = events(&mut u);
        assert!(
            matches!(got[..], [UserEvent::Ended { lost_at_end: 3, .. }]),
            "{got:?}"
        );
        // An end that says no more than was seen (or the broker's, which says 0) adds none.
        let req = u.request(ServiceId("t1/s1".into()));
        grant(&mut u, req, 8, "t1/s1", ServiceKind::Data, "pose2d");
        u.handle(update(8, 2));
        events(&mut u);
        u.handle(ToUser::Ended {
            session: SessionId(8),
            reason: EndReason::PeerGone,
            last_seq: 0,
        });
        assert!(matches!(
            events(&mut u)[..],
            [UserEvent::Ended { lost_at_end: 0, .. }]
        ));
    }

    #[test]
    fn a_grant_after_giving_up_is_ended_at_once() {
        let mut u = user();
        let req = u.request(ServiceId::new("t", "a"));
        u.cancel(req);
        outs(&mut u);
        grant(&mut u, req, 9, "t/a", ServiceKind::Data, "pose2d");
        assert_eq!(
            outs(&mut u),
            vec![UserOutput::ToSystem(
                "t".into(),
                ToSystem::End {
                    user: UserId("u1".into()),
                    session: SessionId(9)
                }
            )]
        );
        assert_eq!(u.sessions().count(), 0);
    }

    #[test]
    fn a_link_converts_and_forwards_then_ends_with_its_command_side() {
        let mut u = user();
        let link = u.link(ServiceId::new("t", "a"), ServiceId::new("d", "go"));
        outs(&mut u);
        grant(&mut u, 1, 10, "t/a", ServiceKind::Data, "pose2d");
        grant(&mut u, 2, 20, "d/go", ServiceKind::Command, "goal2d");
        let out = outs(&mut u);
        assert!(out
            .iter()
            .any(|o| matches!(o, UserOutput::ToBroker(ToBroker::LinkOpened { .. }))));
        assert!(events(&mut u).contains(&UserEvent::LinkUp { link }));
        update(&mut u, 10, 1);
        assert!(outs(&mut u).contains(&UserOutput::ToSystem(
            "d".into(),
            ToSystem::Input {
                user: UserId("u1".into()),
                session: SessionId(20),
                payload: Payload::Goal2d { x: 1.0, y: 2.0 }
            }
        )));
        // The command system ends its side: the link ends and the data session is ended too.
        u.handle(ToUser::Ended {
            session: SessionId(20),
            reason: EndReason::BySystem("done".into()),
            last_seq: 0,
        });
        let out = outs(&mut u);
        assert!(out.contains(&UserOutput::ToSystem(
            "t".into(),
            ToSystem::End {
                user: UserId("u1".into()),
                session: SessionId(10)
            }
        )));
        assert!(out.contains(&UserOutput::ToBroker(ToBroker::LinkClosed {
            user: UserId("u1".into()),
            link
        })));
        assert!(events(&mut u)
            .iter()
            .any(|e| matches!(e, UserEvent::LinkEnded { .. })));
        assert_eq!(u.sessions().count(), 0);
        assert_eq!(u.links().count(), 0);
    }

    #[test]
    fn a_link_that_could_forward_nothing_ends_with_the_reason_not_silently() {
        let ended = |u: &mut UserCore, link: u64| -> Option<String> {
            events(u).into_iter().find_map(|e| match e {
                UserEvent::LinkEnded { link: l, reason } if l == link => Some(reason),
                _ => None,
            })
        };
        // Two services naming their payload `door_state`, a label, no schema: refused
        // when both halves are granted.
        let mut u = user();
        let link = u.link(ServiceId::new("t", "a"), ServiceId::new("d", "go"));
        grant(&mut u, 1, 10, "t/a", ServiceKind::Data, "door_state");
        grant(&mut u, 2, 20, "d/go", ServiceKind::Command, "door_state");
        let why = ended(&mut u, link).expect("the link ended");
        assert!(
            why.contains("cannot link door_state into door_state"),
            "{why}"
        );
        // Compatible types, but a value of another type comes: the link ends, said.
        let mut u = user();
        let link = u.link(ServiceId::new("t", "a"), ServiceId::new("d", "go"));
        grant(&mut u, 1, 10, "t/a", ServiceKind::Data, "pose2d");
        grant(&mut u, 2, 20, "d/go", ServiceKind::Command, "goal2d");
        events(&mut u);
        u.handle(ToUser::Update {
            session: SessionId(10),
            seq: 1,
            sent_ns: 0,
            payload: Payload::Text("open".into()),
        });
        let why = ended(&mut u, link).expect("the link ended");
        assert!(
            why.contains("an update of type text cannot be given to goal2d"),
            "{why}"
        );
        // Text into text, but one value too large for the path to the command's system:
        // the link ends, said, where the transport would have dropped it.
        let mut u = user();
        let link = u.link(ServiceId::new("t", "a"), ServiceId::new("d", "go"));
        grant(&mut u, 1, 10, "t/a", ServiceKind::Data, "text");
        grant(&mut u, 2, 20, "d/go", ServiceKind::Command, "text");
        events(&mut u);
        u.handle(ToUser::Update {
            session: SessionId(10),
            seq: 1,
            sent_ns: 0,
            payload: Payload::Text("x".repeat(5000)),
        });
        let why = ended(&mut u, link).expect("the link ended");
        assert!(why.contains("cannot be forwarded"), "{why}");
        assert!(why.contains("shared memory"), "{why}");
    }

    #[test]
    fn an_input_too_large_for_its_path_is_refused_and_said() {
        let text = |n: usize| Payload::Text("x".repeat(n));
        // A local user: 3,000 bytes go, 5,000 do not fit the 4 KiB frame.
        let mut u = user();
        let req = u.request(ServiceId("d/go".into()));
        grant(&mut u, req, 20, "d/go", ServiceKind::Command, "text");
        outs(&mut u);
        assert_eq!(u.input(SessionId(20), text(3000)), Ok(()));
        assert_eq!(outs(&mut u).len(), 1);
        let e = u.input(SessionId(20), text(5000)).unwrap_err();
        assert!(
            e.contains("larger than the 4096 bytes a shared memory"),
            "{e}"
        );
        assert!(outs(&mut u).is_empty(), "nothing goes");
        // A remote user (pid 0): one datagram, so the same 3,000 bytes are refused.
        let mut u = UserCore::new(UserId("far".into()), 0, false);
        let req = u.request(ServiceId("d/go".into()));
        grant(&mut u, req, 20, "d/go", ServiceKind::Command, "text");
        outs(&mut u);
        let e = u.input(SessionId(20), text(3000)).unwrap_err();
        assert!(e.contains("UDP datagram"), "{e}");
        assert!(outs(&mut u).is_empty(), "nothing goes");
        assert_eq!(u.input(SessionId(20), text(100)), Ok(()));
    }

    #[test]
    fn a_refused_half_cancels_the_other_half_of_a_link() {
        let mut u = user();
        let link = u.link(ServiceId::new("t", "a"), ServiceId::new("d", "go"));
        outs(&mut u);
        u.handle(ToUser::Refused {
            req: 2,
            reason: Refusal::QuotaFull { quota: 1 },
        });
        assert!(
            outs(&mut u).contains(&UserOutput::ToBroker(ToBroker::Cancel {
                user: UserId("u1".into()),
                req: 1
            }))
        );
        assert!(events(&mut u)
            .iter()
            .any(|e| matches!(e, UserEvent::LinkEnded { link: l, .. } if *l == link)));
        assert_eq!(u.pending_requests(), 0);
    }

    #[test]
    fn pending_requests_are_resent_to_a_new_broker() {
        let mut u = user();
        u.hello();
        u.handle(ToUser::Welcome {
            epoch: 1,
            broker_pid: 3,
        });
        let r = u.request(ServiceId::new("t", "a"));
        outs(&mut u);
        u.broker_lost();
        assert_eq!(u.connected(), None);
        u.hello();
        let out = outs(&mut u);
        assert!(matches!(
            &out[0],
            UserOutput::ToBroker(ToBroker::Hello { .. })
        ));
        assert!(out.contains(&UserOutput::ToBroker(ToBroker::Request {
            user: UserId("u1".into()),
            req: r,
            service: ServiceId::new("t", "a")
        })));
    }

    #[test]
    fn input_only_on_command_sessions() {
        let mut u = user();
        let r = u.request(ServiceId::new("t", "a"));
        grant(&mut u, r, 9, "t/a", ServiceKind::Data, "pose2d");
        assert!(u
            .input(SessionId(9), Payload::Scalar(1.0))
            .unwrap_err()
            .contains("data session"));
        assert!(u.input(SessionId(8), Payload::Scalar(1.0)).is_err());
    }
}
