//! The report of a trained model (markdown + PNG plots).

use std::path::PathBuf;

/// `guardian-lab report`: markdown report with plots for a trained model.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Trained embedder.
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset file.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

/// Run `guardian-lab report`.
pub fn run(_args: &Args) -> anyhow::Result<()> {
    anyhow::bail!("not yet implemented")
}
