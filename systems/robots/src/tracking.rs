//! The multi-robot, multi-target tracking system's logic (the paper's T1–T3 after Jung
//! and Sukhatme): each robot localizes, points its camera at the targets users asked
//! for (sweeping while it sees none), and every sighting goes into one track per colour.
//! Mobile trackers patrol while their target is lost and follow it, at a distance, when
//! seen. The processing budget models what the robot's computer sustains beside
//! tracking: fewer sessions than the quota when it tracks many targets (the paper: the
//! client takes 10 requests, the robot about 8).
//!
//! Pure: fed with each robot's sensors samples (sim time inside); returns commands.

use crate::localizer::{Localizer, LocalizerParams};
use crate::navigator::{NavParams, Navigator};
use crate::planner::Planner;
use crate::sensing::{LikelihoodField, SensorGeometry, SensorSample};
use crate::tracker::{MultiTracker, TrackerParams};
use muster_shared::types::Track2d;
use muster_world_model::kinematics::{wrap, Pose};
use muster_world_model::map::OccupancyMap;
use muster_world_model::Colour;
use nalgebra::Matrix3;
use std::sync::Arc;

/// What a tracking robot's computer sustains: a budget of 1 shared by tracking (per
/// target in view) and by sessions.
#[derive(Clone, Debug, PartialEq)]
pub struct Budget {
    /// Cost of serving one session.
    pub per_session: f64,
    /// Cost of tracking one target.
    pub per_target: f64,
}

impl Default for Budget {
    fn default() -> Self {
        // 10 sessions with nothing tracked; 8 with all three of the paper's targets.
        Budget {
            per_session: 0.1,
            per_target: 0.2 / 3.0,
        }
    }
}

impl Budget {
    /// Sessions sustainable while `tracked` targets are tracked.
    pub fn sessions(&self, tracked: usize) -> usize {
        let left = 1.0 - self.per_target * tracked as f64;
        ((left + 1e-9) / self.per_session).floor().max(0.0) as usize
    }
}

/// A mobile tracker searches where its target was last seen for this long, s.
const SEARCH_FOR: f64 = 60.0;

/// A followed target unseen this long (but not lost) is looked for where it was last
/// seen, s.
const UNSEEN_GO_LOOK: f64 = 1.0;

/// Looking for a followed target where it was last seen, a mobile tracker stops this
/// close to that place, m.
const UNSEEN_ARRIVED: f64 = 1.0;

/// A mobile tracker that searched where a lost target was supposed to be, in vain,
/// turns on the spot this long, s, at [`LOOK_ROUND_TURN`] (a full turn).
const LOOK_ROUND: f64 = 2.0 * std::f64::consts::PI / LOOK_ROUND_TURN;

/// ... at this turn rate, rad/s.
const LOOK_ROUND_TURN: f64 = 0.8;

/// Searching or patrolling, a mobile tracker held up this long looks round, s.
const BLOCKED_LOOK_ROUND: f64 = 3.0;

/// Searching where a lost target was supposed to go, a mobile tracker held up this long,
/// s, within [`SPOT_IN_VIEW`] of that place and in sight of it, has been there: what
/// holds it up may be parked on the spot (the delivery robot waits where the target was
/// last seen), and the camera sees the spot from here.
const HELD_UP_THERE: f64 = 2.0;

/// ... that distance, m.
const SPOT_IN_VIEW: f64 = 2.5;

/// A lost target is taken to walk on at least this fast, m/s, when it was moving at
/// all (a filter's speed estimate lags a person's).
const WALK_ON_SPEED: f64 = 0.6;

/// Below this speed, m/s, a lost target is taken to stand where it was last seen.
const STANDING: f64 = 0.2;

/// The walk a lost target is taken to go on: from where it was last seen, along its
/// heading at its speed, turning along corridors rather than through walls: each step
/// of [`WALK_STEP`] goes the nearest way to its heading that is open for a metre or
/// more (straight on first, then ever wider turns; at a corridor's end, the more open
/// side), kept off the walls. Points every [`WALK_STEP`] of walking; the first is where
/// it was last seen. A target standing (below [`STANDING`]) stays there.
fn walk_on(map: &OccupancyMap, t: &crate::tracker::Track, duration: f64) -> Walk {
    let (mut x, mut y, vx, vy) = (t.state[0], t.state[1], t.state[2], t.state[3]);
    let speed = vx.hypot(vy);
    let mut points = vec![(x, y)];
    if speed < STANDING {
        return Walk {
            points,
            step_time: f64::INFINITY,
            from: t.last_seen,
        };
    }
    let speed = speed.max(WALK_ON_SPEED);
    let mut heading = vy.atan2(vx);
    let steps = (duration * speed / WALK_STEP).ceil() as usize;
    let open = |x: f64, y: f64, a: f64| map.raycast(x, y, a, 3.0).unwrap_or(3.0);
    for _ in 0..steps {
        let turns = (0..=6).flat_map(|k| {
            let a = f64::from(k) * std::f64::consts::PI / 12.0;
            if k == 0 {
                vec![0.0]
            } else {
                vec![a, -a]
            }
        });
        let mut best: Option<(f64, f64)> = None;
        for turn in turns {
            let free = open(x, y, heading + turn);
            if free >= 1.0 {
                // Of two turns as wide, the more open side.
                match best {
                    Some((b, f)) if (b.abs() - turn.abs()).abs() < 1e-9 && free > f => {
                        best = Some((turn, free));
                    }
                    None => best = Some((turn, free)),
                    _ => {}
                }
            }
            if best.is_some_and(|(b, _)| turn.abs() > b.abs() + 1e-9) {
                break;
            }
        }
        let Some((turn, _)) = best else { break };
        heading = wrap(heading + turn);
        let (nx, ny) = (x + WALK_STEP * heading.cos(), y + WALK_STEP * heading.sin());
        // Kept off the walls: drift towards the middle of the way.
        let left = open(nx, ny, heading + std::f64::consts::FRAC_PI_2).min(1.5);
        let right = open(nx, ny, heading - std::f64::consts::FRAC_PI_2).min(1.5);
        let shift = (0.25 * (left - right)).clamp(-0.1, 0.1);
        let (nx, ny) = (
            nx + shift * (heading + std::f64::consts::FRAC_PI_2).cos(),
            ny + shift * (heading + std::f64::consts::FRAC_PI_2).sin(),
        );
        if map
            .raycast(x, y, (ny - y).atan2(nx - x), (nx - x).hypot(ny - y))
            .is_some()
        {
            break;
        }
        (x, y) = (nx, ny);
        points.push((x, y));
    }
    Walk {
        points,
        step_time: WALK_STEP / speed,
        from: t.last_seen,
    }
}

/// The length of one step of [`walk_on`], m.
const WALK_STEP: f64 = 0.25;

/// A lost target's supposed walk ([`walk_on`]).
#[derive(Clone, Debug)]
struct Walk {
    points: Vec<(f64, f64)>,
    /// Time per point, s.
    step_time: f64,
    /// The sighting it starts from (sim time).
    from: f64,
}

impl Walk {
    /// Where the target is supposed to be at `now`.
    fn at(&self, now: f64) -> (f64, f64) {
        let k = ((now - self.from).max(0.0) / self.step_time) as usize;
        self.points[k.min(self.points.len() - 1)]
    }

    /// Whether the supposed walk has ended by `now` (nothing more to follow).
    fn ended(&self, now: f64) -> bool {
        (now - self.from).max(0.0) / self.step_time >= (self.points.len() - 1) as f64
    }
}

/// The most the trackers zoom (the simulator's cameras reach 4; the range grows with the
/// square root, the field of view shrinks with it).
const MAX_ZOOM: f64 = 4.0;

/// The zoom that sees a target `d` metres off, with a margin, for a camera reaching
/// `range` at zoom 1: the range grows with the square root of the zoom.
fn zoom_for(d: f64, range: f64) -> f64 {
    (d / (range * 0.8)).powi(2).clamp(1.0, MAX_ZOOM)
}

/// A sweeping camera zooms for where it will point this far ahead, s (a zoom takes
/// time: the simulator's changes by 2 a second).
const ZOOM_AHEAD: f64 = 0.5;

/// A prediction stops this short of a wall it would run into, m (a person's radius and
/// a little).
const WALL_MARGIN: f64 = 0.4;

/// The point `to` predicted from `from` by a straight walk, but short of the first wall
/// on the way: a person does not walk through walls, and a prediction that does points
/// the camera at a wall and sends a robot round to the far side of it.
fn short_of_walls(map: &OccupancyMap, from: (f64, f64), to: (f64, f64)) -> (f64, f64) {
    let (dx, dy) = (to.0 - from.0, to.1 - from.1);
    let d = dx.hypot(dy);
    if d < 1e-6 {
        return to;
    }
    match map.raycast(from.0, from.1, dy.atan2(dx), d + WALL_MARGIN) {
        Some(hit) => {
            let go = (hit - WALL_MARGIN).clamp(0.0, d);
            (from.0 + dx * go / d, from.1 + dy * go / d)
        }
        None => to,
    }
}

/// Narrower than this, a passage is a doorway (the office's doors are 1 m wide, its
/// corridors 2 m and more), m.
const DOORWAY: f64 = 1.4;

/// The width of the narrowest passage through (x, y): the least, over directions, of the
/// free distance to the walls one way plus the other, capped at `cap`, m.
fn passage_width(map: &OccupancyMap, x: f64, y: f64, cap: f64) -> f64 {
    (0..12)
        .map(|k| {
            let a = f64::from(k) * std::f64::consts::PI / 12.0;
            let one = map.raycast(x, y, a, cap).unwrap_or(cap);
            let other = map
                .raycast(x, y, a + std::f64::consts::PI, cap)
                .unwrap_or(cap);
            (one + other).min(cap)
        })
        .fold(cap, f64::min)
}

/// One tracking robot, as configured.
#[derive(Clone, Debug)]
pub struct TrackerRobot {
    /// Name in the simulator.
    pub name: String,
    /// Start pose (the localizer's initial estimate).
    pub start: Pose,
    /// Whether it may drive (patrol, follow).
    pub mobile: bool,
    /// Its sensors.
    pub geometry: SensorGeometry,
    /// Its top speed, m/s.
    pub max_speed: f64,
}

/// How the tracking system behaves.
#[derive(Clone, Debug)]
pub struct TrackingParams {
    /// Colours, one service each.
    pub colours: Vec<Colour>,
    /// Updates to users every this many seconds (the paper: 1 s).
    pub period: f64,
    /// Use ground truth instead of localization (experiments only).
    pub ground_truth: bool,
    /// Where mobile trackers patrol while their target is lost.
    pub patrol: Vec<(f64, f64)>,
    /// Distance a mobile tracker keeps to the target it follows, m.
    pub follow_distance: f64,
    /// The processing budget.
    pub budget: Budget,
    /// The track filter.
    pub tracker: TrackerParams,
    /// The localization filter.
    pub localizer: LocalizerParams,
    /// Period of the camera sweep while no target is in view, s.
    pub sweep_period: f64,
    /// The colour mobile trackers follow (and look at first); `None`: the most wanted
    /// tracked colour.
    pub follow: Option<Colour>,
}

impl Default for TrackingParams {
    fn default() -> Self {
        TrackingParams {
            colours: vec![Colour::Red, Colour::Green, Colour::Blue],
            period: 1.0,
            ground_truth: false,
            patrol: vec![
                (3.0, 3.0),
                (20.0, 3.0),
                (37.0, 3.0),
                (37.0, 10.0),
                (37.0, 17.0),
                (20.0, 17.0),
                (3.0, 17.0),
                (3.0, 10.0),
            ],
            follow_distance: 2.0,
            budget: Budget::default(),
            tracker: TrackerParams::default(),
            localizer: LocalizerParams::default(),
            sweep_period: 8.0,
            follow: None,
        }
    }
}

/// Commands for one robot after one sample.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RobotCommands {
    /// Velocity (m/s, rad/s), for mobile robots.
    pub velocity: Option<(f64, f64)>,
    /// Camera pan, tilt (rad) and zoom.
    pub camera: Option<(f64, f64, f64)>,
}

struct RobotState {
    cfg: TrackerRobot,
    localizer: Option<Localizer>,
    pose: Pose,
    cov: Matrix3<f64>,
    nav: Option<Navigator>,
    patrol_next: usize,
    /// The loss (the sim time its target was last seen) already searched.
    searched: Option<f64>,
    /// Turning on the spot to look round, until this sim time.
    look_round_until: f64,
    last_camera: f64,
}

/// The tracking system's logic over all its robots.
pub struct TrackingCore {
    params: TrackingParams,
    map: Arc<OccupancyMap>,
    robots: Vec<RobotState>,
    tracker: MultiTracker,
    next_publish: f64,
    now: f64,
    /// The followed target's supposed walk since it was last seen ([`walk_on`]).
    walk: Option<(Colour, Walk)>,
}

impl TrackingCore {
    /// The system for `robots` on `map`.
    pub fn new(
        map: Arc<OccupancyMap>,
        field: Arc<LikelihoodField>,
        planner: Arc<Planner>,
        robots: Vec<TrackerRobot>,
        params: TrackingParams,
        seed: u64,
    ) -> Self {
        let robots = robots
            .into_iter()
            .enumerate()
            .map(|(i, cfg)| RobotState {
                localizer: (!params.ground_truth && cfg.geometry.laser.is_some()).then(|| {
                    Localizer::new(
                        field.clone(),
                        cfg.start,
                        params.localizer.clone(),
                        seed ^ (i as u64 + 1).wrapping_mul(0x9e37_79b9),
                    )
                }),
                pose: cfg.start,
                cov: Matrix3::from_diagonal_element(1e-4),
                nav: cfg.mobile.then(|| {
                    Navigator::new(
                        planner.clone(),
                        NavParams {
                            max_speed: cfg.max_speed.min(0.8),
                            ..NavParams::default()
                        },
                    )
                }),
                patrol_next: 0,
                searched: None,
                look_round_until: f64::NEG_INFINITY,
                last_camera: f64::NEG_INFINITY,
                cfg,
            })
            .collect();
        TrackingCore {
            tracker: MultiTracker::new(params.tracker.clone()),
            params,
            map,
            robots,
            next_publish: 0.0,
            now: 0.0,
            walk: None,
        }
    }

    /// The robots' names, in order.
    pub fn robot_names(&self) -> Vec<String> {
        self.robots.iter().map(|r| r.cfg.name.clone()).collect()
    }

    /// Robot `i`'s pose estimate.
    pub fn pose(&self, i: usize) -> Option<Pose> {
        self.robots.get(i).map(|r| r.pose)
    }

    /// The colours offered.
    pub fn colours(&self) -> &[Colour] {
        &self.params.colours
    }

    /// How late robot `i` acts on a command (see [`Navigator::set_latency`]): a mobile
    /// tracker's margins grow with it as the delivery robot's do.
    pub fn set_latency(&mut self, i: usize, latency: f64) {
        if let Some(nav) = self.robots.get_mut(i).and_then(|r| r.nav.as_mut()) {
            nav.set_latency(latency);
        }
    }

    /// Sessions the robots can sustain now, given what they track.
    pub fn session_limit(&self) -> usize {
        self.params.budget.sessions(self.tracker.tracked(self.now))
    }

    /// Targets tracked now.
    pub fn tracked(&self) -> usize {
        self.tracker.tracked(self.now)
    }

    /// Handles one sensors sample of robot `i`; `wanted` are the colours users hold
    /// sessions on (most wanted first). Returns the robot's commands.
    pub fn handle_sample(
        &mut self,
        i: usize,
        s: &SensorSample,
        wanted: &[Colour],
    ) -> RobotCommands {
        let Some(r) = self.robots.get_mut(i) else {
            return RobotCommands::default();
        };
        self.now = self.now.max(s.time);
        // Where am I?
        match (&mut r.localizer, self.params.ground_truth) {
            (Some(l), false) => {
                l.handle_odometry(s.odom);
                if let Some(scan) = r.cfg.geometry.scan(s) {
                    l.handle_scan(s.laser_time, &scan);
                }
                r.pose = l.estimate();
                r.cov = l.covariance();
            }
            _ => {
                r.pose = s.truth;
                r.cov = Matrix3::from_diagonal_element(1e-6);
            }
        }
        // What do I see? Each camera frame once.
        let new_frame = s.camera_time > r.last_camera;
        if new_frame {
            r.last_camera = s.camera_time;
            for sighting in &s.sightings {
                if self.params.colours.contains(&sighting.colour) {
                    self.tracker.handle_sighting(
                        &r.cfg.name,
                        s.camera_time,
                        r.pose,
                        &r.cov,
                        sighting,
                    );
                }
            }
        }
        self.refresh_walk(s.time, wanted);
        let mut cmd = RobotCommands::default();
        if new_frame {
            cmd.camera = Some(self.point_camera(i, s.time, wanted));
        }
        if self.robots[i].cfg.mobile {
            cmd.velocity = Some(self.drive(i, s, wanted));
        }
        cmd
    }

    /// The colours mobile trackers follow, most wanted first.
    fn followed(&self, wanted: &[Colour]) -> Vec<Colour> {
        match self.params.follow {
            Some(c) => vec![c],
            None => wanted.to_vec(),
        }
    }

    /// Works out the supposed walk of the followed target once it is unseen for
    /// [`UNSEEN_GO_LOOK`] (once per sighting it starts from).
    fn refresh_walk(&mut self, now: f64, wanted: &[Colour]) {
        if !self.robots.iter().any(|r| r.cfg.mobile) {
            return;
        }
        let Some((c, t)) = self
            .followed(wanted)
            .into_iter()
            .find_map(|c| self.tracker.track(c).map(|t| (c, t)))
        else {
            self.walk = None;
            return;
        };
        if now - t.last_seen <= UNSEEN_GO_LOOK {
            return;
        }
        if self
            .walk
            .as_ref()
            .is_some_and(|(wc, w)| *wc == c && w.from == t.last_seen)
        {
            return;
        }
        self.walk = Some((c, walk_on(&self.map, t, SEARCH_FOR)));
    }

    /// Where the lost target `colour` is supposed to be at `now`, while it is searched
    /// for ([`SEARCH_FOR`] after it was last seen): its supposed walk's point then, the
    /// loss's time, and whether the walk has ended.
    fn supposed(&self, colour: Colour, now: f64) -> Option<((f64, f64), f64, bool)> {
        let (c, w) = self.walk.as_ref()?;
        // Only the walk from the last sighting: seen since, it is not searched for.
        let current = self
            .tracker
            .track(colour)
            .is_some_and(|t| t.last_seen == w.from);
        (*c == colour && current && now - w.from < SEARCH_FOR)
            .then(|| (w.at(now), w.from, w.ended(now)))
    }

    /// Where robot `i` should look: at the most wanted target it can see (tracked,
    /// within range, in line of sight, within pan), else sweeping.
    fn point_camera(&self, i: usize, now: f64, wanted: &[Colour]) -> (f64, f64, f64) {
        let r = &self.robots[i];
        let Some((fov, range, pan_limit)) = r.cfg.geometry.camera else {
            return (0.0, 0.0, 1.0);
        };
        let candidates = self
            .params
            .follow
            .iter()
            .chain(wanted.iter())
            .chain(self.params.colours.iter())
            .filter(|c| self.tracker.is_tracked(**c, now));
        for &c in candidates {
            let Some((x, y)) = self.predicted(c, now) else {
                continue;
            };
            let (dx, dy) = (x - r.pose.x, y - r.pose.y);
            let d = dx.hypot(dy);
            let bearing = wrap(dy.atan2(dx) - r.pose.theta);
            if d > range * 1.8 || bearing.abs() > pan_limit + fov / 2.0 {
                continue;
            }
            if self
                .map
                .raycast(r.pose.x, r.pose.y, dy.atan2(dx), (d - 0.3).max(0.0))
                .is_some()
            {
                continue;
            }
            return (
                bearing.clamp(-pan_limit, pan_limit),
                0.0,
                zoom_for(d, range),
            );
        }
        // Searching for the followed target: at where it is supposed to be, if in sight,
        // every other half sweep (the other half sweeps round the robot).
        let half = (now / (self.params.sweep_period / 2.0)).floor() as i64;
        if let Some(((x, y), _, _)) = self
            .params
            .follow
            .filter(|_| half % 2 == 0)
            .and_then(|c| self.supposed(c, now))
        {
            let (dx, dy) = (x - r.pose.x, y - r.pose.y);
            let d = dx.hypot(dy);
            let bearing = wrap(dy.atan2(dx) - r.pose.theta);
            if d > 0.5
                && d < range * MAX_ZOOM.sqrt()
                && bearing.abs() < pan_limit + fov / 2.0
                && self.map.in_sight((r.pose.x, r.pose.y), (x, y))
            {
                return (
                    bearing.clamp(-pan_limit, pan_limit),
                    0.0,
                    zoom_for(d, range),
                );
            }
        }
        // Nothing to look at: sweep, each robot at its own phase, zoomed to see as far as
        // the walls let it where the camera will point by the time the zoom is there (a
        // corridor seen down its length, a wall close up).
        let phase = i as f64 * 1.3;
        let sweep = |t: f64| {
            pan_limit * (2.0 * std::f64::consts::PI * t / self.params.sweep_period + phase).sin()
        };
        let far = range * MAX_ZOOM.sqrt();
        let free = self
            .map
            .raycast(
                r.pose.x,
                r.pose.y,
                r.pose.theta + sweep(now + ZOOM_AHEAD),
                far,
            )
            .unwrap_or(far);
        let zoom = (free / (range * 0.9)).powi(2).clamp(1.0, MAX_ZOOM);
        (sweep(now), 0.0, zoom)
    }

    /// A mobile tracker follows the most wanted tracked target at a distance, and
    /// patrols while there is none.
    fn drive(&mut self, i: usize, s: &SensorSample, wanted: &[Colour]) -> (f64, f64) {
        let now = s.time;
        let follow = self.followed(wanted);
        // The target followed: where it is predicted to be, or, unseen for a moment while
        // still tracked, where it is supposed to have walked on from where it was last
        // seen (a prediction runs on through walls; a person goes round corners).
        let target = follow
            .iter()
            .find(|c| self.tracker.is_tracked(**c, now))
            .and_then(|c| {
                let t = self.tracker.track(*c)?;
                if now - t.last_seen > UNSEEN_GO_LOOK {
                    let at = self
                        .supposed(*c, now)
                        .map_or((t.state[0], t.state[1]), |(at, _, _)| at);
                    Some((true, at))
                } else {
                    Some((false, self.predicted(*c, now)?))
                }
            });
        // Lost: follow where it is supposed to have walked on (once), then patrol.
        let search = follow
            .iter()
            .filter(|c| !self.tracker.is_tracked(**c, now))
            .find_map(|c| self.supposed(*c, now));
        let follow_distance = self.params.follow_distance;
        let patrol = &self.params.patrol;
        let map = &self.map;
        let r = &mut self.robots[i];
        let Some(nav) = r.nav.as_mut() else {
            return (0.0, 0.0);
        };
        // It may sprint catching up with the target in sight, not searching or patrolling.
        nav.allow_sprint(matches!(target, Some((false, _))));
        let obstacles = r.cfg.geometry.obstacle_points(s, 3.5);
        let held_up_there = nav
            .blocked_since()
            .is_some_and(|since| now - since >= HELD_UP_THERE);
        // Looking round (searched in vain, or held up): a full turn on the spot, not
        // cut short by the search's goal or an escape, so that the camera passes every
        // bearing once (she may be right behind it, boxed in).
        if target.is_none() && now < r.look_round_until {
            nav.clear();
            return (0.0, LOOK_ROUND_TURN);
        }
        match target {
            Some((unseen, (tx, ty))) => {
                r.searched = None;
                let (dx, dy) = (tx - r.pose.x, ty - r.pose.y);
                let d = dx.hypot(dy);
                let in_sight = map.in_sight((r.pose.x, r.pose.y), (tx, ty));
                // Close enough: in sight at the distance kept, or, looking for it, about
                // where it was last seen (not onto it: it may be there, hidden from the
                // camera, in a doorway).
                let close = if unseen {
                    d <= UNSEEN_ARRIVED
                } else {
                    d <= follow_distance + 0.3 && in_sight
                };
                if close {
                    // Close enough: hold, facing the target, and give way
                    // to anyone (the target included) who walks into the robot. Halted
                    // anew at every step, it must not forget that it is getting clear.
                    nav.halt();
                    // Getting clear, it keeps the target within its camera's reach.
                    let reach = r
                        .cfg
                        .geometry
                        .camera
                        .map_or(std::f64::consts::PI, |(fov, _, pan)| pan + fov / 2.0 - 0.2);
                    nav.keep_in_view(Some((tx, ty)), reach);
                    if let Some(v) = nav.give_way(now, r.pose, &obstacles) {
                        return v;
                    }
                    let err = wrap(dy.atan2(dx) - r.pose.theta);
                    // Much closer than it keeps (the target came back towards the
                    // robot), or standing in a doorway (walls close on both sides): it
                    // may be where she must pass, so it makes room rather than trap her.
                    let narrow = passage_width(map, r.pose.x, r.pose.y, 2.0) < DOORWAY;
                    if d < 0.6 * follow_distance || narrow {
                        if let Some(v) = nav.make_room(now, r.pose, &obstacles, err) {
                            return v;
                        }
                    }
                    return (0.0, (1.5 * err).clamp(-1.0, 1.0));
                }
                // Along the way the target went, not straight at it: a point short of it
                // on a straight line can be behind a wall, in another room. The
                // navigator's body fields keep the robot off the target itself.
                let _ = nav.set_goal(r.pose, (tx, ty), 0.75);
            }
            None if search.is_some_and(|((x, y), from, ended)| {
                let d = (x - r.pose.x).hypot(y - r.pose.y);
                let there = d <= 1.0
                    || (held_up_there
                        && d <= SPOT_IN_VIEW
                        && map.in_sight((r.pose.x, r.pose.y), (x, y)));
                r.searched != Some(from) && !(ended && there)
            }) =>
            {
                let ((x, y), from, _) = search.unwrap_or_default();
                if nav.goal() != Some((x, y)) && nav.set_goal(r.pose, (x, y), 1.0).is_err() {
                    r.searched = Some(from);
                }
            }
            None => {
                if let Some((_, from, _)) = search {
                    if r.searched != Some(from) {
                        // Been there: look round once (a target right behind the robot,
                        // out of its camera's reach, is seen so) before patrolling.
                        // The turn goes on from the check above the match.
                        r.searched = Some(from);
                        r.look_round_until = now + LOOK_ROUND;
                        nav.clear();
                        return (0.0, LOOK_ROUND_TURN);
                    }
                }
                if patrol.is_empty() {
                    nav.clear();
                    return (0.0, 0.0);
                }
                let at = patrol[r.patrol_next % patrol.len()];
                if (at.0 - r.pose.x).hypot(at.1 - r.pose.y) < 1.0 {
                    r.patrol_next = (r.patrol_next + 1) % patrol.len();
                }
                let next = patrol[r.patrol_next];
                if nav.goal() != Some(next) && nav.set_goal(r.pose, next, 0.0).is_err() {
                    r.patrol_next = (r.patrol_next + 1) % patrol.len();
                }
            }
        }
        let step = nav.step(now, r.pose, &obstacles);
        // Searching or patrolling and held up (by people, by another robot): it looks
        // round on the spot while it waits. What holds it up may be the target, beside
        // or behind it where the camera does not reach, boxed in by the robots.
        if target.is_none()
            && step
                .blocked_since
                .is_some_and(|b| now - b >= BLOCKED_LOOK_ROUND)
        {
            r.look_round_until = now + LOOK_ROUND;
            return (0.0, LOOK_ROUND_TURN);
        }
        // Belt and braces: never forward into something closer than the stop gap.
        if step.velocity.0 > 0.0 && step.free_ahead < 0.12 {
            return (0.0, step.velocity.1);
        }
        step.velocity
    }

    /// Whether updates are due at the newest sim time; if so the next one is scheduled.
    pub fn publish_due(&mut self) -> bool {
        if self.now + 1e-9 >= self.next_publish {
            self.next_publish = (self.next_publish + self.params.period).max(self.now);
            true
        } else {
            false
        }
    }

    /// Where `colour` is predicted at `now`: the filter's prediction, short of any wall
    /// between it and where the target was last placed ([`short_of_walls`]).
    fn predicted(&self, colour: Colour, now: f64) -> Option<(f64, f64)> {
        let to = self.tracker.predicted(colour, now)?;
        let t = self.tracker.track(colour)?;
        Some(short_of_walls(&self.map, (t.state[0], t.state[1]), to))
    }

    /// The track of `colour` now, as the service streams it (`None` if never seen): the
    /// position short of walls, as [`TrackingCore::predicted`].
    pub fn payload(&self, colour: Colour) -> Option<Track2d> {
        let mut p = self
            .tracker
            .payload(colour, self.now, self.params.period.max(1.0))?;
        if let Some(t) = self.tracker.track(colour) {
            (p.x, p.y) = short_of_walls(&self.map, (t.state[0], t.state[1]), (p.x, p.y));
        }
        Some(p)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A track last seen at (x, y) at sim time 10, walking at (vx, vy).
    fn track_at(x: f64, y: f64, vx: f64, vy: f64) -> crate::tracker::Track {
        crate::tracker::Track {
            state: nalgebra::Vector4::new(x, y, vx, vy),
            covariance: nalgebra::Matrix4::identity(),
            time: 10.0,
            last_seen: 10.0,
            seen_by: Default::default(),
            sightings: 5,
        }
    }

    #[test]
    fn a_prediction_stops_short_of_the_wall_it_would_run_into() {
        let map = OccupancyMap::office();
        // Along the south corridor: as predicted.
        assert_eq!(short_of_walls(&map, (20.0, 3.0), (25.0, 3.0)), (25.0, 3.0));
        // Into the office block's wall at y 4: 0.4 m short of it, on the corridor's side.
        let (x, y) = short_of_walls(&map, (20.0, 3.0), (20.0, 6.0));
        assert!(
            (x - 20.0).abs() < 1e-9 && (3.5..3.65).contains(&y),
            "({x}, {y})"
        );
    }

    #[test]
    fn a_lost_person_walks_on_down_the_corridor_and_round_its_corner_never_through_a_wall() {
        let map = OccupancyMap::office();
        // Last seen in the middle corridor (y 9..11), walking east at 0.7 m/s.
        let w = walk_on(&map, &track_at(26.0, 10.0, 0.7, 0.0), 60.0);
        for pair in w.points.windows(2) {
            let ((x0, y0), (x1, y1)) = (pair[0], pair[1]);
            let d = (x1 - x0).hypot(y1 - y0);
            assert!(map.raycast(x0, y0, (y1 - y0).atan2(x1 - x0), d).is_none());
            assert!(
                map.clearance(x1, y1, 0.3) >= 0.3,
                "({x1}, {y1}) against a wall"
            );
        }
        // 10 s on: 7 m down the corridor, still in it.
        let (x, y) = w.at(20.0);
        assert!(
            (32.0..34.0).contains(&x) && (9.2..10.8).contains(&y),
            "({x}, {y})"
        );
        // Past the corridor's end (the east corridor, x 36..38): turned north or south
        // along it, not into the outer wall.
        let (x, y) = w.at(40.0);
        assert!(
            (36.0..39.8).contains(&x) && !(8.5..11.5).contains(&y),
            "({x}, {y})"
        );
        // Slow, it is taken to walk at a person's pace; standing, to stay.
        let slow = walk_on(&map, &track_at(26.0, 10.0, 0.3, 0.0), 60.0);
        assert!(slow.at(20.0).0 > 31.0, "{:?}", slow.at(20.0));
        let standing = walk_on(&map, &track_at(26.0, 10.0, 0.1, 0.0), 60.0);
        assert_eq!(standing.at(50.0), (26.0, 10.0));
        assert!(standing.ended(10.5));
    }

    /// A mobile tracker on the office at `start`, with a laser (a half circle ahead, 1
    /// degree apart, 8 m) and no camera, on ground truth, patrolling to (10, 3) and
    /// following `follow`.
    fn mobile_tracker(start: Pose, follow: Option<Colour>) -> TrackingCore {
        use std::f64::consts::{FRAC_PI_2, PI};
        let map = Arc::new(OccupancyMap::office());
        let field = Arc::new(LikelihoodField::new(&map, 1.0));
        let planner = Arc::new(Planner::new(
            &map,
            crate::planner::PlannerParams {
                radius: 0.25,
                ..crate::planner::PlannerParams::default()
            },
        ));
        let robot = TrackerRobot {
            name: "T3".into(),
            start,
            mobile: true,
            geometry: SensorGeometry {
                laser: Some((-FRAC_PI_2, PI / 180.0, 8.0)),
                sonar: None,
                camera: None,
            },
            max_speed: 0.8,
        };
        let params = TrackingParams {
            ground_truth: true,
            patrol: vec![(10.0, 3.0)],
            follow,
            ..TrackingParams::default()
        };
        TrackingCore::new(map, field, planner, vec![robot], params, 1)
    }

    #[test]
    fn held_up_while_patrolling_it_looks_round_a_whole_turn_on_the_spot_uncut() {
        use std::f64::consts::{FRAC_PI_2, PI};
        let start = Pose {
            x: 20.0,
            y: 3.0,
            theta: PI,
        };
        let mut core = mobile_tracker(start, None);
        // Someone pressed against its front who does not step back: 0.42 m ahead,
        // across 40 degrees, wherever it turns.
        let laser: Vec<f32> = (0..181)
            .map(|k| {
                let b = -FRAC_PI_2 + f64::from(k) * PI / 180.0;
                if b.abs() < 0.35 {
                    (0.42 / b.cos()) as f32
                } else {
                    8.0
                }
            })
            .collect();
        let mut pose = start;
        let mut commands = Vec::new();
        for k in 0..400 {
            let t = f64::from(k) * 0.1;
            let s = SensorSample {
                time: t,
                truth: pose,
                odom: pose,
                laser_time: t,
                laser: laser.clone(),
                ..SensorSample::default()
            };
            let (v, w) = core.handle_sample(0, &s, &[Colour::Red]).velocity.unwrap();
            assert!(v <= 0.0, "drove into the person at {t} s: {v}");
            pose.theta = wrap(pose.theta + w * 0.1);
            commands.push((v, w));
        }
        // Held up 3 s, it turns at the look-round rate for a whole turn, not cut short
        // by attempts to get clear (which turned it back and forth on one side).
        let mut longest = 0;
        let mut run = 0;
        for &c in &commands {
            run = if c == (0.0, LOOK_ROUND_TURN) {
                run + 1
            } else {
                0
            };
            longest = longest.max(run);
        }
        assert!(
            f64::from(longest) * 0.1 >= LOOK_ROUND - 0.1,
            "the longest look round was {longest} steps"
        );
        let first = commands
            .iter()
            .position(|&c| c == (0.0, LOOK_ROUND_TURN))
            .unwrap();
        assert!(
            (25..=80).contains(&first),
            "it looked round after {first} steps"
        );
    }

    #[test]
    fn a_robot_parked_where_a_lost_person_stood_ends_the_search_there_and_it_patrols_on() {
        use std::f64::consts::{FRAC_PI_2, PI};
        // She stands at (20, 3), seen for 2 s, then never again; the delivery robot is
        // parked in front of the spot (at 19.5, 3), as it parks where she was last seen.
        let (her, parked, radius) = ((20.0, 3.0), (19.5, 3.0), 0.25);
        let mut pose = Pose {
            x: 16.0,
            y: 3.0,
            theta: 0.0,
        };
        let mut core = mobile_tracker(pose, Some(Colour::Red));
        let mut looked_round_at = None;
        let mut west_most = pose.x;
        for k in 0..400 {
            let t = f64::from(k) * 0.1;
            // The parked robot as the laser sees it (walls are not drawn: 8 m is clear).
            let laser: Vec<f32> = (0..181)
                .map(|b| {
                    let a = pose.theta - FRAC_PI_2 + f64::from(b) * PI / 180.0;
                    let (dx, dy) = (parked.0 - pose.x, parked.1 - pose.y);
                    let along = dx * a.cos() + dy * a.sin();
                    let off2 = dx * dx + dy * dy - along * along;
                    if along > 0.0 && off2 < radius * radius {
                        (along - (radius * radius - off2).sqrt()) as f32
                    } else {
                        8.0
                    }
                })
                .collect();
            let (dx, dy) = (her.0 - pose.x, her.1 - pose.y);
            let sightings = if t < 2.0 {
                vec![crate::sensing::Sighting {
                    colour: Colour::Red,
                    bearing: wrap(dy.atan2(dx) - pose.theta),
                    range: dx.hypot(dy),
                }]
            } else {
                Vec::new()
            };
            let s = SensorSample {
                time: t,
                truth: pose,
                odom: pose,
                laser_time: t,
                laser,
                camera_time: t,
                sightings,
                ..SensorSample::default()
            };
            let (v, w) = core.handle_sample(0, &s, &[Colour::Red]).velocity.unwrap();
            if (v, w) == (0.0, LOOK_ROUND_TURN) && looked_round_at.is_none() {
                looked_round_at = Some(t);
            }
            pose = muster_world_model::kinematics::integrate(pose, v, w, 0.1);
            let gap = (parked.0 - pose.x).hypot(parked.1 - pose.y) - radius;
            assert!(gap > 0.25, "ran into the parked robot at {t} s: {gap:.2} m");
            west_most = west_most.min(pose.x);
        }
        // Lost at 7 s (5 s unseen), held up short of the spot, with the spot in sight:
        // it looks round there once (she may be beside it) ...
        let looked = looked_round_at.expect("it never looked round");
        assert!(
            (7.0..12.0).contains(&looked),
            "it looked round at {looked} s"
        );
        // ... and goes on to patrol (to x = 10) well before the search's 60 s are up,
        // rather than be held up by the parked robot, looking round again and again.
        assert!(
            west_most < 11.0,
            "it got no further west than x = {west_most:.1}"
        );
    }

    #[test]
    fn a_doorway_is_narrower_than_a_corridor() {
        let map = OccupancyMap::office();
        // A south office's door on the middle corridor (x 9.5-10.5 at y 9) and the 2 m
        // middle corridor off its centre line, where T3 once made room as in a door.
        assert!(passage_width(&map, 10.0, 8.95, 2.0) < DOORWAY);
        assert!(passage_width(&map, 20.0, 10.4, 2.0) > DOORWAY);
        assert!(passage_width(&map, 20.0, 3.0, 2.0) > DOORWAY);
    }

    #[test]
    fn the_budget_gives_ten_sessions_idle_and_eight_tracking_three_targets() {
        let b = Budget::default();
        assert_eq!(b.sessions(0), 10);
        assert_eq!(b.sessions(3), 8);
        assert!(b.sessions(6) < 8);
    }
}
