//! One file per command.

/// Prints a line on standard output, like `println!`, but a closed output (`muster
/// user request ... | head`, `muster up | head`) is no panic: the command winds up as
/// on SIGTERM (sessions end cleanly, children are stopped) and later lines are dropped.
macro_rules! out {
    ($($t:tt)*) => {
        $crate::cmd::say(&format!($($t)*))
    };
}

mod behave;
mod bench;
mod broker;
mod capacity;
mod certs;
mod children;
mod console;
mod events;
mod experiment;
mod keygen;
mod netns;
mod operator;
mod paper;
mod record;
mod scalability;
mod sim;
mod standbys;
mod stress;
mod stress_plot;
mod system;
mod taps;
mod tui;
mod up;
mod up_paper;
mod user;
mod user_tui;
mod view;
mod view_gate;

use crate::cli::{Cli, Command};
use anyhow::Context;
use muster_shared::Instance;
use std::process::ExitCode;

/// Writes `line` to standard output; the first write that fails (the reader went away)
/// raises SIGTERM, and nothing more is written.
pub(crate) fn say(line: &str) {
    use std::io::Write;
    use std::sync::atomic::{AtomicBool, Ordering};
    static GONE: AtomicBool = AtomicBool::new(false);
    if GONE.load(Ordering::Relaxed) {
        return;
    }
    let mut o = std::io::stdout().lock();
    let written = writeln!(o, "{line}").and_then(|()| o.flush());
    if written.is_err() && !GONE.swap(true, Ordering::Relaxed) {
        // SAFETY: raise has no preconditions; the command's signal handling (or the
        // default action, before it is set up) takes it from here.
        unsafe {
            libc::raise(libc::SIGTERM);
        }
    }
}

/// The broker's and systems' niceness unless `--nice` says otherwise: ahead of user
/// processes on a crowded host. Measured with `muster stress --users 900`, 20 s runs:
/// service request p99 over the first 10 s (900 users starting) 36-50 ms in 3 of 4 runs
/// at -5, against 167-589 ms in 4 of 4 at 0 (README, "Storms").
pub const INFRASTRUCTURE_NICE: i32 = -5;

/// Runs the parsed command.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    if let Some(ns) = &cli.in_netns {
        netns::enter(ns)?;
    }
    let inst = Instance::new(&cli.instance).context("--instance")?;
    // Before any thread starts: Linux keeps a niceness per thread, and new threads
    // take their creator's.
    let infrastructure = matches!(
        cli.command,
        Command::Broker(_) | Command::System(_) | Command::Agv(_)
    );
    match (cli.nice, infrastructure) {
        (Some(n), _) => {
            if let Err(e) = muster_shared::reactor::set_nice(n) {
                tracing::warn!("--nice {n}: {e}");
            }
        }
        (None, true) => {
            // Expected without privileges (a newcomer's `muster up`): quietly.
            if let Err(e) = muster_shared::reactor::set_nice(INFRASTRUCTURE_NICE) {
                tracing::debug!(
                    "running at the niceness started with, not {INFRASTRUCTURE_NICE}: {e}"
                );
            }
        }
        (None, false) => {}
    }
    match cli.command {
        Command::Broker(a) => broker::run(&inst, a),
        Command::System(s) => system::run(&inst, s),
        Command::User(u) => user::run(&inst, u),
        Command::Up(a) => up::run(&inst, a),
        Command::Bench(b) => bench::run(&inst, b),
        Command::Sim(a) => sim::run(&inst, a),
        Command::Agv(a) => system::agv(&inst, a),
        Command::Stress(a) => stress::run(&inst, a),
        Command::Keygen(a) => keygen::run(a),
        Command::Certs(a) => certs::run(a),
        Command::Events(a) => events::run(&inst, a),
        Command::Record(a) => record::run(&inst, a),
        Command::Operator(a) => operator::run(&inst, a),
        Command::Console(a) => console::run(&inst, a),
        Command::Web(a) => muster_web::serve(muster_web::WebOptions {
            instance: inst.clone(),
            listen: a.listen,
            access: a.access,
            wait_for_broker: a.wait,
            map: a.map,
            tls: a.tls.map(|v| (v[0].clone(), v[1].clone())),
        })
        .map(|()| ExitCode::SUCCESS),
        Command::View(a) => view::run(&inst, a),
        Command::Replay(a) => view::replay(a),
        Command::Netns(a) => netns::run(&inst, a),
        Command::NetProxy(a) => netns::proxy(a),
        Command::Cleanup {
            pid,
            after,
            beside_broker,
        } => {
            std::thread::sleep(after);
            let n = muster_shared::ipc::cleanup_after(pid);
            tracing::debug!(nodes = n, "cleaned up after dead processes");
            // The fence of a run whose brokers were all killed: no broker or standby
            // alive (by their nodes, and the pid the fence names).
            if !beside_broker
                && muster_shared::ipc::live_brokers(&inst) == 0
                && muster_shared::fence::remove_if_orphaned(&inst)
            {
                tracing::info!(instance = %inst, "removed the fence of a broker that was killed");
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Capacity(a) => capacity::run(a),
        Command::Experiment(crate::cli::ExperimentCommand::Link(a)) => experiment::link(&inst, a),
        Command::Experiment(crate::cli::ExperimentCommand::Scalability(a)) => {
            let scale = match cli.time_scale {
                Some(s) => s,
                None => muster_shared::clock::TimeScale::new(10.0).map_err(anyhow::Error::msg)?,
            };
            scalability::run(&inst, a, scale)
        }
    }
}
