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

use clap::Parser;

/// The cell demo's arguments.
#[derive(Debug, Parser)]
#[command(
    about = "Enroll three pick-and-place tasks in a running guardiand serving an anchored cell, send genuine and faulty runs, print a go/no-go table (exit status 1 if any case is not as expected)"
)]
struct Args {
    /// The daemon, and how to report.
    #[command(flatten)]
    session: demo::Session,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let client = args
        .session
        .connect("start it with daemon/run.sh --config systemd/guardiand-cell.toml")?;
    let report = cases::run_cases(&client, args.session.keep)?;
    demo::finish(&report, args.session.json)
}
