//! The paper's robot systems on sim-world: the multi-robot, multi-target **tracking
//! system** (`muster system tracking`) and the **delivery robot** (`muster system
//! delivery`). Each is a separate process that knows the world only through its robots'
//! ports ([`port::RobotPort`]: the simulator's shared memory, [`sim::SimPort`], or any
//! ROS 2 robot's topics) and reaches users only through the broker, like any other system.
//! The cores take this crate's types and the world model's (`muster_world_model`: poses,
//! maps, colours), never the simulator's; [`sim`] is the one module that knows it.
//!
//! The logic is pure, in the style of muster's cores: [`localizer::Localizer`] (Monte
//! Carlo localization), [`tracker::MultiTracker`] (a Kalman filter per target),
//! [`planner::Planner`] (A* on the inflated grid), [`navigator::Navigator`] (path
//! following with obstacle checks), [`delivery::DeliveryCore`] and
//! [`tracking::TrackingCore`] take sim time and sensor samples and return commands and
//! service updates. [`shell`] drives them through their ports as [`muster_systems::SystemApp`]s.

pub mod delivery;
pub mod link_sim;
pub mod localizer;
pub mod navigator;
pub mod planner;
pub mod port;
pub mod sensing;
pub mod shell;
pub mod sim;
pub mod tracker;
pub mod tracking;

/// The `q` quantile (0..=1, nearest rank) of the finite values in `v`; `None` if there
/// are none. For reports: localization and tracking errors, distances.
pub fn percentile(v: &[f64], q: f64) -> Option<f64> {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    s.sort_by(f64::total_cmp);
    quantile_of_sorted(&s, q)
}

/// [`percentile`] of values already sorted and finite.
pub fn quantile_of_sorted(sorted: &[f64], q: f64) -> Option<f64> {
    sorted
        .get(((sorted.len() as f64 - 1.0) * q).round() as usize)
        .copied()
}
