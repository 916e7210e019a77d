//! guardian-fleet: fleet membership for `guardiand` over Zenoh. Signed change records
//! ([`record`]) replicate enrolls and forgets between members, which converge to the same
//! bank by a last-writer-wins order ([`store`]); a member answers remote check, identify and
//! status requests from authenticated callers ([`remote`]) on its own Zenoh queryable
//! ([`node`]). Keys ([`keys`]) and the `[fleet]` config table ([`config`]) complete it. The
//! daemon links this crate only with its `fleet` feature. See `docs/fleet.md`.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod ack;
pub mod config;
pub mod keys;
pub mod node;
pub mod record;
pub mod remote;
pub mod store;

pub use ed25519_dalek::{SigningKey, VerifyingKey};
