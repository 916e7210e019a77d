//! guardian-models: the learned and the physical models behind guardian.
//!
//! It holds the triplet-loss 1D-CNN that embeds a resampled joint trajectory (candle), its
//! losses, the inference fast path used by the daemon and its hand-written backward used by
//! training, the class-bank math (prototypes, thresholds, nearest-class search) and the
//! kinematics of any serial arm (URDF + robot description, forward kinematics, Jacobian,
//! inverse kinematics; the Panda and the UR5e built in). Shipped artifacts (weights, default
//! class bank, `robots/`, model card) live in this crate's folder.
// `deny`, not `forbid`: `fast::gemm_strided` allows its single bounds-checked call into `gemm`.
#![deny(unsafe_code)]

pub mod bank;
pub mod check;
pub mod embedder;
pub mod fast;
pub mod features;
pub mod geometry;
#[cfg(feature = "train")]
pub mod grad;
pub mod kinematics;
#[cfg(feature = "train")]
pub mod loss;
pub mod net;
pub mod picture;
pub mod preprocess;
pub mod workcell;
