//! The UDP path against wrong users, wrong keys, denied services and hostile datagrams.

#![allow(clippy::unwrap_used)]

mod common;

use common::{find, Fed, RemoteSetup, SEC};
use muster_shared::udp::wire::{Datagram, MIN_INITIAL};
use serde_json::Value;
use std::io::Read;
use std::net::UdpSocket;
use std::time::Duration;

fn remote(f: &Fed, r: &RemoteSetup, key: &str, args: &[&str]) -> (i32, String) {
    let mut a: Vec<&str> = args.to_vec();
    a.extend(["--remote", &r.addr, "--key", key, "--wait", "2s"]);
    f.run(&a, 30 * SEC)
}

fn ids(out: &str) -> Vec<String> {
    serde_json::from_str::<Value>(out)
        .unwrap()
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["id"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn access_matrix_users_keys_and_services() {
    let mut f = Fed::new("access");
    let r = f.remote_setup(&[("alice", &["t1/*"]), ("bob", &[])]);
    // Keys the access file does not list: an unknown user, and a second "alice" key.
    let other = r.dir.join("other");
    std::fs::create_dir_all(&other).unwrap();
    for name in ["mallory", "alice"] {
        let (code, _) = f.run(
            &["keygen", "--user", name, "--out", other.to_str().unwrap()],
            20 * SEC,
        );
        assert_eq!(code, 0);
    }
    let wrong_alice = other.join("alice.key").display().to_string();
    let mallory = other.join("mallory.key").display().to_string();
    let broker = f.remote_broker(&r);
    f.system("t1", &["--udp", "127.0.0.1:0"]);
    f.system("t2", &["--udp", "127.0.0.1:0"]);
    f.wait_list(10 * SEC, |l| l.len() == 2);

    // Known user, right key: sees and gets exactly what the patterns allow.
    let (code, out) = remote(&f, &r, &r.key("alice"), &["user", "list", "--json"]);
    assert_eq!((code, ids(&out)), (0, vec!["t1/s0".to_string()]));
    // A filtered list is sent only what the filter and the access file both let
    // through: t2 is hidden whatever the filter says.
    for (filter, want) in [
        (&["--system", "t1"][..], vec!["t1/s0".to_string()]),
        (&["--system", "t2"][..], vec![]),
        (&["--name", "s*", "--offset", "1"][..], vec![]),
        (
            &["--kind", "data", "--limit", "5"][..],
            vec!["t1/s0".to_string()],
        ),
    ] {
        let mut args = vec!["user", "list", "--json"];
        args.extend_from_slice(filter);
        let (code, out) = remote(&f, &r, &r.key("alice"), &args);
        assert_eq!((code, ids(&out)), (0, want), "{filter:?}");
    }
    let (code, out) = remote(
        &f,
        &r,
        &r.key("alice"),
        &["user", "request", "t1/s0", "--duration", "300ms", "--json"],
    );
    assert_eq!(code, 0, "{out}");
    let (code, out) = remote(
        &f,
        &r,
        &r.key("alice"),
        &["user", "request", "t2/s0", "--json"],
    );
    assert_eq!(code, 3);
    assert!(
        out.contains("\"code\":\"unknown\""),
        "a denied service looks absent: {out}"
    );
    // Known user without patterns: connects, sees nothing, gets nothing.
    let (code, out) = remote(&f, &r, &r.key("bob"), &["user", "list", "--json"]);
    assert_eq!((code, ids(&out).len()), (0, 0));
    let (code, _) = remote(
        &f,
        &r,
        &r.key("bob"),
        &["user", "request", "t1/s0", "--json"],
    );
    assert_eq!(code, 3);
    // Known name with the wrong key, and an unknown user: no list, no grant.
    for key in [&wrong_alice, &mallory] {
        for verb in [
            &["user", "list", "--json"][..],
            &["user", "request", "t1/s0", "--json"],
        ] {
            let (code, out) = remote(&f, &r, key, verb);
            assert_ne!(code, 0, "{key} {verb:?}: {out}");
            assert_ne!(code, 3, "not even a refusal: {out}");
            assert!(out.is_empty(), "{out}");
        }
    }
    // Nothing was granted to them (the system counts every session it made).
    assert_eq!(find(&f.list(), "t1/s0").unwrap()["in_use"], 0);

    // Reload without restart: mallory is added, alice removed.
    let mut access = std::fs::read_to_string(&r.access).unwrap();
    access = access
        .lines()
        .filter(|l| !l.starts_with("user alice"))
        .map(|l| format!("{l}\n"))
        .collect();
    let (_, line) = f.run(
        &[
            "keygen",
            "--user",
            "carol",
            "--out",
            r.dir.to_str().unwrap(),
            "--allow",
            "*",
        ],
        20 * SEC,
    );
    access.push_str(&line);
    std::fs::write(&r.access, access).unwrap();
    f.proc(broker).signal(libc::SIGHUP);
    std::thread::sleep(Duration::from_millis(300));
    let (code, out) = remote(&f, &r, &r.key("carol"), &["user", "list", "--json"]);
    assert_eq!((code, ids(&out).len()), (0, 2), "{out}");
    let (code, _) = remote(&f, &r, &r.key("alice"), &["user", "list", "--json"]);
    assert_ne!(code, 0, "alice was removed from the access file");
}

fn stats_of_broker(f: &mut Fed, broker: usize) -> Value {
    f.proc(broker).signal(libc::SIGTERM);
    let v = f.proc(broker).json(10 * SEC).expect("broker stats line");
    v["udp"].clone()
}

#[test]
fn hostile_datagrams_get_nothing_and_are_counted() {
    let mut f = Fed::new("hostile");
    let r = f.remote_setup(&[("alice", &["*"])]);
    let access = r.access.display().to_string();
    let broker = f.broker(&["--udp", &r.addr, "--access", &access, "--stats-json"]);
    f.system("t1", &["--udp", "127.0.0.1:0"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let s = UdpSocket::bind("127.0.0.1:0").unwrap();
    s.set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    let to: std::net::SocketAddr = r.addr.parse().unwrap();
    let mut buf = [0u8; 2048];

    // Garbage, wrong version, truncated, oversized, unpadded initial: no answer at all.
    let initial = Datagram::Initial {
        client: 1,
        token: b"",
        noise: b"",
    }
    .encode()
    .unwrap();
    let mut wrong_version = initial.clone();
    wrong_version[1] = 99;
    let bad: Vec<Vec<u8>> = vec![
        b"hello".to_vec(),
        vec![0u8; 1300],
        wrong_version,
        initial[..600].to_vec(),
        initial[..2].to_vec(),
        Datagram::HsFinal {
            conn: 7,
            noise: &[1; 64],
        }
        .encode()
        .unwrap(),
    ];
    for d in &bad {
        s.send_to(d, to).unwrap();
        assert!(
            s.recv_from(&mut buf).is_err(),
            "no answer to {} bytes",
            d.len()
        );
    }
    // A channel datagram of a connection the broker does not know draws a stateless
    // reset for it, smaller than what came (no amplification), and nothing else.
    let channel = Datagram::Channel {
        conn: 7,
        nonce: 0,
        sealed: &[1; 64],
    }
    .encode()
    .unwrap();
    s.send_to(&channel, to).unwrap();
    let (n, _) = s.recv_from(&mut buf).expect("a stateless reset");
    assert!(n < channel.len(), "{n} bytes for {}", channel.len());
    assert!(
        matches!(
            Datagram::decode(&buf[..n]),
            Ok(Datagram::Reset { conn: 7, .. })
        ),
        "{:?}",
        Datagram::decode(&buf[..n])
    );
    assert!(s.recv_from(&mut buf).is_err(), "one answer only");
    // A padded INITIAL without a token gets a stateless RETRY, at most 3x its size.
    assert_eq!(initial.len(), MIN_INITIAL);
    s.send_to(&initial, to).unwrap();
    let (n, _) = s.recv_from(&mut buf).unwrap();
    assert!(n * 3 <= initial.len(), "retry of {n} bytes");
    let reply = buf[..n].to_vec();
    let Datagram::Retry { client, token } = Datagram::decode(&reply).unwrap() else {
        panic!("expected a retry");
    };
    assert_eq!(client, 1);
    // A forged token (or one for another client id) is refused without an answer.
    let mut forged = token.to_vec();
    forged[10] ^= 1;
    for (c, t) in [(1, forged.as_slice()), (2, token)] {
        let d = Datagram::Initial {
            client: c,
            token: t,
            noise: &[0; 32],
        }
        .encode()
        .unwrap();
        s.send_to(&d, to).unwrap();
        assert!(s.recv_from(&mut buf).is_err());
    }

    let udp = stats_of_broker(&mut f, broker);
    let drops = &udp["drops"]["by_reason"];
    for reason in [
        "bad_magic",
        "oversized",
        "wrong_version",
        "unpadded_initial",
        "truncated",
        "unknown_conn",
        "unknown_handshake",
        "bad_token",
    ] {
        assert!(
            drops[reason].as_u64().unwrap_or(0) >= 1,
            "{reason} in {udp:#}"
        );
    }
    assert_eq!(udp["handshakes"], 0);
    assert!(
        udp["unvalidated_bytes_out"].as_u64().unwrap() * 3
            <= udp["unvalidated_bytes_in"].as_u64().unwrap(),
        "{udp:#}"
    );
}

#[test]
fn under_loss_duplication_reordering_and_a_flood_every_request_completes_once() {
    let f = Fed::new("rbench");
    let (code, out) = f.run(
        &[
            "bench",
            "remote",
            "--requests",
            "30",
            "--round-trips",
            "100",
            "--faults",
            "1,5,20",
            "--flood-rate",
            "3000",
            "--flood-sources",
            "50",
            "--slow",
            "300ms",
            "--handshake-flood",
            "200",
            "--json",
        ],
        300 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    let r: Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}"));
    for k in ["floor_udp_rtt", "list"] {
        assert_eq!(r[k]["count"], 100, "{k}: {r:#}");
    }
    assert_eq!(r["list_entries"], 2);
    assert_eq!(r["service_request"]["granted"], 30);
    let faults = r["faults"].as_array().unwrap();
    assert_eq!(faults.len(), 3);
    for row in faults {
        assert_eq!(row["completion"], 1.0, "{row:#}");
        assert_eq!(row["granted"], 30, "{row:#}");
    }
    // 20 % loss forces retransmissions; duplicates never became second grants.
    assert!(faults[2]["retransmissions"].as_u64().unwrap() > 0);
    assert_eq!(r["flood"]["granted"], 30, "{:#}", r["flood"]);
    assert!(r["flood"]["flood_datagrams"].as_u64().unwrap() > 0);
    // Clean, three fault levels, the flood, and ten on the slow link.
    assert_eq!(r["system_grants"], 30 * 5 + 10, "{r:#}");
    assert_eq!(r["slow"][0]["completion"], 1.0);
    let hf = &r["handshake_flood"];
    assert_eq!(hf["succeeded"], hf["logins"], "{hf:#}");
    assert_eq!(r["duplicate_grants"], 0);
    assert!(
        r["broker_udp"]["retries"].as_u64().unwrap() > 0,
        "the flood got retries"
    );
    // Only our clients got in: five, the slow one, twenty logins during the handshake
    // flood (a lossy one may have reconnected once or twice); the flood's never finish.
    let hs = r["broker_udp"]["handshakes"].as_u64().unwrap();
    assert!((26..=32).contains(&hs), "{hs} handshakes");
    assert_eq!(r["broker_udp"]["auth_failed"], 0);
}

/// User + system CPU of a process so far, in clock ticks (100 per second on Linux).
fn cpu_ticks(pid: i32) -> u64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap()
}

#[test]
fn an_idle_remote_user_sleeps() {
    let mut f = Fed::new("ridle");
    let r = f.remote_setup(&[("alice", &["*"])]);
    f.remote_broker(&r);
    f.system("t1", &["--udp", "127.0.0.1:0"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let key = r.key("alice");
    let u = f.spawn(&[
        "user",
        "--remote",
        &r.addr,
        "--key",
        &key,
        "idle",
        "--duration",
        "20s",
    ]);
    let first = f.proc(u).json(10 * SEC).unwrap();
    assert_eq!(first["connected"], true);
    let pid = f.proc(u).pid();
    let before = cpu_ticks(pid);
    std::thread::sleep(Duration::from_secs(3));
    let used = cpu_ticks(pid) - before;
    // A busy loop would use ~300 ticks; keepalives once a second use next to nothing.
    assert!(used < 30, "an idle remote user used {used} ticks in 3 s");
}

#[test]
fn a_remote_watcher_reconnects_to_a_restarted_broker() {
    let mut f = Fed::new("rwatch");
    let r = f.remote_setup(&[("alice", &["*"])]);
    let broker = f.remote_broker(&r);
    f.system("t1", &["--udp", "127.0.0.1:0"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let key = r.key("alice");
    let w = f.spawn(&[
        "user",
        "--remote",
        &r.addr,
        "--key",
        &key,
        "watch",
        "--json",
        "--duration",
        "60s",
    ]);
    let first = f.proc(w).json(10 * SEC).unwrap();
    assert_eq!(first["services"].as_array().unwrap().len(), 1);
    f.proc(broker).signal(libc::SIGKILL);
    assert!(f.proc(broker).wait(5 * SEC).is_some());
    f.remote_broker(&r);
    f.system("t2", &["--udp", "127.0.0.1:0"]);
    // The watcher notices the silence, shakes hands with the new broker, and sees t2.
    let deadline = std::time::Instant::now() + 40 * SEC;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        let v = f.proc(w).json(left).expect("a list from the new broker");
        if v["services"].as_array().unwrap().len() == 2 {
            break;
        }
    }
}

#[test]
fn slow_links_connect_list_and_request_at_300ms_and_1s_round_trips_with_loss() {
    let f = Fed::new("rslow");
    let (code, out) = f.run(
        &[
            "bench",
            "remote",
            "--requests",
            "5",
            "--round-trips",
            "20",
            "--faults",
            "1",
            "--flood-rate",
            "0",
            "--slow",
            "300ms,1s",
            "--json",
        ],
        300 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    let r: Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}"));
    let slow = r["slow"].as_array().unwrap();
    assert_eq!(slow.len(), 2);
    for (row, rtt) in slow.iter().zip([300, 1000]) {
        assert_eq!(row["rtt_ms"], rtt);
        assert_eq!(row["granted"], 5, "{row:#}");
        assert_eq!(row["completion"], 1.0, "{row:#}");
        // Connected on the first handshake: a slow answer never tore it down.
        assert_eq!(row["handshakes"], 1, "{row:#}");
        // A request takes at least the added round trip.
        assert!(
            row["latency"]["p50_us"].as_u64().unwrap() >= rtt * 1000,
            "{row:#}"
        );
    }
    assert_eq!(r["duplicate_grants"], 0);
}

#[test]
fn the_extra_descriptor_seen_during_a_remote_list_is_still_reported_by_wait() {
    // A view watches its keys' descriptor through `watch_extra`. Readiness is
    // edge-triggered: a key that came while a remote `list()` was turning the reactor
    // must still wake the view's next `wait` (it once waited for the next key: `q` did
    // not quit the remote user view).
    use muster_users::{ConnectOptions, RemoteOptions, UserClient, Wake};
    use std::io::Write;
    use std::os::fd::AsRawFd;
    let mut f = Fed::new("rextra");
    let r = f.remote_setup(&[("alice", &["*"])]);
    f.remote_broker(&r);
    f.system("t1", &["--udp", "127.0.0.1:0"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let (name, key) =
        muster_shared::udp::crypto::KeyPair::read(std::path::Path::new(&r.key("alice"))).unwrap();
    let opts = ConnectOptions {
        handle_signals: false,
        ..ConnectOptions::default()
    };
    let remote = RemoteOptions {
        broker: r.addr.parse().unwrap(),
        name,
        key,
        broker_key: None,
        faults: None,
    };
    let mut c = UserClient::connect_remote(remote, &opts).unwrap();
    let (rx, mut tx) = std::os::unix::net::UnixStream::pair().unwrap();
    rx.set_nonblocking(true).unwrap();
    c.watch_extra(rx.as_raw_fd()).unwrap();
    for _ in 0..3 {
        tx.write_all(&[1]).unwrap();
        // A list over UDP turns the reactor until the chunks came: it sees the byte.
        assert_eq!(c.list().unwrap().views().len(), 1);
        let deadline = std::time::Instant::now() + Duration::from_millis(500);
        let woke = loop {
            match c.wait(deadline).unwrap() {
                Wake::Event(_) => continue,
                w => break w,
            }
        };
        assert!(
            matches!(woke, Wake::Extra),
            "the key's wake-up was lost: {woke:?}"
        );
        let mut buf = [0u8; 8];
        while (&rx).read(&mut buf).is_ok_and(|n| n > 0) {}
    }
    c.close();
}
