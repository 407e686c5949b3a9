//! World tests.

use super::*;
use crate::scenario::{CameraParams, LaserParams, PersonSpec, SonarParams};

fn robot(name: &str, x: f64, y: f64, deg: f64) -> RobotSpec {
    RobotSpec {
        name: name.into(),
        pose: [x, y, deg],
        drive: DriveParams::default(),
        laser: None,
        sonar: None,
        camera: None,
        beacon: None,
        wander: false,
        home: None,
        fixed: false,
    }
}

fn scenario(robots: Vec<RobotSpec>) -> Scenario {
    Scenario {
        map: None,
        seed: 7,
        dt: 0.01,
        robots,
        people: vec![],
        places: vec![],
    }
}

/// A 10 m × 4 m room at 0.05 m with a 0.05 m thin wall across it at x = 5.0..5.05.
fn thin_wall_room() -> OccupancyMap {
    let wall: Vec<(usize, usize)> = (0..80).map(|j| (100, j)).collect();
    crate::map::walled_room(200, 80, 0.05, &wall)
}

#[test]
fn nothing_tunnels_through_a_thin_wall_at_any_step() {
    for dt in [0.01f64, 0.1, 1.0, 10.0] {
        let mut s = scenario(vec![robot("r", 2.0, 2.0, 0.0)]);
        s.robots[0].drive.max_accel = 1000.0;
        s.robots[0].drive.command_timeout = 1e9;
        let mut w = World::new(&s, Some(thin_wall_room())).unwrap();
        w.command_velocity(0, 100.0, 0.0); // clamped to max speed
        let steps = ((5.0 / dt).ceil() as usize).max(20);
        for _ in 0..steps {
            w.step(dt);
            let p = w.robots()[0].pose;
            assert!(
                p.x + 0.25 <= 5.0 + 1e-9,
                "dt {dt}: through the wall at x = {}",
                p.x
            );
        }
        let p = w.robots()[0].pose;
        assert!(p.x > 4.7, "dt {dt}: it did drive up to the wall: {}", p.x);
        assert!(w.robots()[0].bumped);
    }
}

#[test]
fn robots_never_overlap_head_on_at_any_step() {
    for dt in [0.01f64, 0.5, 5.0] {
        let mut s = scenario(vec![robot("a", 2.0, 2.0, 0.0), robot("b", 4.0, 2.0, 180.0)]);
        for r in &mut s.robots {
            r.drive.max_accel = 1000.0;
            r.drive.command_timeout = 1e9;
        }
        let mut w = World::new(&s, Some(thin_wall_room())).unwrap();
        w.command_velocity(0, 1.2, 0.0);
        w.command_velocity(1, 1.2, 0.0);
        let steps = ((3.0 / dt).ceil() as usize).max(10);
        for _ in 0..steps {
            w.step(dt);
            let (a, b) = (w.robots()[0].pose, w.robots()[1].pose);
            assert!(
                (a.x - b.x).hypot(a.y - b.y) >= 0.5 - 1e-9,
                "dt {dt}: overlap {a:?} {b:?}"
            );
        }
        let (a, b) = (w.robots()[0].pose, w.robots()[1].pose);
        assert!(
            (a.x - b.x).hypot(a.y - b.y) < 0.55,
            "dt {dt}: they did meet"
        );
    }
}

#[test]
fn a_fixed_robot_ignores_velocity_commands_and_cannot_wander() {
    let mut s = scenario(vec![
        robot("still", 10.0, 10.0, 0.0),
        robot("free", 5.0, 5.0, 0.0),
    ]);
    s.robots[0].fixed = true;
    let big = OccupancyMap::from_grid(400, 400, 0.05, (0.0, 0.0), vec![false; 400 * 400]);
    let mut w = World::new(&s, Some(big)).unwrap();
    w.command_velocity(0, 0.5, 0.25);
    w.command_velocity(1, 0.5, 0.0);
    w.step(2.0);
    let (still, free) = (w.robots()[0].pose, w.robots()[1].pose);
    assert_eq!((still.x, still.y, still.theta), (10.0, 10.0, 0.0));
    assert!(free.x > 5.1, "the other robot drove: {free:?}");
    s.robots[0].wander = true;
    assert!(s.validate().is_err());
}

#[test]
fn open_space_arcs_and_the_command_timeout() {
    let mut s = scenario(vec![robot("r", 10.0, 10.0, 0.0)]);
    s.robots[0].drive.max_accel = 1e6;
    s.robots[0].drive.max_turn_accel = 1e6;
    s.robots[0].drive.command_timeout = 10.0;
    let big = OccupancyMap::from_grid(400, 400, 0.05, (0.0, 0.0), vec![false; 400 * 400]);
    let mut w = World::new(&s, Some(big)).unwrap();
    w.command_velocity(0, 0.5, 0.25);
    w.step(2.0);
    let expect = integrate(
        Pose {
            x: 10.0,
            y: 10.0,
            theta: 0.0,
        },
        0.5,
        0.25,
        2.0,
    );
    let p = w.robots()[0].pose;
    assert!(
        (p.x - expect.x).abs() < 1e-3 && (p.y - expect.y).abs() < 1e-3,
        "{p:?} vs {expect:?}"
    );
    // Silent controller: after the timeout the robot stops.
    w.step(10.0);
    assert_eq!(w.robots()[0].velocity, (0.0, 0.0));
    let still = w.robots()[0].pose;
    w.step(1.0);
    assert_eq!(w.robots()[0].pose, still);
}

#[test]
fn odometry_drifts_from_ground_truth_by_its_noise() {
    let mut s = scenario(vec![
        robot("noisy", 3.0, 3.0, 0.0),
        robot("exact", 3.0, 10.0, 0.0),
    ]);
    s.robots[1].drive.odom_noise_linear = 0.0;
    s.robots[1].drive.odom_noise_angular = 0.0;
    let mut w = World::new(&s, None).unwrap();
    for _ in 0..40 {
        w.command_velocity(0, 1.0, 0.0);
        w.command_velocity(1, 0.0, 0.5);
        w.step(0.1);
    }
    let noisy = &w.robots()[0];
    let err = (noisy.odom.x - noisy.pose.x).hypot(noisy.odom.y - noisy.pose.y);
    assert!(err > 0.0 && err < 0.3, "{err}");
    let exact = &w.robots()[1];
    assert!((exact.odom.theta - exact.pose.theta).abs() < 1e-9);
}

fn busy_scenario() -> Scenario {
    let mut s = Scenario::paper();
    for (k, x) in [8.0, 14.0, 26.0, 32.0].into_iter().enumerate() {
        let mut r = robot(&format!("w{k}"), x, 3.0, 0.0);
        r.wander = true;
        r.laser = Some(LaserParams::default());
        r.sonar = Some(SonarParams::default());
        r.camera = Some(CameraParams::default());
        r.beacon = Some(Colour::Yellow);
        s.robots.push(r);
    }
    s
}

fn fingerprint(w: &World) -> Vec<u64> {
    let mut f: Vec<u64> = Vec::new();
    for r in w.robots() {
        f.extend([r.pose.x.to_bits(), r.pose.y.to_bits(), r.odom.x.to_bits()]);
        f.extend(r.laser.iter().map(|v| u64::from(v.to_bits())));
        f.extend(r.detections.iter().map(|d| d.range.to_bits()));
    }
    for p in w.people() {
        f.extend([p.pose.x.to_bits(), p.pose.y.to_bits()]);
    }
    f
}

#[test]
fn the_same_seed_and_commands_give_the_same_world_on_any_thread_count() {
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut w = World::new(&busy_scenario(), None).unwrap();
            let mut prints = Vec::new();
            for k in 0..300 {
                w.command_velocity(2, 0.5, if k % 50 < 25 { 0.3 } else { -0.3 });
                w.command_camera(0, 0.5, 0.0, 2.0);
                w.step(0.01);
                if k % 50 == 49 {
                    prints.push(fingerprint(&w));
                }
            }
            prints
        })
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(1));
    let mut other = busy_scenario();
    other.seed = 8;
    let mut w = World::new(&other, None).unwrap();
    for _ in 0..300 {
        w.step(0.01);
    }
    assert_ne!(
        fingerprint(&w),
        *one.last().unwrap(),
        "another seed, another world"
    );
}

#[test]
fn people_walk_between_places_and_never_touch_walls() {
    let mut w = World::new(&Scenario::paper(), None).unwrap();
    let start: Vec<(f64, f64)> = w.people().iter().map(|p| (p.pose.x, p.pose.y)).collect();
    let mut arrivals = 0;
    let mut last_targets: Vec<usize> = w.people().iter().map(|p| p.target).collect();
    for _ in 0..12_000 {
        w.step(0.01);
        for (k, p) in w.people().iter().enumerate() {
            assert!(
                w.map().clearance(p.pose.x, p.pose.y, 0.3) >= PERSON_RADIUS,
                "{} in a wall",
                p.name
            );
            if p.target != last_targets[k] {
                arrivals += 1;
                last_targets[k] = p.target;
            }
        }
        let bodies: Vec<Pose> = w
            .robots()
            .iter()
            .map(|r| r.pose)
            .chain(w.people().iter().map(|p| p.pose))
            .collect();
        for a in 0..bodies.len() {
            for b in a + 1..bodies.len() {
                assert!((bodies[a].x - bodies[b].x).hypot(bodies[a].y - bodies[b].y) >= 0.5 - 1e-9);
            }
        }
    }
    assert!(
        arrivals >= 3,
        "in 2 minutes people reach places: {arrivals}"
    );
    let moved = w
        .people()
        .iter()
        .zip(&start)
        .filter(|(p, s)| (p.pose.x - s.0).hypot(p.pose.y - s.1) > 1.0)
        .count();
    assert!(moved >= 2);
}

#[test]
fn a_person_boxed_in_by_a_robot_in_her_doorway_counts_the_time_held_up() {
    // The office south-0 (x 4-8, y 4-9) opens on the south corridor through a 1 m door
    // at x 5.5-6.5; she walks between the office and the corridor outside it.
    let run = |robots: Vec<RobotSpec>| {
        let mut s = scenario(robots);
        s.people.push(PersonSpec {
            name: "alice".into(),
            beacon: Colour::Red,
            start: [6.0, 6.5],
            speed: 0.7,
        });
        s.places = vec![
            crate::scenario::Place {
                name: "office".into(),
                at: [6.0, 6.5],
            },
            crate::scenario::Place {
                name: "corridor".into(),
                at: [6.0, 3.0],
            },
        ];
        let mut w = World::new(&s, Some(OccupancyMap::office())).unwrap();
        for _ in 0..1200 {
            w.step(0.1);
        }
        w.people()[0].held_up
    };
    // Free to come and go: never held up.
    let free = run(vec![]);
    assert!(free < 0.5, "{free}");
    // A robot standing in the doorway: every time she makes for the corridor she is
    // held up there (until she gives up and turns back, and tries again).
    let mut blocker = robot("T3", 6.0, 4.05, 90.0);
    blocker.fixed = true;
    let held = run(vec![blocker]);
    assert!(held > 20.0, "{held}");
}

#[test]
fn a_tracker_sees_a_person_walking_in_front_of_it() {
    let mut s = scenario(vec![robot("T1", 3.0, 3.0, 0.0)]);
    s.robots[0].camera = Some(CameraParams::default());
    s.people.push(PersonSpec {
        name: "p".into(),
        beacon: Colour::Red,
        start: [6.0, 3.2],
        speed: 0.5,
    });
    s.places = vec![crate::scenario::Place {
        name: "far".into(),
        at: [37.0, 3.0],
    }];
    let mut w = World::new(&s, None).unwrap();
    w.step(0.1);
    let d = &w.robots()[0].detections;
    assert_eq!(d.len(), 1, "{d:?}");
    assert_eq!(d[0].colour, Colour::Red);
    assert!((d[0].range - 3.0).abs() < 0.5, "{:?}", d[0]);
    // Starting somewhere bad is refused clearly.
    let bad = scenario(vec![robot("x", 0.05, 0.05, 0.0)]);
    let err = World::new(&bad, None)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(err.contains("not free"), "{err}");
}
