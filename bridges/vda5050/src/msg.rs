//! VDA 5050 messages (version 2), as serde types in the specification's field names,
//! and the checks every message passes before it is acted on: the fields the JSON
//! schemas require, their enumerations and ranges, the header's version and timestamp,
//! and the order graph's rules (sequence ids, base before horizon, edges joining their
//! nodes). Unknown fields are let through, as the schemas let them through.

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// Why a message was not taken: the reason is logged and the message dropped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Invalid {
    /// Not JSON, or a required field missing or of the wrong type.
    #[error("not a valid {topic} message: {detail}")]
    Shape {
        /// The topic's name (`state`, `order`, ...).
        topic: &'static str,
        /// What the JSON reader said.
        detail: String,
    },
    /// Well formed, but a value breaks the specification's rules.
    #[error("invalid {topic} message: {detail}")]
    Rule {
        /// The topic's name.
        topic: &'static str,
        /// Which rule and value.
        detail: String,
    },
}

/// The header every message starts with.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Header {
    /// Per topic and sender, incremented by 1 with each message sent.
    pub header_id: u32,
    /// ISO 8601 UTC, `YYYY-MM-DDTHH:mm:ss.ssZ`.
    pub timestamp: String,
    /// The protocol version, `major.minor.patch`.
    pub version: String,
    /// The vehicle's manufacturer.
    pub manufacturer: String,
    /// The vehicle's serial number.
    pub serial_number: String,
}

/// The protocol versions taken: major version 2 (2.0 and 2.1 are wire compatible for
/// everything muster reads and writes).
pub fn version_supported(v: &str) -> bool {
    let mut parts = v.split('.');
    parts.next() == Some("2")
        && parts.all(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()))
}

impl Header {
    /// A header for a message sent now.
    pub fn now(header_id: u32, version: &str, manufacturer: &str, serial: &str) -> Self {
        Header {
            header_id,
            timestamp: timestamp_now(),
            version: version.to_string(),
            manufacturer: manufacturer.to_string(),
            serial_number: serial.to_string(),
        }
    }

    fn check(&self) -> Result<(), String> {
        if !version_supported(&self.version) {
            return Err(format!("version {:?} is not 2.x", self.version));
        }
        if chrono::DateTime::parse_from_rfc3339(&self.timestamp).is_err() {
            return Err(format!("timestamp {:?} is not ISO 8601", self.timestamp));
        }
        if self.serial_number.is_empty() {
            return Err("empty serialNumber".into());
        }
        Ok(())
    }
}

/// The time now as VDA 5050 writes it: UTC with milliseconds.
pub fn timestamp_now() -> String {
    humantime::format_rfc3339_millis(std::time::SystemTime::now()).to_string()
}

/// `connection`: sent retained; the last will says `CONNECTIONBROKEN`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Connection {
    /// The header.
    #[serde(flatten)]
    pub header: Header,
    /// Online, gone offline in order, or broken.
    pub connection_state: ConnectionState,
}

/// A vehicle's connection to the MQTT broker.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum ConnectionState {
    /// Connected.
    Online,
    /// Disconnected in an orderly way.
    Offline,
    /// Disconnected unexpectedly (the last will).
    #[serde(rename = "CONNECTIONBROKEN")]
    ConnectionBroken,
}

/// A position on a map.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct NodePosition {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad in [-π, π]; absent: any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub theta: Option<f64>,
    /// How far from the node still counts as on it, m (vda-5050-lib spells it
    /// `allowedDeviationXy`).
    #[serde(
        rename = "allowedDeviationXY",
        alias = "allowedDeviationXy",
        skip_serializing_if = "Option::is_none"
    )]
    pub allowed_deviation_x_y: Option<f64>,
    /// How far from `theta` still counts, rad.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub allowed_deviation_theta: Option<f64>,
    /// The map.
    pub map_id: String,
    /// The map's description.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_description: Option<String>,
}

/// An action's parameter.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct ActionParameter {
    /// Name.
    pub key: String,
    /// Value: any JSON.
    pub value: serde_json::Value,
}

/// How an action blocks driving.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum BlockingType {
    /// Runs while driving.
    None,
    /// Stops driving, other actions may run.
    Soft,
    /// Stops driving and other actions.
    Hard,
}

/// An action on a node, an edge, or at once (`instantActions`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Action {
    /// What to do (`pick`, `cancelOrder`, ...).
    pub action_type: String,
    /// Unique id.
    pub action_id: String,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub action_description: Option<String>,
    /// Blocking.
    pub blocking_type: BlockingType,
    /// Parameters.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub action_parameters: Vec<ActionParameter>,
}

/// A node of an order.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Node {
    /// The node's id.
    pub node_id: String,
    /// Its place in the order: even numbers, 2 apart.
    pub sequence_id: u32,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub node_description: Option<String>,
    /// Base (true) or horizon (false).
    pub released: bool,
    /// Where it is (needed by free-navigating vehicles).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub node_position: Option<NodePosition>,
    /// Actions on arrival.
    pub actions: Vec<Action>,
}

/// An edge of an order.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Edge {
    /// The edge's id.
    pub edge_id: String,
    /// Odd numbers between its nodes'.
    pub sequence_id: u32,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub edge_description: Option<String>,
    /// Base or horizon.
    pub released: bool,
    /// Where it starts.
    pub start_node_id: String,
    /// Where it ends.
    pub end_node_id: String,
    /// Top speed on it, m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_speed: Option<f64>,
    /// Length, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub length: Option<f64>,
    /// Actions while on it.
    pub actions: Vec<Action>,
}

/// `order`: a graph of nodes and edges to drive, base (released) then horizon.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Order {
    /// The header.
    #[serde(flatten)]
    pub header: Header,
    /// The order.
    pub order_id: String,
    /// Its update, unique per order id.
    pub order_update_id: u32,
    /// Zones to use.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub zone_set_id: Option<String>,
    /// Nodes.
    pub nodes: Vec<Node>,
    /// Edges.
    pub edges: Vec<Edge>,
}

/// `instantActions`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct InstantActions {
    /// The header.
    #[serde(flatten)]
    pub header: Header,
    /// The actions.
    pub instant_actions: Vec<Action>,
}

/// Where a vehicle is.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct AgvPosition {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub theta: f64,
    /// The map.
    pub map_id: String,
    /// The map's description.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_description: Option<String>,
    /// Whether the vehicle knows where it is.
    pub position_initialized: bool,
    /// 0..1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub localization_score: Option<f64>,
    /// m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub deviation_range: Option<f64>,
}

/// A velocity in the vehicle's frame.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
pub struct Velocity {
    /// m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vx: Option<f64>,
    /// m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vy: Option<f64>,
    /// rad/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub omega: Option<f64>,
}

/// A node still to pass.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct NodeState {
    /// Id.
    pub node_id: String,
    /// Sequence id.
    pub sequence_id: u32,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub node_description: Option<String>,
    /// Where.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub node_position: Option<NodePosition>,
    /// Base or horizon.
    pub released: bool,
}

/// An edge still to drive.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct EdgeState {
    /// Id.
    pub edge_id: String,
    /// Sequence id.
    pub sequence_id: u32,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub edge_description: Option<String>,
    /// Base or horizon.
    pub released: bool,
}

/// Where an action stands.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum ActionStatus {
    /// Not started.
    Waiting,
    /// Being prepared.
    Initializing,
    /// Running.
    Running,
    /// Paused.
    Paused,
    /// Done.
    Finished,
    /// Failed.
    Failed,
}

/// One action's state.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct ActionState {
    /// Id.
    pub action_id: String,
    /// Type.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub action_type: Option<String>,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub action_description: Option<String>,
    /// Status.
    pub action_status: ActionStatus,
    /// Result.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub result_description: Option<String>,
}

/// Battery.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct BatteryState {
    /// State of charge, %.
    pub battery_charge: f64,
    /// V.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub battery_voltage: Option<f64>,
    /// % (0..100).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub battery_health: Option<f64>,
    /// Charging.
    pub charging: bool,
    /// m it can still drive.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reach: Option<f64>,
}

/// How bad an error is.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum ErrorLevel {
    /// The vehicle goes on.
    Warning,
    /// The vehicle needs help.
    Fatal,
}

/// What an error refers to.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct ErrorReference {
    /// E.g. `orderId`.
    pub reference_key: String,
    /// Its value.
    pub reference_value: String,
}

/// An error the vehicle reports.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct VdaError {
    /// E.g. `orderError`, `noRouteError`.
    pub error_type: String,
    /// What it refers to.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub error_references: Vec<ErrorReference>,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_description: Option<String>,
    /// Level.
    pub error_level: ErrorLevel,
}

impl VdaError {
    /// The value of reference `key`, if named.
    pub fn reference(&self, key: &str) -> Option<&str> {
        self.error_references
            .iter()
            .find(|r| r.reference_key == key)
            .map(|r| r.reference_value.as_str())
    }
}

/// Emergency stop kinds.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum EStop {
    /// Acknowledged by the vehicle itself.
    Autoack,
    /// Acknowledged by hand.
    Manual,
    /// Acknowledged remotely.
    Remote,
    /// None.
    None,
}

/// Safety.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct SafetyState {
    /// E-stop.
    pub e_stop: EStop,
    /// Protective field violated.
    pub field_violation: bool,
}

/// Who drives.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum OperatingMode {
    /// Master control.
    Automatic,
    /// Master control, with someone on board.
    Semiautomatic,
    /// By hand.
    Manual,
    /// Service.
    Service,
    /// Teach-in.
    Teachin,
}

/// An information entry.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Information {
    /// Type.
    pub info_type: String,
    /// Free text.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub info_description: Option<String>,
    /// `DEBUG` or `INFO`.
    pub info_level: String,
}

/// `state`: the vehicle's state, on every relevant event and at least every 30 s.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct State {
    /// The header.
    #[serde(flatten)]
    pub header: Header,
    /// The current (or last) order, empty if none.
    pub order_id: String,
    /// Its update.
    pub order_update_id: u32,
    /// Zones in use.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub zone_set_id: Option<String>,
    /// The last node reached (empty if none).
    pub last_node_id: String,
    /// Its sequence id (0 if none).
    pub last_node_sequence_id: u32,
    /// Driving now.
    pub driving: bool,
    /// Paused by an instant action or a button.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub paused: Option<bool>,
    /// Asks for more base.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub new_base_request: Option<bool>,
    /// m since the last node.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub distance_since_last_node: Option<f64>,
    /// Operating mode.
    pub operating_mode: OperatingMode,
    /// Nodes still to pass.
    pub node_states: Vec<NodeState>,
    /// Edges still to drive.
    pub edge_states: Vec<EdgeState>,
    /// Where it is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub agv_position: Option<AgvPosition>,
    /// How it moves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub velocity: Option<Velocity>,
    /// Loads on board.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub loads: Option<Vec<serde_json::Value>>,
    /// Actions of the order and instant actions.
    pub action_states: Vec<ActionState>,
    /// Battery.
    pub battery_state: BatteryState,
    /// Errors.
    pub errors: Vec<VdaError>,
    /// Information.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub information: Option<Vec<Information>>,
    /// Safety.
    pub safety_state: SafetyState,
}

/// `visualization`: the position, more often than `state`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Visualization {
    /// The header.
    #[serde(flatten)]
    pub header: Header,
    /// Where it is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub agv_position: Option<AgvPosition>,
    /// How it moves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub velocity: Option<Velocity>,
}

/// `factsheet`, read for what muster shows of a vehicle; the rest is kept as JSON.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Factsheet {
    /// The header.
    #[serde(flatten)]
    pub header: Header,
    /// Series, kinematics, class, ...
    #[serde(default)]
    pub type_specification: serde_json::Value,
    /// Speeds and size.
    #[serde(default)]
    pub physical_parameters: serde_json::Value,
}

impl Factsheet {
    /// The series name, if given.
    pub fn series(&self) -> Option<&str> {
        self.type_specification.get("seriesName")?.as_str()
    }
    /// Top speed, m/s, if given.
    pub fn speed_max(&self) -> Option<f64> {
        self.physical_parameters
            .get("speedMax")?
            .as_f64()
            .filter(|v| *v > 0.0)
    }
}

/// A message that can be checked beyond its shape.
pub trait Message: DeserializeOwned + Serialize {
    /// Its topic's name.
    const TOPIC: &'static str;
    /// The header.
    fn header(&self) -> &Header;
    /// The rules beyond the shape.
    fn rules(&self) -> Result<(), String> {
        Ok(())
    }
}

/// Reads and checks one message: shape, header, then the topic's own rules.
pub fn decode<M: Message>(bytes: &[u8]) -> Result<M, Invalid> {
    let m: M = serde_json::from_slice(bytes).map_err(|e| Invalid::Shape {
        topic: M::TOPIC,
        detail: e.to_string(),
    })?;
    m.header()
        .check()
        .and_then(|()| m.rules())
        .map_err(|detail| Invalid::Rule {
            topic: M::TOPIC,
            detail,
        })?;
    Ok(m)
}

/// Checks a message about to be sent, as [`decode`] would on the other side.
pub fn encode<M: Message>(m: &M) -> Result<Vec<u8>, Invalid> {
    m.header()
        .check()
        .and_then(|()| m.rules())
        .map_err(|detail| Invalid::Rule {
            topic: M::TOPIC,
            detail,
        })?;
    serde_json::to_vec(m).map_err(|e| Invalid::Shape {
        topic: M::TOPIC,
        detail: e.to_string(),
    })
}

fn finite(what: &str, v: f64) -> Result<(), String> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(format!("{what} is not a finite number"))
    }
}

fn theta(what: &str, v: f64) -> Result<(), String> {
    finite(what, v)?;
    // The schemas' range is [-π, π]; a rounding past it is taken.
    if v.abs() > std::f64::consts::PI + 1e-9 {
        return Err(format!("{what} {v} is outside [-π, π]"));
    }
    Ok(())
}

fn position(what: &str, p: &NodePosition) -> Result<(), String> {
    finite(&format!("{what}.x"), p.x)?;
    finite(&format!("{what}.y"), p.y)?;
    if let Some(t) = p.theta {
        theta(&format!("{what}.theta"), t)?;
    }
    for (n, v) in [
        ("allowedDeviationXY", p.allowed_deviation_x_y),
        ("allowedDeviationTheta", p.allowed_deviation_theta),
    ] {
        if let Some(v) = v {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{what}.{n} {v} is not a number ≥ 0"));
            }
        }
    }
    Ok(())
}

fn actions(what: &str, list: &[Action]) -> Result<(), String> {
    for a in list {
        if a.action_id.is_empty() || a.action_type.is_empty() {
            return Err(format!("{what}: an action without actionId or actionType"));
        }
    }
    Ok(())
}

impl Message for Connection {
    const TOPIC: &'static str = "connection";
    fn header(&self) -> &Header {
        &self.header
    }
}

impl Message for Factsheet {
    const TOPIC: &'static str = "factsheet";
    fn header(&self) -> &Header {
        &self.header
    }
}

impl Message for Visualization {
    const TOPIC: &'static str = "visualization";
    fn header(&self) -> &Header {
        &self.header
    }
    fn rules(&self) -> Result<(), String> {
        if let Some(p) = &self.agv_position {
            agv_position(p)?;
        }
        Ok(())
    }
}

fn agv_position(p: &AgvPosition) -> Result<(), String> {
    finite("agvPosition.x", p.x)?;
    finite("agvPosition.y", p.y)?;
    theta("agvPosition.theta", p.theta)?;
    if let Some(s) = p.localization_score {
        if !(0.0..=1.0).contains(&s) {
            return Err(format!(
                "agvPosition.localizationScore {s} is outside [0, 1]"
            ));
        }
    }
    Ok(())
}

impl Message for InstantActions {
    const TOPIC: &'static str = "instantActions";
    fn header(&self) -> &Header {
        &self.header
    }
    fn rules(&self) -> Result<(), String> {
        actions("instantActions", &self.instant_actions)
    }
}

impl Message for State {
    const TOPIC: &'static str = "state";
    fn header(&self) -> &Header {
        &self.header
    }
    fn rules(&self) -> Result<(), String> {
        if let Some(p) = &self.agv_position {
            agv_position(p)?;
        }
        // The schemas give the battery's charge and health no range (a percentage, by
        // the text): only a number is asked for.
        finite(
            "batteryState.batteryCharge",
            self.battery_state.battery_charge,
        )?;
        for n in &self.node_states {
            if let Some(p) = &n.node_position {
                position("nodeStates[].nodePosition", p)?;
            }
        }
        if let Some(d) = self.distance_since_last_node {
            finite("distanceSinceLastNode", d)?;
        }
        Ok(())
    }
}

impl Message for Order {
    const TOPIC: &'static str = "order";
    fn header(&self) -> &Header {
        &self.header
    }
    /// The graph's rules: at least one node, the first released; node sequence ids
    /// even and 2 apart, each edge's the odd one between its nodes; the base (released)
    /// before the horizon; one edge fewer than nodes, each joining its two nodes.
    fn rules(&self) -> Result<(), String> {
        if self.order_id.is_empty() {
            return Err("empty orderId".into());
        }
        let Some(first) = self.nodes.first() else {
            return Err("no nodes".into());
        };
        if !first.released {
            return Err("the first node is not released (no base)".into());
        }
        if first.sequence_id % 2 != 0 {
            return Err(format!("node sequenceId {} is odd", first.sequence_id));
        }
        if self.edges.len() + 1 != self.nodes.len() {
            return Err(format!(
                "{} nodes need {} edges, got {}",
                self.nodes.len(),
                self.nodes.len() - 1,
                self.edges.len()
            ));
        }
        let mut base = true;
        for (i, n) in self.nodes.iter().enumerate() {
            if n.node_id.is_empty() {
                return Err(format!("node {i} has an empty nodeId"));
            }
            if i > 0 && Some(n.sequence_id) != self.nodes[i - 1].sequence_id.checked_add(2) {
                return Err(format!(
                    "node {:?} has sequenceId {}, expected {}",
                    n.node_id,
                    n.sequence_id,
                    self.nodes[i - 1].sequence_id as u64 + 2
                ));
            }
            if n.released && !base {
                return Err(format!(
                    "released node {:?} after the horizon began",
                    n.node_id
                ));
            }
            base &= n.released;
            if let Some(p) = &n.node_position {
                position(&format!("node {:?}", n.node_id), p)?;
            }
            actions(&format!("node {:?}", n.node_id), &n.actions)?;
        }
        for (i, e) in self.edges.iter().enumerate() {
            let (a, b) = (&self.nodes[i], &self.nodes[i + 1]);
            if e.sequence_id != a.sequence_id + 1 {
                return Err(format!(
                    "edge {:?} has sequenceId {}, expected {}",
                    e.edge_id,
                    e.sequence_id,
                    a.sequence_id + 1
                ));
            }
            if e.start_node_id != a.node_id || e.end_node_id != b.node_id {
                return Err(format!(
                    "edge {:?} joins {:?}-{:?}, not its nodes {:?}-{:?}",
                    e.edge_id, e.start_node_id, e.end_node_id, a.node_id, b.node_id
                ));
            }
            if e.released && !b.released {
                return Err(format!(
                    "released edge {:?} ends on a horizon node",
                    e.edge_id
                ));
            }
            if !e.released && b.released {
                return Err(format!(
                    "horizon edge {:?} ends on a released node",
                    e.edge_id
                ));
            }
            if let Some(v) = e.max_speed {
                if !(v.is_finite() && v > 0.0) {
                    return Err(format!("edge {:?} maxSpeed {v} is not > 0", e.edge_id));
                }
            }
            actions(&format!("edge {:?}", e.edge_id), &e.actions)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state_json() -> serde_json::Value {
        serde_json::json!({
            "headerId": 4, "timestamp": "2026-11-27T06:00:00.120Z", "version": "2.0.0",
            "manufacturer": "acme", "serialNumber": "agv1",
            "orderId": "", "orderUpdateId": 0, "lastNodeId": "0", "lastNodeSequenceId": 0,
            "driving": false, "operatingMode": "AUTOMATIC", "nodeStates": [], "edgeStates": [],
            "agvPosition": {"x": 1.5, "y": -2.0, "theta": 0.5, "mapId": "local",
                            "positionInitialized": true},
            "actionStates": [], "batteryState": {"batteryCharge": 80.0, "charging": false},
            "errors": [], "safetyState": {"eStop": "NONE", "fieldViolation": false},
            "someExtension": {"kept": true}
        })
    }

    fn bytes(v: &serde_json::Value) -> Vec<u8> {
        serde_json::to_vec(v).unwrap()
    }

    #[test]
    fn a_state_is_read_with_its_values_and_extensions_let_through() {
        let s: State = decode(&bytes(&state_json())).unwrap();
        assert_eq!(s.header.serial_number, "agv1");
        assert_eq!(s.agv_position.as_ref().unwrap().x, 1.5);
        assert_eq!(s.battery_state.battery_charge, 80.0);
        assert_eq!(s.operating_mode, OperatingMode::Automatic);
    }

    #[test]
    fn bad_states_are_refused_with_the_reason() {
        let cases: [(&str, serde_json::Value, &str); 5] = [
            ("driving", serde_json::Value::Null, "driving"),
            ("version", "3.0.0".into(), "not 2.x"),
            ("timestamp", "yesterday".into(), "ISO 8601"),
            ("operatingMode", "FLYING".into(), "unknown variant"),
            (
                "agvPosition",
                serde_json::json!({"x": 0.0, "y": 0.0, "theta": 4.0, "mapId": "m",
                                   "positionInitialized": true}),
                "outside [-π, π]",
            ),
        ];
        for (field, value, why) in cases {
            let mut j = state_json();
            if value.is_null() {
                j.as_object_mut().unwrap().remove(field);
            } else {
                j[field] = value;
            }
            let e = decode::<State>(&bytes(&j)).unwrap_err().to_string();
            assert!(e.contains(why), "{field}: {e}");
        }
        assert!(decode::<State>(b"{not json").is_err());
    }

    fn order(nodes: &[(&str, u32, bool)], edges: &[(u32, &str, &str, bool)]) -> Order {
        Order {
            header: Header::now(1, "2.0.0", "acme", "agv1"),
            order_id: "o1".into(),
            order_update_id: 0,
            zone_set_id: None,
            nodes: nodes
                .iter()
                .map(|(id, seq, rel)| Node {
                    node_id: id.to_string(),
                    sequence_id: *seq,
                    node_description: None,
                    released: *rel,
                    node_position: None,
                    actions: vec![],
                })
                .collect(),
            edges: edges
                .iter()
                .map(|(seq, a, b, rel)| Edge {
                    edge_id: format!("{a}{b}"),
                    sequence_id: *seq,
                    edge_description: None,
                    released: *rel,
                    start_node_id: a.to_string(),
                    end_node_id: b.to_string(),
                    max_speed: None,
                    length: None,
                    actions: vec![],
                })
                .collect(),
        }
    }

    #[test]
    fn order_graph_rules_hold_both_ways() {
        let good = order(
            &[("a", 0, true), ("b", 2, true), ("c", 4, false)],
            &[(1, "a", "b", true), (3, "b", "c", false)],
        );
        let wire = encode(&good).unwrap();
        assert_eq!(decode::<Order>(&wire).unwrap(), good);
        let bad = [
            (order(&[], &[]), "no nodes"),
            (order(&[("a", 0, false)], &[]), "not released"),
            (order(&[("a", 1, true)], &[]), "odd"),
            (
                order(&[("a", 0, true), ("b", 4, true)], &[(1, "a", "b", true)]),
                "expected 2",
            ),
            (
                order(&[("a", 0, true), ("b", 2, true)], &[(1, "a", "c", true)]),
                "not its nodes",
            ),
            (
                order(
                    &[("a", 0, true), ("b", 2, false), ("c", 4, true)],
                    &[(1, "a", "b", false), (3, "b", "c", true)],
                ),
                "after the horizon",
            ),
            (
                order(&[("a", 0, true), ("b", 2, true)], &[]),
                "need 1 edges",
            ),
        ];
        for (o, why) in bad {
            let e = encode(&o).unwrap_err().to_string();
            assert!(e.contains(why), "{why}: {e}");
            let raw = serde_json::to_vec(&o).unwrap();
            assert!(decode::<Order>(&raw).unwrap_err().to_string().contains(why));
        }
    }

    #[test]
    fn connection_states_and_versions() {
        let c = Connection {
            header: Header::now(0, "2.1.0", "acme", "agv1"),
            connection_state: ConnectionState::ConnectionBroken,
        };
        let wire = String::from_utf8(encode(&c).unwrap()).unwrap();
        assert!(
            wire.contains(r#""connectionState":"CONNECTIONBROKEN""#),
            "{wire}"
        );
        assert!(wire.contains(r#""serialNumber":"agv1""#), "{wire}");
        assert!(version_supported("2.0.0") && version_supported("2.1.0"));
        assert!(
            !version_supported("1.1.0") && !version_supported("2.x") && !version_supported("2.")
        );
    }
}
