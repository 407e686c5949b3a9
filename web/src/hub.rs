//! One signed-in muster user's connection to the broker, shared by all of its browser
//! tabs: a [`UserClient`] (shared memory, this host) driven by one of the
//! [`crate::pool::Pool`]'s workers, which takes the tabs' commands and broadcasts what
//! happens as JSON text frames.
//!
//! The broker trusts a local process as whoever it says it is, so the access file's
//! patterns are enforced here, exactly as the UDP front enforces them for remote users:
//! the list shows only what they allow, and a request or link for anything else is
//! refused as an unknown service would be.

use crate::pool::Pool;
use muster_shared::protocol::Operation;
use muster_shared::snapshot::{ServiceListSnapshot, ServiceView};
use muster_shared::types::{Payload, Schema, ServiceId, ServiceKind, SessionId};
use muster_shared::udp::access::Policy;
use muster_users::{UserClient, UserError, UserEvent, Wake};
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashMap};
use std::os::fd::{AsRawFd, OwnedFd};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::broadcast;

/// Frames a hub keeps for a slow tab before that tab has to start again from a
/// snapshot (a few seconds of 10 Hz sessions and list changes).
const BACKLOG: usize = 1024;
/// How long a hub stays connected with no tab open (a reload, a flaky network), its
/// sessions going on.
pub const LINGER: Duration = Duration::from_secs(60);

/// What a tab asks of its user's hub.
#[derive(Debug)]
pub enum Cmd {
    /// Request a service.
    Request(String),
    /// Give up a pending or queued request.
    Cancel(u64),
    /// End a session.
    End(u64),
    /// Task input on a command session, as JSON (see [`Payload::from_json`]).
    Input(u64, Value),
    /// Link a data service into a command service.
    Link(String, String),
    /// End a link.
    Unlink(u64),
    /// An operator's action (the hub's user must be an operator).
    Operate(Operation),
    /// The access file changed: this is the user's policy now.
    Policy(Box<Policy>),
    /// Sign out everywhere: end the sessions and disconnect.
    Close,
}

/// A session as the tabs see it.
#[derive(Clone, Debug)]
struct SessionState {
    service: String,
    kind: ServiceKind,
    payload: String,
    schema: Option<Schema>,
    /// The last update or status frame.
    last: Option<Value>,
    link: Option<u64>,
}

/// The service list, read once for every hub (`server`'s list reader) and handed
/// to them as rows, made once: each hub filters them by its user's patterns, not each
/// reading and decoding the list (at 500 hubs, a change decoded 500 times took the
/// hubs' threads from the updates for tens of milliseconds).
#[derive(Default)]
pub struct ListShare {
    list: Mutex<Option<Arc<SharedList>>>,
    version: AtomicU64,
}

/// One version of the list, as rows, and what changed since the one before.
pub(crate) struct SharedList {
    generation: u64,
    views: Vec<ServiceView>,
    /// Indexes in `views` of the rows new or changed since the version before.
    changed: Vec<usize>,
    /// Whether a row of the version before is gone.
    removed: bool,
}

impl ListShare {
    /// Stores a new snapshot; the hubs are to be rung after.
    pub fn set(&self, s: Arc<ServiceListSnapshot>) {
        let views = s.views();
        let mut slot = self.list.lock().unwrap_or_else(|e| e.into_inner());
        let (changed, removed) = match slot.as_ref() {
            Some(before) => {
                let old: HashMap<&str, &ServiceView> =
                    before.views.iter().map(|v| (v.id.as_str(), v)).collect();
                let changed: Vec<usize> = views
                    .iter()
                    .enumerate()
                    .filter(|(_, v)| old.get(v.id.as_str()) != Some(v))
                    .map(|(i, _)| i)
                    .collect();
                let kept = views.len() - changed.len()
                    + changed
                        .iter()
                        .filter(|i| old.contains_key(views[**i].id.as_str()))
                        .count();
                (changed, kept < old.len())
            }
            None => ((0..views.len()).collect(), false),
        };
        *slot = Some(Arc::new(SharedList {
            generation: s.generation,
            views,
            changed,
            removed,
        }));
        self.version.fetch_add(1, Ordering::AcqRel);
    }

    fn get(&self) -> (u64, Option<Arc<SharedList>>) {
        let list = self.list.lock().unwrap_or_else(|e| e.into_inner());
        (self.version.load(Ordering::Acquire), list.clone())
    }
}

/// What a new tab is shown first.
#[derive(Default)]
pub(crate) struct Model {
    list: Value,
    sessions: BTreeMap<u64, SessionState>,
    /// Requests out: service, queue position (0 while not queued).
    pending: BTreeMap<u64, (String, u16)>,
    links: BTreeMap<u64, Value>,
    broker_up: bool,
}

/// A user's hub, shared by its tabs.
pub struct Hub {
    /// The muster user name it signs in as.
    pub user: String,
    /// Whether the user may act as an operator.
    pub operator: bool,
    cmds: Mutex<mpsc::Sender<Cmd>>,
    wake: Arc<OwnedFd>,
    frames: broadcast::Sender<Arc<str>>,
    model: Arc<Mutex<Model>>,
    alive: Arc<AtomicBool>,
    tabs: AtomicUsize,
}

/// A tab's hold on a hub: counted while it lives.
pub struct Tab {
    hub: Arc<Hub>,
}

impl Drop for Tab {
    fn drop(&mut self) {
        self.hub.tabs.fetch_sub(1, Ordering::AcqRel);
    }
}

pub(crate) use muster_shared::reactor::{drain_eventfd as drain, eventfd, ring_eventfd as ring};

impl Hub {
    /// Connects `user` to the broker (waiting up to `wait` for one) on one of
    /// `pool`'s threads.
    pub fn start(
        pool: &Pool,
        user: &str,
        policy: Policy,
        wait: Duration,
        lists: Arc<ListShare>,
    ) -> Result<Arc<Hub>, String> {
        let (tx, rx) = mpsc::channel();
        let wake = Arc::new(eventfd().map_err(|e| format!("eventfd: {e}"))?);
        let (frames, _) = broadcast::channel(BACKLOG);
        let model = Arc::new(Mutex::new(Model::default()));
        let alive = Arc::new(AtomicBool::new(true));
        let hub = Arc::new(Hub {
            user: user.to_string(),
            operator: policy.operator,
            cmds: Mutex::new(tx),
            wake: wake.clone(),
            frames: frames.clone(),
            model: model.clone(),
            alive: alive.clone(),
            tabs: AtomicUsize::new(0),
        });
        let (ready_tx, ready_rx) = mpsc::channel();
        pool.start(Start {
            user: user.to_string(),
            policy,
            wait,
            lists,
            rx,
            wake,
            frames,
            model,
            alive,
            me: Arc::downgrade(&hub),
            ready: ready_tx,
        })?;
        ready_rx
            .recv()
            .map_err(|_| "the web console's worker thread died".to_string())??;
        Ok(hub)
    }

    /// Wakes the hub's worker for it (the shared list changed).
    pub fn notify(&self) {
        ring(&self.wake);
    }

    /// Whether its worker still drives it.
    pub fn alive(&self) -> bool {
        self.alive.load(Ordering::Acquire)
    }

    /// Sends a command to the hub's worker.
    pub fn send(&self, cmd: Cmd) {
        if let Ok(tx) = self.cmds.lock() {
            let _ = tx.send(cmd);
        }
        ring(&self.wake);
    }

    /// Opens a tab: the frame that shows everything now, and the frames after it (none
    /// lost between the two).
    pub fn open_tab(self: &Arc<Self>) -> (Tab, String, broadcast::Receiver<Arc<str>>) {
        self.tabs.fetch_add(1, Ordering::AcqRel);
        let model = self.model.lock().unwrap_or_else(|e| e.into_inner());
        let rx = self.frames.subscribe();
        let snapshot = self.snapshot(&model);
        drop(model);
        (Tab { hub: self.clone() }, snapshot, rx)
    }

    /// The whole state now, as a `state` frame (for a tab that fell behind).
    pub fn resync(&self) -> (String, broadcast::Receiver<Arc<str>>) {
        let model = self.model.lock().unwrap_or_else(|e| e.into_inner());
        let rx = self.frames.subscribe();
        (self.snapshot(&model), rx)
    }

    fn snapshot(&self, m: &Model) -> String {
        let sessions: Vec<Value> = m
            .sessions
            .iter()
            .map(|(id, s)| session_json(*id, s))
            .collect();
        let pending: Vec<Value> = m
            .pending
            .iter()
            .map(|(req, (service, position))| json!({"req": req, "service": service, "position": position}))
            .collect();
        let links: Vec<&Value> = m.links.values().collect();
        json!({
            "t": "state",
            "user": self.user,
            "operator": self.operator,
            "broker_up": m.broker_up,
            "list": m.list,
            "sessions": sessions,
            "pending": pending,
            "links": links,
        })
        .to_string()
    }

    /// The local systems the user may use a service of (whose tracks and plans the map
    /// shows it).
    pub fn systems(&self) -> std::collections::HashSet<String> {
        let model = self.model.lock().unwrap_or_else(|e| e.into_inner());
        model.list["services"]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|v| v["remote"] != json!(true))
            .filter_map(|v| v["system"].as_str().map(str::to_string))
            .collect()
    }

    /// Open tabs.
    pub fn tabs(&self) -> usize {
        self.tabs.load(Ordering::Acquire)
    }
}

fn session_json(id: u64, s: &SessionState) -> Value {
    json!({
        "session": SessionId(id).to_string(),
        "service": s.service,
        "kind": s.kind.to_string(),
        "payload": s.payload,
        "link": s.link,
        "last": s.last,
    })
}

/// What a worker needs to start a hub's user (see [`crate::pool::Pool`]).
pub(crate) struct Start {
    pub(crate) user: String,
    pub(crate) policy: Policy,
    pub(crate) wait: Duration,
    pub(crate) lists: Arc<ListShare>,
    pub(crate) rx: mpsc::Receiver<Cmd>,
    pub(crate) wake: Arc<OwnedFd>,
    pub(crate) frames: broadcast::Sender<Arc<str>>,
    pub(crate) model: Arc<Mutex<Model>>,
    pub(crate) alive: Arc<AtomicBool>,
    pub(crate) me: std::sync::Weak<Hub>,
    /// Told once the user is welcomed by the broker, or why not.
    pub(crate) ready: mpsc::Sender<Result<(), String>>,
}

/// A hub's user, driven by a worker thread.
pub(crate) struct Run {
    pub(crate) client: UserClient,
    policy: Policy,
    rx: mpsc::Receiver<Cmd>,
    wake: Arc<OwnedFd>,
    frames: broadcast::Sender<Arc<str>>,
    model: Arc<Mutex<Model>>,
    pub(crate) alive: Arc<AtomicBool>,
    me: std::sync::Weak<Hub>,
    pub(crate) name: String,
    lists: Arc<ListShare>,
    /// The version of the shared list last looked at.
    seen: u64,
    /// The services shown (the user's patterns allow them), by id.
    shown: BTreeMap<String, ServiceView>,
    /// Since when no tab is open.
    idle_since: Option<Instant>,
    /// Operator actions out: their number → what was asked.
    ops: HashMap<u64, String>,
}

impl Run {
    /// The hub's user, and whom to tell once it is welcomed.
    pub(crate) fn new(start: Start, client: UserClient) -> (Run, mpsc::Sender<Result<(), String>>) {
        let run = Run {
            client,
            policy: start.policy,
            rx: start.rx,
            wake: start.wake,
            frames: start.frames,
            model: start.model,
            alive: start.alive,
            me: start.me,
            name: start.user,
            lists: start.lists,
            seen: u64::MAX,
            shown: BTreeMap::new(),
            idle_since: None,
            ops: HashMap::new(),
        };
        (run, start.ready)
    }

    /// Ends the user's sessions and says goodbye.
    pub(crate) fn close(self) {
        self.client.close();
    }

    pub(crate) fn send(&self, v: Value) {
        let _ = self.frames.send(Arc::from(v.to_string()));
    }

    /// Updates the model and sends the frame under one lock, so a tab opening now sees
    /// either the state before and the frame, or the state after and not the frame.
    fn apply(&self, v: Value, f: impl FnOnce(&mut Model)) {
        let mut m = self.model.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut m);
        let _ = self.frames.send(Arc::from(v.to_string()));
    }

    /// Once welcomed: the list in the model before the first tab opens.
    pub(crate) fn init(&mut self) -> Result<(), UserError> {
        self.client.watch_extra(self.wake.as_raw_fd())?;
        self.apply(json!({"t": "broker", "up": true}), |m| m.broker_up = true);
        // The first hub comes before the shared reader has read anything.
        if self.lists.get().1.is_none() {
            let snap = self.client.list()?;
            self.lists.set(snap);
        }
        self.refresh_list(true);
        Ok(())
    }

    /// Handles whatever is here for this hub now (its client's news, its tabs'
    /// commands). `Ok(false)`: the hub is done (signed out).
    pub(crate) fn step(&mut self) -> Result<bool, UserError> {
        loop {
            match self.client.poll()? {
                Wake::Event(e) => self.on_event(e)?,
                Wake::Extra => {
                    drain(&self.wake);
                    self.refresh_list(false);
                    while let Ok(cmd) = self.rx.try_recv() {
                        if matches!(cmd, Cmd::Close) {
                            return Ok(false);
                        }
                        self.on_cmd(cmd)?;
                    }
                }
                Wake::Timeout => return Ok(true),
            }
        }
    }

    /// Once a second: whether the hub goes on (a tab is open, or was within
    /// [`LINGER`], and the hub is still wanted).
    pub(crate) fn keep(&mut self, now: Instant) -> bool {
        let Some(hub) = self.me.upgrade() else {
            return false;
        };
        if hub.tabs() > 0 {
            self.idle_since = None;
        } else if now.duration_since(*self.idle_since.get_or_insert(now)) >= LINGER {
            tracing::info!(user = %self.name, "no tab open for {LINGER:?}: disconnecting");
            return false;
        }
        true
    }

    /// Takes a new shared list, if there is one: the services the user's patterns allow,
    /// sent as a `list` frame (`force`: the whole list) or as a `list_delta` of what
    /// changed (`set`: new or changed rows, `removed`: ids), or nothing when nothing
    /// the user sees changed.
    fn refresh_list(&mut self, force: bool) {
        let (version, list) = self.lists.get();
        if !force && version == self.seen {
            return;
        }
        let next = self.seen.wrapping_add(1) == version;
        self.seen = version;
        let Some(list) = list else { return };
        // A hub that saw the version before looks only at the rows that changed: with
        // none it may see (a request elsewhere in the list), that is all.
        if next
            && !force
            && !list.removed
            && !list
                .changed
                .iter()
                .any(|i| self.policy.allows(&list.views[*i].id))
        {
            return;
        }
        // What changed for this user, without copying anything when nothing did.
        let mut allowed = 0;
        let mut new_rows = 0;
        let mut set: Vec<&ServiceView> = Vec::new();
        for v in list.views.iter().filter(|v| self.policy.allows(&v.id)) {
            allowed += 1;
            match self.shown.get(&v.id) {
                Some(old) if old == v => {}
                Some(_) => set.push(v),
                None => {
                    new_rows += 1;
                    set.push(v);
                }
            }
        }
        let gone = (self.shown.len() + new_rows).saturating_sub(allowed);
        if !force && set.is_empty() && gone == 0 {
            return;
        }
        let now: BTreeMap<String, ServiceView> = list
            .views
            .iter()
            .filter(|v| self.policy.allows(&v.id))
            .map(|v| (v.id.clone(), v.clone()))
            .collect();
        let removed: Vec<&String> = self
            .shown
            .keys()
            .filter(|id| !now.contains_key(*id))
            .collect();
        let generation = list.generation;
        let services: Vec<&ServiceView> = now.values().collect();
        let list_json = json!({"generation": generation, "services": services});
        let frame = if force {
            json!({"t": "list", "list": list_json})
        } else {
            json!({"t": "list_delta", "generation": generation, "set": set, "removed": removed})
        };
        self.apply(frame, |m| m.list = list_json);
        self.shown = now;
    }

    fn on_cmd(&mut self, cmd: Cmd) -> Result<(), UserError> {
        match cmd {
            Cmd::Request(service) => {
                if !self.policy.allows(&service) {
                    // As the UDP front answers a denied request: like an unknown service.
                    let r = muster_shared::types::Refusal::Unknown;
                    self.send(json!({"t": "refused", "req": 0, "service": service,
                                     "reason": r.to_string(), "code": r.code()}));
                    return Ok(());
                }
                let req = self.client.request(&ServiceId(service.clone()))?;
                self.apply(
                    json!({"t": "pending", "req": req, "service": service, "position": 0}),
                    |m| {
                        m.pending.insert(req, (service, 0));
                    },
                );
            }
            Cmd::Cancel(req) => {
                self.client.cancel(req);
                self.apply(json!({"t": "cancelled", "req": req}), |m| {
                    m.pending.remove(&req);
                });
            }
            Cmd::End(session) => self.client.end(SessionId(session)),
            Cmd::Input(session, value) => {
                let schema = {
                    let m = self.model.lock().unwrap_or_else(|e| e.into_inner());
                    match m.sessions.get(&session) {
                        Some(s) if s.kind == ServiceKind::Command => Ok(s.schema.clone()),
                        Some(_) => Err("not a command session".to_string()),
                        None => Err("no such session".to_string()),
                    }
                };
                let sent = schema.and_then(|schema| {
                    let payload = Payload::from_json(&value, schema.as_ref())?;
                    self.client.input(SessionId(session), payload)
                });
                if let Err(e) = sent {
                    self.send(
                        json!({"t": "input_refused", "session": SessionId(session).to_string(), "error": e}),
                    );
                }
            }
            Cmd::Link(data, command) => {
                let denied = [&data, &command]
                    .into_iter()
                    .find(|s| !self.policy.allows(s));
                let linked = match denied {
                    Some(s) => Err(UserError::UnknownService(s.to_string()).to_string()),
                    None => self
                        .client
                        .link(&ServiceId(data.clone()), &ServiceId(command.clone()))
                        .map_err(|e| e.to_string()),
                };
                match linked {
                    Ok(link) => {
                        let v = json!({"link": link, "data": data, "command": command, "up": false, "forwarded": 0});
                        self.apply(json!({"t": "link", "link": v}), |m| {
                            m.links.insert(link, v.clone());
                        });
                    }
                    Err(e) => self.send(
                        json!({"t": "link_refused", "data": data, "command": command, "error": e}),
                    ),
                }
            }
            Cmd::Unlink(link) => self.client.unlink(link),
            Cmd::Operate(op) => {
                if !self.policy.operator {
                    self.send(json!({"t": "operated", "ok": false, "error": "not an operator"}));
                    return Ok(());
                }
                let what = format!("{op:?}");
                let id = self.client.operate(op);
                self.ops.insert(id, what);
            }
            Cmd::Policy(p) => {
                self.policy = *p;
                self.refresh_list(true);
            }
            Cmd::Close => {}
        }
        Ok(())
    }

    pub(crate) fn on_event(&mut self, e: UserEvent) -> Result<(), UserError> {
        match e {
            UserEvent::Connected { .. } => {
                self.apply(json!({"t": "broker", "up": true}), |m| m.broker_up = true);
                self.refresh_list(false);
            }
            UserEvent::BrokerLost => {
                self.apply(json!({"t": "broker", "up": false}), |m| m.broker_up = false)
            }
            UserEvent::ListChanged => self.refresh_list(false),
            UserEvent::Queued {
                req,
                service,
                position,
            } => self.apply(
                json!({"t": "pending", "req": req, "service": service.0, "position": position}),
                |m| {
                    m.pending.insert(req, (service.0.clone(), position));
                },
            ),
            UserEvent::Granted {
                req,
                session,
                service,
                kind,
                payload,
                schema,
            } => {
                let link = self.client.core().session_link(session);
                let s = SessionState {
                    service: service.0.clone(),
                    kind,
                    payload,
                    schema,
                    last: None,
                    link,
                };
                let mut frame = session_json(session.0, &s);
                frame["t"] = json!("granted");
                frame["req"] = json!(req);
                self.apply(frame, |m| {
                    m.pending.remove(&req);
                    m.sessions.insert(session.0, s);
                });
            }
            UserEvent::Refused {
                req,
                service,
                reason,
            } => {
                let frame = json!({"t": "refused", "req": req, "service": service.0, "reason": reason.to_string(), "code": reason.code()});
                self.apply(frame, |m| {
                    m.pending.remove(&req);
                });
            }
            UserEvent::Update {
                session,
                service,
                seq,
                gap,
                sent_ns,
                payload,
            } => {
                let mut m = self.model.lock().unwrap_or_else(|e| e.into_inner());
                let Some(s) = m.sessions.get_mut(&session.0) else {
                    return Ok(());
                };
                let value = payload.to_json_with(s.schema.as_ref());
                // `hub_ns`: when this process had it (CLOCK_MONOTONIC), to tell the
                // web's share of the latency from the network's and the browser's.
                let hub_ns = muster_shared::protocol::monotonic_ns();
                let frame = json!({"t": "update", "session": session.to_string(), "service": service.0, "seq": seq, "gap": gap, "sent_ns": sent_ns, "hub_ns": hub_ns, "value": value});
                s.last = Some(frame.clone());
                let _ = self.frames.send(Arc::from(frame.to_string()));
            }
            UserEvent::Status {
                session,
                service,
                seq,
                status,
            } => {
                let frame = json!({"t": "status", "session": session.to_string(), "service": service.0, "seq": seq, "state": status.state(), "detail": status.detail()});
                self.apply(frame.clone(), |m| {
                    if let Some(s) = m.sessions.get_mut(&session.0) {
                        s.last = Some(frame);
                    }
                });
            }
            UserEvent::Ended {
                session,
                service,
                reason,
                ..
            } => {
                let frame = json!({"t": "ended", "session": session.to_string(), "service": service.0, "reason": reason.to_string(), "code": reason.code()});
                self.apply(frame, |m| {
                    m.sessions.remove(&session.0);
                });
            }
            UserEvent::EndConfirmed { .. } | UserEvent::Feed(_) => {}
            UserEvent::LinkUp { link } => {
                self.apply(json!({"t": "link_up", "link": link}), |m| {
                    if let Some(l) = m.links.get_mut(&link) {
                        l["up"] = json!(true);
                    }
                });
            }
            UserEvent::LinkForwarded { link, input } => {
                let input = input.to_json();
                self.apply(
                    json!({"t": "forwarded", "link": link, "input": input}),
                    |m| {
                        if let Some(l) = m.links.get_mut(&link) {
                            let n = l["forwarded"].as_u64().unwrap_or(0) + 1;
                            l["forwarded"] = json!(n);
                        }
                    },
                );
            }
            UserEvent::LinkEnded { link, reason } => {
                self.apply(
                    json!({"t": "link_ended", "link": link, "reason": reason}),
                    |m| {
                        m.links.remove(&link);
                    },
                );
            }
            UserEvent::Operated { id, result } => {
                let what = self.ops.remove(&id).unwrap_or_default();
                let frame = match result {
                    Ok(Some(status)) => {
                        json!({"t": "operated", "ok": true, "what": what, "status": serde_json::to_value(&*status).unwrap_or(Value::Null)})
                    }
                    Ok(None) => json!({"t": "operated", "ok": true, "what": what}),
                    Err(e) => json!({"t": "operated", "ok": false, "what": what, "error": e}),
                };
                self.send(frame);
            }
        }
        Ok(())
    }
}
