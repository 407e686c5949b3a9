//! VDA 5050 against code nobody here wrote: Siemens' vda-5050-lib (its AgvController
//! with the VirtualAgvAdapter plays the vehicle) through Debian's mosquitto. Every
//! message on the interface is checked by the library's VDA 5050 2.0 validators (made
//! from the official JSON schemas) in the peer process.
//!
//! Needs `mosquitto` and `node` with `bridges/vda5050/tests/js/node_modules` (`.ci/run`
//! installs them); skipped without them unless `MUSTER_REQUIRE_VDA5050` is set.

#![allow(clippy::unwrap_used)]

mod common;

use common::{find, free_tcp_port, skip, Fed, Proc};
use muster_shared::types::{EndReason, Payload, ServiceId, SessionId, TaskStatus};
use muster_users::{ConnectOptions, UserClient, UserEvent};
use serde_json::Value;
use std::process::Command;
use std::time::{Duration, Instant};

const SEC: Duration = Duration::from_secs(1);
const JS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/bridges/vda5050/tests/js");

/// Whether mosquitto, node and the library are here (else the test is skipped, or
/// fails where `MUSTER_REQUIRE_VDA5050` says they must be).
fn peers_here() -> bool {
    let has = |prog: &str| {
        Command::new(prog)
            .arg("--help")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok()
    };
    let lib = std::path::Path::new(JS).join("node_modules/vda-5050-lib/package.json");
    let ok = has("mosquitto") && has("node") && lib.exists();
    if !ok {
        assert!(
            std::env::var_os("MUSTER_REQUIRE_VDA5050").is_none(),
            "mosquitto, node or {} missing: run .ci/run's setup",
            lib.display()
        );
        skip("mosquitto, node or vda-5050-lib missing (see .ci/run)");
    }
    ok
}

/// Starts mosquitto on a free loopback port; returns its `host:port`.
fn mosquitto(f: &mut Fed) -> String {
    let port = free_tcp_port();
    let dir = std::env::temp_dir().join(format!("muster-mosq-{}-{port}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let conf = dir.join("mosquitto.conf");
    std::fs::write(
        &conf,
        format!("listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"),
    )
    .unwrap();
    let mut c = Command::new("mosquitto");
    c.arg("-c").arg(&conf);
    f.spawn_command(c);
    let addr = format!("127.0.0.1:{port}");
    let deadline = Instant::now() + 10 * SEC;
    while std::net::TcpStream::connect(&addr).is_err() {
        assert!(
            Instant::now() < deadline,
            "mosquitto did not listen on {addr}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Read once at start: nothing of it need stay in the temporary directory.
    let _ = std::fs::remove_dir_all(&dir);
    addr
}

/// The virtual vehicles (vda-5050-lib) on interface `iface`.
fn virtual_agvs(f: &mut Fed, mqtt: &str, iface: &str, extra: &[&str]) -> usize {
    let mut c = Command::new("node");
    c.current_dir(JS)
        .arg("virtual_agv.js")
        .args(["--broker", &format!("mqtt://{mqtt}"), "--interface", iface])
        .args(extra);
    let i = f.spawn_command(c);
    wait_event(f.proc(i), "ready", 20 * SEC);
    i
}

/// vda-5050-lib's master control (`master.js`) for muster's D1 on interface `iface`.
fn master_control(f: &mut Fed, mqtt: &str, iface: &str) -> usize {
    let mut c = Command::new("node");
    c.current_dir(JS).arg("master.js").args([
        "--broker",
        &format!("mqtt://{mqtt}"),
        "--interface",
        iface,
        "--manufacturer",
        "muster",
        "--serial",
        "D1",
    ]);
    f.spawn_command(c)
}

/// A state of vda-5050-lib's `acme/agv1`, at (x, 0) heading `theta`, charged `charge` %.
fn agv1_state(charge: f64, x: f64, theta: f64) -> Value {
    serde_json::json!({"headerId": 900, "timestamp": "2026-11-27T06:00:00.00Z",
        "version": "2.0.0", "manufacturer": "acme", "serialNumber": "agv1", "orderId": "",
        "orderUpdateId": 0, "lastNodeId": "0", "lastNodeSequenceId": 0, "driving": false,
        "operatingMode": "AUTOMATIC", "nodeStates": [], "edgeStates": [], "actionStates": [],
        "agvPosition": {"x": x, "y": 0.0, "theta": theta, "mapId": "local", "positionInitialized": true},
        "batteryState": {"batteryCharge": charge, "charging": false}, "errors": [],
        "safetyState": {"eStop": "NONE", "fieldViolation": false}})
}

/// The next line of the peer with `"event": event`.
fn wait_event(p: &mut Proc, event: &str, timeout: Duration) -> Value {
    wait_for(p, timeout, |v| v["event"] == event)
}

fn wait_for(p: &mut Proc, timeout: Duration, pred: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        assert!(
            !left.is_zero(),
            "the VDA 5050 peer did not say it within {timeout:?}"
        );
        if let Some(v) = p.json(left) {
            if v["event"] == "invalid" {
                panic!("a message failed its VDA 5050 schema: {v}");
            }
            if pred(&v) {
                return v;
            }
        }
    }
}

fn user(f: &Fed) -> UserClient {
    let inst = muster_shared::Instance::new(&f.inst).unwrap();
    let opts = ConnectOptions {
        handle_signals: false,
        ..ConnectOptions::default()
    };
    UserClient::connect(&inst, &opts).unwrap()
}

fn grant(c: &mut UserClient, id: &str) -> SessionId {
    let (system, name) = id.split_once('/').unwrap();
    let service = ServiceId::new(system, name);
    let req = c.request(&service).unwrap();
    let deadline = Instant::now() + 10 * SEC;
    loop {
        match c.next_event(deadline).unwrap() {
            Some(UserEvent::Granted {
                req: r, session, ..
            }) if r == req => return session,
            Some(UserEvent::Refused { req: r, reason, .. }) if r == req => {
                panic!("{id} refused: {reason:?}")
            }
            Some(_) => {}
            None => panic!("{id} not granted within 10 s"),
        }
    }
}

/// Statuses of `session` until one satisfies `done` (all of them, in order).
fn statuses_until(
    c: &mut UserClient,
    session: SessionId,
    timeout: Duration,
    done: impl Fn(&TaskStatus) -> bool,
) -> Vec<TaskStatus> {
    statuses_and_data(c, session, timeout, done, &mut Vec::new())
}

/// [`statuses_until`], keeping the data sessions' updates (JSON) in `data`.
fn statuses_and_data(
    c: &mut UserClient,
    session: SessionId,
    timeout: Duration,
    done: impl Fn(&TaskStatus) -> bool,
    data: &mut Vec<Value>,
) -> Vec<TaskStatus> {
    let deadline = Instant::now() + timeout;
    let mut seen = Vec::new();
    loop {
        match c.next_event(deadline).unwrap() {
            Some(UserEvent::Status {
                session: s, status, ..
            }) if s == session => {
                let stop = done(&status);
                seen.push(status);
                if stop {
                    return seen;
                }
            }
            Some(UserEvent::Update {
                payload: Payload::Encoded { data: d, .. },
                ..
            }) => data.push(serde_json::from_slice(&d).unwrap()),
            Some(_) => {}
            None => panic!("no such status within {timeout:?}; saw {seen:?}"),
        }
    }
}

fn done(s: &TaskStatus) -> bool {
    matches!(s, TaskStatus::Done(_) | TaskStatus::Rejected(_))
}

/// The metres to go a driving note names.
fn to_go(s: &TaskStatus) -> Option<f64> {
    let d = s.detail()?;
    let (before, _) = d.split_once(" m to go")?;
    before.rsplit(' ').next()?.parse().ok()
}

fn goal(c: &mut UserClient, session: SessionId, x: f64, y: f64) {
    c.input(session, Payload::Goal2d { x, y }).unwrap();
}

/// The vehicle's states (from the sniffer) until one satisfies `pred`.
fn state_until(p: &mut Proc, timeout: Duration, pred: impl Fn(&Value) -> bool) -> Value {
    wait_for(p, timeout, |v| v["event"] == "state" && pred(v))
}

#[test]
fn a_vda5050_vehicle_is_listed_driven_by_a_users_goals_cancelled_and_withdrawn_when_offline() {
    if !peers_here() {
        return;
    }
    let mut f = Fed::new("vda1");
    let mqtt = mosquitto(&mut f);
    let iface = format!("t{}", std::process::id());
    let agv = virtual_agvs(&mut f, &mqtt, &iface, &["--speed", "4"]);
    f.broker(&[]);
    let fleet = f.spawn(&[
        "system",
        "vda5050",
        "--mqtt",
        &mqtt,
        "--interface",
        &iface,
        "--vda-version",
        "2.0.0",
        "--stats-json",
    ]);
    let (list, _) = f.wait_list(20 * SEC, |l| l.len() == 2);
    let cmd = find(&list, "vda5050/agv1").expect("the vehicle's command service");
    assert_eq!(cmd["kind"], "command");
    assert_eq!(cmd["payload"], "goal2d");
    assert_eq!(cmd["quota"], 1);
    let data = find(&list, "vda5050/agv1.state").expect("the vehicle's state service");
    assert_eq!(data["payload"], "vda5050/VehicleState");

    let mut c = user(&f);
    let watch = grant(&mut c, "vda5050/agv1.state");
    let drive = grant(&mut c, "vda5050/agv1");

    // A goal becomes an order: from the node the vehicle stands on to a node at the goal.
    goal(&mut c, drive, 8.0, 0.0);
    let mut updates = Vec::new();
    let seen = statuses_and_data(&mut c, drive, 20 * SEC, done, &mut updates);
    let last = seen.last().unwrap();
    assert_eq!(
        last,
        &TaskStatus::Done("arrived at muster-goal-0 (8.00, 0.00)".into()),
        "{seen:?}"
    );
    let notes: Vec<&str> = seen.iter().filter_map(|s| s.detail()).collect();
    assert!(
        notes
            .iter()
            .any(|n| n.starts_with("order muster-") && n.ends_with("/0 sent: to (8.00, 0.00)")),
        "{notes:?}"
    );
    assert!(
        notes.iter().any(
            |n| n.starts_with("driving to (8.00, 0.00): 1 nodes left") && n.contains("m to go")
        ),
        "{notes:?}"
    );
    let p = f.proc(agv);
    let order = wait_event(p, "order", 5 * SEC);
    let nodes: Vec<&str> = order["message"]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n["nodeId"].as_str().unwrap())
        .collect();
    assert_eq!(nodes, ["0", "muster-goal-0"]);
    let order_id = order["message"]["orderId"].as_str().unwrap().to_string();
    let fin = state_until(p, 5 * SEC, |s| {
        s["orderId"] == order_id.as_str()
            && s["nodeStates"].as_array().unwrap().is_empty()
            && s["driving"] == false
    });
    assert_eq!(fin["lastNodeId"], "muster-goal-0");
    assert!((fin["x"].as_f64().unwrap() - 8.0).abs() < 0.01, "{fin}");

    // The data session saw the vehicle drive.
    while let Ok(Some(e)) = c.try_event() {
        if let UserEvent::Update {
            payload: Payload::Encoded { data, .. },
            ..
        } = e
        {
            updates.push(serde_json::from_slice(&data).unwrap());
        }
    }
    assert!(updates.iter().all(|j| j["serial"] == "agv1"));
    let xs: Vec<f64> = updates.iter().map(|j| j["x"].as_f64().unwrap()).collect();
    assert!(xs.len() >= 3, "{xs:?}");
    assert!(
        xs.windows(2).all(|w| w[1] >= w[0] - 1e-9),
        "x only grows: {xs:?}"
    );
    assert!((xs.last().unwrap() - 8.0).abs() < 0.01, "{xs:?}");

    // The next goal of the session updates the same order from the node reached; a
    // goal given while driving is stitched onto the end of the base.
    goal(&mut c, drive, 8.0, 6.0);
    let seen = statuses_until(&mut c, drive, 20 * SEC, |s| {
        s.detail().is_some_and(|d| d.starts_with("driving"))
    });
    assert!(!done(seen.last().unwrap()));
    goal(&mut c, drive, 0.0, 6.0);
    let seen = statuses_until(&mut c, drive, 30 * SEC, |s| {
        matches!(s, TaskStatus::Done(d) if d.starts_with("arrived at muster-goal-2"))
            || matches!(s, TaskStatus::Rejected(_))
    });
    assert_eq!(
        seen.last().unwrap(),
        &TaskStatus::Done("arrived at muster-goal-2 (0.00, 6.00)".into()),
        "{seen:?}"
    );
    let p = f.proc(agv);
    let u1 = wait_event(p, "order", 5 * SEC);
    let u2 = wait_event(p, "order", 5 * SEC);
    for (u, id, first, seq) in [(&u1, 1, "muster-goal-0", 2), (&u2, 2, "muster-goal-1", 4)] {
        assert_eq!(u["message"]["orderId"], order_id.as_str());
        assert_eq!(u["message"]["orderUpdateId"], id);
        assert_eq!(u["message"]["nodes"][0]["nodeId"], first, "{u}");
        assert_eq!(u["message"]["nodes"][0]["sequenceId"], seq, "{u}");
    }
    let fin = state_until(p, 5 * SEC, |s| {
        s["orderUpdateId"] == 2
            && s["nodeStates"].as_array().unwrap().is_empty()
            && s["driving"] == false
    });
    assert!(fin["errors"].as_array().unwrap().is_empty(), "{fin}");
    assert!(
        fin["x"].as_f64().unwrap().abs() < 0.01 && (fin["y"].as_f64().unwrap() - 6.0).abs() < 0.01,
        "{fin}"
    );

    // Ending the session while the vehicle drives cancels its order.
    goal(&mut c, drive, 30.0, 6.0);
    statuses_until(&mut c, drive, 10 * SEC, |s| {
        s.detail().is_some_and(|d| d.starts_with("driving")) && to_go(s).is_some_and(|m| m < 28.0)
    });
    c.end(drive);
    let p = f.proc(agv);
    let cancel = wait_event(p, "instantActions", 5 * SEC);
    assert_eq!(
        cancel["message"]["instantActions"][0]["actionType"],
        "cancelOrder"
    );
    let stopped = state_until(p, 10 * SEC, |s| {
        s["actions"]
            .as_array()
            .unwrap()
            .iter()
            .any(|a| a == "cancelOrder:FINISHED")
    });
    assert_eq!(stopped["driving"], false);
    assert!(stopped["nodeStates"].as_array().unwrap().is_empty());
    let x = stopped["x"].as_f64().unwrap();
    assert!(x > 0.0 && x < 29.0, "stopped on the way: {stopped}");

    // A message breaking the rules is refused and not acted on: a state with a heading
    // outside [-π, π] (and a made-up position) does not reach the data session.
    let bad = agv1_state(50.0, 99.0, 4.0);
    let p = f.proc(agv);
    p.send(&format!("raw {iface}/v2/acme/agv1/state {bad}"));
    // The sniffer calls it invalid too (the one message expected to be).
    let deadline = Instant::now() + 5 * SEC;
    let (mut sent, mut flagged) = (false, false);
    while !(sent && flagged) {
        let v = p
            .json(deadline.saturating_duration_since(Instant::now()))
            .expect("the peer's word on the bad state");
        match v["event"].as_str() {
            Some("sent") => sent = true,
            Some("invalid") => {
                assert_eq!(v["payload"]["agvPosition"]["theta"], 4.0, "{v}");
                flagged = true;
            }
            _ => {}
        }
    }

    // Offline: withdrawn, its users told; online again: offered again.
    let watch_ended = |c: &mut UserClient| loop {
        match c.next_event(Instant::now() + 10 * SEC).unwrap() {
            Some(UserEvent::Ended {
                session, reason, ..
            }) if session == watch => return reason,
            Some(UserEvent::Update {
                payload: Payload::Encoded { data, .. },
                ..
            }) => {
                let j: Value = serde_json::from_slice(&data).unwrap();
                assert_ne!(j["x"], 99.0, "the refused state was acted on: {j}");
            }
            Some(_) => {}
            None => panic!("the data session did not end"),
        }
    };
    f.proc(agv).send("offline agv1");
    assert_eq!(watch_ended(&mut c), EndReason::Withdrawn);
    let (l, _) = f.wait_list(10 * SEC, |l| {
        find(l, "vda5050/agv1").is_some_and(|s| s["withdrawn"] == true)
    });
    assert_eq!(find(&l, "vda5050/agv1.state").unwrap()["withdrawn"], true);
    f.proc(agv).send("online agv1");
    f.wait_list(10 * SEC, |l| {
        find(l, "vda5050/agv1").is_some_and(|s| s["withdrawn"] == false)
    });
    let drive = grant(&mut c, "vda5050/agv1");
    goal(&mut c, drive, 0.0, 0.0);
    let seen = statuses_until(&mut c, drive, 20 * SEC, done);
    assert!(
        matches!(seen.last().unwrap(), TaskStatus::Done(_)),
        "{seen:?}"
    );

    // Every message both ways passed the library's schema checks, but the test's own.
    let p = f.proc(agv);
    p.send("stats");
    let stats = wait_for(p, 5 * SEC, |v| v["event"] == "checked");
    assert_eq!(
        stats["invalid"], 1,
        "only the test's own bad state: {stats}"
    );
    let by = &stats["byTopic"];
    for topic in [
        "order",
        "instantActions",
        "state",
        "connection",
        "visualization",
    ] {
        assert!(
            by[topic].as_u64().unwrap_or(0) >= 1,
            "no {topic} checked: {stats}"
        );
    }
    assert!(by["order"].as_u64().unwrap() >= 5, "{stats}");

    // The process dies without a word: the last will withdraws it.
    p.send("exit");
    f.wait_list(10 * SEC, |l| {
        find(l, "vda5050/agv1").is_some_and(|s| s["withdrawn"] == true)
    });
    c.close();
    f.proc(fleet).signal(libc::SIGTERM);
    let counts = f.proc(fleet).json(10 * SEC).expect("the bridge's counters");
    assert_eq!(counts["vehicles"], 1, "{counts}");
    assert!(counts["invalid"].as_u64().unwrap() >= 1, "{counts}");
    assert_eq!(counts["cancels"], 1, "{counts}");
    assert!(counts["orders"].as_u64().unwrap() >= 5, "{counts}");
}

/// A headerless order: `nodes` as (id, sequence id, x, y, released), each edge joining
/// two neighbours (released with its end node).
fn order(id: &str, update: u32, nodes: &[(&str, u32, f64, f64, bool)]) -> String {
    let ns: Vec<Value> = nodes
        .iter()
        .map(|(n, seq, x, y, rel)| {
            serde_json::json!({"nodeId": n, "sequenceId": seq, "released": rel, "actions": [],
                "nodePosition": {"x": x, "y": y, "mapId": "muster"}})
        })
        .collect();
    let es: Vec<Value> = nodes
        .windows(2)
        .map(|w| {
            serde_json::json!({"edgeId": format!("{}-{}", w[0].0, w[1].0), "sequenceId": w[0].1 + 1,
                "released": w[1].4, "startNodeId": w[0].0, "endNodeId": w[1].0, "actions": []})
        })
        .collect();
    serde_json::json!({"orderId": id, "orderUpdateId": update, "nodes": ns, "edges": es})
        .to_string()
}

/// The master's events up to `orderProcessed` of `id`: the nodes traversed, and that.
fn processed(p: &mut Proc, id: &str, timeout: Duration) -> (Vec<String>, Value) {
    let mut nodes = Vec::new();
    let deadline = Instant::now() + timeout;
    loop {
        let v = wait_for(p, deadline.saturating_duration_since(Instant::now()), |v| {
            v["event"] == "nodeTraversed" || (v["event"] == "orderProcessed" && v["orderId"] == id)
        });
        if v["event"] == "orderProcessed" {
            return (nodes, v);
        }
        nodes.push(v["nodeId"].as_str().unwrap().to_string());
    }
}

fn connection_state(p: &mut Proc, state: &str, timeout: Duration) -> Value {
    wait_for(p, timeout, |v| says_connection(v, state))
}

/// Whether a line of the peer is D1's connection message saying `state`.
fn says_connection(v: &Value, state: &str) -> bool {
    v["event"] == "connection" && v["serial"] == "D1" && v["message"]["connectionState"] == state
}

#[test]
fn a_simulated_robot_is_a_vda5050_vehicle_that_vda_5050_libs_master_control_drives() {
    if !peers_here() {
        return;
    }
    let mut f = Fed::new("vda2");
    let mqtt = mosquitto(&mut f);
    let iface = format!("u{}", std::process::id());
    f.spawn(&["sim", "--speed", "3"]);
    let agv_args = [
        "agv",
        "--mqtt",
        &mqtt,
        "--interface",
        &iface,
        "--robots",
        "D1",
        "--vda-version",
        "2.0.0",
        "--stats-json",
    ];
    let agv = f.spawn(&agv_args);
    let master = master_control(&mut f, &mqtt, &iface);
    let p = f.proc(master);
    // The retained connection says ONLINE (whether it came before the master or after),
    // and the master says it is ready: in either order. (Waiting for one skips the
    // other's line: when `muster agv` connected after the master was ready, waiting for
    // ONLINE first passed over "ready", and the test then waited for it in vain.)
    let online = |v: &Value| says_connection(v, "ONLINE");
    let (mut is_online, mut is_ready) = (false, false);
    let deadline = Instant::now() + 30 * SEC;
    while !(is_online && is_ready) {
        let left = deadline.saturating_duration_since(Instant::now());
        let v = wait_for(p, left, |v| online(v) || v["event"] == "ready");
        is_online |= online(&v);
        is_ready |= v["event"] == "ready";
    }

    // An order along the corridor from where D1 stands: every node traversed, in order,
    // and processed without error within the deviation of the last node.
    let o1 = order(
        "o1",
        0,
        &[
            ("n0", 0, 30.0, 3.0, true),
            ("n1", 2, 26.0, 3.0, true),
            ("n2", 4, 22.0, 3.0, true),
        ],
    );
    p.send(&format!("order {o1}"));
    let (nodes, done) = processed(p, "o1", 60 * SEC);
    assert_eq!(nodes, ["n0", "n1", "n2"]);
    assert_eq!(done["withError"], Value::Null, "{done}");
    assert_eq!(
        (done["active"].clone(), done["byCancelation"].clone()),
        (false.into(), false.into())
    );
    assert_eq!(done["lastNodeId"], "n2");
    assert!(
        (done["x"].as_f64().unwrap() - 22.0).hypot(done["y"].as_f64().unwrap() - 3.0) <= 0.5,
        "{done}"
    );

    // An update stitched on n2 with a horizon: the base is driven, then the vehicle
    // waits (processed, still active); the next update releases the horizon.
    let u1 = order(
        "o1",
        1,
        &[
            ("n2", 4, 22.0, 3.0, true),
            ("n3", 6, 19.0, 3.0, true),
            ("n4", 8, 16.0, 3.0, false),
        ],
    );
    p.send(&format!("order {u1}"));
    let (nodes, done) = processed(p, "o1", 60 * SEC);
    // The library counts an order's first node traversed at once (the vehicle is on it).
    assert_eq!(nodes, ["n2", "n3"]);
    assert_eq!(done["active"], true, "only the horizon is left: {done}");
    let u2 = order(
        "o1",
        2,
        &[("n3", 6, 19.0, 3.0, true), ("n4", 8, 16.0, 3.0, true)],
    );
    p.send(&format!("order {u2}"));
    let (nodes, done) = processed(p, "o1", 60 * SEC);
    // (still the active order to the library: n3 is not reported again)
    assert_eq!(nodes, ["n4"]);
    assert_eq!(
        (done["active"].clone(), done["withError"].clone()),
        (false.into(), Value::Null)
    );

    // Paused while driving: stops; resumed: arrives.
    let o2 = order(
        "o2",
        0,
        &[("n4", 0, 16.0, 3.0, true), ("n5", 2, 10.0, 3.0, true)],
    );
    p.send(&format!("order {o2}"));
    state_until(p, 30 * SEC, |s| {
        s["orderId"] == "o2" && s["driving"] == true
    });
    p.send("instant startPause");
    let paused = state_until(p, 10 * SEC, |s| {
        s["paused"] == true && s["driving"] == false
    });
    assert!(
        paused["x"].as_f64().unwrap() > 10.5,
        "stopped before n5: {paused}"
    );
    // Once it has come to rest (its last command was under way), it stays.
    let mut at = Vec::new();
    for _ in 0..2 {
        std::thread::sleep(SEC);
        p.send("instant stateRequest");
        let s = state_until(p, 10 * SEC, |s| {
            s["actions"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|a| *a == "stateRequest:FINISHED")
                .count()
                > at.len()
        });
        at.push(s["x"].as_f64().unwrap());
    }
    assert!((at[1] - at[0]).abs() < 0.02, "moved while paused: {at:?}");
    assert!(at[1] > 10.5, "{at:?}");
    p.send("instant stopPause");
    let (nodes, done) = processed(p, "o2", 60 * SEC);
    // (n4's report went by while the test waited for the pause)
    assert_eq!(nodes.last().map(String::as_str), Some("n5"), "{nodes:?}");
    assert_eq!(done["withError"], Value::Null, "{done}");

    // Cancelled while driving.
    let o3 = order(
        "o3",
        0,
        &[("n5", 0, 10.0, 3.0, true), ("n6", 2, 24.0, 3.0, true)],
    );
    p.send(&format!("order {o3}"));
    state_until(p, 30 * SEC, |s| {
        s["orderId"] == "o3" && s["driving"] == true
    });
    p.send("instant cancelOrder");
    let (_, done) = processed(p, "o3", 30 * SEC);
    assert_eq!(done["byCancelation"], true, "{done}");
    // The state that stopped it may be the very one that finished the cancel, printed
    // (by the sniffer) before the library's event, and the next comes in 30 s: ask.
    p.send("instant stateRequest");
    let stopped = state_until(p, 10 * SEC, |s| s["driving"] == false);
    assert!(stopped["nodeStates"].as_array().unwrap().is_empty());
    assert!(stopped["x"].as_f64().unwrap() < 23.0, "{stopped}");

    // Refused: a new order whose first node is not where the vehicle stands.
    let far = order(
        "o4",
        0,
        &[("f0", 0, 5.0, 15.0, true), ("f1", 2, 6.0, 15.0, true)],
    );
    p.send(&format!("order {far}"));
    let (_, done) = processed(p, "o4", 30 * SEC);
    let err = done["withError"].as_str().unwrap_or_default();
    assert!(err.starts_with("noRouteError"), "{done}");

    // A message breaking the schema is refused by the vehicle, which says so in its
    // state (a validationError); the sniffer flags it too: the one invalid message.
    p.send(&format!(
        "raw {iface}/v2/muster/D1/order {{\"orderId\": 5}}"
    ));
    let deadline = Instant::now() + 10 * SEC;
    let (mut said, mut flagged) = (false, false);
    while !(said && flagged) {
        let v = p
            .json(deadline.saturating_duration_since(Instant::now()))
            .expect("the vehicle's and the sniffer's word on the bad order");
        flagged |= v["event"] == "invalid" && v["payload"]["orderId"] == 5;
        said |= v["event"] == "state"
            && v["errors"].as_array().unwrap().iter().any(|e| {
                e.as_str()
                    .unwrap()
                    .starts_with("validationError: not a valid order message")
            });
    }
    p.send("stats");
    let stats = wait_for(p, 5 * SEC, |v| v["event"] == "checked");
    assert_eq!(stats["invalid"], 1, "{stats}");
    for topic in [
        "order",
        "instantActions",
        "state",
        "connection",
        "factsheet",
        "visualization",
    ] {
        assert!(
            stats["byTopic"][topic].as_u64().unwrap_or(0) >= 1,
            "no {topic}: {stats}"
        );
    }

    // Stopped in order: OFFLINE; killed: the broker's last will, CONNECTIONBROKEN.
    f.proc(agv).signal(libc::SIGTERM);
    connection_state(f.proc(master), "OFFLINE", 10 * SEC);
    let counts = f.proc(agv).json(10 * SEC).expect("the vehicles' counters");
    assert_eq!(counts["invalid"], 1, "{counts}");
    let again = f.spawn(&agv_args);
    connection_state(f.proc(master), "ONLINE", 30 * SEC);
    f.proc(again).signal(libc::SIGKILL);
    connection_state(f.proc(master), "CONNECTIONBROKEN", 15 * SEC);
}

#[test]
fn with_a_road_map_a_goal_goes_to_the_nearest_node_along_the_shortest_path() {
    if !peers_here() {
        return;
    }
    let mut f = Fed::new("vda3");
    let mqtt = mosquitto(&mut f);
    let iface = format!("g{}", std::process::id());
    // A square missing its west side: from "0" to "c" the way is round by a and b.
    let graph = std::env::temp_dir().join(format!("muster-graph-{}.json", std::process::id()));
    std::fs::write(
        &graph,
        r#"{"mapId": "local", "nodes": [{"id": "0", "x": 0, "y": 0}, {"id": "a", "x": 5, "y": 0},
            {"id": "b", "x": 5, "y": 5}, {"id": "c", "x": 0, "y": 5}],
            "edges": [["0", "a"], ["a", "b"], ["b", "c"]]}"#,
    )
    .unwrap();
    let agv = virtual_agvs(&mut f, &mqtt, &iface, &["--speed", "8"]);
    f.broker(&[]);
    f.spawn(&[
        "system",
        "vda5050",
        "--mqtt",
        &mqtt,
        "--interface",
        &iface,
        "--vda-version",
        "2.0.0",
        "--graph",
        graph.to_str().unwrap(),
    ]);
    f.wait_list(20 * SEC, |l| l.len() == 2);
    std::fs::remove_file(&graph).unwrap();
    let mut c = user(&f);
    let drive = grant(&mut c, "vda5050/agv1");
    goal(&mut c, drive, 0.4, 4.7);
    let seen = statuses_until(&mut c, drive, 20 * SEC, done);
    assert_eq!(
        seen.last().unwrap(),
        &TaskStatus::Done("arrived at c (0.00, 5.00)".into()),
        "{seen:?}"
    );
    let o = wait_event(f.proc(agv), "order", 5 * SEC);
    let ids: Vec<&str> = o["message"]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n["nodeId"].as_str().unwrap())
        .collect();
    assert_eq!(ids, ["0", "a", "b", "c"]);
    // A node by name: back to b, as an update of the session's order.
    c.input(drive, Payload::Text("node b".into())).unwrap();
    let seen = statuses_until(&mut c, drive, 20 * SEC, done);
    assert_eq!(
        seen.last().unwrap(),
        &TaskStatus::Done("arrived at b (5.00, 5.00)".into()),
        "{seen:?}"
    );
    let o = wait_event(f.proc(agv), "order", 5 * SEC);
    assert_eq!(o["message"]["orderUpdateId"], 1);
    let ids: Vec<&str> = o["message"]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n["nodeId"].as_str().unwrap())
        .collect();
    assert_eq!(ids, ["c", "b"]);
    // Names not on the map, and text that names no node, are refused with the reason.
    c.input(drive, Payload::Text("node z".into())).unwrap();
    let seen = statuses_until(&mut c, drive, 5 * SEC, done);
    assert_eq!(
        seen.last().unwrap(),
        &TaskStatus::Rejected("node \"z\" is not on the road map".into())
    );
    c.input(drive, Payload::Text("go west".into())).unwrap();
    let seen = statuses_until(&mut c, drive, 5 * SEC, done);
    assert!(
        matches!(seen.last().unwrap(), TaskStatus::Rejected(r) if r.contains("send `node ID`")),
        "{seen:?}"
    );
    c.close();
}

#[test]
fn the_vda5050_bench_runs_small_and_reports_what_it_timed() {
    if !peers_here() {
        return;
    }
    let f = Fed::new("vda4");
    let (code, out) = f.run(
        &[
            "bench",
            "vda5050",
            "--vehicles",
            "3",
            "--duration",
            "4s",
            "--goal-every",
            "1s",
            "--round-trips",
            "20",
            "--peers",
            JS,
            "--json",
        ],
        120 * SEC,
    );
    assert_eq!(code, 0, "{out}");
    let r: Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    assert_eq!(r["vehicles"], 3);
    assert_eq!(r["bridges"], 1);
    let goals = r["goals"].as_u64().unwrap();
    assert!(goals >= 6, "{r}");
    assert_eq!(r["refused"], 0, "{r}");
    assert_eq!(r["invalid"], 0, "{r}");
    assert_eq!(r["orders"], goals, "every goal an order: {r}");
    assert_eq!(r["mqtt_round_trip"]["count"], 20, "{r}");
    // Every order was acknowledged by a state, and every user saw it.
    assert_eq!(r["order_to_state"]["count"], goals, "{r}");
    assert_eq!(r["goal_to_vehicle_status"]["count"], goals, "{r}");
}

#[test]
fn both_bridges_reach_a_broker_that_asks_for_tls_and_a_password_and_a_user_drives_d1_through_them()
{
    if !peers_here() {
        return;
    }
    let mut f = Fed::new("vda5");
    let dir = std::env::temp_dir().join(format!("muster-mqtt-tls-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let d = |name: &str| dir.join(name).to_str().unwrap().to_string();
    // The broker's certificate from muster's own authority tool; a password file made
    // by mosquitto's.
    let (code, out) = f.run(&["certs", "--out", &d(""), "--hosts", "mqtt"], 30 * SEC);
    assert_eq!(code, 0, "{out}");
    let made = Command::new("mosquitto_passwd")
        .args(["-b", "-c", &d("passwd"), "fleet", "s3cret"])
        .status()
        .unwrap();
    assert!(made.success());
    std::fs::write(d("pw"), "s3cret\n").unwrap();
    std::fs::write(d("wrong"), "guess\n").unwrap();
    let port = free_tcp_port();
    std::fs::write(
        d("mosquitto.conf"),
        format!(
            "listener {port} 127.0.0.1\ncafile {}\ncertfile {}\nkeyfile {}\npassword_file {}\n\
             allow_anonymous false\npersistence false\nuser root\n",
            d("ca.pem"),
            d("mqtt.pem"),
            d("mqtt.key"),
            d("passwd")
        ),
    )
    .unwrap();
    let mut c = Command::new("mosquitto");
    c.arg("-c").arg(d("mosquitto.conf"));
    f.spawn_command(c);
    let mqtt = format!("127.0.0.1:{port}");
    let deadline = Instant::now() + 10 * SEC;
    while std::net::TcpStream::connect(&mqtt).is_err() {
        assert!(Instant::now() < deadline, "mosquitto did not listen");
        std::thread::sleep(Duration::from_millis(50));
    }
    let iface = format!("s{}", std::process::id());
    let secure = [
        "--mqtt-ca",
        &d("ca.pem"),
        "--mqtt-user",
        "fleet",
        "--mqtt-password-file",
    ];
    f.broker(&[]);
    f.spawn(&["sim", "--speed", "3"]);
    let mut agv = vec![
        "agv",
        "--mqtt",
        &mqtt,
        "--interface",
        &iface,
        "--robots",
        "D1",
    ];
    agv.extend(secure);
    let pw = d("pw");
    agv.push(&pw);
    f.spawn(&agv);
    // A bridge with the wrong password never lists anything; the right one lists D1.
    let wrong = d("wrong");
    let mut bad = vec![
        "system",
        "vda5050",
        "--name",
        "nope",
        "--mqtt",
        &mqtt,
        "--interface",
        &iface,
    ];
    bad.extend(secure);
    bad.push(&wrong);
    f.spawn(&bad);
    let mut good = vec!["system", "vda5050", "--mqtt", &mqtt, "--interface", &iface];
    good.extend(secure);
    good.push(&pw);
    f.spawn(&good);
    let (list, _) = f.wait_list(30 * SEC, |l| find(l, "vda5050/D1").is_some());
    assert!(list.iter().all(|s| s["system"] == "vda5050"), "{list:?}");
    // A muster user → the bridge → TLS MQTT → muster's D1 on the simulator.
    let mut u = user(&f);
    let drive = grant(&mut u, "vda5050/D1");
    goal(&mut u, drive, 26.0, 3.0);
    let seen = statuses_until(&mut u, drive, 60 * SEC, done);
    assert!(
        matches!(seen.last().unwrap(), TaskStatus::Done(d) if d.starts_with("arrived at muster-goal-0")),
        "{seen:?}"
    );
    u.close();
    // Still nothing from the bridge with the wrong password.
    assert!(f.list().iter().all(|s| s["system"] == "vda5050"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn muster_sim_with_vda5050_makes_its_robots_vehicles_and_takes_them_away_when_it_stops() {
    if !peers_here() {
        return;
    }
    let mut f = Fed::new("vda6");
    let mqtt = mosquitto(&mut f);
    let master = master_control(&mut f, &mqtt, "uagv");
    wait_event(f.proc(master), "ready", 20 * SEC);
    let sim = f.spawn(&["sim", "--vda5050", &mqtt, "--vda5050-robots", "D1,T1"]);
    // Both robots say they are online and describe themselves; nothing else does.
    let mut seen = std::collections::BTreeSet::new();
    while seen.len() < 4 {
        let v = wait_for(f.proc(master), 30 * SEC, |v| {
            v["event"] == "factsheet" || v["event"] == "connection"
        });
        assert!(["D1", "T1"].contains(&v["serial"].as_str().unwrap()), "{v}");
        if v["event"] == "connection" {
            assert_eq!(v["message"]["connectionState"], "ONLINE", "{v}");
        }
        seen.insert(format!("{} {}", v["serial"], v["event"]));
    }
    // The simulator stops in order, and its vehicles with it.
    f.proc(sim).signal(libc::SIGTERM);
    connection_state(f.proc(master), "OFFLINE", 15 * SEC);
}

#[test]
fn json_schemas_given_are_checked_on_every_message_with_the_official_ones_among_them() {
    if !peers_here() {
        return;
    }
    let mut f = Fed::new("vda7");
    let mqtt = mosquitto(&mut f);
    let iface = format!("j{}", std::process::id());
    // The official connection schema vda-5050-cli ships (with the files it refers to),
    // and a stricter state schema of our own: a charge above 100 % is refused.
    let dir = std::env::temp_dir().join(format!("muster-vda-schemas-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let official = std::path::Path::new(JS).join("node_modules/vda-5050-cli/schema/v1.1");
    assert!(
        official.exists(),
        "vda-5050-cli is not installed: run .ci/run's setup"
    );
    for name in [
        "common.schema.json",
        "header.schema.json",
        "connection.schema.json",
    ] {
        std::fs::copy(official.join(name), dir.join(name)).unwrap();
    }
    std::fs::write(
        dir.join("state.schema.json"),
        r#"{"$schema": "http://json-schema.org/draft-07/schema#", "type": "object",
            "required": ["batteryState"], "properties": {"batteryState": {"type": "object",
            "properties": {"batteryCharge": {"type": "number", "minimum": 0, "maximum": 100}}}}}"#,
    )
    .unwrap();
    let agv = virtual_agvs(&mut f, &mqtt, &iface, &[]);
    f.broker(&[]);
    let fleet = f.spawn(&[
        "system",
        "vda5050",
        "--mqtt",
        &mqtt,
        "--interface",
        &iface,
        "--vda-version",
        "2.0.0",
        "--vda-schemas",
        dir.to_str().unwrap(),
        "--stats-json",
    ]);
    // The vehicle's connection passed the official schema: it is listed.
    f.wait_list(20 * SEC, |l| find(l, "vda5050/agv1.state").is_some());
    let mut c = user(&f);
    let watch = grant(&mut c, "vda5050/agv1.state");
    // 140 % passes the Rust rules and the library's 2.0 schema, not the one given; the
    // next state (in order after it, same publisher and topic) does.
    let p = f.proc(agv);
    p.send(&format!(
        "raw {iface}/v2/acme/agv1/state {}",
        agv1_state(140.0, 7.0, 0.0)
    ));
    p.send(&format!(
        "raw {iface}/v2/acme/agv1/state {}",
        agv1_state(55.0, 8.0, 0.0)
    ));
    let deadline = Instant::now() + 10 * SEC;
    loop {
        match c.next_event(deadline).unwrap() {
            Some(UserEvent::Update {
                session,
                payload: Payload::Encoded { data, .. },
                ..
            }) if session == watch => {
                let j: Value = serde_json::from_slice(&data).unwrap();
                assert_ne!(
                    j["battery"], 140.0,
                    "a state the schema refuses was shown: {j}"
                );
                if j["battery"] == 55.0 {
                    assert_eq!(j["x"], 8.0);
                    break;
                }
            }
            Some(_) => {}
            None => panic!("the valid state after the refused one never came"),
        }
    }
    c.close();
    f.proc(fleet).signal(libc::SIGTERM);
    let counts = f.proc(fleet).json(10 * SEC).expect("the bridge's counters");
    assert_eq!(counts["invalid"], 1, "{counts}");
    let _ = std::fs::remove_dir_all(&dir);
}
