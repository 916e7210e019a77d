//! The sequence view's network: its serving forward ([`forward`], gemm over overlapping rows)
//! and, with the `train` feature, its backward ([`backward`]) side by side.

pub mod forward;

#[cfg(feature = "train")]
pub mod backward;
