//! `muster bench remote`: the UDP path measured against its floor, under seeded loss,
//! duplication and reordering, and under a flood of hostile datagrams.
//!
//! One run starts a broker with a UDP front and two synthetic systems with UDP
//! endpoints (child processes), then from this process: the raw UDP loopback round trip
//! (an echo thread: the floor), remote list and service-request round trips (request →
//! grant, then the session is ended), their ratio to the floor; then the same requests
//! through a seeded lossy link at each fault level; then, optionally, again while other
//! threads flood the broker from many loopback source addresses. The benchmark's broker
//! lifts the per-user datagram rate limit (it sends requests back to back, far faster
//! than a person); the flood row keeps every other limit.

use super::{row, summary};
use crate::cli::RemoteBenchArgs;
use crate::cmd::children::Children;
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::types::ServiceId;
use muster_shared::udp::access::access_line;
use muster_shared::udp::crypto::KeyPair;
use muster_shared::udp::wire::Datagram;
use muster_shared::Instance;
use muster_users::{ConnectOptions, Faults, RemoteOptions, UserClient, UserEvent};
use serde_json::{json, Value};
use std::io::Read;
use std::net::{SocketAddr, UdpSocket};
use std::process::{ExitCode, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub(super) fn hist() -> Histogram<u64> {
    Histogram::new(3).expect("3 significant figures is a valid precision")
}

pub(super) fn us(d: Duration) -> u64 {
    (d.as_nanos() as u64).div_ceil(1000).max(1)
}

/// What one batch of requests did.
pub(super) struct Batch {
    pub(super) latency: Histogram<u64>,
    pub(super) granted: u64,
    pub(super) refused: u64,
    pub(super) abandoned: u64,
    /// Refusals by reason code.
    pub(super) refusals: std::collections::BTreeMap<&'static str, u64>,
    retransmissions: u64,
    duplicate_grants_heard: u64,
    /// Grants of requests no longer waited for (an earlier, abandoned one): their
    /// sessions were ended at once rather than left open.
    pub(super) stray_grants: u64,
}

fn client(broker: SocketAddr, key: &KeyPair, faults: Option<Faults>) -> anyhow::Result<UserClient> {
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(20),
        handle_signals: false,
        watch_list: false,
    };
    let remote = RemoteOptions {
        broker,
        name: "bench".into(),
        key: key.clone(),
        broker_key: None,
        faults,
    };
    Ok(UserClient::connect_remote(remote, &opts)?)
}

/// `n` requests of `service`, one at a time: time to grant (or refusal), then the
/// session is ended. A request not answered in `deadline` is abandoned (cancelled).
pub(super) fn requests(
    c: &mut UserClient,
    service: &ServiceId,
    n: usize,
    deadline: Duration,
) -> anyhow::Result<Batch> {
    let mut b = Batch {
        latency: hist(),
        granted: 0,
        refused: 0,
        abandoned: 0,
        refusals: std::collections::BTreeMap::new(),
        retransmissions: 0,
        duplicate_grants_heard: 0,
        stray_grants: 0,
    };
    for _ in 0..n {
        let t = Instant::now();
        let req = c.request(service)?;
        let until = t + deadline;
        loop {
            match c.next_event(until)? {
                Some(UserEvent::Granted {
                    req: r, session, ..
                }) if r == req => {
                    let _ = b.latency.record(us(t.elapsed()));
                    b.granted += 1;
                    c.end(session);
                    break;
                }
                Some(UserEvent::Refused { req: r, reason, .. }) if r == req => {
                    let _ = b.latency.record(us(t.elapsed()));
                    b.refused += 1;
                    *b.refusals.entry(reason.code()).or_default() += 1;
                    break;
                }
                // Granted after it was given up: not left open to hold the quota.
                Some(UserEvent::Granted { session, .. }) => {
                    b.stray_grants += 1;
                    c.end(session);
                }
                Some(_) => {}
                None => {
                    b.abandoned += 1;
                    c.cancel(req);
                    break;
                }
            }
        }
    }
    if let Some(s) = c.link_stats() {
        b.retransmissions = s.retransmissions;
        b.duplicate_grants_heard = s.duplicate_grants;
    }
    Ok(b)
}

/// `n` list requests; with a probe, each is paired with a raw UDP round trip (the floor
/// measured interleaved, under the same conditions).
fn lists(
    c: &mut UserClient,
    n: usize,
    mut floor: Option<(&mut UdpProbe, &mut Histogram<u64>)>,
) -> anyhow::Result<(Histogram<u64>, u64)> {
    let mut h = hist();
    let mut entries = 0;
    for _ in 0..n {
        if let Some((p, fh)) = floor.as_mut() {
            if let Some(d) = p.round_trip()? {
                let _ = fh.record(us(d));
            }
        }
        let t = Instant::now();
        let l = c.list()?;
        let _ = h.record(us(t.elapsed()));
        entries = l.count() as u64;
    }
    Ok((h, entries))
}

/// `muster bench udp-echo`: echoes datagrams on a loopback port (printed first), waking
/// through epoll like every muster process; the other end of the UDP floor.
pub fn echo() -> anyhow::Result<ExitCode> {
    use muster_shared::reactor::{Reactor, SignalPipe};
    use std::os::fd::AsRawFd;
    let s = UdpSocket::bind("127.0.0.1:0")?;
    s.set_nonblocking(true)?;
    println!("{}", s.local_addr()?.port());
    let mut signals = SignalPipe::install()?;
    let mut reactor = Reactor::new()?;
    reactor.add(s.as_raw_fd(), 0)?;
    reactor.add(signals.raw(), 1)?;
    let mut buf = [0u8; 1500];
    loop {
        let tokens = reactor.wait(None)?;
        if tokens.contains(&1) && signals.drain() {
            return Ok(ExitCode::SUCCESS);
        }
        while let Ok((n, from)) = s.recv_from(&mut buf) {
            let _ = s.send_to(&buf[..n], from);
        }
    }
}

/// One raw UDP round trip to the echo process, waiting in epoll as a user does.
pub struct UdpProbe {
    sock: UdpSocket,
    to: SocketAddr,
    reactor: muster_shared::reactor::Reactor,
}

impl UdpProbe {
    /// A probe bouncing off an echo process at `to`.
    pub fn new(to: SocketAddr) -> anyhow::Result<Self> {
        use std::os::fd::AsRawFd;
        let sock = UdpSocket::bind("127.0.0.1:0")?;
        sock.set_nonblocking(true)?;
        let reactor = muster_shared::reactor::Reactor::new()?;
        reactor.add(sock.as_raw_fd(), 0)?;
        Ok(UdpProbe { sock, to, reactor })
    }

    /// Starts the echo process (one of `kids`) and a probe aimed at it.
    pub fn start(inst: &Instance, kids: &mut Children) -> anyhow::Result<Self> {
        use std::io::BufRead;
        let echo = kids.spawn(inst, "udp-echo", &["bench", "udp-echo"], Stdio::piped())?;
        let out = echo.stdout.take().context("echo stdout")?;
        let mut line = String::new();
        std::io::BufReader::new(out).read_line(&mut line)?;
        let port: u16 = line.trim().parse().context("echo port")?;
        Self::new(SocketAddr::from(([127, 0, 0, 1], port)))
    }

    /// One round trip; `None` if no answer within a second.
    pub fn round_trip(&mut self) -> anyhow::Result<Option<Duration>> {
        let mut buf = [0u8; 1500];
        let t = Instant::now();
        self.sock.send_to(&[7u8; 64], self.to)?;
        while t.elapsed() < Duration::from_secs(1) {
            if self.sock.recv_from(&mut buf).is_ok() {
                return Ok(Some(t.elapsed()));
            }
            self.reactor.wait(Some(Duration::from_millis(100)))?;
        }
        Ok(None)
    }
}

/// Flood threads: from `sources` loopback addresses (127.0.0.2, .3, ...), a mix of
/// garbage, unpadded and token-less initials, forged tokens and channel datagrams with
/// made-up connection ids, at about `rate` datagrams a second in all.
/// One address does the address-validation round trip honestly and then sends Noise
/// message 1 for a fresh handshake id, `rate` times a second: every one costs the broker
/// a Diffie-Hellman and a pending slot.
fn handshake_flood(
    to: SocketAddr,
    rate: u64,
    stop: Arc<AtomicBool>,
    sent: Arc<AtomicU64>,
) -> anyhow::Result<std::thread::JoinHandle<()>> {
    let sock = UdpSocket::bind("127.0.0.250:0")?;
    sock.set_nonblocking(true)?;
    let key = KeyPair::generate()?;
    let mut hs = muster_shared::udp::crypto::initiator(&key)?;
    let mut m1 = [0u8; 128];
    let n = hs.write_message(&[], &mut m1)?;
    let msg1 = m1[..n].to_vec();
    Ok(std::thread::spawn(move || {
        let gap = Duration::from_secs_f64(1.0 / rate.max(1) as f64);
        let mut next = Instant::now();
        let mut client: u64 = 1 << 50;
        let mut buf = [0u8; 2048];
        while !stop.load(Ordering::Relaxed) {
            client += 1;
            let init = Datagram::Initial {
                client,
                token: b"",
                noise: b"",
            }
            .encode()
            .unwrap_or_default();
            let _ = sock.send_to(&init, to);
            while let Ok((len, _)) = sock.recv_from(&mut buf) {
                if let Ok(Datagram::Retry { client, token }) = Datagram::decode(&buf[..len]) {
                    let i = Datagram::Initial {
                        client,
                        token,
                        noise: &msg1,
                    }
                    .encode()
                    .unwrap_or_default();
                    if sock.send_to(&i, to).is_ok() {
                        sent.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            next += gap;
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
        }
    }))
}

fn flood(
    to: SocketAddr,
    sources: usize,
    rate: u64,
    stop: Arc<AtomicBool>,
    sent: Arc<AtomicU64>,
) -> Vec<std::thread::JoinHandle<()>> {
    let threads = 2.min(sources.max(1));
    (0..threads)
        .map(|t| {
            let stop = stop.clone();
            let sent = sent.clone();
            std::thread::spawn(move || {
                let socks: Vec<UdpSocket> = (0..sources)
                    .filter(|i| i % threads == t)
                    .filter_map(|i| {
                        let ip = format!("127.0.{}.{}", 1 + i / 250, 2 + i % 250);
                        UdpSocket::bind(format!("{ip}:0")).ok()
                    })
                    .collect();
                if socks.is_empty() {
                    return;
                }
                let initial = Datagram::Initial {
                    client: 1,
                    token: b"",
                    noise: b"",
                }
                .encode()
                .unwrap_or_default();
                let forged = Datagram::Initial {
                    client: 2,
                    token: &[9; 24],
                    noise: &[1; 32],
                }
                .encode()
                .unwrap_or_default();
                let per_thread = (rate / threads as u64).max(1);
                let gap = Duration::from_secs_f64(1.0 / per_thread as f64);
                let mut next = Instant::now();
                let mut i: u64 = 0;
                while !stop.load(Ordering::Relaxed) {
                    let s = &socks[(i as usize) % socks.len()];
                    let conn = i.wrapping_mul(0x9e37_79b9_7f4a_7c15);
                    let channel = Datagram::Channel {
                        conn,
                        nonce: i,
                        sealed: &[3; 48],
                    }
                    .encode()
                    .unwrap_or_default();
                    let d: &[u8] = match i % 5 {
                        0 => b"garbage that is no muster datagram",
                        1 => &initial,
                        2 => &initial[..300],
                        3 => &forged,
                        _ => &channel,
                    };
                    let _ = s.send_to(d, to);
                    sent.fetch_add(1, Ordering::Relaxed);
                    i += 1;
                    next += gap;
                    let now = Instant::now();
                    if next > now {
                        std::thread::sleep(next - now);
                    } else if now - next > Duration::from_millis(100) {
                        next = now; // fell behind: do not burst to catch up
                    }
                }
            })
        })
        .collect()
}

pub(super) fn batch_json(b: &Batch, n: usize) -> Value {
    json!({
        "requests": n,
        "granted": b.granted,
        "refused": b.refused,
        "abandoned": b.abandoned,
        "refusals": b.refusals,
        "completion": (b.granted + b.refused) as f64 / n.max(1) as f64,
        "retransmissions": b.retransmissions,
        "duplicate_grants_heard": b.duplicate_grants_heard,
        "stray_grants": b.stray_grants,
        "latency": summary(&b.latency),
    })
}

pub fn run(inst: &Instance, a: RemoteBenchArgs) -> anyhow::Result<ExitCode> {
    if a.requests == 0 || a.round_trips == 0 {
        bail!("--requests and --round-trips must be at least 1");
    }
    let dir = std::env::temp_dir().join(format!("muster-bench-remote-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let key = KeyPair::generate()?;
    let access = dir.join("access");
    std::fs::write(
        &access,
        access_line("bench", &key.public, &["*".to_string()], false) + "\n",
    )?;
    let port = UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port();
    let broker_addr: SocketAddr = format!("127.0.0.1:{port}").parse()?;
    let mut kids = Children::default();
    let bstr = broker_addr.to_string();
    let astr = access.display().to_string();
    let mut broker_out = kids
        .spawn(
            inst,
            "broker",
            &[
                "broker",
                "--udp",
                &bstr,
                "--access",
                &astr,
                "--stats-json",
                "--udp-conn-rate",
                "1000000",
            ],
            Stdio::piped(),
        )?
        .stdout
        .take()
        .context("broker stdout")?;
    let mut sys_out = Vec::new();
    for (name, kind) in [("t1", "data"), ("d1", "command")] {
        let out = kids
            .spawn(
                inst,
                name,
                &[
                    "system",
                    "synthetic",
                    "--name",
                    name,
                    "--kind",
                    kind,
                    "--quota",
                    "1000",
                    "--udp",
                    "127.0.0.1:0",
                    "--stats-json",
                ],
                Stdio::piped(),
            )?
            .stdout
            .take()
            .context("system stdout")?;
        sys_out.push(out);
    }
    super::children::connect_when_listed(inst, 2, Duration::from_secs(30))?.close();

    let service = ServiceId("t1/s0".into());
    let mut probe = UdpProbe::start(inst, &mut kids)?;
    let mut floor = hist();
    let mut c = client(broker_addr, &key, None)?;
    let (list, entries) = lists(&mut c, a.round_trips, Some((&mut probe, &mut floor)))?;
    let clean = requests(&mut c, &service, a.requests, Duration::from_secs(10))?;
    c.close();
    let floor_p50 = floor.value_at_quantile(0.5).max(1) as f64;
    let mut out = json!({
        "floor_udp_rtt": summary(&floor),
        "list": summary(&list),
        "list_entries": entries,
        "service_request": batch_json(&clean, a.requests),
        "ratio_list_p50": list.value_at_quantile(0.5) as f64 / floor_p50,
        "ratio_request_p50": clean.latency.value_at_quantile(0.5) as f64 / floor_p50,
    });

    let mut faults = Vec::new();
    let mut user_grants = clean.granted;
    let mut abandoned = clean.abandoned;
    for (i, p) in a.faults.iter().enumerate() {
        let f = Faults {
            rtt: Duration::ZERO,
            loss: p / 100.0,
            dup: p / 100.0,
            reorder: p / 100.0,
            seed: 1000 + i as u64,
        };
        let mut c = client(broker_addr, &key, Some(f))?;
        let (lh, _) = lists(&mut c, 20, None)?;
        let b = requests(&mut c, &service, a.requests, Duration::from_secs(10))?;
        user_grants += b.granted;
        abandoned += b.abandoned;
        let mut j = batch_json(&b, a.requests);
        j["percent"] = json!(p);
        j["list"] = summary(&lh);
        faults.push(j);
        c.close();
    }
    out["faults"] = json!(faults);

    // Slow links: connect, list and request over an added round trip with 5 % loss.
    let mut slow = Vec::new();
    for (i, rtt) in a.slow.iter().enumerate() {
        let rtt: Duration = (*rtt).into();
        let f = Faults {
            rtt,
            loss: 0.05,
            seed: 2000 + i as u64,
            ..Faults::default()
        };
        let t = Instant::now();
        let mut c = client(broker_addr, &key, Some(f))?;
        let connect_ms = t.elapsed().as_secs_f64() * 1e3;
        let (lh, _) = lists(&mut c, 5, None)?;
        let n = a.requests.min(10);
        let b = requests(&mut c, &service, n, Duration::from_secs(30))?;
        user_grants += b.granted;
        abandoned += b.abandoned;
        let mut j = batch_json(&b, n);
        j["rtt_ms"] = json!(rtt.as_millis() as u64);
        j["loss"] = json!(0.05);
        j["connect_ms"] = json!(connect_ms);
        j["list"] = summary(&lh);
        j["handshakes"] = json!(c.link_stats().map_or(0, |s| s.handshakes));
        slow.push(j);
        c.close();
    }
    out["slow"] = json!(slow);

    // Real users log in while one address floods the broker with handshakes.
    if a.handshake_flood > 0 {
        let stop = Arc::new(AtomicBool::new(false));
        let sent = Arc::new(AtomicU64::new(0));
        let t = Instant::now();
        let th = handshake_flood(broker_addr, a.handshake_flood, stop.clone(), sent.clone())?;
        std::thread::sleep(Duration::from_secs(3)); // the pending table fills
        let mut logins = hist();
        let users = 20;
        let mut ok = 0;
        for _ in 0..users {
            let t0 = Instant::now();
            let opts = ConnectOptions {
                wait_for_broker: Duration::from_secs(5),
                handle_signals: false,
                watch_list: false,
            };
            let remote = RemoteOptions {
                broker: broker_addr,
                name: "bench".into(),
                key: key.clone(),
                broker_key: None,
                faults: None,
            };
            if let Ok(c) = UserClient::connect_remote(remote, &opts) {
                ok += 1;
                let _ = logins.record(t0.elapsed().as_micros() as u64);
                c.close();
            }
        }
        stop.store(true, Ordering::Relaxed);
        let _ = th.join();
        let secs = t.elapsed().as_secs_f64();
        out["handshake_flood"] = json!({
            "rate": a.handshake_flood,
            "rate_measured": sent.load(Ordering::Relaxed) as f64 / secs,
            "logins": users,
            "succeeded": ok,
            "success": ok as f64 / users as f64,
            "login": summary(&logins),
        });
    }

    if a.flood_rate > 0 {
        let stop = Arc::new(AtomicBool::new(false));
        let sent = Arc::new(AtomicU64::new(0));
        let t = Instant::now();
        let th = flood(
            broker_addr,
            a.flood_sources,
            a.flood_rate,
            stop.clone(),
            sent.clone(),
        );
        std::thread::sleep(Duration::from_millis(300));
        let mut c = client(broker_addr, &key, None)?;
        let (lh, _) = lists(&mut c, 100, None)?;
        let b = requests(&mut c, &service, a.requests, Duration::from_secs(10))?;
        user_grants += b.granted;
        abandoned += b.abandoned;
        c.close();
        stop.store(true, Ordering::Relaxed);
        for h in th {
            let _ = h.join();
        }
        let secs = t.elapsed().as_secs_f64();
        let mut j = batch_json(&b, a.requests);
        j["list"] = summary(&lh);
        j["flood_sources"] = json!(a.flood_sources);
        j["flood_datagrams"] = json!(sent.load(Ordering::Relaxed));
        j["flood_rate_measured"] = json!(sent.load(Ordering::Relaxed) as f64 / secs);
        out["flood"] = j;
    }

    // Stop the children and read their counters.
    std::thread::sleep(Duration::from_millis(600)); // let the last ends reach the systems
    kids.stop();
    let mut text = String::new();
    broker_out.read_to_string(&mut text)?;
    out["broker_udp"] = serde_json::from_str::<Value>(text.trim())
        .map(|v| v["udp"].clone())
        .unwrap_or(Value::Null);
    let mut system_grants = 0;
    for mut s in sys_out {
        let mut text = String::new();
        s.read_to_string(&mut text)?;
        if let Ok(v) = serde_json::from_str::<Value>(text.trim()) {
            if let Some(m) = v["services"].as_object() {
                system_grants += m.values().filter_map(|r| r["grants"].as_u64()).sum::<u64>();
            }
        }
    }
    out["system_grants"] = json!(system_grants);
    out["user_grants"] = json!(user_grants);
    out["abandoned"] = json!(abandoned);
    // Every session a system made was heard by exactly one request of ours; with no
    // abandoned request, any surplus would be a duplicate grant.
    out["duplicate_grants"] = json!(system_grants.saturating_sub(user_grants + abandoned));
    let _ = std::fs::remove_dir_all(&dir);

    if a.json {
        println!("{out}");
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "remote path on loopback (2 systems, {} requests per row)",
        a.requests
    );
    println!(
        "{:<28} {:>7} {:>10} {:>10} {:>10} {:>10}",
        "", "count", "p50 µs", "p90 µs", "p99 µs", "max µs"
    );
    println!("{}", row("raw UDP round trip (floor)", &floor));
    println!("{}", row("remote list", &list));
    println!("{}", row("remote service request", &clean.latency));
    println!(
        "ratio to floor (p50): list {:.1}, service request {:.1}",
        out["ratio_list_p50"].as_f64().unwrap_or(0.0),
        out["ratio_request_p50"].as_f64().unwrap_or(0.0)
    );
    for f in out["faults"].as_array().into_iter().flatten() {
        println!(
            "{:>4}% loss+dup+reorder: completion {:.3}, p50 {} µs, p99 {} µs, {} retransmissions",
            f["percent"],
            f["completion"].as_f64().unwrap_or(0.0),
            f["latency"]["p50_us"],
            f["latency"]["p99_us"],
            f["retransmissions"]
        );
    }
    for s in out["slow"].as_array().into_iter().flatten() {
        println!(
            "+{} ms RTT, 5% loss: connect {:.0} ms, list p50 {} µs, request p50 {} µs, p99 {} µs, completion {:.3}, handshakes {}",
            s["rtt_ms"],
            s["connect_ms"].as_f64().unwrap_or(0.0),
            s["list"]["p50_us"],
            s["latency"]["p50_us"],
            s["latency"]["p99_us"],
            s["completion"].as_f64().unwrap_or(0.0),
            s["handshakes"]
        );
    }
    if let Some(f) = out.get("handshake_flood") {
        println!(
            "handshake flood {:.0}/s from one address: {} of {} logins within 5 s, login p50 {} µs, p99 {} µs",
            f["rate_measured"].as_f64().unwrap_or(0.0),
            f["succeeded"],
            f["logins"],
            f["login"]["p50_us"],
            f["login"]["p99_us"]
        );
    }
    if let Some(f) = out.get("flood") {
        println!(
            "flood {:.0} datagrams/s from {} sources: completion {:.3}, request p50 {} µs, p99 {} µs, list p99 {} µs",
            f["flood_rate_measured"].as_f64().unwrap_or(0.0),
            f["flood_sources"],
            f["completion"].as_f64().unwrap_or(0.0),
            f["latency"]["p50_us"],
            f["latency"]["p99_us"],
            f["list"]["p99_us"]
        );
    }
    println!(
        "duplicate grants: {} (systems made {} sessions, users were granted {}, abandoned {})",
        out["duplicate_grants"], system_grants, user_grants, abandoned
    );
    Ok(ExitCode::SUCCESS)
}
