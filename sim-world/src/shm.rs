//! The simulator's shared-memory interface (iceoryx2), read in place by robot systems.
//!
//! Per instance:
//! - `muster/<inst>/sim/world` — publish-subscribe [`WorldState`]: sim clock, every
//!   robot's pose and every person, history 1 (a late subscriber gets the latest);
//! - `muster/<inst>/sim/robot/<name>/sensors` — [`RobotSensors`]: pose, odometry, laser,
//!   sonar, camera detections, published when a sensor updates;
//! - `muster/<inst>/sim/robot/<name>/updated` — event rung after each sensors sample,
//!   so a robot system sleeps until there is news;
//! - `muster/<inst>/sim/robot/<name>/cmd` — [`RobotCommand`]s from controllers
//!   (velocity, camera pan/tilt/zoom), read by the simulator every step.

use crate::scenario::Colour;
use crate::world::World;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use std::time::Duration;

type Ipc = ipc::Service;

/// Most robots the world sample lists.
pub const MAX_ROBOTS: usize = 256;
/// Most people the world sample lists.
pub const MAX_PEOPLE: usize = 64;
/// Most laser beams in a sensors sample.
pub const MAX_BEAMS: usize = 1081;
/// Most sonars.
pub const MAX_SONARS: usize = 32;
/// Most camera detections per frame.
pub const MAX_DETECTIONS: usize = 32;

/// A short name in shared memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct Name {
    len: u8,
    bytes: [u8; 31],
}

impl Name {
    /// Copies up to 31 bytes (cut at a character boundary).
    pub fn new(s: &str) -> Self {
        let mut end = s.len().min(31);
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        let mut bytes = [0u8; 31];
        bytes[..end].copy_from_slice(&s.as_bytes()[..end]);
        Name {
            len: end as u8,
            bytes,
        }
    }
    /// The text.
    pub fn as_str(&self) -> &str {
        std::str::from_utf8(&self.bytes[..(self.len as usize).min(31)]).unwrap_or("")
    }
}

/// A pose in shared memory: x, y (m), theta (rad).
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct PoseC {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub theta: f64,
}

impl From<crate::kinematics::Pose> for PoseC {
    fn from(p: crate::kinematics::Pose) -> Self {
        PoseC {
            x: p.x,
            y: p.y,
            theta: p.theta,
        }
    }
}

/// One robot in the world sample.
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct RobotBrief {
    /// Name.
    pub name: Name,
    /// Beacon colour code + 1 (0: none).
    pub beacon: u8,
    /// Ground-truth pose.
    pub pose: PoseC,
    /// Linear and angular velocity.
    pub velocity: [f64; 2],
    /// Contacts so far (see [`crate::world::Robot::contacts`]).
    pub contacts: u64,
}

/// One person in the world sample.
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct PersonBrief {
    /// Name.
    pub name: Name,
    /// Beacon colour code.
    pub beacon: u8,
    /// Position and heading.
    pub pose: PoseC,
    /// Sim seconds held up so far (see [`crate::world::Person::held_up`]).
    pub held_up: f64,
}

/// The world at one instant.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[repr(C)]
pub struct WorldState {
    /// Sim time, s.
    pub time: f64,
    /// Kinematics steps so far.
    pub steps: u64,
    /// Robots listed.
    pub n_robots: u32,
    /// People listed.
    pub n_people: u32,
    /// Robots.
    pub robots: [RobotBrief; MAX_ROBOTS],
    /// People.
    pub people: [PersonBrief; MAX_PEOPLE],
}

/// One detected beacon.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct DetectionC {
    /// Colour code (see [`Colour::code`]).
    pub colour: u8,
    /// Bearing relative to the robot's heading, rad.
    pub bearing: f64,
    /// Range, m.
    pub range: f64,
}

/// Everything one robot senses.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[repr(C)]
pub struct RobotSensors {
    /// Sim time of this sample.
    pub time: f64,
    /// Ground-truth pose (for tests and evaluation).
    pub pose: PoseC,
    /// Odometry pose.
    pub odom: PoseC,
    /// Linear and angular velocity.
    pub velocity: [f64; 2],
    /// Whether the last move was blocked by a wall or body.
    pub bumped: u8,
    /// Laser scan time, beam count and ranges (right to left).
    pub laser_time: f64,
    /// Beams in `laser`.
    pub n_beams: u32,
    /// Ranges, m.
    pub laser: [f32; MAX_BEAMS],
    /// Sonar ring time.
    pub sonar_time: f64,
    /// Sonars in `sonar`.
    pub n_sonar: u32,
    /// Ranges, m.
    pub sonar: [f32; MAX_SONARS],
    /// Camera frame time.
    pub camera_time: f64,
    /// Camera pan, tilt (rad) and zoom now.
    pub ptz: [f64; 3],
    /// Detections in `detections`.
    pub n_detections: u32,
    /// Detections, nearest first.
    pub detections: [DetectionC; MAX_DETECTIONS],
}

/// A controller's command to a robot.
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct RobotCommand {
    /// 1: velocity (`a` = v m/s, `b` = w rad/s); 2: camera (`a` pan, `b` tilt rad, `c` zoom).
    pub kind: u8,
    /// First value.
    pub a: f64,
    /// Second value.
    pub b: f64,
    /// Third value.
    pub c: f64,
}

/// Command kind: velocity.
pub const CMD_VELOCITY: u8 = 1;
/// Command kind: camera.
pub const CMD_CAMERA: u8 = 2;

/// Why the shared-memory interface failed.
#[derive(Debug, thiserror::Error)]
#[error("sim shared memory ({what}): {detail}")]
pub struct ShmError {
    what: String,
    detail: String,
}

fn err(what: &str, e: impl std::fmt::Debug) -> ShmError {
    ShmError {
        what: what.to_string(),
        detail: format!("{e:?}"),
    }
}

fn name(s: &str) -> Result<ServiceName, ShmError> {
    ServiceName::new(s).map_err(|e| err(s, e))
}

fn robot_service(inst: &str, robot: &str, what: &str) -> String {
    format!("muster/{inst}/sim/robot/{robot}/{what}")
}

struct RobotPorts {
    sensors: Publisher<Ipc, RobotSensors, ()>,
    updated: Notifier<Ipc>,
    commands: Subscriber<Ipc, RobotCommand, ()>,
    stamp: f64,
}

/// The simulator's side: publishes world and sensors, takes commands.
pub struct SimShm {
    world: Publisher<Ipc, WorldState, ()>,
    world_updated: Notifier<Ipc>,
    robots: Vec<RobotPorts>,
    scratch_world: Box<WorldState>,
    scratch_sensors: Box<RobotSensors>,
}

fn empty_world() -> WorldState {
    WorldState {
        time: 0.0,
        steps: 0,
        n_robots: 0,
        n_people: 0,
        robots: [RobotBrief {
            name: Name::new(""),
            beacon: 0,
            pose: PoseC::default(),
            velocity: [0.0; 2],
            contacts: 0,
        }; MAX_ROBOTS],
        people: [PersonBrief {
            name: Name::new(""),
            beacon: 0,
            pose: PoseC::default(),
            held_up: 0.0,
        }; MAX_PEOPLE],
    }
}

fn empty_sensors() -> RobotSensors {
    RobotSensors {
        time: 0.0,
        pose: PoseC::default(),
        odom: PoseC::default(),
        velocity: [0.0; 2],
        bumped: 0,
        laser_time: 0.0,
        n_beams: 0,
        laser: [0.0; MAX_BEAMS],
        sonar_time: 0.0,
        n_sonar: 0,
        sonar: [0.0; MAX_SONARS],
        camera_time: 0.0,
        ptz: [0.0; 3],
        n_detections: 0,
        detections: [DetectionC::default(); MAX_DETECTIONS],
    }
}

impl SimShm {
    /// Creates every service for `world`'s robots on instance `inst`.
    pub fn open(node: &Node<Ipc>, inst: &str, world: &World) -> Result<Self, ShmError> {
        let wname = format!("muster/{inst}/sim/world");
        let svc = node
            .service_builder(&name(&wname)?)
            .publish_subscribe::<WorldState>()
            .history_size(1)
            .subscriber_max_buffer_size(1)
            .max_subscribers(64)
            .max_publishers(1)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(|e| err(&wname, e))?;
        let world_pub = svc
            .publisher_builder()
            .create()
            .map_err(|e| err(&wname, e))?;
        let ev = format!("muster/{inst}/sim/world/updated");
        let world_updated = event(node, &ev)?
            .notifier_builder()
            .create()
            .map_err(|e| err(&ev, e))?;
        let mut robots = Vec::new();
        for r in world.robots() {
            let n = &r.spec.name;
            let sname = robot_service(inst, n, "sensors");
            let svc = node
                .service_builder(&name(&sname)?)
                .publish_subscribe::<RobotSensors>()
                .history_size(1)
                .subscriber_max_buffer_size(1)
                .max_subscribers(16)
                .max_publishers(1)
                .enable_safe_overflow(true)
                .open_or_create()
                .map_err(|e| err(&sname, e))?;
            let sensors = svc
                .publisher_builder()
                .create()
                .map_err(|e| err(&sname, e))?;
            let uname = robot_service(inst, n, "updated");
            let updated = event(node, &uname)?
                .notifier_builder()
                .create()
                .map_err(|e| err(&uname, e))?;
            let cname = robot_service(inst, n, "cmd");
            let commands = command_service(node, &cname)?
                .subscriber_builder()
                .create()
                .map_err(|e| err(&cname, e))?;
            robots.push(RobotPorts {
                sensors,
                updated,
                commands,
                stamp: -1.0,
            });
        }
        Ok(SimShm {
            world: world_pub,
            world_updated,
            robots,
            scratch_world: Box::new(empty_world()),
            scratch_sensors: Box::new(empty_sensors()),
        })
    }

    /// Applies every command waiting for any robot.
    pub fn take_commands(&self, world: &mut World) {
        for (i, ports) in self.robots.iter().enumerate() {
            while let Ok(Some(c)) = ports.commands.receive() {
                let c = *c.payload();
                match c.kind {
                    CMD_VELOCITY => world.command_velocity(i, c.a, c.b),
                    CMD_CAMERA => world.command_camera(i, c.a, c.b, c.c),
                    other => tracing::debug!("unknown command kind {other} dropped"),
                }
            }
        }
    }

    /// Publishes sensors of robots whose sensors updated since the last call, and (if
    /// `with_world`) the world sample; rings the matching events.
    pub fn publish(&mut self, world: &World, with_world: bool) -> Result<(), ShmError> {
        for (ports, r) in self.robots.iter_mut().zip(world.robots()) {
            let newest = r.laser_time.max(r.sonar_time).max(r.camera_time);
            if newest <= ports.stamp {
                continue;
            }
            ports.stamp = newest;
            fill_sensors(&mut self.scratch_sensors, world.time(), r);
            let s = ports
                .sensors
                .loan_uninit()
                .map_err(|e| err("sensors loan", e))?;
            s.write_payload(*self.scratch_sensors)
                .send()
                .map_err(|e| err("sensors send", e))?;
            let _ = ports.updated.notify();
        }
        if with_world {
            fill_world(&mut self.scratch_world, world);
            let s = self.world.loan_uninit().map_err(|e| err("world loan", e))?;
            s.write_payload(*self.scratch_world)
                .send()
                .map_err(|e| err("world send", e))?;
            let _ = self.world_updated.notify();
        }
        Ok(())
    }
}

fn event(
    node: &Node<Ipc>,
    n: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<Ipc>, ShmError> {
    node.service_builder(&name(n)?)
        .event()
        .max_listeners(64)
        .max_notifiers(4)
        .open_or_create()
        .map_err(|e| err(n, e))
}

fn command_service(
    node: &Node<Ipc>,
    n: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, RobotCommand, ()>,
    ShmError,
> {
    node.service_builder(&name(n)?)
        .publish_subscribe::<RobotCommand>()
        .max_publishers(16)
        .max_subscribers(1)
        .subscriber_max_buffer_size(16)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| err(n, e))
}

fn fill_sensors(out: &mut RobotSensors, now: f64, r: &crate::world::Robot) {
    out.time = now;
    out.pose = r.pose.into();
    out.odom = r.odom.into();
    out.velocity = [r.velocity.0, r.velocity.1];
    out.bumped = u8::from(r.bumped);
    out.laser_time = r.laser_time;
    let nb = r.laser.len().min(MAX_BEAMS);
    out.n_beams = nb as u32;
    out.laser[..nb].copy_from_slice(&r.laser[..nb]);
    out.laser[nb..].fill(0.0);
    out.sonar_time = r.sonar_time;
    let ns = r.sonar.len().min(MAX_SONARS);
    out.n_sonar = ns as u32;
    out.sonar[..ns].copy_from_slice(&r.sonar[..ns]);
    out.sonar[ns..].fill(0.0);
    out.camera_time = r.camera_time;
    out.ptz = [r.ptz.pan, r.ptz.tilt, r.ptz.zoom];
    let nd = r.detections.len().min(MAX_DETECTIONS);
    out.n_detections = nd as u32;
    for (o, d) in out
        .detections
        .iter_mut()
        .zip(r.detections.iter().map(Some).chain(std::iter::repeat(None)))
    {
        *o = d.map_or(DetectionC::default(), |d| DetectionC {
            colour: d.colour.code(),
            bearing: d.bearing,
            range: d.range,
        });
    }
}

fn fill_world(out: &mut WorldState, world: &World) {
    out.time = world.time();
    out.steps = world.steps();
    let nr = world.robots().len().min(MAX_ROBOTS);
    out.n_robots = nr as u32;
    let blank_robot = RobotBrief {
        name: Name::new(""),
        beacon: 0,
        pose: PoseC::default(),
        velocity: [0.0; 2],
        contacts: 0,
    };
    for (k, o) in out.robots.iter_mut().enumerate() {
        *o = world
            .robots()
            .get(k)
            .filter(|_| k < nr)
            .map_or(blank_robot, |r| RobotBrief {
                name: Name::new(&r.spec.name),
                beacon: r.spec.beacon.map_or(0, |c| c.code() + 1),
                pose: r.pose.into(),
                velocity: [r.velocity.0, r.velocity.1],
                contacts: r.contacts,
            });
    }
    let np = world.people().len().min(MAX_PEOPLE);
    out.n_people = np as u32;
    let blank_person = PersonBrief {
        name: Name::new(""),
        beacon: 0,
        pose: PoseC::default(),
        held_up: 0.0,
    };
    for (k, o) in out.people.iter_mut().enumerate() {
        *o = world
            .people()
            .get(k)
            .filter(|_| k < np)
            .map_or(blank_person, |p| PersonBrief {
                name: Name::new(&p.name),
                beacon: p.beacon.code(),
                pose: p.pose.into(),
                held_up: p.held_up,
            });
    }
}

/// A robot system's side: reads one robot's sensors in place, waits for updates, sends
/// commands.
pub struct RobotLink {
    sensors: Subscriber<Ipc, RobotSensors, ()>,
    updated: Listener<Ipc>,
    commands: Publisher<Ipc, RobotCommand, ()>,
}

impl RobotLink {
    /// Opens the services of robot `robot` on instance `inst` (the simulator must run).
    pub fn open(node: &Node<Ipc>, inst: &str, robot: &str) -> Result<Self, ShmError> {
        let SensorsView { sensors, updated } = SensorsView::open(node, inst, robot)?;
        let cname = robot_service(inst, robot, "cmd");
        let commands = command_service(node, &cname)?
            .publisher_builder()
            .create()
            .map_err(|e| err(&cname, e))?;
        Ok(RobotLink {
            sensors,
            updated,
            commands,
        })
    }

    /// Waits up to `timeout` for a sensors sample newer than `after` (sim time); calls
    /// `f` with it, read in place from shared memory.
    pub fn next<R>(
        &self,
        after: f64,
        timeout: Duration,
        f: impl FnOnce(&RobotSensors) -> R,
    ) -> Result<Option<R>, ShmError> {
        wait_newest(&self.sensors, &self.updated, after, timeout, |s| s.time, f)
    }

    /// The descriptor of the robot's "sensors updated" event, for an epoll set (a robot
    /// system sleeps on it beside its protocol inbox). Call [`RobotLink::drain`] when it
    /// is readable.
    pub fn fd(&self) -> std::os::fd::RawFd {
        // SAFETY: the descriptor stays owned by the listener; we only read its number.
        unsafe { self.updated.file_descriptor().native_handle() }
    }

    /// Empties the "sensors updated" event without waiting.
    pub fn drain(&self) {
        let _ = self.updated.try_wait(|_| {});
    }

    /// Calls `f` with the newest sensors sample if it is newer than `after` (sim time),
    /// without waiting; read in place from shared memory.
    pub fn latest<R>(
        &self,
        after: f64,
        f: impl FnOnce(&RobotSensors) -> R,
    ) -> Result<Option<R>, ShmError> {
        latest_sensors(&self.sensors, &self.updated, after, f)
    }

    /// Sends a velocity command (m/s, rad/s).
    pub fn velocity(&self, v: f64, w: f64) -> Result<(), ShmError> {
        self.commands
            .send_copy(RobotCommand {
                kind: CMD_VELOCITY,
                a: v,
                b: w,
                c: 0.0,
            })
            .map(|_| ())
            .map_err(|e| err("command send", e))
    }

    /// Points the camera (pan, tilt in rad; zoom ≥ 1).
    pub fn camera(&self, pan: f64, tilt: f64, zoom: f64) -> Result<(), ShmError> {
        self.commands
            .send_copy(RobotCommand {
                kind: CMD_CAMERA,
                a: pan,
                b: tilt,
                c: zoom,
            })
            .map(|_| ())
            .map_err(|e| err("command send", e))
    }
}

/// An observer of one robot's sensors (a recorder, a viewer): no commands.
pub struct SensorsView {
    sensors: Subscriber<Ipc, RobotSensors, ()>,
    updated: Listener<Ipc>,
}

impl SensorsView {
    /// Subscribes to robot `robot`'s sensors on instance `inst` (the simulator must run).
    pub fn open(node: &Node<Ipc>, inst: &str, robot: &str) -> Result<Self, ShmError> {
        let (sensors, updated) = subscribe(
            node,
            &robot_service(inst, robot, "sensors"),
            &robot_service(inst, robot, "updated"),
        )?;
        Ok(SensorsView { sensors, updated })
    }

    /// Calls `f` with the newest sensors sample if it is newer than `after` (sim time),
    /// without waiting.
    pub fn latest<R>(
        &self,
        after: f64,
        f: impl FnOnce(&RobotSensors) -> R,
    ) -> Result<Option<R>, ShmError> {
        latest_sensors(&self.sensors, &self.updated, after, f)
    }
}

fn latest_sensors<R>(
    sensors: &Subscriber<Ipc, RobotSensors, ()>,
    updated: &Listener<Ipc>,
    after: f64,
    f: impl FnOnce(&RobotSensors) -> R,
) -> Result<Option<R>, ShmError> {
    wait_newest(sensors, updated, after, Duration::ZERO, |s| s.time, f)
}

/// An observer's view of the whole world (ground truth: for experiments, renders and
/// tools, never for a robot's own decisions).
pub struct WorldView {
    world: Subscriber<Ipc, WorldState, ()>,
    updated: Listener<Ipc>,
}

impl WorldView {
    /// Subscribes to instance `inst`'s world sample (the simulator must run).
    pub fn open(node: &Node<Ipc>, inst: &str) -> Result<Self, ShmError> {
        let (world, updated) = subscribe(
            node,
            &format!("muster/{inst}/sim/world"),
            &format!("muster/{inst}/sim/world/updated"),
        )?;
        Ok(WorldView { world, updated })
    }

    /// Waits up to `timeout` for a world sample newer than `after` (sim time) and calls
    /// `f` with it, read in place.
    pub fn next<R>(
        &self,
        after: f64,
        timeout: Duration,
        f: impl FnOnce(&WorldState) -> R,
    ) -> Result<Option<R>, ShmError> {
        wait_newest(&self.world, &self.updated, after, timeout, |w| w.time, f)
    }
}

/// A subscriber and the listener on its "updated" event.
type Subscribed<T> = (Subscriber<Ipc, T, ()>, Listener<Ipc>);

/// A subscriber to the simulator's service `sname` and a listener on its event `uname`.
fn subscribe<T: std::fmt::Debug + ZeroCopySend>(
    node: &Node<Ipc>,
    sname: &str,
    uname: &str,
) -> Result<Subscribed<T>, ShmError> {
    let sub = node
        .service_builder(&name(sname)?)
        .publish_subscribe::<T>()
        .open()
        .map_err(|e| err(sname, e))?
        .subscriber_builder()
        .create()
        .map_err(|e| err(sname, e))?;
    let updated = event(node, uname)?
        .listener_builder()
        .create()
        .map_err(|e| err(uname, e))?;
    Ok((sub, updated))
}

/// Waits up to `timeout` (zero: not at all) for a sample of `sub` whose `time` is past
/// `after`, sleeping on `updated`; calls `f` with the newest one, read in place.
fn wait_newest<T: std::fmt::Debug + ZeroCopySend, R>(
    sub: &Subscriber<Ipc, T, ()>,
    updated: &Listener<Ipc>,
    after: f64,
    timeout: Duration,
    time: impl Fn(&T) -> f64,
    f: impl FnOnce(&T) -> R,
) -> Result<Option<R>, ShmError> {
    let deadline = std::time::Instant::now() + timeout;
    loop {
        let mut newest = None;
        while let Some(s) = sub.receive().map_err(|e| err("receive", e))? {
            newest = Some(s);
        }
        if let Some(s) = newest.filter(|s| time(s.payload()) > after) {
            return Ok(Some(f(s.payload())));
        }
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return Ok(None);
        }
        updated
            .timed_wait(|_| {}, left)
            .map_err(|e| err("wait", e))?;
    }
}

/// The colour of a detection.
pub fn detection_colour(d: &DetectionC) -> Option<Colour> {
    Colour::from_code(d.colour)
}
