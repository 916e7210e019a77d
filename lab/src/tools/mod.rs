//! Tools around the screen: the shipped default class bank ([`bank`], `guardian-lab bank`),
//! the go / no-go demo against a running `guardiand` ([`demo`]), a drawing's plot
//! ([`plot`]), a robot description's kinematics check ([`robot`]) and the fusing of trained
//! networks into one model file ([`fuse`]).

pub mod bank;
pub mod demo;
pub mod fuse;
pub mod plot;
pub mod robot;
