//! The paper's interactive menu: the service list numbered, plus refresh, link, end
//! and exit. Session data prints as it arrives (at most one line a second a session).

use crate::client::{UserClient, UserError, Wake};
use crate::core::UserEvent;
use muster_shared::snapshot::{ListPart, ServiceView};
use muster_shared::types::{Payload, Schema, ServiceId, SessionId};
use std::collections::HashMap;
use std::io::{BufRead, Write};
use std::os::fd::AsRawFd;
use std::os::unix::net::UnixStream;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// The service list as a numbered table.
pub fn table(views: &[ServiceView]) -> String {
    // Columns as wide as their longest entry (open payload types are long names).
    let id_w = views.iter().map(|v| v.id.len()).max().unwrap_or(0).max(24);
    let pay_w = views
        .iter()
        .map(|v| v.payload.len())
        .max()
        .unwrap_or(0)
        .max(8);
    let mut out = format!(
        "{:<4} {:<id_w$} {:<8} {:<pay_w$} {:>9} {:<5} {}\n",
        "#", "ID", "KIND", "PAYLOAD", "IN USE", "QUEUE", "DESCRIPTION"
    );
    for (i, v) in views.iter().enumerate() {
        let usage = format!("{}/{}", v.in_use, v.quota);
        let queue = if v.queue {
            v.queued.to_string()
        } else {
            "-".into()
        };
        let mark = if v.withdrawn { " [withdrawn]" } else { "" };
        out.push_str(&format!(
            "{:<4} {:<id_w$} {:<8} {:<pay_w$} {:>9} {:<5} {}{}\n",
            i + 1,
            v.id,
            v.kind,
            v.payload,
            usage,
            queue,
            v.description,
            mark
        ));
    }
    out.trim_end().to_string()
}

const HELP: &str = "\
  N            request service N
  r            refresh the list
  l D C        link data service D into command service C
  g S X Y      send goal (X, Y) on session S
  i S JSON     send any input on session S: \"text\", 2.5, {\"type\": \"goal2d\", \"x\": 1, \"y\": 2},
               or an open type's {\"type\": \"pkg/msg/T\", \"value\": {..}}
  s            show open sessions
  e S          end session S
  x            exit";

/// Runs the menu on the terminal until `x`, end of input, or Ctrl-C.
pub fn run(mut client: UserClient, part: &ListPart) -> Result<(), UserError> {
    let (lines_tx, lines_rx) = mpsc::channel::<String>();
    let (wake_read, mut wake_write) = UnixStream::pair()?;
    wake_read.set_nonblocking(true)?;
    std::thread::spawn(move || {
        let stdin = std::io::stdin();
        for line in stdin.lock().lines() {
            let Ok(line) = line else { break };
            if lines_tx.send(line).is_err() || wake_write.write_all(b"x").is_err() {
                return;
            }
        }
        drop(lines_tx);
        let _ = wake_write.write_all(b"x");
    });
    client.watch_extra(wake_read.as_raw_fd())?;
    let mut views = client.list_part(part)?.views();
    println!("{}\n{HELP}", table(&views));
    prompt();
    // Open sessions, in the order granted, with the schema of each's payload if any.
    let mut sessions: Vec<(SessionId, Option<Schema>)> = Vec::new();
    let mut last_print: HashMap<SessionId, Instant> = HashMap::new();
    let mut stale = false;
    loop {
        let wake = match client.wait(Instant::now() + Duration::from_secs(3600)) {
            Ok(w) => w,
            Err(UserError::Interrupted) => break,
            Err(e) => return Err(e),
        };
        match wake {
            Wake::Timeout => {}
            Wake::Event(e) => show_event(&e, &mut sessions, &mut last_print, &mut stale),
            Wake::Extra => {
                let mut drain = [0u8; 64];
                while std::io::Read::read(&mut &wake_read, &mut drain).is_ok_and(|n| n > 0) {}
                loop {
                    match lines_rx.try_recv() {
                        Ok(line) => {
                            if !command(
                                &mut client,
                                line.trim(),
                                (part, &mut views),
                                &sessions,
                                &mut stale,
                            )? {
                                client.close();
                                return Ok(());
                            }
                            prompt();
                        }
                        Err(mpsc::TryRecvError::Empty) => break,
                        Err(mpsc::TryRecvError::Disconnected) => {
                            client.close();
                            return Ok(());
                        }
                    }
                }
            }
        }
    }
    client.close();
    Ok(())
}

fn prompt() {
    print!("> ");
    let _ = std::io::stdout().flush();
}

fn show_event(
    e: &UserEvent,
    sessions: &mut Vec<(SessionId, Option<Schema>)>,
    last_print: &mut HashMap<SessionId, Instant>,
    stale: &mut bool,
) {
    match e {
        UserEvent::ListChanged => {
            if !*stale {
                println!("\n(the service list changed: r to refresh)");
                *stale = true;
            }
        }
        UserEvent::Granted {
            session,
            service,
            kind,
            schema,
            ..
        } => {
            sessions.push((*session, schema.clone()));
            println!(
                "\ngranted: session {} on {service} ({kind})",
                sessions.len()
            );
        }
        UserEvent::Refused {
            service, reason, ..
        } => println!("\nrefused {service}: {reason}"),
        UserEvent::Queued {
            service, position, ..
        } => {
            println!("\n{service}: queued at position {position}")
        }
        UserEvent::Update {
            session,
            service,
            seq,
            payload,
            ..
        } => {
            let now = Instant::now();
            let due = last_print
                .get(session)
                .is_none_or(|t| now.duration_since(*t) >= Duration::from_secs(1));
            if due {
                last_print.insert(*session, now);
                println!("{service} #{seq}: {payload}");
            }
        }
        UserEvent::Status {
            service, status, ..
        } => println!("{service}: {status}"),
        UserEvent::Ended {
            session,
            service,
            reason,
            lost_at_end,
        } => {
            sessions.retain(|(s, _)| s != session);
            let lost = match lost_at_end {
                0 => String::new(),
                n => format!(" (its last {n} never came)"),
            };
            println!("\nsession on {service} ended: {reason}{lost}");
        }
        UserEvent::LinkUp { link } => println!("\nlink {link} up"),
        UserEvent::LinkEnded { link, reason } => println!("\nlink {link} ended: {reason}"),
        UserEvent::BrokerLost => println!("\n(broker lost: sessions go on; new requests wait)"),
        UserEvent::Connected { .. } => println!("\n(connected to a broker)"),
        UserEvent::LinkForwarded { .. }
        | UserEvent::EndConfirmed { .. }
        | UserEvent::Operated { .. }
        | UserEvent::Feed(_) => {}
    }
}

fn pick(views: &[ServiceView], s: &str) -> Option<ServiceId> {
    let n: usize = s.parse().ok()?;
    views
        .get(n.checked_sub(1)?)
        .map(|v| ServiceId(v.id.clone()))
}

/// Handles one typed line; `false` means exit.
fn command(
    client: &mut UserClient,
    line: &str,
    (part, views): (&ListPart, &mut Vec<ServiceView>),
    sessions: &[(SessionId, Option<Schema>)],
    stale: &mut bool,
) -> Result<bool, UserError> {
    let session = |n: &str| {
        n.parse::<usize>()
            .ok()
            .and_then(|n| sessions.get(n.checked_sub(1)?))
    };
    // `i S JSON`: the JSON is the rest of the line, spaces and all.
    if let Some(rest) = line.strip_prefix("i ") {
        let mut parts = rest.trim_start().splitn(2, ' ');
        let (n, json) = (
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
        );
        match (session(n), serde_json::from_str::<serde_json::Value>(json)) {
            (Some((s, schema)), Ok(v)) => match Payload::from_json(&v, schema.as_ref()) {
                Ok(p) => {
                    if let Err(e) = client.input(*s, p) {
                        println!("{e}");
                    }
                }
                Err(e) => println!("cannot send that: {e}"),
            },
            (None, _) => println!("no session {n} (s lists them)"),
            (_, Err(e)) => println!("not JSON: {e}"),
        }
        return Ok(true);
    }
    let words: Vec<&str> = line.split_whitespace().collect();
    match words.as_slice() {
        [] => {}
        ["x"] | ["exit"] | ["q"] => return Ok(false),
        ["r"] | ["refresh"] => {
            *views = client.list_part(part)?.views();
            *stale = false;
            println!("{}", table(views));
        }
        ["s"] => {
            for (i, (s, _)) in sessions.iter().enumerate() {
                let svc = client
                    .core()
                    .sessions()
                    .find(|(id, _, _)| id == s)
                    .map(|(_, svc, _)| svc.0.clone());
                println!("{}: {} {}", i + 1, s, svc.unwrap_or_default());
            }
        }
        ["e", n] => match session(n) {
            Some((s, _)) => client.end(*s),
            None => println!("no session {n} (s lists them)"),
        },
        ["l", d, c] => match (pick(views, d), pick(views, c)) {
            (Some(d), Some(c)) => match client.link(&d, &c) {
                Ok(l) => println!("linking {d} -> {c} (link {l})"),
                Err(e) => println!("{e}"),
            },
            _ => println!("link takes two service numbers from the list"),
        },
        ["g", n, x, y] => match (session(n), x.parse::<f64>(), y.parse::<f64>()) {
            (Some((s, _)), Ok(x), Ok(y)) => {
                if let Err(e) = client.input(*s, Payload::Goal2d { x, y }) {
                    println!("{e}");
                }
            }
            _ => println!("usage: g SESSION X Y"),
        },
        [n] if n.parse::<usize>().is_ok() => match pick(views, n) {
            Some(id) => {
                client.request(&id)?;
                println!("requested {id}");
            }
            None => println!("no service {n} in the list (r refreshes)"),
        },
        _ => println!("?\n{HELP}"),
    }
    Ok(true)
}
