//! The file that makes a ROS 2 robot a muster system: which topics become which
//! services (`muster system ros2 --config robot.toml`).
//!
//! ```toml
//! system = "turtle"          # the muster system's name
//! namespace = "/turtle"      # relative topic names resolve under it (default "/")
//! silent_after = "2s"        # liveness: a watched topic unheard this long withdraws the robot
//!
//! [[data]]                   # a subscribed topic streamed to users
//! name = "pose"
//! topic = "odom"
//! type = "nav_msgs/msg/Odometry"
//! quota = 10                 # default 10; also description, queue, qos, latched
//!
//! [[command]]                # a goal published for the robot's navigation
//! name = "goal"
//! payload = "goal2d"         # goal2d: geometry_msgs/PoseStamped; twist: geometry_msgs/Twist
//! topic = "goal_pose"
//! pose_topic = "odom"        # where the status comes from (distance, ETA, blocked, arrived)
//! tolerance = 1.0
//!
//! [[command]]
//! name = "drive"
//! payload = "twist"
//! topic = "cmd_vel"          # zero velocity when input stops for the deadman time
//! ```

use crate::definitions::Library;
use muster_shared::types::{
    validate_registration, Schema, SchemaEncoding, ServiceKind, ServiceSpec, SpecError,
};
use serde::Deserialize;
use std::time::Duration;

/// Why a config file is unusable.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The TOML does not parse into a config; the text says where.
    #[error("{path}: {detail}")]
    Toml {
        /// The file.
        path: String,
        /// The parser's words.
        detail: String,
    },
    /// A value is out of range or unsupported; the text says which and what to use.
    #[error("{0}")]
    Invalid(String),
    /// The services it declares break muster's registration rules.
    #[error("{0}")]
    Spec(#[from] SpecError),
}

/// The ROS QoS of one topic; every field defaults to ROS's default profile
/// (reliable, volatile, keep-last 10).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TopicQos {
    /// `reliable` (default) or `best_effort`.
    #[serde(default)]
    pub reliability: Option<String>,
    /// `volatile` (default) or `transient_local`.
    #[serde(default)]
    pub durability: Option<String>,
    /// Keep-last depth (default 10).
    #[serde(default)]
    pub depth: Option<usize>,
}

/// A data service: a subscribed topic.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DataService {
    /// Service name.
    pub name: String,
    /// Topic (relative to the namespace, or absolute).
    pub topic: String,
    /// ROS type, `pkg/msg/Type` (or `pkg/Type`).
    #[serde(rename = "type")]
    pub ros_type: String,
    /// What users get: `ros` (the ROS message itself, an open payload: its definition
    /// travels as the schema, samples as CDR), or the built-in payload the type fits
    /// (`pose2d`, `text`, `scalar`). Default: the built-in one where the type fits one,
    /// else `ros`.
    #[serde(default)]
    pub payload: Option<String>,
    /// One line for the menu (default: says the topic and type).
    #[serde(default)]
    pub description: Option<String>,
    /// Sessions at once (default 10).
    #[serde(default = "ten")]
    pub quota: u16,
    /// Whether requests past the quota wait in a queue.
    #[serde(default)]
    pub queue: bool,
    /// The subscription's QoS.
    #[serde(default)]
    pub qos: TopicQos,
    /// Whether the service is latched (`SystemCore::latch`): every sample goes to the
    /// broker, with or without sessions, and a new session gets the newest with its
    /// grant. Default: when the topic is `transient_local` (a ROS topic sent once or on
    /// change, such as a map or a status, which a late subscriber gets at once: so does
    /// a late muster user). A latched topic is not watched for liveness unless `watch`
    /// names it: it is quiet by nature.
    #[serde(default)]
    pub latched: Option<bool>,
}

impl DataService {
    /// Whether the service is latched: as set, else when its topic is transient-local.
    pub fn is_latched(&self) -> bool {
        self.latched
            .unwrap_or(self.qos.durability.as_deref() == Some("transient_local"))
    }
}

/// What a command service takes and publishes.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum CommandPayload {
    /// `goal2d` → `geometry_msgs/PoseStamped` (the `/goal_pose` convention of RViz and
    /// Nav2), with status from the robot's pose.
    Goal2d,
    /// `twist` → `geometry_msgs/Twist` (`cmd_vel`), with a deadman.
    Twist,
    /// The ROS message itself (`type`): an open payload a user or a link sends, published
    /// as it comes.
    Ros,
}

/// A command service: a published topic.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CommandService {
    /// Service name.
    pub name: String,
    /// `goal2d`, `twist` or `ros`.
    pub payload: CommandPayload,
    /// ros: the ROS type published (`pkg/msg/Type`).
    #[serde(default, rename = "type")]
    pub ros_type: Option<String>,
    /// Topic (default `goal_pose` for goal2d, `cmd_vel` for twist).
    #[serde(default)]
    pub topic: Option<String>,
    /// One line for the menu.
    #[serde(default)]
    pub description: Option<String>,
    /// Sessions at once (default 1).
    #[serde(default = "one")]
    pub quota: u16,
    /// Whether requests past the quota wait in a queue (default: yes for goal2d).
    #[serde(default)]
    pub queue: Option<bool>,
    /// goal2d: the frame goals are in (default `map`).
    #[serde(default)]
    pub frame: Option<String>,
    /// goal2d: the topic of the robot's pose, for status (Odometry, PoseStamped or
    /// PoseWithCovarianceStamped; default `odom`).
    #[serde(default)]
    pub pose_topic: Option<String>,
    /// goal2d: the pose topic's type (default `nav_msgs/msg/Odometry`).
    #[serde(default)]
    pub pose_type: Option<String>,
    /// goal2d: arrived within this many metres (default 1, the paper's).
    #[serde(default)]
    pub tolerance: Option<f64>,
    /// goal2d: no progress this long reports "blocked" (default 5 s).
    #[serde(default, with = "opt_duration")]
    pub blocked_after: Option<Duration>,
    /// twist: zero velocity when input stops this long (default: `--deadman`, 0.5 s).
    #[serde(default, with = "opt_duration")]
    pub deadman: Option<Duration>,
    /// The publisher's QoS.
    #[serde(default)]
    pub qos: TopicQos,
}

/// A message type the config defines (beyond the built-in common ones).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Definition {
    /// Its name, `pkg/msg/Type`.
    #[serde(rename = "type")]
    pub ros_type: String,
    /// Its `.msg` file (relative to the config file).
    pub file: std::path::PathBuf,
}

/// The whole file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2SystemConfig {
    /// The muster system's name.
    pub system: String,
    /// Namespace for relative topic names (default `/`).
    #[serde(default)]
    pub namespace: Option<String>,
    /// A watched topic unheard this long withdraws every service until it is heard
    /// again (default 2 s).
    #[serde(default, with = "opt_duration")]
    pub silent_after: Option<Duration>,
    /// Topics watched for liveness (default: every subscribed topic but those only
    /// latched services take).
    #[serde(default)]
    pub watch: Option<Vec<String>>,
    /// Data services.
    #[serde(default)]
    pub data: Vec<DataService>,
    /// Command services.
    #[serde(default)]
    pub command: Vec<CommandService>,
    /// Message types defined by `.msg` files.
    #[serde(default)]
    pub definition: Vec<Definition>,
    /// Every definition known: the built-in ones and the file's.
    #[serde(skip)]
    pub library: Library,
}

/// How a data service's samples reach users.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DataPayload {
    /// Converted to this built-in payload.
    Builtin(&'static str),
    /// The ROS message itself, with this `ros2msg` schema.
    Ros(String),
}

fn ten() -> u16 {
    10
}
fn one() -> u16 {
    1
}

mod opt_duration {
    use serde::Deserialize;
    use std::time::Duration;

    pub fn deserialize<'de, D: serde::Deserializer<'de>>(
        d: D,
    ) -> Result<Option<Duration>, D::Error> {
        let s: Option<String> = Option::deserialize(d)?;
        s.map(|s| humantime::parse_duration(&s).map_err(serde::de::Error::custom))
            .transpose()
    }
}

/// The ROS types a data service can stream today, and the built-in payload each becomes.
pub const DATA_TYPES: &[(&str, &str)] = &[
    ("nav_msgs/msg/Odometry", "pose2d"),
    ("geometry_msgs/msg/PoseStamped", "pose2d"),
    ("geometry_msgs/msg/PoseWithCovarianceStamped", "pose2d"),
    ("geometry_msgs/msg/Pose2D", "pose2d"),
    ("std_msgs/msg/String", "text"),
    ("std_msgs/msg/Float64", "scalar"),
    ("std_msgs/msg/Float32", "scalar"),
    ("std_msgs/msg/Int32", "scalar"),
    ("std_msgs/msg/Int64", "scalar"),
    ("std_msgs/msg/Bool", "scalar"),
];

/// The pose types a goal2d service's status can follow.
pub const POSE_TYPES: &[&str] = &[
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
];

/// `pkg/Type` or `pkg/msg/Type` as `pkg/msg/Type`.
pub fn full_type(t: &str) -> String {
    match t.split('/').collect::<Vec<_>>()[..] {
        [pkg, name] => format!("{pkg}/msg/{name}"),
        _ => t.to_string(),
    }
}

/// A topic name resolved against `namespace`.
pub fn resolve(namespace: &str, topic: &str) -> String {
    if topic.starts_with('/') {
        topic.to_string()
    } else {
        format!("{}/{topic}", namespace.trim_end_matches('/'))
    }
}

impl Ros2SystemConfig {
    /// Reads and checks a config file; its `[[definition]]` files are read relative to
    /// it.
    pub fn load(path: &std::path::Path) -> Result<Self, ConfigError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: p.clone(),
            source,
        })?;
        let dir = path.parent().unwrap_or(std::path::Path::new("."));
        Self::parse_in(&text, dir).map_err(|e| match e {
            ConfigError::Toml { detail, .. } => ConfigError::Toml { path: p, detail },
            other => other,
        })
    }

    /// Parses and checks a config's text (definition files relative to the working
    /// directory).
    pub fn parse(text: &str) -> Result<Self, ConfigError> {
        Self::parse_in(text, std::path::Path::new("."))
    }

    fn parse_in(text: &str, dir: &std::path::Path) -> Result<Self, ConfigError> {
        let mut c: Ros2SystemConfig = toml::from_str(text).map_err(|e| ConfigError::Toml {
            path: String::new(),
            detail: e.to_string(),
        })?;
        for d in &c.definition {
            let path = dir.join(&d.file);
            let text = std::fs::read_to_string(&path).map_err(|source| ConfigError::Io {
                path: path.display().to_string(),
                source,
            })?;
            c.library.add(&d.ros_type, &text);
        }
        c.check()?;
        Ok(c)
    }

    /// The `ros2msg` schema of type `t`, within muster's limit.
    fn command_schema(&self, service: &str, t: &str) -> Result<String, ConfigError> {
        let t = full_type(t);
        let schema = self
            .library
            .schema(&t)
            .map_err(|e| ConfigError::Invalid(format!("service {service:?}: {e}")))?;
        if schema.len() > muster_shared::types::MAX_SCHEMA {
            return Err(ConfigError::Invalid(format!(
                "service {service:?}: the definition of {t} is {} bytes, at most {}",
                schema.len(),
                muster_shared::types::MAX_SCHEMA
            )));
        }
        Ok(schema)
    }

    /// What data service `d` sends its users.
    pub fn data_payload(&self, d: &DataService) -> Result<DataPayload, ConfigError> {
        let t = full_type(&d.ros_type);
        let fits = DATA_TYPES.iter().find(|(ty, _)| *ty == t).map(|(_, p)| *p);
        match (d.payload.as_deref(), fits) {
            (None, Some(p)) => Ok(DataPayload::Builtin(p)),
            (Some(p), Some(f)) if p == f => Ok(DataPayload::Builtin(f)),
            (None | Some("ros"), _) => {
                let schema = self
                    .library
                    .schema(&t)
                    .map_err(|e| ConfigError::Invalid(format!("data service {:?}: {e}", d.name)))?;
                if schema.len() > muster_shared::types::MAX_SCHEMA {
                    return Err(ConfigError::Invalid(format!(
                        "data service {:?}: the definition of {t} is {} bytes, at most {}",
                        d.name,
                        schema.len(),
                        muster_shared::types::MAX_SCHEMA
                    )));
                }
                Ok(DataPayload::Ros(schema))
            }
            (Some(p), _) => Err(ConfigError::Invalid(format!(
                "data service {:?}: {t} cannot be offered as {p}: use ros{}",
                d.name,
                fits.map_or(String::new(), |f| format!(" or {f}"))
            ))),
        }
    }

    /// The namespace, `/` if none.
    pub fn namespace(&self) -> String {
        let ns = self.namespace.clone().unwrap_or_else(|| "/".into());
        if ns.starts_with('/') {
            ns
        } else {
            format!("/{ns}")
        }
    }

    /// The liveness timeout.
    pub fn silent_after(&self) -> Duration {
        self.silent_after.unwrap_or(Duration::from_secs(2))
    }

    fn check(&self) -> Result<(), ConfigError> {
        if self.data.is_empty() && self.command.is_empty() {
            return Err(ConfigError::Invalid(
                "the config declares no [[data]] and no [[command]] service".into(),
            ));
        }
        for d in &self.data {
            self.data_payload(d)?;
            check_qos(&d.name, &d.qos)?;
        }
        for c in &self.command {
            match (c.payload, &c.ros_type) {
                (CommandPayload::Ros, None) => {
                    return Err(ConfigError::Invalid(format!(
                        "command service {:?}: payload \"ros\" needs the type it publishes",
                        c.name
                    )))
                }
                (CommandPayload::Ros, Some(t)) => {
                    if c.topic.is_none() {
                        return Err(ConfigError::Invalid(format!(
                            "command service {:?}: payload \"ros\" needs a topic",
                            c.name
                        )));
                    }
                    self.command_schema(&c.name, t)?;
                }
                (_, Some(_)) => {
                    return Err(ConfigError::Invalid(format!(
                        "command service {:?}: type is for payload \"ros\"",
                        c.name
                    )))
                }
                _ => {}
            }
            if let Some(t) = &c.pose_type {
                if !POSE_TYPES.contains(&full_type(t).as_str()) {
                    return Err(ConfigError::Invalid(format!(
                        "command service {:?}: pose_type {t} is not one of {}",
                        c.name,
                        POSE_TYPES.join(", ")
                    )));
                }
            }
            if let Some(t) = c.tolerance {
                if !(t.is_finite() && t > 0.0) {
                    return Err(ConfigError::Invalid(format!(
                        "command service {:?}: tolerance must be > 0 m",
                        c.name
                    )));
                }
            }
            if c.deadman.is_some_and(|d| d.is_zero()) {
                return Err(ConfigError::Invalid(format!(
                    "command service {:?}: deadman must be > 0",
                    c.name
                )));
            }
            check_qos(&c.name, &c.qos)?;
        }
        if self.silent_after().is_zero() {
            return Err(ConfigError::Invalid("silent_after must be > 0".into()));
        }
        validate_registration(&self.system, &self.specs())?;
        Ok(())
    }

    /// The services as muster registers them.
    pub fn specs(&self) -> Vec<ServiceSpec> {
        let ns = self.namespace();
        let mut specs = Vec::new();
        for d in &self.data {
            let t = full_type(&d.ros_type);
            let (payload, schema) = match self.data_payload(d) {
                Ok(DataPayload::Builtin(p)) => (p.to_string(), None),
                Ok(DataPayload::Ros(text)) => (
                    t.clone(),
                    Some(Schema {
                        encoding: SchemaEncoding::Ros2Msg,
                        text,
                    }),
                ),
                // Refused by check() already.
                Err(_) => continue,
            };
            specs.push(ServiceSpec {
                name: d.name.clone(),
                description: d
                    .description
                    .clone()
                    .unwrap_or_else(|| short(format!("ROS 2 {} ({t})", resolve(&ns, &d.topic)))),
                kind: ServiceKind::Data,
                queue: d.queue,
                quota: d.quota,
                payload,
                schema,
            });
        }
        for c in &self.command {
            let ros = c.ros_type.as_deref().map(full_type);
            let (payload, topic, ty) = match (c.payload, &ros) {
                (CommandPayload::Goal2d, _) => {
                    ("goal2d".to_string(), "goal_pose", "PoseStamped".to_string())
                }
                (CommandPayload::Twist, _) => ("twist".to_string(), "cmd_vel", "Twist".to_string()),
                (CommandPayload::Ros, Some(t)) => (t.clone(), "", t.clone()),
                // Refused by check() already.
                (CommandPayload::Ros, None) => continue,
            };
            let schema = match &ros {
                Some(t) if c.payload == CommandPayload::Ros => {
                    match self.command_schema(&c.name, t) {
                        Ok(text) => Some(Schema {
                            encoding: SchemaEncoding::Ros2Msg,
                            text,
                        }),
                        Err(_) => continue,
                    }
                }
                _ => None,
            };
            let topic = resolve(&ns, c.topic.as_deref().unwrap_or(topic));
            specs.push(ServiceSpec {
                name: c.name.clone(),
                description: c
                    .description
                    .clone()
                    .unwrap_or_else(|| short(format!("ROS 2 {ty} on {topic}"))),
                kind: ServiceKind::Command,
                queue: c.queue.unwrap_or(c.payload == CommandPayload::Goal2d),
                quota: c.quota,
                payload,
                schema,
            });
        }
        specs
    }
}

/// Cuts a generated description to muster's limit.
fn short(mut s: String) -> String {
    let max = muster_shared::types::MAX_DESCRIPTION;
    if s.len() > max {
        let mut end = max;
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        s.truncate(end);
    }
    s
}

fn check_qos(service: &str, q: &TopicQos) -> Result<(), ConfigError> {
    let bad = |what: &str, v: &str, ok: &str| {
        Err(ConfigError::Invalid(format!(
            "service {service:?}: qos {what} {v:?}: use {ok}"
        )))
    };
    match q.reliability.as_deref() {
        None | Some("reliable" | "best_effort") => {}
        Some(v) => return bad("reliability", v, "reliable or best_effort"),
    }
    match q.durability.as_deref() {
        None | Some("volatile" | "transient_local") => {}
        Some(v) => return bad("durability", v, "volatile or transient_local"),
    }
    if q.depth == Some(0) {
        return bad("depth", "0", "1 or more");
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const TURTLE: &str = r#"
system = "turtle"
namespace = "turtle"
silent_after = "1500ms"

[[data]]
name = "pose"
topic = "odom"
type = "nav_msgs/Odometry"

[[data]]
name = "say"
topic = "/chatter"
type = "std_msgs/msg/String"
quota = 3
qos = { reliability = "best_effort", depth = 5 }

[[command]]
name = "goal"
payload = "goal2d"

[[command]]
name = "drive"
payload = "twist"
deadman = "300ms"
"#;

    #[test]
    fn a_transient_local_topic_is_latched_unless_the_file_says_otherwise() {
        let c = Ros2SystemConfig::parse(
            r#"
system = "x"
[[data]]
name = "map"
topic = "map"
type = "std_msgs/msg/String"
qos = { durability = "transient_local", depth = 1 }
[[data]]
name = "map_live"
topic = "map"
type = "std_msgs/msg/String"
qos = { durability = "transient_local" }
latched = false
[[data]]
name = "pose"
topic = "odom"
type = "nav_msgs/msg/Odometry"
[[data]]
name = "pose_latched"
topic = "odom"
type = "nav_msgs/msg/Odometry"
latched = true
"#,
        )
        .unwrap();
        let latched: Vec<(&str, bool)> = c
            .data
            .iter()
            .map(|d| (d.name.as_str(), d.is_latched()))
            .collect();
        assert_eq!(
            latched,
            vec![
                ("map", true),
                ("map_live", false),
                ("pose", false),
                ("pose_latched", true)
            ]
        );
    }

    #[test]
    fn a_config_becomes_services() {
        let c = Ros2SystemConfig::parse(TURTLE).unwrap();
        assert_eq!(c.namespace(), "/turtle");
        assert_eq!(c.silent_after(), Duration::from_millis(1500));
        let specs = c.specs();
        let row = |s: &ServiceSpec| (s.name.clone(), s.kind, s.payload.clone(), s.quota, s.queue);
        assert_eq!(
            specs.iter().map(row).collect::<Vec<_>>(),
            vec![
                ("pose".into(), ServiceKind::Data, "pose2d".into(), 10, false),
                ("say".into(), ServiceKind::Data, "text".into(), 3, false),
                (
                    "goal".into(),
                    ServiceKind::Command,
                    "goal2d".into(),
                    1,
                    true
                ),
                (
                    "drive".into(),
                    ServiceKind::Command,
                    "twist".into(),
                    1,
                    false
                ),
            ]
        );
        assert_eq!(
            specs[0].description,
            "ROS 2 /turtle/odom (nav_msgs/msg/Odometry)"
        );
        assert_eq!(
            specs[2].description,
            "ROS 2 PoseStamped on /turtle/goal_pose"
        );
        assert_eq!(c.command[1].deadman, Some(Duration::from_millis(300)));
    }

    #[test]
    fn bad_configs_say_what_is_wrong() {
        let err = |t: &str| Ros2SystemConfig::parse(t).unwrap_err().to_string();
        assert!(err("system = \"x\"\n").contains("no [[data]] and no [[command]]"));
        let e = err(
            "system = \"x\"\n[[data]]\nname = \"s\"\ntopic = \"t\"\ntype = \"my_pkg/msg/Nope\"\n",
        );
        assert!(e.contains("no definition of my_pkg/msg/Nope"), "{e}");
        let e = err("system = \"x\"\n[[data]]\nname = \"s\"\ntopic = \"t\"\ntype = \"std_msgs/String\"\npayload = \"pose2d\"\n");
        assert!(
            e.contains("cannot be offered as pose2d: use ros or text"),
            "{e}"
        );
        let e = err("system = \"x\"\n[[command]]\nname = \"g\"\npayload = \"pose3d\"\n");
        assert!(e.contains("pose3d"), "{e}");
        let e = err("system = \"x\"\n[[data]]\nname = \"s\"\ntopic = \"t\"\ntype = \"std_msgs/String\"\nqos = { reliability = \"sometimes\" }\n");
        assert!(e.contains("reliable or best_effort"), "{e}");
        let e = err("system = \"bad name\"\n[[command]]\nname = \"g\"\npayload = \"goal2d\"\n");
        assert!(e.contains("system name"), "{e}");
        let e =
            err("system = \"x\"\nsurprise = 1\n[[command]]\nname = \"g\"\npayload = \"goal2d\"\n");
        assert!(e.contains("surprise"), "{e}");
        let e = err(
            "system = \"x\"\n[[command]]\nname = \"g\"\npayload = \"twist\"\ndeadman = \"soon\"\n",
        );
        assert!(e.contains("soon") || e.contains("deadman"), "{e}");
    }

    #[test]
    fn topics_resolve_against_the_namespace() {
        assert_eq!(resolve("/", "odom"), "/odom");
        assert_eq!(resolve("/r1", "odom"), "/r1/odom");
        assert_eq!(resolve("/r1/", "/clock"), "/clock");
        assert_eq!(full_type("std_msgs/String"), "std_msgs/msg/String");
        assert_eq!(full_type("std_msgs/msg/String"), "std_msgs/msg/String");
    }
}
