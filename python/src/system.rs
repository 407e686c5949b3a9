//! A system: a [`SystemCore`] under muster's runtime, its callbacks in Python.
//!
//! The runtime runs on the thread that calls `run` with the GIL released; each callback
//! takes the GIL, gets a [`Core`] valid for that call only, and may publish, send
//! status, end sessions, withdraw and restore. Other Python threads hand work to the
//! runtime's thread with `call_soon` (it wakes the runtime through a socket).

use crate::{guarded, panic_text, payload_from_py, payload_to_py};
use crate::{Closed, InternalError, MusterError, PayloadError};
use muster_shared::types::{
    EndReason, Schema, SchemaEncoding, ServiceKind, ServiceSpec, SessionId, TaskStatus,
};
use muster_shared::Instance;
use muster_systems::{SystemApp, SystemCore, SystemEvent};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::cell::Cell;
use std::collections::VecDeque;
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, RawFd};
use std::os::unix::net::UnixStream;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// What other threads leave for the runtime's thread.
struct Inbox {
    calls: Mutex<VecDeque<Py<PyAny>>>,
    stop: AtomicBool,
    running: AtomicBool,
    wake_w: UnixStream,
    wake_r: UnixStream,
}

impl Inbox {
    fn ring(&self) {
        let _ = (&self.wake_w).write(&[1]);
    }
}

/// A robot system written in Python.
#[pyclass(module = "muster._native")]
pub struct NativeSystem {
    name: String,
    instance: String,
    udp: Option<std::net::SocketAddr>,
    specs: Mutex<Vec<ServiceSpec>>,
    /// The data services declared latched, latched when `run` makes the core.
    latched: Mutex<Vec<String>>,
    inbox: Arc<Inbox>,
}

#[pymethods]
impl NativeSystem {
    /// System `name` on instance `instance`; with `udp` ("127.0.0.1:0"), remote users'
    /// sessions are served there too.
    #[new]
    #[pyo3(signature = (name, instance="default", udp=None))]
    fn new(name: &str, instance: &str, udp: Option<&str>) -> PyResult<Self> {
        guarded(|| {
            muster_shared::types::validate_registration(name, &[])
                .map_err(|e| MusterError::new_err(e.to_string()))?;
            Instance::new(instance).map_err(|e| MusterError::new_err(e.to_string()))?;
            let udp = udp
                .map(|a| {
                    a.parse().map_err(|e| {
                        MusterError::new_err(format!("udp {a:?}: not HOST:PORT ({e})"))
                    })
                })
                .transpose()?;
            let (wake_r, wake_w) = UnixStream::pair()?;
            wake_r.set_nonblocking(true)?;
            wake_w.set_nonblocking(true)?;
            Ok(NativeSystem {
                name: name.to_string(),
                instance: instance.to_string(),
                udp,
                specs: Mutex::new(Vec::new()),
                latched: Mutex::new(Vec::new()),
                inbox: Arc::new(Inbox {
                    calls: Mutex::new(VecDeque::new()),
                    stop: AtomicBool::new(false),
                    running: AtomicBool::new(false),
                    wake_w,
                    wake_r,
                }),
            })
        })
    }

    /// The system's name.
    #[getter]
    fn name(&self) -> String {
        self.name.clone()
    }

    /// Declares a service (before `run`). `kind` is `data` or `command`; `payload` a
    /// built-in type (`pose2d`, `goal2d`, `scalar`, `text`, `track2d`, `twist`) or an
    /// open type's name with its `schema` (`encoding` `jsonschema` or `ros2msg`).
    /// A `latched` data service's updates also go to the broker, which hands the newest
    /// to each new session with its grant, as its update 0 (`SystemCore::latch`).
    #[pyo3(signature = (name, kind, payload, quota=1, queue=false, description="", encoding=None, schema=None, latched=false))]
    #[allow(clippy::too_many_arguments)]
    fn add_service(
        &self,
        name: &str,
        kind: &str,
        payload: &str,
        quota: u16,
        queue: bool,
        description: &str,
        encoding: Option<&str>,
        schema: Option<&str>,
        latched: bool,
    ) -> PyResult<()> {
        guarded(|| {
            if self.inbox.running.load(Ordering::Relaxed) {
                return Err(MusterError::new_err(
                    "services are declared before run(): the running system's list is fixed",
                ));
            }
            let kind = match kind {
                "data" => ServiceKind::Data,
                "command" => ServiceKind::Command,
                k => return Err(MusterError::new_err(format!("kind {k:?}: data or command"))),
            };
            if latched && kind != ServiceKind::Data {
                return Err(MusterError::new_err(format!(
                    "service {name:?}: only a data service can be latched"
                )));
            }
            let schema = match (encoding, schema) {
                (None, None) => None,
                (Some(e), Some(text)) => {
                    let encoding = match e {
                        "jsonschema" | "json" => SchemaEncoding::JsonSchema,
                        "ros2msg" | "cdr" => SchemaEncoding::Ros2Msg,
                        e => {
                            return Err(MusterError::new_err(format!(
                                "encoding {e:?}: jsonschema or ros2msg"
                            )))
                        }
                    };
                    Some(Schema {
                        encoding,
                        text: text.to_string(),
                    })
                }
                _ => {
                    return Err(MusterError::new_err(
                        "an open payload type gives both its encoding and its schema",
                    ))
                }
            };
            let spec = ServiceSpec {
                name: name.to_string(),
                description: description.to_string(),
                kind,
                queue,
                quota,
                payload: payload.to_string(),
                schema,
            };
            let mut specs = self
                .specs
                .lock()
                .map_err(|_| MusterError::new_err("poisoned"))?;
            if specs.iter().any(|s| s.name == spec.name) {
                return Err(MusterError::new_err(format!(
                    "service {name:?} is declared twice"
                )));
            }
            let mut all = specs.clone();
            all.push(spec.clone());
            // The broker's own checks, now, with the reason.
            SystemCore::create(&self.name, all).map_err(|e| MusterError::new_err(e.to_string()))?;
            if latched {
                self.latched
                    .lock()
                    .map_err(|_| MusterError::new_err("poisoned"))?
                    .push(spec.name.clone());
            }
            specs.push(spec);
            Ok(())
        })
    }

    /// Runs the system until SIGINT/SIGTERM or `stop()`, calling `handler`'s
    /// `on_event(core, now, event)`, `on_tick(core, now)`, `next_tick()` (seconds on the
    /// clock of `now`, or `None`) and `on_call(core, now, fn)` for `call_soon`'s work.
    /// Returns the services' report (grants, refusals, most sessions at once).
    fn run<'py>(&self, py: Python<'py>, handler: Py<PyAny>) -> PyResult<Bound<'py, PyAny>> {
        guarded(|| {
            if self.inbox.running.swap(true, Ordering::Relaxed) {
                return Err(MusterError::new_err("this system is running already"));
            }
            self.inbox.stop.store(false, Ordering::Relaxed);
            let specs = self
                .specs
                .lock()
                .map_err(|_| MusterError::new_err("poisoned"))?
                .clone();
            let result = (|| {
                if specs.is_empty() {
                    return Err(MusterError::new_err(
                        "no services: declare one (System.data_service, command_service)",
                    ));
                }
                let mut core = SystemCore::create(&self.name, specs)
                    .map_err(|e| MusterError::new_err(e.to_string()))?;
                for name in self
                    .latched
                    .lock()
                    .map_err(|_| MusterError::new_err("poisoned"))?
                    .iter()
                {
                    core.latch(name);
                }
                let inst = Instance::new(&self.instance)
                    .map_err(|e| MusterError::new_err(e.to_string()))?;
                let opts = muster_systems::RunOptions {
                    udp: self.udp,
                    stdin_control: false,
                };
                let mut app = PyApp {
                    handler,
                    inbox: self.inbox.clone(),
                    next: None,
                };
                let ran = py.detach(|| {
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                        muster_systems::run_system_with(&inst, core, &mut app, &opts)
                    }))
                });
                // The Ctrl-C that stopped the runtime also tripped Python's own handler
                // (the runtime's chains to it): it asked for this stop, so it is taken
                // here, not raised as a KeyboardInterrupt after `run` returned.
                let _ = py.check_signals();
                match ran {
                    Ok(Ok(core)) => pythonize::pythonize(py, &core.report())
                        .map_err(|e| InternalError::new_err(e.to_string())),
                    Ok(Err(e)) => Err(MusterError::new_err(e.to_string())),
                    Err(p) => Err(InternalError::new_err(format!(
                        "muster panicked: {}",
                        panic_text(p.as_ref())
                    ))),
                }
            })();
            self.inbox.running.store(false, Ordering::Relaxed);
            result
        })
    }

    /// Runs `fn(core)` on the runtime's thread soon (from any thread): the way another
    /// thread (a sensor's reader) publishes.
    fn call_soon(&self, f: Py<PyAny>) -> PyResult<()> {
        guarded(|| {
            self.inbox
                .calls
                .lock()
                .map_err(|_| MusterError::new_err("poisoned"))?
                .push_back(f);
            self.inbox.ring();
            Ok(())
        })
    }

    /// Asks the running system to stop (from any thread, or a callback): it ends its
    /// sessions, unregisters, and `run` returns.
    fn stop(&self) {
        self.inbox.stop.store(true, Ordering::Relaxed);
        self.inbox.ring();
    }

    /// Whether `run` is running.
    #[getter]
    fn running(&self) -> bool {
        self.inbox.running.load(Ordering::Relaxed)
    }
}

/// The runtime's app: each callback goes to the Python handler.
struct PyApp {
    handler: Py<PyAny>,
    inbox: Arc<Inbox>,
    /// The handler's next tick, asked after every callback (`next_tick` has no GIL).
    next: Option<Duration>,
}

impl PyApp {
    /// Calls `method` of the handler with a core valid for the call; a Python exception
    /// is printed with its traceback and given back.
    fn call(
        &mut self,
        core: &mut SystemCore,
        now: Duration,
        method: &str,
        arg: impl for<'py> FnOnce(Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>>,
    ) -> Option<String> {
        Python::attach(|py| {
            let slot = Rc::new(Cell::new(core as *mut SystemCore));
            let c = match Py::new(
                py,
                Core {
                    slot: slot.clone(),
                    now,
                },
            ) {
                Ok(c) => c,
                Err(e) => return Some(e.to_string()),
            };
            let result = arg(py).and_then(|a| {
                let h = self.handler.bind(py);
                match a {
                    Some(a) => h.call_method1(method, (c.clone_ref(py), now.as_secs_f64(), a)),
                    None => h.call_method1(method, (c.clone_ref(py), now.as_secs_f64())),
                }
            });
            // The core is valid for this call only.
            slot.set(std::ptr::null_mut());
            let err = match result {
                Ok(_) => None,
                Err(e) => {
                    let text = e.to_string();
                    e.display(py);
                    Some(text)
                }
            };
            self.next = match self
                .handler
                .bind(py)
                .call_method0("next_tick")
                .and_then(|t| t.extract::<Option<f64>>())
            {
                Ok(t) => t
                    .filter(|t| t.is_finite())
                    .map(|t| Duration::from_secs_f64(t.max(0.0))),
                Err(e) => {
                    e.display(py);
                    None
                }
            };
            err
        })
    }
}

impl SystemApp for PyApp {
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent) {
        let session = match &event {
            SystemEvent::SessionStarted { session, .. } | SystemEvent::Input { session, .. } => {
                Some(*session)
            }
            _ => None,
        };
        let schema = match &event {
            SystemEvent::Input { service, .. } => schema_of(core, service),
            _ => None,
        };
        let err = self.call(core, now, "on_event", |py| {
            event_dict(py, &event, schema.as_ref()).map(|d| Some(d.into_any()))
        });
        // A callback that raised ends its session only, never the system.
        if let (Some(e), Some(s)) = (err, session) {
            core.end_session(
                s,
                EndReason::BySystem(format!("the system's callback raised: {e}")),
            );
        }
    }

    fn on_tick(&mut self, core: &mut SystemCore, now: Duration) {
        self.call(core, now, "on_tick", |_| Ok(None));
    }

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        self.next
    }

    fn descriptors(&self) -> Vec<RawFd> {
        vec![self.inbox.wake_r.as_raw_fd()]
    }

    fn on_ready(&mut self, core: &mut SystemCore, now: Duration, _index: usize) {
        let mut buf = [0u8; 256];
        while (&self.inbox.wake_r).read(&mut buf).is_ok_and(|n| n > 0) {}
        loop {
            let f = match self.inbox.calls.lock() {
                Ok(mut q) => q.pop_front(),
                Err(_) => None,
            };
            let Some(f) = f else { break };
            self.call(core, now, "on_call", move |py| Ok(Some(f.into_bound(py))));
        }
    }

    fn stop_requested(&self) -> bool {
        self.inbox.stop.load(Ordering::Relaxed)
    }
}

/// A service's schema (its open payload type's), to read input with.
fn schema_of(core: &SystemCore, service: &str) -> Option<Schema> {
    core.specs()
        .iter()
        .find(|s| s.name == service)
        .and_then(|s| s.schema.clone())
}

fn event_dict<'py>(
    py: Python<'py>,
    e: &SystemEvent,
    schema: Option<&Schema>,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    match e {
        SystemEvent::Registered => d.set_item("event", "registered")?,
        SystemEvent::RegistrationRefused(r) => {
            d.set_item("event", "registration_refused")?;
            d.set_item("reason", r)?;
        }
        SystemEvent::Delinquent => d.set_item("event", "delinquent")?,
        SystemEvent::BrokerLost => d.set_item("event", "broker_lost")?,
        SystemEvent::SessionStarted {
            session,
            user,
            service,
        } => {
            d.set_item("event", "session_started")?;
            d.set_item("session", session.0)?;
            d.set_item("user", &user.0)?;
            d.set_item("service", service)?;
        }
        SystemEvent::Input {
            session,
            service,
            payload,
        } => {
            d.set_item("event", "input")?;
            d.set_item("session", session.0)?;
            d.set_item("service", service)?;
            d.set_item("value", payload_to_py(py, payload, schema)?)?;
        }
        SystemEvent::Undelivered {
            session,
            service,
            seq,
            reason,
        } => {
            d.set_item("event", "undelivered")?;
            d.set_item("session", session.0)?;
            d.set_item("service", service)?;
            d.set_item("seq", seq)?;
            d.set_item("reason", reason)?;
        }
        SystemEvent::SessionEnded {
            session,
            service,
            reason,
        } => {
            d.set_item("event", "session_ended")?;
            d.set_item("session", session.0)?;
            d.set_item("service", service)?;
            d.set_item("reason", reason.to_string())?;
        }
    }
    Ok(d)
}

/// The system's protocol state, for the length of one callback.
#[pyclass(module = "muster._native", unsendable)]
pub struct Core {
    slot: Rc<Cell<*mut SystemCore>>,
    now: Duration,
}

impl Core {
    fn with<T>(&self, f: impl FnOnce(&mut SystemCore) -> PyResult<T>) -> PyResult<T> {
        let p = self.slot.get();
        if p.is_null() {
            return Err(Closed::new_err(
                "this core was lent for one callback; from elsewhere use System.call_soon",
            ));
        }
        // SAFETY: the pointer is set only while the runtime's callback that made this
        // `Core` runs on this thread (`Core` is `unsendable`), with the runtime's
        // `&mut SystemCore` unused until the callback returns and clears it.
        f(unsafe { &mut *p })
    }
}

#[pymethods]
impl Core {
    /// The runtime's clock, seconds (the `now` of this callback).
    #[getter]
    fn now(&self) -> f64 {
        self.now.as_secs_f64()
    }

    /// Publishes `value` (a payload's JSON form) to every session of data service
    /// `service`; returns how many users got it. Raises `PayloadError` for a value not
    /// of the service's type or too large for a user's path (nobody past the limit got
    /// it; the users count it as lost).
    fn publish(&self, service: &str, value: &Bound<'_, PyAny>) -> PyResult<usize> {
        guarded(|| {
            self.with(|core| {
                let spec = core
                    .specs()
                    .iter()
                    .find(|s| s.name == service)
                    .cloned()
                    .ok_or_else(|| MusterError::new_err(format!("no service {service:?}")))?;
                let payload = payload_from_py(value, spec.schema.as_ref())?;
                if payload.type_name() != spec.payload {
                    return Err(PayloadError::new_err(format!(
                        "{service} streams {}, not {}",
                        spec.payload,
                        payload.type_name()
                    )));
                }
                core.publish(service, &payload, muster_shared::protocol::monotonic_ns())
                    .map_err(|e| PayloadError::new_err(e.to_string()))
            })
        })
    }

    /// Sends task status on command session `session`: `state` is `idle`, `working`,
    /// `done` or `rejected`, `detail` the note beside it.
    #[pyo3(signature = (session, state, detail=""))]
    fn status(&self, session: u64, state: &str, detail: &str) -> PyResult<()> {
        guarded(|| {
            let status = match state {
                "idle" => TaskStatus::Idle,
                "working" => TaskStatus::Working(detail.to_string()),
                "done" => TaskStatus::Done(detail.to_string()),
                "rejected" => TaskStatus::Rejected(detail.to_string()),
                s => {
                    return Err(MusterError::new_err(format!(
                        "state {s:?}: idle, working, done or rejected"
                    )))
                }
            };
            self.with(|core| {
                core.try_status(SessionId(session), status)
                    .map_err(|e| PayloadError::new_err(e.to_string()))
            })
        })
    }

    /// Ends session `session`, telling its user `reason`.
    fn end(&self, session: u64, reason: &str) -> PyResult<()> {
        guarded(|| {
            self.with(|core| {
                core.end_session(SessionId(session), EndReason::BySystem(reason.to_string()));
                Ok(())
            })
        })
    }

    /// Withdraws service `service` for now: its sessions end, requests are refused.
    fn withdraw(&self, service: &str) -> PyResult<()> {
        guarded(|| {
            self.with(|core| {
                core.withdraw(service);
                Ok(())
            })
        })
    }

    /// Offers a withdrawn service again.
    fn restore(&self, service: &str) -> PyResult<()> {
        guarded(|| {
            self.with(|core| {
                core.restore(service);
                Ok(())
            })
        })
    }

    /// The open sessions: `(session, user, service)` tuples.
    fn sessions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        guarded(|| {
            self.with(|core| {
                let out = PyList::empty(py);
                for (s, u, svc) in core.sessions() {
                    out.append((s.0, u.0.clone(), svc.to_string()))?;
                }
                Ok(out)
            })
        })
    }
}
