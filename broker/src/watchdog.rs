//! A watchdog on the broker's loop. The loop says where it is ([`Watchdog::at`]: one
//! store and one increment); a thread of its own looks every 50 ms and, when the loop
//! has made no progress for longer than the threshold outside its wait for work, logs
//! what the loop was doing and what the kernel says of its thread: running (busy),
//! runnable but waiting for a core (starved), or asleep in the kernel (blocked, with the
//! kernel function it waits in). The time it ran is its CPU clock, exact to the moment.
//! When the loop moves again, the stall's length is logged too. A watchdog that was
//! itself late (its own sleep overslept: the whole process starved) says so rather than
//! blaming the loop.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Where the loop is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(usize)]
pub enum Phase {
    /// Waiting for work (the reactor): not a stall, however long.
    Waiting,
    /// Handling a signal.
    Signal,
    /// Reading the inbox and handling frames.
    Inbox,
    /// The UDP front.
    Udp,
    /// The federation.
    Federation,
    /// A dead peer, timers, housekeeping.
    Timers,
    /// Writing outputs to peers (and the list, the event feed).
    Flush,
    /// The replication stream.
    Replication,
    /// Cleanups after dead processes.
    Cleanup,
}

const PHASES: [Phase; 9] = [
    Phase::Waiting,
    Phase::Signal,
    Phase::Inbox,
    Phase::Udp,
    Phase::Federation,
    Phase::Timers,
    Phase::Flush,
    Phase::Replication,
    Phase::Cleanup,
];

/// One stall, as seen when the loop moved again.
#[derive(Clone, Debug, PartialEq)]
pub struct Stall {
    /// Where the loop was.
    pub phase: Phase,
    /// How long it made no progress (at least).
    pub lasted: Duration,
    /// The loop thread's state when the stall was noticed (`R` running or runnable,
    /// `S` asleep, `D` in uninterruptible sleep, ...), from `/proc`.
    pub state: char,
    /// Of the stall's time so far when noticed (from the first look that found the loop
    /// not moving): ms on a core, ms runnable but waiting for one
    /// (`/proc/.../schedstat`).
    pub on_cpu_ms: u64,
    /// See [`Stall::on_cpu_ms`].
    pub waiting_for_cpu_ms: u64,
}

struct Shared {
    phase: AtomicUsize,
    progress: AtomicU64,
    stop: AtomicBool,
    stalls: Mutex<Vec<Stall>>,
}

/// The watchdog; stopped on drop.
pub struct Watchdog {
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Most stalls kept for [`Watchdog::stalls`].
const KEPT: usize = 64;
/// How often the watchdog looks, as a part of the threshold: a stall is seen at most
/// an eighth of the threshold late. (It looked every 50 ms, and read the loop thread's
/// `/proc` files each time the loop had moved: 0.2 % of a core of an idle broker.)
const LOOKS_PER_THRESHOLD: u32 = 8;

/// The calling thread's kernel id.
fn tid() -> i64 {
    // SAFETY: gettid(2) has no preconditions.
    unsafe { libc::syscall(libc::SYS_gettid) }
}

/// The loop thread: its kernel id and its CPU-time clock.
#[derive(Clone, Copy)]
struct LoopThread {
    tid: i64,
    clock: Option<libc::clockid_t>,
}

impl LoopThread {
    /// The calling thread.
    fn me() -> Self {
        let mut clock: libc::clockid_t = 0;
        // SAFETY: pthread_self has no preconditions; pthread_getcpuclockid writes the
        // clock id of a live thread (this one) into `clock`.
        let ok = unsafe { libc::pthread_getcpuclockid(libc::pthread_self(), &mut clock) } == 0;
        LoopThread {
            tid: tid(),
            clock: ok.then_some(clock),
        }
    }

    /// Its state letter, ns it ran (its CPU clock, exact to now: the kernel counts the
    /// slice it is in), and ns it waited for a core (`schedstat`: counted when it runs).
    fn now(self) -> (char, u64, u64) {
        let tid = self.tid;
        let stat =
            std::fs::read_to_string(format!("/proc/self/task/{tid}/stat")).unwrap_or_default();
        let state = stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.trim_start().chars().next())
            .unwrap_or('?');
        let sched =
            std::fs::read_to_string(format!("/proc/self/task/{tid}/schedstat")).unwrap_or_default();
        let mut f = sched
            .split_whitespace()
            .map(|v| v.parse::<u64>().unwrap_or(0));
        let (ran, waited) = (f.next().unwrap_or(0), f.next().unwrap_or(0));
        let ran = self.clock.map_or(ran, |c| {
            let mut ts = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: clock_gettime on the loop thread's CPU clock (the thread outlives
            // the watchdog, which it owns and drops), into a live timespec.
            if unsafe { libc::clock_gettime(c, &mut ts) } == 0 {
                u64::try_from(ts.tv_sec)
                    .unwrap_or(0)
                    .saturating_mul(1_000_000_000)
                    + u64::try_from(ts.tv_nsec).unwrap_or(0)
            } else {
                ran
            }
        });
        (state, ran, waited)
    }
}

impl Watchdog {
    /// Watches the calling thread's loop: a stall is no progress for `threshold`.
    pub fn start(threshold: Duration) -> std::io::Result<Self> {
        let shared = Arc::new(Shared {
            phase: AtomicUsize::new(Phase::Waiting as usize),
            progress: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            stalls: Mutex::new(Vec::new()),
        });
        let me = LoopThread::me();
        let s = shared.clone();
        let thread = std::thread::Builder::new()
            .name("broker-watchdog".into())
            .spawn(move || watch(&s, me, threshold))?;
        Ok(Watchdog {
            shared,
            thread: Some(thread),
        })
    }

    /// The loop is at `phase` now (and has made progress).
    pub fn at(&self, phase: Phase) {
        self.shared.phase.store(phase as usize, Ordering::Relaxed);
        self.shared.progress.fetch_add(1, Ordering::Release);
    }

    /// The stalls seen so far (the last [`KEPT`]).
    pub fn stalls(&self) -> Vec<Stall> {
        self.shared
            .stalls
            .lock()
            .map(|s| s.clone())
            .unwrap_or_default()
    }
}

impl Drop for Watchdog {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn watch(s: &Shared, lt: LoopThread, threshold: Duration) {
    let look_every = (threshold / LOOKS_PER_THRESHOLD).max(Duration::from_millis(1));
    let mut seen = s.progress.load(Ordering::Acquire);
    let mut since = Instant::now();
    // A stall noticed and not over: where, the thread's state, and its schedstat then.
    let mut open: Option<(Phase, char, u64, u64)> = None;
    // The loop thread's CPU and wait for a core when a look first found it not moving
    // outside its wait (read then, not at every move: the stall's figures count from
    // there, at most a look after it began).
    let mut base: Option<(Instant, u64, u64)> = None;
    let mut last_look = Instant::now();
    while !s.stop.load(Ordering::Acquire) {
        std::thread::sleep(look_every);
        let now = Instant::now();
        let overslept = now.duration_since(last_look).saturating_sub(look_every);
        last_look = now;
        if overslept >= threshold {
            tracing::warn!(
                overslept_ms = overslept.as_millis() as u64,
                "the broker's watchdog itself ran late: the whole process waited for a core"
            );
        }
        let progress = s.progress.load(Ordering::Acquire);
        if progress != seen {
            if let Some((phase, state, on_cpu, waiting)) = open.take() {
                let lasted = now.duration_since(since);
                tracing::warn!(
                    phase = ?phase,
                    lasted_ms = lasted.as_millis() as u64,
                    "broker loop moving again after a stall"
                );
                if let Ok(mut v) = s.stalls.lock() {
                    if v.len() >= KEPT {
                        v.remove(0);
                    }
                    v.push(Stall {
                        phase,
                        lasted,
                        state,
                        on_cpu_ms: on_cpu / 1_000_000,
                        waiting_for_cpu_ms: waiting / 1_000_000,
                    });
                }
            }
            seen = progress;
            since = now;
            base = None;
            continue;
        }
        let phase = PHASES
            .get(s.phase.load(Ordering::Relaxed))
            .copied()
            .unwrap_or(Phase::Waiting);
        if phase == Phase::Waiting {
            continue;
        }
        let (t0, cpu0, wait0) = *base.get_or_insert_with(|| {
            let (_, cpu, wait) = lt.now();
            (now, cpu, wait)
        });
        if open.is_none() && now.duration_since(since) >= threshold {
            let (state, cpu, wait) = lt.now();
            let (on_cpu, waiting) = (cpu.saturating_sub(cpu0), wait.saturating_sub(wait0));
            let wchan = std::fs::read_to_string(format!("/proc/self/task/{}/wchan", lt.tid))
                .unwrap_or_default();
            // A thread waiting for a core has its wait counted only once it runs; its CPU
            // clock is exact: one that is runnable and ran little in the stall is starved.
            let stalled = now.duration_since(since);
            let what = match state {
                'R' if waiting > on_cpu
                    || Duration::from_nanos(on_cpu) < now.duration_since(t0) / 2 =>
                {
                    "runnable, waiting for a core (starved)"
                }
                'R' => "running (busy)",
                'D' => "in uninterruptible sleep (the kernel: I/O, a page fault)",
                'S' => "asleep in the kernel (blocked)",
                _ => "in another state",
            };
            tracing::warn!(
                phase = ?phase,
                stalled_ms = stalled.as_millis() as u64,
                state = %state,
                on_cpu_ms = on_cpu / 1_000_000,
                waiting_for_cpu_ms = waiting / 1_000_000,
                wchan = %wchan.trim(),
                "broker loop stalled: {what}"
            );
            open = Some((phase, state, on_cpu, waiting));
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_stall_outside_the_wait_is_seen_with_its_phase_and_the_threads_state() {
        let w = Watchdog::start(Duration::from_millis(150)).unwrap();
        // Waiting for work for long: no stall.
        w.at(Phase::Waiting);
        std::thread::sleep(Duration::from_millis(400));
        w.at(Phase::Inbox);
        assert!(w.stalls().is_empty(), "{:?}", w.stalls());
        // Asleep in the middle of a flush: a stall, blocked.
        w.at(Phase::Flush);
        std::thread::sleep(Duration::from_millis(400));
        w.at(Phase::Waiting);
        // Busy in the federation: a stall, running.
        w.at(Phase::Federation);
        let t = Instant::now();
        let mut x = 0u64;
        while t.elapsed() < Duration::from_millis(400) {
            x = std::hint::black_box(x.wrapping_add(1));
        }
        w.at(Phase::Waiting);
        std::thread::sleep(Duration::from_millis(150));
        let stalls = w.stalls();
        assert_eq!(stalls.len(), 2, "{stalls:?}");
        assert_eq!(stalls[0].phase, Phase::Flush);
        assert_eq!(stalls[0].state, 'S');
        assert!(stalls[0].lasted >= Duration::from_millis(150), "{stalls:?}");
        assert_eq!(stalls[1].phase, Phase::Federation);
        // Running or runnable (on a busy machine it may wait for a core), and it ran.
        assert_eq!(stalls[1].state, 'R');
        assert!(stalls[1].on_cpu_ms > 0, "{stalls:?}");
    }
}
