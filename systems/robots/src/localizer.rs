//! Where a robot is, from what it senses: Monte Carlo localization in the manner of
//! AMCL. Odometry moves the particles (the odometry motion model of Thrun, Burgard and
//! Fox, *Probabilistic Robotics* §5.4); each laser scan weighs them against a likelihood
//! field of the known map (§6.4); low-variance resampling keeps them where the robot is.
//!
//! Pure: fed with odometry and scans, no clock of its own; its randomness is seeded.

use crate::sensing::{LaserScan, LikelihoodField};
use muster_world_model::kinematics::{wrap, Pose};
use nalgebra::{Matrix3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_pcg::Pcg64;
use std::sync::Arc;

/// How the filter is tuned. Defaults suit the simulator's Pioneer with its SICK-like laser.
#[derive(Clone, Debug, PartialEq)]
pub struct LocalizerParams {
    /// Particles.
    pub particles: usize,
    /// Spread of the first particles around the start pose: position, m.
    pub init_sigma_xy: f64,
    /// Spread of the first particles around the start pose: heading, rad.
    pub init_sigma_theta: f64,
    /// Odometry motion noise α1..α4 (rotation from rotation, rotation from translation,
    /// translation from translation, translation from rotation).
    pub alpha: [f64; 4],
    /// Beams used per scan (spread evenly over the scan).
    pub beams: usize,
    /// Standard deviation of a beam end's distance to the nearest wall, m.
    pub sigma_hit: f64,
    /// Weight of the "hit" part of the beam model; the rest is uniform noise (people,
    /// other robots, anything not on the map).
    pub z_hit: f64,
    /// A scan is weighed only after the robot moved this far (m) or turned this much
    /// (rad) since the last weighing, or after `stationary_update` seconds.
    pub update_min: (f64, f64),
    /// Weigh a scan at least this often, s, even standing still (it lets a stationary
    /// robot converge from its start spread).
    pub stationary_update: f64,
    /// Beam-model exponent (< 1 tempers the product over beams, which are not
    /// independent; AMCL's "likelihood field prob" does the same with its own exponent).
    pub temper: f64,
}

impl Default for LocalizerParams {
    fn default() -> Self {
        LocalizerParams {
            particles: 400,
            init_sigma_xy: 0.15,
            init_sigma_theta: 0.05,
            alpha: [0.08, 0.02, 0.05, 0.02],
            beams: 60,
            sigma_hit: 0.08,
            z_hit: 0.85,
            update_min: (0.05, 0.03),
            stationary_update: 1.0,
            temper: 0.3,
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Particle {
    pose: Pose,
    weight: f64,
}

/// One robot's localization filter.
pub struct Localizer {
    params: LocalizerParams,
    field: Arc<LikelihoodField>,
    particles: Vec<Particle>,
    rng: Pcg64,
    last_odom: Option<Pose>,
    moved_since_update: (f64, f64),
    last_update: f64,
    estimate: Pose,
    covariance: Matrix3<f64>,
    updates: u64,
}

fn gaussian(rng: &mut Pcg64, sd: f64) -> f64 {
    if sd > 0.0 && sd.is_finite() {
        Normal::new(0.0, sd).map_or(0.0, |n| n.sample(rng))
    } else {
        0.0
    }
}

impl Localizer {
    /// A filter on `field` whose particles start around `start` (the scenario's start
    /// pose, as AMCL's initial pose).
    pub fn new(
        field: Arc<LikelihoodField>,
        start: Pose,
        params: LocalizerParams,
        seed: u64,
    ) -> Self {
        let mut rng = Pcg64::seed_from_u64(seed);
        let n = params.particles.max(1);
        let particles = (0..n)
            .map(|_| Particle {
                pose: Pose {
                    x: start.x + gaussian(&mut rng, params.init_sigma_xy),
                    y: start.y + gaussian(&mut rng, params.init_sigma_xy),
                    theta: wrap(start.theta + gaussian(&mut rng, params.init_sigma_theta)),
                },
                weight: 1.0 / n as f64,
            })
            .collect();
        let mut l = Localizer {
            params,
            field,
            particles,
            rng,
            last_odom: None,
            moved_since_update: (0.0, 0.0),
            last_update: f64::NEG_INFINITY,
            estimate: start,
            covariance: Matrix3::zeros(),
            updates: 0,
        };
        l.summarise();
        l
    }

    /// The pose estimate: the particles' weighted mean.
    pub fn estimate(&self) -> Pose {
        self.estimate
    }

    /// The estimate's covariance over (x, y, theta).
    pub fn covariance(&self) -> Matrix3<f64> {
        self.covariance
    }

    /// Scans weighed so far.
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// Moves every particle by the odometry change since the last call (the first call
    /// only remembers where odometry stands).
    pub fn handle_odometry(&mut self, odom: Pose) {
        let Some(prev) = self.last_odom.replace(odom) else {
            return;
        };
        let (dx, dy) = (odom.x - prev.x, odom.y - prev.y);
        let trans = dx.hypot(dy);
        let turn = wrap(odom.theta - prev.theta);
        if trans < 1e-9 && turn.abs() < 1e-9 {
            return;
        }
        // Odometry motion model: rotate, translate, rotate; backwards motion keeps its sign.
        let mut rot1 = if trans < 0.01 {
            0.0
        } else {
            wrap(dy.atan2(dx) - prev.theta)
        };
        let mut trans_signed = trans;
        if rot1.abs() > std::f64::consts::FRAC_PI_2 {
            rot1 = wrap(rot1 + std::f64::consts::PI);
            trans_signed = -trans;
        }
        let rot2 = wrap(turn - rot1);
        let [a1, a2, a3, a4] = self.params.alpha;
        let sd_rot1 = a1 * rot1.abs() + a2 * trans;
        let sd_trans = a3 * trans + a4 * (rot1.abs() + rot2.abs());
        let sd_rot2 = a1 * rot2.abs() + a2 * trans;
        for p in &mut self.particles {
            let r1 = rot1 + gaussian(&mut self.rng, sd_rot1);
            let t = trans_signed + gaussian(&mut self.rng, sd_trans);
            let r2 = rot2 + gaussian(&mut self.rng, sd_rot2);
            let th = p.pose.theta + r1;
            p.pose = Pose {
                x: p.pose.x + t * th.cos(),
                y: p.pose.y + t * th.sin(),
                theta: wrap(th + r2),
            };
        }
        self.moved_since_update.0 += trans;
        self.moved_since_update.1 += turn.abs();
        self.summarise();
    }

    /// Weighs the particles against a laser scan taken at sim time `now` (when the robot
    /// moved enough since the last weighing, or it is due anyway), and resamples.
    /// Returns whether the scan was used.
    pub fn handle_scan(&mut self, now: f64, scan: &LaserScan<'_>) -> bool {
        let (dmin, amin) = self.params.update_min;
        let moved = self.moved_since_update.0 >= dmin || self.moved_since_update.1 >= amin;
        let due = now - self.last_update >= self.params.stationary_update;
        if !(moved || due) || scan.ranges.is_empty() {
            return false;
        }
        self.moved_since_update = (0.0, 0.0);
        self.last_update = now;
        let n = scan.ranges.len();
        let step = (n / self.params.beams.max(1)).max(1);
        let beams: Vec<(f64, f64)> = (0..n)
            .step_by(step)
            .filter_map(|k| {
                let r = f64::from(scan.ranges[k]);
                // Max-range readings say nothing about where walls are (AMCL skips them).
                (r.is_finite() && r > 0.05 && r < scan.max_range - 0.05).then(|| (scan.angle(k), r))
            })
            .collect();
        if beams.is_empty() {
            return false;
        }
        let sigma2 = 2.0 * self.params.sigma_hit * self.params.sigma_hit;
        let z_hit = self.params.z_hit;
        let z_rand = (1.0 - z_hit) / scan.max_range;
        let field = &self.field;
        let mut best = f64::NEG_INFINITY;
        let logs: Vec<f64> = self
            .particles
            .iter()
            .map(|p| {
                let (s, c) = p.pose.theta.sin_cos();
                let mut log = 0.0;
                for &(a, r) in &beams {
                    let (sa, ca) = a.sin_cos();
                    // Beam end in the map: rotate (cos a, sin a) by the heading.
                    let ex = p.pose.x + r * (c * ca - s * sa);
                    let ey = p.pose.y + r * (s * ca + c * sa);
                    let d = field.distance(ex, ey);
                    log += (z_hit * (-d * d / sigma2).exp() + z_rand).ln();
                }
                let log = log * self.params.temper;
                best = best.max(log);
                log
            })
            .collect();
        let mut total = 0.0;
        for (p, log) in self.particles.iter_mut().zip(&logs) {
            p.weight *= (log - best).exp();
            total += p.weight;
        }
        if !(total > 0.0 && total.is_finite()) {
            let w = 1.0 / self.particles.len() as f64;
            self.particles.iter_mut().for_each(|p| p.weight = w);
        } else {
            self.particles.iter_mut().for_each(|p| p.weight /= total);
        }
        let n_eff = 1.0
            / self
                .particles
                .iter()
                .map(|p| p.weight * p.weight)
                .sum::<f64>();
        if n_eff < self.particles.len() as f64 / 2.0 {
            self.resample();
        }
        self.updates += 1;
        self.summarise();
        true
    }

    /// Low-variance (systematic) resampling, with a little jitter so that a robot
    /// standing still does not collapse onto one particle.
    fn resample(&mut self) {
        let n = self.particles.len();
        let step = 1.0 / n as f64;
        let mut u = self.rng.random::<f64>() * step;
        let mut c = self.particles[0].weight;
        let mut i = 0;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            while u > c && i + 1 < n {
                i += 1;
                c += self.particles[i].weight;
            }
            let mut p = self.particles[i];
            p.pose.x += gaussian(&mut self.rng, 0.005);
            p.pose.y += gaussian(&mut self.rng, 0.005);
            p.pose.theta = wrap(p.pose.theta + gaussian(&mut self.rng, 0.002));
            p.weight = step;
            out.push(p);
            u += step;
        }
        self.particles = out;
    }

    fn summarise(&mut self) {
        let (mut x, mut y, mut s, mut c, mut w) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for p in &self.particles {
            x += p.weight * p.pose.x;
            y += p.weight * p.pose.y;
            s += p.weight * p.pose.theta.sin();
            c += p.weight * p.pose.theta.cos();
            w += p.weight;
        }
        if w <= 0.0 {
            return;
        }
        let mean = Pose {
            x: x / w,
            y: y / w,
            theta: s.atan2(c),
        };
        let mut cov = Matrix3::zeros();
        for p in &self.particles {
            let d = Vector3::new(
                p.pose.x - mean.x,
                p.pose.y - mean.y,
                wrap(p.pose.theta - mean.theta),
            );
            cov += d * d.transpose() * (p.weight / w);
        }
        self.estimate = mean;
        self.covariance = cov;
    }
}
