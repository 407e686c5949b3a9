//! Replication on the in-memory core with a virtual clock: a follower fed the
//! primary's records ends in the primary's state, and a takeover at any point of a
//! random run loses no session and grants nothing twice.

use super::*;
use crate::core::{BrokerConfig, Output};
use muster_shared::protocol::{ActiveSession, LinkInfo, SessionDigest, ToBroker, ToSystem};
use muster_shared::types::{ServiceId, ServiceKind, ServiceSpec, SessionId, UserId};
use proptest::prelude::*;
use std::collections::{BTreeMap, BTreeSet};

const SYSTEMS: usize = 2;
const USERS: usize = 4;

fn specs() -> Vec<ServiceSpec> {
    vec![
        ServiceSpec {
            name: "a".into(),
            description: "data, queued".into(),
            kind: ServiceKind::Data,
            queue: true,
            quota: 2,
            payload: "pose2d".into(),
            schema: None,
        },
        ServiceSpec {
            name: "b".into(),
            description: "command".into(),
            kind: ServiceKind::Command,
            queue: false,
            quota: 1,
            payload: "goal2d".into(),
            schema: None,
        },
    ]
}

fn sys(i: usize) -> String {
    format!("s{i}")
}

fn user(i: usize) -> UserId {
    UserId(format!("u{i}"))
}

fn svc(i: usize) -> &'static str {
    if i.is_multiple_of(2) {
        "a"
    } else {
        "b"
    }
}

#[derive(Clone, Debug)]
enum Action {
    Register(usize),
    Hello(usize),
    Request(usize, usize, usize),
    Answer(usize, bool),
    End(usize),
    Withdraw(usize, usize),
    Restore(usize, usize),
    Cancel(usize),
    Link(usize, usize, usize),
    UserDies(usize),
    SystemDies(usize),
    Tick(u64),
}

fn action() -> impl Strategy<Value = Action> {
    prop_oneof![
        2 => (0..SYSTEMS).prop_map(Action::Register),
        2 => (0..USERS).prop_map(Action::Hello),
        6 => (0..USERS, 0..SYSTEMS, 0..2usize).prop_map(|(u, s, v)| Action::Request(u, s, v)),
        6 => (0..64usize, prop::bool::weighted(0.8)).prop_map(|(i, g)| Action::Answer(i, g)),
        3 => (0..64usize).prop_map(Action::End),
        1 => (0..SYSTEMS, 0..2usize).prop_map(|(s, v)| Action::Withdraw(s, v)),
        1 => (0..SYSTEMS, 0..2usize).prop_map(|(s, v)| Action::Restore(s, v)),
        1 => (0..64usize).prop_map(Action::Cancel),
        1 => (0..USERS, 0..SYSTEMS, 0..SYSTEMS).prop_map(|(u, a, b)| Action::Link(u, a, b)),
        1 => (0..USERS).prop_map(Action::UserDies),
        1 => (0..SYSTEMS).prop_map(Action::SystemDies),
        3 => (1..30_000u64).prop_map(Action::Tick),
    ]
}

/// A granted session, as its system holds it.
#[derive(Clone, Debug)]
struct Held {
    system: String,
    service: String,
    user: UserId,
    req: u64,
}

/// The systems and users around the broker: they answer offers and pings the way the
/// real ones do (a repeated offer is answered with the session already granted).
#[derive(Default)]
struct World {
    now: Duration,
    alive: BTreeSet<String>,
    users: BTreeSet<UserId>,
    sessions: BTreeMap<SessionId, Held>,
    /// Offers received and not answered yet: (system, ticket, user, req, service,
    /// the session granted).
    offers: Vec<(String, u64, UserId, u64, String, SessionId)>,
    /// Requests each user has out: (user, req) → service.
    pending: BTreeMap<(UserId, u64), ServiceId>,
    next_req: u64,
    /// Requests whose session ended: a repeated offer for one is refused.
    served: BTreeSet<(UserId, u64, String)>,
    /// Every grant answered: (user, req) → sessions given for it.
    granted: BTreeMap<(UserId, u64), BTreeSet<SessionId>>,
}

impl World {
    /// Its user ends session `id` (the system remembers the request as served).
    fn end(&mut self, id: SessionId) -> Option<Held> {
        let h = self.sessions.remove(&id)?;
        self.served
            .insert((h.user.clone(), h.req, h.service.clone()));
        Some(h)
    }

    fn digest(&self, system: &str) -> SessionDigest {
        SessionDigest::of(
            self.sessions
                .iter()
                .filter(|(_, h)| h.system == system)
                .map(|(id, _)| *id),
        )
    }

    fn held(&self, system: &str) -> Vec<ActiveSession> {
        self.sessions
            .iter()
            .filter(|(_, h)| h.system == system)
            .map(|(id, h)| ActiveSession {
                session: *id,
                service: h.service.clone(),
                user: h.user.clone(),
                relayed: false,
            })
            .collect()
    }

    /// Takes what the broker wants sent (or drops it, if `lost`); answers pings.
    fn deliver(&mut self, core: &mut Broker, lost: bool) {
        let mut pongs = Vec::new();
        while let Some(out) = core.poll_output() {
            if lost {
                continue;
            }
            match out {
                Output::ToSystem(
                    system,
                    ToSystem::Offer {
                        ticket,
                        user,
                        req,
                        service,
                        session,
                        ..
                    },
                ) if self.alive.contains(&system) => {
                    self.offers
                        .push((system, ticket, user, req, service, session));
                }
                // A grant that was not confirmed in time: its system reads this after the
                // offer, so it opens the session (if it would) and ends it at once.
                Output::ToSystem(system, ToSystem::Terminate { session, .. })
                    if self.alive.contains(&system) =>
                {
                    if let Some(i) = self.offers.iter().position(|o| o.5 == session) {
                        let (_, _, u, req, service, _) = self.offers.remove(i);
                        self.served.insert((u, req, service));
                    } else if let Some(h) = self.end(session) {
                        pongs.push(ToBroker::SessionEnded {
                            system: h.system,
                            session,
                        });
                    }
                }
                Output::ToSystem(system, ToSystem::Ping { nonce })
                    if self.alive.contains(&system) =>
                {
                    pongs.push(ToBroker::Pong {
                        held: Some(self.digest(&system)),
                        system,
                        nonce,
                    });
                }
                Output::ToSystem(system, ToSystem::ReportSessions)
                    if self.alive.contains(&system) =>
                {
                    pongs.push(ToBroker::Sessions {
                        sessions: self.held(&system),
                        system,
                    });
                }
                Output::ToUser(u, muster_shared::protocol::ToUser::Refused { req, .. }) => {
                    self.pending.remove(&(u, req));
                }
                Output::Granted(g) => {
                    self.pending.remove(&(g.user, g.req));
                }
                _ => {}
            }
        }
        for p in pongs {
            core.handle(self.now, p);
        }
    }

    fn act(&mut self, core: &mut Broker, a: &Action) {
        match *a {
            Action::Register(s) => {
                let name = sys(s);
                self.alive.insert(name.clone());
                core.handle(
                    self.now,
                    ToBroker::Register {
                        sessions: self.held(&name),
                        system: name,
                        pid: 100 + s as u32,
                        services: specs(),
                        udp: None,
                    },
                );
            }
            Action::Hello(u) => {
                self.users.insert(user(u));
                core.handle(
                    self.now,
                    ToBroker::Hello {
                        user: user(u),
                        pid: 200 + u as u32,
                        links: vec![],
                        watch_list: false,
                    },
                );
            }
            Action::Request(u, s, v) => {
                if !self.users.contains(&user(u)) {
                    return;
                }
                self.next_req += 1;
                let service = ServiceId::new(&sys(s), svc(v));
                self.pending
                    .insert((user(u), self.next_req), service.clone());
                core.handle(
                    self.now,
                    ToBroker::Request {
                        user: user(u),
                        req: self.next_req,
                        service,
                    },
                );
            }
            Action::Answer(i, grant) => {
                if self.offers.is_empty() {
                    return;
                }
                let (system, ticket, u, req, service, session) =
                    self.offers.remove(i % self.offers.len());
                if !self.alive.contains(&system) {
                    return;
                }
                let existing = self
                    .sessions
                    .iter()
                    .find(|(_, h)| h.user == u && h.req == req && h.service == service)
                    .map(|(id, _)| *id);
                let answer = match existing {
                    Some(id) => Ok(id),
                    None if self.served.contains(&(u.clone(), req, service.clone())) => {
                        Err("request already served".to_string())
                    }
                    None if grant && self.users.contains(&u) => {
                        self.sessions.insert(
                            session,
                            Held {
                                system: system.clone(),
                                service: service.clone(),
                                user: u.clone(),
                                req,
                            },
                        );
                        Ok(session)
                    }
                    None => Err("refused".to_string()),
                };
                if let Ok(id) = answer {
                    self.granted.entry((u.clone(), req)).or_default().insert(id);
                }
                core.handle(
                    self.now,
                    ToBroker::OfferAnswer {
                        system: system.clone(),
                        ticket,
                        answer: answer.clone(),
                    },
                );
            }
            Action::End(i) => {
                let Some(id) = self
                    .sessions
                    .keys()
                    .nth(i % self.sessions.len().max(1))
                    .copied()
                else {
                    return;
                };
                let h = self.end(id).expect("listed");
                core.handle(
                    self.now,
                    ToBroker::SessionEnded {
                        system: h.system,
                        session: id,
                    },
                );
            }
            Action::Withdraw(s, v) | Action::Restore(s, v) => {
                let (system, service) = (sys(s), svc(v).to_string());
                let msg = if matches!(a, Action::Withdraw(..)) {
                    ToBroker::Withdraw { system, service }
                } else {
                    ToBroker::Restore { system, service }
                };
                core.handle(self.now, msg);
            }
            Action::Cancel(i) => {
                let Some((u, req)) = self
                    .pending
                    .keys()
                    .nth(i % self.pending.len().max(1))
                    .cloned()
                else {
                    return;
                };
                core.handle(self.now, ToBroker::Cancel { user: u, req });
            }
            Action::Link(u, a, b) => core.handle(
                self.now,
                ToBroker::LinkOpened {
                    user: user(u),
                    link: LinkInfo {
                        link: (a * 2 + b) as u64,
                        data: ServiceId::new(&sys(a), "a"),
                        command: ServiceId::new(&sys(b), "b"),
                    },
                },
            ),
            Action::UserDies(u) => {
                // Its systems see it die and end its sessions; the broker forgets it.
                self.users.remove(&user(u));
                self.pending.retain(|(pu, _), _| *pu != user(u));
                let ended: Vec<SessionId> = self
                    .sessions
                    .iter()
                    .filter(|(_, h)| h.user == user(u))
                    .map(|(id, _)| *id)
                    .collect();
                core.user_died(self.now, &user(u));
                for id in ended {
                    // Ended because its user is gone: not a request the system remembers.
                    let h = self.sessions.remove(&id).expect("listed");
                    core.handle(
                        self.now,
                        ToBroker::SessionEnded {
                            system: h.system,
                            session: id,
                        },
                    );
                }
            }
            Action::SystemDies(s) => {
                let name = sys(s);
                self.alive.remove(&name);
                self.sessions.retain(|_, h| h.system != name);
                self.offers.retain(|o| o.0 != name);
                core.system_died(self.now, &name);
            }
            Action::Tick(ms) => {
                self.now += Duration::from_millis(ms);
                if core.poll_timeout().is_some_and(|t| t <= self.now) {
                    core.handle_timeout(self.now);
                }
            }
        }
    }

    /// What peers do when a new broker takes over: systems report their sessions and
    /// users repeat their pending requests (frames the old broker held are lost).
    fn adopt(&mut self, core: &mut Broker) {
        for system in self.alive.clone() {
            core.handle(
                self.now,
                ToBroker::Sessions {
                    sessions: self.held(&system),
                    system,
                },
            );
        }
        for ((u, req), service) in self.pending.clone() {
            core.handle(
                self.now,
                ToBroker::Request {
                    user: u,
                    req,
                    service,
                },
            );
        }
    }

    /// Answers every offer (granting) until none is left.
    fn quiesce(&mut self, core: &mut Broker) {
        for _ in 0..1000 {
            self.deliver(core, false);
            if self.offers.is_empty() {
                return;
            }
            self.act(core, &Action::Answer(0, true));
        }
        panic!("offers never ran out");
    }

    /// The broker counts exactly the sessions the systems hold, within quotas, and no
    /// request was granted twice.
    fn check(&self, core: &Broker) {
        for view in core.views() {
            let held = self
                .sessions
                .values()
                .filter(|h| format!("{}/{}", h.system, h.service) == view.id)
                .count();
            assert_eq!(usize::from(view.in_use), held, "{} in use", view.id);
            assert!(view.in_use <= view.quota, "{} over quota", view.id);
        }
        for (req, ids) in &self.granted {
            assert_eq!(ids.len(), 1, "request {req:?} granted as {ids:?}");
        }
    }
}

fn primary() -> Broker {
    let mut b = Broker::new(BrokerConfig::default(), 1, 1);
    b.keep_journal();
    b
}

#[test]
fn an_image_and_the_ops_after_it_rebuild_the_state() {
    let mut p = primary();
    let mut w = World::default();
    let mut leader = Leader::default();
    let mut records = Vec::new();
    for a in [
        Action::Register(0),
        Action::Hello(0),
        Action::Hello(1),
        Action::Request(0, 0, 0),
        Action::Answer(0, true),
    ] {
        w.act(&mut p, &a);
        records.extend(leader.ops(&mut p));
        w.deliver(&mut p, false);
    }
    let image = leader.image(&p);
    for a in [
        Action::Request(1, 0, 1),
        Action::Tick(25_000),
        Action::End(0),
    ] {
        w.act(&mut p, &a);
        w.deliver(&mut p, false);
        records.extend(leader.ops(&mut p));
    }
    let mut f = Follower::new();
    // Ops before the image are ignored; the image starts the copy; later ops follow.
    assert_eq!(f.apply(&records[0]).unwrap(), Step::Ignored);
    assert_eq!(f.apply(&image).unwrap(), Step::Applied);
    let image_seq = f.seq();
    for r in &records {
        f.apply(r).unwrap();
    }
    assert!(f.seq() > image_seq);
    assert_eq!(f.seq(), leader.seq());
    assert_eq!(f.core().unwrap().archived_state(), p.archived_state());
    assert_eq!(f.apply(&leader.heartbeat()).unwrap(), Step::Ignored);
    assert_eq!(
        f.apply(&leader.stepping_down()).unwrap(),
        Step::SteppingDown
    );
}

#[test]
fn a_lost_record_is_a_gap_and_a_new_image_heals_it() {
    let mut p = primary();
    let mut w = World::default();
    let mut leader = Leader::default();
    let mut f = Follower::new();
    f.apply(&leader.image(&p)).unwrap();
    w.act(&mut p, &Action::Register(0));
    let first = leader.ops(&mut p);
    w.act(&mut p, &Action::Hello(0));
    let second = leader.ops(&mut p);
    assert_eq!(f.apply(&second[0]).unwrap(), Step::Gap);
    assert!(!f.synced());
    assert_eq!(f.apply(&first[0]).unwrap(), Step::Ignored);
    f.apply(&leader.image(&p)).unwrap();
    assert_eq!(f.core().unwrap().archived_state(), p.archived_state());
    // A heartbeat past the copy is a gap too.
    w.act(&mut p, &Action::Hello(1));
    let _lost = leader.ops(&mut p);
    assert_eq!(f.apply(&leader.heartbeat()).unwrap(), Step::Gap);
}

#[test]
fn malformed_records_are_refused_without_touching_the_copy() {
    let mut f = Follower::new();
    let p = primary();
    f.apply(&Leader::default().image(&p)).unwrap();
    for bad in [&b""[..], &[0xff; 7][..], &[0u8; 64][..]] {
        let mut buf = AlignedVec::<16>::new();
        buf.extend_from_slice(bad);
        assert!(f.apply(&buf).is_err(), "{bad:?}");
    }
    assert!(f.synced());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    /// A follower that joins at any point (an image) and is fed every op after it ends
    /// in the primary's state.
    #[test]
    fn a_follower_fed_the_same_stream_ends_in_the_same_state(
        actions in prop::collection::vec(action(), 1..120),
        join in 0usize..120,
    ) {
        let mut p = primary();
        let mut w = World::default();
        let mut leader = Leader::default();
        let mut f = Follower::new();
        let join = join % actions.len();
        for (i, a) in actions.iter().enumerate() {
            if i == join {
                for r in leader.ops(&mut p) { f.apply(&r).unwrap(); }
                f.apply(&leader.image(&p)).unwrap();
            }
            w.act(&mut p, a);
            w.deliver(&mut p, false);
            for r in leader.ops(&mut p) {
                prop_assert_ne!(f.apply(&r).unwrap(), Step::Gap);
            }
        }
        prop_assert_eq!(f.seq(), leader.seq());
        prop_assert_eq!(f.core().unwrap().archived_state(), p.archived_state());
    }

    /// The primary dies at any point (after publishing its records, perhaps before
    /// sending what they made it say); the standby takes over, peers adopt it, and the
    /// run goes on: every session the systems hold is counted, quotas hold, and no
    /// request is granted twice.
    #[test]
    fn a_takeover_at_any_point_loses_no_session(
        actions in prop::collection::vec(action(), 1..120),
        cut in 0usize..120,
        lost in any::<bool>(),
    ) {
        let mut p = primary();
        let mut w = World::default();
        let mut leader = Leader::default();
        let mut f = Follower::new();
        f.apply(&leader.image(&p)).unwrap();
        let cut = cut % actions.len();
        for a in &actions[..cut] {
            w.act(&mut p, a);
            for r in leader.ops(&mut p) { f.apply(&r).unwrap(); }
            w.deliver(&mut p, false);
        }
        // The primary's last step: published, but its outputs perhaps never sent.
        w.act(&mut p, &actions[cut]);
        for r in leader.ops(&mut p) { f.apply(&r).unwrap(); }
        w.deliver(&mut p, lost);
        drop(p);
        let mut n = f.into_core().unwrap();
        n.keep_journal();
        n.take_over(w.now, 2, 2);
        w.deliver(&mut n, false);
        w.adopt(&mut n);
        for a in &actions[cut + 1..] {
            w.act(&mut n, a);
            w.deliver(&mut n, false);
        }
        w.quiesce(&mut n);
        // Nothing waits on a timeout: what the old broker left undone was redone.
        w.check(&n);
        // Let a ping round reconcile anything a lost frame left behind.
        w.act(&mut n, &Action::Tick(25_000));
        w.quiesce(&mut n);
        w.check(&n);
        prop_assert_eq!(n.epoch(), 2);
    }
}
