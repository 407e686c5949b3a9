//! `muster system ...`.

use crate::cli::{DeliveryArgs, RobotSystemArgs, Ros2SystemArgs, SystemCommand, TrackingArgs};
use anyhow::Context;
use muster_robots::port::RobotPort;
use muster_robots::shell::{
    delivery_specs, open_links, tracking_specs, DeliveryApp, DeliveryOptions, TrackingApp,
    TrackingOptions,
};
use muster_shared::types::validate_registration;
use muster_shared::Instance;
use muster_sim_world::map::OccupancyMap;
use muster_sim_world::scenario::{Colour, Scenario};
use muster_systems::synthetic::{Synthetic, SyntheticOptions};
use muster_systems::SystemCore;
use std::process::ExitCode;
use std::sync::Arc;

pub fn run(inst: &Instance, cmd: SystemCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        SystemCommand::Synthetic(a) => {
            let opts = SyntheticOptions {
                name: a.name,
                services: a.services,
                kind: a.kind,
                quota: a.quota,
                queue: a.queue,
                payload: a.payload,
                // Updates per scenario second, sent at that rate on the scenario clock.
                rate_hz: muster_shared::clock::global().wall_rate(a.rate),
            };
            if !(opts.rate_hz.is_finite() && opts.rate_hz > 0.0 && opts.rate_hz <= 10_000.0) {
                anyhow::bail!("--rate times --time-scale must be in (0, 10000] Hz");
            }
            let specs = opts.specs();
            validate_registration(&opts.name, &specs)?;
            let core = SystemCore::new(&opts.name, std::process::id(), specs);
            let run = muster_systems::RunOptions { udp: a.udp };
            let core = muster_systems::run_system_with(inst, core, Synthetic::new(&opts), &run)?;
            if a.stats_json {
                println!(
                    "{}",
                    serde_json::json!({"system": core.name(), "services": core.report()})
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        SystemCommand::Tracking(a) => tracking(inst, a),
        SystemCommand::Delivery(a) => delivery(inst, a),
        SystemCommand::Ros2(a) => ros2(inst, a),
    }
}

/// The ROS domain of a robot system's `--ros2`: `--domain`, else `ROS_DOMAIN_ID`, else 0.
fn ros2_domain(a: &RobotSystemArgs) -> u16 {
    a.domain.or_else(muster_ros2::domain_from_env).unwrap_or(0)
}

fn ros2(inst: &Instance, a: Ros2SystemArgs) -> anyhow::Result<ExitCode> {
    use muster_ros2::system::{config::Ros2SystemConfig, Ros2System, Ros2SystemOptions};
    anyhow::ensure!(!a.deadman.is_zero(), "--deadman must be > 0");
    let cfg = Ros2SystemConfig::load(&a.config)?;
    let opts = Ros2SystemOptions {
        domain: a.domain.or_else(muster_ros2::domain_from_env).unwrap_or(0),
        deadman: a.deadman,
    };
    let app = Ros2System::new(&cfg, &opts)?;
    let core = SystemCore::new(&cfg.system, std::process::id(), cfg.specs());
    let run = muster_systems::RunOptions { udp: a.udp };
    muster_systems::run_system_with(inst, core, app, &run)?;
    Ok(ExitCode::SUCCESS)
}

/// The scenario and map a robot system shares with the simulator.
fn world_of(a: &RobotSystemArgs) -> anyhow::Result<(Scenario, Arc<OccupancyMap>)> {
    let scenario = match &a.scenario {
        Some(p) => Scenario::load(p)?,
        None => Scenario::paper(),
    };
    let map = match (&a.map, &scenario.map) {
        (Some(p), _) | (None, Some(p)) => {
            OccupancyMap::load(p).with_context(|| format!("loading {}", p.display()))?
        }
        (None, None) => OccupancyMap::office(),
    };
    Ok((scenario, Arc::new(map)))
}

fn tracking(inst: &Instance, a: TrackingArgs) -> anyhow::Result<ExitCode> {
    let (scenario, map) = world_of(&a.common)?;
    let robots = if a.robots.is_empty() {
        scenario
            .robots
            .iter()
            .filter(|r| r.camera.is_some())
            .map(|r| r.name.clone())
            .collect()
    } else {
        a.robots.clone()
    };
    anyhow::ensure!(
        !robots.is_empty(),
        "the scenario has no robot with a camera"
    );
    let colours = a
        .colours
        .iter()
        .map(|c| Colour::from_name(c).with_context(|| format!("unknown colour {c:?}")))
        .collect::<anyhow::Result<Vec<_>>>()?;
    anyhow::ensure!(
        a.rate.is_finite() && a.rate > 0.0 && a.rate <= 100.0,
        "--rate must be in (0, 100] Hz"
    );
    anyhow::ensure!(
        a.lost_after.is_finite() && a.lost_after > 0.0,
        "--lost-after must be > 0"
    );
    let mut params = muster_robots::tracking::TrackingParams {
        colours: colours.clone(),
        period: 1.0 / a.rate,
        ground_truth: a.common.ground_truth,
        ..Default::default()
    };
    params.tracker.lost_after = a.lost_after;
    params.follow = a
        .follow
        .as_deref()
        .map(|c| Colour::from_name(c).with_context(|| format!("--follow: unknown colour {c:?}")))
        .transpose()?;
    if !a.patrol.is_empty() {
        params.patrol = a
            .patrol
            .iter()
            .filter(|w| !w.is_empty())
            .map(|w| super::user::parse_point("--patrol", w))
            .collect::<anyhow::Result<_>>()?;
    }
    let opts = TrackingOptions {
        robots: robots.clone(),
        mobile: a.mobile.clone(),
        params,
        quota: a.quota,
        budget: !a.no_budget,
        seed: a.common.seed,
    };
    let specs = tracking_specs(&colours, &robots, a.quota);
    validate_registration(&a.name, &specs)?;
    let node = muster_shared::ipc::create_node(&format!("muster-robots-{}", a.name), false)?;
    let links: Vec<Box<dyn RobotPort>> = if a.common.ros2 {
        let domain = ros2_domain(&a.common);
        robots
            .iter()
            .map(|r| {
                let node_name = format!("{}_{r}", a.name);
                let port = muster_ros2::port::Ros2Port::new(domain, &format!("/{r}"), &node_name)?;
                Ok(Box::new(port) as Box<dyn RobotPort>)
            })
            .collect::<anyhow::Result<_>>()?
    } else {
        open_links(&node, inst.as_str(), &robots, a.common.wait_sim)?
            .into_iter()
            .map(|l| Box::new(l) as Box<dyn RobotPort>)
            .collect()
    };
    let mut app = TrackingApp::new(&scenario, map, links, &opts)?;
    show_view(&node, inst, &a.name, |w| app.show_on(w, &a.name));
    let core = SystemCore::new(&a.name, std::process::id(), specs);
    let run = muster_systems::RunOptions { udp: a.common.udp };
    let core = muster_systems::run_system_with(inst, core, &mut app, &run)?;
    if a.common.stats_json {
        let loc: serde_json::Map<String, serde_json::Value> = app
            .localization()
            .into_iter()
            .map(|(r, s)| (r, s.summary()))
            .collect();
        println!(
            "{}",
            serde_json::json!({"system": core.name(), "services": core.report(),
                "localization": loc, "updates": app.published()})
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn delivery(inst: &Instance, a: DeliveryArgs) -> anyhow::Result<ExitCode> {
    let (scenario, map) = world_of(&a.common)?;
    anyhow::ensure!(
        a.home_after.is_finite() && a.home_after > 0.0,
        "--home-after must be > 0"
    );
    let opts = DeliveryOptions {
        robot: a.robot.clone(),
        service: a.service.clone().unwrap_or_else(|| a.robot.clone()),
        quota: a.quota,
        queue: !a.no_queue,
        ground_truth: a.common.ground_truth,
        params: muster_robots::delivery::DeliveryParams {
            home_after: a.home_after,
            ..Default::default()
        },
        seed: a.common.seed,
    };
    let specs = delivery_specs(&opts);
    validate_registration(&a.name, &specs)?;
    let node = muster_shared::ipc::create_node(&format!("muster-robots-{}", a.name), false)?;
    let link: Box<dyn RobotPort> = if a.common.ros2 {
        let ns = a
            .namespace
            .clone()
            .unwrap_or_else(|| format!("/{}", a.robot));
        Box::new(muster_ros2::port::Ros2Port::new(
            ros2_domain(&a.common),
            &ns,
            &a.name,
        )?)
    } else {
        let mut links = open_links(
            &node,
            inst.as_str(),
            std::slice::from_ref(&a.robot),
            a.common.wait_sim,
        )?;
        Box::new(links.pop().context("no link")?)
    };
    let mut app = DeliveryApp::new(&scenario, map, link, &opts)?;
    show_view(&node, inst, &a.name, |w| app.show_on(w, &a.name));
    let core = SystemCore::new(&a.name, std::process::id(), specs);
    let run = muster_systems::RunOptions { udp: a.common.udp };
    let core = muster_systems::run_system_with(inst, core, &mut app, &run)?;
    if a.common.stats_json {
        println!(
            "{}",
            serde_json::json!({"system": core.name(), "services": core.report(),
                "localization": {a.robot.clone(): app.localization().summary()},
                "arrivals": app.arrivals(),
                "control_latency": app.latency_summary()})
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Opens the system's view for recorders and viewers (`muster record`, `muster view`);
/// a system runs on without it, saying why.
fn show_view(
    node: &iceoryx2::prelude::Node<muster_shared::ipc::Ipc>,
    inst: &Instance,
    system: &str,
    show: impl FnOnce(muster_shared::ipc::VizWriter),
) {
    match muster_shared::ipc::VizWriter::open(node, inst, system) {
        Ok(w) => show(w),
        Err(e) => tracing::warn!("the system's view for viewers: {e}"),
    }
}
