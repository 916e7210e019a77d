//! guardian-daemon: the library behind `guardiand`, the long-running go/no-go screen. It
//! receives candidate trajectories from planners over iceoryx2, embeds them with the shipped
//! model, compares them with the persisted class bank and answers go or no-go with reasons.
#![forbid(unsafe_code)]

pub mod admin;
pub mod config;
pub mod faults;
#[cfg(feature = "fleet")]
pub mod fleet;
pub mod http;
pub mod locator;
pub mod metrics;
pub mod notify;
pub mod record;
pub mod recovery;
pub mod screen;
pub mod serve;
pub mod state;
pub mod stats;
pub mod wakers;
pub mod web;

pub use config::{Config, ServingMode};
pub use serve::{Control, RunError, run};
