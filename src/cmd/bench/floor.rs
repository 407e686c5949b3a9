//! `muster bench floor`: the raw two-process round trip through an iceoryx2 inbox and
//! bell, woken by epoll as every muster process is. No muster logic on the path: this is
//! the floor the request path is measured against.

use super::children::Children;
use super::{row, summary};
use crate::cli::FloorArgs;
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::ipc::{create_node, Endpoint};
use muster_shared::reactor::{Reactor, SignalPipe};
use muster_shared::types::UserId;
use muster_shared::{Address, Instance};
use serde_json::json;
use std::process::{ExitCode, Stdio};
use std::time::{Duration, Instant};

const ECHO: &str = "floor-echo";
const PROBE: &str = "floor-probe";
const TOKEN_BELL: usize = 0;
const TOKEN_SIGNAL: usize = 1;

/// The echo process: sends every frame back to the probe, until a signal.
pub fn echo(inst: &Instance) -> anyhow::Result<ExitCode> {
    let node = create_node(&format!("muster-echo-{}", std::process::id()), false)?;
    let mut ep = Endpoint::open(inst, Address::System(ECHO.into()), node)?;
    let mut signals = SignalPipe::install()?;
    let mut reactor = Reactor::new()?;
    reactor.add(ep.bell_fd(), TOKEN_BELL)?;
    reactor.add(signals.raw(), TOKEN_SIGNAL)?;
    let probe = Address::User(UserId(PROBE.into()));
    loop {
        let tokens = reactor.wait(None)?;
        if tokens.contains(&TOKEN_SIGNAL) && signals.drain() {
            return Ok(ExitCode::SUCCESS);
        }
        ep.drain_bell();
        while let Some(frame) = ep.recv()? {
            let _ = ep.send(&probe, &frame);
        }
    }
}

/// Measures `n` round trips against a fresh echo process; returns their histogram (µs).
pub fn measure(inst: &Instance, n: usize) -> anyhow::Result<Histogram<u64>> {
    let mut children = Children::default();
    children.spawn(inst, "echo", &["bench", "echo"], Stdio::null())?;
    let node = create_node(&format!("muster-probe-{}", std::process::id()), false)?;
    let mut ep = Endpoint::open(inst, Address::User(UserId(PROBE.into())), node)?;
    let mut reactor = Reactor::new()?;
    reactor.add(ep.bell_fd(), TOKEN_BELL)?;
    let echo = Address::System(ECHO.into());
    // Wait for the echo to be up.
    let start = Instant::now();
    while ep.send(&echo, b"hello").is_err() {
        if start.elapsed() > Duration::from_secs(10) {
            bail!("the echo process did not come up");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let mut h = Histogram::<u64>::new(3)?;
    let frame = vec![0x4d_u8; 64];
    let mut received = 0usize;
    let mut warm = 100usize;
    while h.len() < n as u64 {
        let t = Instant::now();
        ep.send(&echo, &frame).context("sending to the echo")?;
        // Sleep on the bell until the echo arrives, as a muster process does.
        let deadline = t + Duration::from_secs(5);
        loop {
            ep.drain_bell();
            let mut got = false;
            while let Some(f) = ep.recv()? {
                received += 1;
                got |= f.len() == frame.len();
            }
            if got {
                break;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                bail!("an echo took more than 5 s");
            }
            reactor.wait(Some(left))?;
        }
        if warm > 0 {
            warm -= 1;
        } else {
            h.record(t.elapsed().as_micros().max(1) as u64)?;
        }
    }
    tracing::debug!(received, "floor measured");
    children.stop();
    Ok(h)
}

pub fn run(inst: &Instance, a: FloorArgs) -> anyhow::Result<ExitCode> {
    let h = measure(inst, a.round_trips.max(1))?;
    if a.json {
        println!("{}", json!({"floor": summary(&h)}));
    } else {
        println!(
            "{:<28} {:>7} {:>10} {:>10} {:>10} {:>10}",
            "latency (us)", "count", "p50", "p90", "p99", "max"
        );
        println!("{}", row("floor: inbox+bell round trip", &h));
    }
    Ok(ExitCode::SUCCESS)
}
