//! A VDA 5050 fleet's vehicles as muster services: `muster system vda5050`.
//!
//! Vehicles are found from their `connection`, `factsheet` and `state` messages (the
//! broker keeps the first two, so a bridge started late finds every vehicle at once).
//! Each becomes two services of this system:
//! - `SERIAL`, a command service (`goal2d`, quota 1, with a task queue): a goal becomes
//!   an `order` — to the nearest node of the road map and along its shortest path when
//!   a graph is given (`--graph`), or straight to the point for a free-navigating
//!   vehicle; a `text` input `node ID` names a node. A new goal in the same session is
//!   an update of the session's order (`orderUpdateId` + 1, stitched onto the end of the
//!   base the vehicle holds); the session's end cancels the order (`cancelOrder`). The
//!   status follows the vehicle's `state`: accepted, driving with the distance and ETA,
//!   paused, blocked, arrived, or the vehicle's own refusal.
//! - `SERIAL.state`, a data service: the vehicle's state as JSON (position, driving,
//!   battery, errors, the order's progress) on every `state` it sends.
//!
//! A vehicle whose connection goes `OFFLINE` or `CONNECTIONBROKEN` is withdrawn (its
//! sessions end, their users told why); `ONLINE` offers it again.

use crate::graph::Graph;
use crate::mqtt::{Incoming, MqttConfig, MqttLink, MqttSecurity};
use crate::msg::{
    self, Action, BlockingType, Connection, ConnectionState, Edge, ErrorLevel, Factsheet, Header,
    InstantActions, Node, NodePosition, Order, State, Visualization,
};
use crate::{muster_name, Topics, VdaFail};
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{
    validate_registration, Payload, Schema, SchemaEncoding, ServiceKind, ServiceSpec, SessionId,
    TaskStatus, MAX_DESCRIPTION, MAX_SERVICES_PER_SYSTEM, MAX_SERVICE_NAME,
};
use muster_systems::{SystemApp, SystemCore, SystemEvent};
use std::collections::{BTreeMap, HashMap};
use std::os::fd::RawFd;
use std::time::Duration;

/// How the bridge is set up.
#[derive(Clone, Debug)]
pub struct FleetOptions {
    /// `host:port` of the MQTT broker.
    pub mqtt: String,
    /// The muster system's name.
    pub system: String,
    /// `interfaceName` of the topics.
    pub interface: String,
    /// Only this manufacturer's vehicles (all when `None`).
    pub manufacturer: Option<String>,
    /// The version written to a vehicle that has not said its own yet.
    pub version: String,
    /// The road map, if the fleet drives on one.
    pub graph: Option<Graph>,
    /// How long a vehicle has to show an order in its state before the session is told
    /// the vehicle did not take it.
    pub order_timeout: Duration,
    /// TLS and credentials for the MQTT broker.
    pub security: MqttSecurity,
    /// JSON schemas every message read and written must also pass (`--vda-schemas`).
    pub schemas: Option<std::sync::Arc<crate::schemas::Schemas>>,
}

impl FleetOptions {
    /// Defaults for the broker at `mqtt`: system `vda5050`, interface `uagv`, all
    /// manufacturers, version 2.1.0, free navigation.
    pub fn new(mqtt: &str) -> Self {
        FleetOptions {
            mqtt: mqtt.to_string(),
            system: "vda5050".into(),
            interface: "uagv".into(),
            manufacturer: None,
            version: "2.1.0".into(),
            graph: None,
            order_timeout: Duration::from_secs(10),
            security: MqttSecurity::default(),
            schemas: None,
        }
    }
}

/// The payload type of the data services.
pub const STATE_TYPE: &str = "vda5050/VehicleState";

/// The JSON Schema of [`STATE_TYPE`] samples, short: it goes with every vehicle's data
/// service in the registration (the fields are listed in the README).
pub const STATE_SCHEMA: &str = r#"{"title":"VehicleState","type":"object","required":["manufacturer","serial","online","driving","battery","errors","orderId","nodesLeft"]}"#;

/// Most errors copied into one state sample (the rest are counted).
const MAX_ERRORS_SHOWN: usize = 8;
/// Most vehicles one bridge keeps track of (found, offered or not): names beyond are
/// ignored, so a flood of made-up vehicles cannot grow the bridge without end.
pub const MAX_VEHICLES: usize = 4096;
/// How often timeouts are looked at.
const TICK: Duration = Duration::from_millis(250);

/// Where a session's order stands.
#[derive(Clone, Debug)]
struct Task {
    order_id: String,
    update_id: u32,
    /// The last base node sent: a new goal is stitched onto it.
    base_end: Node,
    /// The goal, for the notes.
    goal: String,
    sent_at: Duration,
    /// When the order went out (for the acknowledgement time).
    sent_wall: std::time::Instant,
    /// The vehicle's state has shown this order update.
    seen: bool,
    /// Arrived, refused or timed out: nothing more to say until the next goal.
    closed: bool,
    last_note: String,
    next_goal: u32,
}

#[derive(Debug)]
struct Vehicle {
    manufacturer: String,
    serial: String,
    command: String,
    data: String,
    connection: Option<ConnectionState>,
    version: Option<String>,
    factsheet: Option<Factsheet>,
    state: Option<State>,
    order_header: u32,
    instant_header: u32,
    session: Option<SessionId>,
    task: Option<Task>,
    /// A goal that came before the vehicle's first state (asked for with `stateRequest`).
    pending: Option<(SessionId, Payload, Duration)>,
}

impl Vehicle {
    fn online(&self) -> bool {
        match self.connection {
            Some(c) => c == ConnectionState::Online,
            None => self.state.is_some(),
        }
    }
}

type Key = (String, String);

/// Counters for reports and tests.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct FleetStats {
    /// Messages read and taken.
    pub taken: u64,
    /// Messages refused (bad JSON, broken rules), each logged with its reason.
    pub invalid: u64,
    /// Orders sent (new and updates).
    pub orders: u64,
    /// `cancelOrder` actions sent.
    pub cancels: u64,
    /// Vehicles found.
    pub vehicles: u64,
    /// Order sent → first state of the vehicle showing it, µs (the first 100,000).
    #[serde(skip)]
    pub order_ack_us: Vec<u64>,
}

impl FleetStats {
    /// The counters, and the order → acknowledging state times' quantiles (ms).
    pub fn report(&self) -> serde_json::Value {
        let mut j = serde_json::to_value(self).expect("counters are JSON");
        let mut s = self.order_ack_us.clone();
        s.sort_unstable();
        let q = |q: f64| -> Option<f64> {
            let i = ((s.len() as f64 - 1.0) * q).round() as usize;
            s.get(i).map(|us| *us as f64 / 1000.0)
        };
        j["order_ack_ms"] = serde_json::json!({
            "n": s.len(), "p50": q(0.5), "p99": q(0.99), "max": q(1.0),
        });
        j["order_ack_us"] = serde_json::json!(s);
        j
    }
}

/// The bridge's logic, run by muster's system runtime.
pub struct Fleet {
    opts: FleetOptions,
    topics: Topics,
    link: MqttLink,
    vehicles: BTreeMap<Key, Vehicle>,
    by_service: HashMap<String, Key>,
    sessions: HashMap<SessionId, Key>,
    specs_dirty: bool,
    full_warned: bool,
    next_tick: Duration,
    stats: FleetStats,
}

impl Fleet {
    /// Connects to the MQTT broker and waits up to `wait` for the vehicles it already
    /// knows (their retained `connection` and `factsheet`), so the first registration
    /// lists them.
    pub fn connect(opts: FleetOptions, wait: Duration) -> Result<Self, VdaFail> {
        crate::msg::version_supported(&opts.version)
            .then_some(())
            .ok_or_else(|| VdaFail::Config(format!("version {:?} is not 2.x", opts.version)))?;
        let topics = Topics::v2(&opts.interface);
        if topics.interface.is_empty() || topics.interface.contains(['/', '+', '#']) {
            return Err(VdaFail::Config(format!(
                "interface name {:?}: not empty, no / + #",
                opts.interface
            )));
        }
        let m = opts.manufacturer.as_deref();
        let cfg = MqttConfig {
            broker: opts.mqtt.clone(),
            security: opts.security.clone(),
            client_id: format!("muster-{}-{}", opts.system, std::process::id()),
            keep_alive: Duration::from_secs(5),
            subscriptions: ["connection", "factsheet", "state", "visualization"]
                .iter()
                .map(|t| topics.filter(m, t))
                .collect(),
            will: None,
        };
        let link = MqttLink::connect(&cfg)?;
        let mut fleet = Fleet {
            opts,
            topics,
            link,
            vehicles: BTreeMap::new(),
            by_service: HashMap::new(),
            sessions: HashMap::new(),
            specs_dirty: false,
            full_warned: false,
            next_tick: Duration::ZERO,
            stats: FleetStats::default(),
        };
        let deadline = std::time::Instant::now() + wait;
        let mut connected = false;
        while let Some(left) = deadline.checked_duration_since(std::time::Instant::now()) {
            // Once connected, retained messages come at once: a quiet 300 ms ends it.
            let step = if connected {
                left.min(Duration::from_millis(300))
            } else {
                left
            };
            match fleet.link.wait(step) {
                Some(Incoming::Connected) => connected = true,
                Some(m) => fleet.take(None, m),
                None if connected => break,
                None => {}
            }
        }
        if !connected {
            tracing::warn!(mqtt = %fleet.opts.mqtt, "MQTT broker not reached yet; still trying");
        }
        Ok(fleet)
    }

    /// The services of the vehicles found so far, in a stable order: as many vehicles as
    /// one system offers (64, the services per system; fewer if their registration would
    /// not fit one frame).
    pub fn specs(&self) -> Vec<ServiceSpec> {
        let mut out = Vec::new();
        for v in self.vehicles.values() {
            if out.len() + 2 > MAX_SERVICES_PER_SYSTEM {
                break;
            }
            let series = v
                .factsheet
                .as_ref()
                .and_then(|f| f.series())
                .map(|s| format!(" {s}"))
                .unwrap_or_default();
            out.push(ServiceSpec {
                name: v.command.clone(),
                description: clip(format!(
                    "VDA 5050 vehicle{series} {}/{}: a goal becomes an order",
                    v.manufacturer, v.serial
                )),
                kind: ServiceKind::Command,
                queue: true,
                quota: 1,
                payload: "goal2d".into(),
                schema: None,
            });
            out.push(ServiceSpec {
                name: v.data.clone(),
                description: clip(format!(
                    "VDA 5050 vehicle {}/{}: position, battery, errors, order progress",
                    v.manufacturer, v.serial
                )),
                kind: ServiceKind::Data,
                queue: false,
                quota: 64,
                payload: STATE_TYPE.into(),
                schema: Some(Schema {
                    encoding: SchemaEncoding::JsonSchema,
                    text: STATE_SCHEMA.into(),
                }),
            });
            // A vehicle more than one registration frame holds waits for another bridge.
            if validate_registration(&self.opts.system, &out).is_err() {
                out.truncate(out.len() - 2);
                break;
            }
        }
        out
    }

    /// The counters.
    pub fn stats(&self) -> &FleetStats {
        &self.stats
    }

    /// The services of vehicles found offline (listed, withdrawn).
    pub fn offline_services(&self) -> Vec<String> {
        self.vehicles
            .values()
            .filter(|v| !v.online())
            .flat_map(|v| [v.command.clone(), v.data.clone()])
            .collect()
    }

    /// Closes the MQTT connection in order.
    pub fn close(&mut self) {
        self.link.close();
    }

    fn invalid(&mut self, topic: &str, why: &dyn std::fmt::Display) {
        self.stats.invalid += 1;
        let n = self.stats.invalid;
        if n <= 20 || n.is_power_of_two() {
            tracing::warn!(%topic, invalid = n, "VDA 5050 message refused: {why}");
        }
    }

    /// Takes one message (`core` is `None` before the runtime runs).
    fn take(&mut self, mut core: Option<&mut SystemCore>, m: Incoming) {
        let (topic, payload) = match m {
            Incoming::Publish { topic, payload, .. } => (topic, payload),
            Incoming::Connected => {
                tracing::info!(mqtt = %self.opts.mqtt, "connected to the MQTT broker");
                return;
            }
            Incoming::Down(why) => {
                tracing::warn!(mqtt = %self.opts.mqtt, "MQTT connection down: {why}");
                return;
            }
        };
        let Some((m, s, t)) = self.topics.parse(&topic) else {
            return;
        };
        let key = (m.to_string(), s.to_string());
        if !self.vehicles.contains_key(&key) && self.vehicles.len() >= MAX_VEHICLES {
            return self.invalid(
                &topic,
                &format!("more than {MAX_VEHICLES} vehicles: not taken"),
            );
        }
        if let Some(schemas) = &self.opts.schemas {
            if let Err(why) = schemas.check_bytes(t, &payload) {
                return self.invalid(&topic, &why);
            }
        }
        let result = match t {
            "connection" => msg::decode::<Connection>(&payload).map(|c| {
                self.check_sender(&key, &c.header).map(|()| {
                    let v = self.vehicle(&key);
                    v.version = Some(c.header.version.clone());
                    self.connection(core.as_deref_mut(), &key, c.connection_state);
                })
            }),
            "factsheet" => msg::decode::<Factsheet>(&payload).map(|f| {
                self.check_sender(&key, &f.header).map(|()| {
                    let v = self.vehicle(&key);
                    v.factsheet = Some(f);
                })
            }),
            "state" => msg::decode::<State>(&payload).map(|st| {
                self.check_sender(&key, &st.header)
                    .map(|()| self.state(core.as_deref_mut(), &key, st))
            }),
            "visualization" => msg::decode::<Visualization>(&payload).map(|vis| {
                self.check_sender(&key, &vis.header)
                    .map(|()| self.visualization(core.as_deref_mut(), &key, vis))
            }),
            _ => return,
        };
        match result {
            Ok(Ok(())) => self.stats.taken += 1,
            Ok(Err(why)) => self.invalid(&topic, &why),
            Err(e) => self.invalid(&topic, &e),
        }
        if let Some(core) = core {
            self.sync_specs(core);
        }
    }

    /// A message's header must name the vehicle of its topic.
    fn check_sender(&self, key: &Key, h: &Header) -> Result<(), String> {
        if h.manufacturer != key.0 || h.serial_number != key.1 {
            return Err(format!(
                "header names {}/{}, the topic {}/{}",
                h.manufacturer, h.serial_number, key.0, key.1
            ));
        }
        Ok(())
    }

    /// The vehicle of `key`, found now if new.
    fn vehicle(&mut self, key: &Key) -> &mut Vehicle {
        if !self.vehicles.contains_key(key) {
            let base_max = MAX_SERVICE_NAME - ".state".len();
            // The serial as a name; the manufacturer's too, then a number, when another
            // vehicle's names (either of its two) are the same.
            let free = |c: &str| {
                !self.by_service.contains_key(c)
                    && !self.by_service.contains_key(&format!("{c}.state"))
            };
            let mut command = muster_name(&key.1, base_max);
            let mut n = 1;
            while !free(&command) {
                let tail = if n == 1 {
                    String::new()
                } else {
                    format!("-{n}")
                };
                command = muster_name(&format!("{}-{}{tail}", key.0, key.1), base_max);
                n += 1;
            }
            let data = format!("{command}.state");
            tracing::info!(manufacturer = %key.0, serial = %key.1, service = %command, "vehicle found");
            self.by_service.insert(command.clone(), key.clone());
            self.by_service.insert(data.clone(), key.clone());
            self.vehicles.insert(
                key.clone(),
                Vehicle {
                    manufacturer: key.0.clone(),
                    serial: key.1.clone(),
                    command,
                    data,
                    connection: None,
                    version: None,
                    factsheet: None,
                    state: None,
                    order_header: 0,
                    instant_header: 0,
                    session: None,
                    task: None,
                    pending: None,
                },
            );
            self.stats.vehicles += 1;
            self.specs_dirty = true;
        }
        self.vehicles.get_mut(key).expect("inserted above")
    }

    fn sync_specs(&mut self, core: &mut SystemCore) {
        if !std::mem::take(&mut self.specs_dirty) {
            return;
        }
        let specs = self.specs();
        if specs.len() < 2 * self.vehicles.len() && !self.full_warned {
            self.full_warned = true;
            tracing::warn!(
                "{} vehicles found, {} offered: one system offers {} services in one \
                 registration; run another bridge (--manufacturer, --name) for the rest",
                self.vehicles.len(),
                specs.len() / 2,
                MAX_SERVICES_PER_SYSTEM
            );
        }
        let offline = self.offline_services();
        match core.set_specs(specs) {
            Ok(()) => {
                for s in offline {
                    core.withdraw(&s);
                }
            }
            Err(e) => tracing::warn!("the vehicles' services could not be offered: {e}"),
        }
    }

    fn connection(&mut self, core: Option<&mut SystemCore>, key: &Key, c: ConnectionState) {
        let v = self.vehicle(key);
        let was = v.online();
        v.connection = Some(c);
        let now = v.online();
        if was == now {
            return;
        }
        tracing::info!(vehicle = %v.command, state = ?c, "vehicle connection");
        if !now {
            // What it said before is stale once it is back (restarted, moved by hand).
            v.state = None;
            v.task = None;
            v.pending = None;
        } else if v.state.is_none() {
            // State is not kept by the broker: ask for it rather than wait up to 30 s.
            self.instant(key, "stateRequest", "muster-state");
        }
        if let Some(core) = core {
            self.offer(core, key, now);
        }
    }

    fn state(&mut self, core: Option<&mut SystemCore>, key: &Key, st: State) {
        let version = st.header.version.clone();
        let v = self.vehicle(key);
        v.version = Some(version);
        let came_back = !v.online();
        v.state = Some(st);
        if came_back && v.online() {
            // A vehicle that never sent a connection is online while it sends state.
            if let Some(core) = core {
                self.offer(core, key, true);
            }
            return;
        }
        let Some(core) = core else { return };
        self.publish_state(core, key);
        let v = self.vehicles.get_mut(key).expect("known vehicle");
        if let Some((session, payload, at)) = v.pending.take() {
            if v.session == Some(session) {
                return self.goal(core, at, session, payload);
            }
        }
        self.follow(core, key, Duration::ZERO);
    }

    /// The position between states: the data service and the driving note follow it.
    fn visualization(&mut self, core: Option<&mut SystemCore>, key: &Key, vis: Visualization) {
        let Some(v) = self.vehicles.get_mut(key) else {
            return; // not found by its connection, factsheet or state: not ours yet
        };
        let Some(st) = v.state.as_mut() else { return };
        if vis.agv_position.is_none() && vis.velocity.is_none() {
            return;
        }
        if let Some(p) = vis.agv_position {
            st.agv_position = Some(p);
        }
        if let Some(vel) = vis.velocity {
            st.velocity = Some(vel);
        }
        let Some(core) = core else { return };
        self.publish_state(core, key);
        self.follow(core, key, Duration::ZERO);
    }

    /// Offers the vehicle's two services again, or withdraws them (unless the next
    /// registration, already due, says so with the new list).
    fn offer(&mut self, core: &mut SystemCore, key: &Key, online: bool) {
        if self.specs_dirty {
            return;
        }
        let v = &self.vehicles[key];
        for s in [v.command.as_str(), v.data.as_str()] {
            match online {
                true => core.restore(s),
                false => core.withdraw(s),
            }
        }
    }

    /// The vehicle's state as the data service's sample (JSON).
    fn summary(v: &Vehicle) -> Option<Payload> {
        let st = v.state.as_ref()?;
        let mut j = serde_json::json!({
            "manufacturer": v.manufacturer, "serial": v.serial, "online": v.online(),
            "driving": st.driving, "paused": st.paused.unwrap_or(false),
            "battery": st.battery_state.battery_charge, "charging": st.battery_state.charging,
            "operatingMode": st.operating_mode,
            "errors": st.errors.iter().take(MAX_ERRORS_SHOWN).map(|e| serde_json::json!({
                "type": e.error_type, "level": e.error_level,
                "description": e.error_description.as_deref().unwrap_or("")
                    .chars().take(120).collect::<String>(),
            })).collect::<Vec<_>>(),
            "orderId": st.order_id, "orderUpdateId": st.order_update_id,
            "lastNodeId": st.last_node_id, "nodesLeft": st.node_states.len(),
        });
        if let Some(p) = &st.agv_position {
            j["x"] = p.x.into();
            j["y"] = p.y.into();
            j["theta"] = p.theta.into();
            j["mapId"] = p.map_id.clone().into();
        }
        Some(Payload::Encoded {
            type_name: STATE_TYPE.into(),
            data: j.to_string().into_bytes(),
        })
    }

    fn publish_state(&mut self, core: &mut SystemCore, key: &Key) {
        let v = &self.vehicles[key];
        if core.sessions_of(&v.data) == 0 {
            return;
        }
        let Some(payload) = Self::summary(v) else {
            return;
        };
        if let Err(e) = core.publish(&v.data, &payload, monotonic_ns()) {
            tracing::warn!(service = %v.data, "state not sent: {e}");
        }
    }

    /// The session's status from the vehicle's newest state.
    fn follow(&mut self, core: &mut SystemCore, key: &Key, now: Duration) {
        let v = self.vehicles.get_mut(key).expect("known vehicle");
        let (Some(session), Some(task), Some(st)) = (v.session, v.task.as_mut(), v.state.as_ref())
        else {
            return;
        };
        if task.closed {
            return;
        }
        // The vehicle's refusal names the order (and update) it refused.
        let refusal = st.errors.iter().find(|e| {
            e.reference("orderId") == Some(task.order_id.as_str())
                && e.reference("orderUpdateId")
                    .is_none_or(|u| u == task.update_id.to_string())
        });
        if let Some(e) = refusal {
            task.closed = true;
            let why = e.error_description.clone().unwrap_or_default();
            core.status(
                session,
                TaskStatus::Rejected(format!(
                    "{} refused order {}/{}: {} {why}",
                    v.command, task.order_id, task.update_id, e.error_type
                )),
            );
            return;
        }
        let ours = st.order_id == task.order_id && st.order_update_id == task.update_id;
        if !ours {
            if !task.seen
                && !now.is_zero()
                && now.saturating_sub(task.sent_at) > self.opts.order_timeout
            {
                task.closed = true;
                core.status(
                    session,
                    TaskStatus::Rejected(format!(
                        "{} did not take order {}/{} within {:?}",
                        v.command, task.order_id, task.update_id, self.opts.order_timeout
                    )),
                );
            }
            return;
        }
        if !std::mem::replace(&mut task.seen, true) && self.stats.order_ack_us.len() < 100_000 {
            self.stats
                .order_ack_us
                .push(task.sent_wall.elapsed().as_micros() as u64);
        }
        let actions_done = st.action_states.iter().all(|a| {
            matches!(
                a.action_status,
                msg::ActionStatus::Finished | msg::ActionStatus::Failed
            )
        });
        if st.node_states.is_empty() && !st.driving && actions_done {
            task.closed = true;
            let at = st
                .agv_position
                .as_ref()
                .map(|p| format!(" ({:.2}, {:.2})", p.x, p.y))
                .unwrap_or_default();
            core.status(
                session,
                TaskStatus::Done(format!("arrived at {}{at}", st.last_node_id)),
            );
            return;
        }
        let fatal = st
            .errors
            .iter()
            .find(|e| e.error_level == ErrorLevel::Fatal);
        let note = if let Some(e) = fatal {
            format!(
                "blocked: {} {}",
                e.error_type,
                e.error_description.as_deref().unwrap_or("")
            )
        } else if st.paused == Some(true) {
            "paused".to_string()
        } else if !st.driving && task.last_note.is_empty() {
            format!(
                "accepted: order {}/{} to {}",
                task.order_id, task.update_id, task.goal
            )
        } else {
            let left = distance_left(st);
            let speed = v
                .factsheet
                .as_ref()
                .and_then(|f| f.speed_max())
                .or_else(|| {
                    st.velocity
                        .as_ref()
                        .and_then(|s| Some(s.vx?.hypot(s.vy.unwrap_or(0.0))))
                        .filter(|s| *s > 0.05)
                });
            let eta = speed
                .map(|s| format!(", ETA {:.0} s", left / s))
                .unwrap_or_default();
            let what = if st.driving { "driving" } else { "stopped" };
            format!(
                "{what} to {}: {} nodes left, {left:.1} m to go{eta}",
                task.goal,
                st.node_states.len()
            )
        };
        if note != task.last_note {
            task.last_note = note.clone();
            core.status(session, TaskStatus::Working(note));
        }
    }

    /// A message to send, checked by [`msg::encode`] and the schemas given.
    fn encode<M: msg::Message>(&self, m: &M) -> Result<Vec<u8>, String> {
        let bytes = msg::encode(m).map_err(|e| e.to_string())?;
        if let Some(s) = &self.opts.schemas {
            s.check_bytes(M::TOPIC, &bytes)?;
        }
        Ok(bytes)
    }

    /// The version to write to vehicle `v`.
    fn version_for(&self, v: &Vehicle) -> String {
        v.version
            .clone()
            .filter(|s| msg::version_supported(s))
            .unwrap_or_else(|| self.opts.version.clone())
    }

    fn goal(&mut self, core: &mut SystemCore, now: Duration, session: SessionId, p: Payload) {
        let Some(key) = self.sessions.get(&session).cloned() else {
            return;
        };
        let v = self.vehicles.get_mut(&key).expect("known vehicle");
        if v.state.is_none() {
            let first = v.pending.is_none();
            v.pending = Some((session, p, now));
            if first {
                self.instant(&key, "stateRequest", "muster-state");
            }
            return core.status(
                session,
                TaskStatus::Working("waiting for the vehicle's first state".into()),
            );
        }
        let target = match &p {
            Payload::Text(t) => match t.trim().strip_prefix("node ") {
                Some(id) => Target::Node(id.trim().to_string()),
                None => {
                    return core.status(
                        session,
                        TaskStatus::Rejected(format!("text input {t:?}: send `node ID`")),
                    )
                }
            },
            other => match other.convert_to("goal2d") {
                Some(Payload::Goal2d { x, y }) if x.is_finite() && y.is_finite() => {
                    Target::Point(x, y)
                }
                _ => {
                    return core.status(
                        session,
                        TaskStatus::Rejected(format!("cannot use {} as a goal", p.type_name())),
                    )
                }
            },
        };
        match self.order_for(&key, session, now, target) {
            Ok(order) => {
                let v = &self.vehicles[&key];
                let topic = self.topics.topic(&v.manufacturer, &v.serial, "order");
                let sent = self
                    .encode(&order)
                    .and_then(|bytes| self.link.publish(&topic, bytes, false));
                match sent {
                    Ok(()) => {
                        self.stats.orders += 1;
                        let t = self.vehicles.get_mut(&key).and_then(|v| v.task.as_ref());
                        let note = t
                            .map(|t| {
                                format!("order {}/{} sent: to {}", t.order_id, t.update_id, t.goal)
                            })
                            .unwrap_or_default();
                        core.status(session, TaskStatus::Working(note));
                    }
                    Err(e) => {
                        if let Some(t) = self.vehicles.get_mut(&key).and_then(|v| v.task.as_mut()) {
                            t.closed = true;
                        }
                        core.status(
                            session,
                            TaskStatus::Rejected(format!("order not sent: {e}")),
                        )
                    }
                }
            }
            Err(why) => core.status(session, TaskStatus::Rejected(why)),
        }
    }

    /// The order (or order update) that takes the session's vehicle to `target`.
    fn order_for(
        &mut self,
        key: &Key,
        session: SessionId,
        now: Duration,
        target: Target,
    ) -> Result<Order, String> {
        let version = self.version_for(&self.vehicles[key]);
        let graph = self.opts.graph.clone();
        let v = self.vehicles.get_mut(key).expect("known vehicle");
        let st = v
            .state
            .as_ref()
            .ok_or_else(|| format!("{} has sent no state yet", v.command))?;
        let pos = st.agv_position.as_ref();
        let map_id = pos
            .map(|p| p.map_id.clone())
            .or_else(|| graph.as_ref().map(|g| g.map_id.clone()))
            .unwrap_or_else(|| "local".into());
        // Where the order starts: on the end of the base the vehicle holds for this
        // session's order, else where the vehicle stands (its last node, as the
        // specification asks of a new order's first node).
        let held = v
            .task
            .as_ref()
            .filter(|t| st.order_id == t.order_id && (!st.node_states.is_empty() || st.driving));
        let (order_id, update_id, start, next_goal) = match (held, v.task.as_ref()) {
            (Some(t), _) => (
                t.order_id.clone(),
                t.update_id + 1,
                t.base_end.clone(),
                t.next_goal,
            ),
            (None, Some(t)) if st.order_id == t.order_id => {
                // Ours, finished: an update starting on the last node it reached.
                let node = Node {
                    node_id: st.last_node_id.clone(),
                    sequence_id: st.last_node_sequence_id,
                    node_description: None,
                    released: true,
                    node_position: pos.map(here),
                    actions: vec![],
                };
                (t.order_id.clone(), t.update_id + 1, node, t.next_goal)
            }
            _ => {
                let start_id = match (&graph, pos) {
                    (Some(g), _) if g.node(&st.last_node_id).is_some() => st.last_node_id.clone(),
                    (Some(g), Some(p)) => g.nearest(p.x, p.y).id.clone(),
                    _ if !st.last_node_id.is_empty() => st.last_node_id.clone(),
                    _ => "muster-start".into(),
                };
                let position = match (&graph, pos) {
                    (Some(g), _) => g.node(&start_id).map(|n| NodePosition {
                        x: n.x,
                        y: n.y,
                        theta: None,
                        allowed_deviation_x_y: None,
                        allowed_deviation_theta: None,
                        map_id: g.map_id.clone(),
                        map_description: None,
                    }),
                    (None, Some(p)) => Some(here(p)),
                    (None, None) => None,
                };
                let node = Node {
                    node_id: start_id,
                    sequence_id: 0,
                    node_description: None,
                    released: true,
                    node_position: position,
                    actions: vec![],
                };
                (format!("muster-{:016x}", session.0), 0, node, 0)
            }
        };
        let (path, goal_text): (Vec<(String, f64, f64)>, String) = match (&graph, &target) {
            (Some(g), t) => {
                let to = match t {
                    Target::Node(id) => g
                        .node(id)
                        .ok_or_else(|| format!("node {id:?} is not on the road map"))?,
                    Target::Point(x, y) => g.nearest(*x, *y),
                };
                let p = g.path(&start.node_id, &to.id).ok_or_else(|| {
                    format!("no way on the road map from {} to {}", start.node_id, to.id)
                })?;
                let text = format!("node {} ({:.2}, {:.2})", to.id, to.x, to.y);
                (
                    p.into_iter()
                        .skip(1)
                        .map(|n| (n.id.clone(), n.x, n.y))
                        .collect(),
                    text,
                )
            }
            (None, Target::Node(id)) => {
                return Err(format!(
                    "node {id:?}: no road map was given (--graph); send a position"
                ))
            }
            (None, Target::Point(x, y)) => (
                vec![(format!("muster-goal-{}", next_goal), *x, *y)],
                format!("({x:.2}, {y:.2})"),
            ),
        };
        let header_id = v.order_header;
        v.order_header = v.order_header.wrapping_add(1);
        let mut nodes = vec![start];
        let mut edges = Vec::new();
        for (id, x, y) in path {
            let prev = nodes.last().expect("the start node");
            let seq = prev.sequence_id + 2;
            edges.push(Edge {
                edge_id: format!("{}-{}", prev.node_id, id),
                sequence_id: prev.sequence_id + 1,
                edge_description: None,
                released: true,
                start_node_id: prev.node_id.clone(),
                end_node_id: id.clone(),
                max_speed: None,
                length: None,
                actions: vec![],
            });
            nodes.push(Node {
                node_id: id,
                sequence_id: seq,
                node_description: None,
                released: true,
                node_position: Some(NodePosition {
                    x,
                    y,
                    theta: None,
                    allowed_deviation_x_y: None,
                    allowed_deviation_theta: None,
                    map_id: map_id.clone(),
                    map_description: None,
                }),
                actions: vec![],
            });
        }
        let order = Order {
            header: Header::now(header_id, &version, &v.manufacturer, &v.serial),
            order_id: order_id.clone(),
            order_update_id: update_id,
            zone_set_id: None,
            nodes,
            edges,
        };
        v.task = Some(Task {
            order_id,
            update_id,
            base_end: order.nodes.last().expect("one node at least").clone(),
            goal: goal_text,
            sent_at: now,
            sent_wall: std::time::Instant::now(),
            seen: false,
            closed: false,
            last_note: String::new(),
            next_goal: next_goal + 1,
        });
        Ok(order)
    }

    /// Cancels the session's order if the vehicle still drives it.
    fn cancel(&mut self, key: &Key) {
        let v = self.vehicles.get_mut(key).expect("known vehicle");
        v.pending = None;
        let Some(task) = v.task.take() else { return };
        let active = v.state.as_ref().is_some_and(|st| {
            st.order_id == task.order_id && (!st.node_states.is_empty() || st.driving)
        });
        // Sent while the vehicle may not have shown the order yet, too: it may be on
        // its way.
        if !active && task.seen {
            return;
        }
        let id = format!("{}-cancel-{}", task.order_id, task.update_id);
        if self.instant(key, "cancelOrder", &id) {
            self.stats.cancels += 1;
        }
    }

    /// Sends one instant action of `action_type` to the vehicle; whether it went.
    fn instant(&mut self, key: &Key, action_type: &str, id: &str) -> bool {
        let version = self.version_for(&self.vehicles[key]);
        let v = self.vehicles.get_mut(key).expect("known vehicle");
        let msg = InstantActions {
            header: Header::now(v.instant_header, &version, &v.manufacturer, &v.serial),
            instant_actions: vec![Action {
                action_type: action_type.into(),
                action_id: format!("{id}-{}", v.instant_header),
                action_description: None,
                blocking_type: BlockingType::None,
                action_parameters: vec![],
            }],
        };
        v.instant_header = v.instant_header.wrapping_add(1);
        let topic = self
            .topics
            .topic(&v.manufacturer, &v.serial, "instantActions");
        let sent = self
            .encode(&msg)
            .and_then(|bytes| self.link.publish(&topic, bytes, false));
        if let Err(e) = &sent {
            tracing::warn!(%topic, "{action_type} not sent: {e}");
        }
        sent.is_ok()
    }
}

/// A description cut to what the protocol takes (on a character boundary).
fn clip(mut s: String) -> String {
    if s.len() > MAX_DESCRIPTION {
        let mut end = MAX_DESCRIPTION;
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        s.truncate(end);
    }
    s
}

enum Target {
    Point(f64, f64),
    Node(String),
}

fn here(p: &msg::AgvPosition) -> NodePosition {
    NodePosition {
        x: p.x,
        y: p.y,
        theta: None,
        allowed_deviation_x_y: None,
        allowed_deviation_theta: None,
        map_id: p.map_id.clone(),
        map_description: None,
    }
}

/// Metres from the vehicle through the nodes it has left to pass.
fn distance_left(st: &State) -> f64 {
    let mut at = st.agv_position.as_ref().map(|p| (p.x, p.y));
    let mut d = 0.0;
    for n in &st.node_states {
        if let Some(p) = &n.node_position {
            if let Some((x, y)) = at {
                d += (p.x - x).hypot(p.y - y);
            }
            at = Some((p.x, p.y));
        }
    }
    d
}

impl SystemApp for Fleet {
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent) {
        match event {
            SystemEvent::SessionStarted {
                session, service, ..
            } => {
                let Some(key) = self.by_service.get(&service).cloned() else {
                    return;
                };
                let v = self.vehicles.get_mut(&key).expect("known vehicle");
                if service == v.command {
                    v.session = Some(session);
                    v.task = None;
                    self.sessions.insert(session, key);
                    core.status(session, TaskStatus::Idle);
                } else if let Some(payload) = Self::summary(v) {
                    let _ = core.publish_session(session, &payload, monotonic_ns());
                }
            }
            SystemEvent::Input {
                session, payload, ..
            } => self.goal(core, now, session, payload),
            SystemEvent::Registered => {
                // Vehicles found offline are listed, withdrawn.
                for s in self.offline_services() {
                    core.withdraw(&s);
                }
            }
            SystemEvent::SessionEnded { session, .. } => {
                if let Some(key) = self.sessions.remove(&session) {
                    if self.vehicles[&key].session == Some(session) {
                        self.cancel(&key);
                        self.vehicles.get_mut(&key).expect("known").session = None;
                    }
                }
            }
            _ => {}
        }
    }

    fn on_tick(&mut self, core: &mut SystemCore, now: Duration) {
        self.next_tick = now + TICK;
        let keys: Vec<Key> = self
            .vehicles
            .iter()
            .filter(|(_, v)| v.task.as_ref().is_some_and(|t| !t.seen && !t.closed))
            .map(|(k, _)| k.clone())
            .collect();
        for k in keys {
            self.follow(core, &k, now);
        }
        self.sync_specs(core);
    }

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        Some(self.next_tick)
    }

    fn descriptors(&self) -> Vec<RawFd> {
        vec![self.link.fd()]
    }

    fn on_ready(&mut self, core: &mut SystemCore, _now: Duration, _index: usize) {
        for m in self.link.drain() {
            self.take(Some(core), m);
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A bridge whose MQTT broker is never reached: messages are handed to it here.
    fn fleet() -> Fleet {
        Fleet::connect(FleetOptions::new("127.0.0.1:1"), Duration::ZERO).unwrap()
    }

    fn connection(m: &str, s: &str, state: &str) -> Incoming {
        let h = Header::now(0, "2.0.0", m, s);
        let mut j = serde_json::to_value(h).unwrap();
        j["connectionState"] = state.into();
        Incoming::Publish {
            topic: format!("uagv/v2/{m}/{s}/connection"),
            payload: j.to_string().into_bytes(),
            retained: true,
        }
    }

    fn names(f: &Fleet) -> Vec<String> {
        f.specs().into_iter().map(|s| s.name).collect()
    }

    #[test]
    fn vehicles_found_get_names_of_their_own_even_when_serials_clash() {
        let mut f = fleet();
        for (m, s) in [
            ("acme", "x.state"),
            ("acme", "x"),
            ("bcme", "x"),
            ("acme", "a b"),
            ("acme", "a_b"),
        ] {
            f.take(None, connection(m, s, "ONLINE"));
        }
        let n = names(&f);
        assert_eq!(n.len(), 10, "{n:?}");
        let unique: std::collections::BTreeSet<_> = n.iter().collect();
        assert_eq!(unique.len(), 10, "{n:?}");
        validate_registration("vda5050", &f.specs()).unwrap();
        assert!(
            n.contains(&"x.state".to_string()) && n.contains(&"a_b".to_string()),
            "{n:?}"
        );
        assert_eq!(f.stats().vehicles, 5);
        assert!(f.offline_services().is_empty());
        f.take(None, connection("bcme", "x", "CONNECTIONBROKEN"));
        assert_eq!(f.offline_services().len(), 2);
    }

    #[test]
    fn bad_messages_are_counted_and_change_nothing() {
        let mut f = fleet();
        let bad = |topic: &str, payload: &str| Incoming::Publish {
            topic: topic.into(),
            payload: payload.as_bytes().to_vec(),
            retained: false,
        };
        f.take(None, bad("uagv/v2/acme/agv1/connection", "{not json"));
        f.take(None, bad("uagv/v2/acme/agv1/state", r#"{"headerId": 1}"#));
        // A header naming another vehicle than the topic.
        let mut other = connection("acme", "agv2", "ONLINE");
        if let Incoming::Publish { topic, .. } = &mut other {
            *topic = "uagv/v2/acme/agv1/connection".into();
        }
        f.take(None, other);
        // Not our interface or version: not looked at.
        f.take(None, bad("other/v2/acme/agv1/state", "{"));
        f.take(None, bad("uagv/v1/acme/agv1/state", "{"));
        assert_eq!(f.stats().invalid, 3);
        assert_eq!(f.stats().taken, 0);
        assert!(f.specs().is_empty());
    }

    #[test]
    fn a_flood_of_made_up_vehicles_stops_at_the_cap_and_one_system_offers_64() {
        let mut f = fleet();
        for i in 0..MAX_VEHICLES + 10 {
            f.take(None, connection("acme", &format!("v{i}"), "ONLINE"));
        }
        assert_eq!(f.stats().vehicles, MAX_VEHICLES as u64);
        assert_eq!(f.stats().invalid, 10);
        let specs = f.specs();
        assert_eq!(specs.len(), MAX_SERVICES_PER_SYSTEM);
        validate_registration("vda5050", &specs).unwrap();
    }
}
