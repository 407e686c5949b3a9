//! A deterministic in-memory federation: the broker core, system cores (with the
//! synthetic system's logic) and user cores wired together on a virtual clock. Frames
//! still go through the wire codec. Hours of virtual time run in milliseconds.

#![allow(clippy::unwrap_used)]

use muster_broker::core::{Broker, BrokerConfig, Output};
use muster_shared::protocol::{decode, encode, ToBroker, ToSystem, ToUser};
use muster_shared::types::{
    EndReason, Payload, Refusal, ServiceId, ServiceKind, SessionId, TaskStatus, UserId,
};
use muster_systems::core::{SystemCore, SystemOutput};
use muster_systems::runtime::SystemApp;
use muster_systems::synthetic::{Synthetic, SyntheticOptions};
use muster_users::core::{UserCore, UserEvent, UserOutput};
use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

enum Frame {
    Broker(Vec<u8>),
    System(String, Vec<u8>),
    User(UserId, Vec<u8>),
}

struct Sys {
    core: SystemCore,
    app: Synthetic,
    alive: bool,
    frozen: bool,
}

struct Net {
    now: Duration,
    broker: Option<Broker>,
    epoch: u64,
    systems: BTreeMap<String, Sys>,
    users: BTreeMap<UserId, UserCore>,
    events: BTreeMap<UserId, Vec<UserEvent>>,
    wire: VecDeque<Frame>,
    delivered: u64,
}

impl Net {
    fn new() -> Self {
        let mut n = Net {
            now: Duration::ZERO,
            broker: None,
            epoch: 0,
            systems: BTreeMap::new(),
            users: BTreeMap::new(),
            events: BTreeMap::new(),
            wire: VecDeque::new(),
            delivered: 0,
        };
        n.start_broker();
        n
    }

    fn start_broker(&mut self) {
        self.epoch += 1;
        self.broker = Some(Broker::new(BrokerConfig::default(), self.epoch, 1));
        // The presence event: everyone re-registers / says hello.
        for s in self.systems.values_mut().filter(|s| s.alive && !s.frozen) {
            s.core.broker_lost();
            s.core.register();
        }
        for u in self.users.values_mut() {
            u.broker_lost();
            u.hello();
        }
        self.settle();
    }

    fn kill_broker(&mut self) {
        self.broker = None;
        for s in self.systems.values_mut().filter(|s| s.alive) {
            s.core.broker_lost();
        }
        for u in self.users.values_mut() {
            u.broker_lost();
        }
        self.settle();
    }

    fn add_system(&mut self, opts: SyntheticOptions) {
        let mut core =
            SystemCore::new(&opts.name, 100 + self.systems.len() as u32, opts.specs(), 9);
        core.register();
        let app = Synthetic::new(&opts);
        self.systems.insert(
            opts.name.clone(),
            Sys {
                core,
                app,
                alive: true,
                frozen: false,
            },
        );
        self.settle();
    }

    fn add_user(&mut self, n: u32) -> UserId {
        let id = UserId(format!("u{n}"));
        let mut core = UserCore::new(id.clone(), 1000 + n, false);
        core.hello();
        self.users.insert(id.clone(), core);
        self.settle();
        id
    }

    fn user(&mut self, id: &UserId) -> &mut UserCore {
        self.users.get_mut(id).expect("user")
    }

    fn take_events(&mut self, id: &UserId) -> Vec<UserEvent> {
        std::mem::take(self.events.entry(id.clone()).or_default())
    }

    /// Moves frames and outputs until nothing is left to deliver.
    fn settle(&mut self) {
        for _ in 0..100_000 {
            self.collect();
            let Some(frame) = self.wire.pop_front() else {
                return;
            };
            self.delivered += 1;
            match frame {
                Frame::Broker(f) => {
                    let msg: ToBroker = decode(&f).expect("valid frame");
                    if let Some(b) = self.broker.as_mut() {
                        b.handle(self.now, msg);
                    }
                }
                Frame::System(name, f) => {
                    let msg: ToSystem = decode(&f).expect("valid frame");
                    if let Some(s) = self.systems.get_mut(&name).filter(|s| s.alive && !s.frozen) {
                        s.core.handle(msg);
                    }
                }
                Frame::User(id, f) => {
                    let msg: ToUser = decode(&f).expect("valid frame");
                    if let Some(u) = self.users.get_mut(&id) {
                        u.handle(msg);
                    }
                }
            }
        }
        panic!("the federation did not settle");
    }

    fn collect(&mut self) {
        let now = self.now;
        if let Some(b) = self.broker.as_mut() {
            while let Some(o) = b.poll_output() {
                match o {
                    Output::ToSystem(s, m) => {
                        self.wire.push_back(Frame::System(s, encode(&m).unwrap()))
                    }
                    Output::ToUser(u, m) => {
                        self.wire.push_back(Frame::User(u, encode(&m).unwrap()))
                    }
                    _ => {}
                }
            }
            let _ = b.take_list_change();
        }
        let broker_up = self.broker.is_some();
        for s in self.systems.values_mut().filter(|s| s.alive && !s.frozen) {
            loop {
                while let Some(o) = s.core.poll_output() {
                    match o {
                        SystemOutput::ToBroker(m) if broker_up => {
                            self.wire.push_back(Frame::Broker(encode(&m).unwrap()))
                        }
                        SystemOutput::ToUser(u, m) => {
                            self.wire.push_back(Frame::User(u, encode(&m).unwrap()))
                        }
                        _ => {}
                    }
                }
                let Some(ev) = s.core.poll_event() else { break };
                s.app.on_event(&mut s.core, now, ev);
            }
        }
        for (id, u) in self.users.iter_mut() {
            while let Some(o) = u.poll_output() {
                match o {
                    UserOutput::ToBroker(m) if broker_up => {
                        self.wire.push_back(Frame::Broker(encode(&m).unwrap()))
                    }
                    UserOutput::ToSystem(s, m) => {
                        self.wire.push_back(Frame::System(s, encode(&m).unwrap()))
                    }
                    _ => {}
                }
            }
            while let Some(e) = u.poll_event() {
                self.events.entry(id.clone()).or_default().push(e);
            }
        }
    }

    /// Advances virtual time to `until`, running every deadline on the way.
    fn run_until(&mut self, until: Duration) {
        loop {
            let broker_t = self.broker.as_ref().and_then(Broker::poll_timeout);
            let sys_t = self
                .systems
                .values()
                .filter(|s| s.alive && !s.frozen)
                .filter_map(|s| s.app.next_tick(&s.core))
                .min();
            let next = [broker_t, sys_t].into_iter().flatten().min();
            match next {
                Some(t) if t <= until => {
                    self.now = self.now.max(t);
                    if let Some(b) = self.broker.as_mut() {
                        if b.poll_timeout().is_some_and(|bt| bt <= self.now) {
                            b.handle_timeout(self.now);
                        }
                    }
                    let now = self.now;
                    for s in self.systems.values_mut().filter(|s| s.alive && !s.frozen) {
                        if s.app.next_tick(&s.core).is_some_and(|st| st <= now) {
                            s.app.on_tick(&mut s.core, now);
                        }
                    }
                    self.settle();
                }
                _ => {
                    self.now = until;
                    return;
                }
            }
        }
    }

    fn list(&self) -> Vec<muster_shared::snapshot::ServiceView> {
        self.broker.as_ref().map(Broker::views).unwrap_or_default()
    }
}

fn data(name: &str, services: usize, quota: u16) -> SyntheticOptions {
    SyntheticOptions {
        name: name.into(),
        services,
        kind: ServiceKind::Data,
        quota,
        queue: false,
        payload: None,
        rate_hz: 10.0,
    }
}

fn command(name: &str, quota: u16, queue: bool) -> SyntheticOptions {
    SyntheticOptions {
        kind: ServiceKind::Command,
        queue,
        ..data(name, 1, quota)
    }
}

fn secs(s: f64) -> Duration {
    Duration::from_secs_f64(s)
}

fn granted(events: &[UserEvent]) -> Vec<SessionId> {
    events
        .iter()
        .filter_map(|e| match e {
            UserEvent::Granted { session, .. } => Some(*session),
            _ => None,
        })
        .collect()
}

#[test]
fn a_data_session_streams_in_order_without_gaps() {
    let mut net = Net::new();
    net.add_system(data("t1", 3, 10));
    assert_eq!(net.list().len(), 3);
    let u = net.add_user(1);
    net.user(&u).request(ServiceId::new("t1", "s1"));
    net.settle();
    let s = granted(&net.take_events(&u))[0];
    net.run_until(secs(10.0));
    let seqs: Vec<u64> = net
        .take_events(&u)
        .into_iter()
        .filter_map(|e| match e {
            UserEvent::Update {
                seq,
                gap,
                payload: Payload::Pose2d { .. },
                ..
            } => {
                assert_eq!(gap, 0);
                Some(seq)
            }
            _ => None,
        })
        .collect();
    assert_eq!(seqs.len(), 101, "10 s at 10 Hz, both ends included");
    assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1));
    assert_eq!(net.user(&u).counters(s).unwrap().gaps, 0);
    assert_eq!(
        net.list().iter().find(|v| v.id == "t1/s1").unwrap().in_use,
        1
    );
    // The user ends it: the system stops streaming, the broker frees the quota.
    net.user(&u).end(s);
    net.settle();
    net.run_until(secs(20.0));
    assert!(!net
        .take_events(&u)
        .iter()
        .any(|e| matches!(e, UserEvent::Update { .. })));
    assert_eq!(
        net.list().iter().find(|v| v.id == "t1/s1").unwrap().in_use,
        0
    );
}

#[test]
fn several_users_share_a_service_up_to_its_quota() {
    let mut net = Net::new();
    net.add_system(data("t1", 1, 10));
    let users: Vec<UserId> = (0..12).map(|i| net.add_user(i)).collect();
    for u in &users {
        net.user(u).request(ServiceId::new("t1", "s0"));
    }
    net.settle();
    let mut grants = 0;
    let mut full = 0;
    for u in &users {
        for e in net.take_events(u) {
            match e {
                UserEvent::Granted { .. } => grants += 1,
                UserEvent::Refused {
                    reason: Refusal::QuotaFull { quota: 10 },
                    ..
                } => full += 1,
                _ => {}
            }
        }
    }
    assert_eq!((grants, full), (10, 2));
    assert_eq!(net.systems["t1"].core.sessions_of("s0"), 10);
}

#[test]
fn a_queued_request_is_granted_when_it_reaches_the_head() {
    let mut net = Net::new();
    net.add_system(command("d1", 1, true));
    let a = net.add_user(1);
    let b = net.add_user(2);
    net.user(&a).request(ServiceId::new("d1", "s0"));
    net.settle();
    net.user(&b).request(ServiceId::new("d1", "s0"));
    net.settle();
    let sa = granted(&net.take_events(&a))[0];
    let eb = net.take_events(&b);
    assert!(eb
        .iter()
        .any(|e| matches!(e, UserEvent::Queued { position: 1, .. })));
    assert!(granted(&eb).is_empty());
    net.user(&a).end(sa);
    net.settle();
    assert_eq!(granted(&net.take_events(&b)).len(), 1);
}

#[test]
fn a_command_session_drives_to_the_goal_and_reports_arrival() {
    let mut net = Net::new();
    net.add_system(command("d1", 1, false));
    let u = net.add_user(1);
    net.user(&u).request(ServiceId::new("d1", "s0"));
    net.settle();
    let mut events = net.take_events(&u);
    let s = granted(&events)[0];
    net.user(&u)
        .input(s, Payload::Goal2d { x: 6.0, y: 8.0 })
        .unwrap();
    net.settle();
    assert!(net
        .user(&u)
        .input(SessionId(12345), Payload::Scalar(1.0))
        .is_err());
    net.run_until(secs(15.0));
    events.extend(net.take_events(&u));
    let statuses: Vec<TaskStatus> = events
        .into_iter()
        .filter_map(|e| match e {
            UserEvent::Status { status, .. } => Some(status),
            _ => None,
        })
        .collect();
    assert_eq!(statuses[0], TaskStatus::Idle);
    assert!(matches!(&statuses[1], TaskStatus::Working(s) if s.contains("accepted")));
    let done: Vec<_> = statuses
        .iter()
        .filter(|s| matches!(s, TaskStatus::Done(_)))
        .collect();
    assert_eq!(done.len(), 1, "arrival reported once");
    // 10 m at 1 m/s, arriving within 1 m: about 9 s of progress reports at 10 Hz.
    let working = statuses
        .iter()
        .filter(|s| matches!(s, TaskStatus::Working(_)))
        .count();
    assert!((85..=95).contains(&working), "{working} progress reports");
}

#[test]
fn a_link_forwards_tracker_poses_as_delivery_goals() {
    let mut net = Net::new();
    net.add_system(data("t1", 1, 10));
    net.add_system(command("d1", 1, true));
    let u = net.add_user(1);
    let link = net
        .user(&u)
        .link(ServiceId::new("t1", "s0"), ServiceId::new("d1", "s0"));
    net.settle();
    let ev = net.take_events(&u);
    assert!(ev.contains(&UserEvent::LinkUp { link }));
    assert_eq!(
        net.list().iter().map(|v| v.links).sum::<u16>(),
        2,
        "visible to the broker"
    );
    net.run_until(secs(5.0));
    let ev = net.take_events(&u);
    let forwarded: Vec<&Payload> = ev
        .iter()
        .filter_map(|e| match e {
            UserEvent::LinkForwarded { input, .. } => Some(input),
            _ => None,
        })
        .collect();
    let updates = ev
        .iter()
        .filter(|e| matches!(e, UserEvent::Update { .. }))
        .count();
    assert_eq!(forwarded.len(), updates, "every data update is forwarded");
    assert!(forwarded
        .iter()
        .all(|p| matches!(p, Payload::Goal2d { .. })));
    // The data stops (tracker dies): the link ends with a notice, the command session too.
    net.systems.get_mut("t1").unwrap().alive = false;
    net.user(&u).system_died("t1");
    net.settle();
    let ev = net.take_events(&u);
    assert!(ev
        .iter()
        .any(|e| matches!(e, UserEvent::LinkEnded { link: l, .. } if *l == link)));
    assert!(ev.iter().any(|e| matches!(e, UserEvent::Ended { reason: EndReason::ByUser, service, .. } if service.0 == "d1/s0")));
    assert_eq!(net.systems["d1"].core.sessions_of("s0"), 0);
}

#[test]
fn sessions_and_links_survive_a_broker_crash_and_quotas_still_hold() {
    let mut net = Net::new();
    net.add_system(data("t1", 1, 2));
    net.add_system(command("d1", 1, false));
    let u = net.add_user(1);
    let v = net.add_user(2);
    net.user(&u)
        .link(ServiceId::new("t1", "s0"), ServiceId::new("d1", "s0"));
    net.user(&v).request(ServiceId::new("t1", "s0"));
    net.settle();
    net.run_until(secs(2.0));
    net.take_events(&u);
    net.take_events(&v);
    net.kill_broker();
    net.run_until(secs(30.0));
    let ev = net.take_events(&v);
    let seqs: Vec<u64> = ev
        .iter()
        .filter_map(|e| match e {
            UserEvent::Update { seq, gap, .. } => {
                assert_eq!(*gap, 0);
                Some(*seq)
            }
            _ => None,
        })
        .collect();
    assert_eq!(seqs.len(), 280, "28 s at 10 Hz with no broker");
    assert!(ev.contains(&UserEvent::BrokerLost));
    assert!(
        net.take_events(&u)
            .iter()
            .filter(|e| matches!(e, UserEvent::LinkForwarded { .. }))
            .count()
            >= 280
    );
    // A new broker: the list is rebuilt from re-registration, in-use counts included.
    net.start_broker();
    let list = net.list();
    assert_eq!(list.len(), 2);
    assert_eq!(list.iter().find(|s| s.id == "t1/s0").unwrap().in_use, 2);
    assert_eq!(list.iter().find(|s| s.id == "t1/s0").unwrap().links, 1);
    let w = net.add_user(3);
    net.user(&w).request(ServiceId::new("t1", "s0"));
    net.settle();
    assert!(net.take_events(&w).iter().any(|e| matches!(
        e,
        UserEvent::Refused {
            reason: Refusal::QuotaFull { quota: 2 },
            ..
        }
    )));
}

#[test]
fn an_hour_with_a_frozen_system_then_thawed() {
    let mut net = Net::new();
    net.add_system(data("t1", 1, 5));
    net.add_system(data("t2", 1, 5));
    let u = net.add_user(1);
    net.user(&u).request(ServiceId::new("t2", "s0"));
    net.settle();
    net.run_until(secs(600.0));
    assert_eq!(net.list().len(), 2);
    net.systems.get_mut("t1").unwrap().frozen = true; // SIGSTOP
    net.run_until(secs(650.0));
    assert_eq!(
        net.list().len(),
        1,
        "t1 delinquent within ping interval + timeout"
    );
    assert_eq!(net.list()[0].system, "t2");
    // SIGCONT: the frozen system reads the delinquency notice and re-registers.
    let s = net.systems.get_mut("t1").unwrap();
    s.frozen = false;
    s.core.handle(ToSystem::Delinquent);
    net.settle();
    assert_eq!(net.list().len(), 2);
    net.run_until(secs(3600.0));
    assert_eq!(net.list().len(), 2);
    // t2's session streamed the whole hour, undisturbed.
    let updates = net
        .take_events(&u)
        .iter()
        .filter(|e| matches!(e, UserEvent::Update { .. }))
        .count();
    assert_eq!(updates, 36_001, "an hour at 10 Hz, both ends included");
    assert!(net.delivered > 36_000);
}

#[test]
fn withdraw_ends_sessions_and_refuses_then_restore_reopens() {
    let mut net = Net::new();
    net.add_system(data("t1", 1, 5));
    let u = net.add_user(1);
    net.user(&u).request(ServiceId::new("t1", "s0"));
    net.settle();
    net.take_events(&u);
    net.systems.get_mut("t1").unwrap().core.withdraw("s0");
    net.settle();
    let ev = net.take_events(&u);
    assert!(ev.iter().any(|e| matches!(
        e,
        UserEvent::Ended {
            reason: EndReason::Withdrawn,
            ..
        }
    )));
    assert!(net.list()[0].withdrawn);
    net.user(&u).request(ServiceId::new("t1", "s0"));
    net.settle();
    assert!(net.take_events(&u).iter().any(|e| matches!(
        e,
        UserEvent::Refused {
            reason: Refusal::Withdrawn,
            ..
        }
    )));
    net.systems.get_mut("t1").unwrap().core.restore("s0");
    net.settle();
    net.user(&u).request(ServiceId::new("t1", "s0"));
    net.settle();
    assert_eq!(granted(&net.take_events(&u)).len(), 1);
}
