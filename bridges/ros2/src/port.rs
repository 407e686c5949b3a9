//! A ROS 2 robot as a port of muster's robot systems ([`RobotPort`]): its `scan`
//! (`sensor_msgs/LaserScan`), `odom` (`nav_msgs/Odometry`) and, where offered,
//! `ground_truth`, `sonar` (`sensor_msgs/Range`, frame `…/sonar_K` for transducer K),
//! `beacons` and `ptz` (the camera's sightings and pointing, as `muster sim --ros2`
//! publishes them: see [`crate::sim`]) are read; `cmd_vel` (`geometry_msgs/Twist`)
//! drives it and `ptz_cmd` (`geometry_msgs/Vector3`) points its camera. The paper's
//! delivery and tracking systems run on any robot that offers these (`muster system
//! delivery --ros2`, `muster system tracking --ros2`), the simulator bridged to ROS 2
//! among them, with no shared memory between them.

use crate::msgs::{LaserScan, MarkerArray, Odometry, Range, Time, Twist, Vector3, Vector3Stamped};
use crate::node::{qos_reliable, qos_sensor_in, Ros2Node};
use crate::Ros2Error;
use muster_robots::port::{PortError, RobotPort};
use muster_robots::sensing::{SensorSample, Sighting};
use muster_sim_world::kinematics::Pose;
use muster_sim_world::scenario::Colour;
use ros2_client::dds::rustdds::mio1;
use ros2_client::{Publisher, Subscription};
use std::os::fd::{AsRawFd, RawFd};

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
    // Last: readers and writers leave the DDS participant before it closes.
    node: Ros2Node,
}

impl Ros2Port {
    /// Joins domain `domain` as node `/muster/<name>` and subscribes the robot in
    /// `namespace` (e.g. `/D1`).
    pub fn new(domain: u16, namespace: &str, name: &str) -> Result<Self, Ros2Error> {
        let mut node = Ros2Node::new(domain, "/muster", &crate::ros_name(name))?;
        let ns = namespace.trim_end_matches('/');
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
        tracing::info!(domain, namespace, "robot port on ROS 2");
        Ok(Ros2Port {
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
            node,
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
