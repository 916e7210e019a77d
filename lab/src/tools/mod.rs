//! Shipping a model: the default class bank ([`bank`], `guardian-lab bank`) and the fusing of
//! trained networks into one model file ([`fuse`], `guardian-lab fuse`).

pub mod bank;
pub mod fuse;
