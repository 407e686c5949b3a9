//! The muster broker: the registry of systems and their services, request arbitration
//! (quotas, task queues), liveness (pings, process death), and the shared-memory
//! service list. [`core`] is the pure logic; [`run`] drives it over iceoryx2.

pub mod core;
pub mod federation;
pub mod replica;
pub mod rings;
pub mod run;
pub mod takeover;
pub mod udp;
pub mod watchdog;

pub use crate::core::{Broker, BrokerConfig, BrokerStats, Output};
