//! Cleaning up after dead peers beside serving, in a `muster cleanup` process of its
//! own.

#[allow(unused_imports)]
use super::*;

/// The program whose `cleanup` subcommand cleans up after dead processes (see
/// [`set_cleanup_program`]).
static CLEANUP_PROGRAM: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();

/// Names the program (the muster binary) whose `--instance I cleanup [--pid P] --after
/// D` a broker runs to clean up after dead processes. Without it (a broker embedded in
/// another program) cleanups run in a thread of the broker, which a kill can leave
/// half-done.
pub fn set_cleanup_program(exe: PathBuf) {
    let _ = CLEANUP_PROGRAM.set(exe);
}

/// Cleans up after dead processes (those of `pid` first, once it has exited, then all)
/// after `delay`, beside serving. In a process of its own where
/// [`set_cleanup_program`] named one: iceoryx2 never cleans a node whose cleaner died
/// mid-way, and a broker can be killed at any moment.
pub(super) fn cleaner(
    inst: &Instance,
    pid: Option<u32>,
    delay: Duration,
) -> std::thread::JoinHandle<usize> {
    let mut cmd = CLEANUP_PROGRAM.get().map(|exe| {
        let mut c = std::process::Command::new(exe);
        c.args([
            "--instance",
            inst.as_str(),
            "cleanup",
            "--beside-broker",
            "--after",
        ])
        .arg(format!("{}ms", delay.as_millis()))
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null());
        if let Some(pid) = pid {
            c.arg("--pid").arg(pid.to_string());
        }
        c
    });
    std::thread::spawn(move || {
        if let Some(child) = cmd.as_mut().and_then(|c| c.spawn().ok()) {
            let mut child = child;
            let _ = child.wait();
            return 0;
        }
        std::thread::sleep(delay);
        muster_shared::ipc::cleanup_after(pid)
    })
}

/// Cleanups after dead peers while serving: one `muster cleanup` at a time (never in
/// the broker's own process, which may be killed mid-way), and one more owed when
/// deaths come while it runs.
pub(super) struct Cleanups {
    pub(super) inst: Instance,
    pub(super) running: Option<std::thread::JoinHandle<usize>>,
    pub(super) owed: bool,
}

impl Cleanups {
    pub(super) fn new(inst: &Instance, first: Option<std::thread::JoinHandle<usize>>) -> Self {
        Cleanups {
            inst: inst.clone(),
            running: first,
            owed: false,
        }
    }

    /// Someone died: clean up after it now, or after the cleanup under way.
    pub(super) fn request(&mut self) {
        self.owed = true;
        self.poll();
    }

    /// Starts the owed cleanup once the one under way has ended.
    pub(super) fn poll(&mut self) {
        if self.running.as_ref().is_some_and(|h| !h.is_finished()) || !self.owed {
            return;
        }
        self.owed = false;
        self.running = Some(cleaner(&self.inst, None, Duration::ZERO));
    }
}

impl Drop for Cleanups {
    /// A broker leaving lets its cleanups end, and does the one owed: nobody else
    /// would clean up after the peers that died last.
    fn drop(&mut self) {
        if let Some(h) = self.running.take() {
            let _ = h.join();
        }
        if self.owed {
            let _ = cleaner(&self.inst, None, Duration::ZERO).join();
        }
    }
}
