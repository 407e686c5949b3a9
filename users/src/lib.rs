//! The user side of muster: [`core::UserCore`] is the protocol state machine (requests,
//! sessions, links), [`client::UserClient`] drives it over shared memory with a blocking
//! API, and [`menu`] is the paper's interactive terminal menu.

pub mod client;
pub mod conn;
pub mod core;
pub mod menu;
pub mod remote;

pub use crate::client::{ConnectOptions, UserClient, UserError, Wake};
pub use crate::conn::RemoteConn;
pub use crate::core::{UserCore, UserEvent, UserOutput};
pub use crate::remote::{Faults, RemoteOptions};
pub use muster_shared::ipc::{ProcessInbox, ProcessInboxSize};
