//! The handling log (`--handling-log`): how long the core took per message kind.

#[allow(unused_imports)]
use super::*;

/// Most handling records kept for `--handling-log` (32 bytes each); later ones are
/// counted, not kept.
pub const MAX_HANDLING_LOG: usize = 2_000_000;

/// One message handled: when (CLOCK_MONOTONIC ms, one clock for every process on the
/// host), its kind, and how long the core took, µs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HandlingRecord {
    /// CLOCK_MONOTONIC ms when handling began.
    pub at_ms: u64,
    /// The message kind (`ToBroker::kind`), or `list_write` for a list snapshot write.
    pub kind: &'static str,
    /// Handling time, µs.
    pub us: u64,
}

/// Time to handle each message type (µs histograms), and, if asked, every handling.
#[derive(Debug)]
pub struct Handling {
    /// Per kind.
    pub hist: std::collections::BTreeMap<&'static str, hdrhistogram::Histogram<u64>>,
    /// Every handling in order (only with `keep_log`), at most [`MAX_HANDLING_LOG`].
    pub log: Vec<HandlingRecord>,
    /// Handlings not logged because the log was full.
    pub log_dropped: u64,
    pub(super) keep_log: bool,
}

impl Handling {
    /// Empty; `keep_log` keeps every handling for a time series.
    pub fn new(keep_log: bool) -> Self {
        Handling {
            hist: std::collections::BTreeMap::new(),
            log: Vec::new(),
            log_dropped: 0,
            keep_log,
        }
    }

    /// Records one handling of `kind` that began at `began` and took `took`.
    pub fn record(&mut self, kind: &'static str, began: Instant, took: Duration) {
        let us = (took.as_nanos() as u64).div_ceil(1000).max(1);
        let h = self.hist.entry(kind).or_insert_with(|| {
            hdrhistogram::Histogram::new(3).expect("3 significant figures is a valid precision")
        });
        let _ = h.record(us);
        if self.keep_log {
            if self.log.len() < MAX_HANDLING_LOG {
                let ago = began.elapsed().as_nanos() as u64;
                let at_ms = muster_shared::protocol::monotonic_ns().saturating_sub(ago) / 1_000_000;
                self.log.push(HandlingRecord { at_ms, kind, us });
            } else {
                self.log_dropped += 1;
            }
        }
    }

    /// Counts and percentiles per kind, for an operator's status.
    pub fn figures(&self) -> Vec<muster_shared::protocol::HandlingFigures> {
        self.hist
            .iter()
            .map(|(kind, h)| muster_shared::protocol::HandlingFigures {
                kind: (*kind).to_string(),
                count: h.len(),
                p50_us: h.value_at_quantile(0.5),
                p99_us: h.value_at_quantile(0.99),
                max_us: h.max(),
            })
            .collect()
    }

    /// Writes the log as CSV (`at_ms,kind,us`).
    pub fn write_log(&self, path: &std::path::Path) -> std::io::Result<()> {
        use std::io::Write;
        let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
        writeln!(f, "at_ms,kind,us")?;
        for r in &self.log {
            writeln!(f, "{},{},{}", r.at_ms, r.kind, r.us)?;
        }
        f.flush()
    }
}

/// Cuts an operator's status to fit one frame (with room for the message around it):
/// its lists are halved until it does. The totals still count everyone.
pub(super) fn fit_status(status: &mut muster_shared::protocol::BrokerStatus) {
    use muster_shared::protocol::{encode, MAX_FRAME};
    while encode(&*status).map_or(true, |f| f.len() > MAX_FRAME - 64) {
        if status.users.is_empty()
            && status.sessions.is_empty()
            && status.queues.is_empty()
            && status.systems.is_empty()
        {
            status.handling.clear();
            return;
        }
        for q in &mut status.queues {
            q.waiting.truncate(q.waiting.len() / 2);
        }
        status.queues.truncate(status.queues.len() / 2);
        status.users.truncate(status.users.len() / 2);
        status.sessions.truncate(status.sessions.len() / 2);
        status.systems.truncate(status.systems.len() / 2);
    }
}

/// Hands `msg` to the core and records how long that took under the message's kind.
pub fn timed_handle(handling: &mut Handling, core: &mut Broker, now: Duration, msg: ToBroker) {
    let kind = msg.kind();
    let t = Instant::now();
    core.handle(now, msg);
    handling.record(kind, t, t.elapsed());
}
