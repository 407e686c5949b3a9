//! Whether a standby takes over a silent primary: decided from what the kernel knows,
//! not from lateness alone.
//!
//! Silence (no replication record within the deadline) is only a hint: on a saturated
//! host a live primary waits for a core, and a standby that was itself kept from
//! running sees every primary as late. So a silent primary is taken over only when:
//! - it is **dead** (its pidfd; handled before this), or
//! - it is **stopped** (`/proc/PID/stat` state `T`), or
//! - its loop has made no **progress** (the fence's heartbeat word, bumped every pass)
//!   for the whole deadline, while it was **not waiting for a core** (its
//!   `/proc/PID/schedstat` run-queue delay grew by less than half the window) and this
//!   standby was **not late itself** (its own last wake-up came within half the
//!   deadline of when it asked).
//!
//! A primary that is runnable but starved, or whose loop beats while its records are
//! late, is left alone, however long; one starved so long that its loop has not passed
//! for [`STARVED_LIMIT`] is taken over all the same (it serves nobody).

use std::time::Duration;

/// A primary starved this long without one pass of its loop is taken over anyway.
pub const STARVED_LIMIT: Duration = Duration::from_secs(10);

/// A process's scheduling state, from `/proc/PID/stat`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProcState {
    /// Running or runnable (`R`).
    Running,
    /// Sleeping, waiting on something (`S`, `D`, `I`).
    Sleeping,
    /// Stopped by a signal or traced (`T`, `t`).
    Stopped,
    /// Dead or a zombie (`Z`, `X`), or gone.
    Gone,
}

/// What the standby saw of a silent primary.
#[derive(Clone, Copy, Debug)]
pub struct Seen {
    /// Since the last replication record.
    pub silent: Duration,
    /// Since the primary's loop last passed (`None`: it never beat, e.g. still starting).
    pub since_beat: Option<Duration>,
    /// The primary's state now.
    pub state: ProcState,
    /// How much of the silent window the primary spent runnable, waiting for a core
    /// (`None`: unknown, no schedstat).
    pub waited_for_cpu: Option<Duration>,
    /// How much later than it asked this standby woke last.
    pub own_lateness: Duration,
}

/// The verdict on a silent primary.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Not silent long enough, or alive for sure: keep following.
    Follow,
    /// Stopped by a signal: take over.
    Stopped,
    /// Its loop made no progress while it could have run: take over.
    Hung,
    /// Runnable but waiting for a core (or this standby was late itself): not a hang.
    Starved,
}

/// Judges a primary silent for `seen.silent`, against `deadline`.
pub fn judge(seen: &Seen, deadline: Duration) -> Verdict {
    if seen.silent < deadline {
        return Verdict::Follow;
    }
    match seen.state {
        ProcState::Stopped => return Verdict::Stopped,
        // Its pidfd says it first; until then it is as good as stopped.
        ProcState::Gone => return Verdict::Stopped,
        ProcState::Running | ProcState::Sleeping => {}
    }
    // Its loop passed within the deadline: it lives, whatever its records do.
    let stale = seen.since_beat.unwrap_or(seen.silent);
    if stale < deadline {
        return Verdict::Follow;
    }
    if stale >= STARVED_LIMIT {
        return Verdict::Hung;
    }
    // This standby's own lateness is no proof of the primary's.
    if seen.own_lateness >= deadline / 2 {
        return Verdict::Starved;
    }
    // Waiting on a run queue for half the window or more: starved, not hung.
    let window = stale.min(seen.silent);
    if seen.waited_for_cpu.is_some_and(|w| w >= window / 2) {
        return Verdict::Starved;
    }
    Verdict::Hung
}

/// The state of process `pid` (`Gone` if it cannot be read).
pub fn proc_state(pid: u32) -> ProcState {
    let state = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|stat| {
            stat.rsplit_once(')')
                .and_then(|(_, rest)| rest.trim_start().chars().next())
        });
    match state {
        Some('R') => ProcState::Running,
        Some('T' | 't') => ProcState::Stopped,
        Some('Z' | 'X') | None => ProcState::Gone,
        Some(_) => ProcState::Sleeping,
    }
}

/// The time process `pid`'s threads have spent runnable, waiting for a core
/// (`/proc/PID/schedstat`'s second field, summed over its threads: the broker's loop may
/// be any of them); `None` if the kernel does not say.
pub fn run_queue_wait(pid: u32) -> Option<Duration> {
    let tasks = std::fs::read_dir(format!("/proc/{pid}/task")).ok()?;
    let mut total = 0u64;
    let mut any = false;
    for t in tasks.flatten() {
        let Ok(s) = std::fs::read_to_string(t.path().join("schedstat")) else {
            continue;
        };
        if let Some(ns) = s
            .split_whitespace()
            .nth(1)
            .and_then(|v| v.parse::<u64>().ok())
        {
            total = total.saturating_add(ns);
            any = true;
        }
    }
    any.then(|| Duration::from_nanos(total))
}

#[cfg(test)]
mod tests {
    use super::*;

    const D: Duration = Duration::from_millis(100);

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    fn seen(silent: u64) -> Seen {
        Seen {
            silent: ms(silent),
            since_beat: Some(ms(silent)),
            state: ProcState::Sleeping,
            waited_for_cpu: Some(Duration::ZERO),
            own_lateness: Duration::ZERO,
        }
    }

    #[test]
    fn a_silent_primary_whose_loop_stopped_while_it_could_run_is_hung() {
        assert_eq!(
            judge(&seen(50), D),
            Verdict::Follow,
            "not silent long enough"
        );
        assert_eq!(judge(&seen(100), D), Verdict::Hung);
        // Busy in its loop without passing it (a spin): hung too.
        let spin = Seen {
            state: ProcState::Running,
            ..seen(150)
        };
        assert_eq!(judge(&spin, D), Verdict::Hung);
    }

    #[test]
    fn a_stopped_primary_is_taken_over_at_the_deadline_whatever_else() {
        let s = Seen {
            state: ProcState::Stopped,
            since_beat: Some(ms(1)),
            waited_for_cpu: None,
            own_lateness: ms(500),
            ..seen(100)
        };
        assert_eq!(judge(&s, D), Verdict::Stopped);
        assert_eq!(
            judge(
                &Seen {
                    silent: ms(99),
                    ..s
                },
                D
            ),
            Verdict::Follow
        );
    }

    #[test]
    fn a_primary_whose_loop_beats_is_alive_however_late_its_records() {
        let s = Seen {
            since_beat: Some(ms(30)),
            ..seen(2000)
        };
        assert_eq!(judge(&s, D), Verdict::Follow);
    }

    #[test]
    fn a_primary_waiting_for_a_core_is_starved_not_hung_until_the_limit() {
        let s = Seen {
            state: ProcState::Running,
            waited_for_cpu: Some(ms(80)),
            ..seen(150)
        };
        assert_eq!(judge(&s, D), Verdict::Starved);
        // Under half the window on a run queue: it could have run, so it hangs.
        let s2 = Seen {
            waited_for_cpu: Some(ms(50)),
            ..s
        };
        assert_eq!(judge(&s2, D), Verdict::Hung);
        // Starved for ten seconds without one pass: taken over all the same.
        let s3 = Seen {
            silent: STARVED_LIMIT,
            since_beat: Some(STARVED_LIMIT),
            waited_for_cpu: Some(STARVED_LIMIT),
            ..s
        };
        assert_eq!(judge(&s3, D), Verdict::Hung);
    }

    #[test]
    fn a_standby_late_itself_does_not_blame_the_primary() {
        let s = Seen {
            own_lateness: ms(60),
            ..seen(300)
        };
        assert_eq!(judge(&s, D), Verdict::Starved);
        let s2 = Seen {
            own_lateness: ms(10),
            ..s
        };
        assert_eq!(judge(&s2, D), Verdict::Hung);
    }

    #[test]
    fn a_primary_that_never_beat_is_judged_by_its_silence() {
        let s = Seen {
            since_beat: None,
            ..seen(100)
        };
        assert_eq!(judge(&s, D), Verdict::Hung);
        let s2 = Seen {
            since_beat: None,
            ..seen(20)
        };
        assert_eq!(judge(&s2, D), Verdict::Follow);
    }

    #[test]
    fn a_child_reads_as_sleeping_then_stopped_then_gone() {
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .expect("sleep");
        let pid = child.id();
        // The state seen when the wait ends, not a second read: a child still starting
        // up passes through disk sleep (read as sleeping) and running before `sleep`
        // settles, so a re-read could catch it running again.
        let wait_for = |want: ProcState| {
            let deadline = std::time::Instant::now() + Duration::from_secs(5);
            loop {
                let state = proc_state(pid);
                if state == want || std::time::Instant::now() >= deadline {
                    return state;
                }
                std::thread::sleep(ms(5));
            }
        };
        assert_eq!(wait_for(ProcState::Sleeping), ProcState::Sleeping);
        assert!(run_queue_wait(pid).is_some(), "schedstat is readable");
        // SAFETY: a signal to our own child.
        unsafe { libc::kill(pid as i32, libc::SIGSTOP) };
        assert_eq!(wait_for(ProcState::Stopped), ProcState::Stopped);
        let _ = child.kill();
        let _ = child.wait();
        assert_eq!(proc_state(pid), ProcState::Gone);
    }
}
