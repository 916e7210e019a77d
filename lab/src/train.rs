//! Training of the embedding network: class-balanced P x K batches from the training
//! alphabets, feature-level augmentation, a triplet (or, for the Siamese baseline, a
//! contrastive) loss, AdamW, ReduceLROnPlateau and early stopping on the validation loss,
//! fixed seeds, a JSONL metrics log, checkpoints and `--resume`.
//!
//! Output directory:
//! - `model.safetensors` — the best weights by validation loss (an [`Embedder`] file);
//! - `last.safetensors`, `optimizer.safetensors`, `state.json` — the resumable checkpoint;
//! - `metrics.jsonl` — one line per epoch; `train-config.json` — the full configuration.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor, Var};
use guardian_models::embedder::Embedder;
use guardian_models::fast::{FastNet, FastNetError};
use guardian_models::features::{self, Augment, FeatureKind, PenPoint};
use guardian_models::grad::{Grads, Trainable};
use guardian_models::loss;
use guardian_models::net::NetConfig;
use guardian_shared::trajectory::{Resampled, STEPS};
use rand::rngs::StdRng;
use rand::seq::{IndexedRandom, SliceRandom};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::classaug::{self, AugmentPlan, Dihedral, SymmetryRule};
use crate::dataset::{Dataset, StrokeIndex};
use crate::eval::{self, EpisodeSpec};
use crate::faults::{self, Fault};
use crate::path::PathSolver;

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

/// The one-cycle rate at `step` of `total` for a peak rate `peak` (PyTorch's `OneCycleLR`
/// with `pct_start = 0.05`, `div_factor = 25`, `final_div_factor = 10⁴`, cosine annealing).
pub fn one_cycle_lr(peak: f64, step: usize, total: usize) -> f64 {
    let total = total.max(2) as f64;
    let warm = (0.05 * total).max(1.0);
    let (start, end) = (peak / 25.0, peak / 25.0 / 1e4);
    let s = step as f64;
    let cos = |from: f64, to: f64, frac: f64| {
        to + (from - to) * 0.5 * (1.0 + (std::f64::consts::PI * frac.clamp(0.0, 1.0)).cos())
    };
    if s <= warm {
        cos(start, peak, s / warm)
    } else {
        cos(peak, end, (s - warm) / (total - 1.0 - warm).max(1.0))
    }
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

/// Everything that determines a training run (written to `train-config.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub struct TrainConfig {
    /// Network architecture.
    pub net: NetConfig,
    /// Loss.
    pub loss: LossKind,
    /// Triplet / contrastive margin.
    pub margin: f64,
    /// Training alphabets.
    pub train_alphabets: Vec<String>,
    /// Validation alphabets (early stopping, LR schedule).
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
    /// Class augmentation: every training character rotated by 90°, 180°, 270° and
    /// mirrored becomes a class of its own (`classaug`), symmetric ones excepted.
    #[serde(default)]
    pub class_augment: bool,
    /// The split-half quantile of `classaug::SymmetryRule` (with `class_augment`).
    #[serde(default)]
    pub symmetry_quantile: f64,
}

fn yes() -> bool {
    true
}

/// `guardian-lab train`: train the embedding network.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Dataset file (from `guardian-lab dataset`).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Training alphabets, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    pub train_alphabets: Vec<String>,
    /// Validation alphabets, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
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
    /// Margin of the loss.
    #[arg(long, default_value_t = 0.2)]
    pub margin: f64,
    /// Convolution channels per layer, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "64,128,128")]
    pub channels: Vec<usize>,
    /// Convolution kernel size.
    #[arg(long, default_value_t = 5)]
    pub kernel: usize,
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
    /// Omniglot stroke root the corrupted plans are made from (`--fault-share` only).
    #[arg(long, default_value = "../shared/omniglot/strokes")]
    pub strokes: PathBuf,
    /// Class augmentation: every training character rotated by 90°, 180°, 270° and
    /// mirrored (8 symmetries of the square) becomes a class of its own; transforms that
    /// map a character onto itself or onto another class are dropped.
    #[arg(long)]
    pub class_augment: bool,
    /// With `--class-augment`: a transformed character counts as an existing one when its
    /// template is as similar to it as this quantile of the split-half similarities.
    #[arg(long, default_value_t = 0.1)]
    pub symmetry_quantile: f64,
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
                embed_dim: guardian_models::embedder::EMBED_DIM,
                l2_normalize: !self.no_l2,
                reverse_average: self.reverse_average,
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
            class_augment: self.class_augment,
            symmetry_quantile: if self.class_augment {
                self.symmetry_quantile
            } else {
                0.0
            },
        }
    }
}

/// Training failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TrainError {
    /// A tensor operation failed.
    #[error("tensor operation: {0}")]
    Candle(#[from] candle_core::Error),
    /// The network's forward or backward pass failed.
    #[error("network: {0}")]
    Net(#[from] FastNetError),
    /// The configuration or data cannot be used.
    #[error("invalid training setup: {0}")]
    Setup(String),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// Saving the model failed.
    #[error("saving model: {0}")]
    Save(#[from] guardian_models::embedder::SaveModelError),
    /// Loading a checkpoint failed.
    #[error("loading checkpoint: {0}")]
    Load(#[from] guardian_models::embedder::LoadModelError),
    /// Evaluating failed.
    #[error("validation: {0}")]
    Eval(#[from] eval::EvalError),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One epoch's metrics (one JSONL line).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EpochMetrics {
    /// Epoch (1-based).
    pub epoch: usize,
    /// Mean training loss.
    pub train_loss: f64,
    /// Validation loss (fixed batches; for batch-all, the mean over all valid triplets).
    pub val_loss: f64,
    /// Validation 5-way-1-shot accuracy (fixed episodes).
    pub val_acc_5way1shot: f64,
    /// Learning rate used in this epoch.
    pub lr: f64,
    /// Fraction of active (non-zero) triplets or anchors in training.
    pub active_fraction: f64,
    /// Samples embedded per second in training (forward + backward).
    pub samples_per_s: f64,
    /// Mined triplets per second (one per anchor for batch-hard / triplet).
    pub triplets_per_s: f64,
    /// Wall-clock seconds of the epoch including validation.
    pub seconds: f64,
}

/// The resumable state (`state.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    epoch: usize,
    lr: f64,
    best_val_loss: f64,
    epochs_since_best: usize,
    epochs_since_lr_change: usize,
    adam_step: usize,
    train_seconds: f64,
    finished: bool,
}

/// What a finished run reports.
#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    /// Epochs run in total.
    pub epochs: usize,
    /// Best validation loss.
    pub best_val_loss: f64,
    /// Wall-clock seconds of training (all sessions of a resumed run).
    pub seconds: f64,
    /// Version of the best model.
    pub model_version: String,
    /// Why training stopped.
    pub stopped: String,
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

/// Labels of fault negatives in a batch count down from here (one label per corrupted
/// plan, so it is a negative of every genuine sample and the positive of none).
const FAULT_LABEL_TOP: u32 = u32::MAX;

/// One sample of a batch: a genuine drawing, or one of its corrupted plans.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Item {
    /// Sample `i` of the prepared set.
    Genuine(usize),
    /// Corrupted plan `v` of sample `i`.
    Fault(usize, usize),
}

/// The training data in the form the batch sampler needs.
pub struct Prepared {
    kind: FeatureKind,
    /// Pen paths (pen features) or raw inputs (joint features), per sample.
    pen: Vec<[PenPoint; STEPS]>,
    raw: Vec<Resampled>,
    /// Sample indices per class.
    by_class: Vec<Vec<usize>>,
    /// Class label per sample (dense, 0..by_class.len()).
    labels: Vec<u32>,
    /// Dataset index per sample.
    data_index: Vec<usize>,
    /// Pen paths of the corrupted plans of each sample (empty without fault negatives).
    faults: Vec<Vec<[PenPoint; STEPS]>>,
    /// Time reversal among the augmentations.
    reverse_augment: bool,
}

impl Prepared {
    /// Select the samples of `alphabets` from `data`.
    pub fn new(
        data: &Dataset,
        alphabets: &[String],
        kind: FeatureKind,
    ) -> Result<Self, TrainError> {
        let ids = data
            .alphabet_ids(alphabets)
            .map_err(|e| TrainError::Setup(e.to_string()))?;
        let mut class_map: BTreeMap<i64, usize> = BTreeMap::new();
        let mut by_class: Vec<Vec<usize>> = Vec::new();
        let mut raw = Vec::new();
        let mut labels = Vec::new();
        let mut data_index = Vec::new();
        for i in 0..data.len() {
            if !ids.contains(&data.alphabet_ids[i]) {
                continue;
            }
            let next = class_map.len();
            let c = *class_map.entry(data.labels[i]).or_insert(next);
            if c == by_class.len() {
                by_class.push(Vec::new());
            }
            by_class[c].push(raw.len());
            raw.push(data.trajectories[i]);
            labels.push(c as u32);
            data_index.push(i);
        }
        let pen = if kind != FeatureKind::Joints {
            // Pen paths by the forward kinematics of the robot that drew the data set.
            let robot = data.robot().map_err(|e| TrainError::Setup(e.to_string()))?;
            raw.iter()
                .map(|x| features::pen_path_with(&robot, x))
                .collect()
        } else if data.robot.joints != guardian_models::kinematics::PANDA_JOINTS {
            return Err(TrainError::Setup(format!(
                "joint features are for Panda data sets; this one was drawn by {}",
                data.robot
            )));
        } else {
            Vec::new()
        };
        let faults = vec![Vec::new(); raw.len()];
        Ok(Self {
            kind,
            pen,
            raw,
            by_class,
            labels,
            data_index,
            faults,
            reverse_augment: true,
        })
    }

    /// Make `variants` corrupted plans of every sample for fault-negative training: a random
    /// fault of `kinds` at a random severity in [0.25, 1], made on the drawing's
    /// Omniglot strokes (found under `strokes_root` by class and drawer) and re-solved
    /// through the dataset's IK, exactly as the evaluation's faulty plans are. Deterministic
    /// in `seed`. Returns how many were made (a drawing whose strokes are missing, or a
    /// corruption that cannot be solved, gets fewer).
    pub fn make_faults(
        &mut self,
        data: &Dataset,
        strokes_root: &Path,
        kinds: &[Fault],
        variants: usize,
        seed: u64,
    ) -> Result<usize, TrainError> {
        if kinds.is_empty() {
            return Err(TrainError::Setup(
                "no fault kinds to make negatives with".into(),
            ));
        }
        if self.kind == FeatureKind::Joints {
            return Err(TrainError::Setup(
                "fault negatives need pen features".into(),
            ));
        }
        let index = StrokeIndex::scan(&[strokes_root.to_path_buf()])
            .map_err(|e| TrainError::Setup(format!("fault negatives: {e}")))?;
        let solver = PathSolver::new(&data.geometry)
            .map_err(|e| TrainError::Setup(format!("fault negatives: {e}")))?;
        let made: Vec<Vec<[PenPoint; STEPS]>> = self
            .data_index
            .par_iter()
            .map(|&i| {
                let Some(st) = index.strokes_of(data, i) else {
                    return Vec::new();
                };
                let mut rng = StdRng::seed_from_u64(seed ^ (i as u64).wrapping_mul(0x9e37_79b9));
                let mut out = Vec::with_capacity(variants);
                let mut tries = 0;
                while out.len() < variants && tries < 4 * variants {
                    tries += 1;
                    let fault = kinds[rng.random_range(0..kinds.len())];
                    let severity = rng.random_range(0.25..=1.0);
                    if let Ok(x) = faults::corrupt(&solver, fault, severity, &st, &mut rng) {
                        out.push(features::pen_path_with(solver.robot(), &x));
                    }
                }
                out
            })
            .collect();
        self.faults = made;
        Ok(self.faults.iter().map(Vec::len).sum())
    }

    /// Class augmentation: add the transforms of every class that `plan` keeps as classes
    /// of their own (pen paths and corrupted plans transformed; same dataset indices).
    /// Call after [`Prepared::make_faults`]. Returns the plan.
    pub fn augment_classes(&mut self, rule: SymmetryRule) -> Result<AugmentPlan, TrainError> {
        if self.kind == FeatureKind::Joints {
            return Err(TrainError::Setup(
                "class augmentation needs pen features".into(),
            ));
        }
        let groups: Vec<Vec<&[PenPoint; STEPS]>> = self
            .by_class
            .iter()
            .map(|m| m.iter().map(|&i| &self.pen[i]).collect())
            .collect();
        let plan = classaug::plan(&groups, Dihedral::non_identity(), rule);
        for (c, kept) in plan.kept.iter().enumerate() {
            for &d in kept {
                let label = self.by_class.len() as u32;
                let mut members = Vec::with_capacity(self.by_class[c].len());
                for &i in &self.by_class[c].clone() {
                    let mut p = self.pen[i];
                    d.apply(&mut p);
                    let mut f = self.faults[i].clone();
                    f.iter_mut().for_each(|x| d.apply(x));
                    members.push(self.raw.len());
                    self.pen.push(p);
                    self.raw.push(self.raw[i]);
                    self.faults.push(f);
                    self.labels.push(label);
                    self.data_index.push(self.data_index[i]);
                }
                self.by_class.push(members);
            }
        }
        Ok(plan)
    }

    /// The source class of every item: `Some(class label)` for a corrupted plan, `None`
    /// for a genuine sample (the `sources` of `loss::fault_triplet_loss`).
    pub fn sources(&self, items: &[Item]) -> Vec<Option<u32>> {
        items
            .iter()
            .map(|it| match *it {
                Item::Genuine(_) => None,
                Item::Fault(i, _) => Some(self.labels[i]),
            })
            .collect()
    }

    /// Number of corrupted plans of sample `i` (0 without fault negatives).
    pub fn faults_of(&self, i: usize) -> usize {
        self.faults.get(i).map_or(0, Vec::len)
    }

    /// The batch `idx` / `labels` with fault negatives added: each sample that has
    /// corrupted plans brings one at random with probability `share`, labelled as a class
    /// of its own. Draws nothing from `rng` when `share` is 0.
    pub fn with_faults(
        &self,
        idx: &[usize],
        labels: &[u32],
        share: f64,
        rng: &mut StdRng,
    ) -> (Vec<Item>, Vec<u32>) {
        let mut items: Vec<Item> = idx.iter().map(|&i| Item::Genuine(i)).collect();
        let mut out = labels.to_vec();
        if share > 0.0 {
            let mut next = FAULT_LABEL_TOP;
            for &i in idx {
                let n = self.faults[i].len();
                if n > 0 && rng.random_bool(share.min(1.0)) {
                    items.push(Item::Fault(i, rng.random_range(0..n)));
                    out.push(next);
                    next -= 1;
                }
            }
        }
        (items, out)
    }

    /// Allow or forbid time reversal among the augmentations (allowed by default).
    pub fn set_reverse_augment(&mut self, on: bool) {
        self.reverse_augment = on;
    }

    /// Number of classes.
    pub fn classes(&self) -> usize {
        self.by_class.len()
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.raw.len()
    }

    /// True if there are no samples.
    pub fn is_empty(&self) -> bool {
        self.raw.is_empty()
    }

    /// Feature tensor `[B, steps, F]` (see [`FeatureKind::steps`]) of samples `idx`, augmented when `rng` is given.
    pub fn batch(&self, idx: &[usize], rng: Option<&mut StdRng>) -> candle_core::Result<Tensor> {
        let items: Vec<Item> = idx.iter().map(|&i| Item::Genuine(i)).collect();
        self.batch_items(&items, rng)
    }

    /// Feature tensor `[B, STEPS, F]` of genuine and corrupted samples, augmented when
    /// `rng` is given.
    pub fn batch_items(
        &self,
        items: &[Item],
        mut rng: Option<&mut StdRng>,
    ) -> candle_core::Result<Tensor> {
        let (steps, c) = (self.kind.steps(), self.kind.channels());
        let mut buf = vec![0.0f32; items.len() * steps * c];
        for (&item, out) in items.iter().zip(buf.chunks_exact_mut(steps * c)) {
            let path = match item {
                Item::Genuine(i) if self.kind == FeatureKind::Joints => {
                    features::compute(self.kind, &self.raw[i], out);
                    continue;
                }
                Item::Genuine(i) => self.pen.get(i),
                Item::Fault(i, v) => self.faults.get(i).and_then(|f| f.get(v)),
            };
            let Some(path) = path else {
                candle_core::bail!("batch item {item:?} is not in the prepared set");
            };
            let aug = match rng.as_deref_mut() {
                Some(r) => random_augment(r, self.reverse_augment),
                None => Augment::default(),
            };
            features::path_features(self.kind, path, &aug, out);
        }
        Tensor::from_vec(buf, (items.len(), steps, c), &Device::Cpu)
    }

    /// A class-balanced batch: `p` classes, `k` samples each (fewer if a class is small).
    pub fn sample_pk(&self, p: usize, k: usize, rng: &mut StdRng) -> (Vec<usize>, Vec<u32>) {
        let mut classes: Vec<usize> = (0..self.by_class.len()).collect();
        classes.shuffle(rng);
        classes.truncate(p);
        let mut idx = Vec::with_capacity(p * k);
        let mut labels = Vec::with_capacity(p * k);
        for &c in &classes {
            let mut members = self.by_class[c].clone();
            members.shuffle(rng);
            for &m in members.iter().take(k) {
                idx.push(m);
                labels.push(self.labels[m]);
            }
        }
        (idx, labels)
    }

    /// The raw inputs.
    pub fn raw(&self) -> &[Resampled] {
        &self.raw
    }

    /// The pen path of every sample (empty for joint features).
    pub fn pen_paths(&self) -> &[[PenPoint; STEPS]] {
        &self.pen
    }

    /// Dense class label per sample.
    pub fn labels(&self) -> &[u32] {
        &self.labels
    }

    /// The data set index of every sample (a transform's source drawing).
    pub fn data_indices(&self) -> &[usize] {
        &self.data_index
    }
}

/// Random augmentation; with `reverse` false the draw for time reversal is made and
/// ignored, so the other augmentations are the same as with it.
fn random_augment(rng: &mut StdRng, reverse: bool) -> Augment {
    Augment {
        rotation: rng.random_range(-0.2..0.2),
        shear: rng.random_range(-0.2..0.2),
        scale_x: rng.random_range(0.85..1.15),
        scale_y: rng.random_range(0.85..1.15),
        reverse: rng.random_bool(0.5) && reverse,
    }
}

/// The loss of one batch of embeddings `e [B, embed_dim]`. Returns `(loss, active
/// fraction, mined triplets)`.
pub fn batch_loss(
    e: &Tensor,
    labels: &[u32],
    kind: LossKind,
    margin: f64,
    rng: &mut StdRng,
) -> candle_core::Result<(Tensor, f32, usize)> {
    embedding_loss(e, labels, kind, margin, rng)
}

/// The training objective of one batch of embeddings `e [B, embed_dim]` of items: the main
/// loss of `cfg`, plus the fault-negative term (weighted) when the batch has corrupted
/// plans. Returns `(loss to optimise, validation-comparable loss, active fraction, mined
/// triplets)`; the validation-comparable loss takes batch-all's mean over all valid
/// triplets rather than over the active ones (which stays flat as fewer triplets stay
/// active), for both terms.
pub fn objective(
    e: &Tensor,
    labels: &[u32],
    sources: &[Option<u32>],
    cfg: &TrainConfig,
    rng: &mut StdRng,
) -> candle_core::Result<(Tensor, f64, f32, usize)> {
    let (l, active, n) = embedding_loss(e, labels, cfg.loss, cfg.margin, rng)?;
    let lv = f64::from(l.to_scalar::<f32>()?);
    let mut comparable = if cfg.loss == LossKind::BatchAll {
        lv * f64::from(active)
    } else {
        lv
    };
    let mut total = l;
    if cfg.fault_weight > 0.0 && sources.iter().any(Option::is_some) {
        let (lf, af, _) = loss::fault_triplet_loss(e, labels, sources, cfg.fault_margin)?;
        comparable += cfg.fault_weight * f64::from(lf.to_scalar::<f32>()?) * f64::from(af);
        total = (total + (lf * cfg.fault_weight)?)?;
    }
    Ok((total, comparable, active, n))
}

/// Embeddings `[B, embed_dim]` of a feature batch `x [B, STEPS, F]` (no gradient).
pub fn embed(net: &FastNet, x: &Tensor) -> Result<Tensor, TrainError> {
    let (b, l, _) = x.dims3()?;
    let flat = x.flatten_all()?.to_vec1::<f32>()?;
    let e = net.config().embed_dim;
    let mut out = vec![0.0f32; b * e];
    net.forward(&flat, b, l, &mut Default::default(), &mut out)?;
    Ok(Tensor::from_vec(out, (b, e), &Device::Cpu)?)
}

fn embedding_loss(
    e: &Tensor,
    labels: &[u32],
    kind: LossKind,
    margin: f64,
    rng: &mut StdRng,
) -> candle_core::Result<(Tensor, f32, usize)> {
    match kind {
        LossKind::BatchAll => {
            let (l, a) = loss::batch_all_triplet_loss(e, labels, margin)?;
            let n = labels.len();
            let mut valid = 0;
            for i in 0..n {
                let pos = labels
                    .iter()
                    .enumerate()
                    .filter(|&(j, &l)| j != i && l == labels[i])
                    .count();
                valid += pos * labels.iter().filter(|&&l| l != labels[i]).count();
            }
            Ok((l, a, valid))
        }
        LossKind::Triplet => {
            // One random (positive, negative) per anchor.
            let n = labels.len();
            let (mut ai, mut pi, mut ni) = (Vec::new(), Vec::new(), Vec::new());
            for a in 0..n {
                let pos: Vec<u32> = (0..n as u32)
                    .filter(|&j| j as usize != a && labels[j as usize] == labels[a])
                    .collect();
                let neg: Vec<u32> = (0..n as u32)
                    .filter(|&j| labels[j as usize] != labels[a])
                    .collect();
                if let (Some(&p), Some(&q)) = (pos.choose(rng), neg.choose(rng)) {
                    ai.push(a as u32);
                    pi.push(p);
                    ni.push(q);
                }
            }
            let m = ai.len();
            let sel = |v: Vec<u32>| -> candle_core::Result<Tensor> {
                e.index_select(&Tensor::from_vec(v, m, &Device::Cpu)?, 0)
            };
            let (a, p, q) = (sel(ai)?, sel(pi)?, sel(ni)?);
            let l = loss::triplet_loss(&a, &p, &q, margin)?;
            let dp = (&a - &p)?.sqr()?.sum(1)?;
            let dn = (&a - &q)?.sqr()?.sum(1)?;
            let act = ((dp - dn)? + margin)?.relu()?.to_vec1::<f32>()?;
            let frac = act.iter().filter(|&&v| v > 0.0).count() as f32 / m.max(1) as f32;
            Ok((l, frac, m))
        }
        LossKind::Contrastive => {
            let l = loss::contrastive_loss(e, labels, margin)?;
            let n = labels.len();
            Ok((l, 1.0, n * (n - 1) / 2))
        }
    }
}

/// AdamW with decoupled weight decay whose moments can be saved (for exact `--resume`),
/// over the flat parameters of a [`FastNet`].
pub struct AdamW {
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    step: usize,
    weight_decay: f64,
}

impl AdamW {
    /// Fresh optimiser for the parameters of `net`.
    pub fn new(net: &FastNet, weight_decay: f64) -> Self {
        let m: Vec<Vec<f32>> = net.params().iter().map(|p| vec![0.0; p.len()]).collect();
        Self {
            v: m.clone(),
            m,
            step: 0,
            weight_decay,
        }
    }

    /// One update of `params` (in [`NetConfig::param_shapes`] order) along `grads` with
    /// learning rate `lr`.
    pub fn step(&mut self, params: Vec<&mut [f32]>, grads: &Grads, lr: f64) {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8f32);
        self.step += 1;
        let c1 = (1.0 / (1.0 - f64::powi(b1, self.step as i32))) as f32;
        let c2 = (1.0 / (1.0 - f64::powi(b2, self.step as i32))) as f32;
        let (b1, b2) = (b1 as f32, b2 as f32);
        let (lr, decay) = (lr as f32, (1.0 - lr * self.weight_decay) as f32);
        for (((theta, g), m), v) in params
            .into_iter()
            .zip(grads.params())
            .zip(&mut self.m)
            .zip(&mut self.v)
        {
            for (((t, g), m), v) in theta.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *m = *m * b1 + g * (1.0 - b1);
                *v = *v * b2 + g * g * (1.0 - b2);
                let upd = (*m * c1) / ((*v * c2).sqrt() + eps);
                *t = *t * decay - upd * lr;
            }
        }
    }
}

/// A network in training: the fast path's weights with a workspace per thread
/// ([`Trainable`]) and its optimiser. One [`Learner::step`] embeds a batch, takes the loss of
/// the embeddings with candle's autograd, backpropagates through the network by hand and
/// updates the weights.
pub struct Learner {
    model: Trainable,
    opt: AdamW,
    emb: Vec<f32>,
}

impl Learner {
    /// Train `net` with AdamW (`weight_decay`), on as many threads as rayon has.
    pub fn new(net: FastNet, weight_decay: f64) -> Self {
        Self {
            opt: AdamW::new(&net, weight_decay),
            model: Trainable::new(net),
            emb: Vec::new(),
        }
    }

    /// The network with its current weights.
    pub fn net(&self) -> &FastNet {
        self.model.net()
    }

    /// The gradients of `loss` on the embeddings of `x [B, STEPS, F]`, without updating
    /// anything. Returns the gradients, the loss and what `loss` returned besides it.
    pub fn gradients<R>(
        &mut self,
        x: &Tensor,
        loss: impl FnOnce(&Tensor) -> candle_core::Result<(Tensor, R)>,
    ) -> Result<(&Grads, f32, R), TrainError> {
        let (b, l, _) = x.dims3()?;
        let flat = x.flatten_all()?.to_vec1::<f32>()?;
        let e = self.model.net().config().embed_dim;
        self.emb.resize(b * e, 0.0);
        self.model.forward(&flat, b, l, &mut self.emb)?;
        let emb = Var::from_slice(&self.emb, (b, e), &Device::Cpu)?;
        let (value, extra) = loss(emb.as_tensor())?;
        let store = value.backward()?;
        let d_out = match store.get(emb.as_tensor()) {
            Some(g) => g.flatten_all()?.to_vec1::<f32>()?,
            // The loss does not depend on the embeddings (no valid triplet): zero gradient.
            None => vec![0.0; b * e],
        };
        let value = value.to_scalar::<f32>()?;
        Ok((self.model.backward(&d_out)?, value, extra))
    }

    /// One training step on `x` with learning rate `lr`: gradients of `loss` (see
    /// [`Learner::gradients`]) and one AdamW update. Returns the loss and `loss`'s extra.
    pub fn step<R>(
        &mut self,
        x: &Tensor,
        lr: f64,
        loss: impl FnOnce(&Tensor) -> candle_core::Result<(Tensor, R)>,
    ) -> Result<(f32, R), TrainError> {
        let (_, value, extra) = self.gradients(x, loss)?;
        let (params, grads) = self.model.params_and_grads();
        self.opt.step(params, grads, lr);
        Ok((value, extra))
    }
}

/// Train as configured, writing into `out`. With `resume`, continue from the checkpoint
/// there (the configuration must match). `strokes` is the Omniglot stroke root the fault
/// negatives are made from (needed only when `cfg.fault_share > 0`).
pub fn train(
    data: &Dataset,
    cfg: &TrainConfig,
    strokes: Option<&Path>,
    out: &Path,
    resume: bool,
    quiet: bool,
) -> Result<TrainSummary, TrainError> {
    cfg.net
        .check()
        .map_err(|e| TrainError::Setup(format!("network config: {e}")))?;
    if cfg.p_classes < 2 || cfg.k_samples < 2 {
        return Err(TrainError::Setup(
            "need p-classes >= 2 and k-samples >= 2".into(),
        ));
    }
    for a in &cfg.val_alphabets {
        if cfg.train_alphabets.contains(a) {
            return Err(TrainError::Setup(format!(
                "alphabet {a} is in both train and val"
            )));
        }
    }
    if !(0.0..=1.0).contains(&cfg.fault_share) || (cfg.fault_share > 0.0 && cfg.fault_variants == 0)
    {
        return Err(TrainError::Setup(format!(
            "fault share {} must be in [0, 1], with at least one variant",
            cfg.fault_share
        )));
    }
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    let mut train_set = Prepared::new(data, &cfg.train_alphabets, cfg.net.features)?;
    train_set.set_reverse_augment(cfg.reverse_augment);
    let mut val_set = Prepared::new(data, &cfg.val_alphabets, cfg.net.features)?;
    if cfg.fault_share > 0.0 {
        let root = strokes.ok_or_else(|| {
            TrainError::Setup("fault negatives need the Omniglot stroke root".into())
        })?;
        let t0 = Instant::now();
        let kinds = &cfg.fault_kinds;
        let n_train = train_set.make_faults(data, root, kinds, cfg.fault_variants, cfg.seed)?;
        let n_val =
            val_set.make_faults(data, root, kinds, cfg.fault_variants, cfg.seed ^ 0x7a11)?;
        if n_train == 0 {
            return Err(TrainError::Setup(format!(
                "no fault negatives could be made from {}",
                root.display()
            )));
        }
        if !quiet {
            eprintln!(
                "fault negatives: {n_train} training and {n_val} validation plans solved in {:.1} s",
                t0.elapsed().as_secs_f64()
            );
        }
    }
    if cfg.class_augment {
        let plan = train_set.augment_classes(SymmetryRule {
            quantile: cfg.symmetry_quantile,
        })?;
        let dropped = plan.self_symmetric + plan.collides;
        if !quiet {
            eprintln!(
                "class augmentation: {} new classes ({} in all); {dropped} transforms dropped \
                 ({} map a character onto itself, {} onto another class; threshold {:.3}, \
                 {} of {} pairs of original classes at or above it)",
                plan.new_classes(),
                train_set.classes(),
                plan.self_symmetric,
                plan.collides,
                plan.threshold,
                plan.original_pairs_above,
                plan.original_pairs
            );
        }
        write_json(&out.join("class-augment.json"), &plan)?;
    }
    if train_set.classes() < cfg.p_classes.min(2) || val_set.classes() < 5 {
        return Err(TrainError::Setup(format!(
            "too few classes: train {}, val {} (val needs >= 5)",
            train_set.classes(),
            val_set.classes()
        )));
    }

    let config_path = out.join("train-config.json");
    let state_path = out.join("state.json");
    let last_path = out.join("last.safetensors");
    let opt_path = out.join("optimizer.safetensors");
    let best_path = out.join("model.safetensors");
    let metrics_path = out.join("metrics.jsonl");

    let (net, mut state, opt_state) = if resume {
        let saved: TrainConfig = read_json(&config_path)?;
        let mut comparable = TrainConfig {
            max_epochs: cfg.max_epochs,
            ..saved.clone()
        };
        comparable.net.reverse_average = cfg.net.reverse_average;
        if &comparable != cfg {
            return Err(TrainError::Setup(format!(
                "--resume: {} differs from this run's configuration",
                config_path.display()
            )));
        }
        let mut state: State = read_json(&state_path)?;
        // A resumed run may extend the epoch budget.
        if state.finished
            && state.epoch < cfg.max_epochs
            && state.epochs_since_best < cfg.early_stop_patience
        {
            state.finished = false;
        }
        write_json(&config_path, cfg)?;
        let last = Embedder::load(&last_path)?;
        let opt = load_opt(&opt_path)?;
        let params = last.fast().params().iter().map(|p| p.to_vec()).collect();
        (
            FastNet::from_params(cfg.net.clone(), params)?,
            state,
            Some(opt),
        )
    } else {
        write_json(&config_path, cfg)?;
        let _ = std::fs::remove_file(&metrics_path);
        let net = FastNet::random(cfg.net.clone(), cfg.seed)?;
        let state = State {
            epoch: 0,
            lr: cfg.lr,
            best_val_loss: f64::INFINITY,
            epochs_since_best: 0,
            epochs_since_lr_change: 0,
            adam_step: 0,
            train_seconds: 0.0,
            finished: false,
        };
        (net, state, None)
    };
    if state.finished {
        let mut best = Embedder::load(&best_path)?;
        if best.config().reverse_average != cfg.net.reverse_average {
            best.set_reverse_average(cfg.net.reverse_average);
            best.save(&best_path)?;
        }
        return Ok(TrainSummary {
            epochs: state.epoch,
            best_val_loss: state.best_val_loss,
            seconds: state.train_seconds,
            model_version: best.version().to_string(),
            stopped: "already finished".into(),
        });
    }
    let mut learner = Learner::new(net, cfg.weight_decay);
    if let Some((m, v)) = opt_state {
        let opt = &mut learner.opt;
        let shapes_match = |saved: &[Vec<f32>], own: &[Vec<f32>]| {
            saved.len() == own.len() && saved.iter().zip(own).all(|(a, b)| a.len() == b.len())
        };
        if !shapes_match(&m, &opt.m) || !shapes_match(&v, &opt.v) {
            return Err(TrainError::Setup(
                "optimizer checkpoint does not match".into(),
            ));
        }
        opt.m = m;
        opt.v = v;
        opt.step = state.adam_step;
    }

    // Fixed validation batches and episodes.
    let mut vrng = StdRng::seed_from_u64(cfg.seed ^ 0x005e_ed0f_7a11);
    let val_batches: Vec<(Vec<Item>, Vec<u32>)> = (0..10)
        .map(|_| {
            let (idx, labels) = val_set.sample_pk(cfg.p_classes, cfg.k_samples, &mut vrng);
            val_set.with_faults(&idx, &labels, cfg.fault_share, &mut vrng)
        })
        .collect();
    let val_labels: Vec<u32> = val_set.labels().to_vec();
    let val_spec = EpisodeSpec {
        way: 5,
        shot: 1,
        episodes: cfg.val_episodes,
        seed: cfg.seed,
    };

    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new((cfg.max_epochs * cfg.steps_per_epoch) as u64)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} steps ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar.set_position((state.epoch * cfg.steps_per_epoch) as u64);

    let mut metrics_file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&metrics_path)
        .map_err(io_err(&metrics_path))?;
    let mut stopped = "max epochs".to_string();
    while state.epoch < cfg.max_epochs {
        let epoch = state.epoch + 1;
        let t0 = Instant::now();
        // Per-epoch RNG: a resumed run draws the same batches as an uninterrupted one.
        let mut rng =
            StdRng::seed_from_u64(cfg.seed.wrapping_mul(1_000_003).wrapping_add(epoch as u64));
        let (mut loss_sum, mut active_sum, mut samples, mut triplets) = (0.0, 0.0, 0usize, 0usize);
        let total_steps = cfg.max_epochs * cfg.steps_per_epoch;
        for step in 0..cfg.steps_per_epoch {
            if cfg.schedule == Schedule::OneCycle {
                state.lr = one_cycle_lr(
                    cfg.lr,
                    state.epoch * cfg.steps_per_epoch + step,
                    total_steps,
                );
            }
            let (idx, labels) = train_set.sample_pk(cfg.p_classes, cfg.k_samples, &mut rng);
            let (items, labels) = train_set.with_faults(&idx, &labels, cfg.fault_share, &mut rng);
            let x = train_set.batch_items(&items, cfg.augment.then_some(&mut rng))?;
            let sources = train_set.sources(&items);
            let (l, (active, n_trip)) = learner.step(&x, state.lr, |e| {
                let (l, _, active, n) = objective(e, &labels, &sources, cfg, &mut rng)?;
                Ok((l, (active, n)))
            })?;
            loss_sum += f64::from(l);
            active_sum += f64::from(active);
            samples += items.len();
            triplets += n_trip;
            bar.inc(1);
        }
        let train_secs = t0.elapsed().as_secs_f64();
        let train_loss = loss_sum / cfg.steps_per_epoch as f64;

        // Validation.
        let mut val_loss = 0.0;
        let mut dummy = StdRng::seed_from_u64(0);
        for (items, labels) in &val_batches {
            let x = val_set.batch_items(items, None)?;
            let sources = val_set.sources(items);
            let e = embed(learner.net(), &x)?;
            val_loss += objective(&e, labels, &sources, cfg, &mut dummy)?.1;
        }
        val_loss /= val_batches.len() as f64;
        let embs = embed_all(learner.net(), &val_set)?;
        let val_acc =
            eval::run_episodes(&val_labels, &val_spec, &mut eval::Scorer::Prototype(&embs))?
                .accuracy;

        let m = EpochMetrics {
            epoch,
            train_loss,
            val_loss,
            val_acc_5way1shot: val_acc,
            lr: state.lr,
            active_fraction: active_sum / cfg.steps_per_epoch as f64,
            samples_per_s: samples as f64 / train_secs,
            triplets_per_s: triplets as f64 / train_secs,
            seconds: t0.elapsed().as_secs_f64(),
        };
        let line = serde_json::to_string(&m).map_err(|e| TrainError::Setup(e.to_string()))?;
        writeln!(metrics_file, "{line}").map_err(io_err(&metrics_path))?;
        bar.set_message(format!(
            "epoch {epoch} train {train_loss:.4} val {val_loss:.4} acc5 {val_acc:.3} lr {:.1e}",
            state.lr
        ));
        if quiet {
            eprintln!("{line}");
        }

        // Best model, schedule, early stopping.
        let current = Embedder::from_trained(&learner.net().to_net()?)?;
        if cfg.schedule == Schedule::OneCycle {
            // A fixed schedule keeps its last model; validation is only logged.
            state.best_val_loss = state.best_val_loss.min(val_loss);
            current.save(&best_path)?;
        } else if val_loss < state.best_val_loss {
            state.best_val_loss = val_loss;
            state.epochs_since_best = 0;
            current.save(&best_path)?;
        } else {
            state.epochs_since_best += 1;
        }
        state.epochs_since_lr_change += 1;
        if cfg.schedule == Schedule::Plateau
            && state.epochs_since_best > 0
            && state.epochs_since_lr_change > cfg.plateau_patience
            && state.epochs_since_best > cfg.plateau_patience
        {
            state.lr = (state.lr * cfg.lr_factor).max(cfg.min_lr);
            state.epochs_since_lr_change = 0;
        }
        state.epoch = epoch;
        state.adam_step = learner.opt.step;
        state.train_seconds += t0.elapsed().as_secs_f64();
        let stop =
            cfg.schedule == Schedule::Plateau && state.epochs_since_best >= cfg.early_stop_patience;
        if stop {
            stopped = format!(
                "early stopping after {} epochs without improvement",
                state.epochs_since_best
            );
        }
        state.finished = stop || state.epoch >= cfg.max_epochs;
        current.save(&last_path)?;
        save_opt(&opt_path, &learner.opt)?;
        write_json(&state_path, &state)?;
        if stop {
            break;
        }
    }
    bar.finish_and_clear();
    let best = Embedder::load(&best_path)?;
    Ok(TrainSummary {
        epochs: state.epoch,
        best_val_loss: state.best_val_loss,
        seconds: state.train_seconds,
        model_version: best.version().to_string(),
        stopped,
    })
}

/// Embeddings of every sample of a prepared set (no augmentation), in order.
pub fn embed_all(net: &FastNet, set: &Prepared) -> Result<Vec<Vec<f32>>, TrainError> {
    let mut out = Vec::with_capacity(set.len());
    let idx: Vec<usize> = (0..set.len()).collect();
    for chunk in idx.chunks(256) {
        let x = set.batch(chunk, None)?;
        let e = embed(net, &x)?.to_vec2::<f32>()?;
        out.extend(e);
    }
    Ok(out)
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, TrainError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|e| TrainError::Setup(format!("{}: {e}", path.display())))
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), TrainError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| TrainError::Setup(e.to_string()))?;
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, text).map_err(io_err(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

fn save_opt(path: &Path, opt: &AdamW) -> Result<(), TrainError> {
    let mut map = std::collections::HashMap::new();
    for (i, (m, v)) in opt.m.iter().zip(&opt.v).enumerate() {
        map.insert(
            format!("m{i}"),
            Tensor::from_slice(m, m.len(), &Device::Cpu)?,
        );
        map.insert(
            format!("v{i}"),
            Tensor::from_slice(v, v.len(), &Device::Cpu)?,
        );
    }
    let tmp = path.with_extension("tmp");
    candle_core::safetensors::save(&map, &tmp)?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

type Moments = (Vec<Vec<f32>>, Vec<Vec<f32>>);

fn load_opt(path: &Path) -> Result<Moments, TrainError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let map = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)?;
    let n = map.len() / 2;
    let mut m = Vec::with_capacity(n);
    let mut v = Vec::with_capacity(n);
    for i in 0..n {
        let get = |k: String| -> Result<Vec<f32>, TrainError> {
            let t = map
                .get(&k)
                .ok_or_else(|| TrainError::Setup(format!("{}: missing {k}", path.display())))?;
            Ok(t.flatten_all()?.to_vec1::<f32>()?)
        };
        m.push(get(format!("m{i}"))?);
        v.push(get(format!("v{i}"))?);
    }
    Ok((m, v))
}

/// Run `guardian-lab train`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let data = Dataset::load(&args.dataset)?;
    let cfg = args.config();
    eprintln!(
        "training on {:?}, validating on {:?}; {} rayon threads",
        cfg.train_alphabets,
        cfg.val_alphabets,
        rayon::current_num_threads()
    );
    let summary = train(
        &data,
        &cfg,
        Some(&args.strokes),
        &args.out,
        args.resume,
        args.quiet,
    )?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
