//! A robot, as a robot system sees it: a port it reads samples from and sends commands
//! to. The simulator's shared memory ([`RobotLink`]) is one implementation; ROS 2 topics
//! (`muster_ros2::port`) are another, so the paper's systems drive any robot that offers
//! a laser scan, odometry and velocity commands.

use crate::sensing::SensorSample;
use muster_sim_world::shm::RobotLink;
use std::os::fd::RawFd;

/// Why a port could not read or command its robot.
#[derive(Debug, thiserror::Error)]
#[error("robot port: {0}")]
pub struct PortError(pub String);

/// One robot's sensors and commands.
pub trait RobotPort {
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

impl RobotPort for RobotLink {
    fn fd(&self) -> RawFd {
        RobotLink::fd(self)
    }
    fn drain(&mut self) {
        RobotLink::drain(self);
    }
    fn latest(&mut self, after: f64) -> Result<Option<SensorSample>, PortError> {
        RobotLink::latest(self, after, SensorSample::from_shm).map_err(|e| PortError(e.to_string()))
    }
    fn newer_than(&mut self, after: f64) -> Option<f64> {
        RobotLink::latest(self, after, |s| s.time).ok().flatten()
    }
    fn velocity(&mut self, v: f64, w: f64) -> Result<(), PortError> {
        RobotLink::velocity(self, v, w).map_err(|e| PortError(e.to_string()))
    }
    fn camera(&mut self, pan: f64, tilt: f64, zoom: f64) -> Result<(), PortError> {
        RobotLink::camera(self, pan, tilt, zoom).map_err(|e| PortError(e.to_string()))
    }
}
