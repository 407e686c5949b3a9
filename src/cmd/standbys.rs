//! A standby broker kept running beside a `muster up` run: it takes over when the
//! primary dies or hangs, the run says so, and a fresh standby takes its place.

use super::children::Children;
use muster_shared::Instance;
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::process::Stdio;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::Duration;

/// The standby (and, after a takeover, the broker it became), on a thread of its own.
pub struct Standbys {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Standbys {
    /// Keeps one standby running with `broker_args` (those of the primary: its UDP
    /// address and key, so remote users find the new primary where the old one was).
    pub fn start(inst: &Instance, broker_args: Vec<String>) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let inst = inst.clone();
        let thread = std::thread::spawn(move || keep(&inst, &broker_args, &flag));
        Standbys {
            stop,
            thread: Some(thread),
        }
    }

    /// Stops the standbys (and a broker one of them became), newest first.
    pub fn stop(mut self) {
        self.halt();
    }

    fn halt(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Standbys {
    fn drop(&mut self) {
        self.halt();
    }
}

fn keep(inst: &Instance, broker_args: &[String], stop: &AtomicBool) {
    let mut kids = Children::default();
    let (tx, rx) = mpsc::channel::<(usize, Value)>();
    let spawn = |n: usize, kids: &mut Children| {
        let mut args = vec!["broker", "--standby"];
        args.extend(broker_args.iter().map(String::as_str));
        match kids.spawn(inst, &format!("standby broker {n}"), &args, Stdio::piped()) {
            Ok(child) => {
                if let Some(out) = child.stdout.take() {
                    let tx = tx.clone();
                    std::thread::spawn(move || {
                        for line in BufReader::new(out).lines().map_while(Result::ok) {
                            if let Ok(v) = serde_json::from_str::<Value>(&line) {
                                if tx.send((n, v)).is_err() {
                                    break;
                                }
                            }
                        }
                    });
                }
            }
            Err(e) => eprintln!("muster up: cannot start a standby broker: {e}"),
        }
    };
    let mut n = 1;
    spawn(n, &mut kids);
    while !stop.load(Ordering::Relaxed) {
        let Ok((from, v)) = rx.recv_timeout(Duration::from_millis(100)) else {
            continue;
        };
        match v["event"].as_str() {
            Some("took_over") => println!(
                "muster up: the broker {}; standby broker {from} took over (term {}, {})",
                match v["why"].as_str() {
                    Some("died") => "died",
                    Some("hung") => "stopped answering",
                    Some("stopped") => "was stopped",
                    Some("steppeddown") => "stepped down",
                    _ => "was gone",
                },
                v["term"],
                if v["replicated"] == true {
                    "with the whole state"
                } else {
                    "starting cold"
                }
            ),
            Some("serving") => {
                println!(
                    "muster up: standby broker {from} serves, {} ms after taking over; starting a new standby",
                    v["ready_us"].as_u64().unwrap_or(0) / 1000
                );
                n += 1;
                spawn(n, &mut kids);
            }
            _ => {}
        }
    }
    // Newest first, one at a time: the standbys go before the broker they follow, so
    // that it stops for good instead of handing over.
    for i in (1..=n).rev() {
        kids.stop_one(&format!("standby broker {i}"));
    }
}
