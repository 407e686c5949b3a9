//! `muster user behave`: one scripted user, as the paper's users behaved (sped up).

use crate::cli::BehaveArgs;
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{link_compatible, Payload, ServiceId, ServiceKind, SessionId};
use muster_users::{UserClient, UserError, UserEvent};
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// Most update-latency samples one user reports.
const MAX_UPDATE_SAMPLES: usize = 2000;

/// What one user did and saw; printed as one JSON line.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct BehaveReport {
    /// User id.
    pub user: String,
    /// When it connected and when it stopped: CLOCK_MONOTONIC ms.
    pub started_ms: u64,
    /// See `started_ms`.
    pub ended_ms: u64,
    /// When each list read happened (CLOCK_MONOTONIC ms), matching `list_us`.
    pub list_at_ms: Vec<u64>,
    /// When each request was sent (CLOCK_MONOTONIC ms), matching `request_us`.
    pub request_at_ms: Vec<u64>,
    /// List reads.
    pub lists: u64,
    /// List read latencies, µs.
    pub list_us: Vec<u64>,
    /// Requests sent.
    pub requests: u64,
    /// Requests granted.
    pub grants: u64,
    /// Requests refused, by reason code.
    pub refusals: BTreeMap<String, u64>,
    /// Requests queued and given up after waiting.
    pub abandoned: u64,
    /// Request to grant-or-refusal latencies, µs (queued requests excluded).
    pub request_us: Vec<u64>,
    /// Updates received.
    pub updates: u64,
    /// Update latencies (system send to user receive), µs, the first few thousand.
    pub update_us: Vec<u64>,
    /// Updates lost (sequence gaps).
    pub gaps: u64,
    /// Termination latencies (the user ends a session → the system's confirmation), µs.
    pub end_us: Vec<u64>,
    /// Links that came up.
    pub links: u64,
    /// Links that failed to come up.
    pub link_failures: u64,
    /// Errors (no answer in time, transport failures).
    pub errors: u64,
    /// Every request: what was asked, when, and what came of it.
    pub request_log: Vec<RequestRecord>,
    /// Every session granted: how long it ran.
    pub session_log: Vec<SessionRecord>,
    /// Goals sent into command sessions.
    pub goals: u64,
    /// Grants of a request this user no longer waited for: a duplicate grant, had the
    /// broker given one (`UserCore::unwanted_grants`).
    #[serde(default)]
    pub unwanted_grants: u64,
}

/// One request, as the user saw it.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct RequestRecord {
    /// The service.
    pub service: String,
    /// When it was sent: CLOCK_MONOTONIC ms.
    pub at_ms: u64,
    /// `granted`, `queued` (then granted or abandoned: see `granted_us`), a refusal's
    /// code, or `no_answer`.
    pub answer: String,
    /// Request to first answer, µs (wall).
    pub answer_us: u64,
    /// Request to grant, µs (wall), queue wait included; `None` if never granted.
    pub granted_us: Option<u64>,
}

/// One granted session.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct SessionRecord {
    /// The service.
    pub service: String,
    /// When it was granted: CLOCK_MONOTONIC ms.
    pub granted_at_ms: u64,
    /// How long it ran, wall ms (times `--time-scale` for scenario time).
    pub ran_ms: u64,
    /// `user` (this user ended it, hold time over or leaving) or `system` (ended by
    /// the other side: the system, withdrawal, a death).
    pub ended_by: String,
}

/// A refusal as a request log says it: its code, and for a system's refusal the first
/// words of its reason (e.g. `system_refused: overburdened`).
fn answer_of(reason: &muster_shared::types::Refusal) -> String {
    match reason {
        muster_shared::types::Refusal::SystemRefused(r) => {
            format!(
                "system_refused: {}",
                r.split(':').next().unwrap_or("").trim()
            )
        }
        other => other.code().to_string(),
    }
}

/// A request sent and not yet answered for good.
struct Asked {
    req: u64,
    sent: Instant,
    /// Its entry in the request log.
    log: usize,
    done: bool,
}

/// A session granted and held.
struct Held {
    session: SessionId,
    service: String,
    since: Instant,
    /// When it was granted: CLOCK_MONOTONIC ms.
    at_ms: u64,
    ended: bool,
}

impl Held {
    /// Its record, ended now by `ended_by`.
    fn record(&self, ended_by: &str) -> SessionRecord {
        SessionRecord {
            service: self.service.clone(),
            granted_at_ms: self.at_ms,
            ran_ms: self.since.elapsed().as_millis() as u64,
            ended_by: ended_by.into(),
        }
    }
}

fn us(d: Duration) -> u64 {
    (d.as_micros() as u64).max(1)
}

/// Exponentially distributed pause with the given mean.
fn pause(rng: &mut rand_pcg::Pcg64, mean: Duration) -> Duration {
    let u: f64 = rng.random::<f64>().max(1e-9);
    Duration::from_secs_f64((-u.ln() * mean.as_secs_f64()).min(mean.as_secs_f64() * 10.0))
}

struct Run<'a> {
    client: UserClient,
    args: &'a BehaveArgs,
    rng: rand_pcg::Pcg64,
    report: BehaveReport,
    end: Instant,
    next_refresh: Instant,
    /// Sessions this user ended, with when, until the system confirms.
    ending: BTreeMap<muster_shared::types::SessionId, Instant>,
}

pub fn run(client: UserClient, args: &BehaveArgs) -> anyhow::Result<ExitCode> {
    // The flags are scenario time; this process waits them in wall time.
    let scale = muster_shared::clock::global();
    let args = &BehaveArgs {
        duration: scale.wall(args.duration),
        refresh: scale.wall(args.refresh),
        think: scale.wall(args.think),
        hold_min: scale.wall(args.hold_min),
        hold_max: scale.wall(args.hold_max),
        goal_every: scale.wall(args.goal_every),
        ..args.clone()
    };
    let seed = args.seed ^ (u64::from(std::process::id()) << 32);
    let report = BehaveReport {
        user: client.id().0.clone(),
        started_ms: monotonic_ns() / 1_000_000,
        ..BehaveReport::default()
    };
    let now = Instant::now();
    let mut r = Run {
        client,
        args,
        rng: rand_pcg::Pcg64::seed_from_u64(seed),
        report,
        end: now + args.duration,
        next_refresh: now,
        ending: BTreeMap::new(),
    };
    match r.behave() {
        Ok(()) | Err(UserError::Interrupted) => {}
        // Said, not only counted: a stress run's report has the count, its standard
        // error the cause.
        Err(e) => {
            tracing::warn!(user = %r.client.core().id(), "behaving user stopped: {e}");
            r.report.errors += 1;
        }
    }
    r.report.ended_ms = monotonic_ns() / 1_000_000;
    r.report.unwanted_grants = r.client.core().unwanted_grants();
    let Run { client, report, .. } = r;
    super::user::leave(client);
    println!("{}", serde_json::to_string(&report)?);
    Ok(ExitCode::SUCCESS)
}

impl Run<'_> {
    fn behave(&mut self) -> Result<(), UserError> {
        self.refresh()?;
        while Instant::now() < self.end {
            let until = (Instant::now() + pause(&mut self.rng, self.args.think)).min(self.end);
            self.idle_until(until)?;
            if Instant::now() >= self.end {
                break;
            }
            if self.rng.random::<f64>() < self.args.link_prob {
                self.link()?;
            } else {
                self.request()?;
            }
        }
        Ok(())
    }

    /// Waits, refreshing the list when due and taking in stray events.
    fn idle_until(&mut self, until: Instant) -> Result<(), UserError> {
        loop {
            let now = Instant::now();
            if now >= self.next_refresh {
                self.refresh()?;
            }
            if now >= until {
                return Ok(());
            }
            if let Some(e) = self.client.next_event(until.min(self.next_refresh))? {
                self.count(&e);
            }
        }
    }

    fn refresh(&mut self) -> Result<(), UserError> {
        let t = Instant::now();
        let at = monotonic_ns() / 1_000_000;
        let list = self.client.list()?;
        self.report.list_us.push(us(t.elapsed()));
        self.report.list_at_ms.push(at);
        self.report.lists += 1;
        drop(list);
        self.next_refresh = Instant::now() + pause(&mut self.rng, self.args.refresh);
        Ok(())
    }

    fn count(&mut self, e: &UserEvent) {
        if let UserEvent::EndConfirmed { session } = e {
            if let Some(t) = self.ending.remove(session) {
                self.report.end_us.push(us(t.elapsed()));
            }
        }
        if let UserEvent::Update {
            gap, sent_ns, seq, ..
        } = e
        {
            self.report.updates += 1;
            self.report.gaps += gap;
            // Update 0 (a latched service's, with the grant) was sent before the session
            // opened: its age is not a delivery time.
            if *seq > 0 && *sent_ns > 0 && self.report.update_us.len() < MAX_UPDATE_SAMPLES {
                self.report
                    .update_us
                    .push((monotonic_ns().saturating_sub(*sent_ns) / 1000).max(1));
            }
        }
    }

    fn hold_time(&mut self) -> Duration {
        let (a, b) = (
            self.args.hold_min.as_secs_f64(),
            self.args
                .hold_max
                .as_secs_f64()
                .max(self.args.hold_min.as_secs_f64()),
        );
        Duration::from_secs_f64(a + (b - a) * self.rng.random::<f64>())
    }

    fn request(&mut self) -> Result<(), UserError> {
        let ids: Vec<ServiceId> = self
            .client
            .list()?
            .entries()
            .iter()
            .filter(|e| e.withdrawn == 0)
            .map(|e| e.id())
            .collect();
        if ids.is_empty() {
            return Ok(());
        }
        let first = ids[self.rng.random_range(0..ids.len())].clone();
        let mut want = vec![first.clone()];
        // Sometimes several services of one system at once (the paper's footnote).
        if self.rng.random::<f64>() < self.args.multi_prob {
            let system = first.split().map(|(s, _)| s.to_string());
            let mut more: Vec<ServiceId> = ids
                .iter()
                .filter(|i| **i != first && i.split().map(|(s, _)| s.to_string()) == system)
                .cloned()
                .collect();
            let extra = self.rng.random_range(1..=self.args.multi_extra.max(1));
            for _ in 0..extra {
                if more.is_empty() {
                    break;
                }
                want.push(more.swap_remove(self.rng.random_range(0..more.len())));
            }
        }
        let mut asked = Vec::new();
        for id in &want {
            let t = Instant::now();
            let at = monotonic_ns() / 1_000_000;
            let req = self.client.request(id)?;
            self.report.requests += 1;
            self.report.request_log.push(RequestRecord {
                service: id.0.clone(),
                at_ms: at,
                answer: "no_answer".into(),
                ..RequestRecord::default()
            });
            asked.push(Asked {
                req,
                sent: t,
                log: self.report.request_log.len() - 1,
                done: false,
            });
        }
        let mut deadline = Instant::now() + Duration::from_secs(10);
        let mut sessions: Vec<Held> = Vec::new();
        while asked.iter().any(|a| !a.done) {
            let Some(e) = self.client.next_event(deadline)? else {
                for a in asked.iter_mut().filter(|a| !a.done) {
                    self.client.cancel(a.req);
                    a.done = true;
                    if self.report.request_log[a.log].answer == "queued" {
                        self.report.abandoned += 1;
                    } else {
                        self.report.errors += 1;
                    }
                }
                break;
            };
            let (r, answer, session) = match &e {
                UserEvent::Granted { req, session, .. } => {
                    (*req, "granted".to_string(), Some(*session))
                }
                UserEvent::Refused { req, reason, .. } => (*req, answer_of(reason), None),
                UserEvent::Queued { req, .. } => (*req, "queued".to_string(), None),
                _ => {
                    self.count(&e);
                    continue;
                }
            };
            let Some(a) = asked.iter_mut().find(|a| a.req == r && !a.done) else {
                continue;
            };
            let took = us(a.sent.elapsed());
            let rec = &mut self.report.request_log[a.log];
            let first_answer = rec.answer == "no_answer";
            if first_answer {
                rec.answer = answer.clone();
                rec.answer_us = took;
                self.report.request_us.push(took);
                self.report.request_at_ms.push(rec.at_ms);
            }
            match (answer.as_str(), session) {
                ("granted", Some(session)) => {
                    rec.granted_us = Some(took);
                    self.report.grants += 1;
                    a.done = true;
                    sessions.push(Held {
                        session,
                        service: rec.service.clone(),
                        since: Instant::now(),
                        at_ms: monotonic_ns() / 1_000_000,
                        ended: false,
                    });
                }
                ("queued", _) => {
                    // The answer is "wait": then wait a while for the grant, but not
                    // past leaving.
                    deadline = deadline.max((Instant::now() + self.args.hold_max).min(self.end));
                }
                _ => {
                    *self.report.refusals.entry(answer).or_default() += 1;
                    a.done = true;
                }
            }
        }
        if sessions.is_empty() {
            return Ok(());
        }
        let until = (Instant::now() + self.hold_time()).min(self.end);
        let mut next_goal = Instant::now();
        while sessions.iter().any(|s| !s.ended) {
            let now = Instant::now();
            if now >= until {
                break;
            }
            if now >= next_goal && !self.args.goals.is_empty() {
                let (x, y) = self.args.goals[self.rng.random_range(0..self.args.goals.len())];
                for s in sessions.iter().filter(|s| !s.ended) {
                    if self
                        .client
                        .input(s.session, Payload::Goal2d { x, y })
                        .is_ok()
                    {
                        self.report.goals += 1;
                    }
                }
                next_goal = now + self.args.goal_every;
            }
            let wake = if self.args.goals.is_empty() {
                until
            } else {
                until.min(next_goal)
            };
            if let Some(e) = self.client.next_event(wake)? {
                if let UserEvent::Ended { session, .. } = &e {
                    if let Some(s) = sessions
                        .iter_mut()
                        .find(|s| s.session == *session && !s.ended)
                    {
                        s.ended = true;
                        self.report.session_log.push(s.record("system"));
                        continue;
                    }
                }
                self.count(&e);
            }
        }
        for s in sessions.iter().filter(|s| !s.ended) {
            self.report.session_log.push(s.record("user"));
            self.ending.insert(s.session, Instant::now());
            self.client.end(s.session);
        }
        Ok(())
    }

    fn link(&mut self) -> Result<(), UserError> {
        let list = self.client.list()?;
        let data: Vec<_> = list
            .entries()
            .iter()
            .filter(|e| e.kind() == ServiceKind::Data && e.withdrawn == 0)
            .copied()
            .collect();
        let cmds: Vec<_> = list
            .entries()
            .iter()
            .filter(|e| e.kind() == ServiceKind::Command && e.withdrawn == 0)
            .copied()
            .collect();
        let pairs: Vec<(ServiceId, ServiceId)> = data
            .iter()
            .flat_map(|d| {
                cmds.iter()
                    .filter(|c| {
                        link_compatible(
                            d.payload.as_str(),
                            !d.encoding.as_str().is_empty(),
                            c.payload.as_str(),
                        )
                    })
                    .map(move |c| (d.id(), c.id()))
            })
            .collect();
        if pairs.is_empty() {
            return self.request();
        }
        let (d, c) = pairs[self.rng.random_range(0..pairs.len())].clone();
        let link = match self.client.link(&d, &c) {
            Ok(l) => l,
            Err(UserError::CannotLink(_) | UserError::UnknownService(_)) => {
                self.report.link_failures += 1;
                return Ok(());
            }
            Err(e) => return Err(e),
        };
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            match self.client.next_event(deadline)? {
                Some(UserEvent::LinkUp { link: l }) if l == link => break,
                Some(UserEvent::LinkEnded { link: l, .. }) if l == link => {
                    self.report.link_failures += 1;
                    return Ok(());
                }
                Some(e) => self.count(&e),
                None => {
                    self.client.unlink(link);
                    self.report.link_failures += 1;
                    return Ok(());
                }
            }
        }
        self.report.links += 1;
        let until = (Instant::now() + self.hold_time()).min(self.end);
        while let Some(e) = self.client.next_event(until)? {
            if matches!(&e, UserEvent::LinkEnded { link: l, .. } if *l == link) {
                return Ok(());
            }
            self.count(&e);
        }
        self.client.unlink(link);
        Ok(())
    }
}
