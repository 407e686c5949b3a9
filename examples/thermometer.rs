//! A system that sleeps on a device of its own: a thermometer that sends its readings
//! as UDP datagrams (`21.5`, one a datagram) to `127.0.0.1:PORT`. The system lends the
//! socket to the runtime ([`SystemApp::descriptors`]), which wakes it when readings
//! wait ([`SystemApp::on_ready`]); each becomes an update of the data service
//! `celsius`. No tick, no polling.
//!
//! ```sh
//! cargo run --example thermometer -- 127.0.0.1:9750 &
//! echo -n 21.5 > /dev/udp/127.0.0.1/9750               # bash: a reading
//! cargo run --release -- user request thermometer/celsius --duration 5s
//! ```

use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{Payload, ServiceKind, ServiceSpec};
use muster_shared::Instance;
use muster_systems::{run_system, SystemApp, SystemCore, SystemEvent};
use std::net::UdpSocket;
use std::os::fd::{AsRawFd, RawFd};
use std::time::Duration;

struct Thermometer {
    socket: UdpSocket,
}

impl SystemApp for Thermometer {
    fn on_event(&mut self, _core: &mut SystemCore, _now: Duration, _event: SystemEvent) {}

    fn on_tick(&mut self, _core: &mut SystemCore, _now: Duration) {}

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        None // Nothing to do on time: readings wake us.
    }

    fn descriptors(&self) -> Vec<RawFd> {
        vec![self.socket.as_raw_fd()]
    }

    fn on_ready(&mut self, core: &mut SystemCore, _now: Duration, _index: usize) {
        // Edge-triggered: read until nothing waits.
        let mut buf = [0u8; 64];
        while let Ok(n) = self.socket.recv(&mut buf) {
            let text = String::from_utf8_lossy(&buf[..n]);
            match text.trim().parse::<f64>() {
                Ok(c) if c.is_finite() => {
                    if let Err(e) = core.publish("celsius", &Payload::Scalar(c), monotonic_ns()) {
                        eprintln!("thermometer: {e}");
                    }
                }
                _ => eprintln!("thermometer: not a reading: {text:?}"),
            }
        }
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let listen = args.get(1).map_or("127.0.0.1:9750", String::as_str);
    let instance = match args.get(2).map(String::as_str) {
        Some("--instance") => args.get(3).cloned().unwrap_or_default(),
        _ => "default".into(),
    };
    let socket = UdpSocket::bind(listen)?;
    socket.set_nonblocking(true)?;
    println!("{{\"listen\": \"{}\"}}", socket.local_addr()?);
    let specs = vec![ServiceSpec {
        name: "celsius".into(),
        description: "the temperature, as the thermometer reads it".into(),
        kind: ServiceKind::Data,
        queue: false,
        quota: 10,
        payload: "scalar".into(),
        schema: None,
    }];
    let core = SystemCore::create("thermometer", specs)?;
    run_system(&Instance::new(&instance)?, core, Thermometer { socket })?;
    Ok(())
}
