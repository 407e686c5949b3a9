//! `muster sim`: the simulator process.

use crate::cli::SimArgs;
use anyhow::Context;
use muster_ros2::sim::{SimBridge, SimBridgeOptions};
use muster_shared::ipc::create_node;
use muster_shared::reactor::{Reactor, SignalPipe};
use muster_shared::Instance;
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::scenario::Scenario;
use muster_sim_world::shm::SimShm;
use muster_sim_world::world::World;
use muster_sim_world::{bench, render};
use serde_json::json;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// The world sample goes out at this rate (sensors go out at their own rates).
const WORLD_RATE_HZ: f64 = 20.0;

pub fn run(inst: &Instance, a: SimArgs) -> anyhow::Result<ExitCode> {
    if a.bench {
        return run_bench(&a.robots, a.json);
    }
    let mut scenario = match &a.scenario {
        Some(p) => Scenario::load(p)?,
        None => Scenario::paper(),
    };
    if let Some(seed) = a.seed {
        scenario.seed = seed;
    }
    let map = match (&a.map, &scenario.map) {
        (Some(p), _) | (None, Some(p)) => OccupancyMap::load(p)?,
        (None, None) => OccupancyMap::office(),
    };
    if let Some(out) = &a.export_map {
        map.save(out)
            .with_context(|| format!("writing {}", out.display()))?;
        println!(
            "wrote {} ({} x {} cells at {} m)",
            out.display(),
            map.width(),
            map.height(),
            map.resolution()
        );
        return Ok(ExitCode::SUCCESS);
    }
    let mut world = World::new(&scenario, Some(map))?;
    if let Some(out) = &a.render {
        anyhow::ensure!(a.at.is_finite() && a.at >= 0.0, "--at must be ≥ 0 seconds");
        world.step_to(a.at);
        render::render(&world)
            .save(out)
            .with_context(|| format!("writing {}", out.display()))?;
        println!(
            "rendered the world at t = {:.2} s to {}",
            world.time(),
            out.display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    let speed = a.speed.unwrap_or(muster_shared::clock::global().factor());
    anyhow::ensure!(
        a.as_fast_as_possible || (speed.is_finite() && speed > 0.0),
        "--speed must be > 0"
    );
    simulate(inst, &mut world, &scenario, &a, speed)
}

fn simulate(
    inst: &Instance,
    world: &mut World,
    scenario: &Scenario,
    a: &SimArgs,
    speed: f64,
) -> anyhow::Result<ExitCode> {
    let node = create_node(&format!("muster-sim-{inst}"), true)?;
    let mut shm = SimShm::open(&node, inst.as_str(), world)?;
    let mut ros2 = if a.ros2 {
        let domain = a.domain.or_else(muster_ros2::domain_from_env).unwrap_or(0);
        Some(SimBridge::new(
            world,
            SimBridgeOptions {
                domain,
                ..SimBridgeOptions::default()
            },
        )?)
    } else {
        None
    };
    // The robots as VDA 5050 vehicles: `muster agv` beside us, stopped with us.
    let mut agv = match &a.vda5050 {
        Some(mqtt) => Some(start_agv(inst, world, a, mqtt)?),
        None => None,
    };
    let mut signals = SignalPipe::install()?;
    let mut reactor = Reactor::new()?;
    reactor.add(signals.raw(), 0)?;
    tracing::info!(
        robots = world.robots().len(),
        people = world.people().len(),
        speed = if a.as_fast_as_possible {
            "as fast as possible".to_string()
        } else {
            format!("{}x", speed)
        },
        "simulator up"
    );
    let end = a.duration.map(|d| d.as_secs_f64());
    let start = Instant::now();
    let mut next_world = 0.0;
    let mut last_report = Instant::now();
    shm.publish(world, true)?;
    if let Some(r) = &mut ros2 {
        r.publish(world);
    }
    loop {
        shm.take_commands(world);
        if let Some(r) = &mut ros2 {
            r.take_commands(world);
        }
        world.step(scenario.dt);
        let due = world.time() + 1e-9 >= next_world;
        if due {
            next_world += 1.0 / WORLD_RATE_HZ;
        }
        shm.publish(world, due)?;
        if let Some(r) = &mut ros2 {
            r.publish(world);
        }
        if end.is_some_and(|e| world.time() >= e) {
            break;
        }
        let wait = if a.as_fast_as_possible {
            Duration::ZERO
        } else {
            let target = start + Duration::from_secs_f64(world.time() / speed);
            target.saturating_duration_since(Instant::now())
        };
        // Sleep until the next step is due; a signal wakes us at once.
        if (!wait.is_zero() || world.steps().is_multiple_of(100))
            && !reactor.wait(Some(wait))?.is_empty()
            && signals.drain()
        {
            tracing::info!("signal received: simulator stopping");
            break;
        }
        if last_report.elapsed() > Duration::from_secs(10) {
            last_report = Instant::now();
            let rtf = world.time() / start.elapsed().as_secs_f64();
            tracing::info!(
                sim_time = format!("{:.1}", world.time()),
                realtime_factor = format!("{rtf:.2}"),
                "running"
            );
        }
    }
    if let Some(c) = &mut agv {
        c.stop();
    }
    tracing::info!(
        sim_time = world.time(),
        wall = ?start.elapsed(),
        ros2_errors = ros2.as_ref().map_or(0, SimBridge::errors),
        "simulator stopped"
    );
    Ok(ExitCode::SUCCESS)
}

/// Starts `muster agv --mqtt MQTT` for `--vda5050-robots` (every robot by default),
/// on this simulator's scenario and map.
fn start_agv(
    inst: &Instance,
    world: &World,
    a: &SimArgs,
    mqtt: &str,
) -> anyhow::Result<super::children::Children> {
    let robots = if a.vda5050_robots.is_empty() {
        world.robots().iter().map(|r| r.spec.name.clone()).collect()
    } else {
        a.vda5050_robots.clone()
    };
    let robots = robots.join(",");
    let mut args = vec!["agv", "--mqtt", mqtt, "--robots", &robots];
    let scenario = a.scenario.as_ref().map(|p| p.display().to_string());
    let map = a.map.as_ref().map(|p| p.display().to_string());
    if let Some(p) = &scenario {
        args.extend(["--scenario", p]);
    }
    if let Some(p) = &map {
        args.extend(["--map", p]);
    }
    let mut kids = super::children::Children::default();
    kids.spawn(inst, "muster agv", &args, std::process::Stdio::inherit())?;
    tracing::info!(%mqtt, %robots, "the robots are VDA 5050 vehicles (muster agv)");
    Ok(kids)
}

fn run_bench(counts: &[usize], as_json: bool) -> anyhow::Result<ExitCode> {
    if !as_json {
        println!("muster sim --bench: wandering robots, laser 181 beams + 16 sonars + camera at 10 Hz, kinematics 100 Hz");
        println!(
            "{:>7} {:>16} {:>10} {:>10} {:>12} {:>8}",
            "robots", "realtime_factor", "sim_s", "wall_s", "ns/beam", "threads"
        );
    }
    for &n in counts {
        anyhow::ensure!(n > 0 && n <= 100_000, "robot counts must be 1..=100000");
        let mut w = bench::world(n, 1);
        // Calibrate: aim for about 3 s of wall time per size.
        let t = Instant::now();
        w.step(0.1);
        let per_sim_s = t.elapsed().as_secs_f64() / 0.1;
        let sim_s = (3.0 / per_sim_s.max(1e-9)).clamp(0.2, 100_000.0);
        let fig = bench::realtime_factor(&mut w, (sim_s * 100.0).round() / 100.0);
        let ns = bench::ns_per_beam(&w, if n < 100 { 20 } else { 1 });
        if as_json {
            println!(
                "{}",
                json!({"robots": fig.robots, "realtime_factor": fig.realtime_factor, "sim_seconds": fig.sim_seconds,
                       "wall_seconds": fig.wall_seconds, "ns_per_beam": ns, "threads": fig.threads})
            );
        } else {
            println!(
                "{:>7} {:>16.2} {:>10.2} {:>10.2} {:>12.1} {:>8}",
                fig.robots, fig.realtime_factor, fig.sim_seconds, fig.wall_seconds, ns, fig.threads
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
