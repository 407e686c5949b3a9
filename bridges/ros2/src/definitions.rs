//! ROS 2 message definitions: the built-in common types (compiled in from `msg/`) and
//! any a config adds, assembled into the `ros2msg` schema MCAP, Foxglove and muster's
//! users read (the root type's text, then each type it uses after a `====` line and
//! `MSG: pkg/Type`).

use muster_shared::ros2msg::{full_name, parse_fields, Base, Definitions, Ros2MsgError};
use std::collections::BTreeMap;

include!(concat!(env!("OUT_DIR"), "/builtin_msgs.rs"));

/// The line between a definition's types.
const SEPARATOR: &str =
    "================================================================================";

/// Every definition muster knows: (`pkg/msg/Type` → `.msg` text).
#[derive(Clone, Debug)]
pub struct Library {
    texts: BTreeMap<String, String>,
}

impl Default for Library {
    fn default() -> Self {
        Library {
            texts: BUILTIN
                .iter()
                .map(|(t, text)| ((*t).to_string(), (*text).to_string()))
                .collect(),
        }
    }
}

impl Library {
    /// Adds (or replaces) the definition of `ty` (`pkg/msg/Type` or `pkg/Type`).
    pub fn add(&mut self, ty: &str, text: &str) {
        self.texts.insert(full_name(ty, ""), text.to_string());
    }

    /// Whether `ty` is known.
    pub fn has(&self, ty: &str) -> bool {
        self.texts.contains_key(&full_name(ty, ""))
    }

    /// The `ros2msg` schema of `ty` with every type it uses, checked by parsing it.
    pub fn schema(&self, ty: &str) -> Result<String, Ros2MsgError> {
        let root = full_name(ty, "");
        let mut out = String::new();
        let mut done = Vec::new();
        let mut todo = vec![root.clone()];
        while let Some(t) = todo.pop() {
            if done.contains(&t) {
                continue;
            }
            let text = self.texts.get(&t).ok_or_else(|| {
                Ros2MsgError::Definition(format!(
                    "no definition of {t}: name its .msg file in the config's [[definition]]"
                ))
            })?;
            if t != root {
                let short = t.replacen("/msg/", "/", 1);
                out.push_str(&format!("{SEPARATOR}\nMSG: {short}\n"));
            }
            out.push_str(text);
            if !text.ends_with('\n') {
                out.push('\n');
            }
            // Its own fields' message types, in the order they appear.
            let pkg = t.split('/').next().unwrap_or("");
            let mut uses: Vec<String> = Vec::new();
            for f in parse_fields(text, pkg)? {
                if let Base::Msg(m) = f.base {
                    if !uses.contains(&m) {
                        uses.push(m);
                    }
                }
            }
            done.push(t);
            for u in uses.into_iter().rev() {
                todo.push(u);
            }
        }
        Definitions::parse(&root, &out)?;
        Ok(out)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::msgs;

    fn cdr<T: serde::Serialize>(v: &T) -> Vec<u8> {
        let mut b = vec![0, 1, 0, 0];
        b.extend(cdr_encoding::to_vec::<T, byteorder::LittleEndian>(v).unwrap());
        b
    }

    #[test]
    fn the_common_types_are_built_in_with_their_dependencies() {
        let lib = Library::default();
        let s = lib.schema("sensor_msgs/msg/LaserScan").unwrap();
        assert!(s.starts_with("std_msgs/Header header\n"), "{s}");
        assert!(s.contains("MSG: std_msgs/Header\n"), "{s}");
        assert!(s.contains("MSG: builtin_interfaces/Time\n"), "{s}");
        assert_eq!(s.matches("MSG: ").count(), 2);
        for ty in [
            "nav_msgs/msg/Odometry",
            "visualization_msgs/msg/MarkerArray",
            "sensor_msgs/msg/PointCloud2",
            "nav_msgs/msg/OccupancyGrid",
            "sensor_msgs/BatteryState",
        ] {
            let s = lib.schema(ty).unwrap();
            assert!(
                s.len() <= muster_shared::types::MAX_SCHEMA,
                "{ty}: {} bytes",
                s.len()
            );
        }
        let e = lib.schema("my_pkg/msg/Nope").unwrap_err().to_string();
        assert!(e.contains("no definition of my_pkg/msg/Nope"), "{e}");
    }

    #[test]
    fn built_in_schemas_read_what_the_serde_messages_write() {
        let lib = Library::default();
        let scan = msgs::LaserScan {
            header: msgs::Header::at(2.5, "T1/laser"),
            angle_min: -1.5,
            angle_max: 1.5,
            angle_increment: 1.5,
            time_increment: 0.0,
            scan_time: 0.1,
            range_min: 0.0,
            range_max: 8.0,
            ranges: vec![1.0, f32::INFINITY, 3.25],
            intensities: vec![],
        };
        let d = Definitions::parse(
            "sensor_msgs/msg/LaserScan",
            &lib.schema("sensor_msgs/msg/LaserScan").unwrap(),
        )
        .unwrap();
        let v = d.decode(&cdr(&scan)).unwrap();
        assert_eq!(v["header"]["frame_id"], "T1/laser");
        assert_eq!(v["header"]["stamp"]["sec"], 2);
        assert_eq!(v["header"]["stamp"]["nanosec"], 500_000_000);
        assert_eq!(v["ranges"], serde_json::json!([1.0, "inf", 3.25]));
        assert_eq!(v["range_max"], 8.0);

        let odom = msgs::Odometry {
            header: msgs::Header::at(1.0, "odom"),
            child_frame_id: "base_link".into(),
            pose: msgs::PoseWithCovariance {
                pose: msgs::Pose::planar(1.0, 2.0, 0.5),
                covariance: msgs::Covariance::diagonal([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
            },
            twist: msgs::TwistWithCovariance {
                twist: msgs::Twist::default(),
                covariance: msgs::Covariance::diagonal([0.0; 6]),
            },
        };
        let d = Definitions::parse(
            "nav_msgs/Odometry",
            &lib.schema("nav_msgs/Odometry").unwrap(),
        )
        .unwrap();
        let v = d.decode(&cdr(&odom)).unwrap();
        assert_eq!(v["pose"]["pose"]["position"]["y"], 2.0);
        assert_eq!(v["pose"]["covariance"][7], 2.0);
        assert_eq!(v["pose"]["covariance"].as_array().unwrap().len(), 36);
        assert_eq!(v["child_frame_id"], "base_link");
        // The transcoder, walking the CDR reader, writes the same bytes back.
        let bytes = cdr(&odom);
        let mut de = cdr_encoding::CdrDeserializer::<byteorder::LittleEndian>::new(&bytes[4..]);
        assert_eq!(d.transcode(&mut de).unwrap(), bytes);
        // And a sample held as bytes, walked into the CDR writer, is the same message.
        let raw = msgs::RawMsg {
            defs: std::sync::Arc::new(d),
            data: bytes.clone(),
        };
        assert_eq!(cdr(&raw), bytes);
    }
}
