//! The cell demo: a pick-and-place cell screened by guardian (README, "A cell"). With
//! `guardiand` running on the cell's configuration:
//!
//! ```sh
//! daemon/run.sh --config systemd/guardiand-cell.toml
//! cargo run --release --example cell
//! ```
#![forbid(unsafe_code)]

#[allow(dead_code)]
#[path = "../demo/cases.rs"]
mod demo;

mod cases;

use anyhow::Context as _;
use clap::Parser;
use guardian_client::Client;

/// The cell demo's arguments.
#[derive(Debug, Parser)]
#[command(
    about = "Enroll three pick-and-place tasks in a running guardiand serving an anchored cell, send genuine and faulty runs, print a go/no-go table (exit status 1 if any case is not as expected)"
)]
struct Args {
    /// Request-response service name of the daemon.
    #[arg(long, default_value = guardian_shared::wire::DEFAULT_SERVICE_NAME)]
    service: String,
    /// Per-request timeout in milliseconds.
    #[arg(long, default_value_t = 2000)]
    timeout_ms: u64,
    /// Print JSON instead of the table.
    #[arg(long)]
    json: bool,
    /// Keep the demo classes enrolled afterwards.
    #[arg(long)]
    keep: bool,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let client = Client::connect(guardian_client::ClientConfig {
        service_name: args.service.clone(),
        timeout: std::time::Duration::from_millis(args.timeout_ms),
        iceoryx2_root_path: None,
        iceoryx2_prefix: None,
    })
    .context("cannot connect to guardiand (is it running on systemd/guardiand-cell.toml?)")?;
    let report = cases::run_cases(&client, args.keep)?;
    demo::finish(&report, args.json)
}
