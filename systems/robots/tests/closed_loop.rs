//! The robot systems' cores driving robots of an in-process simulator (no processes, no
//! shared memory): the same sensors, kinematics, people and contact counting as
//! `muster sim`, stepped deterministically.
#![allow(clippy::unwrap_used)]

use muster_robots::delivery::{DeliveryCore, DeliveryEvent, DeliveryParams};
use muster_robots::localizer::{Localizer, LocalizerParams};
use muster_robots::navigator::NavParams;
use muster_robots::planner::{Planner, PlannerParams};
use muster_robots::sensing::{LikelihoodField, SensorGeometry, SensorSample};
use muster_sim_world::kinematics::{wrap, Pose};
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::scenario::Scenario;
use muster_sim_world::world::World;
use std::sync::Arc;

struct Delivery {
    world: World,
    d1: usize,
    geometry: SensorGeometry,
    loc: Localizer,
    core: DeliveryCore,
    pose: Pose,
    t: f64,
    errors: Vec<f64>,
    /// Sim seconds between a sensor sample and the command computed from it reaching
    /// the robot (a process's wake-up and scheduling, times the simulator's speed).
    latency: f64,
    pending: std::collections::VecDeque<(f64, f64, f64)>,
}

impl Delivery {
    fn new(seed: u64) -> Self {
        let mut scenario = Scenario::paper();
        scenario.seed = seed;
        let map = OccupancyMap::office();
        let world = World::new(&scenario, Some(map.clone())).unwrap();
        let d1 = world.robot_index("D1").unwrap();
        let spec = &world.robots()[d1].spec;
        let start = Pose {
            x: spec.pose[0],
            y: spec.pose[1],
            theta: wrap(spec.pose[2].to_radians()),
        };
        let geometry = SensorGeometry::of(spec);
        let loc = Localizer::new(
            Arc::new(LikelihoodField::new(&map, 1.0)),
            start,
            LocalizerParams::default(),
            seed,
        );
        let planner = Arc::new(Planner::new(&map, PlannerParams::default()));
        let core = DeliveryCore::new(
            planner,
            NavParams::default(),
            DeliveryParams {
                home: Some((30.0, 6.5)),
                home_after: 30.0,
                ..DeliveryParams::default()
            },
        );
        Delivery {
            world,
            d1,
            geometry,
            loc,
            core,
            pose: start,
            t: 0.0,
            errors: Vec::new(),
            latency: 0.0,
            pending: std::collections::VecDeque::new(),
        }
    }

    /// Runs `seconds` of sim time at the sensors' 10 Hz (or until an arrival, if
    /// `until_arrival`); `goal` gives task input.
    fn run(
        &mut self,
        seconds: f64,
        until_arrival: bool,
        mut goal: impl FnMut(&World) -> Option<(f64, f64)>,
    ) -> Vec<DeliveryEvent> {
        let mut events = Vec::new();
        let end = self.t + seconds;
        while self.t < end {
            let r = &self.world.robots()[self.d1];
            let s = SensorSample::from_robot(r, self.world.time());
            self.loc.handle_odometry(s.odom);
            if let Some(scan) = self.geometry.scan(&s) {
                self.loc.handle_scan(s.laser_time, &scan);
            }
            self.pose = self.loc.estimate();
            self.errors
                .push((self.pose.x - s.truth.x).hypot(self.pose.y - s.truth.y));
            let tasked = if let Some(g) = goal(&self.world) {
                events.extend(self.core.set_goal(self.t, self.pose, g));
                true
            } else {
                false
            };
            let obstacles = self.geometry.obstacle_points(&s, 3.5);
            let ((v, w), ev) = self.core.step(self.t, self.pose, &obstacles, tasked);
            let arrived = ev
                .iter()
                .any(|e| matches!(e, DeliveryEvent::Arrived { .. }));
            events.extend(ev);
            if arrived && until_arrival {
                break;
            }
            let before = self.contacts();
            if self.latency == 0.0 {
                self.world.command_velocity(self.d1, v, w);
                self.world.step(0.1);
            } else {
                self.pending.push_back((self.t + self.latency, v, w));
                for k in 1..=5 {
                    let at = self.t + 0.02 * f64::from(k);
                    while self
                        .pending
                        .front()
                        .is_some_and(|c| c.0 <= at - 0.02 + 1e-9)
                    {
                        let (_, v, w) = self.pending.pop_front().unwrap();
                        self.world.command_velocity(self.d1, v, w);
                    }
                    self.world.step(0.02);
                }
            }
            if self.contacts() > before {
                let r = &self.world.robots()[self.d1];
                let near = obstacles
                    .iter()
                    .map(|(x, y)| (x.hypot(*y), y.atan2(*x)))
                    .min_by(|a, b| a.0.total_cmp(&b.0));
                let people: Vec<_> = self
                    .world
                    .people()
                    .iter()
                    .map(|p| {
                        (
                            (p.pose.x - r.pose.x).hypot(p.pose.y - r.pose.y),
                            p.pose.x,
                            p.pose.y,
                        )
                    })
                    .collect();
                eprintln!("CONTACT t {:.1} cmd ({v:.2},{w:.2}) vel {:?} truth {:?} nearest {near:?} people {people:?}", self.t, r.velocity, r.pose);
            }
            self.t += 0.1;
        }
        events
    }

    fn truth(&self) -> Pose {
        self.world.robots()[self.d1].pose
    }

    fn contacts(&self) -> u64 {
        self.world.robots()[self.d1].contacts
    }
}

#[test]
fn delivery_arrives_across_the_office_among_people_without_contact() {
    let mut d = Delivery::new(1);
    for goal in [
        (20.0, 3.0),
        (10.0, 6.5),
        (20.0, 10.0),
        (37.0, 17.0),
        (3.0, 17.0),
    ] {
        let mut once = Some(goal);
        let ev = d.run(150.0, true, |_| once.take());
        let truth = d.truth();
        eprintln!("goal {goal:?} reached or given up at t {:.1}", d.t);
        let arrived = ev
            .iter()
            .any(|e| matches!(e, DeliveryEvent::Arrived { .. }));
        if !arrived {
            let r = &d.world.robots()[d.d1];
            let s = SensorSample::from_robot(r, d.world.time());
            let pts = d.geometry.obstacle_points(&s, 1.0);
            eprintln!(
                "STUCK path {:?} pts {:?}",
                d.core.path(),
                pts.iter()
                    .map(|(x, y)| (
                        (x.hypot(*y) * 100.0).round() / 100.0,
                        (y.atan2(*x) * 10.0).round() / 10.0
                    ))
                    .collect::<Vec<_>>()
            );
            for p in d.world.people() {
                eprintln!("person {} {:?}", p.name, p.pose);
            }
            for r in d.world.robots() {
                eprintln!("robot {} {:?}", r.spec.name, r.pose);
            }
        }
        assert!(
            arrived,
            "goal {goal:?}: at {truth:?}, last events {:?}",
            &ev[ev.len().saturating_sub(5)..]
        );
        assert!(
            (truth.x - goal.0).hypot(truth.y - goal.1) <= 1.1,
            "goal {goal:?}: truly at {truth:?}"
        );
    }
    assert_eq!(d.contacts(), 0, "contacts");
    d.errors.sort_by(f64::total_cmp);
    let p95 = d.errors[d.errors.len() * 95 / 100];
    assert!(p95 < 0.15, "localization p95 {p95:.3} m");
}

/// D1 started where `pose` says, its description (map, fixtures) from the scenario as
/// the delivery system takes it.
fn delivery_from(pose: [f64; 3], seed: u64) -> Delivery {
    let mut scenario = Scenario::paper();
    scenario.seed = seed;
    scenario.people.clear();
    if let Some(r) = scenario.robots.iter_mut().find(|r| r.name == "D1") {
        r.pose = pose;
    }
    let map = OccupancyMap::office();
    let world = World::new(&scenario, Some(map.clone())).unwrap();
    let d = muster_robots::sim::describe(&scenario, &Arc::new(map), "D1")
        .unwrap()
        .fixtures_drawn();
    let d1 = world.robot_index("D1").unwrap();
    Delivery {
        d1,
        geometry: d.sensors.clone(),
        loc: Localizer::new(
            Arc::new(LikelihoodField::new(&d.map, 1.0)),
            d.start,
            LocalizerParams::default(),
            seed,
        ),
        core: DeliveryCore::for_robot(&d, DeliveryParams::default()),
        pose: d.start,
        world,
        t: 0.0,
        errors: Vec::new(),
        latency: 0.0,
        pending: std::collections::VecDeque::new(),
    }
}

#[test]
fn a_stationary_tracker_in_a_junction_is_on_the_delivery_robots_map_and_passed() {
    // T1 never moves: the scenario says so, and D1's map shows it. Taken for a person
    // who might walk into it, it held D1 just south of it, wanting north into the west
    // corridor, for minutes: each way round came within its body fields.
    let scenario = Scenario::paper();
    let map = Arc::new(OccupancyMap::office());
    let of = |name| {
        muster_robots::sim::describe(&scenario, &map, name)
            .unwrap()
            .fixtures
    };
    assert_eq!(of("D1"), vec![(3.0, 3.0, 0.25), (37.0, 17.0, 0.25)]);
    assert_eq!(of("T1"), vec![(37.0, 17.0, 0.25)]);
    let mut d = delivery_from([2.98, 2.32, 150.0], 4);
    let t1 = {
        let r = &d.world.robots()[d.world.robot_index("T1").unwrap()];
        (r.pose.x, r.pose.y)
    };
    let goal = (3.5, 9.0);
    let mut once = Some(goal);
    let ev = d.run(60.0, true, |_| once.take());
    let truth = d.truth();
    assert!(
        ev.iter()
            .any(|e| matches!(e, DeliveryEvent::Arrived { .. })),
        "not arrived within 60 s: at {truth:?}, last events {:?}",
        &ev[ev.len().saturating_sub(3)..]
    );
    assert!(
        (truth.x - goal.0).hypot(truth.y - goal.1) <= 1.1,
        "truly at {truth:?}"
    );
    assert_eq!(d.contacts(), 0, "contacts");
    // T1 stood where it was all along.
    let r = &d.world.robots()[d.world.robot_index("T1").unwrap()];
    assert_eq!((r.pose.x, r.pose.y), t1);
}

#[test]
fn localization_converges_from_an_offset_start_while_driving() {
    // D1's filter starts 0.25 m and 4° off the truth; driving down the corridor it must
    // find where it is.
    let mut d = Delivery::new(3);
    let spec = &d.world.robots()[d.d1].spec;
    let wrong = Pose {
        x: spec.pose[0] + 0.2,
        y: spec.pose[1] - 0.15,
        theta: wrap(spec.pose[2].to_radians() + 4f64.to_radians()),
    };
    d.loc = Localizer::new(
        Arc::new(LikelihoodField::new(d.world.map(), 1.0)),
        wrong,
        LocalizerParams {
            init_sigma_xy: 0.3,
            init_sigma_theta: 0.1,
            ..LocalizerParams::default()
        },
        3,
    );
    let start_truth = d.truth();
    let e0 = d.loc.estimate();
    // Before any scan the estimate is where it was told, about 0.25 m off.
    assert!((e0.x - start_truth.x).hypot(e0.y - start_truth.y) > 0.15);
    let mut once = Some((12.0, 3.0));
    d.run(30.0, true, |_| once.take());
    let truth = d.truth();
    let est = d.loc.estimate();
    let err = (est.x - truth.x).hypot(est.y - truth.y);
    let heading = wrap(est.theta - truth.theta).abs().to_degrees();
    assert!(err < 0.1, "position error {err:.3} m after 30 s");
    assert!(heading < 3.0, "heading error {heading:.2}°");
}

#[test]
fn the_tracking_system_tracks_the_people_it_sees_with_localized_robots() {
    use muster_robots::tracking::{TrackerRobot, TrackingCore, TrackingParams};
    use muster_sim_world::scenario::Colour;
    let scenario = Scenario::paper();
    let map = OccupancyMap::office();
    let mut world = World::new(&scenario, Some(map.clone())).unwrap();
    let names = ["T1", "T2", "T3"];
    let robots: Vec<TrackerRobot> = names
        .iter()
        .map(|n| {
            let spec = &world.robots()[world.robot_index(n).unwrap()].spec;
            TrackerRobot {
                name: n.to_string(),
                start: Pose {
                    x: spec.pose[0],
                    y: spec.pose[1],
                    theta: wrap(spec.pose[2].to_radians()),
                },
                mobile: *n == "T3",
                geometry: SensorGeometry::of(spec),
                max_speed: spec.drive.max_speed,
            }
        })
        .collect();
    let map = Arc::new(map);
    let mut core = TrackingCore::new(
        map.clone(),
        Arc::new(LikelihoodField::new(&map, 1.0)),
        Arc::new(Planner::new(&map, PlannerParams::default())),
        robots,
        TrackingParams::default(),
        5,
    );
    let idx: Vec<usize> = names
        .iter()
        .map(|n| world.robot_index(n).unwrap())
        .collect();
    let wanted = [Colour::Red, Colour::Green, Colour::Blue];
    let mut errors: Vec<(Colour, f64)> = Vec::new();
    let mut lost_seen = false;
    let mut tracked_seen = 0;
    for step in 0..3000 {
        for (i, &w) in idx.iter().enumerate() {
            let s = SensorSample::from_robot(&world.robots()[w], world.time());
            let cmd = core.handle_sample(i, &s, &wanted);
            if let Some((v, om)) = cmd.velocity {
                world.command_velocity(w, v, om);
            }
            if let Some((pan, tilt, zoom)) = cmd.camera {
                world.command_camera(w, pan, tilt, zoom);
            }
        }
        if step % 10 == 0 {
            for c in wanted {
                let Some(t) = core.payload(c) else { continue };
                let p = world.people().iter().find(|p| p.beacon == c).unwrap();
                if t.lost {
                    lost_seen = true;
                } else if t.age < 0.5 {
                    tracked_seen += 1;
                    errors.push((c, (t.x - p.pose.x).hypot(t.y - p.pose.y)));
                }
            }
        }
        world.step(0.1);
    }
    assert!(tracked_seen >= 30, "tracked in only {tracked_seen} samples");
    let mut e: Vec<f64> = errors.iter().map(|x| x.1).collect();
    e.sort_by(f64::total_cmp);
    let p50 = e[e.len() / 2];
    let p95 = e[e.len() * 95 / 100];
    assert!(p50 < 0.3, "tracking error p50 {p50:.2} m");
    assert!(p95 < 1.0, "tracking error p95 {p95:.2} m");
    // People leave every camera's view now and then: their tracks are reported lost.
    assert!(lost_seen);
    for (i, n) in names.iter().enumerate() {
        let est = core.pose(i).unwrap();
        let truth = world.robots()[idx[i]].pose;
        assert!(
            (est.x - truth.x).hypot(est.y - truth.y) < 0.15,
            "{n} localized at {est:?}, truly {truth:?}"
        );
    }
    let t3 = world.robots()[idx[2]].contacts;
    assert_eq!(t3, 0, "the mobile tracker touched something");
}

/// Ten minutes of D1 following alice, her position every second as a link forwards it.
fn follow_alice(d: &mut Delivery) {
    let mut k = 0u64;
    d.run(600.0, false, |w| {
        k += 1;
        k.is_multiple_of(10).then(|| {
            let p = w.people().iter().find(|p| p.name == "alice").unwrap();
            (p.pose.x, p.pose.y)
        })
    });
}

#[test]
fn delivery_follows_a_walking_person_without_contact() {
    for seed in [1, 2, 3] {
        let mut d = Delivery::new(seed);
        follow_alice(&mut d);
        assert_eq!(d.contacts(), 0, "seed {seed}: contacts while following");
    }
}

/// `f` of each seed, each on a thread of its own (the runs are independent and take
/// seconds each), in the seeds' order.
fn per_seed<T: Send>(seeds: std::ops::RangeInclusive<u64>, f: impl Fn(u64) -> T + Sync) -> Vec<T> {
    std::thread::scope(|s| {
        let f = &f;
        let runs: Vec<_> = seeds.map(|seed| s.spawn(move || f(seed))).collect();
        runs.into_iter().map(|r| r.join().unwrap()).collect()
    })
}

/// D1 following a walking person with every command acting 0.25 s late, on ten seeds of
/// ten minutes, touches nobody: the speed limit and body fields grow with the measured
/// latency, and a body the robot turns towards counts as one ahead of it. Runs are
/// chaotic (a change of 1e-9 m in a laser range sends a run elsewhere), so the count is
/// over ten runs, not one. History: before the lane speed limit and the latency-aware
/// fields, seeds 1 and 5 touched her 3 times in 5 runs; after, 1-2 contacts in 10-16
/// seeds (a person coming up beside the robot as it brakes, or one it turned towards).
/// With the speed limit over every body within 70° of the heading, widened on the side
/// it turns to, seeds 1-40 have 0.
#[test]
fn delivery_follows_a_walking_person_without_contact_despite_latency() {
    let contacts = per_seed(1..=10, |seed| {
        let mut d = Delivery::new(seed);
        d.latency = 0.25;
        d.core.set_latency(d.latency);
        follow_alice(&mut d);
        d.contacts()
    });
    assert_eq!(contacts, vec![0; 10], "contacts per seed");
}

/// The paper's Experiment 2 in process (`link_sim`): T3 follows the red person, her
/// track is forwarded to D1 once a second while tracked. Over eight ten-minute seeds no
/// robot touches anything and D1 keeps near her while she is tracked; with ten more
/// people walking about, no robot touches anything either. Runs are chaotic, so the
/// figures are pooled over the seeds. Before T3 followed along the way she went and walls
/// stopped passing for people, D1's distance while tracked was p50 14 m over seeds 1-3;
/// pooled over seeds 1-8 it was 5.9 m before T3 kept her in view (doorways told from
/// corridors, looking where she was last seen, getting clear without turning its back on
/// her) and is 4.1-4.5 m now (pooled over seeds 1-4 and 5-8), with red tracked 42-81 % of
/// the time per seed (56 % overall before). The goals set for them (p50 ≤ 3 m, p90 ≤ 6 m,
/// tracked ≥ 85 %) are not met yet; this holds what is.
#[test]
fn experiment_two_in_process_follows_the_person_without_contact() {
    use muster_robots::link_sim::{run, LinkSimParams};
    let runs = per_seed(1..=8, |seed| {
        run(&LinkSimParams {
            seed,
            ..LinkSimParams::default()
        })
        .unwrap()
    });
    let mut tracked = Vec::new();
    let (mut updates, mut with_her) = (0, 0);
    for (f, seed) in runs.iter().zip(1..) {
        assert_eq!(f.total_contacts(), 0, "seed {seed}: {:?}", f.contacts);
        assert!(
            f.linked_at.is_some_and(|t| t < 60.0),
            "seed {seed}: linked at {:?}",
            f.linked_at
        );
        assert!(
            f.forwarded > 100,
            "seed {seed}: {} goals forwarded",
            f.forwarded
        );
        tracked.extend(&f.d1_person_tracked);
        updates += f.red_updates;
        with_her += f.red_tracked;
    }
    let fraction = with_her as f64 / updates as f64;
    assert!(fraction > 0.55, "red tracked {fraction:.2} of the time");
    let p50 = muster_robots::percentile(&tracked, 0.5).unwrap();
    assert!(p50 < 5.0, "D1 to the person while tracked, p50 {p50:.2} m");
    // And in a crowd: ten more people walking from office to office across the robots'
    // ways.
    let f = run(&LinkSimParams {
        seed: 4,
        crowd: 10,
        ..LinkSimParams::default()
    })
    .unwrap();
    assert_eq!(f.total_contacts(), 0, "in a crowd: {:?}", f.contacts);
    assert!(
        f.forwarded > 100,
        "in a crowd: {} goals forwarded",
        f.forwarded
    );
}
