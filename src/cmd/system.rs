//! `muster system ...`.

use crate::cli::SystemCommand;
use muster_shared::types::validate_registration;
use muster_shared::Instance;
use muster_systems::synthetic::{Synthetic, SyntheticOptions};
use muster_systems::SystemCore;
use std::process::ExitCode;

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
                rate_hz: a.rate,
            };
            if !(a.rate.is_finite() && a.rate > 0.0 && a.rate <= 10_000.0) {
                anyhow::bail!("--rate must be in (0, 10000] Hz");
            }
            let specs = opts.specs();
            validate_registration(&opts.name, &specs)?;
            let salt = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(0);
            let core = SystemCore::new(&opts.name, std::process::id(), specs, salt);
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
    }
}
