//! The `defvol` command line: the commands live in `cli/`.

mod cli;

use clap::Parser;

fn main() -> anyhow::Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| "info,rustdds=error,ros2_client=warn".into());
    tracing_subscriber::fmt().with_env_filter(filter).with_target(false).init();
    cli::run(cli::Cli::parse())
}
