//! `muster user behave`: one scripted user, as the paper's users behaved (sped up).

use crate::cli::BehaveArgs;
use muster_shared::protocol::monotonic_ns;
use muster_shared::types::{link_compatible, ServiceId, ServiceKind};
use muster_users::{UserClient, UserError, UserEvent};
use rand::{RngExt, SeedableRng};
use serde::Serialize;
use std::collections::BTreeMap;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// Most update-latency samples one user reports.
const MAX_UPDATE_SAMPLES: usize = 2000;

/// What one user did and saw; printed as one JSON line.
#[derive(Debug, Default, Serialize)]
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
        Err(_) => r.report.errors += 1,
    }
    r.report.ended_ms = monotonic_ns() / 1_000_000;
    let Run { client, report, .. } = r;
    client.close();
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
        if let UserEvent::Update { gap, sent_ns, .. } = e {
            self.report.updates += 1;
            self.report.gaps += gap;
            if *sent_ns > 0 && self.report.update_us.len() < MAX_UPDATE_SAMPLES {
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
        let id = ids[self.rng.random_range(0..ids.len())].clone();
        let t = Instant::now();
        let at = monotonic_ns() / 1_000_000;
        let req = self.client.request(&id)?;
        self.report.requests += 1;
        let mut deadline = t + Duration::from_secs(10);
        let mut queued = false;
        let session = loop {
            match self.client.next_event(deadline)? {
                Some(UserEvent::Granted {
                    req: r, session, ..
                }) if r == req => {
                    if !queued {
                        self.report.request_us.push(us(t.elapsed()));
                        self.report.request_at_ms.push(at);
                    }
                    self.report.grants += 1;
                    break Some(session);
                }
                Some(UserEvent::Refused { req: r, reason, .. }) if r == req => {
                    self.report.request_us.push(us(t.elapsed()));
                    self.report.request_at_ms.push(at);
                    *self
                        .report
                        .refusals
                        .entry(reason.code().to_string())
                        .or_default() += 1;
                    break None;
                }
                Some(UserEvent::Queued { req: r, .. }) if r == req && !queued => {
                    // The answer is "wait": that is the response time; then wait a while.
                    self.report.request_us.push(us(t.elapsed()));
                    self.report.request_at_ms.push(at);
                    queued = true;
                    deadline = Instant::now() + self.args.hold_max;
                }
                Some(e) => self.count(&e),
                None => {
                    self.client.cancel(req);
                    if queued {
                        self.report.abandoned += 1;
                    } else {
                        self.report.errors += 1;
                    }
                    break None;
                }
            }
        };
        if let Some(session) = session {
            let until = (Instant::now() + self.hold_time()).min(self.end);
            while let Some(e) = self.client.next_event(until)? {
                if matches!(&e, UserEvent::Ended { session: s, .. } if *s == session) {
                    return Ok(());
                }
                self.count(&e);
            }
            self.ending.insert(session, Instant::now());
            self.client.end(session);
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
                    .filter(|c| link_compatible(d.payload.as_str(), c.payload.as_str()))
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
