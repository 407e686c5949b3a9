//! `cargo bench -p muster-broker`: what the broker's core costs per message type, the
//! list snapshot it writes on a change, the frame codec, and replication (archiving
//! the journal a standby follows). The core is pure (no I/O): these are the CPU costs
//! under every wake-up a process measurement sees.
//!
//! The broker holds 20 systems of 4 services each and 200 users who said hello, as in
//! `muster bench failover`. Each message type is timed alone (`iter_custom`), inside
//! the whole cycle that keeps the state steady: request → offer → answer (grant) →
//! session ended.

use criterion::{criterion_group, criterion_main, Criterion};
use muster_broker::replica::Leader;
use muster_broker::{Broker, BrokerConfig, Output};
use muster_shared::protocol::{decode, encode, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::ServiceListSnapshot;
use muster_shared::types::{ServiceId, ServiceKind, ServiceSpec, SessionId, UserId};
use std::hint::black_box;
use std::time::{Duration, Instant};

const SYSTEMS: usize = 20;
const USERS: usize = 200;

fn specs() -> Vec<ServiceSpec> {
    (0..4)
        .map(|i| ServiceSpec {
            name: format!("s{i}"),
            description: "synthetic data".into(),
            kind: ServiceKind::Data,
            queue: false,
            quota: 1000,
            payload: "pose2d".into(),
            schema: None,
        })
        .collect()
}

fn register(system: usize) -> ToBroker {
    ToBroker::Register {
        system: format!("f{system}"),
        pid: 1000 + system as u32,
        services: specs(),
        sessions: vec![],
        udp: None,
    }
}

fn hello(user: usize) -> ToBroker {
    ToBroker::Hello {
        user: UserId(format!("u{user}")),
        pid: 5000 + user as u32,
        links: vec![],
        watch_list: false,
    }
}

/// A broker with every system registered and every user welcomed.
fn loaded() -> (Broker, Duration) {
    let mut core = Broker::new(BrokerConfig::default(), 1, 1);
    let now = Duration::from_secs(1);
    for s in 0..SYSTEMS {
        core.handle(now, register(s));
    }
    for u in 0..USERS {
        core.handle(now, hello(u));
    }
    drain(&mut core);
    (core, now)
}

/// Empties the core's outputs; returns the ticket of the last offer among them.
/// Takes the outputs; gives the offer's ticket and the session granted, if any.
fn drain(core: &mut Broker) -> Option<(u64, SessionId)> {
    let mut offer = None;
    while let Some(o) = core.poll_output() {
        if let Output::ToSystem(
            _,
            ToSystem::Offer {
                ticket, session, ..
            },
        ) = o
        {
            offer = Some((ticket, session));
        }
    }
    offer
}

/// One request cycle; `time` says which message's handling is timed.
#[derive(Clone, Copy, PartialEq)]
enum Timed {
    Request,
    OfferAnswer,
    SessionEnded,
}

struct Cycle {
    core: Broker,
    now: Duration,
    n: u64,
}

impl Cycle {
    fn run(&mut self, timed: Timed) -> Duration {
        self.n += 1;
        let n = self.n as usize;
        let user = UserId(format!("u{}", n % USERS));
        let system = format!("f{}", n % SYSTEMS);
        let service = ServiceId::new(&system, &format!("s{}", (n / SYSTEMS) % 4));
        let mut spent = Duration::ZERO;
        let mut handle = |core: &mut Broker, msg: ToBroker, this: Timed| {
            let t = Instant::now();
            core.handle(self.now, msg);
            let ticket = drain(core);
            if this == timed {
                spent = t.elapsed();
            }
            ticket
        };
        let (ticket, session) = handle(
            &mut self.core,
            ToBroker::Request {
                user,
                req: self.n,
                service,
            },
            Timed::Request,
        )
        .expect("an offer");
        handle(
            &mut self.core,
            ToBroker::OfferAnswer {
                system: system.clone(),
                ticket,
                answer: Ok(session),
            },
            Timed::OfferAnswer,
        );
        handle(
            &mut self.core,
            ToBroker::SessionEnded { system, session },
            Timed::SessionEnded,
        );
        spent
    }
}

fn handling(c: &mut Criterion) {
    let mut g = c.benchmark_group("broker_handle");
    for (name, timed) in [
        ("request", Timed::Request),
        ("offer_answer_confirm", Timed::OfferAnswer),
        ("session_ended", Timed::SessionEnded),
    ] {
        let (core, now) = loaded();
        let mut cycle = Cycle { core, now, n: 0 };
        g.bench_function(name, |b| {
            b.iter_custom(|iters| (0..iters).map(|_| cycle.run(timed)).sum())
        });
    }
    let (mut core, now) = loaded();
    let mut u = 0;
    g.bench_function("hello_again", |b| {
        b.iter(|| {
            u = (u + 1) % USERS;
            core.handle(now, hello(u));
            drain(&mut core);
        })
    });
    let mut s = 0;
    g.bench_function("register_again_4_services", |b| {
        b.iter(|| {
            s = (s + 1) % SYSTEMS;
            core.handle(now, register(s));
            drain(&mut core);
        })
    });
    g.finish();
}

fn list(c: &mut Criterion) {
    let (core, _) = loaded();
    let mut snapshot = Box::new(ServiceListSnapshot::empty());
    // What the broker does on every list change before the blackboard write: the
    // views of all 80 services, copied into the snapshot.
    c.bench_function("list_snapshot_fill_80_services", |b| {
        b.iter(|| {
            let views = core.views();
            for (slot, v) in snapshot.resize(views.len()).iter_mut().zip(views.iter()) {
                *slot = v.to_entry();
            }
            black_box(&snapshot);
        })
    });
}

/// A user's list read out of a real blackboard (shared memory, one process): the list
/// unchanged since the last read, and changed before every read.
fn list_read(c: &mut Criterion) {
    use muster_shared::fence::Fence;
    use muster_shared::ipc::{create_node, ListReader, ListWriter};
    let inst =
        muster_shared::Instance::new(&format!("bench-list-{}", std::process::id())).expect("name");
    let node = create_node("bench-list", false).expect("node");
    let fence = Fence::open(&inst).expect("fence");
    let mut writer = ListWriter::open(&node, &inst, 1).expect("list");
    let (core, _) = loaded();
    let mut snapshot = Box::new(ServiceListSnapshot::empty());
    let views = core.views();
    for (slot, v) in snapshot.resize(views.len()).iter_mut().zip(views.iter()) {
        *slot = v.to_entry();
    }
    snapshot.generation = 1;
    writer.publish(&node, &snapshot, &fence).expect("publish");
    let mut reader = ListReader::open(&node, &inst).expect("reader");
    let mut g = c.benchmark_group("list_read_80_services");
    g.bench_function("unchanged", |b| {
        b.iter(|| black_box(reader.read_from(&node).expect("read").count()))
    });
    g.bench_function("changed", |b| {
        b.iter_custom(|iters| {
            let mut spent = Duration::ZERO;
            for _ in 0..iters {
                snapshot.generation += 1;
                writer.publish(&node, &snapshot, &fence).expect("publish");
                let t = Instant::now();
                black_box(reader.read_from(&node).expect("read").count());
                spent += t.elapsed();
            }
            spent
        })
    });
    g.finish();
    drop(reader);
    drop(writer);
    fence.remove();
}

fn codec(c: &mut Criterion) {
    let mut g = c.benchmark_group("codec");
    let request = ToBroker::Request {
        user: UserId("u17".into()),
        req: 42,
        service: ServiceId::new("f3", "s1"),
    };
    let frame = encode(&request).expect("encodes");
    g.bench_function("request_encode", |b| b.iter(|| encode(black_box(&request))));
    g.bench_function("request_decode", |b| {
        b.iter(|| decode::<ToBroker>(black_box(&frame)))
    });
    let granted = ToUser::Granted {
        req: 42,
        session: SessionId(7),
        service: ServiceId::new("f3", "s1"),
        kind: ServiceKind::Data,
        payload: "pose2d".into(),
        schema: None,
        system_pid: 1003,
        relayed: false,
    };
    let frame = encode(&granted).expect("encodes");
    g.bench_function("granted_decode", |b| {
        b.iter(|| decode::<ToUser>(black_box(&frame)))
    });
    g.finish();
}

fn replication(c: &mut Criterion) {
    // A primary with standbys archives every input it applies: the cost of one
    // request cycle's records (3 ops).
    let (mut core, now) = loaded();
    core.keep_journal();
    let mut leader = Leader::after(0);
    let _ = leader.ops(&mut core);
    let mut cycle = Cycle { core, now, n: 0 };
    c.bench_function("replica_archive_request_cycle", |b| {
        b.iter_custom(|iters| {
            let mut spent = Duration::ZERO;
            for _ in 0..iters {
                cycle.run(Timed::Request);
                let t = Instant::now();
                black_box(leader.ops(&mut cycle.core));
                spent += t.elapsed();
            }
            spent
        })
    });
    let (core, _) = loaded();
    c.bench_function("replica_image_20_systems_200_users", |b| {
        b.iter(|| black_box(core.archived_state()))
    });
}

criterion_group!(benches, handling, list, list_read, codec, replication);
criterion_main!(benches);
