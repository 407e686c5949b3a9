//! Domain types: services, sessions, payloads, refusals — the paper's words.

use serde::{Deserialize, Serialize};
use std::fmt;

/// Longest system name, in bytes.
pub const MAX_SYSTEM_NAME: usize = 31;
/// Longest host name in a federation, in bytes.
pub const MAX_HOST_NAME: usize = 31;
/// Longest service name, in bytes.
pub const MAX_SERVICE_NAME: usize = 31;
/// Longest service description, in bytes.
pub const MAX_DESCRIPTION: usize = 95;
/// Longest payload type name, in bytes (an open type's name, such as
/// `geometry_msgs/msg/PoseWithCovarianceStamped`, is its schema's).
pub const MAX_PAYLOAD_TYPE: usize = 63;
/// Longest schema a service may declare, in bytes (it travels in the grant, whose frame
/// is 4 KiB on the local path).
pub const MAX_SCHEMA: usize = 3 * 1024;
/// Largest encoded sample of an open payload type, in bytes (an update's frame is 4 KiB
/// on the local path).
pub const MAX_ENCODED: usize = 3584;
/// Largest quota a service may declare.
pub const MAX_QUOTA: u16 = 1000;
/// Largest number of services one system may register.
pub const MAX_SERVICES_PER_SYSTEM: usize = 128;

/// Whether a service streams data to the user or takes task input from the user.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    Hash,
    Serialize,
    Deserialize,
    PartialOrd,
    Ord,
)]
pub enum ServiceKind {
    /// The system streams information and task status (e.g. a tracker's target position).
    Data,
    /// The user supplies task input (e.g. a delivery robot's goal).
    Command,
}

impl ServiceKind {
    /// The lower-case name used on the command line and in JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            ServiceKind::Data => "data",
            ServiceKind::Command => "command",
        }
    }
}

impl fmt::Display for ServiceKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ServiceKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "data" => Ok(ServiceKind::Data),
            "command" => Ok(ServiceKind::Command),
            other => Err(format!(
                "unknown service kind {other:?}: expected data or command"
            )),
        }
    }
}

/// What a system declares about one service when it registers.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
)]
pub struct ServiceSpec {
    /// Name, unique within the system.
    pub name: String,
    /// One line for the user's menu.
    pub description: String,
    /// Data or command.
    pub kind: ServiceKind,
    /// Whether requests beyond the quota wait in a task queue instead of being refused.
    pub queue: bool,
    /// How many sessions the service accepts at once.
    pub quota: u16,
    /// Payload type name (e.g. `pose2d`, `goal2d`), used to check that a link makes sense;
    /// an open type's name is its schema's (e.g. `sensor_msgs/msg/LaserScan`).
    pub payload: String,
    /// The schema of an open payload type, whose updates are [`Payload::Encoded`]; `None`
    /// for the built-in types.
    #[serde(default)]
    pub schema: Option<Schema>,
}

/// How a schema is written, and so how its samples are encoded (MCAP's names).
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    Hash,
    Serialize,
    Deserialize,
)]
pub enum SchemaEncoding {
    /// A ROS 2 message definition with its dependencies; samples are CDR (with the
    /// 4-byte encapsulation header, as in MCAP and rosbag2).
    Ros2Msg,
    /// A JSON Schema; samples are UTF-8 JSON.
    JsonSchema,
}

impl SchemaEncoding {
    /// MCAP's schema encoding name.
    pub fn as_str(self) -> &'static str {
        match self {
            SchemaEncoding::Ros2Msg => "ros2msg",
            SchemaEncoding::JsonSchema => "jsonschema",
        }
    }

    /// MCAP's message encoding name of the samples.
    pub fn message_encoding(self) -> &'static str {
        match self {
            SchemaEncoding::Ros2Msg => "cdr",
            SchemaEncoding::JsonSchema => "json",
        }
    }
}

/// An open payload type's schema: what a user needs to read a sample of a type it has
/// never seen.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
)]
pub struct Schema {
    /// How it is written.
    pub encoding: SchemaEncoding,
    /// The schema text.
    pub text: String,
}

impl Schema {
    /// Reads `data`, a sample of type `type_name` under this schema, as JSON.
    pub fn decode(&self, type_name: &str, data: &[u8]) -> Result<serde_json::Value, String> {
        match self.encoding {
            SchemaEncoding::Ros2Msg => crate::ros2msg::Definitions::parse(type_name, &self.text)
                .and_then(|d| d.decode(data))
                .map_err(|e| e.to_string()),
            SchemaEncoding::JsonSchema => {
                serde_json::from_slice(data).map_err(|e| format!("JSON sample: {e}"))
            }
        }
    }

    /// Writes `value` (as [`Schema::decode`] gives it) as a sample of type `type_name`.
    pub fn encode(&self, type_name: &str, value: &serde_json::Value) -> Result<Vec<u8>, String> {
        match self.encoding {
            SchemaEncoding::Ros2Msg => crate::ros2msg::Definitions::parse(type_name, &self.text)
                .and_then(|d| d.encode_json(value))
                .map_err(|e| e.to_string()),
            SchemaEncoding::JsonSchema => serde_json::to_vec(value).map_err(|e| e.to_string()),
        }
    }
}

impl Payload {
    /// The payload as JSON, the form `muster user --json` prints and `--input` (with
    /// [`Payload::from_json`]) reads: `{"type": "pose2d", "x": .., "y": .., "theta": ..}`;
    /// an open type's sample as its size and bytes in hex (see [`Payload::to_json_with`]).
    pub fn to_json(&self) -> serde_json::Value {
        use serde_json::json;
        match self {
            Payload::Encoded { type_name, data } => {
                json!({"type": type_name, "bytes": data.len(), "hex": hex::encode(data)})
            }
            Payload::Pose2d { x, y, theta } => {
                json!({"type": "pose2d", "x": x, "y": y, "theta": theta})
            }
            Payload::Goal2d { x, y } => json!({"type": "goal2d", "x": x, "y": y}),
            Payload::Twist { v, w } => json!({"type": "twist", "v": v, "w": w}),
            Payload::Scalar(v) => json!({"type": "scalar", "value": v}),
            Payload::Text(t) => json!({"type": "text", "text": t}),
            Payload::Track2d(t) => json!({"type": "track2d", "x": t.x, "y": t.y, "vx": t.vx,
                "vy": t.vy, "sigma": t.sigma, "age": t.age, "seen_by": t.seen_by,
                "lost": t.lost}),
        }
    }

    /// [`Payload::to_json`], an open type's sample decoded by its schema:
    /// `{"type": "sensor_msgs/msg/LaserScan", "encoding": "cdr", "value": {..}}`; without
    /// its schema, or if it does not decode, its size and bytes in hex (and why).
    pub fn to_json_with(&self, schema: Option<&Schema>) -> serde_json::Value {
        use serde_json::json;
        let Payload::Encoded { type_name, data } = self else {
            return self.to_json();
        };
        match schema.map(|s| (s, s.decode(type_name, data))) {
            Some((s, Ok(value))) => json!({"type": type_name,
                "encoding": s.encoding.message_encoding(), "value": value}),
            Some((_, Err(e))) => json!({"type": type_name, "bytes": data.len(),
                "hex": hex::encode(data), "error": e}),
            None => self.to_json(),
        }
    }

    /// Task input given as JSON, the way `muster user` shows payloads: a string is
    /// `text`, a number `scalar`; an object names its `type` (`goal2d` with `x`, `y`;
    /// `pose2d` with `x`, `y`, `theta`; `twist` with `v`, `w`; `text` with `text`;
    /// `scalar` with `value`), or is an open type's `value`, written with `schema`.
    pub fn from_json(v: &serde_json::Value, schema: Option<&Schema>) -> Result<Payload, String> {
        use serde_json::Value;
        let num = |o: &serde_json::Map<String, Value>, k: &str| -> Result<f64, String> {
            o.get(k)
                .and_then(Value::as_f64)
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("a finite number {k:?} expected"))
        };
        match v {
            Value::String(t) => Ok(Payload::Text(t.clone())),
            Value::Number(n) => n
                .as_f64()
                .filter(|x| x.is_finite())
                .map(Payload::Scalar)
                .ok_or_else(|| "a finite number expected".into()),
            Value::Object(o) => {
                let ty = o
                    .get("type")
                    .and_then(Value::as_str)
                    .ok_or("an object names its \"type\" (goal2d, pose2d, twist, text, scalar, or an open type)")?;
                Ok(match ty {
                    "goal2d" => Payload::Goal2d {
                        x: num(o, "x")?,
                        y: num(o, "y")?,
                    },
                    "pose2d" => Payload::Pose2d {
                        x: num(o, "x")?,
                        y: num(o, "y")?,
                        theta: num(o, "theta")?,
                    },
                    "twist" => Payload::Twist {
                        v: num(o, "v")?,
                        w: num(o, "w")?,
                    },
                    "scalar" => Payload::Scalar(num(o, "value")?),
                    "text" => Payload::Text(
                        o.get("text")
                            .and_then(Value::as_str)
                            .ok_or("a string \"text\" expected")?
                            .to_string(),
                    ),
                    "track2d" => return Err("track2d is data, not task input".into()),
                    open => {
                        let schema = schema.ok_or_else(|| {
                            format!("{open} is no built-in type and the service gave no schema to write it with")
                        })?;
                        let value = o.get("value").unwrap_or(&Value::Null);
                        Payload::Encoded {
                            type_name: open.to_string(),
                            data: schema.encode(open, value)?,
                        }
                    }
                })
            }
            other => Err(format!("{other} is no task input")),
        }
    }
}

/// Why a [`ServiceSpec`] or a system name was rejected.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error, Serialize, Deserialize)]
pub enum SpecError {
    /// A name is empty, too long, or holds characters other than `[A-Za-z0-9_.-]`; rename it.
    #[error("invalid {what} {value:?}: 1..={max} characters of [A-Za-z0-9_.-]")]
    BadName {
        /// Which name.
        what: String,
        /// The value given.
        value: String,
        /// The longest allowed.
        max: usize,
    },
    /// The description is longer than [`MAX_DESCRIPTION`] bytes; shorten it.
    #[error("description of {0:?} is longer than {MAX_DESCRIPTION} bytes")]
    DescriptionTooLong(String),
    /// The quota is 0 or above [`MAX_QUOTA`]; pick a value in range.
    #[error("quota of {service:?} is {quota}: must be 1..={MAX_QUOTA}")]
    BadQuota {
        /// The service.
        service: String,
        /// The value given.
        quota: u16,
    },
    /// Two services of one system share a name; rename one.
    #[error("service {0:?} is declared twice")]
    Duplicate(String),
    /// A schema is longer than [`MAX_SCHEMA`] bytes; strip its comments or split the type.
    #[error("schema of {service:?} is {len} bytes, at most {MAX_SCHEMA}")]
    SchemaTooLong {
        /// The service.
        service: String,
        /// Its length.
        len: usize,
    },
    /// A schema does not parse; the detail says where.
    #[error("schema of {service:?}: {detail}")]
    BadSchema {
        /// The service.
        service: String,
        /// What is wrong.
        detail: String,
    },
    /// More services than [`MAX_SERVICES_PER_SYSTEM`]; split the system.
    #[error("{0} services declared, at most {MAX_SERVICES_PER_SYSTEM} per system")]
    TooMany(usize),
    /// The registration (names, descriptions, schemas of all the services) is larger
    /// than one frame; shorten descriptions and schemas, or split the system.
    #[error(
        "the registration of {services} services is {bytes} bytes, more than one \
         {}-byte frame: shorten descriptions and schemas, or split the system",
        crate::protocol::MAX_FRAME
    )]
    RegistrationTooLarge {
        /// Services declared.
        services: usize,
        /// The registration's size.
        bytes: usize,
    },
}

/// Checks a name against the naming rule shared by systems, services and payload types.
pub fn check_name(what: &str, value: &str, max: usize) -> Result<(), SpecError> {
    let ok = !value.is_empty()
        && value.len() <= max
        && value
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.');
    if ok {
        Ok(())
    } else {
        Err(SpecError::BadName {
            what: what.to_string(),
            value: value.to_string(),
            max,
        })
    }
}

impl ServiceSpec {
    /// Checks every field against the protocol's limits.
    pub fn validate(&self) -> Result<(), SpecError> {
        check_name("service name", &self.name, MAX_SERVICE_NAME)?;
        match &self.schema {
            None => check_name("payload type", &self.payload, MAX_PAYLOAD_TYPE)?,
            Some(schema) => {
                // An open type's name is its schema's: `pkg/msg/Type` has slashes.
                let name_ok = !self.payload.is_empty()
                    && self.payload.len() <= MAX_PAYLOAD_TYPE
                    && self
                        .payload
                        .bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b"_-./".contains(&b))
                    && !is_builtin_payload(&self.payload);
                if !name_ok {
                    return Err(SpecError::BadName {
                        what: "open payload type".into(),
                        value: self.payload.clone(),
                        max: MAX_PAYLOAD_TYPE,
                    });
                }
                if schema.text.len() > MAX_SCHEMA {
                    return Err(SpecError::SchemaTooLong {
                        service: self.name.clone(),
                        len: schema.text.len(),
                    });
                }
                if schema.encoding == SchemaEncoding::Ros2Msg {
                    crate::ros2msg::Definitions::parse(&self.payload, &schema.text).map_err(
                        |e| SpecError::BadSchema {
                            service: self.name.clone(),
                            detail: e.to_string(),
                        },
                    )?;
                }
            }
        }
        if self.description.len() > MAX_DESCRIPTION {
            return Err(SpecError::DescriptionTooLong(self.name.clone()));
        }
        if self.quota == 0 || self.quota > MAX_QUOTA {
            return Err(SpecError::BadQuota {
                service: self.name.clone(),
                quota: self.quota,
            });
        }
        Ok(())
    }
}

/// Checks a whole registration: system name, each spec, no duplicates, not too many.
pub fn validate_registration(system: &str, specs: &[ServiceSpec]) -> Result<(), SpecError> {
    check_name("system name", system, MAX_SYSTEM_NAME)?;
    if specs.len() > MAX_SERVICES_PER_SYSTEM {
        return Err(SpecError::TooMany(specs.len()));
    }
    let mut seen = std::collections::BTreeSet::new();
    let mut bytes = 0;
    for s in specs {
        s.validate()?;
        if !seen.insert(s.name.as_str()) {
            return Err(SpecError::Duplicate(s.name.clone()));
        }
        bytes += s.name.len()
            + s.description.len()
            + s.payload.len()
            + s.schema.as_ref().map_or(0, |x| x.text.len());
    }
    // Each spec fits on its own; many may not fit one frame together. Encoded only when
    // the texts alone come near the limit.
    if bytes > crate::protocol::MAX_FRAME / 2 {
        let msg = crate::protocol::ToBroker::Register {
            system: system.to_string(),
            pid: 0,
            services: specs.to_vec(),
            sessions: Vec::new(),
            udp: None,
        };
        let len = crate::protocol::encode(&msg).map_or(usize::MAX, |b| b.len());
        if len > crate::protocol::MAX_FRAME {
            return Err(SpecError::RegistrationTooLarge {
                services: specs.len(),
                bytes: if len == usize::MAX { bytes } else { len },
            });
        }
    }
    Ok(())
}

/// A service's stable identity: `system/service`. Stable across re-registration by construction.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
)]
#[rkyv(derive(PartialEq, Eq, PartialOrd, Ord))]
pub struct ServiceId(pub String);

impl ServiceId {
    /// Builds the id of `service` offered by `system`.
    pub fn new(system: &str, service: &str) -> Self {
        ServiceId(format!("{system}/{service}"))
    }

    /// The id of `service` offered by `system` on another host `host` of a federation.
    pub fn on_host(system: &str, host: &str, service: &str) -> Self {
        ServiceId(format!("{system}@{host}/{service}"))
    }

    /// Splits the id into (system, service), if it has the `system/service` form (the
    /// system of another host's service is `system@host`).
    pub fn split(&self) -> Option<(&str, &str)> {
        self.0.split_once('/')
    }

    /// For another host's service (`system@host/service`): (host, the id on that host).
    pub fn remote(&self) -> Option<(&str, ServiceId)> {
        let (system, service) = self.split()?;
        let (system, host) = system.split_once('@')?;
        Some((host, ServiceId::new(system, service)))
    }
}

impl fmt::Display for ServiceId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// A one-to-one session, numbered by the broker that granted it after the request it
/// grants ([`SessionId::for_request`]).
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
)]
#[rkyv(derive(PartialEq, Eq, PartialOrd, Ord))]
pub struct SessionId(pub u64);

impl SessionId {
    /// The session that grants request `req` of `user` for `service`: the first 8 bytes
    /// of a SHA-256 over the three. A request granted again (a retry that crossed a
    /// broker's restart or takeover, or a standby that took over) gets the same session
    /// from any broker, so its system opens it once; and no request can be shaped to
    /// take another's number.
    pub fn for_request(service: &ServiceId, user: &UserId, req: u64) -> SessionId {
        use sha2::Digest;
        let mut h = sha2::Sha256::new();
        for part in [service.0.as_bytes(), user.0.as_bytes()] {
            h.update((part.len() as u64).to_le_bytes());
            h.update(part);
        }
        h.update(req.to_le_bytes());
        let d = h.finalize();
        let mut first = [0u8; 8];
        first.copy_from_slice(&d[..8]);
        SessionId(u64::from_le_bytes(first))
    }
}

impl fmt::Display for SessionId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:016x}", self.0)
    }
}

/// A user's identity on this host: unique per user process.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
)]
#[rkyv(derive(PartialEq, Eq, PartialOrd, Ord))]
pub struct UserId(pub String);

impl UserId {
    /// Whether this is another host's user, as a federation names it here
    /// (`user@host`): its host's broker relays its frames.
    pub fn is_foreign(&self) -> bool {
        self.0.contains('@')
    }

    /// The pid of the local process whose shared inbox this user is reached at, if it
    /// shares one: its id ends in `~PID` (`u1f2e3d~4242`). A user id without it has an
    /// inbox of its own. The broker takes such an id's hello only from that process.
    pub fn process_inbox(&self) -> Option<u32> {
        let (_, pid) = self.0.rsplit_once('~')?;
        if pid.is_empty() || !pid.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        pid.parse().ok()
    }

    /// An id for a user of process `pid` that shares its process's inbox
    /// ([`UserId::process_inbox`]).
    pub fn in_process_inbox(name: &str, pid: u32) -> UserId {
        UserId(format!("{name}~{pid}"))
    }
}

impl fmt::Display for UserId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// Typed session data and task input.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Payload {
    /// A position and heading in the world frame (metres, radians).
    Pose2d {
        /// x, metres.
        x: f64,
        /// y, metres.
        y: f64,
        /// heading, radians.
        theta: f64,
    },
    /// A goal position in the world frame (metres).
    Goal2d {
        /// x, metres.
        x: f64,
        /// y, metres.
        y: f64,
    },
    /// A single reading.
    Scalar(f64),
    /// Free text.
    Text(String),
    /// A tracked target in the world frame (a tracking system's estimate).
    Track2d(Track2d),
    /// A velocity command in the robot's frame: forward speed (m/s) and turn rate
    /// (rad/s, counter-clockwise), as ROS's `geometry_msgs/Twist` linear.x and angular.z.
    /// A driver keeps sending it; the robot stops when it stops coming.
    Twist {
        /// Forward speed, m/s.
        v: f64,
        /// Turn rate, rad/s.
        w: f64,
    },
    /// A sample of an open payload type, encoded as its service's [`Schema`] says (CDR
    /// for a ROS 2 message, UTF-8 for JSON); at most [`MAX_ENCODED`] bytes.
    Encoded {
        /// The type's name (the service's payload type).
        type_name: String,
        /// The sample.
        data: Vec<u8>,
    },
}

/// The built-in payload types' names.
pub const BUILTIN_PAYLOADS: [&str; 6] = ["pose2d", "goal2d", "scalar", "text", "track2d", "twist"];

/// Whether `name` is a built-in payload type.
pub fn is_builtin_payload(name: &str) -> bool {
    BUILTIN_PAYLOADS.contains(&name)
}

/// Most robots a [`Track2d`] names as seeing its target.
pub const MAX_TRACK_OBSERVERS: usize = 16;

/// A target's tracked state: position, velocity, uncertainty, who sees it, whether lost.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Track2d {
    /// x, metres.
    pub x: f64,
    /// y, metres.
    pub y: f64,
    /// Velocity along x, m/s.
    pub vx: f64,
    /// Velocity along y, m/s.
    pub vy: f64,
    /// Position uncertainty: standard deviation along the worst axis, metres.
    pub sigma: f64,
    /// Seconds since the target was last detected (0 when seen in this update).
    pub age: f64,
    /// Robots that detected it in the last update window (at most
    /// [`MAX_TRACK_OBSERVERS`]).
    pub seen_by: Vec<String>,
    /// Unseen for longer than the system's timeout: the position is the last known one.
    pub lost: bool,
}

impl Payload {
    /// The payload type name this value belongs to.
    pub fn type_name(&self) -> &str {
        match self {
            Payload::Pose2d { .. } => "pose2d",
            Payload::Goal2d { .. } => "goal2d",
            Payload::Scalar(_) => "scalar",
            Payload::Text(_) => "text",
            Payload::Track2d(_) => "track2d",
            Payload::Twist { .. } => "twist",
            Payload::Encoded { type_name, .. } => type_name,
        }
    }

    /// Converts this value into task input of type `target`, as a link does; `None` if the
    /// conversion makes no sense.
    pub fn convert_to(&self, target: &str) -> Option<Payload> {
        match (self, target) {
            (p, t) if p.type_name() == t => Some(p.clone()),
            (Payload::Pose2d { x, y, .. }, "goal2d") => Some(Payload::Goal2d { x: *x, y: *y }),
            // A lost target gives no goal: the command system keeps its last one.
            (Payload::Track2d(t), "goal2d") => (!t.lost && t.x.is_finite() && t.y.is_finite())
                .then_some(Payload::Goal2d { x: t.x, y: t.y }),
            (Payload::Track2d(t), "pose2d") => (!t.lost).then_some(Payload::Pose2d {
                x: t.x,
                y: t.y,
                theta: t.vy.atan2(t.vx),
            }),
            (p, "text") => Some(Payload::Text(p.to_string())),
            _ => None,
        }
    }
}

impl fmt::Display for Payload {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Payload::Pose2d { x, y, theta } => {
                write!(f, "pose2d x={x:.3} y={y:.3} theta={theta:.3}")
            }
            Payload::Goal2d { x, y } => write!(f, "goal2d x={x:.3} y={y:.3}"),
            Payload::Twist { v, w } => write!(f, "twist v={v:.3} w={w:.3}"),
            Payload::Encoded { type_name, data } => write!(f, "{type_name} ({} bytes)", data.len()),
            Payload::Scalar(v) => write!(f, "scalar {v}"),
            Payload::Text(t) => write!(f, "text {t}"),
            Payload::Track2d(t) => {
                write!(
                    f,
                    "track2d x={:.3} y={:.3} v=({:.2}, {:.2}) sigma={:.2}",
                    t.x, t.y, t.vx, t.vy, t.sigma
                )?;
                if t.lost {
                    write!(f, " lost ({:.0} s unseen)", t.age)
                } else if t.seen_by.is_empty() {
                    write!(f, " unseen {:.1} s", t.age)
                } else {
                    write!(f, " seen by {}", t.seen_by.join(","))
                }
            }
        }
    }
}

/// Whether data of payload type `data` can drive a command service taking `command`.
/// `data_open`: the data service's values really are of its declared type (a built-in
/// one, or an open payload with its schema). A declared name that is neither (a label
/// over values sent as text, say) is forwarded nowhere but to `text`: a link between
/// two such services of one name would carry nothing.
pub fn link_compatible(data: &str, data_open: bool, command: &str) -> bool {
    if data == command {
        return is_builtin_payload(data) || data_open;
    }
    (matches!(data, "pose2d" | "track2d") && command == "goal2d")
        || (data == "track2d" && command == "pose2d")
        || command == "text"
}

/// Why a request was refused. Every refusal names one of these.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Refusal {
    /// No service has this id (never registered, or its system was removed).
    Unknown,
    /// The system withdrew the service for now.
    Withdrawn,
    /// All of the service's quota is in use and it keeps no queue.
    QuotaFull {
        /// The quota.
        quota: u16,
    },
    /// The service's task queue is occupied by other users up to its capacity.
    QueueFull {
        /// How many requests wait.
        waiting: u16,
    },
    /// The system is gone (delinquent, dead or unregistered) or did not answer.
    SystemGone,
    /// The system itself refused (e.g. overloaded), with its reason.
    SystemRefused(String),
    /// This user already has a request pending for the service.
    AlreadyPending,
    /// The broker refused a malformed or unauthorised request.
    BadRequest(String),
    /// An operator dropped the request from the service's task queue.
    ByOperator,
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Refusal::Unknown => f.write_str("unknown service"),
            Refusal::Withdrawn => f.write_str("service withdrawn by its system"),
            Refusal::QuotaFull { quota } => write!(f, "quota full ({quota} sessions in use)"),
            Refusal::QueueFull { waiting } => {
                write!(f, "task queue occupied by other users ({waiting} waiting)")
            }
            Refusal::SystemGone => f.write_str("system gone"),
            Refusal::SystemRefused(r) => write!(f, "refused by the system: {r}"),
            Refusal::AlreadyPending => f.write_str("a request for this service is already pending"),
            Refusal::BadRequest(r) => write!(f, "bad request: {r}"),
            Refusal::ByOperator => f.write_str("dropped from the task queue by an operator"),
        }
    }
}

impl Refusal {
    /// A short machine-readable code, for JSON output and counters.
    pub fn code(&self) -> &'static str {
        match self {
            Refusal::Unknown => "unknown",
            Refusal::Withdrawn => "withdrawn",
            Refusal::QuotaFull { .. } => "quota_full",
            Refusal::QueueFull { .. } => "queue_full",
            Refusal::SystemGone => "system_gone",
            Refusal::SystemRefused(_) => "system_refused",
            Refusal::AlreadyPending => "already_pending",
            Refusal::BadRequest(_) => "bad_request",
            Refusal::ByOperator => "by_operator",
        }
    }
}

/// Why a session ended.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EndReason {
    /// The user ended it.
    ByUser,
    /// The system ended it (with its reason).
    BySystem(String),
    /// The system withdrew the service.
    Withdrawn,
    /// The other process died or stopped answering.
    PeerGone,
    /// The user's requested duration ran out.
    DurationOver,
}

impl EndReason {
    /// A short machine-readable code: `by_user`, `by_system`, `withdrawn`, `peer_gone`
    /// or `duration_over`.
    pub fn code(&self) -> &'static str {
        match self {
            EndReason::ByUser => "by_user",
            EndReason::BySystem(_) => "by_system",
            EndReason::Withdrawn => "withdrawn",
            EndReason::PeerGone => "peer_gone",
            EndReason::DurationOver => "duration_over",
        }
    }
}

impl fmt::Display for EndReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EndReason::ByUser => f.write_str("ended by the user"),
            EndReason::BySystem(r) => write!(f, "ended by the system: {r}"),
            EndReason::Withdrawn => f.write_str("service withdrawn"),
            EndReason::PeerGone => f.write_str("peer gone"),
            EndReason::DurationOver => f.write_str("duration over"),
        }
    }
}

/// Task status a command system reports on a session.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum TaskStatus {
    /// Waiting for task input.
    Idle,
    /// Working on the input, with a human-readable progress note.
    Working(String),
    /// Task done (e.g. arrived within 1 m of the goal).
    Done(String),
    /// The input could not be used.
    Rejected(String),
}

impl TaskStatus {
    /// The state alone: `idle`, `working`, `done` or `rejected`.
    pub fn state(&self) -> &'static str {
        match self {
            TaskStatus::Idle => "idle",
            TaskStatus::Working(_) => "working",
            TaskStatus::Done(_) => "done",
            TaskStatus::Rejected(_) => "rejected",
        }
    }

    /// The note beside the state (`None` when idle).
    pub fn detail(&self) -> Option<&str> {
        match self {
            TaskStatus::Idle => None,
            TaskStatus::Working(d) | TaskStatus::Done(d) | TaskStatus::Rejected(d) => Some(d),
        }
    }
}

impl fmt::Display for TaskStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TaskStatus::Idle => f.write_str("idle"),
            TaskStatus::Working(s) => write!(f, "working: {s}"),
            TaskStatus::Done(s) => write!(f, "done: {s}"),
            TaskStatus::Rejected(s) => write!(f, "rejected: {s}"),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn task_input_from_json_makes_each_type_and_an_open_one_with_its_schema() {
        use serde_json::json;
        let p = |v: serde_json::Value, s: Option<&Schema>| Payload::from_json(&v, s);
        assert_eq!(p(json!("open"), None), Ok(Payload::Text("open".into())));
        assert_eq!(p(json!(2.5), None), Ok(Payload::Scalar(2.5)));
        assert_eq!(
            p(json!({"type": "goal2d", "x": 1, "y": -2}), None),
            Ok(Payload::Goal2d { x: 1.0, y: -2.0 })
        );
        assert_eq!(
            p(json!({"type": "twist", "v": 0.5, "w": 0}), None),
            Ok(Payload::Twist { v: 0.5, w: 0.0 })
        );
        let schema = Schema {
            encoding: SchemaEncoding::Ros2Msg,
            text: "float64 x\nstring name\n".into(),
        };
        let door = p(
            json!({"type": "my_pkg/msg/Door", "value": {"x": 1.5, "name": "front"}}),
            Some(&schema),
        )
        .unwrap();
        let Payload::Encoded { type_name, data } = &door else {
            panic!("{door:?}")
        };
        assert_eq!(type_name, "my_pkg/msg/Door");
        assert_eq!(
            schema.decode(type_name, data),
            Ok(json!({"x": 1.5, "name": "front"}))
        );
        for (bad, says) in [
            (json!({"type": "my_pkg/msg/Door"}), "no schema"),
            (json!({"type": "goal2d", "x": 1}), "\"y\""),
            (json!({"x": 1}), "names its \"type\""),
            (json!({"type": "track2d"}), "not task input"),
            (json!([1, 2]), "no task input"),
        ] {
            let e = p(bad.clone(), None).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn a_requests_session_is_the_same_from_any_broker_and_differs_from_others() {
        let s = |svc: &str, user: &str, req| {
            SessionId::for_request(&ServiceId(svc.into()), &UserId(user.into()), req)
        };
        // Fixed: brokers of different runs (and builds) agree.
        assert_eq!(s("t1/s0", "u1-ab", 7), s("t1/s0", "u1-ab", 7));
        assert_eq!(format!("{}", s("t1/s0", "u1-ab", 7)), "173fb7d8109c04e4");
        // Each part counts, and the parts' boundaries too ("t1/s" + "0u" is not
        // "t1/s0" + "u").
        let mut seen = std::collections::HashSet::new();
        for (svc, user, req) in [
            ("t1/s0", "u1-ab", 7),
            ("t1/s0", "u1-ab", 8),
            ("t1/s1", "u1-ab", 7),
            ("t1/s0", "u2-ab", 7),
            ("t1/s", "0u1-ab", 7),
        ] {
            assert!(seen.insert(s(svc, user, req)), "{svc} {user} {req}");
        }
        for req in 0..100_000 {
            assert!(seen.insert(s("t1/s0", "u1-ab", 1_000 + req)));
        }
    }

    fn spec(name: &str) -> ServiceSpec {
        ServiceSpec {
            name: name.into(),
            description: "d".into(),
            kind: ServiceKind::Data,
            queue: false,
            quota: 10,
            payload: "pose2d".into(),
            schema: None,
        }
    }

    #[test]
    fn registration_rules() {
        assert!(validate_registration("t1", &[spec("a"), spec("b")]).is_ok());
        assert_eq!(
            validate_registration("t1", &[spec("a"), spec("a")]),
            Err(SpecError::Duplicate("a".into()))
        );
        assert!(matches!(
            validate_registration("bad name", &[spec("a")]),
            Err(SpecError::BadName { .. })
        ));
        let mut s = spec("a");
        s.quota = 0;
        assert!(matches!(
            validate_registration("t1", &[s]),
            Err(SpecError::BadQuota { .. })
        ));
        let many: Vec<_> = (0..=MAX_SERVICES_PER_SYSTEM)
            .map(|i| spec(&format!("s{i}")))
            .collect();
        assert_eq!(
            validate_registration("t1", &many),
            Err(SpecError::TooMany(MAX_SERVICES_PER_SYSTEM + 1))
        );
        // Each within its limits, together more than one frame: refused with the size.
        let with_schema = |i: usize, len: usize| ServiceSpec {
            payload: "x/Big".into(),
            schema: Some(Schema {
                encoding: SchemaEncoding::JsonSchema,
                text: format!("{{\"title\": \"{}\"}}", "a".repeat(len)),
            }),
            ..spec(&format!("s{i}"))
        };
        let fat: Vec<_> = (0..40).map(|i| with_schema(i, 2000)).collect();
        match validate_registration("t1", &fat) {
            Err(SpecError::RegistrationTooLarge {
                services: 40,
                bytes,
            }) => {
                assert!(bytes > crate::protocol::MAX_FRAME, "{bytes}")
            }
            other => panic!("{other:?}"),
        }
        let fits: Vec<_> = (0..20).map(|i| with_schema(i, 2000)).collect();
        assert!(validate_registration("t1", &fits).is_ok());
    }

    #[test]
    fn link_conversions() {
        let pose = Payload::Pose2d {
            x: 1.0,
            y: 2.0,
            theta: 0.5,
        };
        assert_eq!(
            pose.convert_to("goal2d"),
            Some(Payload::Goal2d { x: 1.0, y: 2.0 })
        );
        assert_eq!(pose.convert_to("pose2d"), Some(pose.clone()));
        assert_eq!(Payload::Scalar(1.0).convert_to("goal2d"), None);
        assert!(link_compatible("pose2d", false, "goal2d"));
        assert!(!link_compatible("scalar", false, "goal2d"));
        // A label over values of another type links into nothing of its name; an open
        // payload (with its schema) does.
        assert!(!link_compatible("door_state", false, "door_state"));
        assert!(link_compatible("door_state", false, "text"));
        assert!(link_compatible(
            "sensor_msgs/msg/LaserScan",
            true,
            "sensor_msgs/msg/LaserScan"
        ));
        let mut track = Track2d {
            x: 3.0,
            y: 4.0,
            vx: 0.5,
            vy: 0.0,
            sigma: 0.1,
            age: 0.0,
            seen_by: vec!["T1".into()],
            lost: false,
        };
        assert!(link_compatible("track2d", false, "goal2d"));
        assert_eq!(
            Payload::Track2d(track.clone()).convert_to("goal2d"),
            Some(Payload::Goal2d { x: 3.0, y: 4.0 })
        );
        track.lost = true;
        assert_eq!(Payload::Track2d(track.clone()).convert_to("goal2d"), None);
        assert!(Payload::Track2d(track).to_string().contains("lost"));
    }

    #[test]
    fn service_id_is_stable_and_splits() {
        let id = ServiceId::new("t1", "track");
        assert_eq!(id, ServiceId::new("t1", "track"));
        assert_eq!(id.split(), Some(("t1", "track")));
    }
}
