//! What every muster process shares: the protocol's types and messages, the wire codec,
//! the service list snapshot layout, instance naming, and the iceoryx2 transport.

pub mod clock;
pub mod fence;
pub mod fits;
pub mod ipc;
pub mod names;
pub mod protocol;
pub mod reactor;
pub mod ros2msg;
pub mod snapshot;
pub mod trace;
pub mod types;
pub mod udp;
pub mod viz;

pub use names::{Address, Instance};
pub use types::*;
