//! Plot one dataset drawing (placeholder until the plot lands).

use std::path::PathBuf;

/// `guardian-lab plot`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Dataset file.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Drawing index.
    #[arg(long)]
    pub index: usize,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
}

/// Run `guardian-lab plot`.
pub fn run(_args: &Args) -> anyhow::Result<()> {
    anyhow::bail!("plot: not implemented yet")
}
