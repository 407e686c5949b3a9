//! Broker core tests on a virtual clock.

use super::*;
use proptest::prelude::*;

const S: Duration = Duration::from_secs(1);

fn spec(name: &str, quota: u16, queue: bool) -> ServiceSpec {
    ServiceSpec {
        name: name.into(),
        description: format!("{name} service"),
        kind: ServiceKind::Data,
        queue,
        quota,
        payload: "pose2d".into(),
        schema: None,
    }
}

fn user(n: u32) -> UserId {
    UserId(format!("u{n}"))
}

fn broker() -> Broker {
    Broker::new(BrokerConfig::default(), 42, 1000)
}

fn drain(b: &mut Broker) -> Vec<Output> {
    std::iter::from_fn(|| b.poll_output()).collect()
}

fn register(b: &mut Broker, now: Duration, system: &str, pid: u32, specs: Vec<ServiceSpec>) {
    b.handle(
        now,
        ToBroker::Register {
            system: system.into(),
            pid,
            services: specs,
            sessions: vec![],
            udp: None,
        },
    );
}

/// Says hello for user `u` (once) and requests `id`.
fn request(b: &mut Broker, now: Duration, u: u32, req: u64, id: &str) {
    if !b.users().any(|x| *x == user(u)) {
        b.handle(
            now,
            ToBroker::Hello {
                user: user(u),
                pid: u,
                links: vec![],
                watch_list: false,
            },
        );
    }
    b.handle(
        now,
        ToBroker::Request {
            user: user(u),
            req,
            service: ServiceId(id.into()),
        },
    );
}

/// The single user-bound answer in `out` for (user, req).
fn answers(out: &[Output], u: u32, req: u64) -> Vec<ToUser> {
    out.iter()
        .filter_map(|o| match o {
            Output::ToUser(who, m) if *who == user(u) => match m {
                ToUser::Refused { req: r, .. } | ToUser::Queued { req: r, .. } if *r == req => {
                    Some(m.clone())
                }
                _ => None,
            },
            _ => None,
        })
        .collect()
}

/// The session `out` grants user `u` for request `req`, if it does.
fn granted(out: &[Output], u: u32, req: u64) -> Option<SessionId> {
    out.iter().find_map(|o| match o {
        Output::Granted(g) if g.user == user(u) && g.req == req => Some(g.session),
        _ => None,
    })
}

/// The sessions of user `u` that `out` ends, with why.
fn ended(out: &[Output], u: u32) -> Vec<(SessionId, EndReason)> {
    out.iter()
        .filter_map(|o| match o {
            Output::ToUser(
                who,
                ToUser::Ended {
                    session, reason, ..
                },
            ) if *who == user(u) => Some((*session, reason.clone())),
            _ => None,
        })
        .collect()
}

fn offers(out: &[Output]) -> Vec<(String, u64, UserId, u64)> {
    out.iter()
        .filter_map(|o| match o {
            Output::ToSystem(
                s,
                ToSystem::Offer {
                    ticket, user, req, ..
                },
            ) => Some((s.clone(), *ticket, user.clone(), *req)),
            _ => None,
        })
        .collect()
}

/// `system` confirms offer `ticket` (with the session the broker granted: 0 if the
/// ticket is not out); returns the session.
fn grant(b: &mut Broker, now: Duration, system: &str, ticket: u64) -> SessionId {
    let session = b.offers.get(&ticket).map_or(SessionId(0), |o| o.session);
    b.handle(
        now,
        ToBroker::OfferAnswer {
            system: system.into(),
            ticket,
            answer: Ok(session),
        },
    );
    session
}

fn view<'a>(views: &'a [ServiceView], id: &str) -> &'a ServiceView {
    views.iter().find(|v| v.id == id).expect("listed")
}

#[test]
fn registration_lists_services_and_bumps_generation() {
    let mut b = broker();
    let (g0, v0) = b.take_list_change().unwrap();
    assert!(v0.is_empty());
    register(
        &mut b,
        S,
        "t1",
        7,
        vec![spec("b", 10, false), spec("a", 3, true)],
    );
    let out = drain(&mut b);
    assert!(out.contains(&Output::WatchSystem {
        system: "t1".into(),
        pid: 7
    }));
    assert!(out.contains(&Output::ToSystem(
        "t1".into(),
        ToSystem::Registered {
            epoch: 42,
            broker_pid: 1000
        }
    )));
    let (g1, views) = b.take_list_change().unwrap();
    assert_eq!(g1, g0 + 1);
    let ids: Vec<&str> = views.iter().map(|v| v.id.as_str()).collect();
    assert_eq!(ids, ["t1/a", "t1/b"]);
    assert_eq!(view(&views, "t1/a").quota, 3);
    assert!(view(&views, "t1/a").queue);
    assert!(
        b.take_list_change().is_none(),
        "no change, no new generation"
    );
}

#[test]
fn rows_taken_by_their_counts_are_the_list_and_name_the_rows_that_changed() {
    let mut b = broker();
    let (mut rows, mut shape) = (Vec::new(), u64::MAX);
    let mut take = |b: &mut Broker, rows: &mut Vec<ServiceView>| {
        let (_, changed) = b.take_list_change_rows(rows, &mut shape).unwrap();
        assert_eq!(*rows, b.views());
        changed
    };
    register(
        &mut b,
        S,
        "t1",
        7,
        vec![
            spec("a", 3, true),
            spec("b", 10, false),
            spec("c", 1, false),
        ],
    );
    assert_eq!(take(&mut b, &mut rows), None, "services came: every row");
    // A grant (t1/b's sessions in use): only its row.
    request(&mut b, S, 1, 1, "t1/b");
    let t = offers(&drain(&mut b))[0].1;
    grant(&mut b, S, "t1", t);
    drain(&mut b);
    assert_eq!(take(&mut b, &mut rows), Some(vec![1]));
    // A request for t1/a (an offer out counts in use) and t1/c withdrawn: two rows.
    request(&mut b, S, 2, 1, "t1/a");
    drain(&mut b);
    b.handle(
        S,
        ToBroker::Withdraw {
            system: "t1".into(),
            service: "c".into(),
        },
    );
    drain(&mut b);
    assert_eq!(take(&mut b, &mut rows), Some(vec![0, 2]));
    // Nothing changed: no new generation.
    assert!(b.take_list_change_rows(&mut rows, &mut shape).is_none());
    // The same system declaring its services anew (a description changed): every row.
    let mut d = spec("a", 3, true);
    d.description = "another".into();
    register(
        &mut b,
        S,
        "t1",
        7,
        vec![d, spec("b", 10, false), spec("c", 1, false)],
    );
    drain(&mut b);
    let (_, changed) = b.take_list_change_rows(&mut rows, &mut shape).unwrap();
    assert_eq!((changed, rows.clone()), (None, b.views()));
    assert_eq!(view(&rows, "t1/a").description, "another");
}

#[test]
fn rows_written_over_in_place_are_the_list() {
    let mut b = broker();
    let mut rows = Vec::new();
    b.take_list_change_into(&mut rows).unwrap();
    register(
        &mut b,
        S,
        "t1",
        7,
        vec![spec("b", 10, false), spec("a", 3, true)],
    );
    b.take_list_change_into(&mut rows).unwrap();
    assert_eq!(rows, b.views());
    // A service that sorts first shifts every row; a withdrawal changes one.
    register(&mut b, S, "t0", 8, vec![spec("z", 2, false)]);
    b.handle(
        S,
        ToBroker::Withdraw {
            system: "t1".into(),
            service: "b".into(),
        },
    );
    b.take_list_change_into(&mut rows).unwrap();
    assert_eq!(rows, b.views());
    let ids: Vec<&str> = rows.iter().map(|v| v.id.as_str()).collect();
    assert_eq!(ids, ["t0/z", "t1/a", "t1/b"]);
    assert!(view(&rows, "t1/b").withdrawn);
    // Fewer services: the rows left over go.
    b.handle(
        S,
        ToBroker::Unregister {
            system: "t1".into(),
        },
    );
    b.take_list_change_into(&mut rows).unwrap();
    assert_eq!(rows, b.views());
    assert_eq!(rows.len(), 1);
}

#[test]
fn bad_registrations_are_refused_with_reasons() {
    let mut b = broker();
    register(
        &mut b,
        S,
        "t1",
        7,
        vec![spec("a", 1, false), spec("a", 1, false)],
    );
    register(&mut b, S, "bad name", 8, vec![spec("a", 1, false)]);
    register(&mut b, S, "t2", 9, vec![spec("a", 0, false)]);
    let reasons: Vec<String> = drain(&mut b)
        .into_iter()
        .filter_map(|o| match o {
            Output::ToSystem(_, ToSystem::RegistrationRefused { reason }) => Some(reason),
            _ => None,
        })
        .collect();
    assert_eq!(reasons.len(), 3);
    assert!(reasons[0].contains("declared twice"));
    assert!(reasons[1].contains("invalid system name"));
    assert!(reasons[2].contains("quota"));
    assert!(b.views().is_empty());
    assert_eq!(b.stats().registrations_refused, 3);
}

#[test]
fn a_name_held_by_a_live_process_cannot_be_taken() {
    let mut b = broker();
    register(&mut b, S, "t1", 7, vec![spec("a", 1, false)]);
    drain(&mut b);
    register(&mut b, S, "t1", 8, vec![spec("evil", 1, false)]);
    let out = drain(&mut b);
    assert!(
        matches!(&out[..], [Output::ToSystem(_, ToSystem::RegistrationRefused { reason })] if reason.contains("held by live process 7"))
    );
    assert_eq!(b.views().len(), 1);
    assert_eq!(b.views()[0].name, "a");
}

#[test]
fn the_list_grows_past_the_old_256_to_the_configured_limit_and_refuses_past_it() {
    let cfg = BrokerConfig {
        max_services: 1000,
        ..BrokerConfig::default()
    };
    let mut b = Broker::new(cfg, 42, 1000);
    let per = muster_shared::types::MAX_SERVICES_PER_SYSTEM;
    let mut registered = 0;
    for i in 0.. {
        let specs: Vec<_> = (0..per).map(|k| spec(&format!("s{k}"), 1, false)).collect();
        register(&mut b, S, &format!("sys{i}"), 100 + i, specs);
        let out = drain(&mut b);
        if out.iter().any(|o| matches!(o, Output::ToSystem(_, ToSystem::RegistrationRefused { reason }) if reason.contains("service list full"))) {
            break;
        }
        registered += per;
    }
    // Seven systems of 128; the eighth would make 1,024.
    assert_eq!(registered, 896);
    assert_eq!(b.views().len(), 896);
}

#[test]
fn ten_hours_of_pings_keep_an_answering_system() {
    let mut b = broker();
    register(&mut b, Duration::ZERO, "t1", 7, vec![spec("a", 1, false)]);
    drain(&mut b);
    let end = Duration::from_secs(10 * 3600);
    // Answer each ping one second later.
    let pings = answer_pings(&mut b, end, S);
    // First ping at 20 s, then every 21 s (20 s after each answer, which takes 1 s).
    assert_eq!(pings, (end.as_secs() - 20) / 21 + 1);
    assert_eq!(b.stats().delinquent, 0);
    assert_eq!(b.views().len(), 1);
}

/// Pings (answered at once) in `span` of wall time, on a broker at `scale`.
fn pings_in(scale: f64, span: Duration) -> u64 {
    let cfg = BrokerConfig::default().scaled(muster_shared::clock::TimeScale::new(scale).unwrap());
    let mut b = Broker::new(cfg, 42, 1000);
    register(&mut b, Duration::ZERO, "t1", 7, vec![spec("a", 1, false)]);
    drain(&mut b);
    answer_pings(&mut b, span, Duration::ZERO)
}

/// Runs the broker's timers until `end`, answering every ping `delay` later; returns
/// how many pings came.
fn answer_pings(b: &mut Broker, end: Duration, delay: Duration) -> u64 {
    let mut pings = 0;
    while let Some(t) = b.poll_timeout() {
        if t > end {
            break;
        }
        b.handle_timeout(t);
        for o in drain(b) {
            if let Output::ToSystem(system, ToSystem::Ping { nonce }) = o {
                pings += 1;
                let pong = ToBroker::Pong {
                    system,
                    nonce,
                    held: None,
                };
                b.handle(t + delay, pong);
            }
        }
    }
    pings
}

#[test]
fn a_broker_at_time_scale_ten_pings_ten_times_as_often() {
    let hour = Duration::from_secs(3600);
    assert_eq!(pings_in(1.0, hour), 180, "every 20 s");
    assert_eq!(pings_in(10.0, hour), 1800, "every 2 s of wall time");
    let cfg = BrokerConfig::default().scaled(muster_shared::clock::TimeScale::new(10.0).unwrap());
    assert_eq!(
        cfg.ping_timeout,
        muster_shared::clock::MIN_WALL_DEADLINE,
        "floored"
    );
    assert_eq!(
        cfg.offer_timeout,
        Duration::from_secs(10),
        "infrastructure: wall time"
    );
    let x2 = BrokerConfig::default().scaled(muster_shared::clock::TimeScale::new(2.0).unwrap());
    assert_eq!(x2.ping_timeout, Duration::from_secs(5));
}

#[test]
fn a_silent_system_becomes_delinquent_and_can_come_back() {
    let mut b = broker();
    register(&mut b, Duration::ZERO, "t1", 7, vec![spec("a", 1, true)]);
    request(&mut b, S, 1, 1, "t1/a");
    request(&mut b, S, 2, 2, "t1/a"); // queued behind user 1's offer
    drain(&mut b);
    assert_eq!(
        b.poll_timeout(),
        Some(Duration::from_secs(11)),
        "offer timeout first"
    );
    b.handle_timeout(Duration::from_secs(20));
    let out = drain(&mut b);
    let ping = out.iter().find_map(|o| match o {
        Output::ToSystem(_, ToSystem::Ping { nonce }) => Some(*nonce),
        _ => None,
    });
    assert!(ping.is_some());
    // No pong: at 30 s the system is delinquent.
    b.handle_timeout(Duration::from_secs(29));
    assert!(!drain(&mut b)
        .iter()
        .any(|o| matches!(o, Output::ToSystem(_, ToSystem::Delinquent))));
    b.handle_timeout(Duration::from_secs(30));
    let out = drain(&mut b);
    assert!(out.contains(&Output::ToSystem("t1".into(), ToSystem::Delinquent)));
    assert!(out.contains(&Output::ForgetSystem("t1".into())));
    assert!(b.views().is_empty());
    assert_eq!(b.stats().delinquent, 1);
    // A late pong from the removed system gets told again, so it re-registers.
    b.handle(
        Duration::from_secs(31),
        ToBroker::Pong {
            system: "t1".into(),
            nonce: ping.unwrap(),
            held: None,
        },
    );
    assert_eq!(
        drain(&mut b),
        vec![Output::ToSystem("t1".into(), ToSystem::Delinquent)]
    );
    register(
        &mut b,
        Duration::from_secs(32),
        "t1",
        7,
        vec![spec("a", 1, true)],
    );
    assert_eq!(b.views().len(), 1);
    assert_eq!(b.views()[0].in_use, 0);
}

#[test]
fn queue_and_quota_arbitration() {
    let mut b = broker();
    register(
        &mut b,
        S,
        "q",
        7,
        vec![spec("a", 2, true), spec("n", 1, false)],
    );
    drain(&mut b);
    // Quota 2 with a queue: two offers, then queue positions 1 and 2.
    for u in 1..=4 {
        request(&mut b, S, u, 10 + u64::from(u), "q/a");
    }
    let out = drain(&mut b);
    let off = offers(&out);
    assert_eq!(
        off.iter().map(|o| o.2.clone()).collect::<Vec<_>>(),
        vec![user(1), user(2)]
    );
    assert_eq!(
        answers(&out, 3, 13),
        vec![ToUser::Queued {
            req: 13,
            position: 1
        }]
    );
    assert_eq!(
        answers(&out, 4, 14),
        vec![ToUser::Queued {
            req: 14,
            position: 2
        }]
    );
    let first = grant(&mut b, S, "q", off[0].1);
    grant(&mut b, S, "q", off[1].1);
    let views = b.views();
    assert_eq!(view(&views, "q/a").in_use, 2);
    assert_eq!(view(&views, "q/a").queued, 2);
    drain(&mut b);
    // A session ends: the head of the queue is offered, the other moves to position 1.
    b.handle(
        S,
        ToBroker::SessionEnded {
            system: "q".into(),
            session: first,
        },
    );
    let out = drain(&mut b);
    assert_eq!(
        offers(&out).iter().map(|o| o.2.clone()).collect::<Vec<_>>(),
        vec![user(3)]
    );
    assert_eq!(
        answers(&out, 4, 14),
        vec![ToUser::Queued {
            req: 14,
            position: 1
        }]
    );
    // Without a queue: quota full.
    request(&mut b, S, 1, 20, "q/n");
    let t = offers(&drain(&mut b))[0].1;
    grant(&mut b, S, "q", t);
    request(&mut b, S, 2, 21, "q/n");
    assert_eq!(
        answers(&drain(&mut b), 2, 21),
        vec![ToUser::Refused {
            req: 21,
            reason: Refusal::QuotaFull { quota: 1 }
        }]
    );
}

#[test]
fn queue_capacity_and_duplicates() {
    let cfg = BrokerConfig {
        queue_capacity: 2,
        ..BrokerConfig::default()
    };
    let mut b = Broker::new(cfg, 1, 1);
    register(&mut b, S, "q", 7, vec![spec("a", 1, true)]);
    request(&mut b, S, 1, 1, "q/a");
    request(&mut b, S, 2, 3, "q/a");
    // A user already waiting in the queue asks again: refused.
    request(&mut b, S, 2, 2, "q/a");
    request(&mut b, S, 3, 4, "q/a");
    request(&mut b, S, 4, 5, "q/a");
    let out = drain(&mut b);
    assert!(granted(&out, 1, 1).is_some());
    assert_eq!(
        answers(&out, 2, 2),
        vec![ToUser::Refused {
            req: 2,
            reason: Refusal::AlreadyPending
        }]
    );
    assert_eq!(
        answers(&out, 2, 3),
        vec![ToUser::Queued {
            req: 3,
            position: 1
        }]
    );
    assert_eq!(
        answers(&out, 3, 4),
        vec![ToUser::Queued {
            req: 4,
            position: 2
        }]
    );
    assert_eq!(
        answers(&out, 4, 5),
        vec![ToUser::Refused {
            req: 5,
            reason: Refusal::QueueFull { waiting: 2 }
        }]
    );
    // Cancelling moves the next one up.
    b.handle(
        S,
        ToBroker::Cancel {
            user: user(2),
            req: 3,
        },
    );
    assert_eq!(
        answers(&drain(&mut b), 3, 4),
        vec![ToUser::Queued {
            req: 4,
            position: 1
        }]
    );
}

#[test]
fn unknown_withdrawn_refused_and_timed_out_requests() {
    let mut b = broker();
    register(&mut b, S, "s", 7, vec![spec("a", 5, true)]);
    request(&mut b, S, 1, 1, "s/zzz");
    request(&mut b, S, 1, 2, "nosuch/a");
    let out = drain(&mut b);
    assert_eq!(
        answers(&out, 1, 1),
        vec![ToUser::Refused {
            req: 1,
            reason: Refusal::Unknown
        }]
    );
    assert_eq!(
        answers(&out, 1, 2),
        vec![ToUser::Refused {
            req: 2,
            reason: Refusal::Unknown
        }]
    );

    b.handle(
        S,
        ToBroker::Withdraw {
            system: "s".into(),
            service: "a".into(),
        },
    );
    assert!(b.views()[0].withdrawn);
    request(&mut b, S, 1, 3, "s/a");
    assert_eq!(
        answers(&drain(&mut b), 1, 3),
        vec![ToUser::Refused {
            req: 3,
            reason: Refusal::Withdrawn
        }]
    );
    b.handle(
        S,
        ToBroker::Restore {
            system: "s".into(),
            service: "a".into(),
        },
    );
    assert!(!b.views()[0].withdrawn);

    // The broker grants at once; a system that cannot take the grant after all (its
    // overload was on its way) makes the broker end it, with the system's reason.
    request(&mut b, S, 1, 4, "s/a");
    let out = drain(&mut b);
    let t = offers(&out)[0].1;
    let session = granted(&out, 1, 4).expect("granted at once");
    assert_eq!(
        session,
        SessionId::for_request(&ServiceId("s/a".into()), &user(1), 4)
    );
    b.handle(
        S,
        ToBroker::OfferAnswer {
            system: "s".into(),
            ticket: t,
            answer: Err("overloaded".into()),
        },
    );
    let out = drain(&mut b);
    assert_eq!(answers(&out, 1, 4), vec![]);
    assert_eq!(
        ended(&out, 1),
        [(session, EndReason::BySystem("overloaded".into()))]
    );
    assert_eq!(b.views()[0].in_use, 0);
    assert_eq!(b.stats().grants_undone, 1);

    // A system that never answers: the user's grant ends, and the system is told to
    // end the session should it open it late.
    request(&mut b, S, 1, 5, "s/a");
    let session = granted(&drain(&mut b), 1, 5).expect("granted at once");
    assert_eq!(b.views()[0].in_use, 1, "an unconfirmed grant holds quota");
    b.handle_timeout(S + BrokerConfig::default().offer_timeout);
    let out = drain(&mut b);
    assert_eq!(answers(&out, 1, 5), vec![]);
    assert_eq!(
        ended(&out, 1),
        [(
            session,
            EndReason::BySystem("the system did not answer".into())
        )]
    );
    assert!(out.contains(&Output::ToSystem(
        "s".into(),
        ToSystem::Terminate {
            session,
            reason: "not confirmed in time".into()
        }
    )));
    assert_eq!(b.views()[0].in_use, 0);
    assert_eq!(b.stats().grants_undone, 2);
}

#[test]
fn a_dead_system_takes_its_services_and_queue_with_it() {
    let mut b = broker();
    register(&mut b, S, "s", 7, vec![spec("a", 1, true)]);
    request(&mut b, S, 1, 1, "s/a");
    request(&mut b, S, 2, 2, "s/a");
    let session = granted(&drain(&mut b), 1, 1).expect("granted at once");
    b.system_died(S, "s");
    let out = drain(&mut b);
    // The grant it had not confirmed ends; the queued request is refused.
    assert_eq!(answers(&out, 1, 1), vec![]);
    assert_eq!(ended(&out, 1), [(session, EndReason::PeerGone)]);
    assert_eq!(
        answers(&out, 2, 2),
        vec![ToUser::Refused {
            req: 2,
            reason: Refusal::SystemGone
        }]
    );
    assert!(out.contains(&Output::ForgetSystem("s".into())));
    assert!(!out
        .iter()
        .any(|o| matches!(o, Output::ToSystem(_, ToSystem::Delinquent))));
    assert!(b.views().is_empty());
    assert_eq!(b.stats().died, 1);
    assert_eq!(b.poll_timeout(), None, "nothing left to ping or time out");
}

#[test]
fn sessions_reported_at_registration_count_against_the_quota() {
    // A new broker after a crash: the system re-registers with its two live sessions.
    let mut b = broker();
    b.handle(
        S,
        ToBroker::Register {
            system: "s".into(),
            pid: 7,
            udp: None,
            services: vec![spec("a", 2, false)],
            sessions: vec![
                ActiveSession {
                    session: SessionId(1),
                    service: "a".into(),
                    user: user(1),
                    relayed: false,
                },
                ActiveSession {
                    session: SessionId(2),
                    service: "a".into(),
                    user: user(2),
                    relayed: false,
                },
            ],
        },
    );
    assert_eq!(b.views()[0].in_use, 2);
    request(&mut b, S, 3, 1, "s/a");
    assert_eq!(
        answers(&drain(&mut b), 3, 1),
        vec![ToUser::Refused {
            req: 1,
            reason: Refusal::QuotaFull { quota: 2 }
        }]
    );
    b.handle(
        S,
        ToBroker::SessionEnded {
            system: "s".into(),
            session: SessionId(2),
        },
    );
    request(&mut b, S, 3, 2, "s/a");
    assert_eq!(offers(&drain(&mut b)).len(), 1);
}

#[test]
fn requests_from_users_that_never_said_hello_are_refused() {
    let mut b = broker();
    register(&mut b, S, "s", 7, vec![spec("a", 1, false)]);
    drain(&mut b);
    b.handle(
        S,
        ToBroker::Request {
            user: user(9),
            req: 1,
            service: ServiceId::new("s", "a"),
        },
    );
    let out = drain(&mut b);
    assert!(
        matches!(&answers(&out, 9, 1)[..], [ToUser::Refused { reason: Refusal::BadRequest(r), .. }] if r.contains("hello"))
    );
    assert!(offers(&out).is_empty());
    // A user known dead is refused the same way.
    request(&mut b, S, 8, 1, "s/a");
    drain(&mut b);
    b.user_died(S, &user(8));
    b.handle(
        S,
        ToBroker::Request {
            user: user(8),
            req: 2,
            service: ServiceId::new("s", "a"),
        },
    );
    assert!(offers(&drain(&mut b)).is_empty());
}

#[test]
fn only_watching_users_are_rung_on_list_changes() {
    let mut b = broker();
    for (u, watch) in [(1, true), (2, false), (3, true)] {
        b.handle(
            S,
            ToBroker::Hello {
                user: user(u),
                pid: u,
                links: vec![],
                watch_list: watch,
            },
        );
    }
    let watchers: Vec<&UserId> = b.list_watchers().collect();
    assert_eq!(watchers, [&user(1), &user(3)]);
    b.user_died(S, &user(3));
    assert_eq!(b.list_watchers().collect::<Vec<_>>(), [&user(1)]);
}

#[test]
fn links_are_visible_and_go_with_their_user() {
    let mut b = broker();
    register(&mut b, S, "t", 7, vec![spec("a", 5, false)]);
    let mut cmd = spec("go", 1, true);
    cmd.kind = ServiceKind::Command;
    register(&mut b, S, "d", 8, vec![cmd]);
    let link = LinkInfo {
        link: 1,
        data: ServiceId::new("t", "a"),
        command: ServiceId::new("d", "go"),
    };
    b.handle(
        S,
        ToBroker::Hello {
            user: user(1),
            pid: 99,
            links: vec![],
            watch_list: true,
        },
    );
    b.handle(
        S,
        ToBroker::LinkOpened {
            user: user(1),
            link,
        },
    );
    let views = b.views();
    assert_eq!(view(&views, "t/a").links, 1);
    assert_eq!(view(&views, "d/go").links, 1);
    b.user_died(S, &user(1));
    let views = b.views();
    assert_eq!(view(&views, "t/a").links, 0);
    assert!(drain(&mut b).contains(&Output::ForgetUser(user(1))));
}

#[test]
fn links_are_bounded_per_user_checked_and_counted_incrementally() {
    let mut b = broker();
    register(
        &mut b,
        S,
        "t",
        7,
        vec![spec("a", 5, false), spec("b", 5, false)],
    );
    let mut cmd = spec("go", 1, true);
    cmd.kind = ServiceKind::Command;
    register(&mut b, S, "d", 8, vec![cmd]);
    b.handle(
        S,
        ToBroker::Hello {
            user: user(1),
            pid: 99,
            links: vec![],
            watch_list: false,
        },
    );
    let link = |n: u64, data: &str, command: &str| ToBroker::LinkOpened {
        user: user(1),
        link: LinkInfo {
            link: n,
            data: ServiceId::new("t", data),
            command: ServiceId::new("d", command),
        },
    };
    // 6,000 links from one user: only the bound is counted.
    for n in 0..6000 {
        b.handle(S, link(n, "a", "go"));
    }
    let views = b.views();
    assert_eq!(view(&views, "t/a").links, MAX_LINKS_PER_USER as u16);
    assert_eq!(view(&views, "d/go").links, MAX_LINKS_PER_USER as u16);
    assert_eq!(b.stats().links_refused, 6000 - MAX_LINKS_PER_USER as u64);
    // A link the wrong way round (command into data) is not counted.
    b.handle(
        S,
        ToBroker::LinkClosed {
            user: user(1),
            link: 0,
        },
    );
    b.handle(
        S,
        ToBroker::LinkOpened {
            user: user(1),
            link: LinkInfo {
                link: 0,
                data: ServiceId::new("d", "go"),
                command: ServiceId::new("t", "b"),
            },
        },
    );
    let views = b.views();
    assert_eq!(view(&views, "t/b").links, 0);
    assert_eq!(view(&views, "t/a").links, MAX_LINKS_PER_USER as u16 - 1);
    // Re-opening the same link number replaces it: counts move, never double.
    b.handle(S, link(1, "b", "go"));
    let views = b.views();
    assert_eq!(view(&views, "t/a").links, MAX_LINKS_PER_USER as u16 - 2);
    assert_eq!(view(&views, "t/b").links, 1);
    assert_eq!(view(&views, "d/go").links, MAX_LINKS_PER_USER as u16 - 1);
    // Hello replaces the user's links (a reconnect).
    b.handle(
        S,
        ToBroker::Hello {
            user: user(1),
            pid: 99,
            links: vec![LinkInfo {
                link: 9,
                data: ServiceId::new("t", "b"),
                command: ServiceId::new("d", "go"),
            }],
            watch_list: false,
        },
    );
    let views = b.views();
    assert_eq!(
        (
            view(&views, "t/a").links,
            view(&views, "t/b").links,
            view(&views, "d/go").links
        ),
        (0, 1, 1)
    );
}

#[derive(Clone, Debug)]
enum Op {
    Request(u32, usize),
    Grant(usize),
    Refuse(usize),
    End(usize),
    Cancel(u32),
    Tick(u64),
    Died(u32),
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        4 => (0..6u32, 0..3usize).prop_map(|(u, s)| Op::Request(u, s)),
        3 => (0..8usize).prop_map(Op::Grant),
        1 => (0..8usize).prop_map(Op::Refuse),
        2 => (0..8usize).prop_map(Op::End),
        1 => (0..6u32).prop_map(Op::Cancel),
        1 => (1..15u64).prop_map(Op::Tick),
        1 => (0..6u32).prop_map(Op::Died),
    ]
}

proptest! {
    /// Whatever happens, a service never has more sessions plus offers out than its quota,
    /// a queue never exceeds its capacity, and every request gets at most one final
    /// answer (a grant or a refusal); one that has none is still queued, was cancelled or
    /// went with its user.
    #[test]
    fn quotas_hold_and_every_request_is_answered(ops in proptest::collection::vec(op(), 1..120)) {
        let cfg = BrokerConfig { queue_capacity: 3, ..BrokerConfig::default() };
        let mut b = Broker::new(cfg, 1, 1);
        let services = ["s/a", "s/b", "s/c"];
        register(&mut b, Duration::ZERO, "s", 7,
            vec![spec("a", 1, true), spec("b", 2, false), spec("c", 3, true)]);
        let mut now = Duration::ZERO;
        let mut next_req = 1u64;
        // Live offers: system, ticket, user, request, session.
        let mut outstanding: Vec<(String, u64, UserId, u64, SessionId)> = Vec::new();
        let mut sessions: Vec<SessionId> = Vec::new();
        let mut final_answers: BTreeMap<(UserId, u64), u32> = BTreeMap::new();
        let mut cancelled: BTreeSet<(UserId, u64)> = BTreeSet::new();
        let mut asked: Vec<(UserId, u64)> = Vec::new();
        for op in ops {
            match op {
                Op::Request(u, s) => {
                    request(&mut b, now, u, next_req, services[s]);
                    asked.push((user(u), next_req));
                    next_req += 1;
                }
                Op::Grant(i) if !outstanding.is_empty() => {
                    let (sys, t, _, _, session) = outstanding.remove(i % outstanding.len());
                    prop_assert_eq!(grant(&mut b, now, &sys, t), session);
                    sessions.push(session);
                }
                Op::Refuse(i) if !outstanding.is_empty() => {
                    let (sys, t, _, _, _) = outstanding.remove(i % outstanding.len());
                    b.handle(now, ToBroker::OfferAnswer { system: sys, ticket: t, answer: Err("no".into()) });
                }
                Op::End(i) if !sessions.is_empty() => {
                    let s = sessions.remove(i % sessions.len());
                    b.handle(now, ToBroker::SessionEnded { system: "s".into(), session: s });
                }
                Op::Cancel(u) => {
                    if let Some((who, r)) = asked.iter().rev().find(|(w, _)| *w == user(u)).cloned() {
                        b.handle(now, ToBroker::Cancel { user: who.clone(), req: r });
                        cancelled.insert((who, r));
                    }
                }
                Op::Tick(secs) => {
                    now += Duration::from_secs(secs);
                    // Keep the system alive: answer pings.
                    b.handle_timeout(now);
                }
                Op::Died(u) => b.user_died(now, &user(u)),
                _ => {}
            }
            for o in drain(&mut b) {
                match o {
                    Output::ToSystem(sys, ToSystem::Offer { ticket, user, req, session, .. }) => {
                        outstanding.push((sys, ticket, user, req, session));
                    }
                    Output::Granted(g) => {
                        *final_answers.entry((g.user, g.req)).or_default() += 1;
                    }
                    Output::ToUser(_, ToUser::Ended { session, .. }) => {
                        // A timed-out grant ends; its system can no longer confirm it.
                        outstanding.retain(|o| o.4 != session);
                    }
                    Output::ToSystem(sys, ToSystem::Ping { nonce }) => {
                        b.handle(
                            now,
                            ToBroker::Pong {
                                system: sys,
                                nonce,
                                held: None,
                            },
                        );
                    }
                    Output::ToUser(user, ToUser::Refused { req, .. }) => {
                        *final_answers.entry((user, req)).or_default() += 1;
                    }
                    _ => {}
                }
            }
            for v in b.views() {
                prop_assert!(v.in_use <= v.quota, "{} in use {} > quota {}", v.id, v.in_use, v.quota);
                prop_assert!(v.queued <= 3);
            }
        }
        for (k, n) in &final_answers {
            prop_assert!(*n <= 1, "request {:?} answered {} times", k, n);
        }
        // Every queued request is one not answered (nor cancelled); every live offer
        // was granted.
        let queued: usize = b.views().iter().map(|v| v.queued as usize).sum();
        let unanswered = asked
            .iter()
            .filter(|k| !final_answers.contains_key(*k) && !cancelled.contains(*k))
            .count();
        prop_assert!(unanswered >= queued);
        for (_, _, w, r, _) in &outstanding {
            prop_assert_eq!(final_answers.get(&(w.clone(), *r)), Some(&1));
        }
    }
}

#[test]
fn only_the_offered_system_may_answer_and_tickets_differ_across_runs() {
    let mut b = broker();
    register(&mut b, S, "t", 7, vec![spec("a", 5, false)]);
    register(&mut b, S, "u", 8, vec![spec("a", 5, false)]);
    drain(&mut b);
    request(&mut b, S, 1, 1, "t/a");
    let (_, ticket, _, _) = offers(&drain(&mut b))[0].clone();
    // Another system answers t's offer: nothing changes.
    grant(&mut b, S, "u", ticket);
    assert!(drain(&mut b).is_empty());
    assert_eq!(b.stats().foreign_answers, 1);
    assert_eq!(view(&b.views(), "u/a").in_use, 0);
    assert_eq!(view(&b.views(), "t/a").in_use, 1);
    let session = grant(&mut b, S, "t", ticket);
    assert!(drain(&mut b).is_empty(), "confirmed: nothing more to say");
    assert_eq!(
        b.systems["t"].sessions.keys().collect::<Vec<_>>(),
        [&session]
    );
    // A broker of another run numbers its offers elsewhere.
    let mut other = Broker::new(BrokerConfig::default(), 43, 1000);
    register(&mut other, S, "t", 7, vec![spec("a", 5, false)]);
    request(&mut other, S, 1, 1, "t/a");
    let (_, t2, _, _) = offers(&drain(&mut other))[0].clone();
    assert_ne!(t2, ticket);
    assert!(ticket.abs_diff(t2) > 1 << 20);
}

#[test]
fn the_same_request_again_while_its_offer_is_out_is_not_a_duplicate() {
    let mut b = broker();
    register(&mut b, S, "t", 7, vec![spec("a", 5, false)]);
    drain(&mut b);
    request(&mut b, S, 1, 1, "t/a");
    let out = drain(&mut b);
    assert_eq!(offers(&out).len(), 1);
    let session = granted(&out, 1, 1).expect("granted");
    // The user reconnected and asks again with the same request number: its grant
    // again (the first may have been lost with the user's connection), no second offer.
    request(&mut b, S, 1, 1, "t/a");
    let out = drain(&mut b);
    assert!(offers(&out).is_empty(), "no second offer");
    assert!(answers(&out, 1, 1).is_empty(), "no already_pending");
    assert_eq!(granted(&out, 1, 1), Some(session));
    // Another request number for the same service is another session, as it would be
    // once the first is confirmed.
    request(&mut b, S, 1, 2, "t/a");
    let out = drain(&mut b);
    assert!(answers(&out, 1, 2).is_empty());
    assert_ne!(granted(&out, 1, 2), Some(session));
    assert!(granted(&out, 1, 2).is_some());
}

#[test]
fn the_event_feed_tells_what_happened_in_order() {
    use muster_shared::protocol::BrokerEvent as E;
    let mut b = broker();
    // Off unless asked: a standby's core keeps none.
    register(&mut b, S, "t0", 6, vec![spec("x", 1, false)]);
    assert_eq!(b.poll_event(), None);
    b.emit_events();
    register(&mut b, S, "t1", 7, vec![spec("s", 1, true)]);
    request(&mut b, S, 1, 1, "t1/s");
    let (_, ticket, _, _) = offers(&drain(&mut b))[0].clone();
    let s99 = grant(&mut b, S, "t1", ticket);
    request(&mut b, S, 2, 1, "t1/s"); // queued behind u1
    request(&mut b, S, 3, 1, "t9/s"); // unknown
    b.handle(
        S,
        ToBroker::Withdraw {
            system: "t1".into(),
            service: "s".into(),
        },
    ); // u2 refused: withdrawn
    b.handle(
        S,
        ToBroker::SessionEnded {
            system: "t1".into(),
            session: s99,
        },
    );
    b.system_died(S, "t1");
    b.user_died(S, &user(3));
    let events: Vec<E> = std::iter::from_fn(|| b.poll_event()).collect();
    let id = ServiceId("t1/s".into());
    let refused = |u: u32, code: &str, reason: &str| E::Refused {
        user: user(u),
        req: 1,
        code: code.into(),
        reason: reason.into(),
    };
    let want = vec![
        E::Registered {
            system: "t1".into(),
            services: vec!["s".into()],
        },
        E::UserJoined { user: user(1) },
        E::Requested {
            user: user(1),
            req: 1,
            service: id.clone(),
        },
        E::Granted {
            user: user(1),
            req: 1,
            service: id.clone(),
            session: s99,
        },
        E::UserJoined { user: user(2) },
        E::Requested {
            user: user(2),
            req: 1,
            service: id.clone(),
        },
        E::Queued {
            user: user(2),
            req: 1,
            service: id.clone(),
            position: 1,
        },
        E::UserJoined { user: user(3) },
        E::Requested {
            user: user(3),
            req: 1,
            service: ServiceId("t9/s".into()),
        },
        refused(3, "unknown", &Refusal::Unknown.to_string()),
        E::Withdrawn {
            service: id.clone(),
            withdrawn: true,
        },
        refused(2, "withdrawn", &Refusal::Withdrawn.to_string()),
        E::SessionEnded {
            service: id,
            session: s99,
        },
        E::SystemRemoved {
            system: "t1".into(),
            why: "died".into(),
        },
        E::UserLeft { user: user(3) },
    ];
    assert_eq!(events, want);
    // And each goes on the feed as JSON a reader can take back.
    let rec = muster_shared::protocol::EventRecord {
        epoch: "000000000000002a".into(),
        seq: 4,
        t_ns: 1,
        event: want[3].clone(),
    };
    let json = serde_json::to_value(&rec).unwrap();
    assert_eq!(json["event"], "granted");
    assert_eq!(json["session"], format!("{s99}"));
    assert_eq!(format!("{s99}").len(), 16, "16 hex digits");
    let back: muster_shared::protocol::EventRecord = serde_json::from_value(json).unwrap();
    assert_eq!(back, rec);
}

#[test]
fn operators_read_the_status_move_and_drop_queued_requests_and_end_sessions() {
    use muster_shared::protocol::Operation as Op_;
    let mut b = broker();
    register(&mut b, S, "d1", 7, vec![spec("s", 1, true)]);
    request(&mut b, S, 1, 1, "d1/s");
    let (_, ticket, _, _) = offers(&drain(&mut b))[0].clone();
    let s77 = grant(&mut b, S, "d1", ticket);
    request(&mut b, S, 2, 1, "d1/s");
    request(&mut b, S, 3, 1, "d1/s");
    drain(&mut b);
    let op = |b: &mut Broker, id: u64, o: Op_| {
        b.handle(
            2 * S,
            ToBroker::Operate {
                user: user(9),
                id,
                op: o,
            },
        );
        let out = drain(b);
        let answer = out
            .iter()
            .find_map(|o| match o {
                Output::ToUser(u, ToUser::Operated { id: i, result }) if *u == user(9) => {
                    assert_eq!(*i, id);
                    Some(result.clone())
                }
                _ => None,
            })
            .expect("an answer to the operator");
        (answer, out)
    };
    // The status: the system and its liveness, the session, the queue in order.
    let (answer, _) = op(&mut b, 1, Op_::Status);
    let st = answer.unwrap().unwrap();
    assert_eq!(st.systems.len(), 1);
    assert_eq!(st.systems[0].name, "d1");
    assert_eq!(st.systems[0].last_answer_ms, Some(1000));
    assert_eq!(st.systems[0].delinquencies, 0);
    assert_eq!(st.sessions_total, 1);
    assert_eq!(st.sessions[0].session, s77);
    assert_eq!(st.sessions[0].user, user(1));
    assert_eq!(st.queues[0].waiting, vec![(user(2), 1), (user(3), 1)]);
    // u3 moves to the head; both hear their new places.
    let (answer, out) = op(
        &mut b,
        2,
        Op_::MoveRequest {
            service: ServiceId("d1/s".into()),
            user: user(3),
            req: 1,
            position: 1,
        },
    );
    assert_eq!(answer, Ok(None));
    assert_eq!(
        answers(&out, 3, 1),
        vec![ToUser::Queued {
            req: 1,
            position: 1
        }]
    );
    assert_eq!(
        answers(&out, 2, 1),
        vec![ToUser::Queued {
            req: 1,
            position: 2
        }]
    );
    // u2 is dropped from the queue and told why.
    let (answer, out) = op(
        &mut b,
        3,
        Op_::DropRequest {
            service: ServiceId("d1/s".into()),
            user: user(2),
            req: 1,
        },
    );
    assert_eq!(answer, Ok(None));
    assert_eq!(
        answers(&out, 2, 1),
        vec![ToUser::Refused {
            req: 1,
            reason: Refusal::ByOperator
        }]
    );
    // Ending the session asks its system to end it.
    let (answer, out) = op(&mut b, 4, Op_::EndSession { session: s77 });
    assert_eq!(answer, Ok(None));
    assert!(out.contains(&Output::ToSystem(
        "d1".into(),
        ToSystem::Terminate {
            session: s77,
            reason: "ended by an operator".into()
        }
    )));
    // What is not there is an error, and nothing changes.
    let (answer, out) = op(
        &mut b,
        5,
        Op_::EndSession {
            session: SessionId(5),
        },
    );
    assert_eq!(answer, Err("no session 0000000000000005".into()));
    assert_eq!(out.len(), 1);
    let (answer, _) = op(
        &mut b,
        6,
        Op_::DropRequest {
            service: ServiceId("d1/s".into()),
            user: user(2),
            req: 1,
        },
    );
    assert!(answer.unwrap_err().contains("no request 1 of u2"));
    // Withdrawing refuses the queue; dropping a user revokes its sessions.
    let (answer, out) = op(
        &mut b,
        7,
        Op_::Withdraw {
            service: ServiceId("d1/s".into()),
        },
    );
    assert_eq!(answer, Ok(None));
    assert_eq!(
        answers(&out, 3, 1),
        vec![ToUser::Refused {
            req: 1,
            reason: Refusal::Withdrawn
        }]
    );
    let (answer, out) = op(&mut b, 8, Op_::DropUser { user: user(1) });
    assert_eq!(answer, Ok(None));
    assert!(out.contains(&Output::ToSystem(
        "d1".into(),
        ToSystem::Revoked { user: user(1) }
    )));
    assert!(!b.users().any(|u| *u == user(1)));
}

#[test]
fn a_systems_own_limit_is_held_here_with_its_reason_and_queues_wait_it_out() {
    let mut b = broker();
    register(
        &mut b,
        S,
        "t",
        7,
        vec![spec("a", 5, false), spec("q", 5, true)],
    );
    let limit = |b: &mut Broker, n: Option<u32>| {
        b.handle(
            S,
            ToBroker::Limit {
                system: "t".into(),
                limit: n.map(|sessions| SessionLimit {
                    sessions,
                    reason: "overburdened".into(),
                }),
            },
        );
    };
    limit(&mut b, Some(2));
    drain(&mut b);
    // Two sessions over its two services, one of them not confirmed yet: the limit.
    request(&mut b, S, 1, 1, "t/a");
    let t1 = offers(&drain(&mut b))[0].1;
    let s1 = grant(&mut b, S, "t", t1);
    request(&mut b, S, 2, 1, "t/q");
    assert!(granted(&drain(&mut b), 2, 1).is_some());
    // A third is refused here with the system's reason, without asking it.
    request(&mut b, S, 3, 1, "t/a");
    let out = drain(&mut b);
    assert!(offers(&out).is_empty());
    assert_eq!(
        answers(&out, 3, 1),
        vec![ToUser::Refused {
            req: 1,
            reason: Refusal::SystemRefused("overburdened".into())
        }]
    );
    // A request for the service with a task queue waits in it instead.
    request(&mut b, S, 4, 1, "t/q");
    assert_eq!(
        answers(&drain(&mut b), 4, 1),
        vec![ToUser::Queued {
            req: 1,
            position: 1
        }]
    );
    // A session of the other service ends: the limit has room, and the queue's head
    // takes it.
    b.handle(
        S,
        ToBroker::SessionEnded {
            system: "t".into(),
            session: s1,
        },
    );
    assert!(granted(&drain(&mut b), 4, 1).is_some());
    request(&mut b, S, 5, 1, "t/q");
    assert_eq!(
        answers(&drain(&mut b), 5, 1),
        vec![ToUser::Queued {
            req: 1,
            position: 1
        }]
    );
    // Raising the limit lets the queue on at once.
    limit(&mut b, Some(3));
    assert!(granted(&drain(&mut b), 5, 1).is_some());
    // Overloaded (a limit of 0) refuses everything; lifting it lets requests through.
    limit(&mut b, Some(0));
    request(&mut b, S, 6, 1, "t/a");
    assert_eq!(answers(&drain(&mut b), 6, 1).len(), 1);
    limit(&mut b, None);
    request(&mut b, S, 6, 2, "t/a");
    assert!(granted(&drain(&mut b), 6, 2).is_some());
}

#[test]
fn a_user_reached_at_a_processs_shared_inbox_says_hello_only_from_that_process() {
    let mut b = broker();
    let hello = |user: &str, pid: u32| ToBroker::Hello {
        user: UserId(user.into()),
        pid,
        links: vec![],
        watch_list: false,
    };
    // Its own process: let through; so is a user with an inbox of its own.
    assert!(b.sender_allowed(Some(4242), &hello("u1f2e3d~4242", 4242)));
    assert!(b.sender_allowed(Some(4242), &hello("u4242-1f2e3d", 4242)));
    // Another process claiming a user of 4242's inbox (its own pid, honestly): refused,
    // or frames for that user would go to process 4242.
    assert!(!b.sender_allowed(Some(77), &hello("u1f2e3d~4242", 77)));
    assert!(!b.sender_allowed(Some(77), &hello("u1f2e3d~4242", 4242)));
    assert_eq!(b.stats().impersonations, 2);
}
