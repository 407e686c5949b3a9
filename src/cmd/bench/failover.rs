//! `muster bench failover`: the primary broker killed (SIGKILL) or stopped (SIGSTOP)
//! again and again under load, a standby taking over each time; how soon new
//! interactions work, and what was lost.
//!
//! The load: systems with data services, users holding data sessions for the whole run
//! (each its own process), and users making requests one after another (each its own
//! process; every answer stamped on the host's monotonic clock). Each round starts a
//! fresh standby, waits until it holds the primary's state, then signals the primary and
//! times, from the signal, the first grant to any requester, the whole list written by
//! the new primary, and the new primary's own report that it serves.

use super::children::Children;
use super::{header, row, summary};
use crate::cli::{FailoverArgs, FailoverUserArgs};
use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::ServiceId;
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient, UserError, UserEvent};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::process::{ExitCode, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// One line a child printed, with who printed it and when it arrived.
struct Line {
    who: String,
    at_ns: u64,
    v: Value,
}

fn pipe_lines(who: String, out: std::process::ChildStdout, tx: mpsc::Sender<Line>) {
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines() {
            let Ok(line) = line else { break };
            let at_ns = monotonic_ns();
            let Ok(v) = serde_json::from_str::<Value>(&line) else {
                continue;
            };
            if tx
                .send(Line {
                    who: who.clone(),
                    at_ns,
                    v,
                })
                .is_err()
            {
                break;
            }
        }
    });
}

/// Files iceoryx2 keeps in /dev/shm (data segments at the top, metadata under muster/).
fn shm_files() -> usize {
    let top = std::fs::read_dir("/dev/shm")
        .map(|d| {
            d.flatten()
                .filter(|e| e.file_name().to_string_lossy().starts_with("iox2_"))
                .count()
        })
        .unwrap_or(0);
    fn walk(p: &std::path::Path) -> usize {
        std::fs::read_dir(p)
            .map(|d| {
                d.flatten()
                    .map(|e| {
                        let p = e.path();
                        if p.is_dir() {
                            walk(&p)
                        } else {
                            1
                        }
                    })
                    .sum()
            })
            .unwrap_or(0)
    }
    top + walk(std::path::Path::new("/dev/shm/muster"))
}

struct Rounds {
    signal: &'static str,
    /// The reason a standby must give for taking over after this fault.
    why: &'static str,
    to_grant: Histogram<u64>,
    to_list: Histogram<u64>,
    to_serving: Histogram<u64>,
    to_notice: Histogram<u64>,
    cold: usize,
    /// Takeovers whose reason was not the fault caused (a kill read as a hang, ...).
    misread: usize,
}

impl Rounds {
    fn new(signal: &'static str, why: &'static str) -> anyhow::Result<Self> {
        Ok(Rounds {
            signal,
            why,
            to_grant: Histogram::new(3)?,
            to_list: Histogram::new(3)?,
            to_serving: Histogram::new(3)?,
            to_notice: Histogram::new(3)?,
            cold: 0,
            misread: 0,
        })
    }
}

pub fn run(inst: &Instance, a: FailoverArgs) -> anyhow::Result<ExitCode> {
    // Each fault: its name, the signal that causes it, and the reason a standby must
    // give for taking over.
    const KILL: (&str, i32, &str) = ("kill", libc::SIGKILL, "died");
    const STOP: (&str, i32, &str) = ("stop", libc::SIGSTOP, "stopped");
    const HANG: (&str, i32, &str) = ("hang", libc::SIGUSR1, "hung");
    let signals: Vec<(&'static str, i32, &'static str)> = match a.signal.as_str() {
        "kill" => vec![KILL],
        "stop" => vec![STOP],
        "hang" => vec![HANG],
        "both" => vec![KILL, STOP],
        "all" => vec![KILL, STOP, HANG],
        other => bail!("--signal {other:?}: expected kill, stop, hang, both or all"),
    };
    // A hang: every broker runs with the fault armed, and SIGUSR1 stops the primary's
    // loop while its process lives on.
    let hang_fault: &[&str] = if signals.contains(&HANG) {
        &["--fault", "hang-on-usr1"]
    } else {
        &[]
    };
    let shm_before = shm_files();
    let (tx, rx) = mpsc::channel::<Line>();
    let mut children = Children::default();
    let mut primary = "broker-0".to_string();
    let first: Vec<&str> = std::iter::once("broker")
        .chain(hang_fault.iter().copied())
        .collect();
    children.spawn(inst, &primary, &first, Stdio::null())?;
    let services_per = a.services_per_system.max(1);
    let quota = ((a.users + a.requesters) / (a.systems * services_per) + 4).min(1000);
    let quota_s = quota.to_string();
    let per = services_per.to_string();
    for i in 0..a.systems {
        let name = format!("f{i}");
        children.spawn(
            inst,
            &name,
            &[
                "system",
                "synthetic",
                "--name",
                &name,
                "--services",
                &per,
                "--quota",
                &quota_s,
                "--rate",
                "10",
            ],
            Stdio::null(),
        )?;
    }
    let total = a.systems * services_per;
    let mut client = super::children::connect_when_listed(inst, total, Duration::from_secs(60))?;
    let service = |i: usize| format!("f{}/s{}", i % a.systems, (i / a.systems) % services_per);
    eprintln!(
        "failover: {} systems x {services_per} services (quota {quota}), {} holders, {} requesters",
        a.systems, a.users, a.requesters
    );
    for i in 0..a.users {
        let label = format!("hold-{i}");
        let svc = service(i);
        let c = children.spawn(
            inst,
            &label,
            &["bench", "failover-user", "--hold", &svc],
            Stdio::piped(),
        )?;
        pipe_lines(label, c.stdout.take().context("holder stdout")?, tx.clone());
    }
    // Every holder granted before the first round.
    let mut granted = 0;
    let setup = Instant::now() + Duration::from_secs(120);
    while granted < a.users {
        let l = rx
            .recv_timeout(setup.saturating_duration_since(Instant::now()))
            .context("holders were not all granted within 120 s")?;
        if l.v["granted"] == true {
            granted += 1;
        } else if l.v["granted"] == false {
            bail!("{} was refused: {}", l.who, l.v);
        }
    }
    for i in 0..a.requesters {
        let label = format!("req-{i}");
        let svcs: Vec<String> = (0..4).map(|k| service(i * 7 + k * 3)).collect();
        let c = children.spawn(
            inst,
            &label,
            &[
                "bench",
                "failover-user",
                "--request",
                &svcs.join(","),
                "--pause",
                &format!("{}ms", a.pause.as_millis()),
            ],
            Stdio::piped(),
        )?;
        pipe_lines(
            label,
            c.stdout.take().context("requester stdout")?,
            tx.clone(),
        );
    }
    std::thread::sleep(Duration::from_millis(500));

    let mut rounds: Vec<Rounds> = signals
        .iter()
        .map(|(n, _, why)| Rounds::new(n, why))
        .collect::<anyhow::Result<_>>()?;
    let mut finals: Vec<Line> = Vec::new();
    let mut incomplete_lists = 0u64;
    let mut false_takeovers = 0u64;
    let mut grants = 0u64;
    let mut refusals = 0u64;
    for k in 0..a.kills {
        let (ri, (_, sig, _)) = signals
            .iter()
            .enumerate()
            .nth(k % signals.len())
            .expect("at least one signal");
        let standby = format!("broker-{}", k + 1);
        let deadline = format!("{}ms", a.deadline.as_millis());
        let args: Vec<&str> = ["broker", "--standby", "--takeover-deadline", &deadline]
            .into_iter()
            .chain(hang_fault.iter().copied())
            .collect();
        let c = children.spawn(inst, &standby, &args, Stdio::piped())?;
        pipe_lines(
            standby.clone(),
            c.stdout.take().context("standby stdout")?,
            tx.clone(),
        );
        let until = Instant::now() + Duration::from_secs(30);
        let mut taken = false;
        loop {
            let l = rx
                .recv_timeout(until.saturating_duration_since(Instant::now()))
                .with_context(|| format!("round {k}: the standby did not get in sync"))?;
            if l.who == standby && l.v["event"] == "in_sync" {
                break;
            }
            if l.who == standby && l.v["event"] == "took_over" {
                // The primary did not answer the new standby in time: it took over (and
                // ended the primary). Counted; the next round starts from it.
                eprintln!(
                    "failover: round {k}: the new standby took over a live primary: {}",
                    l.v
                );
                false_takeovers += 1;
                taken = true;
                break;
            }
            count(&l, &mut grants, &mut refusals, &mut finals);
        }
        if taken {
            children.kill(&primary);
            primary = standby;
            std::thread::sleep(a.settle);
            continue;
        }
        let epoch_before = client.list()?.epoch;
        let pid = children
            .child_mut(&primary)
            .map(|c| c.id())
            .context("the primary is gone")?;
        let t_kill = monotonic_ns();
        // SAFETY: signalling a child we spawned and have not reaped.
        unsafe { libc::kill(pid as i32, *sig) };
        // The new primary's report, the first grant of a request made after the signal,
        // and the list written by the new primary (polled every 2 ms; the old one stays
        // readable, and whole, meanwhile: checked too).
        let mut to_serving = None;
        let mut to_grant = None;
        let mut to_list = None;
        let deadline = Instant::now() + Duration::from_secs(20);
        while to_serving.is_none() || to_grant.is_none() || to_list.is_none() {
            if Instant::now() > deadline {
                bail!(
                    "round {k}: within 20 s: serving {to_serving:?}, a grant {to_grant:?}, the new list {to_list:?}"
                );
            }
            if to_list.is_none() {
                let l = client.list()?;
                if l.count() < total {
                    incomplete_lists += 1;
                }
                if l.epoch != epoch_before && l.count() == total {
                    to_list = Some(monotonic_ns() - t_kill);
                }
            }
            let Ok(l) = rx.recv_timeout(Duration::from_millis(2)) else {
                continue;
            };
            if l.who == standby && l.v["event"] == "took_over" {
                if l.v["replicated"] == false {
                    rounds[ri].cold += 1;
                }
                if l.v["why"] != rounds[ri].why {
                    eprintln!(
                        "failover: round {k}: {} taken over as {}",
                        rounds[ri].signal, l.v["why"]
                    );
                    rounds[ri].misread += 1;
                }
                if let Some(t) = l.v["noticed_ns"].as_u64() {
                    rounds[ri]
                        .to_notice
                        .record((t.saturating_sub(t_kill) / 1000).max(1))?;
                }
            }
            if l.who == standby && l.v["event"] == "serving" {
                let at = l.v["at_ns"].as_u64().unwrap_or(l.at_ns);
                to_serving = Some(at.saturating_sub(t_kill));
            }
            // A new interaction: a request made after the signal, granted.
            if l.v["granted"] == true && l.v["asked_ns"].as_u64().is_some_and(|a| a > t_kill) {
                if let Some(t) = l.v["t_ns"].as_u64() {
                    to_grant.get_or_insert(t - t_kill);
                }
            }
            count(&l, &mut grants, &mut refusals, &mut finals);
        }
        let to_list = to_list.unwrap_or(0);
        let r = &mut rounds[ri];
        r.to_list.record((to_list / 1000).max(1))?;
        r.to_grant.record((to_grant.unwrap_or(0) / 1000).max(1))?;
        r.to_serving
            .record((to_serving.unwrap_or(0) / 1000).max(1))?;
        // The old primary is gone (a stopped one is ended by the standby); reap it.
        children.kill(&primary);
        primary = standby;
        // Let systems re-register and the load settle before the next round.
        let settle = Instant::now() + a.settle;
        while let Ok(l) = rx.recv_timeout(settle.saturating_duration_since(Instant::now())) {
            count(&l, &mut grants, &mut refusals, &mut finals);
        }
        if !a.json && (k + 1) % 10 == 0 {
            eprintln!("failover: {} of {} rounds", k + 1, a.kills);
        }
    }

    // Stop the users: each ends its session and prints what it saw.
    let labels = (0..a.users)
        .map(|i| format!("hold-{i}"))
        .chain((0..a.requesters).map(|i| format!("req-{i}")));
    for label in labels {
        if let Some(c) = children.child_mut(&label) {
            // SAFETY: signalling a child we spawned and have not reaped.
            unsafe { libc::kill(c.id() as i32, libc::SIGTERM) };
        }
    }
    let mut done = finals.len();
    let until = Instant::now() + Duration::from_secs(30);
    while done < a.users + a.requesters {
        let Ok(l) = rx.recv_timeout(until.saturating_duration_since(Instant::now())) else {
            break;
        };
        if l.v["done"] == true {
            done += 1;
        }
        count(&l, &mut grants, &mut refusals, &mut finals);
    }
    // Every session has ended: nothing may still be counted in use.
    std::thread::sleep(Duration::from_millis(500));
    let after = client.list()?;
    let in_use_after: u64 = after.entries().iter().map(|e| u64::from(e.in_use)).sum();
    if in_use_after > 0 {
        let busy: Vec<String> = after
            .entries()
            .iter()
            .filter(|e| e.in_use > 0)
            .map(|e| format!("{} {}", e.id(), e.in_use))
            .collect();
        eprintln!("failover: still counted in use after every session ended: {busy:?}");
    }
    client.close();
    children.stop();
    std::thread::sleep(Duration::from_millis(200));
    let shm_left = shm_files().saturating_sub(shm_before);

    let holders: Vec<&Line> = finals
        .iter()
        .filter(|l| l.who.starts_with("hold-"))
        .collect();
    let lost = holders.iter().filter(|l| l.v["lost"] == true).count()
        + a.users.saturating_sub(holders.len());
    let gaps: u64 = holders.iter().filter_map(|l| l.v["gaps"].as_u64()).sum();
    let updates: u64 = holders.iter().filter_map(|l| l.v["updates"].as_u64()).sum();
    let unwanted: u64 = finals
        .iter()
        .filter_map(|l| l.v["unwanted_grants"].as_u64())
        .sum();
    let regrants: u64 = finals.iter().filter_map(|l| l.v["regrants"].as_u64()).sum();
    if a.json {
        let per: serde_json::Map<String, Value> = rounds
            .iter()
            .map(|r| {
                (
                    r.signal.to_string(),
                    json!({"rounds": r.to_grant.len(), "to_first_grant": summary(&r.to_grant),
                           "to_standby_notices": summary(&r.to_notice),
                           "to_whole_list": summary(&r.to_list), "to_serving": summary(&r.to_serving),
                           "cold_takeovers": r.cold, "misread_takeovers": r.misread}),
                )
            })
            .collect();
        println!(
            "{}",
            json!({"signals": per, "holders": a.users, "requesters": a.requesters,
                   "systems": a.systems, "services": total, "deadline_ms": a.deadline.as_millis() as u64,
                   "lost_sessions": lost, "sequence_gaps": gaps, "updates": updates,
                   "duplicate_grants": unwanted, "regrants_ignored": regrants,
                   "grants": grants, "refusals": refusals,
                   "in_use_after_all_ended": in_use_after, "shm_files_left": shm_left,
                   "incomplete_list_reads": incomplete_lists, "false_takeovers": false_takeovers})
        );
    } else {
        println!(
            "muster bench failover: {} holders, {} requesters, {} services on {} systems, deadline {:?}",
            a.users, a.requesters, total, a.systems, a.deadline
        );
        println!("{}", header("from the signal (us)"));
        for r in &rounds {
            for (what, h) in [
                ("standby notices", &r.to_notice),
                ("new primary serves", &r.to_serving),
                ("first new grant", &r.to_grant),
                ("list rewritten", &r.to_list),
            ] {
                println!("{}", row(&format!("{}: {what}", r.signal), h));
            }
        }
        println!(
            "lost sessions {lost}, sequence gaps {gaps} in {updates} updates, duplicate grants {unwanted} \
             (repeated grants of a held session ignored: {regrants}), grants {grants}, refusals {refusals}"
        );
        println!(
            "in use after every session ended: {in_use_after}; files left in /dev/shm: {shm_left}; cold takeovers: {}; \
             takeovers whose reason was not the fault caused: {}",
            rounds.iter().map(|r| r.cold).sum::<usize>(),
            rounds.iter().map(|r| r.misread).sum::<usize>()
        );
        println!(
            "list reads during takeovers that were not whole: {incomplete_lists} (the old list stays readable until the new primary rewrites it); standbys that took over a live primary: {false_takeovers}"
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn count(l: &Line, grants: &mut u64, refusals: &mut u64, finals: &mut Vec<Line>) {
    if l.who.starts_with("req-") {
        if l.v["granted"] == true {
            *grants += 1;
        } else if l.v["granted"] == false {
            *refusals += 1;
        }
    }
    if l.v["done"] == true {
        finals.push(Line {
            who: l.who.clone(),
            at_ns: l.at_ns,
            v: l.v.clone(),
        });
    }
}

fn print(v: Value) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{v}");
    let _ = out.flush();
}

/// The users of `bench failover`: one holds a data session until SIGTERM; the other
/// requests services one after another, ending each session at once.
pub fn user(inst: &Instance, a: FailoverUserArgs) -> anyhow::Result<ExitCode> {
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(30),
        handle_signals: true,
        watch_list: false,
    };
    let mut client = crate::cmd::user::connect(inst, &a.remote, &opts)?;
    let r = match (&a.hold, &a.request) {
        (Some(svc), _) => hold(&mut client, &ServiceId(svc.clone())),
        (None, Some(svcs)) => request(&mut client, svcs, a.pause),
        (None, None) => bail!("--hold SERVICE or --request SERVICES"),
    };
    let core = client.core();
    let (regrants, unwanted) = (core.regrants(), core.unwanted_grants());
    let resets = client.link_stats().map(|s| s.resets);
    let mut summary = r?;
    summary["done"] = json!(true);
    summary["regrants"] = json!(regrants);
    summary["unwanted_grants"] = json!(unwanted);
    summary["resets"] = json!(resets);
    print(summary);
    client.close();
    Ok(ExitCode::SUCCESS)
}

fn hold(client: &mut UserClient, svc: &ServiceId) -> anyhow::Result<Value> {
    let req = client.request(svc)?;
    let deadline = Instant::now() + Duration::from_secs(60);
    let session = loop {
        match client.next_event(deadline) {
            Ok(Some(UserEvent::Granted {
                req: r, session, ..
            })) if r == req => break session,
            Ok(Some(UserEvent::Refused { req: r, reason, .. })) if r == req => {
                print(json!({"granted": false, "reason": reason.to_string()}));
                return Ok(json!({"lost": true, "reason": "refused"}));
            }
            Ok(Some(_)) => {}
            Ok(None) => bail!("no answer within 60 s"),
            Err(UserError::Interrupted) => return Ok(json!({"lost": true, "reason": "stopped"})),
            Err(e) => return Err(e.into()),
        }
    };
    print(json!({"granted": true, "session": session.to_string()}));
    let mut updates = 0u64;
    let far = Instant::now() + Duration::from_secs(24 * 3600);
    let ended = loop {
        match client.next_event(far) {
            Ok(Some(UserEvent::Update { session: s, .. })) if s == session => updates += 1,
            Ok(Some(UserEvent::Ended {
                session: s, reason, ..
            })) if s == session => break Some(reason.to_string()),
            Ok(_) => {}
            Err(UserError::Interrupted) => break None,
            Err(e) => return Err(e.into()),
        }
    };
    let c = client.core().counters(session).unwrap_or_default();
    if ended.is_none() {
        client.end(session);
    }
    Ok(
        json!({"lost": ended.is_some(), "reason": ended, "updates": updates, "gaps": c.gaps,
              "last_seq": c.last_seq}),
    )
}

fn request(client: &mut UserClient, svcs: &str, pause: Duration) -> anyhow::Result<Value> {
    let svcs: Vec<ServiceId> = svcs.split(',').map(|s| ServiceId(s.to_string())).collect();
    let (mut asked, mut ok) = (0u64, 0u64);
    for i in 0usize.. {
        let asked_ns = monotonic_ns();
        let req = client.request(&svcs[i % svcs.len()])?;
        asked += 1;
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            match client.next_event(deadline) {
                Ok(Some(UserEvent::Granted {
                    req: r, session, ..
                })) if r == req => {
                    print(json!({"granted": true, "t_ns": monotonic_ns(), "asked_ns": asked_ns}));
                    ok += 1;
                    client.end(session);
                    break;
                }
                Ok(Some(UserEvent::Refused { req: r, reason, .. })) if r == req => {
                    print(
                        json!({"granted": false, "t_ns": monotonic_ns(), "reason": reason.to_string()}),
                    );
                    break;
                }
                Ok(Some(_)) => {}
                Ok(None) => {
                    client.cancel(req);
                    print(
                        json!({"granted": false, "t_ns": monotonic_ns(), "reason": "no answer in 10 s"}),
                    );
                    break;
                }
                Err(UserError::Interrupted) => {
                    return Ok(json!({"requests": asked, "granted": ok}));
                }
                Err(e) => return Err(e.into()),
            }
        }
        let until = Instant::now() + pause;
        loop {
            match client.next_event(until) {
                Ok(None) => break,
                Ok(Some(_)) => {}
                Err(UserError::Interrupted) => {
                    return Ok(json!({"requests": asked, "granted": ok}))
                }
                Err(e) => return Err(e.into()),
            }
        }
    }
    Ok(json!({"requests": asked, "granted": ok}))
}
