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

// Joint-indexed loops over several parallel arrays read best with an index.
#![allow(clippy::needless_range_loop)]

use guardian_shared::trajectory::{JOINTS, Q_MAX, Q_MIN, Waypoint};
use nalgebra::{Matrix3, Matrix6, Matrix6x1, Rotation3, SMatrix, Vector3, Vector6};

/// The robot model shipped with guardian (kinematic only).
pub const PANDA_URDF: &str = include_str!("../panda.urdf");

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

/// A rigid transform: `p_parent = rotation * p_child + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Orientation of the child frame in the parent frame.
    pub rotation: Matrix3<f64>,
    /// Origin of the child frame in the parent frame (m).
    pub translation: Vector3<f64>,
}

impl Frame {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// A URDF `<origin xyz rpy>`: rotation `Rz(yaw) * Ry(pitch) * Rx(roll)`.
    pub fn from_xyz_rpy(xyz: [f64; 3], rpy: [f64; 3]) -> Self {
        Self {
            rotation: Rotation3::from_euler_angles(rpy[0], rpy[1], rpy[2]).into_inner(),
            translation: Vector3::new(xyz[0], xyz[1], xyz[2]),
        }
    }

    /// `self * other`.
    pub fn compose(&self, other: &Frame) -> Frame {
        Frame {
            rotation: self.rotation * other.rotation,
            translation: self.translation + self.rotation * other.translation,
        }
    }

    /// `self * Rz(q)`: the frame after a revolute joint about its z axis.
    #[inline]
    fn rotate_z(&self, q: f64) -> Frame {
        let (s, c) = q.sin_cos();
        let r = &self.rotation;
        let x = r.column(0) * c + r.column(1) * s;
        let y = r.column(1) * c - r.column(0) * s;
        Frame {
            rotation: Matrix3::from_columns(&[x, y, r.column(2).into_owned()]),
            translation: self.translation,
        }
    }
}

/// Building a [`Panda`] from a URDF failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum UrdfLoadError {
    /// urdf-rs could not parse the text.
    #[error("cannot parse URDF: {0}")]
    Parse(String),
    /// No single root link (a link that is nobody's child) was found.
    #[error("URDF has {roots} root links, expected 1")]
    Root {
        /// Number of root links found.
        roots: usize,
    },
    /// A link has more than one child joint: not a serial chain.
    #[error("link {link} has {children} child joints; a serial chain is expected")]
    Branching {
        /// The link name.
        link: String,
        /// Number of child joints.
        children: usize,
    },
    /// The chain does not have 7 revolute joints.
    #[error("expected {expected} revolute joints, got {got}")]
    JointCount {
        /// Revolute joints expected.
        expected: usize,
        /// Revolute joints found.
        got: usize,
    },
    /// A joint type other than revolute or fixed, or a fixed joint between revolute ones.
    #[error("joint {joint}: unsupported {kind} here")]
    Unsupported {
        /// The joint name.
        joint: String,
        /// What was found.
        kind: String,
    },
    /// A revolute joint does not rotate about its z axis.
    #[error("joint {joint}: axis {axis:?} is not +z")]
    Axis {
        /// The joint name.
        joint: String,
        /// The axis in the URDF.
        axis: [f64; 3],
    },
    /// No fixed joint after the last revolute joint (the flange).
    #[error("no fixed flange joint after the last revolute joint")]
    NoFlange,
}

/// Inverse kinematics did not find a solution.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum IkError {
    /// The iteration limit was reached before the tolerances.
    #[error(
        "IK did not converge in {iterations} iterations: position error {position_error:.3e} m, \
         orientation error {orientation_error:.3e} rad"
    )]
    NoConvergence {
        /// Iterations run.
        iterations: usize,
        /// Remaining position error (m).
        position_error: f64,
        /// Remaining orientation error (rad).
        orientation_error: f64,
    },
    /// The seed or an iterate was not finite.
    #[error("IK produced a non-finite value (seed or target not finite)")]
    NonFinite,
}

/// Damped-least-squares IK settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkOptions {
    /// Accept when the pen-tip position error is below this (m).
    pub position_tolerance: f64,
    /// Accept when the orientation error is below this (rad).
    pub orientation_tolerance: f64,
    /// Damping factor lambda of `J^T (J J^T + lambda^2 I)^-1`.
    pub damping: f64,
    /// Largest joint step per iteration (rad, infinity norm).
    pub max_step: f64,
    /// Iteration limit.
    pub max_iterations: usize,
}

impl Default for IkOptions {
    fn default() -> Self {
        Self {
            position_tolerance: 1e-6,
            orientation_tolerance: 1e-5,
            damping: 1e-3,
            max_step: 0.2,
            max_iterations: 100,
        }
    }
}

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
    /// Parse the shipped `panda.urdf` ([`PANDA_URDF`]).
    pub fn from_embedded_urdf() -> Result<Self, UrdfLoadError> {
        Self::from_urdf_str(PANDA_URDF)
    }

    /// Parse a URDF: a serial chain of 7 revolute joints about z, then one fixed joint (the
    /// flange), then optionally more fixed joints composed into the tool frame (identity if
    /// none).
    pub fn from_urdf_str(text: &str) -> Result<Self, UrdfLoadError> {
        let robot =
            urdf_rs::read_from_string(text).map_err(|e| UrdfLoadError::Parse(e.to_string()))?;
        let roots: Vec<&str> = robot
            .links
            .iter()
            .map(|l| l.name.as_str())
            .filter(|name| !robot.joints.iter().any(|j| j.child.link == *name))
            .collect();
        if roots.len() != 1 {
            return Err(UrdfLoadError::Root { roots: roots.len() });
        }
        let mut link = roots[0].to_string();
        let mut revolute: Vec<(Frame, f64, f64)> = Vec::new();
        let mut fixed_after: Vec<Frame> = Vec::new();
        loop {
            let children: Vec<&urdf_rs::Joint> = robot
                .joints
                .iter()
                .filter(|j| j.parent.link == link)
                .collect();
            let joint = match children.as_slice() {
                [] => break,
                [j] => *j,
                _ => {
                    return Err(UrdfLoadError::Branching {
                        link,
                        children: children.len(),
                    });
                }
            };
            let origin = Frame::from_xyz_rpy(*joint.origin.xyz, *joint.origin.rpy);
            match joint.joint_type {
                urdf_rs::JointType::Revolute => {
                    if !fixed_after.is_empty() {
                        return Err(UrdfLoadError::Unsupported {
                            joint: joint.name.clone(),
                            kind: "revolute joint after a fixed joint".into(),
                        });
                    }
                    let axis = *joint.axis.xyz;
                    if axis != [0.0, 0.0, 1.0] {
                        return Err(UrdfLoadError::Axis {
                            joint: joint.name.clone(),
                            axis,
                        });
                    }
                    revolute.push((origin, joint.limit.lower, joint.limit.upper));
                }
                urdf_rs::JointType::Fixed => {
                    if revolute.is_empty() {
                        return Err(UrdfLoadError::Unsupported {
                            joint: joint.name.clone(),
                            kind: "fixed joint before the first revolute joint".into(),
                        });
                    }
                    fixed_after.push(origin);
                }
                ref other => {
                    return Err(UrdfLoadError::Unsupported {
                        joint: joint.name.clone(),
                        kind: format!("{other:?} joint"),
                    });
                }
            }
            link = joint.child.link.clone();
        }
        if revolute.len() != JOINTS {
            return Err(UrdfLoadError::JointCount {
                expected: JOINTS,
                got: revolute.len(),
            });
        }
        let flange = *fixed_after.first().ok_or(UrdfLoadError::NoFlange)?;
        let tool = fixed_after[1..]
            .iter()
            .fold(Frame::identity(), |acc, f| acc.compose(f));
        let mut joints = [Frame::identity(); JOINTS];
        let mut q_min = [0.0; JOINTS];
        let mut q_max = [0.0; JOINTS];
        for (i, (origin, lo, hi)) in revolute.into_iter().enumerate() {
            joints[i] = origin;
            q_min[i] = lo;
            q_max[i] = hi;
        }
        Ok(Self {
            joints,
            flange,
            tool,
            q_min,
            q_max,
            position_fk: None,
        }
        .with_position_fk())
    }

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

    /// Frame of link 7 (after joint 7, before the flange offset).
    #[inline]
    fn link7(&self, q: &JointVector) -> Frame {
        let mut t = Frame::identity();
        for (origin, &qi) in self.joints.iter().zip(q.iter()) {
            t = t.compose(origin).rotate_z(qi);
        }
        t
    }

    /// Forward kinematics of the flange (panda_link8) in the base frame.
    pub fn flange(&self, q: &JointVector) -> Frame {
        self.link7(q).compose(&self.flange)
    }

    /// Forward kinematics of the pen tip (tool frame) in the base frame.
    pub fn pen_tip(&self, q: &JointVector) -> Frame {
        self.flange(q).compose(&self.tool)
    }

    /// Pen-tip position only (m), the fast path for path lengths and features: the
    /// specialised [`PositionFk`] when the joint origins allow it, else the general chain
    /// ([`Panda::pen_tip`]).
    #[inline]
    pub fn pen_tip_position(&self, q: &JointVector) -> Vector3<f64> {
        match &self.position_fk {
            Some(fk) => Vector3::from(fk.position(q)),
            None => self.pen_tip(q).translation,
        }
    }

    /// Pen-tip position through the general chain (full frames), the reference
    /// [`Panda::pen_tip_position`] is tested against.
    pub fn pen_tip_position_general(&self, q: &JointVector) -> Vector3<f64> {
        self.pen_tip(q).translation
    }

    /// Pen-tip positions (m, base frame) of the joint parts of `waypoints` into `out`
    /// (same length; extra slots are left alone). Uses [`PositionFk::positions_into`] when
    /// available; allocates nothing.
    pub fn pen_tip_positions_into(&self, waypoints: &[Waypoint], out: &mut [[f64; 3]]) {
        match &self.position_fk {
            Some(fk) => fk.positions_into(waypoints, out),
            None => {
                for (o, w) in out.iter_mut().zip(waypoints) {
                    let q: JointVector = std::array::from_fn(|j| f64::from(w[j]));
                    *o = self.pen_tip(&q).translation.into();
                }
            }
        }
    }

    /// Pen-tip positions and tool rotations (base frame) of the joint parts of `waypoints`
    /// (pairs up to the shortest of the three): [`PositionFk::poses_into`] when available,
    /// else the general chain. The positions equal [`Panda::pen_tip_positions_into`]'s bit for
    /// bit. Allocates nothing.
    pub fn pen_tip_poses_into(
        &self,
        waypoints: &[Waypoint],
        positions: &mut [[f64; 3]],
        rotations: &mut [Matrix3<f64>],
    ) {
        match &self.position_fk {
            Some(fk) => fk.poses_into(waypoints, positions, rotations),
            None => {
                for ((p, r), w) in positions.iter_mut().zip(rotations).zip(waypoints) {
                    let q: JointVector = std::array::from_fn(|j| f64::from(w[j]));
                    let f = self.pen_tip(&q);
                    *p = f.translation.into();
                    *r = f.rotation;
                }
            }
        }
    }

    /// Pen-tip frame and its geometric Jacobian (base frame).
    pub fn jacobian(&self, q: &JointVector) -> (Frame, Jacobian) {
        let mut axes = [Vector3::zeros(); JOINTS];
        let mut origins = [Vector3::zeros(); JOINTS];
        let mut t = Frame::identity();
        for j in 0..JOINTS {
            t = t.compose(&self.joints[j]).rotate_z(q[j]);
            axes[j] = t.rotation.column(2).into_owned();
            origins[j] = t.translation;
        }
        let tip = t.compose(&self.flange).compose(&self.tool);
        let mut jac = Jacobian::zeros();
        for j in 0..JOINTS {
            let lin = axes[j].cross(&(tip.translation - origins[j]));
            jac.fixed_view_mut::<3, 1>(0, j).copy_from(&lin);
            jac.fixed_view_mut::<3, 1>(3, j).copy_from(&axes[j]);
        }
        (tip, jac)
    }

    /// Damped-least-squares IK for a full pen-tip pose, starting from `seed`.
    ///
    /// Each iteration takes `dq = J^T (J J^T + lambda^2 I)^-1 e` (the minimum-norm step, so a
    /// nearby seed gives a nearby solution), limits the step to `max_step` and clamps to the
    /// joint limits. The result is always inside the limits; if the target cannot be reached
    /// inside them, the result is [`IkError::NoConvergence`].
    pub fn ik(
        &self,
        target: &Frame,
        seed: &JointVector,
        options: &IkOptions,
    ) -> Result<JointVector, IkError> {
        if seed.iter().any(|v| !v.is_finite()) {
            return Err(IkError::NonFinite);
        }
        let mut state = self.ik_state(seed);
        self.ik_from(target, &mut state, options)?;
        Ok(state.q)
    }

    /// The IK state at `q` (clamped to the limits): pen-tip frame and Jacobian.
    pub fn ik_state(&self, q: &JointVector) -> IkState {
        let mut q = *q;
        for j in 0..JOINTS {
            q[j] = q[j].clamp(self.q_min[j], self.q_max[j]);
        }
        let (tip, jacobian) = self.jacobian(&q);
        IkState { q, tip, jacobian }
    }

    /// [`Panda::ik`] from a state whose frame and Jacobian are already known, updated in
    /// place to the solution (on error it holds the last iterate), so a path solver seeding
    /// each point with the previous solution evaluates the Jacobian once per converged step
    /// instead of twice.
    pub fn ik_from(
        &self,
        target: &Frame,
        state: &mut IkState,
        options: &IkOptions,
    ) -> Result<(), IkError> {
        if state.q.iter().any(|v| !v.is_finite())
            || target.translation.iter().any(|v| !v.is_finite())
            || target.rotation.iter().any(|v| !v.is_finite())
        {
            return Err(IkError::NonFinite);
        }
        let lambda2 = options.damping * options.damping;
        let mut position_error = f64::INFINITY;
        let mut orientation_error = f64::INFINITY;
        for iteration in 0..=options.max_iterations {
            if iteration > 0 {
                let (tip, jacobian) = self.jacobian(&state.q);
                state.tip = tip;
                state.jacobian = jacobian;
            }
            let jac = &state.jacobian;
            let dp = target.translation - state.tip.translation;
            let dw = orientation_error_vector(&target.rotation, &state.tip.rotation);
            position_error = dp.norm();
            orientation_error = dw.norm();
            if position_error <= options.position_tolerance
                && orientation_error <= options.orientation_tolerance
            {
                return Ok(());
            }
            if iteration == options.max_iterations {
                break;
            }
            let e = Vector6::new(dp.x, dp.y, dp.z, dw.x, dw.y, dw.z);
            let a: Matrix6<f64> = jac * jac.transpose() + Matrix6::identity() * lambda2;
            let y: Matrix6x1<f64> = match a.cholesky() {
                Some(ch) => ch.solve(&e),
                None => return Err(IkError::NonFinite),
            };
            let dq = jac.transpose() * y;
            let largest = dq.amax();
            if !largest.is_finite() {
                return Err(IkError::NonFinite);
            }
            let scale = if largest > options.max_step {
                options.max_step / largest
            } else {
                1.0
            };
            for j in 0..JOINTS {
                state.q[j] = (state.q[j] + dq[j] * scale).clamp(self.q_min[j], self.q_max[j]);
            }
        }
        Err(IkError::NoConvergence {
            iterations: options.max_iterations,
            position_error,
            orientation_error,
        })
    }
}

/// A rotation that is a signed permutation of the axes: `(R v)[i] = sign[i] * v[src[i]]`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AxisMap {
    src: [usize; 3],
    sign: [f64; 3],
}

impl AxisMap {
    /// `Some` if every entry of `r` is within `tol` of 0 or +-1, with exactly one +-1 in
    /// every row and every column.
    fn from_matrix(r: &Matrix3<f64>, tol: f64) -> Option<Self> {
        let mut src = [0usize; 3];
        let mut sign = [0.0f64; 3];
        let mut used = [false; 3];
        for i in 0..3 {
            let mut found = None;
            for k in 0..3 {
                let v = r[(i, k)];
                if (v.abs() - 1.0).abs() <= tol {
                    if found.is_some() {
                        return None;
                    }
                    found = Some((k, v.signum()));
                } else if v.abs() > tol || !v.is_finite() {
                    return None;
                }
            }
            let (k, s) = found?;
            if used[k] {
                return None;
            }
            used[k] = true;
            src[i] = k;
            sign[i] = s;
        }
        Some(Self { src, sign })
    }
}

/// Largest distance (m) between [`PositionFk`] and the general chain accepted when the
/// specialised FK is built; above it [`Panda`] keeps using the general chain.
pub const POSITION_FK_TOLERANCE: f64 = 1e-12;

/// Pen-tip position forward kinematics specialised to a chain whose joint origin rotations
/// are signed axis permutations (the Panda's are the identity or +-pi/2 about x).
///
/// Evaluated from the pen tip back to the base: per joint one rotation about z (4
/// multiplies), a signed axis permutation (no arithmetic) and the origin offset; f64, no
/// allocation, no 4x4 or 3x3 products. It is built by [`Panda`] from the numbers of the
/// loaded chain (URDF or built-in) and checked at construction against the general chain
/// ([`Panda::pen_tip_position_general`]) at several joint vectors; if the origins are not
/// signed permutations (to 1e-12 per entry) or the check misses [`POSITION_FK_TOLERANCE`],
/// there is no `PositionFk` and [`Panda`] uses the general chain, so another URDF cannot be
/// silently mis-computed. The general chain stays the source of truth and serves IK and
/// Jacobians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionFk {
    rotations: [AxisMap; JOINTS],
    offsets: [[f64; 3]; JOINTS],
    /// The pen tip in the frame of link 7 (flange offset and tool composed).
    tip: [f64; 3],
    /// The tool's x and z axes in the frame of link 7.
    tool_axes: [[f64; 3]; 2],
}

/// Waypoints per block of [`PositionFk::positions_into`] (the sines and cosines of a block
/// are computed together, which the compiler vectorises).
pub const FK_LANES: usize = 8;

impl PositionFk {
    fn from_panda(panda: &Panda) -> Option<Self> {
        let mut rotations = [AxisMap {
            src: [0, 1, 2],
            sign: [1.0; 3],
        }; JOINTS];
        let mut offsets = [[0.0; 3]; JOINTS];
        for j in 0..JOINTS {
            rotations[j] = AxisMap::from_matrix(&panda.joints[j].rotation, 1e-12)?;
            offsets[j] = panda.joints[j].translation.into();
        }
        let tip = panda.flange.translation + panda.flange.rotation * panda.tool.translation;
        let tool = panda.flange.rotation * panda.tool.rotation;
        let fk = Self {
            rotations,
            offsets,
            tip: tip.into(),
            tool_axes: [tool.column(0).into(), tool.column(2).into()],
        };
        // Verify against the general chain at the limits, their middle and the ready pose.
        let mid: JointVector = std::array::from_fn(|j| 0.5 * (panda.q_min[j] + panda.q_max[j]));
        let mixed: JointVector = std::array::from_fn(|j| {
            if j % 2 == 0 {
                panda.q_min[j]
            } else {
                panda.q_max[j]
            }
        });
        let probes = [READY_POSE, mid, panda.q_min, panda.q_max, mixed];
        for q in &probes {
            let general = panda.pen_tip(q);
            let fast = Vector3::from(fk.position(q));
            let d = (general.translation - fast).norm();
            if d.is_nan() || d > POSITION_FK_TOLERANCE {
                return None;
            }
            let mut p = [[0.0; 3]];
            let mut r = [Matrix3::zeros()];
            let w: Waypoint = std::array::from_fn(|j| if j < JOINTS { q[j] as f32 } else { 0.0 });
            fk.poses_into(&[w], &mut p, &mut r);
            let qf: JointVector = std::array::from_fn(|j| f64::from(w[j]));
            let e = (panda.pen_tip(&qf).rotation - r[0]).norm();
            if e.is_nan() || e > POSITION_FK_TOLERANCE {
                return None;
            }
        }
        Some(fk)
    }

    /// One joint on a block of lanes: `v` in the frame after joint `j` to the frame before
    /// it, with the joint origin's offset added when `offset` (a point) and without (a
    /// direction). The same operations, in the same order, as [`PositionFk::position`] per
    /// lane, so results are bit for bit those of the scalar chain.
    #[inline(always)]
    fn joint_lanes(
        &self,
        j: usize,
        s: &[f64; FK_LANES],
        c: &[f64; FK_LANES],
        v: &Lanes,
        offset: bool,
    ) -> Lanes {
        let mut r = [[0.0f64; FK_LANES]; 3];
        for l in 0..FK_LANES {
            r[0][l] = c[l] * v[0][l] - s[l] * v[1][l];
            r[1][l] = s[l] * v[0][l] + c[l] * v[1][l];
        }
        r[2] = v[2];
        let m = &self.rotations[j];
        let t = if offset { Some(self.offsets[j]) } else { None };
        // The axes as constants (one arm per permutation), so `r` stays in registers; a
        // run-time index would keep it in memory.
        match m.src {
            [0, 1, 2] => permute_lanes::<0, 1, 2>(&r, m.sign, t),
            [0, 2, 1] => permute_lanes::<0, 2, 1>(&r, m.sign, t),
            [1, 0, 2] => permute_lanes::<1, 0, 2>(&r, m.sign, t),
            [1, 2, 0] => permute_lanes::<1, 2, 0>(&r, m.sign, t),
            [2, 0, 1] => permute_lanes::<2, 0, 1>(&r, m.sign, t),
            // [2, 1, 0], the only permutation left (`AxisMap` holds permutations only).
            _ => permute_lanes::<2, 1, 0>(&r, m.sign, t),
        }
    }

    /// Pen-tip positions of a block of waypoints from their joint sines and cosines.
    #[inline(always)]
    fn block_positions(&self, s: &LaneTable, c: &LaneTable) -> Lanes {
        let mut v = self.tip.map(|x| [x; FK_LANES]);
        for j in (0..JOINTS).rev() {
            v = self.joint_lanes(j, &s[j], &c[j], &v, true);
        }
        v
    }

    /// Pen-tip positions and the tool's x and z axes (base frame) of a block of waypoints.
    #[inline(always)]
    fn block_poses(&self, s: &LaneTable, c: &LaneTable) -> PoseLanes {
        let mut p = self.tip.map(|x| [x; FK_LANES]);
        let mut x = self.tool_axes[0].map(|v| [v; FK_LANES]);
        let mut z = self.tool_axes[1].map(|v| [v; FK_LANES]);
        for j in (0..JOINTS).rev() {
            p = self.joint_lanes(j, &s[j], &c[j], &p, true);
            x = self.joint_lanes(j, &s[j], &c[j], &x, false);
            z = self.joint_lanes(j, &s[j], &c[j], &z, false);
        }
        PoseLanes { p, x, z }
    }

    /// Pen-tip position (m, base frame) at `q`.
    #[inline]
    pub fn position(&self, q: &JointVector) -> [f64; 3] {
        let mut v = self.tip;
        for j in (0..JOINTS).rev() {
            let (s, c) = q[j].sin_cos();
            let r = [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]];
            let m = &self.rotations[j];
            let t = &self.offsets[j];
            v = std::array::from_fn(|i| m.sign[i] * r[m.src[i]] + t[i]);
        }
        v
    }

    /// Pen-tip positions and tool axes of a block of at most [`FK_LANES`] waypoints (lanes
    /// past `ws.len()` hold the pose at all-zero joints). Inlined into its caller, so a
    /// caller compiled for a wider SIMD instruction set (a [`pulp::WithSimd`] run under
    /// [`pulp::Arch::dispatch`]) gets the block vectorised with it.
    #[inline(always)]
    pub fn pose_lanes(&self, ws: &[Waypoint]) -> PoseLanes {
        let (s, c) = joint_sin_cos(ws);
        self.block_poses(&s, &c)
    }

    /// Pen-tip positions (m, base frame) of the joint parts of `waypoints` into `out`
    /// (pairs up to the shorter of the two). Blocks of [`FK_LANES`] waypoints are evaluated
    /// together (sines and cosines by [`sin_cos_block`], the chain lane by lane), compiled
    /// for the widest SIMD instruction set this CPU has (runtime dispatch); allocates
    /// nothing.
    pub fn positions_into(&self, waypoints: &[Waypoint], out: &mut [[f64; 3]]) {
        pulp::Arch::new().dispatch(PositionsOp {
            fk: self,
            waypoints,
            out,
        });
    }

    /// Pen-tip positions and tool rotations of `waypoints` (pairs up to the shortest of the
    /// three). The positions are bit for bit those of [`PositionFk::positions_into`] (same
    /// operations); the rotation's x and z columns are the tool axes carried through the same
    /// joint rotations, y = z x x. Allocates nothing.
    pub fn poses_into(
        &self,
        waypoints: &[Waypoint],
        positions: &mut [[f64; 3]],
        rotations: &mut [Matrix3<f64>],
    ) {
        pulp::Arch::new().dispatch(PosesOp {
            fk: self,
            waypoints,
            positions,
            rotations,
        });
    }
}

/// [`PositionFk::positions_into`] as a runtime-dispatched SIMD operation.
struct PositionsOp<'a> {
    fk: &'a PositionFk,
    waypoints: &'a [Waypoint],
    out: &'a mut [[f64; 3]],
}

impl pulp::WithSimd for PositionsOp<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        for (ws, os) in self
            .waypoints
            .chunks(FK_LANES)
            .zip(self.out.chunks_mut(FK_LANES))
        {
            let n = ws.len().min(os.len());
            let (s, c) = joint_sin_cos(&ws[..n]);
            let v = self.fk.block_positions(&s, &c);
            for (l, o) in os[..n].iter_mut().enumerate() {
                *o = [v[0][l], v[1][l], v[2][l]];
            }
        }
    }
}

/// [`PositionFk::poses_into`] as a runtime-dispatched SIMD operation.
struct PosesOp<'a> {
    fk: &'a PositionFk,
    waypoints: &'a [Waypoint],
    positions: &'a mut [[f64; 3]],
    rotations: &'a mut [Matrix3<f64>],
}

impl pulp::WithSimd for PosesOp<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let blocks = self
            .waypoints
            .chunks(FK_LANES)
            .zip(self.positions.chunks_mut(FK_LANES))
            .zip(self.rotations.chunks_mut(FK_LANES));
        for ((ws, ps), rs) in blocks {
            let n = ws.len().min(ps.len()).min(rs.len());
            let b = self.fk.pose_lanes(&ws[..n]);
            for l in 0..n {
                ps[l] = [b.p[0][l], b.p[1][l], b.p[2][l]];
                let x = Vector3::new(b.x[0][l], b.x[1][l], b.x[2][l]);
                let z = Vector3::new(b.z[0][l], b.z[1][l], b.z[2][l]);
                rs[l] = Matrix3::from_columns(&[x, z.cross(&x), z]);
            }
        }
    }
}

/// `out[i] = sign[i] * r[src[i]] (+ t[i])` lane by lane with `src = [A, B, C]`: the same
/// operations as [`PositionFk::position`].
#[inline(always)]
fn permute_lanes<const A: usize, const B: usize, const C: usize>(
    r: &Lanes,
    sign: [f64; 3],
    t: Option<[f64; 3]>,
) -> Lanes {
    let mut out = [[0.0f64; FK_LANES]; 3];
    for l in 0..FK_LANES {
        out[0][l] = sign[0] * r[A][l];
        out[1][l] = sign[1] * r[B][l];
        out[2][l] = sign[2] * r[C][l];
    }
    if let Some(t) = t {
        for (o, t) in out.iter_mut().zip(t) {
            for v in o.iter_mut() {
                *v += t;
            }
        }
    }
    out
}

/// Sines and cosines of every joint of a block of at most [`FK_LANES`] waypoints, per joint.
type LaneTable = [[f64; FK_LANES]; JOINTS];

/// A 3-vector per lane of a block: `v[axis][lane]`.
pub type Lanes = [[f64; FK_LANES]; 3];

/// Pen-tip positions and tool axes of a block of waypoints, lane by lane (base frame).
#[derive(Debug, Clone, Copy)]
pub struct PoseLanes {
    /// Pen-tip positions (m).
    pub p: Lanes,
    /// The tool's x axis.
    pub x: Lanes,
    /// The tool's z axis.
    pub z: Lanes,
}

#[inline(always)]
fn joint_sin_cos(ws: &[Waypoint]) -> (LaneTable, LaneTable) {
    let mut s = [[0.0f64; FK_LANES]; JOINTS];
    let mut c = [[0.0f64; FK_LANES]; JOINTS];
    for j in 0..JOINTS {
        let mut x = [0.0f64; FK_LANES];
        for (l, w) in ws.iter().take(FK_LANES).enumerate() {
            x[l] = f64::from(w[j]);
        }
        sin_cos_block(&x, &mut s[j], &mut c[j]);
    }
    (s, c)
}

/// Sine and cosine of a block of angles, branch-free so the compiler vectorises it:
/// reduction to `[-pi/4, pi/4]` by the nearest multiple of pi/2 and Taylor polynomials to
/// degree 17 (sine) and 18 (cosine), whose truncation error there is below 1e-19. Absolute
/// error against `f64::sin_cos` is a few 1e-16 for `|x| <= 1e3` (tested over the joint
/// range); larger or non-finite angles fall back to `f64::sin_cos`.
#[inline(always)]
fn sin_cos_block(x: &[f64; FK_LANES], s: &mut [f64; FK_LANES], c: &mut [f64; FK_LANES]) {
    // Adding and subtracting 1.5 * 2^52 rounds to the nearest integer (ties to even), and
    // the low bits of the sum are that integer modulo 4.
    const ROUND: f64 = 6_755_399_441_055_744.0;
    // pi/2 = PIO2_HI + PIO2_LO to about 1e-33.
    const PIO2_HI: f64 = std::f64::consts::FRAC_PI_2;
    const PIO2_LO: f64 = 6.123_233_995_736_766e-17;
    for l in 0..FK_LANES {
        let v = x[l];
        let shifted = v * std::f64::consts::FRAC_2_PI + ROUND;
        let quadrant = shifted.to_bits() & 3;
        let k = shifted - ROUND;
        let r = (v - k * PIO2_HI) - k * PIO2_LO;
        let z = r * r;
        let sp = 1.0 / 355_687_428_096_000.0;
        let sp = -1.0 / 1_307_674_368_000.0 + z * sp;
        let sp = 1.0 / 6_227_020_800.0 + z * sp;
        let sp = -1.0 / 39_916_800.0 + z * sp;
        let sp = 1.0 / 362_880.0 + z * sp;
        let sp = -1.0 / 5_040.0 + z * sp;
        let sp = 1.0 / 120.0 + z * sp;
        let sp = -1.0 / 6.0 + z * sp;
        let sin_r = r + r * z * sp;
        let cp = -1.0 / 6_402_373_705_728_000.0;
        let cp = 1.0 / 20_922_789_888_000.0 + z * cp;
        let cp = -1.0 / 87_178_291_200.0 + z * cp;
        let cp = 1.0 / 479_001_600.0 + z * cp;
        let cp = -1.0 / 3_628_800.0 + z * cp;
        let cp = 1.0 / 40_320.0 + z * cp;
        let cp = -1.0 / 720.0 + z * cp;
        let cp = 1.0 / 24.0 + z * cp;
        let cp = -0.5 + z * cp;
        let cos_r = 1.0 + z * cp;
        // Quadrant q: (sin, cos) = (s, c), (c, -s), (-s, -c), (-c, s).
        let swap = 0u64.wrapping_sub(quadrant & 1);
        let (sb, cb) = (sin_r.to_bits(), cos_r.to_bits());
        let sin_bits = (sb & !swap) | (cb & swap);
        let cos_bits = (cb & !swap) | (sb & swap);
        s[l] = f64::from_bits(sin_bits ^ ((quadrant & 2) << 62));
        c[l] = f64::from_bits(cos_bits ^ (((quadrant + 1) & 2) << 62));
    }
    for l in 0..FK_LANES {
        if x[l].is_nan() || x[l].abs() > 1e3 {
            (s[l], c[l]) = x[l].sin_cos();
        }
    }
}

/// Joints with their pen-tip frame and Jacobian, carried from one IK solve to the next.
#[derive(Debug, Clone, PartialEq)]
pub struct IkState {
    /// Joint positions (rad), inside the limits.
    pub q: JointVector,
    /// Pen-tip frame at `q`.
    pub tip: Frame,
    /// Pen-tip Jacobian at `q`.
    pub jacobian: Jacobian,
}

/// Rotation vector (axis * angle, base frame) taking `current` to `target`.
fn orientation_error_vector(target: &Matrix3<f64>, current: &Matrix3<f64>) -> Vector3<f64> {
    let r = target * current.transpose();
    let v = 0.5
        * Vector3::new(
            r[(2, 1)] - r[(1, 2)],
            r[(0, 2)] - r[(2, 0)],
            r[(1, 0)] - r[(0, 1)],
        );
    let sin = v.norm();
    let cos = (0.5 * (r.trace() - 1.0)).clamp(-1.0, 1.0);
    let angle = sin.atan2(cos);
    if sin > 1e-9 {
        return v * (angle / sin);
    }
    if cos > 0.0 {
        // Tiny angle: sin(angle) ~ angle.
        return v;
    }
    // Half turn: the axis is the dominant column of (R + I) / 2.
    let s = (r + Matrix3::identity()) * 0.5;
    let k = (0..3)
        .max_by(|&a, &b| s[(a, a)].total_cmp(&s[(b, b)]))
        .unwrap_or(0);
    let axis = s.column(k).into_owned();
    let n = axis.norm();
    if n > 0.0 {
        axis * (angle / n)
    } else {
        Vector3::zeros()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    #[test]
    fn flange_at_the_check_pose() {
        let panda = Panda::default();
        let f = panda.flange(&READY_POSE);
        let expected = Vector3::new(0.3069, 0.0, 0.5903);
        assert!(
            (f.translation - expected).norm() < 1e-4,
            "{}",
            f.translation
        );
        // Flange z points straight down at the ready pose.
        assert!((f.rotation.column(2) - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-9);
        // The pen tip is 0.15 m further down, its x axis along base +x.
        let p = panda.pen_tip(&READY_POSE);
        assert!((p.translation - (expected - Vector3::new(0.0, 0.0, 0.15))).norm() < 1e-4);
        assert!((p.rotation.column(0) - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-9);
    }

    #[test]
    fn urdf_parse_matches_the_published_numbers() {
        let parsed = Panda::from_embedded_urdf().expect("shipped URDF parses");
        let builtin = Panda::default();
        assert_eq!(parsed.q_min, builtin.q_min);
        assert_eq!(parsed.q_max, builtin.q_max);
        for (a, b) in parsed.joints.iter().zip(builtin.joints.iter()) {
            assert!((a.rotation - b.rotation).amax() < 1e-15);
            assert!((a.translation - b.translation).amax() < 1e-15);
        }
        assert!((parsed.tool.rotation - builtin.tool.rotation).amax() < 1e-15);
        assert!((parsed.tool.translation - builtin.tool.translation).amax() < 1e-15);
        let f = parsed.flange(&READY_POSE);
        assert!((f.translation - Vector3::new(0.3069, 0.0, 0.5903)).norm() < 1e-4);
    }

    #[test]
    fn malformed_urdf_is_a_typed_error() {
        assert!(matches!(
            Panda::from_urdf_str("<robot"),
            Err(UrdfLoadError::Parse(_))
        ));
        let six = PANDA_URDF.replace(
            r#"<joint name="panda_joint7" type="revolute">"#,
            r#"<joint name="panda_joint7" type="fixed">"#,
        );
        assert!(matches!(
            Panda::from_urdf_str(&six),
            Err(UrdfLoadError::JointCount {
                expected: 7,
                got: 6
            })
        ));
        let tilted = PANDA_URDF.replacen(r#"<axis xyz="0 0 1"/>"#, r#"<axis xyz="1 0 0"/>"#, 1);
        assert!(matches!(
            Panda::from_urdf_str(&tilted),
            Err(UrdfLoadError::Axis { .. })
        ));
    }

    fn random_q(rng: &mut StdRng, panda: &Panda) -> JointVector {
        std::array::from_fn(|j| {
            let (lo, hi) = (panda.q_min[j], panda.q_max[j]);
            let pad = 0.1 * (hi - lo);
            rng.random_range(lo + pad..hi - pad)
        })
    }

    #[test]
    fn block_sin_cos_matches_std() {
        let mut x = [0.0f64; FK_LANES];
        let (mut s, mut c) = ([0.0; FK_LANES], [0.0; FK_LANES]);
        let mut worst = 0.0f64;
        let n = 200_000;
        for i in 0..n {
            let l = i % FK_LANES;
            x[l] = -4.0 + 8.0 * i as f64 / n as f64;
            if l == FK_LANES - 1 {
                sin_cos_block(&x, &mut s, &mut c);
                for k in 0..FK_LANES {
                    let (es, ec) = x[k].sin_cos();
                    worst = worst.max((s[k] - es).abs()).max((c[k] - ec).abs());
                }
            }
        }
        assert!(worst < 1e-15, "worst {worst:e}");
        // Quadrant boundaries, zero, large and non-finite angles.
        let h = std::f64::consts::FRAC_PI_4;
        let x = [0.0, -0.0, h, -h, 3.0 * h, -3.0 * h, 1e4, f64::NAN];
        sin_cos_block(&x, &mut s, &mut c);
        for k in 0..7 {
            let (es, ec) = x[k].sin_cos();
            assert!(
                (s[k] - es).abs() < 1e-15 && (c[k] - ec).abs() < 1e-15,
                "{}",
                x[k]
            );
        }
        assert!(s[7].is_nan() && c[7].is_nan());
    }

    #[test]
    fn specialised_fk_equals_the_general_chain() {
        for panda in [
            Panda::default(),
            Panda::from_embedded_urdf().expect("shipped URDF parses"),
            Panda::default().with_tool(0.2, 0.3),
        ] {
            let fk = *panda
                .position_fk()
                .expect("the Panda's origins are permutations");
            let mut rng = StdRng::seed_from_u64(17);
            let mut ws = Vec::new();
            let mut worst = 0.0f64;
            for _ in 0..2000 {
                // Anywhere within the limits, the limits included.
                let q: JointVector =
                    std::array::from_fn(|j| rng.random_range(panda.q_min[j]..=panda.q_max[j]));
                let general = panda.pen_tip(&q).translation;
                worst = worst.max((Vector3::from(fk.position(&q)) - general).norm());
                worst = worst.max((panda.pen_tip_position(&q) - general).norm());
                let mut w = [0.0f32; 8];
                for j in 0..JOINTS {
                    w[j] = q[j] as f32;
                }
                ws.push(w);
            }
            // The batch path on f32 waypoints, including a partial last block.
            let ws = &ws[..ws.len() - 3];
            let mut out = vec![[0.0; 3]; ws.len()];
            panda.pen_tip_positions_into(ws, &mut out);
            for (w, o) in ws.iter().zip(&out) {
                let q: JointVector = std::array::from_fn(|j| f64::from(w[j]));
                let general = panda.pen_tip_position_general(&q);
                worst = worst.max((Vector3::from(*o) - general).norm());
            }
            assert!(worst <= 1e-12, "worst {worst:e} m");
            // Poses: positions bit for bit those of the position path, rotations equal to
            // the general chain's.
            let mut pos = vec![[0.0; 3]; ws.len()];
            let mut rot = vec![Matrix3::zeros(); ws.len()];
            panda.pen_tip_poses_into(ws, &mut pos, &mut rot);
            assert_eq!(pos, out);
            let mut worst_r = 0.0f64;
            for (w, r) in ws.iter().zip(&rot) {
                let q: JointVector = std::array::from_fn(|j| f64::from(w[j]));
                worst_r = worst_r.max((panda.pen_tip(&q).rotation - r).norm());
            }
            assert!(worst_r <= 1e-12, "worst rotation {worst_r:e}");
        }
    }

    #[test]
    fn other_origins_fall_back_to_the_general_chain() {
        // A joint origin tilted by 0.1 rad is not an axis permutation: no specialised FK,
        // and positions still come from the general chain.
        let tilted = PANDA_URDF.replacen(
            r#"rpy="-1.5707963267948966 0 0""#,
            r#"rpy="-1.4707963267948966 0 0""#,
            1,
        );
        assert_ne!(tilted, PANDA_URDF, "the URDF spells the origin as expected");
        let panda = Panda::from_urdf_str(&tilted).expect("still a valid chain");
        assert!(panda.position_fk().is_none());
        let q = READY_POSE;
        assert_eq!(panda.pen_tip_position(&q), panda.pen_tip(&q).translation);
        let w = [0.1f32, -0.7, 0.2, -2.3, 0.1, 1.6, 0.8, 1.0];
        let mut out = [[0.0; 3]; 1];
        panda.pen_tip_positions_into(&[w], &mut out);
        let q: JointVector = std::array::from_fn(|j| f64::from(w[j]));
        assert_eq!(Vector3::from(out[0]), panda.pen_tip(&q).translation);
        // A permutation with the wrong numbers would be caught by the construction check;
        // the default Panda has its specialised FK.
        assert!(Panda::default().position_fk().is_some());
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let panda = Panda::default();
        let mut rng = StdRng::seed_from_u64(7);
        for _ in 0..50 {
            let q = random_q(&mut rng, &panda);
            let (tip, jac) = panda.jacobian(&q);
            let h = 1e-6;
            for j in 0..JOINTS {
                let mut qp = q;
                qp[j] += h;
                let mut qm = q;
                qm[j] -= h;
                let (fp, fm) = (panda.pen_tip(&qp), panda.pen_tip(&qm));
                let lin = (fp.translation - fm.translation) / (2.0 * h);
                // Angular: (R+ - R-) R^T / 2h is skew([w]).
                let s = (fp.rotation - fm.rotation) * tip.rotation.transpose() / (2.0 * h);
                let w = Vector3::new(s[(2, 1)], s[(0, 2)], s[(1, 0)]);
                let col = jac.column(j);
                for k in 0..3 {
                    assert!((col[k] - lin[k]).abs() < 1e-6, "lin j{j} k{k}");
                    assert!((col[3 + k] - w[k]).abs() < 1e-6, "ang j{j} k{k}");
                }
            }
        }
    }

    #[test]
    fn ik_round_trip_on_random_reachable_poses() {
        let panda = Panda::default();
        let mut rng = StdRng::seed_from_u64(11);
        let opts = IkOptions::default();
        let mut solved = 0;
        for _ in 0..200 {
            let q_true = random_q(&mut rng, &panda);
            let target = panda.pen_tip(&q_true);
            // Seed near the true solution, as the generator does (previous solution).
            let seed: JointVector =
                std::array::from_fn(|j| q_true[j] + rng.random_range(-0.05..0.05));
            let q = panda
                .ik(&target, &seed, &opts)
                .expect("reachable pose near the seed");
            let got = panda.pen_tip(&q);
            assert!((got.translation - target.translation).norm() <= opts.position_tolerance);
            assert!(
                orientation_error_vector(&target.rotation, &got.rotation).norm()
                    <= opts.orientation_tolerance
            );
            assert!(panda.limit_margin(&q) >= 0.0);
            solved += 1;
        }
        assert_eq!(solved, 200);
    }

    #[test]
    fn no_solution_outside_the_limits() {
        let panda = Panda::default();
        let opts = IkOptions::default();
        // Out of reach: 2 m in front of the robot.
        let mut far = panda.pen_tip(&READY_POSE);
        far.translation = Vector3::new(2.0, 0.0, 0.3);
        assert!(matches!(
            panda.ik(&far, &READY_POSE, &opts),
            Err(IkError::NoConvergence { .. })
        ));
        // Reachable only with joint 4 beyond its upper limit: a pose from q4 = +0.5.
        let mut q_bad = READY_POSE;
        q_bad[3] = 0.5;
        let target = panda.pen_tip(&q_bad);
        match panda.ik(&target, &READY_POSE, &opts) {
            Ok(q) => assert!(panda.limit_margin(&q) >= 0.0),
            Err(e) => assert!(matches!(e, IkError::NoConvergence { .. })),
        }
        // Whatever the seed, iterates are clamped: a seed outside the limits comes back inside.
        let mut seed = READY_POSE;
        seed[5] = 10.0;
        if let Ok(q) = panda.ik(&panda.pen_tip(&READY_POSE), &seed, &opts) {
            assert!(panda.limit_margin(&q) >= 0.0);
        }
        assert_eq!(
            panda.ik(&far, &[f64::NAN; JOINTS], &opts),
            Err(IkError::NonFinite)
        );
    }
}
