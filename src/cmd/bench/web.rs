//! `muster bench web`: the web console under many viewers.
//!
//! A broker, a synthetic system `bw` (one `pose2d` data service per ten clients, at
//! 10 Hz, quota 11) and `muster web`; N users in its access file. N WebSocket clients
//! (`web/bench/ws_clients.py`, Python's `websockets`) sign in, each as its own user,
//! watch the list and hold one session of `bw`. Timed in the same run, on
//! CLOCK_MONOTONIC: every update from the system's send to the browser-side client's
//! receive, and to a shared-memory user's (this process) on the same system; the
//! broker's request → grant for a service of its own (`probe/s0`) before the clients
//! come and while they watch; the web process's CPU and memory.

use super::children::{connect_when_listed, request_granted, Children};
use super::procfs::{cpu_ticks, pss_kib, rss_kib, ticks_per_second};
use super::{header, histogram, row, summary, LineChild};
use crate::cli::WebBenchArgs;
use anyhow::Context as _;
use hdrhistogram::Histogram;
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::ServiceId;
use muster_shared::udp::access::{access_line, new_web_token, web_line};
use muster_shared::Instance;
use muster_users::{UserClient, UserEvent};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long after the last client is in the measured window opens.
const SETTLE: Duration = Duration::from_secs(1);
const SCRIPT: &str = include_str!("../../../web/bench/ws_clients.py");
/// Clients per service of `bw` (its quota leaves one place for the shm user).
const PER_SERVICE: usize = 10;

/// Requests `service` `n` times (each session ended before the next request);
/// request → grant, µs.
fn probe(client: &mut UserClient, service: &ServiceId, n: usize) -> anyhow::Result<Histogram<u64>> {
    let mut h = histogram();
    for _ in 0..n {
        let t0 = Instant::now();
        let session = request_granted(client, service, Duration::from_secs(10))?;
        h.saturating_record(t0.elapsed().as_micros() as u64);
        client.end(session);
        let deadline = Instant::now() + Duration::from_secs(10);
        while let Some(e) = client.next_event(deadline)? {
            if matches!(e, UserEvent::EndConfirmed { session: s } | UserEvent::Ended { session: s, .. } if s == session)
            {
                break;
            }
        }
    }
    Ok(h)
}

pub fn run(inst: &Instance, a: WebBenchArgs) -> anyhow::Result<std::process::ExitCode> {
    anyhow::ensure!(
        a.clients > 0 && a.procs > 0,
        "--clients and --procs must be > 0"
    );
    super::in_temp_dir("web", a.json, |dir| bench(inst, &a, dir))
}

fn bench(inst: &Instance, a: &WebBenchArgs, dir: &std::path::Path) -> anyhow::Result<Value> {
    // N users, each allowed bw's services, with a web token.
    let services = a.clients.div_ceil(PER_SERVICE);
    let mut access = String::new();
    let mut users = Vec::new();
    for i in 0..a.clients {
        let name = format!("w{i}");
        let token = new_web_token();
        let mut key = [0u8; 32];
        rand::fill(&mut key);
        access.push_str(&access_line(&name, &key, &["bw/*".to_string()], false));
        access.push('\n');
        access.push_str(&web_line(&name, &token));
        access.push('\n');
        users.push(json!([name, token, format!("bw/s{}", i % services)]));
    }
    let access_path = dir.join("access");
    std::fs::write(&access_path, access)?;
    let script = dir.join("ws_clients.py");
    std::fs::write(&script, SCRIPT)?;

    let mut kids = Children::default();
    let room = (a.clients + 16).to_string();
    kids.spawn(
        inst,
        "broker",
        &["broker", "--max-users-per-process", &room],
        Stdio::null(),
    )?;
    let n = services.to_string();
    kids.spawn(
        inst,
        "system bw",
        &[
            "system",
            "synthetic",
            "--name",
            "bw",
            "--services",
            &n,
            "--quota",
            "11",
            "--rate",
            "10",
        ],
        Stdio::null(),
    )?;
    kids.spawn(
        inst,
        "system probe",
        &[
            "system",
            "synthetic",
            "--name",
            "probe",
            "--services",
            "1",
            "--quota",
            "1000",
        ],
        Stdio::null(),
    )?;
    let mut client = connect_when_listed(inst, services + 1, Duration::from_secs(30))?;
    let probe_id = ServiceId::new("probe", "s0");
    let before = probe(&mut client, &probe_id, a.probes)?;

    let web = kids.spawn(
        inst,
        "web",
        &[
            "web",
            "--listen",
            "127.0.0.1:0",
            "--access",
            access_path.to_str().unwrap_or_default(),
            "--wait",
            "30s",
        ],
        Stdio::piped(),
    )?;
    let web_pid = web.id();
    let out = web.stdout.take().context("the web console's output")?;
    let mut line = String::new();
    BufReader::new(out).read_line(&mut line)?;
    let url = serde_json::from_str::<Value>(&line)
        .with_context(|| format!("muster web said {line:?}"))?["url"]
        .as_str()
        .context("muster web's url")?
        .to_string();

    // The clients, spread over processes.
    let started = Instant::now();
    let mut procs = Vec::new();
    let per = a.clients.div_ceil(a.procs);
    // Every process measures from the same moment: once all of them are in.
    let go = dir.join("go");
    for (k, chunk) in users.chunks(per).enumerate() {
        let tokens = dir.join(format!("tokens-{k}.json"));
        std::fs::write(&tokens, Value::Array(chunk.to_vec()).to_string())?;
        let mut cmd = Command::new(&a.python);
        cmd.arg(&script)
            .arg(&url)
            .arg(&tokens)
            .arg("--duration")
            .arg(a.duration.as_secs_f64().to_string())
            .arg("--go")
            .arg(&go);
        procs.push(LineChild::spawn(
            cmd,
            "the clients",
            "pip install websockets",
        )?);
    }
    let mut ready = Vec::new();
    for p in &procs {
        let r = p.expect("being ready", Duration::from_secs(180), |r| {
            r["event"] == "ready"
        })?;
        let failed = r["failed"].as_array().map_or(0, Vec::len);
        anyhow::ensure!(failed == 0, "clients failed to start: {}", r["failed"]);
        ready.push(r);
    }
    let setup_s = started.elapsed().as_secs_f64();
    // The window opens a second after the last client is in: the sign-in storm's last
    // sessions (first contacts, a system's first frames to new users) settle first, and
    // updates sent during it and taken after the window opened counted 0.1-0.3 s.
    std::thread::sleep(SETTLE);
    std::fs::write(&go, "")?;

    // While they watch: a shared-memory user on the same system, the broker's requests,
    // the web process's CPU.
    let stop = Arc::new(AtomicBool::new(false));
    let shm = {
        let inst = inst.clone();
        let stop = stop.clone();
        std::thread::spawn(move || -> anyhow::Result<Histogram<u64>> {
            let mut c = connect_when_listed(&inst, 1, Duration::from_secs(10))?;
            c.request(&ServiceId::new("bw", "s0"))?;
            let mut h = histogram();
            while !stop.load(Ordering::Acquire) {
                if let Some(UserEvent::Update { sent_ns, .. }) =
                    c.next_event(Instant::now() + Duration::from_millis(100))?
                {
                    h.saturating_record(monotonic_ns().saturating_sub(sent_ns) / 1000);
                }
            }
            c.close();
            Ok(h)
        })
    };
    let cpu0 = cpu_ticks(web_pid).unwrap_or(0);
    let t0 = Instant::now();
    let during = probe(&mut client, &probe_id, a.probes)?;
    let mut results = Vec::new();
    for p in &procs {
        let r = p.expect(
            "the window's figures",
            a.duration + Duration::from_secs(60),
            |r| r["event"] == "done",
        )?;
        results.push(r);
    }
    let window = t0.elapsed().as_secs_f64();
    let cpu = (cpu_ticks(web_pid).unwrap_or(0).saturating_sub(cpu0)) as f64
        / ticks_per_second() as f64
        / window;
    let (rss, pss) = (rss_kib(web_pid), pss_kib(web_pid));
    stop.store(true, Ordering::Release);
    let shm = shm
        .join()
        .map_err(|_| anyhow::anyhow!("the shm user panicked"))??;
    drop(procs);
    client.close();
    kids.stop();

    let mut web_h = histogram();
    let mut hub_h = histogram();
    let (mut updates, mut gaps, mut resyncs, mut errors) = (0u64, 0u64, 0u64, Vec::new());
    for r in &results {
        for l in r["latencies_us"].as_array().into_iter().flatten() {
            web_h.saturating_record(l.as_u64().unwrap_or(0));
        }
        for l in r["to_hub_us"].as_array().into_iter().flatten() {
            hub_h.saturating_record(l.as_u64().unwrap_or(0));
        }
        updates += r["updates"].as_u64().unwrap_or(0);
        gaps += r["gaps"].as_u64().unwrap_or(0);
        resyncs += r["resyncs"].as_u64().unwrap_or(0);
        errors.extend(r["errors"].as_array().into_iter().flatten().cloned());
    }
    let expected = (a.clients as f64 * 10.0 * a.duration.as_secs_f64()) as u64;
    let report = json!({
        "clients": a.clients,
        "procs": a.procs,
        "services": services,
        "window_s": a.duration.as_secs_f64(),
        "setup_s": setup_s,
        "web_update": summary(&web_h),
        "to_web_process": summary(&hub_h),
        "shm_update": summary(&shm),
        "ratio_p50": web_h.value_at_quantile(0.5) as f64 / shm.value_at_quantile(0.5).max(1) as f64,
        "updates": updates,
        "updates_expected": expected,
        "gaps": gaps,
        "resyncs": resyncs,
        "errors": errors,
        "web_cpu_cores": cpu,
        "web_rss_kib": rss,
        "web_pss_kib": pss,
        "broker_request_before": summary(&before),
        "broker_request_during": summary(&during),
    });
    if !a.json {
        println!(
            "{} WebSocket clients ({} processes) watching the list and one 10 Hz session each, {:.0} s (setup {:.1} s)",
            a.clients,
            a.procs,
            a.duration.as_secs_f64(),
            setup_s
        );
        println!("{}", header("send -> receive, µs"));
        println!("{}", row("web client (websockets)", &web_h));
        println!("{}", row("  of which up to muster web", &hub_h));
        println!("{}", row("shm user, same run", &shm));
        println!("{}", header("broker request -> grant, µs"));
        println!("{}", row("before the clients", &before));
        println!("{}", row("while they watch", &during));
        println!(
            "updates {updates} (expected about {expected}), sequence gaps {gaps}, resyncs {resyncs}, errors {}",
            errors.len()
        );
        println!(
            "web process: {:.2} cores, RSS {} MiB, PSS {} MiB",
            cpu,
            rss.unwrap_or(0) / 1024,
            pss.unwrap_or(0) / 1024
        );
    }
    Ok(report)
}
