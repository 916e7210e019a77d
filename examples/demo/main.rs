//! The go/no-go demo: a first look at the shipped guardian on real drawings (README,
//! "The two commands"). With `guardiand` running on its shipped defaults:
//!
//! ```sh
//! cargo run --release --example demo
//! ```
#![forbid(unsafe_code)]

mod cases;

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Parser;
use guardian_client::Client;

use cases::{Options, run_cases};

/// The demo's arguments.
#[derive(Debug, Parser)]
#[command(
    about = "Enroll real drawings in a running guardiand, send genuine and faulty plans, print a go/no-go table (exit status 1 if any case is not as expected)"
)]
struct Args {
    /// Omniglot stroke root of the official files (the demo draws Latin).
    #[arg(long, default_value = "../shared/omniglot/strokes")]
    strokes: PathBuf,
    /// Request-response service name of the daemon.
    #[arg(long, default_value = guardian_shared::wire::DEFAULT_SERVICE_NAME)]
    service: String,
    /// Per-request timeout in milliseconds.
    #[arg(long, default_value_t = 2000)]
    timeout_ms: u64,
    /// iceoryx2 root path (must match the daemon's config).
    #[arg(long)]
    iceoryx2_root_path: Option<PathBuf>,
    /// iceoryx2 prefix (must match the daemon's config).
    #[arg(long)]
    iceoryx2_prefix: Option<String>,
    /// Print JSON instead of the table.
    #[arg(long)]
    json: bool,
    /// Keep the demo classes enrolled afterwards.
    #[arg(long)]
    keep: bool,
}

/// Connect, run the cases, print; an error if any case is not as expected.
fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let client = Client::connect(guardian_client::ClientConfig {
        service_name: args.service.clone(),
        timeout: std::time::Duration::from_millis(args.timeout_ms),
        iceoryx2_root_path: args.iceoryx2_root_path.clone(),
        iceoryx2_prefix: args.iceoryx2_prefix.clone(),
    })
    .context("cannot connect to guardiand (is it running? see README)")?;
    let report = run_cases(
        &client,
        &Options {
            strokes: args.strokes.clone(),
            keep: args.keep,
        },
    )?;
    cases::finish(&report, args.json)
}
