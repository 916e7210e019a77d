//! guardian-screen: the whole check of a plan, without transport.
//!
//! - [`check`]: one check from the plan's joints to the bank's decision (workcell
//!   inspection, embedding with the tool path computed once, plan geometry, decision), for
//!   one plan or a micro-batch; identify and enroll through the same stages.
//! - [`reembed`]: a bank for a new model, its classes enrolled again through the same
//!   stages.
//!
//! The daemon decodes a request, hands it here and encodes what comes back; the lab and the
//! benches call the same functions, so serving and evaluation cannot disagree.
#![forbid(unsafe_code)]

pub mod check;
pub mod reembed;
