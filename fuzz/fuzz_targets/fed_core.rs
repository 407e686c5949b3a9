//! The federation core driven by any sequence of what other hosts can send (tokens,
//! lists, frames: well-formed ones with fuzzed fields, and raw bytes), what local
//! processes write into its inboxes, local users' requests, the local system's answers
//! to offers, and time. Never a panic; every output is one the driver can carry out;
//! the merged list never holds more than it may.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_broker::federation::{FedCore, FedInput, FedMsg, FedOutput, HeldSession, Inboxes};
use muster_broker::{Broker, BrokerConfig, Output};
use muster_shared::names::Address;
use muster_shared::protocol::{encode, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::{ServiceView, DEFAULT_MAX_SERVICES};
use muster_shared::types::{
    EndReason, Payload, Refusal, ServiceId, ServiceKind, ServiceSpec, SessionId, UserId,
};
use std::collections::BTreeSet;
use std::time::Duration;

struct Io {
    open: BTreeSet<Address>,
}

impl Inboxes for Io {
    fn open(&mut self, peer: &Address) -> Result<(), String> {
        if self.open.len() >= 64 {
            return Err("full".into());
        }
        self.open.insert(peer.clone());
        Ok(())
    }
    fn close(&mut self, peer: &Address) {
        self.open.remove(peer);
    }
    fn send(&mut self, peer: &Address, _to: &Address, _msg: &ToSystem) {
        assert!(self.open.contains(peer), "sent through a closed inbox");
    }
    fn owner_pid(&mut self, _peer: &Address, of: &Address) -> Option<u32> {
        (*of == Address::System("t".into())).then_some(7)
    }
}

struct Bytes<'a>(&'a [u8]);

impl Bytes<'_> {
    fn u8(&mut self) -> Option<u8> {
        let (b, rest) = self.0.split_first()?;
        self.0 = rest;
        Some(*b)
    }
    fn take(&mut self, n: usize) -> &[u8] {
        let n = n.min(self.0.len());
        let (a, b) = self.0.split_at(n);
        self.0 = b;
        a
    }
}

const HOSTS: [&str; 4] = ["a", "b", "c", "me"];

fn host(b: u8) -> String {
    HOSTS[usize::from(b) % HOSTS.len()].to_string()
}

fn user(b: u8) -> UserId {
    UserId(format!("u{}", b % 5))
}

fn session(b: u8) -> SessionId {
    SessionId(u64::from(b % 7))
}

fn service(b: u8) -> ServiceId {
    match b % 4 {
        0 => ServiceId::new("t", "s0"),
        1 => ServiceId::new("t", "nope"),
        2 => ServiceId("t@b/s0".into()),
        _ => ServiceId("x/y/z".into()),
    }
}

fn to_user(b: &mut Bytes) -> ToUser {
    let (k, s, r) = (
        b.u8().unwrap_or(0),
        b.u8().unwrap_or(0),
        b.u8().unwrap_or(0),
    );
    match k % 5 {
        0 => ToUser::Granted {
            req: u64::from(r % 4),
            session: session(s),
            service: service(r),
            kind: ServiceKind::Data,
            payload: "pose2d".into(),
            schema: None,
            system_pid: 7,
            relayed: false,
        },
        1 => ToUser::Update {
            session: session(s),
            seq: u64::from(r),
            sent_ns: 0,
            payload: Payload::Text("x".into()),
        },
        2 => ToUser::Ended {
            session: session(s),
            reason: EndReason::ByUser,
            last_seq: u64::from(r),
        },
        3 => ToUser::Queued {
            req: u64::from(r % 4),
            position: 1,
        },
        _ => ToUser::Refused {
            req: u64::from(r % 4),
            reason: Refusal::Unknown,
        },
    }
}

fn fed_msg(b: &mut Bytes) -> FedMsg {
    let (k, u, x) = (
        b.u8().unwrap_or(0),
        b.u8().unwrap_or(0),
        b.u8().unwrap_or(0),
    );
    match k % 9 {
        7 => FedMsg::Resync,
        8 => FedMsg::Held {
            sessions: vec![HeldSession {
                user: user(u),
                session: session(x),
                system: if x % 2 == 0 { "t".into() } else { "t/x".into() },
            }],
            done: u % 2 == 0,
        },
        0 => FedMsg::Request {
            user: user(u),
            req: u64::from(x % 4),
            service: service(x),
            remote: None,
        },
        1 => FedMsg::Cancel {
            user: user(u),
            req: u64::from(x % 4),
        },
        2 => FedMsg::ToSystem {
            system: "t".into(),
            msg: ToSystem::End {
                user: user(u),
                session: session(x),
            },
        },
        3 => FedMsg::UserGone { user: user(u) },
        4 => FedMsg::Link {
            user: user(u),
            link: u64::from(x % 3),
            services: vec![service(x)],
            open: x % 2 == 0,
        },
        _ => FedMsg::ToUser {
            user: user(u),
            msg: to_user(b),
        },
    }
}

fuzz_target!(|data: &[u8]| {
    let mut b = Bytes(data);
    let mut now = Duration::from_secs(1);
    let mut broker = Broker::new(BrokerConfig::default(), 1, 1);
    let mut fed = FedCore::new("me", 1, None, None, now);
    let mut io = Io {
        open: BTreeSet::new(),
    };
    broker.handle(
        now,
        ToBroker::Register {
            system: "t".into(),
            pid: 7,
            services: vec![ServiceSpec {
                name: "s0".into(),
                description: String::new(),
                kind: ServiceKind::Data,
                queue: true,
                quota: 2,
                payload: "pose2d".into(),
                schema: None,
            }],
            sessions: Vec::new(),
            udp: None,
        },
    );
    let mut offers: Vec<(u64, SessionId)> = Vec::new();
    let mut views: Vec<ServiceView> = Vec::new();
    let mut local: Vec<ServiceView> = Vec::new();
    for _ in 0..64 {
        let Some(op) = b.u8() else { break };
        match op % 10 {
            0 => {
                let (h, up) = (b.u8().unwrap_or(0), b.u8().unwrap_or(0));
                let input = if up % 4 < 2 {
                    FedInput::Alive(host(h), up % 2 == 0)
                } else {
                    FedInput::Standby(host(h), up % 2 == 0)
                };
                fed.handle(now, input, &mut broker, &mut io);
            }
            1 => {
                let h = b.u8().unwrap_or(0);
                let version = u64::from(b.u8().unwrap_or(0));
                let n = usize::from(b.u8().unwrap_or(0));
                let body = b.take(n).to_vec();
                let input = FedInput::List {
                    host: host(h),
                    version,
                    body,
                };
                fed.handle(now, input, &mut broker, &mut io);
            }
            2 => {
                let h = b.u8().unwrap_or(0);
                let n = usize::from(b.u8().unwrap_or(0));
                let bytes = b.take(n).to_vec();
                let input = FedInput::Frame {
                    from: host(h),
                    users_side: h % 2 == 0,
                    bytes,
                };
                fed.handle(now, input, &mut broker, &mut io);
            }
            3 | 4 => {
                let h = b.u8().unwrap_or(0);
                let m = fed_msg(&mut b);
                let input = FedInput::Frame {
                    from: host(h),
                    users_side: m.on_users_key(),
                    bytes: encode(&m).unwrap_or_default(),
                };
                fed.handle(now, input, &mut broker, &mut io);
            }
            5 => {
                // A local process writes into an inbox.
                let k = b.u8().unwrap_or(0);
                let (peer, frame) = if k % 2 == 0 {
                    let u = UserId(format!("{}@{}", user(k).0, host(k / 2)));
                    (Address::User(u), encode(&to_user(&mut b)).unwrap_or_default())
                } else {
                    let m = ToSystem::End {
                        user: user(k),
                        session: session(k / 2),
                    };
                    (Address::System(format!("t@{}", host(k / 2))), encode(&m).unwrap())
                };
                let sender = (k % 3 != 0).then_some(7);
                fed.inbox_frame(&peer, &frame, sender, &broker, &mut io);
            }
            6 => {
                // A local user asks for (or cancels) another host's service.
                let (u, x) = (b.u8().unwrap_or(0), b.u8().unwrap_or(0));
                broker.handle(
                    now,
                    ToBroker::Hello {
                        user: user(u),
                        pid: 100 + u32::from(u % 5),
                        links: Vec::new(),
                        watch_list: false,
                    },
                );
                let msg = if x % 3 == 0 {
                    ToBroker::Cancel {
                        user: user(u),
                        req: u64::from(x % 4),
                    }
                } else {
                    ToBroker::Request {
                        user: user(u),
                        req: u64::from(x % 4),
                        service: ServiceId(format!("t@{}/s0", host(x))),
                    }
                };
                if !fed.intercept(now, &msg, |_, _| None) {
                    broker.handle(now, msg);
                }
            }
            7 => {
                // The local system answers the oldest offer.
                if !offers.is_empty() {
                    let (ticket, s) = offers.remove(0);
                    let grant = b.u8().unwrap_or(0) % 3 != 0;
                    broker.handle(
                        now,
                        ToBroker::OfferAnswer {
                            system: "t".into(),
                            ticket,
                            answer: if grant { Ok(s) } else { Err("no".into()) },
                        },
                    );
                }
            }
            8 => {
                let k = b.u8().unwrap_or(0);
                if k % 5 == 4 {
                    // A standby takes over this state.
                    fed = FedCore::new("me", 2, None, None, now);
                    broker.take_over(now, 2, 2);
                    fed.take_over(now, &mut broker, &mut io);
                } else if k % 2 == 0 {
                    fed.local_user_gone(&user(k));
                    broker.user_died(now, &user(k));
                } else {
                    fed.local_system_gone("t");
                }
            }
            _ => {
                now += Duration::from_millis(u64::from(b.u8().unwrap_or(0)) * 40);
                if fed.poll_timeout().is_some_and(|t| t <= now) {
                    fed.handle_timeout(now, &mut broker, &mut io);
                }
                if broker.poll_timeout().is_some_and(|t| t <= now) {
                    broker.handle_timeout(now);
                }
            }
        }
        // What the shell does after each step: the core's outputs through the
        // federation, the list published and merged, the federation's outputs out.
        while let Some(o) = broker.poll_output() {
            if let Some(Output::ToSystem(_, ToSystem::Offer { ticket, session, .. })) =
                fed.route(&broker, o)
            {
                offers.push((ticket, session));
            }
        }
        if broker.take_list_change_into(&mut views).is_some() || fed.take_links_change() {
            local = fed.publish_list(now, now.as_nanos() as u64, &views, &["t"]);
        }
        assert!(fed.merged_views(&local, DEFAULT_MAX_SERVICES).len() <= DEFAULT_MAX_SERVICES);
        while let Some(o) = fed.poll_output() {
            match o {
                FedOutput::Send { to, msg } => {
                    assert_ne!(to, "me", "a frame for this host itself");
                    assert!(encode(&msg).is_ok(), "a frame that does not encode");
                }
                FedOutput::QueryList(h) => assert_ne!(h, "me"),
                _ => {}
            }
        }
    }
});
