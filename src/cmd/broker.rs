//! `muster broker`.

use crate::cli::BrokerArgs;
use muster_broker::BrokerConfig;
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
    };
    let report = muster_broker::run::run(inst, cfg)?;
    if a.stats_json {
        println!("{}", report.to_json());
    }
    Ok(ExitCode::SUCCESS)
}
