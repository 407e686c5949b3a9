//! A ROS 2 robot as a muster system, with no code: `muster system ros2 --config FILE`.
//! Subscribed topics become data services, published topics command services, as the
//! file says ([`config`]); the robot is withdrawn while its topics are silent.
//!
//! It runs under muster's system runtime like any system ([`muster_systems::SystemApp`]):
//! the runtime sleeps on this node's DDS readers through one epoll descriptor and wakes
//! it for samples, protocol events and its own deadlines.

pub mod config;
mod inputs;

use crate::msgs::{Header, Pose, PoseStamped, RawMsg, Twist, Vector3};
use crate::node::Ros2Node;
use crate::Ros2Error;
use config::{full_type, resolve, CommandPayload, DataPayload, Ros2SystemConfig, TopicQos};
use inputs::TopicIn;
use muster_shared::ros2msg::Definitions;
use muster_shared::types::{EndReason, Payload, SessionId, TaskStatus};
use muster_systems::{SystemApp, SystemCore, SystemEvent};
use ros2_client::dds::rustdds::mio1;
use ros2_client::qos::{Durability, History, Reliability, WhenFull};
use ros2_client::{Publisher, QosProfile};
use std::collections::BTreeMap;
use std::os::fd::{AsRawFd, RawFd};
use std::sync::Arc;
use std::time::Duration;

/// Options the command line adds to the file.
#[derive(Clone, Debug)]
pub struct Ros2SystemOptions {
    /// ROS domain id.
    pub domain: u16,
    /// Deadman of twist services whose file entry names none.
    pub deadman: Duration,
}

impl Default for Ros2SystemOptions {
    fn default() -> Self {
        Ros2SystemOptions {
            domain: 0,
            deadman: Duration::from_millis(500),
        }
    }
}

/// How often a goal's status is reported while it is driven.
const STATUS_EVERY: Duration = Duration::from_secs(1);
/// How often DDS discovery is asked whether a topic has another type.
const TYPE_CHECK_EVERY: Duration = Duration::from_secs(2);
/// A topic never heard yet gets this long at least before it counts as silent: DDS
/// discovery between two participants takes seconds (measured: 1-4 s between
/// ros2-client and Fast DDS on one host).
const DISCOVERY_GRACE: Duration = Duration::from_secs(10);
/// Moving less than this counts as no progress, m.
const PROGRESS: f64 = 0.05;

struct GoalTask {
    goal: Option<(f64, f64)>,
    arrived: bool,
    /// When and where the robot last made progress.
    progress: Option<(Duration, (f64, f64))>,
    /// Where it was at the last report, and when.
    reported: Option<(Duration, (f64, f64))>,
    blocked_told: Option<Duration>,
}

struct GoalService {
    name: String,
    publisher: Publisher<PoseStamped>,
    topic: String,
    frame: String,
    pose_input: usize,
    tolerance: f64,
    blocked_after: Duration,
    tasks: BTreeMap<SessionId, GoalTask>,
    next_status: Duration,
}

struct TwistTask {
    last_input: Duration,
    moving: bool,
}

struct TwistService {
    name: String,
    publisher: Publisher<Twist>,
    topic: String,
    deadman: Duration,
    tasks: BTreeMap<SessionId, TwistTask>,
}

/// A command service publishing the ROS message it is sent (an open payload).
struct RawService {
    name: String,
    publisher: Publisher<RawMsg>,
    topic: String,
    ros_type: String,
    defs: Arc<Definitions>,
}

/// The system's logic and its ROS 2 node.
pub struct Ros2System {
    inputs: Vec<TopicIn>,
    /// Data services: (service, input).
    data: Vec<(String, usize)>,
    goals: Vec<GoalService>,
    twists: Vec<TwistService>,
    raws: Vec<RawService>,
    watched: Vec<usize>,
    silent_after: Duration,
    /// Why the robot's services are withdrawn, while they are.
    silenced: Option<String>,
    started: Option<Duration>,
    next_type_check: Duration,
    /// Topics whose other type on the ROS graph was reported.
    type_errors: std::collections::BTreeSet<String>,
    poll: mio1::Poll,
    events: mio1::Events,
    scratch: Vec<Payload>,
    // Last: readers and writers leave the DDS participant before it closes.
    node: Ros2Node,
}

fn qos_of(q: &TopicQos, publisher: bool) -> QosProfile {
    let reliable = q.reliability.as_deref() != Some("best_effort");
    let mut p = QosProfile::publisher_default()
        .reliability(if reliable {
            Reliability::Reliable {
                when_full: if publisher {
                    WhenFull::Fail
                } else {
                    WhenFull::DEFAULT
                },
            }
        } else {
            Reliability::BestEffort
        })
        .history(History::KeepLast {
            depth: q.depth.unwrap_or(10).max(1),
        });
    if q.durability.as_deref() == Some("transient_local") {
        p = p.durability(Durability::TransientLocal);
    } else {
        p = p.durability(Durability::Volatile);
    }
    p
}

/// The system core for `cfg`: its services, the latched ones latched.
pub fn system_core(cfg: &Ros2SystemConfig) -> SystemCore {
    let mut core = SystemCore::new(&cfg.system, std::process::id(), cfg.specs());
    for d in cfg.data.iter().filter(|d| d.is_latched()) {
        core.latch(&d.name);
    }
    core
}

impl Ros2System {
    /// Joins ROS domain `opts.domain` as node `/muster/<system>` with the file's topics.
    pub fn new(cfg: &Ros2SystemConfig, opts: &Ros2SystemOptions) -> Result<Self, Ros2Error> {
        let mut node = Ros2Node::new(opts.domain, "/muster", &crate::ros_name(&cfg.system))?;
        let ns = cfg.namespace();
        let mut inputs: Vec<TopicIn> = Vec::new();
        // A topic is subscribed once per type and kind (converted, or kept as the ROS
        // message itself with its definition).
        let mut input = |node: &mut Ros2Node,
                         topic: &str,
                         ty: &str,
                         qos: &TopicQos,
                         raw: Option<Arc<Definitions>>| {
            let topic = resolve(&ns, topic);
            let ty = full_type(ty);
            if let Some(k) = inputs
                .iter()
                .position(|i| i.topic == topic && i.ros_type == ty && i.raw == raw.is_some())
            {
                return Ok::<usize, Ros2Error>(k);
            }
            inputs.push(match raw {
                Some(defs) => TopicIn::subscribe_raw(node, &topic, &ty, qos_of(qos, false), defs)?,
                None => TopicIn::subscribe(node, &topic, &ty, qos_of(qos, false))?,
            });
            Ok(inputs.len() - 1)
        };
        let mut data = Vec::new();
        // The inputs some service needs heard all the time: every one but those only
        // latched data services take.
        let mut lively = Vec::new();
        for d in &cfg.data {
            let raw = match cfg.data_payload(d) {
                Ok(DataPayload::Ros(schema)) => Some(Arc::new(
                    Definitions::parse(&full_type(&d.ros_type), &schema)
                        .map_err(|e| Ros2Error::create(&d.name, e))?,
                )),
                Ok(DataPayload::Builtin(_)) => None,
                Err(e) => return Err(Ros2Error::create(&d.name, e)),
            };
            let k = input(&mut node, &d.topic, &d.ros_type, &d.qos, raw)?;
            data.push((d.name.clone(), k));
            if !d.is_latched() {
                lively.push(k);
            }
        }
        let (mut goals, mut twists, mut raws) = (Vec::new(), Vec::new(), Vec::new());
        for c in &cfg.command {
            match c.payload {
                CommandPayload::Goal2d => {
                    let pose_input = input(
                        &mut node,
                        c.pose_topic.as_deref().unwrap_or("odom"),
                        c.pose_type.as_deref().unwrap_or("nav_msgs/msg/Odometry"),
                        &TopicQos::default(),
                        None,
                    )?;
                    lively.push(pose_input);
                    let topic = resolve(&ns, c.topic.as_deref().unwrap_or("goal_pose"));
                    goals.push(GoalService {
                        name: c.name.clone(),
                        publisher: node.publisher(
                            &topic,
                            ("geometry_msgs", "PoseStamped"),
                            qos_of(&c.qos, true),
                        )?,
                        topic,
                        frame: c.frame.clone().unwrap_or_else(|| "map".into()),
                        pose_input,
                        tolerance: c.tolerance.unwrap_or(1.0),
                        blocked_after: c.blocked_after.unwrap_or(Duration::from_secs(5)),
                        tasks: BTreeMap::new(),
                        next_status: Duration::ZERO,
                    });
                }
                CommandPayload::Twist => {
                    let topic = resolve(&ns, c.topic.as_deref().unwrap_or("cmd_vel"));
                    twists.push(TwistService {
                        name: c.name.clone(),
                        publisher: node.publisher(
                            &topic,
                            ("geometry_msgs", "Twist"),
                            qos_of(&c.qos, true),
                        )?,
                        topic,
                        deadman: c.deadman.unwrap_or(opts.deadman),
                        tasks: BTreeMap::new(),
                    });
                }
                CommandPayload::Ros => {
                    let ty = full_type(c.ros_type.as_deref().unwrap_or_default());
                    let topic = resolve(&ns, c.topic.as_deref().unwrap_or_default());
                    let text = cfg
                        .library
                        .schema(&ty)
                        .map_err(|e| Ros2Error::create(&c.name, e))?;
                    let defs = Definitions::parse(&ty, &text)
                        .map_err(|e| Ros2Error::create(&c.name, e))?;
                    let (pkg, name) = (
                        ty.split('/').next().unwrap_or_default(),
                        ty.rsplit('/').next().unwrap_or_default(),
                    );
                    raws.push(RawService {
                        name: c.name.clone(),
                        publisher: node.publisher_named(&topic, pkg, name, qos_of(&c.qos, true))?,
                        topic,
                        ros_type: ty,
                        defs: Arc::new(defs),
                    });
                }
            }
        }
        let watched = match &cfg.watch {
            Some(topics) => topics
                .iter()
                .map(|t| {
                    let t = resolve(&ns, t);
                    inputs
                        .iter()
                        .position(|i| i.topic == t)
                        .ok_or_else(|| Ros2Error::Create {
                            what: format!("liveness watch of {t}"),
                            detail: "no [[data]] or pose_topic subscribes it".into(),
                        })
                })
                .collect::<Result<Vec<_>, _>>()?,
            // Every subscribed topic, but one only latched services take: a latched
            // topic is sent once or on change, and its silence says nothing of the robot.
            None => {
                lively.sort_unstable();
                lively.dedup();
                lively
            }
        };
        let poll = mio1::Poll::new().map_err(|e| Ros2Error::create("epoll", e))?;
        for (k, i) in inputs.iter_mut().enumerate() {
            i.register(poll.registry(), mio1::Token(k))
                .map_err(|e| Ros2Error::create(&i.topic, e))?;
        }
        tracing::info!(
            domain = opts.domain,
            system = cfg.system,
            subscribed = inputs.len(),
            published = goals.len() + twists.len() + raws.len(),
            "ROS 2 robot joining muster"
        );
        Ok(Ros2System {
            inputs,
            data,
            goals,
            twists,
            raws,
            watched,
            silent_after: cfg.silent_after(),
            silenced: None,
            started: None,
            next_type_check: Duration::ZERO,
            type_errors: std::collections::BTreeSet::new(),
            poll,
            events: mio1::Events::with_capacity(64),
            scratch: Vec::new(),
            node,
        })
    }

    /// Samples that could not be sent or decoded so far.
    pub fn errors(&self) -> u64 {
        self.node.errors()
    }

    fn drain(&mut self, core: &mut SystemCore, now: Duration) {
        for k in 0..self.inputs.len() {
            self.scratch.clear();
            let heard = self.inputs[k].drain(&self.node, now, &mut self.scratch);
            if !heard {
                continue;
            }
            for (service, _) in self.data.iter().filter(|(_, i)| *i == k) {
                // A latched service's samples go to the broker with no session too.
                if core.sessions_of(service) == 0 && !core.latched(service) {
                    continue;
                }
                for p in &self.scratch {
                    if let Err(e) =
                        core.publish(service, p, muster_shared::protocol::monotonic_ns())
                    {
                        self.node
                            .warn_limited(&format!("{service}: sample not sent: {e}"));
                    }
                }
            }
        }
        if self.silenced.is_some() && self.silent(now).is_none() {
            self.silenced = None;
            tracing::info!("the robot's topics are heard again: services restored");
            let names: Vec<String> = core.specs().iter().map(|s| s.name.clone()).collect();
            for n in names {
                core.restore(&n);
            }
        }
    }

    /// The first watched topic unheard for `silent_after`, with why.
    fn silent(&self, now: Duration) -> Option<String> {
        let started = self.started.unwrap_or(now);
        self.watched.iter().find_map(|&k| {
            let i = &self.inputs[k];
            (now >= self.deadline(i, started)).then(|| match &i.mismatch {
                Some(m) => m.clone(),
                None => format!(
                    "robot silent: nothing on {} for {}",
                    i.topic,
                    humantime::format_duration(self.silent_after)
                ),
            })
        })
    }

    /// When input `i` counts as silent.
    fn deadline(&self, i: &TopicIn, started: Duration) -> Duration {
        match i.last_heard {
            Some(t) => t + self.silent_after,
            None => started + self.silent_after.max(DISCOVERY_GRACE),
        }
    }

    fn stop(&self, t: &TwistService) {
        self.node.send(&t.publisher, Twist::default(), &t.topic);
    }

    fn liveness(&mut self, core: &mut SystemCore, now: Duration) {
        if self.silenced.is_some() {
            return;
        }
        let Some(reason) = self.silent(now) else {
            return;
        };
        tracing::warn!("{reason}: every service withdrawn until it is heard again");
        for t in &self.twists {
            self.stop(t);
        }
        let sessions: Vec<SessionId> = core.sessions().map(|(s, _, _)| s).collect();
        for s in sessions {
            core.end_session(s, EndReason::BySystem(reason.clone()));
        }
        let names: Vec<String> = core.specs().iter().map(|s| s.name.clone()).collect();
        for n in names {
            core.withdraw(&n);
        }
        self.silenced = Some(reason);
    }

    fn check_types(&mut self) {
        let mut topics: Vec<(usize, String, String)> = self
            .inputs
            .iter()
            .enumerate()
            .map(|(k, i)| (k, i.topic.clone(), i.ros_type.clone()))
            .collect();
        topics.extend(self.goals.iter().map(|g| {
            (
                usize::MAX,
                g.topic.clone(),
                "geometry_msgs/msg/PoseStamped".into(),
            )
        }));
        topics.extend(self.twists.iter().map(|t| {
            (
                usize::MAX,
                t.topic.clone(),
                "geometry_msgs/msg/Twist".into(),
            )
        }));
        topics.extend(
            self.raws
                .iter()
                .map(|r| (usize::MAX, r.topic.clone(), r.ros_type.clone())),
        );
        for (k, topic, ty) in topics {
            let others: Vec<String> = self
                .node
                .discovered_types(&topic)
                .into_iter()
                .filter(|t| *t != ty)
                .collect();
            let mismatch = (!others.is_empty()).then(|| {
                format!(
                    "topic {topic} has type {} on the ROS graph, but the config says {ty}",
                    others.join(" and ")
                )
            });
            // Said once while it lasts (again if it comes back).
            match &mismatch {
                Some(m) => {
                    if self.type_errors.insert(topic.clone()) {
                        tracing::error!("{m}");
                    }
                }
                None => {
                    self.type_errors.remove(&topic);
                }
            }
            if let Some(i) = self.inputs.get_mut(k) {
                i.mismatch = mismatch;
            }
        }
    }

    fn goal_input(
        &mut self,
        core: &mut SystemCore,
        now: Duration,
        g: usize,
        session: SessionId,
        payload: &Payload,
    ) {
        let goal = match payload.convert_to("goal2d") {
            Some(Payload::Goal2d { x, y }) if x.is_finite() && y.is_finite() => (x, y),
            _ => {
                core.status(
                    session,
                    TaskStatus::Rejected(format!("cannot use {} as a goal", payload.type_name())),
                );
                return;
            }
        };
        let pose = self.pose(self.goals[g].pose_input);
        let svc = &mut self.goals[g];
        let heading = pose.map_or(0.0, |(px, py)| (goal.1 - py).atan2(goal.0 - px));
        let msg = PoseStamped {
            // Stamp 0: "the latest transform" to tf2, whatever clock the robot runs on.
            header: Header::at(0.0, &svc.frame),
            pose: Pose::planar(goal.0, goal.1, heading),
        };
        self.node.send(&svc.publisher, msg, &svc.topic);
        let task = svc.tasks.entry(session).or_insert(GoalTask {
            goal: None,
            arrived: false,
            progress: None,
            reported: None,
            blocked_told: None,
        });
        task.goal = Some(goal);
        task.arrived = false;
        task.progress = pose.map(|p| (now, p));
        task.reported = pose.map(|p| (now, p));
        task.blocked_told = None;
        svc.next_status = now + STATUS_EVERY;
        let text = match pose {
            Some((px, py)) => format!(
                "accepted goal ({:.2}, {:.2}): {:.1} m, sent on {}",
                goal.0,
                goal.1,
                (goal.0 - px).hypot(goal.1 - py),
                svc.topic
            ),
            None => format!(
                "accepted goal ({:.2}, {:.2}): sent on {}",
                goal.0, goal.1, svc.topic
            ),
        };
        core.status(session, TaskStatus::Working(text));
    }

    fn pose(&self, input: usize) -> Option<(f64, f64)> {
        match self.inputs.get(input)?.latest {
            Some(Payload::Pose2d { x, y, .. }) => Some((x, y)),
            _ => None,
        }
    }

    fn goal_status(&mut self, core: &mut SystemCore, now: Duration) {
        for g in 0..self.goals.len() {
            if now < self.goals[g].next_status {
                continue;
            }
            let pose = self.pose(self.goals[g].pose_input);
            let svc = &mut self.goals[g];
            svc.next_status = now + STATUS_EVERY;
            let Some(p) = pose else { continue };
            for (&session, task) in svc.tasks.iter_mut() {
                let Some(goal) = task.goal.filter(|_| !task.arrived) else {
                    continue;
                };
                let left = (goal.0 - p.0).hypot(goal.1 - p.1);
                if left <= svc.tolerance {
                    task.arrived = true;
                    core.status(
                        session,
                        TaskStatus::Done(format!(
                            "arrived within {left:.2} m of ({:.2}, {:.2})",
                            goal.0, goal.1
                        )),
                    );
                    continue;
                }
                let (since, at) = *task.progress.get_or_insert((now, p));
                if (p.0 - at.0).hypot(p.1 - at.1) >= PROGRESS {
                    task.progress = Some((now, p));
                    task.blocked_told = None;
                    let speed = task.reported.map_or(0.0, |(t, q)| {
                        let dt = now.saturating_sub(t).as_secs_f64();
                        if dt > 0.0 {
                            (p.0 - q.0).hypot(p.1 - q.1) / dt
                        } else {
                            0.0
                        }
                    });
                    task.reported = Some((now, p));
                    let eta = if speed > 0.01 {
                        format!("ETA {:.0} s", left / speed)
                    } else {
                        "ETA unknown".into()
                    };
                    core.status(
                        session,
                        TaskStatus::Working(format!(
                            "driving: at ({:.2}, {:.2}), {left:.1} m to go, {eta}",
                            p.0, p.1
                        )),
                    );
                } else if now.saturating_sub(since) >= svc.blocked_after
                    && task
                        .blocked_told
                        .is_none_or(|t| now.saturating_sub(t) >= svc.blocked_after)
                {
                    task.blocked_told = Some(now);
                    core.status(
                        session,
                        TaskStatus::Working(format!(
                            "blocked at ({:.2}, {:.2}) for {:.0} s: {left:.1} m to go",
                            p.0,
                            p.1,
                            now.saturating_sub(since).as_secs_f64()
                        )),
                    );
                }
            }
        }
    }

    fn twist_input(
        &mut self,
        core: &mut SystemCore,
        now: Duration,
        t: usize,
        session: SessionId,
        payload: &Payload,
    ) {
        let svc = &mut self.twists[t];
        match payload {
            Payload::Twist { v, w } if v.is_finite() && w.is_finite() => {
                let msg = Twist {
                    linear: Vector3 {
                        x: *v,
                        ..Vector3::default()
                    },
                    angular: Vector3 {
                        z: *w,
                        ..Vector3::default()
                    },
                };
                self.node.send(&svc.publisher, msg, &svc.topic);
                let task = svc.tasks.entry(session).or_insert(TwistTask {
                    last_input: now,
                    moving: false,
                });
                let was_moving = task.moving;
                task.last_input = now;
                task.moving = *v != 0.0 || *w != 0.0;
                if task.moving && !was_moving {
                    core.status(
                        session,
                        TaskStatus::Working(format!(
                            "driving at {v:.2} m/s, {w:.2} rad/s (stops when input stops for {})",
                            humantime::format_duration(svc.deadman)
                        )),
                    );
                }
            }
            other => core.status(
                session,
                TaskStatus::Rejected(format!("cannot use {} as a velocity", other.type_name())),
            ),
        }
    }

    fn deadman(&mut self, core: &mut SystemCore, now: Duration) {
        for t in 0..self.twists.len() {
            let mut stop = Vec::new();
            let deadman = self.twists[t].deadman;
            for (&session, task) in self.twists[t].tasks.iter_mut() {
                if task.moving && now.saturating_sub(task.last_input) >= deadman {
                    task.moving = false;
                    stop.push(session);
                }
            }
            if !stop.is_empty() {
                self.stop(&self.twists[t]);
                for s in stop {
                    core.status(s, TaskStatus::Idle);
                }
            }
        }
    }
}

impl SystemApp for Ros2System {
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent) {
        match event {
            SystemEvent::SessionStarted {
                session, service, ..
            } if self.twists.iter().any(|t| t.name == service)
                || self.goals.iter().any(|g| g.name == service) =>
            {
                core.status(session, TaskStatus::Idle);
            }
            SystemEvent::Input {
                session,
                service,
                payload,
            } => {
                if let Some(g) = self.goals.iter().position(|g| g.name == service) {
                    self.goal_input(core, now, g, session, &payload);
                } else if let Some(t) = self.twists.iter().position(|t| t.name == service) {
                    self.twist_input(core, now, t, session, &payload);
                } else if let Some(r) = self.raws.iter().find(|r| r.name == service) {
                    match payload {
                        Payload::Encoded { type_name, data } if type_name == r.ros_type => {
                            // Checked whole before it is written (a bad sample is refused,
                            // never half-sent).
                            match r.defs.decode(&data) {
                                Ok(_) => {
                                    let msg = RawMsg {
                                        defs: r.defs.clone(),
                                        data,
                                    };
                                    self.node.send(&r.publisher, msg, &r.topic);
                                }
                                Err(e) => core.status(
                                    session,
                                    TaskStatus::Rejected(format!("not a {}: {e}", r.ros_type)),
                                ),
                            }
                        }
                        other => core.status(
                            session,
                            TaskStatus::Rejected(format!(
                                "cannot publish {} as {}",
                                other.type_name(),
                                r.ros_type
                            )),
                        ),
                    }
                }
            }
            SystemEvent::SessionEnded {
                session, service, ..
            } => {
                for g in self.goals.iter_mut().filter(|g| g.name == service) {
                    g.tasks.remove(&session);
                }
                // Whatever ended the session — its user, its user's death, the
                // system — the robot stops.
                for t in 0..self.twists.len() {
                    if self.twists[t].name == service
                        && self.twists[t].tasks.remove(&session).is_some()
                    {
                        self.stop(&self.twists[t]);
                    }
                }
            }
            _ => {}
        }
    }

    fn on_tick(&mut self, core: &mut SystemCore, now: Duration) {
        self.started.get_or_insert(now);
        if now >= self.next_type_check {
            self.next_type_check = now + TYPE_CHECK_EVERY;
            self.check_types();
        }
        self.deadman(core, now);
        self.goal_status(core, now);
        self.liveness(core, now);
    }

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        let Some(started) = self.started else {
            return Some(Duration::ZERO);
        };
        let mut next = self.next_type_check;
        if self.silenced.is_none() {
            for &k in &self.watched {
                next = next.min(self.deadline(&self.inputs[k], started));
            }
        }
        for t in &self.twists {
            for task in t.tasks.values().filter(|t| t.moving) {
                next = next.min(task.last_input + t.deadman);
            }
        }
        for g in &self.goals {
            if g.tasks.values().any(|t| t.goal.is_some() && !t.arrived) {
                next = next.min(g.next_status);
            }
        }
        Some(next)
    }

    fn descriptors(&self) -> Vec<RawFd> {
        vec![self.poll.as_raw_fd()]
    }

    fn on_ready(&mut self, core: &mut SystemCore, now: Duration, _index: usize) {
        self.started.get_or_insert(now);
        // Empty the epoll set's ready list (its readers are edge-triggered), then take
        // every sample from every reader.
        if let Err(e) = self.poll.poll(&mut self.events, Some(Duration::ZERO)) {
            self.node.warn_limited(&format!("epoll: {e}"));
        }
        self.drain(core, now);
    }
}
