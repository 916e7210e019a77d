//! guardian-robot: the robot behind a plan, without any learned model.
//!
//! - [`kinematics`]: any serial arm from its URDF and a small description file (the Panda and
//!   the UR5e built in): forward kinematics, the Jacobian, a damped-least-squares IK.
//! - [`pen`]: the tool (pen) path of a resampled plan by forward kinematics.
//! - [`workcell`]: the one validation of a plan, its workcell rules on every waypoint and its
//!   resampling to the model's steps; [`preprocess`] is the same with the rules off.
//! - [`geometry`]: the plan geometry (position, size, strokes, direction) the screen compares
//!   with a class's enrolled examples.
//! - [`ink`]: where a plan's pen draws, point by point, and how far that is from an
//!   example's drawing (what a plan stopped early or drawn mirrored leaves out).
//! - [`place`]: where a plan happens (its tool path in the base frame), for cells whose tasks
//!   are anchored to their place; [`cell`]: a cell's rules (allowed and keep-out boxes).
//! - [`variant`]: near misses of a plan (stopped early, drawn mirrored) the screen compares
//!   a plan with.
//!
//! `guardianctl`, the ROS 2 gate and the data generator link this crate and no network code.
#![forbid(unsafe_code)]

pub mod cell;
pub mod geometry;
pub mod ink;
pub mod kinematics;
pub mod pen;
pub mod place;
pub mod preprocess;
pub mod variant;
pub mod workcell;
