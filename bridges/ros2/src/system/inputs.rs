//! Subscribed topics, each typed by its config and turned into muster payloads.

use crate::msgs::*;
use crate::node::Ros2Node;
use crate::Ros2Error;
use muster_shared::ros2msg::Definitions;
use muster_shared::types::{Payload, MAX_ENCODED};
use ros2_client::dds::rustdds::mio1;
use ros2_client::{QosProfile, Subscription};
use serde::de::DeserializeOwned;
use std::sync::Arc;
use std::time::Duration;

/// Most samples taken from one reader in one wake-up (the rest wait for the next).
const MAX_TAKE: usize = 1024;

trait Reader {
    /// Takes every waiting sample; converted ones go to `out`. Undecodable samples are
    /// counted on `node` and dropped.
    fn take_all(&self, node: &Ros2Node, topic: &str, out: &mut Vec<Payload>) -> usize;
    fn register(&mut self, registry: &mio1::Registry, token: mio1::Token) -> std::io::Result<()>;
}

struct Typed<M: 'static> {
    sub: Subscription<M>,
    convert: fn(&M) -> Option<Payload>,
}

impl<M: DeserializeOwned + 'static> Reader for Typed<M> {
    fn take_all(&self, node: &Ros2Node, topic: &str, out: &mut Vec<Payload>) -> usize {
        let mut taken = 0;
        for _ in 0..MAX_TAKE {
            match self.sub.take() {
                Ok(Some((m, _))) => {
                    taken += 1;
                    if let Some(p) = (self.convert)(&m) {
                        out.push(p);
                    }
                }
                Ok(None) => break,
                Err(e) => node.warn_limited(&format!("{topic}: sample dropped: {e}")),
            }
        }
        taken
    }

    fn register(&mut self, registry: &mio1::Registry, token: mio1::Token) -> std::io::Result<()> {
        mio1::event::Source::register(&mut self.sub, registry, token, mio1::Interest::READABLE)
    }
}

/// A ROS message read by its definition and kept as little-endian CDR (with its
/// encapsulation header), whatever byte order it came in.
#[derive(Clone)]
struct RawSeed(Arc<Definitions>);

impl<'de> serde::de::DeserializeSeed<'de> for RawSeed {
    type Value = Vec<u8>;
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<Vec<u8>, D::Error> {
        self.0.transcode(d)
    }
}

struct Raw {
    sub: Subscription<Vec<u8>>,
    seed: RawSeed,
    type_name: String,
}

impl Reader for Raw {
    fn take_all(&self, node: &Ros2Node, topic: &str, out: &mut Vec<Payload>) -> usize {
        let mut taken = 0;
        for _ in 0..MAX_TAKE {
            match self.sub.take_seed(self.seed.clone()) {
                Ok(Some((data, _))) => {
                    taken += 1;
                    if data.len() > MAX_ENCODED {
                        node.warn_limited(&format!(
                            "{topic}: a sample of {} bytes dropped: open payloads are at most {MAX_ENCODED} bytes",
                            data.len()
                        ));
                        continue;
                    }
                    out.push(Payload::Encoded {
                        type_name: self.type_name.clone(),
                        data,
                    });
                }
                Ok(None) => break,
                Err(e) => node.warn_limited(&format!("{topic}: sample dropped: {e}")),
            }
        }
        taken
    }

    fn register(&mut self, registry: &mio1::Registry, token: mio1::Token) -> std::io::Result<()> {
        mio1::event::Source::register(&mut self.sub, registry, token, mio1::Interest::READABLE)
    }
}

/// One subscribed topic.
pub struct TopicIn {
    /// Absolute topic name.
    pub topic: String,
    /// `pkg/msg/Type`.
    pub ros_type: String,
    /// Kept as the ROS message itself (an open payload), not converted.
    pub raw: bool,
    /// When the last sample came (runtime time).
    pub last_heard: Option<Duration>,
    /// The last sample, converted.
    pub latest: Option<Payload>,
    /// Set while the ROS graph has the topic under another type.
    pub mismatch: Option<String>,
    reader: Box<dyn Reader>,
}

fn planar(p: &Pose) -> Payload {
    Payload::Pose2d {
        x: p.position.x,
        y: p.position.y,
        theta: p.orientation.yaw(),
    }
}

fn typed<M: DeserializeOwned + 'static>(
    node: &mut Ros2Node,
    topic: &str,
    ty: RosTypeName,
    qos: QosProfile,
    convert: fn(&M) -> Option<Payload>,
) -> Result<Box<dyn Reader>, Ros2Error> {
    Ok(Box::new(Typed {
        sub: node.subscription::<M>(topic, (ty.0, ty.1), qos)?,
        convert,
    }))
}

type RosTypeName = (&'static str, &'static str);

impl TopicIn {
    /// Subscribes `topic` as `ros_type` (one of [`super::config::DATA_TYPES`] or
    /// [`super::config::POSE_TYPES`]).
    pub fn subscribe(
        node: &mut Ros2Node,
        topic: &str,
        ros_type: &str,
        qos: QosProfile,
    ) -> Result<Self, Ros2Error> {
        let reader = match ros_type {
            "nav_msgs/msg/Odometry" => {
                typed::<Odometry>(node, topic, ("nav_msgs", "Odometry"), qos, |m| {
                    Some(planar(&m.pose.pose))
                })?
            }
            "geometry_msgs/msg/PoseStamped" => {
                typed::<PoseStamped>(node, topic, ("geometry_msgs", "PoseStamped"), qos, |m| {
                    Some(planar(&m.pose))
                })?
            }
            "geometry_msgs/msg/PoseWithCovarianceStamped" => typed::<PoseWithCovarianceStamped>(
                node,
                topic,
                ("geometry_msgs", "PoseWithCovarianceStamped"),
                qos,
                |m| Some(planar(&m.pose.pose)),
            )?,
            "geometry_msgs/msg/Pose2D" => {
                typed::<Pose2D>(node, topic, ("geometry_msgs", "Pose2D"), qos, |m| {
                    Some(Payload::Pose2d {
                        x: m.x,
                        y: m.y,
                        theta: m.theta,
                    })
                })?
            }
            "std_msgs/msg/String" => {
                typed::<StringMsg>(node, topic, ("std_msgs", "String"), qos, |m| {
                    Some(Payload::Text(m.data.clone()))
                })?
            }
            "std_msgs/msg/Float64" => {
                typed::<Float64>(node, topic, ("std_msgs", "Float64"), qos, |m| {
                    Some(Payload::Scalar(m.data))
                })?
            }
            "std_msgs/msg/Float32" => {
                typed::<Float32>(node, topic, ("std_msgs", "Float32"), qos, |m| {
                    Some(Payload::Scalar(f64::from(m.data)))
                })?
            }
            "std_msgs/msg/Int32" => typed::<Int32>(node, topic, ("std_msgs", "Int32"), qos, |m| {
                Some(Payload::Scalar(f64::from(m.data)))
            })?,
            "std_msgs/msg/Int64" => typed::<Int64>(node, topic, ("std_msgs", "Int64"), qos, |m| {
                Some(Payload::Scalar(m.data as f64))
            })?,
            "std_msgs/msg/Bool" => typed::<Bool>(node, topic, ("std_msgs", "Bool"), qos, |m| {
                Some(Payload::Scalar(if m.data { 1.0 } else { 0.0 }))
            })?,
            other => {
                return Err(Ros2Error::Create {
                    what: format!("a subscription to {topic}"),
                    detail: format!("ROS type {other} is not supported"),
                })
            }
        };
        Ok(TopicIn {
            topic: topic.to_string(),
            ros_type: ros_type.to_string(),
            raw: false,
            last_heard: None,
            latest: None,
            mismatch: None,
            reader,
        })
    }

    /// Subscribes `topic` as `ros_type`, defined by `defs`: samples become open
    /// payloads (the message itself, as CDR).
    pub fn subscribe_raw(
        node: &mut Ros2Node,
        topic: &str,
        ros_type: &str,
        qos: QosProfile,
        defs: Arc<Definitions>,
    ) -> Result<Self, Ros2Error> {
        let (pkg, name) = split_type(ros_type);
        let sub = node.subscription_named::<Vec<u8>>(topic, pkg, name, qos)?;
        Ok(TopicIn {
            topic: topic.to_string(),
            ros_type: ros_type.to_string(),
            raw: true,
            last_heard: None,
            latest: None,
            mismatch: None,
            reader: Box::new(Raw {
                sub,
                seed: RawSeed(defs),
                type_name: ros_type.to_string(),
            }),
        })
    }

    /// Registers the reader with an epoll set.
    pub fn register(
        &mut self,
        registry: &mio1::Registry,
        token: mio1::Token,
    ) -> std::io::Result<()> {
        self.reader.register(registry, token)
    }

    /// Takes every waiting sample into `out`; true if any came (even undecodable ones:
    /// the robot is alive).
    pub fn drain(&mut self, node: &Ros2Node, now: Duration, out: &mut Vec<Payload>) -> bool {
        let before = out.len();
        let taken = self.reader.take_all(node, &self.topic, out);
        if let Some(p) = out[before..].last() {
            self.latest = Some(p.clone());
        }
        if taken > 0 {
            self.last_heard = Some(now);
        }
        taken > 0
    }
}

/// `pkg/msg/Type` as (`pkg`, `Type`).
fn split_type(t: &str) -> (&str, &str) {
    let pkg = t.split('/').next().unwrap_or("");
    let name = t.rsplit('/').next().unwrap_or("");
    (pkg, name)
}
