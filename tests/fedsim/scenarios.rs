//! Three hosts on the virtual clock: lists across hosts, sessions across hosts, host
//! loss, partitions and heals, duplicated and reordered frames, relay failovers, and
//! hours of all of it at once.

use super::{LinkFaults, World};
use crate::secs;
use muster_broker::federation::{HOST_GRACE, LIST_REFRESH};
use muster_shared::types::{EndReason, SessionId, UserId};
use muster_systems::synthetic::SyntheticOptions;
use muster_users::core::UserEvent;
use rand::{RngExt, SeedableRng};
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

fn data(name: &str, quota: u16) -> SyntheticOptions {
    crate::data(name, 1, quota)
}

fn sorted(ids: &[&str]) -> Vec<String> {
    let mut v: Vec<String> = ids.iter().map(|s| s.to_string()).collect();
    v.sort();
    v
}

fn granted(events: &[UserEvent]) -> Vec<(u64, SessionId)> {
    events
        .iter()
        .filter_map(|e| match e {
            UserEvent::Granted { req, session, .. } => Some((*req, *session)),
            _ => None,
        })
        .collect()
}

fn ended(events: &[UserEvent]) -> Vec<(SessionId, EndReason)> {
    events
        .iter()
        .filter_map(|e| match e {
            UserEvent::Ended {
                session, reason, ..
            } => Some((*session, reason.clone())),
            _ => None,
        })
        .collect()
}

/// The updates of `session` in `events`: their sequence numbers, and the gaps counted.
fn updates(events: &[UserEvent], session: SessionId) -> (Vec<u64>, u64) {
    let mut seqs = Vec::new();
    let mut gaps = 0;
    for e in events {
        if let UserEvent::Update {
            session: s,
            seq,
            gap,
            ..
        } = e
        {
            if *s == session {
                seqs.push(*seq);
                gaps += gap;
            }
        }
    }
    (seqs, gaps)
}

/// The world of most scenarios: hosts a, b, c; a data system on a and b, a command
/// system on c.
fn three_hosts(seed: u64) -> World {
    let mut w = World::new(&["a", "b", "c"], seed);
    w.add_system(0, &data("ta", 2));
    w.add_system(1, &data("tb", 1));
    w.add_system(2, &crate::command("dc", 1, true));
    w.run_for(secs(1.0));
    w
}

/// User `u` of host `h` asks for `service` and is granted it: the session.
fn grant(w: &mut World, h: usize, u: &UserId, service: &str) -> SessionId {
    let req = w.request(h, u, service);
    w.run_for(secs(0.1));
    let ev = w.take_events(h, u);
    let g = granted(&ev);
    assert_eq!(g.len(), 1, "{u} on host {h} asked for {service}: {ev:?}");
    assert_eq!(g[0].0, req);
    g[0].1
}

#[test]
fn three_hosts_list_each_other_and_a_session_streams_across_hosts_for_an_hour() {
    let mut w = three_hosts(1);
    let (a, b, c) = (0, 1, 2);
    assert_eq!(w.list_ids(a), sorted(&["ta/s0", "tb@b/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(b), sorted(&["ta@a/s0", "tb/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(c), sorted(&["ta@a/s0", "tb@b/s0", "dc/s0"]));
    let u1 = w.add_user(a, "u1");
    let u2 = w.add_user(c, "u2");
    let s1 = grant(&mut w, a, &u1, "tb@b/s0");
    let s2 = grant(&mut w, c, &u2, "ta@a/s0");
    // Each system serves the other host's user as `user@host`.
    let users_of = |w: &World, h: usize, s: &str| -> Vec<String> {
        w.system(h, s)
            .sessions()
            .map(|(_, u, _)| u.0.clone())
            .collect()
    };
    assert_eq!(users_of(&w, b, "tb"), ["u1@a"]);
    assert_eq!(users_of(&w, a, "ta"), ["u2@c"]);
    // The services in use are counted in every host's list.
    let in_use =
        |w: &World, h: usize, id: &str| w.list(h).iter().find(|v| v.id == id).map(|v| v.in_use);
    assert_eq!(in_use(&w, c, "tb@b/s0"), Some(1));
    assert_eq!(in_use(&w, b, "ta@a/s0"), Some(1));
    w.run_for(secs(3600.0));
    for (h, u, s) in [(a, &u1, s1), (c, &u2, s2)] {
        let ev = w.take_events(h, u);
        let (seqs, gaps) = updates(&ev, s);
        assert!(
            seqs.len() >= 35_900,
            "{u}: {} updates in an hour",
            seqs.len()
        );
        assert!(seqs.windows(2).all(|p| p[1] == p[0] + 1), "{u}: in order");
        assert_eq!(gaps, 0, "{u}");
        assert!(ended(&ev).is_empty(), "{u}: {:?}", ended(&ev));
    }
    // Ended by the user: the system hears, the quota comes back.
    w.end(a, &u1, s1);
    w.run_for(secs(0.1));
    assert!(users_of(&w, b, "tb").is_empty());
    let u3 = w.add_user(c, "u3");
    grant(&mut w, c, &u3, "tb@b/s0");
    assert_eq!(w.fed(a).unwrap().stats().hosts_lost, 0);
}

#[test]
fn a_host_lost_ends_its_sessions_everywhere_and_frees_what_its_users_held() {
    let mut w = three_hosts(2);
    let (a, b, c) = (0, 1, 2);
    let ub = w.add_user(b, "ub");
    let ua = w.add_user(a, "ua");
    let uc = w.add_user(c, "uc");
    // ub holds one of ta's two places; ua holds tb's only one.
    grant(&mut w, b, &ub, "ta@a/s0");
    let sa = grant(&mut w, a, &ua, "tb@b/s0");
    grant(&mut w, c, &uc, "ta@a/s0");
    let uc2 = w.add_user(c, "uc2");
    let req = w.request(c, &uc2, "ta@a/s0");
    w.run_for(secs(0.1));
    let ev = w.take_events(c, &uc2);
    assert!(
        ev.iter()
            .any(|e| matches!(e, UserEvent::Refused { req: r, .. } if *r == req)),
        "ta is full: {ev:?}"
    );
    w.lose_host(b);
    w.run_for(secs(0.1));
    // Its services leave every list; the sessions there end as the peer's going.
    assert_eq!(w.list_ids(a), sorted(&["ta/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(c), sorted(&["ta@a/s0", "dc/s0"]));
    assert_eq!(ended(&w.take_events(a, &ua)), [(sa, EndReason::PeerGone)]);
    // Its user's place on ta is free again, and nobody of b is a user of a any more.
    let users: Vec<String> = w.broker(a).unwrap().users().map(|u| u.0.clone()).collect();
    assert_eq!(users, ["ua", "uc2@c", "uc@c"]);
    grant(&mut w, c, &uc2, "ta@a/s0");
    assert_eq!(w.fed(a).unwrap().stats().hosts_lost, 1);
    assert_eq!(w.fed(a).unwrap().stats().sessions_lost, 1);
    // A request for a lost host's service is refused as unknown, not left waiting.
    let req = w.request(a, &ua, "tb@b/s0");
    w.run_for(secs(0.1));
    let ev = w.take_events(a, &ua);
    assert!(
        ev.iter()
            .any(|e| matches!(e, UserEvent::Refused { req: r, .. } if *r == req)),
        "{ev:?}"
    );
}

#[test]
fn a_user_dying_ends_its_sessions_on_other_hosts_and_frees_their_places() {
    let mut w = three_hosts(9);
    let (a, b) = (w.h("a"), w.h("b"));
    let u1 = w.add_user(a, "u1");
    grant(&mut w, a, &u1, "tb@b/s0");
    assert_eq!(w.system(b, "tb").sessions().count(), 1);
    w.kill_user(a, &u1);
    w.run_for(secs(0.5));
    assert_eq!(w.system(b, "tb").sessions().count(), 0);
    let users: Vec<String> = w.broker(b).unwrap().users().map(|u| u.0.clone()).collect();
    assert!(users.is_empty(), "{users:?}");
    let u2 = w.add_user(a, "u2");
    grant(&mut w, a, &u2, "tb@b/s0");
}

#[test]
fn a_host_with_a_standby_is_waited_for_then_given_up() {
    let mut w = three_hosts(12);
    let (a, b) = (w.h("a"), w.h("b"));
    w.set_standby(b, true);
    let ua = w.add_user(a, "ua");
    let sa = grant(&mut w, a, &ua, "tb@b/s0");
    w.lose_host(b);
    // Its standby may take over: it stays listed, and the session open, a while.
    w.run_for(HOST_GRACE - secs(0.5));
    assert!(w.list_ids(a).contains(&"tb@b/s0".to_string()));
    assert!(ended(&w.take_events(a, &ua)).is_empty());
    w.run_for(secs(1.0));
    assert_eq!(w.list_ids(a), sorted(&["ta/s0", "dc@c/s0"]));
    assert_eq!(ended(&w.take_events(a, &ua)), [(sa, EndReason::PeerGone)]);
    assert_eq!(w.fed(a).unwrap().stats().hosts_lost, 1);
}

/// Lists go out whole only when they change; each host says only the version it is at,
/// soon after another host joins and then every [`LIST_REFRESH`]. A host that missed a
/// change (its subscription not yet known where the list was put) sees from that it is
/// behind and asks; one that is up to date asks nothing.
#[test]
fn a_host_that_missed_a_list_change_catches_up_from_the_versions_announced() {
    let mut w = three_hosts(11);
    let (a, b, c) = (0, 1, 2);
    w.run_for(LIST_REFRESH * 3);
    let missed = |w: &World, h: usize| w.fed(h).unwrap().stats().lists_missed;
    assert_eq!(
        (missed(&w, a), missed(&w, b)),
        (0, 0),
        "up to date: nothing asked"
    );
    // b's list changes while a hears no list put whole.
    w.deaf_to_lists.insert(a);
    w.add_system(b, &data("tb2", 1));
    w.run_for(secs(0.1));
    assert!(w.list_ids(b).contains(&"tb2/s0".to_string()));
    assert!(w.list_ids(c).contains(&"tb2@b/s0".to_string()));
    assert!(
        !w.list_ids(a).contains(&"tb2@b/s0".to_string()),
        "a missed it"
    );
    // At b's next announcement a asks, and has it.
    w.run_for(LIST_REFRESH + secs(0.1));
    assert!(w.list_ids(a).contains(&"tb2@b/s0".to_string()));
    assert_eq!(missed(&w, a), 1);
    assert_eq!(missed(&w, c), 0, "c heard the change itself");
    // Caught up: later announcements ask nothing more.
    w.run_for(LIST_REFRESH * 5);
    assert_eq!(missed(&w, a), 1);
    // A host that (re)joins is announced to soon: a change it missed just after its
    // start is caught up within a second, not at the next steady announcement (half a
    // period away).
    w.run_for(LIST_REFRESH / 2);
    w.restart_broker(a);
    w.run_for(secs(0.2));
    assert!(
        w.list_ids(a).contains(&"tb2@b/s0".to_string()),
        "queried at its start"
    );
    assert_eq!(missed(&w, a), 0, "a new core counts anew");
    w.add_system(b, &data("tb3", 1));
    w.run_for(secs(0.1));
    assert!(
        !w.list_ids(a).contains(&"tb3@b/s0".to_string()),
        "a missed it"
    );
    w.run_for(secs(1.0));
    assert!(w.list_ids(a).contains(&"tb3@b/s0".to_string()));
    assert_eq!(missed(&w, a), 1);
}

#[test]
fn a_partition_past_the_lease_ends_cross_host_sessions_and_the_heal_restores_lists_and_service() {
    let mut w = three_hosts(3);
    let (a, b, c) = (0, 1, 2);
    let u1 = w.add_user(a, "u1");
    let s1 = grant(&mut w, a, &u1, "tb@b/s0");
    w.cut(a, b);
    // Within the lease both still list each other; the session waits.
    w.run_for(secs(9.0));
    assert!(w.list_ids(a).contains(&"tb@b/s0".to_string()));
    assert!(ended(&w.take_events(a, &u1)).is_empty());
    // Past it: a and b are gone for each other (not for c), the session ends on both
    // sides, and tb's place is free.
    w.run_for(secs(2.0));
    assert_eq!(w.list_ids(a), sorted(&["ta/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(b), sorted(&["tb/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(c), sorted(&["ta@a/s0", "tb@b/s0", "dc/s0"]));
    assert_eq!(ended(&w.take_events(a, &u1)), [(s1, EndReason::PeerGone)]);
    assert_eq!(w.system(b, "tb").sessions().count(), 0);
    w.run_for(secs(20.0));
    w.heal(a, b);
    w.run_for(secs(1.0));
    assert_eq!(w.list_ids(a), sorted(&["ta/s0", "tb@b/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(b), sorted(&["ta@a/s0", "tb/s0", "dc@c/s0"]));
    let s2 = grant(&mut w, a, &u1, "tb@b/s0");
    w.run_for(secs(600.0));
    let (seqs, gaps) = updates(&w.take_events(a, &u1), s2);
    assert!(seqs.len() >= 5_990, "{}", seqs.len());
    assert_eq!(gaps, 0);
}

#[test]
fn a_partition_shorter_than_the_lease_loses_no_update() {
    let mut w = three_hosts(4);
    let (a, b) = (0, 1);
    let u1 = w.add_user(a, "u1");
    let s1 = grant(&mut w, a, &u1, "tb@b/s0");
    w.run_for(secs(5.0));
    w.cut(a, b);
    w.run_for(secs(4.0));
    w.heal(a, b);
    w.run_for(secs(5.0));
    let ev = w.take_events(a, &u1);
    let (seqs, gaps) = updates(&ev, s1);
    assert!(seqs.len() >= 139, "{}", seqs.len());
    assert!(seqs.windows(2).all(|p| p[1] == p[0] + 1));
    assert_eq!(gaps, 0);
    assert!(ended(&ev).is_empty());
    assert_eq!(w.fed(a).unwrap().stats().hosts_lost, 0);
}

/// Users taking turns with one service: each asks, holds what it is granted a few
/// seconds, and ends it. Every step checks that no request is granted twice, no user
/// holds two sessions of it, and the system never serves more than the quota.
struct Turns {
    rng: rand_pcg::Pcg64,
    users: Vec<(usize, UserId)>,
    service: String,
    /// The host and name of the system behind the service.
    system: (usize, String),
    quota: usize,
    /// user → (session held, when to end it)
    holding: BTreeMap<UserId, (SessionId, Duration)>,
    /// user → when it last asked, while it waits for an answer
    asked: BTreeMap<UserId, Duration>,
    grants: BTreeMap<(UserId, u64), u32>,
    /// Grants made.
    total: u64,
}

impl Turns {
    fn new(seed: u64, users: &[(usize, UserId)], service: &str, system: (usize, &str)) -> Self {
        Turns {
            rng: rand_pcg::Pcg64::seed_from_u64(seed),
            users: users.to_vec(),
            service: service.into(),
            system: (system.0, system.1.into()),
            quota: 1,
            holding: BTreeMap::new(),
            asked: BTreeMap::new(),
            grants: BTreeMap::new(),
            total: 0,
        }
    }

    /// Runs the turns for `d` of virtual time; the grants made in it.
    fn run(&mut self, w: &mut World, d: Duration) -> u64 {
        let before = self.total;
        let end = w.now + d;
        while w.now < end {
            w.run_for(secs(0.25));
            let n = w.system(self.system.0, &self.system.1).sessions_of("s0");
            assert!(
                n <= self.quota,
                "{n} sessions of {} at {:?}",
                self.service,
                w.now
            );
            for (h, u) in self.users.clone() {
                self.step(w, h, &u);
            }
        }
        self.total - before
    }

    fn step(&mut self, w: &mut World, h: usize, u: &UserId) {
        for e in w.take_events(h, u) {
            match e {
                UserEvent::Granted { req, session, .. } => {
                    let n = self.grants.entry((u.clone(), req)).or_default();
                    *n += 1;
                    assert_eq!(*n, 1, "{u}'s request {req} granted twice");
                    assert!(
                        !self.holding.contains_key(u),
                        "{u} granted a second session of {}",
                        self.service
                    );
                    self.total += 1;
                    self.asked.remove(u);
                    let hold = secs(self.rng.random_range(1.0..6.0));
                    self.holding.insert(u.clone(), (session, w.now + hold));
                }
                UserEvent::Refused { .. } => {
                    self.asked.remove(u);
                }
                UserEvent::Ended { session, .. }
                    if self.holding.get(u).is_some_and(|(s, _)| *s == session) =>
                {
                    self.holding.remove(u);
                }
                _ => {}
            }
        }
        match self.holding.get(u).copied() {
            Some((s, until)) if w.now >= until => {
                self.holding.remove(u);
                w.end(h, u, s);
            }
            Some(_) => {}
            // Asks when it has no request out (a refusal, or an end of its host's
            // broker, answers one).
            None if !self.asked.contains_key(u) && self.rng.random_bool(0.5) => {
                self.asked.insert(u.clone(), w.now);
                w.request(h, u, &self.service.clone());
            }
            None => {}
        }
    }
}

#[test]
fn duplicated_and_reordered_frames_never_grant_twice_nor_exceed_a_quota() {
    let mut w = three_hosts(5);
    let (a, b, c) = (0, 1, 2);
    w.faults = LinkFaults {
        dup: 0.3,
        jitter: Duration::from_millis(40),
    };
    let mut users = Vec::new();
    for (h, name) in [(a, "a"), (b, "b")] {
        for k in 0..3 {
            users.push((h, w.add_user(h, &format!("{name}{k}"))));
        }
    }
    let mut turns = Turns::new(5, &users, "dc@c/s0", (c, "dc"));
    let grants = turns.run(&mut w, secs(3600.0));
    assert!(w.duplicated > 1_000, "{} duplicated", w.duplicated);
    // One at a time, a few seconds each, for an hour: hundreds of turns.
    assert!(grants >= 300, "{grants} grants");
    // With the faults gone, turns go on.
    w.faults = LinkFaults::default();
    let grants = turns.run(&mut w, secs(900.0));
    assert!(grants >= 75, "{grants} grants");
}

/// User u1 of host a streams from tb on host b while host `relay`'s broker dies and its
/// standby takes over: the session goes on (same session, updates in order, the ones
/// lost in the takeover counted as a gap), and both directions still work after it (the
/// user's end reaches the system).
fn a_relay_failover_keeps_the_session(relay: &str, seed: u64) {
    let mut w = three_hosts(seed);
    let (a, b, r) = (w.h("a"), w.h("b"), w.h(relay));
    w.set_standby(r, true);
    let u1 = w.add_user(a, "u1");
    let s1 = grant(&mut w, a, &u1, "tb@b/s0");
    w.run_for(secs(10.0));
    w.fail_over(r);
    w.run_for(secs(10.0));
    let ev = w.take_events(a, &u1);
    assert!(ended(&ev).is_empty(), "{:?}", ended(&ev));
    let (seqs, gaps) = updates(&ev, s1);
    assert!(seqs.windows(2).all(|p| p[1] > p[0]), "in order");
    // 20 s at 10 Hz: what came and what was counted lost add up to all of it.
    let last = *seqs.last().unwrap();
    assert!(last >= 200, "{last}");
    assert_eq!(
        seqs.len() as u64 + gaps,
        last - seqs[0] + 1,
        "every update came or is counted"
    );
    assert!(gaps <= 2, "{gaps} lost in the takeover");
    let users: Vec<String> = w.broker(b).unwrap().users().map(|u| u.0.clone()).collect();
    assert_eq!(users, ["u1@a"]);
    let held: Vec<String> = w
        .system(b, "tb")
        .sessions()
        .map(|(_, u, _)| u.0.clone())
        .collect();
    assert_eq!(held, ["u1@a"]);
    // The user's end reaches the system through the new relay; the place is free.
    w.end(a, &u1, s1);
    w.run_for(secs(0.5));
    assert_eq!(w.system(b, "tb").sessions().count(), 0);
    let u2 = w.add_user(a, "u2");
    grant(&mut w, a, &u2, "tb@b/s0");
}

#[test]
fn a_relay_failover_on_the_systems_host_keeps_cross_host_sessions() {
    a_relay_failover_keeps_the_session("b", 6);
}

#[test]
fn a_relay_failover_on_the_users_host_keeps_cross_host_sessions() {
    a_relay_failover_keeps_the_session("a", 7);
}

/// A broker that starts cold (no standby: nothing of the last one's state) relays none
/// of the sessions that went through its predecessor: they end on both hosts, cleanly,
/// and are granted again.
fn a_cold_restart_ends_relayed_sessions(host: &str, seed: u64) {
    let mut w = three_hosts(seed);
    let (a, b, r) = (w.h("a"), w.h("b"), w.h(host));
    let u1 = w.add_user(a, "u1");
    let s1 = grant(&mut w, a, &u1, "tb@b/s0");
    w.run_for(secs(5.0));
    w.restart_broker(r);
    w.run_for(secs(2.0));
    let ev = w.take_events(a, &u1);
    assert_eq!(ended(&ev), [(s1, EndReason::PeerGone)]);
    assert_eq!(w.system(b, "tb").sessions().count(), 0);
    let s2 = grant(&mut w, a, &u1, "tb@b/s0");
    w.run_for(secs(60.0));
    let (seqs, gaps) = updates(&w.take_events(a, &u1), s2);
    assert!(seqs.len() >= 590, "{}", seqs.len());
    assert_eq!(gaps, 0);
}

#[test]
fn a_cold_restart_on_the_systems_host_ends_cross_host_sessions_cleanly() {
    a_cold_restart_ends_relayed_sessions("b", 10);
}

#[test]
fn a_cold_restart_on_the_users_host_ends_cross_host_sessions_cleanly() {
    a_cold_restart_ends_relayed_sessions("a", 11);
}

/// Six hours of everything: users on every host taking turns with every other host's
/// services while links are cut (short and long), brokers fail over and restart, and
/// frames are duplicated and reordered. Checked all along: no request granted twice, no
/// quota exceeded; at the end, with the faults gone, lists agree and service resumes.
#[test]
fn six_hours_of_partitions_failovers_and_churn_keep_grants_single_and_lists_converging() {
    let mut w = three_hosts(8);
    let (a, b, c) = (0, 1, 2);
    let mut users = Vec::new();
    for (h, name) in [(a, "a"), (b, "b")] {
        for k in 0..2 {
            users.push((h, w.add_user(h, &format!("{name}{k}"))));
        }
    }
    w.set_standby(b, true);
    w.set_standby(c, true);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(8);
    let mut turns = Turns::new(8, &users, "dc@c/s0", (c, "dc"));
    let mut grants = 0;
    for round in 0..24u32 {
        // A quarter hour per round, with one fault in it.
        match round % 6 {
            0 => w.fail_over(c),
            1 => w.restart_broker(a),
            2 => w.cut(a, c),
            3 => {
                w.faults = LinkFaults {
                    dup: 0.2,
                    jitter: Duration::from_millis(30),
                }
            }
            4 => w.cut(b, c),
            _ => w.fail_over(b),
        }
        let t = rng.random_range(60.0..600.0);
        grants += turns.run(&mut w, secs(t));
        w.heal(a, c);
        w.heal(b, c);
        w.faults = LinkFaults::default();
        grants += turns.run(&mut w, secs(900.0 - t));
    }
    assert!(w.now >= secs(6.0 * 3600.0));
    // The faults happened: frames lost with links gone down, duplicates, hosts lost.
    assert!(
        w.lost > 0 && w.duplicated > 0,
        "{} {}",
        w.lost,
        w.duplicated
    );
    // c, since its last failover (round 18): cut from a (round 20), from b (round 22).
    assert!(
        w.fed(c).unwrap().stats().hosts_lost >= 2,
        "{:?}",
        w.fed(c).unwrap().stats()
    );
    assert!(grants >= 1_000, "{grants} grants");
    w.run_for(secs(10.0));
    assert_eq!(w.list_ids(a), sorted(&["ta/s0", "tb@b/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(b), sorted(&["ta@a/s0", "tb/s0", "dc@c/s0"]));
    assert_eq!(w.list_ids(c), sorted(&["ta@a/s0", "tb@b/s0", "dc/s0"]));
    let seen: BTreeSet<usize> = users.iter().map(|(h, _)| *h).collect();
    assert_eq!(seen.len(), 2);
}
