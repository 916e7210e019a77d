//! guardian-gate: guardian in a ROS 2 / MoveIt 2 stack. The gate serves
//! `control_msgs/action/FollowJointTrajectory` at `<gate>/follow_joint_trajectory`, maps
//! each goal's joint trajectory to a guardian plan, asks guardiand (over iceoryx2, as any
//! planner) whether it is the claimed task (`<gate>/task`) or, with no claim, some enrolled
//! task, and forwards go goals unchanged to the real controller's action server, relaying
//! acceptance, feedback, result and cancel. Everything else is refused with `INVALID_GOAL`
//! (or `INVALID_JOINTS`) and never forwarded: it fails closed. Every verdict is published
//! on `<gate>/verdicts` (`guardian_msgs/msg/Verdict`), health on `/diagnostics`.
//!
//! Without the `node` feature the crate is the messages ([`msgs`]), their CDR encoding
//! ([`cdr`]), the goal → plan mapping ([`plan`]) and rosbag2 reading ([`bag`]), which
//! `guardianctl --bag` uses.
// Denied, not forbidden: `sockets::borrow` is the one exception (see there).
#![deny(unsafe_code)]
#![warn(missing_docs)]

pub mod bag;
pub mod cdr;
pub mod config;
pub mod msgs;
pub mod plan;

#[cfg(feature = "node")]
pub mod claim;
#[cfg(feature = "node")]
pub mod guardiand;
#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod sockets;
