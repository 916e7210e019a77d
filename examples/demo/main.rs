//! The go/no-go demo: a first look at the shipped guardian on real drawings (README,
//! "The two commands"). With `guardiand` running on its shipped defaults:
//!
//! ```sh
//! cargo run --release --example demo
//! ```
#![forbid(unsafe_code)]

mod cases;

use std::path::PathBuf;

use clap::Parser;

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
    /// The daemon, and how to report.
    #[command(flatten)]
    session: cases::Session,
}

/// Connect, run the cases, print; an error if any case is not as expected.
fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let client = args.session.connect("see README")?;
    let report = run_cases(
        &client,
        &Options {
            strokes: args.strokes.clone(),
            keep: args.session.keep,
        },
    )?;
    cases::finish(&report, args.session.json)
}
