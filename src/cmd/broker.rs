//! `muster broker`.

use crate::cli::BrokerArgs;
use muster_broker::federation::FedConfig;
use muster_broker::udp::{UdpConfig, UdpLimits};
use muster_broker::BrokerConfig;
use muster_shared::udp::crypto::KeyPair;
use muster_shared::Instance;
use std::process::ExitCode;

pub fn run(inst: &Instance, a: BrokerArgs) -> anyhow::Result<ExitCode> {
    if a.ping_interval.is_zero() || a.ping_timeout.is_zero() {
        anyhow::bail!("--ping-interval and --ping-timeout must be greater than zero");
    }
    let cfg = BrokerConfig {
        ping_interval: a.ping_interval,
        ping_timeout: a.ping_timeout,
        offer_timeout: a.offer_timeout,
        queue_capacity: a.queue_capacity,
        max_links_per_user: a.max_links_per_user,
        max_users_per_process: a.max_users_per_process,
        max_services: a.max_services,
    }
    .scaled(muster_shared::clock::global());
    let udp = match a.udp {
        None => None,
        Some(bind) => {
            let key = match &a.key {
                Some(p) => KeyPair::read(p)?.1,
                None => KeyPair::generate()?,
            };
            if a.access.is_none() {
                tracing::warn!("no --access file: every remote user will be refused");
            }
            Some(UdpConfig {
                bind,
                key,
                access_path: a.access.clone(),
                limits: UdpLimits {
                    conn_rate: (a.udp_conn_rate, 2.0 * a.udp_conn_rate),
                    max_conns: a.udp_max_users,
                    ..UdpLimits::default()
                },
            })
        }
    };
    let acl = match &a.acl {
        Some(p) => Some(muster_broker::federation::Acl::load(p)?),
        None => None,
    };
    let fed = a.federate.then(|| FedConfig {
        host: a.host.clone().unwrap_or_else(default_host),
        federation: a.federation.clone(),
        zenoh_config: a.zenoh_config.clone(),
        connect: a.connect.clone(),
        listen: a.listen.clone(),
        lease: a.lease,
        multicast: a.multicast,
        mode: a.zenoh_mode,
        tls: a.tls.clone(),
        acl,
        insecure: a.insecure_no_tls,
    });
    let keep_log = a.handling_log.is_some();
    // Cleanups after dead processes run as `muster cleanup`, outliving a killed broker.
    if let Ok(exe) = std::env::current_exe() {
        muster_broker::run::set_cleanup_program(exe);
    }
    if let Some(f) = a.fault {
        muster_broker::run::set_fault(f);
    }
    let report = if a.standby {
        muster_broker::run::run_standby(inst, cfg, udp, fed, keep_log, a.takeover_deadline)?
    } else {
        muster_broker::run::run_with(inst, cfg, udp, fed, keep_log)?
    };
    if let Some(path) = &a.handling_log {
        report
            .handling
            .write_log(path)
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
        if report.handling.log_dropped > 0 {
            tracing::warn!(
                dropped = report.handling.log_dropped,
                "the handling log was full"
            );
        }
    }
    if a.stats_json {
        out!("{}", report.to_json());
    }
    Ok(ExitCode::SUCCESS)
}

/// The machine's host name, cut to what a federation's host name may hold.
fn default_host() -> String {
    let raw = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
    let name: String = raw
        .trim()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .take(31)
        .collect();
    if name.is_empty() {
        "host".into()
    } else {
        name
    }
}
