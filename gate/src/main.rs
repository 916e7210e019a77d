//! `guardian-gate`: parse args, init tracing, load the config, run the gate until SIGTERM
//! or SIGINT (docs/ros2.md).
#![forbid(unsafe_code)]

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use clap::Parser;
use guardian_gate::config::{DEFAULT_CONFIG_PATH, GateConfig};

/// A ROS 2 FollowJointTrajectory gate: every goal is screened by guardiand before the
/// real controller sees it.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Config file; unset: $GUARDIAN_GATE_CONFIG, else /etc/guardian/guardian-gate.toml if
    /// it exists, else the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print the default config and exit.
    #[arg(long)]
    print_default_config: bool,
}

/// The log filter unless `RUST_LOG` is set. RustDDS logs every discovery event at INFO, and
/// two of its WARNs repeat without end: "No locators for RtpsReaderProxy" from its writers
/// (tens a second while a peer's reader has no UDP locator, e.g. Cyclone DDS's on an idle
/// gate) and "Message size" for every datagram over 1,500 bytes (one per forwarded goal);
/// those two modules log errors only.
const DEFAULT_LOG: &str = "info,rustdds=warn,rustdds::rtps::writer=error,rustdds::network::udp_sender=error,ros2_client=warn";

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", GateConfig::default_toml());
        return Ok(());
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| DEFAULT_LOG.into()),
        )
        .with_writer(std::io::stderr)
        // Colour only on a terminal: the journal and log files get plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let path = args
        .config
        .or_else(|| std::env::var_os("GUARDIAN_GATE_CONFIG").map(PathBuf::from))
        .or_else(|| {
            let p = PathBuf::from(DEFAULT_CONFIG_PATH);
            p.exists().then_some(p)
        });
    let config = match &path {
        Some(p) => GateConfig::load(p)?,
        None => GateConfig::default(),
    };
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(sig, stop.clone()).context("signal handler")?;
    }
    guardian_gate::node::run(config, stop)
}
