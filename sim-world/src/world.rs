//! The world: robots and people on a map, advanced by [`World::step`].
//!
//! Kinematics run at the scenario's `dt` (100 Hz by default), each sensor at its own
//! rate. Bodies never overlap walls or each other at any speed or step size: a body
//! moves in pieces no longer than its clearance to walls and half its gap to any other
//! body (conservative advancement). Robots are advanced in parallel; every random draw
//! comes from a per-robot or per-person generator seeded from the scenario, so a run is
//! the same step for step whatever the thread count.

use crate::bodies::{Body, BodyGrid, Nearby, PERSON_HEIGHT, ROBOT_HEIGHT};
use crate::kinematics::{approach, integrate, wrap, Pose};
use crate::map::OccupancyMap;
use crate::people::Navigation;
use crate::scenario::{Colour, DriveParams, RobotSpec, Scenario};
use crate::sensors::{camera_cone, camera_frame, laser_scan, sonar_ring, Detection, Ptz};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use std::sync::Arc;

/// Why a world could not be built.
#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    /// The scenario's map could not be loaded.
    #[error(transparent)]
    Map(#[from] crate::map::MapError),
    /// A robot or person starts inside a wall or another body; move it.
    #[error("{0} starts at ({1:.2}, {2:.2}), which is not free")]
    Blocked(String, f64, f64),
}

/// Bodies are kept this far from walls, m (a hair, so they can always move away).
const SKIN: f64 = 0.002;
/// Side of the body grid's cells, m.
const GRID_CELL: f64 = 2.0;
/// Below this many bodies a step runs on one thread.
const PARALLEL_FROM: usize = 16;
/// Radius of a person, m.
pub const PERSON_RADIUS: f64 = 0.25;

/// One robot's state.
pub struct Robot {
    /// The robot as the scenario gave it.
    pub spec: RobotSpec,
    /// Ground-truth pose.
    pub pose: Pose,
    /// Current (v, w).
    pub velocity: (f64, f64),
    /// Commanded (v, w).
    pub command: (f64, f64),
    /// Sim time of the last command.
    pub command_time: f64,
    /// Odometry: the pose as the robot's wheel encoders believe it.
    pub odom: Pose,
    /// Last laser scan and its time.
    pub laser: Vec<f32>,
    /// Time of the last laser scan.
    pub laser_time: f64,
    /// Last sonar ring and its time.
    pub sonar: Vec<f32>,
    /// Time of the last sonar ring.
    pub sonar_time: f64,
    /// Camera pose now, and where it is driven to.
    pub ptz: Ptz,
    /// The PTZ command.
    pub ptz_target: Ptz,
    /// Last camera detections and their time.
    pub detections: Vec<Detection>,
    /// Time of the last camera frame.
    pub camera_time: f64,
    /// Whether the last move was cut short by a wall or body.
    pub bumped: bool,
    /// Contacts so far: moves cut short by a wall or body after a move that was not
    /// (a robot pressing on for a second counts once).
    pub contacts: u64,
    next: [f64; 3],
    rng: Pcg64,
    turning: f64,
}

impl Robot {
    /// Whether any fitted sensor is due at `now`.
    fn sensor_due(&self, now: f64) -> bool {
        let due = |k: usize| now + 1e-9 >= self.next[k];
        (self.spec.laser.is_some() && due(0))
            || (self.spec.sonar.is_some() && due(1))
            || (self.spec.camera.is_some() && due(2))
    }
}

/// One person's state.
pub struct Person {
    /// Name.
    pub name: String,
    /// Beacon colour.
    pub beacon: Colour,
    /// Position and heading.
    pub pose: Pose,
    /// Walking speed, m/s.
    pub speed: f64,
    /// The place walked to.
    pub target: usize,
    /// Standing still until this sim time.
    pub pause_until: f64,
    /// Where and when the person last made progress (0.3 m) while walking.
    pub progress: (f64, f64, f64),
    /// Sim seconds this person wanted to walk on but had not got 0.3 m further for
    /// [`HELD_UP_AFTER`]: boxed in by robots or other people (in a doorway, a corner).
    pub held_up: f64,
    rng: Pcg64,
}

/// The whole simulated world.
pub struct World {
    map: Arc<OccupancyMap>,
    nav: Navigation,
    robots: Vec<Robot>,
    people: Vec<Person>,
    time: f64,
    dt: f64,
    steps: u64,
    /// Every body where it is now, bucketed; rebuilt in place after bodies move.
    grid: BodyGrid,
    /// Whether `grid` is as the bodies are now.
    grid_fresh: bool,
}

fn seeded(seed: u64, kind: u64, index: usize) -> Pcg64 {
    Pcg64::seed_from_u64(
        seed ^ kind.wrapping_mul(0x9e37_79b9_7f4a_7c15)
            ^ (index as u64).wrapping_mul(0xbf58_476d_1ce4_e5b9),
    )
}

impl World {
    /// Builds the world of `scenario` on `map` (or the scenario's own map if `None`).
    pub fn new(scenario: &Scenario, map: Option<OccupancyMap>) -> Result<Self, WorldError> {
        let map = match (map, &scenario.map) {
            (Some(m), _) => m,
            (None, Some(path)) => OccupancyMap::load(path)?,
            (None, None) => OccupancyMap::office(),
        };
        let mut places: Vec<(f64, f64)> =
            scenario.places.iter().map(|p| (p.at[0], p.at[1])).collect();
        if places.is_empty() && !scenario.people.is_empty() {
            places = sample_places(&map, scenario.seed, 24);
        }
        let nav = Navigation::new(&map, &places);
        let mut robots = Vec::with_capacity(scenario.robots.len());
        for (i, spec) in scenario.robots.iter().enumerate() {
            let pose = Pose {
                x: spec.pose[0],
                y: spec.pose[1],
                theta: wrap(spec.pose[2].to_radians()),
            };
            if map.clearance(pose.x, pose.y, spec.drive.radius) < spec.drive.radius {
                return Err(WorldError::Blocked(
                    format!("robot {}", spec.name),
                    pose.x,
                    pose.y,
                ));
            }
            robots.push(Robot {
                spec: spec.clone(),
                pose,
                velocity: (0.0, 0.0),
                command: (0.0, 0.0),
                command_time: 0.0,
                odom: pose,
                laser: Vec::new(),
                laser_time: 0.0,
                sonar: Vec::new(),
                sonar_time: 0.0,
                ptz: Ptz::default(),
                ptz_target: Ptz::default(),
                detections: Vec::new(),
                camera_time: 0.0,
                bumped: false,
                contacts: 0,
                next: [0.0; 3],
                rng: seeded(scenario.seed, 1, i),
                turning: 0.0,
            });
        }
        let mut people = Vec::with_capacity(scenario.people.len());
        for (i, p) in scenario.people.iter().enumerate() {
            if map.clearance(p.start[0], p.start[1], PERSON_RADIUS) < PERSON_RADIUS {
                return Err(WorldError::Blocked(
                    format!("person {}", p.name),
                    p.start[0],
                    p.start[1],
                ));
            }
            let mut rng = seeded(scenario.seed, 2, i);
            let target = if nav.places() > 0 {
                rng.random_range(0..nav.places())
            } else {
                0
            };
            people.push(Person {
                name: p.name.clone(),
                beacon: p.beacon,
                pose: Pose {
                    x: p.start[0],
                    y: p.start[1],
                    theta: 0.0,
                },
                speed: p.speed,
                target,
                pause_until: 0.0,
                progress: (p.start[0], p.start[1], 0.0),
                held_up: 0.0,
                rng,
            });
        }
        let grid = BodyGrid::new(Vec::new(), map.origin(), map.size(), GRID_CELL);
        let mut w = World {
            map: Arc::new(map),
            nav,
            robots,
            people,
            time: 0.0,
            dt: scenario.dt,
            steps: 0,
            grid,
            grid_fresh: false,
        };
        let bodies = w.body_grid();
        for (i, r) in w.robots.iter().enumerate() {
            if bodies.half_gap(i, r.pose.x, r.pose.y, r.spec.drive.radius, 1.0) < 0.0 {
                return Err(WorldError::Blocked(
                    format!("robot {} (overlaps a body)", r.spec.name),
                    r.pose.x,
                    r.pose.y,
                ));
            }
        }
        w.sense(true);
        Ok(w)
    }

    /// Sim time, s.
    pub fn time(&self) -> f64 {
        self.time
    }
    /// Kinematics steps taken.
    pub fn steps(&self) -> u64 {
        self.steps
    }
    /// The map.
    pub fn map(&self) -> &OccupancyMap {
        &self.map
    }
    /// The robots.
    pub fn robots(&self) -> &[Robot] {
        &self.robots
    }
    /// The people.
    pub fn people(&self) -> &[Person] {
        &self.people
    }
    /// The navigation fields.
    pub fn navigation(&self) -> &Navigation {
        &self.nav
    }
    /// Index of the robot named `name`.
    pub fn robot_index(&self, name: &str) -> Option<usize> {
        self.robots.iter().position(|r| r.spec.name == name)
    }

    /// Sets a robot's velocity command (clamped to its limits); it holds until the
    /// command timeout.
    pub fn command_velocity(&mut self, robot: usize, v: f64, w: f64) {
        if let Some(r) = self.robots.get_mut(robot) {
            let d = &r.spec.drive;
            let v = if v.is_finite() {
                v.clamp(-d.max_speed, d.max_speed)
            } else {
                0.0
            };
            let w = if w.is_finite() {
                w.clamp(-d.max_turn, d.max_turn)
            } else {
                0.0
            };
            r.command = (v, w);
            r.command_time = self.time;
        }
    }

    /// Points a robot's camera (pan and tilt in rad relative to the heading; zoom ≥ 1).
    pub fn command_camera(&mut self, robot: usize, pan: f64, tilt: f64, zoom: f64) {
        if let Some(r) = self.robots.get_mut(robot) {
            if let Some(c) = &r.spec.camera {
                let lim = c.pan_limit_deg.to_radians();
                let ok = |v: f64, d: f64| if v.is_finite() { v } else { d };
                r.ptz_target = Ptz {
                    pan: ok(pan, 0.0).clamp(-lim, lim),
                    tilt: ok(tilt, 0.0).clamp(-0.5, 0.5),
                    zoom: ok(zoom, 1.0).clamp(1.0, c.max_zoom),
                };
            }
        }
    }

    /// Every body (robots, then people) bucketed for queries, as the sensors see them now.
    pub fn body_grid_snapshot(&self) -> BodyGrid {
        self.body_grid()
    }

    fn body_grid(&self) -> BodyGrid {
        let mut grid = BodyGrid::new(Vec::new(), self.map.origin(), self.map.size(), GRID_CELL);
        grid.rebuild(bodies(&self.robots, &self.people));
        grid
    }

    /// Brings `grid` up to where the bodies are (they move only in kinematics).
    fn refresh_grid(&mut self) {
        if !self.grid_fresh {
            self.grid.rebuild(bodies(&self.robots, &self.people));
            self.grid_fresh = true;
        }
    }

    /// Advances the world by `dt` seconds, in kinematics steps of at most the scenario's
    /// `dt`. Never fails; any `dt` is safe (no tunnelling, no overlap).
    pub fn step(&mut self, dt: f64) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        let n = (dt / self.dt).ceil().max(1.0) as usize;
        let h = dt / n as f64;
        for _ in 0..n {
            self.kinematics(h);
            self.time += h;
            self.steps += 1;
            self.sense(false);
        }
    }

    /// Runs until sim time `t` (no-op if already past it).
    pub fn step_to(&mut self, t: f64) {
        if t > self.time {
            self.step(t - self.time);
        }
    }

    fn kinematics(&mut self, h: f64) {
        self.refresh_grid();
        self.grid_fresh = false; // bodies move below
        let bodies = &self.grid;
        let map = &*self.map;
        let now = self.time;
        for_each_maybe_par(&mut self.robots, |(i, r)| {
            if r.spec.wander {
                wander(r, map, now);
            }
            let d = r.spec.drive.clone();
            let target = if r.spec.fixed || now - r.command_time > d.command_timeout {
                (0.0, 0.0)
            } else {
                r.command
            };
            let v = approach(r.velocity.0, target.0, d.max_accel * h);
            let w = approach(r.velocity.1, target.1, d.max_turn_accel * h);
            let (pose, done) = advance(map, bodies, i, r.pose, v, w, h, d.radius);
            let bumped = done < 1.0;
            if bumped && !r.bumped {
                r.contacts += 1;
                log_contact(map, bodies, i, r, v, w, now);
            }
            r.bumped = bumped;
            r.velocity = if r.bumped { (0.0, w) } else { (v, w) };
            odometry(r, pose, &d);
            r.pose = pose;
            // Camera drive.
            if let Some(c) = &r.spec.camera {
                let step = c.pan_speed_deg.to_radians() * h;
                r.ptz.pan = approach(r.ptz.pan, r.ptz_target.pan, step);
                r.ptz.tilt = approach(r.ptz.tilt, r.ptz_target.tilt, step);
                r.ptz.zoom = approach(r.ptz.zoom, r.ptz_target.zoom, 2.0 * h);
            }
        });
        let offset = self.robots.len();
        let nav = &self.nav;
        for_each_maybe_par(&mut self.people, |(k, p)| {
            walk(p, nav, map, bodies, offset + k, now, h)
        });
    }

    fn sense(&mut self, all: bool) {
        let now = self.time;
        if !all && !self.robots.iter().any(|r| r.sensor_due(now)) {
            return; // sensors run at their own rates, slower than kinematics
        }
        self.refresh_grid();
        let grid = &self.grid;
        let map = &*self.map;
        for_each_maybe_par(&mut self.robots, |(i, r)| {
            let eps = 1e-9;
            if !(all || r.sensor_due(now)) {
                return;
            }
            // One grid query for all of this robot's sensors: the bodies within the
            // longest reach (each sensor then looks within its own).
            let reach = [
                r.spec.laser.as_ref().map(|l| l.range),
                r.spec.sonar.as_ref().map(|s| s.range),
                r.spec.camera.as_ref().map(|c| camera_cone(c, r.ptz.zoom).1),
            ]
            .into_iter()
            .flatten()
            .fold(0.0, f64::max);
            NEARBY.with(|nearby| {
                let bodies = &mut *nearby.borrow_mut();
                bodies.gather(grid, r.pose.x, r.pose.y, reach + 0.5);
                let bodies = &*bodies;
                if let Some(l) = &r.spec.laser {
                    if all || now + eps >= r.next[0] {
                        laser_scan(map, bodies, i, r.pose, l, &mut r.rng, &mut r.laser);
                        r.laser_time = now;
                        r.next[0] = next_time(r.next[0], now, l.rate);
                    }
                }
                if let Some(s) = &r.spec.sonar {
                    if all || now + eps >= r.next[1] {
                        sonar_ring(map, bodies, i, r.pose, s, &mut r.rng, &mut r.sonar);
                        r.sonar_time = now;
                        r.next[1] = next_time(r.next[1], now, s.rate);
                    }
                }
                if let Some(c) = &r.spec.camera {
                    if all || now + eps >= r.next[2] {
                        camera_frame(
                            map,
                            bodies,
                            i,
                            r.pose,
                            r.ptz,
                            c,
                            &mut r.rng,
                            &mut r.detections,
                        );
                        r.camera_time = now;
                        r.next[2] = next_time(r.next[2], now, c.rate);
                    }
                }
            });
        });
    }
}

thread_local! {
    /// The bodies near the robot a thread is sensing for.
    static NEARBY: std::cell::RefCell<Nearby> = std::cell::RefCell::new(Nearby::default());
}

/// Every body: the robots, then the people.
fn bodies<'a>(robots: &'a [Robot], people: &'a [Person]) -> impl Iterator<Item = Body> + 'a {
    let robots = robots.iter().map(|r| Body {
        x: r.pose.x,
        y: r.pose.y,
        r: r.spec.drive.radius,
        beacon: r.spec.beacon,
        height: ROBOT_HEIGHT,
    });
    robots.chain(people.iter().map(|p| Body {
        x: p.pose.x,
        y: p.pose.y,
        r: PERSON_RADIUS,
        beacon: Some(p.beacon),
        height: PERSON_HEIGHT,
    }))
}

/// Runs `f` over the items; on the thread pool only when there are enough of them to
/// pay for waking it (for a handful of robots, waking the pool 200 times a simulated
/// second costs more than the work).
fn for_each_maybe_par<T: Send>(items: &mut [T], f: impl Fn((usize, &mut T)) + Sync + Send) {
    if items.len() < PARALLEL_FROM {
        items.iter_mut().enumerate().for_each(f);
    } else {
        items.par_iter_mut().enumerate().for_each(f);
    }
}

fn next_time(prev: f64, now: f64, rate: f64) -> f64 {
    let period = 1.0 / rate;
    let mut t = prev + period;
    if t <= now {
        t = now + period; // fell behind (large step): resync
    }
    t
}

/// Says what a robot touched, where, and how it was moving, for diagnosing contacts.
fn log_contact(
    map: &OccupancyMap,
    bodies: &BodyGrid,
    me: usize,
    r: &Robot,
    v: f64,
    w: f64,
    now: f64,
) {
    let p = r.pose;
    let radius = r.spec.drive.radius;
    let wall = map.clearance(p.x, p.y, radius + 1.0) - radius;
    let mut nearest: Option<(usize, f64, f64)> = None;
    bodies.near(p.x, p.y, radius + 1.0, |n, b| {
        if n != me {
            let gap = (b.x - p.x).hypot(b.y - p.y) - radius - b.r;
            let bearing = wrap((b.y - p.y).atan2(b.x - p.x) - p.theta).to_degrees();
            if nearest.is_none_or(|(_, g, _)| gap < g) {
                nearest = Some((n, gap, bearing));
            }
        }
    });
    let (body, gap, bearing) =
        nearest.map_or((None, f64::INFINITY, 0.0), |(n, g, b)| (Some(n), g, b));
    tracing::info!(
        robot = %r.spec.name,
        t = format!("{now:.2}"),
        x = format!("{:.2}", p.x),
        y = format!("{:.2}", p.y),
        theta_deg = format!("{:.0}", p.theta.to_degrees()),
        v = format!("{v:.3}"),
        w = format!("{w:.3}"),
        commanded = format!("{:.3},{:.3}", r.command.0, r.command.1),
        wall_gap = format!("{wall:.3}"),
        body = ?body,
        body_gap = format!("{gap:.3}"),
        body_bearing_deg = format!("{bearing:.0}"),
        "contact"
    );
}

/// Moves a body along the arc (v, w, h) as far as it can without touching a wall or
/// coming closer than half the gap to another body. Returns the pose and the fraction
/// of the arc driven.
#[allow(clippy::too_many_arguments)]
fn advance(
    map: &OccupancyMap,
    bodies: &BodyGrid,
    me: usize,
    p: Pose,
    v: f64,
    w: f64,
    h: f64,
    r: f64,
) -> (Pose, f64) {
    let length = v.abs() * h;
    if length < 1e-12 {
        return (integrate(p, 0.0, w, h), 1.0); // turning in place sweeps no new space
    }
    let reach = r + SKIN;
    // Other bodies move in the same step: each may close at most half the gap measured
    // at the start, so the budget is fixed here, not re-measured on the way.
    let budget = bodies.half_gap(me, p.x, p.y, r, length + 0.01);
    let mut s = 0.0;
    for _ in 0..64 {
        let q = if s == 0.0 {
            p
        } else {
            integrate(p, v, w, h * s)
        };
        let left = length * (1.0 - s);
        let walls = map.clearance(q.x, q.y, reach + left) - reach;
        let others = budget - length * s;
        let free = walls.min(others);
        if free >= left {
            return (integrate(p, v, w, h), 1.0);
        }
        if free > 1e-6 {
            s += free / length; // arc length ≥ displacement, so this never overshoots
            continue;
        }
        // Touching: a short step is allowed only if it moves away from what we touch.
        let tiny = (0.002 / length).min(1.0 - s);
        let t = integrate(p, v, w, h * (s + tiny));
        let walls_after = map.clearance(t.x, t.y, reach + 0.01) - reach;
        let others_after = bodies.half_gap(me, t.x, t.y, r, 0.01);
        let away_from_walls = walls > 1e-6 || walls_after > walls.max(0.0);
        // Bodies already overlapping (budget < 0) may still move apart.
        let away_from_bodies = others > 1e-6 || others_after > budget;
        if away_from_walls && away_from_bodies && walls_after >= 0.0 {
            s += tiny;
            continue;
        }
        break;
    }
    (integrate(p, v, w, h * s), s)
}

fn odometry(r: &mut Robot, new: Pose, d: &DriveParams) {
    let (dx, dy) = (new.x - r.pose.x, new.y - r.pose.y);
    let dist = dx.hypot(dy);
    let dtheta = wrap(new.theta - r.pose.theta);
    if dist == 0.0 && dtheta == 0.0 {
        return;
    }
    let noisy = |rng: &mut Pcg64, x: f64, frac: f64| {
        use rand_distr::Distribution;
        let sd = frac * x.abs();
        if sd > 0.0 {
            x + rand_distr::Normal::new(0.0, sd)
                .map(|n| n.sample(rng))
                .unwrap_or(0.0)
        } else {
            x
        }
    };
    let forward = dist.copysign(dx * r.pose.theta.cos() + dy * r.pose.theta.sin());
    let f = noisy(&mut r.rng, forward, d.odom_noise_linear);
    let t = noisy(&mut r.rng, dtheta, d.odom_noise_angular);
    let mid = r.odom.theta + t / 2.0;
    r.odom = Pose {
        x: r.odom.x + f * mid.cos(),
        y: r.odom.y + f * mid.sin(),
        theta: wrap(r.odom.theta + t),
    };
}

/// The built-in wander controller: drive ahead, turn away from anything close in front.
fn wander(r: &mut Robot, map: &OccupancyMap, now: f64) {
    let front = if r.laser.is_empty() {
        let p = r.pose;
        let ahead = integrate(p, 1.0, 0.0, 0.6);
        map.clearance(ahead.x, ahead.y, 1.0) + 0.35
    } else {
        let n = r.laser.len();
        let (lo, hi) = (n * 3 / 8, (n * 5 / 8).max(n * 3 / 8 + 1));
        r.laser[lo..hi.min(n)]
            .iter()
            .copied()
            .fold(f32::INFINITY, f32::min) as f64
    };
    let d = &r.spec.drive;
    let cmd = if front < 0.8 || r.bumped {
        if r.turning == 0.0 {
            r.turning = if r.rng.random::<bool>() { 1.0 } else { -1.0 };
        }
        (0.0, r.turning * d.max_turn.min(1.5))
    } else {
        r.turning = 0.0;
        let drift = (r.rng.random::<f64>() - 0.5) * 0.6;
        (d.max_speed.min(0.7), drift)
    };
    r.command = cmd;
    r.command_time = now;
}

/// A person's step: pause, or walk the navigation gradient to the current place.
fn walk(
    p: &mut Person,
    nav: &Navigation,
    map: &OccupancyMap,
    bodies: &BodyGrid,
    me: usize,
    now: f64,
    h: f64,
) {
    if now < p.pause_until || nav.places() == 0 {
        p.progress = (p.pose.x, p.pose.y, now);
        return;
    }
    // Boxed in (by other people, robots, a crowd in a door) for a while, a person goes
    // somewhere else instead.
    if (p.pose.x - p.progress.0).hypot(p.pose.y - p.progress.1) > 0.3 {
        p.progress = (p.pose.x, p.pose.y, now);
    } else if now - p.progress.2 >= HELD_UP_AFTER {
        p.held_up += h;
    }
    if now - p.progress.2 > STUCK_GIVE_UP {
        p.progress = (p.pose.x, p.pose.y, now);
        let places = nav.places();
        p.target = (p.target + 1 + p.rng.random_range(0..places.max(2) - 1)) % places;
    }
    let arrived = nav
        .distance(p.target, p.pose.x, p.pose.y)
        .is_none_or(|d| d < 0.4);
    if arrived {
        // Stop a while, then pick another place.
        p.pause_until = now + 2.0 + p.rng.random::<f64>() * 6.0;
        let places = nav.places();
        p.target = (p.target + 1 + p.rng.random_range(0..places.max(2) - 1)) % places;
        return;
    }
    if p.rng.random::<f64>() < 0.05 * h {
        // Now and then: stop and look around.
        p.pause_until = now + 1.0 + p.rng.random::<f64>() * 2.0;
        p.pose.theta = wrap(p.pose.theta + (p.rng.random::<f64>() - 0.5) * 2.0);
        return;
    }
    let Some(heading) = nav.heading(p.target, p.pose.x, p.pose.y) else {
        return;
    };
    // Straight on if possible; otherwise sidestep round a corner or another body.
    for turn in [0.0, 0.5, -0.5, 1.0, -1.0, 1.57, -1.57] {
        let start = Pose {
            theta: wrap(heading + turn),
            ..p.pose
        };
        let (pose, done) = advance(map, bodies, me, start, p.speed, 0.0, h, PERSON_RADIUS);
        if done > 0.5 || turn == -1.57 {
            p.pose = pose;
            break;
        }
    }
}

/// A person walking who has not got 0.3 m further for this long is held up, s (free,
/// she walks it in under half a second).
pub const HELD_UP_AFTER: f64 = 1.0;

/// A person who cannot move on for this long picks another place, s.
pub const STUCK_GIVE_UP: f64 = 5.0;

/// `n` places spread over the free space of a map, for scenarios that name none.
pub fn sample_places(map: &OccupancyMap, seed: u64, n: usize) -> Vec<(f64, f64)> {
    let mut rng = seeded(seed, 3, 0);
    let (w, h) = map.size();
    let (ox, oy) = map.origin();
    let mut out = Vec::new();
    for _ in 0..n * 200 {
        if out.len() == n {
            break;
        }
        let (x, y) = (ox + rng.random::<f64>() * w, oy + rng.random::<f64>() * h);
        if map.clearance(x, y, 0.6) >= 0.6 {
            out.push((x, y));
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
#[path = "world_tests.rs"]
mod tests;
