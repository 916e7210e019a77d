//! guardian-models: the embedding networks behind guardian.
//!
//! A plan's tool path (`guardian_robot::pen`) is seen in two views, a time sequence of pen
//! features and a picture of the pen-down path ([`features`]); each has a CNN trained with a
//! metric loss, and a fused model concatenates their embeddings ([`embedder`]: the model
//! file, fusion, embedding). [`fast`] is the serving forward of the sequence network (gemm
//! over overlapping rows), [`picture`] the picture network's, and, with the `train` feature,
//! [`grad`] and the picture module's backward train them; [`net`] is the architecture and its
//! candle reference, [`loss`] the losses. Shipped artifacts (weights, default class bank,
//! `robots/`, model card) live in this crate's folder.
// `deny`, not `forbid`: `fast::gemm_strided` allows its single bounds-checked call into `gemm`.
#![deny(unsafe_code)]

pub mod embedder;
pub mod fast;
pub mod features;
#[cfg(feature = "train")]
pub mod grad;
#[cfg(feature = "train")]
pub mod loss;
pub mod net;
pub mod picture;
