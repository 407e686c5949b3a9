//! A user of the door (examples/door_system.rs): lists the services, asks for
//! `door/open`, sends it input and prints each status until the door is open; then
//! watches `door/state` for a second.
//!
//! ```sh
//! cargo run --example door_user            # with the broker and the door running
//! ```

use muster_shared::types::{Payload, ServiceId, TaskStatus};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient, UserEvent};
use std::time::{Duration, Instant};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let instance = match args.get(1).map(String::as_str) {
        Some("--instance") => args.get(2).cloned().unwrap_or_default(),
        _ => "default".into(),
    };
    let mut client = UserClient::connect(&Instance::new(&instance)?, &ConnectOptions::default())?;
    for v in client.list()?.views() {
        println!("listed: {} ({}, {})", v.id, v.kind, v.payload);
    }
    // Ask for the command service; input once granted; statuses until done.
    let open = ServiceId::new("door", "open");
    let req = client.request(&open)?;
    let deadline = Instant::now() + Duration::from_secs(10);
    while let Some(event) = client.next_event(deadline)? {
        match event {
            UserEvent::Granted {
                req: r, session, ..
            } if r == req => {
                println!("granted {open}");
                client.input(session, Payload::Text("open".into()))?;
            }
            UserEvent::Refused { reason, .. } => return Err(format!("refused: {reason}").into()),
            UserEvent::Status {
                status, session, ..
            } => {
                println!("status: {status}");
                if let TaskStatus::Done(_) = status {
                    client.end(session);
                    break;
                }
            }
            _ => {}
        }
    }
    // Watch the data service for a second.
    let state = ServiceId::new("door", "state");
    client.request(&state)?;
    let until = Instant::now() + Duration::from_secs(1);
    while let Some(event) = client.next_event(until)? {
        if let UserEvent::Update { seq, payload, .. } = event {
            println!("state #{seq}: {payload}");
        }
    }
    client.close();
    Ok(())
}
