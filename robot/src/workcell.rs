//! The physical side of a check: workcell rules on every waypoint and the plan geometry of
//! the pen path. This module is the one place outside the embedder that runs forward
//! kinematics for a check:
//!
//! * [`inspect`] validates the raw waypoints, computes the pen-tip frame of each waypoint
//!   **once**, checks the [`Workcell`] rules on those frames, and derives from their
//!   positions the cumulative path length that resampling needs (the same numbers
//!   [`crate::preprocess::preprocess`] computes, so the resampled model input is identical);
//! * [`plan_geometry`] describes the drawing of a resampled trajectory (centre, size,
//!   pen-down length, strokes, start / end, direction; un-normalised, in metres) from the
//!   pen path of the robot ([`crate::pen::pen_path_with`], 128 forward-kinematics
//!   evaluations).
//!
//! Orientation error is the rotation angle between the tool frame and the commanded one
//! (tool z straight down, tool x along base +x): `θ = 2 asin(‖R − R_cmd‖_F / (2√2))`, exact
//! for small angles.

use std::cell::RefCell;

use guardian_shared::trajectory::{self, InvalidTrajectory, Resampled, TOOL, Waypoint};
use guardian_shared::workcell::{Workcell, WorkcellKind, WorkcellViolation};
use nalgebra::{Matrix3, Vector3};

use crate::geometry::PlanGeometry;
use crate::kinematics::default_panda;
use crate::kinematics::{FK_LANES, Frame, PositionFk, Robot, WithJoints};
use crate::pen::PenPoint;

/// Result of [`inspect`].
#[derive(Debug, Clone)]
pub struct Inspection {
    /// The model input (validated, resampled to 128 waypoints uniform in pen-tip path
    /// length).
    pub resampled: Resampled,
    /// The first waypoint that breaks a workcell rule (rules in the order orientation,
    /// pen height, canvas, hover height at that waypoint); `None` if every waypoint obeys
    /// them or the rules are disabled.
    pub violation: Option<WorkcellViolation>,
    /// The largest deviation over every waypoint and rule, each divided by its tolerance:
    /// `> 1` exactly when there is a violation (0 when the rules are disabled). Used as a
    /// continuous score for ROC curves.
    pub score: f32,
}

/// Cumulative polyline length through `positions` into `out` (element 0 is 0): the one
/// summation every resampling length comes from.
pub(crate) fn cumulative_lengths(positions: &[[f64; 3]], out: &mut [f64]) {
    let mut total = 0.0;
    for (i, o) in out.iter_mut().enumerate() {
        if i > 0 {
            let (a, b) = (positions[i - 1], positions[i]);
            let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            total += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        }
        *o = total;
    }
}

/// Tool orientation the workcell commands: tool z down (−z of the base), tool x along +x.
pub fn commanded_rotation() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// Rotation angle (rad) between `r` and the commanded orientation.
pub fn orientation_error(r: &Matrix3<f64>) -> f64 {
    angle_of_norm((r - commanded_rotation()).norm())
}

/// Normalised deviations of one pen-tip frame from the workcell rules, in rule order
/// (orientation, pen height, canvas, hover height); each `> 1` breaks that rule.
fn deviations(
    cell: &Workcell,
    p: Vector3<f64>,
    rotation: &Matrix3<f64>,
    pen_down: bool,
) -> [f64; 4] {
    let orient = orientation_error(rotation) / cell.orientation_tolerance;
    let [height, canvas, hover] = position_deviations(cell, [p.x, p.y, p.z], pen_down);
    [orient, height, canvas, hover]
}

/// The position part of [`deviations`]: pen height, canvas, hover height.
#[inline(always)]
fn position_deviations(cell: &Workcell, p: [f64; 3], pen_down: bool) -> [f64; 3] {
    let half = 0.5 * cell.canvas_side;
    let outside = ((p[0] - cell.canvas_x).abs() - half)
        .max((p[1] - cell.canvas_y).abs() - half)
        .max(0.0);
    // 0 inside the square, 1 at the margin.
    let canvas = if cell.margin > 0.0 {
        outside / cell.margin
    } else if outside > 0.0 {
        f64::INFINITY
    } else {
        0.0
    };
    let dz = p[2] - cell.canvas_z;
    let (height, hover) = if pen_down {
        (dz.abs() / cell.height_tolerance, 0.0)
    } else {
        let below = (-dz).max(0.0) / cell.height_tolerance;
        let above = if cell.margin > 0.0 {
            (dz - cell.hover).max(0.0) / cell.margin
        } else if dz > cell.hover {
            f64::INFINITY
        } else {
            0.0
        };
        (0.0, below.max(above))
    };
    [height, canvas, hover]
}

/// `‖R − R_cmd‖_F` of the rotation with columns `x`, `z × x`, `z` (what
/// [`orientation_error`] takes the angle of), without building the matrix.
#[inline(always)]
fn orientation_norm(x: [f64; 3], z: [f64; 3]) -> f64 {
    let y = [
        z[1] * x[2] - z[2] * x[1],
        z[2] * x[0] - z[0] * x[2],
        z[0] * x[1] - z[1] * x[0],
    ];
    let sq = (x[0] - 1.0).powi(2)
        + x[1] * x[1]
        + x[2] * x[2]
        + y[0] * y[0]
        + (y[1] + 1.0).powi(2)
        + y[2] * y[2]
        + z[0] * z[0]
        + z[1] * z[1]
        + (z[2] + 1.0).powi(2);
    sq.sqrt()
}

/// The orientation error (rad) of a rotation `f = ‖R − R_cmd‖_F` away from the commanded
/// one, as in [`orientation_error`].
fn angle_of_norm(f: f64) -> f64 {
    2.0 * (f / (2.0 * std::f64::consts::SQRT_2)).min(1.0).asin()
}

const KINDS: [WorkcellKind; 4] = [
    WorkcellKind::ToolOrientation,
    WorkcellKind::PenHeight,
    WorkcellKind::OffCanvas,
    WorkcellKind::HoverHeight,
];

/// Check the workcell rules on pen-tip frames (one per waypoint, `tool[i]` its tool
/// channel): the first violation and the largest normalised deviation.
pub fn check_frames(
    cell: &Workcell,
    frames: &[Frame],
    tool: impl Iterator<Item = f32>,
) -> (Option<WorkcellViolation>, f32) {
    check_poses(
        cell,
        frames
            .iter()
            .zip(tool)
            .map(|(f, t)| (f.translation, f.rotation, t)),
    )
}

/// [`check_frames`] over (position, rotation, tool value) per waypoint.
fn check_poses(
    cell: &Workcell,
    poses: impl Iterator<Item = (Vector3<f64>, Matrix3<f64>, f32)>,
) -> (Option<WorkcellViolation>, f32) {
    if !cell.enabled {
        return (None, 0.0);
    }
    let mut first = None;
    let mut worst = 0.0f64;
    for (i, (p, r, t)) in poses.enumerate() {
        let d = deviations(cell, p, &r, t > 0.5);
        for (k, &v) in d.iter().enumerate() {
            // NaN (a degenerate frame) counts as a violation.
            if first.is_none() && (v > 1.0 || v.is_nan()) {
                first = Some(WorkcellViolation {
                    kind: KINDS[k],
                    index: u32::try_from(i).unwrap_or(u32::MAX),
                });
            }
            worst = worst.max(if v.is_nan() { f64::INFINITY } else { v });
        }
    }
    (first, worst as f32)
}

/// Validate `raw`, check the workcell rules on it and resample it, with one forward
/// kinematics evaluation per waypoint (the default robot, the Panda).
pub fn inspect(cell: &Workcell, raw: &[Waypoint]) -> Result<Inspection, InvalidTrajectory> {
    inspect_with(default_panda(), cell, raw)
}

/// Per-thread buffers of [`inspect_with`] (grown to the longest trajectory seen).
#[derive(Default)]
struct Scratch {
    positions: Vec<[f64; 3]>,
    rotations: Vec<Matrix3<f64>>,
    lengths: Vec<f64>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// [`inspect`] with a given robot: validated against its limits, the rules applied to its
/// tool frame. One pass of the forward kinematics gives every
/// waypoint's pen-tip position and tool axes; the positions are those
/// [`crate::preprocess::preprocess_with`] uses, summed the same way, so the model input is
/// identical. With the specialised FK ([`PositionFk`]) the pass and the rules run block by
/// block under runtime SIMD dispatch ([`InspectOp`]); otherwise through the general chain and
/// [`check_poses`]. Uses per-thread buffers: after the longest trajectory has been seen
/// once, nothing is allocated.
pub fn inspect_with(
    robot: &Robot,
    cell: &Workcell,
    raw: &[Waypoint],
) -> Result<Inspection, InvalidTrajectory> {
    inspect_in(robot, cell, &crate::cell::Cell::NONE, raw)
}

/// [`inspect_with`], then a cell's region rules ([`crate::cell::Cell::violation`]) on the
/// same tool-tip positions, for a plan that broke no workcell rule.
pub fn inspect_in(
    robot: &Robot,
    cell: &Workcell,
    rules: &crate::cell::Cell,
    raw: &[Waypoint],
) -> Result<Inspection, InvalidTrajectory> {
    trajectory::validate(raw, robot.limits())?;
    let n = raw.len();
    let run = |s: &mut Scratch| {
        if s.positions.len() < n {
            s.positions.resize(n, [0.0; 3]);
            s.lengths.resize(n, 0.0);
        }
        let (positions, lengths) = (&mut s.positions[..n], &mut s.lengths[..n]);
        let (violation, score) = match robot.position_fk() {
            Some(fk) => pulp::Arch::new().dispatch(InspectOp {
                fk,
                cell,
                raw,
                positions,
            }),
            None => {
                if s.rotations.len() < n {
                    s.rotations.resize(n, Matrix3::zeros());
                }
                let rotations = &mut s.rotations[..n];
                robot.pen_tip_poses_into(raw, positions, rotations);
                let poses = positions
                    .iter()
                    .zip(rotations.iter())
                    .zip(raw)
                    .map(|((p, r), w)| (Vector3::from(*p), *r, w[TOOL]));
                check_poses(cell, poses)
            }
        };
        let violation = violation.or_else(|| rules.violation(positions));
        cumulative_lengths(positions, lengths);
        Inspection {
            resampled: trajectory::resample(raw, lengths, robot.joints()),
            violation,
            score,
        }
    };
    Ok(SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut s) => run(&mut s),
        Err(_) => run(&mut Scratch::default()),
    }))
}

/// The specialised forward kinematics and the workcell rules of a whole trajectory, block
/// by block, as one runtime-dispatched SIMD operation: pen-tip positions into `positions`,
/// and [`check_poses`]'s answer. The orientation rule is decided on `‖R − R_cmd‖` (monotone
/// in the angle), so no arc sine per waypoint; a waypoint near or past any limit is checked
/// again exactly as [`check_poses`] does, which decides the violation reported.
struct InspectOp<'a> {
    fk: &'a PositionFk,
    cell: &'a Workcell,
    raw: &'a [Waypoint],
    positions: &'a mut [[f64; 3]],
}

impl pulp::WithSimd for InspectOp<'_> {
    type Output = (Option<WorkcellViolation>, f32);

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> Self::Output {
        let fk = self.fk;
        fk.with_joints(self)
    }
}

impl WithJoints for InspectOp<'_> {
    type Output = (Option<WorkcellViolation>, f32);

    #[inline(always)]
    fn with_joints<const N: usize>(self, joints: usize) -> Self::Output {
        let cell = self.cell;
        // The norm at the tolerance, with a little slack so that rounding near the limit is
        // settled by the exact check; `None` (an unusual tolerance): check every waypoint.
        let tol = cell.orientation_tolerance;
        let bound = (tol.is_finite() && tol > 0.0 && tol < std::f64::consts::PI)
            .then(|| 2.0 * std::f64::consts::SQRT_2 * (0.5 * tol).sin() * (1.0 - 1e-9));
        let mut first = None;
        let mut worst_norm = 0.0f64;
        let mut worst_position = 0.0f64;
        let blocks = self
            .raw
            .chunks(FK_LANES)
            .zip(self.positions.chunks_mut(FK_LANES));
        for (b, (ws, ps)) in blocks.enumerate() {
            let n = ws.len().min(ps.len());
            let lanes = self.fk.pose_lanes::<N>(&ws[..n], joints);
            for (l, p) in ps[..n].iter_mut().enumerate() {
                *p = [lanes.p[0][l], lanes.p[1][l], lanes.p[2][l]];
            }
            if !cell.enabled {
                continue;
            }
            let mut norms = [0.0f64; FK_LANES];
            for (l, f) in norms.iter_mut().enumerate() {
                let x = [lanes.x[0][l], lanes.x[1][l], lanes.x[2][l]];
                let z = [lanes.z[0][l], lanes.z[1][l], lanes.z[2][l]];
                *f = orientation_norm(x, z);
            }
            for l in 0..n {
                let pen_down = ws[l][TOOL] > 0.5;
                let dev = position_deviations(cell, ps[l], pen_down);
                // NaN counts as near (it is a violation).
                let past = |v: f64, limit: f64| v > limit || v.is_nan();
                let near =
                    bound.is_none_or(|b| past(norms[l], b)) || dev.iter().any(|v| past(*v, 1.0));
                if near && first.is_none() {
                    let x = Vector3::new(lanes.x[0][l], lanes.x[1][l], lanes.x[2][l]);
                    let z = Vector3::new(lanes.z[0][l], lanes.z[1][l], lanes.z[2][l]);
                    let r = Matrix3::from_columns(&[x, z.cross(&x), z]);
                    let exact = deviations(cell, Vector3::from(ps[l]), &r, pen_down);
                    first = exact.iter().position(|v| *v > 1.0 || v.is_nan()).map(|k| {
                        WorkcellViolation {
                            kind: KINDS[k],
                            index: u32::try_from(b * FK_LANES + l).unwrap_or(u32::MAX),
                        }
                    });
                }
                worst_norm = worst_norm.max(norms[l]);
                for v in dev {
                    worst_position = worst_position.max(if v.is_nan() { f64::INFINITY } else { v });
                }
            }
        }
        if !cell.enabled {
            return (None, 0.0);
        }
        let orient = angle_of_norm(worst_norm) / tol;
        let orient = if orient.is_nan() {
            f64::INFINITY
        } else {
            orient
        };
        (first, worst_position.max(orient) as f32)
    }
}

/// The plan geometry of a resampled trajectory of `robot` (see [`PlanGeometry`]); `None` if
/// the pen never touches the canvas.
pub fn plan_geometry(robot: &Robot, x: &Resampled) -> Option<PlanGeometry> {
    plan_geometry_of_path(&crate::pen::pen_path_with(robot, x))
}

/// [`plan_geometry`] of an already computed pen path ([`crate::pen::pen_path`], e.g.
/// the one `guardian_models::embedder::Embedder::embed_with_pen_path` returns).
pub fn plan_geometry_of_path(path: &[PenPoint]) -> Option<PlanGeometry> {
    PlanGeometry::from_pen_path(path.iter().map(|p| ([p[0], p[1]], p[2] > 0.5)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preprocess::preprocess;

    #[test]
    fn orientation_error_is_the_rotation_angle() {
        let rc = commanded_rotation();
        assert!(orientation_error(&rc) < 1e-12);
        for a in [1e-4, 0.005, 0.05, 1.0] {
            let r = rc * nalgebra::Rotation3::from_euler_angles(0.0, a, 0.0).into_inner();
            assert!((orientation_error(&r) - a).abs() < 1e-9, "{a}");
        }
    }

    /// The block-wise SIMD inspection answers exactly like the rules applied to the general
    /// chain's full frames ([`check_frames`]): same first violation, same score (to
    /// rounding), on random walks from the ready pose under several rule settings (loose
    /// ones, so that some walks obey the rules and the first violation falls mid-plan).
    #[test]
    fn block_inspection_matches_the_rules_on_general_frames() {
        use rand::{Rng, SeedableRng};
        let robot = default_panda();
        let base = Workcell::default();
        let ready = robot.pen_tip(&crate::kinematics::READY_POSE).translation;
        let cells = [
            base,
            // Around the ready pose's pen tip, loose: violations appear mid-walk.
            Workcell {
                canvas_x: ready.x,
                canvas_y: ready.y,
                canvas_z: ready.z,
                canvas_side: 0.3,
                orientation_tolerance: 0.2,
                height_tolerance: 0.05,
                hover: 0.05,
                margin: 0.02,
                ..base
            },
            Workcell {
                canvas_x: ready.x,
                canvas_y: ready.y,
                canvas_z: ready.z,
                canvas_side: 1.0,
                orientation_tolerance: 1.5,
                height_tolerance: 0.5,
                hover: 0.5,
                margin: 0.0,
                ..base
            },
        ];
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let (mut violations, mut clean) = (0, 0);
        for round in 0..60 {
            let cell = &cells[round % cells.len()];
            let mut q = crate::kinematics::READY_POSE;
            let len = rng.random_range(2..150);
            let step = [0.002, 0.01, 0.03][round % 3];
            let mut ws = Vec::with_capacity(len);
            for _ in 0..len {
                for (j, v) in q.iter_mut().take(robot.joints()).enumerate() {
                    *v = (*v + rng.random_range(-step..step))
                        .clamp(robot.q_min()[j] + 0.01, robot.q_max()[j] - 0.01);
                }
                let mut w = [0.0f32; guardian_shared::trajectory::SLOTS];
                for (j, v) in q.iter().enumerate() {
                    w[j] = *v as f32;
                }
                w[TOOL] = if rng.random_bool(0.5) { 1.0 } else { 0.0 };
                ws.push(w);
            }
            let fast = inspect_with(robot, cell, &ws).unwrap();
            let frames: Vec<Frame> = ws
                .iter()
                .map(|w| robot.pen_tip(&crate::kinematics::joints_of(w)))
                .collect();
            let (violation, score) = check_frames(cell, &frames, ws.iter().map(|w| w[TOOL]));
            assert_eq!(fast.violation, violation, "round {round}");
            assert!(
                (fast.score - score).abs() <= 1e-5 * score.abs().max(1.0),
                "round {round}: {} vs {score}",
                fast.score
            );
            if violation.is_some() {
                violations += 1;
            } else {
                clean += 1;
            }
        }
        // Both outcomes were exercised.
        assert!(violations > 5 && clean > 5, "{violations} / {clean}");
    }

    #[test]
    fn inspect_resamples_exactly_like_preprocess() {
        // A pen-up swing of joint 1 from the ready pose (outside the canvas: a violation,
        // but the resampled input must still equal preprocess's).
        let mut ws = Vec::new();
        for k in 0..50 {
            let mut w = [0.0f32; guardian_shared::trajectory::SLOTS];
            for (j, v) in crate::kinematics::READY_POSE.iter().enumerate() {
                w[j] = *v as f32;
            }
            w[0] = 0.01 * k as f32;
            ws.push(w);
        }
        let a = inspect(&Workcell::default(), &ws).unwrap();
        assert_eq!(a.resampled, preprocess(&ws).unwrap());
        assert!(a.violation.is_some());
        assert!(a.score > 1.0);
        let off = Workcell {
            enabled: false,
            ..Workcell::default()
        };
        let b = inspect(&off, &ws).unwrap();
        assert_eq!((b.violation, b.score), (None, 0.0));
    }
}
