//! muster and ROS 2, on `ros2-client` (Atostek's pure-Rust DDS: no ROS install, no C++
//! build): the simulator's robots as ROS 2 topics ([`sim::SimBridge`]), and a ROS 2
//! robot as a muster system with no code ([`system::Ros2System`]).
//!
//! The messages are serde structs in their definitions' field order ([`msgs`]), so their
//! CDR bytes are what rclpy and Fast DDS send.

pub mod definitions;
pub mod msgs;
pub mod node;
pub mod port;
pub mod sim;
pub mod system;

/// Why joining ROS 2 failed.
#[derive(Debug, thiserror::Error)]
pub enum Ros2Error {
    /// A DDS participant, node, topic, publisher or subscription could not be made
    /// (ports taken, a bad name); the detail says which and why.
    #[error("ROS 2: could not create {what}: {detail}")]
    Create {
        /// What was being made.
        what: String,
        /// The library's reason.
        detail: String,
    },
    /// ROS domain ids run 0..=232 (the DDS port mapping's range); pick one there.
    #[error("ROS domain id {0} is out of range: use 0..=232")]
    Domain(u16),
    /// A robot could not be described: a topic that did not come, a bad parameter file.
    #[error("ROS 2: {0}")]
    Robot(String),
}

impl Ros2Error {
    fn create(what: &str, e: impl std::fmt::Debug) -> Self {
        Ros2Error::Create {
            what: what.to_string(),
            detail: format!("{e:?}"),
        }
    }
}

/// The ROS domain id from `ROS_DOMAIN_ID`, if set and valid.
pub fn domain_from_env() -> Option<u16> {
    std::env::var("ROS_DOMAIN_ID")
        .ok()?
        .trim()
        .parse()
        .ok()
        .filter(|d| *d <= 232)
}

/// A muster name (robot, system, service) as a ROS name token: `[A-Za-z0-9_]`, not
/// starting with a digit, no doubled or trailing underscores.
pub fn ros_name(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 1);
    for c in s.chars() {
        let c = if c.is_ascii_alphanumeric() { c } else { '_' };
        if c == '_' && (out.is_empty() || out.ends_with('_')) {
            continue;
        }
        out.push(c);
    }
    while out.ends_with('_') {
        out.pop();
    }
    if out.is_empty() || out.starts_with(|c: char| c.is_ascii_digit()) {
        out.insert(0, 'r');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_become_ros_tokens() {
        assert_eq!(ros_name("T1"), "T1");
        assert_eq!(ros_name("d-1.x"), "d_1_x");
        assert_eq!(ros_name("9lives"), "r9lives");
        assert_eq!(ros_name("__a--b__"), "a_b");
        assert_eq!(ros_name(""), "r");
    }
}
