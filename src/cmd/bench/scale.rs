//! `muster bench scale`: N separate user processes connected at once to a broker serving
//! S services. Reports setup time per user, shared memory, broker RSS and idle CPU,
//! per-user PSS, and request / list latency measured with everyone connected.

use super::children::Children;
use super::procfs;
use super::{header, row, summary};
use crate::cli::ScaleArgs;
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::types::ServiceId;
use muster_shared::Instance;
use muster_users::UserEvent;
use serde_json::json;
use std::io::{BufRead, BufReader};
use std::process::{ExitCode, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

fn histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 600_000_000, 3).expect("valid bounds")
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

pub fn run(inst: &Instance, a: ScaleArgs) -> anyhow::Result<ExitCode> {
    a.load.check(2)?;
    let shm_start = (procfs::shm_allocated_bytes(), procfs::shm_reserved_bytes());
    let mut children = Children::default();
    children.spawn(inst, "broker", &["broker"], Stdio::inherit())?;
    let broker_pid = children.pids().next().expect("broker");
    let mut system_pids = Vec::new();
    for i in 0..a.load.systems {
        let n = a.load.services_of(i);
        let name = format!("b{i}");
        let n = n.to_string();
        let args = [
            "system",
            "synthetic",
            "--name",
            &name,
            "--services",
            &n,
            "--quota",
            "10",
            "--rate",
            "10",
        ];
        system_pids.push(children.spawn(inst, &name, &args, Stdio::inherit())?.id());
    }
    let mut client =
        super::children::connect_when_listed(inst, a.load.services, Duration::from_secs(30))?;
    let shm_systems = (procfs::shm_allocated_bytes(), procfs::shm_reserved_bytes());

    // Users: each a separate process; setup = spawn until it has read the list.
    let (tx, rx) = mpsc::channel::<(usize, Result<(Duration, u64), String>)>();
    let mut user_pids = Vec::with_capacity(a.load.users);
    let all_start = Instant::now();
    for i in 0..a.load.users {
        let spawned = Instant::now();
        let child = children.spawn(
            inst,
            "user",
            &["user", "idle", "--wait", "60s"],
            Stdio::piped(),
        )?;
        user_pids.push(child.id());
        let stdout = child.stdout.take().context("user stdout")?;
        let tx = tx.clone();
        std::thread::spawn(move || {
            let mut lines = BufReader::new(stdout).lines();
            let first = match lines.next() {
                Some(Ok(l)) if l.contains("\"connected\":true") => {
                    let connect_us = serde_json::from_str::<serde_json::Value>(&l)
                        .ok()
                        .and_then(|v| v["connect_us"].as_u64())
                        .unwrap_or(0);
                    Ok((spawned.elapsed(), connect_us))
                }
                Some(Ok(l)) => Err(format!("unexpected first line {l}")),
                _ => Err("exited before connecting".to_string()),
            };
            let _ = tx.send((i, first));
            for _ in lines {} // keep the pipe open until the user exits
        });
    }
    drop(tx);
    let mut setup = histogram();
    let mut connect = histogram();
    let mut failures = Vec::new();
    for _ in 0..a.load.users {
        match rx.recv_timeout(Duration::from_secs(180)) {
            Ok((_, Ok((d, c)))) => {
                setup.record(d.as_micros().max(1) as u64)?;
                connect.record(c.max(1))?;
            }
            Ok((i, Err(e))) => failures.push(format!("user {i}: {e}")),
            Err(_) => {
                failures.push("timed out waiting for users".into());
                break;
            }
        }
    }
    let all_connected = all_start.elapsed();
    let shm_users = (procfs::shm_allocated_bytes(), procfs::shm_reserved_bytes());

    // Idle: everyone connected, nobody doing anything.
    let tps = procfs::ticks_per_second();
    let cpu0 = procfs::cpu_ticks(broker_pid).unwrap_or(0);
    let sys0: u64 = system_pids
        .iter()
        .filter_map(|p| procfs::cpu_ticks(*p))
        .sum();
    let users0: u64 = user_pids.iter().filter_map(|p| procfs::cpu_ticks(*p)).sum();
    std::thread::sleep(a.idle);
    let idle_s = a.idle.as_secs_f64();
    let pct = |ticks: u64| ticks as f64 / tps as f64 / idle_s * 100.0;
    let broker_cpu = pct(procfs::cpu_ticks(broker_pid)
        .unwrap_or(0)
        .saturating_sub(cpu0));
    let systems_cpu = pct(system_pids
        .iter()
        .filter_map(|p| procfs::cpu_ticks(*p))
        .sum::<u64>()
        .saturating_sub(sys0));
    let users_cpu = pct(user_pids
        .iter()
        .filter_map(|p| procfs::cpu_ticks(*p))
        .sum::<u64>()
        .saturating_sub(users0));
    let broker_rss = procfs::rss_kib(broker_pid).unwrap_or(0);
    let broker_pss = procfs::pss_kib(broker_pid).unwrap_or(0);
    let user_pss: Vec<u64> = user_pids
        .iter()
        .filter_map(|p| procfs::pss_kib(*p))
        .collect();
    let user_pss_mean = user_pss.iter().sum::<u64>() as f64 / user_pss.len().max(1) as f64;
    let user_pss_max = user_pss.iter().copied().max().unwrap_or(0);

    // Latency with everyone connected: list reads and request round trips.
    let mut list_read = histogram();
    for _ in 0..1000 {
        let t = Instant::now();
        let l = client.list()?;
        list_read.record(t.elapsed().as_micros().max(1) as u64)?;
        std::hint::black_box(l);
    }
    let ids: Vec<ServiceId> = client
        .list()?
        .views()
        .into_iter()
        .map(|v| ServiceId(v.id))
        .collect();
    // Requests interleaved with floor round trips, so both see the same conditions
    // (on a VM, waking an idle vCPU dominates both, and it varies over a run).
    let mut probe = super::floor::FloorProbe::start(inst)?;
    let mut floor = histogram();
    let mut request = histogram();
    let mut refused: std::collections::BTreeMap<&'static str, u64> = Default::default();
    for k in 0..a.requests {
        let id = &ids[k % ids.len()];
        floor.record(probe.round_trip()?.as_micros().max(1) as u64)?;
        let t = Instant::now();
        let req = client.request(id)?;
        let deadline = t + Duration::from_secs(10);
        loop {
            match client.next_event(deadline)? {
                Some(UserEvent::Granted {
                    req: r, session, ..
                }) if r == req => {
                    request.record(t.elapsed().as_micros().max(1) as u64)?;
                    client.end(session);
                    break;
                }
                Some(UserEvent::Refused { req: r, reason, .. }) if r == req => {
                    *refused.entry(reason.code()).or_default() += 1;
                    break;
                }
                Some(_) => {}
                None => bail!("request {req} unanswered within 10 s"),
            }
        }
    }
    client.close();
    probe.stop();
    let teardown = Instant::now();
    children.stop();
    let teardown = teardown.elapsed();

    let report = json!({
        "users": a.load.users,
        "services": a.load.services,
        "systems": a.load.systems,
        "connected": setup.len(),
        "failures": failures,
        "all_connected_s": all_connected.as_secs_f64(),
        "setup": summary(&setup),
        "connect": summary(&connect),
        "shm_allocated_mib": {"systems": mib(shm_systems.0 - shm_start.0.min(shm_systems.0)),
                               "users": mib(shm_users.0.saturating_sub(shm_systems.0)),
                               "per_user_kib": shm_users.0.saturating_sub(shm_systems.0) as f64 / 1024.0 / a.load.users.max(1) as f64},
        "shm_reserved_mib": {"systems": mib(shm_systems.1.saturating_sub(shm_start.1)),
                              "users": mib(shm_users.1.saturating_sub(shm_systems.1))},
        "broker": {"rss_kib": broker_rss, "pss_kib": broker_pss, "idle_cpu_percent": broker_cpu},
        "systems_idle_cpu_percent": systems_cpu,
        "users_idle_cpu_percent": users_cpu,
        "user_pss_kib": {"mean": user_pss_mean, "max": user_pss_max},
        "list_read": summary(&list_read),
        "service_request": summary(&request),
        "service_request_refused": refused,
        "floor": summary(&floor),
        "service_request_p50_over_floor_p50": request.value_at_quantile(0.5) as f64 / floor.value_at_quantile(0.5).max(1) as f64,
        "teardown_s": teardown.as_secs_f64(),
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "muster bench scale: {} user processes, {} services on {} systems",
            a.load.users, a.load.services, a.load.systems
        );
        println!(
            "connected {} of {} in {:.2} s ({} failures)",
            setup.len(),
            a.load.users,
            all_connected.as_secs_f64(),
            failures.len()
        );
        for f in failures.iter().take(5) {
            println!("  {f}");
        }
        println!("\n{}", header("latency (us)"));
        println!("{}", row("user spawn..list (queued)", &setup));
        println!("{}", row("user connect+list (in-proc)", &connect));
        println!("{}", row("list read (shared memory)", &list_read));
        println!("{}", row("service request (to grant)", &request));
        println!("{}", row("floor (raw 2-process trip)", &floor));
        println!(
            "service request p50 / floor p50 = {:.2} (the request crosses 3 processes, the floor 2)",
            request.value_at_quantile(0.5) as f64 / floor.value_at_quantile(0.5).max(1) as f64
        );
        if !refused.is_empty() {
            println!("refused requests: {refused:?}");
        }
        println!(
            "\nshared memory allocated: systems+broker {:.1} MiB, users {:.1} MiB ({:.0} KiB per user); reserved {:.1} MiB for users",
            mib(shm_systems.0.saturating_sub(shm_start.0)),
            mib(shm_users.0.saturating_sub(shm_systems.0)),
            shm_users.0.saturating_sub(shm_systems.0) as f64 / 1024.0 / a.load.users.max(1) as f64,
            mib(shm_users.1.saturating_sub(shm_systems.1)),
        );
        println!("broker: RSS {broker_rss} KiB, PSS {broker_pss} KiB, CPU while all idle {broker_cpu:.2} % over {:.0} s", idle_s);
        println!("systems CPU while idle {systems_cpu:.2} %, all users together {users_cpu:.2} %");
        println!("user PSS: mean {user_pss_mean:.0} KiB, max {user_pss_max} KiB");
        println!("teardown of all processes: {:.2} s", teardown.as_secs_f64());
    }
    Ok(if failures.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}
