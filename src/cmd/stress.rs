//! `muster stress`: many separate scripted user processes against a broker and
//! synthetic systems, measured from both sides, with the floor in the same run.

use super::bench::floor::FloorProbe;
use super::bench::procfs;
use super::bench::remote::UdpProbe;
use super::bench::summary;
use super::children::Children;
use crate::cli::StressArgs;
use anyhow::Context;
use hdrhistogram::Histogram;
use muster_shared::trace::Stage;
use muster_shared::Instance;
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::process::{ChildStdout, ExitCode, Stdio};
use std::time::{Duration, Instant};

fn histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 600_000_000, 3).expect("valid bounds")
}

fn samples(v: &Value, key: &str, h: &mut Histogram<u64>) {
    for x in v[key].as_array().into_iter().flatten() {
        if let Some(x) = x.as_u64() {
            let _ = h.record(x.clamp(1, 600_000_000));
        }
    }
}

fn read_all(out: Option<ChildStdout>) -> String {
    let mut s = String::new();
    if let Some(mut o) = out {
        let _ = o.read_to_string(&mut s);
    }
    s
}

/// Per-second buckets of the run: online users and latencies by message type.
#[derive(Default)]
struct Timeline {
    online: BTreeMap<u64, i64>,
    list: BTreeMap<u64, Histogram<u64>>,
    request: BTreeMap<u64, Histogram<u64>>,
}

impl Timeline {
    fn add(&mut self, r: &Value, start_ms: u64) {
        let sec = |ms: u64| ms.saturating_sub(start_ms) / 1000;
        if let (Some(a), Some(b)) = (r["started_ms"].as_u64(), r["ended_ms"].as_u64()) {
            *self.online.entry(sec(a)).or_default() += 1;
            *self.online.entry(sec(b) + 1).or_default() -= 1;
        }
        for (at, us, buckets) in [
            ("list_at_ms", "list_us", &mut self.list),
            ("request_at_ms", "request_us", &mut self.request),
        ] {
            let ats = r[at].as_array().cloned().unwrap_or_default();
            let uss = r[us].as_array().cloned().unwrap_or_default();
            for (a, u) in ats.iter().zip(&uss) {
                if let (Some(a), Some(u)) = (a.as_u64(), u.as_u64()) {
                    let _ = buckets
                        .entry(sec(a))
                        .or_insert_with(histogram)
                        .record(u.clamp(1, 600_000_000));
                }
            }
        }
    }

    /// Service requests sent before and after `secs` seconds.
    fn split_requests(&self, secs: u64) -> (Histogram<u64>, Histogram<u64>) {
        let (mut early, mut late) = (histogram(), histogram());
        for (s, h) in &self.request {
            let _ = if *s < secs { early.add(h) } else { late.add(h) };
        }
        (early, late)
    }

    /// The second of the run from which requests count as the leaving storm's: the
    /// second before the first user left (`None` if nobody left).
    fn leaving_from(&self) -> Option<u64> {
        let first_gone = self
            .online
            .iter()
            .find(|(_, delta)| **delta < 0)
            .map(|(s, _)| *s)?;
        // (A departure counts from the second after the user's last; see `add`.)
        Some(first_gone.saturating_sub(2))
    }

    /// The requests sent from [`Timeline::leaving_from`] to the end: the leaving
    /// storm's (empty if nobody left).
    fn leaving_requests(&self) -> Histogram<u64> {
        let mut h = histogram();
        if let Some(from) = self.leaving_from() {
            for (_, r) in self.request.range(from..) {
                let _ = h.add(r);
            }
        }
        h
    }

    fn to_json(&self) -> Value {
        // Up to the last sample or the last departure, whichever is later.
        let last = [&self.list, &self.request]
            .iter()
            .filter_map(|m| m.keys().next_back().copied())
            .chain(self.online.keys().next_back().copied())
            .max()
            .unwrap_or(0);
        let mut online = 0i64;
        let mut out = Vec::new();
        for s in 0..=last {
            online += self.online.get(&s).copied().unwrap_or(0);
            let cell = |m: &BTreeMap<u64, Histogram<u64>>| m.get(&s).map_or(Value::Null, summary);
            out.push(json!({"t_s": s, "online": online, "list": cell(&self.list), "service_request": cell(&self.request)}));
        }
        Value::Array(out)
    }
}

/// Keys and access for remote stress users (one user name; each process is its own
/// connection with its own id).
struct RemoteUsers {
    dir: std::path::PathBuf,
    addr: String,
    access: String,
    key: String,
}

impl RemoteUsers {
    fn new() -> anyhow::Result<Self> {
        use muster_shared::udp::access::access_line;
        use muster_shared::udp::crypto::KeyPair;
        let dir = std::env::temp_dir().join(format!("muster-stress-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let kp = KeyPair::generate()?;
        let key = dir.join("stress.key");
        let _ = std::fs::remove_file(&key);
        kp.write("stress", &key)?;
        let access = dir.join("access");
        std::fs::write(
            &access,
            access_line("stress", &kp.public, &["*".into()], false) + "\n",
        )?;
        let port = std::net::UdpSocket::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        Ok(RemoteUsers {
            addr: format!("127.0.0.1:{port}"),
            access: access.display().to_string(),
            key: key.display().to_string(),
            dir,
        })
    }
}

impl Drop for RemoteUsers {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The broker and systems of a stress run.
struct Setup {
    children: Children,
    broker_out: Option<ChildStdout>,
    system_outs: Vec<Option<ChildStdout>>,
    broker_pid: u32,
    system_pids: Vec<u32>,
    remote: Option<RemoteUsers>,
    /// The broker's niceness, as the kernel reports it.
    broker_nice: Option<i32>,
    /// The users' niceness: their own, unless the broker could not take its lead
    /// ([`crate::cmd::INFRASTRUCTURE_NICE`] needs privileges) and the users lower
    /// themselves by as much instead, which needs none: the same ratio of CPU shares.
    users_nice: Option<i32>,
}

impl Setup {
    fn start(inst: &Instance, a: &StressArgs) -> anyhow::Result<Self> {
        let remote = if a.remote {
            Some(RemoteUsers::new()?)
        } else {
            None
        };
        let mut children = Children::default();
        let mut broker_args = vec!["broker", "--stats-json"];
        if let Some(r) = &remote {
            broker_args.extend(["--udp", &r.addr, "--access", &r.access]);
        }
        let broker = children.spawn(inst, "broker", &broker_args, Stdio::piped())?;
        let broker_pid = broker.id();
        let broker_out = broker.stdout.take();
        let mut system_outs = Vec::new();
        let mut system_pids = Vec::new();
        for i in 0..a.load.systems {
            let n = a.load.services_of(i);
            let name = format!("s{i}");
            let quota = (1 + (i * 3) % 10).to_string();
            let kind = if i % 2 == 0 { "data" } else { "command" };
            let (n_s, rate) = (n.to_string(), "10".to_string());
            let mut args = vec![
                "system",
                "synthetic",
                "--name",
                &name,
                "--services",
                &n_s,
                "--kind",
                kind,
            ];
            args.extend(["--quota", &quota, "--rate", &rate, "--stats-json"]);
            if i % 3 == 2 {
                args.push("--queue");
            }
            if a.latched && kind == "data" {
                args.push("--latched");
            }
            if remote.is_some() {
                args.extend(["--udp", "127.0.0.1:0"]);
            }
            let child = children.spawn(inst, &name, &args, Stdio::piped())?;
            system_pids.push(child.id());
            system_outs.push(child.stdout.take());
        }
        super::children::connect_when_listed(inst, a.load.services, Duration::from_secs(30))?
            .close();
        let broker_nice = procfs::nice(broker_pid);
        let own = procfs::nice(std::process::id()).unwrap_or(0);
        let users_nice = a.users_nice.or_else(|| match broker_nice {
            Some(b) if b > own + super::INFRASTRUCTURE_NICE => {
                let n = (b - super::INFRASTRUCTURE_NICE).min(19);
                eprintln!(
                    "stress: the broker runs at niceness {b} (raising its priority needs privileges): users lower theirs to {n} instead"
                );
                Some(n)
            }
            _ => None,
        });
        Ok(Setup {
            broker_nice,
            users_nice,
            children,
            broker_out,
            system_outs,
            broker_pid,
            system_pids,
            remote,
        })
    }

    /// `muster user` arguments up to the verb (the transport).
    fn user_prefix(&self) -> Vec<String> {
        let mut v: Vec<String> = Vec::new();
        if let Some(n) = self.users_nice {
            v.extend(["--nice".into(), n.to_string()]);
        }
        v.extend(["user", "--wait", "60s"].map(String::from));
        if let Some(r) = &self.remote {
            v.extend([
                "--remote".into(),
                r.addr.clone(),
                "--key".into(),
                r.key.clone(),
            ]);
        }
        v
    }

    fn cpu_ticks(&self) -> (u64, u64) {
        let b = procfs::cpu_ticks(self.broker_pid).unwrap_or(0);
        let s = self
            .system_pids
            .iter()
            .filter_map(|p| procfs::cpu_ticks(*p))
            .sum();
        (b, s)
    }
}

/// CPU percent of one core from clock ticks over `secs`.
fn cpu_percent(ticks: u64, secs: f64) -> f64 {
    100.0 * ticks as f64 / procfs::ticks_per_second() as f64 / secs.max(1e-9)
}

/// Memory of the federation at one moment: broker, systems, users (PSS), shared memory;
/// `users`: the user processes, each running `per_process` users.
fn memory(setup: &Setup, users: &[u32], per_process: u32) -> Value {
    let pss: Vec<u64> = users.iter().filter_map(|p| procfs::pss_kib(*p)).collect();
    let mean = pss.iter().sum::<u64>() as f64 / pss.len().max(1) as f64;
    json!({
        "broker_rss_kib": procfs::rss_kib(setup.broker_pid),
        "broker_pss_kib": procfs::pss_kib(setup.broker_pid),
        "systems_pss_kib": setup.system_pids.iter().filter_map(|p| procfs::pss_kib(*p)).sum::<u64>(),
        "user_pss_kib_mean": mean / f64::from(per_process),
        "user_process_pss_kib_max": pss.iter().max(),
        "users_per_process": per_process,
        "processes_measured": pss.len(),
        "shm_allocated_bytes": procfs::shm_allocated_bytes(),
    })
}

impl StressArgs {
    /// The user processes: each one's first user (its index) and how many it runs.
    fn groups(&self) -> Vec<(usize, usize)> {
        let k = self.users_per_process as usize;
        (0..self.load.users)
            .step_by(k)
            .map(|first| (first, k.min(self.load.users - first)))
            .collect()
    }
}

/// The users' standard outputs, a file each in a directory of the run's (removed after).
struct UserOutputs(std::path::PathBuf);

impl UserOutputs {
    fn new() -> anyhow::Result<Self> {
        let dir = std::env::temp_dir().join(format!("muster-stress-out-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        Ok(UserOutputs(dir))
    }

    /// User `i`'s standard output.
    fn stdout(&self, i: usize) -> anyhow::Result<Stdio> {
        let path = self.0.join(i.to_string());
        let f =
            std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
        Ok(Stdio::from(f))
    }

    /// What user `i` has written so far.
    fn read(&self, i: usize) -> String {
        std::fs::read_to_string(self.0.join(i.to_string())).unwrap_or_default()
    }
}

impl Drop for UserOutputs {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Idle mode: users connect and stay idle; CPU over `--duration`, and memory.
fn run_idle(inst: &Instance, a: &StressArgs, mut setup: Setup) -> anyhow::Result<ExitCode> {
    let stay = format!("{}ms", (a.duration + Duration::from_secs(120)).as_millis());
    let prefix = setup.user_prefix();
    let outs = UserOutputs::new()?;
    let groups = a.groups();
    let mut users = Vec::new();
    for (p, &(_, n)) in groups.iter().enumerate() {
        let count = n.to_string();
        let mut args: Vec<&str> = prefix.iter().map(String::as_str).collect();
        if a.own_inboxes {
            args.push("--own-inboxes");
        }
        args.extend(["--count", &count, "idle", "--duration", &stay]);
        let child = setup.children.spawn(inst, "user", &args, outs.stdout(p)?)?;
        users.push(child.id());
    }
    // Each user says it is connected in a line of its process's file (the harness holds
    // no descriptor per user, so that 10,000 fit the limit it has).
    let t0 = Instant::now();
    let said = |p: usize| {
        outs.read(p)
            .lines()
            .filter(|l| l.contains("\"connected\":true"))
            .count()
    };
    let mut connected_of = vec![0; groups.len()];
    while connected_of.iter().sum::<usize>() < a.load.users
        && t0.elapsed() < Duration::from_secs(180)
    {
        for (p, &(_, n)) in groups.iter().enumerate() {
            if connected_of[p] < n {
                connected_of[p] = said(p);
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let connected = connected_of.iter().sum::<usize>();
    let setup_s = t0.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_secs(2)); // let the connection storm settle
    let (b0, s0) = setup.cpu_ticks();
    let u0: u64 = users.iter().filter_map(|p| procfs::cpu_ticks(*p)).sum();
    let t = Instant::now();
    std::thread::sleep(a.duration);
    let secs = t.elapsed().as_secs_f64();
    let (b1, s1) = setup.cpu_ticks();
    let u1: u64 = users.iter().filter_map(|p| procfs::cpu_ticks(*p)).sum();
    let mem = memory(&setup, &users, a.users_per_process);
    setup.children.stop();
    let report = json!({
        "mode": "idle", "transport": if a.remote { "udp" } else { "shm" },
        "users": a.load.users, "connected": connected, "services": a.load.services,
        "connect_all_s": setup_s, "measured_s": secs,
        "broker_cpu_percent": cpu_percent(b1.saturating_sub(b0), secs),
        "systems_cpu_percent": cpu_percent(s1.saturating_sub(s0), secs),
        "users_cpu_percent": cpu_percent(u1.saturating_sub(u0), secs),
        "memory": mem,
        "errors": a.load.users - connected,
    });
    if let Some(dir) = &a.report {
        std::fs::create_dir_all(dir)?;
        std::fs::write(
            dir.join("report.json"),
            serde_json::to_string_pretty(&report)?,
        )?;
    }
    if a.json {
        println!("{report}");
    } else {
        println!(
            "muster stress --idle: {connected}/{} users connected over {} in {setup_s:.1} s; over {secs:.0} s idle: broker CPU {:.3} %, systems {:.3} %, all users {:.3} %",
            a.load.users,
            report["transport"],
            report["broker_cpu_percent"].as_f64().unwrap_or(0.0),
            report["systems_cpu_percent"].as_f64().unwrap_or(0.0),
            report["users_cpu_percent"].as_f64().unwrap_or(0.0),
        );
        println!("memory: {}", report["memory"]);
    }
    Ok(if connected == a.load.users {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// A granted request's path to its user: its stamps in order, and the hop between
/// each two.
struct GrantPath {
    stages: &'static [Stage],
    hops: &'static [&'static str],
}

/// A local user's: the broker sends the offer to the system, then the grant to the user.
const LOCAL_GRANT: GrantPath = GrantPath {
    stages: &[
        Stage::UserSend,
        Stage::BrokerRecv,
        Stage::BrokerSend,
        Stage::BrokerRelay,
        Stage::UserRecv,
    ],
    hops: &[
        "user → broker",
        "broker (handling, queue, the offer sent)",
        "broker (the grant sent)",
        "broker → user",
    ],
};

/// A remote user's: the broker sends the grant's datagrams first, the offer after them.
const REMOTE_GRANT: GrantPath = GrantPath {
    stages: &[
        Stage::UserSend,
        Stage::BrokerRecv,
        Stage::BrokerRelay,
        Stage::UserRecv,
    ],
    hops: &[
        "user → broker",
        "broker (handling, queue, the grant sent)",
        "broker → user",
    ],
};

/// The system's side, off the user's path: it opens the session and confirms it.
const CONFIRM_PATH: [Stage; 4] = [
    Stage::BrokerSend,
    Stage::SystemRecv,
    Stage::SystemSend,
    Stage::BrokerAnswer,
];
const CONFIRM_HOPS: [&str; 3] = [
    "broker → system (the offer)",
    "system (opening the session)",
    "system → broker (its confirmation)",
];

/// Per-hop latency (µs) of granted requests whose stamps all came.
struct PerHop {
    /// The hops of the [`GrantPath`] asked for.
    grant: Vec<Histogram<u64>>,
    /// The hops of [`CONFIRM_PATH`].
    confirm: Vec<Histogram<u64>>,
    /// The whole path, user send to grant taken.
    whole: Histogram<u64>,
    /// User send to the system's confirmation: the session open where it runs (requests
    /// granted at once, as the users' own request figure counts them).
    session_open: Histogram<u64>,
    /// User send to the session's first update taken (data sessions granted at once).
    first_update: Histogram<u64>,
    /// The same, of requests that were queued first: their wait for a free place.
    first_update_queued: Histogram<u64>,
    /// Grant taken to the session's first update taken: what the first update adds to
    /// the grant, whatever the request waited for in a queue.
    grant_to_first_update: Histogram<u64>,
}

/// Each stamped request's stamps (CLOCK_MONOTONIC ns), by stage in [`Stage::ALL`]'s
/// order.
type Stamps = HashMap<(String, u64), [Option<u64>; Stage::ALL.len()]>;

/// The stamps every process wrote to `dir`, joined by user and request.
fn read_stamps(dir: &std::path::Path) -> Stamps {
    let mut paths = Stamps::new();
    for (stage, user, req, ns) in muster_shared::trace::read_dir(dir) {
        let i = Stage::ALL.iter().position(|s| *s == stage).unwrap_or(0);
        let slot = &mut paths.entry((user, req)).or_default()[i];
        // A request sent again (UDP) keeps its first stamps.
        if slot.is_none() {
            *slot = Some(ns);
        }
    }
    paths
}

/// A path's hops for the JSON report: each name with its latency summary.
fn hops_json(names: &[&str], hops: &[Histogram<u64>]) -> Vec<Value> {
    names
        .iter()
        .zip(hops)
        .map(|(name, h)| json!({"hop": name, "latency": summary(h)}))
        .collect()
}

/// Prints a path's hops under `title` (each as `line` makes it), if any request took
/// it; says whether one did.
fn print_hops(
    title: &str,
    names: &[&str],
    hops: &[Histogram<u64>],
    line: impl Fn(&str, &Histogram<u64>) -> String,
) -> bool {
    if hops[0].is_empty() {
        return false;
    }
    println!("  {title}:");
    for (name, h) in names.iter().zip(hops) {
        println!("{}", line(&format!("    {name}"), h));
    }
    true
}

/// Per hop, of the requests whose user sent them at a time (CLOCK_MONOTONIC ns) that
/// `sent_at` keeps.
fn per_hop(paths: &Stamps, grant: &GrantPath, sent_at: impl Fn(u64) -> bool) -> PerHop {
    let at = |stamps: &[Option<u64>; Stage::ALL.len()], s: &Stage| {
        stamps[Stage::ALL.iter().position(|x| x == s).unwrap_or(0)]
    };
    let mut out = PerHop {
        grant: grant.hops.iter().map(|_| histogram()).collect(),
        confirm: CONFIRM_HOPS.iter().map(|_| histogram()).collect(),
        whole: histogram(),
        session_open: histogram(),
        first_update: histogram(),
        first_update_queued: histogram(),
        grant_to_first_update: histogram(),
    };
    let us = |from: u64, to: u64| ((to - from) / 1000).max(1);
    // A path's stamps, if all came in order.
    let path = |stamps, path: &[Stage]| -> Option<Vec<u64>> {
        let t: Vec<u64> = path.iter().map(|s| at(stamps, s)).collect::<Option<_>>()?;
        t.windows(2).all(|w| w[0] <= w[1]).then_some(t)
    };
    for stamps in paths.values() {
        if !at(stamps, &Stage::UserSend).is_some_and(&sent_at) {
            continue;
        }
        // A request queued first waited for a place to free: not the path's latency
        // (the users' request figure leaves those out too), but counted apart.
        let queued = at(stamps, &Stage::UserQueued).is_some();
        let to_first_update = if queued {
            &mut out.first_update_queued
        } else {
            &mut out.first_update
        };
        if let Some(t) = path(stamps, &[Stage::UserSend, Stage::FirstUpdate]) {
            let _ = to_first_update.record(us(t[0], t[1]));
        }
        if let Some(t) = path(stamps, &[Stage::UserSend, Stage::SystemSend]).filter(|_| !queued) {
            let _ = out.session_open.record(us(t[0], t[1]));
        }
        if let Some(t) = path(stamps, &[Stage::UserRecv, Stage::FirstUpdate]) {
            let _ = out.grant_to_first_update.record(us(t[0], t[1]));
        }
        if let Some(t) = path(stamps, &CONFIRM_PATH) {
            for (h, w) in out.confirm.iter_mut().zip(t.windows(2)) {
                let _ = h.record(us(w[0], w[1]));
            }
        }
        let Some(t) = path(stamps, grant.stages) else {
            continue;
        };
        for (h, w) in out.grant.iter_mut().zip(t.windows(2)) {
            let _ = h.record(us(w[0], w[1]));
        }
        let _ = out.whole.record(us(t[0], t[t.len() - 1]));
    }
    out
}

pub fn run(inst: &Instance, a: StressArgs) -> anyhow::Result<ExitCode> {
    a.load.check_for(0, a.remote)?;
    let per_process = muster_broker::core::MAX_USERS_PER_PROCESS;
    if !a.remote && a.users_per_process as usize > per_process {
        anyhow::bail!(
            "--users-per-process: at most {per_process} local users a process (the broker's cap)"
        );
    }
    // Every process on a request's path stamps it (per-hop breakdown below); the
    // variable is set before any thread starts, and the children inherit it.
    let trace_dir =
        std::env::temp_dir().join(format!("muster-stress-trace-{}", std::process::id()));
    if !a.idle {
        let _ = std::fs::remove_dir_all(&trace_dir);
        std::fs::create_dir_all(&trace_dir)?;
        std::env::set_var(muster_shared::trace::TRACE_DIR, &trace_dir);
    }
    let mut setup = Setup::start(inst, &a)?;
    if a.idle {
        return run_idle(inst, &a, setup);
    }
    let mut probe = FloorProbe::start(inst)?;
    let mut udp_probe = match &setup.remote {
        Some(_) => Some(UdpProbe::start(inst, &mut setup.children)?),
        None => None,
    };
    let prefix = setup.user_prefix();
    let (b0, s0) = setup.cpu_ticks();

    // Users. Each writes its report to its own file, and with --together all wait on
    // one pipe: the harness holds no descriptor per user.
    let outs = UserOutputs::new()?;
    let duration = format!("{}ms", a.duration.as_millis());
    let think = format!("{}ms", a.think.as_millis().max(1));
    let refresh = format!("{}ms", a.refresh.as_millis().max(1));
    let mut start = Instant::now();
    let mut start_ms = muster_shared::protocol::monotonic_ns() / 1_000_000;
    let mut user_pids = Vec::new();
    let mut group_of = HashMap::new();
    let groups = a.groups();
    // With --together, the users' standard input: closing it lets them all go.
    let mut gate = None;
    let gate_read = if a.together {
        let (r, w) = std::io::pipe().context("the start gate")?;
        gate = Some(w);
        Some(r)
    } else {
        None
    };
    for (p, &(first, n)) in groups.iter().enumerate() {
        let seed = first.to_string();
        let count = n.to_string();
        let mut args: Vec<&str> = prefix.iter().map(String::as_str).collect();
        if a.own_inboxes {
            args.push("--own-inboxes");
        }
        args.extend([
            "--count",
            &count,
            "behave",
            "--duration",
            &duration,
            "--think",
            &think,
            "--refresh",
            &refresh,
            "--seed",
            &seed,
        ]);
        let stdin = match &gate_read {
            Some(r) => {
                args.push("--start-on-stdin");
                Stdio::from(r.try_clone().context("the start gate")?)
            }
            None => Stdio::null(),
        };
        let child = setup.children.spawn_io(
            inst,
            "user",
            &args,
            [stdin, outs.stdout(p)?, Stdio::inherit()],
        )?;
        user_pids.push(child.id());
        group_of.insert(child.id(), p);
    }
    drop(gate_read);
    let mut waiting_at_start = None;
    if a.together {
        // Every user started and waiting on its input, then all let go at once.
        let until = Instant::now() + Duration::from_secs(120);
        // The users of the processes blocked reading the gate.
        let waiting = |pids: &[u32]| -> usize {
            pids.iter()
                .filter(|p| {
                    std::fs::read_to_string(format!("/proc/{p}/wchan"))
                        .is_ok_and(|w| w.contains("pipe_read"))
                })
                .map(|p| group_of.get(p).map_or(0, |&g| groups[g].1))
                .sum()
        };
        let mut n = waiting(&user_pids);
        while n < a.load.users && Instant::now() < until {
            std::thread::sleep(Duration::from_millis(50));
            n = waiting(&user_pids);
        }
        waiting_at_start = Some(n);
        tracing::info!(
            waiting = n,
            users = a.load.users,
            "stress: every user let go at once"
        );
        start = Instant::now();
        start_ms = muster_shared::protocol::monotonic_ns() / 1_000_000;
        drop(gate.take());
    }
    // While they behave, the floor, every 20 ms, under the same load.
    let mut floor = histogram();
    let mut floor_udp = histogram();
    let mut mem = Value::Null;
    let mut users_cpu = 0.0;
    let mut reports: Vec<Option<Value>> = vec![None; a.load.users];
    let mut groups_done = 0;
    let give_up = start + a.duration + Duration::from_secs(120);
    while groups_done < groups.len() && Instant::now() < give_up {
        floor.record((probe.round_trip()?.as_micros() as u64).max(1))?;
        if let Some(p) = udp_probe.as_mut() {
            if let Some(d) = p.round_trip()? {
                floor_udp.record((d.as_micros() as u64).max(1))?;
            }
        }
        if mem.is_null() && start.elapsed() >= a.duration / 2 {
            mem = memory(&setup, &user_pids, a.users_per_process);
            let ticks: u64 = user_pids.iter().filter_map(|p| procfs::cpu_ticks(*p)).sum();
            users_cpu = cpu_percent(ticks, start.elapsed().as_secs_f64());
        }
        for pid in setup.children.exited("user") {
            if let Some(&p) = group_of.get(&pid) {
                // Its users' reports, one line each (a user that failed has none).
                let (first, n) = groups[p];
                let mine = outs
                    .read(p)
                    .lines()
                    .filter_map(|l| serde_json::from_str::<Value>(l).ok())
                    .filter(Value::is_object)
                    .take(n)
                    .collect::<Vec<_>>();
                for (k, r) in mine.into_iter().enumerate() {
                    reports[first + k] = Some(r);
                }
                groups_done += 1;
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let run_time = start.elapsed();
    let (b1, s1) = setup.cpu_ticks();
    let run_s = run_time.as_secs_f64();
    let cpu = json!({
        "broker_percent": cpu_percent(b1.saturating_sub(b0), run_s),
        "systems_percent": cpu_percent(s1.saturating_sub(s0), run_s),
        "users_percent_first_half": users_cpu,
    });
    probe.stop();
    setup.children.stop(); // SIGTERM: systems and broker print their statistics
    let broker: Value =
        serde_json::from_str(read_all(setup.broker_out.take()).trim()).unwrap_or(Value::Null);
    let systems: Vec<Value> = std::mem::take(&mut setup.system_outs)
        .into_iter()
        .filter_map(|o| serde_json::from_str(read_all(o).trim()).ok())
        .collect();

    // Aggregate.
    let stamps = read_stamps(&trace_dir);
    let grant = if a.remote {
        &REMOTE_GRANT
    } else {
        &LOCAL_GRANT
    };
    let hops = per_hop(&stamps, grant, |_| true);
    // The start-up storm's: requests sent in the first 10 s.
    let early_end = (start_ms + 10_000) * 1_000_000;
    let early_hops = per_hop(&stamps, grant, |ns| ns < early_end);
    let (mut list, mut request, mut update) = (histogram(), histogram(), histogram());
    let mut termination = histogram();
    let mut timeline = Timeline::default();
    let mut totals: BTreeMap<&str, u64> = BTreeMap::new();
    let mut refusals: BTreeMap<String, u64> = BTreeMap::new();
    let mut users_with_list = 0;
    let mut users_requesting = 0;
    let mut missing = 0;
    for r in &reports {
        let Some(r) = r else {
            missing += 1;
            continue;
        };
        samples(r, "list_us", &mut list);
        samples(r, "request_us", &mut request);
        timeline.add(r, start_ms);
        samples(r, "update_us", &mut update);
        samples(r, "end_us", &mut termination);
        for k in [
            "lists",
            "requests",
            "grants",
            "abandoned",
            "updates",
            "gaps",
            "links",
            "link_failures",
            "errors",
        ] {
            *totals.entry(k).or_default() += r[k].as_u64().unwrap_or(0);
        }
        for (code, n) in r["refusals"].as_object().into_iter().flatten() {
            *refusals.entry(code.clone()).or_default() += n.as_u64().unwrap_or(0);
        }
        if r["lists"].as_u64().unwrap_or(0) > 0 {
            users_with_list += 1;
        }
        if r["requests"].as_u64().unwrap_or(0) > 0 {
            users_requesting += 1;
        }
    }
    let refused: u64 = refusals.values().sum();
    let answered = totals["grants"] + refused + totals["abandoned"] + totals["errors"];
    let mut over_quota = Vec::new();
    let mut system_grants = 0;
    for s in &systems {
        for (svc, rep) in s["services"].as_object().into_iter().flatten() {
            system_grants += rep["grants"].as_u64().unwrap_or(0);
            let (max, quota) = (
                rep["max_in_use"].as_u64().unwrap_or(0),
                rep["quota"].as_u64().unwrap_or(0),
            );
            if max > quota {
                over_quota.push(format!("{}/{svc}: {max} > {quota}", s["system"]));
            }
        }
    }
    let checks = json!({
        "every_user_got_a_list": users_with_list == a.load.users,
        "every_request_answered": answered == totals["requests"],
        "quota_never_exceeded": over_quota.is_empty() && systems.len() == a.load.systems,
    });
    let ok = checks
        .as_object()
        .is_some_and(|c| c.values().all(|v| v == true))
        && missing == 0;
    let errors = totals["errors"] + missing as u64;
    let floor_base_p50 = if a.remote { &floor_udp } else { &floor }
        .value_at_quantile(0.5)
        .max(1) as f64;
    let (early, late) = timeline.split_requests(10);
    let leaving = timeline.leaving_requests();
    // The leaving storm's requests, hop by hop: where they waited.
    let leaving_hops = timeline.leaving_from().map(|from| {
        let from_ns = (start_ms + from * 1000) * 1_000_000;
        per_hop(&stamps, grant, |ns| ns >= from_ns)
    });
    drop(stamps);
    let _ = std::fs::remove_dir_all(&trace_dir);
    let mut report = json!({
        "users": a.load.users,
        "services": a.load.services, "systems": a.load.systems,
        "duration_s": a.duration.as_secs_f64(), "run_s": run_time.as_secs_f64(),
        "errors": errors, "missing_user_reports": missing,
        "totals": totals, "system_grants": system_grants, "refusals": refusals, "over_quota": over_quota, "checks": checks,
        "list": summary(&list), "service_request": summary(&request),
        "service_request_first_10s": summary(&early), "service_request_after_10s": summary(&late), "service_request_leaving": summary(&leaving), "update": summary(&update), "termination": summary(&termination),
        "floor": summary(&floor),
        "floor_udp": if a.remote { summary(&floor_udp) } else { Value::Null },
        "transport": if a.remote { "udp" } else { "shm" },
        "broker_nice": setup.broker_nice, "users_nice": setup.users_nice,
        "together": a.together, "users_waiting_at_start": waiting_at_start,
        "cpu": cpu, "memory": mem,
        "timeline": timeline.to_json(),
        "service_request_p50_over_floor_p50": request.value_at_quantile(0.5) as f64
            / if a.remote { &floor_udp } else { &floor }.value_at_quantile(0.5).max(1) as f64,
        "p50_over_floor_p50": {
            "list": list.value_at_quantile(0.5) as f64 / floor_base_p50,
            "service_request": request.value_at_quantile(0.5) as f64 / floor_base_p50,
            "update": update.value_at_quantile(0.5) as f64 / floor_base_p50,
            "termination": termination.value_at_quantile(0.5) as f64 / floor_base_p50,
        },
        "broker": broker,
        "per_hop": hops_json(grant.hops, &hops.grant),
        "per_hop_confirm": hops_json(&CONFIRM_HOPS, &hops.confirm),
        "per_hop_whole": summary(&hops.whole),
        "request_to_session_open": summary(&hops.session_open),
        "request_to_first_update": summary(&hops.first_update),
        "request_to_first_update_p50_over_floor_p50": hops.first_update.value_at_quantile(0.5) as f64
            / if a.remote { &floor_udp } else { &floor }.value_at_quantile(0.5).max(1) as f64,
        "per_hop_first_10s": hops_json(grant.hops, &early_hops.grant),
        "per_hop_whole_first_10s": summary(&early_hops.whole),
        "per_hop_leaving": leaving_hops.as_ref().map_or(Value::Null, |h| hops_json(grant.hops, &h.grant).into()),
    });
    report["grant_to_first_update"] = summary(&hops.grant_to_first_update);
    report["request_to_first_update_queued"] = summary(&hops.first_update_queued);
    report["latched"] = a.latched.into();
    report["users_per_process"] = a.users_per_process.into();
    report["shared_inboxes"] = (a.users_per_process > 1 && !a.remote && !a.own_inboxes).into();
    report["users_requesting"] = users_requesting.into();
    if let Some(dir) = &a.report {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        std::fs::write(
            dir.join("report.json"),
            serde_json::to_string_pretty(&report)?,
        )?;
        let title = format!(
            "muster stress: {} users, {} services",
            a.load.users, a.load.services
        );
        let timeline = report["timeline"].as_array().cloned().unwrap_or_default();
        super::stress_plot::draw(&timeline, &title, &dir.join("response-times.png"))?;
    }
    if a.json {
        println!("{report}");
    } else {
        println!(
            "muster stress: {} users ({} a process; {} requested at least once), {} services on {} systems, {:.0} s",
            a.load.users,
            a.users_per_process,
            users_requesting,
            a.load.services,
            a.load.systems,
            a.duration.as_secs_f64()
        );
        if let Some(n) = waiting_at_start {
            // How fast they came: users online at the end of each of the first seconds.
            let online: Vec<String> = report["timeline"]
                .as_array()
                .into_iter()
                .flatten()
                .take(3)
                .map(|t| format!("{} s: {}", t["t_s"].as_u64().unwrap_or(0) + 1, t["online"]))
                .collect();
            println!(
                "started together: {n} of {} users waiting when let go; online after {}",
                a.load.users,
                online.join(", ")
            );
        }
        // The paper's Table 1 (count, max, median, min) plus p90/p99, and each median
        // as a multiple of the floor's median measured in the same run.
        let base = if a.remote { &floor_udp } else { &floor };
        let line = |name: &str, h: &Histogram<u64>| {
            format!(
                "{name:<30} {:>7} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8.1}",
                h.len(),
                h.min(),
                h.value_at_quantile(0.5),
                h.value_at_quantile(0.9),
                h.value_at_quantile(0.99),
                h.max(),
                h.value_at_quantile(0.5) as f64 / base.value_at_quantile(0.5).max(1) as f64
            )
        };
        println!(
            "\n{:<30} {:>7} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8}",
            "latency (µs)", "count", "min", "p50", "p90", "p99", "max", "p50/floor"
        );
        println!("{}", line("list request", &list));
        println!("{}", line("service request", &request));
        println!("{}", line("session update", &update));
        println!("{}", line("termination (end → confirmed)", &termination));
        println!("{}", line("floor (raw 2-process trip)", &floor));
        if a.remote {
            println!("{}", line("floor (raw UDP round trip)", &floor_udp));
        }
        println!("{}", line("service request, first 10 s", &early));
        println!("{}", line("service request, after 10 s", &late));
        println!("{}", line("service request, users leaving", &leaving));
        println!("\nper hop of a granted request (stamps at each process, CLOCK_MONOTONIC):");
        print_hops("to the user", grant.hops, &hops.grant, line);
        println!("{}", line("  whole path (stamped)", &hops.whole));
        println!(
            "{}",
            line(
                "  request → session open (granted at once)",
                &hops.session_open
            )
        );
        println!(
            "{}",
            line(
                "  request → first update (granted at once)",
                &hops.first_update
            )
        );
        if !hops.first_update_queued.is_empty() {
            println!(
                "{}",
                line("  ... queued first (waiting)", &hops.first_update_queued)
            );
        }
        println!(
            "{}",
            line("  grant → first update", &hops.grant_to_first_update)
        );
        print_hops(
            "the system, off the user's path",
            &CONFIRM_HOPS,
            &hops.confirm,
            line,
        );
        // A part of the run's requests, hop by hop and whole.
        let print_part = |title: &str, h: &PerHop| {
            if print_hops(title, grant.hops, &h.grant, line) {
                println!("{}", line("    whole path (stamped)", &h.whole));
            }
        };
        print_part("requests sent in the first 10 s, to the user", &early_hops);
        if let Some(h) = &leaving_hops {
            print_part("requests sent while users leave, to the user", h);
        }
        if let Some(h) = broker["handling"].as_object() {
            println!("\nbroker, time to handle (us):");
            for (kind, v) in h {
                println!(
                    "  {kind:<14} count {:>7}  p50 {:>5}  p99 {:>5}  max {:>6}",
                    v["count"], v["p50_us"], v["p99_us"], v["max_us"]
                );
            }
        }
        println!(
            "\ncpu over the run: {}; memory at half time: {}",
            report["cpu"], report["memory"]
        );
        println!("totals: {totals:?}; refusals: {refusals:?}");
        println!("checks: {checks}; errors {errors}");
    }
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stamps of one request: `(stage, µs after 0)` each.
    fn request(paths: &mut Stamps, user: &str, req: u64, stamps: &[(Stage, u64)]) {
        let slots = paths.entry((user.to_string(), req)).or_default();
        for (stage, us) in stamps {
            let i = Stage::ALL.iter().position(|s| s == stage).unwrap();
            slots[i] = Some(us * 1000);
        }
    }

    #[test]
    fn a_request_queued_first_counts_apart_from_those_granted_at_once() {
        let mut paths = Stamps::new();
        let granted = |sent: u64, waited: u64| {
            let t = sent + waited;
            [
                (Stage::UserSend, sent),
                (Stage::BrokerRecv, sent + 50),
                (Stage::BrokerSend, t + 70),
                (Stage::SystemRecv, t + 500),
                (Stage::SystemSend, t + 520),
                (Stage::BrokerAnswer, t + 600),
                (Stage::BrokerRelay, t + 90),
                (Stage::UserRecv, t + 130),
                (Stage::FirstUpdate, t + 135),
            ]
        };
        // Two granted at once, one queued for 40 ms first.
        request(&mut paths, "a", 1, &granted(1_000, 0));
        request(&mut paths, "b", 1, &granted(2_000, 0));
        let mut queued = granted(3_000, 40_000).to_vec();
        queued.push((Stage::UserQueued, 3_080));
        request(&mut paths, "c", 1, &queued);
        let h = per_hop(&paths, &LOCAL_GRANT, |_| true);
        assert_eq!(h.first_update.len(), 2);
        assert_eq!(h.first_update.max(), 135);
        assert_eq!(h.first_update_queued.len(), 1);
        // (3 significant digits: the histogram's bucket of 40,135.)
        let q = &h.first_update_queued;
        assert_eq!(q.max(), q.highest_equivalent(40_135));
        assert_eq!((h.session_open.len(), h.session_open.max()), (2, 520));
        // What the first update adds to the grant counts every request.
        assert_eq!(h.grant_to_first_update.len(), 3);
        assert_eq!(h.grant_to_first_update.max(), 5);
    }

    #[test]
    fn a_remote_users_grant_goes_before_its_offer_and_is_counted_hop_by_hop() {
        let mut paths = Stamps::new();
        // The grant's datagram at 90 µs, the offer written after it at 110.
        let remote = [
            (Stage::UserSend, 0),
            (Stage::BrokerRecv, 40),
            (Stage::BrokerRelay, 90),
            (Stage::BrokerSend, 110),
            (Stage::SystemRecv, 400),
            (Stage::SystemSend, 420),
            (Stage::BrokerAnswer, 500),
            (Stage::UserRecv, 150),
            (Stage::FirstUpdate, 160),
        ];
        request(&mut paths, "r", 1, &remote);
        let h = per_hop(&paths, &REMOTE_GRANT, |_| true);
        let p50s: Vec<u64> = h.grant.iter().map(|x| x.value_at_quantile(0.5)).collect();
        assert_eq!(p50s, [40, 50, 60]);
        assert_eq!((h.whole.len(), h.whole.max()), (1, 150));
        assert_eq!(h.first_update.max(), 160);
        // The offer's path to the system is counted from when it was sent.
        assert_eq!(h.confirm[0].max(), 290);
        // Taken for a local path (offer first), its stamps are out of order: not counted.
        let local = per_hop(&paths, &LOCAL_GRANT, |_| true);
        assert_eq!(local.whole.len(), 0);
        assert_eq!(local.first_update.len(), 1);
    }
}
