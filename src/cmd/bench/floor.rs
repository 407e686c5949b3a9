//! `muster bench floor`: the raw two-process round trip through an iceoryx2 inbox and
//! bell, woken by epoll as every muster process is. No muster logic on the path: this is
//! the floor the request path is measured against.

use super::children::Children;
use super::{header, row, summary};
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
        while let Some(frame) = ep.recv() {
            let _ = ep.send(&probe, &frame);
        }
    }
}

/// A probe bouncing frames off an echo process it started.
pub struct FloorProbe {
    children: Children,
    ep: Endpoint,
    reactor: Reactor,
    frame: Vec<u8>,
}

impl FloorProbe {
    /// Starts the echo process and waits until it answers.
    pub fn start(inst: &Instance) -> anyhow::Result<Self> {
        let mut children = Children::default();
        children.spawn(inst, "echo", &["bench", "echo"], Stdio::null())?;
        let node = create_node(&format!("muster-probe-{}", std::process::id()), false)?;
        let mut ep = Endpoint::open(inst, Address::User(UserId(PROBE.into())), node)?;
        let reactor = Reactor::new()?;
        reactor.add(ep.bell_fd(), TOKEN_BELL)?;
        let echo = Address::System(ECHO.into());
        let start = Instant::now();
        while ep.send(&echo, b"hello").is_err() {
            if start.elapsed() > Duration::from_secs(10) {
                bail!("the echo process did not come up");
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let mut probe = FloorProbe {
            children,
            ep,
            reactor,
            frame: vec![0x4d_u8; 64],
        };
        // Warm up. A frame written before the echo's inbox has taken our publisher's
        // connection can be lost (iceoryx2 connects lazily): a warm-up round trip
        // unanswered for 200 ms is sent again, within the start's 10 s.
        let mut warm = 0;
        while warm < 100 {
            match probe.try_round_trip(Duration::from_millis(200))? {
                Some(_) => warm += 1,
                None if start.elapsed() > Duration::from_secs(10) => {
                    bail!("the echo process did not answer")
                }
                None => {}
            }
        }
        Ok(probe)
    }

    /// One round trip, sleeping on the bell as a muster process does.
    pub fn round_trip(&mut self) -> anyhow::Result<Duration> {
        self.try_round_trip(Duration::from_secs(5))?
            .context("an echo took more than 5 s")
    }

    /// One round trip, or `None` if no answer within `patience`.
    fn try_round_trip(&mut self, patience: Duration) -> anyhow::Result<Option<Duration>> {
        let t = Instant::now();
        self.ep
            .send(&Address::System(ECHO.into()), &self.frame)
            .context("sending to the echo")?;
        let deadline = t + patience;
        loop {
            self.ep.drain_bell();
            let mut got = false;
            while let Some(f) = self.ep.recv() {
                got |= f.len() == self.frame.len();
            }
            if got {
                return Ok(Some(t.elapsed()));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            self.reactor.wait(Some(left))?;
        }
    }

    /// Stops the echo process.
    pub fn stop(mut self) {
        self.children.stop();
    }
}

pub fn run(inst: &Instance, a: FloorArgs) -> anyhow::Result<ExitCode> {
    let mut probe = FloorProbe::start(inst)?;
    let mut h = Histogram::<u64>::new(3)?;
    for _ in 0..a.round_trips.max(1) {
        h.record(probe.round_trip()?.as_micros().max(1) as u64)?;
    }
    probe.stop();
    if a.json {
        println!("{}", json!({"floor": summary(&h)}));
    } else {
        println!("{}", header("latency (us)"));
        println!("{}", row("floor: inbox+bell round trip", &h));
    }
    Ok(ExitCode::SUCCESS)
}
