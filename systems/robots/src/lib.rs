//! The paper's robot systems on sim-world: the multi-robot, multi-target **tracking
//! system** (`muster system tracking`) and the **delivery robot** (`muster system
//! delivery`). Each is a separate process that knows the world only through its robots'
//! sensors ([`muster_sim_world::shm::RobotLink`]) and reaches users only through the
//! broker, like any other system.
//!
//! The logic is pure, in the style of muster's cores: [`localizer::Localizer`] (Monte
//! Carlo localization), [`tracker::MultiTracker`] (a Kalman filter per target),
//! [`planner::Planner`] (A* on the inflated grid), [`navigator::Navigator`] (path
//! following with obstacle checks), [`delivery::DeliveryCore`] and
//! [`tracking::TrackingCore`] take sim time and sensor samples and return commands and
//! service updates. [`shell`] drives them over shared memory as [`muster_systems::SystemApp`]s.

pub mod delivery;
pub mod localizer;
pub mod navigator;
pub mod planner;
pub mod sensing;
pub mod shell;
pub mod tracker;
pub mod tracking;
