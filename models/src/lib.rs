//! guardian-models: the embedding networks behind guardian.
//!
//! A plan's tool path (`guardian_robot::pen`) is seen in two views, a time sequence of pen
//! features and a picture of the pen-down path ([`features`]); each has a CNN trained with a
//! metric loss, and a fused model concatenates their embeddings ([`embedder`]: the model
//! file, fusion, embedding). One module per view holds its network's forward and, with the
//! `train` feature, its backward side by side: [`sequence`] (gemm over overlapping rows) and
//! [`picture`]; [`net`] is the architecture and its candle reference, [`loss`] the losses. Shipped artifacts (weights, default class bank,
//! `robots/`, model card) live in this crate's folder.
// `deny`, not `forbid`: `sequence::forward::gemm_strided` allows its single bounds-checked call into `gemm`.
#![deny(unsafe_code)]

pub mod embedder;
pub mod features;
#[cfg(feature = "train")]
pub mod loss;
pub mod net;
pub mod picture;
pub mod sequence;
