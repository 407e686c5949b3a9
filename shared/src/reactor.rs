//! The event loop's waiting part: one epoll (through mio) over the bell, the presence
//! event, process-death descriptors (pidfd) and a signal pipe. A process sleeps here
//! until something happens or its core's next deadline, never polling.

use mio::unix::SourceFd;
use mio::{Events, Interest, Poll, Token};
use std::io::{self, Read};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::os::unix::net::UnixStream;
use std::time::Duration;

/// An epoll set of file descriptors, each under a caller-chosen token.
pub struct Reactor {
    poll: Poll,
    events: Events,
    /// A timer for short waits that epoll's whole milliseconds would stretch (made on
    /// first need, watched under [`TIMER_TOKEN`]), and whether it is armed.
    timer: Option<OwnedFd>,
    timer_armed: bool,
}

/// The token of a reactor's own timer: never handed to callers, and refused to them
/// ([`Reactor::add`]). Not `usize::MAX`, which callers take for a token of their own.
pub const TIMER_TOKEN: usize = usize::MAX - 0xfe11;

/// Waits shorter than this that are not whole milliseconds end on a timer of the
/// reactor's own, to the microsecond: epoll counts in whole milliseconds, rounded up,
/// so a wait of 0.5 ms (a deferred bell) would last 1 ms and more. Longer waits keep
/// epoll's rounding (at most 1 ms on 5 ms or more) and cost no timer call.
pub const PRECISE_BELOW: Duration = Duration::from_millis(5);

impl Reactor {
    /// A new, empty reactor.
    pub fn new() -> io::Result<Self> {
        Ok(Reactor {
            poll: Poll::new()?,
            events: Events::with_capacity(256),
            timer: None,
            timer_armed: false,
        })
    }

    /// Arms the reactor's timer to fire once after `after` (0: disarms it), making and
    /// watching it first if need be.
    fn arm_timer(&mut self, after: Duration) -> io::Result<()> {
        if self.timer.is_none() {
            // SAFETY: timerfd_create takes no pointers; a non-negative result is a new
            // descriptor we own.
            let fd = unsafe {
                libc::timerfd_create(
                    libc::CLOCK_MONOTONIC,
                    libc::TFD_NONBLOCK | libc::TFD_CLOEXEC,
                )
            };
            if fd < 0 {
                return Err(io::Error::last_os_error());
            }
            // SAFETY: fd was just created and is owned by nothing else.
            let fd = unsafe { OwnedFd::from_raw_fd(fd) };
            self.add_any(fd.as_raw_fd(), TIMER_TOKEN)?;
            self.timer = Some(fd);
        }
        let Some(fd) = &self.timer else {
            return Ok(());
        };
        let spec = libc::itimerspec {
            it_interval: libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            },
            it_value: libc::timespec {
                tv_sec: after.as_secs() as libc::time_t,
                tv_nsec: after.subsec_nanos() as libc::c_long,
            },
        };
        // SAFETY: a valid itimerspec, no old value asked for, on a timerfd we own.
        if unsafe { libc::timerfd_settime(fd.as_raw_fd(), 0, &spec, std::ptr::null_mut()) } != 0 {
            return Err(io::Error::last_os_error());
        }
        self.timer_armed = !after.is_zero();
        Ok(())
    }

    /// Watches `fd` for readability under `token` (any but [`TIMER_TOKEN`]). The fd must
    /// outlive its registration.
    pub fn add(&self, fd: RawFd, token: usize) -> io::Result<()> {
        if token == TIMER_TOKEN {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("token {TIMER_TOKEN} is the reactor's own timer's"),
            ));
        }
        self.add_any(fd, token)
    }

    fn add_any(&self, fd: RawFd, token: usize) -> io::Result<()> {
        self.poll
            .registry()
            .register(&mut SourceFd(&fd), Token(token), Interest::READABLE)
    }

    /// The epoll descriptor itself: readable while a watched fd has news (for a host
    /// event loop that watches the whole set through one descriptor).
    pub fn raw(&self) -> RawFd {
        use std::os::fd::AsRawFd;
        self.poll.as_raw_fd()
    }

    /// Stops watching `fd`.
    pub fn remove(&self, fd: RawFd) {
        let _ = self.poll.registry().deregister(&mut SourceFd(&fd));
    }

    /// Waits until a watched fd is readable or `timeout` passes; returns the ready tokens.
    /// An interrupted wait returns no tokens.
    /// A wait shorter than [`PRECISE_BELOW`] ends within microseconds of `timeout`, not
    /// at epoll's next whole millisecond.
    pub fn wait(&mut self, timeout: Option<Duration>) -> io::Result<Vec<usize>> {
        let precise = timeout
            .filter(|t| !t.is_zero() && *t < PRECISE_BELOW && t.subsec_nanos() % 1_000_000 != 0);
        match precise {
            // The timer ends the wait; epoll's own deadline (rounded up) backs it.
            Some(t) if self.arm_timer(t).is_ok() => {}
            // A timer left armed by a wait cut short must not end this one.
            _ if self.timer_armed => {
                let _ = self.arm_timer(Duration::ZERO);
            }
            _ => {}
        }
        match self.poll.poll(&mut self.events, timeout) {
            Ok(()) => {
                let mut fired = false;
                let tokens = self
                    .events
                    .iter()
                    .map(|e| e.token().0)
                    .filter(|&t| {
                        fired |= t == TIMER_TOKEN;
                        t != TIMER_TOKEN
                    })
                    .collect();
                if fired {
                    // (A timerfd reads as an eventfd does: a count, 8 bytes.)
                    if let Some(fd) = &self.timer {
                        drain_eventfd(fd);
                    }
                    self.timer_armed = false;
                }
                Ok(tokens)
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(Vec::new()),
            Err(e) => Err(e),
        }
    }
}

/// A new non-blocking eventfd: one thread rings it ([`ring_eventfd`]) to wake another
/// whose reactor watches it, which drains it ([`drain_eventfd`]) before looking for work.
pub fn eventfd() -> io::Result<OwnedFd> {
    // SAFETY: eventfd takes no pointers; a non-negative result is a new descriptor we own.
    let fd = unsafe { libc::eventfd(0, libc::EFD_NONBLOCK | libc::EFD_CLOEXEC) };
    if fd < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: fd was just created and is owned by nothing else.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// Makes an [`eventfd`] readable.
pub fn ring_eventfd(fd: &OwnedFd) {
    let one: u64 = 1;
    // SAFETY: writes 8 bytes from a live u64 to an eventfd we own.
    unsafe { libc::write(fd.as_raw_fd(), (&one as *const u64).cast(), 8) };
}

/// Empties an [`eventfd`] (non-blocking).
pub fn drain_eventfd(fd: &OwnedFd) {
    let mut n: u64 = 0;
    // SAFETY: reads 8 bytes into a live u64 from an eventfd we own (non-blocking).
    unsafe { libc::read(fd.as_raw_fd(), (&mut n as *mut u64).cast(), 8) };
}

/// A process-exit descriptor: readable once the process has exited.
#[derive(Debug)]
pub struct PidFd {
    fd: OwnedFd,
    pid: u32,
}

impl PidFd {
    /// Opens a pidfd for `pid`; fails if the process does not exist.
    pub fn open(pid: u32) -> io::Result<Self> {
        let pid_t = libc::pid_t::try_from(pid)
            .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "pid out of range"))?;
        // SAFETY: pidfd_open takes a pid and flags and returns a new fd or -1.
        let fd = unsafe { libc::syscall(libc::SYS_pidfd_open, pid_t, 0) };
        if fd < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: the syscall returned a fresh descriptor that we now own.
        let fd = unsafe { OwnedFd::from_raw_fd(fd as RawFd) };
        Ok(PidFd { fd, pid })
    }

    /// The watched process id.
    pub fn pid(&self) -> u32 {
        self.pid
    }

    /// The descriptor, for the reactor.
    pub fn raw(&self) -> RawFd {
        self.fd.as_raw_fd()
    }

    /// Whether the process has exited (checked without blocking).
    pub fn exited(&self) -> bool {
        let mut pfd = libc::pollfd {
            fd: self.raw(),
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: one valid pollfd, zero timeout.
        let n = unsafe { libc::poll(&mut pfd, 1, 0) };
        n > 0 && pfd.revents & libc::POLLIN != 0
    }
}

/// Whether a process with this pid exists (signal 0 probe; no signal is sent).
pub fn process_exists(pid: u32) -> bool {
    let Ok(p) = libc::pid_t::try_from(pid) else {
        return false;
    };
    // SAFETY: kill with signal 0 only checks existence and permission.
    unsafe {
        libc::kill(p, 0) == 0 || io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
    }
}

/// Whether process `pid` runs (or is stopped): it exists and has not exited (a zombie,
/// dead but not yet reaped by its parent, does not count).
pub fn process_alive(pid: u32) -> bool {
    if !process_exists(pid) {
        return false;
    }
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the command name, which is in parentheses and may hold any
        // character: read it after the last ')'.
        Ok(stat) => stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.trim_start().chars().next())
            .is_none_or(|state| state != 'Z' && state != 'X'),
        Err(_) => true,
    }
}

/// Whether process `pid` is stopped (SIGSTOP, or traced), from `/proc/PID/stat`.
pub fn process_stopped(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|stat| {
            stat.rsplit_once(')')
                .and_then(|(_, rest)| rest.trim_start().chars().next())
        })
        .is_some_and(|state| state == 'T' || state == 't')
}

/// SIGINT/SIGTERM/SIGHUP delivered through a pipe, so the reactor wakes on them.
pub struct SignalPipe {
    read: UnixStream,
}

impl SignalPipe {
    /// Installs the handlers.
    pub fn install() -> io::Result<Self> {
        let (read, write) = UnixStream::pair()?;
        read.set_nonblocking(true)?;
        for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
            signal_hook::low_level::pipe::register(sig, write.try_clone()?)?;
        }
        Ok(SignalPipe { read })
    }

    /// A pipe that SIGHUP writes to (reload configuration).
    pub fn hangup() -> io::Result<Self> {
        let (read, write) = UnixStream::pair()?;
        read.set_nonblocking(true)?;
        signal_hook::low_level::pipe::register(signal_hook::consts::SIGHUP, write)?;
        Ok(SignalPipe { read })
    }

    /// The read end, for the reactor.
    pub fn raw(&self) -> RawFd {
        self.read.as_raw_fd()
    }

    /// Empties the pipe; true if a signal arrived.
    pub fn drain(&mut self) -> bool {
        let mut buf = [0u8; 64];
        let mut got = false;
        while let Ok(n) = self.read.read(&mut buf) {
            if n == 0 {
                break;
            }
            got = true;
        }
        got
    }
}

/// Makes the calling thread's remaining work (a leaving user's teardown: unmapping
/// its shared memory, closing ports, exiting) wait for every other runnable thread on
/// the machine: `SCHED_IDLE` (no privilege needed to lower one's own priority), or
/// niceness 19 where that is refused. When hundreds of users leave in the same second
/// their teardowns otherwise compete, at the broker's own priority, with the broker
/// and with the users still asking it something.
pub fn yield_for_exit() {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: sched_setscheduler(2) on the calling thread (pid 0) with a valid param.
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } != 0 {
        let _ = set_nice(19);
    }
}

/// Sets the calling thread's niceness (-20 first to 19 last); threads it starts later
/// take it too (Linux keeps one per thread). Lowering it needs root, CAP_SYS_NICE or
/// RLIMIT_NICE: without, the error says so and nothing changes.
pub fn set_nice(nice: i32) -> io::Result<()> {
    if !(-20..=19).contains(&nice) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("niceness {nice} is outside -20..=19"),
        ));
    }
    // SAFETY: setpriority(2) on the calling thread (Linux: `who` 0 is the caller).
    if unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, nice) } != 0 {
        let e = io::Error::last_os_error();
        return Err(match e.kind() {
            io::ErrorKind::PermissionDenied => io::Error::new(
                e.kind(),
                format!("not permitted to set niceness {nice} (it needs root, CAP_SYS_NICE or RLIMIT_NICE): {e}"),
            ),
            _ => e,
        });
    }
    Ok(())
}

/// This process's descriptor limit (the soft one; 1,024 if it cannot be read).
pub fn fd_limit() -> u64 {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: valid out-pointer.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } == 0 {
        lim.rlim_cur
    } else {
        1024
    }
}

/// Whether `e` says the process (EMFILE) or the system (ENFILE) has no descriptor left.
pub fn is_out_of_descriptors(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE))
}

/// Whether `n` more descriptors can be opened now (opened and closed again to find out:
/// a few microseconds; for a failure path, not a loop).
pub fn descriptors_free(n: usize) -> bool {
    let mut held = Vec::with_capacity(n);
    for _ in 0..n {
        // SAFETY: no pointers; the descriptor, if any, is owned at once.
        let fd = unsafe { libc::eventfd(0, libc::EFD_CLOEXEC) };
        if fd < 0 {
            return !is_out_of_descriptors(&io::Error::last_os_error());
        }
        // SAFETY: a new descriptor nothing else owns.
        held.push(unsafe { OwnedFd::from_raw_fd(fd) });
    }
    true
}

/// Raises this process's descriptor limit as far as it may (the broker, a system and the
/// web console hold a few descriptors per peer): with the privilege to (root,
/// CAP_SYS_RESOURCE), the hard limit too, up to the kernel's `nr_open` (at most 2^20);
/// otherwise the soft limit to the hard one. Returns the new soft limit.
pub fn raise_fd_limit() -> io::Result<u64> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: valid out-pointer.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
        return Err(io::Error::last_os_error());
    }
    let nr_open = std::fs::read_to_string("/proc/sys/fs/nr_open")
        .ok()
        .and_then(|s| s.trim().parse::<u64>().ok())
        .unwrap_or(1 << 20)
        .min(1 << 20);
    if lim.rlim_max < nr_open {
        let want = libc::rlimit {
            rlim_cur: nr_open,
            rlim_max: nr_open,
        };
        // SAFETY: a valid in-pointer; the kernel refuses a raise without the privilege.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &want) } == 0 {
            return Ok(nr_open);
        }
    }
    if lim.rlim_cur < lim.rlim_max {
        lim.rlim_cur = lim.rlim_max;
        // SAFETY: valid in-pointer.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &lim) } != 0 {
            return Err(io::Error::last_os_error());
        }
    }
    Ok(lim.rlim_cur)
}

/// This process's open file descriptors, counted every `every` by a thread of its own
/// (reading `/proc/self/fd`, which takes milliseconds at tens of thousands: off the
/// event loop). The count is `None` until first taken, and stays `None` if it cannot be.
///
/// A count that finds no descriptor free to count with (`EMFILE`) reads as the limit
/// ([`FdGauge::open`], for a caller sizing what it holds), but is kept apart in its
/// [`FdGauge::seen`]: the most actually counted, and how many counts found none free.
pub struct FdGauge {
    shared: std::sync::Arc<GaugeShared>,
}

#[derive(Default)]
struct GaugeShared {
    /// The last count, `u64::MAX` before the first.
    open: std::sync::atomic::AtomicU64,
    /// The most descriptors counted (counts at the limit aside).
    most: std::sync::atomic::AtomicU64,
    /// Counts taken, and those that found every descriptor open.
    counts: std::sync::atomic::AtomicU64,
    at_limit: std::sync::atomic::AtomicU64,
}

/// What an [`FdGauge`] saw since it started.
#[derive(Clone, Copy, Debug, Default)]
pub struct FdSeen {
    /// The most descriptors open at a count that could count them.
    pub most_counted: u64,
    /// Counts taken.
    pub counts: u64,
    /// Counts that found no descriptor free (`EMFILE`): the process was at its limit.
    pub at_limit: u64,
}

impl FdGauge {
    /// Starts counting, every `every` or a hundred times as long as a count took,
    /// whichever is longer (at most 1 % of a core: a count of 19,000 takes about 20–30
    /// ms); the thread ends with the process.
    pub fn start(every: Duration) -> io::Result<FdGauge> {
        use std::sync::atomic::Ordering::Relaxed;
        let shared = std::sync::Arc::new(GaugeShared {
            open: std::sync::atomic::AtomicU64::new(u64::MAX),
            ..GaugeShared::default()
        });
        let out = shared.clone();
        std::thread::Builder::new()
            .name("fd-gauge".into())
            .spawn(move || loop {
                let started = std::time::Instant::now();
                let n = std::fs::read_dir("/proc/self/fd").map(|d| d.count() as u64);
                let took = started.elapsed();
                let n = match n {
                    // The directory's own descriptor, open while it is read, is not counted.
                    Ok(n) => {
                        let n = n.saturating_sub(1);
                        out.most.fetch_max(n, Relaxed);
                        n
                    }
                    // Not one descriptor left to count them with: all are open.
                    Err(e) if is_out_of_descriptors(&e) => {
                        out.at_limit.fetch_add(1, Relaxed);
                        fd_limit()
                    }
                    Err(_) => return,
                };
                out.counts.fetch_add(1, Relaxed);
                out.open.store(n, Relaxed);
                std::thread::sleep(every.max(took.saturating_mul(100)));
            })?;
        Ok(FdGauge { shared })
    }

    /// Descriptors open at the last count (the limit if it found none free).
    pub fn open(&self) -> Option<u64> {
        match self.shared.open.load(std::sync::atomic::Ordering::Relaxed) {
            u64::MAX => None,
            n => Some(n),
        }
    }

    /// What the counts saw so far.
    pub fn seen(&self) -> FdSeen {
        use std::sync::atomic::Ordering::Relaxed;
        FdSeen {
            most_counted: self.shared.most.load(Relaxed),
            counts: self.shared.counts.load(Relaxed),
            at_limit: self.shared.at_limit.load(Relaxed),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_short_wait_ends_on_the_reactors_own_timer_which_never_wakes_a_later_wait() {
        use std::time::Instant;
        let mut r = Reactor::new().unwrap();
        let bell = eventfd().unwrap();
        r.add(bell.as_raw_fd(), 7).unwrap();
        // The timer's token is refused to a caller; `usize::MAX` (a token some take for
        // their signals) is theirs, and rung during a short wait it comes back.
        let e = r.add(bell.as_raw_fd(), TIMER_TOKEN).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{e}");
        let signal = eventfd().unwrap();
        r.add(signal.as_raw_fd(), usize::MAX).unwrap();
        ring_eventfd(&signal);
        assert_eq!(
            r.wait(Some(Duration::from_micros(300))).unwrap(),
            vec![usize::MAX]
        );
        drain_eventfd(&signal);
        // Nothing ready: a wait lasts at least what it was asked, and the timer's own
        // token is never handed out.
        let waits_out = |r: &mut Reactor, d: Duration| {
            let t = Instant::now();
            assert_eq!(r.wait(Some(d)).unwrap(), Vec::<usize>::new());
            assert!(t.elapsed() >= d, "{:?} of {d:?}", t.elapsed());
        };
        // The bell rung: a wait of `d` ends at once, under the bell's token (leaving the
        // timer armed, for a short one).
        let cut_short = |r: &mut Reactor, d: Duration| {
            ring_eventfd(&bell);
            assert_eq!(r.wait(Some(d)).unwrap(), vec![7]);
            drain_eventfd(&bell);
        };
        for _ in 0..20 {
            waits_out(&mut r, Duration::from_micros(300));
        }
        cut_short(&mut r, Duration::from_micros(300));
        // A longer wait after one cut short is not ended by the timer left armed.
        cut_short(&mut r, Duration::from_micros(2_500));
        waits_out(&mut r, Duration::from_millis(30));
        // Nor is a wait for ever: the bell, rung 20 ms on, is what ends it.
        cut_short(&mut r, Duration::from_micros(700));
        let ringer = std::thread::spawn({
            let bell = bell.try_clone().unwrap();
            move || {
                std::thread::sleep(Duration::from_millis(20));
                ring_eventfd(&bell);
            }
        });
        let t = Instant::now();
        assert_eq!(r.wait(None).unwrap(), vec![7]);
        assert!(
            t.elapsed() >= Duration::from_millis(20),
            "{:?}",
            t.elapsed()
        );
        ringer.join().unwrap();
    }

    #[test]
    fn the_gauge_counts_descriptors_as_they_open_and_close() {
        let gauge = FdGauge::start(Duration::from_millis(5)).unwrap();
        let wait_for = |want: &dyn Fn(u64) -> bool| {
            let until = std::time::Instant::now() + Duration::from_secs(5);
            loop {
                match gauge.open() {
                    Some(n) if want(n) => return n,
                    _ if std::time::Instant::now() > until => panic!("{:?}", gauge.open()),
                    _ => std::thread::sleep(Duration::from_millis(5)),
                }
            }
        };
        let before = wait_for(&|n| n > 0);
        // Other tests open and close descriptors meanwhile: look for a jump of 200.
        let files: Vec<std::fs::File> = (0..200)
            .map(|_| std::fs::File::open("/dev/null").unwrap())
            .collect();
        wait_for(&|n| n >= before + 150);
        drop(files);
        wait_for(&|n| n < before + 100);
        // The most it counted holds the 200, and none of its counts found the limit.
        let seen = gauge.seen();
        assert!(seen.most_counted >= before + 150, "{seen:?}");
        assert!(seen.counts >= 3, "{seen:?}");
        assert_eq!(seen.at_limit, 0, "{seen:?}");
    }

    #[test]
    fn a_threads_niceness_is_set_and_its_new_threads_take_it() {
        let nice_now = || {
            // SAFETY: getpriority(2) on the calling thread.
            unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
        };
        let (own, child) = std::thread::spawn(move || {
            set_nice(7).unwrap();
            let child = std::thread::spawn(nice_now).join().unwrap();
            (nice_now(), child)
        })
        .join()
        .unwrap();
        assert_eq!((own, child), (7, 7));
        assert_ne!(nice_now(), 7, "other threads keep theirs");
        let e = set_nice(20).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{e}");
        assert!(e.to_string().contains("-20..=19"), "{e}");
    }

    #[test]
    fn a_thread_yielding_for_exit_runs_only_when_nothing_else_would_and_alone() {
        // SAFETY: sched_getscheduler(2) and getpriority(2) on the calling thread.
        let class = || unsafe {
            (
                libc::sched_getscheduler(0),
                libc::getpriority(libc::PRIO_PROCESS, 0),
            )
        };
        let before = class();
        let yielded = std::thread::spawn(move || {
            yield_for_exit();
            class()
        })
        .join()
        .unwrap();
        // SCHED_IDLE, or niceness 19 where a kernel refuses it.
        assert!(
            yielded.0 == libc::SCHED_IDLE || yielded.1 == 19,
            "{yielded:?}"
        );
        assert_eq!(class(), before, "other threads keep their class");
    }

    #[test]
    fn a_stopped_process_is_told_from_a_running_one() {
        let mut child = std::process::Command::new("sleep")
            .arg("5")
            .spawn()
            .unwrap();
        let pid = child.id();
        assert!(!process_stopped(pid));
        // SAFETY: signals to our own child, not yet reaped.
        unsafe { libc::kill(pid as i32, libc::SIGSTOP) };
        let until = std::time::Instant::now() + Duration::from_secs(5);
        while !process_stopped(pid) && std::time::Instant::now() < until {
            std::thread::sleep(Duration::from_millis(1));
        }
        assert!(process_stopped(pid));
        assert!(process_alive(pid), "stopped is not dead");
        child.kill().unwrap();
        child.wait().unwrap();
        assert!(!process_stopped(pid));
    }

    #[test]
    fn pidfd_sees_child_exit() {
        let mut child = std::process::Command::new("sleep")
            .arg("5")
            .spawn()
            .unwrap();
        let pfd = PidFd::open(child.id()).unwrap();
        assert!(!pfd.exited());
        let mut r = Reactor::new().unwrap();
        r.add(pfd.raw(), 7).unwrap();
        assert!(r.wait(Some(Duration::from_millis(10))).unwrap().is_empty());
        child.kill().unwrap();
        let tokens = r.wait(Some(Duration::from_secs(5))).unwrap();
        assert_eq!(tokens, vec![7]);
        assert!(pfd.exited());
        child.wait().unwrap();
        assert!(PidFd::open(u32::MAX).is_err());
    }
}
