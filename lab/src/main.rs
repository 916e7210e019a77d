//! `guardian-lab`: command-line entry to the research bench. One subcommand per module; each
//! module owns its `Args` and `run`.
#![forbid(unsafe_code)]

use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(name = "guardian-lab", version, about = "guardian research bench")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Convert Omniglot strokes into joint trajectories of a robot (safetensors dataset).
    Dataset(guardian_lab::dataset::Args),
    /// Train the embedding network.
    Train(Box<guardian_lab::train::Args>),
    /// Few-shot evaluation of a model or a baseline.
    Eval(guardian_lab::eval::Args),
    /// K-fold by alphabet: train both branches per fold on the other folds' alphabets,
    /// measure episodes and cross-fitted go / no-go on the held-out ones, write the report.
    Kfold(Box<guardian_lab::eval::kfold::Args>),
    /// Fuse trained networks into one model file (the branches of a fused model).
    Fuse(guardian_lab::tools::fuse::Args),
    /// Markdown + PNG report of a trained model.
    Report(guardian_lab::eval::report::Args),
    /// Calibrate thresholds on validation alphabets and build a class bank.
    Bank(guardian_lab::tools::bank::Args),
    /// Faulty-plan detection metrics (AUROC, TPR at 1% FPR, detection, false rejects).
    Outliers(guardian_lab::eval::outliers::Args),
    /// Manipulation cells never seen: identify, genuine go, wrong task and faults, anchored
    /// against today's decision (or `--calibrate`: sweep the place rule).
    Cell(guardian_lab::eval::cell::Args),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match &cli.command {
        Command::Dataset(args) => guardian_lab::dataset::run(args),
        Command::Train(args) => guardian_lab::train::run(args),
        Command::Eval(args) => guardian_lab::eval::run(args),
        Command::Kfold(args) => guardian_lab::eval::kfold::run(args),
        Command::Fuse(args) => guardian_lab::tools::fuse::run(args),
        Command::Report(args) => guardian_lab::eval::report::run(args),
        Command::Bank(args) => guardian_lab::tools::bank::run(args),
        Command::Outliers(args) => guardian_lab::eval::outliers::run(args),
        Command::Cell(args) => guardian_lab::eval::cell::run(args),
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    /// Every subcommand's arguments, shared groups flattened in, are consistent (no option
    /// defined twice, defaults that parse).
    #[test]
    fn the_command_line_is_consistent() {
        super::Cli::command().debug_assert();
    }
}
