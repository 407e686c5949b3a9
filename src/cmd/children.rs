//! Child `muster` processes started by a command, stopped by PID.

use anyhow::{bail, Context};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Makes the process `cmd` starts get SIGTERM when this one dies, however it dies (a
/// SIGKILLed `muster up` leaves no simulator, systems or standby running; they stop as
/// on Ctrl-C). If this process is already gone when the child starts, the child stops
/// at once.
pub fn die_with_parent(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id();
    // SAFETY: between fork and exec, only async-signal-safe calls: prctl, getppid and
    // raise, and an io::Error made from the errno on failure.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            if u32::try_from(libc::getppid()).ok() != Some(parent) {
                libc::raise(libc::SIGTERM);
            }
            Ok(())
        });
    }
}

/// The children we started; stopped (SIGTERM, then SIGKILL) on drop.
#[derive(Default)]
pub struct Children(Vec<(String, Instance, Child)>);

impl Children {
    /// Starts `muster --instance INST ARGS...`.
    pub fn spawn(
        &mut self,
        inst: &Instance,
        label: &str,
        args: &[&str],
        stdout: Stdio,
    ) -> anyhow::Result<&mut Child> {
        self.spawn_with(inst, label, args, stdout, Stdio::inherit())
    }

    /// [`Children::spawn`] with the child's standard error set too.
    pub fn spawn_with(
        &mut self,
        inst: &Instance,
        label: &str,
        args: &[&str],
        stdout: Stdio,
        stderr: Stdio,
    ) -> anyhow::Result<&mut Child> {
        self.spawn_io(inst, label, args, [Stdio::null(), stdout, stderr])
    }

    /// [`Children::spawn`] with the child's standard input, output and error.
    pub fn spawn_io(
        &mut self,
        inst: &Instance,
        label: &str,
        args: &[&str],
        [stdin, stdout, stderr]: [Stdio; 3],
    ) -> anyhow::Result<&mut Child> {
        let exe = std::env::current_exe().context("locating the muster binary")?;
        let mut cmd = Command::new(exe);
        die_with_parent(&mut cmd);
        let child = cmd
            .arg("--instance")
            .arg(inst.as_str())
            .arg("--time-scale")
            .arg(muster_shared::clock::global().to_string())
            .args(args)
            .stdin(stdin)
            .stdout(stdout)
            .stderr(stderr)
            .spawn()
            .with_context(|| format!("starting {label}"))?;
        self.0.push((label.to_string(), inst.clone(), child));
        Ok(&mut self.0.last_mut().expect("pushed").2)
    }

    /// The child labelled `label`, if we started it and have not stopped it.
    pub fn child_mut(&mut self, label: &str) -> Option<&mut Child> {
        self.0
            .iter_mut()
            .find(|(l, _, _)| l == label)
            .map(|(_, _, c)| c)
    }

    /// SIGKILLs the child labelled `label` (one we started) and reaps it.
    pub fn kill(&mut self, label: &str) {
        if let Some(i) = self.0.iter().position(|(l, _, _)| l == label) {
            let (_, _, mut c) = self.0.remove(i);
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERMs the child labelled `label` and waits for it (up to 5 s, then SIGKILL).
    pub fn stop_one(&mut self, label: &str) {
        let Some(i) = self.0.iter().position(|(l, _, _)| l == label) else {
            return;
        };
        let (label, inst, mut c) = self.0.remove(i);
        if let Ok(pid) = libc::pid_t::try_from(c.id()) {
            // SAFETY: signalling a child we spawned and have not reaped.
            unsafe { libc::kill(pid, libc::SIGTERM) };
        }
        if !exits_by(&label, &mut c, Instant::now() + Duration::from_secs(5)) {
            clean_after_killed(&[inst]);
        }
    }

    /// SIGKILLs every child we started and reaps them.
    pub fn kill_all(&mut self) {
        for (_, _, mut c) in self.0.drain(..) {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// The children labelled `label` that have exited since the last look, reaped and
    /// forgotten: their process ids.
    pub fn exited(&mut self, label: &str) -> Vec<u32> {
        let mut gone = Vec::new();
        self.0.retain_mut(|(l, _, c)| {
            if l != label || !matches!(c.try_wait(), Ok(Some(_))) {
                return true;
            }
            gone.push(c.id());
            false
        });
        gone
    }

    /// Process ids, in start order.
    pub fn pids(&self) -> impl Iterator<Item = u32> + '_ {
        self.0.iter().map(|(_, _, c)| c.id())
    }

    /// SIGTERM every child we started (by PID, last first), wait up to 5 s, then SIGKILL.
    pub fn stop(&mut self) {
        for (_, _, c) in self.0.iter().rev() {
            if let Ok(pid) = libc::pid_t::try_from(c.id()) {
                // SAFETY: signalling a child we spawned and have not reaped.
                unsafe { libc::kill(pid, libc::SIGTERM) };
            }
        }
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut killed = Vec::new();
        for (label, inst, c) in self.0.iter_mut().rev() {
            if !exits_by(label, c, deadline) {
                killed.push(inst.clone());
            }
        }
        self.0.clear();
        clean_after_killed(&killed);
    }
}

/// Waits until `deadline` for the signalled child `c` to exit; SIGKILLs and reaps it
/// if it has not (saying so). Whether it exited by itself.
fn exits_by(label: &str, c: &mut Child, deadline: Instant) -> bool {
    loop {
        match c.try_wait() {
            Ok(Some(_)) => return true,
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(5)),
            _ => {
                eprintln!("muster: {label} did not stop; killing it");
                let _ = c.kill();
                let _ = c.wait();
                return false;
            }
        }
    }
}

/// Removes what children SIGKILLed because they did not stop left in shared memory:
/// their iceoryx2 nodes, and the fence of an instance none of whose brokers is left (a
/// command leaves nothing of its children behind, however they ended).
fn clean_after_killed(insts: &[Instance]) {
    if insts.is_empty() {
        return;
    }
    muster_shared::ipc::cleanup_dead_nodes(None);
    for inst in insts {
        if muster_shared::ipc::live_brokers(inst) == 0 {
            muster_shared::fence::remove_if_orphaned(inst);
        }
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Connects a quiet client (no signal handling, no list watching) and waits until the
/// list holds at least `services` entries.
/// Requests `service` and waits up to `wait` for its grant; the session, or why not.
pub fn request_granted(
    client: &mut UserClient,
    service: &muster_shared::types::ServiceId,
    wait: Duration,
) -> anyhow::Result<muster_shared::types::SessionId> {
    let req = client.request(service)?;
    let deadline = Instant::now() + wait;
    loop {
        match client.next_event(deadline)? {
            Some(muster_users::UserEvent::Granted {
                req: r, session, ..
            }) if r == req => return Ok(session),
            Some(muster_users::UserEvent::Refused { req: r, reason, .. }) if r == req => {
                bail!("{service} refused: {reason}")
            }
            Some(_) => {}
            None => bail!("{service}: no answer within {wait:?}"),
        }
    }
}

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
    while client.list()?.count() < services {
        if Instant::now() > deadline {
            bail!("the systems did not register {services} services within {timeout:?}");
        }
        let _ = client.next_event(Instant::now() + Duration::from_millis(50))?;
    }
    Ok(client)
}

impl crate::cli::LoadArgs {
    /// Checks the sizes against muster's limits and raises the fd limit for them.
    pub fn check(&self, fds_per_user: u64) -> anyhow::Result<()> {
        self.check_for(fds_per_user, false)
    }

    /// [`LoadArgs::check`]; remote users hold no shared-memory ports, so the per-instance
    /// participant limit does not bound them (the UDP front's connection cap does).
    pub fn check_for(&self, fds_per_user: u64, remote: bool) -> anyhow::Result<()> {
        use muster_shared::ipc::MAX_PARTICIPANTS;
        use muster_shared::snapshot::DEFAULT_MAX_SERVICES;
        use muster_shared::types::MAX_SERVICES_PER_SYSTEM;
        if self.systems == 0 || self.services < self.systems {
            bail!("--services must be at least --systems (and --systems at least 1)");
        }
        if self.services > DEFAULT_MAX_SERVICES
            || self.services.div_ceil(self.systems) > MAX_SERVICES_PER_SYSTEM
        {
            bail!("at most {DEFAULT_MAX_SERVICES} services, {MAX_SERVICES_PER_SYSTEM} per system");
        }
        let cap = if remote {
            muster_broker::udp::DEFAULT_MAX_REMOTE_USERS
        } else {
            MAX_PARTICIPANTS - self.systems - 8
        };
        if self.users == 0 || self.users > cap {
            bail!("--users must be 1..={cap} with {} systems", self.systems);
        }
        let fds = muster_shared::reactor::raise_fd_limit()
            .context("raising the file-descriptor limit")?;
        if fds < self.users as u64 * fds_per_user + 64 {
            bail!(
                "file-descriptor limit {fds} is too low for {} users (raise `ulimit -Hn`)",
                self.users
            );
        }
        let broker_fds = muster_broker::run::FDS_PER_LOCAL_USER;
        let most = muster_broker::run::max_local_users(fds);
        if !remote && self.users as u64 > most {
            tracing::warn!(
                "the broker gets this limit ({fds} descriptors) and holds at least {broker_fds} per local user: \
                 beyond about {most} users, the next are refused (\"no broker\"); raising it needs \
                 root with CAP_SYS_RESOURCE (`ulimit -Hn`), or use remote users (--remote)"
            );
        }
        Ok(())
    }

    /// How many services system `i` offers, spreading them evenly.
    pub fn services_of(&self, i: usize) -> usize {
        self.services / self.systems + usize::from(i < self.services % self.systems)
    }
}

/// Hosts of a federation run on one machine: an instance per host (`INST-host`) and a
/// free loopback port per host for its broker's Zenoh.
pub struct LoopbackHosts {
    /// The hosts' names.
    pub names: Vec<String>,
    /// Their instances.
    pub insts: Vec<Instance>,
    /// Their brokers' Zenoh ports.
    pub ports: Vec<u16>,
    /// The federation's name (unique to this process).
    pub federation: String,
    /// How many of the hosts (the first ones) are Zenoh routers, the rest their clients
    /// (0: every host a peer, dialling the ones before it).
    pub routers: usize,
}

impl LoopbackHosts {
    /// Hosts `names` under `inst`, in a federation named `prefix` plus this process's id.
    pub fn new(inst: &Instance, names: &[&str], prefix: &str) -> anyhow::Result<Self> {
        let insts = names
            .iter()
            .map(|h| {
                let mut name = inst.as_str().to_string();
                name.truncate(30);
                Ok(Instance::new(&format!("{name}-{h}"))?)
            })
            .collect::<anyhow::Result<_>>()?;
        let ports = names
            .iter()
            .map(|_| free_tcp_port())
            .collect::<anyhow::Result<_>>()?;
        Ok(LoopbackHosts {
            names: names.iter().map(|n| n.to_string()).collect(),
            insts,
            ports,
            federation: format!("{prefix}{}", std::process::id()),
            routers: 0,
        })
    }

    /// `muster broker` arguments for host `i`: it listens on its port and connects to
    /// the hosts before it (each pair of hosts has one side that dials, which dials
    /// again when the link drops); `extra` is appended. Both sides dialling each other
    /// raced when one restarted: a refused handshake ("close ... in response to an
    /// OpenSyn") left the two apart for good, about one restart in 40.
    ///
    /// With [`LoopbackHosts::routers`], the first hosts are routers (each listening, and
    /// dialling the routers before it) and the rest clients, each dialling every router,
    /// its own share of them first.
    pub fn broker_args(&self, i: usize, extra: &[String]) -> Vec<String> {
        let mut args = self.federated(i);
        let r = self.routers;
        let dial: Vec<usize> = if r == 0 || i < r {
            (0..i).collect()
        } else {
            (0..r).map(|k| (i + k) % r).collect()
        };
        if r > 0 {
            args.push("--zenoh-mode".into());
            args.push(if i < r { "router" } else { "client" }.into());
        }
        if r == 0 || i < r {
            args.push("--listen".into());
            args.push(format!("tcp/127.0.0.1:{}", self.ports[i]));
        }
        for j in dial {
            args.push("--connect".into());
            args.push(format!("tcp/127.0.0.1:{}", self.ports[j]));
        }
        args.extend(extra.iter().cloned());
        args
    }

    /// `muster broker --federate --host HOST --federation NAME` for host `i`, without
    /// where it listens and connects. Without TLS (`--insecure-no-tls`): these hosts are
    /// on this machine, on loopback or in network namespaces their command made.
    pub fn federated(&self, i: usize) -> Vec<String> {
        [
            "broker",
            "--federate",
            "--insecure-no-tls",
            "--host",
            &self.names[i],
            "--federation",
            &self.federation,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    }

    /// Starts every host's broker (labelled `broker-HOST`), with `extra` arguments.
    pub fn spawn_brokers(
        &self,
        kids: &mut Children,
        extra: &[String],
        stdout: impl Fn() -> Stdio,
    ) -> anyhow::Result<()> {
        for (i, host) in self.names.iter().enumerate() {
            let args = self.broker_args(i, extra);
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            kids.spawn(&self.insts[i], &format!("broker-{host}"), &args, stdout())?;
        }
        Ok(())
    }
}

/// A free loopback TCP port (bound and released).
pub fn free_tcp_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// After a run's brokers have all stopped: removes the instance's fence if no live
/// broker holds it (the last of them, stopped while taking over, could not remove it),
/// so the run leaves nothing in shared memory.
pub fn leave_no_fence(inst: &Instance) {
    if muster_shared::fence::remove_if_orphaned(inst) {
        tracing::debug!(instance = %inst, "removed the fence no broker held");
    }
}
