//! guardian-lab: the research bench behind guardian — Omniglot strokes to Panda joint
//! trajectories, training of the embedding network, baselines, few-shot evaluation and reports.
//!
//! - [`strokes`]: the Omniglot stroke reader.
//! - [`path`]: canvas geometry, the Cartesian pen path and IK along it.
//! - [`dataset`]: dataset generation and the safetensors file ([`dataset::Dataset`]).
//! - [`plot`]: a drawing, its FK-reconstructed pen tip and its joint curves as a PNG.
#![forbid(unsafe_code)]

pub mod dataset;
pub mod path;
pub mod plot;
pub mod strokes;
