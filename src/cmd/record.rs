//! `muster record`: the world and the infrastructure into an MCAP file, on Foxglove's
//! well-known schemas where one fits (the `foxglove` crate).
//!
//! Topics:
//!
//! | topic | schema | what |
//! |---|---|---|
//! | `/map` | `foxglove.Grid` | the map, once (cell value 100: occupied) |
//! | `/tf` | `foxglove.FrameTransforms` | each robot's frame (its name) in `map` |
//! | `/robots` | `foxglove.SceneUpdate` | the robots, named |
//! | `/people` | `foxglove.SceneUpdate` | the people, in their beacons' colours |
//! | `/ROBOT/laser` | `foxglove.LaserScan` | each robot's laser scans, in its frame |
//! | `/ROBOT/detections` | JSON, `muster.Detections` | each robot's camera detections (colour, bearing, range) |
//! | `/tracks` | `foxglove.SceneUpdate` | the targets the tracking systems track (a disc of their uncertainty, their velocity, named) |
//! | `/plans` | `foxglove.SceneUpdate` | the paths the delivery robots plan, from where they believe they are to their goal |
//! | `/muster/events` | JSON, `muster.Event` | the broker's event feed (`muster events`) |
//! | `/muster/list` | JSON, `muster.ServiceList` | the service list at each change |
//!
//! Log times are the recorder's clock (Unix time) when it took each sample; the world's
//! own (simulated) time is in each message.

use crate::cli::RecordArgs;
use anyhow::Context as _;
use foxglove::messages::{
    line_primitive, packed_element_field::NumericType, Color, CylinderPrimitive, FrameTransform,
    FrameTransforms, Grid, LaserScan, LinePrimitive, PackedElementField, Point3, Pose, Quaternion,
    SceneEntity, SceneUpdate, TextPrimitive, Timestamp, Vector2, Vector3,
};
use foxglove::{Channel, ChannelBuilder, Context, PartialMetadata, RawChannel, Schema};
use muster_shared::ipc::{create_node, EventReader, ListReader, VizReader};
use muster_shared::reactor::SignalPipe;
use muster_shared::viz::SystemView;
use muster_shared::Instance;
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::scenario::{Colour, Scenario};
use muster_sim_world::shm::{SensorsView, WorldState, WorldView};
use std::collections::BTreeMap;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Unix time now, ns.
fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

fn stamp(ns: u64) -> Option<Timestamp> {
    Some(Timestamp::new(
        u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX),
        (ns % 1_000_000_000) as u32,
    ))
}

fn yaw(theta: f64) -> Option<Quaternion> {
    Some(Quaternion {
        x: 0.0,
        y: 0.0,
        z: (theta / 2.0).sin(),
        w: (theta / 2.0).cos(),
    })
}

fn at(x: f64, y: f64, z: f64, theta: f64) -> Option<Pose> {
    Some(Pose {
        position: Some(Vector3 { x, y, z }),
        orientation: yaw(theta),
    })
}

fn colour(c: Option<Colour>, fallback: [u8; 3]) -> Option<Color> {
    let [r, g, b] = c.map_or(fallback, Colour::rgb);
    Some(Color {
        r: f64::from(r) / 255.0,
        g: f64::from(g) / 255.0,
        b: f64::from(b) / 255.0,
        a: 1.0,
    })
}

/// A named body as a scene entity: a cylinder and its name above it.
fn body(
    id: String,
    ns: u64,
    (x, y, theta): (f64, f64, f64),
    radius: f64,
    height: f64,
    color: Option<Color>,
    name: &str,
) -> SceneEntity {
    SceneEntity {
        timestamp: stamp(ns),
        frame_id: "map".into(),
        id,
        cylinders: vec![CylinderPrimitive {
            pose: at(x, y, height / 2.0, theta),
            size: Some(Vector3 {
                x: 2.0 * radius,
                y: 2.0 * radius,
                z: height,
            }),
            bottom_scale: 1.0,
            top_scale: 1.0,
            color,
        }],
        texts: vec![TextPrimitive {
            pose: at(x, y, height + 0.3, 0.0),
            billboard: true,
            font_size: 14.0,
            scale_invariant: true,
            color: colour(None, [0, 0, 0]),
            text: name.to_string(),
        }],
        ..Default::default()
    }
}

/// The JSON channels' schemas. Foxglove and Lichtblick take a JSON channel's fields from
/// its schema's `properties` (a schema without them is refused, "Failed to parse channel
/// schema"), each of one plain type: no `null`, no type lists, no `$ref`. A field that is
/// sometimes absent or null is still named with its type; an event's other fields depend
/// on its kind (`event`) and are not named.
mod json_schema {
    use serde_json::{json, Value};

    /// `/muster/events`: one [`muster_shared::protocol::EventRecord`].
    pub fn event() -> Value {
        json!({
            "title": "muster.Event",
            "description": "One event of the broker's feed; its other fields depend on `event`",
            "type": "object",
            "properties": {
                "epoch": {"type": "string", "description": "The broker run, 16 hex digits"},
                "seq": {"type": "integer", "description": "Number on this run's feed, from 1"},
                "t_ns": {"type": "integer", "description": "Unix time of publishing, ns"},
                "event": {"type": "string", "description": "What happened (registered, granted, refused, ...)"},
                "user": {"type": "string"},
                "system": {"type": "string"},
                "service": {"type": "string"},
                "req": {"type": "integer", "description": "The user's request number"},
                "session": {"type": "string", "description": "16 hex digits"},
                "code": {"type": "string"},
                "reason": {"type": "string"},
            },
        })
    }

    /// `/muster/list`: the list's generation and its rows
    /// ([`muster_shared::snapshot::ServiceView`]).
    pub fn service_list() -> Value {
        json!({
            "title": "muster.ServiceList",
            "type": "object",
            "properties": {
                "generation": {"type": "integer"},
                "services": {"type": "array", "items": {
                    "type": "object",
                    "properties": {
                        "id": {"type": "string"},
                        "system": {"type": "string"},
                        "name": {"type": "string"},
                        "description": {"type": "string"},
                        "kind": {"type": "string"},
                        "queue": {"type": "boolean"},
                        "quota": {"type": "integer"},
                        "in_use": {"type": "integer"},
                        "queued": {"type": "integer"},
                        "links": {"type": "integer"},
                        "withdrawn": {"type": "boolean"},
                        "payload": {"type": "string"},
                        "encoding": {"type": "string"},
                        "host": {"type": "string"},
                        "remote": {"type": "boolean"},
                    },
                }},
            },
        })
    }

    /// `/ROBOT/detections`: a camera frame's detections.
    pub fn detections() -> Value {
        json!({
            "title": "muster.Detections",
            "type": "object",
            "properties": {
                "time": {"type": "number", "description": "The frame's simulated time, s"},
                "detections": {"type": "array", "items": {
                    "type": "object",
                    "properties": {
                        "colour": {"type": "string", "description": "The beacon's colour (null: none seen)"},
                        "bearing": {"type": "number", "description": "rad, in the robot's frame"},
                        "range": {"type": "number", "description": "m"},
                    },
                }},
            },
        })
    }
}

fn json_channel(
    ctx: &Arc<Context>,
    topic: &str,
    schema: &serde_json::Value,
) -> anyhow::Result<Arc<RawChannel>> {
    let name = schema["title"].as_str().unwrap_or("muster.Json");
    Ok(ChannelBuilder::new(topic)
        .context(ctx)
        .message_encoding("json")
        .schema(Schema::new(
            name,
            "jsonschema",
            schema.to_string().into_bytes(),
        ))
        .build_raw()?)
}

/// The world and the infrastructure as Foxglove channels on one context: whatever sinks
/// the context has (an MCAP file, a live viewer) get every message.
pub struct Scene {
    ctx: Arc<Context>,
    inst: Instance,
    scenario: Scenario,
    map: OccupancyMap,
    map_channel: Channel<Grid>,
    tf: Channel<FrameTransforms>,
    robots: Channel<SceneUpdate>,
    people: Channel<SceneUpdate>,
    scans: BTreeMap<String, (Channel<LaserScan>, Arc<RawChannel>)>,
    events: Arc<RawChannel>,
    list: Arc<RawChannel>,
    tracks: Channel<SceneUpdate>,
    plans: Channel<SceneUpdate>,
    /// The local systems (from the list), and the views of those that show one.
    systems: std::collections::BTreeSet<String>,
    views: BTreeMap<String, VizReader>,
    node: iceoryx2::prelude::Node<muster_shared::ipc::Ipc>,
    world: Option<WorldView>,
    world_time: f64,
    sensors: BTreeMap<String, (SensorsView, f64)>,
    feed: Option<EventReader>,
    list_reader: Option<ListReader>,
    list_generation: Option<(u64, u64)>,
    next_list_read: Instant,
    next_attach: Instant,
    /// Messages written, per topic.
    pub counts: BTreeMap<String, u64>,
    /// Also given each event record's JSON (the view's operators).
    event_hook: Option<EventHook>,
}

/// Where a scene also sends each event record's JSON.
type EventHook = Box<dyn FnMut(&str)>;

impl Scene {
    /// Channels on `ctx` for instance `inst`'s world (as `scenario` and `map` set it up)
    /// and infrastructure.
    pub fn new(
        ctx: &Arc<Context>,
        inst: &Instance,
        scenario: Scenario,
        map: OccupancyMap,
    ) -> anyhow::Result<Self> {
        let node = create_node("muster-record", false).context("iceoryx2 node")?;
        let channel = |topic: &str| ChannelBuilder::new(topic).context(ctx);
        Ok(Scene {
            ctx: ctx.clone(),
            inst: inst.clone(),
            scenario,
            map,
            map_channel: channel("/map").build(),
            tf: channel("/tf").build(),
            robots: channel("/robots").build(),
            people: channel("/people").build(),
            scans: BTreeMap::new(),
            events: json_channel(ctx, "/muster/events", &json_schema::event())?,
            list: json_channel(ctx, "/muster/list", &json_schema::service_list())?,
            tracks: channel("/tracks").build(),
            plans: channel("/plans").build(),
            systems: std::collections::BTreeSet::new(),
            views: BTreeMap::new(),
            node,
            world: None,
            world_time: f64::NEG_INFINITY,
            sensors: BTreeMap::new(),
            feed: None,
            list_reader: None,
            list_generation: None,
            next_list_read: Instant::now(),
            next_attach: Instant::now(),
            counts: BTreeMap::new(),
            event_hook: None,
        })
    }

    /// Gives each of the broker's event records (JSON) to `f` too.
    pub fn on_event(&mut self, f: impl FnMut(&str) + 'static) {
        self.event_hook = Some(Box::new(f));
    }

    fn count(&mut self, topic: &str) {
        *self.counts.entry(topic.to_string()).or_default() += 1;
    }

    /// Writes the map (once per sink that should have it: call again for a new sink).
    pub fn log_map(&mut self) {
        let (w, h) = (self.map.width(), self.map.height());
        let mut data = Vec::with_capacity(w * h);
        for j in 0..h {
            for i in 0..w {
                data.push(if self.map.occupied(i as i64, j as i64) {
                    100u8
                } else {
                    0
                });
            }
        }
        let (ox, oy) = self.map.origin();
        let res = self.map.resolution();
        let ns = now_ns();
        self.map_channel.log_with_time(
            &Grid {
                timestamp: stamp(ns),
                frame_id: "map".into(),
                pose: at(ox, oy, 0.0, 0.0),
                column_count: u32::try_from(w).unwrap_or(u32::MAX),
                cell_size: Some(Vector2 { x: res, y: res }),
                row_stride: u32::try_from(w).unwrap_or(u32::MAX),
                cell_stride: 1,
                fields: vec![PackedElementField {
                    name: "occupied".into(),
                    offset: 0,
                    r#type: NumericType::Uint8 as i32,
                }],
                data: data.into(),
            },
            ns,
        );
        self.count("/map");
    }

    /// Opens what is not open yet (the simulator, the broker may start after us).
    fn attach(&mut self) {
        if Instant::now() < self.next_attach {
            return;
        }
        self.next_attach = Instant::now() + Duration::from_secs(1);
        if self.world.is_none() {
            self.world = WorldView::open(&self.node, self.inst.as_str()).ok();
        }
        if self.feed.is_none() {
            self.feed = EventReader::open(&self.node, &self.inst).ok();
        }
        if self.list_reader.is_none() {
            self.list_reader = ListReader::open(&self.node, &self.inst).ok();
        }
        let names: Vec<String> = self
            .scenario
            .robots
            .iter()
            .filter(|r| !self.sensors.contains_key(&r.name))
            .map(|r| r.name.clone())
            .collect();
        for n in names {
            if let Ok(v) = SensorsView::open(&self.node, self.inst.as_str(), &n) {
                self.sensors.insert(n, (v, f64::NEG_INFINITY));
            }
        }
        // The systems' own views (their tracks and plans).
        let new: Vec<String> = self
            .systems
            .iter()
            .filter(|s| !self.views.contains_key(*s))
            .cloned()
            .collect();
        for s in new {
            match VizReader::open(&self.node, &self.inst, &s) {
                Ok(r) => {
                    tracing::debug!("reading the view of system {s}");
                    self.views.insert(s, r);
                }
                Err(e) => tracing::debug!("the view of system {s}: {e}"),
            }
        }
    }

    /// Takes every new sample and event and logs it; returns whether anything was new.
    pub fn poll(&mut self) -> anyhow::Result<bool> {
        self.attach();
        let mut any = false;
        // The world: frames, robots, people.
        let mut sample = None;
        if let Some(w) = &self.world {
            sample = w
                .next(self.world_time, Duration::ZERO, |s: &WorldState| {
                    Box::new(*s)
                })
                .ok()
                .flatten();
        }
        if let Some(s) = sample {
            self.world_time = s.time;
            self.log_world(&s);
            any = true;
        }
        // Each robot's sensors.
        let names: Vec<String> = self.sensors.keys().cloned().collect();
        for n in names {
            let Some((view, after)) = self.sensors.get(&n) else {
                continue;
            };
            let got = view
                .latest(*after, |s| {
                    let laser: Vec<f64> = s.laser[..(s.n_beams as usize).min(s.laser.len())]
                        .iter()
                        .map(|r| f64::from(*r))
                        .collect();
                    let dets: Vec<serde_json::Value> = s.detections
                        [..(s.n_detections as usize).min(s.detections.len())]
                        .iter()
                        .map(|d| {
                            serde_json::json!({
                                "colour": muster_sim_world::shm::detection_colour(d).map(Colour::name),
                                "bearing": d.bearing,
                                "range": d.range,
                            })
                        })
                        .collect();
                    (s.time, s.laser_time, laser, s.camera_time, dets)
                })
                .ok()
                .flatten();
            if let Some((time, laser_time, laser, camera_time, dets)) = got {
                self.log_sensors(&n, time, laser_time, laser, camera_time, dets)?;
                any = true;
            }
        }
        // The systems' views.
        let views: Vec<SystemView> = self
            .views
            .values_mut()
            .filter_map(VizReader::latest)
            .collect();
        for v in views {
            tracing::trace!(system = %v.system, t = v.t, tracks = v.tracks.len(), plans = v.plans.len(), "a system's view");
            self.log_view(&v);
            any = true;
        }
        // The broker's events.
        let mut events = Vec::new();
        if let Some(f) = self.feed.as_mut() {
            while let Some(rec) = f.next_event() {
                events.push(rec);
            }
        }
        for rec in events {
            let json = serde_json::to_string(&rec)?;
            if let Some(f) = self.event_hook.as_mut() {
                f(&json);
            }
            self.events
                .log_with_meta(json.as_bytes(), PartialMetadata::with_log_time(rec.t_ns));
            self.count("/muster/events");
            any = true;
        }
        // The list, when it changed.
        if Instant::now() >= self.next_list_read {
            self.next_list_read = Instant::now() + Duration::from_millis(100);
            let node = &self.node;
            // `read_from` moves to a new broker's list (a restart, a takeover).
            if let Some(snap) = self
                .list_reader
                .as_mut()
                .and_then(|r| r.read_from(node).ok())
            {
                let key = (snap.epoch, snap.generation);
                if snap.epoch != 0 && self.list_generation != Some(key) {
                    self.list_generation = Some(key);
                    for v in snap.views() {
                        if !v.remote {
                            self.systems.insert(v.system.clone());
                        }
                    }
                    let v = serde_json::json!({
                        "generation": snap.generation,
                        "services": snap.views(),
                    });
                    let ns = now_ns();
                    self.list.log_with_meta(
                        &serde_json::to_vec(&v)?,
                        PartialMetadata::with_log_time(ns),
                    );
                    self.count("/muster/list");
                    any = true;
                }
            }
        }
        Ok(any)
    }

    /// A system's tracks and plans. Each entity lives 2 s unless shown again, so what a
    /// system stops showing (a track it lost, a goal reached) leaves the scene.
    fn log_view(&mut self, v: &SystemView) {
        let ns = now_ns();
        let lifetime = Some(foxglove::messages::Duration::new(2, 0));
        let point = |(x, y): (f64, f64), z: f64| Point3 { x, y, z };
        let line = |points: Vec<Point3>, color: Option<Color>| LinePrimitive {
            r#type: line_primitive::Type::LineStrip as i32,
            pose: at(0.0, 0.0, 0.0, 0.0),
            thickness: 3.0,
            scale_invariant: true,
            points,
            color,
            colors: Vec::new(),
            indices: Vec::new(),
        };
        if !v.tracks.is_empty() {
            let entities = v
                .tracks
                .iter()
                .map(|t| {
                    let c = Colour::from_name(&t.colour);
                    let mut color = colour(c, [120, 120, 120]);
                    if let Some(c) = color.as_mut() {
                        c.a = if t.lost { 0.2 } else { 0.5 };
                    }
                    let mut e = body(
                        format!("track/{}/{}", v.system, t.colour),
                        ns,
                        (t.x, t.y, 0.0),
                        t.sigma.max(0.15),
                        0.05,
                        color,
                        &format!("track {}{}", t.colour, if t.lost { " (lost)" } else { "" }),
                    );
                    // Where it will be in a second.
                    e.lines.push(line(
                        vec![
                            point((t.x, t.y), 0.05),
                            point((t.x + t.vx, t.y + t.vy), 0.05),
                        ],
                        colour(c, [120, 120, 120]),
                    ));
                    e.lifetime = lifetime;
                    e
                })
                .collect();
            self.tracks.log_with_time(
                &SceneUpdate {
                    deletions: Vec::new(),
                    entities,
                },
                ns,
            );
            self.count("/tracks");
        }
        if !v.plans.is_empty() {
            let entities = v
                .plans
                .iter()
                .map(|p| {
                    let from = v
                        .robots
                        .iter()
                        .find(|r| r.name == p.robot)
                        .map(|r| (r.x, r.y));
                    let points = from
                        .into_iter()
                        .chain(p.path.iter().copied())
                        .map(|xy| point(xy, 0.02))
                        .collect();
                    let mut e = body(
                        format!("plan/{}", p.robot),
                        ns,
                        (p.goal.0, p.goal.1, 0.0),
                        0.2,
                        0.02,
                        colour(None, [230, 120, 20]),
                        &format!("goal of {}", p.robot),
                    );
                    e.lines.push(line(points, colour(None, [230, 120, 20])));
                    e.lifetime = lifetime;
                    e
                })
                .collect();
            self.plans.log_with_time(
                &SceneUpdate {
                    deletions: Vec::new(),
                    entities,
                },
                ns,
            );
            self.count("/plans");
        }
    }

    fn log_world(&mut self, s: &WorldState) {
        let ns = now_ns();
        let robots = &s.robots[..(s.n_robots as usize).min(s.robots.len())];
        let people = &s.people[..(s.n_people as usize).min(s.people.len())];
        let transforms = robots
            .iter()
            .map(|r| FrameTransform {
                timestamp: stamp(ns),
                parent_frame_id: "map".into(),
                child_frame_id: r.name.as_str().to_string(),
                translation: Some(Vector3 {
                    x: r.pose.x,
                    y: r.pose.y,
                    z: 0.0,
                }),
                rotation: yaw(r.pose.theta),
            })
            .collect();
        self.tf.log_with_time(&FrameTransforms { transforms }, ns);
        self.count("/tf");
        let entities = robots
            .iter()
            .map(|r| {
                let name = r.name.as_str();
                let c = Colour::from_code(r.beacon.wrapping_sub(1));
                body(
                    format!("robot/{name}"),
                    ns,
                    (r.pose.x, r.pose.y, r.pose.theta),
                    0.25,
                    0.4,
                    colour(c, [40, 40, 40]),
                    name,
                )
            })
            .collect();
        self.robots.log_with_time(
            &SceneUpdate {
                deletions: Vec::new(),
                entities,
            },
            ns,
        );
        self.count("/robots");
        let entities = people
            .iter()
            .map(|p| {
                let name = p.name.as_str();
                body(
                    format!("person/{name}"),
                    ns,
                    (p.pose.x, p.pose.y, p.pose.theta),
                    0.2,
                    1.7,
                    colour(Colour::from_code(p.beacon), [120, 120, 120]),
                    name,
                )
            })
            .collect();
        self.people.log_with_time(
            &SceneUpdate {
                deletions: Vec::new(),
                entities,
            },
            ns,
        );
        self.count("/people");
    }

    fn log_sensors(
        &mut self,
        robot: &str,
        time: f64,
        laser_time: f64,
        laser: Vec<f64>,
        camera_time: f64,
        detections: Vec<serde_json::Value>,
    ) -> anyhow::Result<()> {
        let ns = now_ns();
        let last = self
            .sensors
            .get(robot)
            .map_or(f64::NEG_INFINITY, |(_, t)| *t);
        if let Some((_, t)) = self.sensors.get_mut(robot) {
            *t = time;
        }
        if !self.scans.contains_key(robot) {
            let scan = ChannelBuilder::new(format!("/{robot}/laser"))
                .context(&self.ctx)
                .build();
            let dets = json_channel(
                &self.ctx,
                &format!("/{robot}/detections"),
                &json_schema::detections(),
            )?;
            self.scans.insert(robot.to_string(), (scan, dets));
        }
        let fov = self
            .scenario
            .robots
            .iter()
            .find(|r| r.name == robot)
            .and_then(|r| r.laser.as_ref())
            .map_or(std::f64::consts::PI, |l| l.fov_deg.to_radians());
        let Some((scan, dets)) = self.scans.get(robot) else {
            return Ok(());
        };
        // A sample carries the latest scan and frame: log each once.
        let (mut scanned, mut seen) = (false, false);
        if laser_time > last && !laser.is_empty() {
            scan.log_with_time(
                &LaserScan {
                    timestamp: stamp(ns),
                    frame_id: robot.to_string(),
                    pose: at(0.0, 0.0, 0.0, 0.0),
                    start_angle: -fov / 2.0,
                    end_angle: fov / 2.0,
                    ranges: laser,
                    intensities: Vec::new(),
                },
                ns,
            );
            scanned = true;
        }
        // A robot without a camera never has a frame (its time stays 0).
        if camera_time > last && camera_time > 0.0 {
            let v = serde_json::json!({"time": camera_time, "detections": detections});
            dets.log_with_meta(&serde_json::to_vec(&v)?, PartialMetadata::with_log_time(ns));
            seen = true;
        }
        if scanned {
            self.count(&format!("/{robot}/laser"));
        }
        if seen {
            self.count(&format!("/{robot}/detections"));
        }
        Ok(())
    }
}

/// The scenario and map a recorder or viewer draws: the simulator's own flags.
pub fn scenario_and_map(
    scenario: Option<&std::path::Path>,
    map: Option<&std::path::Path>,
) -> anyhow::Result<(Scenario, OccupancyMap)> {
    let scenario = match scenario {
        Some(p) => Scenario::load(p)?,
        None => Scenario::paper(),
    };
    let map = match (map, scenario.map.as_deref()) {
        (Some(p), _) | (None, Some(p)) => OccupancyMap::load(p)?,
        (None, None) => OccupancyMap::office(),
    };
    Ok((scenario, map))
}

/// `muster record`.
pub fn run(inst: &Instance, a: RecordArgs) -> anyhow::Result<ExitCode> {
    let mut signals = SignalPipe::install().context("signal handlers")?;
    let (scenario, map) = scenario_and_map(a.scene.scenario.as_deref(), a.scene.map.as_deref())?;
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| format!("muster-{inst}.mcap").into());
    let ctx = Context::new();
    let writer = ctx
        .mcap_writer()
        .create_new_buffered_file(&out)
        .with_context(|| format!("creating {}", out.display()))?;
    let mut scene = Scene::new(&ctx, inst, scenario, map)?;
    scene.log_map();
    eprintln!(
        "muster record: recording instance {inst} into {}",
        out.display()
    );
    let mut taps = super::taps::Taps::new(inst, &ctx, &a.scene.services);
    let end = a.duration.map(|d| Instant::now() + d);
    loop {
        let any = scene.poll()? | taps.poll();
        if signals.drain() || end.is_some_and(|e| Instant::now() >= e) {
            break;
        }
        if !any {
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    writer.close().context("closing the MCAP file")?;
    let mut counts = scene.counts.clone();
    counts.extend(taps.counts.clone());
    let total: u64 = counts.values().sum();
    println!(
        "{}",
        serde_json::json!({"out": out, "messages": total, "topics": counts})
    );
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::json_schema;
    use muster_shared::protocol::{BrokerEvent, EventRecord};
    use muster_shared::snapshot::ServiceView;
    use muster_shared::types::{ServiceId, SessionId, UserId};
    use serde_json::{json, Value};

    const PLAIN: [&str; 6] = ["boolean", "string", "number", "integer", "object", "array"];

    /// What Foxglove's and Lichtblick's `parseJsonSchema` take: an object with
    /// `properties`, each of one plain type, arrays with typed items; `path` names the
    /// first thing they would refuse.
    fn parsable(schema: &Value, path: &str) -> Result<(), String> {
        if schema["type"] != "object" {
            return Err(format!("{path}: not an object"));
        }
        let props = schema["properties"]
            .as_object()
            .ok_or(format!("{path}: no properties"))?;
        for (name, p) in props {
            let path = format!("{path}.{name}");
            let ty = p["type"]
                .as_str()
                .ok_or(format!("{path}: no single type"))?;
            if !PLAIN.contains(&ty) {
                return Err(format!("{path}: type {ty}"));
            }
            if ty == "object" {
                parsable(p, &path)?;
            }
            if ty == "array" {
                let item = &p["items"];
                match item["type"].as_str() {
                    Some("object") => parsable(item, &path)?,
                    Some(t) if PLAIN.contains(&t) && t != "array" => {}
                    _ => return Err(format!("{path}: items of no plain type")),
                }
            }
        }
        Ok(())
    }

    /// Every field `schema` names that `v` has (and is not null) has the named type.
    fn conforms(schema: &Value, v: &Value, path: &str) -> Result<(), String> {
        let Some(props) = schema["properties"].as_object() else {
            return Ok(());
        };
        for (name, p) in props {
            let Some(field) = v.get(name).filter(|f| !f.is_null()) else {
                continue;
            };
            let path = format!("{path}.{name}");
            let ok = match p["type"].as_str() {
                Some("boolean") => field.is_boolean(),
                Some("string") => field.is_string(),
                Some("number") => field.is_number(),
                Some("integer") => field.is_u64() || field.is_i64(),
                Some("object") => {
                    conforms(p, field, &path)?;
                    field.is_object()
                }
                Some("array") => {
                    for (i, item) in field.as_array().into_iter().flatten().enumerate() {
                        conforms(&p["items"], item, &format!("{path}[{i}]"))?;
                    }
                    field.is_array()
                }
                _ => false,
            };
            if !ok {
                return Err(format!("{path}: {field} is not {}", p["type"]));
            }
        }
        Ok(())
    }

    #[test]
    fn the_json_channels_schemas_are_ones_foxglove_parses_and_describe_their_messages() {
        for (schema, name) in [
            (json_schema::event(), "muster.Event"),
            (json_schema::service_list(), "muster.ServiceList"),
            (json_schema::detections(), "muster.Detections"),
        ] {
            assert_eq!(schema["title"], name);
            assert_eq!(parsable(&schema, name), Ok(()));
        }
        // The check refuses what Foxglove refuses.
        assert!(parsable(&json!({"type": "object"}), "s").is_err());
        let nullable = json!({"type": "object", "properties": {"a": {"type": ["string", "null"]}}});
        assert!(parsable(&nullable, "s").is_err());

        let service = ServiceId("T1/track".into());
        let user = UserId("u1-ab".into());
        let events = [
            BrokerEvent::Granted {
                user: user.clone(),
                req: 7,
                service: service.clone(),
                session: SessionId(0x173f_b7d8_109c_04e4),
            },
            BrokerEvent::Refused {
                user: user.clone(),
                req: 8,
                code: "quota_full".into(),
                reason: "quota full".into(),
            },
            BrokerEvent::Registered {
                system: "T1".into(),
                services: vec!["track".into()],
            },
            BrokerEvent::Withdrawn {
                service,
                withdrawn: true,
            },
        ];
        for event in events {
            let rec = serde_json::to_value(EventRecord {
                epoch: "00000000000000ab".into(),
                seq: 3,
                t_ns: 1_700_000_000_000_000_000,
                event,
            })
            .unwrap();
            for always in ["epoch", "seq", "t_ns", "event"] {
                assert!(rec.get(always).is_some(), "{rec}");
            }
            assert_eq!(conforms(&json_schema::event(), &rec, "event"), Ok(()));
        }
        let row = ServiceView {
            id: "T1/track".into(),
            system: "T1".into(),
            name: "track".into(),
            quota: 3,
            in_use: 1,
            ..ServiceView::default()
        };
        let list = json!({"generation": 4, "services": [row]});
        let list_schema = json_schema::service_list();
        assert_eq!(conforms(&list_schema, &list, "list"), Ok(()));
        // Every field of a row is named.
        let row = &list["services"][0];
        let named = &list_schema["properties"]["services"]["items"]["properties"];
        for field in row.as_object().unwrap().keys() {
            assert!(named.get(field).is_some(), "{field} is not in the schema");
        }
        let dets = json!({"time": 1.5, "detections": [
            {"colour": "red", "bearing": 0.25, "range": 3.0},
            {"colour": null, "bearing": -0.5, "range": 7.5},
        ]});
        assert_eq!(conforms(&json_schema::detections(), &dets, "dets"), Ok(()));
        // The tapped services' built-in payloads (`muster record --service`): each
        // schema is one Foxglove parses, and describes what is written.
        use muster_shared::types::{Payload, Track2d};
        for p in [
            Payload::Pose2d {
                x: 1.0,
                y: 2.0,
                theta: 0.5,
            },
            Payload::Goal2d { x: 1.0, y: 2.0 },
            Payload::Twist { v: 0.3, w: -0.1 },
            Payload::Scalar(4.5),
            Payload::Text("hello".into()),
            Payload::Track2d(Track2d {
                x: 1.0,
                y: 2.0,
                vx: 0.1,
                vy: 0.0,
                sigma: 0.2,
                age: 0.0,
                seen_by: vec!["T1".into()],
                lost: false,
            }),
        ] {
            let t = p.type_name().to_string();
            let schema = super::super::taps::builtin_schema(&t);
            assert_eq!(parsable(&schema, &t), Ok(()));
            let msg = p.to_json();
            assert_eq!(conforms(&schema, &msg, &t), Ok(()));
            for field in msg.as_object().unwrap().keys() {
                assert!(
                    schema["properties"].get(field).is_some(),
                    "{t}: {field} is not in the schema"
                );
            }
        }
        // And the check finds a field of the wrong type.
        let wrong = json!({"time": "soon", "detections": []});
        assert!(conforms(&json_schema::detections(), &wrong, "dets").is_err());
    }
}
