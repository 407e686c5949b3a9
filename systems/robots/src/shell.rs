//! Thin shells: the tracking and delivery cores as [`SystemApp`]s. Each sleeps on its
//! robots' "sensors updated" events beside the protocol inbox (the SDK's
//! [`SystemApp::descriptors`]), reads each sample in place, feeds the core with it and
//! sends the core's commands back to the simulator. Everything runs on the simulator's
//! clock (the samples' sim time), so the systems follow a simulator running faster than
//! real time.

use crate::delivery::{DeliveryCore, DeliveryEvent, DeliveryParams};
use crate::localizer::{Localizer, LocalizerParams};
use crate::planner::{Planner, PlannerParams};
use crate::port::PortError;
use crate::port::RobotPort;
use crate::sensing::{LikelihoodField, SensorGeometry};
use crate::tracking::{TrackerRobot, TrackingCore, TrackingParams};
use muster_shared::ipc::VizWriter;
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{Payload, ServiceKind, ServiceSpec, TaskStatus};
use muster_shared::viz::{PlanView, RobotEstimate, SystemView, TrackView};
use muster_systems::{SystemApp, SystemCore, SystemEvent};
use muster_world_model::{wrap, Colour, Pose};
use std::os::fd::RawFd;
use std::sync::Arc;
use std::time::Duration;

/// Why a robot system could not start.
#[derive(Debug, thiserror::Error)]
pub enum RobotSystemError {
    /// The scenario has no such robot.
    #[error("the scenario has no robot {0:?}")]
    NoRobot(String),
    /// The robot lacks a sensor the system needs.
    #[error("robot {0} has no {1}")]
    MissingSensor(String, &'static str),
    /// The robot's port could not be opened or described.
    #[error(transparent)]
    Port(#[from] PortError),
    /// iceoryx2 refused a node.
    #[error(transparent)]
    Transport(#[from] muster_shared::ipc::TransportError),
    /// A configuration value is unusable; the text says which.
    #[error("{0}")]
    Config(String),
}

/// Localization error against ground truth, sampled once per weighed scan (for the
/// report only: ground truth never steers anything unless `--ground-truth`).
#[derive(Clone, Debug, Default)]
pub struct LocalizationStats {
    /// Position errors, m.
    pub position: Vec<f64>,
    /// Heading errors, degrees.
    pub heading: Vec<f64>,
}

impl LocalizationStats {
    fn add(&mut self, est: Pose, truth: Pose) {
        self.position.push((est.x - truth.x).hypot(est.y - truth.y));
        self.heading
            .push(wrap(est.theta - truth.theta).abs().to_degrees());
    }

    /// `{samples, position_p50, position_p95, position_max, heading_p50, heading_p95, heading_max}`.
    pub fn summary(&self) -> serde_json::Value {
        let sorted = |v: &[f64]| {
            let mut s = v.to_vec();
            s.sort_by(f64::total_cmp);
            s
        };
        let (pos, head) = (sorted(&self.position), sorted(&self.heading));
        let q = |s: &[f64], q: f64| crate::quantile_of_sorted(s, q);
        serde_json::json!({
            "samples": self.position.len(),
            "position_p50_m": q(&pos, 0.5),
            "position_p95_m": q(&pos, 0.95),
            "position_max_m": q(&pos, 1.0),
            "heading_p50_deg": q(&head, 0.5),
            "heading_p95_deg": q(&head, 0.95),
            "heading_max_deg": q(&head, 1.0),
        })
    }
}

/// How the tracking system runs.
#[derive(Clone, Debug)]
pub struct TrackingOptions {
    /// Robots it drives (default: every robot of the scenario with a camera).
    pub robots: Vec<String>,
    /// Those of them that may drive (patrol, follow).
    pub mobile: Vec<String>,
    /// The core's parameters (colours, rate, budget, ground truth, ...).
    pub params: TrackingParams,
    /// Quota of each colour's service.
    pub quota: u16,
    /// Whether the processing budget limits sessions.
    pub budget: bool,
    /// Seed of the filters' randomness.
    pub seed: u64,
}

/// The tracking system's services: one data service per colour.
pub fn tracking_specs(colours: &[Colour], robots: &[String], quota: u16) -> Vec<ServiceSpec> {
    colours
        .iter()
        .map(|c| ServiceSpec {
            name: c.name().to_string(),
            description: format!(
                "{} beacon tracked by {}: position, velocity, uncertainty",
                c.name(),
                robots.join(",")
            )
            .chars()
            .take(95)
            .collect(),
            kind: ServiceKind::Data,
            queue: false,
            quota,
            payload: "track2d".into(),
            schema: None,
        })
        .collect()
}

/// The tracking system as a [`SystemApp`].
pub struct TrackingApp {
    links: Vec<Box<dyn RobotPort>>,
    core: TrackingCore,
    after: Vec<f64>,
    budget: bool,
    /// The number of tracked targets the session limit was last set for.
    budgeted_for: Option<usize>,
    truth_stats: Vec<LocalizationStats>,
    last_scan: Vec<f64>,
    /// Per robot, how far the simulator had run past the sample a command was made
    /// from (sim s), as a slowly decaying peak (see [`DeliveryApp`]).
    latency: Vec<f64>,
    published: u64,
    /// Where the system shows its estimates and tracks (recorders, viewers).
    viz: Option<Viz>,
}

/// A system's view in shared memory, and its name.
struct Viz {
    writer: VizWriter,
    system: String,
    /// Sim time of the next view (a system that publishes on every sample throttles).
    next: f64,
}

/// Views a second a system publishes at most.
const VIZ_PERIOD: f64 = 0.5;

impl Viz {
    fn new(writer: VizWriter, system: &str) -> Self {
        Viz {
            writer,
            system: system.to_string(),
            next: f64::NEG_INFINITY,
        }
    }

    /// Publishes `view` (made at sim time `view.t`); the next is due a period later.
    fn publish(&mut self, view: SystemView) {
        self.next = view.t + VIZ_PERIOD;
        match self.writer.publish(&view) {
            Ok(()) => tracing::trace!(t = view.t, "system view shown"),
            Err(e) => tracing::debug!("system view: {e}"),
        }
    }
}

/// Every fixture the ports' descriptions name, once each.
fn fixtures_of(links: &[Box<dyn RobotPort>]) -> Vec<(f64, f64, f64)> {
    let mut all: Vec<(f64, f64, f64)> = Vec::new();
    for f in links.iter().flat_map(|l| l.description().fixtures.iter()) {
        if !all.contains(f) {
            all.push(*f);
        }
    }
    all
}

impl TrackingApp {
    /// Builds the system for `opts`, driving the robots behind `links` (opened to
    /// `opts.robots` in that order, all on one map: the first's).
    pub fn new(
        links: Vec<Box<dyn RobotPort>>,
        opts: &TrackingOptions,
    ) -> Result<Self, RobotSystemError> {
        let mut robots = Vec::new();
        let Some(map) = links.first().map(|l| Arc::clone(&l.description().map)) else {
            return Err(RobotSystemError::Config("no robots".into()));
        };
        if links.len() != opts.robots.len() {
            return Err(RobotSystemError::Config(format!(
                "{} robot ports for {} robots",
                links.len(),
                opts.robots.len()
            )));
        }
        let mut radius: f64 = 0.0;
        for (name, link) in opts.robots.iter().zip(&links) {
            let d = link.description();
            if d.sensors.camera.is_none() {
                return Err(RobotSystemError::MissingSensor(name.clone(), "camera"));
            }
            if d.sensors.laser.is_none() && !opts.params.ground_truth {
                return Err(RobotSystemError::MissingSensor(
                    name.clone(),
                    "laser (needed to localize; or run with --ground-truth)",
                ));
            }
            radius = radius.max(d.radius);
            robots.push(TrackerRobot {
                name: name.clone(),
                start: d.start,
                mobile: opts.mobile.contains(name),
                geometry: d.sensors.clone(),
                max_speed: d.max_speed,
            });
        }
        if let Some(m) = opts.mobile.iter().find(|m| !opts.robots.contains(m)) {
            return Err(RobotSystemError::Config(format!(
                "mobile robot {m} is not one of this system's robots"
            )));
        }
        let field = Arc::new(LikelihoodField::new(&map, 1.0));
        // The mobile robots plan round every fixture any robot's description names
        // (the system's own stationary trackers among them). Sight lines and the
        // localizers keep the bare map: a stationary robot stands inside its own disc.
        let planner = Arc::new(Planner::new(
            &crate::port::with_fixtures(&map, &fixtures_of(&links)),
            PlannerParams {
                radius,
                ..PlannerParams::default()
            },
        ));
        let n = robots.len();
        Ok(TrackingApp {
            core: TrackingCore::new(map, field, planner, robots, opts.params.clone(), opts.seed),
            after: vec![f64::NEG_INFINITY; links.len()],
            links,
            budget: opts.budget,
            budgeted_for: None,
            truth_stats: vec![LocalizationStats::default(); n],
            last_scan: vec![f64::NEG_INFINITY; n],
            latency: vec![0.0; n],
            published: 0,
            viz: None,
        })
    }

    /// Shows the system's robot estimates and tracks on `writer` (as system `system`).
    pub fn show_on(&mut self, writer: VizWriter, system: &str) {
        self.viz = Some(Viz::new(writer, system));
    }

    fn show(&mut self, now: f64) {
        let Some(viz) = self.viz.as_mut().filter(|v| v.next <= now) else {
            return;
        };
        let robots = self
            .core
            .robot_names()
            .into_iter()
            .enumerate()
            .filter_map(|(i, name)| {
                self.core.pose(i).map(|p| RobotEstimate {
                    name,
                    x: p.x,
                    y: p.y,
                    theta: p.theta,
                })
            })
            .collect();
        let tracks = self
            .core
            .colours()
            .iter()
            .filter_map(|c| {
                self.core.payload(*c).map(|t| TrackView {
                    colour: c.name().to_string(),
                    x: t.x,
                    y: t.y,
                    vx: t.vx,
                    vy: t.vy,
                    sigma: t.sigma,
                    lost: t.lost,
                })
            })
            .collect();
        let view = SystemView {
            system: viz.system.clone(),
            t: now,
            robots,
            tracks,
            plans: Vec::new(),
        };
        viz.publish(view);
    }

    /// Localization error per robot, against ground truth.
    pub fn localization(&self) -> Vec<(String, &LocalizationStats)> {
        self.core
            .robot_names()
            .into_iter()
            .zip(&self.truth_stats)
            .collect()
    }

    /// Updates streamed so far.
    pub fn published(&self) -> u64 {
        self.published
    }

    /// Colours users hold sessions on, most sessions first.
    fn wanted(&self, core: &SystemCore) -> Vec<Colour> {
        let mut w: Vec<(usize, Colour)> = self
            .core
            .colours()
            .iter()
            .map(|c| (core.sessions_of(c.name()), *c))
            .filter(|(n, _)| *n > 0)
            .collect();
        w.sort_by_key(|x| std::cmp::Reverse(x.0));
        w.into_iter().map(|(_, c)| c).collect()
    }

    fn publish(&mut self, core: &mut SystemCore, only: Option<Colour>) {
        for c in self.core.colours().to_vec() {
            if only.is_some_and(|o| o != c) || core.sessions_of(c.name()) == 0 {
                continue;
            }
            if let Some(t) = self.core.payload(c) {
                match core.publish(c.name(), &Payload::Track2d(t), monotonic_ns()) {
                    Ok(n) => self.published += n as u64,
                    Err(e) => tracing::warn!(colour = c.name(), "track not sent: {e}"),
                }
            }
        }
    }
}

impl SystemApp for TrackingApp {
    fn on_event(&mut self, core: &mut SystemCore, _now: Duration, event: SystemEvent) {
        if let SystemEvent::SessionStarted { service, .. } = event {
            // The new user sees where the target is at once, not a period later.
            if let Some(c) = Colour::from_name(&service) {
                self.publish(core, Some(c));
            }
        }
    }

    fn on_tick(&mut self, _core: &mut SystemCore, _now: Duration) {}

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        None // driven by the robots' sensors
    }

    fn descriptors(&self) -> Vec<RawFd> {
        self.links.iter().map(|l| l.fd()).collect()
    }

    fn on_ready(&mut self, core: &mut SystemCore, _now: Duration, index: usize) {
        let Some(link) = self.links.get_mut(index) else {
            return;
        };
        link.drain();
        let sample = link.latest(self.after[index]);
        let sample = match sample {
            Ok(Some(s)) => s,
            Ok(None) => return,
            Err(e) => {
                tracing::warn!("robot {index}: {e}");
                return;
            }
        };
        self.after[index] = sample.time;
        let wanted = self.wanted(core);
        let cmd = self.core.handle_sample(index, &sample, &wanted);
        if sample.laser_time > self.last_scan[index] {
            self.last_scan[index] = sample.laser_time;
            if let Some(est) = self.core.pose(index) {
                self.truth_stats[index].add(est, sample.truth);
            }
        }
        let link = &mut self.links[index];
        if let Some((v, w)) = cmd.velocity {
            if let Err(e) = link.velocity(v, w) {
                tracing::warn!("robot {index}: {e}");
            }
            // As the delivery system measures it: a mobile tracker's margins grow with it.
            let peak = &mut self.latency[index];
            *peak = latency_peak(*peak, command_lag(link.as_mut(), sample.time));
            self.core.set_latency(index, *peak);
        }
        if let Some((pan, tilt, zoom)) = cmd.camera {
            if let Err(e) = link.camera(pan, tilt, zoom) {
                tracing::warn!("robot {index}: {e}");
            }
        }
        // The limit follows the number of targets tracked; set it when that changes.
        let tracked = self.core.tracked();
        if self.budget && self.budgeted_for != Some(tracked) {
            self.budgeted_for = Some(tracked);
            let limit = self.core.session_limit();
            // The paper's two reasons: the system client manages so many requests at
            // once (its quota), and fewer while its robots track (overburdened).
            let reason = if tracked == 0 {
                format!("quota exceeded: the system manages {limit} requests at once")
            } else {
                format!(
                    "overburdened: tracking {tracked} targets, the robots sustain {limit} sessions"
                )
            };
            core.set_session_limit(Some(limit), &reason);
        }
        if self.core.publish_due() {
            self.publish(core, None);
        }
        self.show(sample.time);
    }
}

/// How the delivery system runs.
#[derive(Clone, Debug)]
pub struct DeliveryOptions {
    /// The robot it drives.
    pub robot: String,
    /// The service's name.
    pub service: String,
    /// Quota of the service.
    pub quota: u16,
    /// Whether it keeps a task queue.
    pub queue: bool,
    /// Use ground truth instead of localization (experiments only).
    pub ground_truth: bool,
    /// Delivery behaviour (arrival distance, going home, ...); `home` is filled from
    /// the scenario if empty.
    pub params: DeliveryParams,
    /// Seed of the localizer's randomness.
    pub seed: u64,
}

/// The delivery system's service: one command service taking `goal2d`.
pub fn delivery_specs(opts: &DeliveryOptions) -> Vec<ServiceSpec> {
    vec![ServiceSpec {
        name: opts.service.clone(),
        description: format!(
            "delivery robot {}: give a goal2d; reports pose, distance, ETA, arrival within {} m",
            opts.robot, opts.params.arrival
        )
        .chars()
        .take(95)
        .collect(),
        kind: ServiceKind::Command,
        queue: opts.queue,
        quota: opts.quota,
        payload: "goal2d".into(),
        schema: None,
    }]
}

/// The delivery robot's control loop on one robot: reads each sensor sample, localizes
/// (or takes ground truth), steps the [`DeliveryCore`] and sends its velocity. The
/// delivery system ([`DeliveryApp`]) drives it from muster sessions; a fleet bridge (VDA
/// 5050) from orders.
pub struct DeliveryDriver {
    link: Box<dyn RobotPort>,
    geometry: SensorGeometry,
    localizer: Option<Localizer>,
    core: DeliveryCore,
    pose: Pose,
    after: f64,
    last_scan: f64,
    now: f64,
    stats: LocalizationStats,
    bumped: bool,
    last_command: (f64, f64),
    /// How far the simulator had run past the sample a command was made from, when it
    /// was sent (sim s): the controller's own latency, fed to the navigator as a
    /// slowly decaying peak.
    latency: f64,
    latencies: Vec<f64>,
    robot: String,
}

impl DeliveryDriver {
    /// Drives the robot behind `link` (the simulator's shared memory, ROS 2 topics, ...)
    /// as robot `robot`, localizing unless `ground_truth`.
    pub fn new(
        link: Box<dyn RobotPort>,
        robot: &str,
        ground_truth: bool,
        params: DeliveryParams,
        seed: u64,
    ) -> Result<Self, RobotSystemError> {
        let d = link.description().clone();
        let geometry = d.sensors.clone();
        if geometry.laser.is_none() {
            return Err(RobotSystemError::MissingSensor(robot.to_string(), "laser"));
        }
        let d = d.fixtures_drawn();
        let core = DeliveryCore::for_robot(&d, params);
        let (start, map) = (d.start, d.map);
        let localizer = (!ground_truth).then(|| {
            Localizer::new(
                Arc::new(LikelihoodField::new(&map, 1.0)),
                start,
                LocalizerParams::default(),
                seed,
            )
        });
        Ok(DeliveryDriver {
            link,
            geometry,
            localizer,
            core,
            pose: start,
            after: f64::NEG_INFINITY,
            last_scan: f64::NEG_INFINITY,
            now: 0.0,
            stats: LocalizationStats::default(),
            bumped: false,
            last_command: (0.0, 0.0),
            latency: 0.0,
            latencies: Vec::new(),
            robot: robot.to_string(),
        })
    }

    /// The robot's name.
    pub fn robot(&self) -> &str {
        &self.robot
    }

    /// What the robot is.
    pub fn description(&self) -> &crate::port::RobotDescription {
        self.link.description()
    }

    /// The descriptor readable when the robot has a new sample.
    pub fn fd(&self) -> RawFd {
        self.link.fd()
    }

    /// The pose estimate.
    pub fn pose(&self) -> Pose {
        self.pose
    }

    /// The newest sample's sim time, s.
    pub fn now(&self) -> f64 {
        self.now
    }

    /// The last velocity sent (v m/s, w rad/s).
    pub fn last_command(&self) -> (f64, f64) {
        self.last_command
    }

    /// The task logic (goal, path, arrivals).
    pub fn core(&self) -> &DeliveryCore {
        &self.core
    }

    /// A new goal (it replaces the current one).
    pub fn set_goal(&mut self, goal: (f64, f64)) -> Vec<DeliveryEvent> {
        self.core.set_goal(self.now, self.pose, goal)
    }

    /// Drops the goal and halts.
    pub fn halt(&mut self) {
        self.core.halt(self.now);
    }

    /// Drops the goal and stops the robot now (not at the next sample): for a
    /// controller about to go away.
    pub fn stop(&mut self) {
        self.core.halt(self.now);
        self.last_command = (0.0, 0.0);
        if let Err(e) = self.link.velocity(0.0, 0.0) {
            tracing::warn!("{e}");
        }
    }

    /// Nobody is tasking the robot any more: the home timer starts.
    pub fn untasked(&mut self) {
        self.core.untasked(self.now);
    }

    /// Localization error against ground truth.
    pub fn localization(&self) -> &LocalizationStats {
        &self.stats
    }

    /// The controller's latency (see `latency` above): `{samples, p50_s, p99_s, max_s}`.
    pub fn latency_summary(&self) -> serde_json::Value {
        let mut s = self.latencies.clone();
        s.sort_by(f64::total_cmp);
        let q = |q: f64| crate::quantile_of_sorted(&s, q);
        serde_json::json!({"samples": s.len(), "p50_s": q(0.5), "p99_s": q(0.99), "max_s": q(1.0)})
    }

    /// One control step on the robot's newest sample, if there is a new one (call when
    /// [`DeliveryDriver::fd`] is readable): what the task logic reported.
    pub fn step(&mut self, tasked: bool) -> Option<Vec<DeliveryEvent>> {
        self.link.drain();
        let sample = match self.link.latest(self.after) {
            Ok(Some(s)) => s,
            Ok(None) => return None,
            Err(e) => {
                tracing::warn!("{e}");
                return None;
            }
        };
        self.after = sample.time;
        self.now = sample.time;
        match &mut self.localizer {
            Some(l) => {
                l.handle_odometry(sample.odom);
                if let Some(scan) = self.geometry.scan(&sample) {
                    l.handle_scan(sample.laser_time, &scan);
                }
                self.pose = l.estimate();
            }
            None => self.pose = sample.truth,
        }
        if sample.laser_time > self.last_scan {
            self.last_scan = sample.laser_time;
            self.stats.add(self.pose, sample.truth);
        }
        let obstacles = self.geometry.obstacle_points(&sample, 3.5);
        if sample.bumped && !self.bumped {
            // A contact: say what the robot saw and did, to find out why.
            let nearest = obstacles
                .iter()
                .map(|(x, y)| (x.hypot(*y), y.atan2(*x).to_degrees()))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            tracing::warn!(
                t = sample.time,
                pose = ?self.pose,
                last_command = ?self.last_command,
                ?nearest,
                "contact: the robot's move was cut short"
            );
        }
        self.bumped = sample.bumped;
        let ((v, w), events) = self.core.step(sample.time, self.pose, &obstacles, tasked);
        self.last_command = (v, w);
        if let Err(e) = self.link.velocity(v, w) {
            tracing::warn!("{e}");
        }
        let lag = command_lag(self.link.as_mut(), sample.time);
        if self.latencies.len() < 200_000 {
            self.latencies.push(lag);
        }
        self.latency = latency_peak(self.latency, lag);
        self.core.set_latency(self.latency);
        Some(events)
    }
}

/// The delivery system as a [`SystemApp`].
pub struct DeliveryApp {
    driver: DeliveryDriver,
    service: String,
    /// Where the system shows its estimate and plan (recorders, viewers).
    viz: Option<Viz>,
}

impl DeliveryApp {
    /// Builds the system for `opts`, driving the robot behind `link` (the simulator's
    /// shared memory, ROS 2 topics, ...).
    pub fn new(link: Box<dyn RobotPort>, opts: &DeliveryOptions) -> Result<Self, RobotSystemError> {
        Ok(DeliveryApp {
            driver: DeliveryDriver::new(
                link,
                &opts.robot,
                opts.ground_truth,
                opts.params.clone(),
                opts.seed,
            )?,
            service: opts.service.clone(),
            viz: None,
        })
    }

    /// Shows the robot's estimated pose and planned path on `writer` (as system
    /// `system`).
    pub fn show_on(&mut self, writer: VizWriter, system: &str) {
        self.viz = Some(Viz::new(writer, system));
    }

    fn show(&mut self) {
        let d = &self.driver;
        let now = d.now();
        let Some(viz) = self.viz.as_mut().filter(|v| v.next <= now) else {
            return;
        };
        let plans = d
            .core()
            .goal()
            .map(|goal| PlanView {
                robot: d.robot().to_string(),
                goal,
                path: d.core().path().to_vec(),
            })
            .into_iter()
            .collect();
        let pose = d.pose();
        let view = SystemView {
            system: viz.system.clone(),
            t: now,
            robots: vec![RobotEstimate {
                name: d.robot().to_string(),
                x: pose.x,
                y: pose.y,
                theta: pose.theta,
            }],
            tracks: Vec::new(),
            plans,
        };
        viz.publish(view);
    }

    /// Localization error against ground truth.
    pub fn localization(&self) -> &LocalizationStats {
        self.driver.localization()
    }

    /// The controller's latency: `{samples, p50_s, p99_s, max_s}`.
    pub fn latency_summary(&self) -> serde_json::Value {
        self.driver.latency_summary()
    }

    /// Goals reached.
    pub fn arrivals(&self) -> u64 {
        self.driver.core().arrivals()
    }

    fn tell(&self, core: &mut SystemCore, events: Vec<DeliveryEvent>) {
        if events.is_empty() {
            return;
        }
        let sessions: Vec<_> = core
            .sessions()
            .filter(|(_, _, s)| *s == self.service)
            .map(|(id, _, _)| id)
            .collect();
        for e in events {
            tracing::debug!(?e, "delivery");
            let status = match e {
                DeliveryEvent::Accepted {
                    goal,
                    distance,
                    eta,
                } => TaskStatus::Working(format!(
                    "accepted goal ({:.2}, {:.2}): {distance:.1} m, ETA {eta:.0} s",
                    goal.0, goal.1
                )),
                DeliveryEvent::Driving {
                    pose,
                    distance,
                    eta,
                } => TaskStatus::Working(format!(
                    "driving: at ({:.2}, {:.2}), {distance:.1} m to go, ETA {eta:.0} s",
                    pose.x, pose.y
                )),
                DeliveryEvent::Blocked { pose, for_s } => TaskStatus::Working(format!(
                    "blocked at ({:.2}, {:.2}) for {for_s:.0} s: waiting or replanning",
                    pose.x, pose.y
                )),
                DeliveryEvent::Arrived { goal, distance } => TaskStatus::Done(format!(
                    "arrived within {distance:.2} m of ({:.2}, {:.2}); halted",
                    goal.0, goal.1
                )),
                DeliveryEvent::Unreachable { reason, .. } => {
                    TaskStatus::Rejected(format!("unreachable: {reason}"))
                }
                DeliveryEvent::ReturningHome => {
                    TaskStatus::Working("not tasked: returning home".into())
                }
                DeliveryEvent::Home => TaskStatus::Idle,
            };
            for &s in &sessions {
                core.status(s, status.clone());
            }
        }
    }
}

impl SystemApp for DeliveryApp {
    fn on_event(&mut self, core: &mut SystemCore, _now: Duration, event: SystemEvent) {
        match event {
            SystemEvent::SessionStarted { session, .. } => core.status(session, TaskStatus::Idle),
            SystemEvent::Input {
                session, payload, ..
            } => match payload.convert_to("goal2d") {
                Some(Payload::Goal2d { x, y }) if x.is_finite() && y.is_finite() => {
                    let ev = self.driver.set_goal((x, y));
                    self.tell(core, ev);
                }
                _ => core.status(
                    session,
                    TaskStatus::Rejected(format!("cannot use {} as a goal", payload.type_name())),
                ),
            },
            SystemEvent::SessionEnded { .. } if core.sessions_of(&self.service) == 0 => {
                self.driver.untasked();
            }
            _ => {}
        }
    }

    fn on_tick(&mut self, _core: &mut SystemCore, _now: Duration) {}

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        None // driven by the robot's sensors
    }

    fn descriptors(&self) -> Vec<RawFd> {
        vec![self.driver.fd()]
    }

    fn on_ready(&mut self, core: &mut SystemCore, _now: Duration, _index: usize) {
        let tasked = core.sessions_of(&self.service) > 0;
        if let Some(events) = self.driver.step(tasked) {
            self.tell(core, events);
            self.show();
        }
    }
}

/// How far the simulator ran while the system worked on the sample of `sample_time`, as
/// the newest sample says once the command is sent (sim s): the controller's latency.
fn command_lag(link: &mut dyn RobotPort, sample_time: f64) -> f64 {
    link.newer_than(sample_time)
        .map_or(0.0, |t| (t - sample_time).max(0.0))
}

/// The latency a navigator plans with: the newest lag, or the last peak decaying (a
/// half-life of about 2 s at the sensors' 10 Hz).
fn latency_peak(peak: f64, lag: f64) -> f64 {
    lag.max(peak * 0.97)
}
