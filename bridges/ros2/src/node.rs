//! One ROS 2 node on `ros2-client` (pure-Rust DDS, no ROS install): topics by name and
//! type, publishers that never stall their caller, and errors counted instead of
//! fatal.

use crate::Ros2Error;
use ros2_client::qos::{Durability, History, Reliability, WhenFull};
use ros2_client::{
    Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher,
    QosProfile, Subscription,
};
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::cell::Cell;

/// A ROS message type: (package, name), e.g. `("sensor_msgs", "LaserScan")`.
pub type RosType = (&'static str, &'static str);

/// Reliable, volatile, keep-last `depth`: matches reliable and best-effort subscribers
/// alike. A full send window drops the sample at once (the caller is a real-time loop:
/// a slow subscriber loses samples, it never stalls the world).
pub fn qos_reliable(depth: usize) -> QosProfile {
    QosProfile::publisher_default()
        .reliability(Reliability::Reliable {
            when_full: WhenFull::Fail,
        })
        .durability(Durability::Volatile)
        .history(History::KeepLast {
            depth: depth.max(1),
        })
}

/// Reliable and transient-local, keep-last 1: a late subscriber gets the last sample
/// (the `/map` and `/tf_static` convention).
pub fn qos_latched() -> QosProfile {
    qos_reliable(1).durability(Durability::TransientLocal)
}

/// Best-effort, volatile, keep-last `depth`, for what muster takes in: matches best-effort
/// and reliable publishers alike.
pub fn qos_sensor_in(depth: usize) -> QosProfile {
    QosProfile::subscription_default()
        .reliability(Reliability::BestEffort)
        .history(History::KeepLast {
            depth: depth.max(1),
        })
}

/// A node in one ROS domain.
pub struct Ros2Node {
    // The node keeps its context alive; both are dropped together.
    node: Node,
    context: Context,
    errors: Cell<u64>,
    /// Errors per kind (the text before its first `:`, e.g. the topic), for the log.
    kinds: std::cell::RefCell<std::collections::HashMap<String, u64>>,
}

impl Ros2Node {
    /// Joins domain `domain` as node `namespace/name`.
    pub fn new(domain: u16, namespace: &str, name: &str) -> Result<Self, Ros2Error> {
        if domain > 232 {
            return Err(Ros2Error::Domain(domain));
        }
        let context = Context::with_options(ContextOptions::new().domain_id(domain))
            .map_err(|e| Ros2Error::create("ROS 2 context", e))?;
        let node_name =
            NodeName::new(namespace, name).map_err(|e| Ros2Error::create("node name", e))?;
        let node = context
            .new_node(node_name, NodeOptions::new().enable_rosout(true))
            .map_err(|e| Ros2Error::create("ROS 2 node", e))?;
        Ok(Ros2Node {
            node,
            context,
            errors: Cell::new(0),
            kinds: Default::default(),
        })
    }

    fn topic(
        &mut self,
        name: &str,
        pkg: &str,
        ty: &str,
        qos: &QosProfile,
    ) -> Result<ros2_client::dds::rustdds::Topic, Ros2Error> {
        let parsed = Name::parse(name).map_err(|e| Ros2Error::create(name, e))?;
        self.node
            .create_topic(&parsed, MessageTypeName::new(pkg, ty), qos)
            .map_err(|e| Ros2Error::create(name, e))
    }

    /// A publisher of `ty` on topic `name` (absolute, e.g. `/T1/scan`).
    pub fn publisher<M: Serialize>(
        &mut self,
        name: &str,
        ty: RosType,
        qos: QosProfile,
    ) -> Result<Publisher<M>, Ros2Error> {
        let topic = self.topic(name, ty.0, ty.1, &qos)?;
        self.node
            .create_publisher(&topic, Some(qos))
            .map_err(|e| Ros2Error::create(name, e))
    }

    /// A subscription to `ty` on topic `name`.
    pub fn subscription<M: DeserializeOwned + 'static>(
        &mut self,
        name: &str,
        ty: RosType,
        qos: QosProfile,
    ) -> Result<Subscription<M>, Ros2Error> {
        let topic = self.topic(name, ty.0, ty.1, &qos)?;
        self.node
            .create_subscription(&topic, Some(qos))
            .map_err(|e| Ros2Error::create(name, e))
    }

    /// A publisher of type `pkg/msg/name` on topic `topic`, for a type known only at run
    /// time.
    pub fn publisher_named<M: Serialize>(
        &mut self,
        topic: &str,
        pkg: &str,
        name: &str,
        qos: QosProfile,
    ) -> Result<Publisher<M>, Ros2Error> {
        let t = self.topic(topic, pkg, name, &qos)?;
        self.node
            .create_publisher(&t, Some(qos))
            .map_err(|e| Ros2Error::create(topic, e))
    }

    /// A subscription to type `pkg/msg/name` on topic `name`, for a type known only at
    /// run time (read with `take_seed`).
    pub fn subscription_named<M: 'static>(
        &mut self,
        topic: &str,
        pkg: &str,
        name: &str,
        qos: QosProfile,
    ) -> Result<Subscription<M>, Ros2Error> {
        let t = self.topic(topic, pkg, name, &qos)?;
        self.node
            .create_subscription(&t, Some(qos))
            .map_err(|e| Ros2Error::create(topic, e))
    }

    /// Publishes `msg`; a failure (a full send window, a closed writer) is counted and
    /// logged now and then, never returned: one lost sample must not stop a robot.
    pub fn send<M: Serialize>(&self, p: &Publisher<M>, msg: M, what: &str) {
        if let Err(e) = p.publish(msg) {
            let e = match e {
                ros2_client::WriteError::WouldBlock { .. } => "send window full".to_string(),
                other => other.to_string(),
            };
            self.warn_limited(&format!("{what}: sample not sent: {e}"));
        }
    }

    /// Counts an error and logs the first of its kind and then every 1000th.
    pub fn warn_limited(&self, what: &str) {
        self.errors.set(self.errors.get() + 1);
        // Counted per kind, so one noisy topic does not hide another's first error.
        let kind = what.split(':').next().unwrap_or(what);
        let mut kinds = self.kinds.borrow_mut();
        // At most 256 kinds are told apart; the rest share one count.
        let key = if kinds.contains_key(kind) || kinds.len() < 256 {
            kind
        } else {
            ""
        };
        let n = kinds.entry(key.to_string()).or_default();
        *n += 1;
        if *n == 1 || n.is_multiple_of(1000) {
            tracing::warn!(errors = *n, "ROS 2: {what}");
        }
    }

    /// Errors counted so far.
    pub fn errors(&self) -> u64 {
        self.errors.get()
    }

    /// The ROS types (`pkg/msg/Type`) DDS discovery has seen on topic `name` (e.g.
    /// `/turtle/odom`), from every participant, this one included.
    pub fn discovered_types(&self, name: &str) -> Vec<String> {
        let dds = format!("rt{name}");
        let mut types: Vec<String> = self
            .context
            .discovered_topics()
            .into_iter()
            .filter(|t| t.name == dds)
            .map(|t| ros_type_of_dds(&t.type_name))
            .collect();
        types.sort();
        types.dedup();
        types
    }
}

/// A DDS type name (`nav_msgs::msg::dds_::Odometry_`) as ROS writes it
/// (`nav_msgs/msg/Odometry`); other names unchanged.
pub fn ros_type_of_dds(t: &str) -> String {
    match t.split("::").collect::<Vec<_>>()[..] {
        [pkg, kind, "dds_", name] => {
            format!("{pkg}/{kind}/{}", name.strip_suffix('_').unwrap_or(name))
        }
        _ => t.to_string(),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn dds_type_names_read_as_ros_types() {
        assert_eq!(
            super::ros_type_of_dds("nav_msgs::msg::dds_::Odometry_"),
            "nav_msgs/msg/Odometry"
        );
        assert_eq!(super::ros_type_of_dds("odd"), "odd");
    }
}
