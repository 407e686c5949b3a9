//! `muster operator ...`: an operator's actions, through the protocol.

use crate::cli::{OperatorAction, OperatorArgs};
use anyhow::{bail, Context};
use muster_shared::protocol::{BrokerStatus, Operation};
use muster_shared::types::{ServiceId, SessionId, UserId};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserEvent};
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// How long the broker has to answer.
const ANSWER: Duration = Duration::from_secs(5);

pub fn run(inst: &Instance, a: OperatorArgs) -> anyhow::Result<ExitCode> {
    let op = match a.action {
        OperatorAction::Status => Operation::Status,
        OperatorAction::Withdraw { service } => Operation::Withdraw {
            service: ServiceId(service),
        },
        OperatorAction::Restore { service } => Operation::Restore {
            service: ServiceId(service),
        },
        OperatorAction::End { session } => Operation::EndSession {
            session: SessionId(
                u64::from_str_radix(&session, 16)
                    .with_context(|| format!("{session:?} is not a session (16 hex digits)"))?,
            ),
        },
        OperatorAction::DropUser { user } => Operation::DropUser { user: UserId(user) },
        OperatorAction::Move {
            service,
            user,
            req,
            position,
        } => Operation::MoveRequest {
            service: ServiceId(service),
            user: UserId(user),
            req,
            position,
        },
        OperatorAction::DropRequest { service, user, req } => Operation::DropRequest {
            service: ServiceId(service),
            user: UserId(user),
            req,
        },
    };
    let opts = ConnectOptions {
        wait_for_broker: a.wait,
        handle_signals: true,
        watch_list: false,
    };
    let mut client = super::user::connect(inst, &a.remote, &opts)?;
    let id = client.operate(op);
    let deadline = Instant::now() + ANSWER;
    let result = loop {
        match client.next_event(deadline)? {
            Some(UserEvent::Operated { id: i, result }) if i == id => break result,
            Some(_) => {}
            None => bail!("the broker did not answer within {ANSWER:?}"),
        }
    };
    client.close();
    match result {
        Ok(status) => {
            match (status, a.json) {
                (Some(s), true) => println!("{}", serde_json::to_string(&s)?),
                (Some(s), false) => print_status(&s),
                (None, true) => println!("{}", serde_json::json!({"done": true})),
                (None, false) => println!("done"),
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(why) => {
            if a.json {
                println!("{}", serde_json::json!({"done": false, "error": why}));
            } else {
                eprintln!("muster operator: {why}");
            }
            Ok(ExitCode::from(1))
        }
    }
}

fn print_status(s: &BrokerStatus) {
    println!("broker run {:016x}", s.epoch);
    println!("systems ({}):", s.systems.len());
    for sys in &s.systems {
        let answer = sys
            .last_answer_ms
            .map_or("never".to_string(), |ms| format!("{ms} ms ago"));
        println!(
            "  {:<16} pid {:<7} services {:<3} sessions {:<4} last answer {answer}{}{}",
            sys.name,
            sys.pid,
            sys.services.len(),
            sys.sessions,
            if sys.ping_outstanding {
                " (ping out)"
            } else {
                ""
            },
            if sys.delinquencies > 0 {
                format!(", delinquent {} times", sys.delinquencies)
            } else {
                String::new()
            },
        );
    }
    println!("users ({}):", s.users_total);
    for u in &s.users {
        let kind = if u.pid == 0 {
            "remote".to_string()
        } else {
            format!("pid {}", u.pid)
        };
        println!("  {:<24} {kind:<12} links {}", u.user, u.links.len());
    }
    println!("sessions ({}):", s.sessions_total);
    for x in &s.sessions {
        println!("  {:016x} {:<24} {}", x.session.0, x.service, x.user);
    }
    for q in &s.queues {
        println!("queue of {} ({} waiting):", q.service, q.waiting.len());
        for (i, (user, req)) in q.waiting.iter().enumerate() {
            println!("  {}. {user} request {req}", i + 1);
        }
    }
    if !s.handling.is_empty() {
        println!(
            "handling in this run:\n  {:<16} {:>10} {:>8} {:>8} {:>8}",
            "kind", "count", "p50 µs", "p99 µs", "max µs"
        );
    }
    for h in &s.handling {
        println!(
            "  {:<16} {:>10} {:>8} {:>8} {:>8}",
            h.kind, h.count, h.p50_us, h.p99_us, h.max_us
        );
    }
}
