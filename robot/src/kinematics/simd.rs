//! The pen-tip position (and tool axes) forward kinematics specialised to a chain whose
//! joint origins are signed axis permutations: blocks of waypoints at once, compiled for the
//! widest SIMD instruction set of the CPU (runtime dispatch), checked against the general
//! chain when built.

use guardian_shared::trajectory::Waypoint;
use nalgebra::{Matrix3, Vector3};

use super::{JointVector, MAX_JOINTS, Robot};

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
/// specialised FK is built; above it [`Robot`] keeps using the general chain.
pub const POSITION_FK_TOLERANCE: f64 = 1e-12;

/// Pen-tip position forward kinematics specialised to a chain of revolute joints about z
/// whose joint origin rotations are signed axis permutations (the Panda's and the UR5e's are
/// the identity or +-pi/2 about x).
///
/// Evaluated from the pen tip back to the base: per joint one rotation about z (4
/// multiplies), a signed axis permutation (no arithmetic) and the origin offset; f64, no
/// allocation, no 4x4 or 3x3 products. It is built by [`Robot`] from the numbers of the
/// loaded chain (URDF or built-in) and checked at construction against the general chain
/// ([`Robot::pen_tip`]) at several joint vectors; if a joint is not revolute about z, the
/// origins are not signed permutations (to 1e-12 per entry) or the check misses
/// [`POSITION_FK_TOLERANCE`], there is no `PositionFk` and [`Robot`] uses the general chain,
/// so another URDF cannot be silently mis-computed. The general chain stays the source of truth and serves IK and
/// Jacobians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionFk {
    /// Joints of the chain.
    joints: usize,
    rotations: [AxisMap; MAX_JOINTS],
    offsets: [[f64; 3]; MAX_JOINTS],
    /// The pen tip in the frame after the last joint (flange offset and tool composed).
    tip: [f64; 3],
    /// The tool's x and z axes in the frame after the last joint.
    tool_axes: [[f64; 3]; 2],
}

/// A computation over the blocks of a chain, given its joint count as the constant `N` of
/// the lane tables (and `joints <= N`, the count the loops run to): see
/// [`PositionFk::with_joints`].
pub trait WithJoints {
    /// What the computation returns.
    type Output;
    /// Run with tables of `N` joints, of which the chain uses the first `joints`.
    fn with_joints<const N: usize>(self, joints: usize) -> Self::Output;
}

/// Waypoints per block of [`PositionFk::positions_into`] (the sines and cosines of a block
/// are computed together, which the compiler vectorises).
pub const FK_LANES: usize = 8;

impl PositionFk {
    pub(super) fn from_robot(robot: &Robot) -> Option<Self> {
        let mut rotations = [AxisMap {
            src: [0, 1, 2],
            sign: [1.0; 3],
        }; MAX_JOINTS];
        let mut offsets = [[0.0; 3]; MAX_JOINTS];
        let n = robot.joints();
        for j in 0..n {
            let joint = &robot.joints[j];
            if !joint.about_z() {
                return None;
            }
            rotations[j] = AxisMap::from_matrix(&joint.origin.rotation, 1e-12)?;
            offsets[j] = joint.origin.translation.into();
        }
        let tip = robot.flange.translation + robot.flange.rotation * robot.tool.translation;
        let tool = robot.flange.rotation * robot.tool.rotation;
        let fk = Self {
            joints: n,
            rotations,
            offsets,
            tip: tip.into(),
            tool_axes: [tool.column(0).into(), tool.column(2).into()],
        };
        // Verify against the general chain at the limits, their middle, a mix of both and
        // an arbitrary pose.
        let (lo, hi) = (robot.q_min(), robot.q_max());
        let mut probes = [[0.0; MAX_JOINTS]; 5];
        for j in 0..n {
            probes[0][j] = (0.3 + 0.1 * j as f64).clamp(lo[j], hi[j]);
            probes[1][j] = 0.5 * (lo[j] + hi[j]);
            probes[2][j] = lo[j];
            probes[3][j] = hi[j];
            probes[4][j] = if j % 2 == 0 { lo[j] } else { hi[j] };
        }
        for q in &probes {
            let general = robot.pen_tip(q);
            let fast = Vector3::from(fk.position(q));
            let d = (general.translation - fast).norm();
            if d.is_nan() || d > POSITION_FK_TOLERANCE {
                return None;
            }
            let mut p = [[0.0; 3]];
            let mut r = [Matrix3::zeros()];
            let w: Waypoint = std::array::from_fn(|j| if j < n { q[j] as f32 } else { 0.0 });
            fk.poses_into(&[w], &mut p, &mut r);
            let qf = robot.joints_of(&w);
            let e = (robot.pen_tip(&qf).rotation - r[0]).norm();
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

    /// Run `op` with this chain's joint count as a constant where it is a shipped arm's (6:
    /// the UR5e, 7: the Panda), so their lane tables and joint loops have fixed sizes; any
    /// other count runs with tables of [`MAX_JOINTS`]. Inlined, so the SIMD instruction set
    /// of a caller under [`pulp::Arch::dispatch`] applies.
    #[inline(always)]
    pub fn with_joints<W: WithJoints>(&self, op: W) -> W::Output {
        match self.joints {
            6 => op.with_joints::<6>(6),
            7 => op.with_joints::<7>(7),
            n => op.with_joints::<MAX_JOINTS>(n),
        }
    }

    /// Pen-tip positions of a block of waypoints (tables of `N` joints, the first `joints`
    /// used; see [`PositionFk::with_joints`]).
    #[inline(always)]
    fn block_positions<const N: usize>(&self, ws: &[Waypoint], joints: usize) -> Lanes {
        let (s, c) = joint_sin_cos::<N>(ws, joints);
        let mut v = self.tip.map(|x| [x; FK_LANES]);
        for j in (0..joints).rev() {
            v = self.joint_lanes(j, &s[j], &c[j], &v, true);
        }
        v
    }

    /// Pen-tip positions and the tool's x and z axes (base frame) of a block of waypoints
    /// (tables of `N` joints, the first `joints` used).
    #[inline(always)]
    fn block_poses<const N: usize>(&self, ws: &[Waypoint], joints: usize) -> PoseLanes {
        let (s, c) = joint_sin_cos::<N>(ws, joints);
        let mut p = self.tip.map(|x| [x; FK_LANES]);
        let mut x = self.tool_axes[0].map(|v| [v; FK_LANES]);
        let mut z = self.tool_axes[1].map(|v| [v; FK_LANES]);
        for j in (0..joints).rev() {
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
        for j in (0..self.joints).rev() {
            let (s, c) = q[j].sin_cos();
            let r = [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]];
            let m = &self.rotations[j];
            let t = &self.offsets[j];
            v = std::array::from_fn(|i| m.sign[i] * r[m.src[i]] + t[i]);
        }
        v
    }

    /// Pen-tip positions and tool axes of a block of at most [`FK_LANES`] waypoints (lanes
    /// past `ws.len()` hold the pose at all-zero joints), with tables of `N` joints of which
    /// the chain uses the first `joints`: the arguments [`PositionFk::with_joints`] passes to
    /// an operation. Inlined into its caller, so a caller compiled for a wider SIMD
    /// instruction set (a [`pulp::WithSimd`] run under [`pulp::Arch::dispatch`]) gets the
    /// block vectorised with it.
    #[inline(always)]
    pub fn pose_lanes<const N: usize>(&self, ws: &[Waypoint], joints: usize) -> PoseLanes {
        self.block_poses::<N>(ws, joints)
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
        let fk = self.fk;
        fk.with_joints(self)
    }
}

impl WithJoints for PositionsOp<'_> {
    type Output = ();

    #[inline(always)]
    fn with_joints<const N: usize>(self, joints: usize) {
        for (ws, os) in self
            .waypoints
            .chunks(FK_LANES)
            .zip(self.out.chunks_mut(FK_LANES))
        {
            let n = ws.len().min(os.len());
            let v = self.fk.block_positions::<N>(&ws[..n], joints);
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
        let fk = self.fk;
        fk.with_joints(self)
    }
}

impl WithJoints for PosesOp<'_> {
    type Output = ();

    #[inline(always)]
    fn with_joints<const N: usize>(self, joints: usize) {
        let blocks = self
            .waypoints
            .chunks(FK_LANES)
            .zip(self.positions.chunks_mut(FK_LANES))
            .zip(self.rotations.chunks_mut(FK_LANES));
        for ((ws, ps), rs) in blocks {
            let n = ws.len().min(ps.len()).min(rs.len());
            let b = self.fk.pose_lanes::<N>(&ws[..n], joints);
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
type LaneTable<const N: usize> = [[f64; FK_LANES]; N];

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
fn joint_sin_cos<const N: usize>(ws: &[Waypoint], joints: usize) -> (LaneTable<N>, LaneTable<N>) {
    let mut s = [[0.0f64; FK_LANES]; N];
    let mut c = [[0.0f64; FK_LANES]; N];
    for j in 0..joints.min(N) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{PANDA_URDF, READY_POSE, RobotDescription};
    use rand::{Rng, SeedableRng, rngs::StdRng};

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
        for robot in [
            Robot::panda(),
            Robot::from_embedded_urdf().expect("shipped URDF parses"),
            Robot::panda().with_tool(0.2, 0.3),
            RobotDescription::named("ur5e").unwrap().robot,
        ] {
            let fk = *robot
                .position_fk()
                .expect("the Panda's origins are permutations");
            let mut rng = StdRng::seed_from_u64(17);
            let mut ws = Vec::new();
            let mut worst = 0.0f64;
            for _ in 0..2000 {
                // Anywhere within the limits, the limits included.
                let mut q: JointVector = [0.0; MAX_JOINTS];
                for j in 0..robot.joints() {
                    q[j] = rng.random_range(robot.q_min()[j]..=robot.q_max()[j]);
                }
                let general = robot.pen_tip(&q).translation;
                worst = worst.max((Vector3::from(fk.position(&q)) - general).norm());
                worst = worst.max((robot.pen_tip_position(&q) - general).norm());
                let mut w = [0.0f32; guardian_shared::trajectory::SLOTS];
                for j in 0..robot.joints() {
                    w[j] = q[j] as f32;
                }
                ws.push(w);
            }
            // The batch path on f32 waypoints, including a partial last block.
            let ws = &ws[..ws.len() - 3];
            let mut out = vec![[0.0; 3]; ws.len()];
            robot.pen_tip_positions_into(ws, &mut out);
            for (w, o) in ws.iter().zip(&out) {
                let q = robot.joints_of(w);
                let general = robot.pen_tip_position_general(&q);
                worst = worst.max((Vector3::from(*o) - general).norm());
            }
            assert!(worst <= 1e-12, "worst {worst:e} m");
            // Poses: positions bit for bit those of the position path, rotations equal to
            // the general chain's.
            let mut pos = vec![[0.0; 3]; ws.len()];
            let mut rot = vec![Matrix3::zeros(); ws.len()];
            robot.pen_tip_poses_into(ws, &mut pos, &mut rot);
            assert_eq!(pos, out);
            let mut worst_r = 0.0f64;
            for (w, r) in ws.iter().zip(&rot) {
                let q = robot.joints_of(w);
                worst_r = worst_r.max((robot.pen_tip(&q).rotation - r).norm());
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
        let robot = Robot::from_urdf_str(&tilted).expect("still a valid chain");
        assert!(robot.position_fk().is_none());
        let q = READY_POSE;
        assert_eq!(robot.pen_tip_position(&q), robot.pen_tip(&q).translation);
        let w =
            guardian_shared::trajectory::waypoint(&[0.1f32, -0.7, 0.2, -2.3, 0.1, 1.6, 0.8], 1.0);
        let mut out = [[0.0; 3]; 1];
        robot.pen_tip_positions_into(&[w], &mut out);
        let q = robot.joints_of(&w);
        assert_eq!(Vector3::from(out[0]), robot.pen_tip(&q).translation);
        // A permutation with the wrong numbers would be caught by the construction check;
        // the default Panda has its specialised FK.
        assert!(Robot::panda().position_fk().is_some());
    }
}
