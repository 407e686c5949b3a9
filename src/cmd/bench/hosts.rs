//! `muster bench federation --hosts N`: a federation of N light hosts on this machine.
//!
//! Each host is an instance of its own (`<inst>-h000`, ...) with a federated broker
//! (Zenoh over loopback TCP, as `muster up --hosts` wires them) and one synthetic system
//! `t` of K data services. This process reads every host's list in place in shared
//! memory (no user of its own on any host) and times:
//! - the first start: N-1 hosts started together until every list holds them all;
//! - the join of the Nth host: until every list holds its services and it holds
//!   everyone's;
//! - idle: each broker's CPU, memory and the loopback traffic over a window;
//! - list changes: a service withdrawn or restored on one host until every other
//!   host's list shows it (each host's time, and the last host's: convergence);
//! - host loss: a broker SIGKILLed until its services have left every other list,
//!   then restarted until they are back everywhere;
//! - a restart of every broker at once until every list is whole again.

use super::{histogram, procfs, row};
use crate::cli::FederationBenchArgs;
use crate::cmd::children::{Children, LoopbackHosts};
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::ipc::{create_node, Ipc, ListReader};
use muster_shared::snapshot::{ServiceEntry, ServiceListSnapshot};
use muster_shared::Instance;
use serde_json::{json, Value};
use std::io::Write;
use std::process::{ChildStdin, ExitCode, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How often every host's list is looked at while waiting.
const POLL: Duration = Duration::from_millis(2);
/// The system every host runs.
const SYSTEM: &str = "t";

/// Every host's list, read in place from this process.
struct Lists {
    node: iceoryx2::node::Node<Ipc>,
    insts: Vec<Instance>,
    readers: Vec<Option<ListReader>>,
    /// Where in each host's list the entry last looked for was.
    at: Vec<usize>,
}

impl Lists {
    fn new(insts: &[Instance]) -> anyhow::Result<Self> {
        Ok(Lists {
            node: create_node("bench-hosts", false)?,
            insts: insts.to_vec(),
            readers: insts.iter().map(|_| None).collect(),
            at: vec![0; insts.len()],
        })
    }

    /// Host `i`'s list now, if its broker ever wrote one.
    fn read(&mut self, i: usize) -> Option<Arc<ServiceListSnapshot>> {
        if self.readers[i].is_none() {
            self.readers[i] = ListReader::open(&self.node, &self.insts[i]).ok();
        }
        self.readers[i].as_mut()?.read_from(&self.node).ok()
    }

    /// Host `i`'s entry for service `name` of host `of`'s system, if listed.
    fn entry(&mut self, i: usize, of: &str, name: &str) -> Option<ServiceEntry> {
        let list = self.read(i)?;
        let is = |e: &ServiceEntry| e.host.as_str() == of && e.name.as_str() == name;
        let entries = list.entries();
        if let Some(e) = entries.get(self.at[i]).filter(|e| is(e)) {
            return Some(*e);
        }
        let k = entries.iter().position(is)?;
        self.at[i] = k;
        Some(entries[k])
    }

    /// Polls the hosts `which` until `done` holds for each; the time each first held it
    /// (from `since`), in `which`'s order. Fails past `limit`, naming the hosts not done.
    fn wait_all(
        &mut self,
        which: &[usize],
        since: Instant,
        limit: Duration,
        what: &str,
        mut done: impl FnMut(&mut Self, usize) -> bool,
    ) -> anyhow::Result<Vec<Duration>> {
        let mut at: Vec<Option<Duration>> = vec![None; which.len()];
        loop {
            for (k, &i) in which.iter().enumerate() {
                if at[k].is_none() && done(self, i) {
                    at[k] = Some(since.elapsed());
                }
            }
            if at.iter().all(Option::is_some) {
                return Ok(at.into_iter().flatten().collect());
            }
            if since.elapsed() > limit {
                let late: Vec<usize> = which
                    .iter()
                    .zip(&at)
                    .filter(|(_, t)| t.is_none())
                    .map(|(i, _)| *i)
                    .take(5)
                    .collect();
                let late: Vec<String> = late
                    .into_iter()
                    .map(|i| {
                        let listed = self.read(i).map_or(0, |l| l.count());
                        format!("{} ({listed} listed)", self.insts[i])
                    })
                    .collect();
                bail!(
                    "{what}: {} of {} hosts not there after {limit:?} (e.g. {late:?})",
                    at.iter().filter(|t| t.is_none()).count(),
                    which.len()
                );
            }
            std::thread::sleep(POLL);
        }
    }

    /// Until every host of `which` lists exactly `count` services.
    fn wait_count(
        &mut self,
        which: &[usize],
        count: usize,
        since: Instant,
        limit: Duration,
        what: &str,
    ) -> anyhow::Result<Vec<Duration>> {
        self.wait_all(which, since, limit, what, |l, i| {
            l.read(i).is_some_and(|s| s.count() == count)
        })
    }
}

/// The hosts, their processes and their systems' operator inputs.
struct Fleet {
    hosts: LoopbackHosts,
    kids: Children,
    extra: Vec<String>,
    logs: Option<std::path::PathBuf>,
    stdin: Vec<Option<ChildStdin>>,
    services: usize,
}

impl Fleet {
    fn broker_label(&self, i: usize) -> String {
        format!("broker-{}", self.hosts.names[i])
    }

    fn start_broker(&mut self, i: usize) -> anyhow::Result<()> {
        let args = self.hosts.broker_args(i, &self.extra);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let label = self.broker_label(i);
        let stderr = match &self.logs {
            Some(dir) => std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(dir.join(format!("{label}.log")))?
                .into(),
            None => Stdio::null(),
        };
        self.kids
            .spawn_with(&self.hosts.insts[i], &label, &args, Stdio::null(), stderr)?;
        Ok(())
    }

    fn start_system(&mut self, i: usize) -> anyhow::Result<()> {
        let k = self.services.to_string();
        let child = self.kids.spawn_io(
            &self.hosts.insts[i],
            &format!("system-{}", self.hosts.names[i]),
            &[
                "system",
                "synthetic",
                "--name",
                SYSTEM,
                "--services",
                &k,
                "--rate",
                "1",
            ],
            [Stdio::piped(), Stdio::null(), Stdio::null()],
        )?;
        self.stdin[i] = child.stdin.take();
        Ok(())
    }

    /// Starts host `i`: its broker, then its system.
    fn start(&mut self, i: usize) -> anyhow::Result<()> {
        self.start_broker(i)?;
        self.start_system(i)
    }

    /// An operator line to host `i`'s system.
    fn say(&mut self, i: usize, line: &str) -> anyhow::Result<()> {
        let w = self.stdin[i].as_mut().context("the system's input")?;
        writeln!(w, "{line}")?;
        w.flush()?;
        Ok(())
    }

    fn broker_pids(&mut self) -> Vec<u32> {
        (0..self.hosts.names.len())
            .filter_map(|i| {
                let label = self.broker_label(i);
                self.kids.child_mut(&label).map(|c| c.id())
            })
            .collect()
    }
}

/// Bytes and packets sent on loopback so far (every process's: the federation's
/// traffic while nothing else talks there).
fn loopback_tx() -> Option<(u64, u64)> {
    let dev = std::fs::read_to_string("/proc/net/dev").ok()?;
    let line = dev.lines().find(|l| l.trim_start().starts_with("lo:"))?;
    let f: Vec<u64> = line
        .split_once(':')?
        .1
        .split_whitespace()
        .filter_map(|v| v.parse().ok())
        .collect();
    Some((*f.get(8)?, *f.get(9)?))
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

/// Records `d` in `h`, in µs.
fn record(h: &mut Histogram<u64>, d: Duration) {
    let _ = h.record(d.as_micros().max(1) as u64);
}

/// A histogram (µs) of `times`.
fn hist_of(times: &[Duration]) -> Histogram<u64> {
    let mut h = histogram();
    for t in times {
        record(&mut h, *t);
    }
    h
}

fn last(times: &[Duration]) -> Duration {
    times.iter().copied().max().unwrap_or_default()
}

/// p50 / p99 / max of a histogram of µs, in ms, as JSON.
fn ms_summary(h: &Histogram<u64>) -> Value {
    let q = |x: f64| h.value_at_quantile(x) as f64 / 1000.0;
    json!({"count": h.len(), "p50_ms": q(0.5), "p90_ms": q(0.9), "p99_ms": q(0.99),
           "max_ms": h.max() as f64 / 1000.0})
}

pub fn run(inst: &Instance, a: &FederationBenchArgs, n: usize) -> anyhow::Result<ExitCode> {
    if n < 2 {
        bail!("--hosts must be at least 2");
    }
    if a.services_per_host == 0 {
        bail!("--services-per-host must be at least 1");
    }
    let names: Vec<String> = (0..n).map(|i| format!("h{i:03}")).collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    if a.routers >= n {
        bail!("--routers must be fewer than --hosts");
    }
    let mut hosts = LoopbackHosts::new(inst, &names, "hosts")?;
    hosts.routers = a.routers;
    let k = a.services_per_host;
    let mut extra = Vec::new();
    if let Some(lease) = a.lease {
        extra.extend(["--lease".to_string(), format!("{}ms", lease.as_millis())]);
    }
    if let Some(dir) = &a.logs {
        std::fs::create_dir_all(dir)?;
    }
    let mut lists = Lists::new(&hosts.insts)?;
    let mut fleet = Fleet {
        hosts,
        kids: Children::default(),
        extra,
        logs: a.logs.clone(),
        stdin: (0..n).map(|_| None).collect(),
        services: k,
    };
    let all: Vec<usize> = (0..n).collect();
    let first: Vec<usize> = (0..n - 1).collect();
    let limit = Duration::from_secs(120).max(Duration::from_millis(1500) * n as u32);
    let mut out = json!({"hosts": n, "services_per_host": k,
                         "lease_ms": a.lease.map(|l| l.as_millis() as u64)});
    let say = |s: String| {
        if !a.json {
            println!("{s}");
        }
    };
    let topology = match a.routers {
        0 => "Zenoh peers over TCP, each host dialling the ones before it".to_string(),
        r => format!("{r} of them Zenoh routers, the rest their clients, over TCP"),
    };
    say(format!(
        "{n} hosts on loopback ({topology}), each a broker and a system of {k} services; \
         lease {}",
        a.lease
            .map_or("Zenoh's default (10 s)".to_string(), |l| format!("{l:?}"))
    ));
    out["routers"] = json!(a.routers);

    // The first N-1 hosts, started together.
    let t = Instant::now();
    for i in 0..n - 1 {
        fleet.start(i)?;
    }
    let started = t.elapsed();
    let whole = lists.wait_count(&first, (n - 1) * k, t, limit, "first start")?;
    let h = hist_of(&whole);
    say(format!(
        "first start: {} hosts spawned in {:.0} ms; every list whole after {:.2} s (p50 \
         host {:.2} s)",
        n - 1,
        ms(started),
        last(&whole).as_secs_f64(),
        h.value_at_quantile(0.5) as f64 / 1e6
    ));
    out["first_start"] = json!({"hosts": n - 1, "spawned_ms": ms(started),
        "all_whole_ms": ms(last(&whole)), "per_host": ms_summary(&h)});
    // Let the start's work settle before the join is timed.
    std::thread::sleep(Duration::from_secs(2));

    // The Nth host joins.
    let t = Instant::now();
    fleet.start(n - 1)?;
    let joined = lists.wait_count(&all, n * k, t, limit, "the join")?;
    let h = hist_of(&joined);
    say(format!(
        "join of host {n}: every list holds it (and it them) after {:.0} ms (p50 host {:.0} ms, \
         its own list {:.0} ms)",
        ms(last(&joined)),
        h.value_at_quantile(0.5) as f64 / 1000.0,
        ms(joined[n - 1])
    ));
    out["join"] = json!({"all_ms": ms(last(&joined)), "own_list_ms": ms(joined[n - 1]),
                         "per_host": ms_summary(&h)});

    // Idle.
    std::thread::sleep(Duration::from_secs(2));
    let pids = fleet.broker_pids();
    let cpu0: Vec<u64> = pids
        .iter()
        .map(|p| procfs::cpu_ticks(*p).unwrap_or(0))
        .collect();
    let (b0, p0) = loopback_tx().unwrap_or_default();
    let t = Instant::now();
    std::thread::sleep(a.idle);
    let window = t.elapsed().as_secs_f64();
    let (b1, p1) = loopback_tx().unwrap_or_default();
    let tps = procfs::ticks_per_second() as f64;
    let cpu: Vec<f64> = pids
        .iter()
        .zip(&cpu0)
        .map(|(p, c0)| {
            procfs::cpu_ticks(*p).unwrap_or(0).saturating_sub(*c0) as f64 / tps / window * 100.0
        })
        .collect();
    let rss: Vec<u64> = pids
        .iter()
        .map(|p| procfs::rss_kib(*p).unwrap_or(0))
        .collect();
    let cpu_sum: f64 = cpu.iter().sum();
    let cpu_max = cpu.iter().copied().fold(0.0, f64::max);
    let rss_mib = rss.iter().sum::<u64>() as f64 / 1024.0;
    let bytes_s = (b1 - b0) as f64 / window;
    let packets_s = (p1 - p0) as f64 / window;
    say(format!(
        "idle ({:.0} s): brokers' CPU {:.1} % of a core in all ({:.2} % a host, max {:.2} %); \
         loopback {:.0} KB/s, {:.0} packets/s ({:.1} KB/s a host); brokers' RSS {:.0} MiB \
         in all ({:.1} a host)",
        window,
        cpu_sum,
        cpu_sum / n as f64,
        cpu_max,
        bytes_s / 1000.0,
        packets_s,
        bytes_s / 1000.0 / n as f64,
        rss_mib,
        rss_mib / n as f64
    ));
    out["idle"] = json!({"window_s": window, "cpu_percent_all": cpu_sum,
        "cpu_percent_per_host": cpu_sum / n as f64, "cpu_percent_max": cpu_max,
        "loopback_bytes_per_s": bytes_s, "loopback_packets_per_s": packets_s,
        "rss_mib_all": rss_mib});

    // List changes: one host's service withdrawn, then restored; the other hosts.
    let mut each = histogram();
    let mut converged = histogram();
    for c in 0..a.list_changes {
        let i = (c * 7 + 3) % n;
        let s = format!("s{}", (c / 2) % k);
        let withdraw = c % 2 == 0;
        let others: Vec<usize> = all.iter().copied().filter(|j| *j != i).collect();
        let host = fleet.hosts.names[i].clone();
        let t = Instant::now();
        fleet.say(
            i,
            &format!("{} {s}", if withdraw { "withdraw" } else { "restore" }),
        )?;
        let times = lists.wait_all(&others, t, limit, "a list change", |l, j| {
            l.entry(j, &host, &s)
                .is_some_and(|e| (e.withdrawn == 1) == withdraw)
        })?;
        for d in &times {
            record(&mut each, *d);
        }
        record(&mut converged, last(&times));
    }
    if a.list_changes > 0 {
        say(format!(
            "\nlist changes ({}; µs from the operator's line to the system)",
            a.list_changes
        ));
        say(super::header(""));
        say(row("each other host's list", &each));
        say(row("every host's (convergence)", &converged));
        out["list_change"] = json!({"each_host": ms_summary(&each),
                                    "convergence": ms_summary(&converged)});
    }

    // Host loss: a broker SIGKILLed; its services leave every other list; then back.
    let mut gone_h = histogram();
    let mut back_h = histogram();
    // Hosts that are not routers: a router's loss is its clients' too (they are unseen
    // until they reconnect to another), which this row does not time.
    let r = a.routers;
    for l in 0..a.losses {
        let i = r + (l * 13 + 5) % (n - r);
        let others: Vec<usize> = all.iter().copied().filter(|j| *j != i).collect();
        let label = fleet.broker_label(i);
        let t = Instant::now();
        fleet.kids.kill(&label);
        let gone = lists.wait_count(&others, (n - 1) * k, t, limit, "a lost host")?;
        record(&mut gone_h, last(&gone));
        let t = Instant::now();
        fleet.start_broker(i)?;
        let back = lists.wait_count(&all, n * k, t, limit, "a host back")?;
        record(&mut back_h, last(&back));
    }
    if a.losses > 0 {
        say(format!(
            "\nhost lost ({} times, never a router; its broker SIGKILLed, then started \
             again; µs until every other list)",
            a.losses
        ));
        say(super::header(""));
        say(row("its services gone", &gone_h));
        say(row("back everywhere", &back_h));
        out["host_loss"] = json!({"removed": ms_summary(&gone_h), "back": ms_summary(&back_h)});
    }

    // Every broker restarted at once (their systems stay and register again).
    {
        let t = Instant::now();
        for i in 0..n {
            let label = fleet.broker_label(i);
            fleet.kids.kill(&label);
        }
        for i in 0..n {
            fleet.start_broker(i)?;
        }
        let whole = lists.wait_count(&all, n * k, t, limit, "the restart of all")?;
        let h = hist_of(&whole);
        say(format!(
            "\nevery broker SIGKILLed and started again at once: every list whole after \
             {:.2} s (p50 host {:.2} s)",
            last(&whole).as_secs_f64(),
            h.value_at_quantile(0.5) as f64 / 1e6
        ));
        out["restart_all"] = json!({"all_whole_ms": ms(last(&whole)),
                                    "per_host": ms_summary(&h)});
    }
    drop(lists);
    fleet.kids.stop();
    for inst in &fleet.hosts.insts {
        crate::cmd::children::leave_no_fence(inst);
    }
    if a.json {
        println!("{out}");
    }
    Ok(ExitCode::SUCCESS)
}
