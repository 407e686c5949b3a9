//! `muster bench ...`: benchmarks that print figures (never assertions).

mod failover;
mod federation;
pub mod floor;
mod leftovers;
mod liveness;
pub mod procfs;
pub mod remote;
mod ros2;
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
        BenchCommand::FailoverUser(a) => failover::user(inst, a),
        BenchCommand::Leftovers(a) => leftovers::run(inst, a),
    }
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
