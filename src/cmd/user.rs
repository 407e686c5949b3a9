//! `muster user ...`: list, request, link, and the interactive menu.

use crate::cli::{UserArgs, UserVerb};
use anyhow::Context;
use muster_shared::types::{EndReason, Payload, Schema, ServiceId, ServiceKind};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient, UserError, UserEvent};
use serde_json::{json, Value};
use std::process::ExitCode;
use std::time::{Duration, Instant};

pub fn run(inst: &Instance, a: UserArgs) -> anyhow::Result<ExitCode> {
    // The menu and `watch` want to hear of list changes; one-shot verbs do not.
    let watch_list = matches!(a.verb, None | Some(UserVerb::Watch { .. }));
    let opts = ConnectOptions {
        wait_for_broker: a.wait,
        handle_signals: true,
        watch_list,
    };
    if let Some(UserVerb::Behave(b)) = &a.verb {
        if b.start_on_stdin {
            // Until the harness lets every user go at once (a line, or the end).
            let mut line = String::new();
            let _ = std::io::stdin().read_line(&mut line);
        }
    }
    if a.count > 1 {
        return run_many(inst, a, opts);
    }
    let started = Instant::now();
    let mut client = connect(inst, &a.remote, &opts)?;
    if a.verb.is_none() {
        client.watch_part(Some(a.list.filter()))?;
    }
    match a.verb {
        None if !a.plain && super::tui::interactive() => {
            let who = match &a.remote.remote {
                Some(addr) => format!("{} via {addr}", client.id()),
                None => format!("{} on instance {inst}", client.id()),
            };
            super::user_tui::run(client, who, &a.list.part())?;
            Ok(ExitCode::SUCCESS)
        }
        None => {
            muster_users::menu::run(client, &a.list.part())?;
            Ok(ExitCode::SUCCESS)
        }
        Some(UserVerb::List { filter, json }) => list(client, &filter, json),
        Some(UserVerb::Request {
            id,
            duration,
            goal,
            twist,
            input,
            json,
        }) => {
            let input = match (goal, twist, input) {
                (Some(g), _, _) => Some(Input::Once(parse_goal(&g)?)),
                (None, Some(t), _) => {
                    let (v, w) = parse_point("--twist", &t)?;
                    Some(Input::Repeated(Payload::Twist { v, w }))
                }
                (None, None, Some(j)) => Some(Input::Json(
                    serde_json::from_str(&j).context("--input is not JSON")?,
                )),
                (None, None, None) => None,
            };
            request(client, &ServiceId(id), duration, input, json)
        }
        Some(UserVerb::Watch {
            filter,
            duration,
            json,
        }) => watch(client, &filter, duration, json),
        Some(UserVerb::Idle { duration }) => idle(client, duration, started),
        Some(UserVerb::Behave(b)) => super::behave::run(client, &b),
        Some(UserVerb::Link {
            data,
            command,
            duration,
            json,
        }) => link(
            client,
            &ServiceId(data),
            &ServiceId(command),
            duration,
            json,
        ),
    }
}

/// Ends a user whose thread has nothing left to do: it says goodbye, removes its shared
/// memory in its turn ([`muster_shared::ipc::TeardownTurn`]: one process at a time,
/// the others asleep, so a broker removing files of its own waits for one removal at
/// most), and then yields ([`muster_shared::reactor::yield_for_exit`]): the rest of
/// its exit runs when nothing else would (hundreds of users leaving together otherwise
/// take the cores from the broker and from the users still asking it).
pub fn leave(mut client: UserClient) {
    client.goodbye();
    let turn = muster_shared::ipc::TeardownTurn::wait(TEARDOWN_PATIENCE);
    drop(client);
    drop(turn);
    muster_shared::reactor::yield_for_exit();
}

/// How long a leaving user waits for its turn to remove its shared memory before it
/// goes on without it (one process's removal takes a few ms).
const TEARDOWN_PATIENCE: Duration = Duration::from_secs(2);

/// `--count N`: N users of `idle` or `behave`, a thread and a connection each.
fn run_many(inst: &Instance, a: UserArgs, opts: ConnectOptions) -> anyhow::Result<ExitCode> {
    let behave = match &a.verb {
        Some(UserVerb::Idle { .. }) => None,
        Some(UserVerb::Behave(b)) => Some(b.clone()),
        _ => anyhow::bail!("--count is for `idle` and `behave`"),
    };
    let idle_for = match &a.verb {
        Some(UserVerb::Idle { duration }) => *duration,
        _ => None,
    };
    // Local users share their process's inbox unless told otherwise, sized for a burst
    // to all of them.
    let shared = match (&a.remote.remote, a.own_inboxes) {
        (None, false) => Some(
            muster_users::ProcessInbox::of_this_process(
                inst,
                muster_users::ProcessInboxSize::for_users(a.count as usize),
            )
            .context("opening the inbox this process's users share")?,
        ),
        _ => None,
    };
    let threads: Vec<_> = (0..a.count)
        .map(|k| {
            let (inst, remote, opts, behave) =
                (inst.clone(), a.remote.clone(), opts.clone(), behave.clone());
            let shared = shared.clone();
            std::thread::Builder::new().name(format!("user-{k}")).spawn(
                move || -> anyhow::Result<()> {
                    let started = Instant::now();
                    let client = match &shared {
                        Some(inbox) => UserClient::connect_in(&inst, &opts, "u", inbox)?,
                        None => connect(&inst, &remote, &opts)?,
                    };
                    match behave {
                        Some(b) => {
                            let b = crate::cli::BehaveArgs {
                                seed: b.seed.wrapping_add(u64::from(k)),
                                ..b
                            };
                            super::behave::run(client, &b)?;
                        }
                        None => {
                            idle(client, idle_for, started)?;
                        }
                    }
                    Ok(())
                },
            )
        })
        .collect::<Result<_, _>>()
        .context("starting the users' threads")?;
    let mut failed = 0;
    for t in threads {
        match t.join() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                eprintln!("muster: {e:#}");
                failed += 1;
            }
            Err(_) => failed += 1,
        }
    }
    // Every user has said goodbye: the process's own teardown waits its turn.
    muster_shared::reactor::yield_for_exit();
    Ok(if failed == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// Connects over shared memory, or over UDP with `--remote`.
pub fn connect(
    inst: &Instance,
    r: &crate::cli::RemoteArgs,
    opts: &ConnectOptions,
) -> anyhow::Result<UserClient> {
    let Some(broker) = r.remote else {
        if r.key.is_some() {
            anyhow::bail!("--key is for remote users: add --remote ADDR");
        }
        return Ok(UserClient::connect(inst, opts)?);
    };
    let path = r.key.as_ref().context("--remote needs --key FILE")?;
    let (name, key) = muster_shared::udp::crypto::KeyPair::read(path)?;
    let broker_key = r
        .broker_key
        .as_deref()
        .map(muster_shared::udp::crypto::parse_key)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--broker-key: {e}"))?;
    let remote = muster_users::RemoteOptions {
        broker,
        name,
        key,
        broker_key,
        faults: r.faults,
    };
    Ok(UserClient::connect_remote(remote, opts)?)
}

/// Task input a request sends once granted.
enum Input {
    /// Sent once (a goal).
    Once(Payload),
    /// Sent every [`REPEAT_INPUT`] while the session lasts (a velocity).
    Repeated(Payload),
    /// Sent once, made from JSON once the grant says the service's schema.
    Json(Value),
}

/// How often repeated input goes out.
const REPEAT_INPUT: Duration = Duration::from_millis(100);

fn parse_goal(s: &str) -> anyhow::Result<Payload> {
    let (x, y) = parse_point("--goal", s)?;
    Ok(Payload::Goal2d { x, y })
}

/// A point given to flag `flag` as `X,Y` (metres, finite).
pub fn parse_point(flag: &str, s: &str) -> anyhow::Result<(f64, f64)> {
    let (x, y) = s
        .split_once(',')
        .with_context(|| format!("{flag} takes X,Y (metres), e.g. 3.5,-2"))?;
    let x: f64 = x.trim().parse().with_context(|| format!("{flag} X"))?;
    let y: f64 = y.trim().parse().with_context(|| format!("{flag} Y"))?;
    anyhow::ensure!(x.is_finite() && y.is_finite(), "{flag} must be finite");
    Ok((x, y))
}

/// A payload as one line of text, an open type's sample decoded by its schema.
pub fn payload_text(p: &Payload, schema: Option<&Schema>) -> String {
    match p {
        Payload::Encoded { type_name, .. } => match p.to_json_with(schema).get("value") {
            Some(v) => format!("{type_name} {v}"),
            None => p.to_string(),
        },
        other => other.to_string(),
    }
}

fn list(
    mut client: UserClient,
    part: &crate::cli::ListFilterArgs,
    as_json: bool,
) -> anyhow::Result<ExitCode> {
    let page = client.list_part(&part.part())?;
    let views = page.views();
    if as_json {
        out!("{}", serde_json::to_string_pretty(&views)?);
    } else {
        out!("{}", muster_users::menu::table(&views));
        out!(
            "({}, list generation {})",
            shown(&page, part.offset),
            page.generation
        );
    }
    client.close();
    Ok(ExitCode::SUCCESS)
}

/// "12 services", or which of how many a filtered or paged list shows.
fn shown(page: &muster_shared::snapshot::ListPage, offset: usize) -> String {
    let n = page.entries.len();
    if n == page.matching {
        format!("{n} services")
    } else if n == 0 {
        format!("none of {} from {}", page.matching, offset + 1)
    } else {
        format!("{}-{} of {}", offset + 1, offset + n, page.matching)
    }
}

fn watch(
    mut client: UserClient,
    part: &crate::cli::ListFilterArgs,
    duration: Option<Duration>,
    as_json: bool,
) -> anyhow::Result<ExitCode> {
    let deadline = Instant::now() + duration.unwrap_or(Duration::from_secs(100 * 365 * 86400));
    let want = part.part();
    // The broker rings this process only when that part changes.
    client.watch_part(Some(want.filter.clone()))?;
    // What was shown last: a change elsewhere in the list is not shown again.
    let mut shown_views: Option<(u64, Vec<muster_shared::snapshot::ServiceView>)> = None;
    loop {
        let page = match client.list_part(&want) {
            Ok(p) => Some(p),
            // Remote, with the broker away: keep waiting for it.
            Err(UserError::ListTimeout(_)) => None,
            Err(e) => return Err(e.into()),
        };
        if let Some(page) = page {
            let views = page.views();
            if shown_views
                .as_ref()
                .is_none_or(|(epoch, shown)| (*epoch, shown) != (page.epoch, &views))
            {
                emit(
                    as_json,
                    json!({"generation": page.generation, "matching": page.matching, "services": views}),
                    format!(
                        "-- generation {} ({}) --\n{}",
                        page.generation,
                        shown(&page, part.offset),
                        muster_users::menu::table(&views)
                    ),
                );
                shown_views = Some((page.epoch, views));
            }
        }
        match client.next_event(deadline) {
            Ok(Some(_)) => {}
            Ok(None) | Err(UserError::Interrupted) => break,
            Err(e) => return Err(e.into()),
        }
    }
    leave(client);
    Ok(ExitCode::SUCCESS)
}

fn idle(
    mut client: UserClient,
    duration: Option<Duration>,
    started: Instant,
) -> anyhow::Result<ExitCode> {
    let services = client.list()?.count();
    let connect_us = started.elapsed().as_micros() as u64;
    out!(
        "{}",
        json!({"connected": true, "user": client.id().0, "services": services, "connect_us": connect_us})
    );
    let deadline = Instant::now() + duration.unwrap_or(Duration::from_secs(100 * 365 * 86400));
    loop {
        match client.next_event(deadline) {
            Ok(Some(_)) => {}
            Ok(None) | Err(UserError::Interrupted) => break,
            Err(e) => return Err(e.into()),
        }
    }
    leave(client);
    Ok(ExitCode::SUCCESS)
}

fn emit(as_json: bool, value: Value, text: String) {
    if as_json {
        out!("{value}");
    } else {
        out!("{text}");
    }
}

fn request(
    mut client: UserClient,
    id: &ServiceId,
    duration: Duration,
    input: Option<Input>,
    as_json: bool,
) -> anyhow::Result<ExitCode> {
    let req = client.request(id)?;
    let answer_deadline = Instant::now() + Duration::from_secs(30);
    let mut first_position = None;
    let session = loop {
        match client.next_event(answer_deadline) {
            Ok(Some(UserEvent::Granted {
                req: r,
                session,
                kind,
                payload,
                schema,
                ..
            })) if r == req => {
                emit(
                    as_json,
                    json!({"granted": true, "reason": null, "queue_position": first_position,
                           "session": session.to_string(), "service": id.0, "kind": kind.as_str(),
                           "payload": payload}),
                    format!("granted: session {session} on {id} ({kind}, {payload})"),
                );
                break (session, kind, schema);
            }
            Ok(Some(UserEvent::Refused { req: r, reason, .. })) if r == req => {
                emit(
                    as_json,
                    json!({"granted": false, "reason": reason.to_string(), "code": reason.code(),
                           "queue_position": first_position}),
                    format!("refused: {reason}"),
                );
                client.close();
                return Ok(ExitCode::from(3));
            }
            Ok(Some(UserEvent::Queued {
                req: r, position, ..
            })) if r == req => {
                first_position.get_or_insert(position);
                if !as_json {
                    out!("queued at position {position}");
                }
            }
            Ok(Some(_)) => {}
            Ok(None) => {
                client.cancel(req);
                anyhow::bail!("no answer to the request within 30 s");
            }
            Err(UserError::Interrupted) => {
                client.cancel(req);
                return Ok(ExitCode::from(130));
            }
            Err(e) => return Err(e.into()),
        }
    };
    let (session, kind, schema) = session;
    let (first, repeated) = match input {
        Some(_) if kind != ServiceKind::Command => {
            eprintln!("muster: --goal/--twist/--input ignored: {id} is a data service");
            (None, None)
        }
        Some(Input::Once(p)) => (Some(p), None),
        Some(Input::Repeated(p)) => (Some(p.clone()), Some(p)),
        Some(Input::Json(v)) => match Payload::from_json(&v, schema.as_ref()) {
            Ok(p) => (Some(p), None),
            Err(e) => {
                client.end(session);
                client.close();
                anyhow::bail!("--input: {e}");
            }
        },
        None => (None, None),
    };
    if let Some(p) = first {
        client.input(session, p).map_err(|e| anyhow::anyhow!(e))?;
    }
    // Counted as the updates arrive: the session is gone from the client once ended.
    let mut counters = muster_users::core::SessionCounters::default();
    let end_at = Instant::now() + duration;
    let end = loop {
        let until = match repeated {
            Some(_) => (Instant::now() + REPEAT_INPUT).min(end_at),
            None => end_at,
        };
        let end = stream(
            &mut client,
            session,
            schema.as_ref(),
            until,
            as_json,
            &mut counters,
            |_| true,
        )?;
        // Ended, the duration over, or interrupted (back before its deadline).
        let now = Instant::now();
        if end.is_some() || now >= end_at || now < until {
            break end;
        }
        if let Some(p) = &repeated {
            client
                .input(session, p.clone())
                .map_err(|e| anyhow::anyhow!(e))?;
        }
    };
    if end.is_none() {
        client.end(session);
    }
    let reason = end.unwrap_or(EndReason::DurationOver);
    emit(
        as_json,
        json!({"ended": true, "reason": reason.to_string(), "last_seq": counters.last_seq, "gaps": counters.gaps}),
        format!(
            "ended: {reason} (last seq {}, {} lost)",
            counters.last_seq, counters.gaps
        ),
    );
    client.close();
    Ok(ExitCode::SUCCESS)
}

/// Prints updates and status of `session` until it ends (returns why) or the deadline.
fn stream(
    client: &mut UserClient,
    session: muster_shared::types::SessionId,
    schema: Option<&Schema>,
    deadline: Instant,
    as_json: bool,
    counters: &mut muster_users::core::SessionCounters,
    mut other: impl FnMut(&UserEvent) -> bool,
) -> anyhow::Result<Option<EndReason>> {
    loop {
        match client.next_event(deadline) {
            Ok(Some(UserEvent::Update {
                session: s,
                seq,
                gap,
                payload,
                ..
            })) if s == session => {
                counters.last_seq = counters.last_seq.max(seq);
                counters.gaps += gap;
                emit(
                    as_json,
                    json!({"seq": seq, "gap": gap, "payload": &payload.to_json_with(schema)}),
                    format!(
                        "#{seq} {}{}",
                        payload_text(&payload, schema),
                        if gap > 0 {
                            format!(" ({gap} lost)")
                        } else {
                            String::new()
                        }
                    ),
                )
            }
            Ok(Some(UserEvent::Status {
                session: s,
                seq,
                status,
                ..
            })) if s == session => {
                counters.last_seq = counters.last_seq.max(seq);
                emit(
                    as_json,
                    json!({"seq": seq, "status": status.to_string(),
                           "state": status.state(), "detail": status.detail(),
                           "payload": null}),
                    format!("#{seq} status: {status}"),
                )
            }
            Ok(Some(UserEvent::Ended {
                session: s,
                reason,
                lost_at_end,
                ..
            })) if s == session => {
                counters.gaps += lost_at_end;
                return Ok(Some(reason));
            }
            Ok(Some(UserEvent::BrokerLost)) => {
                if !as_json {
                    eprintln!("(broker lost; the session goes on)");
                }
            }
            Ok(Some(e)) => {
                if !other(&e) {
                    return Ok(None);
                }
            }
            Ok(None) => return Ok(None),
            Err(UserError::Interrupted) => return Ok(None),
            Err(e) => return Err(e.into()),
        }
    }
}

fn link(
    mut client: UserClient,
    data: &ServiceId,
    command: &ServiceId,
    duration: Duration,
    as_json: bool,
) -> anyhow::Result<ExitCode> {
    let link = match client.link(data, command) {
        Ok(l) => l,
        Err(e @ (UserError::CannotLink(_) | UserError::UnknownService(_))) => {
            emit(
                as_json,
                json!({"linked": false, "reason": e.to_string()}),
                format!("link refused: {e}"),
            );
            client.close();
            return Ok(ExitCode::from(3));
        }
        Err(e) => return Err(e.into()),
    };
    let setup_deadline = Instant::now() + Duration::from_secs(30);
    let (mut data_session, mut cmd_session) = (None, None);
    loop {
        match client.next_event(setup_deadline) {
            Ok(Some(UserEvent::Granted { session, kind, .. })) => match kind {
                ServiceKind::Data => data_session = Some(session),
                ServiceKind::Command => cmd_session = Some(session),
            },
            Ok(Some(UserEvent::LinkUp { link: l })) if l == link => break,
            Ok(Some(UserEvent::LinkEnded { link: l, reason })) if l == link => {
                emit(
                    as_json,
                    json!({"linked": false, "reason": reason}),
                    format!("link failed: {reason}"),
                );
                client.close();
                return Ok(ExitCode::from(3));
            }
            Ok(Some(UserEvent::Queued {
                service, position, ..
            })) => {
                if !as_json {
                    out!("{service}: queued at position {position}");
                }
            }
            Ok(Some(_)) => {}
            Ok(None) => {
                client.unlink(link);
                anyhow::bail!("link not set up within 30 s");
            }
            Err(UserError::Interrupted) => {
                client.unlink(link);
                return Ok(ExitCode::from(130));
            }
            Err(e) => return Err(e.into()),
        }
    }
    let (Some(ds), Some(cs)) = (data_session, cmd_session) else {
        anyhow::bail!("link up without both sessions");
    };
    emit(
        as_json,
        json!({"linked": true, "link": link, "data": data.0, "command": command.0,
               "data_session": ds.to_string(), "command_session": cs.to_string()}),
        format!("linked: {data} -> {command} (link {link})"),
    );
    let deadline = Instant::now() + duration;
    let mut ended = None;
    while ended.is_none() {
        match client.next_event(deadline) {
            Ok(Some(UserEvent::Update {
                session,
                seq,
                gap,
                payload,
                ..
            })) if session == ds => emit(
                as_json,
                json!({"seq": seq, "gap": gap, "payload": payload.to_json(), "from": data.0}),
                format!("#{seq} {data}: {payload}"),
            ),
            Ok(Some(UserEvent::LinkForwarded { input, .. })) => emit(
                as_json,
                json!({"forwarded": input.to_json(), "to": command.0}),
                format!("  -> {command}: {input}"),
            ),
            Ok(Some(UserEvent::Status {
                session,
                seq,
                status,
                ..
            })) if session == cs => emit(
                as_json,
                json!({"seq": seq, "status": status.to_string(), "state": status.state(),
                   "detail": status.detail(), "from": command.0, "payload": null}),
                format!("#{seq} {command}: {status}"),
            ),
            Ok(Some(UserEvent::LinkEnded { link: l, reason })) if l == link => ended = Some(reason),
            Ok(Some(_)) => {}
            Ok(None) | Err(UserError::Interrupted) => break,
            Err(e) => return Err(e.into()),
        }
    }
    let reason = match ended {
        Some(r) => r,
        None => {
            client.unlink(link);
            EndReason::DurationOver.to_string()
        }
    };
    emit(
        as_json,
        json!({"ended": true, "reason": reason}),
        format!("link ended: {reason}"),
    );
    client.close();
    Ok(ExitCode::SUCCESS)
}
