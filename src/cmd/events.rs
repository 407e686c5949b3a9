//! `muster events`: the broker's event feed, one JSON object a line.

use crate::cli::EventsArgs;
use anyhow::Context;
use muster_shared::ipc::{create_node, EventReader};
use muster_shared::reactor::SignalPipe;
use muster_shared::Instance;
use std::io::Write;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// Prints the feed's recent history, then each event as it comes, until stopped.
pub fn run(inst: &Instance, a: EventsArgs) -> anyhow::Result<ExitCode> {
    let mut signals = SignalPipe::install().context("signal handlers")?;
    let node = create_node("muster-events", false).context("iceoryx2 node")?;
    let mut feed = EventReader::open(&node, inst).context("opening the event feed")?;
    let end = a.duration.map(|d| Instant::now() + d);
    let mut out = std::io::stdout().lock();
    loop {
        while let Some(rec) = feed.next_event() {
            let line = serde_json::to_string(&rec)?;
            if writeln!(out, "{line}").and_then(|()| out.flush()).is_err() {
                // The reader went away (a closed pipe): done.
                return Ok(ExitCode::SUCCESS);
            }
        }
        if signals.drain() || end.is_some_and(|e| Instant::now() >= e) {
            return Ok(ExitCode::SUCCESS);
        }
        feed.wait(Duration::from_millis(100));
    }
}
