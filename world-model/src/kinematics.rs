//! Differential-drive kinematics: exact arcs and acceleration limits.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// A position and heading in the world frame (m, m, rad in (-π, π]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub theta: f64,
}

/// Wraps an angle into (-π, π].
pub fn wrap(a: f64) -> f64 {
    // Most angles are in range or one turn off; the subtraction is exact there
    // (Sterbenz), so these give what the remainder below gives.
    if a > -PI && a <= PI {
        return a;
    }
    if a > PI && a <= 3.0 * PI {
        return a - 2.0 * PI;
    }
    if a <= -PI && a > -3.0 * PI {
        return a + 2.0 * PI;
    }
    let mut a = a % (2.0 * PI);
    if a <= -PI {
        a += 2.0 * PI;
    } else if a > PI {
        a -= 2.0 * PI;
    }
    a
}

/// The pose after driving at `v` m/s and `w` rad/s for `t` s: an exact arc.
pub fn integrate(p: Pose, v: f64, w: f64, t: f64) -> Pose {
    let dtheta = w * t;
    if dtheta.abs() < 1e-12 {
        return Pose {
            x: p.x + v * t * p.theta.cos(),
            y: p.y + v * t * p.theta.sin(),
            theta: p.theta,
        };
    }
    let r = v / w;
    let th = p.theta + dtheta;
    Pose {
        x: p.x + r * (th.sin() - p.theta.sin()),
        y: p.y - r * (th.cos() - p.theta.cos()),
        theta: wrap(th),
    }
}

/// Moves `current` towards `target` by at most `max_step`.
pub fn approach(current: f64, target: f64, max_step: f64) -> f64 {
    if (target - current).abs() <= max_step {
        target
    } else {
        current + max_step.copysign(target - current)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arcs_match_the_closed_form() {
        // A quarter circle of radius 2 turning left from the origin facing +x ends at (2, 2) facing +y.
        let w = 0.5;
        let p = integrate(Pose::default(), 1.0, w, PI / 2.0 / w);
        assert!(
            (p.x - 2.0).abs() < 1e-12 && (p.y - 2.0).abs() < 1e-12,
            "{p:?}"
        );
        assert!((p.theta - PI / 2.0).abs() < 1e-12);
        // A full circle returns to the start; many small steps agree with one big one.
        let start = Pose {
            x: 1.0,
            y: -3.0,
            theta: 0.3,
        };
        let full = integrate(start, 0.7, 1.1, 2.0 * PI / 1.1);
        assert!((full.x - start.x).abs() < 1e-9 && (full.y - start.y).abs() < 1e-9);
        let mut q = start;
        for _ in 0..1000 {
            q = integrate(q, 0.7, -0.4, 0.01);
        }
        let once = integrate(start, 0.7, -0.4, 10.0);
        assert!(
            (q.x - once.x).abs() < 1e-9
                && (q.y - once.y).abs() < 1e-9
                && (wrap(q.theta - once.theta)).abs() < 1e-9
        );
        // Straight line and turning on the spot.
        let s = integrate(
            Pose {
                x: 0.0,
                y: 0.0,
                theta: PI / 2.0,
            },
            2.0,
            0.0,
            1.5,
        );
        assert!(s.x.abs() < 1e-12 && (s.y - 3.0).abs() < 1e-12);
        let spin = integrate(Pose::default(), 0.0, 1.0, 1.0);
        assert_eq!((spin.x, spin.y), (0.0, 0.0));
        assert!((spin.theta - 1.0).abs() < 1e-12);
    }

    #[test]
    fn wrapping_near_the_range_equals_the_remainder() {
        let slow = |a: f64| {
            let mut a = a % (2.0 * PI);
            if a <= -PI {
                a += 2.0 * PI;
            } else if a > PI {
                a -= 2.0 * PI;
            }
            a
        };
        let mut a = -9.5f64;
        while a < 9.5 {
            // Equal values (at exactly -2π the remainder gives -0, this +0).
            assert_eq!(wrap(a), slow(a), "{a}");
            for edge in [PI, -PI, 3.0 * PI, -3.0 * PI, 2.0 * PI, -2.0 * PI] {
                for e in [edge, edge.next_up(), edge.next_down()] {
                    assert_eq!(wrap(e), slow(e), "{e}");
                }
            }
            a += 0.000_37;
        }
    }

    #[test]
    fn acceleration_limits_and_wrapping() {
        assert_eq!(approach(0.0, 1.0, 0.25), 0.25);
        assert_eq!(approach(1.0, -1.0, 0.5), 0.5);
        assert_eq!(approach(0.9, 1.0, 0.5), 1.0);
        assert!((wrap(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap(-3.5 * PI) - 0.5 * PI).abs() < 1e-12);
    }
}
