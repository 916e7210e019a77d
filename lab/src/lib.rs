//! guardian-lab: the research bench behind guardian — Omniglot strokes to joint trajectories
//! of a robot arm (the Panda by default, the UR5e or any described arm), training of the
//! embedding network, baselines, few-shot evaluation and reports. Laid out by role:
//!
//! - [`data`]: the Omniglot stroke reader, canvas geometry and IK along the pen path, the
//!   dataset file, faulty-plan generators.
//! - [`train`]: training of the embedding network (configuration, batches, class
//!   augmentation, objective, optimiser, schedule, checkpoints, the loop).
//! - [`eval`]: few-shot episodes and baselines, go / no-go on faulty plans, calibration,
//!   metrics, the report.
//! - [`tools`]: the default class bank, the demo against a running `guardiand`, plots, the
//!   robot description check.
//! - [`cli`]: argument groups shared by the subcommands.
//!
//! Every subcommand's module owns its `Args` and a `run(&Args)`.
#![forbid(unsafe_code)]

pub mod cli;
pub mod data;
pub mod eval;
pub mod tools;
pub mod train;

// Used by other crates of the workspace (guardian-tests): the stroke reader, the path
// solver and the dataset conversion.
pub use data::{dataset, path, strokes};
