//! `muster`: multi-user, multi-robot interaction over iceoryx2 shared memory.

mod cli;
mod cmd;

use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = cli::Cli::parse();
    muster_shared::clock::set_global(cli.time_scale.unwrap_or_default());
    // iceoryx2's own log: errors only, unless IOX2_LOG_LEVEL says otherwise.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
                tracing_subscriber::EnvFilter::new(
                    // ros2-client warns that ROS_DISTRO is unset: muster needs no ROS install.
                    "info,zenoh=warn,zenoh_transport=warn,zenoh_link_tcp=warn,rustdds=warn,ros2_client=warn,ros2_client::distributions=error",
                )
            }),
        )
        .with_writer(std::io::stderr)
        .with_target(false)
        .init();
    match cmd::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("muster: {e:#}");
            std::process::ExitCode::from(1)
        }
    }
}
