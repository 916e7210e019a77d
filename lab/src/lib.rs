//! guardian-lab: the research bench behind guardian — Omniglot strokes to joint trajectories
//! of a robot arm (the Panda by default, the UR5e or any described arm), training of the embedding network, baselines, few-shot evaluation and reports.
//!
//! - [`strokes`]: the Omniglot stroke reader.
//! - [`path`]: canvas geometry, the Cartesian pen path and IK along it.
//! - [`dataset`]: dataset generation and the safetensors file ([`dataset::Dataset`]).
//! - [`plot`]: a drawing, its FK-reconstructed pen tip and its joint curves as a PNG.
//! - [`train`]: training of the embedding network (triplet, or contrastive for the Siamese
//!   baseline).
//! - [`eval`]: N-way K-shot episodes for the model and the baselines.
//! - [`report`]: the markdown + PNG report of a trained model.
//! - [`calibrate`]: threshold calibration and the default class bank.
//! - [`classaug`]: class augmentation (rotated and mirrored characters as classes).
//! - [`faults`]: faulty-plan generators (corruptions of a genuine plan).
//! - [`metrics`]: AUROC, ROC curve, TPR at an FPR and the pair AUC.
//! - [`outliers`]: go / no-go metrics on faulty and genuine plans.
//! - [`robot`]: print a robot description and check its kinematics (`guardian-lab robot`).
//! - [`demo`]: enroll real drawings in a running `guardiand` and check genuine and faulty
//!   plans through the client (`guardian-lab demo`).
#![forbid(unsafe_code)]

pub mod calibrate;
pub mod classaug;
pub mod dataset;
pub mod demo;
pub mod eval;
pub mod faults;
pub mod metrics;
pub mod outliers;
pub mod path;
pub mod plot;
pub mod report;
pub mod robot;
pub mod strokes;
pub mod train;
