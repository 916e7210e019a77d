//! Tools around the screen: the shipped default class bank ([`bank`], `guardian-lab bank`),
//! the go / no-go demo against a running `guardiand` ([`demo`]), a drawing's plot
//! ([`plot`]) and a robot description's kinematics check ([`robot`]).

pub mod bank;
pub mod demo;
pub mod plot;
pub mod robot;
