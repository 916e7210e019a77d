//! Training of the embedding network: class-balanced P x K batches from the training
//! alphabets, feature-level augmentation, a triplet (or, for the Siamese baseline, a
//! contrastive) loss with fault negatives, AdamW, ReduceLROnPlateau and early stopping on the
//! validation loss (or a fixed one-cycle schedule), fixed seeds, a JSONL metrics log,
//! checkpoints and `--resume`. By concern:
//!
//! - [`config`]: the command line and the [`TrainConfig`] it describes;
//! - [`batches`]: the prepared data, P x K batches, fault negatives, augmentation;
//! - [`classaug`]: class augmentation (rotated and mirrored characters as classes);
//! - [`objective`]: the loss of a batch;
//! - [`optim`]: AdamW and one training step ([`Learner`]);
//! - [`schedule`]: the learning-rate schedule and early stopping;
//! - [`checkpoint`]: the resumable state and the optimiser's moments on disk;
//! - [`trainer`]: the loop ([`train`]) and `guardian-lab train` ([`run`]).
//!
//! Output directory:
//! - `model.safetensors` — the best weights by validation loss (an
//!   [`Embedder`](guardian_models::embedder::Embedder) file);
//! - `last.safetensors`, `optimizer.safetensors`, `state.json` — the resumable checkpoint;
//! - `metrics.jsonl` — one line per epoch; `train-config.json` — the full configuration.

use std::path::{Path, PathBuf};

use guardian_models::sequence::forward::FastNetError;

pub mod batches;
pub mod checkpoint;
pub mod classaug;
pub mod config;
pub mod objective;
pub mod optim;
pub mod schedule;
pub mod trainer;

pub use batches::{Item, Prepared};
pub use config::{Args, FeatureArg, LossKind, Schedule, TRAIN_FAULTS, TrainConfig};
pub use objective::{batch_loss, objective};
pub use optim::{AdamW, Learner, Proxies};
pub use schedule::one_cycle_lr;
pub use trainer::{EpochMetrics, TrainSummary, embed, embed_all, run, train};

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
    Eval(#[from] crate::eval::EvalError),
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}
