//! guardian-tests: end-to-end tests that run the real `guardiand` binary and real clients as
//! separate processes over iceoryx2 shared memory, fault injection, and the latency
//! benchmarks (`harness = false`).
#![forbid(unsafe_code)]

pub mod fleet;
pub mod harness;
