//! A generic system for tests, demos and load: K data services streaming poses on
//! circles, or K command services that drive a virtual robot to each goal given and
//! report progress and arrival within 1 m.

use crate::core::{SystemCore, SystemEvent};
use crate::runtime::SystemApp;
use muster_shared::types::{Payload, ServiceKind, ServiceSpec, SessionId, TaskStatus};
use std::collections::BTreeMap;
use std::time::Duration;

/// How a synthetic system is made.
#[derive(Clone, Debug)]
pub struct SyntheticOptions {
    /// System name.
    pub name: String,
    /// Number of services.
    pub services: usize,
    /// Their kind.
    pub kind: ServiceKind,
    /// Quota of each.
    pub quota: u16,
    /// Whether each keeps a task queue.
    pub queue: bool,
    /// Payload type (default: `pose2d` for data, `goal2d` for command).
    pub payload: Option<String>,
    /// Update rate, Hz.
    pub rate_hz: f64,
}

impl SyntheticOptions {
    /// The service declarations, named `s0`, `s1`, ...
    pub fn specs(&self) -> Vec<ServiceSpec> {
        let payload = self.payload.clone().unwrap_or_else(|| {
            match self.kind {
                ServiceKind::Data => "pose2d",
                ServiceKind::Command => "goal2d",
            }
            .to_string()
        });
        (0..self.services)
            .map(|i| ServiceSpec {
                name: format!("s{i}"),
                description: match self.kind {
                    ServiceKind::Data => {
                        format!("synthetic target {i} of {}: {payload} stream", self.name)
                    }
                    ServiceKind::Command => format!(
                        "synthetic robot {i} of {}: takes {payload} goals",
                        self.name
                    ),
                },
                kind: self.kind,
                queue: self.queue,
                quota: self.quota,
                payload: payload.clone(),
                schema: None,
            })
            .collect()
    }
}

/// Speed of the virtual robot behind a command service, m/s.
pub const ROBOT_SPEED: f64 = 1.0;
/// Distance at which a goal counts as reached, m (the paper's delivery robot: 1 m).
pub const ARRIVAL_RADIUS: f64 = 1.0;

#[derive(Clone, Debug, PartialEq)]
struct Drive {
    pos: (f64, f64),
    goal: Option<(f64, f64)>,
    arrived: bool,
}

/// The synthetic system's logic.
#[derive(Debug)]
pub struct Synthetic {
    kind: ServiceKind,
    period: Duration,
    next: Duration,
    last: Duration,
    drives: BTreeMap<SessionId, Drive>,
}

impl Synthetic {
    /// Logic for `opts`.
    pub fn new(opts: &SyntheticOptions) -> Self {
        let hz = if opts.rate_hz.is_finite() && opts.rate_hz > 0.0 {
            opts.rate_hz
        } else {
            10.0
        };
        Synthetic {
            kind: opts.kind,
            period: Duration::from_secs_f64(1.0 / hz),
            next: Duration::ZERO,
            last: Duration::ZERO,
            drives: BTreeMap::new(),
        }
    }

    /// The pose service `index` streams at time `t`: a 5 m circle, phase by index.
    pub fn pose_at(index: usize, t: Duration) -> Payload {
        let w = 0.2;
        let phase = index as f64 * 0.7;
        let a = w * t.as_secs_f64() + phase;
        Payload::Pose2d {
            x: 5.0 * a.cos(),
            y: 5.0 * a.sin(),
            theta: a + std::f64::consts::FRAC_PI_2,
        }
    }
}

/// How far behind its rate a data system still catches up (sending the missed updates
/// at once); further behind, it starts again from now.
const MAX_CATCH_UP: Duration = Duration::from_millis(100);

impl SystemApp for Synthetic {
    fn on_event(&mut self, core: &mut SystemCore, now: Duration, event: SystemEvent) {
        match event {
            SystemEvent::SessionStarted {
                session, service, ..
            } => {
                // The tick due now sends the session its first update; when the next
                // one is up to a period away (others hold sessions already), a data
                // session gets the current value at once.
                let tick_now = self.next <= now;
                if self.next < now {
                    self.next = now;
                    self.last = now;
                }
                if self.kind == ServiceKind::Data && !tick_now {
                    let i = core.specs().iter().position(|s| s.name == service);
                    if let Some(i) = i {
                        let sent = core.publish_session(
                            session,
                            &Self::pose_at(i, now),
                            muster_shared::protocol::monotonic_ns(),
                        );
                        debug_assert!(sent.is_ok(), "{sent:?}");
                    }
                }
                if self.kind == ServiceKind::Command {
                    self.drives.insert(
                        session,
                        Drive {
                            pos: (0.0, 0.0),
                            goal: None,
                            arrived: false,
                        },
                    );
                    core.status(session, TaskStatus::Idle);
                }
            }
            SystemEvent::Input {
                session, payload, ..
            } => match payload.convert_to("goal2d") {
                Some(Payload::Goal2d { x, y }) => {
                    if let Some(d) = self.drives.get_mut(&session) {
                        let fresh = d.goal.is_none() || d.arrived;
                        d.goal = Some((x, y));
                        d.arrived = false;
                        if fresh {
                            core.status(
                                session,
                                TaskStatus::Working(format!("goal ({x:.2}, {y:.2}) accepted")),
                            );
                        }
                    }
                }
                _ => core.status(
                    session,
                    TaskStatus::Rejected(format!("cannot use {} as a goal", payload.type_name())),
                ),
            },
            SystemEvent::SessionEnded { session, .. } => {
                self.drives.remove(&session);
            }
            _ => {}
        }
    }

    fn on_tick(&mut self, core: &mut SystemCore, now: Duration) {
        let dt = now.saturating_sub(self.last).as_secs_f64();
        self.last = now;
        // The updates due since the last tick, on the grid of the rate: a rate above
        // what one wake-up per period gives (a wake-up is late by its own cost, and the
        // reactor rounds sleeps of 5 ms or more to whole milliseconds)
        // is kept by sending the due ones together. A system far behind (stopped, or a
        // session just started) starts again from now.
        let due = if now.saturating_sub(self.next) > MAX_CATCH_UP {
            self.next = now + self.period;
            1
        } else {
            let mut n = 0u32;
            while self.next <= now {
                self.next += self.period;
                n += 1;
            }
            n.max(1)
        };
        match self.kind {
            ServiceKind::Data => {
                let names: Vec<String> = core.specs().iter().map(|s| s.name.clone()).collect();
                for (i, name) in names.iter().enumerate() {
                    // A latched service updates with no session too: its newest value
                    // waits at the broker for the next one.
                    if core.sessions_of(name) > 0 || core.latched(name) {
                        for _ in 0..due {
                            // A pose always fits every path.
                            let sent = core.publish(
                                name,
                                &Self::pose_at(i, now),
                                muster_shared::protocol::monotonic_ns(),
                            );
                            debug_assert!(sent.is_ok(), "{sent:?}");
                        }
                    }
                }
            }
            ServiceKind::Command => {
                for (session, d) in self.drives.iter_mut() {
                    let Some(goal) = d.goal else { continue };
                    if d.arrived {
                        continue;
                    }
                    let (dx, dy) = (goal.0 - d.pos.0, goal.1 - d.pos.1);
                    let dist = dx.hypot(dy);
                    let step = (ROBOT_SPEED * dt).min(dist);
                    if dist > 0.0 {
                        d.pos.0 += dx / dist * step;
                        d.pos.1 += dy / dist * step;
                    }
                    let left = (goal.0 - d.pos.0).hypot(goal.1 - d.pos.1);
                    if left <= ARRIVAL_RADIUS {
                        d.arrived = true;
                        core.status(
                            *session,
                            TaskStatus::Done(format!(
                                "arrived within {ARRIVAL_RADIUS} m of ({:.2}, {:.2})",
                                goal.0, goal.1
                            )),
                        );
                    } else {
                        core.status(
                            *session,
                            TaskStatus::Working(format!(
                                "at ({:.2}, {:.2}), {left:.2} m to go",
                                d.pos.0, d.pos.1
                            )),
                        );
                    }
                }
            }
        }
    }

    fn next_tick(&self, core: &SystemCore) -> Option<Duration> {
        // Idle costs nothing: tick only while someone holds a session, or while a
        // latched service's newest value is kept at the broker.
        let latched = core.specs().iter().any(|s| core.latched(&s.name));
        (latched || core.sessions().next().is_some()).then_some(self.next)
    }
}
