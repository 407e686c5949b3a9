//! ROS 2, tested against nodes nobody here wrote: rclpy (ROS 2 Kilted's wheels, in the
//! venv `.ci/run` makes) and Fast DDS, talking to muster's pure-Rust DDS. Each test runs
//! on a ROS domain of its own.

mod common;

use common::Fed;
use serde_json::Value;
use std::path::Path;
use std::process::Command;

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
