//! ROS 2, tested against nodes nobody here wrote: rclpy (ROS 2 Kilted's wheels, in the
//! venv `.ci/run` makes) and Fast DDS, talking to muster's pure-Rust DDS. Each test runs
//! on a ROS domain of its own.

#![allow(clippy::unwrap_used)]

mod common;

use common::Fed;
use serde_json::Value;
use std::path::Path;
use std::process::Command;

const SEC: std::time::Duration = std::time::Duration::from_secs(1);

/// A ROS domain for test `k` of this process, away from 0 (where a developer's own ROS
/// may run) and from other test processes' as far as the pid spreads them.
fn domain(k: u32) -> u16 {
    (10 + (std::process::id() * 3 + k) % 200) as u16
}

/// An rclpy interpreter (the venv's), or `None` (skipped) outside CI.
fn rclpy() -> Option<String> {
    common::python_with("rclpy", "ros-kilted-rclpy")
}

/// A 24 m × 8 m room (0.05 m cells; walls one cell thick along the edges) with one
/// robot `R1` at (3, 4) facing +x, its laser and sonar noiseless, and one person walking
/// behind it (never in the laser's half-plane).
fn room(dir: &Path) -> std::path::PathBuf {
    let (w, h) = (480usize, 160usize);
    let mut pgm = format!("P5\n{w} {h}\n255\n").into_bytes();
    for row in 0..h {
        for col in 0..w {
            let wall = row == 0 || col == 0 || row == h - 1 || col == w - 1;
            pgm.push(if wall { 0 } else { 254 });
        }
    }
    std::fs::write(dir.join("room.pgm"), pgm).unwrap();
    std::fs::write(
        dir.join("room.yaml"),
        "image: room.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
    )
    .unwrap();
    let scenario = dir.join("room.toml");
    std::fs::write(
        &scenario,
        r#"map = "room.yaml"
seed = 7

[[robots]]
name = "R1"
pose = [3.0, 4.0, 0.0]
laser = { noise = 0.0 }
sonar = { noise = 0.0 }

[[people]]
name = "alice"
beacon = "red"
start = [1.0, 1.0]

[[places]]
name = "a"
at = [1.0, 1.0]

[[places]]
name = "b"
at = [1.5, 7.0]
"#,
    )
    .unwrap();
    scenario
}

fn f(v: &Value, k: &str) -> f64 {
    v[k].as_f64()
        .unwrap_or_else(|| panic!("{k} missing in {v}"))
}

#[test]
fn the_simulators_robots_appear_in_ros2() {
    let Some(python) = rclpy() else { return };
    let dir = std::env::temp_dir().join(format!("muster-ros2-sim-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scenario = room(&dir);
    let d = domain(0);
    let mut fed = Fed::new("ros2sim");
    let ds = d.to_string();
    fed.spawn(&[
        "sim",
        "--scenario",
        scenario.to_str().unwrap(),
        "--speed",
        "4",
        "--ros2",
        "--domain",
        &ds,
    ]);
    let out = Command::new(&python)
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/ros2/sim_check.py"
        ))
        .arg("R1")
        .env("ROS_DOMAIN_ID", &ds)
        .env(FASTDDS_TRANSPORT.0, FASTDDS_TRANSPORT.1)
        .output()
        .expect("run rclpy");
    fed.shutdown();
    let _ = std::fs::remove_dir_all(&dir);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "rclpy check failed: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"));
    assert_eq!(v["all_seen"], true, "topics not seen: {}", v["missing"]);

    // The scan: 181 beams over 180°, counter-clockwise, in R1's laser frame, with sim
    // stamps; ranges against the room's geometry (walls 3.95 m to either side, the far
    // wall 20.95 m ahead: beyond the 8 m range, so no return, +inf).
    let scan = &v["scan"];
    assert_eq!(scan["frame_id"], "R1/laser");
    assert_eq!(scan["n"], 181);
    assert!(
        (f(scan, "angle_min") + std::f64::consts::FRAC_PI_2).abs() < 1e-5,
        "{scan}"
    );
    assert!(
        (f(scan, "angle_max") - std::f64::consts::FRAC_PI_2).abs() < 1e-5,
        "{scan}"
    );
    assert!(
        (f(scan, "angle_increment") - 1f64.to_radians()).abs() < 1e-6,
        "{scan}"
    );
    assert_eq!(f(scan, "range_min"), 0.0);
    assert_eq!(f(scan, "range_max"), 8.0);
    assert!((f(scan, "scan_time") - 0.1).abs() < 1e-6);
    assert_eq!(scan["stamps_increase"], true);
    let ranges = scan["ranges"].as_array().unwrap();
    let mut infinite = 0;
    for (k, r) in ranges.iter().enumerate() {
        let a = (-90.0 + k as f64).to_radians();
        let side = 3.95 / a.sin().abs();
        if (side - 8.0).abs() < 0.3 {
            continue; // at the range's edge either answer is right
        }
        if side < 8.0 {
            let got = r
                .as_f64()
                .unwrap_or_else(|| panic!("beam {k}: {r}, expected {side:.3}"));
            assert!(
                (got - side).abs() < 0.08,
                "beam {k}: {got}, expected {side:.3}"
            );
        } else {
            assert_eq!(r, "inf", "beam {k}: no wall within 8 m");
            infinite += 1;
        }
    }
    assert!(infinite > 40, "{infinite} beams with no return");

    // Odometry and ground truth: R1's frames, at (3, 4) heading 0 before it moves.
    let odom = &v["odom"];
    assert_eq!(odom["frame_id"], "R1/odom");
    assert_eq!(odom["child_frame_id"], "R1/base_link");
    assert_eq!(v["truth"]["frame_id"], "map");
    let drive = &v["drive"];
    assert!((f(drive, "before") - 3.0).abs() < 1e-6, "{drive}");
    assert!((f(&v["truth"], "y") - 4.0).abs() < 1e-6);

    // cmd_vel drives it (0.5 m/s for 1.5 s of wall time at 4x: at least a metre), and
    // when commands stop it stops (the drive's 0.5 s command timeout).
    let moved = f(drive, "stopped_at") - f(drive, "before");
    assert!(moved > 1.0 && moved < 3.5, "moved {moved} m: {drive}");
    assert!(
        (f(drive, "later") - f(drive, "stopped_at")).abs() < 1e-3,
        "still moving: {drive}"
    );
    assert!(f(drive, "twist_after_stop").abs() < 1e-3, "{drive}");

    // /clock is sim time, and an rclpy node with use_sim_time follows it.
    assert_eq!(v["clock_increases"], true);
    assert!(f(&v, "clock") > 1.0);
    assert!(
        (f(&v, "node_clock") - f(&v, "clock_at_node_clock")).abs() < 0.5,
        "{v}"
    );

    // /map (transient-local: this subscriber came after it was sent).
    let map = &v["map"];
    assert_eq!(map["frame_id"], "map");
    assert_eq!(
        (map["width"].as_u64(), map["height"].as_u64()),
        (Some(480), Some(160))
    );
    assert!((f(map, "resolution") - 0.05).abs() < 1e-6);
    assert_eq!(map["occupied"], 2 * 480 + 2 * 158);
    assert_eq!(map["free"], 478 * 158);
    assert_eq!(
        (map["corner"].as_i64(), map["centre"].as_i64()),
        (Some(100), Some(0))
    );

    // People: alice, a red cylinder and her name, in the map frame.
    let people = v["people"].as_array().unwrap();
    assert_eq!(people.len(), 2, "{people:?}");
    assert_eq!(people[0]["ns"], "people");
    assert_eq!(people[0]["type"], 3);
    assert_eq!(people[0]["frame_id"], "map");
    assert!(
        f(&people[0], "x") < 2.5,
        "alice stays behind R1: {people:?}"
    );
    assert_eq!(people[1]["text"], "alice");
    let rgba: Vec<f64> = people[0]["rgba"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_f64().unwrap())
        .collect();
    assert!(
        rgba[0] > 0.5 && rgba[1] < 0.5 && rgba[2] < 0.5 && rgba[3] == 1.0,
        "{rgba:?}"
    );

    // Sonar: the Pioneer ring, one frame per transducer.
    let sonar = &v["sonar"];
    let frames: Vec<&str> = sonar["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    assert_eq!(frames.len(), 16);
    assert!(frames.contains(&"R1/sonar_0") && frames.contains(&"R1/sonar_15"));
    assert_eq!(sonar["radiation_type"], 0);
    assert_eq!(f(sonar, "max_range"), 5.0);

    // The graph as ROS tools see it: every topic with its type, and the node.
    let topics = &v["topics"];
    for (name, ty) in [
        ("/R1/scan", "sensor_msgs/msg/LaserScan"),
        ("/R1/odom", "nav_msgs/msg/Odometry"),
        ("/R1/ground_truth", "nav_msgs/msg/Odometry"),
        ("/R1/sonar", "sensor_msgs/msg/Range"),
        ("/R1/cmd_vel", "geometry_msgs/msg/Twist"),
        ("/clock", "rosgraph_msgs/msg/Clock"),
        ("/map", "nav_msgs/msg/OccupancyGrid"),
        ("/people", "visualization_msgs/msg/MarkerArray"),
        ("/tf", "tf2_msgs/msg/TFMessage"),
        ("/tf_static", "tf2_msgs/msg/TFMessage"),
    ] {
        assert_eq!(topics[name], serde_json::json!([ty]), "{name} in {topics}");
    }
    assert!(
        v["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|n| n == "muster_sim"),
        "nodes: {}",
        v["nodes"]
    );
}

/// Fast DDS (rclpy's middleware) over UDP only: its shared-memory transport leaves
/// segments in /dev/shm when a node is killed, and the tests leave nothing behind.
const FASTDDS_TRANSPORT: (&str, &str) = ("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4");

/// The rclpy robot (tests/ros2/robot.py) in `namespace`, starting at `start`.
fn robot(python: &str, domain: u16, namespace: &str, start: &str, extra: &[&str]) -> Command {
    let mut c = Command::new(python);
    c.arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/ros2/robot.py"))
        .args([namespace, start])
        .args(extra)
        .env("ROS_DOMAIN_ID", domain.to_string())
        .env(FASTDDS_TRANSPORT.0, FASTDDS_TRANSPORT.1);
    c
}

/// The services of the README's example.
const TURTLE_SERVICES: [&str; 8] = [
    "turtle/pose",
    "turtle/say",
    "turtle/status",
    "turtle/goal",
    "turtle/drive",
    "turtle/scan",
    "turtle/odom",
    "turtle/relay",
];

/// The README's example config (`docs/ros2/turtle.toml`).
const TURTLE: &str = include_str!("../docs/ros2/turtle.toml");

/// Reads a process's JSON lines until `pred` holds for one (returned), or panics.
fn until(
    p: &common::Proc,
    what: &str,
    timeout: std::time::Duration,
    mut pred: impl FnMut(&Value) -> bool,
) -> Value {
    let end = std::time::Instant::now() + timeout;
    let mut seen = Vec::new();
    loop {
        let left = end.saturating_duration_since(std::time::Instant::now());
        match p.line(left) {
            Some(l) => {
                if let Ok(v) = serde_json::from_str::<Value>(&l) {
                    if pred(&v) {
                        return v;
                    }
                }
                seen.push(l);
            }
            None => panic!("{what}: not seen within {timeout:?}; saw {seen:?}"),
        }
    }
}

/// Stops robot system `proc` (SIGTERM) and returns what its `--stats-json` printed:
/// grants, localization error per robot and the system's own figures.
fn stats_on_stop(fed: &mut Fed, proc: usize) -> Value {
    fed.proc(proc).signal(libc::SIGTERM);
    until(fed.proc(proc), "the system's stats", 20 * SEC, |v| {
        v["localization"].is_object()
    })
}

/// `muster user request ID --duration D --json`, which must succeed: its output.
fn request_json(fed: &Fed, id: &str, duration: &str) -> String {
    let (code, out) = fed.run(
        &["user", "request", id, "--duration", duration, "--json"],
        30 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    out
}

fn row<'a>(list: &'a [Value], id: &str) -> &'a Value {
    common::find(list, id).unwrap_or_else(|| panic!("{id} not listed: {list:?}"))
}

#[test]
fn a_ros2_robot_becomes_a_muster_system() {
    use std::time::Instant;
    let Some(python) = rclpy() else { return };
    let d = domain(1);
    let dir = std::env::temp_dir().join(format!("muster-ros2-robot-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("turtle.toml");
    std::fs::write(&config, TURTLE).unwrap();
    let mut fed = Fed::new("ros2sys");
    fed.broker(&[]);
    let bot = fed.spawn_command(robot(&python, d, "/turtle", "1,2", &[]));
    until(fed.proc(bot), "the robot up", 20 * SEC, |v| {
        v["event"] == "up"
    });
    let ds = d.to_string();
    fed.spawn(&[
        "system",
        "ros2",
        "--config",
        config.to_str().unwrap(),
        "--domain",
        &ds,
    ]);

    // Listed as the file says, and offered once the robot's topics are heard.
    let (list, _) = fed.wait_list(30 * SEC, |l| {
        TURTLE_SERVICES
            .iter()
            .all(|id| common::find(l, id).is_some_and(|r| r["withdrawn"] == false))
    });
    let kinds = |id: &str| {
        let r = row(&list, id);
        (
            r["kind"].as_str().unwrap().to_string(),
            r["payload"].as_str().unwrap().to_string(),
            r["quota"].as_u64(),
        )
    };
    assert_eq!(
        kinds("turtle/pose"),
        ("data".into(), "pose2d".into(), Some(10))
    );
    assert_eq!(kinds("turtle/say"), ("data".into(), "text".into(), Some(3)));
    assert_eq!(
        kinds("turtle/goal"),
        ("command".into(), "goal2d".into(), Some(1))
    );
    assert_eq!(
        kinds("turtle/drive"),
        ("command".into(), "twist".into(), Some(1))
    );
    assert_eq!(row(&list, "turtle/goal")["queue"], true);

    // A muster user streams the robot's pose (it stands at (1, 2)) and its chatter.
    let out = request_json(&fed, "turtle/pose", "2s");
    let poses: Vec<Value> = out
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["payload"]["type"] == "pose2d")
        .collect();
    assert!(
        poses.len() >= 10,
        "{} poses in 2 s at 20 Hz: {out}",
        poses.len()
    );
    for p in &poses {
        assert!(
            (f(&p["payload"], "x") - 1.0).abs() < 1e-9
                && (f(&p["payload"], "y") - 2.0).abs() < 1e-9,
            "{p}"
        );
    }
    let out = request_json(&fed, "turtle/say", "2s");
    assert!(
        out.lines().any(|l| l.contains("\"text\":\"hello ")),
        "{out}"
    );
    // A transient-local topic the robot sent once, long before this user came: latched,
    // so the user gets it with its grant (update 0), and nothing after.
    let out = request_json(&fed, "turtle/status", "1s");
    let updates: Vec<(u64, Value)> = out
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter_map(|v| Some((v["seq"].as_u64()?, v["payload"].clone())))
        .collect();
    assert_eq!(
        updates,
        vec![(0, serde_json::json!({"type": "text", "text": "ready"}))],
        "{out}"
    );

    // Open payloads: the robot's LaserScan and its whole Odometry, types muster has no
    // payload of its own for, listed with their encoding, decoded for the user by the
    // definition that came with the grant.
    assert_eq!(
        row(&list, "turtle/scan")["payload"],
        "sensor_msgs/msg/LaserScan"
    );
    assert_eq!(row(&list, "turtle/scan")["encoding"], "cdr");
    assert_eq!(
        row(&list, "turtle/odom")["payload"],
        "nav_msgs/msg/Odometry"
    );
    assert_eq!(row(&list, "turtle/pose")["encoding"], "");
    let out = request_json(&fed, "turtle/scan", "2s");
    let lines: Vec<Value> = out
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    assert_eq!(lines[0]["payload"], "sensor_msgs/msg/LaserScan", "{out}");
    let scans: Vec<&Value> = lines.iter().filter(|v| v["payload"].is_object()).collect();
    assert!(scans.len() >= 2, "{out}");
    for s in &scans {
        let p = &s["payload"];
        assert_eq!(p["type"], "sensor_msgs/msg/LaserScan");
        assert_eq!(p["encoding"], "cdr");
        let v = &p["value"];
        assert_eq!(v["header"]["frame_id"], "laser", "{p}");
        assert_eq!(v["header"]["stamp"]["sec"], 7);
        assert_eq!(v["angle_min"], -0.75);
        assert_eq!(v["range_max"], 8.0);
        assert_eq!(v["ranges"], serde_json::json!([1.0, 2.0, "inf", 4.5]));
        assert_eq!(v["intensities"], serde_json::json!([]));
    }
    let out = request_json(&fed, "turtle/odom", "1s");
    let odom: Value = out
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .find(|v| v["payload"].is_object())
        .unwrap_or_else(|| panic!("no odometry: {out}"));
    let v = &odom["payload"]["value"];
    assert_eq!(v["header"]["frame_id"], "odom");
    assert_eq!(v["child_frame_id"], "base_link");
    let position = &v["pose"]["pose"]["position"];
    assert_eq!((f(position, "x"), f(position, "y")), (1.0, 2.0));
    assert_eq!(v["pose"]["covariance"].as_array().map(Vec::len), Some(36));
    // A link forwards an open payload into a command service taking that type: every
    // scan of turtle/scan is published again on /turtle/scan_relay, the same message.
    assert_eq!(
        row(&list, "turtle/relay")["payload"],
        "sensor_msgs/msg/LaserScan"
    );
    assert_eq!(row(&list, "turtle/relay")["kind"], "command");
    let linker = fed.spawn(&[
        "user",
        "link",
        "turtle/scan",
        "turtle/relay",
        "--duration",
        "20s",
        "--json",
    ]);
    let relayed = until(fed.proc(bot), "a relayed scan", 20 * SEC, |v| {
        v["event"] == "relayed"
    });
    assert_eq!(relayed["frame"], "laser");
    assert_eq!(relayed["ranges"], serde_json::json!([1.0, 2.0, "inf", 4.5]));
    let forwarded = until(fed.proc(linker), "a forwarded line", 10 * SEC, |v| {
        v["forwarded"].is_object()
    });
    assert_eq!(forwarded["forwarded"]["type"], "sensor_msgs/msg/LaserScan");
    fed.proc(linker).signal(libc::SIGTERM);

    // Recorded: `muster record --service` writes the LaserScan as CDR with its ros2msg
    // definition, which the Python mcap reader's ROS 2 decoder (mcap-ros2-support)
    // decodes natively, and the pose as JSON with a JSON Schema.
    check_recording(&fed, &dir);
    // The text view prints it decoded too.
    let (code, out) = fed.run(
        &["user", "request", "turtle/scan", "--duration", "1s"],
        30 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    assert!(
        out.contains("sensor_msgs/msg/LaserScan {\"angle_increment\":0.5"),
        "{out}"
    );

    // A goal: the robot gets a PoseStamped on /turtle/goal_pose in frame map, facing the
    // goal, drives there, and the user hears accepted, driving, arrived.
    let user = fed.spawn(&[
        "user",
        "request",
        "turtle/goal",
        "--goal",
        "3,2",
        "--duration",
        "40s",
        "--json",
    ]);
    let g = until(
        fed.proc(bot),
        "the goal on /turtle/goal_pose",
        20 * SEC,
        |v| v["event"] == "goal",
    );
    assert_eq!((f(&g, "x"), f(&g, "y")), (3.0, 2.0));
    assert_eq!(g["frame"], "map");
    assert!(
        f(&g, "z").abs() < 1e-9 && (f(&g, "w") - 1.0).abs() < 1e-9,
        "heading +x: {g}"
    );
    let mut statuses = Vec::new();
    until(fed.proc(user), "arrival", 30 * SEC, |v| {
        if let Some(s) = v["status"].as_str() {
            statuses.push(s.to_string());
        }
        v["status"]
            .as_str()
            .is_some_and(|s| s.starts_with("done: arrived within"))
    });
    // The closure above saw every status line; check their order.
    let user_statuses = statuses;
    let pos = |p: &str| user_statuses.iter().position(|s| s.starts_with(p));
    let (acc, drv) = (
        pos("working: accepted goal (3.00, 2.00)"),
        pos("working: driving: at ("),
    );
    assert!(
        acc.is_some() && drv.is_some() && acc < drv,
        "{user_statuses:?}"
    );
    fed.proc(user).signal(libc::SIGTERM);

    // Driving by twist, and the deadman: the user is SIGKILLed, the robot is sent zero.
    let driver = fed.spawn(&[
        "user",
        "request",
        "turtle/drive",
        "--twist",
        "0.3,0.1",
        "--duration",
        "60s",
        "--json",
    ]);
    let c = until(fed.proc(bot), "cmd_vel from the user", 20 * SEC, |v| {
        v["event"] == "cmd_vel" && v["v"] != 0.0
    });
    assert_eq!((f(&c, "v"), f(&c, "w")), (0.3, 0.1));
    // The driver freezes (alive, silent): the deadman stops the robot.
    fed.proc(driver).signal(libc::SIGSTOP);
    let frozen = Instant::now();
    let mut last_moving = f(&c, "t");
    let stop = until(
        fed.proc(bot),
        "zero velocity from the deadman",
        10 * SEC,
        |v| {
            if v["event"] == "cmd_vel" && v["v"] != 0.0 {
                last_moving = f(v, "t");
            }
            v["event"] == "cmd_vel" && v["v"] == 0.0 && v["w"] == 0.0
        },
    );
    let gap = f(&stop, "t") - last_moving;
    eprintln!(
        "deadman: zero velocity {gap:.3} s after the last input, {:?} after the driver froze",
        frozen.elapsed()
    );
    // Only the deadman stops it, and not before its time (the robot stamps what it
    // takes every 50 ms: ±0.05 s).
    assert!(
        gap >= 0.4,
        "stopped {gap} s after the last input, before the 0.5 s deadman"
    );
    // It wakes, drives again, and dies: its session ends and the robot is stopped.
    fed.proc(driver).signal(libc::SIGCONT);
    until(fed.proc(bot), "cmd_vel again", 20 * SEC, |v| {
        v["event"] == "cmd_vel" && v["v"] != 0.0
    });
    fed.proc(driver).signal(libc::SIGKILL);
    let killed = Instant::now();
    let stop = until(
        fed.proc(bot),
        "zero velocity after the user died",
        10 * SEC,
        |v| v["event"] == "cmd_vel" && v["v"] == 0.0 && v["w"] == 0.0,
    );
    eprintln!(
        "deadman: the robot was stopped {:?} after its driver was SIGKILLed",
        killed.elapsed()
    );
    assert!(f(&stop, "t") > f(&c, "t"));

    // The robot vanishes mid-session: its user is told why, every service is withdrawn;
    // it comes back and so do they.
    let watcher = fed.spawn(&[
        "user",
        "request",
        "turtle/pose",
        "--duration",
        "60s",
        "--json",
    ]);
    until(fed.proc(watcher), "pose updates", 20 * SEC, |v| {
        v["payload"]["type"] == "pose2d"
    });
    fed.proc(bot).signal(libc::SIGKILL);
    let ended = until(fed.proc(watcher), "the session's end", 20 * SEC, |v| {
        v["ended"] == true
    });
    // The first of its topics to fall silent is named (chatter at 2 Hz, or odom).
    let reason = ended["reason"].as_str().unwrap();
    assert!(
        [
            "ended by the system: robot silent: nothing on /turtle/odom for 2s",
            "ended by the system: robot silent: nothing on /turtle/chatter for 2s"
        ]
        .contains(&reason),
        "{ended}"
    );
    fed.wait_list(20 * SEC, |l| {
        TURTLE_SERVICES
            .iter()
            .all(|id| common::find(l, id).is_some_and(|r| r["withdrawn"] == true))
    });
    let (code, out) = fed.run(&["user", "request", "turtle/goal", "--json"], 30 * SEC);
    assert_eq!(code, 3, "a withdrawn service is refused: {out}");
    assert!(out.contains("\"code\":\"withdrawn\""), "{out}");
    fed.spawn_command(robot(&python, d, "/turtle", "1,2", &[]));
    fed.wait_list(30 * SEC, |l| {
        TURTLE_SERVICES
            .iter()
            .all(|id| common::find(l, id).is_some_and(|r| r["withdrawn"] == false))
    });
    fed.shutdown();
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_ros2_robot_that_sends_bad_input_gets_clear_errors() {
    let Some(python) = rclpy() else { return };
    let d = domain(2);
    let dir = std::env::temp_dir().join(format!("muster-ros2-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("bad.toml");
    std::fs::write(
        &config,
        r#"
system = "bad"
namespace = "/bad"
watch = ["odom"]

[[data]]
name = "pose"
topic = "odom"
type = "nav_msgs/msg/Odometry"

[[data]]
name = "battery"
topic = "battery"
type = "std_msgs/msg/Float32"

[[data]]
name = "bigscan"
topic = "bigscan"
type = "sensor_msgs/msg/LaserScan"
"#,
    )
    .unwrap();
    let log = dir.join("system.log");
    let mut fed = Fed::new("ros2bad");
    fed.broker(&[]);
    let ds = d.to_string();
    let mut sys = fed.command(&[
        "system",
        "ros2",
        "--config",
        config.to_str().unwrap(),
        "--domain",
        &ds,
    ]);
    sys.stderr(std::fs::File::create(&log).unwrap());
    let mut sys = sys.stdin(std::process::Stdio::null()).spawn().unwrap();
    fed.spawn_command(robot(
        &python,
        d,
        "/bad",
        "5,5",
        &["--wrong-type", "--malformed", "20", "--oversized"],
    ));

    // Good samples after bad ones still flow.
    fed.wait_list(30 * SEC, |l| {
        common::find(l, "bad/pose").is_some_and(|r| r["withdrawn"] == false)
    });
    let out = request_json(&fed, "bad/pose", "2s");
    assert!(
        out.lines().filter(|l| l.contains("\"pose2d\"")).count() >= 10,
        "{out}"
    );

    // The wrong type is named, with both types, in the system's log.
    let end = std::time::Instant::now() + 20 * SEC;
    let want = "topic /bad/battery has type std_msgs/msg/String on the ROS graph, but the config says std_msgs/msg/Float32";
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains(want)
    {
        assert!(
            std::time::Instant::now() < end,
            "no type error in: {}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    // A sample past the open payloads' limit (a 2000-beam scan, 8 KB) is refused with
    // the sizes, not sent half or silently: a user of the service gets nothing of it,
    // and the session goes on.
    let out = request_json(&fed, "bad/bigscan", "2s");
    assert!(!out.contains("\"seq\""), "{out}");
    assert!(out.contains("\"ended\":true"), "{out}");
    let said = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(
        said.contains("/bad/bigscan: a sample of 8")
            && said.contains("bytes dropped: open payloads are at most 3584 bytes"),
        "{said}"
    );
    // Said once, not at every check (one every 2 s).
    std::thread::sleep(std::time::Duration::from_millis(4500));
    let said = std::fs::read_to_string(&log).unwrap_or_default();
    assert_eq!(said.matches(want).count(), 1, "{said}");
    assert_eq!(sys.try_wait().unwrap(), None, "the system stays up");
    // SAFETY: our own child.
    unsafe { libc::kill(sys.id() as i32, libc::SIGTERM) };
    let status = sys.wait().unwrap();
    assert!(status.success(), "{status:?}");
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(!text.contains("panicked"), "{text}");
    fed.shutdown();
    let _ = std::fs::remove_dir_all(&dir);
}

/// `muster record --service` of the turtle's scan and pose, read back by the Python
/// `mcap` reader with `mcap-ros2-support`'s decoder (installed by .ci/run).
fn check_recording(fed: &Fed, dir: &std::path::Path) {
    let Some(python) = common::python_with("mcap_ros2.decoder", "mcap-ros2-support") else {
        return;
    };
    let out = dir.join("turtle.mcap");
    let (code, said) = fed.run(
        &[
            "record",
            "--service",
            "turtle/scan",
            "--service",
            "turtle/pose",
            "--duration",
            "3s",
            "--out",
            out.to_str().unwrap(),
        ],
        60 * SEC,
    );
    assert_eq!(code, 0, "{said}");
    let script = r#"
import json, math, sys
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
out = {"scan": [], "pose": []}
with open(sys.argv[1], "rb") as f:
    r = make_reader(f, decoder_factories=[DecoderFactory()])
    for schema, channel, message, m in r.iter_decoded_messages(topics=["/muster/services/turtle/scan"]):
        out["scan"].append({"schema": schema.name, "schema_encoding": schema.encoding,
            "message_encoding": channel.message_encoding, "frame": m.header.frame_id,
            "stamp": m.header.stamp.sec, "angle_min": m.angle_min,
            "ranges": [v if math.isfinite(v) else "inf" for v in m.ranges]})
with open(sys.argv[1], "rb") as f:
    r = make_reader(f)
    for schema, channel, message in r.iter_messages(topics=["/muster/services/turtle/pose"]):
        out["pose"].append({"schema": schema.name, "schema_encoding": schema.encoding,
            "message_encoding": channel.message_encoding, "value": json.loads(message.data)})
print(json.dumps(out))
"#;
    let res = Command::new(&python)
        .args(["-c", script, out.to_str().unwrap()])
        .output()
        .expect("python");
    let stdout = String::from_utf8_lossy(&res.stdout);
    assert!(
        res.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&res.stderr)
    );
    let v: Value = serde_json::from_str(stdout.trim()).unwrap();
    let scans = v["scan"].as_array().unwrap();
    assert!(scans.len() >= 3, "2 Hz for 3 s: {v}");
    for s in scans {
        assert_eq!(s["schema"], "sensor_msgs/msg/LaserScan");
        assert_eq!(s["schema_encoding"], "ros2msg");
        assert_eq!(s["message_encoding"], "cdr");
        assert_eq!(s["frame"], "laser");
        assert_eq!(s["stamp"], 7);
        assert_eq!(s["angle_min"], -0.75);
        assert_eq!(s["ranges"], serde_json::json!([1.0, 2.0, "inf", 4.5]));
    }
    let poses = v["pose"].as_array().unwrap();
    assert!(poses.len() >= 20, "20 Hz for 3 s: {}", poses.len());
    assert_eq!(poses[0]["schema"], "muster.pose2d");
    assert_eq!(poses[0]["schema_encoding"], "jsonschema");
    assert_eq!(poses[0]["message_encoding"], "json");
    assert_eq!(poses[0]["value"]["type"], "pose2d");
    assert_eq!(f(&poses[0]["value"], "x"), 1.0);
    let _ = std::fs::remove_file(&out);
}

/// The paper's delivery robot drives a robot it knows only through ROS 2 topics: the
/// simulator bridged to ROS 2 on one instance, the delivery system (`--ros2`) and its
/// user on another, so nothing passes between them but DDS.
#[test]
fn the_paper_delivery_robot_drives_a_robot_through_ros2() {
    let d = domain(3).to_string();
    let mut world = Fed::new("ros2dsim");
    world.spawn(&["sim", "--ros2", "--domain", &d, "--speed", "4"]);
    let mut fed = Fed::new("ros2dlv");
    assert_ne!(world.inst, fed.inst);
    fed.broker(&[]);
    let delivery = fed.spawn(&[
        "system",
        "delivery",
        "--ros2",
        "--domain",
        &d,
        "--home-after",
        "600",
        "--stats-json",
    ]);
    fed.wait_list(30 * SEC, |l| {
        common::find(l, "delivery/D1").is_some_and(|r| r["withdrawn"] == false)
    });
    // D1 starts at (30, 3) facing west along the south corridor.
    let user = fed.spawn(&[
        "user",
        "request",
        "delivery/D1",
        "--goal",
        "24,3",
        "--duration",
        "90s",
        "--json",
    ]);
    let mut statuses = Vec::new();
    until(fed.proc(user), "arrival at (24, 3)", 80 * SEC, |v| {
        if let Some(s) = v["status"].as_str() {
            statuses.push(s.to_string());
        }
        v["status"]
            .as_str()
            .is_some_and(|s| s.starts_with("done: arrived within"))
    });
    assert!(
        statuses
            .iter()
            .any(|s| s.starts_with("working: accepted goal (24.00, 3.00)")),
        "{statuses:?}"
    );
    let arrived = statuses.last().unwrap();
    let within: f64 = arrived
        .trim_start_matches("done: arrived within ")
        .split(' ')
        .next()
        .and_then(|m| m.parse().ok())
        .unwrap_or_else(|| panic!("{arrived}"));
    assert!(within <= 1.0, "{arrived}");
    // It localized itself from the ROS scan and odometry: against the simulator's ground
    // truth (its `ground_truth` topic), within half a metre at the 95th percentile.
    let stats = stats_on_stop(&mut fed, delivery);
    assert_eq!(stats["arrivals"], 1, "{stats}");
    // What it took D1 to be, from the robot's own topics alone (no scenario, no
    // parameter file): the start from its first odometry, the laser from its first
    // scan, the sonar from /tf_static and its ranges, the map from /map.
    let me = &stats["robots"]["D1"];
    let start: Vec<f64> = serde_json::from_value(me["start"].clone()).unwrap();
    assert!(
        (start[0] - 30.0).abs() < 0.01 && (start[1] - 3.0).abs() < 0.01,
        "{me}"
    );
    assert!((start[2].abs() - 180.0).abs() < 0.1, "{me}");
    assert!((f(&me["laser"], "first_deg") + 90.0).abs() < 1e-3, "{me}");
    assert!((f(&me["laser"], "step_deg") - 1.0).abs() < 1e-3, "{me}");
    assert_eq!(me["laser"]["range_m"], 8.0, "{me}");
    assert_eq!(me["sonar"]["transducers"], 16, "{me}");
    assert_eq!(me["sonar"]["range_m"], 5.0, "{me}");
    let bearings: Vec<f64> = serde_json::from_value(me["sonar"]["bearings_deg"].clone()).unwrap();
    assert!(
        (bearings[0] - 90.0).abs() < 1e-6 && (bearings[11] + 170.0).abs() < 1e-6,
        "{me}"
    );
    let near = |v: &Value, want: f64| v.as_f64().is_some_and(|x| (x - want).abs() < 1e-4);
    assert!(
        near(&me["map_m"][0], 40.0) && near(&me["map_m"][1], 20.0),
        "{me}"
    );
    assert_eq!(me["camera"], Value::Null, "{me}");
    let loc = &stats["localization"]["D1"];
    assert!(f(loc, "samples") > 5.0, "{stats}");
    assert!(f(loc, "position_p95_m") < 0.5, "{stats}");
    fed.shutdown();
    world.shutdown();
}

/// The same delivery system drives a robot written in rclpy (tests/ros2/robot.py with
/// `--room`: a differential drive whose laser sees the walls of the room the test's map
/// draws), with the room's map and what its topics do not say (start, size, speed) from
/// files, as for any robot.
#[test]
fn the_paper_delivery_robot_drives_an_rclpy_robot() {
    let Some(python) = rclpy() else { return };
    let dir = std::env::temp_dir().join(format!("muster-ros2-rclpy-d1-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    room(&dir);
    let params = dir.join("r1.toml");
    std::fs::write(
        &params,
        "[R1]\nstart = [3.0, 4.0, 0.0]\nradius = 0.2\nmax_speed = 1.0\n",
    )
    .unwrap();
    let d = domain(4);
    let mut fed = Fed::new("ros2rdlv");
    fed.broker(&[]);
    let bot = fed.spawn_command(robot(&python, d, "/turtle", "3,4", &["--room", "24,8"]));
    until(fed.proc(bot), "the robot up", 20 * SEC, |v| {
        v["event"] == "up"
    });
    let ds = d.to_string();
    let delivery = fed.spawn(&[
        "system",
        "delivery",
        "--ros2",
        "--domain",
        &ds,
        "--namespace",
        "/turtle",
        "--robot",
        "R1",
        "--map",
        dir.join("room.yaml").to_str().unwrap(),
        "--robot-params",
        params.to_str().unwrap(),
        "--home-after",
        "600",
        "--stats-json",
    ]);
    fed.wait_list(30 * SEC, |l| common::find(l, "delivery/R1").is_some());
    let user = fed.spawn(&[
        "user",
        "request",
        "delivery/R1",
        "--goal",
        "10,4",
        "--duration",
        "90s",
        "--json",
    ]);
    let done = until(fed.proc(user), "arrival at (10, 4)", 80 * SEC, |v| {
        v["status"]
            .as_str()
            .is_some_and(|s| s.starts_with("done: arrived within"))
    });
    // The rclpy robot was driven by velocity commands from muster's navigator.
    let moved = until(
        fed.proc(bot),
        "cmd_vel from the delivery system",
        5 * SEC,
        |v| v["event"] == "cmd_vel",
    );
    assert!(moved["v"].is_number(), "{moved}");
    let stats = stats_on_stop(&mut fed, delivery);
    assert_eq!(stats["arrivals"], 1, "{stats} {done}");
    let me = &stats["robots"]["R1"];
    assert_eq!(me["start"], serde_json::json!([3.0, 4.0, 0.0]), "{me}");
    assert_eq!(me["radius_m"], 0.2, "{me}");
    assert_eq!(me["max_speed"], 1.0, "{me}");
    assert_eq!(me["sonar"], Value::Null, "{me}");
    assert_eq!(me["laser"]["beams_if_symmetric"], 181, "{me}");
    let near = |v: &Value, want: f64| v.as_f64().is_some_and(|x| (x - want).abs() < 1e-4);
    assert!(
        near(&me["map_m"][0], 24.0) && near(&me["map_m"][1], 8.0),
        "{me}"
    );
    // This robot's odometry is exact: the localizer's estimate against it.
    let loc = &stats["localization"]["R1"];
    assert!(f(loc, "position_p95_m") < 0.5, "{stats}");
    fed.shutdown();
    let _ = std::fs::remove_dir_all(&dir);
}

/// The paper's tracking system on robots it knows only through ROS 2 (the simulator
/// bridged on another instance): its cameras' beacon sightings (`beacons`), pointing
/// (`ptz`, `ptz_cmd`), lasers, sonars and odometry all over DDS.
#[test]
fn the_paper_tracking_system_tracks_through_ros2() {
    let d = domain(5).to_string();
    let mut world = Fed::new("ros2tsim");
    world.spawn(&["sim", "--ros2", "--domain", &d, "--speed", "4"]);
    let mut fed = Fed::new("ros2trk");
    fed.broker(&[]);
    let tracking = fed.spawn(&[
        "system",
        "tracking",
        "--ros2",
        "--domain",
        &d,
        "--robots",
        "T1,T2,T3",
        "--stats-json",
    ]);
    fed.wait_list(30 * SEC, |l| {
        ["tracking/red", "tracking/green", "tracking/blue"]
            .iter()
            .all(|id| common::find(l, id).is_some())
    });
    // 25 s at 4x: 100 s of the paper's scenario, in which T1 sees the green and blue
    // people pass (the same sightings as over shared memory, seed for seed).
    let users: Vec<usize> = ["red", "green", "blue"]
        .iter()
        .map(|c| {
            let id = format!("tracking/{c}");
            fed.spawn(&["user", "request", &id, "--duration", "25s", "--json"])
        })
        .collect();
    let mut seen = Vec::new();
    for u in users {
        for l in fed.proc(u).rest_lines(60 * SEC) {
            let Ok(v) = serde_json::from_str::<Value>(&l) else {
                continue;
            };
            let p = &v["payload"];
            if p["type"] == "track2d" {
                for r in p["seen_by"].as_array().into_iter().flatten() {
                    seen.push(r.as_str().unwrap_or_default().to_string());
                }
            }
        }
    }
    assert!(!seen.is_empty(), "no target seen by any tracker over ROS 2");
    assert!(
        seen.iter()
            .all(|r| ["T1", "T2", "T3"].contains(&r.as_str())),
        "{seen:?}"
    );
    // Each tracker localized itself from its ROS scan and odometry.
    let stats = stats_on_stop(&mut fed, tracking);
    for r in ["T1", "T2", "T3"] {
        // Each camera's geometry: the simulator's, by default, once the robot's camera
        // topics were heard.
        let fov = f(&stats["robots"][r]["camera"], "fov_deg");
        assert!((fov - 60.0).abs() < 1e-9, "{r}: {stats}");
        let loc = &stats["localization"][r];
        assert!(f(loc, "samples") > 10.0, "{r}: {stats}");
        assert!(f(loc, "position_p95_m") < 0.5, "{r}: {stats}");
    }
    fed.shutdown();
    world.shutdown();
}

/// A robot system told to drive a ROS 2 robot that is not there, or given a parameter
/// file it cannot use, stops with an error that says what is missing or wrong.
#[test]
fn a_ros2_robot_system_says_what_it_waited_for() {
    let d = domain(6).to_string();
    let fed = Fed::new("ros2ghost");
    // Runs `system delivery --ros2` for robot "ghost" with `extra`: fails, says `says`.
    let refused = |extra: &[&str], says: &str| {
        let mut args = vec![
            "system", "delivery", "--ros2", "--domain", &d, "--robot", "ghost",
        ];
        args.extend_from_slice(extra);
        let (code, _, err) = fed.run_full(&args, 30 * SEC);
        assert_ne!(code, 0, "{err}");
        assert!(err.contains(says), "{extra:?}: {err}");
    };
    refused(
        &["--wait-sim", "2s"],
        "robot ghost: waited 2s for a scan on /ghost/scan, odometry on /ghost/odom, \
         a map on /map (or give --map)",
    );
    let dir = std::env::temp_dir().join(format!("muster-ros2-ghost-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let params = dir.join("p.toml");
    let p = params.to_str().unwrap();
    std::fs::write(&params, "[ghost]\nradius = -0.2\n").unwrap();
    refused(
        &["--robot-params", p],
        "[ghost] radius must be a positive number",
    );
    std::fs::write(&params, "[other]\nradius = 0.2\n").unwrap();
    refused(
        &["--robot-params", p],
        "other is not one of this system's robots",
    );
    // A scenario describes simulated robots only.
    refused(&["--scenario", "x.toml"], "cannot be used with");
    let _ = std::fs::remove_dir_all(&dir);
}
