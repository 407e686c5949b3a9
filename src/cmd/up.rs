//! `muster up`: the main job on the built-in default scenario.
//!
//! Starts a broker and synthetic systems as child processes (three tracker-like data
//! services on `t1`, one delivery-like command service with a task queue on `d1`),
//! then acts as a user: lists, requests a data service, links tracker to delivery.
//! Runs until Ctrl-C (or `--duration`), then stops its children cleanly.

use super::children::Children;
use crate::cli::UpArgs;
use muster_shared::types::ServiceId;
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient, UserError, UserEvent};
use std::process::{ExitCode, Stdio};
use std::time::{Duration, Instant};

pub fn run(inst: &Instance, a: UpArgs) -> anyhow::Result<ExitCode> {
    let mut children = Children::default();
    children.spawn(inst, "broker", &["broker"], Stdio::inherit())?;
    children.spawn(
        inst,
        "tracker system t1",
        &[
            "system",
            "synthetic",
            "--name",
            "t1",
            "--services",
            "3",
            "--kind",
            "data",
            "--quota",
            "10",
        ],
        Stdio::inherit(),
    )?;
    children.spawn(
        inst,
        "delivery system d1",
        &[
            "system",
            "synthetic",
            "--name",
            "d1",
            "--services",
            "1",
            "--kind",
            "command",
            "--quota",
            "1",
            "--queue",
        ],
        Stdio::inherit(),
    )?;
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(10),
        handle_signals: true,
        watch_list: false,
    };
    let mut client = UserClient::connect(inst, &opts)?;
    let end = a.duration.map(|d| Instant::now() + d);
    match demo(&mut client, end) {
        Ok(()) | Err(UserError::Interrupted) => {}
        Err(e) => return Err(e.into()),
    }
    client.close();
    children.stop();
    println!("muster up: stopped");
    Ok(ExitCode::SUCCESS)
}

fn wait_for_services(client: &mut UserClient, n: usize) -> Result<(), UserError> {
    let deadline = Instant::now() + Duration::from_secs(10);
    while client.list()?.count < n as u32 && Instant::now() < deadline {
        let _ = client.next_event(Instant::now() + Duration::from_millis(200))?;
    }
    Ok(())
}

fn demo(client: &mut UserClient, end: Option<Instant>) -> Result<(), UserError> {
    wait_for_services(client, 4)?;
    let list = client.list()?;
    println!("== service list (generation {}) ==", list.generation);
    println!("{}", muster_users::menu::table(&list.views()));

    let tracker = ServiceId::new("t1", "s0");
    let delivery = ServiceId::new("d1", "s0");
    println!("\n== request {tracker} for 2 s ==");
    let req = client.request(&tracker)?;
    let mut session = None;
    let until = Instant::now() + Duration::from_secs(2);
    while let Some(e) = client.next_event(until)? {
        match e {
            UserEvent::Granted {
                req: r, session: s, ..
            } if r == req => {
                println!("granted: session {s}");
                session = Some(s);
            }
            UserEvent::Refused { req: r, reason, .. } if r == req => println!("refused: {reason}"),
            UserEvent::Update { seq, payload, .. } => println!("  #{seq} {payload}"),
            _ => {}
        }
    }
    if let Some(s) = session {
        client.end(s);
        println!("session ended by the user");
    }

    println!("\n== link {tracker} -> {delivery} ==");
    let link = client.link(&tracker, &delivery)?;
    let mut shown = 0u32;
    loop {
        let deadline = end.unwrap_or(Instant::now() + Duration::from_secs(3600));
        let Some(e) = client.next_event(deadline)? else {
            break;
        };
        match e {
            UserEvent::LinkUp { link: l } if l == link => {
                println!("link up: tracker positions become delivery goals (Ctrl-C to stop)")
            }
            UserEvent::LinkForwarded { input, .. } if shown.is_multiple_of(10) => {
                println!("  forwarded {input}");
                shown += 1;
            }
            UserEvent::LinkForwarded { .. } => shown += 1,
            UserEvent::Status { status, .. } if shown % 10 == 1 => println!("  delivery: {status}"),
            UserEvent::LinkEnded { link: l, reason } if l == link => {
                println!("link ended: {reason}");
                break;
            }
            UserEvent::BrokerLost => println!("(broker lost; the link goes on)"),
            _ => {}
        }
    }
    Ok(())
}
