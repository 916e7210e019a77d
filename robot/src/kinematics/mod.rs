//! Serial-arm kinematics: a [`Robot`] read from a URDF (urdf-rs) and a small description
//! file ([`RobotDescription`]), forward kinematics of the flange and the pen tip (tool
//! frame), the geometric Jacobian of the tool, and a damped-least-squares inverse kinematics
//! that stays continuous (seeded with the previous solution) and inside the joint limits.
//!
//! A robot is a serial chain of 1 to [`MAX_JOINTS`] revolute or prismatic joints about any
//! axis, fixed joints composed into the next origin. Joint vectors have a fixed capacity
//! ([`JointVector`], slots past the robot's joints are 0), so nothing allocates per
//! waypoint. Two robots are built in ([`RobotDescription::named`]): the Franka Emika Panda
//! (`models/robots/panda.*`, the published numbers of `shared/GUIDE.md` §3) and the
//! Universal Robots UR5e (`models/robots/ur5e.*`, UR's standard DH table); any other arm
//! comes from its own description file ([`RobotDescription::load`], `docs/robots.md`).
//!
//! Why a hand-written IK rather than the `k` crate: on these machines a damped-least-squares
//! solver on fixed-size matrices converts 1,800-3,600 Omniglot drawings/s per core while `k`
//! manages 220-460/s, and `k` 0.32 pins nalgebra 0.30 / urdf-rs 0.9 (two copies of nalgebra in
//! the workspace). See `docs/dataset.md` for the figures measured with this solver.
//!
//! One concern per file:
//! - this file: the chain's data ([`Robot`], [`Joint`]), the published Panda numbers
//!   ([`Robot::panda`]), the joint-space types and the re-exports;
//! - `frame.rs`: rigid transforms ([`Frame`]);
//! - `urdf.rs`: a serial chain read from a URDF ([`Robot::from_urdf_str`], [`UrdfLoadError`]);
//! - `description.rs`: the robot description file and the built-in robots
//!   ([`RobotDescription`], [`RobotLoadError`]);
//! - `fk.rs`: forward kinematics through the general chain (full frames), the source of
//!   truth, and the choice between it and the specialised position FK;
//! - `ik.rs`: the geometric Jacobian and the damped-least-squares IK;
//! - `simd.rs`: the pen-tip position FK specialised to a chain's numbers ([`PositionFk`],
//!   blocks of [`FK_LANES`] waypoints, runtime SIMD dispatch), built for chains of revolute
//!   joints about z whose origins are signed axis permutations (the Panda and the UR5e) and
//!   checked against `fk.rs` when the robot is built; other chains use the general chain.

// Joint-indexed loops over several parallel arrays read best with an index.
#![allow(clippy::needless_range_loop)]

mod description;
mod fk;
mod frame;
mod ik;
mod simd;
mod urdf;

use guardian_shared::trajectory::JointLimits;
pub use guardian_shared::trajectory::MAX_JOINTS;
use nalgebra::{SMatrix, Vector3};
use sha2::{Digest, Sha256};

pub use description::{
    BUILTIN_ROBOTS, DEFAULT_ROBOT, RobotDescription, RobotLoadError, RobotSource, ToolSpec,
    WorkcellOverrideError, apply_workcell_overrides,
};
pub use frame::Frame;
pub use ik::{IkError, IkOptions, IkState};
pub use simd::{FK_LANES, Lanes, POSITION_FK_TOLERANCE, PoseLanes, PositionFk, WithJoints};
pub use urdf::{PANDA_URDF, UR5E_URDF, UrdfLoadError};

/// Joint positions (rad for revolute, m for prismatic joints) in slots `0..joints`; the
/// slots past the robot's joints are 0.
pub type JointVector = [f64; MAX_JOINTS];

/// The geometric Jacobian of the pen tip: rows 0-2 linear velocity, rows 3-5 angular
/// velocity, both in the base frame; one column per joint, the columns past the robot's
/// joints zero.
pub type Jacobian = SMatrix<f64, 6, MAX_JOINTS>;

/// `v` rounded to `f32` without leaving `[lo, hi]` (a value clamped to a joint limit may
/// round outside it): how solved joints are stored in a plan.
pub fn f32_within(v: f64, lo: f64, hi: f64) -> f32 {
    let mut x = v as f32;
    while f64::from(x) > hi {
        x = x.next_down();
    }
    while f64::from(x) < lo {
        x = x.next_up();
    }
    x
}

/// A joint vector from the first `q.len()` (at most [`MAX_JOINTS`]) values.
pub fn joint_vector(q: &[f64]) -> JointVector {
    let mut v = [0.0; MAX_JOINTS];
    v[..q.len()].copy_from_slice(q);
    v
}

/// Joints of the Franka Emika Panda.
pub const PANDA_JOINTS: usize = 7;

/// Lower joint limits of the Panda (rad), from the published kinematics.
pub const PANDA_Q_MIN: [f64; PANDA_JOINTS] = [
    -2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973,
];
/// Upper joint limits of the Panda (rad), from the published kinematics.
pub const PANDA_Q_MAX: [f64; PANDA_JOINTS] =
    [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973];

/// The Franka "ready" pose (the Panda's home seed).
pub const READY_POSE: JointVector = {
    let mut q = [0.0; MAX_JOINTS];
    q[1] = -std::f64::consts::FRAC_PI_4;
    q[3] = -3.0 * std::f64::consts::FRAC_PI_4;
    q[5] = std::f64::consts::FRAC_PI_2;
    q[6] = std::f64::consts::FRAC_PI_4;
    q
};

/// Which robot a file's plans were made with (a class bank, a data set): name, joints and
/// the SHA-256 of its URDF.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RobotRecord {
    /// The robot's name.
    pub name: String,
    /// Its joints.
    pub joints: usize,
    /// SHA-256 of its URDF (64 hex digits).
    pub urdf_sha256: String,
}

impl RobotRecord {
    /// The record of `robot`.
    pub fn of(robot: &Robot) -> Self {
        Self {
            name: robot.name().to_string(),
            joints: robot.joints(),
            urdf_sha256: robot.urdf_sha256_hex(),
        }
    }

    /// The Panda as recorded implicitly by files made before records existed.
    pub fn panda() -> Self {
        Self::of(&Robot::panda())
    }

    /// Whether plans recorded as `self` may be served or compared as `robot`'s: same name,
    /// joints and URDF.
    pub fn matches(&self, robot: &Robot) -> bool {
        *self == Self::of(robot)
    }
}

impl std::fmt::Display for RobotRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let sha = &self.urdf_sha256[..self.urdf_sha256.len().min(12)];
        write!(f, "{} ({} joints, URDF {sha})", self.name, self.joints)
    }
}

/// How a joint moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointKind {
    /// Rotation about the axis (rad).
    Revolute,
    /// Translation along the axis (m).
    Prismatic,
}

/// One movable joint of the chain.
#[derive(Debug, Clone, PartialEq)]
pub struct Joint {
    /// The URDF joint name.
    pub name: String,
    /// Revolute or prismatic.
    pub kind: JointKind,
    /// Fixed origin of the joint in its parent link (fixed joints before it composed in).
    pub origin: Frame,
    /// Unit axis in the joint frame.
    pub axis: Vector3<f64>,
    /// Velocity limit (rad/s or m/s) where the URDF gives one (> 0).
    pub velocity: Option<f64>,
}

impl Joint {
    /// The axis is exactly +z (the fast, bit-stable path of FK and the Jacobian).
    pub(crate) fn about_z(&self) -> bool {
        self.kind == JointKind::Revolute && self.axis == Vector3::z()
    }
}

/// A serial arm: its movable joints, the fixed flange (tip link) and the tool, its limits,
/// and the checksum of the URDF it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Robot {
    name: String,
    joints: Vec<Joint>,
    /// The tip link (flange) in the frame after the last movable joint.
    flange: Frame,
    /// Tool (pen tip) in the flange frame.
    tool: Frame,
    limits: JointLimits,
    urdf_sha256: [u8; 32],
    /// The pen-tip position specialised to these joint origins, if they allow it.
    position_fk: Option<PositionFk>,
}

const HALF_PI: f64 = std::f64::consts::FRAC_PI_2;

/// Published Panda joint origins (xyz, rpy), the same numbers as `panda.urdf`.
const PANDA_ORIGINS: [([f64; 3], [f64; 3]); PANDA_JOINTS] = [
    ([0.0, 0.0, 0.333], [0.0, 0.0, 0.0]),
    ([0.0, 0.0, 0.0], [-HALF_PI, 0.0, 0.0]),
    ([0.0, -0.316, 0.0], [HALF_PI, 0.0, 0.0]),
    ([0.0825, 0.0, 0.0], [HALF_PI, 0.0, 0.0]),
    ([-0.0825, 0.384, 0.0], [-HALF_PI, 0.0, 0.0]),
    ([0.0, 0.0, 0.0], [HALF_PI, 0.0, 0.0]),
    ([0.088, 0.0, 0.0], [HALF_PI, 0.0, 0.0]),
];
/// Published Panda joint velocity limits (rad/s).
const PANDA_DQ_MAX: [f64; PANDA_JOINTS] = [2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100];

const PANDA_FLANGE: ([f64; 3], [f64; 3]) = ([0.0, 0.0, 0.107], [0.0, 0.0, 0.0]);
/// Default Panda pen: 0.15 m along flange z, rotated -pi/4 about z.
pub const PEN_LENGTH: f64 = 0.15;
/// Default Panda pen yaw about the flange z axis (rad).
pub const PEN_YAW: f64 = -std::f64::consts::FRAC_PI_4;

/// The default robot (published Panda, default pen), built once: the lab's data sets and
/// the paths that take no robot use it.
static PANDA: std::sync::LazyLock<Robot> = std::sync::LazyLock::new(Robot::panda);

/// The default robot: the published Panda with the default pen.
pub fn default_panda() -> &'static Robot {
    &PANDA
}

/// Joint part of a waypoint in f64 (the unused slots of a waypoint are 0, so they stay 0).
#[inline]
pub fn joints_of(w: &guardian_shared::trajectory::Waypoint) -> JointVector {
    std::array::from_fn(|j| f64::from(w[j]))
}

/// SHA-256 of a file's bytes.
pub(crate) fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
}

impl Robot {
    /// The published Panda with the default pen, built without parsing (a test keeps it
    /// identical to `models/robots/panda.urdf` + `panda.toml`).
    pub fn panda() -> Self {
        let joints = PANDA_ORIGINS
            .iter()
            .enumerate()
            .map(|(j, &(xyz, rpy))| Joint {
                name: format!("panda_joint{}", j + 1),
                kind: JointKind::Revolute,
                origin: Frame::from_xyz_rpy(xyz, rpy),
                axis: Vector3::z(),
                velocity: Some(PANDA_DQ_MAX[j]),
            })
            .collect();
        let limits = JointLimits::new(PANDA_Q_MIN.to_vec(), PANDA_Q_MAX.to_vec())
            .expect("the published limits are a valid range");
        Self {
            name: "panda".to_string(),
            joints,
            flange: Frame::from_xyz_rpy(PANDA_FLANGE.0, PANDA_FLANGE.1),
            tool: Frame::from_xyz_rpy([0.0, 0.0, PEN_LENGTH], [0.0, 0.0, PEN_YAW]),
            limits,
            urdf_sha256: sha256(PANDA_URDF.as_bytes()),
            position_fk: None,
        }
        .with_position_fk()
    }

    /// Build (or drop) the specialised pen-tip position FK for the current numbers.
    fn with_position_fk(mut self) -> Self {
        self.position_fk = PositionFk::from_robot(&self);
        self
    }

    /// The specialised pen-tip position FK, if the chain allows it (revolute joints about z
    /// whose origin rotations are signed axis permutations: the Panda's and the UR5e's).
    /// `None` means every position goes through the general chain.
    pub fn position_fk(&self) -> Option<&PositionFk> {
        self.position_fk.as_ref()
    }

    /// The same robot with another tool: `length` along flange z, rotated `yaw` about it.
    pub fn with_tool(self, length: f64, yaw: f64) -> Self {
        self.with_tool_frame(Frame::from_xyz_rpy([0.0, 0.0, length], [0.0, 0.0, yaw]))
    }

    /// The same robot with another tool frame (in the flange frame).
    pub fn with_tool_frame(mut self, tool: Frame) -> Self {
        self.tool = tool;
        self.with_position_fk()
    }

    /// The robot's name (its description's `name`).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Number of movable joints (1..=[`MAX_JOINTS`]).
    pub fn joints(&self) -> usize {
        self.joints.len()
    }

    /// Floats per waypoint of this robot's trajectories: the joints, then the tool.
    pub fn channels(&self) -> usize {
        self.joints.len() + 1
    }

    /// The movable joints, base to tip.
    pub fn joint_list(&self) -> &[Joint] {
        &self.joints
    }

    /// The joint limits trajectories are validated against.
    pub fn limits(&self) -> &JointLimits {
        &self.limits
    }

    /// SHA-256 of the URDF this robot was read from.
    pub fn urdf_sha256(&self) -> &[u8; 32] {
        &self.urdf_sha256
    }

    /// [`Robot::urdf_sha256`] as 64 lower-case hex digits.
    pub fn urdf_sha256_hex(&self) -> String {
        self.urdf_sha256
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }

    /// The tool (pen tip) frame in the flange frame.
    pub fn tool(&self) -> &Frame {
        &self.tool
    }

    /// The flange (tip link) in the frame after the last movable joint.
    pub fn flange_offset(&self) -> &Frame {
        &self.flange
    }

    /// Lower joint limits.
    pub fn q_min(&self) -> &[f64] {
        self.limits.lower()
    }

    /// Upper joint limits.
    pub fn q_max(&self) -> &[f64] {
        self.limits.upper()
    }

    /// Smallest distance of `q` to a joint limit; negative if a limit is violated.
    pub fn limit_margin(&self, q: &JointVector) -> f64 {
        let (lo, hi) = (self.q_min(), self.q_max());
        (0..self.joints())
            .map(|j| (q[j] - lo[j]).min(hi[j] - q[j]))
            .fold(f64::INFINITY, f64::min)
    }

    /// `q` clamped into the joint limits (slots past the joints set to 0).
    pub fn clamp(&self, q: &JointVector) -> JointVector {
        let mut out = [0.0; MAX_JOINTS];
        for j in 0..self.joints() {
            out[j] = q[j].clamp(self.q_min()[j], self.q_max()[j]);
        }
        out
    }

    /// The waypoint a plan stores for solved joints `q` (the robot's joints, slots past them
    /// 0) and tool value `tool`: each joint rounded to `f32` inside its limits
    /// ([`f32_within`]), so a solved pose never fails validation for the rounding.
    pub fn waypoint(&self, q: &[f64], tool: f32) -> guardian_shared::trajectory::Waypoint {
        let mut w = [0.0f32; guardian_shared::trajectory::SLOTS];
        for j in 0..self.joints() {
            w[j] = f32_within(q[j], self.q_min()[j], self.q_max()[j]);
        }
        w[guardian_shared::trajectory::TOOL] = tool;
        w
    }
}
