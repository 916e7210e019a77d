//! The data: Omniglot drawings ([`strokes`]), the canvas and the IK along the pen path
//! ([`path`]), the dataset file and its generation ([`dataset`], `guardian-lab dataset`),
//! and corruptions of a genuine plan ([`faults`]).

pub mod dataset;
pub mod faults;
pub mod path;
pub mod strokes;
