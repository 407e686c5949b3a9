//! The paper's Experiment 2 in one process: the tracking system's core (T1–T3, T3
//! mobile and following the person) and the delivery robot's core (D1) drive the robots
//! of an in-process simulator, and the red track is forwarded to D1 as its goal once a
//! second while tracked, as a link does (a lost track forwards nothing). No broker, no
//! processes, no shared memory: the same cores, sensors, kinematics, people and contact
//! counting as `muster experiment link`, stepped deterministically, so that many seeds
//! run in seconds each. Commands may be made late (`latency`), as a busy machine makes
//! them.

use crate::delivery::{DeliveryCore, DeliveryEvent, DeliveryParams};
use crate::localizer::{Localizer, LocalizerParams};
use crate::planner::{Planner, PlannerParams};
use crate::sensing::{LikelihoodField, SensorGeometry, SensorSample};
use crate::tracking::{TrackerRobot, TrackingCore, TrackingParams};
use muster_sim_world::scenario::Scenario;
use muster_sim_world::world::World;
use muster_world_model::{wrap, Colour, OccupancyMap, Pose};
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

/// One run's settings.
#[derive(Clone, Debug)]
pub struct LinkSimParams {
    /// The scenario's seed (people's walks, sensor noise).
    pub seed: u64,
    /// Sim seconds to run.
    pub duration: f64,
    /// Sim seconds between a sensor sample and the command made from it acting.
    pub latency: f64,
    /// Extra people (no beacon the link follows) walking the floor: a crowd.
    pub crowd: usize,
    /// The tracking system's settings (T3 follows red unless told otherwise).
    pub tracking: TrackingParams,
    /// Print a line a second to stderr (positions, tracked or not), to see a run.
    pub trace: bool,
}

impl Default for LinkSimParams {
    fn default() -> Self {
        LinkSimParams {
            seed: 1,
            duration: 600.0,
            latency: 0.0,
            crowd: 0,
            tracking: TrackingParams {
                follow: Some(Colour::Red),
                ..TrackingParams::default()
            },
            trace: false,
        }
    }
}

/// What one run measured, against the simulator's ground truth.
#[derive(Clone, Debug, Default)]
pub struct LinkSimFigures {
    /// D1's distance to the person, every 0.25 s from the link on, while the red track
    /// was not lost, m.
    pub d1_person_tracked: Vec<f64>,
    /// ... and at every sample from the link on, tracked or not, m.
    pub d1_person_all: Vec<f64>,
    /// T3's distance to the person, every 0.25 s from the link on, m.
    pub t3_person: Vec<f64>,
    /// D1's distance to T3, every 0.25 s from the link on, m.
    pub d1_t3: Vec<f64>,
    /// T3's localization error (its estimate against the truth), every 0.25 s from the
    /// link on, m.
    pub t3_localization: Vec<f64>,
    /// D1's localization error, every 0.25 s from the link on, m.
    pub d1_localization: Vec<f64>,
    /// The red track's updates (1 Hz) from the first sighting on, and those not lost.
    pub red_updates: u64,
    /// Of those, the ones with the person tracked.
    pub red_tracked: u64,
    /// Sim time of the link (the first tracked update), s.
    pub linked_at: Option<f64>,
    /// Goals forwarded to D1.
    pub forwarded: u64,
    /// D1's arrivals, each with D1's true distance to the person then, m.
    pub arrivals: Vec<f64>,
    /// Contacts per robot (the simulator's count).
    pub contacts: BTreeMap<String, u64>,
    /// Sim seconds the red person wanted to walk on and could not, boxed in (by the
    /// robots following her, in a doorway), s.
    pub red_held_up: f64,
    /// The run's length, s.
    pub duration: f64,
}

impl LinkSimFigures {
    /// Contacts of all robots.
    pub fn total_contacts(&self) -> u64 {
        self.contacts.values().sum()
    }

    /// Share of the run the red person was held up, boxed in.
    pub fn held_up_fraction(&self) -> f64 {
        self.red_held_up / self.duration.max(1e-9)
    }

    /// Share of red's updates with the person tracked.
    pub fn tracked_fraction(&self) -> f64 {
        self.red_tracked as f64 / (self.red_updates.max(1) as f64)
    }
}

/// How far apart two poses are, m (a pose estimate and the truth).
fn apart(a: Pose, b: Pose) -> f64 {
    (a.x - b.x).hypot(a.y - b.y)
}

/// A robot's commands made at one time, acting `latency` later.
struct Pending {
    at: f64,
    robot: usize,
    velocity: (f64, f64),
}

/// Runs Experiment 2 in process for `p.duration` sim seconds. Fails if the scenario
/// does not make a world (e.g. a crowd that does not fit).
pub fn run(p: &LinkSimParams) -> Result<LinkSimFigures, String> {
    let mut scenario = Scenario::paper();
    scenario.seed = p.seed;
    scenario.add_crowd(p.crowd).map_err(|e| e.to_string())?;
    let map = OccupancyMap::office();
    let mut world = World::new(&scenario, Some(map.clone())).map_err(|e| e.to_string())?;
    let map = Arc::new(map);
    let field = Arc::new(LikelihoodField::new(&map, 1.0));
    let pose_of = |w: &World, i: usize| {
        let s = &w.robots()[i].spec;
        Pose {
            x: s.pose[0],
            y: s.pose[1],
            theta: wrap(s.pose[2].to_radians()),
        }
    };
    let names = ["T1", "T2", "T3"];
    let idx: Vec<usize> = names.iter().filter_map(|n| world.robot_index(n)).collect();
    let d1 = world
        .robot_index("D1")
        .ok_or("the paper's scenario has no D1")?;
    let radius = idx
        .iter()
        .map(|&i| world.robots()[i].spec.drive.radius)
        .fold(0.0, f64::max);
    let fixtures = crate::sim::fixtures(&scenario, None);
    let robots: Vec<TrackerRobot> = names
        .iter()
        .zip(&idx)
        .map(|(n, &i)| {
            let spec = &world.robots()[i].spec;
            TrackerRobot {
                name: n.to_string(),
                start: pose_of(&world, i),
                mobile: *n == "T3",
                geometry: SensorGeometry::of(spec),
                max_speed: spec.drive.max_speed,
            }
        })
        .collect();
    let mut tracking = TrackingCore::new(
        map.clone(),
        field.clone(),
        Arc::new(Planner::new(
            // The mobile tracker plans round the stationary ones, as the system does.
            &crate::port::with_fixtures(&map, &fixtures),
            PlannerParams {
                radius,
                ..PlannerParams::default()
            },
        )),
        robots,
        p.tracking.clone(),
        p.seed,
    );
    let d1_robot = crate::sim::describe(&scenario, &map, "D1")
        .map_err(|e| e.to_string())?
        .fixtures_drawn();
    let d1_geometry = d1_robot.sensors.clone();
    let mut localizer = Localizer::new(
        Arc::new(LikelihoodField::new(&d1_robot.map, 1.0)),
        d1_robot.start,
        LocalizerParams::default(),
        p.seed,
    );
    let mut delivery = DeliveryCore::for_robot(&d1_robot, DeliveryParams::default());
    delivery.set_latency(p.latency);
    for i in 0..idx.len() {
        tracking.set_latency(i, p.latency);
    }
    // The red person: where she is, and how long she has been held up.
    let red = |w: &World| {
        w.people()
            .iter()
            .find(|q| q.beacon == Colour::Red)
            .map_or(((0.0, 0.0), 0.0), |q| ((q.pose.x, q.pose.y), q.held_up))
    };
    let person = |w: &World| red(w).0;
    let wanted = [Colour::Red, Colour::Green, Colour::Blue];
    let mut figures = LinkSimFigures::default();
    let mut pending: VecDeque<Pending> = VecDeque::new();
    let mut d1_pose = pose_of(&world, d1);
    let mut red_lost = true;
    let mut t = 0.0;
    let mut next_record = 0.0;
    while t < p.duration {
        let now = world.time();
        let mut commands = Vec::new();
        for (i, &w) in idx.iter().enumerate() {
            let s = SensorSample::from_robot(&world.robots()[w], now);
            let cmd = tracking.handle_sample(i, &s, &wanted);
            if let Some((pan, tilt, zoom)) = cmd.camera {
                world.command_camera(w, pan, tilt, zoom);
            }
            if let Some(v) = cmd.velocity {
                commands.push((w, v));
            }
        }
        // The link: the red track, once a second, forwarded while not lost.
        if tracking.publish_due() {
            if let Some(track) = tracking.payload(Colour::Red) {
                figures.red_updates += 1;
                red_lost = track.lost;
                if !track.lost {
                    figures.red_tracked += 1;
                    figures.linked_at.get_or_insert(now);
                    figures.forwarded += 1;
                    let _ = delivery.set_goal(now, d1_pose, (track.x, track.y));
                }
            }
        }
        let s = SensorSample::from_robot(&world.robots()[d1], now);
        localizer.handle_odometry(s.odom);
        if let Some(scan) = d1_geometry.scan(&s) {
            localizer.handle_scan(s.laser_time, &scan);
        }
        d1_pose = localizer.estimate();
        let obstacles = d1_geometry.obstacle_points(&s, 3.5);
        let (v, events) = delivery.step(now, d1_pose, &obstacles, figures.linked_at.is_some());
        commands.push((d1, v));
        let (px, py) = person(&world);
        for e in &events {
            if matches!(e, DeliveryEvent::Arrived { .. }) {
                let r = &world.robots()[d1].pose;
                figures.arrivals.push((r.x - px).hypot(r.y - py));
            }
        }
        for (robot, velocity) in commands {
            pending.push_back(Pending {
                at: now + p.latency,
                robot,
                velocity,
            });
        }
        // The simulator runs 0.1 s (the sensors' period) in five steps; commands act
        // when their time comes.
        for k in 1..=5 {
            let step_end = now + 0.02 * f64::from(k);
            while pending
                .front()
                .is_some_and(|c| c.at <= step_end - 0.02 + 1e-9)
            {
                if let Some(c) = pending.pop_front() {
                    world.command_velocity(c.robot, c.velocity.0, c.velocity.1);
                }
            }
            world.step(0.02);
        }
        t += 0.1;
        if p.trace && ((t * 10.0).round() as u64).is_multiple_of(10) {
            let (px, py) = person(&world);
            let d1p = world.robots()[d1].pose;
            let t3 = &world.robots()[idx[2]];
            let t3p = t3.pose;
            // Whether T3 could see her (no wall between) and how far off its camera's
            // axis she is, degrees.
            let (bearing, d3) = (
                (py - t3p.y).atan2(px - t3p.x),
                (t3p.x - px).hypot(t3p.y - py),
            );
            let sight = map.raycast(t3p.x, t3p.y, bearing, d3).is_none();
            let off = wrap(bearing - t3p.theta - t3.ptz.pan).to_degrees();
            let tr = tracking.payload(Colour::Red);
            let (t3v, d1v) = (t3.velocity, world.robots()[d1].velocity);
            eprintln!(
                "t {t:6.1} person ({px:5.1},{py:5.1}) held {:5.1} T3 ({:5.1},{:5.1}) d {d3:4.1} sight {sight} off {off:4.0} D1 ({:5.1},{:5.1}) d {:4.1} track {} | T3 hdg {:4.0} v {:4.2} w {:5.2} D1 hdg {:4.0} v {:4.2} w {:5.2} | T3 pan {:4.0} zoom {:.1} sees {:?} others {} | D1 est ({:.2},{:.2}) err {:.2} | T3 est err {:.2}",
                red(&world).1,
                t3p.x, t3p.y,
                d1p.x, d1p.y, (d1p.x - px).hypot(d1p.y - py),
                tr.map_or("none".to_string(), |tr| format!("({:5.1},{:5.1}) lost {} age {:.1}", tr.x, tr.y, tr.lost, tr.age)),
                t3p.theta.to_degrees(), t3v.0, t3v.1,
                d1p.theta.to_degrees(), d1v.0, d1v.1,
                t3.ptz.pan.to_degrees(), t3.ptz.zoom,
                t3.detections.iter().map(|d| d.colour).collect::<Vec<_>>(),
                world
                    .people()
                    .iter()
                    .filter(|q| q.beacon != Colour::Red && ((q.pose.x - t3p.x).hypot(q.pose.y - t3p.y) < 3.0 || (q.pose.x - d1p.x).hypot(q.pose.y - d1p.y) < 2.0))
                    .map(|q| format!("{:?} ({:.1},{:.1})", q.beacon, q.pose.x, q.pose.y))
                    .collect::<Vec<_>>()
                    .join(" "),
                d1_pose.x, d1_pose.y, apart(d1_pose, d1p),
                tracking.pose(2).map_or(f64::NAN, |e| apart(e, t3p)),
            );
        }
        if figures.linked_at.is_some() && t >= next_record {
            next_record = t + 0.25;
            let (px, py) = person(&world);
            let d1p = world.robots()[d1].pose;
            let t3p = world.robots()[idx[2]].pose;
            let d = (d1p.x - px).hypot(d1p.y - py);
            figures.d1_person_all.push(d);
            if !red_lost {
                figures.d1_person_tracked.push(d);
            }
            figures.t3_person.push((t3p.x - px).hypot(t3p.y - py));
            figures.d1_t3.push(apart(d1p, t3p));
            figures.d1_localization.push(apart(d1_pose, d1p));
            if let Some(e) = tracking.pose(2) {
                figures.t3_localization.push(apart(e, t3p));
            }
        }
    }
    figures.contacts = world
        .robots()
        .iter()
        .map(|r| (r.spec.name.clone(), r.contacts))
        .collect();
    figures.red_held_up = red(&world).1;
    figures.duration = p.duration;
    Ok(figures)
}
