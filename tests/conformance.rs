//! One protocol, two transports: the same scenarios, run by users over shared memory
//! and by remote users over UDP (authenticated, through the broker's front and the
//! systems' own endpoints).

#![allow(clippy::unwrap_used)]

mod common;

use common::{find, Fed, RemoteSetup, Via, SEC};
use serde_json::Value;
use std::time::Duration;

/// A federation whose broker and systems serve both kinds of user.
struct Conf {
    f: Fed,
    r: RemoteSetup,
    via: Via,
    broker: usize,
}

impl Conf {
    fn new(name: &str, via: Via) -> Self {
        let tag = match via {
            Via::Shm => "s",
            Via::Udp => "u",
        };
        let f = Fed::new(&format!("cf{tag}-{name}"));
        let r = f.remote_setup(&[("alice", &["*"])]);
        let mut c = Conf {
            f,
            r,
            via,
            broker: 0,
        };
        c.broker = c.f.remote_broker(&c.r);
        c
    }

    fn system(&mut self, name: &str, extra: &[&str]) -> usize {
        let mut args = vec!["--udp", "127.0.0.1:0"];
        args.extend_from_slice(extra);
        self.f.system(name, &args)
    }

    fn args(&self, args: &[&str]) -> Vec<String> {
        Fed::user_args(self.via, Some(&self.r), args)
    }

    fn run_raw(&self, args: &[&str]) -> (i32, String) {
        let a = self.args(args);
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        self.f.run(&a, 30 * SEC)
    }

    fn run(&self, args: &[&str]) -> (i32, Vec<Value>) {
        let (code, out) = self.run_raw(args);
        let lines = out
            .lines()
            .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
            .collect();
        (code, lines)
    }

    fn spawn(&mut self, args: &[&str]) -> usize {
        let a = self.args(args);
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        self.f.spawn(&a)
    }

    /// The list as this transport's user sees it.
    fn list(&self) -> Vec<Value> {
        let (code, out) = self.run_raw(&["user", "list", "--json"]);
        assert_eq!(code, 0, "{out}");
        serde_json::from_str::<Value>(&out)
            .unwrap()
            .as_array()
            .unwrap()
            .clone()
    }

    fn wait_list(&self, pred: impl Fn(&[Value]) -> bool) -> Vec<Value> {
        let deadline = std::time::Instant::now() + 15 * SEC;
        loop {
            let l = self.list();
            if pred(&l) {
                return l;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "list condition not met: {l:?}"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

fn seqs(lines: &[Value]) -> Vec<u64> {
    lines.iter().filter_map(|v| v["seq"].as_u64()).collect()
}

macro_rules! both {
    ($name:ident) => {
        mod $name {
            use super::*;
            #[test]
            fn shm() {
                super::$name(Via::Shm);
            }
            #[test]
            fn udp() {
                super::$name(Via::Udp);
            }
        }
    };
}

fn lists_every_service_with_its_fields(via: Via) {
    let mut c = Conf::new("list", via);
    c.system("t1", &["--services", "2"]);
    c.system("d1", &["--kind", "command", "--quota", "1", "--queue"]);
    let l = c.wait_list(|l| l.len() == 3);
    let d = find(&l, "d1/s0").unwrap();
    assert_eq!(
        (
            d["kind"].as_str(),
            d["quota"].as_u64(),
            d["queue"].as_bool()
        ),
        (Some("command"), Some(1), Some(true))
    );
    assert_eq!(find(&l, "t1/s1").unwrap()["payload"], "pose2d");
}
both!(lists_every_service_with_its_fields);

fn refusals_name_their_reason(via: Via) {
    let mut c = Conf::new("refuse", via);
    c.system("t1", &["--quota", "1"]);
    c.wait_list(|l| l.len() == 1);
    let (code, lines) = c.run(&["user", "request", "nosuch/s0", "--json"]);
    assert_eq!((code, lines[0]["code"].as_str()), (3, Some("unknown")));
    let holder = c.spawn(&["user", "request", "t1/s0", "--duration", "10s", "--json"]);
    assert_eq!(c.f.proc(holder).json(15 * SEC).unwrap()["granted"], true);
    let (code, lines) = c.run(&["user", "request", "t1/s0", "--json"]);
    assert_eq!((code, lines[0]["code"].as_str()), (3, Some("quota_full")));
}
both!(refusals_name_their_reason);

fn a_data_session_streams_in_order_and_frees_its_quota(via: Via) {
    let mut c = Conf::new("data", via);
    c.system("t1", &["--rate", "20", "--quota", "1"]);
    c.wait_list(|l| l.len() == 1);
    let (code, lines) = c.run(&["user", "request", "t1/s0", "--duration", "2s", "--json"]);
    assert_eq!(code, 0);
    assert_eq!(lines[0]["granted"], true);
    let s = seqs(&lines);
    assert_eq!(s[0], 1, "the first update is not lost");
    assert!(
        s.len() >= 20,
        "about 40 updates at 20 Hz over 2 s, got {}",
        s.len()
    );
    assert!(s.windows(2).all(|w| w[1] == w[0] + 1), "in order, no gaps");
    let last = lines.last().unwrap();
    assert_eq!(
        (last["reason"].as_str(), last["gaps"].as_u64()),
        (Some("duration over"), Some(0))
    );
    // The quota is free again: a second user gets the service.
    c.wait_list(|l| l[0]["in_use"] == 0);
    let (code, _) = c.run(&["user", "request", "t1/s0", "--duration", "200ms", "--json"]);
    assert_eq!(code, 0);
}
both!(a_data_session_streams_in_order_and_frees_its_quota);

fn a_latched_service_gives_a_new_session_its_newest_value_with_the_grant(via: Via) {
    let mut c = Conf::new("latched", via);
    c.system("t1", &["--rate", "5", "--latched"]);
    c.system("t2", &["--rate", "5"]);
    c.wait_list(|l| l.len() == 2);
    // t1 updates with nobody in a session: the broker keeps its newest value. (Half a
    // second is two updates at 5 Hz; the first session's update 0 is asserted below.)
    std::thread::sleep(Duration::from_millis(500));
    let (code, lines) = c.run(&["user", "request", "t1/s0", "--duration", "1s", "--json"]);
    assert_eq!(
        (code, &lines[0]["granted"]),
        (0, &Value::Bool(true)),
        "{lines:?}"
    );
    // Update 0, from the broker with the grant (through its UDP front for a remote
    // user), then the system's stream from 1, nothing counted lost.
    let s = seqs(&lines);
    assert_eq!(
        lines[1]["seq"], 0,
        "update 0 right behind the grant: {lines:?}"
    );
    assert_eq!(lines[1]["payload"]["type"], "pose2d");
    assert_eq!(&s[..2], &[0, 1], "{s:?}");
    assert!(s.windows(2).all(|w| w[1] == w[0] + 1), "in order: {s:?}");
    let last = lines.last().unwrap();
    assert_eq!(last["gaps"], 0, "{last}");
    // A service not latched starts at update 1, for every user.
    let (code, lines) = c.run(&["user", "request", "t2/s0", "--duration", "500ms", "--json"]);
    assert_eq!(code, 0);
    assert_eq!(seqs(&lines)[0], 1, "{lines:?}");
}
both!(a_latched_service_gives_a_new_session_its_newest_value_with_the_grant);

fn a_latched_value_outlives_a_broker_crash(via: Via) {
    let mut c = Conf::new("latchcrash", via);
    // One update every 20 s: the first, at the system's start, is all there is for the
    // length of this test.
    c.system("t1", &["--rate", "0.05", "--latched"]);
    c.wait_list(|l| l.len() == 1);
    std::thread::sleep(Duration::from_millis(500));
    let b = c.broker;
    c.f.proc(b).signal(libc::SIGKILL);
    assert!(c.f.proc(b).wait(5 * SEC).is_some());
    c.broker = c.f.remote_broker(&c.r);
    c.wait_list(|l| l.len() == 1);
    // The new broker has the value from the system's registration, not from an update
    // (the next comes 20 s on): the first one, at the circle's start (5, 0), as update
    // 0; then the system's own first update to the session.
    let (code, lines) = c.run(&["user", "request", "t1/s0", "--duration", "500ms", "--json"]);
    assert_eq!(code, 0, "{lines:?}");
    assert_eq!(lines[0]["granted"], true, "{lines:?}");
    assert_eq!(seqs(&lines), vec![0, 1], "{lines:?}");
    let p = &lines[1]["payload"];
    assert!(
        (p["x"].as_f64().unwrap() - 5.0).abs() < 0.01 && p["y"].as_f64().unwrap().abs() < 0.1,
        "update 0 is the value sent before the crash: {p}"
    );
}
both!(a_latched_value_outlives_a_broker_crash);

fn the_system_ends_a_session_and_the_user_is_told(via: Via) {
    let mut c = Conf::new("sysend", via);
    let t1 = c.system("t1", &[]);
    c.wait_list(|l| l.len() == 1);
    let req = c.spawn(&["user", "request", "t1/s0", "--duration", "30s", "--json"]);
    assert_eq!(c.f.proc(req).json(15 * SEC).unwrap()["granted"], true);
    c.f.proc(t1).send("end all");
    let lines = c.f.proc(req).all_json(15 * SEC);
    let last = lines.last().expect("an end line");
    assert!(
        last["reason"]
            .as_str()
            .unwrap()
            .contains("ended by the system"),
        "{last}"
    );
    assert_eq!(c.f.proc(req).wait(5 * SEC), Some(0));
}
both!(the_system_ends_a_session_and_the_user_is_told);

fn a_command_session_takes_a_goal_and_reports_arrival(via: Via) {
    let mut c = Conf::new("command", via);
    c.system("d1", &["--kind", "command", "--quota", "1", "--rate", "20"]);
    c.wait_list(|l| l.len() == 1);
    let (code, lines) = c.run(&[
        "user",
        "request",
        "d1/s0",
        "--goal",
        "1.5,-1.5",
        "--duration",
        "3s",
        "--json",
    ]);
    assert_eq!(code, 0);
    let statuses: Vec<&str> = lines.iter().filter_map(|v| v["status"].as_str()).collect();
    assert_eq!(statuses[0], "idle", "{statuses:?}");
    assert!(
        statuses
            .iter()
            .any(|s| s.contains("goal (1.50, -1.50) accepted")),
        "{statuses:?}"
    );
    assert_eq!(
        statuses
            .iter()
            .filter(|s| s.starts_with("done: arrived within 1 m"))
            .count(),
        1,
        "{statuses:?}"
    );
}
both!(a_command_session_takes_a_goal_and_reports_arrival);

fn a_queued_request_is_granted_at_the_head_of_the_queue(via: Via) {
    let mut c = Conf::new("queue", via);
    c.system("d1", &["--kind", "command", "--quota", "1", "--queue"]);
    c.wait_list(|l| l.len() == 1);
    let first = c.spawn(&["user", "request", "d1/s0", "--duration", "2s", "--json"]);
    assert_eq!(c.f.proc(first).json(15 * SEC).unwrap()["granted"], true);
    let second = c.spawn(&["user", "request", "d1/s0", "--duration", "1s", "--json"]);
    let v =
        c.f.proc(second)
            .json(20 * SEC)
            .expect("granted once the first ends");
    assert_eq!(
        (v["granted"].as_bool(), v["queue_position"].as_u64()),
        (Some(true), Some(1))
    );
    assert_eq!(c.f.proc(second).wait(10 * SEC), Some(0));
}
both!(a_queued_request_is_granted_at_the_head_of_the_queue);

fn sessions_survive_a_broker_crash(via: Via) {
    let mut c = Conf::new("crash", via);
    c.system("t1", &["--rate", "20", "--quota", "1"]);
    c.wait_list(|l| l.len() == 1);
    let req = c.spawn(&["user", "request", "t1/s0", "--duration", "6s", "--json"]);
    assert_eq!(c.f.proc(req).json(15 * SEC).unwrap()["granted"], true);
    std::thread::sleep(Duration::from_millis(1500));
    let b = c.broker;
    c.f.proc(b).signal(libc::SIGKILL);
    assert!(c.f.proc(b).wait(5 * SEC).is_some());
    std::thread::sleep(Duration::from_millis(1000));
    c.broker = c.f.remote_broker(&c.r);
    // The restarted broker learns the old session from the system.
    c.wait_list(|l| l.len() == 1 && l[0]["in_use"] == 1);
    let lines = c.f.proc(req).all_json(20 * SEC);
    let s = seqs(&lines);
    assert!(s.len() >= 60, "updates through the crash: {}", s.len());
    assert!(s.windows(2).all(|w| w[1] == w[0] + 1), "no gap");
    assert_eq!(lines.last().unwrap()["reason"], "duration over");
}
both!(sessions_survive_a_broker_crash);

fn a_link_forwards_data_as_task_input(via: Via) {
    let mut c = Conf::new("link", via);
    c.system("t1", &["--rate", "20"]);
    c.system("d1", &["--kind", "command", "--rate", "20"]);
    c.wait_list(|l| l.len() == 2);
    let (code, lines) = c.run(&[
        "user",
        "link",
        "t1/s0",
        "d1/s0",
        "--duration",
        "2s",
        "--json",
    ]);
    assert_eq!(code, 0, "{lines:?}");
    let forwarded = lines
        .iter()
        .filter(|v| v["forwarded"]["type"] == "goal2d")
        .count();
    assert!(
        forwarded >= 10,
        "data became task input: {forwarded} in {lines:?}"
    );
}
both!(a_link_forwards_data_as_task_input);

fn the_event_feed_shows_a_users_grant_refusal_and_end(via: Via) {
    let mut c = Conf::new("events", via);
    // A reader from the start, and one that joins late (it gets the feed's history).
    let early = c.f.spawn(&["events"]);
    c.system("t1", &["--quota", "1"]);
    c.wait_list(|l| l.len() == 1);
    let (code, lines) = c.run(&["user", "request", "t1/s0", "--duration", "300ms", "--json"]);
    assert_eq!(code, 0, "{lines:?}");
    let session = lines[0]["session"].as_str().unwrap().to_string();
    let (_, lines) = c.run(&["user", "request", "t9/s0", "--duration", "300ms", "--json"]);
    assert_eq!(lines[0]["code"], "unknown", "{lines:?}");
    let late = c.f.spawn(&["events"]);
    for reader in [early, late] {
        let mut seen: Vec<Value> = Vec::new();
        while !seen.iter().any(|e| e["event"] == "refused") {
            let e = c.f.proc(reader).json(20 * SEC).expect("an event");
            seen.push(e);
        }
        let kinds: Vec<&str> = seen.iter().filter_map(|e| e["event"].as_str()).collect();
        let at = |k: &str| {
            kinds
                .iter()
                .position(|x| *x == k)
                .unwrap_or_else(|| panic!("no {k}: {kinds:?}"))
        };
        assert!(at("registered") < at("requested"), "{kinds:?}");
        assert!(at("requested") < at("granted"), "{kinds:?}");
        assert!(at("granted") < at("session_ended"), "{kinds:?}");
        assert!(at("session_ended") < at("refused"), "{kinds:?}");
        let granted = &seen[at("granted")];
        assert_eq!(granted["service"], "t1/s0");
        assert_eq!(granted["session"], session.as_str(), "{granted}");
        let refused = &seen[at("refused")];
        assert_eq!(refused["code"], "unknown", "{refused}");
        let seqs: Vec<u64> = seen.iter().filter_map(|e| e["seq"].as_u64()).collect();
        assert!(
            seqs.windows(2).all(|w| w[1] == w[0] + 1),
            "in order, none lost: {seqs:?}"
        );
    }
}
both!(the_event_feed_shows_a_users_grant_refusal_and_end);

fn an_operator_ends_a_session_and_drops_a_queued_request(via: Via) {
    let mut c = Conf::new("operator", via);
    c.system("d1", &["--kind", "command", "--quota", "1", "--queue"]);
    c.wait_list(|l| l.len() == 1);
    let holder = c.spawn(&["user", "request", "d1/s0", "--duration", "30s", "--json"]);
    let first = c.f.proc(holder).json(20 * SEC).unwrap();
    assert_eq!(first["granted"], true, "{first}");
    let session = first["session"].as_str().unwrap().to_string();
    let waiter = c.spawn(&["user", "request", "d1/s0", "--duration", "30s", "--json"]);
    c.wait_list(|l| l[0]["queued"] == 1);
    // The operator: a local process of the instance's owner.
    let operator = |f: &Fed, args: &[&str]| -> (i32, Value) {
        let mut a = vec!["operator", "--json"];
        a.extend_from_slice(args);
        let (code, out) = f.run(&a, 20 * SEC);
        (
            code,
            serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}")),
        )
    };
    let (code, status) = operator(&c.f, &["status"]);
    assert_eq!(code, 0, "{status}");
    // The broker's handling figures: the system's registration and the users' hellos
    // (two users and this operator, so far) counted, with their times.
    let handled = |kind: &str| {
        status["handling"]
            .as_array()
            .unwrap()
            .iter()
            .find(|h| h["kind"] == kind)
            .cloned()
            .unwrap_or_else(|| panic!("no {kind} in {status}"))
    };
    assert!(
        handled("register")["count"].as_u64().unwrap() >= 1,
        "{status}"
    );
    let hello = handled("hello");
    assert!(hello["count"].as_u64().unwrap() >= 3, "{status}");
    assert!(
        hello["p50_us"].as_u64().unwrap() <= hello["max_us"].as_u64().unwrap(),
        "{status}"
    );
    assert_eq!(
        status["sessions"][0]["session"],
        session.as_str(),
        "{status}"
    );
    let waiting = &status["queues"][0]["waiting"][0];
    let (user, req) = (waiting[0].as_str().unwrap(), waiting[1].as_u64().unwrap());
    let (code, done) = operator(&c.f, &["drop-request", "d1/s0", user, &req.to_string()]);
    assert_eq!((code, &done["done"]), (0, &Value::Bool(true)), "{done}");
    let told = c.f.proc(waiter).json(20 * SEC).unwrap();
    assert_eq!(told["code"], "by_operator", "{told}");
    let (code, _) = operator(&c.f, &["end", &session]);
    assert_eq!(code, 0);
    ended_by_an_operator(&mut c.f, holder);
    // An action on what is not there is refused with the reason.
    let (code, answer) = operator(&c.f, &["end", &session]);
    assert_eq!(code, 1);
    assert!(
        answer["error"].as_str().unwrap().contains("no session"),
        "{answer}"
    );
    if via == Via::Udp {
        // A remote user the access file does not call an operator is told so.
        let (code, out) = c.run_raw(&["operator", "--json", "status"]);
        assert_eq!(code, 1, "{out}");
        assert!(out.contains("not an operator"), "{out}");
    }
}
both!(an_operator_ends_a_session_and_drops_a_queued_request);

/// Waits for the end line of `holder`'s session, and checks an operator ended it.
fn ended_by_an_operator(f: &mut Fed, holder: usize) {
    let ended = loop {
        let v = f.proc(holder).json(20 * SEC).expect("the session's end");
        if v.get("ended").is_some() {
            break v;
        }
    };
    let reason = ended["reason"].as_str().unwrap();
    assert!(reason.contains("ended by an operator"), "{ended}");
}

/// A tmux session running a command (its name, ours) on a server of its own (the socket's
/// path), killed with the server on drop.
struct Tmux(String, String);

/// `tmux` on the server of session `name` alone (`-L`): tests that start sessions at once
/// on one default server raced its start ("server exited unexpectedly").
fn tmux_on(name: &str) -> std::process::Command {
    let mut c = std::process::Command::new("tmux");
    c.args(["-L", name]);
    c
}

impl Tmux {
    /// `None` (the test skips, saying so) if tmux is missing, unless
    /// `MUSTER_REQUIRE_TMUX` is set (as .ci/run does).
    fn start(name: &str, cmd: &str) -> Option<Self> {
        let ok = tmux_on(name)
            .args([
                "new-session",
                "-d",
                "-s",
                name,
                "-x",
                "180",
                "-y",
                "45",
                cmd,
            ])
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            assert!(
                std::env::var_os("MUSTER_REQUIRE_TMUX").is_none(),
                "tmux could not start {cmd}"
            );
            common::skip("no tmux (the console tests)");
            return None;
        }
        let socket = tmux_on(name)
            .args(["display-message", "-p", "-t", name, "#{socket_path}"])
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
            .unwrap_or_default();
        Some(Tmux(name.to_string(), socket))
    }

    fn screen(&self) -> String {
        let out = tmux_on(&self.0)
            .args(["capture-pane", "-p", "-t", &self.0])
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).to_string()
    }

    /// Waits until the screen satisfies `pred`; returns it.
    fn wait(&self, what: &str, pred: impl Fn(&str) -> bool) -> String {
        let deadline = std::time::Instant::now() + 15 * SEC;
        loop {
            let s = self.screen();
            if pred(&s) {
                return s;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "no {what} on the screen:\n{s}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn keys(&self, keys: &[&str]) {
        let mut a = vec!["send-keys", "-t", &self.0];
        a.extend_from_slice(keys);
        assert!(tmux_on(&self.0).args(&a).status().unwrap().success());
    }

    /// What a stuck view is doing: its screen, and the state and kernel wait channel
    /// of each of its process's threads.
    fn diagnose(&self) -> String {
        let pane = tmux_on(&self.0)
            .args([
                "list-panes",
                "-t",
                &self.0,
                "-F",
                "#{pane_dead} #{pane_pid}",
            ])
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
            .unwrap_or_default();
        let threads = pane
            .split_whitespace()
            .nth(1)
            .map(common::threads_of)
            .unwrap_or_default();
        format!(
            "pane (dead, pid): {pane}; threads:{threads}\nscreen:\n{}",
            self.screen()
        )
    }

    /// `q`, then waits (bounded) for the program to end and its session to close.
    fn quit(&self) {
        self.keys(&["q"]);
        let deadline = std::time::Instant::now() + 20 * SEC;
        while self.alive() {
            assert!(
                std::time::Instant::now() < deadline,
                "the view did not quit; {}",
                self.diagnose()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn alive(&self) -> bool {
        tmux_on(&self.0)
            .args(["has-session", "-t", &self.0])
            .status()
            .is_ok_and(|s| s.success())
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = tmux_on(&self.0).args(["kill-server"]).status();
        // Its own server's socket goes with it.
        if !self.1.is_empty() {
            let _ = std::fs::remove_file(&self.1);
        }
    }
}

#[test]
fn the_console_shows_grants_ends_and_withdrawals_and_acts_on_keys() {
    let mut c = Conf::new("console", Via::Shm);
    c.system("d1", &["--kind", "command", "--quota", "1", "--queue"]);
    c.wait_list(|l| l.len() == 1);
    let holder = c.spawn(&["user", "request", "d1/s0", "--duration", "60s", "--json"]);
    let first = c.f.proc(holder).json(20 * SEC).unwrap();
    let session = first["session"].as_str().unwrap().to_string();
    let name = format!("muster-console-{}", std::process::id());
    let cmd = format!("{} --instance {} console", common::BIN, c.f.inst);
    let Some(t) = Tmux::start(&name, &cmd) else {
        return;
    };
    // The service, the session and its grant.
    t.wait("the session", |s| {
        s.contains("d1/s0") && s.contains(&session)
    });
    t.wait("the grant", |s| {
        s.contains("granted") && s.contains(&format!("session={session}"))
    });
    // The broker's own figures: how many of each message it handled, and how fast.
    t.wait("the broker's figures", |s| {
        s.contains("broker figures:")
            && s.lines().any(|l| {
                let w: Vec<&str> = l.split(['│', ' ']).filter(|w| !w.is_empty()).collect();
                w.windows(2)
                    .any(|p| p[0] == "hello" && p[1].parse::<u64>().is_ok_and(|n| n >= 2))
            })
    });
    // A request waits in the queue: shown in the queue pane and the event log.
    let waiter = c.spawn(&["user", "request", "d1/s0", "--duration", "60s", "--json"]);
    t.wait("the queued request", |s| s.contains("queued position=1"));
    // Tab to the sessions, `e`: the session ends and the waiter is granted.
    t.keys(&["Tab", "e"]);
    t.wait("the end", |s| {
        s.contains(&format!("op=end session {session}")) && s.contains("session_ended")
    });
    let granted = c.f.proc(waiter).json(20 * SEC).unwrap();
    assert_eq!(granted["granted"], true, "{granted}");
    let second = granted["session"].as_str().unwrap().to_string();
    t.wait("the new session", |s| s.contains(&second));
    // Back to the services, `w`: withdrawn, on screen.
    t.keys(&["Tab", "Tab", "Tab", "w"]);
    t.wait("the withdrawal", |s| {
        s.contains("withdrawn=true") && s.contains("withdrawn  ")
    });
    assert_eq!(c.list()[0]["withdrawn"], true);
    // `q` quits and gives the terminal back.
    t.quit();
}

fn the_user_view_requests_links_ends_and_shows_withdrawals(via: Via) {
    let mut c = Conf::new("usertui", via);
    c.system("t1", &[]);
    c.system("d1", &["--kind", "command", "--quota", "1", "--queue"]);
    let list = c.wait_list(|l| l.len() == 2);
    let row = |id: &str| list.iter().position(|v| v["id"] == id).unwrap();
    let (t1, d1) = (row("t1/s0"), row("d1/s0"));
    let name = format!("muster-user-{}-{via:?}", std::process::id());
    let args: Vec<String> = c.args(&["user"]);
    let cmd = format!("{} --instance {} {}", common::BIN, c.f.inst, args.join(" "));
    let Some(t) = Tmux::start(&name, &cmd) else {
        return;
    };
    t.wait("the services", |s| {
        s.contains("t1/s0") && s.contains("d1/s0") && s.contains("2 services")
    });
    // Request t1/s0: granted, and its updates come into the updates pane once the
    // session is selected.
    let down = |n: usize| {
        for _ in 0..n {
            t.keys(&["Down"]);
        }
    };
    for _ in 0..3 {
        t.keys(&["Up"]);
    }
    down(t1);
    t.keys(&["Enter"]);
    t.wait("the grant", |s| s.contains("granted t1/s0: session"));
    t.keys(&["Tab"]);
    t.wait("the session's updates", |s| {
        s.contains("updates of t1/s0") && s.contains("pose2d x=")
    });
    // Link t1/s0 into d1/s0: `l` on the data service, Enter on the command service.
    t.keys(&["Tab", "Tab"]);
    for _ in 0..3 {
        t.keys(&["Up"]);
    }
    down(t1);
    t.keys(&["l"]);
    t.wait("the link prompt", |s| {
        s.contains("select a command service")
    });
    for _ in 0..3 {
        t.keys(&["Up"]);
    }
    down(d1);
    t.keys(&["Enter"]);
    t.wait("the link", |s| {
        s.contains("t1/s0 -> d1/s0") && s.contains(" up ")
    });
    t.wait("a forwarded input", |s| {
        s.lines()
            .any(|l| l.contains("t1/s0 -> d1/s0") && l.contains("goal2d x="))
    });
    // The broker's list counts it.
    c.wait_list(|l| l[d1]["in_use"] == 1 && l[t1]["links"] == 1);
    // End the first session (the sessions pane's first row).
    t.keys(&["Tab"]);
    for _ in 0..5 {
        t.keys(&["Up"]);
    }
    t.keys(&["e"]);
    t.wait("the end", |s| s.contains("ended: ended by the user"));
    // An operator withdraws d1/s0: shown at once (the link's session goes on).
    let (code, out) = c.f.run(&["operator", "withdraw", "d1/s0"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
    t.wait("the withdrawal", |s| {
        s.lines()
            .any(|l| l.contains("d1/s0") && l.contains("withdrawn"))
    });
    // The links pane, `e`: the link ends, and the broker's list counts no link.
    t.keys(&["Tab", "e"]);
    t.wait("the link's end", |s| s.contains("link 1 ended"));
    c.wait_list(|l| l[d1]["links"] == 0 && l[d1]["in_use"] == 0 && l[t1]["in_use"] == 0);
    // `q` quits and gives the terminal back.
    t.quit();
}
both!(the_user_view_requests_links_ends_and_shows_withdrawals);

#[test]
fn a_remote_operator_acts_and_its_console_follows_the_event_feed() {
    // Olga has an `operator` line in the access file: over UDP she reads the status,
    // drops a queued request and ends a session, and her console shows the broker's
    // event feed, sent over her connection.
    let mut f = Fed::new("remop");
    let r = f.remote_setup_with(&[("alice", &["*"])], &["olga"]);
    f.remote_broker(&r);
    f.system(
        "d1",
        &[
            "--udp",
            "127.0.0.1:0",
            "--kind",
            "command",
            "--quota",
            "1",
            "--queue",
        ],
    );
    f.wait_list(15 * SEC, |l| l.len() == 1);
    let alice = |args: &[&str]| Fed::user_args(Via::Udp, Some(&r), args);
    let a = alice(&["user", "request", "d1/s0", "--duration", "60s", "--json"]);
    let a: Vec<&str> = a.iter().map(String::as_str).collect();
    let holder = f.spawn(&a);
    let first = f.proc(holder).json(20 * SEC).unwrap();
    assert_eq!(first["granted"], true, "{first}");
    let session = first["session"].as_str().unwrap().to_string();
    let olga_key = r.key("olga");
    let olga_args = ["--remote", r.addr.as_str(), "--key", olga_key.as_str()];
    let name = format!("muster-remop-{}", std::process::id());
    let cmd = format!(
        "{} --instance {} console {}",
        common::BIN,
        f.inst,
        olga_args.join(" ")
    );
    let console = Tmux::start(&name, &cmd);
    if let Some(t) = &console {
        t.wait("the remote console", |s| {
            s.contains("olga.") && s.contains(&session)
        });
    }
    let waiter = f.spawn(&["user", "request", "d1/s0", "--duration", "60s", "--json"]);
    f.wait_list(15 * SEC, |l| l[0]["queued"] == 1);
    // Each step shows in the console's log, sent over its connection.
    let feed = |what: &str, want: &str| {
        if let Some(t) = &console {
            t.wait(what, |s| s.contains(want));
        }
    };
    feed(
        "the queued request, on the feed over UDP",
        "queued position=1",
    );
    let olga = |f: &Fed, args: &[&str]| -> (i32, Value) {
        let mut a = vec!["operator", "--json"];
        a.extend_from_slice(args);
        a.extend_from_slice(&olga_args);
        let (code, out) = f.run(&a, 30 * SEC);
        (
            code,
            serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}")),
        )
    };
    let (code, status) = olga(&f, &["status"]);
    assert_eq!(code, 0, "{status}");
    assert_eq!(
        status["sessions"][0]["session"],
        session.as_str(),
        "{status}"
    );
    assert!(
        status["handling"].as_array().is_some_and(|h| !h.is_empty()),
        "{status}"
    );
    let waiting = &status["queues"][0]["waiting"][0];
    let (user, req) = (waiting[0].as_str().unwrap(), waiting[1].as_u64().unwrap());
    let (code, done) = olga(&f, &["drop-request", "d1/s0", user, &req.to_string()]);
    assert_eq!((code, &done["done"]), (0, &Value::Bool(true)), "{done}");
    let told = f.proc(waiter).json(20 * SEC).unwrap();
    assert_eq!(told["code"], "by_operator", "{told}");
    feed("the drop, on the feed over UDP", "op=drop request");
    let (code, done) = olga(&f, &["end", &session]);
    assert_eq!(code, 0, "{done}");
    ended_by_an_operator(&mut f, holder);
    // The console heard the end on the feed, and quits.
    if let Some(t) = &console {
        t.wait("the end, on the feed over UDP", |s| {
            s.contains(&format!("op=end session {session}")) && s.contains("session_ended")
        });
        t.keys(&["q"]);
    }
}
