//! guardian-omniglot: the data guardian learns and is measured on — Omniglot drawings made
//! into joint plans of a robot arm.
//!
//! - [`strokes`]: the Omniglot stroke reader (the official `<Alphabet>/characterNN/` layout).
//! - [`path`]: the canvas, the Cartesian pen path of a drawing and the IK along it.
//! - [`dataset`]: the dataset file and its generation (a drawing → a resampled plan).
//! - [`corrupt`]: corruptions of a genuine plan (the faulty plans of the evaluation, the
//!   demo and training's fault negatives).
//!
//! Links the robot crate only: no network code.
#![forbid(unsafe_code)]

pub mod corrupt;
pub mod dataset;
pub mod path;
pub mod strokes;
