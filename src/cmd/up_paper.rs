//! `muster up`: the main job on the built-in default, the paper's setup. Starts the
//! simulator (the paper's scenario: trackers T1–T3, delivery robot D1, three people with
//! beacons), the broker (also serving remote users over UDP), the tracking system (T3
//! mobile) and the delivery system; then acts as a user: lists the four services,
//! requests the trackers and prints the targets' positions, links the first tracked
//! colour into the delivery robot and prints the robot following the person. On Ctrl-C
//! or `--duration` it stops everything and writes a picture of the run.

use super::paper::{PaperOptions, PaperRun, Recorder};
use super::up::{remote_list, wait_for_services, Guest};
use crate::cli::UpArgs;
use muster_shared::ipc::VizReader;
use muster_shared::types::{Payload, ServiceId};
use muster_shared::Instance;
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::render::render_paths;
use muster_users::{ConnectOptions, UserClient, UserError, UserEvent};
use std::process::ExitCode;
use std::time::{Duration, Instant};

const COLOURS: [&str; 3] = ["red", "green", "blue"];

pub fn run(inst: &Instance, a: UpArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        a.speed.is_finite() && a.speed > 0.0 && a.speed <= 50.0,
        "--speed must be in (0, 50]"
    );
    let guest = Guest::new(inst, (!a.no_udp).then_some(a.udp))?;
    let broker_args = guest.broker_args();
    let mut system_args = Vec::new();
    if guest.addr.is_some() {
        system_args = vec!["--udp".to_string(), "127.0.0.1:0".to_string()];
    }
    let run = PaperRun::start(
        inst,
        &PaperOptions {
            speed: a.speed,
            mobile: vec!["T3".into()],
            broker_args,
            sim_args: Vec::new(),
            system_args,
            extra_systems: Vec::new(),
            tracking_args: Vec::new(),
            seed: 1,
            quiet: false,
        },
    )?;
    let standbys =
        (!a.no_standby).then(|| super::standbys::Standbys::start(inst, guest.broker_args()));
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(20),
        handle_signals: true,
        watch_list: false,
    };
    let mut client = UserClient::connect(inst, &opts)?;
    let end = a.duration.map(|d| Instant::now() + d);
    let mut rec = Recorder::new(0.5);
    let mut seen = Seen::open(&run, inst);
    let mut web = super::children::Children::default();
    let shown = wait_for_services(&mut client, 4, Duration::from_secs(60))
        .and_then(|()| remote_list(&guest));
    if !a.no_web {
        guest.start_web(&mut web, inst, a.web)?;
    }
    let followed = match shown.and_then(|()| demo(&mut client, &run, &mut rec, &mut seen, end)) {
        Ok(c) => c,
        Err(UserError::Interrupted) => None,
        Err(e) => return Err(e.into()),
    };
    client.close();
    web.stop();
    if let Some(s) = standbys {
        s.stop();
    }
    let stats = run.stop();
    super::children::leave_no_fence(inst);
    let picture = a
        .picture
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join(format!("muster-up-{}.png", inst.as_str())));
    let people =
        |k: usize| -> Vec<(f64, f64)> { rec.samples.iter().map(|s| s.people[k]).collect() };
    let track = |c: &str| seen.tracks.get(c).cloned().unwrap_or_default();
    render_paths(
        &OccupancyMap::office(),
        &[
            // What the systems believed, under the truth: the tracks the user was sent
            // (pale, in each beacon's colour) and D1's last plan.
            (track("green"), [150, 220, 150], "track (green)"),
            (track("blue"), [160, 175, 255], "track (blue)"),
            (track("red"), [255, 160, 175], "track (red)"),
            (seen.plan.clone(), [250, 200, 120], "D1's plan"),
            (people(1), [30, 170, 30], "person (green)"),
            (people(2), [40, 60, 230], "person (blue)"),
            (people(0), [220, 30, 30], "person (red)"),
            (
                rec.samples.iter().map(|s| s.t3).collect(),
                [120, 120, 120],
                "T3",
            ),
            (
                rec.samples.iter().map(|s| s.d1).collect(),
                [230, 140, 0],
                "D1",
            ),
        ],
    )
    .save(&picture)?;
    out!(
        "muster up: stopped after {:.0} sim s; {} contacts; followed {}; picture of the run (people in their beacon colours, their tracks pale, T3 grey, D1 orange, its last plan pale orange): {}",
        rec.now,
        rec.total_contacts(),
        followed.unwrap_or("nobody"),
        picture.display()
    );
    if let Some(d) = stats.delivery {
        out!("delivery: {} arrivals", d["arrivals"]);
    }
    Ok(ExitCode::SUCCESS)
}

/// The user's part; returns the colour it linked into the delivery robot.
fn demo(
    client: &mut UserClient,
    run: &PaperRun,
    rec: &mut Recorder,
    seen: &mut Seen,
    end: Option<Instant>,
) -> Result<Option<&'static str>, UserError> {
    let list = client.list()?;
    out!("== service list (generation {}) ==", list.generation);
    out!("{}", muster_users::menu::table(&list.views()));
    let delivery = ServiceId::new("delivery", "D1");
    out!("\n== request the three trackers; link the first target tracked into {delivery} ==");
    let mut sessions = Vec::new();
    for c in COLOURS {
        let id = ServiceId::new("tracking", c);
        sessions.push((client.request(&id)?, c, None));
    }
    let mut link = None;
    let mut followed = None;
    let give_up = Instant::now() + Duration::from_secs(20);
    let mut shown = 0u64;
    let mut forwarded = 0u64;
    let mut link_ends = 0u32;
    loop {
        rec.poll(&run.world);
        seen.poll();
        let now = Instant::now();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        if link.is_none() && followed.is_none() && now >= give_up {
            // Nobody seen yet: link red anyway; the robot waits for a first position.
            out!("no target seen for 20 s: linking red anyway");
            followed = Some("red");
            link = Some(client.link(&ServiceId::new("tracking", "red"), &delivery)?);
        }
        let Some(e) = client.next_event(now + Duration::from_millis(100))? else {
            continue;
        };
        match e {
            UserEvent::Granted {
                req,
                session,
                service,
                ..
            } => {
                if let Some(s) = sessions.iter_mut().find(|s| s.0 == req) {
                    s.2 = Some(session);
                    out!("granted: {service} (session {session})");
                }
            }
            UserEvent::Refused {
                service, reason, ..
            } => out!("refused: {service}: {reason}"),
            UserEvent::Update {
                session,
                payload,
                service,
                ..
            } => {
                let colour = sessions.iter().find(|s| s.2 == Some(session)).map(|s| s.1);
                if let (Some(c), Payload::Track2d(t)) = (colour, &payload) {
                    if !t.lost {
                        seen.tracks.entry(c).or_default().push((t.x, t.y));
                    }
                    if link.is_none() || shown.is_multiple_of(5) {
                        out!("  {service}: {payload}");
                    }
                    shown += 1;
                    if link.is_none() && !t.lost && link_ends < 5 {
                        followed = Some(c);
                        out!("\n== {c} is tracked: link tracking/{c} -> {delivery} ==");
                        link = Some(client.link(&ServiceId::new("tracking", c), &delivery)?);
                    }
                }
            }
            UserEvent::LinkForwarded { input, .. } => {
                forwarded += 1;
                if forwarded % 5 == 1 {
                    out!("  forwarded {input} (goal {forwarded})");
                }
            }
            UserEvent::LinkUp { .. } => {
                out!("link up: the target's positions become the robot's goals (Ctrl-C to stop)")
            }
            UserEvent::Status {
                service, status, ..
            } if service == delivery => {
                if let Some(t) = rec.last() {
                    out!("  {delivery}: {status}  [sim {:.0} s]", t.t);
                } else {
                    out!("  {delivery}: {status}");
                }
            }
            UserEvent::LinkEnded { reason, .. } => {
                // E.g. refused while our own request's grant is still pending at the
                // broker: link again on the next tracked update.
                out!("link ended: {reason}");
                link = None;
                link_ends += 1;
            }
            UserEvent::BrokerLost => out!("(broker lost; sessions and the link go on)"),
            _ => {}
        }
    }
    Ok(followed)
}

/// What the systems believed, for the picture: the tracks the user was sent, and the
/// delivery system's last plan (from its view in shared memory: from where D1 believed
/// it was, through its waypoints).
struct Seen {
    tracks: std::collections::BTreeMap<&'static str, Vec<(f64, f64)>>,
    plan: Vec<(f64, f64)>,
    view: Option<VizReader>,
}

impl Seen {
    fn open(run: &PaperRun, inst: &Instance) -> Self {
        let view = VizReader::open(&run.node, inst, "delivery").ok();
        Seen {
            tracks: Default::default(),
            plan: Vec::new(),
            view,
        }
    }

    fn poll(&mut self) {
        let Some(v) = self.view.as_mut().and_then(VizReader::latest) else {
            return;
        };
        if let Some(p) = v.plans.iter().find(|p| p.robot == "D1") {
            let from = v.robots.iter().find(|r| r.name == "D1").map(|r| (r.x, r.y));
            self.plan = from.into_iter().chain(p.path.iter().copied()).collect();
        }
    }
}
