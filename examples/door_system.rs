//! A door as a muster robot system: a command service `open` (send it any input; it
//! reports "opening", then "open" two seconds later) and a data service `state`
//! streaming the door's state five times a second.
//!
//! ```sh
//! cargo run --release -- broker &                       # the broker
//! cargo run --example door_system                       # this system
//! cargo run --release -- user request door/open --input '"open"' --duration 3s
//! cargo run --release -- user request door/state --duration 2s
//! ```
//!
//! `--instance NAME` as the first argument runs it on another instance.

use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{Payload, ServiceKind, ServiceSpec, SessionId, TaskStatus};
use muster_shared::Instance;
use muster_systems::{run_system, SystemApp, SystemCore, SystemEvent};
use std::time::Duration;

/// How long the door takes to open.
const OPENING: Duration = Duration::from_secs(2);
/// How often `state` streams.
const STATE_PERIOD: Duration = Duration::from_millis(200);

#[derive(Default)]
struct Door {
    /// Open for good.
    open: bool,
    /// Opening for a session, done at that time.
    opening: Option<(SessionId, Duration)>,
    /// The next `state` update.
    next_state: Duration,
}

impl Door {
    fn state(&self) -> &'static str {
        match (self.open, self.opening) {
            (true, _) => "open",
            (false, Some(_)) => "opening",
            (false, None) => "closed",
        }
    }
}

impl SystemApp for Door {
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent) {
        match event {
            SystemEvent::SessionStarted {
                session, service, ..
            } if service == "open" => {
                core.status(session, TaskStatus::Idle);
            }
            SystemEvent::Input { session, .. } if self.open => {
                core.status(session, TaskStatus::Done("open".into()));
            }
            SystemEvent::Input { session, .. } => {
                self.opening = Some((session, now + OPENING));
                core.status(session, TaskStatus::Working("opening".into()));
            }
            _ => {}
        }
    }

    fn on_tick(&mut self, core: &mut SystemCore, now: Duration) {
        if let Some((session, done)) = self.opening {
            if now >= done {
                self.opening = None;
                self.open = true;
                core.status(session, TaskStatus::Done("open".into()));
            }
        }
        if now >= self.next_state {
            self.next_state = now + STATE_PERIOD;
            // A short text always fits: the error (too large for a user's path) cannot come.
            if let Err(e) =
                core.publish("state", &Payload::Text(self.state().into()), monotonic_ns())
            {
                eprintln!("door: {e}");
            }
        }
    }

    fn next_tick(&self, _core: &SystemCore) -> Option<Duration> {
        // An absolute time on the runtime's clock: the sooner of the next state update
        // and the moment the door is open.
        let open_at = self.opening.map(|(_, t)| t);
        Some(open_at.map_or(self.next_state, |t| t.min(self.next_state)))
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let instance = match args.get(1).map(String::as_str) {
        Some("--instance") => args.get(2).cloned().unwrap_or_default(),
        _ => "default".into(),
    };
    let specs = vec![
        ServiceSpec {
            name: "open".into(),
            description: "open the door: reports opening, then open".into(),
            kind: ServiceKind::Command,
            queue: true,
            quota: 1,
            payload: "text".into(),
            schema: None,
        },
        ServiceSpec {
            name: "state".into(),
            description: "the door's state, 5 times a second".into(),
            kind: ServiceKind::Data,
            queue: false,
            quota: 10,
            payload: "text".into(),
            schema: None,
        },
    ];
    let core = SystemCore::create("door", specs)?;
    // Runs until SIGINT or SIGTERM; logs to stderr (RUST_LOG, default info).
    run_system(&Instance::new(&instance)?, core, Door::default())?;
    Ok(())
}
