//! Robot systems and the SDK a new system uses to join muster: [`core::SystemCore`] is
//! the protocol state machine, [`runtime::run_system`] drives it over shared memory and
//! calls the system's own [`runtime::SystemApp`], and [`synthetic`] is a generic system
//! for tests, demos and load.
//!
//! # A system in four steps
//!
//! 1. Say what it offers: [`muster_shared::types::ServiceSpec`]s (a name, data or
//!    command, a quota, a payload type: `pose2d`, `goal2d`, `twist`, `scalar`, `text`,
//!    `track2d`, or an open type with its schema).
//! 2. Make its core with [`SystemCore::create`], which checks the specs as the broker
//!    will.
//! 3. Write its logic as a [`SystemApp`]: [`SystemApp::on_event`] hears of sessions
//!    (`SessionStarted` always first), task input and ends; [`SystemApp::on_tick`] runs
//!    at the absolute times [`SystemApp::next_tick`] asks for; a system that waits on a
//!    device of its own lends its descriptors ([`SystemApp::descriptors`]) and is
//!    called in [`SystemApp::on_ready`]. It streams with [`SystemCore::publish`] (an
//!    update too large for a user's path is an error, never a silent drop; one that a
//!    user's full inbox cannot take comes back as `SystemEvent::Undelivered`) and
//!    reports with [`SystemCore::status`].
//! 4. Run it: [`run_system`] registers, answers the broker, re-registers after a broker
//!    restart, and returns on SIGINT or SIGTERM, or when [`SystemApp::stop_requested`]
//!    says so. It logs to standard error (`RUST_LOG`,
//!    default `info`) unless the program set up `tracing` itself.
//!
//! The repository's `examples/` hold a complete door (`door_system.rs`, with a user
//! program `door_user.rs` on `muster_users::UserClient`) and a thermometer that
//! sleeps on its own socket (`thermometer.rs`); `tests/examples.rs` runs them.

pub mod core;
pub mod remote;
pub mod runtime;
pub mod synthetic;

pub use crate::core::{BrokerState, SendError, SystemCore, SystemEvent, SystemOutput};
pub use crate::runtime::{run_system, run_system_with, RunOptions, SystemApp, SystemError};
