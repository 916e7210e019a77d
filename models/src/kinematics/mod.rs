//! Franka Emika Panda kinematics: the URDF parsed once into a [`Panda`] chain, forward
//! kinematics of the flange and the pen tip, the geometric Jacobian of the pen tip, and a
//! damped-least-squares inverse kinematics that stays continuous (seeded with the previous
//! solution) and inside the joint limits.
//!
//! Everything runs on nalgebra fixed-size types; nothing allocates. The chain is parsed from
//! `models/panda.urdf` with urdf-rs ([`Panda::from_urdf_str`]); [`Panda::default`] builds the
//! same chain from the published numbers without parsing (a test keeps both identical), so
//! the daemon needs no file at run time.
//!
//! Why a hand-written IK rather than the `k` crate: on these machines a damped-least-squares
//! solver on fixed-size matrices converts 1,800-3,600 Omniglot drawings/s per core while `k`
//! manages 220-460/s, and `k` 0.32 pins nalgebra 0.30 / urdf-rs 0.9 (two copies of nalgebra in
//! the workspace). See `docs/dataset.md` for the figures measured with this solver.
//!
//! One concern per file:
//! - this file: the chain's data ([`Panda`]: joint origins, limits, flange, tool), the
//!   published Panda numbers ([`Panda::default`]), the joint-space types and the re-exports;
//! - `frame.rs`: rigid transforms ([`Frame`]);
//! - `urdf.rs`: a serial chain read from a URDF ([`Panda::from_urdf_str`], [`UrdfLoadError`]);
//! - `fk.rs`: forward kinematics through the general chain (full frames), the source of
//!   truth, and the choice between it and the specialised position FK;
//! - `ik.rs`: the geometric Jacobian and the damped-least-squares IK;
//! - `simd.rs`: the pen-tip position FK specialised to a chain's numbers ([`PositionFk`],
//!   blocks of [`FK_LANES`] waypoints, runtime SIMD dispatch), checked against `fk.rs` when
//!   it is built.
//!
//! The seams for a robot read from any URDF: only [`Panda`]'s fixed-size arrays (and
//! [`JointVector`], [`Jacobian`]) pin the chain to [`JOINTS`] revolute joints; `urdf.rs`
//! walks any serial chain and checks the count in one place ([`UrdfLoadError::JointCount`]);
//! `fk.rs` and `ik.rs` loop over the chain's joints; `simd.rs` is derived from a built chain
//! and falls back to the general chain when it does not fit.

// Joint-indexed loops over several parallel arrays read best with an index.
#![allow(clippy::needless_range_loop)]

mod fk;
mod frame;
mod ik;
mod simd;
mod urdf;

use guardian_shared::trajectory::{JOINTS, Q_MAX, Q_MIN};
use nalgebra::SMatrix;

pub use frame::Frame;
pub use ik::{IkError, IkOptions, IkState};
pub use simd::{FK_LANES, Lanes, POSITION_FK_TOLERANCE, PoseLanes, PositionFk};
pub use urdf::{PANDA_URDF, UrdfLoadError};

/// Joint positions of the 7 revolute joints (rad).
pub type JointVector = [f64; JOINTS];

/// The geometric Jacobian of the pen tip: rows 0-2 linear velocity, rows 3-5 angular
/// velocity, both in the base frame; one column per joint.
pub type Jacobian = SMatrix<f64, 6, JOINTS>;

/// The Franka "ready" pose.
pub const READY_POSE: JointVector = [
    0.0,
    -std::f64::consts::FRAC_PI_4,
    0.0,
    -3.0 * std::f64::consts::FRAC_PI_4,
    0.0,
    std::f64::consts::FRAC_PI_2,
    std::f64::consts::FRAC_PI_4,
];

/// The Panda as a serial chain: 7 revolute joints about z, the fixed flange and the tool.
#[derive(Debug, Clone, PartialEq)]
pub struct Panda {
    /// Fixed origin of each revolute joint in its parent link.
    joints: [Frame; JOINTS],
    /// Flange (panda_link8) in panda_link7.
    flange: Frame,
    /// Tool (pen tip) in the flange frame.
    tool: Frame,
    q_min: JointVector,
    q_max: JointVector,
    /// The pen-tip position specialised to these joint origins, if they allow it.
    position_fk: Option<PositionFk>,
}

const HALF_PI: f64 = std::f64::consts::FRAC_PI_2;

/// Published joint origins (xyz, rpy), the same numbers as `panda.urdf`.
const ORIGINS: [([f64; 3], [f64; 3]); JOINTS] = [
    ([0.0, 0.0, 0.333], [0.0, 0.0, 0.0]),
    ([0.0, 0.0, 0.0], [-HALF_PI, 0.0, 0.0]),
    ([0.0, -0.316, 0.0], [HALF_PI, 0.0, 0.0]),
    ([0.0825, 0.0, 0.0], [HALF_PI, 0.0, 0.0]),
    ([-0.0825, 0.384, 0.0], [-HALF_PI, 0.0, 0.0]),
    ([0.0, 0.0, 0.0], [HALF_PI, 0.0, 0.0]),
    ([0.088, 0.0, 0.0], [HALF_PI, 0.0, 0.0]),
];

const FLANGE: ([f64; 3], [f64; 3]) = ([0.0, 0.0, 0.107], [0.0, 0.0, 0.0]);
/// Default pen: 0.15 m along flange z, rotated -pi/4 about z.
pub const PEN_LENGTH: f64 = 0.15;
/// Default pen yaw about the flange z axis (rad).
pub const PEN_YAW: f64 = -std::f64::consts::FRAC_PI_4;

impl Default for Panda {
    /// The published Panda with the default pen, built without parsing.
    fn default() -> Self {
        Self {
            joints: ORIGINS.map(|(xyz, rpy)| Frame::from_xyz_rpy(xyz, rpy)),
            flange: Frame::from_xyz_rpy(FLANGE.0, FLANGE.1),
            tool: Frame::from_xyz_rpy([0.0, 0.0, PEN_LENGTH], [0.0, 0.0, PEN_YAW]),
            q_min: Q_MIN,
            q_max: Q_MAX,
            position_fk: None,
        }
        .with_position_fk()
    }
}

impl Panda {
    /// Build (or drop) the specialised pen-tip position FK for the current numbers.
    fn with_position_fk(mut self) -> Self {
        self.position_fk = PositionFk::from_panda(&self);
        self
    }

    /// The specialised pen-tip position FK, if the joint origins allow it (they do for the
    /// Panda: every origin rotation is a signed axis permutation). `None` means every
    /// position goes through the general chain.
    pub fn position_fk(&self) -> Option<&PositionFk> {
        self.position_fk.as_ref()
    }

    /// The same robot with another tool: `length` along flange z, rotated `yaw` about it.
    pub fn with_tool(mut self, length: f64, yaw: f64) -> Self {
        self.tool = Frame::from_xyz_rpy([0.0, 0.0, length], [0.0, 0.0, yaw]);
        self.with_position_fk()
    }

    /// The tool (pen tip) frame in the flange frame.
    pub fn tool(&self) -> &Frame {
        &self.tool
    }

    /// Lower joint limits (rad).
    pub fn q_min(&self) -> &JointVector {
        &self.q_min
    }

    /// Upper joint limits (rad).
    pub fn q_max(&self) -> &JointVector {
        &self.q_max
    }

    /// Smallest distance of `q` to a joint limit (rad); negative if a limit is violated.
    pub fn limit_margin(&self, q: &JointVector) -> f64 {
        (0..JOINTS)
            .map(|j| (q[j] - self.q_min[j]).min(self.q_max[j] - q[j]))
            .fold(f64::INFINITY, f64::min)
    }
}
