//! The geometric Jacobian of the pen tip and the damped-least-squares inverse kinematics.

use nalgebra::{Matrix3, Matrix6, Matrix6x1, Vector3, Vector6};

use super::{Frame, Jacobian, JointKind, JointVector, MAX_JOINTS, Robot};

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

impl Robot {
    /// Pen-tip frame and its geometric Jacobian (base frame); the columns past the robot's
    /// joints are zero.
    pub fn jacobian(&self, q: &JointVector) -> (Frame, Jacobian) {
        let n = self.joints();
        let mut axes = [Vector3::zeros(); MAX_JOINTS];
        let mut origins = [Vector3::zeros(); MAX_JOINTS];
        let mut t = Frame::identity();
        for j in 0..n {
            let joint = &self.joints[j];
            t = joint.apply(&t, q[j]);
            axes[j] = if joint.about_z() {
                t.rotation.column(2).into_owned()
            } else {
                t.rotation * joint.axis
            };
            origins[j] = t.translation;
        }
        let tip = t.compose(&self.flange).compose(&self.tool);
        let mut jac = Jacobian::zeros();
        for j in 0..n {
            let (lin, ang) = match self.joints[j].kind {
                JointKind::Revolute => (axes[j].cross(&(tip.translation - origins[j])), axes[j]),
                JointKind::Prismatic => (axes[j], Vector3::zeros()),
            };
            jac.fixed_view_mut::<3, 1>(0, j).copy_from(&lin);
            jac.fixed_view_mut::<3, 1>(3, j).copy_from(&ang);
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
        let q = self.clamp(q);
        let (tip, jacobian) = self.jacobian(&q);
        IkState { q, tip, jacobian }
    }

    /// [`Robot::ik`] from a state whose frame and Jacobian are already known, updated in
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
        let (n, lo, hi) = (self.joints(), self.q_min(), self.q_max());
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
            for j in 0..n {
                state.q[j] = (state.q[j] + dq[j] * scale).clamp(lo[j], hi[j]);
            }
        }
        Err(IkError::NoConvergence {
            iterations: options.max_iterations,
            position_error,
            orientation_error,
        })
    }
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
    use crate::kinematics::READY_POSE;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    fn random_q(rng: &mut StdRng, robot: &Robot) -> JointVector {
        let mut q = [0.0; MAX_JOINTS];
        for j in 0..robot.joints() {
            let (lo, hi) = (robot.q_min()[j], robot.q_max()[j]);
            let pad = 0.1 * (hi - lo);
            q[j] = rng.random_range(lo + pad..hi - pad);
        }
        q
    }

    /// A 6-joint arm mixing joint kinds and axes (revolute about z, y, x, a tilted axis, and
    /// a prismatic joint), with a fixed joint between two movable ones: the general chain.
    const MIXED_URDF: &str = r#"<robot name="mixed">
      <link name="l0"/><link name="l1"/><link name="l2"/><link name="l2b"/><link name="l3"/>
      <link name="l4"/><link name="l5"/><link name="l6"/><link name="tip"/>
      <joint name="j1" type="revolute"><parent link="l0"/><child link="l1"/>
        <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
        <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
        <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 1 0"/>
        <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
      <joint name="fixed" type="fixed"><parent link="l2"/><child link="l2b"/>
        <origin xyz="0.05 0 0.1" rpy="0 0.2 0"/></joint>
      <joint name="slide" type="prismatic"><parent link="l2b"/><child link="l3"/>
        <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/>
        <limit lower="0.1" upper="0.5" effort="1" velocity="0.5"/></joint>
      <joint name="j4" type="revolute"><parent link="l3"/><child link="l4"/>
        <origin xyz="0.1 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/>
        <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
      <joint name="j5" type="revolute"><parent link="l4"/><child link="l5"/>
        <origin xyz="0.05 0 0" rpy="0 0 0"/><axis xyz="0 1 1"/>
        <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
      <joint name="j6" type="revolute"><parent link="l5"/><child link="l6"/>
        <origin xyz="0.05 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
        <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
      <joint name="flange" type="fixed"><parent link="l6"/><child link="tip"/>
        <origin xyz="0 0 0.08" rpy="0 0 0"/></joint>
    </robot>"#;

    fn mixed() -> Robot {
        Robot::from_urdf_chain(MIXED_URDF, "mixed", None, Some("tip"))
            .expect("a valid mixed chain")
            .with_tool(0.05, 0.0)
    }

    fn robots() -> Vec<Robot> {
        vec![
            Robot::panda(),
            crate::kinematics::RobotDescription::named("ur5e")
                .unwrap()
                .robot,
            mixed(),
        ]
    }

    /// The general chain of the mixed arm against the product of its URDF transforms, the
    /// prismatic joint moving along its axis.
    #[test]
    fn a_mixed_chain_is_the_product_of_its_joints() {
        use nalgebra::{Rotation3, Unit};
        let robot = mixed();
        assert_eq!(robot.joints(), 6);
        assert!(
            robot.position_fk().is_none(),
            "not revolute about z: general chain"
        );
        assert_eq!(
            robot.joint_list()[2].kind,
            crate::kinematics::JointKind::Prismatic
        );
        let q = [0.4, -0.3, 0.25, 0.7, -0.5, 1.1];
        let frame = |xyz: [f64; 3], rpy: [f64; 3]| Frame::from_xyz_rpy(xyz, rpy);
        let rot = |axis: [f64; 3], a: f64| Frame {
            rotation: Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), a)
                .into_inner(),
            translation: Vector3::zeros(),
        };
        let slide = Frame {
            rotation: Matrix3::identity(),
            translation: Vector3::new(q[2], 0.0, 0.0),
        };
        let want = frame([0.0, 0.0, 0.3], [0.0; 3])
            .compose(&rot([0.0, 0.0, 1.0], q[0]))
            .compose(&frame([0.0, 0.0, 0.1], [0.0; 3]))
            .compose(&rot([0.0, 1.0, 0.0], q[1]))
            .compose(&frame([0.05, 0.0, 0.1], [0.0, 0.2, 0.0]))
            .compose(&slide)
            .compose(&frame([0.1, 0.0, 0.0], [0.0; 3]))
            .compose(&rot([1.0, 0.0, 0.0], q[3]))
            .compose(&frame([0.05, 0.0, 0.0], [0.0; 3]))
            .compose(&rot([0.0, 1.0, 1.0], q[4]))
            .compose(&frame([0.05, 0.0, 0.0], [0.0; 3]))
            .compose(&rot([0.0, 0.0, 1.0], q[5]))
            .compose(&frame([0.0, 0.0, 0.08], [0.0; 3]));
        let got = robot.flange(&crate::kinematics::joint_vector(&q));
        assert!((got.translation - want.translation).norm() < 1e-12);
        assert!((got.rotation - want.rotation).amax() < 1e-12);
        assert_eq!(robot.q_min()[2], 0.1);
        assert_eq!(robot.joint_list()[2].velocity, Some(0.5));
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        for robot in robots() {
            let mut rng = StdRng::seed_from_u64(7);
            for _ in 0..50 {
                let q = random_q(&mut rng, &robot);
                let (tip, jac) = robot.jacobian(&q);
                let h = 1e-6;
                for j in 0..MAX_JOINTS {
                    let mut qp = q;
                    qp[j] += h;
                    let mut qm = q;
                    qm[j] -= h;
                    let (fp, fm) = (robot.pen_tip(&qp), robot.pen_tip(&qm));
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
    }

    #[test]
    fn ik_round_trip_on_random_reachable_poses() {
        for robot in robots() {
            let mut rng = StdRng::seed_from_u64(11);
            let opts = IkOptions::default();
            let mut solved = 0;
            for _ in 0..200 {
                let q_true = random_q(&mut rng, &robot);
                let target = robot.pen_tip(&q_true);
                // Seed near the true solution, as the generator does (previous solution).
                let mut seed = q_true;
                for q in &mut seed[..robot.joints()] {
                    *q += rng.random_range(-0.05..0.05);
                }
                let q = robot
                    .ik(&target, &seed, &opts)
                    .expect("reachable pose near the seed");
                let got = robot.pen_tip(&q);
                assert!((got.translation - target.translation).norm() <= opts.position_tolerance);
                assert!(
                    orientation_error_vector(&target.rotation, &got.rotation).norm()
                        <= opts.orientation_tolerance
                );
                assert!(robot.limit_margin(&q) >= 0.0);
                solved += 1;
            }
            assert_eq!(solved, 200, "{}", robot.name());
        }
    }

    #[test]
    fn no_solution_outside_the_limits() {
        let robot = Robot::panda();
        let opts = IkOptions::default();
        // Out of reach: 2 m in front of the robot.
        let mut far = robot.pen_tip(&READY_POSE);
        far.translation = Vector3::new(2.0, 0.0, 0.3);
        assert!(matches!(
            robot.ik(&far, &READY_POSE, &opts),
            Err(IkError::NoConvergence { .. })
        ));
        // Reachable only with joint 4 beyond its upper limit: a pose from q4 = +0.5.
        let mut q_bad = READY_POSE;
        q_bad[3] = 0.5;
        let target = robot.pen_tip(&q_bad);
        match robot.ik(&target, &READY_POSE, &opts) {
            Ok(q) => assert!(robot.limit_margin(&q) >= 0.0),
            Err(e) => assert!(matches!(e, IkError::NoConvergence { .. })),
        }
        // Whatever the seed, iterates are clamped: a seed outside the limits comes back inside.
        let mut seed = READY_POSE;
        seed[5] = 10.0;
        if let Ok(q) = robot.ik(&robot.pen_tip(&READY_POSE), &seed, &opts) {
            assert!(robot.limit_margin(&q) >= 0.0);
        }
        assert_eq!(
            robot.ik(&far, &[f64::NAN; MAX_JOINTS], &opts),
            Err(IkError::NonFinite)
        );
    }
}
