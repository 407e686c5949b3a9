//! Services a recorder or viewer taps as a user (`muster record --service ID`, `muster
//! view --service ID`): each granted session's updates on a channel of their own,
//! `/muster/services/<system>/<service>`, with their schema — an open type's own (a ROS
//! 2 message: `ros2msg` schema, `cdr` messages, which Foxglove and the Python `mcap`
//! readers decode natively), a JSON Schema for the built-in types.

use foxglove::{ChannelBuilder, Context, RawChannel, Schema};
use muster_shared::types::{Payload, SchemaEncoding, ServiceId, SessionId};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient, UserEvent};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A refused or ended tap is asked for again after this long.
const RETRY: Duration = Duration::from_secs(1);

/// The JSON Schema of a built-in payload type's JSON form (`Payload::to_json`).
pub fn builtin_schema(payload: &str) -> Value {
    let num = json!({"type": "number"});
    let props = match payload {
        "pose2d" => json!({"type": {"type": "string"}, "x": num, "y": num, "theta": num}),
        "goal2d" => json!({"type": {"type": "string"}, "x": num, "y": num}),
        "twist" => json!({"type": {"type": "string"}, "v": num, "w": num}),
        "scalar" => json!({"type": {"type": "string"}, "value": num}),
        "track2d" => json!({"type": {"type": "string"}, "x": num, "y": num, "vx": num,
            "vy": num, "sigma": num, "age": num, "lost": {"type": "boolean"},
            "seen_by": {"type": "array", "items": {"type": "string"}}}),
        _ => json!({"type": {"type": "string"}, "text": {"type": "string"}}),
    };
    json!({"title": format!("muster.{payload}"), "type": "object", "properties": props})
}

struct Tap {
    service: ServiceId,
    /// The request waiting for an answer, or the session granted.
    req: Option<u64>,
    session: Option<SessionId>,
    channel: Option<Arc<RawChannel>>,
    retry_at: Instant,
}

/// The tapped services of one instance, written to `ctx`'s sinks.
pub struct Taps {
    inst: Instance,
    ctx: Arc<Context>,
    client: Option<UserClient>,
    taps: Vec<Tap>,
    next_connect: Instant,
    /// Messages written, per topic.
    pub counts: BTreeMap<String, u64>,
}

impl Taps {
    /// Taps `services` of `inst` (connecting when a broker is there).
    pub fn new(inst: &Instance, ctx: &Arc<Context>, services: &[String]) -> Self {
        let now = Instant::now();
        Taps {
            inst: inst.clone(),
            ctx: ctx.clone(),
            client: None,
            taps: services
                .iter()
                .map(|s| Tap {
                    service: ServiceId(s.clone()),
                    req: None,
                    session: None,
                    channel: None,
                    retry_at: now,
                })
                .collect(),
            next_connect: now,
            counts: BTreeMap::new(),
        }
    }

    /// Requests what is due and writes every update waiting; true if it wrote any.
    pub fn poll(&mut self) -> bool {
        let now = Instant::now();
        if self.taps.is_empty() {
            return false;
        }
        if self.client.is_none() {
            if now < self.next_connect {
                return false;
            }
            self.next_connect = now + RETRY;
            // The welcome is a round trip (a few ms); while no broker runs, each try
            // holds the recorder this long once a second.
            let opts = ConnectOptions {
                wait_for_broker: Duration::from_millis(300),
                handle_signals: false,
                watch_list: false,
            };
            match UserClient::connect(&self.inst, &opts) {
                Ok(c) => self.client = Some(c),
                Err(e) => {
                    tracing::debug!("taps: no broker yet: {e}");
                    return false;
                }
            }
        }
        let Some(client) = self.client.as_mut() else {
            return false;
        };
        for t in &mut self.taps {
            if t.req.is_none() && t.session.is_none() && now >= t.retry_at {
                match client.request(&t.service) {
                    Ok(req) => t.req = Some(req),
                    Err(e) => {
                        tracing::warn!("taps: cannot request {}: {e}", t.service);
                        t.retry_at = now + RETRY;
                    }
                }
            }
        }
        let mut wrote = false;
        loop {
            let event = match client.try_event() {
                Ok(Some(e)) => e,
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!("taps: the connection failed ({e}); connecting again");
                    self.client = None;
                    for t in &mut self.taps {
                        (t.req, t.session) = (None, None);
                    }
                    break;
                }
            };
            match event {
                UserEvent::Granted {
                    req,
                    session,
                    payload,
                    schema,
                    ..
                } => {
                    let Some(t) = self.taps.iter_mut().find(|t| t.req == Some(req)) else {
                        continue;
                    };
                    t.req = None;
                    t.session = Some(session);
                    let topic = format!("/muster/services/{}", t.service);
                    let (encoding, schema) = match &schema {
                        Some(s) => (
                            s.encoding.message_encoding(),
                            Schema::new(
                                payload.as_str(),
                                s.encoding.as_str(),
                                s.text.clone().into_bytes(),
                            ),
                        ),
                        None => (
                            "json",
                            Schema::new(
                                format!("muster.{payload}"),
                                SchemaEncoding::JsonSchema.as_str(),
                                builtin_schema(&payload).to_string().into_bytes(),
                            ),
                        ),
                    };
                    // A channel per grant: a service whose type changed across a restart
                    // gets a new one.
                    match ChannelBuilder::new(&topic)
                        .context(&self.ctx)
                        .message_encoding(encoding)
                        .schema(schema)
                        .build_raw()
                    {
                        Ok(c) => t.channel = Some(c),
                        Err(e) => tracing::warn!("taps: channel {topic}: {e}"),
                    }
                    tracing::info!(service = %t.service, payload, "tapping");
                }
                UserEvent::Refused { req, reason, .. } => {
                    if let Some(t) = self.taps.iter_mut().find(|t| t.req == Some(req)) {
                        tracing::info!(service = %t.service, "taps: refused ({reason}); asking again");
                        t.req = None;
                        t.retry_at = now + RETRY;
                    }
                }
                UserEvent::Ended {
                    session, reason, ..
                } => {
                    if let Some(t) = self.taps.iter_mut().find(|t| t.session == Some(session)) {
                        tracing::info!(service = %t.service, "taps: session ended ({reason}); asking again");
                        t.session = None;
                        t.retry_at = now + RETRY;
                    }
                }
                UserEvent::Update {
                    session, payload, ..
                } => {
                    let Some(t) = self.taps.iter().find(|t| t.session == Some(session)) else {
                        continue;
                    };
                    let Some(c) = &t.channel else { continue };
                    match &payload {
                        Payload::Encoded { data, .. } => c.log(data),
                        p => c.log(p.to_json().to_string().as_bytes()),
                    }
                    *self.counts.entry(c.topic().to_string()).or_default() += 1;
                    wrote = true;
                }
                _ => {}
            }
        }
        wrote
    }
}
