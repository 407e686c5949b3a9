//! `muster bench leftovers`: every kind of muster process SIGKILLed again and again,
//! then what the instance leaves in /dev/shm after its next start, and after `muster
//! cleanup`.
//!
//! Each kind runs on an instance of its own, beside the processes it needs (a broker,
//! a system, a user holding a session): the victim is started, waited for until it
//! works (listed, granted, in sync, up), and SIGKILLed, `--kills` times. Then every
//! other process of the instance is SIGKILLed too; the instance's broker is started once
//! more and stopped (its own cleanup of the dead, beside serving, has run), and /dev/shm
//! is compared with before; then every process is SIGKILLed once more, `muster cleanup`
//! runs and /dev/shm is compared again. Files in /dev/shm cannot all be told apart
//! by instance (iceoryx2's segments are named by port), so nothing else may run on
//! this host meanwhile.

use super::children::{Children, LoopbackHosts};
use crate::cli::LeftoversArgs;
use anyhow::{bail, Context};
use muster_shared::Instance;
use serde_json::{json, Value};
use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::process::{ExitCode, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Every file under /dev/shm, by path.
fn shm_files() -> BTreeSet<String> {
    fn walk(p: &std::path::Path, out: &mut BTreeSet<String>) {
        let Ok(dir) = std::fs::read_dir(p) else {
            return;
        };
        for e in dir.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, out);
            } else {
                out.insert(p.to_string_lossy().into_owned());
            }
        }
    }
    let mut out = BTreeSet::new();
    walk(std::path::Path::new("/dev/shm"), &mut out);
    out
}

/// Lines a child prints, one JSON value or text line at a time.
fn lines(out: impl std::io::Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Waits for a line holding `needle`, up to `timeout`.
fn wait_line(rx: &mpsc::Receiver<String>, needle: &str, timeout: Duration) -> anyhow::Result<()> {
    let until = Instant::now() + timeout;
    loop {
        let line = rx
            .recv_timeout(until.saturating_duration_since(Instant::now()))
            .with_context(|| format!("no line with {needle:?} within {timeout:?}"))?;
        if line.contains(needle) {
            return Ok(());
        }
    }
}

/// Polls `inst`'s list until it holds `id` (a new broker's list when `epoch_not` is
/// given), up to `timeout`.
fn wait_listed(
    client: &mut muster_users::UserClient,
    id: &str,
    epoch_not: Option<u64>,
    timeout: Duration,
) -> anyhow::Result<()> {
    let until = Instant::now() + timeout;
    loop {
        let l = client.list()?;
        if epoch_not.is_none_or(|e| l.epoch != e) && l.entries().iter().any(|e| e.id().0 == id) {
            return Ok(());
        }
        if Instant::now() > until {
            bail!("{id} not listed within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

fn client(inst: &Instance) -> anyhow::Result<muster_users::UserClient> {
    let opts = muster_users::ConnectOptions {
        wait_for_broker: Duration::from_secs(20),
        handle_signals: false,
        watch_list: false,
    };
    Ok(muster_users::UserClient::connect(inst, &opts)?)
}

/// Waits until no dead process's node is left to clean up (bounded).
fn wait_cleaned(timeout: Duration) {
    let until = Instant::now() + timeout;
    while muster_shared::ipc::dead_nodes() > 0 && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Starts the victim of `kind` once, waits until it works; returns its label.
fn start_victim(
    kind: &str,
    k: usize,
    inst: &Instance,
    kids: &mut Children,
    c: &mut muster_users::UserClient,
) -> anyhow::Result<String> {
    let long = Duration::from_secs(30);
    match kind {
        "broker" => {
            let epoch = c.list()?.epoch;
            kids.spawn(inst, "victim", &["broker"], Stdio::null())?;
            wait_listed(c, "base/s0", Some(epoch), long)?;
        }
        "standby" => {
            let ch = kids.spawn(inst, "victim", &["broker", "--standby"], Stdio::piped())?;
            let rx = lines(ch.stdout.take().context("standby stdout")?);
            wait_line(&rx, "in_sync", long)?;
        }
        "system" => {
            let name = format!("v{k}");
            kids.spawn(
                inst,
                "victim",
                &["system", "synthetic", "--name", &name],
                Stdio::null(),
            )?;
            wait_listed(c, &format!("{name}/s0"), None, long)?;
        }
        "user" => {
            let ch = kids.spawn(
                inst,
                "victim",
                &["bench", "failover-user", "--hold", "base/s0"],
                Stdio::piped(),
            )?;
            let rx = lines(ch.stdout.take().context("user stdout")?);
            wait_line(&rx, "\"granted\":true", long)?;
        }
        "sim" => {
            let ch = kids.spawn_with(inst, "victim", &["sim"], Stdio::null(), Stdio::piped())?;
            let rx = lines(ch.stderr.take().context("sim stderr")?);
            wait_line(&rx, "simulator up", long)?;
        }
        other => bail!("unknown kind {other:?}"),
    }
    Ok("victim".into())
}

/// Starts a broker (labelled `broker`) and the system `base` (one service, `base/s0`);
/// returns a client once `base/s0` is listed.
fn start_base(
    inst: &Instance,
    kids: &mut Children,
    broker: &str,
) -> anyhow::Result<muster_users::UserClient> {
    kids.spawn(inst, broker, &["broker"], Stdio::null())?;
    kids.spawn(
        inst,
        "base",
        &["system", "synthetic", "--name", "base"],
        Stdio::null(),
    )?;
    let mut c = super::children::connect_when_listed(inst, 1, Duration::from_secs(30))?;
    wait_listed(&mut c, "base/s0", None, Duration::from_secs(30))?;
    Ok(c)
}

/// Runs one kind on `inst`; returns its figures.
fn one_kind(inst: &Instance, kind: &str, kills: usize) -> anyhow::Result<Value> {
    let before = shm_files();
    let started = Instant::now();
    let mut kids = Children::default();
    if kind == "federated" {
        return federated(inst, kills, before);
    }
    let broker = if kind == "broker" { "victim" } else { "broker" };
    let mut c = start_base(inst, &mut kids, broker)?;
    if kind != "user" {
        let ch = kids.spawn(
            inst,
            "holder",
            &["bench", "failover-user", "--hold", "base/s0"],
            Stdio::piped(),
        )?;
        let rx = lines(ch.stdout.take().context("holder stdout")?);
        wait_line(&rx, "\"granted\":true", Duration::from_secs(30))?;
        // Keep draining it.
        std::thread::spawn(move || while rx.recv().is_ok() {});
    }
    for k in 0..kills {
        if kind == "broker" {
            kids.kill("victim");
            start_victim(kind, k, inst, &mut kids, &mut c)?;
        } else {
            let label = start_victim(kind, k, inst, &mut kids, &mut c)?;
            kids.kill(&label);
        }
    }
    c.close();
    kids.kill_all();
    next_start_and_cleanup(inst, before, kind, kills, started)
}

/// A federated broker SIGKILLed: host a's broker (with a system) killed and started
/// again, while a user of host b requests a's service over and over (so a holds proxy
/// inboxes for b's user when it dies).
fn federated(inst: &Instance, kills: usize, before: BTreeSet<String>) -> anyhow::Result<Value> {
    let started = Instant::now();
    let hosts = LoopbackHosts::new(inst, &["a", "b"], "leftovers")?;
    let mut kids = Children::default();
    hosts.spawn_brokers(&mut kids, &[], Stdio::null)?;
    let (a, b) = (&hosts.insts[0], &hosts.insts[1]);
    kids.spawn(
        a,
        "base",
        &["system", "synthetic", "--name", "base"],
        Stdio::null(),
    )?;
    let mut ca = super::children::connect_when_listed(a, 1, Duration::from_secs(30))?;
    let mut cb = client(b)?;
    let far = "base@a/s0".to_string();
    wait_listed(&mut cb, &far, None, Duration::from_secs(30))
        .context("host a's service in host b's list")?;
    let ch = kids.spawn(
        b,
        "requester",
        &[
            "bench",
            "failover-user",
            "--request",
            &far,
            "--pause",
            "5ms",
        ],
        Stdio::piped(),
    )?;
    let rx = lines(ch.stdout.take().context("requester stdout")?);
    wait_line(&rx, "\"granted\":true", Duration::from_secs(30))?;
    std::thread::spawn(move || while rx.recv().is_ok() {});
    let args = hosts.broker_args(0, &[]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    for _ in 0..kills {
        let epoch = ca.list()?.epoch;
        kids.kill("broker-a");
        kids.spawn(a, "broker-a", &args, Stdio::null())?;
        wait_listed(&mut ca, "base/s0", Some(epoch), Duration::from_secs(30))?;
        // b sees a again, and its user is granted across (a holds its proxy inbox).
        wait_listed(&mut cb, &far, None, Duration::from_secs(30))?;
        std::thread::sleep(Duration::from_millis(100));
    }
    ca.close();
    cb.close();
    kids.kill_all();
    // Host b's instance was SIGKILLed too: its `muster cleanup` first, so that what is
    // counted after is host a's.
    cleanup(b)?;
    next_start_and_cleanup(a, before, "federated", kills, started)
}

/// The instance's broker started again and stopped once its cleanup of the dead ran,
/// then `muster cleanup`: what is left in /dev/shm after each, against `before`.
fn next_start_and_cleanup(
    inst: &Instance,
    before: BTreeSet<String>,
    kind: &str,
    kills: usize,
    started: Instant,
) -> anyhow::Result<Value> {
    let killed_for = started.elapsed();
    let left_after_kills = shm_files().difference(&before).count();
    // The next start: the broker cleans up after the dead beside serving.
    let mut kids = Children::default();
    kids.spawn(inst, "broker", &["broker"], Stdio::null())?;
    let c = client(inst)?;
    wait_cleaned(Duration::from_secs(120));
    c.close();
    kids.stop();
    std::thread::sleep(Duration::from_millis(200));
    let after_start: Vec<String> = shm_files().difference(&before).cloned().collect();
    for f in &after_start {
        eprintln!("leftovers: {kind}: still there after the next start: {f}");
    }
    // Killed once more, everything; then `muster cleanup`.
    let mut kids = Children::default();
    start_base(inst, &mut kids, "broker")?.close();
    kids.kill_all();
    let left_after_second_kill = shm_files().difference(&before).count();
    cleanup(inst)?;
    let after_cleanup: Vec<String> = shm_files().difference(&before).cloned().collect();
    for f in &after_cleanup {
        eprintln!("leftovers: {kind}: still there after muster cleanup: {f}");
    }
    Ok(
        json!({"kind": kind, "kills": kills, "seconds": killed_for.as_secs_f64(),
              "new_files_after_kills": left_after_kills,
              "left_after_next_start": after_start.len(),
              "new_files_after_killing_all_again": left_after_second_kill,
              "left_after_cleanup": after_cleanup.len(),
              "examples_after_next_start": after_start.iter().take(5).collect::<Vec<_>>()}),
    )
}

/// `muster --instance INST cleanup`, as a user would type it.
fn cleanup(inst: &Instance) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("locating the muster binary")?;
    let status = std::process::Command::new(exe)
        .args(["--instance", inst.as_str(), "cleanup"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .status()
        .context("muster cleanup")?;
    if !status.success() {
        bail!("muster cleanup failed: {status}");
    }
    Ok(())
}

pub fn run(inst: &Instance, a: LeftoversArgs) -> anyhow::Result<ExitCode> {
    let mut rows = Vec::new();
    for kind in &a.kinds {
        let mut name = inst.as_str().to_string();
        name.truncate(20);
        let k_inst = Instance::new(&format!("{name}-{kind}"))?;
        eprintln!("leftovers: {kind}: {} kills", a.kills);
        rows.push(one_kind(&k_inst, kind, a.kills).with_context(|| kind.clone())?);
    }
    if a.json {
        println!("{}", json!({"kinds": rows}));
    } else {
        println!(
            "muster bench leftovers: each kind SIGKILLed {} times; files in /dev/shm not there before",
            a.kills
        );
        println!(
            "{:<10} {:>8} {:>12} {:>17} {:>14} {:>14}",
            "kind", "seconds", "all killed", "after next start", "killed again", "after cleanup"
        );
        let n = |r: &Value, k: &str| r[k].as_u64().unwrap_or(0);
        for r in &rows {
            println!(
                "{:<10} {:>8.1} {:>12} {:>17} {:>14} {:>14}",
                r["kind"].as_str().unwrap_or(""),
                r["seconds"].as_f64().unwrap_or(0.0),
                n(r, "new_files_after_kills"),
                n(r, "left_after_next_start"),
                n(r, "new_files_after_killing_all_again"),
                n(r, "left_after_cleanup")
            );
        }
        println!("(files in /dev/shm that were not there before: after the kills and every other process of the instance SIGKILLed too; after the instance's next start and stop; after all SIGKILLed once more; after `muster cleanup`)");
    }
    Ok(ExitCode::SUCCESS)
}
