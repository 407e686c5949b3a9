//! Broker redundancy with real processes: a standby follows the primary and takes
//! over when it is killed, stopped or steps down; sessions, queues and quotas survive.

#![allow(clippy::unwrap_used)]

mod common;

use common::{find, Fed, SEC};
use serde_json::Value;
use std::time::{Duration, Instant};

/// The takeover tests count a 20 Hz stream's updates across a takeover: run them one at
/// a time, so that six brokers, standbys, systems and users taking over at once on a
/// 2-core machine do not starve each other's streams (as the robots' tests do).
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Starts a standby and waits until it holds the primary's state.
fn standby(f: &mut Fed) -> usize {
    let s = f.broker(&["--standby"]);
    let v = next_event(f, s, "in_sync");
    assert!(v["seq"].is_u64(), "{v}");
    s
}

/// The standby's next event named `name` (it prints one JSON line per event); the
/// events passed over on the way are named if it never comes.
fn next_event(f: &mut Fed, proc: usize, name: &str) -> Value {
    let deadline = Instant::now() + 15 * SEC;
    let mut passed = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let v = f.proc(proc).json(left).unwrap_or_else(|| {
            panic!("no {name:?} event from the standby (it said before: {passed:?})")
        });
        if v["event"] == name {
            return v;
        }
        passed.push(v);
    }
}

fn seqs(lines: &[Value]) -> Vec<u64> {
    lines
        .iter()
        .filter_map(|v| {
            v.get("payload")
                .filter(|p| !p.is_null())
                .and(v["seq"].as_u64())
        })
        .collect()
}

/// The stream of a data session: every update in order, no gap, ended by its duration.
fn assert_unbroken(lines: &[Value], at_least: usize) {
    let s = seqs(lines);
    assert!(
        s.len() >= at_least,
        "updates through the takeover: {} {lines:?}",
        s.len()
    );
    assert!(s.windows(2).all(|w| w[1] == w[0] + 1), "a gap in {s:?}");
    let last = lines.last().unwrap();
    assert_eq!(last["gaps"], 0, "{last}");
    assert_eq!(last["reason"], "duration over", "{last}");
}

#[test]
fn a_killed_primary_is_replaced_at_once_with_its_sessions_queue_and_quotas() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-kill");
    let primary = f.broker(&[]);
    let s = standby(&mut f);
    f.system("t1", &["--rate", "20", "--quota", "1"]);
    f.system("d1", &["--kind", "command", "--quota", "1", "--queue"]);
    f.system("t2", &["--services", "3"]);
    f.wait_list(10 * SEC, |l| l.len() == 5);
    let data = f.spawn(&["user", "request", "t1/s0", "--duration", "12s", "--json"]);
    assert_eq!(f.proc(data).json(10 * SEC).unwrap()["granted"], true);
    let holder = f.spawn(&["user", "request", "d1/s0", "--duration", "6s", "--json"]);
    assert_eq!(f.proc(holder).json(10 * SEC).unwrap()["granted"], true);
    let waiter = f.spawn(&["user", "request", "d1/s0", "--duration", "1s", "--json"]);
    f.wait_list(10 * SEC, |l| {
        find(l, "d1/s0").is_some_and(|s| s["queued"] == 1)
    });
    std::thread::sleep(Duration::from_millis(500));

    f.proc(primary).signal(libc::SIGKILL);
    let took = next_event(&mut f, s, "took_over");
    assert_eq!(took["why"], "died");
    assert_eq!(took["replicated"], true);
    next_event(&mut f, s, "serving");
    // The list is whole at once, counting what the old primary had granted and queued.
    let list = f.list();
    assert_eq!(list.len(), 5, "{list:?}");
    assert_eq!(find(&list, "t1/s0").unwrap()["in_use"], 1);
    assert_eq!(find(&list, "d1/s0").unwrap()["in_use"], 1);
    assert_eq!(find(&list, "d1/s0").unwrap()["queued"], 1);
    // A new request is granted; the quota of t1/s0 is still taken.
    let (code, out) = f.run(&["user", "request", "t2/s0", "--json"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("\"granted\":true"), "{out}");
    let (code, out) = f.run(&["user", "request", "t1/s0", "--json"], 20 * SEC);
    assert_eq!(code, 3, "quota still counted: {out}");
    // The queued request moves up when the holder's session ends.
    let v = f
        .proc(waiter)
        .json(15 * SEC)
        .expect("granted after the holder");
    assert_eq!(v["granted"], true);
    assert_eq!(v["queue_position"], 1);
    assert_unbroken(&f.proc(data).all_json(20 * SEC), 200);
    // Once everything has ended, nothing is counted in use.
    f.wait_list(10 * SEC, |l| l.iter().all(|s| s["in_use"] == 0));
}

#[test]
fn a_stopped_primary_is_taken_over_and_never_acts_again() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-stop");
    let primary = f.broker(&[]);
    let s = standby(&mut f);
    f.system("t1", &["--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let data = f.spawn(&["user", "request", "t1/s0", "--duration", "8s", "--json"]);
    assert_eq!(f.proc(data).json(10 * SEC).unwrap()["granted"], true);

    f.proc(primary).signal(libc::SIGSTOP);
    let took = next_event(&mut f, s, "took_over");
    // The kernel says it is stopped (`/proc/PID/stat`): taken over as such.
    assert_eq!(took["why"], "stopped");
    next_event(&mut f, s, "serving");
    f.proc(primary).signal(libc::SIGCONT);
    // The old primary is gone: it does not come back to serve the instance.
    assert!(
        f.proc(primary).wait(5 * SEC).is_some(),
        "the old primary still runs"
    );
    let list = f.list();
    assert_eq!(find(&list, "t1/s0").unwrap()["in_use"], 1);
    let (code, out) = f.run(&["user", "request", "t1/s0", "--json"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
    assert_unbroken(&f.proc(data).all_json(20 * SEC), 140);
}

#[test]
fn a_primary_whose_loop_hangs_while_its_process_lives_is_taken_over() {
    // The fault hook stops the primary's loop for good after 250 passes (about 5 s of
    // heartbeats with a standby following): not dead, not stopped, sleeping: only the
    // loop's progress word tells the standby it hangs.
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-hang");
    let primary = f.broker(&["--fault", "hang-after:250"]);
    let s = standby(&mut f);
    f.system("t1", &["--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let data = f.spawn(&["user", "request", "t1/s0", "--duration", "12s", "--json"]);
    assert_eq!(f.proc(data).json(10 * SEC).unwrap()["granted"], true);
    let took = next_event(&mut f, s, "took_over");
    assert_eq!(took["why"], "hung", "{took}");
    next_event(&mut f, s, "serving");
    // The standby ends the hung primary (it must never wake to act again).
    assert!(
        f.proc(primary).wait(5 * SEC).is_some(),
        "the hung primary still runs"
    );
    let (code, out) = f.run(&["user", "request", "t1/s0", "--json"], 20 * SEC);
    assert_eq!(code, 0, "the new primary grants: {out}");
    assert_unbroken(&f.proc(data).all_json(30 * SEC), 200);
}

#[test]
fn a_standby_started_before_its_primary_follows_it_instead_of_starting_cold() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-early");
    // Started first, the standby sees no primary for longer than its 100 ms deadline
    // (as on a loaded host, when `muster up` starts both at once): it waits for one.
    let s = f.broker(&["--standby"]);
    std::thread::sleep(Duration::from_millis(600));
    let primary = f.broker(&[]);
    let v = next_event(&mut f, s, "in_sync");
    assert_eq!(v["primary"], f.proc(primary).pid(), "{v}");
    // And it is a standby of that primary: it takes over when the primary dies.
    f.system("t1", &["--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    f.proc(primary).signal(libc::SIGKILL);
    let took = next_event(&mut f, s, "took_over");
    assert_eq!(took["why"], "died", "{took}");
    assert_eq!(took["replicated"], true, "{took}");
    next_event(&mut f, s, "serving");
    assert!(find(&f.list(), "t1/s0").is_some());
}

#[test]
fn a_standby_with_no_broker_to_follow_serves_the_instance_itself() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-alone");
    let s = f.broker(&["--standby"]);
    let took = next_event(&mut f, s, "took_over");
    assert_eq!(took["why"], "noprimary", "{took}");
    assert_eq!(took["replicated"], false, "{took}");
    next_event(&mut f, s, "serving");
    f.system("t1", &["--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
}

#[test]
fn a_killed_standby_leaves_the_primary_unaffected() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-standby");
    f.broker(&[]);
    let s = standby(&mut f);
    f.system("t1", &["--quota", "2"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    f.proc(s).signal(libc::SIGKILL);
    assert!(f.proc(s).wait(5 * SEC).is_some());
    let (code, out) = f.run(&["user", "request", "t1/s0", "--json"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
    f.system("t2", &[]);
    f.wait_list(10 * SEC, |l| l.len() == 2);
}

#[test]
fn standbys_killed_one_after_another_beyond_the_replicas_slots_leave_room_for_the_next() {
    // Nothing watches a standby's death, so a SIGKILLed one holds its reader slots of
    // the replication stream until some cleanup: the stream has four. Six killed in a
    // row, the seventh must still get in sync, and take over.
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-standbys");
    let p = f.broker(&[]);
    f.system("t1", &[]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    for _ in 0..6 {
        let s = standby(&mut f);
        f.proc(s).signal(libc::SIGKILL);
        assert!(f.proc(s).wait(5 * SEC).is_some());
    }
    let s = standby(&mut f);
    f.proc(p).signal(libc::SIGKILL);
    let v = next_event(&mut f, s, "took_over");
    assert_eq!(v["why"], "died", "{v}");
    let (code, out) = f.run(&["user", "request", "t1/s0", "--json"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
}

#[test]
fn muster_cleanup_removes_the_fence_of_a_run_killed_whole_and_no_other() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let fence =
        |f: &Fed| std::path::PathBuf::from(format!("/dev/shm/muster/{}.broker-fence", f.inst));
    let mut f = Fed::new("fo-fence");
    let p = f.broker(&[]);
    f.system("t1", &[]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    // A live broker's fence is left alone.
    let (code, out) = f.run(&["cleanup"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
    assert!(fence(&f).exists(), "a live broker's fence was removed");
    // Killed, it stays; `muster cleanup` takes it away.
    f.proc(p).signal(libc::SIGKILL);
    assert!(f.proc(p).wait(5 * SEC).is_some());
    assert!(fence(&f).exists(), "nothing removes it by itself");
    let (code, out) = f.run(&["cleanup"], 20 * SEC);
    assert_eq!(code, 0, "{out}");
    assert!(
        !fence(&f).exists(),
        "muster cleanup left the killed broker's fence"
    );
}

#[test]
fn three_takeovers_in_a_row_keep_one_session_running() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-three");
    let mut primary = f.broker(&[]);
    f.system("t1", &["--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let data = f.spawn(&["user", "request", "t1/s0", "--duration", "20s", "--json"]);
    assert_eq!(f.proc(data).json(10 * SEC).unwrap()["granted"], true);
    for round in 1..=3 {
        // Each new standby catches up with whoever is primary now.
        let s = standby(&mut f);
        f.proc(primary).signal(libc::SIGKILL);
        let took = next_event(&mut f, s, "took_over");
        assert_eq!(took["replicated"], true, "round {round}");
        next_event(&mut f, s, "serving");
        let list = f.list();
        assert_eq!(find(&list, "t1/s0").unwrap()["in_use"], 1, "round {round}");
        let (code, out) = f.run(&["user", "request", "t1/s0", "--json"], 20 * SEC);
        assert_eq!(code, 0, "round {round}: {out}");
        primary = s;
    }
    assert_unbroken(&f.proc(data).all_json(30 * SEC), 350);
}

#[test]
fn a_primary_stopping_on_purpose_hands_over_to_its_standby() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-step");
    let primary = f.broker(&[]);
    let s = standby(&mut f);
    f.system("t1", &["--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let data = f.spawn(&["user", "request", "t1/s0", "--duration", "6s", "--json"]);
    assert_eq!(f.proc(data).json(10 * SEC).unwrap()["granted"], true);
    f.proc(primary).signal(libc::SIGTERM);
    assert_eq!(f.proc(primary).wait(5 * SEC), Some(0));
    let took = next_event(&mut f, s, "took_over");
    assert_eq!(took["why"], "steppeddown");
    next_event(&mut f, s, "serving");
    assert_eq!(find(&f.list(), "t1/s0").unwrap()["in_use"], 1);
    assert_unbroken(&f.proc(data).all_json(20 * SEC), 100);
}

#[test]
fn remote_users_resume_with_the_new_primary_and_their_sessions_never_pause() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-remote");
    let r = f.remote_setup(&[("alice", &["*"])]);
    let dir = r.dir.display().to_string();
    let (code, _) = f.run(&["keygen", "--broker", "--out", &dir], 20 * SEC);
    assert_eq!(code, 0);
    let key = r.dir.join("broker.key").display().to_string();
    let access = r.access.display().to_string();
    let front = ["--udp", r.addr.as_str(), "--access", &access, "--key", &key];
    let primary = f.broker(&front);
    let mut standby_args = vec!["--standby"];
    standby_args.extend(front);
    let s = f.broker(&standby_args);
    next_event(&mut f, s, "in_sync");
    f.system(
        "t1",
        &["--rate", "20", "--quota", "5", "--udp", "127.0.0.1:0"],
    );
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let alice = r.key("alice");
    let remote = ["--remote", r.addr.as_str(), "--key", alice.as_str()];
    let mut data_args = vec!["user", "request", "t1/s0", "--duration", "8s", "--json"];
    data_args.extend(remote);
    let data = f.spawn(&data_args);
    assert_eq!(f.proc(data).json(10 * SEC).unwrap()["granted"], true);
    // A remote user making requests one after another, through the takeover.
    let mut req_args = vec!["bench", "failover-user", "--request", "t1/s0"];
    req_args.extend(remote);
    let req = f.spawn(&req_args);
    assert_eq!(f.proc(req).json(10 * SEC).unwrap()["granted"], true);

    let t_kill = muster_shared::protocol::monotonic_ns();
    f.proc(primary).signal(libc::SIGKILL);
    next_event(&mut f, s, "serving");
    // Its next request made after the kill is granted by the new primary, the user
    // having done nothing (a stateless reset, a new handshake, the request again).
    let deadline = Instant::now() + 20 * SEC;
    let took = loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let v = f
            .proc(req)
            .json(left)
            .expect("a grant from the new primary");
        if v["granted"] == true && v["asked_ns"].as_u64().is_some_and(|a| a > t_kill) {
            break Duration::from_nanos(v["t_ns"].as_u64().unwrap() - t_kill);
        }
    };
    eprintln!("remote user: first new grant {took:?} after the kill");
    // Told by the new front (a stateless reset), not by the 6 s of silence it would
    // otherwise have waited for.
    assert!(took < Duration::from_secs(5), "{took:?}");
    assert_unbroken(&f.proc(data).all_json(20 * SEC), 140);
    f.proc(req).signal(libc::SIGTERM);
    let done = loop {
        let v = f.proc(req).json(10 * SEC).expect("the requester's summary");
        if v["done"] == true {
            break v;
        }
    };
    assert_eq!(done["resets"], 1, "{done}");
    assert_eq!(done["unwanted_grants"], 0, "{done}");
}

#[test]
fn only_the_primary_speaks_on_the_replication_stream() {
    // Another process of the same account publishes on the standbys' stream: a notice
    // that the primary is stepping down (under every sequence number near the
    // standby's), heartbeats far ahead (each a gap: the whole state asked for again).
    // The standby heeds none of it: no takeover of the healthy primary, which goes on
    // serving; and a real kill is still taken over, sessions whole.
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut f = Fed::new("fo-forge");
    let primary = f.broker(&[]);
    let s = f.broker(&["--standby"]);
    let seq = next_event(&mut f, s, "in_sync")["seq"].as_u64().unwrap();
    f.system("t1", &["--quota", "2", "--rate", "20"]);
    f.wait_list(10 * SEC, |l| l.len() == 1);
    let inst = muster_shared::Instance::new(&f.inst).unwrap();
    let node = muster_shared::ipc::create_node(
        &format!("muster-test-forger-{}", std::process::id()),
        false,
    )
    .unwrap();
    let writer = muster_shared::ipc::ReplicaWriter::open(&node, &inst).unwrap();
    for k in 0..300 {
        let forger = muster_broker::replica::Leader::after(seq + k);
        writer.publish(&forger.stepping_down()).unwrap();
        if k % 10 == 0 {
            writer.ring();
            std::thread::sleep(Duration::from_millis(2));
        }
    }
    for k in 0..100 {
        writer
            .publish(&muster_broker::replica::Leader::after(1_000_000 + k).heartbeat())
            .unwrap();
    }
    writer.ring();
    // Time for a takeover to have happened, were it going to.
    std::thread::sleep(SEC);
    let (code, out) = f.run(
        &["user", "request", "t1/s0", "--duration", "300ms", "--json"],
        20 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    let said: Vec<String> =
        std::iter::from_fn(|| f.proc(s).line(Duration::from_millis(200))).collect();
    assert!(
        !said.iter().any(|l| l.contains("\"serving\"")),
        "the standby took over: {said:?}"
    );
    assert!(
        f.proc(s).wait(Duration::ZERO).is_none(),
        "the standby still runs"
    );
    assert!(
        f.proc(primary).wait(Duration::ZERO).is_none(),
        "the primary still runs"
    );
    drop(writer);
    drop(node);
    // Still a standby with the state: killed, the primary is replaced, and a session
    // across the kill runs on unbroken.
    let user = f.spawn(&["user", "request", "t1/s0", "--duration", "3s", "--json"]);
    assert_eq!(f.proc(user).json(10 * SEC).unwrap()["granted"], true);
    std::thread::sleep(SEC);
    f.proc(primary).signal(libc::SIGKILL);
    let v = next_event(&mut f, s, "serving");
    assert!(v["term"].is_u64(), "{v}");
    let lines = f.proc(user).all_json(20 * SEC);
    assert_unbroken(&lines, 40);
}
