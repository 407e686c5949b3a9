//! `muster bench ...`: benchmarks that print figures (never assertions).

mod failover;
mod federation;
pub mod floor;
mod hosts;
mod leftovers;
mod list;
mod liveness;
pub mod procfs;
pub mod remote;
mod ros2;
mod vda5050;
mod web;
use super::children;
mod scale;

use crate::cli::BenchCommand;
use muster_shared::Instance;
use std::process::ExitCode;

pub fn run(inst: &Instance, cmd: BenchCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        BenchCommand::Scale(a) => scale::run(inst, a),
        BenchCommand::Liveness(a) => liveness::run(inst, a),
        BenchCommand::Floor(a) => floor::run(inst, a),
        BenchCommand::Remote(a) => remote::run(inst, a),
        BenchCommand::UdpEcho => remote::echo(),
        BenchCommand::ZenohEcho { port } => federation::echo(port),
        BenchCommand::Echo => floor::echo(inst),
        BenchCommand::Failover(a) => failover::run(inst, a),
        BenchCommand::Federation(a) => federation::run(inst, a),
        BenchCommand::Ros2(a) => ros2::run(inst, a),
        BenchCommand::Web(a) => web::run(inst, a),
        BenchCommand::Vda5050(a) => vda5050::run(inst, a),
        BenchCommand::FailoverUser(a) => failover::user(inst, a),
        BenchCommand::Leftovers(a) => leftovers::run(inst, a),
        BenchCommand::List(a) => list::run(inst, a),
    }
}

/// Runs a bench with a fresh temporary folder `muster-bench-NAME-PID` (removed after,
/// whatever happened) and prints its report as one JSON line when `json` (the bench
/// printed its tables otherwise).
pub fn in_temp_dir(
    name: &str,
    json: bool,
    bench: impl FnOnce(&std::path::Path) -> anyhow::Result<serde_json::Value>,
) -> anyhow::Result<ExitCode> {
    let dir = std::env::temp_dir().join(format!("muster-bench-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let result = bench(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let report = result?;
    if json {
        println!("{report}");
    }
    Ok(ExitCode::SUCCESS)
}

/// p50/p99/max of a histogram of microseconds, as a JSON object.
pub fn summary(h: &hdrhistogram::Histogram<u64>) -> serde_json::Value {
    serde_json::json!({
        "count": h.len(),
        "min_us": h.min(),
        "p50_us": h.value_at_quantile(0.5),
        "p90_us": h.value_at_quantile(0.9),
        "p99_us": h.value_at_quantile(0.99),
        "max_us": h.max(),
    })
}

/// The header of a table of [`row`]s, `first` naming its first column.
pub fn header(first: &str) -> String {
    format!(
        "{first:<28} {:>7} {:>10} {:>10} {:>10} {:>10}",
        "count", "p50", "p90", "p99", "max"
    )
}

/// One table row for a histogram of microseconds.
pub fn row(name: &str, h: &hdrhistogram::Histogram<u64>) -> String {
    format!(
        "{name:<28} {:>7} {:>10} {:>10} {:>10} {:>10}",
        h.len(),
        h.value_at_quantile(0.5),
        h.value_at_quantile(0.9),
        h.value_at_quantile(0.99),
        h.max()
    )
}

/// Latencies in µs, 1 µs to 60 s, three significant digits (the benches that time
/// against outside clients).
pub fn histogram() -> hdrhistogram::Histogram<u64> {
    hdrhistogram::Histogram::new_with_bounds(1, 60_000_000, 3).expect("histogram bounds")
}

/// A client process nobody here wrote (rclpy, Python `websockets`) driven by a bench:
/// its stdout's lines read on a thread of their own; SIGKILLed and reaped when dropped.
pub struct LineChild {
    name: &'static str,
    child: std::process::Child,
    lines: std::sync::mpsc::Receiver<String>,
}

impl LineChild {
    /// Starts `cmd` (stdin closed, stdout read here, stderr shared); `name` says what it
    /// is in errors, `hint` how to get it when it will not start.
    pub fn spawn(
        mut cmd: std::process::Command,
        name: &'static str,
        hint: &str,
    ) -> anyhow::Result<LineChild> {
        use anyhow::Context as _;
        use std::io::{BufRead, BufReader};
        use std::process::Stdio;
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("starting {:?} ({hint})", cmd.get_program()))?;
        let out = child.stdout.take().context("stdout")?;
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        Ok(LineChild { name, child, lines })
    }

    /// Its process id.
    pub fn id(&self) -> u32 {
        self.child.id()
    }

    /// The next JSON line within `timeout` (other lines are skipped).
    pub fn json(&self, timeout: std::time::Duration) -> Option<serde_json::Value> {
        let end = std::time::Instant::now() + timeout;
        loop {
            let l = self
                .lines
                .recv_timeout(end.saturating_duration_since(std::time::Instant::now()))
                .ok()?;
            if let Ok(v) = serde_json::from_str(&l) {
                return Some(v);
            }
        }
    }

    /// The next JSON line for which `pred` holds, within `timeout`.
    pub fn expect(
        &self,
        what: &str,
        timeout: std::time::Duration,
        pred: impl Fn(&serde_json::Value) -> bool,
    ) -> anyhow::Result<serde_json::Value> {
        use anyhow::Context as _;
        let end = std::time::Instant::now() + timeout;
        loop {
            let v = self
                .json(end.saturating_duration_since(std::time::Instant::now()))
                .with_context(|| format!("{}: no {what} within {timeout:?}", self.name))?;
            if pred(&v) {
                return Ok(v);
            }
        }
    }
}

impl Drop for LineChild {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
