//! A user: a [`UserClient`] on a thread of its own, driven through channels.

use crate::{guarded, payload_from_py, payload_to_py, recv_interruptibly};
use crate::{Closed, MusterError, NoBroker, PayloadError, UnknownService};
use muster_shared::snapshot::ServiceView;
use muster_shared::types::{EndReason, Refusal, Schema, ServiceId, SessionId};
use muster_shared::Instance;
use muster_users::{ConnectOptions, RemoteOptions, UserClient, UserError, UserEvent, Wake};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::collections::HashMap;
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// What Python asks of the client's thread.
enum Cmd {
    List(Sender<Result<Vec<ServiceView>, String>>),
    Request(ServiceId, Sender<u64>),
    Cancel(u64),
    Input(SessionId, muster_shared::types::Payload, Sender<Result<(), String>>),
    End(SessionId),
    Link(ServiceId, ServiceId, Sender<Result<u64, String>>),
    Unlink(u64),
    Close(Sender<()>),
}

/// What the client's thread hands Python.
enum Out {
    Event(Box<UserEvent>),
    /// The client stopped (its error).
    Failed(String),
}

/// How to connect, carried to the client's thread.
enum Target {
    Local(Instance),
    Remote(RemoteOptions),
}

/// A user of the federation: local (shared memory) or remote (UDP with a key).
#[pyclass(module = "muster._native")]
pub struct NativeUser {
    id: String,
    remote: bool,
    cmds: Sender<Cmd>,
    bell: UnixStream,
    events: Mutex<Receiver<Out>>,
    /// Rung (a byte) when events come, once Python asked for the descriptor (asyncio).
    notify_r: UnixStream,
    notify_on: std::sync::Arc<AtomicBool>,
    /// Each held session's payload type and schema, from its grant: input is checked
    /// against the type, and an open type's samples decode by the schema.
    schemas: Mutex<HashMap<u64, (String, Option<Schema>)>>,
    closed: AtomicBool,
}

impl NativeUser {
    /// Sends a command and wakes the client's thread.
    fn send(&self, cmd: Cmd) -> PyResult<()> {
        if self.closed.load(Ordering::Relaxed) {
            return Err(Closed::new_err("this user is closed"));
        }
        self.cmds
            .send(cmd)
            .map_err(|_| Closed::new_err("the user's client stopped"))?;
        let _ = (&self.bell).write(&[1]);
        Ok(())
    }

    /// Sends a command and waits for its answer.
    fn ask<T: Send>(&self, py: Python<'_>, make: impl FnOnce(Sender<T>) -> Cmd) -> PyResult<T> {
        let (tx, rx) = channel();
        self.send(make(tx))?;
        recv_interruptibly(py, &Mutex::new(rx), None)?
            .ok_or_else(|| Closed::new_err("the user's client stopped"))
    }
}

#[pymethods]
impl NativeUser {
    /// Connects: to the broker of `instance` over shared memory, or to the broker's UDP
    /// front at `remote` with the key file `key` (`muster keygen`).
    #[new]
    #[pyo3(signature = (instance="default", remote=None, key=None, broker_key=None, wait=5.0))]
    fn new(
        py: Python<'_>,
        instance: &str,
        remote: Option<&str>,
        key: Option<&str>,
        broker_key: Option<&str>,
        wait: f64,
    ) -> PyResult<Self> {
        guarded(|| {
            let target = match (remote, key) {
                (None, None) => Target::Local(
                    Instance::new(instance).map_err(|e| MusterError::new_err(e.to_string()))?,
                ),
                (None, Some(_)) => {
                    return Err(MusterError::new_err(
                        "key is for remote users: give remote=\"HOST:PORT\" too",
                    ))
                }
                (Some(_), None) => {
                    return Err(MusterError::new_err(
                        "a remote user needs its key file: key=\"NAME.key\" (muster keygen)",
                    ))
                }
                (Some(addr), Some(path)) => {
                    let broker = addr.parse().map_err(|e| {
                        MusterError::new_err(format!("remote {addr:?}: not HOST:PORT ({e})"))
                    })?;
                    let (name, key) =
                        muster_shared::udp::crypto::KeyPair::read(std::path::Path::new(path))
                            .map_err(|e| MusterError::new_err(e.to_string()))?;
                    let broker_key = broker_key
                        .map(muster_shared::udp::crypto::parse_key)
                        .transpose()
                        .map_err(|e| MusterError::new_err(format!("broker_key: {e}")))?;
                    Target::Remote(RemoteOptions {
                        broker,
                        name,
                        key,
                        broker_key,
                        faults: None,
                    })
                }
            };
            let is_remote = matches!(target, Target::Remote(_));
            if !(wait.is_finite() && wait >= 0.0) {
                return Err(MusterError::new_err("wait must be a number of seconds ≥ 0"));
            }
            let opts = ConnectOptions {
                wait_for_broker: Duration::from_secs_f64(wait),
                handle_signals: false,
                watch_list: true,
            };
            let (bell_r, bell) = UnixStream::pair()?;
            bell_r.set_nonblocking(true)?;
            bell.set_nonblocking(true)?;
            let (notify_r, notify_w) = UnixStream::pair()?;
            notify_r.set_nonblocking(true)?;
            notify_w.set_nonblocking(true)?;
            let notify_on = std::sync::Arc::new(AtomicBool::new(false));
            let (cmds, cmd_rx) = channel();
            let (ev_tx, events) = channel();
            let (ready_tx, ready) = channel();
            let on = notify_on.clone();
            std::thread::Builder::new()
                .name("muster-user".into())
                .spawn(move || {
                    let run = std::panic::AssertUnwindSafe(|| {
                        drive(target, opts, ready_tx, cmd_rx, bell_r, &ev_tx, notify_w, on)
                    });
                    if let Err(p) = std::panic::catch_unwind(run) {
                        let _ = ev_tx.send(Out::Failed(format!(
                            "muster panicked: {}",
                            crate::panic_text(p.as_ref())
                        )));
                    }
                })?;
            let id = recv_interruptibly(py, &Mutex::new(ready), None)?
                .ok_or_else(|| Closed::new_err("the user's client did not start"))??;
            Ok(NativeUser {
                id,
                remote: is_remote,
                cmds,
                bell,
                events: Mutex::new(events),
                notify_r,
                notify_on,
                schemas: Mutex::new(HashMap::new()),
                closed: AtomicBool::new(false),
            })
        })
    }

    /// This user's id, as the broker knows it.
    #[getter]
    fn id(&self) -> String {
        self.id.clone()
    }

    /// Whether this user is remote (UDP).
    #[getter]
    fn remote(&self) -> bool {
        self.remote
    }

    /// The service list, as dicts.
    fn list<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guarded(|| {
            let views = self
                .ask(py, Cmd::List)?
                .map_err(MusterError::new_err)?;
            let out = PyList::empty(py);
            for v in &views {
                out.append(
                    pythonize::pythonize(py, v)
                        .map_err(|e| MusterError::new_err(e.to_string()))?,
                )?;
            }
            Ok(out)
        })
    }

    /// Asks for service `id`; returns the request's number (its answer comes as an
    /// event: `queued`, `granted` or `refused`).
    fn request(&self, py: Python<'_>, id: &str) -> PyResult<u64> {
        guarded(|| self.ask(py, |tx| Cmd::Request(ServiceId(id.to_string()), tx)))
    }

    /// Gives up request `req` (waiting in a queue, or not answered yet).
    fn cancel(&self, req: u64) -> PyResult<()> {
        guarded(|| self.send(Cmd::Cancel(req)))
    }

    /// Sends task input `value` (a payload's JSON form) on command session `session`.
    fn input(&self, py: Python<'_>, session: u64, value: &Bound<'_, PyAny>) -> PyResult<()> {
        guarded(|| {
            let (declared, schema) = self
                .schemas
                .lock()
                .map_err(|_| MusterError::new_err("poisoned"))?
                .get(&session)
                .cloned()
                .ok_or_else(|| Closed::new_err(format!("no session {session}")))?;
            let payload = payload_from_py(value, schema.as_ref())?;
            if payload.type_name() != declared {
                return Err(PayloadError::new_err(format!(
                    "the service takes {declared}, not {}",
                    payload.type_name()
                )));
            }
            self.ask(py, |tx| Cmd::Input(SessionId(session), payload, tx))?
                .map_err(PayloadError::new_err)
        })
    }

    /// Ends session `session`.
    fn end(&self, session: u64) -> PyResult<()> {
        guarded(|| self.send(Cmd::End(SessionId(session))))
    }

    /// Links data service `data` into command service `command`; returns the link's
    /// number. Refused at once (with the reason) if they cannot be linked.
    fn link(&self, py: Python<'_>, data: &str, command: &str) -> PyResult<u64> {
        guarded(|| {
            let (d, c) = (ServiceId(data.to_string()), ServiceId(command.to_string()));
            self.ask(py, |tx| Cmd::Link(d, c, tx))?.map_err(|e| {
                if e.starts_with("unknown service") {
                    UnknownService::new_err(e)
                } else {
                    MusterError::new_err(e)
                }
            })
        })
    }

    /// Ends link `link` and its sessions.
    fn unlink(&self, link: u64) -> PyResult<()> {
        guarded(|| self.send(Cmd::Unlink(link)))
    }

    /// The next event as a dict, waiting up to `timeout` seconds (`None`: as long as it
    /// takes); `None` if none came.
    #[pyo3(signature = (timeout=None))]
    fn next_event<'py>(
        &self,
        py: Python<'py>,
        timeout: Option<f64>,
    ) -> PyResult<Option<Bound<'py, PyDict>>> {
        guarded(|| {
            let timeout = timeout
                .map(|t| {
                    if t.is_finite() && t >= 0.0 {
                        Ok(Duration::from_secs_f64(t))
                    } else {
                        Err(MusterError::new_err("timeout must be seconds ≥ 0"))
                    }
                })
                .transpose()?;
            // Without releasing the GIL first: an event already here is taken at once.
            let now = self
                .events
                .lock()
                .map_err(|_| MusterError::new_err("poisoned"))?
                .try_recv();
            let got = match now {
                Ok(o) => Some(o),
                Err(std::sync::mpsc::TryRecvError::Empty) if timeout == Some(Duration::ZERO) => {
                    None
                }
                Err(std::sync::mpsc::TryRecvError::Empty) => {
                    recv_interruptibly(py, &self.events, timeout)?
                }
                Err(std::sync::mpsc::TryRecvError::Disconnected) => {
                    return Err(Closed::new_err("the user's client stopped"))
                }
            };
            match got {
                None => Ok(None),
                Some(Out::Failed(e)) => Err(Closed::new_err(e)),
                Some(Out::Event(e)) => self.event_dict(py, *e).map(Some),
            }
        })
    }

    /// A descriptor that becomes readable when events wait (for an asyncio loop's
    /// `add_reader`); read it empty with `drain_notify`, then take events with
    /// `next_event(0)`.
    fn fileno(&self) -> i32 {
        self.notify_on.store(true, Ordering::Relaxed);
        self.notify_r.as_raw_fd()
    }

    /// Empties the descriptor of `fileno`.
    fn drain_notify(&self) {
        let mut buf = [0u8; 256];
        while (&self.notify_r).read(&mut buf).is_ok_and(|n| n > 0) {}
    }

    /// Ends every session and link and says goodbye to the broker. Idempotent.
    fn close(&self, py: Python<'_>) -> PyResult<()> {
        guarded(|| {
            if self.closed.swap(true, Ordering::Relaxed) {
                return Ok(());
            }
            let (tx, rx) = channel();
            if self.cmds.send(Cmd::Close(tx)).is_ok() {
                let _ = (&self.bell).write(&[1]);
                // The client waits up to half a second for remote systems' confirmations.
                let _ = recv_interruptibly(py, &Mutex::new(rx), Some(Duration::from_secs(5)));
            }
            Ok(())
        })
    }
}

impl Drop for NativeUser {
    fn drop(&mut self) {
        if !self.closed.swap(true, Ordering::Relaxed) {
            let (tx, _rx) = channel();
            if self.cmds.send(Cmd::Close(tx)).is_ok() {
                let _ = (&self.bell).write(&[1]);
            }
        }
    }
}

impl NativeUser {
    fn event_dict<'py>(&self, py: Python<'py>, e: UserEvent) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        let mut schemas = self
            .schemas
            .lock()
            .map_err(|_| MusterError::new_err("poisoned"))?;
        match e {
            UserEvent::Connected { epoch } => {
                d.set_item("event", "connected")?;
                d.set_item("epoch", epoch)?;
            }
            UserEvent::BrokerLost => d.set_item("event", "broker_lost")?,
            UserEvent::ListChanged => d.set_item("event", "list_changed")?,
            UserEvent::Queued {
                req,
                service,
                position,
            } => {
                d.set_item("event", "queued")?;
                d.set_item("req", req)?;
                d.set_item("service", service.0)?;
                d.set_item("position", position)?;
            }
            UserEvent::Granted {
                req,
                session,
                service,
                kind,
                payload,
                schema,
            } => {
                d.set_item("event", "granted")?;
                d.set_item("req", req)?;
                d.set_item("session", session.0)?;
                d.set_item("service", service.0)?;
                d.set_item("kind", kind.to_string())?;
                d.set_item("payload", &payload)?;
                let payload_name = payload;
                match &schema {
                    Some(s) => {
                        d.set_item("encoding", s.encoding.message_encoding())?;
                        d.set_item("schema", s.text.clone())?;
                    }
                    None => {
                        d.set_item("encoding", py.None())?;
                        d.set_item("schema", py.None())?;
                    }
                }
                schemas.insert(session.0, (payload_name, schema));
            }
            UserEvent::EndConfirmed { session } => {
                d.set_item("event", "end_confirmed")?;
                d.set_item("session", session.0)?;
                schemas.remove(&session.0);
            }
            UserEvent::Refused {
                req,
                service,
                reason,
            } => {
                d.set_item("event", "refused")?;
                d.set_item("req", req)?;
                d.set_item("service", service.0)?;
                d.set_item("code", refusal_code(&reason))?;
                d.set_item("reason", reason.to_string())?;
            }
            UserEvent::Operated { id, result } => {
                d.set_item("event", "operated")?;
                d.set_item("id", id)?;
                d.set_item("error", result.err())?;
            }
            UserEvent::Update {
                session,
                service,
                seq,
                gap,
                sent_ns,
                payload,
            } => {
                d.set_item("event", "update")?;
                d.set_item("session", session.0)?;
                d.set_item("service", service.0)?;
                d.set_item("seq", seq)?;
                d.set_item("gap", gap)?;
                d.set_item("sent_ns", sent_ns)?;
                let schema = schemas.get(&session.0).and_then(|(_, s)| s.as_ref());
                d.set_item("value", payload_to_py(py, &payload, schema)?)?;
            }
            UserEvent::Status {
                session,
                service,
                seq,
                status,
            } => {
                d.set_item("event", "status")?;
                d.set_item("session", session.0)?;
                d.set_item("service", service.0)?;
                d.set_item("seq", seq)?;
                d.set_item("state", status.state())?;
                d.set_item("detail", status.detail())?;
                d.set_item("text", status.to_string())?;
            }
            UserEvent::Ended {
                session,
                service,
                reason,
                lost_at_end,
            } => {
                d.set_item("event", "ended")?;
                d.set_item("session", session.0)?;
                d.set_item("service", service.0)?;
                d.set_item("code", end_code(&reason))?;
                d.set_item("reason", reason.to_string())?;
                d.set_item("lost_at_end", lost_at_end)?;
                schemas.remove(&session.0);
            }
            UserEvent::LinkUp { link } => {
                d.set_item("event", "link_up")?;
                d.set_item("link", link)?;
            }
            UserEvent::LinkForwarded { link, input } => {
                d.set_item("event", "link_forwarded")?;
                d.set_item("link", link)?;
                d.set_item("value", payload_to_py(py, &input, None)?)?;
            }
            UserEvent::Feed(_) => d.set_item("event", "feed")?,
            UserEvent::LinkEnded { link, reason } => {
                d.set_item("event", "link_ended")?;
                d.set_item("link", link)?;
                d.set_item("reason", reason)?;
            }
        }
        Ok(d)
    }
}

/// A refusal's code, stable for programs: `unknown`, `withdrawn`, `quota_full`, ...
fn refusal_code(r: &Refusal) -> &'static str {
    match r {
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

/// An end's code: `by_user`, `by_system`, `withdrawn`, `peer_gone`, `duration_over`.
fn end_code(r: &EndReason) -> &'static str {
    match r {
        EndReason::ByUser => "by_user",
        EndReason::BySystem(_) => "by_system",
        EndReason::Withdrawn => "withdrawn",
        EndReason::PeerGone => "peer_gone",
        EndReason::DurationOver => "duration_over",
    }
}

/// The client's thread: connects, then carries out commands and hands over events
/// until closed (or Python drops the user).
#[allow(clippy::too_many_arguments)]
fn drive(
    target: Target,
    opts: ConnectOptions,
    ready: Sender<PyResult<String>>,
    cmds: Receiver<Cmd>,
    bell: UnixStream,
    events: &Sender<Out>,
    notify: UnixStream,
    notify_on: std::sync::Arc<AtomicBool>,
) {
    let connected = match target {
        Target::Local(inst) => UserClient::connect(&inst, &opts),
        Target::Remote(r) => UserClient::connect_remote(r, &opts),
    };
    let mut client = match connected {
        Ok(c) => c,
        Err(e @ (UserError::NoBroker(_) | UserError::NoRemoteBroker { .. })) => {
            let _ = ready.send(Err(NoBroker::new_err(e.to_string())));
            return;
        }
        Err(e) => {
            let _ = ready.send(Err(MusterError::new_err(e.to_string())));
            return;
        }
    };
    if let Err(e) = client.watch_extra(bell.as_raw_fd()) {
        let _ = ready.send(Err(MusterError::new_err(e.to_string())));
        return;
    }
    if ready.send(Ok(client.id().0.clone())).is_err() {
        return client.close();
    }
    let ring = || {
        if notify_on.load(Ordering::Relaxed) {
            let _ = (&notify).write(&[1]);
        }
    };
    loop {
        match client.wait(Instant::now() + Duration::from_secs(3600)) {
            Ok(Wake::Event(e)) => {
                if events.send(Out::Event(Box::new(e))).is_err() {
                    return client.close();
                }
                ring();
            }
            Ok(Wake::Extra) => {
                let mut buf = [0u8; 256];
                while (&bell).read(&mut buf).is_ok_and(|n| n > 0) {}
                loop {
                    match cmds.try_recv() {
                        Ok(Cmd::Close(done)) => {
                            client.close();
                            let _ = done.send(());
                            return;
                        }
                        Ok(cmd) => apply(&mut client, cmd),
                        Err(std::sync::mpsc::TryRecvError::Empty) => break,
                        Err(std::sync::mpsc::TryRecvError::Disconnected) => {
                            return client.close()
                        }
                    }
                }
            }
            Ok(Wake::Timeout) => {}
            Err(e) => {
                let _ = events.send(Out::Failed(e.to_string()));
                ring();
                return;
            }
        }
    }
}

fn apply(client: &mut UserClient, cmd: Cmd) {
    match cmd {
        Cmd::List(tx) => {
            let _ = tx.send(client.list().map(|l| l.views()).map_err(|e| e.to_string()));
        }
        Cmd::Request(id, tx) => {
            // The client checks the id against the list: an unknown one is refused by
            // the broker as `unknown`, an event like any refusal.
            let req = match client.request(&id) {
                Ok(r) => r,
                Err(e) => {
                    tracing::warn!("request {id}: {e}");
                    0
                }
            };
            let _ = tx.send(req);
        }
        Cmd::Cancel(req) => client.cancel(req),
        Cmd::Input(s, p, tx) => {
            let _ = tx.send(client.input(s, p));
        }
        Cmd::End(s) => client.end(s),
        Cmd::Link(d, c, tx) => {
            let _ = tx.send(client.link(&d, &c).map_err(|e| match e {
                UserError::UnknownService(s) => format!("unknown service {s:?}"),
                UserError::CannotLink(why) => why,
                e => e.to_string(),
            }));
        }
        Cmd::Unlink(l) => client.unlink(l),
        Cmd::Close(_) => {}
    }
}

/// The benchmark's floor: `n` requests of `service` on instance `instance` from the Rust
/// client itself (no Python in the loop), each ended once granted; the request → grant
/// times in microseconds, for comparison with the same loop through this package.
#[pyfunction]
#[pyo3(signature = (instance, service, n))]
pub fn rust_request_latencies(
    py: Python<'_>,
    instance: &str,
    service: &str,
    n: usize,
) -> PyResult<Vec<f64>> {
    guarded(|| {
        let inst = Instance::new(instance).map_err(|e| MusterError::new_err(e.to_string()))?;
        let id = ServiceId(service.to_string());
        py.detach(move || -> Result<Vec<f64>, String> {
            let opts = ConnectOptions {
                handle_signals: false,
                ..ConnectOptions::default()
            };
            let mut c = UserClient::connect(&inst, &opts).map_err(|e| e.to_string())?;
            let mut out = Vec::with_capacity(n);
            for _ in 0..n {
                let t0 = Instant::now();
                let req = c.request(&id).map_err(|e| e.to_string())?;
                let deadline = t0 + Duration::from_secs(10);
                loop {
                    match c.next_event(deadline).map_err(|e| e.to_string())? {
                        Some(UserEvent::Granted { req: r, session, .. }) if r == req => {
                            out.push(t0.elapsed().as_secs_f64() * 1e6);
                            c.end(session);
                            break;
                        }
                        Some(UserEvent::Refused { req: r, reason, .. }) if r == req => {
                            return Err(format!("refused: {reason}"))
                        }
                        Some(_) => {}
                        None => return Err("no grant within 10 s".into()),
                    }
                }
            }
            c.close();
            Ok(out)
        })
        .map_err(MusterError::new_err)
    })
}
