//! The paper's setup as processes: the simulator on the paper's scenario, a broker, the
//! tracking system and the delivery system; and a recorder of the ground truth the
//! simulator publishes (for reports and pictures only: the systems never see it).
//! Shared by `muster up` and `muster experiment link`.

use super::children::Children;
use muster_shared::Instance;
use muster_sim_world::scenario::Colour;
use muster_sim_world::shm::{PersonBrief, WorldState, WorldView};
use serde_json::Value;
use std::io::Read;
use std::process::{ChildStdout, Stdio};
use std::time::Duration;

/// How the paper's processes are started.
pub struct PaperOptions {
    /// Simulator speed (sim seconds per wall second).
    pub speed: f64,
    /// Tracking robots that may drive.
    pub mobile: Vec<String>,
    /// Extra broker flags (e.g. UDP for remote users).
    pub broker_args: Vec<String>,
    /// Extra simulator flags (e.g. a scenario file).
    pub sim_args: Vec<String>,
    /// Extra flags for both robot systems (e.g. their UDP endpoints).
    pub system_args: Vec<String>,
    /// Extra flags for the tracking system only.
    pub tracking_args: Vec<String>,
    /// Further robot systems, each its arguments after `muster` (e.g. `system tracking
    /// --name tracking-2 --robots T4,T5,T6`); `--stats-json` and `--seed` are added.
    pub extra_systems: Vec<Vec<String>>,
    /// Seed of the simulator and the filters.
    pub seed: u64,
    /// Children's standard error: inherited (a demo) or discarded (an experiment).
    pub quiet: bool,
}

/// The running processes.
pub struct PaperRun {
    /// The children, stopped on drop.
    pub children: Children,
    tracking_out: Option<ChildStdout>,
    delivery_out: Option<ChildStdout>,
    extra_out: Vec<Option<ChildStdout>>,
    /// This process's iceoryx2 node, for what it reads of the run.
    pub node: iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    /// The simulator's world, for the recorder.
    pub world: WorldView,
}

/// What the robot systems printed when they stopped (`--stats-json`).
#[derive(Debug, Default)]
pub struct SystemStats {
    /// The tracking system's line.
    pub tracking: Option<Value>,
    /// The delivery system's line.
    pub delivery: Option<Value>,
    /// The further systems' lines, in [`PaperOptions::extra_systems`] order.
    pub extra: Vec<Option<Value>>,
}

impl PaperRun {
    /// Starts the simulator, the broker and both robot systems on `inst`.
    pub fn start(inst: &Instance, o: &PaperOptions) -> anyhow::Result<Self> {
        // One clock: every child (broker pings, scripted users) runs at the simulator's speed.
        muster_shared::clock::set_global(
            muster_shared::clock::TimeScale::new(o.speed).map_err(anyhow::Error::msg)?,
        );
        let mut children = Children::default();
        let speed = o.speed.to_string();
        let seed = o.seed.to_string();
        let err = || {
            if o.quiet {
                Stdio::null()
            } else {
                Stdio::inherit()
            }
        };
        children.spawn_with(
            inst,
            "simulator",
            &["sim", "--speed", &speed, "--seed", &seed]
                .into_iter()
                .chain(o.sim_args.iter().map(String::as_str))
                .collect::<Vec<_>>(),
            Stdio::null(),
            err(),
        )?;
        let broker: Vec<&str> = std::iter::once("broker")
            .chain(o.broker_args.iter().map(String::as_str))
            .collect();
        children.spawn_with(inst, "broker", &broker, Stdio::null(), err())?;
        let mobile = o.mobile.join(",");
        let mut tracking = vec!["system", "tracking", "--stats-json", "--seed", &seed];
        if !mobile.is_empty() {
            tracking.extend(["--mobile", &mobile]);
        }
        tracking.extend(o.system_args.iter().map(String::as_str));
        tracking.extend(o.tracking_args.iter().map(String::as_str));
        let t = children.spawn_with(inst, "tracking system", &tracking, Stdio::piped(), err())?;
        let tracking_out = t.stdout.take();
        let mut delivery = vec!["system", "delivery", "--stats-json", "--seed", &seed];
        delivery.extend(o.system_args.iter().map(String::as_str));
        let d = children.spawn_with(inst, "delivery system", &delivery, Stdio::piped(), err())?;
        let delivery_out = d.stdout.take();
        let mut extra_out = Vec::new();
        for (k, args) in o.extra_systems.iter().enumerate() {
            let args: Vec<&str> = args
                .iter()
                .map(String::as_str)
                .chain(["--stats-json", "--seed", &seed])
                .chain(o.system_args.iter().map(String::as_str))
                .collect();
            let label = format!("system {k}");
            let c = children.spawn_with(inst, &label, &args, Stdio::piped(), err())?;
            extra_out.push(c.stdout.take());
        }
        let node = muster_shared::ipc::create_node(
            &format!("muster-observer-{}", std::process::id()),
            false,
        )?;
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        let world = loop {
            match WorldView::open(&node, inst.as_str()) {
                Ok(w) => break w,
                Err(e) if std::time::Instant::now() > deadline => {
                    anyhow::bail!("the simulator did not come up: {e}")
                }
                Err(_) => std::thread::sleep(Duration::from_millis(50)),
            }
        };
        Ok(PaperRun {
            children,
            tracking_out,
            delivery_out,
            extra_out,
            node,
            world,
        })
    }

    /// Stops every process and collects what the robot systems printed.
    pub fn stop(mut self) -> SystemStats {
        self.children.stop();
        let read = |out: Option<ChildStdout>| {
            let mut text = String::new();
            out?.read_to_string(&mut text).ok()?;
            text.lines()
                .rev()
                .find_map(|l| serde_json::from_str(l).ok())
        };
        SystemStats {
            tracking: read(self.tracking_out.take()),
            delivery: read(self.delivery_out.take()),
            extra: self.extra_out.drain(..).map(read).collect(),
        }
    }
}

/// The beacons of the paper's scenario, in the order samples keep them: the first is
/// the person a run follows.
pub const BEACONS: [Colour; 3] = [Colour::Red, Colour::Green, Colour::Blue];

/// One ground-truth sample.
#[derive(Clone, Copy, Debug)]
pub struct TruthSample {
    /// Sim time, s.
    pub t: f64,
    /// The people wearing the [`BEACONS`], in that order.
    pub people: [(f64, f64); 3],
    /// The delivery robot.
    pub d1: (f64, f64),
    /// The mobile tracker.
    pub t3: (f64, f64),
}

impl TruthSample {
    /// The followed person (red beacon).
    pub fn person(&self) -> (f64, f64) {
        self.people[0]
    }
}

/// Ground truth over a run, sampled every `period` sim seconds.
pub struct Recorder {
    period: f64,
    /// Samples in time order.
    pub samples: Vec<TruthSample>,
    /// Contacts per robot at the last sample.
    pub contacts: Vec<(String, u64)>,
    /// Sim seconds each beacon's person was held up, boxed in, at the last sample.
    pub held_up: [f64; 3],
    /// Newest sim time seen.
    pub now: f64,
}

fn find(w: &WorldState, robot: &str) -> Option<(f64, f64)> {
    w.robots[..(w.n_robots as usize).min(w.robots.len())]
        .iter()
        .find(|r| r.name.as_str() == robot)
        .map(|r| (r.pose.x, r.pose.y))
}

/// The person wearing `colour` in the world sample.
fn wearing(w: &WorldState, colour: Colour) -> Option<&PersonBrief> {
    w.people[..(w.n_people as usize).min(w.people.len())]
        .iter()
        .find(|p| p.beacon == colour.code())
}

/// Where the person wearing `colour` is in the world sample.
pub fn person(w: &WorldState, colour: Colour) -> Option<(f64, f64)> {
    wearing(w, colour).map(|p| (p.pose.x, p.pose.y))
}

impl Recorder {
    /// A recorder sampling every `period` sim seconds.
    pub fn new(period: f64) -> Self {
        Recorder {
            period,
            samples: Vec::new(),
            contacts: Vec::new(),
            held_up: [0.0; 3],
            now: 0.0,
        }
    }

    /// Takes the newest world sample if one is due (never waits).
    pub fn poll(&mut self, view: &WorldView) {
        let after = self
            .samples
            .last()
            .map_or(-1.0, |s| s.t + self.period - 1e-9);
        let taken = view.next(after, Duration::ZERO, |w| {
            let s = TruthSample {
                t: w.time,
                people: BEACONS.map(|c| person(w, c).unwrap_or_default()),
                d1: find(w, "D1").unwrap_or_default(),
                t3: find(w, "T3").unwrap_or_default(),
            };
            let contacts = w.robots[..(w.n_robots as usize).min(w.robots.len())]
                .iter()
                .map(|r| (r.name.as_str().to_string(), r.contacts))
                .collect::<Vec<_>>();
            let held_up = BEACONS.map(|c| wearing(w, c).map_or(0.0, |p| p.held_up));
            (s, contacts, held_up)
        });
        if let Ok(Some((s, contacts, held_up))) = taken {
            self.now = s.t;
            self.samples.push(s);
            self.contacts = contacts;
            self.held_up = held_up;
        }
    }

    /// The newest ground truth, if any.
    pub fn last(&self) -> Option<TruthSample> {
        self.samples.last().copied()
    }

    /// Total contacts of all robots.
    pub fn total_contacts(&self) -> u64 {
        self.contacts.iter().map(|(_, c)| c).sum()
    }
}
