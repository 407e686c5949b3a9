//! The delivery robot's task logic (the paper's D1): a goal location given at any time,
//! replacing the current one; it plans, drives, avoids what it meets, halts within 1 m of
//! the goal and says so; when the input stops it goes on to the last goal it was given;
//! not tasked for a while, it goes back to its home office.
//!
//! Pure: fed with sim time, the pose estimate and obstacle points; returns the velocity
//! command and what to tell the user.

use crate::navigator::{NavParams, Navigator};
use crate::planner::{Planner, PlannerParams};
use crate::port::RobotDescription;
use muster_world_model::kinematics::Pose;
use std::sync::Arc;

/// How the delivery robot behaves.
#[derive(Clone, Debug, PartialEq)]
pub struct DeliveryParams {
    /// A goal is reached within this distance, m (the paper: 1 m).
    pub arrival: f64,
    /// Not tasked for this long, it returns home, s.
    pub home_after: f64,
    /// Where home is (e.g. its office), if it has one.
    pub home: Option<(f64, f64)>,
    /// Driving status every this many seconds, s.
    pub status_period: f64,
    /// A goal that moves less than this from the one planned for keeps the plan, m.
    pub replan_within: f64,
    /// A new goal farther than this from the current one is announced as accepted, m.
    pub announce_beyond: f64,
}

impl Default for DeliveryParams {
    fn default() -> Self {
        DeliveryParams {
            arrival: 1.0,
            home_after: 60.0,
            home: None,
            status_period: 1.0,
            replan_within: 0.75,
            announce_beyond: 2.0,
        }
    }
}

/// What the delivery robot reports.
#[derive(Clone, Debug, PartialEq)]
pub enum DeliveryEvent {
    /// A new goal was taken: distance along the planned path and estimated time.
    Accepted {
        /// The goal.
        goal: (f64, f64),
        /// Path length, m.
        distance: f64,
        /// Estimated time to arrive, s.
        eta: f64,
    },
    /// On the way.
    Driving {
        /// The robot's pose estimate.
        pose: Pose,
        /// Path length left, m.
        distance: f64,
        /// Estimated time to arrive, s.
        eta: f64,
    },
    /// Something is in the way and there is no way round yet.
    Blocked {
        /// The robot's pose estimate.
        pose: Pose,
        /// Seconds blocked so far.
        for_s: f64,
    },
    /// Within the arrival distance of the goal: halted.
    Arrived {
        /// The goal.
        goal: (f64, f64),
        /// Distance to it, m.
        distance: f64,
    },
    /// No path to the goal; the reason says why.
    Unreachable {
        /// The goal.
        goal: (f64, f64),
        /// Why.
        reason: String,
    },
    /// Not tasked for a while: going home.
    ReturningHome,
    /// At home.
    Home,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Task {
    None,
    Goal { goal: (f64, f64), arrived: bool },
    Home { arrived: bool },
}

/// A goal renewed within this long comes from a link to a person seen (a tracker sends
/// one a second while she is tracked), s.
const FRESH_GOAL: f64 = 2.0;

/// The delivery robot's logic.
pub struct DeliveryCore {
    params: DeliveryParams,
    nav: Navigator,
    task: Task,
    idle_since: f64,
    /// When the goal was last set: a goal renewed within [`FRESH_GOAL`] is a person
    /// followed and seen.
    goal_at: f64,
    next_status: f64,
    blocked_reported: bool,
    arrivals: u64,
}

impl DeliveryCore {
    /// A delivery robot planning on `planner`.
    pub fn new(planner: Arc<Planner>, nav: NavParams, params: DeliveryParams) -> Self {
        DeliveryCore {
            params,
            nav: Navigator::new(planner, nav),
            task: Task::None,
            idle_since: 0.0,
            goal_at: f64::NEG_INFINITY,
            next_status: 0.0,
            blocked_reported: false,
            arrivals: 0,
        }
    }

    /// The delivery robot `d` describes: planning on its map inflated by its radius, its
    /// footprint a skin wider, at most 0.8 m/s, home where `d` says unless `params` names
    /// one. The delivery system and the in-process Experiment 2 build it so.
    pub fn for_robot(d: &RobotDescription, mut params: DeliveryParams) -> Self {
        if params.home.is_none() {
            params.home = d.home;
        }
        let planner = Arc::new(Planner::new(
            &d.map_with_fixtures(),
            PlannerParams {
                radius: d.radius,
                ..PlannerParams::default()
            },
        ));
        let nav = NavParams {
            max_speed: d.max_speed.min(0.8),
            footprint: d.radius + 0.03,
            ..NavParams::default()
        };
        DeliveryCore::new(planner, nav, params)
    }

    /// The goal being driven to, if any (home included).
    pub fn goal(&self) -> Option<(f64, f64)> {
        self.nav.goal()
    }

    /// The planned path's waypoints.
    pub fn path(&self) -> &[(f64, f64)] {
        self.nav.path()
    }

    /// Goals reached so far.
    pub fn arrivals(&self) -> u64 {
        self.arrivals
    }

    /// How late the robot acts on a command (see [`Navigator::set_latency`]).
    pub fn set_latency(&mut self, latency: f64) {
        self.nav.set_latency(latency);
    }

    /// A new goal at sim time `now` (it replaces the current one).
    pub fn set_goal(&mut self, now: f64, pose: Pose, goal: (f64, f64)) -> Vec<DeliveryEvent> {
        let previous = match self.task {
            Task::Goal { goal, arrived } => Some((goal, arrived)),
            _ => None,
        };
        self.idle_since = now;
        self.goal_at = now;
        // A goal within reach of where it halted: stay, already there.
        if let Some((_, true)) = previous {
            let d = (goal.0 - pose.x).hypot(goal.1 - pose.y);
            if d <= self.params.arrival {
                self.task = Task::Goal {
                    goal,
                    arrived: true,
                };
                return Vec::new();
            }
        }
        let replan_within = match previous {
            Some((_, false)) => self.params.replan_within,
            _ => 0.0,
        };
        match self.nav.set_goal(pose, goal, replan_within) {
            Ok(()) => {
                self.task = Task::Goal {
                    goal,
                    arrived: false,
                };
                self.blocked_reported = false;
                // A goal that moved a little (a followed person) is not a new task.
                let announce = previous.is_none_or(|(g, _)| {
                    (g.0 - goal.0).hypot(g.1 - goal.1) > self.params.announce_beyond
                });
                if announce {
                    self.next_status = now + self.params.status_period;
                    let distance = crate::planner::path_length((pose.x, pose.y), self.nav.path());
                    vec![DeliveryEvent::Accepted {
                        goal,
                        distance,
                        eta: self.eta(distance),
                    }]
                } else {
                    Vec::new()
                }
            }
            Err(e) => {
                self.nav.clear();
                self.task = Task::None;
                vec![DeliveryEvent::Unreachable {
                    goal,
                    reason: e.to_string(),
                }]
            }
        }
    }

    /// Drops the goal and halts where it is (a cancelled or paused order); the home
    /// timer starts.
    pub fn halt(&mut self, now: f64) {
        self.nav.clear();
        self.task = Task::None;
        self.idle_since = now;
    }

    /// Nobody is tasking the robot any more (its session ended): the home timer starts.
    pub fn untasked(&mut self, now: f64) {
        self.idle_since = now;
    }

    /// Time to drive `distance` at 80 % of the top speed (turns, doors, people).
    fn eta(&self, distance: f64) -> f64 {
        distance / (self.nav.params().max_speed * 0.8)
    }

    /// One control step at sim time `now`.
    pub fn step(
        &mut self,
        now: f64,
        pose: Pose,
        obstacles: &[(f64, f64)],
        tasked: bool,
    ) -> ((f64, f64), Vec<DeliveryEvent>) {
        let mut events = Vec::new();
        // Going home after a while with nothing to do.
        let done = matches!(self.task, Task::None | Task::Goal { arrived: true, .. });
        if done && !tasked && now - self.idle_since >= self.params.home_after {
            if let Some(home) = self.params.home {
                if (home.0 - pose.x).hypot(home.1 - pose.y) > self.params.arrival
                    && self.nav.set_goal(pose, home, 0.0).is_ok()
                {
                    self.task = Task::Home { arrived: false };
                    events.push(DeliveryEvent::ReturningHome);
                }
            }
            self.idle_since = now;
        }
        let target = match self.task {
            Task::Goal {
                goal,
                arrived: false,
            } => Some(goal),
            Task::Home { arrived: false } => self.params.home,
            _ => None,
        };
        let Some(target) = target else {
            let v = self
                .nav
                .give_way(now, pose, obstacles)
                .unwrap_or((0.0, 0.0));
            return (v, events);
        };
        let distance = (target.0 - pose.x).hypot(target.1 - pose.y);
        if distance <= self.params.arrival {
            let was_driving = self.nav.goal().is_some();
            self.nav.clear();
            self.idle_since = now;
            match &mut self.task {
                Task::Goal { arrived, goal } if was_driving || !*arrived => {
                    *arrived = true;
                    self.arrivals += 1;
                    events.push(DeliveryEvent::Arrived {
                        goal: *goal,
                        distance,
                    });
                }
                Task::Home { arrived } => {
                    *arrived = true;
                    events.push(DeliveryEvent::Home);
                }
                _ => {}
            }
            return ((0.0, 0.0), events);
        }
        // Catching up with a person followed and seen, it may sprint; on the way to
        // where she was last seen, or to a goal given once, it does not.
        self.nav.allow_sprint(now - self.goal_at <= FRESH_GOAL);
        let s = self.nav.step(now, pose, obstacles);
        match s.blocked_since {
            Some(since) if now - since >= 1.0 => {
                if !self.blocked_reported || now >= self.next_status {
                    self.blocked_reported = true;
                    self.next_status = now + self.params.status_period;
                    events.push(DeliveryEvent::Blocked {
                        pose,
                        for_s: now - since,
                    });
                }
            }
            _ => {
                self.blocked_reported = false;
                if now >= self.next_status {
                    self.next_status = now + self.params.status_period;
                    events.push(DeliveryEvent::Driving {
                        pose,
                        distance: s.remaining,
                        eta: self.eta(s.remaining),
                    });
                }
            }
        }
        (s.velocity, events)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::planner::PlannerParams;
    use muster_world_model::kinematics::integrate;
    use muster_world_model::map::OccupancyMap;

    fn core(home: Option<(f64, f64)>) -> DeliveryCore {
        let map = OccupancyMap::office();
        let planner = Arc::new(Planner::new(&map, PlannerParams::default()));
        DeliveryCore::new(
            planner,
            NavParams::default(),
            DeliveryParams {
                home,
                home_after: 5.0,
                ..DeliveryParams::default()
            },
        )
    }

    /// Drives the core on ideal kinematics (the process tests drive it on the simulator).
    fn drive(
        c: &mut DeliveryCore,
        pose: &mut Pose,
        t: &mut f64,
        seconds: f64,
        goal_at: impl Fn(f64) -> Option<(f64, f64)>,
    ) -> Vec<DeliveryEvent> {
        let mut all = Vec::new();
        let end = *t + seconds;
        while *t < end {
            if let Some(g) = goal_at(*t) {
                all.extend(c.set_goal(*t, *pose, g));
            }
            let (v, ev) = c.step(*t, *pose, &[], goal_at(*t).is_some());
            all.extend(ev);
            *pose = integrate(*pose, v.0, v.1, 0.1);
            *t += 0.1;
        }
        all
    }

    #[test]
    fn arrives_within_a_metre_for_goals_across_the_office_and_halts() {
        let mut c = core(None);
        let mut pose = Pose {
            x: 30.0,
            y: 3.0,
            theta: std::f64::consts::PI,
        };
        let mut t = 0.0;
        for goal in [(6.0, 6.5), (20.0, 10.0), (37.0, 17.0), (14.0, 13.5)] {
            let ev = c.set_goal(t, pose, goal);
            assert!(
                matches!(ev[0], DeliveryEvent::Accepted { distance, .. } if distance > 3.0),
                "{ev:?}"
            );
            let ev = drive(&mut c, &mut pose, &mut t, 150.0, |_| None);
            let arrived = ev
                .iter()
                .filter(|e| matches!(e, DeliveryEvent::Arrived { .. }))
                .count();
            assert_eq!(arrived, 1, "goal {goal:?}: {ev:?}");
            assert!(
                (pose.x - goal.0).hypot(pose.y - goal.1) <= 1.05,
                "goal {goal:?} pose {pose:?}"
            );
            assert!(ev
                .iter()
                .any(|e| matches!(e, DeliveryEvent::Driving { .. })));
        }
        assert_eq!(c.arrivals(), 4);
        // Halted: no more motion.
        let (v, _) = c.step(t, pose, &[], false);
        assert_eq!(v, (0.0, 0.0));
    }

    #[test]
    fn follows_a_moving_goal() {
        let mut c = core(None);
        let mut pose = Pose {
            x: 3.0,
            y: 3.0,
            theta: 0.0,
        };
        let mut t = 0.0;
        // A person walking east along the corridor at 0.5 m/s, goal updated every second.
        let person = |t: f64| (6.0 + 0.5 * t.min(50.0), 2.5);
        let ev = drive(&mut c, &mut pose, &mut t, 60.0, |t| {
            ((t * 10.0).round() as i64 % 10 == 0).then(|| person(t))
        });
        let p = person(t);
        assert!(
            (pose.x - p.0).hypot(pose.y - p.1) <= 1.5,
            "robot {pose:?} person {p:?}"
        );
        // Only the first goal is announced; the moving goal does not spam "accepted".
        let accepted = ev
            .iter()
            .filter(|e| matches!(e, DeliveryEvent::Accepted { .. }))
            .count();
        assert!(accepted <= 2, "{accepted} accepted");
    }

    #[test]
    fn goes_home_when_idle_and_reports_unreachable_goals() {
        let mut c = core(Some((30.0, 6.5)));
        let mut pose = Pose {
            x: 20.0,
            y: 10.0,
            theta: 0.0,
        };
        let mut t = 0.0;
        let ev = c.set_goal(t, pose, (60.0, 3.0));
        assert!(
            matches!(&ev[0], DeliveryEvent::Unreachable { reason, .. } if reason.contains("outside")),
            "{ev:?}"
        );
        let ev = drive(&mut c, &mut pose, &mut t, 120.0, |_| None);
        assert!(ev.contains(&DeliveryEvent::ReturningHome), "{ev:?}");
        assert!(ev.contains(&DeliveryEvent::Home), "{ev:?}");
        assert!((pose.x - 30.0).hypot(pose.y - 6.5) <= 1.05);
    }
}
