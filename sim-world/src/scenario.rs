//! Scenario files (TOML): the map, robots with their sensors and start poses, people,
//! places, rates and the seed. Every field has a default; the built-in scenario is the
//! paper's: three tracking robots, one delivery robot, three people with beacons.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

pub use muster_world_model::Colour;

/// Differential-drive parameters; defaults are Pioneer-2-DX-like.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct DriveParams {
    /// Body radius, m.
    pub radius: f64,
    /// Top speed, m/s.
    pub max_speed: f64,
    /// Top turn rate, rad/s.
    pub max_turn: f64,
    /// Linear acceleration limit, m/s².
    pub max_accel: f64,
    /// Angular acceleration limit, rad/s².
    pub max_turn_accel: f64,
    /// A robot whose controller sends nothing for this long stops, s.
    pub command_timeout: f64,
    /// Odometry noise: standard deviation as a fraction of the distance driven.
    pub odom_noise_linear: f64,
    /// Odometry noise: standard deviation as a fraction of the angle turned.
    pub odom_noise_angular: f64,
}

impl Default for DriveParams {
    fn default() -> Self {
        DriveParams {
            radius: 0.25,
            max_speed: 1.2,
            max_turn: 2.6,
            max_accel: 1.0,
            max_turn_accel: 3.0,
            command_timeout: 0.5,
            odom_noise_linear: 0.02,
            odom_noise_angular: 0.05,
        }
    }
}

/// A SICK-like laser.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LaserParams {
    /// Beams, spread evenly over the field of view.
    pub beams: usize,
    /// Field of view, degrees, centred on the heading.
    pub fov_deg: f64,
    /// Range, m.
    pub range: f64,
    /// Scans per second.
    pub rate: f64,
    /// Range noise standard deviation, m.
    pub noise: f64,
}

impl Default for LaserParams {
    fn default() -> Self {
        LaserParams {
            beams: 181,
            fov_deg: 180.0,
            range: 8.0,
            rate: 10.0,
            noise: 0.01,
        }
    }
}

/// A ring of sonars.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SonarParams {
    /// Transducer bearings, degrees (default: the Pioneer's 16-sonar ring).
    pub bearings_deg: Vec<f64>,
    /// Beam cone, degrees (full width).
    pub cone_deg: f64,
    /// Range, m.
    pub range: f64,
    /// Rays sampled across each cone.
    pub rays_per_cone: usize,
    /// Rings per second.
    pub rate: f64,
    /// Range noise standard deviation, m.
    pub noise: f64,
}

impl Default for SonarParams {
    fn default() -> Self {
        SonarParams {
            bearings_deg: vec![
                90.0, 50.0, 30.0, 10.0, -10.0, -30.0, -50.0, -90.0, -90.0, -130.0, -150.0, -170.0,
                170.0, 150.0, 130.0, 90.0,
            ],
            cone_deg: 15.0,
            range: 5.0,
            rays_per_cone: 5,
            rate: 10.0,
            noise: 0.02,
        }
    }
}

/// A pan-tilt-zoom camera with a blob tracker that detects coloured beacons.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CameraParams {
    /// Horizontal field of view at zoom 1, degrees.
    pub fov_deg: f64,
    /// Detection range at zoom 1, m (grows with zoom).
    pub range: f64,
    /// Pan limits, degrees either side.
    pub pan_limit_deg: f64,
    /// Pan speed, degrees per second.
    pub pan_speed_deg: f64,
    /// Largest zoom.
    pub max_zoom: f64,
    /// Frames per second.
    pub rate: f64,
    /// Bearing noise standard deviation, degrees.
    pub bearing_noise_deg: f64,
    /// Range noise standard deviation as a fraction of the range.
    pub range_noise: f64,
}

impl Default for CameraParams {
    fn default() -> Self {
        CameraParams {
            fov_deg: 60.0,
            range: 8.0,
            pan_limit_deg: 100.0,
            pan_speed_deg: 100.0,
            max_zoom: 4.0,
            rate: 10.0,
            bearing_noise_deg: 0.5,
            range_noise: 0.05,
        }
    }
}

/// A robot in a scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RobotSpec {
    /// Name, unique.
    pub name: String,
    /// Start pose: x, y (m), heading (degrees).
    pub pose: [f64; 3],
    /// Drive parameters.
    #[serde(default)]
    pub drive: DriveParams,
    /// Laser, if fitted.
    #[serde(default)]
    pub laser: Option<LaserParams>,
    /// Sonar ring, if fitted.
    #[serde(default)]
    pub sonar: Option<SonarParams>,
    /// Camera, if fitted.
    #[serde(default)]
    pub camera: Option<CameraParams>,
    /// A beacon the robot carries, if any.
    #[serde(default)]
    pub beacon: Option<Colour>,
    /// Drive by the built-in wander controller instead of waiting for commands.
    #[serde(default)]
    pub wander: bool,
    /// A named place that is this robot's home (e.g. the delivery robot's office).
    #[serde(default)]
    pub home: Option<String>,
    /// Never drives (a stationary tracker): a fixture, which the other robots' maps
    /// show as they show walls. The simulator ignores its velocity commands.
    #[serde(default)]
    pub fixed: bool,
}

/// A person wandering between places with a coloured beacon.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PersonSpec {
    /// Name.
    pub name: String,
    /// Beacon colour.
    pub beacon: Colour,
    /// Start position, m.
    pub start: [f64; 2],
    /// Walking speed, m/s.
    #[serde(default = "default_walk")]
    pub speed: f64,
}

fn default_walk() -> f64 {
    0.7
}

/// A named place people walk to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Place {
    /// Name.
    pub name: String,
    /// Position, m.
    pub at: [f64; 2],
}

/// A whole scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scenario {
    /// A map_server YAML file; the built-in office if absent.
    #[serde(default)]
    pub map: Option<PathBuf>,
    /// Seed of every random draw (noise, people, wandering).
    #[serde(default)]
    pub seed: u64,
    /// Kinematics step, s (default 0.01: 100 Hz).
    #[serde(default = "default_dt")]
    pub dt: f64,
    /// Robots.
    #[serde(default)]
    pub robots: Vec<RobotSpec>,
    /// People.
    #[serde(default)]
    pub people: Vec<PersonSpec>,
    /// Places people walk between (default: the office's rooms and corridors).
    #[serde(default)]
    pub places: Vec<Place>,
}

fn default_dt() -> f64 {
    0.01
}

/// `x > 0`, false for NaN: every rate and range must pass this.
fn positive(x: f64) -> bool {
    x > 0.0
}

/// Why a scenario is unusable.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// The file could not be read.
    #[error("cannot read {0}: {1}")]
    Io(String, std::io::Error),
    /// The TOML does not parse into a scenario.
    #[error("{0}: {1}")]
    Toml(String, String),
    /// A value is out of range; the text says which.
    #[error("scenario: {0}")]
    Invalid(String),
}

impl Scenario {
    /// Reads and checks a TOML scenario file.
    pub fn load(path: &std::path::Path) -> Result<Self, ScenarioError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ScenarioError::Io(p.clone(), e))?;
        let mut s: Scenario =
            toml::from_str(&text).map_err(|e| ScenarioError::Toml(p, e.to_string()))?;
        if let Some(m) = &s.map {
            if m.is_relative() {
                s.map = Some(path.parent().unwrap_or(std::path::Path::new(".")).join(m));
            }
        }
        s.validate()?;
        Ok(s)
    }

    /// Checks names, rates and sizes.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let bad = |m: String| Err(ScenarioError::Invalid(m));
        if !(self.dt > 0.0 && self.dt <= 0.1) {
            return bad(format!("dt {} must be in (0, 0.1] s", self.dt));
        }
        let mut names = std::collections::BTreeSet::new();
        for r in &self.robots {
            if r.name.is_empty() || r.name.len() > 31 || !names.insert(r.name.as_str()) {
                return bad(format!(
                    "robot name {:?} empty, too long or repeated",
                    r.name
                ));
            }
            if r.fixed && r.wander {
                return bad(format!("robot {}: a fixed robot cannot wander", r.name));
            }
            let d = &r.drive;
            if !(d.radius > 0.0
                && d.max_speed >= 0.0
                && d.max_turn >= 0.0
                && d.max_accel > 0.0
                && d.max_turn_accel > 0.0)
            {
                return bad(format!(
                    "robot {}: drive parameters must be positive",
                    r.name
                ));
            }
            if let Some(l) = &r.laser {
                if l.beams == 0 || l.beams > 1081 || !positive(l.rate) || !positive(l.range) {
                    return bad(format!(
                        "robot {}: laser needs 1..=1081 beams, rate > 0, range > 0",
                        r.name
                    ));
                }
            }
            if let Some(s) = &r.sonar {
                if s.bearings_deg.len() > 32 || s.rays_per_cone == 0 || !positive(s.rate) {
                    return bad(format!(
                        "robot {}: at most 32 sonars, ≥ 1 ray per cone, rate > 0",
                        r.name
                    ));
                }
            }
            if let Some(c) = &r.camera {
                if !(c.rate > 0.0 && c.max_zoom >= 1.0 && c.fov_deg > 0.0) {
                    return bad(format!(
                        "robot {}: camera rate > 0, max_zoom ≥ 1, fov > 0",
                        r.name
                    ));
                }
            }
        }
        for p in &self.people {
            if !(p.speed > 0.0 && p.speed < 5.0) {
                return bad(format!("person {}: speed must be in (0, 5) m/s", p.name));
            }
        }
        Ok(())
    }

    /// Adds a crowd of `n` people who carry no beacon a tracking service offers (yellow,
    /// magenta and cyan): they start in every other office of the scenario's places (the
    /// corridor places are where robots stand) and walk from place to place like
    /// everyone, across the robots' ways, at 0.5-0.8 m/s. Fails if they do not fit the
    /// offices.
    pub fn add_crowd(&mut self, n: usize) -> Result<(), ScenarioError> {
        let offices: Vec<[f64; 2]> = self
            .places
            .iter()
            .filter(|pl| pl.name.starts_with("office-"))
            .map(|pl| pl.at)
            .collect();
        if n > offices.len() {
            return Err(ScenarioError::Invalid(format!(
                "a crowd of at most {} fits the offices",
                offices.len()
            )));
        }
        for k in 0..n {
            // Every other office first, so that neighbours do not start side by side.
            let at = offices[(2 * k) % offices.len() + (2 * k) / offices.len()];
            self.people.push(PersonSpec {
                name: format!("walker-{k}"),
                beacon: [Colour::Yellow, Colour::Magenta, Colour::Cyan][k % 3],
                start: at,
                speed: 0.5 + 0.05 * (k % 7) as f64,
            });
        }
        Ok(())
    }

    /// The paper's scenario on the built-in office: tracking robots T1 and T2 stationary
    /// in the corridors, T3 able to move, delivery robot D1 with a home office, and three
    /// people with red, green and blue beacons.
    pub fn paper() -> Self {
        let tracker = |name: &str, pose: [f64; 3]| RobotSpec {
            name: name.into(),
            pose,
            drive: DriveParams::default(),
            laser: Some(LaserParams::default()),
            sonar: Some(SonarParams::default()),
            camera: Some(CameraParams::default()),
            beacon: None,
            wander: false,
            home: None,
            fixed: false,
        };
        let fixed = |name: &str, pose: [f64; 3]| RobotSpec {
            fixed: true,
            ..tracker(name, pose)
        };
        let mut d1 = tracker("D1", [30.0, 3.0, 180.0]);
        d1.camera = None;
        d1.home = Some("office-south-6".into());
        Scenario {
            map: None,
            seed: 1,
            dt: 0.01,
            robots: vec![
                fixed("T1", [3.0, 3.0, 0.0]),
                fixed("T2", [37.0, 17.0, 180.0]),
                // Against the middle corridor's south wall, so robots can pass it.
                tracker("T3", [20.0, 9.4, 0.0]),
                d1,
            ],
            people: vec![
                PersonSpec {
                    name: "alice".into(),
                    beacon: Colour::Red,
                    start: [10.0, 3.0],
                    speed: 0.7,
                },
                PersonSpec {
                    name: "bob".into(),
                    beacon: Colour::Green,
                    start: [20.0, 17.0],
                    speed: 0.6,
                },
                PersonSpec {
                    name: "carol".into(),
                    beacon: Colour::Blue,
                    start: [3.0, 10.0],
                    speed: 0.8,
                },
            ],
            places: office_places(),
        }
    }
}

/// Places of the built-in office: corridor points and the middle of every office.
pub fn office_places() -> Vec<Place> {
    let mut p = vec![
        Place {
            name: "corridor-sw".into(),
            at: [3.0, 3.0],
        },
        Place {
            name: "corridor-se".into(),
            at: [37.0, 3.0],
        },
        Place {
            name: "corridor-nw".into(),
            at: [3.0, 17.0],
        },
        Place {
            name: "corridor-ne".into(),
            at: [37.0, 17.0],
        },
        Place {
            name: "corridor-mid".into(),
            at: [20.0, 10.0],
        },
        Place {
            name: "lab".into(),
            at: [1.0, 2.0],
        },
        Place {
            name: "lobby".into(),
            at: [38.9, 18.0],
        },
    ];
    for (row, y) in [("south", 6.5), ("north", 13.5)] {
        for k in 0..8 {
            p.push(Place {
                name: format!("office-{row}-{k}"),
                at: [6.0 + 4.0 * k as f64, y],
            });
        }
    }
    p
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_scenario_round_trips_through_toml() {
        let s = Scenario::paper();
        s.validate().unwrap();
        let text = toml::to_string(&s).unwrap();
        let back: Scenario = toml::from_str(&text).unwrap();
        assert_eq!(back, s);
        assert_eq!(
            s.robots.iter().map(|r| r.name.as_str()).collect::<Vec<_>>(),
            ["T1", "T2", "T3", "D1"]
        );
        assert_eq!(
            s.people.iter().map(|p| p.beacon).collect::<Vec<_>>(),
            [Colour::Red, Colour::Green, Colour::Blue]
        );
    }

    #[test]
    fn a_minimal_file_gets_defaults_and_bad_values_are_refused() {
        let s: Scenario =
            toml::from_str("[[robots]]\nname = \"r\"\npose = [1.0, 2.0, 90.0]\nlaser = {}\n")
                .unwrap();
        assert_eq!(s.dt, 0.01);
        assert_eq!(s.robots[0].laser.as_ref().unwrap().beams, 181);
        assert_eq!(s.robots[0].drive, DriveParams::default());
        let bad: Scenario = toml::from_str("dt = 0.5\n").unwrap();
        assert!(bad.validate().unwrap_err().to_string().contains("dt"));
        let dup: Scenario =
            toml::from_str("[[robots]]\nname = \"r\"\npose = [1.0, 2.0, 0.0]\n[[robots]]\nname = \"r\"\npose = [3.0, 2.0, 0.0]\n")
                .unwrap();
        assert!(dup.validate().unwrap_err().to_string().contains("repeated"));
        assert!(toml::from_str::<Scenario>("robots = 3").is_err());
    }
}
