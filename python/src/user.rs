//! A user: a [`UserClient`] driven on the thread that made it (the pyclass is
//! `unsendable`), its waits in the kernel with the GIL released. No thread of its own,
//! no handoff: a request costs what the Rust client's costs, plus the call.

use crate::{guarded, payload_from_py, payload_to_py};
use crate::{Closed, MusterError, NoBroker, PayloadError, UnknownService};
use muster_shared::types::{Schema, ServiceId, SessionId};
use muster_shared::Instance;
use muster_users::{ConnectOptions, RemoteOptions, UserClient, UserError, UserEvent, Wake};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::collections::HashMap;
use std::time::{Duration, Instant};

/// The client (lent, made or closed) crossing a wait with the GIL released. The wait
/// runs on this same thread (`Python::detach` runs its closure in place), so the client
/// never changes threads.
struct InPlace<T>(T);
// SAFETY: see above: `detach` calls the closure on the current thread and returns; the
// client is only ever touched from the thread that made it (the pyclass is unsendable).
unsafe impl<T> Send for InPlace<T> {}

/// How long one wait lasts at most before Python's signals are checked (Ctrl-C).
const SIGNAL_SLICE: Duration = Duration::from_millis(100);

/// A user of the federation: local (shared memory) or remote (UDP with a key).
#[pyclass(module = "muster._native", unsendable)]
pub struct NativeUser {
    client: Option<UserClient>,
    remote: bool,
    /// Each held session's payload type and schema, from its grant: input is checked
    /// against the type, and an open type's samples decode by the schema.
    schemas: HashMap<u64, (String, Option<Schema>)>,
}

impl NativeUser {
    fn client(&mut self) -> PyResult<&mut UserClient> {
        self.client
            .as_mut()
            .ok_or_else(|| Closed::new_err("this user is closed"))
    }
}

fn connect_error(e: UserError) -> PyErr {
    match e {
        e @ (UserError::NoBroker(_) | UserError::NoRemoteBroker { .. }) => {
            NoBroker::new_err(e.to_string())
        }
        e => MusterError::new_err(e.to_string()),
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
            if !(wait.is_finite() && wait >= 0.0) {
                return Err(MusterError::new_err("wait must be a number of seconds ≥ 0"));
            }
            let opts = ConnectOptions {
                wait_for_broker: Duration::from_secs_f64(wait),
                handle_signals: false,
                watch_list: true,
            };
            let client = match (remote, key) {
                (None, None) => {
                    let inst =
                        Instance::new(instance).map_err(|e| MusterError::new_err(e.to_string()))?;
                    py.detach(|| InPlace(UserClient::connect(&inst, &opts))).0
                }
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
                    let r = RemoteOptions {
                        broker,
                        name,
                        key,
                        broker_key,
                        faults: None,
                    };
                    py.detach(|| InPlace(UserClient::connect_remote(r, &opts)))
                        .0
                }
            }
            .map_err(connect_error)?;
            Ok(NativeUser {
                remote: client.is_remote(),
                client: Some(client),
                schemas: HashMap::new(),
            })
        })
    }

    /// This user's id, as the broker knows it.
    #[getter]
    fn id(&mut self) -> PyResult<String> {
        Ok(self.client()?.id().0.clone())
    }

    /// Whether this user is remote (UDP).
    #[getter]
    fn remote(&self) -> bool {
        self.remote
    }

    /// The service list, as dicts.
    fn list<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guarded(|| {
            let c = InPlace(self.client()?);
            let views = py
                .detach(move || {
                    let c = c;
                    c.0.list().map(|l| l.views())
                })
                .map_err(|e| MusterError::new_err(e.to_string()))?;
            let out = PyList::empty(py);
            for v in &views {
                out.append(
                    pythonize::pythonize(py, v).map_err(|e| MusterError::new_err(e.to_string()))?,
                )?;
            }
            Ok(out)
        })
    }

    /// One page of the list: the services the filters let through (every one given
    /// must hold; `name` is a glob), from the `offset`th, at most `limit`; returns how
    /// many the filters let through in all, and the page as dicts.
    #[pyo3(signature = (host=None, system=None, kind=None, payload=None, name=None, offset=0, limit=None))]
    #[allow(clippy::too_many_arguments)]
    fn list_page<'py>(
        &mut self,
        py: Python<'py>,
        host: Option<String>,
        system: Option<String>,
        kind: Option<&str>,
        payload: Option<String>,
        name: Option<String>,
        offset: usize,
        limit: Option<usize>,
    ) -> PyResult<(usize, Bound<'py, PyList>)> {
        guarded(|| {
            let filter = list_filter(host, system, kind, payload, name)?;
            let c = InPlace(self.client()?);
            let limit = limit.unwrap_or(usize::MAX);
            let page = py
                .detach(move || {
                    let c = c;
                    c.0.list_page(&filter, offset, limit)
                })
                .map_err(|e| MusterError::new_err(e.to_string()))?;
            let out = PyList::empty(py);
            for v in &page.views() {
                out.append(
                    pythonize::pythonize(py, v).map_err(|e| MusterError::new_err(e.to_string()))?,
                )?;
            }
            Ok((page.matching, out))
        })
    }

    /// Watches only the part of the list the filters let through (none: all of it):
    /// list changes are then told only when that part changes.
    #[pyo3(signature = (host=None, system=None, kind=None, payload=None, name=None))]
    fn watch_part(
        &mut self,
        host: Option<String>,
        system: Option<String>,
        kind: Option<&str>,
        payload: Option<String>,
        name: Option<String>,
    ) -> PyResult<()> {
        guarded(|| {
            let filter = list_filter(host, system, kind, payload, name)?;
            self.client()?
                .watch_part(Some(filter))
                .map_err(|e| MusterError::new_err(e.to_string()))
        })
    }

    /// Asks for service `id`; returns the request's number (its answer comes as an
    /// event: `queued`, `granted` or `refused`).
    fn request(&mut self, id: &str) -> PyResult<u64> {
        guarded(|| {
            self.client()?
                .request(&ServiceId(id.to_string()))
                .map_err(|e| MusterError::new_err(e.to_string()))
        })
    }

    /// Gives up request `req` (waiting in a queue, or not answered yet).
    fn cancel(&mut self, req: u64) -> PyResult<()> {
        guarded(|| {
            self.client()?.cancel(req);
            Ok(())
        })
    }

    /// Sends task input `value` (a payload's JSON form) on command session `session`.
    fn input(&mut self, session: u64, value: &Bound<'_, PyAny>) -> PyResult<()> {
        guarded(|| {
            let (declared, schema) = self
                .schemas
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
            self.client()?
                .input(SessionId(session), payload)
                .map_err(PayloadError::new_err)
        })
    }

    /// Ends session `session`.
    fn end(&mut self, session: u64) -> PyResult<()> {
        guarded(|| {
            self.client()?.end(SessionId(session));
            Ok(())
        })
    }

    /// Links data service `data` into command service `command`; returns the link's
    /// number. Refused at once (with the reason) if they cannot be linked.
    fn link(&mut self, py: Python<'_>, data: &str, command: &str) -> PyResult<u64> {
        guarded(|| {
            let (d, c) = (ServiceId(data.to_string()), ServiceId(command.to_string()));
            let client = InPlace(self.client()?);
            py.detach(move || {
                let client = client;
                client.0.link(&d, &c)
            })
            .map_err(|e| match e {
                UserError::UnknownService(s) => {
                    UnknownService::new_err(format!("unknown service {s:?}"))
                }
                UserError::CannotLink(why) => MusterError::new_err(why),
                e => MusterError::new_err(e.to_string()),
            })
        })
    }

    /// Ends link `link` and its sessions.
    fn unlink(&mut self, link: u64) -> PyResult<()> {
        guarded(|| {
            self.client()?.unlink(link);
            Ok(())
        })
    }

    /// The next event as a dict, waiting up to `timeout` seconds (`None`: as long as it
    /// takes); `None` if none came.
    #[pyo3(signature = (timeout=None))]
    fn next_event<'py>(
        &mut self,
        py: Python<'py>,
        timeout: Option<f64>,
    ) -> PyResult<Option<Bound<'py, PyDict>>> {
        guarded(|| {
            let deadline = match timeout {
                None => None,
                Some(t) if t.is_finite() && t >= 0.0 => {
                    Some(Instant::now() + Duration::from_secs_f64(t))
                }
                Some(_) => return Err(MusterError::new_err("timeout must be seconds ≥ 0")),
            };
            loop {
                let slice = Instant::now() + SIGNAL_SLICE;
                let until = deadline.map_or(slice, |d| d.min(slice));
                let client = self.client()?;
                // An event already here is taken without releasing the GIL.
                let woke = if let Some(e) = client.try_event().map_err(closed)? {
                    Wake::Event(e)
                } else if until <= Instant::now() {
                    Wake::Timeout
                } else {
                    let c = InPlace(client);
                    py.detach(move || {
                        let c = c;
                        c.0.wait(until)
                    })
                    .map_err(closed)?
                };
                match woke {
                    Wake::Event(e) => return self.event_dict(py, e).map(Some),
                    Wake::Extra | Wake::Timeout => {}
                }
                py.check_signals()?;
                if deadline.is_some_and(|d| Instant::now() >= d) {
                    return Ok(None);
                }
            }
        })
    }

    /// A descriptor that becomes readable when events may wait (for an asyncio loop's
    /// `add_reader`); then take them with `next_event(0)`. A remote user's timers also
    /// want a `next_event(0)` by `next_deadline()`.
    fn fileno(&mut self) -> PyResult<i32> {
        Ok(self.client()?.fd())
    }

    /// Seconds until a remote user's timers want a turn (`None`: a local user has none).
    fn next_deadline(&mut self) -> PyResult<Option<f64>> {
        Ok(self
            .client()?
            .next_deadline()
            .map(|d| d.saturating_duration_since(Instant::now()).as_secs_f64()))
    }

    /// Ends every session and link and says goodbye to the broker. Idempotent.
    fn close(&mut self, py: Python<'_>) -> PyResult<()> {
        guarded(|| {
            if let Some(c) = self.client.take() {
                // A remote client waits up to half a second for systems' confirmations.
                let c = InPlace(c);
                py.detach(move || {
                    let c = c;
                    c.0.close()
                });
            }
            Ok(())
        })
    }
}

fn closed(e: UserError) -> PyErr {
    Closed::new_err(e.to_string())
}

impl NativeUser {
    fn event_dict<'py>(&mut self, py: Python<'py>, e: UserEvent) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        let schemas = &mut self.schemas;
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
                d.set_item("code", reason.code())?;
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
                d.set_item("code", reason.code())?;
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
                        Some(UserEvent::Granted {
                            req: r, session, ..
                        }) if r == req => {
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

/// A list filter from Python's keyword arguments.
fn list_filter(
    host: Option<String>,
    system: Option<String>,
    kind: Option<&str>,
    payload: Option<String>,
    name: Option<String>,
) -> PyResult<muster_shared::snapshot::ListFilter> {
    let kind = match kind {
        None => None,
        Some("data") => Some(muster_shared::types::ServiceKind::Data),
        Some("command") => Some(muster_shared::types::ServiceKind::Command),
        Some(other) => {
            return Err(pyo3::exceptions::PyValueError::new_err(format!(
                "kind must be \"data\" or \"command\", not {other:?}"
            )))
        }
    };
    let f = muster_shared::snapshot::ListFilter {
        host,
        system,
        kind,
        payload,
        name,
    };
    f.check().map_err(pyo3::exceptions::PyValueError::new_err)?;
    Ok(f)
}
