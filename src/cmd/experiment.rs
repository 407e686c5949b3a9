//! `muster experiment link`: the paper's Experiment 2. The simulator, the broker, the
//! tracking system (T3 mobile) and the delivery system run as processes; a person with
//! a red beacon wanders the floor; a scripted user requests the red tracker, waits until
//! the target is tracked, and links red tracker → delivery robot. Ground truth from the
//! simulator measures how well it went; every process follows the simulator's clock, so
//! the run goes faster than real time.

use super::children::connect_when_listed;
use super::paper::{PaperOptions, PaperRun, Recorder, BEACONS};
use crate::cli::ExperimentLinkArgs;
use muster_robots::percentile as pct;
use muster_shared::types::{Payload, ServiceId, SessionId, TaskStatus};
use muster_shared::Instance;
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::render::render_paths;
use muster_sim_world::scenario::Scenario;
use muster_users::UserEvent;
use plotters::prelude::*;
use serde_json::json;
use std::path::Path;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// Runs Experiment 2 and writes its report.
pub fn link(inst: &Instance, a: ExperimentLinkArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        a.speed.is_finite() && a.speed > 0.0 && a.speed <= 50.0,
        "--speed must be in (0, 50]"
    );
    let duration = a.duration.as_secs_f64();
    anyhow::ensure!(duration >= 10.0, "--duration must be at least 10 s");
    std::fs::create_dir_all(&a.report)?;
    // A crowd is the paper's scenario with more people, given to the simulator and the
    // systems as a file; without one, they run on the built-in scenario.
    let scenario_args = if a.crowd > 0 {
        let mut scenario = Scenario::paper();
        scenario.seed = a.seed;
        scenario.add_crowd(a.crowd)?;
        let path = std::fs::canonicalize(&a.report)?.join("scenario.toml");
        std::fs::write(&path, toml::to_string(&scenario)?)?;
        vec!["--scenario".to_string(), path.display().to_string()]
    } else {
        Vec::new()
    };
    let wall_start = Instant::now();
    let run = PaperRun::start(
        inst,
        &PaperOptions {
            speed: a.speed,
            mobile: vec!["T3".into()],
            broker_args: Vec::new(),
            sim_args: scenario_args.clone(),
            system_args: scenario_args,
            // T3 follows the person the user links (the paper's convoy).
            extra_systems: Vec::new(),
            tracking_args: vec!["--follow".into(), "red".into()],
            seed: a.seed,
            quiet: !a.verbose,
        },
    )?;
    let mut client = connect_when_listed(inst, 4, Duration::from_secs(60))?;
    let red = ServiceId::new("tracking", "red");
    let d1 = ServiceId::new("delivery", "D1");
    let mut rec = Recorder::new(0.25);
    let wall_limit = wall_start + Duration::from_secs_f64(duration / a.speed * 4.0 + 120.0);
    // Every colour is watched for its tracking error; red is the one linked.
    let mut requests = Vec::new();
    for (k, c) in BEACONS.iter().enumerate() {
        requests.push((client.request(&ServiceId::new("tracking", c.name()))?, k));
    }
    let mut sessions: Vec<(SessionId, usize)> = Vec::new();
    let mut targets: [TargetStats; 3] = Default::default();
    let mut link = None;
    let mut link_at = None;
    let mut first_sim = None;
    let mut arrivals = 0u64;
    let mut forwarded = 0u64;
    // The red tracker's estimates of the person, for the picture.
    let mut red_track: Vec<(f64, f64)> = Vec::new();
    // Sim time and `lost` of each red update, to tell which samples had her tracked.
    let mut red_states: Vec<(f64, bool)> = Vec::new();
    let mut refusal = None;
    let mut link_ended = None;
    let mut link_attempts = 0u32;
    while Instant::now() < wall_limit {
        rec.poll(&run.world);
        let sim_start = *first_sim.get_or_insert(rec.now);
        if rec.now - sim_start >= duration {
            break;
        }
        let Some(ev) = client.next_event(Instant::now() + Duration::from_millis(20))? else {
            continue;
        };
        match ev {
            UserEvent::Granted {
                req: r, session, ..
            } => {
                if let Some((_, k)) = requests.iter().find(|q| q.0 == r) {
                    sessions.push((session, *k));
                }
            }
            UserEvent::Refused { req: r, reason, .. } if r == requests[0].0 => {
                refusal = Some(reason.to_string());
                break;
            }
            UserEvent::Update {
                session,
                payload: Payload::Track2d(t),
                ..
            } => {
                let Some(&(_, k)) = sessions.iter().find(|q| q.0 == session) else {
                    continue; // the link's own data session
                };
                let st = &mut targets[k];
                st.updates += 1;
                if k == 0 {
                    red_states.push((rec.now, t.lost));
                }
                if !t.lost {
                    st.tracked += 1;
                    if k == 0 {
                        red_track.push((t.x, t.y));
                    }
                    if let Some(truth) = rec.last() {
                        let p = truth.people[k];
                        st.errors.push((t.x - p.0).hypot(t.y - p.1));
                    }
                    if k == 0 && link.is_none() && link_attempts < 10 {
                        link = Some(client.link(&red, &d1)?);
                        link_at.get_or_insert(rec.now);
                    }
                }
            }
            UserEvent::LinkForwarded { .. } => forwarded += 1,
            UserEvent::Status {
                service,
                status: TaskStatus::Done(_),
                ..
            } if service == d1 => arrivals += 1,
            UserEvent::LinkEnded { link: l, reason } if Some(l) == link => {
                // Refused (e.g. the grant of our own red request still pending at the
                // broker): link again on the next tracked update.
                link = None;
                link_attempts += 1;
                link_ended = Some(reason);
            }
            _ => {}
        }
    }
    let wall = wall_start.elapsed().as_secs_f64();
    client.close();
    let stats = run.stop();
    let sim_start = first_sim.unwrap_or(0.0);
    let sim_seconds = rec.now - sim_start;
    // Distance between the delivery robot and the person, from the link on.
    let linked_from = link_at.unwrap_or(f64::INFINITY);
    let dist: Vec<(f64, f64)> = rec
        .samples
        .iter()
        .filter(|s| s.t >= linked_from)
        .map(|s| {
            (
                s.t - sim_start,
                (s.d1.0 - s.person().0).hypot(s.d1.1 - s.person().1),
            )
        })
        .collect();
    let dvals: Vec<f64> = dist.iter().map(|d| d.1).collect();
    // ... and only while the red track was not lost (the latest update before each sample).
    let tracked_at = |t: f64| {
        let k = red_states.partition_point(|u| u.0 <= t);
        k > 0 && !red_states[k - 1].1
    };
    let dvals_tracked: Vec<f64> = dist
        .iter()
        .filter(|d| tracked_at(d.0 + sim_start))
        .map(|d| d.1)
        .collect();
    let t3vals: Vec<f64> = rec
        .samples
        .iter()
        .filter(|s| s.t >= linked_from)
        .map(|s| (s.t3.0 - s.person().0).hypot(s.t3.1 - s.person().1))
        .collect();
    let d1_t3: Vec<f64> = rec
        .samples
        .iter()
        .filter(|s| s.t >= linked_from)
        .map(|s| (s.d1.0 - s.t3.0).hypot(s.d1.1 - s.t3.1))
        .collect();
    let convoy = rec
        .samples
        .iter()
        .filter(|s| s.t >= linked_from)
        .filter(|s| {
            (s.t3.0 - s.person().0).hypot(s.t3.1 - s.person().1) < 5.0
                && (s.d1.0 - s.person().0).hypot(s.d1.1 - s.person().1) < 5.0
        })
        .count() as f64
        / (dvals.len().max(1) as f64);
    let contacts: serde_json::Map<String, serde_json::Value> = rec
        .contacts
        .iter()
        .map(|(r, c)| (r.clone(), json!(c)))
        .collect();
    let report = json!({
        "experiment": "link (the paper's Experiment 2)",
        "clock": "sim seconds unless named wall",
        "sim_seconds": sim_seconds,
        "wall_seconds": wall,
        "sim_seconds_per_wall_second": sim_seconds / wall.max(1e-9),
        "speed_asked": a.speed,
        "seed": a.seed,
        "crowd": a.crowd,
        "refused": refusal,
        "tracking": {
            "red": targets[0].json(),
            "green": targets[1].json(),
            "blue": targets[2].json(),
            "note": "updates at 1 Hz per target; error against the simulator's ground truth while tracked",
        },
        "link": {
            "linked_at_s": link_at.map(|t| t - sim_start),
            "forwarded_goals": forwarded,
            "ended": link_ended.map(|r| r.to_string()),
            "ends_before_the_last": link_attempts,
        },
        "delivery": {
            "arrivals": arrivals,
            "distance_to_person_p50_m": pct(&dvals, 0.5),
            "distance_to_person_p90_m": pct(&dvals, 0.9),
            "distance_to_person_while_tracked_p50_m": pct(&dvals_tracked, 0.5),
            "distance_to_person_while_tracked_p90_m": pct(&dvals_tracked, 0.9),
        },
        "convoy": {
            "t3_distance_to_person_p50_m": pct(&t3vals, 0.5),
            "d1_distance_to_t3_p50_m": pct(&d1_t3, 0.5),
            "fraction_both_within_5m": convoy,
        },
        "person": {
            "held_up_s": rec.held_up[0],
            "held_up_fraction": rec.held_up[0] / sim_seconds.max(1e-9),
            "note": "sim seconds the red person wanted to walk on and could not, boxed in (by the robots following her, in a doorway)",
        },
        "contacts": contacts,
        "contacts_total": rec.total_contacts(),
        "systems": {"tracking": stats.tracking, "delivery": stats.delivery},
    });
    let dir = &a.report;
    std::fs::write(
        dir.join("report.json"),
        serde_json::to_string_pretty(&report)? + "\n",
    )?;
    let map = OccupancyMap::office();
    let path = |f: fn(&super::paper::TruthSample) -> (f64, f64)| -> Vec<(f64, f64)> {
        rec.samples
            .iter()
            .filter(|s| s.t >= linked_from.min(sim_start + 1.0))
            .map(f)
            .collect()
    };
    render_paths(
        &map,
        &[
            (red_track, [245, 160, 160], "T3's track of the person"),
            (path(|s| s.t3), [120, 120, 120], "T3"),
            (path(|s| s.person()), [220, 30, 30], "person followed"),
            (path(|s| s.d1), [30, 90, 230], "D1"),
        ],
    )
    .save(dir.join("figure3.png"))?;
    draw_distance(&dist, &dir.join("distance.png"))?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    println!(
        "wrote {0}/report.json, {0}/figure3.png (paths: person red, T3's track of the person pink, D1 blue, T3 grey), {0}/distance.png",
        dir.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// One target's tracking figures: updates, those with the target tracked, and the
/// error against ground truth of each of those.
#[derive(Default)]
struct TargetStats {
    updates: u64,
    tracked: u64,
    errors: Vec<f64>,
}

impl TargetStats {
    fn json(&self) -> serde_json::Value {
        json!({
            "updates": self.updates,
            "tracked_updates": self.tracked,
            "tracked_fraction": if self.updates > 0 { self.tracked as f64 / self.updates as f64 } else { 0.0 },
            "error_p50_m": pct(&self.errors, 0.5),
            "error_p95_m": pct(&self.errors, 0.95),
        })
    }
}

/// Distance between the delivery robot and the person over the run.
fn draw_distance(dist: &[(f64, f64)], path: &Path) -> anyhow::Result<()> {
    super::stress_plot::register_font()?;
    let root = BitMapBackend::new(path, (900, 350)).into_drawing_area();
    root.fill(&WHITE)?;
    let t_max = dist.iter().map(|d| d.0).fold(1.0, f64::max);
    let d_max = dist.iter().map(|d| d.1).fold(2.0, f64::max) * 1.1;
    let mut chart = ChartBuilder::on(&root)
        .caption("delivery robot to the followed person", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(0.0..t_max, 0.0..d_max)?;
    chart
        .configure_mesh()
        .x_desc("sim time, s")
        .y_desc("distance, m")
        .draw()?;
    chart.draw_series(LineSeries::new(dist.iter().copied(), &BLUE))?;
    chart.draw_series(LineSeries::new([(0.0, 1.0), (t_max, 1.0)], &RED))?;
    root.present()?;
    Ok(())
}
