//! What a robot system shows of its own state: its estimates of its robots' poses, the
//! targets it tracks and the paths it plans. The systems publish it in shared memory
//! ([`crate::ipc::VizWriter`], a few times a second); `muster record`, `muster view`
//! and the pictures draw it beside the simulator's ground truth.

use serde::{Deserialize, Serialize};

/// One system's view, as it publishes it (JSON in shared memory).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SystemView {
    /// The system's name.
    pub system: String,
    /// Simulation time of the view, s.
    pub t: f64,
    /// Where the system believes its robots are.
    pub robots: Vec<RobotEstimate>,
    /// The targets it tracks.
    pub tracks: Vec<TrackView>,
    /// The paths it plans.
    pub plans: Vec<PlanView>,
}

/// A robot's pose as its system estimates it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RobotEstimate {
    /// The robot's name.
    pub name: String,
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub theta: f64,
}

/// A tracked target.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrackView {
    /// The beacon's colour (`red`, ...).
    pub colour: String,
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Velocity along x, m/s.
    pub vx: f64,
    /// Velocity along y, m/s.
    pub vy: f64,
    /// Position uncertainty (standard deviation along the worst axis), m.
    pub sigma: f64,
    /// Unseen too long: the position is the last known one.
    pub lost: bool,
}

/// A robot's planned path.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanView {
    /// The robot.
    pub robot: String,
    /// Where it goes.
    pub goal: (f64, f64),
    /// The waypoints still ahead, in order, m.
    pub path: Vec<(f64, f64)>,
}
