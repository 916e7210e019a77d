//! What determines a training run: the command line (`guardian-lab train`), the
//! [`TrainConfig`] it describes (written to `train-config.json` and compared on
//! `--resume`), the loss and feature choices, and the fault kinds of fault negatives.

use std::path::PathBuf;

use guardian_models::features::FeatureKind;
use guardian_models::net::NetConfig;
use serde::{Deserialize, Serialize};

use crate::cli::{DatasetArgs, StrokesArgs};
use crate::train::TrainError;
use guardian_omniglot::corrupt::Fault;

/// Which loss trains the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum LossKind {
    /// Online batch-all triplet loss (mean over active triplets).
    BatchAll,
    /// The paper's loss on random explicit triplets (one per anchor).
    Triplet,
    /// Contrastive pair loss: the Siamese baseline.
    Contrastive,
    /// Supervised contrastive loss (a softmax over the batch's cosine similarities; its
    /// temperature is `--margin`).
    Supcon,
    /// Normalised softmax over one learned proxy per training class, every class a
    /// negative of every item (`loss::norm_softmax_loss`; its temperature is `--margin`).
    NormSoftmax,
}

/// Feature choice on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FeatureArg {
    /// Normalised pen-tip path from forward kinematics.
    Pen,
    /// Scaled joint angles (the paper's input).
    Joints,
    /// A picture of the pen-down path, read by a 2D CNN.
    Picture,
}

impl From<FeatureArg> for FeatureKind {
    fn from(f: FeatureArg) -> Self {
        match f {
            FeatureArg::Pen => FeatureKind::Pen,
            FeatureArg::Joints => FeatureKind::Joints,
            FeatureArg::Picture => FeatureKind::Picture,
        }
    }
}

/// The corruptions fault-negative training makes of a genuine drawing: the ones that change
/// the drawn shape. Shift and scale are not among them (the pen features remove position
/// and size by design; the plan-geometry check sees them), nor time reversal (training
/// augments with it, since drawers of one character draw strokes in either direction),
/// nor joint faults (the workcell rules catch every one of them).
pub const TRAIN_FAULTS: [Fault; 5] = [
    Fault::MissingStroke,
    Fault::ExtraStroke,
    Fault::Mirrored,
    Fault::Truncated,
    Fault::Rotated,
];

/// Learning-rate schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Schedule {
    /// Halve the rate when the validation loss stalls and stop early; the model with the best
    /// validation loss is kept.
    #[default]
    Plateau,
    /// A fixed one-cycle schedule over every step of `epochs x steps-per-epoch` (linear
    /// warm-up from lr/25 over the first 5 %, then cosine annealing to lr/10⁴), no early
    /// stopping; the last model is kept. Validation is measured and logged only.
    OneCycle,
}

/// Everything that determines a training run (written to `train-config.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub struct TrainConfig {
    /// Network architecture.
    pub net: NetConfig,
    /// Loss.
    pub loss: LossKind,
    /// Triplet / contrastive margin (the temperature of `supcon` and `norm-softmax`).
    pub margin: f64,
    /// Training alphabets.
    pub train_alphabets: Vec<String>,
    /// Validation alphabets (early stopping, LR schedule). Empty only with
    /// [`Schedule::OneCycle`], which keeps the last model and needs no validation.
    pub val_alphabets: Vec<String>,
    /// Classes per batch.
    pub p_classes: usize,
    /// Samples per class per batch.
    pub k_samples: usize,
    /// Optimiser steps per epoch.
    pub steps_per_epoch: usize,
    /// Most epochs.
    pub max_epochs: usize,
    /// Learning-rate schedule (and whether validation stops training early).
    #[serde(default)]
    pub schedule: Schedule,
    /// Initial learning rate.
    pub lr: f64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// ReduceLROnPlateau: epochs without improvement before the LR is multiplied by
    /// `lr_factor`.
    pub plateau_patience: usize,
    /// ReduceLROnPlateau factor.
    pub lr_factor: f64,
    /// Smallest learning rate.
    pub min_lr: f64,
    /// Early stopping: epochs without validation-loss improvement.
    pub early_stop_patience: usize,
    /// Feature augmentation (rotation, shear, scale, time reversal).
    pub augment: bool,
    /// Time reversal among the augmentations (with `augment`).
    #[serde(default = "yes")]
    pub reverse_augment: bool,
    /// Seed of initialisation, batches and augmentation.
    pub seed: u64,
    /// Episodes of the per-epoch validation 5-way-1-shot accuracy.
    pub val_episodes: usize,
    /// Fault negatives (outlier exposure): the chance that a batch sample brings one of its
    /// own corrupted plans into the batch, labelled as a class of its own, so the loss
    /// pushes corrupted plans away from the genuine class they were made from. 0 = off.
    #[serde(default)]
    pub fault_share: f64,
    /// Corrupted plans made per training (and validation) drawing when `fault_share > 0`.
    #[serde(default)]
    pub fault_variants: usize,
    /// Weight of the fault-negative triplet term (`loss::fault_triplet_loss`) added to the
    /// main loss; 0 leaves corrupted plans as plain negatives of the main loss only.
    #[serde(default)]
    pub fault_weight: f64,
    /// Margin of the fault-negative triplet term.
    #[serde(default)]
    pub fault_margin: f64,
    /// The corruptions fault negatives are made with (empty: none).
    #[serde(default)]
    pub fault_kinds: Vec<Fault>,
    /// The fault-negative margin of some kinds, instead of `fault_margin`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fault_margin_for: Vec<(Fault, f64)>,
    /// Class augmentation: every training character rotated by 90°, 180°, 270° and
    /// mirrored becomes a class of its own (`classaug`), symmetric ones excepted.
    #[serde(default)]
    pub class_augment: bool,
    /// The split-half quantile of `classaug::SymmetryRule` (with `class_augment`).
    #[serde(default)]
    pub symmetry_quantile: f64,
    /// The class proxies' learning rate over the network's ([`LossKind::NormSoftmax`]).
    #[serde(default = "one")]
    pub proxy_lr_scale: f64,
}

impl TrainConfig {
    /// The fault-negative margin of a corrupted plan of kind `kind` (`None`: a kind not
    /// known, `fault_margin`).
    pub fn fault_margin_of(&self, kind: Option<Fault>) -> f64 {
        kind.and_then(|k| self.fault_margin_for.iter().find(|(f, _)| *f == k))
            .map_or(self.fault_margin, |&(_, m)| m)
    }

    /// Refuse a configuration that cannot train: an invalid network, batches without
    /// positives or negatives, an alphabet both trained and validated on, a fault share
    /// outside [0, 1], fault negatives without a variant, or a fault margin that is not
    /// positive or names a kind not trained with.
    pub fn check(&self) -> Result<(), TrainError> {
        self.net
            .check()
            .map_err(|e| TrainError::Setup(format!("network config: {e}")))?;
        if self.p_classes < 2 || self.k_samples < 2 {
            return Err(TrainError::Setup(
                "need p-classes >= 2 and k-samples >= 2".into(),
            ));
        }
        if self.val_alphabets.is_empty() && self.schedule != Schedule::OneCycle {
            return Err(TrainError::Setup(
                "the plateau schedule stops on the validation loss: give --val-alphabets \
                 (only --schedule one-cycle trains without validation)"
                    .into(),
            ));
        }
        if self.loss == LossKind::NormSoftmax && !self.val_alphabets.is_empty() {
            return Err(TrainError::Setup(
                "norm-softmax scores items against the training classes' proxies, which a \
                 validation alphabet's classes have none of: train without --val-alphabets \
                 (--schedule one-cycle) and measure on held-out alphabets"
                    .into(),
            ));
        }
        for a in &self.val_alphabets {
            if self.train_alphabets.contains(a) {
                return Err(TrainError::Setup(format!(
                    "alphabet {a} is in both train and val"
                )));
            }
        }
        if !(0.0..=1.0).contains(&self.fault_share)
            || (self.fault_share > 0.0 && self.fault_variants == 0)
        {
            return Err(TrainError::Setup(format!(
                "fault share {} must be in [0, 1], with at least one variant",
                self.fault_share
            )));
        }
        for &(kind, m) in &self.fault_margin_for {
            if !(m > 0.0 && m.is_finite() && self.fault_kinds.contains(&kind)) {
                return Err(TrainError::Setup(format!(
                    "fault margin {m} for {}: it must be > 0, for a kind of --fault-kinds",
                    kind.name()
                )));
            }
        }
        Ok(())
    }
}

fn yes() -> bool {
    true
}

fn one() -> f64 {
    1.0
}

/// `guardian-lab train`: train the embedding network.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// The dataset.
    #[command(flatten)]
    pub data: DatasetArgs,
    /// Training alphabets, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    pub train_alphabets: Vec<String>,
    /// Validation alphabets, comma-separated (per-epoch loss and 5-way accuracy; the
    /// plateau schedule stops on them). Optional with `--schedule one-cycle`, which keeps
    /// the last model: then every labelled alphabet can be trained on.
    #[arg(long, value_delimiter = ',')]
    pub val_alphabets: Vec<String>,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Continue from the checkpoint in `--out`.
    #[arg(long)]
    pub resume: bool,
    /// Input features.
    #[arg(long, value_enum, default_value = "pen")]
    pub features: FeatureArg,
    /// Loss (`contrastive` trains the Siamese baseline).
    #[arg(long, value_enum, default_value = "batch-all")]
    pub loss: LossKind,
    /// Margin of the loss (for `supcon` and `norm-softmax`, its temperature).
    #[arg(long, default_value_t = 0.2)]
    pub margin: f64,
    /// Convolution channels per layer, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "64,128,128")]
    pub channels: Vec<usize>,
    /// Convolution kernel size.
    #[arg(long, default_value_t = 5)]
    pub kernel: usize,
    /// Embedding dimension, at most 128 (`EMBED_DIM`; a smaller embedding is served
    /// zero-padded). The two branches of a fused model (`guardian-lab fuse`): 64 each.
    #[arg(long, default_value_t = guardian_models::embedder::EMBED_DIM)]
    pub embed_dim: usize,
    /// Do not L2-normalise embeddings.
    #[arg(long)]
    pub no_l2: bool,
    /// Classes per batch.
    #[arg(long, default_value_t = 16)]
    pub p_classes: usize,
    /// Samples per class per batch.
    #[arg(long, default_value_t = 4)]
    pub k_samples: usize,
    /// Optimiser steps per epoch.
    #[arg(long, default_value_t = 50)]
    pub steps_per_epoch: usize,
    /// Most epochs.
    #[arg(long, default_value_t = 60)]
    pub epochs: usize,
    /// Learning-rate schedule: `plateau` (early stopping on the validation loss) or
    /// `one-cycle` (a fixed schedule over all epochs).
    #[arg(long, value_enum, default_value = "plateau")]
    pub schedule: Schedule,
    /// Learning rate.
    #[arg(long, default_value_t = 2e-3)]
    pub lr: f64,
    /// AdamW weight decay.
    #[arg(long, default_value_t = 1e-4)]
    pub weight_decay: f64,
    /// ReduceLROnPlateau patience (epochs).
    #[arg(long, default_value_t = 3)]
    pub plateau_patience: usize,
    /// Early-stopping patience (epochs).
    #[arg(long, default_value_t = 8)]
    pub patience: usize,
    /// No augmentation.
    #[arg(long)]
    pub no_augment: bool,
    /// Augment without time reversal (the other augmentations stay).
    #[arg(long)]
    pub no_reverse_augment: bool,
    /// Seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Validation episodes per epoch (5-way-1-shot).
    #[arg(long, default_value_t = 1000)]
    pub val_episodes: usize,
    /// Store test-time reverse averaging in the saved models (inference only; training is
    /// unaffected).
    #[arg(long)]
    pub reverse_average: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Fault negatives: chance per batch sample of adding one of its corrupted plans
    /// (missing / extra stroke, mirrored, truncated, rotated; `TRAIN_FAULTS`) as a
    /// negative of its class. 0 trains on genuine plans only.
    #[arg(long, default_value_t = 0.0)]
    pub fault_share: f64,
    /// Corrupted plans made per drawing for `--fault-share` (re-solved through the IK).
    #[arg(long, default_value_t = 8)]
    pub fault_variants: usize,
    /// Weight of the fault-negative triplet term (anchor and positive of a class, one of
    /// the class's corrupted plans as the negative) added to the main loss.
    #[arg(long, default_value_t = 1.0)]
    pub fault_weight: f64,
    /// Margin of the fault-negative triplet term (squared embedding distance).
    #[arg(long, default_value_t = 0.4)]
    pub fault_margin: f64,
    /// The corruptions fault negatives are made with (default: `TRAIN_FAULTS`).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub fault_kinds: Vec<Fault>,
    /// The fault-negative margin of some kinds instead of `--fault-margin`,
    /// comma-separated `kind=margin` (e.g. `truncated=0.8,mirrored=0.8`).
    #[arg(long, value_delimiter = ',', value_parser = parse_kind_margin)]
    pub fault_margin_for: Vec<(Fault, f64)>,
    /// Omniglot stroke root the corrupted plans are made from (`--fault-share` only).
    #[command(flatten)]
    pub strokes: StrokesArgs,
    /// Class augmentation: every training character rotated by 90°, 180°, 270° and
    /// mirrored (8 symmetries of the square) becomes a class of its own; transforms that
    /// map a character onto itself or onto another class are dropped.
    #[arg(long)]
    pub class_augment: bool,
    /// With `--class-augment`: a transformed character counts as an existing one when its
    /// template is as similar to it as this quantile of the split-half similarities.
    #[arg(long, default_value_t = 0.1)]
    pub symmetry_quantile: f64,
    /// With `--loss norm-softmax`: the class proxies' learning rate as a multiple of the
    /// network's.
    #[arg(long, default_value_t = 1.0)]
    pub proxy_lr_scale: f64,
}

impl Args {
    /// The training configuration these arguments describe.
    pub fn config(&self) -> TrainConfig {
        let faults = self.fault_share > 0.0;
        TrainConfig {
            net: NetConfig {
                features: self.features.into(),
                channels: self.channels.clone(),
                kernel: self.kernel,
                embed_dim: self.embed_dim,
                l2_normalize: !self.no_l2,
                reverse_average: self.reverse_average,
                test_views: Vec::new(),
            },
            loss: self.loss,
            margin: self.margin,
            train_alphabets: self.train_alphabets.clone(),
            val_alphabets: self.val_alphabets.clone(),
            p_classes: self.p_classes,
            k_samples: self.k_samples,
            steps_per_epoch: self.steps_per_epoch,
            max_epochs: self.epochs,
            schedule: self.schedule,
            lr: self.lr,
            weight_decay: self.weight_decay,
            plateau_patience: self.plateau_patience,
            lr_factor: 0.5,
            min_lr: 1e-5,
            early_stop_patience: self.patience,
            augment: !self.no_augment,
            reverse_augment: !self.no_reverse_augment,
            seed: self.seed,
            val_episodes: self.val_episodes,
            fault_share: self.fault_share,
            // Without fault negatives the other fault settings are recorded as off.
            fault_variants: if faults { self.fault_variants } else { 0 },
            fault_weight: if faults { self.fault_weight } else { 0.0 },
            fault_margin: if faults { self.fault_margin } else { 0.0 },
            fault_kinds: match (faults, self.fault_kinds.is_empty()) {
                (false, _) => Vec::new(),
                (true, true) => TRAIN_FAULTS.to_vec(),
                (true, false) => self.fault_kinds.clone(),
            },
            fault_margin_for: if faults {
                self.fault_margin_for.clone()
            } else {
                Vec::new()
            },
            class_augment: self.class_augment,
            symmetry_quantile: if self.class_augment {
                self.symmetry_quantile
            } else {
                0.0
            },
            proxy_lr_scale: if self.loss == LossKind::NormSoftmax {
                self.proxy_lr_scale
            } else {
                1.0
            },
        }
    }
}

/// `kind=margin` of `--fault-margin-for`.
fn parse_kind_margin(s: &str) -> Result<(Fault, f64), String> {
    let (kind, margin) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}`: expected kind=margin, e.g. truncated=0.8"))?;
    let kind = <Fault as clap::ValueEnum>::from_str(kind, false)?;
    let margin: f64 = margin.parse().map_err(|e| format!("`{s}`: margin: {e}"))?;
    Ok((kind, margin))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use clap::Parser;

    /// A small valid configuration (a tiny pen network, Latin / Greek), for unit tests.
    pub(crate) fn small_config() -> TrainConfig {
        Cli::try_parse_from([
            "train",
            "--dataset",
            "d",
            "--train-alphabets",
            "Latin",
            "--val-alphabets",
            "Greek",
            "--out",
            "o",
            "--channels",
            "8,16",
        ])
        .expect("parse")
        .args
        .config()
    }

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: Args,
    }

    fn parse(extra: &[&str]) -> Args {
        let mut argv = vec![
            "train",
            "--dataset",
            "d",
            "--train-alphabets",
            "Latin,Korean",
            "--val-alphabets",
            "Greek",
            "--out",
            "o",
        ];
        argv.extend_from_slice(extra);
        Cli::try_parse_from(argv).expect("parse").args
    }

    #[test]
    fn the_proxy_learning_rate_is_recorded_for_norm_softmax_only_and_it_refuses_validation() {
        let cfg = parse(&["--proxy-lr-scale", "100"]).config();
        assert_eq!(cfg.proxy_lr_scale, 1.0, "no proxies without norm-softmax");
        let cfg = parse(&["--loss", "norm-softmax", "--proxy-lr-scale", "100"]).config();
        assert_eq!(cfg.proxy_lr_scale, 100.0);
        assert!(cfg.check().is_err(), "validation alphabets have no proxies");
        // A run recorded before the option existed reads back at 1.
        let mut json = serde_json::to_value(&cfg).expect("json");
        json.as_object_mut()
            .expect("object")
            .remove("proxy-lr-scale");
        let old: TrainConfig = serde_json::from_value(json).expect("old config");
        assert_eq!(old.proxy_lr_scale, 1.0);
    }

    #[test]
    fn without_fault_negatives_the_fault_settings_are_recorded_as_off() {
        let cfg = parse(&["--fault-variants", "3", "--fault-weight", "2"]).config();
        assert_eq!(cfg.fault_share, 0.0);
        assert_eq!(
            (cfg.fault_variants, cfg.fault_weight, cfg.fault_margin),
            (0, 0.0, 0.0)
        );
        assert!(cfg.fault_kinds.is_empty());
        assert_eq!(cfg.symmetry_quantile, 0.0, "no class augmentation");
        // With them, the defaults are the shipped recipe's kinds.
        let cfg = parse(&["--fault-share", "1", "--class-augment"]).config();
        assert_eq!(cfg.fault_kinds, TRAIN_FAULTS);
        assert_eq!(cfg.fault_variants, 8);
        assert_eq!(cfg.symmetry_quantile, 0.1);
        let cfg = parse(&["--fault-share", "0.5", "--fault-kinds", "mirrored"]).config();
        assert_eq!(cfg.fault_kinds, [Fault::Mirrored]);
        assert_eq!(cfg.train_alphabets, ["Latin", "Korean"]);
        assert_eq!(cfg.net.features, FeatureKind::Pen);
    }

    #[test]
    fn a_kind_can_have_its_own_fault_margin() {
        let cfg = parse(&[
            "--fault-share",
            "1",
            "--fault-margin-for",
            "truncated=0.8,mirrored=1.2",
        ])
        .config();
        cfg.check().expect("valid");
        assert_eq!(cfg.fault_margin_of(Some(Fault::Truncated)), 0.8);
        assert_eq!(cfg.fault_margin_of(Some(Fault::Mirrored)), 1.2);
        assert_eq!(cfg.fault_margin_of(Some(Fault::Rotated)), 0.4);
        assert_eq!(cfg.fault_margin_of(None), 0.4);
        // Recorded, and read back.
        let back: TrainConfig =
            serde_json::from_str(&serde_json::to_string(&cfg).unwrap()).unwrap();
        assert_eq!(back.fault_margin_for, cfg.fault_margin_for);
        // A kind not trained with, a margin that is not positive, a malformed pair.
        let bad = |args: &[&str]| {
            let mut all = vec!["--fault-share", "1"];
            all.extend_from_slice(args);
            parse(&all).config().check().is_err()
        };
        assert!(bad(&[
            "--fault-kinds",
            "mirrored",
            "--fault-margin-for",
            "truncated=0.8"
        ]));
        assert!(bad(&["--fault-margin-for", "truncated=0"]));
        for malformed in ["truncated:0.8", "sideways=0.8", "truncated=wide"] {
            let argv = [
                "t",
                "--dataset",
                "d",
                "--out",
                "o",
                "--fault-margin-for",
                malformed,
            ];
            assert!(Cli::try_parse_from(argv).is_err(), "{malformed}");
        }
        // Without fault negatives it is recorded as off.
        let off = parse(&["--fault-margin-for", "truncated=0.8"]).config();
        assert!(off.fault_margin_for.is_empty());
    }

    #[test]
    fn a_config_round_trips_through_json_and_older_fields_are_ignored() {
        let cfg = parse(&[
            "--features",
            "picture",
            "--channels",
            "8,8,8,8",
            "--kernel",
            "3",
        ])
        .config();
        cfg.check().expect("valid");
        let json = serde_json::to_value(&cfg).expect("json");
        assert_eq!(json["net"]["features"], "picture");
        assert_eq!(
            serde_json::from_value::<TrainConfig>(json.clone()).expect("back"),
            cfg
        );
        // A configuration written before the lab's pruning (options since removed, off)
        // still reads, so `--resume` of such a run compares equal.
        let mut old = json;
        old["pool-mode"] = "none".into();
        old["warp"] = 0.0.into();
        old["teachers"] = serde_json::json!([]);
        assert_eq!(
            serde_json::from_value::<TrainConfig>(old).expect("old"),
            cfg
        );
    }

    #[test]
    fn configurations_that_cannot_train_are_refused() {
        let good = small_config();
        good.check().expect("valid");
        let mut c = good.clone();
        c.p_classes = 1;
        assert!(c.check().is_err());
        let mut c = good.clone();
        c.val_alphabets = vec!["Latin".into()];
        let err = c.check().unwrap_err();
        assert!(err.to_string().contains("Latin"), "{err}");
        // No validation set: only the one-cycle schedule, which keeps the last model.
        let mut c = good.clone();
        c.val_alphabets.clear();
        c.schedule = Schedule::Plateau;
        let err = c.check().unwrap_err();
        assert!(err.to_string().contains("one-cycle"), "{err}");
        c.schedule = Schedule::OneCycle;
        c.check().expect("one-cycle trains without validation");
        let mut c = good.clone();
        c.fault_share = 1.5;
        assert!(c.check().is_err());
        let mut c = good.clone();
        c.fault_share = 0.5;
        c.fault_variants = 0;
        assert!(c.check().is_err());
        let mut c = good;
        c.net.channels.clear();
        assert!(c.check().is_err());
    }
}
