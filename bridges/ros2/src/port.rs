//! A ROS 2 robot as a port of muster's robot systems ([`RobotPort`]): its `scan`
//! (`sensor_msgs/LaserScan`), `odom` (`nav_msgs/Odometry`) and, where offered,
//! `ground_truth`, `sonar` (`sensor_msgs/Range`, frame `…/sonar_K` for transducer K),
//! `beacons` and `ptz` (the camera's sightings and pointing, as `muster sim --ros2`
//! publishes them: see [`crate::sim`]) are read; `cmd_vel` (`geometry_msgs/Twist`)
//! drives it and `ptz_cmd` (`geometry_msgs/Vector3`) points its camera. The paper's
//! delivery and tracking systems run on any robot that offers these (`muster system
//! delivery --ros2`, `muster system tracking --ros2`), the simulator bridged to ROS 2
//! among them, with no shared memory between them.
//!
//! What the robot is comes from the robot itself where ROS says it, and from a
//! parameter file ([`RobotParams`]) where it does not: the laser's geometry from its
//! first scan (`angle_min`, `angle_increment`, `range_max`; the laser at the robot's
//! centre, facing ahead), the sonar's bearings from `/tf_static` (`…/base_link` →
//! `…/sonar_K`) and its range from the first `Range`, the map from `/map`
//! (`nav_msgs/OccupancyGrid`, transient-local) unless a file is given; size, top speed,
//! start pose, home and camera from the parameter file, with the simulator's defaults
//! (a robot without a start pose starts where its first odometry says: its odometry
//! frame is taken to be the map's).

use crate::msgs::{
    LaserScan, MarkerArray, OccupancyGrid, Odometry, Range, TfMessage, Time, Twist, Vector3,
    Vector3Stamped,
};
use crate::node::{qos_latched, qos_reliable, qos_sensor_in, Ros2Node};
use crate::Ros2Error;
use muster_robots::port::{PortError, RobotDescription, RobotPort};
use muster_robots::sensing::{SensorGeometry, SensorSample, Sighting};
use muster_world_model::{wrap, Colour, OccupancyMap, Pose};
use ros2_client::dds::rustdds::mio1;
use ros2_client::{Publisher, Subscription};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::os::fd::{AsRawFd, RawFd};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Most samples taken from one topic in one wake-up.
const MAX_TAKE: usize = 256;

fn seconds(t: &Time) -> f64 {
    t.to_nanos() as f64 * 1e-9
}

fn planar(o: &Odometry) -> Pose {
    let p = &o.pose.pose;
    Pose {
        x: p.position.x,
        y: p.position.y,
        theta: p.orientation.yaw(),
    }
}

/// How long a described robot's sonar frames and ranges are waited for.
const SONAR_GRACE: Duration = Duration::from_secs(1);
/// Body radius without a parameter, m (the simulator's robots').
const DEFAULT_RADIUS: f64 = 0.25;
/// Top speed without a parameter, m/s (the simulator's robots').
const DEFAULT_MAX_SPEED: f64 = 1.2;

/// A beacon camera's geometry.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraParams {
    /// Field of view at zoom 1, degrees.
    pub fov_deg: f64,
    /// Detection range at zoom 1, m.
    pub range: f64,
    /// How far it pans either way, degrees.
    pub pan_limit_deg: f64,
}

impl Default for CameraParams {
    fn default() -> Self {
        // The simulator's camera.
        let c = muster_sim_world::scenario::CameraParams::default();
        CameraParams {
            fov_deg: c.fov_deg,
            range: c.range,
            pan_limit_deg: c.pan_limit_deg,
        }
    }
}

/// What a ROS 2 robot's topics do not say: one table per robot in a TOML file
/// (`--robot-params`), every key optional.
///
/// ```toml
/// [D1]
/// radius = 0.25            # m
/// max_speed = 1.2          # m/s
/// start = [2.0, 3.5, 90]   # x, y (m), heading (degrees) on the map
/// home = [1.0, 1.0]        # where it goes when idle
/// camera = { fov_deg = 60, range = 8, pan_limit_deg = 100 }
/// ```
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotParams {
    /// Body radius, m.
    pub radius: Option<f64>,
    /// Top speed, m/s.
    pub max_speed: Option<f64>,
    /// Start pose: x, y (m), heading (degrees).
    pub start: Option<[f64; 3]>,
    /// Home: x, y (m).
    pub home: Option<[f64; 2]>,
    /// The beacon camera (tracking robots).
    pub camera: Option<CameraParams>,
}

impl RobotParams {
    /// The robots' parameters in `path` (tables by robot name); each value checked.
    pub fn load(path: &Path) -> Result<BTreeMap<String, RobotParams>, Ros2Error> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| Ros2Error::Robot(format!("{}: {e}", path.display())))?;
        Self::parse(&text).map_err(|e| Ros2Error::Robot(format!("{}: {e}", path.display())))
    }

    /// [`RobotParams::load`] of a file's text.
    pub fn parse(text: &str) -> Result<BTreeMap<String, RobotParams>, String> {
        let all: BTreeMap<String, RobotParams> = toml::from_str(text).map_err(|e| e.to_string())?;
        for (name, p) in &all {
            let positive = |v: Option<f64>, what: &str| match v {
                Some(x) if !(x.is_finite() && x > 0.0) => {
                    Err(format!("[{name}] {what} must be a positive number"))
                }
                _ => Ok(()),
            };
            positive(p.radius, "radius")?;
            positive(p.max_speed, "max_speed")?;
            if let Some(c) = &p.camera {
                positive(Some(c.fov_deg), "camera.fov_deg")?;
                positive(Some(c.range), "camera.range")?;
                positive(Some(c.pan_limit_deg), "camera.pan_limit_deg")?;
            }
            let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
            if !p.start.is_none_or(|s| finite(&s)) || !p.home.is_none_or(|h| finite(&h)) {
                return Err(format!("[{name}] start and home must be finite numbers"));
            }
        }
        Ok(all)
    }
}

/// How to open a ROS 2 robot's port.
#[derive(Clone, Debug)]
pub struct PortOptions {
    /// The ROS domain.
    pub domain: u16,
    /// The robot's namespace, e.g. `/D1`.
    pub namespace: String,
    /// This side's node name (under `/muster`).
    pub node: String,
    /// The robot's name in muster.
    pub robot: String,
    /// What its topics do not say.
    pub params: RobotParams,
    /// The map, if given (else `/map`).
    pub map: Option<Arc<OccupancyMap>>,
    /// Whether the system needs the camera (waits for it).
    pub camera: bool,
    /// How long to wait for the robot's first samples.
    pub wait: Duration,
}

/// Transducer K's number if `frame` is `<ns>/sonar_K` (or `sonar_K` with no namespace).
fn sonar_frame(ns: &str, frame: &str) -> Option<usize> {
    let frame = frame.trim_start_matches('/');
    let rest = if ns.is_empty() {
        frame
    } else {
        frame.strip_prefix(ns)?.strip_prefix('/')?
    };
    rest.strip_prefix("sonar_")?
        .parse()
        .ok()
        .filter(|k| *k < 64)
}

/// Most cells of a map taken from `/map`.
const MAX_MAP_CELLS: usize = 16_000_000;

/// An occupancy grid as a map: cells at or above 65 (map_server's `occupied_thresh`)
/// and unknown cells (−1) are occupied. A rotated origin is refused.
pub fn occupancy_map(g: &OccupancyGrid) -> Result<OccupancyMap, String> {
    let (w, h) = (g.info.width as usize, g.info.height as usize);
    let res = f64::from(g.info.resolution);
    if w == 0 || h == 0 || w.saturating_mul(h) > MAX_MAP_CELLS {
        return Err(format!("a {w}x{h} grid: must be 1..={MAX_MAP_CELLS} cells"));
    }
    if g.data.len() != w * h {
        return Err(format!("{} cells for a {w}x{h} grid", g.data.len()));
    }
    if !(res.is_finite() && res > 0.0) {
        return Err(format!("resolution {res}: must be > 0"));
    }
    let o = &g.info.origin;
    if o.orientation.yaw().abs() > 1e-6 || !(o.position.x.is_finite() && o.position.y.is_finite()) {
        return Err("the origin must be finite and not rotated".into());
    }
    let occupied = g.data.iter().map(|&c| !(0..65).contains(&c)).collect();
    Ok(OccupancyMap::from_grid(
        w,
        h,
        res,
        (o.position.x, o.position.y),
        occupied,
    ))
}

/// One ROS 2 robot's topics.
pub struct Ros2Port {
    scan: Subscription<LaserScan>,
    odom: Subscription<Odometry>,
    truth: Subscription<Odometry>,
    sonar: Subscription<Range>,
    beacons: Subscription<MarkerArray>,
    ptz: Subscription<Vector3Stamped>,
    cmd: Publisher<Twist>,
    ptz_cmd: Publisher<Vector3>,
    cmd_topic: String,
    poll: mio1::Poll,
    events: mio1::Events,
    /// The newest of everything, assembled.
    sample: SensorSample,
    heard_truth: bool,
    heard_odom: bool,
    /// The first odometry pose heard.
    first_odom: Option<Pose>,
    /// The newest scan's geometry: first bearing, step, range.
    laser: Option<(f64, f64, f64)>,
    /// Each sonar transducer's range, by number, as its samples say.
    sonar_range: BTreeMap<usize, f64>,
    /// Whether the camera was heard from (`beacons` or `ptz`).
    heard_camera: bool,
    description: RobotDescription,
    // Last: readers and writers leave the DDS participant before it closes.
    node: Ros2Node,
}

impl Ros2Port {
    /// Joins the domain as node `/muster/<node>`, subscribes the robot in its namespace
    /// and waits (up to `opts.wait`) until it knows what the robot is: see the module's
    /// documentation. The error says what did not come.
    pub fn open(opts: &PortOptions) -> Result<Self, Ros2Error> {
        let mut node = Ros2Node::new(opts.domain, "/muster", &crate::ros_name(&opts.node))?;
        let ns = opts.namespace.trim_end_matches('/');
        let mut scan = node.subscription::<LaserScan>(
            &format!("{ns}/scan"),
            ("sensor_msgs", "LaserScan"),
            qos_sensor_in(5),
        )?;
        let mut odom = node.subscription::<Odometry>(
            &format!("{ns}/odom"),
            ("nav_msgs", "Odometry"),
            qos_sensor_in(10),
        )?;
        let mut truth = node.subscription::<Odometry>(
            &format!("{ns}/ground_truth"),
            ("nav_msgs", "Odometry"),
            qos_sensor_in(10),
        )?;
        let mut sonar = node.subscription::<Range>(
            &format!("{ns}/sonar"),
            ("sensor_msgs", "Range"),
            qos_sensor_in(64),
        )?;
        let mut beacons = node.subscription::<MarkerArray>(
            &format!("{ns}/beacons"),
            ("visualization_msgs", "MarkerArray"),
            qos_sensor_in(5),
        )?;
        let mut ptz = node.subscription::<Vector3Stamped>(
            &format!("{ns}/ptz"),
            ("geometry_msgs", "Vector3Stamped"),
            qos_sensor_in(5),
        )?;
        let ptz_cmd = node.publisher::<Vector3>(
            &format!("{ns}/ptz_cmd"),
            ("geometry_msgs", "Vector3"),
            qos_reliable(1),
        )?;
        let cmd_topic = format!("{ns}/cmd_vel");
        let cmd =
            node.publisher::<Twist>(&cmd_topic, ("geometry_msgs", "Twist"), qos_reliable(1))?;
        let poll = mio1::Poll::new().map_err(|e| Ros2Error::create("epoll", e))?;
        for (k, s) in [
            &mut scan as &mut dyn mio1::event::Source,
            &mut odom,
            &mut truth,
            &mut sonar,
            &mut beacons,
            &mut ptz,
        ]
        .into_iter()
        .enumerate()
        {
            poll.registry()
                .register(s, mio1::Token(k), mio1::Interest::READABLE)
                .map_err(|e| Ros2Error::create("epoll registration", e))?;
        }
        let map_sub = match &opts.map {
            Some(_) => None,
            None => Some(node.subscription::<OccupancyGrid>(
                "/map",
                ("nav_msgs", "OccupancyGrid"),
                qos_latched(),
            )?),
        };
        let tf_static = node.subscription::<TfMessage>(
            "/tf_static",
            ("tf2_msgs", "TFMessage"),
            qos_latched().history(ros2_client::qos::History::KeepLast { depth: 64 }),
        )?;
        let placeholder = RobotDescription {
            name: opts.robot.clone(),
            start: Pose::default(),
            sensors: SensorGeometry::default(),
            radius: 0.0,
            max_speed: 0.0,
            home: None,
            map: Arc::new(OccupancyMap::from_grid(1, 1, 1.0, (0.0, 0.0), vec![true])),
            fixtures: Vec::new(),
        };
        let mut port = Ros2Port {
            scan,
            odom,
            truth,
            sonar,
            beacons,
            ptz,
            cmd,
            ptz_cmd,
            cmd_topic,
            poll,
            events: mio1::Events::with_capacity(8),
            sample: SensorSample {
                time: f64::NEG_INFINITY,
                ..SensorSample::default()
            },
            heard_truth: false,
            heard_odom: false,
            first_odom: None,
            laser: None,
            sonar_range: BTreeMap::new(),
            heard_camera: false,
            description: placeholder,
            node,
        };
        port.description = port.describe(opts, map_sub, tf_static)?;
        tracing::info!(
            domain = opts.domain,
            namespace = %opts.namespace,
            robot = %opts.robot,
            start = ?port.description.start,
            sensors = ?port.description.sensors,
            "robot port on ROS 2"
        );
        Ok(port)
    }

    /// Waits for what describes the robot: a scan, odometry, the map (unless given),
    /// the camera (if needed), then up to a second more for `/tf_static`'s sonar frames
    /// and their ranges.
    fn describe(
        &mut self,
        opts: &PortOptions,
        mut map_sub: Option<Subscription<OccupancyGrid>>,
        tf_static: Subscription<TfMessage>,
    ) -> Result<RobotDescription, Ros2Error> {
        let ns = opts.namespace.trim_matches('/');
        let ns_topic = opts.namespace.trim_end_matches('/');
        let deadline = Instant::now() + opts.wait;
        let mut map = opts.map.clone();
        let mut bearings: BTreeMap<usize, f64> = BTreeMap::new();
        let mut settled: Option<Instant> = None;
        loop {
            self.take();
            if let Some(sub) = &mut map_sub {
                loop {
                    match sub.take() {
                        Ok(Some((grid, _))) => match occupancy_map(&grid) {
                            Ok(m) => map = Some(Arc::new(m)),
                            Err(e) => self.node.warn_limited(&format!("/map: {e}")),
                        },
                        Ok(None) => break,
                        Err(e) => self
                            .node
                            .warn_limited(&format!("/map: sample dropped: {e}")),
                    }
                }
            }
            loop {
                match tf_static.take() {
                    Ok(Some((tf, _))) => {
                        for t in &tf.transforms {
                            if let Some(k) = sonar_frame(ns, &t.child_frame_id) {
                                bearings.insert(k, t.transform.rotation.yaw());
                            }
                        }
                    }
                    Ok(None) => break,
                    Err(e) => self
                        .node
                        .warn_limited(&format!("/tf_static: sample dropped: {e}")),
                }
            }
            let missing: Vec<String> = [
                (self.laser.is_none(), format!("a scan on {ns_topic}/scan")),
                (!self.heard_odom, format!("odometry on {ns_topic}/odom")),
                (map.is_none(), "a map on /map (or give --map)".to_string()),
                (
                    opts.camera && !self.heard_camera && opts.params.camera.is_none(),
                    format!("the camera on {ns_topic}/beacons or {ns_topic}/ptz"),
                ),
            ]
            .into_iter()
            .filter_map(|(m, what)| m.then_some(what))
            .collect();
            let now = Instant::now();
            if missing.is_empty() {
                let since = *settled.get_or_insert(now);
                let sonar_known = bearings.keys().all(|k| self.sonar_range.contains_key(k));
                if (!bearings.is_empty() && sonar_known)
                    || now >= since + SONAR_GRACE
                    || now >= deadline
                {
                    break;
                }
            } else if now >= deadline {
                return Err(Ros2Error::Robot(format!(
                    "robot {}: waited {:?} for {}",
                    opts.robot,
                    opts.wait,
                    missing.join(", ")
                )));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        // (The loop ends with a map: its absence keeps it waiting, or is the error.)
        let Some(map) = map else {
            return Err(Ros2Error::Robot(format!("robot {}: no map", opts.robot)));
        };
        let p = &opts.params;
        let sonar = (!bearings.is_empty()).then(|| {
            let range = bearings
                .keys()
                .filter_map(|k| self.sonar_range.get(k))
                .fold(0.0, |a: f64, b| a.max(*b));
            (bearings.values().copied().collect::<Vec<_>>(), range)
        });
        let camera = p
            .camera
            .clone()
            .or_else(|| self.heard_camera.then(CameraParams::default));
        let start = match p.start {
            Some([x, y, deg]) => Pose {
                x,
                y,
                theta: wrap(deg.to_radians()),
            },
            None => self.first_odom.unwrap_or_default(),
        };
        Ok(RobotDescription {
            name: opts.robot.clone(),
            start,
            sensors: SensorGeometry {
                laser: self.laser,
                sonar: sonar.filter(|(b, r)| !b.is_empty() && *r > 0.0),
                camera: camera.map(|c| {
                    (
                        c.fov_deg.to_radians(),
                        c.range,
                        c.pan_limit_deg.to_radians(),
                    )
                }),
            },
            radius: p.radius.unwrap_or(DEFAULT_RADIUS),
            max_speed: p.max_speed.unwrap_or(DEFAULT_MAX_SPEED),
            home: p.home.map(|[x, y]| (x, y)),
            map,
            // A real robot's map shows what stands still.
            fixtures: Vec::new(),
        })
    }

    /// Takes what arrived into the sample.
    fn take(&mut self) {
        for _ in 0..MAX_TAKE {
            match self.scan.take() {
                Ok(Some((s, _))) => {
                    let t = seconds(&s.header.stamp);
                    let max = f64::from(s.range_max);
                    // The cores read "no return" as the scanner's maximum range.
                    self.sample.laser = s
                        .ranges
                        .iter()
                        .map(|&r| {
                            if r.is_finite() && f64::from(r) < max {
                                r
                            } else {
                                max as f32
                            }
                        })
                        .collect();
                    self.sample.laser_time = t;
                    self.sample.time = self.sample.time.max(t);
                    if max > 0.0 && !s.ranges.is_empty() && s.angle_increment.is_finite() {
                        self.laser =
                            Some((f64::from(s.angle_min), f64::from(s.angle_increment), max));
                    }
                }
                Ok(None) => break,
                Err(e) => self
                    .node
                    .warn_limited(&format!("scan: sample dropped: {e}")),
            }
        }
        for _ in 0..MAX_TAKE {
            match self.odom.take() {
                Ok(Some((o, _))) => {
                    self.heard_odom = true;
                    self.sample.odom = planar(&o);
                    self.first_odom.get_or_insert(self.sample.odom);
                    if !self.heard_truth {
                        self.sample.truth = self.sample.odom;
                    }
                    self.sample.time = self.sample.time.max(seconds(&o.header.stamp));
                }
                Ok(None) => break,
                Err(e) => self
                    .node
                    .warn_limited(&format!("odom: sample dropped: {e}")),
            }
        }
        for _ in 0..MAX_TAKE {
            match self.sonar.take() {
                Ok(Some((r, _))) => {
                    // One transducer per message, named by its frame (`…/sonar_K`).
                    let k = r
                        .header
                        .frame_id
                        .rsplit_once("sonar_")
                        .and_then(|(_, k)| k.parse::<usize>().ok())
                        .filter(|k| *k < 64);
                    if let Some(k) = k {
                        if self.sample.sonar.len() <= k {
                            self.sample.sonar.resize(k + 1, r.max_range);
                        }
                        let max = r.max_range;
                        self.sample.sonar[k] = if r.range.is_finite() && r.range < max {
                            r.range
                        } else {
                            max
                        };
                        self.sample.sonar_time = seconds(&r.header.stamp);
                        if max.is_finite() && max > 0.0 {
                            self.sonar_range.insert(k, f64::from(max));
                        }
                    }
                }
                Ok(None) => break,
                Err(e) => self
                    .node
                    .warn_limited(&format!("sonar: sample dropped: {e}")),
            }
        }
        for _ in 0..MAX_TAKE {
            match self.beacons.take() {
                Ok(Some((m, _))) => {
                    self.heard_camera = true;
                    let stamp = m.markers.first().map(|k| seconds(&k.header.stamp));
                    self.sample.sightings = m
                        .markers
                        .iter()
                        .filter_map(|k| {
                            let (x, y) = (k.pose.position.x, k.pose.position.y);
                            Some(Sighting {
                                colour: Colour::from_name(&k.ns)?,
                                bearing: y.atan2(x),
                                range: x.hypot(y),
                            })
                        })
                        .collect();
                    // An empty frame (nothing seen) has no stamp of its own: the newest.
                    self.sample.camera_time = stamp.unwrap_or(self.sample.time);
                }
                Ok(None) => break,
                Err(e) => self
                    .node
                    .warn_limited(&format!("beacons: sample dropped: {e}")),
            }
        }
        for _ in 0..MAX_TAKE {
            match self.ptz.take() {
                Ok(Some((p, _))) => {
                    self.heard_camera = true;
                    self.sample.pan = p.vector.x;
                    self.sample.camera_time = self.sample.camera_time.max(seconds(&p.header.stamp));
                }
                Ok(None) => break,
                Err(e) => self.node.warn_limited(&format!("ptz: sample dropped: {e}")),
            }
        }
        for _ in 0..MAX_TAKE {
            match self.truth.take() {
                Ok(Some((o, _))) => {
                    self.heard_truth = true;
                    self.sample.truth = planar(&o);
                }
                Ok(None) => break,
                Err(e) => self
                    .node
                    .warn_limited(&format!("ground_truth: sample dropped: {e}")),
            }
        }
    }
}

impl RobotPort for Ros2Port {
    fn description(&self) -> &RobotDescription {
        &self.description
    }

    fn fd(&self) -> RawFd {
        self.poll.as_raw_fd()
    }

    fn drain(&mut self) {
        if let Err(e) = self
            .poll
            .poll(&mut self.events, Some(std::time::Duration::ZERO))
        {
            self.node.warn_limited(&format!("epoll: {e}"));
        }
    }

    fn latest(&mut self, after: f64) -> Result<Option<SensorSample>, PortError> {
        self.take();
        // A sample is whole once both a scan and odometry came (a localizer must never
        // see the odometry jump from a default pose).
        let ready = self.heard_odom && !self.sample.laser.is_empty() && self.sample.time > after;
        Ok(ready.then(|| self.sample.clone()))
    }

    fn newer_than(&mut self, after: f64) -> Option<f64> {
        self.take();
        (self.sample.time > after).then_some(self.sample.time)
    }

    fn velocity(&mut self, v: f64, w: f64) -> Result<(), PortError> {
        let t = Twist {
            linear: Vector3 {
                x: v,
                ..Vector3::default()
            },
            angular: Vector3 {
                z: w,
                ..Vector3::default()
            },
        };
        self.cmd
            .publish(t)
            .map_err(|e| PortError(format!("{}: {e}", self.cmd_topic)))
    }

    fn camera(&mut self, pan: f64, tilt: f64, zoom: f64) -> Result<(), PortError> {
        self.ptz_cmd
            .publish(Vector3 {
                x: pan,
                y: tilt,
                z: zoom,
            })
            .map_err(|e| PortError(format!("ptz_cmd: {e}")))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn robot_params_are_read_per_robot_and_bad_values_refused() {
        let all = RobotParams::parse(
            "[D1]\nstart = [1.0, 2.0, 90]\nradius = 0.3\n[T1]\ncamera = { fov_deg = 45 }\n",
        )
        .unwrap();
        assert_eq!(all["D1"].start, Some([1.0, 2.0, 90.0]));
        assert_eq!(all["D1"].radius, Some(0.3));
        assert_eq!(all["D1"].max_speed, None);
        let cam = all["T1"].camera.as_ref().unwrap();
        assert_eq!((cam.fov_deg, cam.range), (45.0, 8.0));
        for (bad, says) in [
            ("[D1]\nradius = -1.0\n", "radius must be a positive"),
            ("[D1]\nmax_speed = 0.0\n", "max_speed must be a positive"),
            ("[D1]\nstart = [1.0, 2.0]\n", "invalid length"),
            ("[D1]\nstart = [1.0, nan, 0.0]\n", "finite"),
            ("[D1]\nspeed = 1.0\n", "unknown field `speed`"),
            ("[D1]\ncamera = { range = -8 }\n", "camera.range"),
        ] {
            let e = RobotParams::parse(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn an_occupancy_grid_becomes_the_same_map() {
        let office = OccupancyMap::office();
        let grid = crate::sim::occupancy_grid(&office, 0.0);
        let back = occupancy_map(&grid).unwrap();
        assert_eq!(
            (back.width(), back.height()),
            (office.width(), office.height())
        );
        assert_eq!(back.origin(), office.origin());
        for j in 0..office.height() as i64 {
            for i in 0..office.width() as i64 {
                assert_eq!(back.occupied(i, j), office.occupied(i, j), "({i}, {j})");
            }
        }
        // Unknown (-1) and likely-occupied (≥ 65) cells are walls; the rest free.
        let mut g = grid.clone();
        g.info.width = 4;
        g.info.height = 1;
        g.data = vec![-1, 0, 64, 65];
        let m = occupancy_map(&g).unwrap();
        let occ: Vec<bool> = (0..4).map(|i| m.occupied(i, 0)).collect();
        assert_eq!(occ, [true, false, false, true]);
        // Bad grids are refused with what is wrong.
        g.data.pop();
        assert!(occupancy_map(&g)
            .unwrap_err()
            .contains("3 cells for a 4x1 grid"));
        g.data.push(0);
        g.info.resolution = 0.0;
        assert!(occupancy_map(&g).unwrap_err().contains("resolution"));
        g.info.resolution = 0.05;
        g.info.origin = crate::msgs::Pose::planar(0.0, 0.0, 0.5);
        assert!(occupancy_map(&g).unwrap_err().contains("rotated"));
        g.info.width = 100_000;
        g.info.height = 100_000;
        assert!(occupancy_map(&g).unwrap_err().contains("cells"));
    }

    #[test]
    fn sonar_frames_are_matched_in_the_robots_namespace() {
        assert_eq!(sonar_frame("D1", "D1/sonar_3"), Some(3));
        assert_eq!(sonar_frame("D1", "/D1/sonar_15"), Some(15));
        assert_eq!(sonar_frame("D1", "T1/sonar_3"), None);
        assert_eq!(sonar_frame("D1", "D1/sonar_x"), None);
        assert_eq!(sonar_frame("D1", "D1/sonar_64"), None);
        assert_eq!(sonar_frame("", "sonar_2"), Some(2));
        assert_eq!(sonar_frame("", "D1/sonar_2"), None);
    }
}
