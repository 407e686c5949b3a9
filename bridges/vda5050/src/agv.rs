//! muster's robots as VDA 5050 vehicles: `muster agv --mqtt HOST:PORT --robots D1,...`.
//!
//! Each robot (the simulator's, or a ROS 2 robot behind the same port) connects to the
//! MQTT broker as its own vehicle (serial number = robot name): `connection` retained
//! with the last will `CONNECTIONBROKEN`, `factsheet` retained, `state` on every event
//! and at least every 30 s, `visualization` once a second. It takes `order`s (base and
//! horizon; updates stitched onto the base end, as the specification's rules say) and
//! drives the base node by node with the delivery robot's planner and safety
//! ([`DeliveryDriver`]); it answers `instantActions`: `startPause`, `stopPause`,
//! `cancelOrder`, `stateRequest`, `factsheetRequest`. Node and edge actions are not
//! supported: each is reported `FAILED` with the reason. The simulator has no battery:
//! the charge is reported as 100 %.
//!
//! [`AgvCore`] is the protocol's bookkeeping with no I/O; [`run_agvs`] runs the robots.

use crate::mqtt::{Incoming, MqttConfig, MqttLink, MqttSecurity};
use crate::msg::{
    self, Action, ActionState, ActionStatus, AgvPosition, BatteryState, Connection,
    ConnectionState, EStop, Edge, EdgeState, ErrorLevel, ErrorReference, Header, InstantActions,
    Node, NodeState, OperatingMode, Order, SafetyState, State, VdaError, Velocity, Visualization,
};
use crate::{Topics, VdaFail};
use muster_robots::delivery::DeliveryEvent;
use muster_robots::shell::DeliveryDriver;
use muster_shared::reactor::{Reactor, SignalPipe};
use std::time::{Duration, Instant};

/// How the vehicles speak.
#[derive(Clone, Debug)]
pub struct AgvOptions {
    /// `host:port` of the MQTT broker.
    pub mqtt: String,
    /// `interfaceName` of the topics.
    pub interface: String,
    /// The vehicles' manufacturer.
    pub manufacturer: String,
    /// The version written (2.x.y).
    pub version: String,
    /// The map the robots' positions are on.
    pub map_id: String,
    /// A node counts as reached within this distance, m (unless the order allows more);
    /// a new order's first node must be this close to the vehicle.
    pub deviation: f64,
    /// State at least this often.
    pub state_every: Duration,
    /// Visualization this often (`None`: none).
    pub visualization_every: Option<Duration>,
    /// TLS and credentials for the MQTT broker.
    pub security: MqttSecurity,
    /// JSON schemas every message read and written must also pass (`--vda-schemas`).
    pub schemas: Option<std::sync::Arc<crate::schemas::Schemas>>,
}

impl AgvOptions {
    /// Defaults for the broker at `mqtt`: interface `uagv`, manufacturer `muster`,
    /// version 2.1.0, map `muster`, 0.5 m, state every 30 s, visualization every 1 s.
    pub fn new(mqtt: &str) -> Self {
        AgvOptions {
            mqtt: mqtt.into(),
            interface: "uagv".into(),
            manufacturer: "muster".into(),
            version: "2.1.0".into(),
            map_id: "muster".into(),
            deviation: 0.5,
            state_every: Duration::from_secs(30),
            visualization_every: Some(Duration::from_secs(1)),
            security: MqttSecurity::default(),
            schemas: None,
        }
    }
}

/// The instant actions a vehicle takes.
pub const INSTANT_ACTIONS: [&str; 5] = [
    "startPause",
    "stopPause",
    "cancelOrder",
    "stateRequest",
    "factsheetRequest",
];

/// What an instant action asks of the vehicle beyond its state.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Effect {
    /// Send the state now.
    State,
    /// Send the factsheet.
    Factsheet,
}

/// One vehicle's protocol state: the order it holds, the nodes and edges left, the
/// actions' states, its errors, pause.
#[derive(Clone, Debug)]
pub struct AgvCore {
    manufacturer: String,
    serial: String,
    version: String,
    map_id: String,
    deviation: f64,
    order_id: String,
    order_update_id: u32,
    /// Nodes not yet traversed (base, then horizon).
    nodes: Vec<Node>,
    /// Edges not yet traversed.
    edges: Vec<Edge>,
    last_node_id: String,
    last_node_seq: u32,
    actions: Vec<ActionState>,
    errors: Vec<VdaError>,
    paused: bool,
    /// Something changed that the state must say.
    pub dirty: bool,
}

/// Most instant actions' states kept (the oldest ended ones go first).
const MAX_ACTION_STATES: usize = 32;

impl AgvCore {
    /// A vehicle with no order, standing on no node.
    pub fn new(opts: &AgvOptions, serial: &str) -> Self {
        AgvCore {
            manufacturer: opts.manufacturer.clone(),
            serial: serial.into(),
            version: opts.version.clone(),
            map_id: opts.map_id.clone(),
            deviation: opts.deviation,
            order_id: String::new(),
            order_update_id: 0,
            nodes: Vec::new(),
            edges: Vec::new(),
            last_node_id: String::new(),
            last_node_seq: 0,
            actions: Vec::new(),
            errors: Vec::new(),
            paused: false,
            dirty: true,
        }
    }

    /// A header for a message of this vehicle.
    pub fn header(&self, id: u32) -> Header {
        Header::now(id, &self.version, &self.manufacturer, &self.serial)
    }

    /// Whether base (released) nodes are left to drive.
    pub fn active(&self) -> bool {
        self.nodes.iter().any(|n| n.released)
    }

    /// Where to drive now: the next released node (none while paused).
    pub fn target(&self) -> Option<(f64, f64)> {
        if self.paused {
            return None;
        }
        let n = self.nodes.first().filter(|n| n.released)?;
        n.node_position.as_ref().map(|p| (p.x, p.y))
    }

    /// The id of the next node, if any.
    pub fn target_node(&self) -> Option<&str> {
        self.nodes.first().map(|n| n.node_id.as_str())
    }

    /// How close the next node must be reached, m.
    pub fn tolerance(&self) -> f64 {
        self.nodes
            .first()
            .and_then(|n| n.node_position.as_ref()?.allowed_deviation_x_y)
            .filter(|d| *d > 0.0)
            .unwrap_or(self.deviation)
    }

    fn refuse(&mut self, o: &Order, error_type: &str, why: String) {
        tracing::info!(vehicle = %self.serial, order = %o.order_id, "order refused: {why}");
        self.errors.push(VdaError {
            error_type: error_type.into(),
            error_references: vec![
                reference("headerId", o.header.header_id.to_string()),
                reference("orderId", o.order_id.clone()),
                reference("orderUpdateId", o.order_update_id.to_string()),
            ],
            error_description: Some(why),
            error_level: ErrorLevel::Warning,
        });
        self.dirty = true;
    }

    /// Takes an order (checked by [`msg::decode`]) while the vehicle stands at `at`:
    /// accepted (its nodes to drive), discarded (the same update again), or refused with
    /// an error in the state naming it.
    pub fn order(&mut self, o: Order, at: (f64, f64)) -> bool {
        // Free navigation: every node after the first needs a position on our map.
        if let Some(n) = o.nodes.iter().skip(1).find(|n| n.node_position.is_none()) {
            let why = format!("node {:?} has no nodePosition (free navigation)", n.node_id);
            self.refuse(&o, "noRouteError", why);
            return false;
        }
        if let Some(p) = o
            .nodes
            .iter()
            .filter_map(|n| n.node_position.as_ref())
            .find(|p| p.map_id != self.map_id)
        {
            let why = format!(
                "map {:?} is not this vehicle's ({:?})",
                p.map_id, self.map_id
            );
            self.refuse(&o, "noRouteError", why);
            return false;
        }
        let first = &o.nodes[0];
        let stitch_on = |nodes: &[Node], last: (&str, u32)| -> bool {
            // The end of the base this vehicle holds, or the node it last reached.
            let base_end = nodes
                .iter()
                .take_while(|n| n.released)
                .last()
                .map(|n| (n.node_id.as_str(), n.sequence_id))
                .unwrap_or(last);
            base_end == (first.node_id.as_str(), first.sequence_id)
        };
        let last = (self.last_node_id.as_str(), self.last_node_seq);
        if o.order_id == self.order_id {
            if o.order_update_id < self.order_update_id {
                let why = format!(
                    "orderUpdateId {} is older than {}",
                    o.order_update_id, self.order_update_id
                );
                self.refuse(&o, "orderUpdateError", why);
                return false;
            }
            if o.order_update_id == self.order_update_id {
                self.dirty = true; // the same update again: say where we are
                return false;
            }
            if !stitch_on(&self.nodes, last) {
                let why = "the update does not start on the end of the base".to_string();
                self.refuse(&o, "orderUpdateError", why);
                return false;
            }
        } else if self.active() {
            if !stitch_on(&self.nodes, last) {
                let why =
                    "an order is active and the new one does not start on its base end".to_string();
                self.refuse(&o, "orderError", why);
                return false;
            }
        } else {
            let near = first.node_position.as_ref().is_none_or(|p| {
                let allowed = p
                    .allowed_deviation_x_y
                    .filter(|d| *d > 0.0)
                    .unwrap_or(self.deviation);
                (p.x - at.0).hypot(p.y - at.1) <= allowed
            });
            if !near {
                let why = format!(
                    "the first node {:?} is not where the vehicle stands ({:.2}, {:.2})",
                    first.node_id, at.0, at.1
                );
                self.refuse(&o, "noRouteError", why);
                return false;
            }
        }
        // Accepted: errors of earlier orders and messages go, the horizon held is replaced.
        self.errors
            .retain(|e| e.reference("orderId").is_none() && e.error_type != "validationError");
        let stitching = o.order_id == self.order_id || self.active();
        self.order_id = o.order_id.clone();
        self.order_update_id = o.order_update_id;
        self.nodes.retain(|n| n.released);
        self.edges.retain(|e| e.released);
        if !stitching {
            self.actions.retain(|a| {
                a.action_type
                    .as_deref()
                    .is_some_and(|t| INSTANT_ACTIONS.contains(&t))
            });
            self.nodes.clear();
            self.edges.clear();
        }
        let mut nodes = o.nodes.into_iter();
        let first = nodes.next().expect("checked: one node at least");
        for a in &first.actions {
            self.unsupported(a);
        }
        for n in nodes {
            for a in &n.actions {
                self.actions
                    .push(action_state(a, ActionStatus::Waiting, None));
            }
            self.nodes.push(n);
        }
        for e in o.edges {
            for a in &e.actions {
                self.actions
                    .push(action_state(a, ActionStatus::Waiting, None));
            }
            self.edges.push(e);
        }
        if !stitching {
            // A new order starts on the node the vehicle stands on: traversed now.
            self.last_node_id = first.node_id;
            self.last_node_seq = first.sequence_id;
        }
        self.dirty = true;
        true
    }

    /// Node and edge actions are not supported: failed, with the reason.
    fn unsupported(&mut self, a: &Action) {
        let why = format!(
            "action {:?} is not supported by this vehicle",
            a.action_type
        );
        match self.actions.iter_mut().find(|s| s.action_id == a.action_id) {
            Some(s) => {
                s.action_status = ActionStatus::Failed;
                s.result_description = Some(why);
            }
            None => self
                .actions
                .push(action_state(a, ActionStatus::Failed, Some(why))),
        }
    }

    /// The next node is reached: it and the edge to it are traversed.
    pub fn reached(&mut self) {
        if self.nodes.first().is_none_or(|n| !n.released) {
            return;
        }
        let n = self.nodes.remove(0);
        if let Some(i) = self
            .edges
            .iter()
            .position(|e| e.end_node_id == n.node_id && e.sequence_id + 1 == n.sequence_id)
        {
            let e = self.edges.remove(i);
            for a in &e.actions {
                self.unsupported(a);
            }
        }
        for a in &n.actions {
            self.unsupported(a);
        }
        self.last_node_id = n.node_id;
        self.last_node_seq = n.sequence_id;
        self.dirty = true;
    }

    /// The next node cannot be reached: a fatal `noRouteError` naming it; the order
    /// stays for the master to cancel or replace.
    pub fn unreachable(&mut self, why: &str) {
        let node = self.target_node().unwrap_or_default().to_string();
        if self
            .errors
            .iter()
            .any(|e| e.error_type == "noRouteError" && e.reference("nodeId") == Some(node.as_str()))
        {
            return;
        }
        self.errors.push(VdaError {
            error_type: "noRouteError".into(),
            error_references: vec![
                reference("orderId", self.order_id.clone()),
                reference("nodeId", node),
            ],
            error_description: Some(why.chars().take(200).collect()),
            error_level: ErrorLevel::Fatal,
        });
        self.dirty = true;
    }

    /// A message on `topic` was refused (bad JSON, broken rules, another vehicle's): the
    /// state says so with a `validationError` (the newest one only).
    pub fn invalid_message(&mut self, topic: &str, why: &str) {
        self.errors.retain(|e| e.error_type != "validationError");
        self.errors.push(VdaError {
            error_type: "validationError".into(),
            error_references: vec![reference("topic", topic.to_string())],
            error_description: Some(why.chars().take(200).collect()),
            error_level: ErrorLevel::Warning,
        });
        self.dirty = true;
    }

    /// Takes instant actions; what else the vehicle must do.
    pub fn instant(&mut self, ia: InstantActions) -> Vec<Effect> {
        let mut effects = Vec::new();
        for a in ia.instant_actions {
            let (status, why) = match a.action_type.as_str() {
                "startPause" | "stopPause" => {
                    self.paused = a.action_type == "startPause";
                    (ActionStatus::Finished, None)
                }
                "cancelOrder" if self.active() || self.nodes.iter().any(|n| !n.released) => {
                    self.nodes.clear();
                    self.edges.clear();
                    for s in &mut self.actions {
                        if matches!(
                            s.action_status,
                            ActionStatus::Waiting
                                | ActionStatus::Initializing
                                | ActionStatus::Running
                                | ActionStatus::Paused
                        ) {
                            s.action_status = ActionStatus::Failed;
                            s.result_description = Some("order cancelled".into());
                        }
                    }
                    (ActionStatus::Finished, None)
                }
                "cancelOrder" => {
                    self.errors.push(VdaError {
                        error_type: "noOrderToCancel".into(),
                        error_references: vec![reference("actionId", a.action_id.clone())],
                        error_description: Some("no order to cancel".into()),
                        error_level: ErrorLevel::Warning,
                    });
                    (ActionStatus::Failed, Some("no order to cancel".to_string()))
                }
                "stateRequest" => {
                    effects.push(Effect::State);
                    (ActionStatus::Finished, None)
                }
                "factsheetRequest" => {
                    effects.push(Effect::Factsheet);
                    (ActionStatus::Finished, None)
                }
                other => {
                    let why = format!("instant action {other:?} is not supported");
                    self.errors.push(VdaError {
                        error_type: "unsupportedActionError".into(),
                        error_references: vec![
                            reference("actionId", a.action_id.clone()),
                            reference("actionType", other.to_string()),
                        ],
                        error_description: Some(why.clone()),
                        error_level: ErrorLevel::Warning,
                    });
                    (ActionStatus::Failed, Some(why))
                }
            };
            self.actions.retain(|s| s.action_id != a.action_id);
            self.actions.push(action_state(&a, status, why));
        }
        // Keep the newest instant actions' states.
        while self.actions.len() > MAX_ACTION_STATES {
            let Some(i) = self.actions.iter().position(|s| {
                matches!(
                    s.action_status,
                    ActionStatus::Finished | ActionStatus::Failed
                )
            }) else {
                break;
            };
            self.actions.remove(i);
        }
        self.dirty = true;
        effects
    }

    /// The state, with the vehicle at `pose` moving at `velocity`.
    pub fn state(&self, header_id: u32, pose: (f64, f64, f64), velocity: (f64, f64)) -> State {
        let driving = velocity.0.abs() > 1e-3 || velocity.1.abs() > 1e-3;
        State {
            header: self.header(header_id),
            order_id: self.order_id.clone(),
            order_update_id: self.order_update_id,
            zone_set_id: None,
            last_node_id: self.last_node_id.clone(),
            last_node_sequence_id: self.last_node_seq,
            driving,
            paused: Some(self.paused),
            new_base_request: Some(!self.active() && !self.nodes.is_empty()),
            distance_since_last_node: None,
            operating_mode: OperatingMode::Automatic,
            node_states: self
                .nodes
                .iter()
                .map(|n| NodeState {
                    node_id: n.node_id.clone(),
                    sequence_id: n.sequence_id,
                    node_description: n.node_description.clone(),
                    node_position: n.node_position.clone(),
                    released: n.released,
                })
                .collect(),
            edge_states: self
                .edges
                .iter()
                .map(|e| EdgeState {
                    edge_id: e.edge_id.clone(),
                    sequence_id: e.sequence_id,
                    edge_description: e.edge_description.clone(),
                    released: e.released,
                })
                .collect(),
            agv_position: Some(self.position(pose)),
            velocity: Some(moving(velocity)),
            loads: None,
            action_states: self.actions.clone(),
            battery_state: BatteryState {
                battery_charge: 100.0,
                battery_voltage: None,
                battery_health: None,
                charging: false,
                reach: None,
            },
            errors: self.errors.clone(),
            information: None,
            safety_state: SafetyState {
                e_stop: EStop::None,
                field_violation: false,
            },
        }
    }

    fn position(&self, pose: (f64, f64, f64)) -> AgvPosition {
        AgvPosition {
            x: pose.0,
            y: pose.1,
            theta: muster_world_model::wrap(pose.2),
            map_id: self.map_id.clone(),
            map_description: None,
            position_initialized: true,
            localization_score: None,
            deviation_range: None,
        }
    }

    /// The visualization message.
    pub fn visualization(
        &self,
        header_id: u32,
        pose: (f64, f64, f64),
        velocity: (f64, f64),
    ) -> Visualization {
        Visualization {
            header: self.header(header_id),
            agv_position: Some(self.position(pose)),
            velocity: Some(moving(velocity)),
        }
    }

    /// The factsheet of a robot of radius `radius` m, top speed `speed` m/s.
    pub fn factsheet(
        &self,
        header_id: u32,
        radius: f64,
        speed: f64,
        state_every: Duration,
    ) -> serde_json::Value {
        let mut j = serde_json::to_value(self.header(header_id)).expect("a header is JSON");
        let actions: Vec<serde_json::Value> = INSTANT_ACTIONS
            .iter()
            .map(|t| serde_json::json!({"actionType": t, "actionScopes": ["INSTANT"]}))
            .collect();
        let extra = serde_json::json!({
            "typeSpecification": {
                "seriesName": "muster simulated delivery robot",
                "seriesDescription": "differential drive, laser and sonar, planner and safety of muster's delivery robot",
                "agvKinematic": "DIFF", "agvClass": "CARRIER", "maxLoadMass": 0,
                "localizationTypes": ["NATURAL"], "navigationTypes": ["AUTONOMOUS"]
            },
            "physicalParameters": {
                "speedMin": 0.0, "speedMax": speed, "accelerationMax": 1.0, "decelerationMax": 1.0,
                "heightMin": 0.3, "heightMax": 0.5, "width": 2.0 * radius, "length": 2.0 * radius
            },
            "protocolLimits": {
                "maxStringLens": {}, "maxArrayLens": {},
                "timing": {"minOrderInterval": 0.1, "minStateInterval": 0.05,
                           "defaultStateInterval": state_every.as_secs_f64(), "visualizationInterval": 1.0}
            },
            "protocolFeatures": {"optionalParameters": [], "agvActions": actions},
            "agvGeometry": {}, "loadSpecification": {}
        });
        if let (Some(o), Some(e)) = (j.as_object_mut(), extra.as_object()) {
            o.extend(e.clone());
        }
        j
    }
}

/// A differential drive's velocity (v m/s, w rad/s) as VDA 5050 says it.
fn moving((v, w): (f64, f64)) -> Velocity {
    Velocity {
        vx: Some(v),
        vy: Some(0.0),
        omega: Some(w),
    }
}

fn reference(key: &str, value: String) -> ErrorReference {
    ErrorReference {
        reference_key: key.into(),
        reference_value: value,
    }
}

fn action_state(a: &Action, status: ActionStatus, why: Option<String>) -> ActionState {
    ActionState {
        action_id: a.action_id.clone(),
        action_type: Some(a.action_type.clone()),
        action_description: a.action_description.clone(),
        action_status: status,
        result_description: why,
    }
}

/// One robot on the wire.
struct Vehicle {
    core: AgvCore,
    driver: DeliveryDriver,
    link: MqttLink,
    topics: Topics,
    goal: Option<(f64, f64)>,
    headers: [u32; 4],
    next_state: Instant,
    next_vis: Instant,
    invalid: u64,
    driving: bool,
    schemas: Option<std::sync::Arc<crate::schemas::Schemas>>,
}

const H_STATE: usize = 0;
const H_VIS: usize = 1;
const H_CONNECTION: usize = 2;
const H_FACTSHEET: usize = 3;

impl Vehicle {
    fn topic(&self, t: &str) -> String {
        self.topics
            .topic(&self.core.manufacturer, &self.core.serial, t)
    }

    fn next_header(&mut self, which: usize) -> u32 {
        let h = self.headers[which];
        self.headers[which] = h.wrapping_add(1);
        h
    }

    fn pose(&self) -> (f64, f64, f64) {
        let p = self.driver.pose();
        (p.x, p.y, p.theta)
    }

    fn send(&mut self, topic: &str, bytes: Result<Vec<u8>, String>, retain: bool) {
        let t = self.topic(topic);
        let checked = bytes.and_then(|b| match &self.schemas {
            Some(s) => s.check_bytes(topic, &b).map(|()| b),
            None => Ok(b),
        });
        if let Err(e) = checked.and_then(|b| self.link.publish(&t, b, retain)) {
            tracing::warn!(topic = %t, "not sent: {e}");
        }
    }

    fn publish_state(&mut self, opts: &AgvOptions) {
        let id = self.next_header(H_STATE);
        let st = self.core.state(id, self.pose(), self.driver.last_command());
        self.send("state", msg::encode(&st).map_err(|e| e.to_string()), false);
        self.core.dirty = false;
        self.next_state = Instant::now() + opts.state_every;
    }

    fn publish_connection(&mut self, c: ConnectionState) {
        let id = self.next_header(H_CONNECTION);
        let m = Connection {
            header: self.core.header(id),
            connection_state: c,
        };
        self.send(
            "connection",
            msg::encode(&m).map_err(|e| e.to_string()),
            true,
        );
    }

    fn publish_factsheet(&mut self, opts: &AgvOptions) {
        let id = self.next_header(H_FACTSHEET);
        let d = self.driver.description();
        let f = self
            .core
            .factsheet(id, d.radius, d.max_speed.min(0.8), opts.state_every);
        self.send(
            "factsheet",
            serde_json::to_vec(&f).map_err(|e| e.to_string()),
            true,
        );
    }

    /// Drives to the next node (skipping nodes already within reach), or halts.
    fn retarget(&mut self) {
        loop {
            let target = self.core.target();
            if let Some(t) = target {
                let p = self.driver.pose();
                if (t.0 - p.x).hypot(t.1 - p.y) <= self.core.tolerance() {
                    self.core.reached();
                    continue;
                }
            }
            if target == self.goal {
                return;
            }
            self.goal = target;
            match target {
                Some(t) => {
                    for e in self.driver.set_goal(t) {
                        if let DeliveryEvent::Unreachable { reason, .. } = e {
                            self.core.unreachable(&reason);
                        }
                    }
                }
                None => self.driver.halt(),
            }
            return;
        }
    }

    fn on_sample(&mut self) {
        let tasked = self.goal.is_some();
        let Some(events) = self.driver.step(tasked) else {
            return;
        };
        for e in events {
            match e {
                DeliveryEvent::Arrived { .. } => {
                    self.goal = None;
                    self.core.reached();
                }
                DeliveryEvent::Unreachable { reason, .. } => self.core.unreachable(&reason),
                _ => {}
            }
        }
        self.retarget();
        // Started or stopped driving: the state says so.
        let (v, w) = self.driver.last_command();
        let driving = v.abs() > 1e-3 || w.abs() > 1e-3;
        if driving != std::mem::replace(&mut self.driving, driving) {
            self.core.dirty = true;
        }
    }

    fn on_mqtt(&mut self, opts: &AgvOptions) {
        let got = self.link.drain();
        tracing::trace!(n = got.len(), "MQTT drained");
        for m in got {
            match m {
                Incoming::Connected => {
                    self.publish_connection(ConnectionState::Online);
                    self.publish_factsheet(opts);
                    self.core.dirty = true;
                }
                Incoming::Down(why) => {
                    tracing::warn!(vehicle = %self.core.serial, "MQTT down: {why}")
                }
                Incoming::Publish { topic, payload, .. } => self.on_message(opts, &topic, &payload),
            }
        }
    }

    fn on_message(&mut self, opts: &AgvOptions, topic: &str, payload: &[u8]) {
        let Some((_, _, kind)) = self.topics.parse(topic) else {
            return;
        };
        if let Some(Err(why)) = self.schemas.as_ref().map(|s| s.check_bytes(kind, payload)) {
            return self.refused(topic, kind, &why);
        }
        let ours = |h: &Header, core: &AgvCore| {
            if h.manufacturer == core.manufacturer && h.serial_number == core.serial {
                Ok(())
            } else {
                Err(format!(
                    "header names {}/{}",
                    h.manufacturer, h.serial_number
                ))
            }
        };
        let result = match kind {
            "order" => msg::decode::<Order>(payload)
                .map_err(|e| e.to_string())
                .and_then(|o| {
                    ours(&o.header, &self.core)?;
                    let p = self.driver.pose();
                    if self.core.order(o, (p.x, p.y)) {
                        self.goal = None; // a new base: plan again
                        self.retarget();
                    }
                    Ok(())
                }),
            "instantActions" => msg::decode::<InstantActions>(payload)
                .map_err(|e| e.to_string())
                .and_then(|ia| {
                    ours(&ia.header, &self.core)?;
                    for e in self.core.instant(ia) {
                        match e {
                            Effect::State => self.core.dirty = true,
                            Effect::Factsheet => self.publish_factsheet(opts),
                        }
                    }
                    self.retarget();
                    Ok(())
                }),
            _ => return,
        };
        if let Err(why) = result {
            self.refused(topic, kind, &why);
        }
    }

    /// A message not taken: counted, logged, and said in the next state.
    fn refused(&mut self, topic: &str, kind: &str, why: &str) {
        self.invalid += 1;
        if self.invalid <= 20 || self.invalid.is_power_of_two() {
            tracing::warn!(%topic, invalid = self.invalid, "VDA 5050 message refused: {why}");
        }
        self.core.invalid_message(kind, why);
    }
}

/// Counters of a run.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct AgvStats {
    /// Messages refused (each logged with its reason).
    pub invalid: u64,
    /// States sent, all vehicles.
    pub states: u64,
}

/// Runs `drivers` (one per robot; the robot's name is its serial number) as VDA 5050
/// vehicles until SIGINT or SIGTERM; then says `OFFLINE` and disconnects.
pub fn run_agvs(opts: &AgvOptions, drivers: Vec<DeliveryDriver>) -> Result<AgvStats, VdaFail> {
    if !msg::version_supported(&opts.version) {
        return Err(VdaFail::Config(format!(
            "version {:?} is not 2.x",
            opts.version
        )));
    }
    let topics = Topics::v2(&opts.interface);
    let mut vehicles = Vec::new();
    for driver in drivers {
        let serial = driver.robot().to_string();
        let core = AgvCore::new(opts, &serial);
        let will = Connection {
            header: core.header(0),
            connection_state: ConnectionState::ConnectionBroken,
        };
        let will = msg::encode(&will).map_err(|e| VdaFail::Config(e.to_string()))?;
        if let Some(s) = &opts.schemas {
            s.check_bytes("connection", &will)
                .map_err(|e| VdaFail::Config(format!("the last will: {e}")))?;
        }
        let cfg = MqttConfig {
            broker: opts.mqtt.clone(),
            security: opts.security.clone(),
            client_id: format!("{}-{}-{}", opts.manufacturer, serial, std::process::id()),
            keep_alive: Duration::from_secs(5),
            subscriptions: ["order", "instantActions"]
                .iter()
                .map(|t| topics.topic(&opts.manufacturer, &serial, t))
                .collect(),
            will: Some((
                topics.topic(&opts.manufacturer, &serial, "connection"),
                will,
                true,
            )),
        };
        let link = MqttLink::connect(&cfg)?;
        vehicles.push(Vehicle {
            core,
            driver,
            link,
            topics: topics.clone(),
            goal: None,
            headers: [0, 0, 1, 0],
            next_state: Instant::now(),
            next_vis: Instant::now(),
            invalid: 0,
            driving: false,
            schemas: opts.schemas.clone(),
        });
    }
    let os = |e: std::io::Error| VdaFail::Config(format!("os: {e}"));
    let mut signals = SignalPipe::install().map_err(os)?;
    let mut reactor = Reactor::new().map_err(os)?;
    const SIGNAL: usize = usize::MAX;
    reactor.add(signals.raw(), SIGNAL).map_err(os)?;
    for (i, v) in vehicles.iter().enumerate() {
        reactor.add(v.driver.fd(), 2 * i).map_err(os)?;
        reactor.add(v.link.fd(), 2 * i + 1).map_err(os)?;
    }
    tracing::info!(vehicles = vehicles.len(), mqtt = %opts.mqtt, "VDA 5050 vehicles up");
    loop {
        let now = Instant::now();
        let next = vehicles
            .iter()
            .flat_map(|v| {
                [
                    Some(v.next_state),
                    opts.visualization_every.map(|_| v.next_vis),
                ]
            })
            .flatten()
            .min()
            .unwrap_or(now + Duration::from_secs(1));
        let ready = reactor
            .wait(Some(next.saturating_duration_since(now)))
            .map_err(os)?;
        tracing::trace!(?ready, "woke");
        if ready.contains(&SIGNAL) && signals.drain() {
            break;
        }
        for token in ready {
            let Some(v) = vehicles.get_mut(token / 2) else {
                continue;
            };
            match token % 2 {
                0 => v.on_sample(),
                _ => v.on_mqtt(opts),
            }
        }
        let now = Instant::now();
        for v in &mut vehicles {
            if v.core.dirty || now >= v.next_state {
                v.publish_state(opts);
            }
            if let Some(every) = opts.visualization_every {
                if now >= v.next_vis {
                    v.next_vis = now + every;
                    let id = v.next_header(H_VIS);
                    let m = v.core.visualization(id, v.pose(), v.driver.last_command());
                    v.send(
                        "visualization",
                        msg::encode(&m).map_err(|e| e.to_string()),
                        false,
                    );
                }
            }
        }
    }
    let mut stats = AgvStats::default();
    for v in &mut vehicles {
        v.driver.stop();
        v.publish_connection(ConnectionState::Offline);
        v.link.close();
        stats.invalid += v.invalid;
        stats.states += v.headers[H_STATE] as u64;
    }
    tracing::info!("VDA 5050 vehicles offline");
    Ok(stats)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::msg::{BlockingType, NodePosition};

    fn core() -> AgvCore {
        AgvCore::new(&AgvOptions::new("x:1"), "D1")
    }

    fn node(id: &str, seq: u32, x: f64, released: bool) -> Node {
        Node {
            node_id: id.into(),
            sequence_id: seq,
            node_description: None,
            released,
            node_position: Some(NodePosition {
                x,
                y: 0.0,
                theta: None,
                allowed_deviation_x_y: None,
                allowed_deviation_theta: None,
                map_id: "muster".into(),
                map_description: None,
            }),
            actions: vec![],
        }
    }

    fn order(id: &str, update: u32, nodes: Vec<Node>) -> Order {
        let edges = nodes
            .windows(2)
            .map(|w| Edge {
                edge_id: format!("{}{}", w[0].node_id, w[1].node_id),
                sequence_id: w[0].sequence_id + 1,
                edge_description: None,
                released: w[1].released,
                start_node_id: w[0].node_id.clone(),
                end_node_id: w[1].node_id.clone(),
                max_speed: None,
                length: None,
                actions: vec![],
            })
            .collect();
        Order {
            header: Header::now(7, "2.1.0", "muster", "D1"),
            order_id: id.into(),
            order_update_id: update,
            zone_set_id: None,
            nodes,
            edges,
        }
    }

    fn action(t: &str, id: &str) -> Action {
        Action {
            action_type: t.into(),
            action_id: id.into(),
            action_description: None,
            blocking_type: BlockingType::None,
            action_parameters: vec![],
        }
    }

    fn instant(c: &mut AgvCore, t: &str, id: &str) -> Vec<Effect> {
        c.instant(InstantActions {
            header: Header::now(1, "2.1.0", "muster", "D1"),
            instant_actions: vec![action(t, id)],
        })
    }

    fn errors(c: &AgvCore) -> Vec<String> {
        c.errors.iter().map(|e| e.error_type.clone()).collect()
    }

    fn status(c: &AgvCore, id: &str) -> Option<ActionStatus> {
        c.actions
            .iter()
            .find(|a| a.action_id == id)
            .map(|a| a.action_status)
    }

    #[test]
    fn a_new_order_starts_where_the_vehicle_stands_and_is_driven_node_by_node() {
        let mut c = core();
        // Too far from the first node: refused, the error names the order.
        assert!(!c.order(
            order(
                "o1",
                0,
                vec![node("a", 0, 5.0, true), node("b", 2, 9.0, true)]
            ),
            (0.0, 0.0)
        ));
        assert_eq!(errors(&c), ["noRouteError"]);
        assert_eq!(c.errors[0].reference("orderId"), Some("o1"));
        assert!(c.target().is_none());
        // From here: the first node is traversed at once, the rest are driven in turn;
        // the refusal of before is gone.
        assert!(c.order(
            order(
                "o1",
                0,
                vec![
                    node("a", 0, 0.2, true),
                    node("b", 2, 4.0, true),
                    node("c", 4, 8.0, true)
                ]
            ),
            (0.0, 0.0)
        ));
        assert!(c.errors.is_empty());
        let st = c.state(0, (0.0, 0.0, 0.0), (0.0, 0.0));
        assert_eq!(
            (st.last_node_id.as_str(), st.last_node_sequence_id),
            ("a", 0)
        );
        let left: Vec<&str> = st.node_states.iter().map(|n| n.node_id.as_str()).collect();
        assert_eq!(left, ["b", "c"]);
        assert_eq!(st.edge_states.len(), 2);
        assert_eq!(c.target(), Some((4.0, 0.0)));
        c.reached();
        assert_eq!(c.target(), Some((8.0, 0.0)));
        c.reached();
        assert_eq!(c.target(), None);
        assert!(!c.active());
        let st = c.state(1, (8.0, 0.0, 0.0), (0.0, 0.0));
        assert!(st.node_states.is_empty() && st.edge_states.is_empty() && !st.driving);
        assert_eq!(
            (st.last_node_id.as_str(), st.last_node_sequence_id),
            ("c", 4)
        );
        // What goes out passes the checks the other side makes.
        msg::encode(&st).unwrap();
    }

    #[test]
    fn updates_stitch_on_the_base_end_and_release_the_horizon() {
        let mut c = core();
        let base = vec![
            node("a", 0, 0.0, true),
            node("b", 2, 4.0, true),
            node("c", 4, 8.0, false),
        ];
        assert!(c.order(order("o1", 0, base), (0.0, 0.0)));
        assert!(c.active());
        c.reached(); // b
        assert_eq!(c.target(), None, "the horizon is not driven");
        assert!(!c.active());
        let st = c.state(0, (4.0, 0.0, 0.0), (0.0, 0.0));
        assert_eq!(st.new_base_request, Some(true));
        // The same update again: nothing changes.
        assert!(!c.order(order("o1", 0, vec![node("a", 0, 0.0, true)]), (4.0, 0.0)));
        // An update that does not start on the last base node: refused.
        assert!(!c.order(
            order(
                "o1",
                1,
                vec![node("a", 0, 0.0, true), node("c", 2, 8.0, true)]
            ),
            (4.0, 0.0)
        ));
        assert_eq!(errors(&c), ["orderUpdateError"]);
        // An older update: refused.
        c.order_update_id = 3;
        assert!(!c.order(
            order(
                "o1",
                2,
                vec![node("b", 2, 4.0, true), node("c", 4, 8.0, true)]
            ),
            (4.0, 0.0)
        ));
        assert_eq!(errors(&c), ["orderUpdateError", "orderUpdateError"]);
        // On b: accepted, the horizon replaced by the released c and a new d.
        let up = vec![
            node("b", 2, 4.0, true),
            node("c", 4, 8.0, true),
            node("d", 6, 12.0, true),
        ];
        assert!(c.order(order("o1", 4, up), (4.0, 0.0)));
        assert!(c.errors.is_empty());
        let ids: Vec<&str> = c.nodes.iter().map(|n| n.node_id.as_str()).collect();
        assert_eq!(ids, ["c", "d"]);
        assert_eq!(c.target(), Some((8.0, 0.0)));
        // While it is active, another order must stitch on its base end too.
        assert!(!c.order(order("o2", 0, vec![node("x", 0, 4.0, true)]), (4.0, 0.0)));
        assert_eq!(errors(&c), ["orderError"]);
        assert!(c.order(
            order(
                "o2",
                0,
                vec![node("d", 6, 12.0, true), node("e", 8, 16.0, true)]
            ),
            (4.0, 0.0)
        ));
        let ids: Vec<&str> = c.nodes.iter().map(|n| n.node_id.as_str()).collect();
        assert_eq!(ids, ["c", "d", "e"]);
    }

    #[test]
    fn orders_off_the_map_or_without_positions_are_refused() {
        let mut c = core();
        let mut o = order(
            "o1",
            0,
            vec![node("a", 0, 0.0, true), node("b", 2, 4.0, true)],
        );
        o.nodes[1].node_position = None;
        assert!(!c.order(o, (0.0, 0.0)));
        let mut o = order(
            "o1",
            0,
            vec![node("a", 0, 0.0, true), node("b", 2, 4.0, true)],
        );
        o.nodes[1].node_position.as_mut().unwrap().map_id = "other".into();
        assert!(!c.order(o, (0.0, 0.0)));
        assert_eq!(errors(&c), ["noRouteError", "noRouteError"]);
        let why = c.errors[1].error_description.clone().unwrap();
        assert!(why.contains("\"other\""), "{why}");
    }

    #[test]
    fn instant_actions_pause_cancel_and_say_what_they_cannot_do() {
        let mut c = core();
        // Nothing to cancel: failed, with an error.
        assert!(instant(&mut c, "cancelOrder", "i1").is_empty());
        assert_eq!(status(&c, "i1"), Some(ActionStatus::Failed));
        assert_eq!(errors(&c), ["noOrderToCancel"]);
        let mut o = order(
            "o1",
            0,
            vec![node("a", 0, 0.0, true), node("b", 2, 4.0, true)],
        );
        o.nodes[1].actions.push(action("pick", "p1"));
        assert!(c.order(o, (0.0, 0.0)));
        assert_eq!(status(&c, "p1"), Some(ActionStatus::Waiting));
        instant(&mut c, "startPause", "i2");
        assert_eq!(c.target(), None, "paused");
        assert_eq!(c.state(0, (0.0, 0.0, 0.0), (0.0, 0.0)).paused, Some(true));
        instant(&mut c, "stopPause", "i3");
        assert_eq!(c.target(), Some((4.0, 0.0)));
        assert_eq!(instant(&mut c, "stateRequest", "i4"), [Effect::State]);
        assert_eq!(
            instant(&mut c, "factsheetRequest", "i5"),
            [Effect::Factsheet]
        );
        instant(&mut c, "liftFork", "i6");
        assert_eq!(status(&c, "i6"), Some(ActionStatus::Failed));
        assert!(errors(&c).contains(&"unsupportedActionError".to_string()));
        instant(&mut c, "cancelOrder", "i7");
        assert_eq!(status(&c, "i7"), Some(ActionStatus::Finished));
        assert_eq!(c.target(), None);
        assert!(c.nodes.is_empty() && c.edges.is_empty());
        // The node's action never ran: failed with the reason.
        assert_eq!(status(&c, "p1"), Some(ActionStatus::Failed));
        for id in ["i2", "i3", "i4", "i5"] {
            assert_eq!(status(&c, id), Some(ActionStatus::Finished), "{id}");
        }
        // A message refused is said once, the newest.
        c.invalid_message("order", "bad 1");
        c.invalid_message("order", "bad 2");
        let v: Vec<_> = c
            .errors
            .iter()
            .filter(|e| e.error_type == "validationError")
            .collect();
        assert_eq!(v.len(), 1);
        assert_eq!(v[0].error_description.as_deref(), Some("bad 2"));
    }

    #[test]
    fn node_actions_are_reported_failed_when_their_node_is_reached() {
        let mut c = core();
        let mut o = order(
            "o1",
            0,
            vec![node("a", 0, 0.0, true), node("b", 2, 4.0, true)],
        );
        o.nodes[0].actions.push(action("beep", "on-a"));
        o.edges[0].actions.push(action("blink", "on-ab"));
        o.nodes[1].actions.push(action("drop", "on-b"));
        assert!(c.order(o, (0.0, 0.0)));
        assert_eq!(
            status(&c, "on-a"),
            Some(ActionStatus::Failed),
            "the first node is traversed at once"
        );
        assert_eq!(status(&c, "on-ab"), Some(ActionStatus::Waiting));
        c.reached();
        for id in ["on-ab", "on-b"] {
            let a = c.actions.iter().find(|a| a.action_id == id).unwrap();
            assert_eq!(a.action_status, ActionStatus::Failed);
            assert!(a
                .result_description
                .as_deref()
                .unwrap()
                .contains("not supported"));
        }
    }
}
