//! Bad input and dying peers, against real processes: a hand-driven fake peer writes
//! garbage into the broker's and a system's inbox, and requests on behalf of a dead user.

#![allow(clippy::unwrap_used)]

mod common;

use common::{Fed, SEC};
use muster_shared::ipc::{create_node, Endpoint, TransportError};
use muster_shared::protocol::{encode, ToBroker, MAGIC, VERSION};
use muster_shared::types::{ServiceId, UserId};
use muster_shared::{Address, Instance};
use std::time::Duration;

fn fake(inst: &str, me: Address) -> Endpoint {
    let inst = Instance::new(inst).unwrap();
    let node = create_node(&format!("muster-test-{}", std::process::id()), false).unwrap();
    Endpoint::open(&inst, me, node).unwrap()
}

fn garbage() -> Vec<Vec<u8>> {
    let valid = encode(&ToBroker::Goodbye {
        user: UserId("x".into()),
    })
    .unwrap();
    let mut trailing = valid.clone();
    trailing.extend_from_slice(b"junk");
    let mut wrong_version = valid.clone();
    wrong_version[1] = VERSION + 1;
    let mut frames = vec![
        vec![],
        vec![MAGIC],
        vec![0xff; 64],
        wrong_version,
        trailing,
        valid[..valid.len() - 1].to_vec(),
        vec![
            MAGIC, VERSION, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f,
        ],
    ];
    // Deterministic pseudo-random frames with a valid header.
    let mut x: u32 = 0x1234_5678;
    for len in 0..200usize {
        let mut f = vec![MAGIC, VERSION];
        for _ in 0..len % 97 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            f.push(x as u8);
        }
        frames.push(f);
    }
    frames
}

#[test]
fn garbage_frames_are_dropped_and_lose_nothing() {
    let mut f = Fed::new("garbage");
    f.broker(&[]);
    f.system("t1", &["--quota", "3"]);
    let (before, _) = f.wait_list(10 * SEC, |l| l.len() == 1);
    let holder = f.spawn(&["user", "request", "t1/s0", "--duration", "20s", "--json"]);
    assert_eq!(f.proc(holder).json(10 * SEC).unwrap()["granted"], true);

    let mut as_user = fake(&f.inst, Address::User(UserId("evil".into())));
    for (i, frame) in garbage().iter().enumerate() {
        for to in [Address::Broker, Address::System("t1".into())] {
            match as_user.send(&to, frame) {
                Ok(()) | Err(TransportError::Full(_)) => {}
                Err(e) => panic!("frame {i} to {to}: {e}"),
            }
        }
        if i % 16 == 15 {
            std::thread::sleep(Duration::from_millis(20)); // let the readers drain
        }
    }
    // Larger than any frame may be, on the one path that allows large frames.
    let mut as_system = fake(&f.inst, Address::System("evilsys".into()));
    let mut huge = vec![MAGIC, VERSION];
    huge.resize(100 * 1024, 0x42);
    as_system.send(&Address::Broker, &huge).unwrap();
    // A frame too large for a user's path is refused by the sender, not sent.
    assert!(as_user.send(&Address::Broker, &huge).is_err());

    // Everything still works, and nothing was lost.
    std::thread::sleep(Duration::from_millis(300));
    let after = f.list();
    assert_eq!(after.len(), before.len());
    assert_eq!(after[0]["in_use"], 1, "the live session still counts");
    let (code, out) = f.run(
        &["user", "request", "t1/s0", "--duration", "500ms", "--json"],
        20 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    let seqs: Vec<u64> = (0..5)
        .filter_map(|_| f.proc(holder).json(5 * SEC))
        .filter_map(|v| v["seq"].as_u64())
        .collect();
    assert!(
        seqs.len() >= 4 && seqs.windows(2).all(|w| w[1] == w[0] + 1),
        "the old session streams on: {seqs:?}"
    );
}

#[test]
fn a_user_that_dies_before_its_grant_does_not_leak_quota() {
    let mut f = Fed::new("diedreq");
    f.broker(&[]);
    f.system("t1", &["--quota", "1"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    // A pid that surely belongs to no process any more.
    let mut gone = std::process::Command::new("true").spawn().unwrap();
    let dead_pid = gone.id();
    gone.wait().unwrap();

    let ghost = UserId("ghost".into());
    let mut ep = fake(&f.inst, Address::User(ghost.clone()));
    let hello = ToBroker::Hello {
        user: ghost.clone(),
        pid: dead_pid,
        links: vec![],
        watch_list: false,
    };
    let request = ToBroker::Request {
        user: ghost,
        req: 1,
        service: ServiceId::new("t1", "s0"),
    };
    ep.send(&Address::Broker, &encode(&hello).unwrap()).unwrap();
    ep.send(&Address::Broker, &encode(&request).unwrap())
        .unwrap();
    // The hello claims a pid that is not the writer's: refused, so the request is from an
    // unknown user and refused too. Either way no quota may leak.
    f.wait_list(10 * SEC, |l| l[0]["in_use"] == 0);
    let (code, out) = f.run(
        &["user", "request", "t1/s0", "--duration", "200ms", "--json"],
        20 * SEC,
    );
    assert_eq!(code, 0, "the quota of 1 is free again: {out}");
}

#[test]
fn control_frames_beyond_a_full_inbox_are_held_back_and_arrive_in_order() {
    let inst = format!("backlog{}", std::process::id());
    let mut broker = fake(&inst, Address::Broker);
    let mut system = fake(&inst, Address::System("t1".into()));
    // 200 session ends at once: far more than the broker's inbox holds for one writer.
    for n in 0..200u64 {
        system.send_control(
            &Address::Broker,
            &ToBroker::SessionEnded {
                system: "t1".into(),
                session: muster_shared::types::SessionId(n),
            },
        );
    }
    assert!(system.backlog() > 0, "the inbox filled up");
    let mut got = Vec::new();
    for _ in 0..10_000 {
        while let Some(f) = broker.recv() {
            got.push(muster_shared::protocol::decode::<ToBroker>(&f).unwrap());
        }
        if got.len() == 200 {
            break;
        }
        system.sweep();
    }
    let ids: Vec<u64> = got
        .iter()
        .map(|m| match m {
            ToBroker::SessionEnded { session, .. } => session.0,
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(ids, (0..200).collect::<Vec<_>>(), "all of them, in order");
    assert_eq!(system.backlog(), 0);
    assert_eq!(system.dropped_sends(), 0);
    drop(system);
    drop(broker);
    common::cleanup_dead_nodes();
}

#[test]
fn a_local_process_can_speak_only_as_itself() {
    let mut f = Fed::new("impostor");
    let b = f.broker(&[]);
    let t1 = f.system("t1", &["--services", "2", "--quota", "1"]);
    f.wait_list(10 * SEC, |l| l.len() == 2);
    // A process that is not t1 writes into the broker's inbox as t1, and as a user with
    // another process's pid.
    let mut ep = fake(&f.inst, Address::User(UserId("mallory".into())));
    // Who owns an address's inbox is who may speak as it (users and systems check the
    // broker's and systems' frames against it).
    let (b_pid, t1_pid) = (f.proc(b).pid() as u32, f.proc(t1).pid() as u32);
    assert_eq!(ep.owner_pid(&Address::Broker), Some(b_pid));
    assert_eq!(ep.owner_pid(&Address::System("t1".into())), Some(t1_pid));
    assert_eq!(ep.owner_pid(&Address::System("nobody".into())), None);
    assert_eq!(
        ep.owner_pid(&Address::User(UserId("mallory".into()))),
        Some(std::process::id())
    );
    let forged = [
        ToBroker::Withdraw {
            system: "t1".into(),
            service: "s0".into(),
        },
        ToBroker::Unregister {
            system: "t1".into(),
        },
        ToBroker::Hello {
            user: UserId("mallory".into()),
            pid: 1,
            links: vec![],
            watch_list: false,
        },
    ];
    for m in &forged {
        ep.send(&Address::Broker, &encode(m).unwrap()).unwrap();
    }
    // And it offers itself t1's only s1 session, past arbitration, as if it were the broker.
    let offer = muster_shared::protocol::ToSystem::Offer {
        ticket: 1,
        session: muster_shared::types::SessionId(1),
        user: UserId("mallory".into()),
        user_pid: std::process::id(),
        req: 1,
        service: "s1".into(),
        remote: None,
    };
    ep.send(&Address::System("t1".into()), &encode(&offer).unwrap())
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let list = f.list();
    assert_eq!(list.len(), 2, "t1 is still registered: {list:?}");
    assert!(
        list.iter().all(|s| s["withdrawn"] == false),
        "nothing withdrawn: {list:?}"
    );
    // Speaking as itself works: a hello with its own pid, then a request.
    let me = std::process::id();
    let hello = ToBroker::Hello {
        user: UserId("mallory".into()),
        pid: me,
        links: vec![],
        watch_list: false,
    };
    ep.send(&Address::Broker, &encode(&hello).unwrap()).unwrap();
    let (code, out) = f.run(
        &["user", "request", "t1/s1", "--duration", "200ms", "--json"],
        20 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    drop(ep);
    common::cleanup_dead_nodes();
}

/// The pids of processes running on instance `inst` (`--instance INST` in their command
/// line), but the cleanups a broker leaves to outlive it on purpose.
fn on_instance(inst: &str) -> Vec<i32> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(cmd) = std::fs::read(format!("/proc/{pid}/cmdline")) else {
            continue;
        };
        let args: Vec<&[u8]> = cmd.split(|&b| b == 0).collect();
        let ours = args
            .windows(2)
            .any(|w| w[0] == b"--instance" && w[1] == inst.as_bytes());
        if ours && !args.iter().any(|a| *a == b"cleanup") {
            out.push(pid);
        }
    }
    out
}

#[test]
fn a_killed_up_leaves_no_process_running() {
    // `muster up` starts a broker, its standby, the simulator, the robot systems: when
    // it is SIGKILLed, they stop too (each gets SIGTERM as its parent dies).
    let mut f = Fed::new("orphans");
    let up = f.spawn(&[
        "up",
        "--no-udp",
        "--no-web",
        "--speed",
        "2",
        "--duration",
        "120s",
    ]);
    f.wait_list(60 * SEC, |l| l.len() >= 4);
    let started = on_instance(&f.inst);
    assert!(started.len() >= 4, "{started:?}");
    f.proc(up).signal(libc::SIGKILL);
    assert!(f.proc(up).wait(5 * SEC).is_some());
    let deadline = std::time::Instant::now() + 20 * SEC;
    let mut left = on_instance(&f.inst);
    while !left.is_empty() && std::time::Instant::now() < deadline {
        std::thread::sleep(std::time::Duration::from_millis(100));
        left = on_instance(&f.inst);
    }
    let what: Vec<String> = left
        .iter()
        .map(|p| {
            let c = std::fs::read(format!("/proc/{p}/cmdline")).unwrap_or_default();
            format!("{p}: {}", String::from_utf8_lossy(&c).replace('\0', " "))
        })
        .collect();
    // (Processes of this test's own instance, left by a failure: killed before failing.)
    for pid in &left {
        // SAFETY: kill(2) on processes of this test's unique instance.
        unsafe { libc::kill(*pid, libc::SIGKILL) };
    }
    assert!(
        left.is_empty(),
        "still running after up was killed: {what:?}"
    );
    // And the instance's fence went with its last broker: nothing of it in /dev/shm.
    let fence = format!("{}{}.broker-fence", muster_shared::ipc::iox2_root(), f.inst);
    assert!(!std::path::Path::new(&fence).exists(), "{fence} left");
}
