//! `muster._native`: the Rust client and SDK under the `muster` Python package.
//!
//! Nothing of the protocol is written twice: a user is a [`muster_users::UserClient`]
//! and a system a [`muster_systems::SystemCore`] under [`muster_systems::run_system_with`],
//! each on a thread of its own (iceoryx2's ports stay on the thread that opened them).
//! Python talks to them through channels; it waits with the GIL released, and every
//! call checks for Ctrl-C while it waits. The pure-Python layer (`muster/__init__.py`)
//! gives the objects people use: `User`, `Session`, `System`, the payload classes.
//!
//! Payloads cross as their JSON form ([`Payload::to_json_with`],
//! [`Payload::from_json`]): the one `muster user --json` prints and `--input` reads.

use muster_shared::types::{Payload, Schema};
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;

mod system;
mod user;

create_exception!(muster, MusterError, PyException, "Base of muster's errors.");
create_exception!(
    muster,
    NoBroker,
    MusterError,
    "No broker answered (start one with `muster broker` or `muster up`)."
);
create_exception!(
    muster,
    UnknownService,
    MusterError,
    "The service id is not in the list."
);
create_exception!(
    muster,
    PayloadError,
    MusterError,
    "A value that is not of the payload type the service declares, or does not fit its path."
);
create_exception!(
    muster,
    InternalError,
    MusterError,
    "A fault inside muster's Rust code (a panic): the call failed, the process lives."
);
create_exception!(
    muster,
    Closed,
    MusterError,
    "The user or system was closed, or its thread stopped."
);

/// Runs `f`, turning a Rust panic into `muster.InternalError`: a fault in muster's own
/// code fails the call, never the Python process.
pub(crate) fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => Err(InternalError::new_err(format!(
            "muster panicked: {}",
            panic_text(p.as_ref())
        ))),
    }
}

/// A panic's message.
pub(crate) fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into())
}

/// A payload as the Python layer sees it: its JSON form as dicts, lists and numbers.
pub(crate) fn payload_to_py<'py>(
    py: Python<'py>,
    p: &Payload,
    schema: Option<&Schema>,
) -> PyResult<Bound<'py, PyAny>> {
    pythonize::pythonize(py, &p.to_json_with(schema))
        .map_err(|e| InternalError::new_err(e.to_string()))
}

/// A payload from its JSON form (a dict, a string for text, a number for a scalar),
/// written with `schema` if it is an open type's.
pub(crate) fn payload_from_py(v: &Bound<'_, PyAny>, schema: Option<&Schema>) -> PyResult<Payload> {
    let json: serde_json::Value =
        pythonize::depythonize(v).map_err(|e| PayloadError::new_err(e.to_string()))?;
    Payload::from_json(&json, schema).map_err(PayloadError::new_err)
}

/// Panics inside the guard every call into muster goes through: the self-check that a
/// fault in muster's Rust code reaches Python as `muster.InternalError`, not as a
/// `PanicException` or a dead process (the tests call it).
#[pyfunction]
fn _check_panic_guard() -> PyResult<()> {
    guarded(|| -> PyResult<()> { panic!("the panic guard's self-check") })
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("MusterError", py.get_type::<MusterError>())?;
    m.add("NoBroker", py.get_type::<NoBroker>())?;
    m.add("UnknownService", py.get_type::<UnknownService>())?;
    m.add("PayloadError", py.get_type::<PayloadError>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    m.add("Closed", py.get_type::<Closed>())?;
    m.add_class::<user::NativeUser>()?;
    m.add_class::<system::NativeSystem>()?;
    m.add_class::<system::Core>()?;
    m.add_function(wrap_pyfunction!(user::rust_request_latencies, m)?)?;
    m.add_function(wrap_pyfunction!(_check_panic_guard, m)?)?;
    Ok(())
}
