//! The SDK's examples (`examples/`), built by `cargo test` and run here as a new user
//! would run them: the door system and its user, and the thermometer that sleeps on a
//! socket of its own.

#![allow(clippy::unwrap_used)]

mod common;

use common::{Fed, BIN, SEC};
use serde_json::Value;
use std::process::Command;

/// An example's binary (beside the muster binary, in `examples/`).
fn example(name: &str) -> Command {
    let path = std::path::Path::new(BIN)
        .parent()
        .unwrap()
        .join("examples")
        .join(name);
    assert!(
        path.exists(),
        "{} is not built: `cargo test` builds the examples (or `cargo build --examples`)",
        path.display()
    );
    Command::new(path)
}

#[test]
fn the_door_example_opens_for_the_user_example() {
    let mut f = Fed::new("ex-door");
    f.broker(&[]);
    let mut door = example("door_system");
    door.args(["--instance", &f.inst]);
    f.spawn_command(door);
    f.wait_list(20 * SEC, |l| l.len() == 2);
    let list = f.list();
    let open = common::find(&list, "door/open").unwrap();
    assert_eq!(
        (open["kind"].as_str(), open["payload"].as_str()),
        (Some("command"), Some("text"))
    );
    // The user example: granted, opening, open; then the state streams "open".
    let out = example("door_user")
        .args(["--instance", &f.inst])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<&str> = text.lines().collect();
    let at = |needle: &str| {
        lines
            .iter()
            .position(|l| l.contains(needle))
            .unwrap_or_else(|| panic!("no {needle:?} in:\n{text}"))
    };
    assert!(at("listed: door/open (command, text)") < at("granted door/open"));
    assert!(at("granted door/open") < at("status: working: opening"));
    assert!(at("status: working: opening") < at("status: done: open"));
    assert!(at("status: done: open") < at("state #"));
    assert!(
        lines
            .iter()
            .filter(|l| l.starts_with("state #"))
            .all(|l| l.ends_with("text open")),
        "{text}"
    );
}

#[test]
fn the_thermometer_example_publishes_what_its_socket_reads() {
    let mut f = Fed::new("ex-thermo");
    f.broker(&[]);
    let mut t = example("thermometer");
    t.args(["127.0.0.1:0", "--instance", &f.inst]);
    let t = f.spawn_command(t);
    let addr: Value = f.proc(t).json(20 * SEC).unwrap();
    let addr = addr["listen"].as_str().unwrap().to_string();
    f.wait_list(20 * SEC, |l| {
        common::find(l, "thermometer/celsius").is_some()
    });
    let user = f.spawn(&[
        "user",
        "request",
        "thermometer/celsius",
        "--duration",
        "3s",
        "--json",
    ]);
    assert_eq!(f.proc(user).json(10 * SEC).unwrap()["granted"], true);
    let sensor = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    // The system hears of the session just after the user is granted: readings until
    // the first arrives.
    let deadline = std::time::Instant::now() + 10 * SEC;
    loop {
        sensor.send_to(b"20", &addr).unwrap();
        let v = f.proc(user).json(std::time::Duration::from_millis(200));
        if v.is_some_and(|v| v["payload"]["value"] == 20.0) {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "no reading arrived");
    }
    for reading in ["21.5", "not a number", "22"] {
        sensor.send_to(reading.as_bytes(), &addr).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let values: Vec<f64> = f
        .proc(user)
        .all_json(10 * SEC)
        .iter()
        .filter_map(|v| v["payload"]["value"].as_f64())
        .filter(|v| *v != 20.0)
        .collect();
    // Each reading once, in order; what is no reading, nothing.
    assert_eq!(values, [21.5, 22.0]);
}
