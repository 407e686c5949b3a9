//! `muster bench federation`: three hosts federated over Zenoh, on loopback.
//!
//! One run starts three instances (`<inst>-a`, `-b`, `-c`), each with a federated broker
//! (child processes, Zenoh over loopback TCP), a data system `t1` and a command system
//! `d1` on b and a data system `t2` on c. From this process it then measures:
//! - the floor: the raw Zenoh round trip between this process and an echo process
//!   (put → subscriber → put back → subscriber), peers over loopback TCP like the
//!   brokers;
//! - service requests from a user on a to `t1@b/s0` (request → grant, then end), their
//!   ratio to the floor, beside the same request made locally on b;
//! - list propagation: a session begun or ended by a user on b until a user on a sees
//!   the change in its shared-memory list;
//! - session update latency (system send → user receive, one clock for the host) for a
//!   user on a holding `t1@b/s0`, beside a user on b holding `t1/s0`;
//! - host loss: b's broker SIGKILLed (then restarted) and SIGSTOPped (then continued),
//!   until b's services leave a's list and until they are back, with `--lease`;
//! - the same rows again with `--users` processes per host each holding a 10 Hz
//!   session on another host (with `--local-fan-out`, b's hold t1's on their own host,
//!   so that the local update row shares its ticks with as many subscribers of one host
//!   as the cross-host row does).

use super::remote::{batch_json, hist, requests, us, Batch};
use super::{row, summary};
use crate::cli::FederationBenchArgs;
use crate::cmd::children::{
    connect_when_listed, free_tcp_port as free_port, Children, LoopbackHosts,
};
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::types::ServiceId;
use muster_shared::Instance;
use muster_users::{UserClient, UserEvent};
use serde_json::{json, Value};
use std::collections::HashSet;
use std::process::{ExitCode, Stdio};
use std::time::{Duration, Instant};
use zenoh::Wait;

const HOSTS: [&str; 3] = ["a", "b", "c"];

fn zenoh_config(port: u16, listen: bool) -> anyhow::Result<zenoh::Config> {
    let z = |e: zenoh::Error| anyhow::anyhow!("{e}");
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").map_err(z)?;
    c.insert_json5("scouting/multicast/enabled", "false")
        .map_err(z)?;
    let ep = format!("[\"tcp/127.0.0.1:{port}\"]");
    let key = if listen {
        "listen/endpoints"
    } else {
        "connect/endpoints"
    };
    c.insert_json5(key, &ep).map_err(z)?;
    Ok(c)
}

/// `muster bench zenoh-echo PORT`: a Zenoh peer listening on PORT that puts back on
/// `muster-bench/pong` whatever arrives on `muster-bench/ping`, until SIGTERM; the
/// other end of the Zenoh floor (a process of its own, as a broker is).
pub fn echo(port: u16) -> anyhow::Result<ExitCode> {
    let z = |e: zenoh::Error| anyhow::anyhow!("{e}");
    let session = zenoh::open(zenoh_config(port, true)?).wait().map_err(z)?;
    let back = session
        .declare_publisher("muster-bench/pong")
        .wait()
        .map_err(z)?;
    let _sub = session
        .declare_subscriber("muster-bench/ping")
        .callback(move |s| {
            let _ = back.put(s.payload().clone()).wait();
        })
        .wait()
        .map_err(z)?;
    let mut signals = muster_shared::reactor::SignalPipe::install()?;
    let mut reactor = muster_shared::reactor::Reactor::new()?;
    reactor.add(signals.raw(), 0)?;
    loop {
        if !reactor.wait(None)?.is_empty() && signals.drain() {
            return Ok(ExitCode::SUCCESS);
        }
    }
}

/// Raw Zenoh round trips between this process and an echo process (`bench
/// zenoh-echo`), peers over loopback TCP as the brokers are: put → the echo's
/// subscriber → put back → ours.
struct ZenohProbe {
    ping: zenoh::pubsub::Publisher<'static>,
    rx: std::sync::mpsc::Receiver<()>,
    _sub: zenoh::pubsub::Subscriber<()>,
    _session: zenoh::Session,
}

impl ZenohProbe {
    /// Starts the echo process (one of `kids`) and a probe connected to it.
    fn start(kids: &mut Children, inst: &Instance) -> anyhow::Result<Self> {
        let port = free_port()?;
        let p = port.to_string();
        kids.spawn(
            inst,
            "zenoh-echo",
            &["bench", "zenoh-echo", &p],
            Stdio::null(),
        )?;
        let z = |e: zenoh::Error| anyhow::anyhow!("{e}");
        let until = Instant::now() + Duration::from_secs(10);
        let session = loop {
            match zenoh::open(zenoh_config(port, false)?).wait() {
                Ok(s) => break s,
                Err(e) if Instant::now() > until => bail!("cannot reach the Zenoh echo: {e}"),
                Err(_) => std::thread::sleep(Duration::from_millis(50)),
            }
        };
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let sub = session
            .declare_subscriber("muster-bench/pong")
            .callback(move |_| {
                let _ = tx.send(());
            })
            .wait()
            .map_err(z)?;
        let ping = session
            .declare_publisher("muster-bench/ping")
            .wait()
            .map_err(z)?;
        // Until the two have found each other.
        loop {
            ping.put(vec![0u8; 64]).wait().map_err(z)?;
            if rx.recv_timeout(Duration::from_millis(50)).is_ok() {
                break;
            }
            if Instant::now() > until {
                bail!("the Zenoh echo did not answer within 10 s");
            }
        }
        std::thread::sleep(Duration::from_millis(100));
        while rx.try_recv().is_ok() {}
        Ok(ZenohProbe {
            ping,
            rx,
            _sub: sub,
            _session: session,
        })
    }

    /// One round trip; `None` if no answer within a second.
    fn round_trip(&mut self) -> anyhow::Result<Option<Duration>> {
        let t = Instant::now();
        self.ping
            .put(vec![0u8; 64])
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(self
            .rx
            .recv_timeout(Duration::from_secs(1))
            .ok()
            .map(|()| t.elapsed()))
    }

    /// `n` round trips.
    fn floor(&mut self, n: usize) -> anyhow::Result<Histogram<u64>> {
        let mut h = hist();
        for _ in 0..n {
            if let Some(d) = self.round_trip()? {
                let _ = h.record(us(d));
            }
        }
        Ok(h)
    }
}

/// `n` cross-host requests, each after one raw Zenoh round trip (the floor, measured
/// interleaved, under the same conditions).
fn interleaved(
    c: &mut UserClient,
    service: &ServiceId,
    n: usize,
    probe: &mut ZenohProbe,
) -> anyhow::Result<(Batch, Histogram<u64>)> {
    let mut floor = hist();
    let mut all: Option<Batch> = None;
    for _ in 0..n {
        if let Some(d) = probe.round_trip()? {
            let _ = floor.record(us(d));
        }
        let b = requests(c, service, 1, Duration::from_secs(10))?;
        match all.as_mut() {
            None => all = Some(b),
            Some(a) => {
                let _ = a.latency.add(&b.latency);
                a.granted += b.granted;
                a.refused += b.refused;
                a.abandoned += b.abandoned;
                a.stray_grants += b.stray_grants;
                for (k, v) in b.refusals {
                    *a.refusals.entry(k).or_default() += v;
                }
            }
        }
    }
    let all = all.context("at least one request")?;
    Ok((all, floor))
}

/// A change of b's list (a local session begun or ended on b) until a sees it.
fn list_propagation(
    on_a: &mut UserClient,
    on_b: &mut UserClient,
    n: usize,
) -> anyhow::Result<Histogram<u64>> {
    // s1: no user of the loaded rows holds it.
    let far = ServiceId("t1@b/s1".into());
    let here = ServiceId("t1/s1".into());
    let in_use = |c: &mut UserClient| -> anyhow::Result<u16> {
        Ok(c.list()?.find(&far).map_or(u16::MAX, |e| e.in_use))
    };
    let mut h = hist();
    // The sessions of the rows before have all ended first. b's user is driven
    // meanwhile: its last ends may be held back for `t1`'s full inbox (`t1` busy with
    // the loaded rows' ticks), and go only when it next turns (they stayed held, and
    // counted in use, while only a's user was polled here).
    let mut settle = hist();
    wait_for(
        on_a,
        |c| {
            while !matches!(on_b.poll()?, muster_users::Wake::Timeout) {}
            Ok(in_use(c)? == 0)
        },
        Instant::now(),
        &mut settle,
    )
    .with_context(|| {
        format!(
            "{far} still in use ({:?} in a's list, {:?} in b's) after the request rows",
            in_use(on_a).ok(),
            on_b.list()
                .ok()
                .and_then(|l| l.find(&here).map(|e| e.in_use))
        )
    })?;
    let base = 0;
    for _ in 0..n {
        let t = Instant::now();
        let req = on_b.request(&here)?;
        let session = loop {
            match on_b.next_event(t + Duration::from_secs(10))? {
                Some(UserEvent::Granted {
                    req: r, session, ..
                }) if r == req => break session,
                Some(_) => {}
                None => bail!("no grant on b within 10 s"),
            }
        };
        // a's list shows it (in use counts the request from the moment it is offered).
        wait_for(on_a, |c| Ok(in_use(c)? > base), t, &mut h).context("a session begun on b")?;
        let t = Instant::now();
        on_b.end(session);
        wait_for(on_a, |c| Ok(in_use(c)? == base), t, &mut h).context("a session ended on b")?;
    }
    Ok(h)
}

fn wait_for(
    c: &mut UserClient,
    mut done: impl FnMut(&mut UserClient) -> anyhow::Result<bool>,
    since: Instant,
    h: &mut Histogram<u64>,
) -> anyhow::Result<()> {
    let until = since + Duration::from_secs(10);
    while !done(c)? {
        if Instant::now() > until {
            bail!("a's list did not change within 10 s");
        }
        // The list is read in place from shared memory; watchers are rung at most
        // every 100 ms, so this polls it (every 100 µs) rather than wait for the bell.
        std::thread::sleep(Duration::from_micros(100));
    }
    let _ = h.record(us(since.elapsed()));
    Ok(())
}

/// Sessions each update row holds at once. Under load a session's update latency is
/// mostly its turn in its system's fan-out: the system writes a tick's update to each of
/// its 900 sessions in the order of their numbers, which are hashes, so one session's
/// turn is a random place in the tick, kept while it lasts (a trace of every frame
/// showed one local session at 14 ms p50 beside a median of 0.4 ms after its system's
/// write). One session a row made the cross-host / local ratio a draw (0.7–11× between
/// runs); pooled over this many, the rows compare like with like.
const UPDATE_SESSIONS: usize = 16;

/// Update latency (system send → this user's receive) over [`UPDATE_SESSIONS`]
/// sessions on `service` held at once for `d`, and their gaps.
fn updates(
    c: &mut UserClient,
    service: &ServiceId,
    d: Duration,
) -> anyhow::Result<(Histogram<u64>, u64)> {
    let reqs = (0..UPDATE_SESSIONS)
        .map(|_| c.request(service))
        .collect::<Result<HashSet<u64>, _>>()?;
    let mut sessions = HashSet::new();
    let t = Instant::now();
    while sessions.len() < UPDATE_SESSIONS {
        match c.next_event(t + Duration::from_secs(10))? {
            Some(UserEvent::Granted { req, session, .. }) if reqs.contains(&req) => {
                sessions.insert(session);
            }
            Some(UserEvent::Refused { reason, .. }) => bail!("{service} refused: {reason}"),
            Some(_) => {}
            None => bail!(
                "{} of {UPDATE_SESSIONS} sessions of {service} granted within 10 s",
                sessions.len()
            ),
        }
    }
    let mut h = hist();
    let mut gaps = 0;
    tracing::info!("bench: updates of {service} for {d:?}");
    let until = Instant::now() + d;
    while let Some(ev) = c.next_event(until)? {
        if let UserEvent::Update {
            session: s,
            sent_ns,
            gap,
            ..
        } = ev
        {
            if sessions.contains(&s) && sent_ns > 0 {
                let now = muster_shared::protocol::monotonic_ns();
                let _ = h.record(now.saturating_sub(sent_ns).div_ceil(1000).max(1));
                gaps += gap;
            }
        }
    }
    for s in sessions {
        c.end(s);
    }
    Ok((h, gaps))
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Whether a's list holds any of b's services.
fn lists_b(on_a: &mut UserClient) -> anyhow::Result<bool> {
    Ok(on_a
        .list()?
        .entries()
        .iter()
        .any(|e| e.remote == 1 && e.host.as_str() == "b"))
}

/// ms from `since` until a's list holds b's services (`want`) or not; polled in place.
fn until_b(on_a: &mut UserClient, want: bool, since: Instant) -> anyhow::Result<f64> {
    let limit = since + Duration::from_secs(30);
    while lists_b(on_a)? != want {
        if Instant::now() > limit {
            bail!(
                "b's services did not {} a's list within 30 s",
                if want { "return to" } else { "leave" }
            );
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    Ok(since.elapsed().as_secs_f64() * 1000.0)
}

/// Host b lost `n` times by SIGKILL of its broker (restarted: its systems re-register)
/// and `n` times by SIGSTOP (silent, connections open; SIGCONT brings it back): for
/// each, ms until b's services left a's list and until they were back.
#[allow(clippy::type_complexity)]
fn host_losses(
    n: usize,
    kids: &mut Children,
    inst_b: &Instance,
    b_args: &[&str],
    on_a: &mut UserClient,
) -> anyhow::Result<Vec<(&'static str, Vec<f64>, Vec<f64>)>> {
    let (mut kill_gone, mut kill_back, mut stop_gone, mut stop_back) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..n {
        until_b(on_a, true, Instant::now())?;
        let t = Instant::now();
        kids.kill("broker-b");
        kill_gone.push(until_b(on_a, false, t)?);
        let t = Instant::now();
        kids.spawn(inst_b, "broker-b", b_args, Stdio::null())?;
        kill_back.push(until_b(on_a, true, t)?);
    }
    for _ in 0..n {
        until_b(on_a, true, Instant::now())?;
        std::thread::sleep(Duration::from_millis(500));
        let pid = kids.child_mut("broker-b").context("broker b")?.id() as i32;
        let t = Instant::now();
        // SAFETY: signals to a child we started and have not reaped.
        unsafe { libc::kill(pid, libc::SIGSTOP) };
        stop_gone.push(until_b(on_a, false, t)?);
        let t = Instant::now();
        unsafe { libc::kill(pid, libc::SIGCONT) };
        stop_back.push(until_b(on_a, true, t)?);
    }
    Ok(vec![
        ("broker SIGKILLed", kill_gone, kill_back),
        ("broker SIGSTOPped", stop_gone, stop_back),
    ])
}

struct Rows {
    /// Raw Zenoh round trips, one before each cross-host request.
    floor: Histogram<u64>,
    far_request: Batch,
    local_request: Batch,
    list: Histogram<u64>,
    far_updates: (Histogram<u64>, u64),
    local_updates: (Histogram<u64>, u64),
}

fn measure(
    a: &FederationBenchArgs,
    on_a: &mut UserClient,
    on_b: &mut UserClient,
    probe: &mut ZenohProbe,
) -> anyhow::Result<Rows> {
    // Requests on s1 (no user of the loaded rows holds it, so no quota is in the
    // way); updates on s0, the service the loaded rows' users stream from.
    let deadline = Duration::from_secs(10);
    let far = ServiceId("t1@b/s1".into());
    let local = ServiceId("t1/s1".into());
    let (far_request, floor) = interleaved(on_a, &far, a.requests, probe)?;
    let local_request = requests(on_b, &local, a.requests, deadline)?;
    tracing::info!(
        cross_host = far_request.stray_grants,
        local = local_request.stray_grants,
        "bench: grants of requests given up, ended"
    );
    let list = list_propagation(on_a, on_b, a.list_changes)?;
    let far = ServiceId("t1@b/s0".into());
    let local = ServiceId("t1/s0".into());
    Ok(Rows {
        floor,
        far_request,
        local_request,
        list,
        far_updates: updates(on_a, &far, a.updates_for)?,
        local_updates: updates(on_b, &local, a.updates_for)?,
    })
}

fn rows_json(r: &Rows, a: &FederationBenchArgs) -> Value {
    let floor_p50 = r.floor.value_at_quantile(0.5).max(1) as f64;
    json!({
        "floor_zenoh_rtt_interleaved": summary(&r.floor),
        "cross_host_request": batch_json(&r.far_request, a.requests),
        "local_request": batch_json(&r.local_request, a.requests),
        "ratio_cross_host_request_p50_to_floor":
            r.far_request.latency.value_at_quantile(0.5) as f64 / floor_p50,
        "list_propagation": summary(&r.list),
        "cross_host_update": summary(&r.far_updates.0),
        "cross_host_update_gaps": r.far_updates.1,
        "local_update": summary(&r.local_updates.0),
        "local_update_gaps": r.local_updates.1,
    })
}

fn print_rows(title: &str, r: &Rows) {
    println!("{title}");
    println!(
        "{:<28} {:>7} {:>10} {:>10} {:>10} {:>10}",
        "", "count", "p50 us", "p90 us", "p99 us", "max us"
    );
    println!("{}", row("Zenoh round trip (floor)", &r.floor));
    println!(
        "{}",
        row("request a -> b (cross-host)", &r.far_request.latency)
    );
    println!(
        "{}",
        row("request b -> b (local)", &r.local_request.latency)
    );
    println!("{}", row("list change b -> a", &r.list));
    println!("{}", row("update b -> a (cross-host)", &r.far_updates.0));
    println!("{}", row("update b -> b (local)", &r.local_updates.0));
    println!(
        "gaps: cross-host {}, local {}; refused: cross-host {:?}, local {:?}; abandoned {}/{}; \
         granted after being given up (ended) {}/{}",
        r.far_updates.1,
        r.local_updates.1,
        r.far_request.refusals,
        r.local_request.refusals,
        r.far_request.abandoned,
        r.local_request.abandoned,
        r.far_request.stray_grants,
        r.local_request.stray_grants
    );
}

pub fn run(inst: &Instance, a: FederationBenchArgs) -> anyhow::Result<ExitCode> {
    if let Some(n) = a.hosts {
        return super::hosts::run(inst, &a, n);
    }
    let lease_d = a.lease.unwrap_or(Duration::from_millis(500));
    if a.requests == 0 || a.round_trips == 0 || a.list_changes == 0 {
        bail!("--requests, --round-trips and --list-changes must be at least 1");
    }
    let hosts = LoopbackHosts::new(inst, &HOSTS, "bench")?;
    let insts = &hosts.insts;
    let mut kids = Children::default();
    let lease = vec!["--lease".to_string(), format!("{}ms", lease_d.as_millis())];
    hosts.spawn_brokers(&mut kids, &lease, Stdio::null)?;
    let quota = (a.users * 3 + 100).min(1000).to_string();
    for (i, name, kind) in [(1, "t1", "data"), (1, "d1", "command"), (2, "t2", "data")] {
        kids.spawn(
            &insts[i],
            name,
            &[
                "system",
                "synthetic",
                "--name",
                name,
                "--kind",
                kind,
                "--quota",
                &quota,
                "--rate",
                "10",
                "--services",
                "2",
            ],
            Stdio::null(),
        )?;
    }
    let timeout = Duration::from_secs(30);
    let mut on_b = connect_when_listed(&insts[1], 6, timeout).context("host b")?;
    let opts = muster_users::ConnectOptions {
        wait_for_broker: Duration::from_secs(20),
        handle_signals: false,
        watch_list: true,
    };
    let mut on_a = UserClient::connect(&insts[0], &opts)?;
    let until = Instant::now() + timeout;
    while on_a.list()?.count() < 6 {
        if Instant::now() > until {
            bail!("a did not see b's and c's services within {timeout:?}");
        }
        let _ = on_a.next_event(Instant::now() + Duration::from_millis(50))?;
    }

    let mut probe = ZenohProbe::start(&mut kids, inst)?;
    let floor = probe.floor(a.round_trips)?;
    let idle = measure(&a, &mut on_a, &mut on_b, &mut probe)?;
    let mut out = json!({
        "floor_zenoh_rtt": summary(&floor),
        "idle": rows_json(&idle, &a),
    });
    if !a.json {
        println!("three hosts on loopback, Zenoh peers over TCP");
        println!("{}", row("raw Zenoh round trips alone", &floor));
        print_rows("\nno other users", &idle);
        println!(
            "cross-host request p50 = {:.1} x the Zenoh floor measured beside it",
            idle.far_request.latency.value_at_quantile(0.5) as f64
                / idle.floor.value_at_quantile(0.5).max(1) as f64
        );
    }
    if a.losses > 0 {
        let b_args = hosts.broker_args(1, &lease);
        let b_args: Vec<&str> = b_args.iter().map(String::as_str).collect();
        let losses = host_losses(a.losses, &mut kids, &insts[1], &b_args, &mut on_a)?;
        if !a.json {
            println!(
                "\nhost b lost and back ({} times each; lease {:?}), ms from the signal",
                a.losses, lease_d
            );
            println!(
                "{:<28} {:>7} {:>10} {:>10} {:>10}",
                "", "count", "p50 ms", "max ms", "back p50"
            );
            for (name, gone, back) in &losses {
                println!(
                    "{:<28} {:>7} {:>10.1} {:>10.1} {:>10.1}",
                    name,
                    gone.len(),
                    median(gone),
                    gone.iter().copied().fold(0.0, f64::max),
                    median(back)
                );
            }
        }
        out["host_loss"] = losses
            .iter()
            .map(|(name, gone, back)| {
                (
                    name.to_string(),
                    json!({"removed_ms": gone, "back_ms": back, "removed_p50_ms": median(gone),
                           "back_p50_ms": median(back)}),
                )
            })
            .collect::<serde_json::Map<_, _>>()
            .into();
        out["lease_ms"] = json!(lease_d.as_millis() as u64);
        // On with the loaded rows once b's services are back and b's user is reconnected.
        on_b.close();
        on_b = connect_when_listed(&insts[1], 6, timeout).context("host b again")?;
    }
    if a.users > 0 {
        // Each host's users hold 10 Hz sessions on another host's data service (with
        // `--local-fan-out`, b's on its own t1, beside the local row's user).
        let b_target = if a.local_fan_out { "t1/s0" } else { "t2@c/s0" };
        let targets = ["t1@b/s0", b_target, "t1@b/s0"];
        for (i, host) in HOSTS.iter().enumerate() {
            for k in 0..a.users {
                kids.spawn(
                    &insts[i],
                    &format!("user-{host}-{k}"),
                    &[
                        "user",
                        "--wait",
                        "120s",
                        "request",
                        targets[i],
                        "--duration",
                        "1h",
                    ],
                    Stdio::null(),
                )?;
                // Not all at once: 900 processes starting together on 2 cores is a
                // storm of its own (issue "Faster" measures those).
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        // Until every session is held.
        let want = a.users * 3;
        let until = Instant::now() + Duration::from_secs(120);
        let held = |c: &mut UserClient| -> anyhow::Result<usize> {
            let l = c.list()?;
            Ok(["t1@b/s0", "t2@c/s0"]
                .iter()
                .filter_map(|id| l.find(&ServiceId(id.to_string())))
                .map(|e| e.in_use as usize)
                .sum())
        };
        while held(&mut on_a)? < want {
            if Instant::now() > until {
                bail!(
                    "only {} of {want} cross-host sessions held after 120 s",
                    held(&mut on_a)?
                );
            }
            let _ = on_a.next_event(Instant::now() + Duration::from_millis(100))?;
        }
        std::thread::sleep(Duration::from_secs(1));
        let loaded = measure(&a, &mut on_a, &mut on_b, &mut probe)?;
        out["loaded"] = rows_json(&loaded, &a);
        out["users_per_host"] = json!(a.users);
        out["local_fan_out"] = json!(a.local_fan_out);
        if !a.json {
            print_rows(
                &if a.local_fan_out {
                    format!(
                        "\n{} users per host, each holding a 10 Hz session: a's and c's on \
                         t1@b/s0, b's on t1/s0 (their own host's, as the local row's user)",
                        a.users
                    )
                } else {
                    format!(
                        "\n{} users per host, each holding a 10 Hz session on another host",
                        a.users
                    )
                },
                &loaded,
            );
        }
    }
    on_a.close();
    on_b.close();
    kids.stop();
    if a.json {
        println!("{out}");
    }
    Ok(ExitCode::SUCCESS)
}
