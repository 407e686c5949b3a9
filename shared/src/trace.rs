//! Stamps along a service request's path, for `muster stress`'s per-hop breakdown.
//!
//! With `MUSTER_TRACE_DIR` set, every process on the path notes when a request passed
//! it (CLOCK_MONOTONIC ns, one clock for every process on the host), keyed by the user
//! and its request number: the user sending it, the broker receiving it, sending the
//! offer and then the grant, the user receiving the grant; and off the user's path, the
//! system receiving the offer and confirming it, the broker taking the confirmation;
//! the user taking the session's first update, and the user hearing its request was
//! queued (it waits for a free place).
//! Each process writes its stamps to `DIR/trace-PID.csv` when it exits; the stress
//! harness joins them. Without the variable a stamp costs one load.

use crate::protocol::monotonic_ns;
use crate::types::UserId;
use std::io::Write;
use std::sync::{Mutex, OnceLock};

/// The environment variable naming the folder stamps go to.
pub const TRACE_DIR: &str = "MUSTER_TRACE_DIR";

/// Most stamps a process keeps.
const MAX_STAMPS: usize = 1 << 20;

/// Where on a request's path a stamp was made.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Stage {
    /// The user sent the request.
    UserSend,
    /// The broker took it from its inbox (or its UDP front).
    BrokerRecv,
    /// The broker sends the offer to the system.
    BrokerSend,
    /// The system took the offer.
    SystemRecv,
    /// The system opened the session and confirms it.
    SystemSend,
    /// The broker took the system's confirmation.
    BrokerAnswer,
    /// The broker sends the grant to the user (over shared memory or UDP).
    BrokerRelay,
    /// The user took the grant.
    UserRecv,
    /// The user took the session's first update (a data session: its system sends one
    /// as the session opens).
    FirstUpdate,
    /// The user heard its request was queued: it waits for a free place, and its grant
    /// comes when one frees (its path's figures then hold that wait).
    UserQueued,
}

impl Stage {
    /// Every stage.
    pub const ALL: [Stage; 10] = [
        Stage::UserSend,
        Stage::BrokerRecv,
        Stage::BrokerSend,
        Stage::SystemRecv,
        Stage::SystemSend,
        Stage::BrokerAnswer,
        Stage::BrokerRelay,
        Stage::UserRecv,
        Stage::FirstUpdate,
        Stage::UserQueued,
    ];

    /// Its name in the files.
    pub fn name(self) -> &'static str {
        match self {
            Stage::UserSend => "user_send",
            Stage::BrokerRecv => "broker_recv",
            Stage::BrokerSend => "broker_send",
            Stage::SystemRecv => "system_recv",
            Stage::SystemSend => "system_send",
            Stage::BrokerAnswer => "broker_answer",
            Stage::BrokerRelay => "broker_relay",
            Stage::UserRecv => "user_recv",
            Stage::FirstUpdate => "first_update",
            Stage::UserQueued => "user_queued",
        }
    }

    /// The stage a name in the files stands for.
    pub fn from_name(s: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|x| x.name() == s)
    }
}

struct Trace {
    dir: std::path::PathBuf,
    stamps: Mutex<Vec<(Stage, String, u64, u64)>>,
}

fn trace() -> Option<&'static Trace> {
    static T: OnceLock<Option<Trace>> = OnceLock::new();
    T.get_or_init(|| {
        let dir = std::env::var_os(TRACE_DIR)?;
        extern "C" fn at_exit() {
            flush();
        }
        // SAFETY: registering a plain function with no preconditions.
        unsafe { libc::atexit(at_exit) };
        Some(Trace {
            dir: dir.into(),
            stamps: Mutex::new(Vec::new()),
        })
    })
    .as_ref()
}

/// Notes that request `req` of `user` passed `stage` now (if tracing).
pub fn stamp(stage: Stage, user: &UserId, req: u64) {
    let Some(t) = trace() else { return };
    let now = monotonic_ns();
    if let Ok(mut s) = t.stamps.lock() {
        if s.len() < MAX_STAMPS {
            s.push((stage, user.0.clone(), req, now));
        }
    }
}

/// Writes the stamps so far to `DIR/trace-PID.csv` (appending) and forgets them;
/// called at exit, and by processes that end otherwise.
pub fn flush() {
    let Some(t) = trace() else { return };
    let Ok(mut s) = t.stamps.lock() else { return };
    if s.is_empty() {
        return;
    }
    let path = t.dir.join(format!("trace-{}.csv", std::process::id()));
    let file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path);
    let Ok(file) = file else { return };
    let mut w = std::io::BufWriter::new(file);
    for (stage, user, req, ns) in s.drain(..) {
        let _ = writeln!(w, "{},{user},{req},{ns}", stage.name());
    }
    let _ = w.flush();
}

/// Reads every stamp file in `dir`: (stage, user, req, ns); lines that do not parse
/// are skipped.
pub fn read_dir(dir: &std::path::Path) -> Vec<(Stage, String, u64, u64)> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return out;
    };
    for e in entries.flatten() {
        let Ok(text) = std::fs::read_to_string(e.path()) else {
            continue;
        };
        for line in text.lines() {
            let mut f = line.split(',');
            let (Some(stage), Some(user), Some(req), Some(ns), None) =
                (f.next(), f.next(), f.next(), f.next(), f.next())
            else {
                continue;
            };
            if let (Some(stage), Ok(req), Ok(ns)) =
                (Stage::from_name(stage), req.parse(), ns.parse())
            {
                out.push((stage, user.to_string(), req, ns));
            }
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn stamp_files_are_read_back_and_bad_lines_skipped() {
        for s in Stage::ALL {
            assert_eq!(Stage::from_name(s.name()), Some(s));
        }
        let dir = std::env::temp_dir().join(format!("muster-trace-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(
            dir.join("trace-1.csv"),
            "user_send,u1-ab,3,100\nbroker_recv,u1-ab,3,150\nnonsense\nuser_recv,u1-ab,x,1\nwho_knows,u,1,1\nsystem_send,u1-ab,3,170,extra\n",
        )
        .unwrap();
        std::fs::write(dir.join("trace-2.csv"), "system_send,alice.7,9,200\n").unwrap();
        let mut got = read_dir(&dir);
        got.sort();
        assert_eq!(
            got,
            [
                (Stage::UserSend, "u1-ab".to_string(), 3, 100),
                (Stage::BrokerRecv, "u1-ab".to_string(), 3, 150),
                (Stage::SystemSend, "alice.7".to_string(), 9, 200),
            ]
        );
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(read_dir(&dir).is_empty(), "a missing folder is no stamps");
    }
}
