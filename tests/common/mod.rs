//! Helpers for tests that run real `muster` processes: a unique instance per test,
//! bounded waits, and only our own children killed (by PID) when the test ends.

#![allow(dead_code)]

use serde_json::Value;
use std::collections::BTreeSet;
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::sync::Mutex;
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_muster");

/// One child process with its stdout as lines.
pub struct Proc {
    pub child: Child,
    pub lines: Receiver<String>,
    pub stdin: Option<ChildStdin>,
}

impl Proc {
    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// The next stdout line, or `None` at the deadline or end of output.
    pub fn line(&self, timeout: Duration) -> Option<String> {
        self.lines.recv_timeout(timeout).ok()
    }

    /// The next stdout line as JSON.
    pub fn json(&self, timeout: Duration) -> Option<Value> {
        let l = self.line(timeout)?;
        Some(serde_json::from_str(&l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
    }

    /// Every JSON line until the output ends (bounded by `timeout`).
    pub fn all_json(&self, timeout: Duration) -> Vec<Value> {
        let deadline = Instant::now() + timeout;
        let mut out = Vec::new();
        while let Some(v) = self.json(deadline.saturating_duration_since(Instant::now())) {
            out.push(v);
        }
        out
    }

    /// Every remaining stdout line until the output ends (bounded by `timeout`).
    pub fn rest_lines(&self, timeout: Duration) -> Vec<String> {
        let deadline = Instant::now() + timeout;
        std::iter::from_fn(|| self.line(deadline.saturating_duration_since(Instant::now())))
            .collect()
    }

    /// Writes one control line to the child's stdin.
    pub fn send(&mut self, line: &str) {
        let stdin = self.stdin.as_mut().expect("stdin piped");
        writeln!(stdin, "{line}").expect("write control line");
        stdin.flush().expect("flush");
    }

    pub fn signal(&self, sig: i32) {
        // SAFETY: signalling our own child, not yet reaped.
        unsafe { libc::kill(self.pid(), sig) };
    }

    /// Waits for exit up to `timeout`; the exit code, or `None` if still running.
    pub fn wait(&mut self, timeout: Duration) -> Option<i32> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Ok(Some(status)) = self.child.try_wait() {
                return Some(status.code().unwrap_or(-1));
            }
            if Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

/// A federation of processes on one instance, torn down on drop.
pub struct Fed {
    pub inst: String,
    procs: Vec<Proc>,
}

impl Fed {
    /// A fresh instance named after the test.
    pub fn new(name: &str) -> Self {
        let mut inst = format!("{}-{}", name, std::process::id());
        inst.truncate(32);
        Fed {
            inst,
            procs: Vec::new(),
        }
    }

    pub fn command(&self, args: &[&str]) -> Command {
        let mut c = Command::new(BIN);
        c.arg("--instance").arg(&self.inst).args(args).env(
            "RUST_LOG",
            std::env::var("MUSTER_TEST_LOG").unwrap_or_else(|_| "warn".into()),
        );
        c
    }

    /// Starts a long-running process; returns its index.
    pub fn spawn(&mut self, args: &[&str]) -> usize {
        let c = self.command(args);
        self.spawn_command(c)
    }

    /// Starts any long-running program (a test's rclpy node), torn down with the rest.
    pub fn spawn_command(&mut self, mut c: Command) -> usize {
        let mut child = c
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn");
        let stdout = child.stdout.take().expect("stdout");
        let stdin = child.stdin.take();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        self.procs.push(Proc {
            child,
            lines,
            stdin,
        });
        self.procs.len() - 1
    }

    pub fn proc(&mut self, i: usize) -> &mut Proc {
        &mut self.procs[i]
    }

    pub fn broker(&mut self, extra: &[&str]) -> usize {
        let mut args = vec!["broker"];
        args.extend_from_slice(extra);
        self.spawn(&args)
    }

    /// `muster system synthetic --name NAME` plus `extra`.
    pub fn system(&mut self, name: &str, extra: &[&str]) -> usize {
        let mut args = vec!["system", "synthetic", "--name", name];
        args.extend_from_slice(extra);
        self.spawn(&args)
    }

    /// Runs a command to completion (bounded); returns exit code and stdout. Its
    /// stderr goes into the test's own output (shown when the test fails).
    pub fn run(&self, args: &[&str], timeout: Duration) -> (i32, String) {
        let (code, out, err) = self.run_full(args, timeout);
        if !err.is_empty() {
            eprint!("`muster {}` said on stderr:\n{err}", args.join(" "));
        }
        (code, out)
    }

    /// [`Fed::run`], returning exit code, stdout and stderr.
    pub fn run_full(&self, args: &[&str], timeout: Duration) -> (i32, String, String) {
        let child = self
            .command(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn muster");
        let pid = child.id() as i32;
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(child.wait_with_output());
        });
        match rx.recv_timeout(timeout) {
            Ok(out) => {
                let out = out.expect("output");
                (
                    out.status.code().unwrap_or(-1),
                    String::from_utf8_lossy(&out.stdout).into(),
                    String::from_utf8_lossy(&out.stderr).into(),
                )
            }
            Err(_) => {
                // SAFETY: kill(2) on the child we started (not yet reaped: the waiting
                // thread has not returned).
                unsafe { libc::kill(pid, libc::SIGKILL) };
                let said = match rx.recv_timeout(Duration::from_secs(5)) {
                    Ok(Ok(out)) => format!(
                        "; its stdout:\n{}\nits stderr:\n{}",
                        String::from_utf8_lossy(&out.stdout),
                        String::from_utf8_lossy(&out.stderr)
                    ),
                    _ => String::new(),
                };
                panic!(
                    "`muster {}` did not finish within {timeout:?}{said}",
                    args.join(" ")
                );
            }
        }
    }

    /// The list, from `muster user list --json`.
    pub fn list(&self) -> Vec<Value> {
        let (code, out) = self.run(&["user", "list", "--json"], Duration::from_secs(20));
        assert_eq!(code, 0, "user list failed: {out}");
        serde_json::from_str::<Value>(&out)
            .expect("list JSON")
            .as_array()
            .expect("array")
            .clone()
    }

    /// Polls the list until `pred` holds; returns it and how long it took.
    pub fn wait_list(
        &self,
        timeout: Duration,
        pred: impl Fn(&[Value]) -> bool,
    ) -> (Vec<Value>, Duration) {
        let start = Instant::now();
        loop {
            let l = self.list();
            if pred(&l) {
                return (l, start.elapsed());
            }
            assert!(
                start.elapsed() < timeout,
                "list condition not met within {timeout:?}: {l:?}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Stops everything: SIGTERM, then SIGKILL after 5 s, then cleans up what dead
    /// processes left in shared memory.
    pub fn shutdown(&mut self) {
        for p in self.procs.iter().rev() {
            p.signal(libc::SIGTERM);
        }
        for p in self.procs.iter_mut().rev() {
            if p.wait(Duration::from_secs(5)).is_none() {
                let _ = p.child.kill();
                let _ = p.child.wait();
            }
        }
        self.procs.clear();
        cleanup_dead_nodes();
        // What `muster up` of this instance leaves in the temporary directory: its
        // picture where no `--picture` was given, and its keys' folder when it was
        // killed before it could remove it.
        let tmp = std::env::temp_dir();
        let _ = std::fs::remove_file(tmp.join(format!("muster-up-{}.png", self.inst)));
        let keys = format!("muster-up-{}-", self.inst);
        for e in std::fs::read_dir(&tmp).into_iter().flatten().flatten() {
            if e.file_name().to_string_lossy().starts_with(&keys) {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
}

impl Drop for Fed {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// Removes the iceoryx2 resources of dead processes (ours, SIGKILLed on purpose).
pub fn cleanup_dead_nodes() {
    muster_shared::ipc::cleanup_dead_nodes(None);
}

/// What process `pid`'s threads are doing, for a test's failure message: each
/// thread's id, state (R, S, D, ...) and kernel wait channel, as `[tid state wchan]`.
pub fn threads_of(pid: impl std::fmt::Display) -> String {
    let mut threads = String::new();
    if let Ok(dir) = std::fs::read_dir(format!("/proc/{pid}/task")) {
        for t in dir.flatten() {
            let p = t.path();
            let stat = std::fs::read_to_string(p.join("stat")).unwrap_or_default();
            let wchan = std::fs::read_to_string(p.join("wchan")).unwrap_or_default();
            // After the name: the state (R, S, D, ...), then utime and stime as fields
            // 12 and 13 (a thread that spins gains them between two looks).
            let fields: Vec<&str> = stat.rsplit(") ").next().unwrap_or("").split(' ').collect();
            let state = fields.first().and_then(|f| f.chars().next());
            let (user, sys) = (fields.get(11).copied(), fields.get(12).copied());
            threads += &format!(
                " [{:?} {state:?} {wchan} cpu ticks user {} sys {}]",
                t.file_name(),
                user.unwrap_or("?"),
                sys.unwrap_or("?")
            );
        }
    }
    // Where gdb is installed (CI installs it), each thread's stack too: a thread
    // running (R) with no wait channel is busy somewhere in user space.
    let gdb = std::process::Command::new("timeout")
        .args(["30", "gdb", "-p", &pid.to_string(), "-batch", "-nx"])
        .args(["-ex", "thread apply all bt 40"])
        .output();
    if let Ok(out) = gdb {
        let text = String::from_utf8_lossy(&out.stdout);
        let stacks: Vec<&str> = text
            .lines()
            .filter(|l| l.starts_with('#') || l.starts_with("Thread "))
            .collect();
        if !stacks.is_empty() {
            threads += &format!("\nits stacks (gdb):\n{}", stacks.join("\n"));
        }
    }
    threads
}

pub fn ids(list: &[Value]) -> Vec<String> {
    list.iter()
        .map(|v| v["id"].as_str().unwrap_or_default().to_string())
        .collect()
}

pub fn find<'a>(list: &'a [Value], id: &str) -> Option<&'a Value> {
    list.iter().find(|v| v["id"] == id)
}

pub const SEC: Duration = Duration::from_secs(1);

/// How a test's users reach the federation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Via {
    /// iceoryx2 shared memory.
    Shm,
    /// UDP to the broker's front, as remote user `alice` (allowed everything).
    Udp,
}

/// Keys and an access file for remote users of one federation.
pub struct RemoteSetup {
    pub dir: std::path::PathBuf,
    pub addr: String,
    pub access: std::path::PathBuf,
}

impl RemoteSetup {
    /// Path of a user's key file.
    pub fn key(&self, name: &str) -> String {
        self.dir.join(format!("{name}.key")).display().to_string()
    }
}

/// A port `bind` found free, never one this test process handed out before: the
/// kernel may give a port just released to the next bind, and two brokers of one
/// federation given the same port each found themselves there ("CONNECTION_TO_SELF").
fn fresh_port(bind: impl Fn() -> std::io::Result<u16>) -> u16 {
    static GIVEN: Mutex<BTreeSet<u16>> = Mutex::new(BTreeSet::new());
    for _ in 0..1000 {
        let port = bind().expect("a free port");
        if GIVEN.lock().unwrap().insert(port) {
            return port;
        }
    }
    panic!("no port this process has not handed out already, in 1000 binds")
}

/// A free loopback UDP port (bound and released; tests run on loopback only).
pub fn free_udp_port() -> u16 {
    fresh_port(|| {
        std::net::UdpSocket::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .map(|a| a.port())
    })
}

/// A free loopback TCP port (bound and released), as [`free_udp_port`].
pub fn free_tcp_port() -> u16 {
    fresh_port(|| {
        std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .map(|a| a.port())
    })
}

impl Fed {
    /// Makes keys for `users` (name, allow patterns) and an access file listing them.
    pub fn remote_setup(&self, users: &[(&str, &[&str])]) -> RemoteSetup {
        self.remote_setup_with(users, &[])
    }

    /// The same, plus `operators` (their names; `operator` lines allowing `*`).
    pub fn remote_setup_with(&self, users: &[(&str, &[&str])], operators: &[&str]) -> RemoteSetup {
        let dir = std::env::temp_dir().join(format!("muster-keys-{}", self.inst));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("key dir");
        let mut access = String::new();
        let all: &[&str] = &["*"];
        let everyone = users
            .iter()
            .map(|(n, a)| (*n, *a, false))
            .chain(operators.iter().map(|n| (*n, all, true)));
        for (name, allow, operator) in everyone {
            let mut args = vec!["keygen", "--user", name, "--out", dir.to_str().unwrap()];
            for a in allow {
                args.push("--allow");
                args.push(a);
            }
            if operator {
                args.push("--operator");
            }
            let (code, line) = self.run(&args, Duration::from_secs(20));
            assert_eq!(code, 0, "keygen failed");
            access.push_str(&line);
        }
        let path = dir.join("access");
        std::fs::write(&path, access).expect("access file");
        RemoteSetup {
            addr: format!("127.0.0.1:{}", free_udp_port()),
            dir,
            access: path,
        }
    }

    /// A broker with a UDP front for `r`.
    pub fn remote_broker(&mut self, r: &RemoteSetup) -> usize {
        let access = r.access.display().to_string();
        self.broker(&["--udp", &r.addr, "--access", &access])
    }

    /// The arguments of a user command over `via` (adds `--remote`/`--key alice`).
    pub fn user_args(via: Via, r: Option<&RemoteSetup>, args: &[&str]) -> Vec<String> {
        let mut v: Vec<String> = args.iter().map(|s| s.to_string()).collect();
        if via == Via::Udp {
            let r = r.expect("remote setup");
            v.extend([
                "--remote".into(),
                r.addr.clone(),
                "--key".into(),
                r.key("alice"),
            ]);
        }
        v
    }
}

impl Drop for RemoteSetup {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The Python interpreter with `module` (`.venv/bin/python`, which `.ci/run` sets up, or
/// `MUSTER_PYTHON`), or `None` with a message saying the test is skipped. With
/// `MUSTER_REQUIRE_PYTHON` set (as `.ci/run` does), a missing module fails instead.
pub fn python_with(module: &str, package: &str) -> Option<String> {
    let python = std::env::var("MUSTER_PYTHON")
        .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/.venv/bin/python").to_string());
    let has = std::process::Command::new(&python)
        .args(["-c", &format!("import {module}")])
        .status()
        .is_ok_and(|s| s.success());
    if !has {
        assert!(
            std::env::var_os("MUSTER_REQUIRE_PYTHON").is_none(),
            "{python} has no {module} module ({package}): run .ci/run's setup"
        );
        skip(&format!(
            "{python} has no {module} module (pip install {package})"
        ));
        return None;
    }
    Some(python)
}

/// The TCP addresses process `pid` listens on (its sockets in LISTEN state, from
/// `/proc`).
pub fn tcp_listening(pid: i32) -> Vec<std::net::SocketAddr> {
    let inodes: std::collections::HashSet<String> = std::fs::read_dir(format!("/proc/{pid}/fd"))
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| std::fs::read_link(e.path()).ok())
        .filter_map(|l| {
            let l = l.to_string_lossy().to_string();
            Some(l.strip_prefix("socket:[")?.strip_suffix(']')?.to_string())
        })
        .collect();
    let mut out = Vec::new();
    for table in ["tcp", "tcp6"] {
        let text = std::fs::read_to_string(format!("/proc/{pid}/net/{table}")).unwrap_or_default();
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() < 10 || f[3] != "0A" || !inodes.contains(f[9]) {
                continue;
            }
            let Some((ip, port)) = f[1].split_once(':') else {
                continue;
            };
            let port = u16::from_str_radix(port, 16).unwrap_or(0);
            // Each 32-bit word of the address is in host (little-endian) order.
            let words: Vec<u32> = (0..ip.len() / 8)
                .filter_map(|k| u32::from_str_radix(&ip[k * 8..k * 8 + 8], 16).ok())
                .map(u32::swap_bytes)
                .collect();
            let ip: std::net::IpAddr = match words.as_slice() {
                [a] => std::net::Ipv4Addr::from(*a).into(),
                [a, b, c, d] => {
                    let mut bytes = [0u8; 16];
                    for (k, w) in [a, b, c, d].iter().enumerate() {
                        bytes[k * 4..k * 4 + 4].copy_from_slice(&w.to_be_bytes());
                    }
                    std::net::Ipv6Addr::from(bytes).into()
                }
                _ => continue,
            };
            out.push(std::net::SocketAddr::new(ip, port));
        }
    }
    out
}

/// Says a test is skipped (an outside client is not set up), on the test run's own
/// output: straight to stderr, not through the test harness's capture, so that the
/// run shows it even when the test passes. `bash scripts/test` sets everything up.
pub fn skip(why: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "SKIPPED: {why}");
}

/// One HTTP/1.1 request (`request_line`: `GET / HTTP/1.1`) on a fresh connection to
/// `addr`; the whole answer as text.
#[allow(dead_code)]
pub fn http(addr: &str, request_line: &str, headers: &[(&str, &str)], body: &str) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(10)))
        .expect("timeout");
    let mut req = format!(
        "{request_line}\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    req.push_str(body);
    s.write_all(req.as_bytes()).expect("send");
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    String::from_utf8_lossy(&raw).to_string()
}
