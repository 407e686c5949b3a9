//! The UDP front driven by hand: datagrams in, datagrams and core messages out.

#![allow(clippy::unwrap_used)]

use super::*;
use crate::core::BrokerConfig;
use muster_shared::udp::access::access_line;
use muster_shared::udp::msgs::{to_bytes, Down, Hs3, Up};
use muster_shared::udp::wire::Datagram;

struct Rig {
    front: UdpFront,
    core: Broker,
    now: Instant,
    addr: SocketAddr,
    user: KeyPair,
}

impl Rig {
    fn new(limits: UdpLimits) -> Self {
        Self::allowing(limits, &["*"])
    }

    /// A rig where alice may use the services matching `patterns`.
    fn allowing(limits: UdpLimits, patterns: &[&str]) -> Self {
        Self::allowing_as(limits, patterns, false)
    }

    /// The same, alice an operator if `operator`.
    fn allowing_as(limits: UdpLimits, patterns: &[&str], operator: bool) -> Self {
        let user = KeyPair::generate().unwrap();
        let patterns: Vec<String> = patterns.iter().map(|p| p.to_string()).collect();
        let access =
            AccessFile::parse(&access_line("alice", &user.public, &patterns, operator)).unwrap();
        let now = Instant::now();
        let front = UdpFront::new(
            KeyPair::generate().unwrap(),
            access,
            limits,
            "127.0.0.1:7000".parse().unwrap(),
            1,
            now,
            [7; 32],
        );
        Rig {
            front,
            core: Broker::new(BrokerConfig::default(), 1, 1),
            now,
            addr: "127.0.0.1:40000".parse().unwrap(),
            user,
        }
    }

    /// Hands the front a datagram, the core what the front made of it, and returns
    /// every datagram sent back.
    fn exchange(&mut self, d: &[u8]) -> Vec<Vec<u8>> {
        self.front.handle(self.now, self.addr, d, &self.core);
        while let Some(ev) = self.front.poll_event() {
            match ev {
                FrontEvent::ToCore(m) => self.core.handle(Duration::ZERO, m),
                FrontEvent::UserGone(u) => self.core.user_died(Duration::ZERO, &u),
                FrontEvent::Revoked(u) => self.core.revoke(Duration::ZERO, &u),
            }
        }
        while let Some(out) = self.core.poll_output() {
            let _ = self.front.route(&self.core, out);
        }
        let mut got = Vec::new();
        while let Some(t) = self.front.poll_transmit() {
            assert_eq!(t.to, self.addr);
            got.push(t.bytes);
        }
        got
    }

    fn token(&mut self, client: u64) -> Vec<u8> {
        let init = Datagram::Initial {
            client,
            token: b"",
            noise: b"",
        }
        .encode()
        .unwrap();
        let got = self.exchange(&init);
        match Datagram::decode(&got[0]).unwrap() {
            Datagram::Retry { token, .. } => token.to_vec(),
            other => panic!("{other:?}"),
        }
    }

    /// Token, then message 1; returns the handshake and the reply datagrams.
    fn start(&mut self, client: u64) -> (HandshakeState, Vec<Vec<u8>>) {
        let token = self.token(client);
        let mut hs = crypto::initiator(&self.user).unwrap();
        let mut m1 = [0u8; 128];
        let n = hs.write_message(&[], &mut m1).unwrap();
        let d = Datagram::Initial {
            client,
            token: &token,
            noise: &m1[..n],
        }
        .encode()
        .unwrap();
        let got = self.exchange(&d);
        (hs, got)
    }
}

impl Rig {
    /// A whole handshake as alice; returns the connection id and the user's channel.
    fn connect(&mut self, client: u64) -> (u64, Channel) {
        let (mut hs, got) = self.start(client);
        let Datagram::HsReply { conn, noise, .. } = Datagram::decode(&got[0]).unwrap() else {
            panic!()
        };
        let mut scratch = [0u8; 256];
        hs.read_message(noise, &mut scratch).unwrap();
        let payload = to_bytes(&Hs3 {
            name: "alice".into(),
            suffix: "abc".into(),
        })
        .unwrap();
        let mut m3 = [0u8; 256];
        let n = hs.write_message(&payload, &mut m3).unwrap();
        let fin = Datagram::HsFinal {
            conn,
            noise: &m3[..n],
        }
        .encode()
        .unwrap();
        assert!(self.exchange(&fin).is_empty());
        (conn, Channel::new(hs).unwrap())
    }

    /// Sends `m` on the channel; returns the answers, opened.
    fn say(&mut self, conn: u64, chan: &mut Channel, m: &Up) -> Vec<Down> {
        let d = sealed(conn, chan, m);
        self.exchange(&d)
            .iter()
            .map(|b| match Datagram::decode(b).unwrap() {
                Datagram::Channel { nonce, sealed, .. } => {
                    from_bytes(&chan.open(nonce, sealed).unwrap()).unwrap()
                }
                other => panic!("{other:?}"),
            })
            .collect()
    }
}

/// A `CHANNEL` datagram carrying `m`.
fn sealed(conn: u64, chan: &mut Channel, m: &Up) -> Vec<u8> {
    let (nonce, sealed) = chan.seal(&to_bytes(m).unwrap()).unwrap();
    Datagram::Channel {
        conn,
        nonce,
        sealed: &sealed,
    }
    .encode()
    .unwrap()
}

#[test]
fn forged_channel_datagrams_do_not_spend_the_users_rate() {
    let mut r = Rig::new(UdpLimits {
        conn_rate: (0.001, 10.0),
        ..UdpLimits::default()
    });
    let (conn, mut chan) = r.connect(1);
    // 1000 forgeries carrying the live connection id.
    for i in 0..1000u64 {
        let d = Datagram::Channel {
            conn,
            nonce: i,
            sealed: &[0u8; 40],
        }
        .encode()
        .unwrap();
        assert!(r.exchange(&d).is_empty());
    }
    assert_eq!(r.front.stats().drops.by_reason["forged_or_replayed"], 1000);
    // The user still has its whole burst.
    for k in 0..10 {
        let got = r.say(conn, &mut chan, &Up::Ping { nonce: k });
        assert!(
            matches!(&got[..], [Down::Pong { nonce, .. }] if *nonce == k),
            "ping {k}: {got:?}"
        );
    }
    assert!(r.say(conn, &mut chan, &Up::Ping { nonce: 10 }).is_empty());
    assert_eq!(r.front.stats().drops.by_reason["conn_rate"], 1);
}

#[test]
fn pending_handshakes_are_capped_and_expire() {
    let mut r = Rig::new(UdpLimits {
        max_pending: 4,
        handshake_timeout: Duration::from_millis(50),
        ..UdpLimits::default()
    });
    let answered = (0..10).filter(|c| !r.start(*c).1.is_empty()).count();
    assert_eq!(answered, 4);
    assert_eq!(r.front.stats().drops.by_reason["pending_full"], 6);
    r.now += Duration::from_millis(60);
    r.front.handle_timeout(r.now);
    assert!(!r.start(99).1.is_empty(), "room again after expiry");
}

#[test]
fn a_validated_source_is_rate_limited() {
    let mut r = Rig::new(UdpLimits {
        source_rate: (0.001, 3.0),
        ..UdpLimits::default()
    });
    let answered = (0..6).filter(|c| !r.start(*c).1.is_empty()).count();
    assert_eq!(answered, 3);
    assert_eq!(r.front.stats().drops.by_reason["source_rate"], 3);
}

#[test]
fn a_full_handshake_then_a_duplicated_request_is_answered_once() {
    let mut r = Rig::new(UdpLimits::default());
    let (conn, mut chan) = r.connect(1);
    assert_eq!(r.front.connections(), 1);
    let mut say = |r: &mut Rig, m: &Up| r.say(conn, &mut chan, m);
    let hello = Up::Msg(ToBroker::Hello {
        user: UserId("claimed-to-be-bob".into()),
        pid: 4242,
        links: vec![],
        watch_list: false,
    });
    let welcome = say(&mut r, &hello);
    assert!(
        matches!(&welcome[..], [Down::Welcome { user, .. }] if user.0 == "alice.abc"),
        "the id is the authenticated name, not the claimed one: {welcome:?}"
    );
    let req = Up::Msg(ToBroker::Request {
        user: UserId("bob".into()),
        req: 1,
        service: ServiceId::new("nosuch", "s0"),
    });
    let first = say(&mut r, &req);
    let second = say(&mut r, &req);
    assert_eq!(first, second, "the repeat gets the remembered answer");
    assert!(matches!(
        &first[..],
        [Down::Msg(ToUser::Refused { req: 1, .. })]
    ));
    assert_eq!(r.core.stats().requests, 1, "the core saw the request once");
    assert_eq!(r.front.stats().duplicate_requests, 1);
    // A replayed datagram is dropped.
    let d = sealed(conn, &mut chan, &Up::Ping { nonce: 5 });
    assert_eq!(r.exchange(&d).len(), 1);
    assert!(r.exchange(&d).is_empty());
    assert_eq!(r.front.stats().drops.by_reason["forged_or_replayed"], 1);
}

#[test]
fn links_over_services_a_user_may_not_use_are_not_counted() {
    use muster_shared::protocol::LinkInfo;
    use muster_shared::types::{ServiceKind, ServiceSpec};
    let mut r = Rig::allowing(UdpLimits::default(), &["s/s0", "d/*"]);
    let spec = |name: &str, kind: ServiceKind| ServiceSpec {
        name: name.into(),
        description: String::new(),
        kind,
        queue: false,
        quota: 5,
        payload: "pose2d".into(),
        schema: None,
    };
    for (system, specs) in [
        (
            "s",
            vec![spec("s0", ServiceKind::Data), spec("s1", ServiceKind::Data)],
        ),
        ("d", vec![spec("go", ServiceKind::Command)]),
    ] {
        r.core.handle(
            Duration::ZERO,
            ToBroker::Register {
                system: system.into(),
                pid: 1,
                services: specs,
                sessions: vec![],
                udp: None,
            },
        );
    }
    let (conn, mut chan) = r.connect(1);
    let link = |n: u64, data: &str| LinkInfo {
        link: n,
        data: ServiceId::new("s", data),
        command: ServiceId::new("d", "go"),
    };
    let hello = Up::Msg(ToBroker::Hello {
        user: UserId("x".into()),
        pid: 0,
        links: vec![link(1, "s1")],
        watch_list: false,
    });
    r.say(conn, &mut chan, &hello);
    for (n, data) in [(2, "s1"), (3, "s0")] {
        let m = Up::Msg(ToBroker::LinkOpened {
            user: UserId("x".into()),
            link: link(n, data),
        });
        r.say(conn, &mut chan, &m);
    }
    let views = r.core.views();
    let links = |id: &str| views.iter().find(|v| v.id == id).unwrap().links;
    assert_eq!((links("s/s0"), links("s/s1"), links("d/go")), (1, 0, 1));
    assert_eq!(r.front.stats().drops.by_reason["link_not_allowed"], 1);
}

#[test]
fn an_operators_action_reaches_the_core_once_and_its_answer_comes_in_pieces() {
    use muster_shared::protocol::{BrokerEvent, Operation};
    use muster_shared::udp::msgs::OperatedAssembly;
    let hello = Up::Msg(ToBroker::Hello {
        user: UserId("x".into()),
        pid: 1,
        links: vec![],
        watch_list: false,
    });
    let operate = |id: u64, op: Operation| {
        Up::Msg(ToBroker::Operate {
            user: UserId("claimed".into()),
            id,
            op,
        })
    };
    // A plain user is told it is no operator; the core never hears of it.
    let mut r = Rig::allowing_as(UdpLimits::default(), &["*"], false);
    r.core.emit_events();
    let (conn, mut chan) = r.connect(1);
    r.say(conn, &mut chan, &hello);
    let got = r.say(conn, &mut chan, &operate(1, Operation::Status));
    assert!(
        matches!(&got[..], [Down::Msg(ToUser::Operated { id: 1, result: Err(e) })] if e.contains("not an operator")),
        "{got:?}"
    );
    assert!(std::iter::from_fn(|| r.core.poll_event())
        .all(|e| !matches!(e, BrokerEvent::Operated { .. })));
    // Nor does it get the event feed.
    r.front
        .feed(r#"{"epoch":"1","seq":1,"t_ns":1,"event":"user_left","user":"u"}"#);
    assert!(r.front.poll_transmit().is_none());

    // An operator: its status comes in pieces that make the whole answer, and an
    // action sent again is answered again from memory, not done again.
    let mut r = Rig::allowing_as(UdpLimits::default(), &["*"], true);
    r.core.emit_events();
    let (conn, mut chan) = r.connect(1);
    r.say(conn, &mut chan, &hello);
    let whole = |pieces: Vec<Down>| {
        let mut a = OperatedAssembly::default();
        let mut out = None;
        for d in pieces {
            match d {
                Down::OperatedChunk {
                    id: 2,
                    index,
                    total,
                    bytes,
                } => out = a.add(index, total, bytes).or(out),
                other => panic!("{other:?}"),
            }
        }
        out.expect("a whole answer")
    };
    let status = whole(r.say(conn, &mut chan, &operate(2, Operation::Status)))
        .unwrap()
        .unwrap();
    assert_eq!(
        status.users[0].user.0, "alice.abc",
        "the operator is who it authenticated as"
    );
    let withdraw = operate(
        3,
        Operation::Withdraw {
            service: ServiceId::new("nosuch", "s0"),
        },
    );
    let first = r.say(conn, &mut chan, &withdraw);
    let again = r.say(conn, &mut chan, &withdraw);
    assert_eq!(first, again);
    let operated: Vec<_> = std::iter::from_fn(|| r.core.poll_event())
        .filter_map(|e| match e {
            BrokerEvent::Operated { user, error, .. } => Some((user.0, error)),
            _ => None,
        })
        .collect();
    // (A status read is not told on the feed.)
    assert_eq!(operated.len(), 1, "the withdrawal, once: {operated:?}");
    assert_eq!(operated[0].0, "alice.abc");
    assert!(operated[0]
        .1
        .as_deref()
        .is_some_and(|e| e.contains("no service")));
    // Having acted, it follows the event feed.
    let json = r#"{"epoch":"1","seq":1,"t_ns":1,"event":"user_left","user":"u"}"#;
    r.front.feed(json);
    let t = r.front.poll_transmit().expect("the record, sent");
    let Datagram::Channel { nonce, sealed, .. } = Datagram::decode(&t.bytes).unwrap() else {
        panic!()
    };
    let d: Down = from_bytes(&chan.open(nonce, sealed).unwrap()).unwrap();
    assert_eq!(d, Down::Event(json.into()));
    // A record too large for a datagram is not sent.
    r.front
        .feed(&format!("{{\"pad\":\"{}\"}}", "x".repeat(2000)));
    assert!(r.front.poll_transmit().is_none());
    // Demoted (its `operator` line made a `user` line, SIGHUP): connected still, as a
    // user, but the feed stops.
    let line = access_line("alice", &r.user.public, &["*".to_string()], false);
    r.front.reload(r.now, AccessFile::parse(&line).unwrap());
    r.front.feed(json);
    assert!(
        r.front.poll_transmit().is_none(),
        "a demoted operator is fed"
    );
    let got = r.say(conn, &mut chan, &operate(4, Operation::Status));
    assert!(
        matches!(&got[..], [Down::Msg(ToUser::Operated { id: 4, result: Err(e) })] if e.contains("not an operator")),
        "{got:?}"
    );
}
