//! A robot, as a robot system sees it: a port it reads samples from and sends commands
//! to, and a description of the robot (its sensors' geometry, size, speed, where it
//! starts, the map it drives on). The simulator's shared memory ([`crate::sim::SimPort`])
//! is one implementation; ROS 2 topics (`muster_ros2::port`) are another, so the paper's
//! systems drive any robot that offers a laser scan, odometry and velocity commands.

use crate::sensing::{SensorGeometry, SensorSample};
use muster_world_model::{OccupancyMap, Pose};
use std::os::fd::RawFd;
use std::sync::Arc;

/// Why a port could not read or command its robot.
#[derive(Debug, thiserror::Error)]
#[error("robot port: {0}")]
pub struct PortError(pub String);

/// What a robot system knows of a robot before it drives it.
#[derive(Clone, Debug)]
pub struct RobotDescription {
    /// The robot's name.
    pub name: String,
    /// Where it starts on the map (the localizer's first belief).
    pub start: Pose,
    /// Its sensors.
    pub sensors: SensorGeometry,
    /// Body radius, m.
    pub radius: f64,
    /// Top speed, m/s.
    pub max_speed: f64,
    /// Where it goes when idle, if anywhere (x, y on the map).
    pub home: Option<(f64, f64)>,
    /// The map it drives on.
    pub map: Arc<OccupancyMap>,
    /// Fixtures the map does not show: other robots that never move (x, y, radius; m).
    /// A robot plans round them and localizes against them as against walls, and does
    /// not take them for people who may walk into it (which held a robot beside a
    /// stationary tracker in a corridor junction for minutes).
    pub fixtures: Vec<(f64, f64, f64)>,
}

/// One robot's sensors and commands.
pub trait RobotPort {
    /// What the robot is.
    fn description(&self) -> &RobotDescription;
    /// A descriptor readable when the robot has news (edge-triggered: call
    /// [`RobotPort::drain`] when it is).
    fn fd(&self) -> RawFd;
    /// Empties the news descriptor.
    fn drain(&mut self);
    /// The newest sample, if it is newer than `after` (robot time, s).
    fn latest(&mut self, after: f64) -> Result<Option<SensorSample>, PortError>;
    /// The time of a sample newer than `after` that arrived since, if any (how far the
    /// robot ran while the system worked).
    fn newer_than(&mut self, after: f64) -> Option<f64>;
    /// Drives at `v` m/s, turning at `w` rad/s.
    fn velocity(&mut self, v: f64, w: f64) -> Result<(), PortError>;
    /// Points the camera (pan, tilt rad; zoom ≥ 1); robots without one ignore it.
    fn camera(&mut self, pan: f64, tilt: f64, zoom: f64) -> Result<(), PortError>;
}

impl RobotDescription {
    /// The map with the fixtures drawn in ([`RobotDescription::fixtures`]).
    pub fn map_with_fixtures(&self) -> Arc<OccupancyMap> {
        with_fixtures(&self.map, &self.fixtures)
    }

    /// This description with its fixtures drawn into its map (and none left beside
    /// it), so that the planner and the localizer built from it share one map.
    pub fn fixtures_drawn(&self) -> RobotDescription {
        RobotDescription {
            map: self.map_with_fixtures(),
            fixtures: Vec::new(),
            ..self.clone()
        }
    }

    /// What the robot was taken to be, for reports (`--stats-json`): start pose, laser
    /// beams and field of view, sonar transducers, camera, size, speed, map size.
    pub fn summary(&self) -> serde_json::Value {
        let laser = self.sensors.laser.map(|(first, step, range)| {
            let beams = (-2.0 * first / step).round() as i64 + 1;
            serde_json::json!({"first_deg": first.to_degrees(), "step_deg": step.to_degrees(),
                "range_m": range, "beams_if_symmetric": beams})
        });
        let sonar = self.sensors.sonar.as_ref().map(|(b, range)| {
            serde_json::json!({"transducers": b.len(), "range_m": range,
                "bearings_deg": b.iter().map(|a| a.to_degrees()).collect::<Vec<_>>()})
        });
        let camera = self.sensors.camera.map(|(fov, range, pan)| {
            serde_json::json!({"fov_deg": fov.to_degrees(), "range_m": range,
                "pan_limit_deg": pan.to_degrees()})
        });
        let (w, h) = self.map.size();
        serde_json::json!({
            "start": [self.start.x, self.start.y, self.start.theta.to_degrees()],
            "laser": laser, "sonar": sonar, "camera": camera,
            "radius_m": self.radius, "max_speed": self.max_speed, "home": self.home,
            "map_m": [w, h],
        })
    }
}

/// `map` with `fixtures` (x, y, radius) drawn in as occupied; the map itself if there
/// are none.
pub fn with_fixtures(map: &Arc<OccupancyMap>, fixtures: &[(f64, f64, f64)]) -> Arc<OccupancyMap> {
    if fixtures.is_empty() {
        Arc::clone(map)
    } else {
        Arc::new(map.with_discs(fixtures))
    }
}
