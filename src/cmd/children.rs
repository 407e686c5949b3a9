//! Child `muster` processes started by a command, stopped by PID.

use anyhow::{bail, Context};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The children we started; stopped (SIGTERM, then SIGKILL) on drop.
#[derive(Default)]
pub struct Children(Vec<(String, Child)>);

impl Children {
    /// Starts `muster --instance INST ARGS...`.
    pub fn spawn(
        &mut self,
        inst: &Instance,
        label: &str,
        args: &[&str],
        stdout: Stdio,
    ) -> anyhow::Result<&mut Child> {
        let exe = std::env::current_exe().context("locating the muster binary")?;
        let child = Command::new(exe)
            .arg("--instance")
            .arg(inst.as_str())
            .args(args)
            .stdin(Stdio::null())
            .stdout(stdout)
            .spawn()
            .with_context(|| format!("starting {label}"))?;
        self.0.push((label.to_string(), child));
        Ok(&mut self.0.last_mut().expect("pushed").1)
    }

    /// SIGKILLs the child labelled `label` (one we started) and reaps it.
    pub fn kill(&mut self, label: &str) {
        if let Some(i) = self.0.iter().position(|(l, _)| l == label) {
            let (_, mut c) = self.0.remove(i);
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Process ids, in start order.
    pub fn pids(&self) -> impl Iterator<Item = u32> + '_ {
        self.0.iter().map(|(_, c)| c.id())
    }

    /// SIGTERM every child we started (by PID, last first), wait up to 5 s, then SIGKILL.
    pub fn stop(&mut self) {
        for (_, c) in self.0.iter().rev() {
            if let Ok(pid) = libc::pid_t::try_from(c.id()) {
                // SAFETY: signalling a child we spawned and have not reaped.
                unsafe { libc::kill(pid, libc::SIGTERM) };
            }
        }
        let deadline = Instant::now() + Duration::from_secs(5);
        for (label, c) in self.0.iter_mut().rev() {
            loop {
                match c.try_wait() {
                    Ok(Some(_)) => break,
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(5))
                    }
                    _ => {
                        eprintln!("muster: {label} did not stop; killing it");
                        let _ = c.kill();
                        let _ = c.wait();
                        break;
                    }
                }
            }
        }
        self.0.clear();
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Connects a quiet client (no signal handling, no list watching) and waits until the
/// list holds at least `services` entries.
pub fn connect_when_listed(
    inst: &Instance,
    services: usize,
    timeout: Duration,
) -> anyhow::Result<UserClient> {
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(20),
        handle_signals: false,
        watch_list: false,
    };
    let mut client = UserClient::connect(inst, &opts)?;
    let deadline = Instant::now() + timeout;
    while (client.list()?.count as usize) < services {
        if Instant::now() > deadline {
            bail!("the systems did not register {services} services within {timeout:?}");
        }
        let _ = client.next_event(Instant::now() + Duration::from_millis(50))?;
    }
    Ok(client)
}
