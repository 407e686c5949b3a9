//! `muster system ...`.

use crate::cli::{
    AgvArgs, DeliveryArgs, RobotSystemArgs, Ros2SystemArgs, SystemCommand, TrackingArgs,
    Vda5050SystemArgs,
};
use anyhow::Context;
use muster_robots::port::RobotPort;
use muster_robots::shell::{
    delivery_specs, tracking_specs, DeliveryApp, DeliveryOptions, TrackingApp, TrackingOptions,
};
use muster_robots::sim::open_ports;
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
            let mut core = SystemCore::new(&opts.name, std::process::id(), specs);
            if a.latched {
                if opts.kind != muster_shared::types::ServiceKind::Data {
                    anyhow::bail!("--latched is for data services");
                }
                for s in opts.specs() {
                    core.latch(&s.name);
                }
            }
            let run = muster_systems::RunOptions {
                udp: a.udp,
                ..Default::default()
            };
            let core = muster_systems::run_system_with(inst, core, Synthetic::new(&opts), &run)?;
            if a.stats_json {
                out!(
                    "{}",
                    serde_json::json!({"system": core.name(), "services": core.report()})
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        SystemCommand::Tracking(a) => tracking(inst, a),
        SystemCommand::Delivery(a) => delivery(inst, a),
        SystemCommand::Ros2(a) => ros2(inst, a),
        SystemCommand::Vda5050(a) => vda5050(inst, a),
    }
}

fn vda5050(inst: &Instance, a: Vda5050SystemArgs) -> anyhow::Result<ExitCode> {
    use muster_vda5050::fleet::{Fleet, FleetOptions};
    let graph = match &a.graph {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            let g = muster_vda5050::graph::Graph::parse(&text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            Some(g)
        }
        None => None,
    };
    let opts = FleetOptions {
        mqtt: a.mqtt,
        system: a.name,
        interface: a.interface,
        manufacturer: a.manufacturer,
        version: a.vda_version,
        graph,
        order_timeout: a.order_timeout,
        security: mqtt_security(&a.mqtt_security)?,
        schemas: vda_schemas(&a.mqtt_security)?,
    };
    validate_registration(&opts.system, &[])?;
    let mut fleet = Fleet::connect(opts.clone(), a.wait)?;
    let core = SystemCore::create(&opts.system, fleet.specs())?;
    let run = muster_systems::RunOptions {
        udp: a.udp,
        ..Default::default()
    };
    muster_systems::run_system_with(inst, core, &mut fleet, &run)?;
    fleet.close();
    if a.stats_json {
        out!("{}", fleet.stats().report());
    }
    Ok(ExitCode::SUCCESS)
}

/// The ROS domain of a robot system's `--ros2`: `--domain`, else `ROS_DOMAIN_ID`, else 0.
fn ros2_domain(a: &RobotSystemArgs) -> u16 {
    a.domain.or_else(muster_ros2::domain_from_env).unwrap_or(0)
}

fn ros2(inst: &Instance, a: Ros2SystemArgs) -> anyhow::Result<ExitCode> {
    use muster_ros2::system::{
        config::Ros2SystemConfig, system_core, Ros2System, Ros2SystemOptions,
    };
    anyhow::ensure!(!a.deadman.is_zero(), "--deadman must be > 0");
    let cfg = Ros2SystemConfig::load(&a.config)?;
    let opts = Ros2SystemOptions {
        domain: a.domain.or_else(muster_ros2::domain_from_env).unwrap_or(0),
        deadman: a.deadman,
    };
    let app = Ros2System::new(&cfg, &opts)?;
    let core = system_core(&cfg);
    let run = muster_systems::RunOptions {
        udp: a.udp,
        ..Default::default()
    };
    muster_systems::run_system_with(inst, core, app, &run)?;
    Ok(ExitCode::SUCCESS)
}

/// TLS and credentials for an MQTT broker, from the flags.
fn mqtt_security(a: &crate::cli::MqttArgs) -> anyhow::Result<muster_vda5050::mqtt::MqttSecurity> {
    use muster_vda5050::mqtt::MqttSecurity;
    let credentials = match (&a.mqtt_user, &a.mqtt_password_file) {
        (Some(u), Some(f)) => Some(MqttSecurity::password_from(u, f)?),
        _ => None,
    };
    if credentials.is_some() && a.mqtt_ca.is_none() {
        tracing::warn!("--mqtt-user without --mqtt-ca: the password goes in clear");
    }
    Ok(MqttSecurity {
        ca: a.mqtt_ca.clone(),
        client_cert: a
            .mqtt_client_cert
            .as_ref()
            .map(|v| (v[0].clone(), v[1].clone())),
        credentials,
    })
}

/// The JSON schemas of `--vda-schemas`, compiled.
fn vda_schemas(
    a: &crate::cli::MqttArgs,
) -> anyhow::Result<Option<std::sync::Arc<muster_vda5050::schemas::Schemas>>> {
    let Some(dir) = &a.vda_schemas else {
        return Ok(None);
    };
    let s = muster_vda5050::schemas::Schemas::load(dir)?;
    tracing::info!(dir = %dir.display(), topics = ?s.topics(), "VDA 5050 JSON schemas");
    Ok(Some(std::sync::Arc::new(s)))
}

/// `muster agv`: the robots as VDA 5050 vehicles.
pub fn agv(inst: &Instance, a: AgvArgs) -> anyhow::Result<ExitCode> {
    use muster_robots::delivery::DeliveryParams;
    use muster_robots::shell::DeliveryDriver;
    use muster_vda5050::agv::{run_agvs, AgvOptions};
    anyhow::ensure!(
        a.deviation.is_finite() && a.deviation > 0.0,
        "--deviation must be > 0"
    );
    anyhow::ensure!(!a.state_every.is_zero(), "--state-every must be > 0");
    anyhow::ensure!(!a.robots.is_empty(), "--robots: name one at least");
    let opts = AgvOptions {
        mqtt: a.mqtt,
        interface: a.interface,
        manufacturer: a.manufacturer,
        version: a.vda_version,
        map_id: a.map_id,
        deviation: a.deviation,
        state_every: a.state_every,
        visualization_every: (!a.visualization_every.is_zero()).then_some(a.visualization_every),
        security: mqtt_security(&a.mqtt_security)?,
        schemas: vda_schemas(&a.mqtt_security)?,
    };
    let node = muster_shared::ipc::create_node("muster-agv", false)?;
    let robots: Vec<(String, String)> = a
        .robots
        .iter()
        .map(|r| (r.clone(), format!("/{r}")))
        .collect();
    let ports = robot_ports(inst, &node, &a.common, "agv", &robots, false)?;
    let params = DeliveryParams {
        // A node is reached within the deviation; no going home between orders.
        arrival: a.deviation,
        home_after: f64::INFINITY,
        ..DeliveryParams::default()
    };
    let drivers = ports
        .into_iter()
        .zip(&a.robots)
        .map(|(port, robot)| {
            DeliveryDriver::new(
                port,
                robot,
                a.common.ground_truth,
                params.clone(),
                a.common.seed,
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let stats = run_agvs(&opts, drivers)?;
    if a.common.stats_json {
        out!("{}", serde_json::to_string(&stats)?);
    }
    Ok(ExitCode::SUCCESS)
}

/// The scenario and map a robot system shares with the simulator.
fn world_of(a: &RobotSystemArgs) -> anyhow::Result<(Scenario, Arc<OccupancyMap>)> {
    let scenario = match &a.scenario {
        Some(p) => Scenario::load(p)?,
        None => Scenario::paper(),
    };
    let map = match (&a.map, &scenario.map) {
        (Some(p), _) | (None, Some(p)) => load_map(p)?,
        (None, None) => OccupancyMap::office(),
    };
    Ok((scenario, Arc::new(map)))
}

fn load_map(p: &std::path::Path) -> anyhow::Result<OccupancyMap> {
    OccupancyMap::load(p).with_context(|| format!("loading {}", p.display()))
}

/// The ports of `robots` (in ROS namespaces `namespaces`): ROS 2 topics with `--ros2`,
/// else the simulator's shared memory.
fn robot_ports(
    inst: &Instance,
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    a: &RobotSystemArgs,
    system: &str,
    robots: &[(String, String)],
    camera: bool,
) -> anyhow::Result<Vec<Box<dyn RobotPort>>> {
    if a.ros2 {
        let params = match &a.robot_params {
            Some(p) => muster_ros2::port::RobotParams::load(p)?,
            None => Default::default(),
        };
        if let Some(unknown) = params.keys().find(|k| !robots.iter().any(|(r, _)| r == *k)) {
            anyhow::bail!("--robot-params: {unknown} is not one of this system's robots");
        }
        let map = a.map.as_deref().map(load_map).transpose()?.map(Arc::new);
        return robots
            .iter()
            .map(|(r, ns)| {
                let opts = muster_ros2::port::PortOptions {
                    domain: ros2_domain(a),
                    namespace: ns.clone(),
                    node: format!("{system}_{r}"),
                    robot: r.clone(),
                    params: params.get(r).cloned().unwrap_or_default(),
                    map: map.clone(),
                    camera,
                    wait: a.wait_sim,
                };
                Ok(Box::new(muster_ros2::port::Ros2Port::open(&opts)?) as Box<dyn RobotPort>)
            })
            .collect();
    }
    let (scenario, map) = world_of(a)?;
    let names: Vec<String> = robots.iter().map(|(r, _)| r.clone()).collect();
    Ok(
        open_ports(node, inst.as_str(), &scenario, &map, &names, a.wait_sim)?
            .into_iter()
            .map(|l| Box::new(l) as Box<dyn RobotPort>)
            .collect(),
    )
}

fn tracking(inst: &Instance, a: TrackingArgs) -> anyhow::Result<ExitCode> {
    let robots = if !a.robots.is_empty() {
        a.robots.clone()
    } else if a.common.ros2 {
        anyhow::bail!("--ros2: name the robots with --robots");
    } else {
        world_of(&a.common)?
            .0
            .robots
            .iter()
            .filter(|r| r.camera.is_some())
            .map(|r| r.name.clone())
            .collect()
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
    let named: Vec<(String, String)> = robots
        .iter()
        .map(|r| (r.clone(), format!("/{r}")))
        .collect();
    let links = robot_ports(inst, &node, &a.common, &a.name, &named, true)?;
    let described: serde_json::Map<String, serde_json::Value> = links
        .iter()
        .map(|l| (l.description().name.clone(), l.description().summary()))
        .collect();
    let mut app = TrackingApp::new(links, &opts)?;
    show_view(&node, inst, &a.name, |w| app.show_on(w, &a.name));
    let core = SystemCore::new(&a.name, std::process::id(), specs);
    let run = muster_systems::RunOptions {
        udp: a.common.udp,
        ..Default::default()
    };
    let core = muster_systems::run_system_with(inst, core, &mut app, &run)?;
    if a.common.stats_json {
        let loc: serde_json::Map<String, serde_json::Value> = app
            .localization()
            .into_iter()
            .map(|(r, s)| (r, s.summary()))
            .collect();
        out!(
            "{}",
            serde_json::json!({"system": core.name(), "services": core.report(),
                "localization": loc, "updates": app.published(), "robots": described})
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn delivery(inst: &Instance, a: DeliveryArgs) -> anyhow::Result<ExitCode> {
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
    let ns = a
        .namespace
        .clone()
        .unwrap_or_else(|| format!("/{}", a.robot));
    let link = robot_ports(
        inst,
        &node,
        &a.common,
        &a.name,
        &[(a.robot.clone(), ns)],
        false,
    )?
    .pop()
    .context("no port")?;
    let described = serde_json::json!({a.robot.clone(): link.description().summary()});
    let mut app = DeliveryApp::new(link, &opts)?;
    show_view(&node, inst, &a.name, |w| app.show_on(w, &a.name));
    let core = SystemCore::new(&a.name, std::process::id(), specs);
    let run = muster_systems::RunOptions {
        udp: a.common.udp,
        ..Default::default()
    };
    let core = muster_systems::run_system_with(inst, core, &mut app, &run)?;
    if a.common.stats_json {
        out!(
            "{}",
            serde_json::json!({"system": core.name(), "services": core.report(),
                "localization": {a.robot.clone(): app.localization().summary()},
                "arrivals": app.arrivals(), "robots": described,
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
