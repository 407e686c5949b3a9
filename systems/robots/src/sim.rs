//! The simulator's robots as ports ([`SimPort`]): samples read in place from sim-world's
//! shared memory, commands written back there, and each robot's description taken from
//! the scenario the simulator runs. The only part of the robot systems that knows the
//! simulator.

use crate::port::{PortError, RobotDescription, RobotPort};
use crate::sensing::{SensorGeometry, SensorSample, Sighting};
use crate::shell::RobotSystemError;
use muster_sim_world::scenario::{RobotSpec, Scenario};
use muster_sim_world::shm::{PoseC, RobotLink, RobotSensors};
use muster_sim_world::world::Robot;
use muster_world_model::{wrap, Colour, OccupancyMap, Pose};
use std::os::fd::RawFd;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A simulated robot: its link to the simulator's shared memory and its description.
pub struct SimPort {
    link: RobotLink,
    description: RobotDescription,
}

/// The description of the scenario's robot `name` on `map`.
pub fn describe(
    scenario: &Scenario,
    map: &Arc<OccupancyMap>,
    name: &str,
) -> Result<RobotDescription, RobotSystemError> {
    let spec = scenario
        .robots
        .iter()
        .find(|r| r.name == name)
        .ok_or_else(|| RobotSystemError::NoRobot(name.to_string()))?;
    Ok(RobotDescription {
        name: name.to_string(),
        start: Pose {
            x: spec.pose[0],
            y: spec.pose[1],
            theta: wrap(spec.pose[2].to_radians()),
        },
        sensors: SensorGeometry::of(spec),
        radius: spec.drive.radius,
        max_speed: spec.drive.max_speed,
        home: spec.home.as_ref().and_then(|h| {
            scenario
                .places
                .iter()
                .find(|p| &p.name == h)
                .map(|p| (p.at[0], p.at[1]))
        }),
        map: Arc::clone(map),
        fixtures: fixtures(scenario, Some(name)),
    })
}

/// The scenario's fixed robots (x, y, radius) but `except`: fixtures for the others'
/// maps ([`RobotDescription::fixtures`]).
pub fn fixtures(scenario: &Scenario, except: Option<&str>) -> Vec<(f64, f64, f64)> {
    scenario
        .robots
        .iter()
        .filter(|r| r.fixed && Some(r.name.as_str()) != except)
        .map(|r| (r.pose[0], r.pose[1], r.drive.radius))
        .collect()
}

/// Opens the ports to the scenario's `robots` on instance `inst`, retrying until the
/// simulator is up or `wait` passes.
pub fn open_ports(
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    inst: &str,
    scenario: &Scenario,
    map: &Arc<OccupancyMap>,
    robots: &[String],
    wait: Duration,
) -> Result<Vec<SimPort>, RobotSystemError> {
    let descriptions = robots
        .iter()
        .map(|r| describe(scenario, map, r))
        .collect::<Result<Vec<_>, _>>()?;
    let deadline = Instant::now() + wait;
    let mut logged = false;
    loop {
        match robots
            .iter()
            .map(|r| RobotLink::open(node, inst, r))
            .collect::<Result<Vec<_>, _>>()
        {
            Ok(links) => {
                return Ok(links
                    .into_iter()
                    .zip(descriptions)
                    .map(|(link, description)| SimPort { link, description })
                    .collect())
            }
            Err(e) if Instant::now() >= deadline => {
                return Err(RobotSystemError::Port(PortError(format!(
                    "{e} (is `muster sim` running on this instance?)"
                ))))
            }
            Err(e) => {
                if !logged {
                    tracing::info!("waiting for the simulator: {e}");
                    logged = true;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
}

impl RobotPort for SimPort {
    fn description(&self) -> &RobotDescription {
        &self.description
    }
    fn fd(&self) -> RawFd {
        self.link.fd()
    }
    fn drain(&mut self) {
        self.link.drain();
    }
    fn latest(&mut self, after: f64) -> Result<Option<SensorSample>, PortError> {
        self.link
            .latest(after, SensorSample::from_shm)
            .map_err(|e| PortError(e.to_string()))
    }
    fn newer_than(&mut self, after: f64) -> Option<f64> {
        self.link.latest(after, |s| s.time).ok().flatten()
    }
    fn velocity(&mut self, v: f64, w: f64) -> Result<(), PortError> {
        self.link
            .velocity(v, w)
            .map_err(|e| PortError(e.to_string()))
    }
    fn camera(&mut self, pan: f64, tilt: f64, zoom: f64) -> Result<(), PortError> {
        self.link
            .camera(pan, tilt, zoom)
            .map_err(|e| PortError(e.to_string()))
    }
}

impl SensorSample {
    /// Copies what the systems use out of a sample read in place.
    pub fn from_shm(s: &RobotSensors) -> Self {
        let nb = (s.n_beams as usize).min(s.laser.len());
        let ns = (s.n_sonar as usize).min(s.sonar.len());
        let nd = (s.n_detections as usize).min(s.detections.len());
        let pose = |p: &PoseC| Pose {
            x: p.x,
            y: p.y,
            theta: p.theta,
        };
        SensorSample {
            time: s.time,
            odom: pose(&s.odom),
            truth: pose(&s.pose),
            laser_time: s.laser_time,
            laser: s.laser[..nb].to_vec(),
            sonar_time: s.sonar_time,
            sonar: s.sonar[..ns].to_vec(),
            camera_time: s.camera_time,
            pan: s.ptz[0],
            sightings: s.detections[..nd]
                .iter()
                .filter_map(|d| {
                    Some(Sighting {
                        colour: Colour::from_code(d.colour)?,
                        bearing: d.bearing,
                        range: d.range,
                    })
                })
                .collect(),
            bumped: s.bumped != 0,
        }
    }
}

impl SensorSample {
    /// The same sample taken straight from a robot of an in-process [`World`] (tests and
    /// benchmarks run the cores on the simulator without processes).
    ///
    /// [`World`]: muster_sim_world::world::World
    pub fn from_robot(r: &Robot, time: f64) -> Self {
        SensorSample {
            time,
            odom: r.odom,
            truth: r.pose,
            laser_time: r.laser_time,
            laser: r.laser.clone(),
            sonar_time: r.sonar_time,
            sonar: r.sonar.clone(),
            camera_time: r.camera_time,
            pan: r.ptz.pan,
            sightings: r
                .detections
                .iter()
                .map(|d| Sighting {
                    colour: d.colour,
                    bearing: d.bearing,
                    range: d.range,
                })
                .collect(),
            bumped: r.bumped,
        }
    }
}

impl SensorGeometry {
    /// The geometry of a scenario robot's sensors.
    pub fn of(spec: &RobotSpec) -> Self {
        SensorGeometry {
            laser: spec.laser.as_ref().map(|l| {
                let fov = l.fov_deg.to_radians();
                let step = if l.beams > 1 {
                    fov / (l.beams - 1) as f64
                } else {
                    0.0
                };
                let first = if l.beams > 1 { -fov / 2.0 } else { 0.0 };
                (first, step, l.range)
            }),
            sonar: spec.sonar.as_ref().map(|s| {
                (
                    s.bearings_deg.iter().map(|b| b.to_radians()).collect(),
                    s.range,
                )
            }),
            camera: spec.camera.as_ref().map(|c| {
                (
                    c.fov_deg.to_radians(),
                    c.range,
                    c.pan_limit_deg.to_radians(),
                )
            }),
        }
    }
}
