//! `muster bench vda5050`: a VDA 5050 fleet behind muster, under many users.
//!
//! Debian's mosquitto on a free loopback port; N virtual vehicles from vda-5050-lib
//! (`virtual_agv.js`, one process, state at least every second); a broker and `muster
//! system vda5050` (the bridge); N muster users (threads of this process, shared
//! memory), each holding one vehicle's command service and giving it a goal every few
//! seconds. Timed in the same run: the bridge's order → the vehicle's first state
//! showing it (the bridge's own clock), a raw MQTT publish → subscribe round trip
//! through the same mosquitto (the floor: the order's way has two such hops plus the
//! vehicle), the same order → state seen on the wire by a client one hop from both
//! (the vehicle's share), and each user's goal → the first status the vehicle's state
//! made; the CPU of mosquitto, the bridge, the vehicles' process and the broker.

use super::children::{connect_when_listed, free_tcp_port, request_granted, Children};
use super::procfs::{cpu_ticks, ticks_per_second};
use super::{header, histogram, row, summary, LineChild};
use crate::cli::Vda5050BenchArgs;
use anyhow::Context as _;
use hdrhistogram::Histogram;
use muster_shared::types::{Payload, ServiceId, TaskStatus};
use muster_shared::Instance;
use muster_users::UserEvent;
use muster_vda5050::mqtt::{Incoming, MqttConfig, MqttLink};
use rand::{RngExt, SeedableRng};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

/// Vehicles per bridge: one muster system offers 128 services, two per vehicle.
const PER_BRIDGE: usize = muster_shared::types::MAX_SERVICES_PER_SYSTEM / 2;

pub fn run(inst: &Instance, a: Vda5050BenchArgs) -> anyhow::Result<std::process::ExitCode> {
    anyhow::ensure!(a.vehicles > 0, "--vehicles must be > 0");
    anyhow::ensure!(!a.goal_every.is_zero(), "--goal-every must be > 0");
    let lib = a.peers.join("node_modules/vda-5050-lib");
    anyhow::ensure!(
        lib.exists(),
        "{} is missing: run `npm ci --prefix {}` (bash scripts/test does)",
        lib.display(),
        a.peers.display()
    );
    // A thread of this process per user: each holds an iceoryx2 node.
    let _ = muster_shared::reactor::raise_fd_limit();
    super::in_temp_dir("vda", a.json, |dir| bench(inst, &a, dir))
}

/// What one user measured: goal → first status from the vehicle's state (µs), goals
/// given, refusals.
struct UserFigures {
    to_vehicle: Histogram<u64>,
    goals: u64,
    refused: u64,
}

fn user(
    inst: &Instance,
    services: usize,
    vehicle: usize,
    users: usize,
    goal_every: Duration,
    start: &Barrier,
    stop: &AtomicBool,
) -> anyhow::Result<UserFigures> {
    let mut c = connect_when_listed(inst, services, Duration::from_secs(60))?;
    let (group, serial) = ((vehicle - 1) / PER_BRIDGE, (vehicle - 1) % PER_BRIDGE + 1);
    let id = ServiceId::new(&format!("vda{group}"), &format!("agv{serial}"));
    let session = request_granted(&mut c, &id, Duration::from_secs(30));
    start.wait();
    let session = session?;
    // Users spread over the period, not all at once.
    std::thread::sleep(goal_every.mul_f64(vehicle as f64 / users as f64));
    let mut rng = rand_pcg::Pcg64::seed_from_u64(vehicle as u64);
    let mut f = UserFigures {
        to_vehicle: histogram(),
        goals: 0,
        refused: 0,
    };
    while !stop.load(Ordering::Acquire) {
        let (x, y) = (rng.random_range(1.0..9.0), rng.random_range(1.0..9.0));
        let t0 = Instant::now();
        c.input(session, Payload::Goal2d { x, y })
            .map_err(|e| anyhow::anyhow!(e))?;
        f.goals += 1;
        let next = t0 + goal_every;
        let mut timed = false;
        while let Some(e) = c.next_event(next)? {
            if let UserEvent::Status {
                session: s, status, ..
            } = e
            {
                if s != session || timed {
                    continue;
                }
                match &status {
                    // The bridge's own word that it sent the order.
                    TaskStatus::Working(d) if d.starts_with("order ") => {}
                    TaskStatus::Rejected(_) => {
                        f.refused += 1;
                        timed = true;
                    }
                    // Anything else comes from the vehicle's state.
                    TaskStatus::Working(_) | TaskStatus::Done(_) => {
                        f.to_vehicle
                            .saturating_record(t0.elapsed().as_micros() as u64);
                        timed = true;
                    }
                    TaskStatus::Idle => {}
                }
            }
        }
    }
    c.end(session);
    c.close();
    Ok(f)
}

/// On the wire, seen from one MQTT client of this process: raw publish → subscribe
/// round trips through the broker at `mqtt` (`n` spread over `window`), and each order
/// on interface `iface` → the vehicle's first state showing it (the vehicle's share of
/// the bridge's order → state time, both one hop from here).
fn on_the_wire(
    mqtt: &str,
    iface: &str,
    n: usize,
    window: Duration,
) -> anyhow::Result<(Histogram<u64>, Histogram<u64>)> {
    let topic = format!("muster-bench-rtt/{}", std::process::id());
    let mut link = MqttLink::connect(&MqttConfig {
        broker: mqtt.to_string(),
        security: Default::default(),
        client_id: format!("muster-bench-rtt-{}", std::process::id()),
        keep_alive: Duration::from_secs(5),
        subscriptions: vec![
            topic.clone(),
            format!("{iface}/v2/+/+/order"),
            format!("{iface}/v2/+/+/state"),
        ],
        will: None,
    })?;
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        match link.wait(deadline.saturating_duration_since(Instant::now())) {
            Some(Incoming::Connected) => break,
            Some(_) => {}
            None => anyhow::bail!("the MQTT broker did not answer within 10 s"),
        }
    }
    let (mut rtt, mut vehicle) = (histogram(), histogram());
    // Orders seen, by (serial, orderId, orderUpdateId).
    let mut orders: std::collections::HashMap<(String, String, u64), Instant> = Default::default();
    let gap = window / n.max(1) as u32;
    let end = Instant::now() + window;
    // The n round trips spread over the window (a last one may end just after it).
    let last_send = end + Duration::from_secs(5);
    let (mut seq, mut sent_at, mut next_send) = (0u64, None::<Instant>, Instant::now());
    // The first round trip only proves the subscription is in.
    let (mut warmed, mut taken) = (false, 0usize);
    while Instant::now() < end || (taken < n && Instant::now() < last_send) {
        if sent_at.is_none() && Instant::now() >= next_send && taken < n {
            seq += 1;
            let t0 = Instant::now();
            link.publish(&topic, seq.to_string().into_bytes(), false)
                .map_err(|e| anyhow::anyhow!(e))?;
            sent_at = Some(t0);
            next_send = t0 + if warmed { gap } else { Duration::ZERO };
        }
        let horizon = if taken < n { last_send } else { end };
        let wake = if sent_at.is_some() || taken >= n {
            horizon
        } else {
            next_send.min(horizon)
        };
        let Some(m) = link.wait(wake.saturating_duration_since(Instant::now())) else {
            continue;
        };
        let Incoming::Publish {
            topic: t, payload, ..
        } = m
        else {
            continue;
        };
        if t == topic {
            if let Some(t0) = sent_at.filter(|_| payload == seq.to_string().as_bytes()) {
                if warmed {
                    rtt.saturating_record(t0.elapsed().as_micros() as u64);
                    taken += 1;
                }
                warmed = true;
                sent_at = None;
            }
            continue;
        }
        let Ok(j) = serde_json::from_slice::<Value>(&payload) else {
            continue;
        };
        let key = (
            j["serialNumber"].as_str().unwrap_or_default().to_string(),
            j["orderId"].as_str().unwrap_or_default().to_string(),
            j["orderUpdateId"].as_u64().unwrap_or(0),
        );
        if t.ends_with("/order") {
            orders.insert(key, Instant::now());
        } else if let Some(t0) = orders.remove(&key) {
            vehicle.saturating_record(t0.elapsed().as_micros() as u64);
        }
    }
    link.close();
    Ok((rtt, vehicle))
}

fn bench(inst: &Instance, a: &Vda5050BenchArgs, dir: &std::path::Path) -> anyhow::Result<Value> {
    let port = free_tcp_port()?;
    let mqtt = format!("127.0.0.1:{port}");
    let conf = dir.join("mosquitto.conf");
    std::fs::write(
        &conf,
        format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n\
             max_queued_messages 10000\nlog_dest none\nset_tcp_nodelay true\n"
        ),
    )?;
    let mut mosq_cmd = Command::new(&a.mosquitto);
    mosq_cmd.arg("-c").arg(&conf);
    let mosquitto = LineChild::spawn(mosq_cmd, "mosquitto", "apt-get install mosquitto")?;
    let deadline = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect(&mqtt).is_err() {
        anyhow::ensure!(
            Instant::now() < deadline,
            "mosquitto did not listen on {mqtt}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let iface = format!("bench{}", std::process::id());

    // A manufacturer, a process of virtual vehicles and a bridge per 64 vehicles.
    let groups = a.vehicles.div_ceil(PER_BRIDGE);
    let mut fleets = Vec::new();
    for k in 0..groups {
        let count = PER_BRIDGE.min(a.vehicles - k * PER_BRIDGE);
        let mut node = Command::new("node");
        node.current_dir(&a.peers).arg("virtual_agv.js").args([
            "--broker",
            &format!("mqtt://{mqtt}"),
            "--interface",
            &iface,
            "--manufacturer",
            &format!("m{k}"),
            "--count",
            &count.to_string(),
            "--state-every-ms",
            "1000",
        ]);
        fleets.push(LineChild::spawn(
            node,
            "the virtual vehicles",
            "npm ci in --peers",
        )?);
    }
    for f in &fleets {
        f.expect("being ready", Duration::from_secs(120), |v| {
            v["event"] == "ready"
        })?;
    }

    let mut kids = Children::default();
    let room = (a.vehicles + 16).to_string();
    kids.spawn(
        inst,
        "broker",
        &["broker", "--max-users-per-process", &room],
        Stdio::null(),
    )?;
    let mut bridges = Vec::new();
    for k in 0..groups {
        let (name, manufacturer) = (format!("vda{k}"), format!("m{k}"));
        let label = format!("bridge {k}");
        let bridge = kids.spawn(
            inst,
            &label,
            &[
                "system",
                "vda5050",
                "--mqtt",
                &mqtt,
                "--interface",
                &iface,
                "--vda-version",
                "2.0.0",
                "--name",
                &name,
                "--manufacturer",
                &manufacturer,
                "--stats-json",
                "--wait",
                "5s",
            ],
            Stdio::piped(),
        )?;
        let out = bridge.stdout.take().context("the bridge's output")?;
        bridges.push((label, bridge.id(), out));
    }
    let services = 2 * a.vehicles;

    let started = Instant::now();
    let stop = Arc::new(AtomicBool::new(false));
    let start = Arc::new(Barrier::new(a.vehicles + 1));
    let mut users = Vec::new();
    for i in 1..=a.vehicles {
        let (inst, stop, start) = (inst.clone(), stop.clone(), start.clone());
        let (every, n) = (a.goal_every, a.vehicles);
        users.push(std::thread::spawn(move || {
            user(&inst, services, i, n, every, &start, &stop)
        }));
    }
    start.wait();
    let setup_s = started.elapsed().as_secs_f64();

    let pids: Vec<(&str, Vec<u32>)> = vec![
        ("mosquitto", vec![mosquitto.id()]),
        ("bridges", bridges.iter().map(|b| b.1).collect()),
        (
            "vehicles (node)",
            fleets.iter().map(LineChild::id).collect(),
        ),
        ("broker", kids.pids().next().into_iter().collect()),
    ];
    let ticks = |ps: &[u32]| -> u64 { ps.iter().map(|p| cpu_ticks(*p).unwrap_or(0)).sum() };
    let cpu0: Vec<u64> = pids.iter().map(|(_, p)| ticks(p)).collect();
    let t0 = Instant::now();
    let (rtt, in_vehicle) = on_the_wire(&mqtt, &iface, a.round_trips, a.duration)?;
    std::thread::sleep(a.duration.saturating_sub(t0.elapsed()));
    let window = t0.elapsed().as_secs_f64();
    let cpu: Vec<(&str, f64)> = pids
        .iter()
        .zip(&cpu0)
        .map(|((name, p), c0)| {
            let used = ticks(p).saturating_sub(*c0);
            (*name, used as f64 / ticks_per_second() as f64 / window)
        })
        .collect();
    stop.store(true, Ordering::Release);
    let mut to_vehicle = histogram();
    let (mut goals, mut refused, mut failed) = (0u64, 0u64, Vec::new());
    for u in users {
        match u.join() {
            Ok(Ok(f)) => {
                to_vehicle.add(&f.to_vehicle).ok();
                goals += f.goals;
                refused += f.refused;
            }
            Ok(Err(e)) => failed.push(e.to_string()),
            Err(_) => failed.push("a user thread panicked".into()),
        }
    }
    // The bridges' own figures, printed when they stop.
    let mut acks = histogram();
    let (mut orders, mut invalid) = (0u64, 0u64);
    for (label, _, out) in bridges {
        kids.stop_one(&label);
        let mut line = String::new();
        BufReader::new(out).read_line(&mut line)?;
        let stats: Value =
            serde_json::from_str(&line).with_context(|| format!("{label} said {line:?}"))?;
        for us in stats["order_ack_us"].as_array().into_iter().flatten() {
            acks.saturating_record(us.as_u64().unwrap_or(0));
        }
        orders += stats["orders"].as_u64().unwrap_or(0);
        invalid += stats["invalid"].as_u64().unwrap_or(0);
    }
    kids.stop();
    drop(fleets);
    drop(mosquitto);
    anyhow::ensure!(failed.is_empty(), "users failed: {failed:?}");

    let ratio = acks.value_at_quantile(0.5) as f64 / rtt.value_at_quantile(0.5).max(1) as f64;
    let report = json!({
        "vehicles": a.vehicles,
        "window_s": window,
        "setup_s": setup_s,
        "bridges": groups,
        "order_to_state": summary(&acks),
        "mqtt_round_trip": summary(&rtt),
        "order_to_state_on_the_wire": summary(&in_vehicle),
        "ratio_p50": ratio,
        "goal_to_vehicle_status": summary(&to_vehicle),
        "goals": goals,
        "refused": refused,
        "orders": orders,
        "invalid": invalid,
        "cpu_cores": cpu.iter().map(|(n, c)| (n.to_string(), json!(c))).collect::<serde_json::Map<_, _>>(),
    });
    if !a.json {
        println!(
            "{} virtual vehicles (vda-5050-lib, state every 1 s) behind muster system vda5050, {} users giving goals every {:.1} s, {:.0} s (setup {:.1} s)",
            a.vehicles,
            a.vehicles,
            a.goal_every.as_secs_f64(),
            window,
            setup_s
        );
        println!("{}", header("µs"));
        println!("{}", row("order -> state (bridge clock)", &acks));
        println!("{}", row("raw MQTT publish -> subscribe", &rtt));
        println!("{}", row("order -> state, on the wire", &in_vehicle));
        println!("{}", row("user goal -> vehicle's status", &to_vehicle));
        println!("order -> state p50 / raw round trip p50: {ratio:.1}x");
        println!("goals {goals}, refused {refused}, orders {orders}, invalid messages {invalid}, bridges {groups}");
        let cpu_line: Vec<String> = cpu.iter().map(|(n, c)| format!("{n} {c:.2}")).collect();
        println!("CPU, cores: {}", cpu_line.join(", "));
    }
    Ok(report)
}
