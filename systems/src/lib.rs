//! Robot systems and the SDK a new system uses to join muster: [`core::SystemCore`] is
//! the protocol state machine, [`runtime::run_system`] drives it over shared memory and
//! calls the system's own [`runtime::SystemApp`], and [`synthetic`] is a generic system
//! for tests, demos and load.

pub mod core;
pub mod remote;
pub mod runtime;
pub mod synthetic;

pub use crate::core::{BrokerState, SendError, SystemCore, SystemEvent, SystemOutput};
pub use crate::runtime::{run_system, run_system_with, RunOptions, SystemApp, SystemError};
