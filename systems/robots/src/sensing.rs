//! What a robot system takes from its robot: one sensors sample in plain values the cores
//! read (whatever port it came through), and the map turned into the forms the cores
//! use (a likelihood field for localization).

use muster_world_model::kinematics::Pose;
use muster_world_model::map::OccupancyMap;
use muster_world_model::Colour;

/// A laser scan: ranges at evenly spread bearings relative to the robot's heading.
#[derive(Clone, Copy, Debug)]
pub struct LaserScan<'a> {
    /// Ranges, m; `max_range` where nothing was hit.
    pub ranges: &'a [f32],
    /// Bearing of the first beam, rad (relative to the heading).
    pub first: f64,
    /// Angle between beams, rad.
    pub step: f64,
    /// Range of the scanner, m.
    pub max_range: f64,
}

impl LaserScan<'_> {
    /// Bearing of beam `k`, rad, relative to the heading.
    pub fn angle(&self, k: usize) -> f64 {
        self.first + self.step * k as f64
    }
}

/// One beacon the camera saw: colour, bearing relative to the robot's heading, range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sighting {
    /// Beacon colour.
    pub colour: Colour,
    /// Bearing relative to the robot's heading, rad.
    pub bearing: f64,
    /// Range, m.
    pub range: f64,
}

/// One sensors sample of one robot, copied out of shared memory.
#[derive(Clone, Debug, Default)]
pub struct SensorSample {
    /// Sim time of the sample, s.
    pub time: f64,
    /// Odometry (the wheel encoders' belief).
    pub odom: Pose,
    /// Ground truth, for experiments only (`--ground-truth`), never used otherwise.
    pub truth: Pose,
    /// Sim time of the laser scan in `laser`.
    pub laser_time: f64,
    /// Laser ranges.
    pub laser: Vec<f32>,
    /// Sim time of the sonar ring.
    pub sonar_time: f64,
    /// Sonar ranges, one per transducer.
    pub sonar: Vec<f32>,
    /// Sim time of the camera frame.
    pub camera_time: f64,
    /// Camera pan, rad (relative to the heading).
    pub pan: f64,
    /// Beacons seen in the camera frame.
    pub sightings: Vec<Sighting>,
    /// Whether the robot's last move was cut short by contact.
    pub bumped: bool,
}

/// The sensor geometry of one robot: where its laser beams and sonar transducers point,
/// what its camera sees.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SensorGeometry {
    /// Laser: first bearing, step, range (if fitted).
    pub laser: Option<(f64, f64, f64)>,
    /// Sonar bearings, rad, and range (if fitted).
    pub sonar: Option<(Vec<f64>, f64)>,
    /// Camera: field of view at zoom 1 (rad), range at zoom 1 (m), pan limit (rad).
    pub camera: Option<(f64, f64, f64)>,
}

impl SensorGeometry {
    /// The scan in `sample` with this geometry (`None` without a laser).
    pub fn scan<'a>(&self, sample: &'a SensorSample) -> Option<LaserScan<'a>> {
        let (first, step, max_range) = self.laser?;
        Some(LaserScan {
            ranges: &sample.laser,
            first,
            step,
            max_range,
        })
    }

    /// Obstacle points seen by laser and sonar in the robot's frame (x ahead, y left),
    /// up to `within` metres.
    pub fn obstacle_points(&self, sample: &SensorSample, within: f64) -> Vec<(f64, f64)> {
        let mut pts = Vec::new();
        if let Some(scan) = self.scan(sample) {
            for (k, &r) in scan.ranges.iter().enumerate() {
                let r = f64::from(r);
                if r < scan.max_range - 0.02 && r <= within {
                    let a = scan.angle(k);
                    pts.push((r * a.cos(), r * a.sin()));
                }
            }
        }
        if let Some((bearings, range)) = &self.sonar {
            for (b, &r) in bearings.iter().zip(&sample.sonar) {
                let r = f64::from(r);
                if r < range - 0.02 && r <= within {
                    pts.push((r * b.cos(), r * b.sin()));
                }
            }
        }
        pts
    }
}

/// Distance from every point of the map to the nearest wall, capped, on the map's grid:
/// the likelihood field a scan is weighed against.
pub struct LikelihoodField {
    width: usize,
    height: usize,
    resolution: f64,
    origin: (f64, f64),
    cap: f64,
    distance: Vec<f32>,
}

impl LikelihoodField {
    /// The field of `map`, distances capped at `cap` metres (beyond it a beam end is as
    /// wrong as it gets).
    pub fn new(map: &OccupancyMap, cap: f64) -> Self {
        let (width, height) = (map.width(), map.height());
        let resolution = map.resolution();
        let origin = map.origin();
        let mut distance = Vec::with_capacity(width * height);
        for j in 0..height {
            for i in 0..width {
                let x = origin.0 + (i as f64 + 0.5) * resolution;
                let y = origin.1 + (j as f64 + 0.5) * resolution;
                let d = if map.occupied(i as i64, j as i64) {
                    0.0
                } else {
                    map.clearance(x, y, cap)
                };
                distance.push(d as f32);
            }
        }
        LikelihoodField {
            width,
            height,
            resolution,
            origin,
            cap,
            distance,
        }
    }

    /// Distance from (x, y) to the nearest wall, capped; the cap outside the map.
    pub fn distance(&self, x: f64, y: f64) -> f64 {
        let i = ((x - self.origin.0) / self.resolution).floor();
        let j = ((y - self.origin.1) / self.resolution).floor();
        if i < 0.0 || j < 0.0 || i >= self.width as f64 || j >= self.height as f64 {
            return self.cap;
        }
        f64::from(self.distance[j as usize * self.width + i as usize])
    }
}
