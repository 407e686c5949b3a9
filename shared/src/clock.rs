//! One clock for every process: scenario time, which may run faster than wall time.
//!
//! Every interval that belongs to the *scenario* (the broker's pings and their
//! deadline, a system's update rate, a scripted user's think and hold times, the
//! simulator) is given in scenario seconds and divided by the process's time scale
//! (`muster --time-scale X`, the same on every process of an instance) to get the wall
//! time it is waited. Latencies of the infrastructure itself (a list read, a request's
//! answer, a handshake's retransmission) are wall time: they measure muster, not the
//! scenario, and are never scaled.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// The shortest wall time a scaled *deadline* (not an interval) is given: a process on a
/// loaded 2-core machine may take this long to answer, whatever the scenario's speed.
pub const MIN_WALL_DEADLINE: Duration = Duration::from_secs(2);

/// How many scenario seconds pass per wall second (1: real time).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimeScale(f64);

impl Default for TimeScale {
    fn default() -> Self {
        TimeScale(1.0)
    }
}

impl TimeScale {
    /// Real time.
    pub const REAL: TimeScale = TimeScale(1.0);

    /// A scale of `x` scenario seconds per wall second; `x` must be finite, in
    /// [0.01, 1000].
    pub fn new(x: f64) -> Result<Self, String> {
        if x.is_finite() && (0.01..=1000.0).contains(&x) {
            Ok(TimeScale(x))
        } else {
            Err(format!("time scale {x} is not in [0.01, 1000]"))
        }
    }

    /// The factor.
    pub fn factor(self) -> f64 {
        self.0
    }

    /// The wall time a scenario interval takes.
    pub fn wall(self, scenario: Duration) -> Duration {
        Duration::from_secs_f64(scenario.as_secs_f64() / self.0)
    }

    /// The wall time a scenario deadline is given: [`TimeScale::wall`], but never under
    /// [`MIN_WALL_DEADLINE`] (nor over the unscaled deadline).
    pub fn wall_deadline(self, scenario: Duration) -> Duration {
        self.wall(scenario).max(MIN_WALL_DEADLINE.min(scenario))
    }

    /// The scenario time a wall interval stands for.
    pub fn scenario(self, wall: Duration) -> Duration {
        Duration::from_secs_f64(wall.as_secs_f64() * self.0)
    }

    /// A scenario rate (per scenario second) as a rate per wall second.
    pub fn wall_rate(self, per_scenario_second: f64) -> f64 {
        per_scenario_second * self.0
    }
}

impl std::str::FromStr for TimeScale {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let x: f64 = s
            .trim()
            .parse()
            .map_err(|_| format!("{s:?} is not a number"))?;
        TimeScale::new(x)
    }
}

impl std::fmt::Display for TimeScale {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)
    }
}

static GLOBAL: AtomicU64 = AtomicU64::new(0x3ff0_0000_0000_0000); // 1.0f64

/// Sets this process's time scale (once, from `--time-scale`); child processes it
/// starts are given the same.
pub fn set_global(scale: TimeScale) {
    GLOBAL.store(scale.0.to_bits(), Ordering::Relaxed);
}

/// This process's time scale.
pub fn global() -> TimeScale {
    TimeScale(f64::from_bits(GLOBAL.load(Ordering::Relaxed)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenario_intervals_shrink_and_deadlines_keep_a_floor() {
        let x10 = TimeScale::new(10.0).unwrap();
        assert_eq!(x10.wall(Duration::from_secs(20)), Duration::from_secs(2));
        assert_eq!(
            x10.scenario(Duration::from_secs(2)),
            Duration::from_secs(20)
        );
        assert_eq!(x10.wall_rate(1.0), 10.0);
        let x2 = TimeScale::new(2.0).unwrap();
        assert_eq!(
            x2.wall_deadline(Duration::from_secs(10)),
            Duration::from_secs(5)
        );
        assert_eq!(
            x10.wall_deadline(Duration::from_secs(10)),
            MIN_WALL_DEADLINE
        );
        // A deadline shorter than the floor is not lengthened.
        assert_eq!(
            x10.wall_deadline(Duration::from_millis(100)),
            Duration::from_millis(100)
        );
        assert_eq!(
            TimeScale::REAL.wall(Duration::from_secs(3)),
            Duration::from_secs(3)
        );
        assert!("0".parse::<TimeScale>().is_err());
        assert!("nan".parse::<TimeScale>().is_err());
        assert!("5000".parse::<TimeScale>().is_err());
        assert_eq!("2.5".parse::<TimeScale>().unwrap().factor(), 2.5);
    }

    #[test]
    fn the_global_scale_is_what_was_set() {
        assert_eq!(global().factor(), 1.0);
        set_global(TimeScale::new(4.0).unwrap());
        assert_eq!(global().factor(), 4.0);
        set_global(TimeScale::REAL);
    }
}
