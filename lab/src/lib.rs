//! guardian-lab: the research bench behind guardian — training of the embedding networks,
//! baselines, few-shot evaluation and reports, shipping a model and its bank. Laid out by role:
//!
//! - [`dataset`]: `guardian-lab dataset` (the data itself is `guardian_omniglot`'s).
//! - [`train`]: training of the embedding network (configuration, batches, class
//!   augmentation, objective, optimiser, schedule, checkpoints, the loop).
//! - [`eval`]: few-shot episodes and baselines, go / no-go on faulty plans, calibration,
//!   metrics, the report.
//! - [`tools`]: shipping — the default class bank, fusing trained networks into one file.
//! - [`cli`]: argument groups shared by the subcommands.
//!
//! Every subcommand's module owns its `Args` and a `run(&Args)`. The data is
//! `guardian_omniglot`'s; the demo and the plot are `examples/`, the robot description check
//! is `guardianctl robot`.
#![forbid(unsafe_code)]

pub mod cli;
pub mod dataset;
pub mod eval;
pub mod tools;
pub mod train;
