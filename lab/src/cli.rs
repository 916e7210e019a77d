//! Argument groups shared by the subcommands (flattened into each command's `Args` with
//! `#[command(flatten)]`), so one option means one thing with one default everywhere.

use std::path::PathBuf;

/// The Omniglot stroke root of this workspace's shared data.
pub const DEFAULT_STROKES: &str = "../shared/omniglot/strokes";

/// The shipped embedder.
pub const SHIPPED_MODEL: &str = "models/embedder.safetensors";

/// The dataset file a command reads.
#[derive(Debug, Clone, clap::Args)]
pub struct DatasetArgs {
    /// Dataset file (from `guardian-lab dataset`).
    #[arg(long)]
    pub dataset: PathBuf,
}

/// The recovered Omniglot alphabets of this workspace's shared data (same layout).
pub const DEFAULT_RECOVERED: &str = "../shared/omniglot/recovered";

/// The Omniglot stroke roots (faulty plans and demo drawings are made from the strokes).
#[derive(Debug, Clone, clap::Args)]
pub struct StrokesArgs {
    /// Omniglot stroke roots, comma-separated (each in the official layout; an alphabet
    /// may appear under one root only).
    #[arg(long, value_delimiter = ',', default_values = [DEFAULT_STROKES, DEFAULT_RECOVERED])]
    pub strokes: Vec<PathBuf>,
}

/// The screen under test and its split: a model, the alphabets whose classes are enrolled,
/// the alphabets it is calibrated on, and the calibration's settings (`bank`, `outliers`).
#[derive(Debug, Clone, clap::Args)]
pub struct ScreenArgs {
    /// Embedder file.
    #[arg(long, default_value = SHIPPED_MODEL)]
    pub model: PathBuf,
    /// Alphabets whose classes are enrolled (never calibrated on).
    #[arg(long, value_delimiter = ',', default_value = "Greek,Korean")]
    pub alphabets: Vec<String>,
    /// Alphabets to calibrate on (validation; never the enrolled ones).
    #[arg(long, value_delimiter = ',', default_value = "Latin")]
    pub calib_alphabets: Vec<String>,
    /// Enrolled drawings per class (calibration uses the same number).
    #[arg(long, default_value_t = 5)]
    pub shots: usize,
    /// Target false-reject rate on genuine plans (embedding and geometry together).
    #[arg(long, default_value_t = 0.01)]
    pub target_frr: f32,
    /// Share of the false-reject budget given to the geometry check (the embedding gets
    /// the rest); 0 turns the geometry check off.
    #[arg(long, default_value_t = 0.25)]
    pub geometry_share: f32,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl ScreenArgs {
    /// Refuse a geometry share outside [0, 1].
    pub fn check_geometry_share(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            (0.0..=1.0).contains(&self.geometry_share),
            "--geometry-share must be in [0, 1]"
        );
        Ok(())
    }

    /// Refuse calibration alphabets that are also enrolled.
    pub fn check_disjoint(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            !self
                .calib_alphabets
                .iter()
                .any(|a| self.alphabets.contains(a)),
            "calibration and enrolled alphabets overlap"
        );
        Ok(())
    }
}

/// N-way K-shot episodes.
#[derive(Debug, Clone, clap::Args)]
pub struct EpisodeArgs {
    /// N (classes per episode).
    #[arg(long, default_value_t = 5)]
    pub way: usize,
    /// K (support examples per class).
    #[arg(long, default_value_t = 1)]
    pub shot: usize,
    /// Episodes.
    #[arg(long, default_value_t = 10_000)]
    pub episodes: usize,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        data: DatasetArgs,
        #[command(flatten)]
        screen: ScreenArgs,
    }

    #[derive(Debug, Parser)]
    struct EpisodeCli {
        #[command(flatten)]
        episodes: EpisodeArgs,
    }

    #[test]
    fn flattened_groups_parse_with_their_defaults() {
        let cli = Cli::try_parse_from(["lab", "--dataset", "d.safetensors"]).expect("parse");
        assert_eq!(cli.data.dataset, PathBuf::from("d.safetensors"));
        assert_eq!(cli.screen.model, PathBuf::from(SHIPPED_MODEL));
        assert_eq!(cli.screen.alphabets, ["Greek", "Korean"]);
        assert_eq!(cli.screen.calib_alphabets, ["Latin"]);
        let spec = EpisodeCli::try_parse_from(["lab"])
            .expect("parse")
            .episodes
            .spec();
        assert_eq!(
            (spec.way, spec.shot, spec.episodes, spec.seed),
            (5, 1, 10_000, 0)
        );
        cli.screen
            .check_disjoint()
            .expect("the default split is disjoint");
        cli.screen
            .check_geometry_share()
            .expect("the default share");
        // Without the dataset the command does not parse.
        assert!(Cli::try_parse_from(["lab"]).is_err());
    }

    #[test]
    fn an_overlapping_split_or_a_bad_geometry_share_is_refused() {
        let parse = |extra: &[&str]| {
            let mut args = vec!["lab", "--dataset", "d"];
            args.extend_from_slice(extra);
            Cli::try_parse_from(args).expect("parse").screen
        };
        let err = parse(&["--alphabets", "Latin,Greek"])
            .check_disjoint()
            .unwrap_err();
        assert!(err.to_string().contains("overlap"), "{err}");
        assert!(
            parse(&["--geometry-share", "1.5"])
                .check_geometry_share()
                .is_err()
        );
        assert!(
            parse(&["--geometry-share", "0"])
                .check_geometry_share()
                .is_ok()
        );
    }
}
