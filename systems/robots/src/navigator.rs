//! Following a planned path without touching anything: pure pursuit toward a carrot on
//! the path, with speed limited by the free distance ahead. The free distance is the
//! robot's footprint (a parry2d `Ball`) cast along its heading against what laser and
//! sonar see right now (the scan as parry2d polylines, split where the scan jumps, and
//! sonar echoes as points), so the robot neither slips between two beams nor drives
//! into a person the map does not know. Blocked for a while, it replans round what it
//! sees; blocked for good, it waits and says so.
//!
//! Pure: fed with sim time, the pose estimate and obstacle points.

use crate::planner::{path_length, PlanError, Planner};
use muster_world_model::kinematics::{wrap, Pose};
use parry2d::math::{Pose2, Vec2};
use parry2d::query::{cast_shapes, ShapeCastOptions};
use parry2d::shape::{Ball, Polyline};
use std::sync::Arc;

/// How the navigator drives.
#[derive(Clone, Debug, PartialEq)]
pub struct NavParams {
    /// Top speed, m/s.
    pub max_speed: f64,
    /// Top speed with more than `sprint_beyond` of path left, m/s: a robot fallen
    /// behind a person it follows (who walks at up to 0.7 m/s) catches up at the
    /// difference, so at `max_speed` alone a gap of a few metres takes a minute to
    /// close. Every other limit (free distance, fields, bodies) holds as at any speed.
    /// Never below `max_speed`.
    pub sprint_speed: f64,
    /// Path left beyond which `sprint_speed` applies, m.
    pub sprint_beyond: f64,
    /// Top turn rate, rad/s.
    pub max_turn: f64,
    /// Braking the speed limit assumes, m/s² (below the robot's own limit).
    pub brake: f64,
    /// Time between a reading and the robot acting on it, s (sensor period plus margin).
    pub reaction: f64,
    /// Gap kept to anything ahead, m.
    pub stop_gap: f64,
    /// Pure-pursuit carrot distance, m.
    pub lookahead: f64,
    /// Turn-rate gain on the heading error, 1/s.
    pub turn_gain: f64,
    /// Blocked this long, it replans round what it sees, s.
    pub replan_after: f64,
    /// The footprint's radius: the robot's radius plus a skin, m.
    pub footprint: f64,
    /// Depth of the protective field beyond the footprint: anything in it stops the
    /// robot, m.
    pub protective_field: f64,
    /// Depth of the warning field beyond the footprint: anything in it slows the robot, m.
    pub warning_field: f64,
    /// Top speed inside the warning field, m/s.
    pub warning_speed: f64,
    /// A body not on the map (a person) closer than this beyond the footprint, in
    /// front or to the side, stops the robot, m.
    pub body_protective: f64,
    /// ... and closer than this slows it, m.
    pub body_warning: f64,
    /// The fastest a body not on the map is taken to walk, m/s: the body fields grow by
    /// the distance it walks in the controller's latency ([`Navigator::set_latency`]),
    /// and with one in its lane ahead the robot is never faster than it can stop at
    /// before that body, walking straight at it, could reach it (speed and separation
    /// monitoring, as in ISO/TS 15066), down to the warning speed; the protective field
    /// does the rest.
    pub body_speed: f64,
    /// Half-width of that lane beyond the footprint, m.
    pub body_lane: f64,
    /// Time from a reading to the robot acting on it in that speed limit, s (the sensor
    /// period and the drive's lag; the measured latency is added).
    pub body_reaction: f64,
}

impl Default for NavParams {
    fn default() -> Self {
        NavParams {
            max_speed: 0.8,
            sprint_speed: 0.8,
            sprint_beyond: 3.0,
            max_turn: 1.5,
            brake: 0.6,
            reaction: 0.25,
            stop_gap: 0.3,
            lookahead: 0.8,
            turn_gain: 2.0,
            replan_after: 2.0,
            footprint: 0.28,
            protective_field: 0.1,
            warning_field: 0.45,
            warning_speed: 0.12,
            body_protective: 0.3,
            body_warning: 0.8,
            body_speed: 0.8,
            body_lane: 0.3,
            body_reaction: 0.35,
        }
    }
}

/// One control step's result.
#[derive(Clone, Debug, PartialEq)]
pub struct NavStep {
    /// Velocity command (m/s, rad/s).
    pub velocity: (f64, f64),
    /// Path length left to the goal, m.
    pub remaining: f64,
    /// Blocked since this sim time (something in the way and no way round yet).
    pub blocked_since: Option<f64>,
    /// The last (re)plan failed: why.
    pub error: Option<PlanError>,
    /// Free distance ahead along the heading, m (capped at the look distance).
    pub free_ahead: f64,
}

/// Drives a robot along planned paths.
pub struct Navigator {
    planner: Arc<Planner>,
    params: NavParams,
    goal: Option<(f64, f64)>,
    planned_for: Option<(f64, f64)>,
    path: Vec<(f64, f64)>,
    next: usize,
    blocked_since: Option<f64>,
    last_replan: f64,
    error: Option<PlanError>,
    /// Getting clear of something pressing on the robot: a map heading, until a time.
    escape: Option<(f64, f64)>,
    /// Time from a reading to the robot acting on the command made from it, beyond the
    /// sensor period (a process's wake-up, scheduling, the simulator's step), s.
    latency: f64,
    /// Getting clear keeps this map point within this angle of the heading, if it can
    /// ([`Navigator::keep_in_view`]).
    keep_in_view: Option<((f64, f64), f64)>,
    /// Whether `sprint_speed` may apply ([`Navigator::allow_sprint`]).
    sprint: bool,
}

/// The laser's period: a body moves this long between two looks at it, s.
const SENSOR_PERIOD: f64 = 0.1;

/// A body within the body protective field stops the robot when it lies within this
/// angle either side of the heading, rad (70°), or beside it on the side it turns to;
/// beside it otherwise, only the warning field's speed holds.
const STOP_CONE: f64 = 70.0 * std::f64::consts::PI / 180.0;

/// How fast a robot creeps clear giving way or making room, m/s.
const CREEP: f64 = 0.2;

/// The most a robot stuck on its way drives while it gets clear, m/s.
const ESCAPE_SPEED: f64 = 0.3;

/// How far ahead the footprint is cast, m.
const LOOK: f64 = 3.0;

/// Distances from the path, m, at which a sprinting robot looks for places a person
/// could stand in unseen ([`Navigator::hidden_beside_way`]): from just beside its lane
/// to a step and a half away.
const SIDE_REACH: [f64; 3] = [0.5, 0.9, 1.3];

/// Spacing along the path of those looks, m.
const SIDE_STEP: f64 = 0.25;

/// A place a person fits in is this far from any wall, m.
const PERSON_RADIUS: f64 = 0.2;

impl Navigator {
    /// A navigator planning on `planner`.
    pub fn new(planner: Arc<Planner>, params: NavParams) -> Self {
        Navigator {
            planner,
            params,
            goal: None,
            planned_for: None,
            path: Vec::new(),
            next: 0,
            blocked_since: None,
            last_replan: f64::NEG_INFINITY,
            error: None,
            escape: None,
            latency: 0.0,
            keep_in_view: None,
            sprint: false,
        }
    }

    /// How it drives.
    pub fn params(&self) -> &NavParams {
        &self.params
    }

    /// The goal being driven to.
    pub fn goal(&self) -> Option<(f64, f64)> {
        self.goal
    }

    /// The current path's waypoints.
    pub fn path(&self) -> &[(f64, f64)] {
        &self.path
    }

    /// Held up since this sim time, as its last step said ([`NavStep::blocked_since`]);
    /// `None` once it is cleared or halted.
    pub fn blocked_since(&self) -> Option<f64> {
        self.blocked_since
    }

    /// Drive to `goal` from `pose`. Plans at once unless the goal moved less than
    /// `replan_within` metres from the one planned for (a followed target's small
    /// moves just shift the path's end).
    pub fn set_goal(
        &mut self,
        pose: Pose,
        goal: (f64, f64),
        replan_within: f64,
    ) -> Result<(), PlanError> {
        self.goal = Some(goal);
        if let Some(p) = self.planned_for {
            if (p.0 - goal.0).hypot(p.1 - goal.1) < replan_within && !self.path.is_empty() {
                if let Some(last) = self.path.last_mut() {
                    *last = goal;
                }
                return Ok(());
            }
        }
        self.replan(pose, &[])
    }

    /// Stop and forget the goal.
    pub fn clear(&mut self) {
        self.goal = None;
        self.planned_for = None;
        self.path.clear();
        self.next = 0;
        self.blocked_since = None;
        self.error = None;
        self.escape = None;
    }

    /// Stop and forget the goal, but finish getting clear of anything pressing on the
    /// robot ([`Navigator::give_way`]): for a robot that halts again at every step.
    pub fn halt(&mut self) {
        let escape = self.escape.take();
        self.clear();
        self.escape = escape;
    }

    /// While getting clear ([`Navigator::give_way`], [`Navigator::make_room`]), keep the
    /// map point `at` within `within` rad of the heading when a free heading allows it
    /// (a tracker's camera pans only so far: turning its back on the person it follows
    /// loses her). `None`: any heading.
    pub fn keep_in_view(&mut self, at: Option<(f64, f64)>, within: f64) {
        self.keep_in_view = at.map(|a| (a, within));
    }

    /// The robot-frame headings getting clear may take at `pose`, as [`Navigator::keep_in_view`] says.
    fn in_view(&self, pose: Pose) -> impl Fn(f64) -> bool {
        let keep = self
            .keep_in_view
            .map(|((x, y), within)| (wrap((y - pose.y).atan2(x - pose.x) - pose.theta), within));
        move |a| keep.is_none_or(|(bearing, within)| wrap(a - bearing).abs() <= within)
    }

    fn replan(&mut self, pose: Pose, obstacles: &[(f64, f64, f64)]) -> Result<(), PlanError> {
        let Some(goal) = self.goal else { return Ok(()) };
        self.planned_for = Some(goal);
        match self.planner.plan((pose.x, pose.y), goal, obstacles) {
            Ok(path) => {
                self.path = path;
                self.next = 0;
                self.error = None;
                Ok(())
            }
            Err(e) => {
                self.error = Some(e.clone());
                Err(e)
            }
        }
    }

    /// A halted robot gives way: when something presses on it (closer than the
    /// footprint plus a few centimetres, e.g. a person who walked into it), it turns
    /// away and creeps clear. Returns the velocity while it does, `None` when nothing
    /// presses on it.
    pub fn give_way(
        &mut self,
        now: f64,
        pose: Pose,
        obstacles: &[(f64, f64)],
    ) -> Option<(f64, f64)> {
        let (footprint, stop_gap) = (self.params.footprint, self.params.stop_gap);
        // Creeping clear never runs into someone else: not with a body in the protective
        // field (grown by the latency) where its creeping closes on it.
        let bodies = self.bodies(pose, obstacles);
        let creep_blocked = self.creep_check(obstacles, &bodies);
        let creep = |w: f64| {
            let body_near = creep_blocked(CREEP, w);
            if !body_near && free_distance(footprint, obstacles, 1.0) > stop_gap {
                CREEP
            } else {
                0.0
            }
        };
        if let Some(v) = self.escaping(now, pose, creep) {
            return Some(v);
        }
        let p = &self.params;
        let (d, toward) = obstacles
            .iter()
            .map(|&(x, y)| (x.hypot(y), y.atan2(x)))
            .min_by(|a, b| a.0.total_cmp(&b.0))?;
        if d >= p.footprint + 0.04 {
            return None;
        }
        let away = wrap(toward + std::f64::consts::PI);
        // Pressed on, it gets clear even if it must turn its back.
        let a = escape_heading(p.footprint, obstacles, away, 0.4, self.in_view(pose))
            .or_else(|| escape_heading(p.footprint, obstacles, away, 0.4, |_| true))?;
        self.escape = Some((wrap(pose.theta + a), now + 3.0));
        Some((0.0, 0.0))
    }

    /// Gets out of the way of something at bearing `toward` (rad, robot frame) that
    /// needs to pass, before it presses on the robot (a followed person who turns back
    /// in a doorway): turns away and creeps clear along the free heading nearest to
    /// straight away, as [`Navigator::give_way`] does when pressed. `None` when there is
    /// no free heading.
    pub fn make_room(
        &mut self,
        now: f64,
        pose: Pose,
        obstacles: &[(f64, f64)],
        toward: f64,
    ) -> Option<(f64, f64)> {
        if self.escape.is_none_or(|(_, until)| now >= until) {
            let away = wrap(toward + std::f64::consts::PI);
            let a = escape_heading(
                self.params.footprint,
                obstacles,
                away,
                0.4,
                self.in_view(pose),
            )?;
            self.escape = Some((wrap(pose.theta + a), now + 3.0));
        }
        self.give_way(now, pose, obstacles)
    }

    /// How far from its centre a body the map does not know could be and still reach
    /// the footprint, ahead of or beside it, before a creeping robot's next command
    /// acts: within the protective
    /// field plus the distance it walks in a sensor period and the latency. (The wider
    /// body field would also hold a robot still beside another halted robot, and two
    /// followers of one person then hold each other in a doorway for good.)
    fn creep_reach(&self) -> f64 {
        let p = &self.params;
        p.footprint + p.protective_field + p.body_speed * (SENSOR_PERIOD + self.latency)
    }

    /// Whether a body point lies ahead of or beside the robot within `reach` of its
    /// centre.
    fn body_within(obstacles: &[(f64, f64)], bodies: &[bool], reach: f64) -> bool {
        obstacles
            .iter()
            .zip(bodies)
            .any(|(&(x, y), &body)| body && x > -0.1 && x.hypot(y) < reach)
    }

    /// While getting clear: turn to the escape heading, and once facing it (within
    /// 0.3 rad) move at `speed()`. `None` when not escaping (any more).
    fn escaping(
        &mut self,
        now: f64,
        pose: Pose,
        speed: impl FnOnce(f64) -> f64,
    ) -> Option<(f64, f64)> {
        let (heading, until) = self.escape?;
        if now >= until {
            self.escape = None;
            return None;
        }
        let p = &self.params;
        let e = wrap(heading - pose.theta);
        let w = (p.turn_gain * e).clamp(-p.max_turn, p.max_turn);
        let v = if e.abs() < 0.3 { speed(w) } else { 0.0 };
        Some((v, w))
    }

    /// The segment the robot is on (index of its end waypoint; the first segment starts
    /// where the path was planned from) and how far along it (0..=1). Looks a few
    /// segments ahead only, and never goes back, so a path that doubles back on itself
    /// is followed in order.
    fn progress(&self, pose: Pose) -> (usize, f64) {
        let p = (pose.x, pose.y);
        let last = self.path.len() - 1;
        let mut best = (self.next.min(last), 0.0, f64::INFINITY);
        for k in self.next..=(self.next + 3).min(last) {
            let (t, d) = project(self.segment_start(k), self.path[k], p);
            if d < best.2 - 1e-9 {
                best = (k, t, d);
            }
        }
        let (mut k, mut t, _) = best;
        if t >= 1.0 - 1e-9 && k < last {
            k += 1;
            t = 0.0;
        }
        (k, t)
    }

    fn segment_start(&self, k: usize) -> (f64, f64) {
        if k == 0 {
            self.path[0]
        } else {
            self.path[k - 1]
        }
    }

    /// Whether the robot may drive faster than `max_speed` on a long way (up to
    /// `sprint_speed`): the caller allows it while catching up with a person it sees,
    /// not on the way to where one was last seen (she may stand there, out of sight).
    pub fn allow_sprint(&mut self, on: bool) {
        self.sprint = on;
    }

    /// Whether someone could stand beside the way ahead out of the robot's sight: a place
    /// a person fits in, within [`SIDE_REACH`] of the path's next [`LOOK`] metres and
    /// joined to the path by a straight line the walls leave open, that the map hides
    /// from the robot where it is (a doorway's recess, a corridor coming in from the
    /// side, the far side of a corner). People step out of such places into the way,
    /// and a robot faster than its cruising speed could not stop for them (seen in
    /// simulation: a person stepping out of a doorway, another round a junction's
    /// corner). The laser cannot see past walls, so this asks the map.
    fn hidden_beside_way(&self, pose: Pose, here: (f64, f64), rest: &[(f64, f64)]) -> bool {
        let me = (pose.x, pose.y);
        let mut s = 0.0;
        while s <= LOOK {
            let a = along(here, rest, s);
            let b = along(here, rest, s + 0.1);
            let (dx, dy) = (b.0 - a.0, b.1 - a.1);
            let len = dx.hypot(dy);
            if len < 1e-6 {
                // The path ends here.
                break;
            }
            let (nx, ny) = (-dy / len, dx / len);
            for side in [-1.0, 1.0] {
                for off in SIDE_REACH {
                    let q = (a.0 + side * nx * off, a.1 + side * ny * off);
                    if self.planner.wall_distance(q.0, q.1) >= PERSON_RADIUS
                        && self.planner.in_sight(a, q)
                        && !self.planner.in_sight(me, q)
                    {
                        return true;
                    }
                }
            }
            s += SIDE_STEP;
        }
        false
    }

    /// Tells the navigator how late its commands act (measured by its shell): the
    /// reaction time of the speed limit and the body fields grow with it, so that a
    /// slower controller keeps the same margins. Not capped: a latency of seconds (seen
    /// on a loaded machine: 1.9–2.6 s) grows the fields by metres, and the robot stops
    /// near anyone rather than keep margins made for a fraction of it. A latency that
    /// is not a number is ignored.
    pub fn set_latency(&mut self, latency: f64) {
        if latency.is_finite() {
            self.latency = latency.max(0.0);
        }
    }

    /// Which obstacle points (in the robot's frame) are bodies the map does not know
    /// (people, robots): more than a grid cell from any wall, with another such point
    /// within 0.2 m. A lone one is the laser's noise or the pose estimate's error putting
    /// a wall's point a cell off it (which made a wall into a person now and then, and
    /// the robot crept past it at the warning speed); a body is wider than one beam.
    /// Two cells off instead would miss a person in a doorway, where every point of her
    /// is near a wall.
    fn bodies(&self, pose: Pose, obstacles: &[(f64, f64)]) -> Vec<bool> {
        let (s, c) = pose.theta.sin_cos();
        let cell = self.planner.params().cell;
        let off: Vec<bool> = obstacles
            .iter()
            .map(|&(x, y)| {
                self.planner
                    .wall_distance(pose.x + c * x - s * y, pose.y + s * x + c * y)
                    > cell
            })
            .collect();
        let candidates: Vec<usize> = (0..obstacles.len()).filter(|&k| off[k]).collect();
        let mut body = vec![false; obstacles.len()];
        for &k in &candidates {
            let (x, y) = obstacles[k];
            body[k] = candidates
                .iter()
                .any(|&j| j != k && (obstacles[j].0 - x).hypot(obstacles[j].1 - y) < 0.2);
        }
        body
    }

    /// The bodies creeping clear (at `v`, turning at `w`) would close on, able to reach
    /// the footprint before the next command acts: within [`Self::creep_reach`] and where
    /// the creeping closes on them ([`Self::ahead_of_motion`]). A body beside or behind,
    /// which creeping moves away from, does not hold it: that held two robots each
    /// waiting for the other to creep clear first (a tracker in a doorway, its target
    /// boxed in behind it, and a follower just outside).
    fn creep_check<'a>(
        &self,
        obstacles: &'a [(f64, f64)],
        bodies: &'a [bool],
    ) -> impl Fn(f64, f64) -> bool + 'a {
        let reach = self.creep_reach();
        let (reaction, brake) = (self.params.body_reaction + self.latency, self.params.brake);
        move |v, w| {
            obstacles.iter().zip(bodies).any(|(&(x, y), &body)| {
                body && x.hypot(y) < reach && closes_on(x, y, v, w, reaction, brake)
            })
        }
    }

    /// Whether a point (robot frame) lies where driving on closes on it: within ±70° of
    /// the heading, widened on the side the robot turns to by the angle it turns
    /// before a command made now has stopped it: turn rate `w` times the body reaction
    /// time, the latency and the time to brake from `v` (it still rolls forward while it
    /// brakes, and a body behind its shoulder comes round to its side meanwhile).
    fn ahead_of_motion(&self, x: f64, y: f64, v: f64, w: f64) -> bool {
        let p = &self.params;
        closes_on(x, y, v, w, p.body_reaction + self.latency, p.brake)
    }

    /// The speed at which the robot can still stop before any body the map does not know,
    /// in its lane ahead or where its driving closes on it ([`Self::ahead_of_motion`]),
    /// could reach it walking straight at it: gap g > vb·(T + v/a) +
    /// v·T + v²/2a, with T the body reaction time plus the latency and a the braking.
    fn body_speed_limit(&self, obstacles: &[(f64, f64)], bodies: &[bool], v: f64, w: f64) -> f64 {
        let p = &self.params;
        let gap = obstacles
            .iter()
            .zip(bodies)
            .filter(|&(&(x, _), &body)| body && x > 0.0)
            .map(|(&(x, y), _)| (x, y, x.hypot(y)))
            .filter(|&(x, y, d)| {
                d < p.footprint + LOOK
                    && (y.abs() < p.footprint + p.body_lane || self.ahead_of_motion(x, y, v, w))
            })
            .map(|(_, _, d)| d - p.footprint)
            .fold(f64::INFINITY, f64::min);
        let (a, t, vb) = (p.brake, p.body_reaction + self.latency, p.body_speed);
        let room = gap - vb * t;
        if room <= 0.0 {
            return 0.0;
        }
        if !room.is_finite() {
            return f64::INFINITY;
        }
        let b = t + vb / a;
        a * ((b * b + 2.0 * room / a).sqrt() - b)
    }

    /// One control step at sim time `now` from the pose estimate `pose`, with obstacle
    /// points in the robot's frame (x ahead, y left) from laser and sonar.
    pub fn step(&mut self, now: f64, pose: Pose, obstacles: &[(f64, f64)]) -> NavStep {
        let free_ahead = free_distance(self.params.footprint, obstacles, 1.0);
        let idle = NavStep {
            velocity: (0.0, 0.0),
            remaining: 0.0,
            blocked_since: None,
            error: self.error.clone(),
            free_ahead,
        };
        if self.goal.is_none() || self.path.is_empty() {
            return idle;
        }
        // Where along the path the robot is: the nearest of the next few segments.
        let (seg, t) = self.progress(pose);
        self.next = seg;
        let here = lerp(self.segment_start(seg), self.path[seg], t);
        let rest = &self.path[seg..];
        let remaining = (here.0 - pose.x).hypot(here.1 - pose.y) + path_length(here, rest);
        let carrot = along(here, rest, self.params.lookahead);
        let heading = (carrot.1 - pose.y).atan2(carrot.0 - pose.x);
        let err = wrap(heading - pose.theta);
        let p = &self.params;
        let w = (p.turn_gain * err).clamp(-p.max_turn, p.max_turn);
        let align = err.cos().max(0.0);
        let top = if self.sprint && remaining > p.sprint_beyond {
            p.sprint_speed.max(p.max_speed)
        } else {
            p.max_speed
        };
        let mut v = if err.abs() > 1.0 {
            0.0
        } else {
            top * align * align
        };
        // Slow down towards the end of the path.
        v = v.min((2.0 * p.brake * remaining).sqrt());
        // Never faster than can stop short of what is ahead, reaction time included.
        let room = (free_ahead - p.stop_gap).max(0.0);
        let reaction = p.reaction + self.latency;
        let v_safe =
            ((reaction * p.brake).powi(2) + 2.0 * p.brake * room).sqrt() - reaction * p.brake;
        let wants_forward = v > 0.05 || err.abs() <= 1.0;
        v = v.min(v_safe.max(0.0));
        let p = &self.params;
        // Safety fields, as on industrial vehicles: slow when anything is near in front
        // (people walk into a robot faster than it can see them coming round a corner),
        // stop when it is close. They are boxes ahead of the footprint, as wide as it
        // plus a side margin, so walls alongside a corridor or a door do not slow it.
        let bodies = self.bodies(pose, obstacles);
        // A box ahead `depth` deep and `side` wider than the footprint, holding any point
        // or (`bodies_only`) a body's.
        let inside = |depth: f64, side: f64, bodies_only: bool| {
            obstacles.iter().zip(&bodies).any(|(&(x, y), &body)| {
                (body || !bodies_only)
                    && x > -0.05
                    && x < p.footprint + depth
                    && y.abs() < p.footprint + side
            })
        };
        // Bodies the map does not know (people, robots) may walk into the robot: they
        // get wider fields, so that it has stopped before they reach it.
        let body_near = |reach: f64| Self::body_within(obstacles, &bodies, p.footprint + reach);
        // A body walks this far towards the robot before a command acts.
        let late = p.body_speed * self.latency;
        let body_slow = body_near(p.body_warning + late);
        // Faster than `max_speed` only with no body ahead or beside within the look
        // distance, and nowhere beside the way ahead that one could step out of unseen:
        // near people and robots, doorways and corners it keeps to its cruising speed.
        if v > p.max_speed && (body_near(LOOK) || self.hidden_beside_way(pose, here, rest)) {
            v = p.max_speed;
        }
        let in_protective = inside(p.protective_field, 0.05, false);
        // The warning field's side margin is for what may step into the lane (people,
        // robots); a wall alongside never does, and a robot may drive close along one.
        let in_warning = inside(p.warning_field, 0.05, false) || inside(p.warning_field, 0.2, true);
        let lane_limit = self
            .body_speed_limit(obstacles, &bodies, v, w)
            .max(p.warning_speed);
        let creep_blocked = self.creep_check(obstacles, &bodies);
        v = v.min(lane_limit);
        // Stopped only by bodies its driving would close on: ahead, within ±70°, and
        // beside or behind it on the side it turns to, as far round as it turns before
        // it has stopped from the speed it would drive at. A body right beside a robot
        // driving straight is not approached, and stopping for it held two robots side
        // by side in a corridor, each for the other, for minutes.
        let going = if in_warning || body_slow {
            v.min(p.warning_speed)
        } else {
            v
        };
        let body_stop = obstacles.iter().zip(&bodies).any(|(&(x, y), &body)| {
            let d = x.hypot(y);
            body && d < p.footprint + p.body_protective + late
                && self.ahead_of_motion(x, y, going, w)
        });
        // Getting clear: turn to the escape heading and creep out along it.
        if let Some(velocity) = self.escaping(now, pose, |w| {
            // Getting clear never runs into someone else: the lane limit and the body
            // protective field hold here too.
            if creep_blocked(ESCAPE_SPEED, w) {
                0.0
            } else {
                v_safe.clamp(0.0, ESCAPE_SPEED).min(lane_limit)
            }
        }) {
            return NavStep {
                velocity,
                remaining,
                blocked_since: self.blocked_since,
                error: self.error.clone(),
                free_ahead,
            };
        }
        let p = &self.params;
        let protective = in_protective || body_stop;
        if protective {
            v = 0.0;
        } else if in_warning || body_slow {
            v = v.min(p.warning_speed);
        }
        let stuck = wants_forward && (room < 0.02 || protective) && remaining > 0.3;
        if stuck
            && self
                .blocked_since
                .is_some_and(|b| now - b >= p.replan_after / 2.0)
        {
            // Something presses on the robot where it wants to go: find the free heading
            // nearest to the wanted one and get clear along it first.
            if let Some(a) = escape_heading(p.footprint, obstacles, err, p.stop_gap + 0.4, |_| true)
            {
                self.escape = Some((wrap(pose.theta + a), now + 2.0));
            }
        }
        if stuck {
            let since = *self.blocked_since.get_or_insert(now);
            if now - since >= p.replan_after && now - self.last_replan >= p.replan_after {
                self.last_replan = now;
                let seen = obstacles_in_map(pose, obstacles, 1.5);
                // A failed replan keeps the old path: the way may clear.
                let old = (self.path.clone(), self.next);
                if self.replan(pose, &seen).is_err() {
                    (self.path, self.next) = old;
                }
            }
        } else {
            self.blocked_since = None;
        }
        NavStep {
            velocity: (v, w),
            remaining,
            blocked_since: self.blocked_since,
            error: self.error.clone(),
            free_ahead,
        }
    }
}

/// The heading (relative to the robot's, rad) nearest to `wanted` along which the
/// footprint moves at least `need` metres free, if any.
///
/// Against something in contact, only headings that move away from it count: a body
/// pressed on the robot side-on lets it neither pass nor slide along (nor, in the
/// simulator, lets it move past itself).
fn escape_heading(
    radius: f64,
    pts: &[(f64, f64)],
    wanted: f64,
    need: f64,
    allowed: impl Fn(f64) -> bool,
) -> Option<f64> {
    let nearest = pts
        .iter()
        .map(|&(x, y)| (x.hypot(y), y.atan2(x)))
        .min_by(|a, b| a.0.total_cmp(&b.0));
    let touching = nearest.filter(|(d, _)| *d < radius + 0.05).map(|(_, a)| a);
    (0..24)
        .map(|k| wrap(f64::from(k) * std::f64::consts::PI / 12.0))
        .filter(|a| touching.is_none_or(|t| (a - t).cos() < -0.3) && allowed(*a))
        .filter(|a| {
            let (s, c) = (-a).sin_cos();
            let turned: Vec<(f64, f64)> = pts
                .iter()
                .map(|&(x, y)| (c * x - s * y, s * x + c * y))
                .collect();
            free_distance(radius, &turned, 1.0) >= need
        })
        .min_by(|a, b| wrap(a - wanted).abs().total_cmp(&wrap(b - wanted).abs()))
}

/// Whether driving at `v` and turning at `w` closes on a point (robot frame): within
/// ±70° of the heading ([`STOP_CONE`]), widened on the side the robot turns to by the
/// angle it turns in `reaction` s and while braking (at `brake`) to a stop.
fn closes_on(x: f64, y: f64, v: f64, w: f64, reaction: f64, brake: f64) -> bool {
    let bearing = y.atan2(x);
    let turn = (w.abs() * (reaction + v.max(0.0) / brake)).min(std::f64::consts::PI - STOP_CONE);
    bearing.abs() < STOP_CONE || (bearing * w > 0.0 && bearing.abs() < STOP_CONE + turn)
}

/// The point `distance` metres along the polyline `from` → `path`.
fn along(from: (f64, f64), path: &[(f64, f64)], distance: f64) -> (f64, f64) {
    let mut prev = from;
    let mut left = distance;
    for &q in path {
        let len = (q.0 - prev.0).hypot(q.1 - prev.1);
        if len >= left && len > 1e-12 {
            return lerp(prev, q, left / len);
        }
        left -= len;
        prev = q;
    }
    prev
}

fn lerp(a: (f64, f64), b: (f64, f64), t: f64) -> (f64, f64) {
    (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t)
}

/// The parameter (0..=1) of the point of a → b nearest to p, and its distance.
fn project(a: (f64, f64), b: (f64, f64), p: (f64, f64)) -> (f64, f64) {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let len2 = dx * dx + dy * dy;
    let t = if len2 < 1e-12 {
        1.0
    } else {
        (((p.0 - a.0) * dx + (p.1 - a.1) * dy) / len2).clamp(0.0, 1.0)
    };
    let q = lerp(a, b, t);
    (t, (q.0 - p.0).hypot(q.1 - p.1))
}

/// Obstacle points near the robot, in the map frame, as small circles for the planner.
fn obstacles_in_map(pose: Pose, pts: &[(f64, f64)], within: f64) -> Vec<(f64, f64, f64)> {
    let (s, c) = pose.theta.sin_cos();
    let mut out: Vec<(f64, f64, f64)> = Vec::new();
    for &(x, y) in pts {
        if x.hypot(y) > within {
            continue;
        }
        let m = (pose.x + c * x - s * y, pose.y + s * x + c * y);
        // Thin the points: one per 0.15 m.
        if out.iter().all(|o| (o.0 - m.0).hypot(o.1 - m.1) > 0.15) {
            out.push((m.0, m.1, 0.05));
        }
    }
    out
}

/// How far a footprint of radius `radius` can move along `direction` (+1 ahead, -1
/// back) from the robot's origin before touching an obstacle point, up to [`LOOK`].
///
/// The points are joined into parry2d polylines wherever neighbours are closer than the
/// footprint's diameter (the scan's surfaces; the robot cannot pass between such
/// points anyway), and the rest stay single points; the footprint `Ball` is cast
/// against each shape.
pub fn free_distance(radius: f64, pts: &[(f64, f64)], direction: f64) -> f64 {
    let ball = Ball::new(radius as f32);
    let vel = Vec2::new(direction.signum() as f32, 0.0);
    // A contact the motion moves away from does not stop it.
    let opts = ShapeCastOptions {
        stop_at_penetration: false,
        ..ShapeCastOptions::with_max_time_of_impact(LOOK as f32)
    };
    // Points that cannot be reached within the look distance are skipped.
    let join = (2.0 * radius) as f32;
    let mut runs: Vec<Vec<Vec2>> = Vec::new();
    for &(x, y) in pts {
        if x * direction.signum() <= -radius || x.hypot(y) >= LOOK + radius {
            continue;
        }
        let p = Vec2::new(x as f32, y as f32);
        match runs.last_mut() {
            Some(run) if run.last().is_some_and(|q| q.distance(p) <= join) => run.push(p),
            _ => runs.push(vec![p]),
        }
    }
    let mut best = LOOK;
    for run in runs {
        let hit = if run.len() == 1 {
            let at = Pose2::from_translation(run[0]);
            cast_shapes(
                &Pose2::IDENTITY,
                vel,
                &ball,
                &at,
                Vec2::ZERO,
                &Ball::new(0.01),
                opts,
            )
        } else {
            let line = Polyline::new(run, None);
            cast_shapes(
                &Pose2::IDENTITY,
                vel,
                &ball,
                &Pose2::IDENTITY,
                Vec2::ZERO,
                &line,
                opts,
            )
        };
        if let Ok(Some(hit)) = hit {
            best = best.min(f64::from(hit.time_of_impact));
        }
    }
    best
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::planner::PlannerParams;
    use muster_world_model::map::OccupancyMap;

    /// A planner on the built-in office floor, with the default parameters.
    fn office_planner() -> Arc<Planner> {
        Arc::new(Planner::new(
            &OccupancyMap::office(),
            PlannerParams::default(),
        ))
    }

    #[test]
    fn free_distance_sees_walls_between_beams_and_single_echoes() {
        // A wall 2 m ahead made of points 0.3 m apart: the footprint cannot pass.
        let wall: Vec<(f64, f64)> = (-5..=5).map(|k| (2.0, f64::from(k) * 0.3)).collect();
        let d = free_distance(0.28, &wall, 1.0);
        assert!((d - 1.72).abs() < 0.05, "free {d}");
        // A single echo off to the side does not block; one ahead does.
        assert_eq!(free_distance(0.28, &[(1.0, 0.5)], 1.0), LOOK);
        let d = free_distance(0.28, &[(1.0, 0.1)], 1.0);
        assert!(d > 0.6 && d < 0.75, "free {d}");
        // Behind the robot does not count going forward.
        assert_eq!(free_distance(0.28, &[(-1.0, 0.0)], 1.0), LOOK);
        assert_eq!(free_distance(0.28, &[], 1.0), LOOK);
    }

    #[test]
    fn a_halted_robot_gives_way_to_a_body_pressing_on_it() {
        let planner = office_planner();
        let mut nav = Navigator::new(planner, NavParams::default());
        let mut pose = Pose {
            x: 20.0,
            y: 3.0,
            theta: 0.0,
        };
        assert_eq!(
            nav.give_way(0.0, pose, &[(1.0, 0.0)]),
            None,
            "nothing presses on it"
        );
        // A body touching the front: turn round, then creep away from it.
        let body_at = (20.26, 3.0);
        let mut t = 0.0;
        let mut moved_away = false;
        for _ in 0..40 {
            let local = in_robot_frame(pose, body_at);
            let Some((v, w)) = nav.give_way(t, pose, &[local]) else {
                break;
            };
            pose = muster_world_model::kinematics::integrate(pose, v, w, 0.1);
            t += 0.1;
            moved_away |= v > 0.0;
        }
        assert!(moved_away);
        assert!(
            (pose.x - body_at.0).hypot(pose.y - body_at.1) > 0.35,
            "{pose:?}"
        );
    }

    #[test]
    fn making_room_keeps_the_point_in_view_when_a_free_heading_allows() {
        let planner = office_planner();
        let pose = Pose {
            x: 20.0,
            y: 3.0,
            theta: 0.0,
        };
        // Someone 0.6 m ahead needs to pass; the followed person is 3 m ahead.
        let body = [(0.6, 0.0)];
        let escape_of = |keep: Option<(f64, f64)>| {
            let mut nav = Navigator::new(planner.clone(), NavParams::default());
            nav.keep_in_view(keep, 2.0);
            nav.make_room(0.0, pose, &body, 0.0).unwrap();
            wrap(nav.escape.unwrap().0 - pose.theta)
        };
        // Free to turn: straight away from her, its back to the person.
        assert!(escape_of(None).abs() > 2.5, "{}", escape_of(None));
        // Keeping her in view: the free heading nearest to away, within 2 rad of her.
        let a = escape_of(Some((23.0, 3.0)));
        assert!(a.abs() <= 2.0 + 1e-9 && a.abs() > 1.5, "{a}");
    }

    /// A world point in the frame of the robot at `pose` (x ahead, y left).
    fn in_robot_frame(pose: Pose, (px, py): (f64, f64)) -> (f64, f64) {
        let (s, c) = pose.theta.sin_cos();
        let (dx, dy) = (px - pose.x, py - pose.y);
        (c * dx + s * dy, -s * dx + c * dy)
    }

    /// Body points (two, 0.1 m apart across the bearing: a body, not a lone echo) at
    /// world positions, as the robot at `pose` sees them.
    fn seen_from(pose: Pose, bodies: &[(f64, f64)]) -> Vec<(f64, f64)> {
        bodies
            .iter()
            .flat_map(|&b| {
                let (x, y) = in_robot_frame(pose, b);
                let d = x.hypot(y);
                let (ux, uy) = (-y / d * 0.05, x / d * 0.05);
                [(x + ux, y + uy), (x - ux, y - uy)]
            })
            .collect()
    }

    #[test]
    fn making_room_it_creeps_clear_past_a_body_beside_it_but_never_towards_one() {
        let planner = office_planner();
        // The middle corridor (y 9-11), facing east; someone 0.5 m ahead needs to pass.
        let start = Pose {
            x: 20.0,
            y: 10.0,
            theta: 0.0,
        };
        let person = (20.5, 10.0);
        // Makes room for 4 s; returns where it got to and whether it ever moved.
        let run = |others: &[(f64, f64)]| {
            let mut nav = Navigator::new(planner.clone(), NavParams::default());
            let (mut pose, mut t, mut moved) = (start, 0.0, false);
            for _ in 0..40 {
                let mut all = vec![person];
                all.extend_from_slice(others);
                let pts = seen_from(pose, &all);
                let toward = {
                    let (x, y) = in_robot_frame(pose, person);
                    y.atan2(x)
                };
                let Some((v, w)) = nav.make_room(t, pose, &pts, toward) else {
                    break;
                };
                moved |= v > 0.0;
                pose = muster_world_model::kinematics::integrate(pose, v, w, 0.1);
                t += 0.1;
            }
            (pose, moved)
        };
        // Alone: it turns its back on her and creeps west.
        let (alone, _) = run(&[]);
        assert!(alone.x < 19.7, "{alone:?}");
        // Another robot's flank right beside it (0.42 m north of its centre, within the
        // reach a body could close before its next command): creeping west moves away
        // from it, so it creeps clear all the same. (It used to wait for the other to
        // move first, and the other, a tracker in a doorway with her behind it, waited
        // for it: she stood boxed in for minutes.)
        let (beside, _) = run(&[(20.0, 10.42)]);
        assert!(beside.x < 19.7, "{beside:?}");
        // A body where its creeping closes on it (60° off the way west, 0.45 m off):
        // it turns to its way out but does not move.
        let a = (180.0f64 - 60.0).to_radians();
        let ahead = (20.0 + 0.45 * a.cos(), 10.0 + 0.45 * a.sin());
        let (held, moved) = run(&[ahead]);
        assert!(!moved, "{held:?}");
    }

    #[test]
    fn a_lone_point_in_the_lasers_field_is_noise_and_latency_grows_the_fields_uncapped() {
        let planner = office_planner();
        let pose = Pose {
            x: 10.0,
            y: 3.0,
            theta: 0.0,
        };
        let fresh = |latency: f64| {
            let mut nav = Navigator::new(planner.clone(), NavParams::default());
            nav.set_goal(pose, (20.0, 3.0), 0.5).unwrap();
            nav.set_latency(latency);
            nav
        };
        // Every point below is well off the walls, so only its company decides.
        for (x, y) in [(0.6, 0.35), (0.6, 0.45), (2.0, 0.0), (2.0, 0.1)] {
            assert!(
                planner.wall_distance(pose.x + x, pose.y + y) > 0.3,
                "({x}, {y})"
            );
        }
        let speed = |nav: &mut Navigator, pts: &[(f64, f64)]| nav.step(0.0, pose, pts).velocity.0;
        let free = speed(&mut fresh(0.0), &[]);
        assert!(free > 0.3, "free corridor: {free}");
        // One laser point beside the lane: noise, the robot does not slow for it.
        assert_eq!(speed(&mut fresh(0.0), &[(0.6, 0.45)]), free);
        // Two points together there: a body, the robot slows to the warning speed.
        let slow = speed(&mut fresh(0.0), &[(0.6, 0.35), (0.6, 0.45)]);
        assert!(slow <= 0.12 + 1e-9, "beside a body: {slow}");
        // A body 2 m ahead: driven towards slowly without latency, but with commands
        // 2.5 s late (seen on a loaded machine) the fields reach it and the robot stops.
        let body = [(2.0, 0.0), (2.0, 0.1)];
        assert!(speed(&mut fresh(0.0), &body) > 0.12);
        assert_eq!(speed(&mut fresh(2.5), &body), 0.0);
    }

    #[test]
    fn follows_a_path_and_stops_short_of_a_body_in_the_way() {
        let planner = office_planner();
        let mut nav = Navigator::new(planner, NavParams::default());
        let mut pose = Pose {
            x: 5.0,
            y: 3.0,
            theta: 0.0,
        };
        nav.set_goal(pose, (15.0, 3.0), 0.5).unwrap();
        // Free corridor: drives forward towards the goal.
        let s = nav.step(0.0, pose, &[]);
        assert!(s.velocity.0 > 0.0 && s.blocked_since.is_none());
        assert!((s.remaining - 10.0).abs() < 0.5);
        // A body 0.4 m ahead: stops (turning allowed), and reports blocked over time.
        let body: Vec<(f64, f64)> = (-3..=3).map(|k| (0.4, f64::from(k) * 0.05)).collect();
        let s = nav.step(1.0, pose, &body);
        assert_eq!(s.velocity.0, 0.0);
        assert_eq!(s.blocked_since, Some(1.0));
        // After the replan delay it plans round the body and turns away from it.
        let s = nav.step(3.5, pose, &body);
        assert!(s.error.is_none());
        let first = nav.path()[1.min(nav.path().len() - 1)];
        assert!(
            (first.1 - 3.0).abs() > 0.2 || first.0 < 5.4,
            "path goes round: {:?}",
            nav.path()
        );
        // Drive it in a kinematic loop with no obstacles: it reaches the goal.
        let mut t = 4.0;
        for _ in 0..400 {
            let s = nav.step(t, pose, &[]);
            pose = muster_world_model::kinematics::integrate(pose, s.velocity.0, s.velocity.1, 0.1);
            t += 0.1;
            if s.remaining < 0.2 {
                break;
            }
        }
        assert!(
            (pose.x - 15.0).hypot(pose.y - 3.0) < 0.5,
            "ended at {pose:?}"
        );
    }

    /// A navigator on the office map that may sprint at 1.2 m/s.
    fn sprinter() -> Navigator {
        let params = NavParams {
            sprint_speed: 1.2,
            ..NavParams::default()
        };
        Navigator::new(office_planner(), params)
    }

    #[test]
    fn a_robot_sprints_only_when_allowed_far_from_its_goal_and_with_no_body_near() {
        let mut nav = sprinter();
        // The path keeps to grid cells' centres: the heading is a little off, and the
        // speed a little under the top.
        let cruising = |v: f64| v > 0.75 && v <= 0.8 + 1e-9;
        // The south corridor, heading east, the goal 10 m on, no doorway near.
        let pose = Pose {
            x: 15.0,
            y: 3.0,
            theta: 0.0,
        };
        nav.set_goal(pose, (25.0, 3.0), 0.5).unwrap();
        // Not allowed: the cruising speed.
        let s = nav.step(0.0, pose, &[]);
        assert!(cruising(s.velocity.0), "{:?}", s.velocity);
        // Allowed, a clear way and 10 m to go: the sprint speed.
        nav.allow_sprint(true);
        let s = nav.step(0.1, pose, &[]);
        assert!(s.velocity.0 > 1.1, "{:?}", s.velocity);
        // A body (a person's front, points 5 cm apart) 2.5 m ahead and 0.7 m to the left,
        // out of its lane: it keeps to the cruising speed.
        let body: Vec<(f64, f64)> = (-2..=2).map(|k| (2.5, 0.7 + 0.05 * f64::from(k))).collect();
        let s = nav.step(0.2, pose, &body);
        assert!(cruising(s.velocity.0), "{:?}", s.velocity);
        // The same body behind it does not hold it back.
        let behind: Vec<(f64, f64)> = body.iter().map(|&(x, y)| (-x, y)).collect();
        let s = nav.step(0.3, pose, &behind);
        assert!(s.velocity.0 > 1.1, "{:?}", s.velocity);
        // Within 3 m of its goal: the cruising speed at most.
        let near = Pose { x: 22.5, ..pose };
        let s = nav.step(0.4, near, &[]);
        assert!(
            s.velocity.0 <= 0.8 + 1e-9 && s.velocity.0 > 0.0,
            "{:?}",
            s.velocity
        );
    }

    #[test]
    fn a_robot_keeps_to_its_cruising_speed_nearing_a_doorway_it_cannot_see_into() {
        let mut nav = sprinter();
        nav.allow_sprint(true);
        // The south corridor (y 0.2-4), heading east; an office door in its north wall at
        // x 21.5-22.5, the next ones 8 m either way.
        let at = |x: f64| Pose {
            x,
            y: 3.0,
            theta: 0.0,
        };
        nav.set_goal(at(15.0), (30.0, 3.0), 0.5).unwrap();
        let v = |nav: &mut Navigator, x: f64| nav.step(x, at(x), &[]).velocity.0;
        // 6.5 m short of it: the way is in full view, it sprints.
        assert!(v(&mut nav, 15.0) > 1.1);
        // 2-3 m short of it: someone standing just inside the office, beside the way,
        // is hidden by the wall; it cruises.
        let near = v(&mut nav, 19.5);
        assert!(near > 0.7 && near <= 0.8 + 1e-9, "{near}");
        // Level with the door, it sees into the office: it sprints again.
        assert!(v(&mut nav, 21.7) > 1.1);
        // The east corridor (x 36-38) comes in 2.5 m ahead, round the corner of an
        // office block: heading for it, it cruises.
        nav.set_goal(at(33.5), (37.0, 10.0), 0.5).unwrap();
        let corner = v(&mut nav, 33.5);
        assert!(corner <= 0.8 + 1e-9, "{corner}");
    }

    #[test]
    fn a_body_beside_a_robot_driving_straight_slows_it_but_one_it_turns_towards_stops_it() {
        let planner = office_planner();
        let mut nav = Navigator::new(planner, NavParams::default());
        let pose = Pose {
            x: 20.0,
            y: 10.0,
            theta: 0.0,
        };
        nav.set_goal(pose, (30.0, 10.0), 0.5).unwrap();
        // Another robot's flank at 85° to the right, 0.55 m from the centre: inside the
        // body protective field (0.58 m), beside the robot.
        let side: Vec<(f64, f64)> = (-2..=2)
            .map(|k| {
                let a = (-85.0 + 4.0 * f64::from(k)).to_radians();
                (0.55 * a.cos(), 0.55 * a.sin())
            })
            .collect();
        // Driving straight, it is not closed on: the robot drives on at the warning
        // speed (two robots side by side no longer hold each other for good).
        let s = nav.step(0.0, pose, &side);
        assert!((s.velocity.0 - 0.12).abs() < 1e-9, "{:?}", s.velocity);
        // Turning right, towards it: it is as good as ahead, and the robot stops.
        let turning = Pose { theta: 0.5, ..pose };
        let s = nav.step(0.1, turning, &side);
        assert!(s.velocity.1 < -0.5, "turns right: {:?}", s.velocity);
        assert_eq!(s.velocity.0, 0.0);
        // Turning left, away from it: on at the warning speed.
        let away = Pose {
            theta: -0.5,
            ..pose
        };
        let s = nav.step(0.2, away, &side);
        assert!(s.velocity.1 > 0.5, "turns left: {:?}", s.velocity);
        assert!(s.velocity.0 > 0.0, "{:?}", s.velocity);
    }

    #[test]
    fn a_robot_turning_towards_a_body_behind_its_shoulder_stops_rolling_forward() {
        let planner = office_planner();
        // Facing 0.5 rad left of its path east: it turns right at 1 rad/s, and would
        // drive on at 0.6 m/s meanwhile.
        let pose = Pose {
            x: 20.0,
            y: 10.0,
            theta: 0.5,
        };
        // A person 0.5 m from its centre, 125° off its heading (behind its shoulder),
        // on one side or the other: out of the ±70° cone, and behind the robot, so no
        // field slows it for her.
        let behind = |side: f64| -> Vec<(f64, f64)> {
            (-2..=2)
                .map(|k| {
                    let a = (side * 125.0 + 4.0 * f64::from(k)).to_radians();
                    (0.5 * a.cos(), 0.5 * a.sin())
                })
                .collect()
        };
        for latency in [0.0, 0.25] {
            let step = |pts: &[(f64, f64)]| {
                let mut nav = Navigator::new(planner.clone(), NavParams::default());
                nav.set_goal(pose, (30.0, 10.0), 0.5).unwrap();
                nav.set_latency(latency);
                nav.step(0.0, pose, pts).velocity
            };
            let (v, w) = step(&[]);
            assert!(v > 0.5 && w < -0.5, "free, latency {latency}: {v}, {w}");
            // Behind its left shoulder, away from the turn: it drives on as if free.
            assert_eq!(step(&behind(1.0)), (v, w), "latency {latency}");
            // Behind its right shoulder: in the time it takes to brake from 0.6 m/s it
            // turns her round to its side and would roll into her (seen with commands
            // 0.25 s late: a person walking behind a tracker that slowed to turn). It
            // stops rolling forward and goes on turning.
            let (v, w) = step(&behind(-1.0));
            assert_eq!(v, 0.0, "latency {latency}");
            assert!(w < -0.5, "latency {latency}: {w}");
        }
    }
}
