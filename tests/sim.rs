//! The simulator process, read and driven from a second process through shared memory.

#![allow(clippy::unwrap_used)]

mod common;

use common::{Fed, SEC};
use muster_sim_world::shm::RobotLink;
use std::time::{Duration, Instant};

#[test]
fn a_second_process_reads_sensors_and_drives_a_robot() {
    let mut f = Fed::new("sim");
    let sim = f.spawn(&["sim", "--speed", "4"]);
    let node = muster_shared::ipc::create_node("muster-test-sim", false).unwrap();
    let deadline = Instant::now() + 20 * SEC;
    let link = loop {
        match RobotLink::open(&node, &f.inst, "T3") {
            Ok(l) => break l,
            Err(e) => {
                assert!(Instant::now() < deadline, "simulator never came up: {e}");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    };
    // Sensors arrive, woken by the robot's event, read in place.
    let (t0, pose0, beams, sonars) = link
        .next(0.0, 10 * SEC, |s| (s.time, s.pose, s.n_beams, s.n_sonar))
        .unwrap()
        .expect("a sensors sample");
    assert_eq!((beams, sonars), (181, 16));
    // T3 starts at (20, 9.4) facing +x, against the middle corridor's south wall.
    assert!(
        (pose0.x - 20.0).abs() < 0.01 && (pose0.y - 9.4).abs() < 0.01,
        "{pose0:?}"
    );
    // Drive it: keep commanding (a silent controller stops after 0.5 s).
    let mut last = t0;
    let mut moved = 0.0;
    for _ in 0..40 {
        link.velocity(0.8, 0.0).unwrap();
        let (t, x, front) = link
            .next(last, 5 * SEC, |s| (s.time, s.pose.x, s.laser[90]))
            .unwrap()
            .expect("sensors keep coming");
        assert!(t > last);
        assert!(front > 0.0 && front <= 8.0);
        last = t;
        moved = x - pose0.x;
    }
    assert!(moved > 0.5, "the robot drove forward: {moved}");
    // Point the camera; the reported pan follows.
    link.camera(0.8, 0.0, 2.0).unwrap();
    let mut pan = 0.0;
    for _ in 0..40 {
        link.velocity(0.0, 0.0).unwrap();
        pan = link
            .next(last, 5 * SEC, |s| {
                last = s.time;
                s.ptz[0]
            })
            .unwrap()
            .unwrap();
        if (pan - 0.8).abs() < 1e-6 {
            break;
        }
    }
    assert!((pan - 0.8).abs() < 1e-6, "pan {pan}");
    f.proc(sim).signal(libc::SIGTERM);
    assert_eq!(f.proc(sim).wait(10 * SEC), Some(0));
}

#[test]
fn render_export_and_bad_maps() {
    let f = Fed::new("simcli");
    let dir = std::env::temp_dir().join(format!("muster-simcli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let png = dir.join("w.png");
    let (code, out) = f.run(
        &["sim", "--render", png.to_str().unwrap(), "--at", "2"],
        60 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    let img = image::open(&png).unwrap();
    assert_eq!((img.width(), img.height()), (800, 400));
    let yaml = dir.join("office.yaml");
    let (code, _) = f.run(&["sim", "--export-map", yaml.to_str().unwrap()], 60 * SEC);
    assert_eq!(code, 0);
    assert!(dir.join("office.pgm").exists());
    // The exported map loads back and renders the same size.
    let (code, _) = f.run(
        &[
            "sim",
            "--map",
            yaml.to_str().unwrap(),
            "--render",
            png.to_str().unwrap(),
        ],
        60 * SEC,
    );
    assert_eq!(code, 0);
    std::fs::write(
        dir.join("bad.yaml"),
        "image: nothere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n",
    )
    .unwrap();
    let out = f
        .command(&[
            "sim",
            "--map",
            dir.join("bad.yaml").to_str().unwrap(),
            "--render",
            png.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot decode the map image"));
    std::fs::write(dir.join("bad.toml"), "dt = 7\n").unwrap();
    let out = f
        .command(&["sim", "--scenario", dir.join("bad.toml").to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("dt 7 must be in"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_sim_bench_reports_every_size_it_was_asked_for() {
    let f = Fed::new("simbench");
    let (code, out) = f.run(&["sim", "--bench", "--robots", "1,20", "--json"], 120 * SEC);
    assert_eq!(code, 0, "{out}");
    let rows: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect();
    assert_eq!(rows.len(), 2, "{out}");
    for (row, robots) in rows.iter().zip([1, 20]) {
        assert_eq!(row["robots"], robots, "{row}");
        let factor = row["realtime_factor"].as_f64().unwrap();
        let (sim, wall) = (
            row["sim_seconds"].as_f64().unwrap(),
            row["wall_seconds"].as_f64().unwrap(),
        );
        // The factor is simulated over wall time, and every sensor ran.
        assert!(factor > 1.0 && sim > 0.0 && wall > 0.0, "{row}");
        assert!((factor - sim / wall).abs() < 1e-6 * factor, "{row}");
        assert!(row["ns_per_beam"].as_f64().unwrap() > 0.0, "{row}");
        assert!(row["threads"].as_u64().unwrap() >= 1, "{row}");
    }
    let out = f
        .command(&["sim", "--bench", "--robots", "0"])
        .output()
        .unwrap();
    assert_ne!(out.status.code(), Some(0));
    assert!(String::from_utf8_lossy(&out.stderr).contains("robot counts must be 1..=100000"));
}
