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
//!   pen path [`crate::features::pen_path`] (128 forward-kinematics evaluations).
//!
//! Orientation error is the rotation angle between the tool frame and the commanded one
//! (tool z straight down, tool x along base +x): `θ = 2 asin(‖R − R_cmd‖_F / (2√2))`, exact
//! for small angles.

use std::cell::RefCell;

use guardian_shared::trajectory::{self, InvalidTrajectory, Resampled, TOOL, Waypoint};
use guardian_shared::workcell::{Workcell, WorkcellKind, WorkcellViolation};
use nalgebra::{Matrix3, Vector3};

use crate::geometry::PlanGeometry;
use crate::kinematics::{Frame, Panda};
use crate::preprocess::{cumulative_lengths, default_panda};

/// Result of [`inspect`].
#[derive(Debug, Clone)]
pub struct Inspection {
    /// The model input (validated, resampled to 128 x 8 uniform in pen-tip path length).
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

/// Tool orientation the workcell commands: tool z down (−z of the base), tool x along +x.
pub fn commanded_rotation() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// Rotation angle (rad) between `r` and the commanded orientation.
pub fn orientation_error(r: &Matrix3<f64>) -> f64 {
    let f = (r - commanded_rotation()).norm();
    2.0 * (f / (2.0 * std::f64::consts::SQRT_2)).min(1.0).asin()
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
    let half = 0.5 * cell.canvas_side;
    let outside = ((p.x - cell.canvas_x).abs() - half)
        .max((p.y - cell.canvas_y).abs() - half)
        .max(0.0);
    // 0 inside the square, 1 at the margin.
    let canvas = if cell.margin > 0.0 {
        outside / cell.margin
    } else if outside > 0.0 {
        f64::INFINITY
    } else {
        0.0
    };
    let dz = p.z - cell.canvas_z;
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
    [orient, height, canvas, hover]
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
/// kinematics evaluation per waypoint (the default robot).
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

/// [`inspect`] with a given robot. One pass of the specialised forward kinematics
/// ([`Panda::pen_tip_poses_into`]) gives every waypoint's pen-tip position and tool
/// rotation; the positions are those [`crate::preprocess::preprocess_with`] uses, summed the
/// same way, so the model input is identical. Uses per-thread buffers: after the longest
/// trajectory has been seen once, nothing is allocated.
pub fn inspect_with(
    panda: &Panda,
    cell: &Workcell,
    raw: &[Waypoint],
) -> Result<Inspection, InvalidTrajectory> {
    trajectory::validate(raw)?;
    let n = raw.len();
    let run = |s: &mut Scratch| {
        if s.positions.len() < n {
            s.positions.resize(n, [0.0; 3]);
            s.rotations.resize(n, Matrix3::zeros());
            s.lengths.resize(n, 0.0);
        }
        let (positions, rotations, lengths) = (
            &mut s.positions[..n],
            &mut s.rotations[..n],
            &mut s.lengths[..n],
        );
        panda.pen_tip_poses_into(raw, positions, rotations);
        cumulative_lengths(positions, lengths);
        let resampled = trajectory::resample(raw, lengths);
        let poses = positions
            .iter()
            .zip(rotations.iter())
            .zip(raw)
            .map(|((p, r), w)| (Vector3::from(*p), *r, w[TOOL]));
        let (violation, score) = check_poses(cell, poses);
        Inspection {
            resampled,
            violation,
            score,
        }
    };
    Ok(SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut s) => run(&mut s),
        Err(_) => run(&mut Scratch::default()),
    }))
}

/// The plan geometry of a resampled trajectory (see [`PlanGeometry`]); `None` if the pen
/// never touches the canvas.
pub fn plan_geometry(x: &Resampled) -> Option<PlanGeometry> {
    let path = crate::features::pen_path(x);
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

    #[test]
    fn inspect_resamples_exactly_like_preprocess() {
        // A pen-up swing of joint 1 from the ready pose (outside the canvas: a violation,
        // but the resampled input must still equal preprocess's).
        let mut ws = Vec::new();
        for k in 0..50 {
            let mut w = [0.0f32; 8];
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
