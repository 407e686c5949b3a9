//! One track per beacon colour, in map coordinates: a constant-velocity Kalman filter
//! per target that fuses the camera sightings of every robot, each with its own
//! uncertainty (the camera's range and bearing noise and the observing robot's pose
//! covariance, carried through the measurement's Jacobians). A target unseen for
//! `lost_after` seconds is *lost*: its last position is kept and said to be stale.
//!
//! Pure: fed with sightings and sim time; nalgebra holds the state and covariance.

use crate::sensing::Sighting;
use muster_shared::types::{Track2d, MAX_TRACK_OBSERVERS};
use muster_world_model::kinematics::Pose;
use muster_world_model::Colour;
use nalgebra::{Matrix2, Matrix2x3, Matrix2x4, Matrix3, Matrix4, Vector2, Vector4};
use std::collections::BTreeMap;

/// How the tracker is tuned.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackerParams {
    /// White-acceleration process noise, m²/s³ (people start, stop and turn).
    pub accel_noise: f64,
    /// Camera bearing noise, rad (1 σ).
    pub bearing_sigma: f64,
    /// Camera range noise as a fraction of the range (1 σ).
    pub range_sigma: f64,
    /// A target unseen this long is lost, s.
    pub lost_after: f64,
    /// Sightings farther than this (squared Mahalanobis distance) from the prediction
    /// are taken as a new appearance and restart the track (χ², 2 dof, 99.9 %: 13.8).
    pub gate: f64,
    /// Speed beyond which the velocity estimate is clipped, m/s.
    pub max_speed: f64,
}

impl Default for TrackerParams {
    fn default() -> Self {
        TrackerParams {
            accel_noise: 0.5,
            bearing_sigma: 0.5_f64.to_radians() * 1.5,
            range_sigma: 0.05 * 1.5,
            lost_after: 5.0,
            gate: 13.8,
            max_speed: 3.0,
        }
    }
}

/// One target's filter.
#[derive(Clone, Debug)]
pub struct Track {
    /// State: x, y, vx, vy.
    pub state: Vector4<f64>,
    /// Its covariance.
    pub covariance: Matrix4<f64>,
    /// Sim time the state refers to.
    pub time: f64,
    /// Sim time of the last sighting.
    pub last_seen: f64,
    /// Robots that saw it, with the sim time of their last sighting.
    pub seen_by: BTreeMap<String, f64>,
    /// Sightings fused.
    pub sightings: u64,
}

/// The tracks of all colours.
#[derive(Clone, Debug, Default)]
pub struct MultiTracker {
    params: TrackerParams,
    tracks: BTreeMap<Colour, Track>,
}

impl MultiTracker {
    /// An empty tracker.
    pub fn new(params: TrackerParams) -> Self {
        MultiTracker {
            params,
            tracks: BTreeMap::new(),
        }
    }

    /// The track of `colour`, if it was ever seen.
    pub fn track(&self, colour: Colour) -> Option<&Track> {
        self.tracks.get(&colour)
    }

    /// Whether `colour` is tracked (seen within `lost_after`) at sim time `now`.
    pub fn is_tracked(&self, colour: Colour, now: f64) -> bool {
        self.tracks
            .get(&colour)
            .is_some_and(|t| now - t.last_seen <= self.params.lost_after)
    }

    /// Number of targets tracked at `now`.
    pub fn tracked(&self, now: f64) -> usize {
        self.tracks
            .values()
            .filter(|t| now - t.last_seen <= self.params.lost_after)
            .count()
    }

    /// The predicted position of `colour` at `now` (the last one if lost).
    pub fn predicted(&self, colour: Colour, now: f64) -> Option<(f64, f64)> {
        let t = self.tracks.get(&colour)?;
        if now - t.last_seen > self.params.lost_after {
            return Some((t.state[0], t.state[1]));
        }
        let dt = (now - t.time).max(0.0);
        Some((t.state[0] + t.state[2] * dt, t.state[1] + t.state[3] * dt))
    }

    /// Fuses one sighting by robot `robot` at sim time `time`, from its pose estimate
    /// `pose` with covariance `pose_cov` (x, y, theta).
    pub fn handle_sighting(
        &mut self,
        robot: &str,
        time: f64,
        pose: Pose,
        pose_cov: &Matrix3<f64>,
        s: &Sighting,
    ) {
        let phi = pose.theta + s.bearing;
        let (sn, cs) = phi.sin_cos();
        let z = Vector2::new(pose.x + s.range * cs, pose.y + s.range * sn);
        // Measurement noise: camera (range, bearing) and the observer's pose, first order.
        let sr = self.params.range_sigma * s.range.max(0.3);
        let sb = self.params.bearing_sigma;
        let jm = Matrix2::new(cs, -s.range * sn, sn, s.range * cs);
        let jp = Matrix2x3::new(1.0, 0.0, -s.range * sn, 0.0, 1.0, s.range * cs);
        let r = jm * Matrix2::new(sr * sr, 0.0, 0.0, sb * sb) * jm.transpose()
            + jp * pose_cov * jp.transpose();
        let p = &self.params;
        let lost_after = p.lost_after;
        let restart = |z: Vector2<f64>, r: Matrix2<f64>| {
            let mut cov = Matrix4::zeros();
            cov.fixed_view_mut::<2, 2>(0, 0).copy_from(&r);
            cov[(2, 2)] = 1.0;
            cov[(3, 3)] = 1.0;
            Track {
                state: Vector4::new(z[0], z[1], 0.0, 0.0),
                covariance: cov,
                time,
                last_seen: time,
                seen_by: BTreeMap::new(),
                sightings: 0,
            }
        };
        let track = self.tracks.entry(s.colour).or_insert_with(|| restart(z, r));
        if time - track.last_seen > lost_after {
            *track = restart(z, r);
        }
        predict(track, time, p.accel_noise);
        let h = Matrix2x4::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0);
        let innovation = z - h * track.state;
        let s_cov = h * track.covariance * h.transpose() + r;
        let Some(s_inv) = s_cov.try_inverse() else {
            return;
        };
        let d2 = (innovation.transpose() * s_inv * innovation)[0];
        if track.sightings > 0 && d2 > p.gate {
            // Too far from where it should be: the target reappeared elsewhere (or was
            // mistaken); start again from this sighting.
            *track = restart(z, r);
        } else if track.sightings > 0 {
            let k = track.covariance * h.transpose() * s_inv;
            track.state += k * innovation;
            let i_kh = Matrix4::identity() - k * h;
            // Joseph form: stays symmetric and positive.
            track.covariance = i_kh * track.covariance * i_kh.transpose() + k * r * k.transpose();
            let speed = track.state[2].hypot(track.state[3]);
            if speed > p.max_speed {
                track.state[2] *= p.max_speed / speed;
                track.state[3] *= p.max_speed / speed;
            }
        }
        track.last_seen = time;
        track.sightings += 1;
        track.seen_by.insert(robot.to_string(), time);
    }

    /// The state of `colour` at `now` as a service payload; robots that saw it within
    /// `window` seconds are named. `None` if it was never seen.
    pub fn payload(&self, colour: Colour, now: f64, window: f64) -> Option<Track2d> {
        let t = self.tracks.get(&colour)?;
        let age = (now - t.last_seen).max(0.0);
        let lost = age > self.params.lost_after;
        let mut shown = t.clone();
        if !lost {
            predict(&mut shown, now, self.params.accel_noise);
        }
        let pos = shown.covariance.fixed_view::<2, 2>(0, 0).into_owned();
        let sigma = pos.symmetric_eigenvalues().max().max(0.0).sqrt();
        Some(Track2d {
            x: shown.state[0],
            y: shown.state[1],
            vx: if lost { 0.0 } else { shown.state[2] },
            vy: if lost { 0.0 } else { shown.state[3] },
            sigma,
            age,
            seen_by: t
                .seen_by
                .iter()
                .filter(|(_, at)| now - **at <= window)
                .map(|(r, _)| r.clone())
                .take(MAX_TRACK_OBSERVERS)
                .collect(),
            lost,
        })
    }
}

/// Moves a track's state to `time` (constant velocity, white-acceleration noise).
fn predict(t: &mut Track, time: f64, q: f64) {
    let dt = time - t.time;
    if dt <= 0.0 {
        return;
    }
    let f = Matrix4::new(
        1.0, 0.0, dt, 0.0, //
        0.0, 1.0, 0.0, dt, //
        0.0, 0.0, 1.0, 0.0, //
        0.0, 0.0, 0.0, 1.0,
    );
    let (d2, d3) = (dt * dt / 2.0, dt * dt * dt / 3.0);
    let qm = Matrix4::new(
        d3, 0.0, d2, 0.0, //
        0.0, d3, 0.0, d2, //
        d2, 0.0, dt, 0.0, //
        0.0, d2, 0.0, dt,
    ) * q;
    t.state = f * t.state;
    t.covariance = f * t.covariance * f.transpose() + qm;
    t.time = time;
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    fn sighting_of(
        robot: Pose,
        target: (f64, f64),
        colour: Colour,
        rng: &mut rand_pcg::Pcg64,
        noisy: bool,
    ) -> Sighting {
        let (dx, dy) = (target.0 - robot.x, target.1 - robot.y);
        let mut bearing = dy.atan2(dx) - robot.theta;
        let mut range = dx.hypot(dy);
        if noisy {
            bearing += Normal::new(0.0, 0.5_f64.to_radians()).unwrap().sample(rng);
            range *= 1.0 + Normal::new(0.0, 0.05).unwrap().sample(rng);
        }
        Sighting {
            colour,
            bearing,
            range,
        }
    }

    fn still_cov() -> Matrix3<f64> {
        Matrix3::from_diagonal(&nalgebra::Vector3::new(
            0.03f64.powi(2),
            0.03f64.powi(2),
            0.01f64.powi(2),
        ))
    }

    #[test]
    fn converges_on_a_target_moving_along_a_known_path() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut tr = MultiTracker::new(TrackerParams::default());
        let robot = Pose {
            x: 0.0,
            y: 0.0,
            theta: 0.0,
        };
        let mut errors = Vec::new();
        for k in 0..200 {
            let t = k as f64 * 0.1;
            let target = (2.0 + 0.3 * t, 2.0);
            let s = sighting_of(robot, target, Colour::Red, &mut rng, true);
            tr.handle_sighting("T1", t, robot, &still_cov(), &s);
            if t > 5.0 {
                let p = tr.payload(Colour::Red, t, 1.0).unwrap();
                errors.push((p.x - target.0).hypot(p.y - target.1));
            }
        }
        errors.sort_by(f64::total_cmp);
        let p50 = errors[errors.len() / 2];
        let p95 = errors[errors.len() * 95 / 100];
        assert!(p50 < 0.25, "p50 error {p50}");
        assert!(p95 < 0.6, "p95 error {p95}");
        let p = tr.payload(Colour::Red, 19.9, 1.0).unwrap();
        assert!((p.vx - 0.3).abs() < 0.25, "vx {}", p.vx);
        assert!(p.vy.abs() < 0.25, "vy {}", p.vy);
        assert_eq!(p.seen_by, vec!["T1".to_string()]);
        assert!(!p.lost);
    }

    #[test]
    fn two_robots_sightings_fuse_into_a_tighter_estimate() {
        let target = (5.0, 5.0);
        let a = Pose {
            x: 0.0,
            y: 5.0,
            theta: 0.0,
        };
        let b = Pose {
            x: 5.0,
            y: 0.0,
            theta: std::f64::consts::FRAC_PI_2,
        };
        let run = |robots: &[(&str, Pose)]| {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
            let mut tr = MultiTracker::new(TrackerParams::default());
            for k in 0..100 {
                let t = k as f64 * 0.1;
                for (name, pose) in robots {
                    let s = sighting_of(*pose, target, Colour::Green, &mut rng, true);
                    tr.handle_sighting(name, t, *pose, &still_cov(), &s);
                }
            }
            tr.payload(Colour::Green, 9.9, 1.0).unwrap()
        };
        let one = run(&[("T1", a)]);
        let two = run(&[("T1", a), ("T2", b)]);
        assert!(
            two.sigma < one.sigma * 0.8,
            "fused sigma {} vs {}",
            two.sigma,
            one.sigma
        );
        assert_eq!(two.seen_by, vec!["T1".to_string(), "T2".to_string()]);
        assert!((two.x - 5.0).hypot(two.y - 5.0) < 0.3);
    }

    #[test]
    fn lost_after_the_timeout_and_found_again_elsewhere() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let mut tr = MultiTracker::new(TrackerParams::default());
        let robot = Pose::default();
        for k in 0..20 {
            let s = sighting_of(robot, (4.0, 0.0), Colour::Blue, &mut rng, false);
            tr.handle_sighting("T1", k as f64 * 0.1, robot, &still_cov(), &s);
        }
        assert!(tr.is_tracked(Colour::Blue, 6.0));
        assert!(!tr.is_tracked(Colour::Blue, 7.1));
        let p = tr.payload(Colour::Blue, 7.1, 1.0).unwrap();
        assert!(p.lost && p.seen_by.is_empty() && p.age > 5.0);
        assert!((p.x - 4.0).abs() < 0.1, "last known position kept");
        // Seen again far away: a fresh track there, not a jump through the gate.
        let s = sighting_of(robot, (0.0, 6.0), Colour::Blue, &mut rng, false);
        tr.handle_sighting("T2", 8.0, robot, &still_cov(), &s);
        let p = tr.payload(Colour::Blue, 8.0, 1.0).unwrap();
        assert!(!p.lost);
        assert!((p.y - 6.0).abs() < 0.1 && p.x.abs() < 0.1);
        assert_eq!(p.seen_by, vec!["T2".to_string()]);
    }

    #[test]
    fn colours_are_kept_apart() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        let mut tr = MultiTracker::new(TrackerParams::default());
        let robot = Pose::default();
        for k in 0..30 {
            let t = k as f64 * 0.1;
            let r = sighting_of(robot, (3.0, 1.0), Colour::Red, &mut rng, false);
            let g = sighting_of(robot, (3.0, -1.0), Colour::Green, &mut rng, false);
            tr.handle_sighting("T1", t, robot, &still_cov(), &r);
            tr.handle_sighting("T1", t, robot, &still_cov(), &g);
        }
        let r = tr.payload(Colour::Red, 3.0, 1.0).unwrap();
        let g = tr.payload(Colour::Green, 3.0, 1.0).unwrap();
        assert!((r.y - 1.0).abs() < 0.1 && (g.y + 1.0).abs() < 0.1);
        assert!(tr.payload(Colour::Blue, 3.0, 1.0).is_none());
        assert_eq!(tr.tracked(3.0), 2);
    }
}
