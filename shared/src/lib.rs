//! guardian-shared: everything the daemon, the planner client and the lab must agree on.
//!
//! It holds the trajectory contract (the served robot's joint count and limits, validation
//! and the resampling to the model's fixed 128 steps), written once so that training data and served requests are
//! preprocessed by the same code. The iceoryx2 wire types and service names live here too,
//! so the thin client never depends on the model crates, and so does the one verdict type
//! ([`verdict`]) that the bank, the wire, the client and the daemon's observers share.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod ipc;
pub mod trajectory;
pub mod verdict;
pub mod wire;
pub mod workcell;
