//! `muster bench liveness`: how fast failures are seen and repaired, polling the
//! shared-memory list every millisecond.

use super::children::Children;
use super::{header, row, summary};
use crate::cli::LivenessArgs;
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient};
use serde_json::json;
use std::process::{ExitCode, Stdio};
use std::time::{Duration, Instant};

/// Polls the list until `pred` holds; returns how long it took.
fn until(
    client: &mut UserClient,
    timeout: Duration,
    pred: impl Fn(&[String]) -> bool,
) -> anyhow::Result<Duration> {
    let start = Instant::now();
    loop {
        let ids: Vec<String> = client.list()?.entries().iter().map(|e| e.id().0).collect();
        if pred(&ids) {
            return Ok(start.elapsed());
        }
        if start.elapsed() > timeout {
            bail!(
                "condition not met within {timeout:?} (list: {} services)",
                ids.len()
            );
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

pub fn run(inst: &Instance, a: LivenessArgs) -> anyhow::Result<ExitCode> {
    let mut children = Children::default();
    children.spawn(inst, "broker", &["broker"], Stdio::null())?;
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(20),
        handle_signals: false,
        watch_list: false,
    };
    let mut client = UserClient::connect(inst, &opts)?;
    let mut kill = Histogram::<u64>::new(3)?;
    for i in 0..a.trials {
        let name = format!("k{i}");
        children.spawn(
            inst,
            &name,
            &["system", "synthetic", "--name", &name],
            Stdio::null(),
        )?;
        let id = format!("{name}/s0");
        until(&mut client, Duration::from_secs(20), |l| l.contains(&id))?;
        let t = Instant::now();
        children.kill(&name);
        until(&mut client, Duration::from_secs(60), |l| !l.contains(&id))?;
        kill.record(t.elapsed().as_micros().max(1) as u64)?;
    }

    for i in 0..a.systems {
        let name = format!("r{i}");
        children.spawn(
            inst,
            &name,
            &["system", "synthetic", "--name", &name, "--services", "8"],
            Stdio::null(),
        )?;
    }
    let total = a.systems * 8;
    until(&mut client, Duration::from_secs(30), |l| l.len() == total)?;
    // Users holding data sessions through the restarts: each says hello to every new
    // broker.
    let mut held = 0;
    for i in 0..a.users {
        let svc = format!("r{}/s{}", i % a.systems.max(1), (i / a.systems.max(1)) % 8);
        let c = children.spawn(
            inst,
            &format!("hold-{i}"),
            &["bench", "failover-user", "--hold", &svc],
            Stdio::piped(),
        )?;
        let mut out = std::io::BufReader::new(c.stdout.take().context("holder stdout")?);
        let mut line = String::new();
        if std::io::BufRead::read_line(&mut out, &mut line)? > 0
            && line.contains("\"granted\":true")
        {
            held += 1;
        }
        // Keep reading its lines so its pipe never fills.
        std::thread::spawn(move || {
            let mut sink = String::new();
            while std::io::BufRead::read_line(&mut out, &mut sink).unwrap_or(0) > 0 {
                sink.clear();
            }
        });
    }
    if held < a.users {
        bail!("only {held} of {} users were granted a session", a.users);
    }
    let mut restart = Histogram::<u64>::new(3)?;
    let mut cleaned = Histogram::<u64>::new(3)?;
    let mut unsettled = 0usize;
    for _ in 0..a.trials {
        let killed = Instant::now();
        children.kill("broker");
        // The list stays readable while no broker runs; wait until systems noticed.
        std::thread::sleep(Duration::from_millis(200));
        let t = Instant::now();
        children.spawn(inst, "broker", &["broker"], Stdio::null())?;
        // Complete again: every service listed by the new broker.
        let epoch_before = client.list()?.epoch;
        loop {
            let l = client.list()?;
            if l.epoch != epoch_before && l.count() == total {
                break;
            }
            if t.elapsed() > Duration::from_secs(30) {
                bail!(
                    "the list was not complete within 30 s of the restart ({} of {total})",
                    l.count()
                );
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        restart.record(t.elapsed().as_micros().max(1) as u64)?;
        // Each restart from a settled host: the killed broker's cleanup (by the new
        // broker's `muster cleanup`, at niceness 19) over before the next kill, unless
        // --crash-loop. Its time is a figure of its own.
        if !a.crash_loop {
            let until = killed + Duration::from_secs(120);
            loop {
                if muster_shared::ipc::dead_nodes() == 0 {
                    cleaned.record(killed.elapsed().as_micros().max(1) as u64)?;
                    break;
                }
                if Instant::now() >= until {
                    unsettled += 1;
                    break;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    }
    client.close();
    children.stop();
    if a.json {
        println!(
            "{}",
            json!({"system_sigkill_to_unlisted": summary(&kill), "broker_restart_to_complete_list": summary(&restart),
                   "broker_sigkill_to_cleaned_up": summary(&cleaned), "not_cleaned_up_within_120s": unsettled,
                   "crash_loop": a.crash_loop, "services": total, "users_holding_sessions": a.users})
        );
    } else {
        println!("muster bench liveness: {} trials", a.trials);
        println!("{}", header("latency (us)"));
        println!("{}", row("system SIGKILL -> unlisted", &kill));
        println!(
            "{}",
            row(&format!("broker restart -> {total} listed"), &restart)
        );
        if !a.crash_loop {
            println!("{}", row("broker SIGKILL -> cleaned up", &cleaned));
        }
        println!(
            "(restart time counts from spawning the new broker process; {} users held sessions; {})",
            a.users,
            if a.crash_loop {
                "crash loop: each broker killed as soon as its list was complete".to_string()
            } else {
                format!("each kill after the last one was cleaned up; {unsettled} not within 120 s")
            }
        );
    }
    Ok(ExitCode::SUCCESS)
}
