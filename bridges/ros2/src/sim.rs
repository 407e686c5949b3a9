//! muster's simulator in ROS 2: every robot's sensors and odometry as ROS topics, its
//! `cmd_vel` obeyed, the map, the people and the simulated clock — a Stage for ROS 2.
//!
//! Per robot `R` (its name made a ROS name), in namespace `/R`:
//! - `scan` — `sensor_msgs/LaserScan` in frame `R/laser`, at the laser's rate;
//! - `sonar` — `sensor_msgs/Range`, one message per transducer per ring, frame
//!   `R/sonar_K` (each transducer's bearing is on `/tf_static`);
//! - `odom` — `nav_msgs/Odometry`, frame `R/odom` → `R/base_link` (the robot's drifting
//!   odometry; the same transform on `/tf`);
//! - `ground_truth` — `nav_msgs/Odometry` in frame `map` (the simulator's true pose, as
//!   Stage publishes it; for evaluation, not for a robot's own decisions);
//! - `cmd_vel` — `geometry_msgs/Twist` subscribed: linear.x and angular.z drive the
//!   robot, clamped to its limits; it stops when commands stop for its command timeout;
//! - with a camera: `beacons` — the beacons its camera sees, a
//!   `visualization_msgs/MarkerArray` of spheres in frame `R/base_link` at each beacon's
//!   place (its range along its bearing from the robot's heading), `ns` the beacon's
//!   colour name (`red`, ...), `color` its colour, one array per frame (empty: none
//!   seen); `ptz` — `geometry_msgs/Vector3Stamped`, the camera's pan and tilt (rad) and
//!   zoom in x, y, z; and `ptz_cmd` — `geometry_msgs/Vector3` subscribed, where to point
//!   it (the same axes).
//!
//! And `/clock` (`rosgraph_msgs/Clock`, every step: nodes run with `use_sim_time` at any
//! speed), `/map` (`nav_msgs/OccupancyGrid`, transient-local), `/people`
//! (`visualization_msgs/MarkerArray`), `/tf` and `/tf_static` (`tf2_msgs/TFMessage`).
//! Every stamp is simulated time.

use crate::msgs::*;
use crate::node::{qos_latched, qos_reliable, qos_sensor_in, Ros2Node};
use crate::{ros_name, Ros2Error};
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::world::{Robot, World};
use ros2_client::{Publisher, Subscription};

/// How often the bridge sends what has no rate of its own (simulated seconds).
#[derive(Clone, Debug)]
pub struct SimBridgeOptions {
    /// ROS domain id (`ROS_DOMAIN_ID`).
    pub domain: u16,
    /// Odometry, ground truth and `/tf`, Hz.
    pub odom_rate: f64,
    /// People markers, Hz.
    pub people_rate: f64,
}

impl Default for SimBridgeOptions {
    fn default() -> Self {
        SimBridgeOptions {
            domain: 0,
            odom_rate: 20.0,
            people_rate: 10.0,
        }
    }
}

struct Camera {
    beacons: Publisher<MarkerArray>,
    ptz: Publisher<Vector3Stamped>,
    ptz_cmd: Subscription<Vector3>,
    stamp: f64,
}

struct RobotTopics {
    name: String,
    camera: Option<Camera>,
    scan: Option<Publisher<LaserScan>>,
    sonar: Option<Publisher<Range>>,
    odom: Publisher<Odometry>,
    ground_truth: Publisher<Odometry>,
    cmd_vel: Subscription<Twist>,
    laser_stamp: f64,
    sonar_stamp: f64,
}

/// The simulator's ROS 2 side. Call [`SimBridge::take_commands`] before each step and
/// [`SimBridge::publish`] after it.
pub struct SimBridge {
    clock: Publisher<Clock>,
    tf: Publisher<TfMessage>,
    // Latched (transient-local): sent once, and kept so late subscribers get them.
    tf_static: Publisher<TfMessage>,
    map: Publisher<OccupancyGrid>,
    people: Publisher<MarkerArray>,
    robots: Vec<RobotTopics>,
    opts: SimBridgeOptions,
    next_odom: f64,
    next_people: f64,
    // Last: the publishers above leave the DDS participant before it closes.
    node: Ros2Node,
}

impl SimBridge {
    /// Joins ROS domain `opts.domain` as node `/muster_sim` with every robot of `world`,
    /// and sends the map and the static transforms (latched: late subscribers get them).
    pub fn new(world: &World, opts: SimBridgeOptions) -> Result<Self, Ros2Error> {
        let mut node = Ros2Node::new(opts.domain, "/", "muster_sim")?;
        let clock =
            node.publisher::<Clock>("/clock", ("rosgraph_msgs", "Clock"), qos_reliable(1))?;
        let tf =
            node.publisher::<TfMessage>("/tf", ("tf2_msgs", "TFMessage"), qos_reliable(100))?;
        let tf_static =
            node.publisher::<TfMessage>("/tf_static", ("tf2_msgs", "TFMessage"), qos_latched())?;
        let map =
            node.publisher::<OccupancyGrid>("/map", ("nav_msgs", "OccupancyGrid"), qos_latched())?;
        let people = node.publisher::<MarkerArray>(
            "/people",
            ("visualization_msgs", "MarkerArray"),
            qos_reliable(1),
        )?;
        let mut robots = Vec::with_capacity(world.robots().len());
        let mut statics = Vec::new();
        for r in world.robots() {
            let ns = format!("/{}", ros_name(&r.spec.name));
            let name = ros_name(&r.spec.name);
            let scan = match &r.spec.laser {
                Some(_) => {
                    statics.push(fixed(&name, "laser", 0.0));
                    Some(node.publisher::<LaserScan>(
                        &format!("{ns}/scan"),
                        ("sensor_msgs", "LaserScan"),
                        qos_reliable(5),
                    )?)
                }
                None => None,
            };
            let sonar = match &r.spec.sonar {
                Some(s) => {
                    for (k, b) in s.bearings_deg.iter().enumerate() {
                        statics.push(fixed(&name, &format!("sonar_{k}"), b.to_radians()));
                    }
                    Some(node.publisher::<Range>(
                        &format!("{ns}/sonar"),
                        ("sensor_msgs", "Range"),
                        qos_reliable(s.bearings_deg.len().max(1) * 2),
                    )?)
                }
                None => None,
            };
            let camera = match &r.spec.camera {
                Some(_) => Some(Camera {
                    beacons: node.publisher(
                        &format!("{ns}/beacons"),
                        ("visualization_msgs", "MarkerArray"),
                        qos_reliable(5),
                    )?,
                    ptz: node.publisher(
                        &format!("{ns}/ptz"),
                        ("geometry_msgs", "Vector3Stamped"),
                        qos_reliable(5),
                    )?,
                    ptz_cmd: node.subscription(
                        &format!("{ns}/ptz_cmd"),
                        ("geometry_msgs", "Vector3"),
                        qos_sensor_in(10),
                    )?,
                    stamp: -1.0,
                }),
                None => None,
            };
            robots.push(RobotTopics {
                camera,
                scan,
                sonar,
                odom: node.publisher(
                    &format!("{ns}/odom"),
                    ("nav_msgs", "Odometry"),
                    qos_reliable(5),
                )?,
                ground_truth: node.publisher(
                    &format!("{ns}/ground_truth"),
                    ("nav_msgs", "Odometry"),
                    qos_reliable(5),
                )?,
                cmd_vel: node.subscription(
                    &format!("{ns}/cmd_vel"),
                    ("geometry_msgs", "Twist"),
                    qos_sensor_in(10),
                )?,
                name,
                laser_stamp: -1.0,
                sonar_stamp: -1.0,
            });
        }
        let bridge = SimBridge {
            clock,
            tf,
            people,
            robots,
            opts,
            next_odom: 0.0,
            next_people: 0.0,
            tf_static,
            map,
            node,
        };
        bridge.node.send(
            &bridge.map,
            occupancy_grid(world.map(), world.time()),
            "/map",
        );
        let statics = TfMessage {
            transforms: statics
                .into_iter()
                .map(|(parent, child, t)| TransformStamped {
                    header: Header::at(world.time(), &parent),
                    child_frame_id: child,
                    transform: t,
                })
                .collect(),
        };
        bridge.node.send(&bridge.tf_static, statics, "/tf_static");
        tracing::info!(
            domain = bridge.opts.domain,
            robots = bridge.robots.len(),
            "simulator bridged to ROS 2"
        );
        Ok(bridge)
    }

    /// Applies the newest `cmd_vel` each robot was sent since the last call. A sample
    /// that does not decode is dropped with a warning.
    pub fn take_commands(&mut self, world: &mut World) {
        for (i, r) in self.robots.iter().enumerate() {
            let mut newest = None;
            loop {
                match r.cmd_vel.take() {
                    Ok(Some((t, _))) => newest = Some(t),
                    Ok(None) => break,
                    Err(e) => {
                        self.node
                            .warn_limited(&format!("/{}/cmd_vel: sample dropped: {e:?}", r.name));
                        break;
                    }
                }
            }
            if let Some(t) = newest {
                world.command_velocity(i, t.linear.x, t.angular.z);
            }
            if let Some(c) = &r.camera {
                let mut newest = None;
                loop {
                    match c.ptz_cmd.take() {
                        Ok(Some((v, _))) => newest = Some(v),
                        Ok(None) => break,
                        Err(e) => {
                            self.node.warn_limited(&format!(
                                "/{}/ptz_cmd: sample dropped: {e:?}",
                                r.name
                            ));
                            break;
                        }
                    }
                }
                if let Some(v) = newest {
                    world.command_camera(i, v.x, v.y, v.z);
                }
            }
        }
    }

    /// Publishes the clock, every sensor that updated since the last call, and
    /// odometry, ground truth, `/tf` and people when their rate says so.
    pub fn publish(&mut self, world: &World) {
        let now = world.time();
        self.node.send(
            &self.clock,
            Clock {
                clock: sim_time(now),
            },
            "/clock",
        );
        for (t, r) in self.robots.iter_mut().zip(world.robots()) {
            if let (Some(p), Some(params)) = (&t.scan, &r.spec.laser) {
                if r.laser_time > t.laser_stamp {
                    t.laser_stamp = r.laser_time;
                    self.node.send(p, laser_scan(&t.name, r, params), "scan");
                }
            }
            if let Some(c) = &mut t.camera {
                if r.camera_time > c.stamp {
                    c.stamp = r.camera_time;
                    self.node.send(&c.beacons, beacons(&t.name, r), "beacons");
                    let ptz = Vector3Stamped {
                        header: Header::at(r.camera_time, &format!("{}/base_link", t.name)),
                        vector: Vector3 {
                            x: r.ptz.pan,
                            y: r.ptz.tilt,
                            z: r.ptz.zoom,
                        },
                    };
                    self.node.send(&c.ptz, ptz, "ptz");
                }
            }
            if let (Some(p), Some(params)) = (&t.sonar, &r.spec.sonar) {
                if r.sonar_time > t.sonar_stamp {
                    t.sonar_stamp = r.sonar_time;
                    let fov = params.cone_deg.to_radians() as f32;
                    let variance = (params.noise * params.noise) as f32;
                    for (k, &range) in r.sonar.iter().enumerate() {
                        let msg = Range {
                            header: Header::at(r.sonar_time, &format!("{}/sonar_{k}", t.name)),
                            radiation_type: ULTRASOUND,
                            field_of_view: fov,
                            min_range: 0.0,
                            max_range: params.range as f32,
                            range: no_return_is_inf(range, params.range),
                            variance,
                        };
                        self.node.send(p, msg, "sonar");
                    }
                }
            }
        }
        if now + 1e-9 >= self.next_odom {
            self.next_odom = now + 1.0 / self.opts.odom_rate.max(1e-3);
            let mut tf = TfMessage::default();
            for (t, r) in self.robots.iter().zip(world.robots()) {
                let (odom, truth) = odometry(&t.name, r, now);
                tf.transforms.push(TransformStamped {
                    header: odom.header.clone(),
                    child_frame_id: odom.child_frame_id.clone(),
                    transform: Transform {
                        translation: odom.pose.pose.position,
                        rotation: odom.pose.pose.orientation,
                    },
                });
                self.node.send(&t.odom, odom, "odom");
                self.node.send(&t.ground_truth, truth, "ground_truth");
            }
            self.node.send(&self.tf, tf, "/tf");
        }
        if now + 1e-9 >= self.next_people {
            self.next_people = now + 1.0 / self.opts.people_rate.max(1e-3);
            self.node.send(&self.people, people(world), "/people");
        }
    }

    /// Samples that could not be sent or decoded so far.
    pub fn errors(&self) -> u64 {
        self.node.errors()
    }
}

/// A static transform from `robot/base_link` to `robot/child`, turned by `yaw`.
fn fixed(robot: &str, child: &str, yaw: f64) -> (String, String, Transform) {
    (
        format!("{robot}/base_link"),
        format!("{robot}/{child}"),
        Transform {
            translation: Vector3::default(),
            rotation: Quaternion::from_yaw(yaw),
        },
    )
}

/// A reading at the sensor's maximum is no return: +inf, as REP 117 says.
fn no_return_is_inf(r: f32, max: f64) -> f32 {
    if f64::from(r) >= max {
        f32::INFINITY
    } else {
        r
    }
}

/// The robot's last scan. The simulator's beams run right to left over the field of
/// view, centred on the heading: ROS's counter-clockwise order from `angle_min`.
pub fn laser_scan(
    name: &str,
    r: &Robot,
    params: &muster_sim_world::scenario::LaserParams,
) -> LaserScan {
    let n = r.laser.len();
    let fov = params.fov_deg.to_radians();
    let (min, inc) = if n > 1 {
        (-fov / 2.0, fov / (n - 1) as f64)
    } else {
        (0.0, 0.0)
    };
    LaserScan {
        header: Header::at(r.laser_time, &format!("{name}/laser")),
        angle_min: min as f32,
        angle_max: (min + inc * n.saturating_sub(1) as f64) as f32,
        angle_increment: inc as f32,
        time_increment: 0.0,
        scan_time: (1.0 / params.rate.max(1e-6)) as f32,
        range_min: 0.0,
        range_max: params.range as f32,
        ranges: r
            .laser
            .iter()
            .map(|&v| no_return_is_inf(v, params.range))
            .collect(),
        intensities: Vec::new(),
    }
}

/// What robot `name`'s camera saw in its last frame: a sphere per beacon, `ns` its
/// colour's name.
pub fn beacons(name: &str, r: &Robot) -> MarkerArray {
    let frame = format!("{name}/base_link");
    MarkerArray {
        markers: r
            .detections
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let [cr, cg, cb] = d.colour.rgb();
                Marker {
                    header: Header::at(r.camera_time, &frame),
                    ns: d.colour.name().to_string(),
                    id: k as i32,
                    kind: Marker::SPHERE,
                    action: Marker::ADD,
                    pose: Pose::planar(d.range * d.bearing.cos(), d.range * d.bearing.sin(), 0.0),
                    scale: Vector3 {
                        x: 0.3,
                        y: 0.3,
                        z: 0.3,
                    },
                    color: ColorRgba {
                        r: f32::from(cr) / 255.0,
                        g: f32::from(cg) / 255.0,
                        b: f32::from(cb) / 255.0,
                        a: 1.0,
                    },
                    ..Marker::default()
                }
            })
            .collect(),
    }
}

/// The robot's odometry (frame `name/odom`) and its true pose (frame `map`).
fn odometry(name: &str, r: &Robot, now: f64) -> (Odometry, Odometry) {
    let d = &r.spec.drive;
    let twist = TwistWithCovariance {
        twist: Twist {
            linear: Vector3 {
                x: r.velocity.0,
                ..Vector3::default()
            },
            angular: Vector3 {
                z: r.velocity.1,
                ..Vector3::default()
            },
        },
        covariance: Covariance::diagonal([
            d.odom_noise_linear.powi(2),
            1e-6,
            1e6,
            1e6,
            1e6,
            d.odom_noise_angular.powi(2),
        ]),
    };
    let base = format!("{name}/base_link");
    let odom = Odometry {
        header: Header::at(now, &format!("{name}/odom")),
        child_frame_id: base.clone(),
        pose: PoseWithCovariance {
            pose: Pose::planar(r.odom.x, r.odom.y, r.odom.theta),
            // Odometry drifts: its covariance grows without bound; say "large" in the
            // planar axes, "unused" in the others.
            covariance: Covariance::diagonal([1.0, 1.0, 1e6, 1e6, 1e6, 0.5]),
        },
        twist: twist.clone(),
    };
    let truth = Odometry {
        header: Header::at(now, "map"),
        child_frame_id: base,
        pose: PoseWithCovariance {
            pose: Pose::planar(r.pose.x, r.pose.y, r.pose.theta),
            covariance: Covariance::diagonal([0.0; 6]),
        },
        twist,
    };
    (odom, truth)
}

/// The map as an occupancy grid in frame `map` (occupied 100, free 0).
pub fn occupancy_grid(map: &OccupancyMap, now: f64) -> OccupancyGrid {
    let (w, h) = (map.width(), map.height());
    let mut data = Vec::with_capacity(w * h);
    for j in 0..h {
        for i in 0..w {
            data.push(if map.occupied(i as i64, j as i64) {
                100
            } else {
                0
            });
        }
    }
    let (ox, oy) = map.origin();
    OccupancyGrid {
        header: Header::at(now, "map"),
        info: MapMetaData {
            map_load_time: sim_time(now),
            resolution: map.resolution() as f32,
            width: w as u32,
            height: h as u32,
            origin: Pose::planar(ox, oy, 0.0),
        },
        data,
    }
}

/// Each person as a cylinder in their beacon's colour, with their name above.
fn people(world: &World) -> MarkerArray {
    let now = world.time();
    let mut markers = Vec::with_capacity(world.people().len() * 2);
    for (k, p) in world.people().iter().enumerate() {
        let [r, g, b] = p.beacon.rgb();
        let color = ColorRgba {
            r: f32::from(r) / 255.0,
            g: f32::from(g) / 255.0,
            b: f32::from(b) / 255.0,
            a: 1.0,
        };
        let at = |z: f64| Pose {
            position: Point {
                x: p.pose.x,
                y: p.pose.y,
                z,
            },
            orientation: Quaternion::from_yaw(p.pose.theta),
        };
        markers.push(Marker {
            header: Header::at(now, "map"),
            ns: "people".into(),
            id: k as i32,
            kind: Marker::CYLINDER,
            action: Marker::ADD,
            pose: at(0.85),
            scale: Vector3 {
                x: 0.4,
                y: 0.4,
                z: 1.7,
            },
            color,
            ..Marker::default()
        });
        markers.push(Marker {
            header: Header::at(now, "map"),
            ns: "people_names".into(),
            id: k as i32,
            kind: Marker::TEXT_VIEW_FACING,
            action: Marker::ADD,
            pose: at(2.0),
            scale: Vector3 {
                z: 0.4,
                ..Vector3::default()
            },
            color,
            text: p.name.clone(),
            ..Marker::default()
        });
    }
    MarkerArray { markers }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use muster_sim_world::scenario::Scenario;

    #[test]
    fn a_scan_spans_the_field_of_view_counter_clockwise() {
        let mut world = World::new(&Scenario::paper(), None).unwrap();
        world.step_to(0.5);
        let r = &world.robots()[0];
        let params = r.spec.laser.clone().unwrap();
        let scan = laser_scan("T1", r, &params);
        assert_eq!(scan.ranges.len(), params.beams);
        assert!((f64::from(scan.angle_min) + params.fov_deg.to_radians() / 2.0).abs() < 1e-6);
        assert!((f64::from(scan.angle_max) - params.fov_deg.to_radians() / 2.0).abs() < 1e-6);
        let span = scan.angle_increment * (scan.ranges.len() - 1) as f32;
        assert!((span - (scan.angle_max - scan.angle_min)).abs() < 1e-5);
        assert_eq!(scan.header.frame_id, "T1/laser");
        // Every reading is a hit within range or a no-return (+inf), never the maximum.
        for (k, (&ros, &sim)) in scan.ranges.iter().zip(&r.laser).enumerate() {
            if f64::from(sim) >= params.range {
                assert_eq!(ros, f32::INFINITY, "beam {k}");
            } else {
                assert_eq!(ros, sim, "beam {k}");
            }
        }
    }

    #[test]
    fn the_grid_is_row_major_from_the_lower_left_corner() {
        let map = OccupancyMap::office();
        let g = occupancy_grid(&map, 0.0);
        assert_eq!(g.data.len(), map.width() * map.height());
        let (i, j) = (map.width() / 3, map.height() / 2);
        for (i, j) in [(0, 0), (i, j), (map.width() - 1, map.height() - 1)] {
            let v = g.data[j * map.width() + i];
            assert_eq!(v == 100, map.occupied(i as i64, j as i64), "cell {i},{j}");
        }
        // Some walls and some floor.
        assert!(g.data.contains(&100) && g.data.contains(&0));
    }
}
