//! `muster bench ros2`: the ROS 2 bridges against rclpy (ROS 2 Kilted's wheels, Fast
//! DDS) on this host, every stamp on CLOCK_MONOTONIC.
//!
//! 1. An rclpy publisher's `std_msgs/String` (stamped when published) through `muster
//!    system ros2` to a muster user (this process), one way, beside the same samples
//!    to an rclpy subscriber in the same run: the bridge's cost is the ratio of the
//!    medians.
//! 2. A muster user's goal (`goal2d`) to an rclpy subscriber of `geometry_msgs/PoseStamped`.
//! 3. `muster sim --ros2` with N wandering robots (laser 181 beams at 10 Hz, sonar,
//!    odometry) and one rclpy node subscribed to every robot's scan: the simulator's
//!    real-time factor (from `/clock`), scans received, and the simulator's CPU per robot.

use super::children::{connect_when_listed, request_granted, Children};
use super::{header, histogram, row, summary, LineChild};
use crate::cli::Ros2BenchArgs;
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{Payload, ServiceId};
use muster_shared::Instance;
use muster_users::UserEvent;
use serde_json::{json, Value};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const SCRIPT: &str = include_str!("../../../bridges/ros2/bench/rclpy_bench.py");

/// An rclpy process of the bench script.
type Py = LineChild;

/// Starts the bench script with `args` on ROS domain `domain`.
fn start_py(
    python: &str,
    script: &std::path::Path,
    domain: u16,
    args: &[&str],
) -> anyhow::Result<Py> {
    let mut cmd = Command::new(python);
    cmd.arg(script)
        .args(args)
        .env("ROS_DOMAIN_ID", domain.to_string());
    LineChild::spawn(cmd, "rclpy", "rclpy: see the README's ROS 2 section")
}

pub fn run(inst: &Instance, a: Ros2BenchArgs) -> anyhow::Result<std::process::ExitCode> {
    let dir = std::env::temp_dir().join(format!("muster-bench-ros2-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let script = dir.join("rclpy_bench.py");
    std::fs::write(&script, SCRIPT)?;
    let result = (|| -> anyhow::Result<Value> {
        let bridge = bridge_latency(inst, &a, &dir, &script)?;
        let sim = sim_scaling(inst, &a, &dir, &script)?;
        Ok(json!({"bridge": bridge, "sim": sim}))
    })();
    let _ = std::fs::remove_dir_all(&dir);
    let report = result?;
    if a.json {
        println!("{report}");
    }
    Ok(std::process::ExitCode::SUCCESS)
}

const CONFIG: &str = r#"
system = "bench"
namespace = "/bench"
watch = ["chatter"]

[[data]]
name = "chatter"
topic = "chatter"
type = "std_msgs/msg/String"
qos = { depth = 100 }

[[command]]
name = "goal"
payload = "goal2d"
"#;

fn bridge_latency(
    inst: &Instance,
    a: &Ros2BenchArgs,
    dir: &std::path::Path,
    script: &std::path::Path,
) -> anyhow::Result<Value> {
    let domain = a.domain;
    let config = dir.join("bench.toml");
    std::fs::write(&config, CONFIG)?;
    let mut kids = Children::default();
    kids.spawn(inst, "broker", &["broker"], Stdio::null())?;
    let ds = domain.to_string();
    kids.spawn(
        inst,
        "system ros2",
        &[
            "system",
            "ros2",
            "--config",
            config.to_str().unwrap_or_default(),
            "--domain",
            &ds,
        ],
        Stdio::null(),
    )?;
    let mut client = connect_when_listed(inst, 2, Duration::from_secs(30))?;
    let count = a.samples.to_string();
    let secs = (a.samples as f64 / a.rate + 30.0).to_string();
    let sub = start_py(
        &a.python,
        script,
        domain,
        &["sub", "/bench/chatter", &count, &secs],
    )?;
    sub.expect("subscriber", Duration::from_secs(30), |v| {
        v["event"] == "ready"
    })?;

    // 1. rclpy → muster user, beside rclpy → rclpy. The system withdraws the service
    // until the topic is heard: ask until it is granted.
    let rate = a.rate.to_string();
    let pubr = start_py(
        &a.python,
        script,
        domain,
        &["pub", "/bench/chatter", &rate, &count],
    )?;
    pubr.expect("publisher", Duration::from_secs(30), |v| {
        v["event"] == "ready"
    })?;
    let chatter = ServiceId::new("bench", "chatter");
    let deadline = Instant::now() + Duration::from_secs(30);
    let session = loop {
        let req = client.request(&chatter)?;
        let mut granted = None;
        while let Some(e) = client.next_event(Instant::now() + Duration::from_secs(5))? {
            match e {
                UserEvent::Granted {
                    req: r, session, ..
                } if r == req => {
                    granted = Some(session);
                    break;
                }
                UserEvent::Refused { req: r, .. } if r == req => break,
                _ => {}
            }
        }
        if let Some(s) = granted {
            break s;
        }
        anyhow::ensure!(Instant::now() < deadline, "bench/chatter was never granted");
        std::thread::sleep(Duration::from_millis(200));
    };
    let mut muster = histogram();
    let end = Instant::now() + Duration::from_secs_f64(a.samples as f64 / a.rate + 20.0);
    while (muster.len() as usize) < a.samples && Instant::now() < end {
        if let Some(UserEvent::Update {
            session: s,
            payload: Payload::Text(t),
            ..
        }) = client.next_event(end)?
        {
            let now = monotonic_ns();
            if s == session {
                // "-1 NS": the untimed keep-alive after the timed samples.
                let mut parts = t.split_whitespace();
                let timed = parts.next().is_some_and(|seq| seq != "-1");
                if let Some(sent) = parts
                    .next()
                    .and_then(|n| n.parse::<u64>().ok())
                    .filter(|_| timed)
                {
                    let _ = muster.record(now.saturating_sub(sent) / 1000);
                }
            }
        }
    }
    let mut rclpy = histogram();
    let lat = sub.expect("latencies", Duration::from_secs(30), |v| {
        v["latencies_us"].is_array()
    })?;
    for l in lat["latencies_us"].as_array().into_iter().flatten() {
        let _ = rclpy.record(l.as_f64().unwrap_or(0.0).max(1.0) as u64);
    }
    client.end(session);

    // 2. A muster user's goal → an rclpy subscriber of PoseStamped.
    let goals = start_py(
        &a.python,
        script,
        domain,
        &["goals", "/bench/goal_pose", "120"],
    )?;
    goals.expect("goal subscriber", Duration::from_secs(30), |v| {
        v["event"] == "ready"
    })?;
    let goal_session = request_granted(
        &mut client,
        &ServiceId::new("bench", "goal"),
        Duration::from_secs(30),
    )?;
    // Discovery between the system's writer and the new reader: send until one arrives.
    let mut sent = Vec::new();
    let warm_end = Instant::now() + Duration::from_secs(30);
    loop {
        client
            .input(goal_session, Payload::Goal2d { x: -1.0, y: 0.0 })
            .map_err(anyhow::Error::msg)?;
        if goals.json(Duration::from_millis(200)).is_some() || Instant::now() > warm_end {
            break;
        }
    }
    while goals.json(Duration::from_millis(100)).is_some() {}
    // One goal every 20 ms (a burst would time the subscriber's queue, not the path),
    // the user's own inbox drained in between (status lines come back).
    let start = Instant::now();
    for k in 0..a.goals {
        sent.push(monotonic_ns());
        let goal = Payload::Goal2d {
            x: k as f64,
            y: 0.0,
        };
        client
            .input(goal_session, goal)
            .map_err(anyhow::Error::msg)?;
        let next = start + Duration::from_millis(20) * (k as u32 + 1);
        while client.next_event(next)?.is_some() {}
    }
    let mut goal = histogram();
    let end = Instant::now() + Duration::from_secs(10);
    while (goal.len() as usize) < a.goals && Instant::now() < end {
        let Some(v) = goals.json(end.saturating_duration_since(Instant::now())) else {
            break;
        };
        if let (Some(x), Some(recv)) = (v["x"].as_f64(), v["recv_ns"].as_u64()) {
            if x >= 0.0 && (x as usize) < sent.len() {
                let _ = goal.record(recv.saturating_sub(sent[x as usize]) / 1000);
            }
        }
    }
    client.end(goal_session);
    client.close();
    drop(pubr);
    kids.stop();

    let ratio = muster.value_at_quantile(0.5) as f64 / rclpy.value_at_quantile(0.5).max(1) as f64;
    if !a.json {
        println!("muster bench ros2: rclpy (ROS 2 Kilted, Fast DDS) and muster on this host; one way, us");
        println!("{}", header("one way (us)"));
        println!("{}", row("rclpy pub -> rclpy sub", &rclpy));
        println!("{}", row("rclpy pub -> muster user", &muster));
        println!("{}", row("muster goal -> rclpy sub", &goal));
        println!("ratio (muster user p50 / rclpy sub p50): {ratio:.2} (goal: <= 1.5)");
    }
    Ok(
        json!({"rclpy_to_rclpy": summary(&rclpy), "rclpy_to_muster": summary(&muster),
              "muster_goal_to_rclpy": summary(&goal), "ratio": ratio,
              "samples": a.samples, "rate_hz": a.rate}),
    )
}

fn sim_scaling(
    inst: &Instance,
    a: &Ros2BenchArgs,
    dir: &std::path::Path,
    script: &std::path::Path,
) -> anyhow::Result<Value> {
    use muster_sim_world::map::OccupancyMap;
    let map = OccupancyMap::office();
    let mut rows = Vec::new();
    if !a.json && !a.robots.is_empty() {
        println!("muster sim --ros2: N wandering robots (laser 181 beams + 16 sonars, 10 Hz; odometry 20 Hz), one rclpy node on every scan");
        println!(
            "{:>7} {:>10} {:>16} {:>14} {:>16}",
            "robots", "rtf", "scans/robot/s", "sim CPU %", "CPU %/robot"
        );
    }
    for &n in &a.robots {
        anyhow::ensure!((1..=1000).contains(&n), "--robots: 1..=1000 each");
        let mut toml = String::from("seed = 1\n");
        for (k, (x, y)) in spots(&map, n)?.into_iter().enumerate() {
            toml.push_str(&format!(
                "\n[[robots]]\nname = \"R{k}\"\npose = [{x:.2}, {y:.2}, 0.0]\nlaser = {{}}\nsonar = {{}}\nwander = true\n"
            ));
        }
        let scenario = dir.join(format!("robots-{n}.toml"));
        std::fs::write(&scenario, toml)?;
        let domain = a.domain.wrapping_add(1).min(232);
        let ds = domain.to_string();
        let sim_inst = Instance::new(&format!("{}-sim{n}", inst.as_str()))?;
        let mut kids = Children::default();
        let sim = kids
            .spawn(
                &sim_inst,
                "sim",
                &[
                    "sim",
                    "--ros2",
                    "--domain",
                    &ds,
                    "--scenario",
                    scenario.to_str().unwrap_or_default(),
                ],
                Stdio::null(),
            )?
            .id();
        let pid = sim;
        let secs = a.window.as_secs_f64();
        let ns = n.to_string();
        let ws = secs.to_string();
        let sub = start_py(&a.python, script, domain, &["scans", &ns, &ws])?;
        sub.expect("scan subscriber", Duration::from_secs(30), |v| {
            v["event"] == "ready"
        })?;
        // The window starts when every robot's scans flow (discovery of N writers takes a
        // while); the CPU is taken over it.
        sub.expect("scans flowing", Duration::from_secs(90), |v| {
            v["event"] == "flowing"
        })?;
        let t0 = Instant::now();
        let c0 = super::procfs::cpu_ticks(pid);
        let v = sub.expect("scan figures", Duration::from_secs_f64(secs + 90.0), |v| {
            v["robots"].is_number()
        })?;
        let c1 = super::procfs::cpu_ticks(pid);
        let wall = t0.elapsed().as_secs_f64();
        kids.stop();
        let cpu = match (c0, c1) {
            (Some(c0), Some(c1)) => {
                Some((c1 - c0) as f64 / super::procfs::ticks_per_second() as f64 / wall * 100.0)
            }
            _ => None,
        };
        let rtf = v["realtime_factor"].as_f64();
        if !a.json {
            println!(
                "{n:>7} {:>10} {:>16.2} {:>14} {:>16}",
                rtf.map_or("-".into(), |r| format!("{r:.2}")),
                v["scans_per_robot_per_s"].as_f64().unwrap_or(0.0),
                cpu.map_or("-".into(), |c| format!("{c:.0}")),
                cpu.map_or("-".into(), |c| format!("{:.2}", c / n as f64)),
            );
        }
        rows.push(json!({"robots": n, "realtime_factor": rtf, "scans_per_robot_per_s": v["scans_per_robot_per_s"],
                         "robots_flowing": v["robots_flowing"], "sim_cpu_percent": cpu,
                         "cpu_percent_per_robot": cpu.map(|c| c / n as f64)}));
    }
    Ok(json!(rows))
}

/// `n` start places on `map` a metre apart and half a metre from walls, row by row.
fn spots(map: &muster_sim_world::map::OccupancyMap, n: usize) -> anyhow::Result<Vec<(f64, f64)>> {
    let (w, h) = map.size();
    let (ox, oy) = map.origin();
    let mut out = Vec::with_capacity(n);
    let mut y = oy + 1.0;
    while y < oy + h - 0.5 && out.len() < n {
        let mut x = ox + 1.0;
        while x < ox + w - 0.5 && out.len() < n {
            if map.clearance(x, y, 1.0) >= 0.5 {
                out.push((x, y));
            }
            x += 1.0;
        }
        y += 1.0;
    }
    anyhow::ensure!(
        out.len() == n,
        "the map has room for {} robots a metre apart, not {n}",
        out.len()
    );
    Ok(out)
}
