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
        Delivery { world, d1, geometry, loc, core, pose: start, t: 0.0, errors: Vec::new() }
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
            self.errors.push((self.pose.x - s.truth.x).hypot(self.pose.y - s.truth.y));
            let tasked = if let Some(g) = goal(&self.world) {
                events.extend(self.core.set_goal(self.t, self.pose, g));
                true
            } else {
                false
            };
            let obstacles = self.geometry.obstacle_points(&s, 3.5);
            let ((v, w), ev) = self.core.step(self.t, self.pose, &obstacles, tasked);
            let arrived = ev.iter().any(|e| matches!(e, DeliveryEvent::Arrived { .. }));
            events.extend(ev);
            if arrived && until_arrival {
                break;
            }
            self.world.command_velocity(self.d1, v, w);
            let before = self.contacts();
            self.world.step(0.1);
            if self.contacts() > before {
                let r = &self.world.robots()[self.d1];
                let near = obstacles.iter().map(|(x, y)| (x.hypot(*y), y.atan2(*x))).min_by(|a, b| a.0.total_cmp(&b.0));
                let people: Vec<_> = self.world.people().iter().map(|p| ((p.pose.x - r.pose.x).hypot(p.pose.y - r.pose.y), p.pose.x, p.pose.y)).collect();
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
    for goal in [(20.0, 3.0), (10.0, 6.5), (20.0, 10.0), (37.0, 17.0), (3.0, 17.0)] {
        let mut once = Some(goal);
        let ev = d.run(150.0, true, |_| once.take());
        let truth = d.truth();
        let arrived = ev.iter().any(|e| matches!(e, DeliveryEvent::Arrived { .. }));
        if !arrived {
            let r = &d.world.robots()[d.d1];
            let s = SensorSample::from_robot(r, d.world.time());
            let pts = d.geometry.obstacle_points(&s, 1.0);
            eprintln!("STUCK path {:?} pts {:?}", d.core.path(), pts.iter().map(|(x, y)| ((x.hypot(*y) * 100.0).round() / 100.0, (y.atan2(*x) * 10.0).round() / 10.0)).collect::<Vec<_>>());
            for p in d.world.people() { eprintln!("person {} {:?}", p.name, p.pose); }
            for r in d.world.robots() { eprintln!("robot {} {:?}", r.spec.name, r.pose); }
        }
        assert!(arrived, "goal {goal:?}: at {truth:?}, last events {:?}", &ev[ev.len().saturating_sub(5)..]);
        assert!((truth.x - goal.0).hypot(truth.y - goal.1) <= 1.1, "goal {goal:?}: truly at {truth:?}");
    }
    assert_eq!(d.contacts(), 0, "contacts");
    d.errors.sort_by(f64::total_cmp);
    let p95 = d.errors[d.errors.len() * 95 / 100];
    assert!(p95 < 0.15, "localization p95 {p95:.3} m");
}

