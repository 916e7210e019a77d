//! Near misses of a plan: the same plan stopped early ([`truncated`]), drawn mirrored
//! ([`mirrored`]) or with one stroke mirrored ([`mirrored_stroke`]), made from a resampled
//! plan by forward and inverse kinematics.
//!
//! The embedder puts a class's drawings close together, and a plan that stops after 80 % of
//! its path is often as close to them as another person's drawing of the class. It can
//! still be closer to the *same near miss of the enrolled examples*. The lab measures a
//! decision step built on that (`guardian-lab outliers --near-misses`: every enrolled
//! example's near misses embedded, a plan nearer to a near miss of its class than to the
//! class refused; `docs/report/log-2026-12-06.md`, "Near misses in the decision"). The
//! daemon does not use near misses.
//!
//! All three work on any serial arm: positions come from the robot's forward kinematics, new
//! poses from its IK seeded along the path, and every result goes through the one
//! preprocessing ([`crate::preprocess::preprocess_with`]), so a near miss is seen exactly
//! as a plan would be.

use guardian_shared::trajectory::{InvalidTrajectory, Resampled, STEPS, TOOL, Waypoint};

use crate::kinematics::{IkError, IkOptions, Robot};
use crate::preprocess::preprocess_with;

/// Height the pen is lifted by after a plan stops early (m): the lift of the drawings the
/// data set was generated with.
pub const LIFT: f64 = 0.02;

/// Making a near miss failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VariantError {
    /// The plan never puts the pen down (nothing to cut or mirror).
    #[error("the plan never puts the pen down")]
    NoPenDown,
    /// A pose of the variant is out of the arm's reach.
    #[error("a pose of the near miss is out of reach: {0}")]
    Ik(#[from] IkError),
    /// The variant is not a valid trajectory.
    #[error(transparent)]
    Invalid(#[from] InvalidTrajectory),
}

/// The pen is down on the segment from step `i` to step `i + 1`.
fn down(x: &Resampled, i: usize) -> bool {
    x[i][TOOL] > 0.5 && x[i + 1][TOOL] > 0.5
}

/// `x` stopped once `1 - share` of its pen-down path is drawn (`share` in (0, 1)), the pen
/// then lifted by [`LIFT`] straight up: what a plan that ends early draws.
pub fn truncated(robot: &Robot, x: &Resampled, share: f64) -> Result<Resampled, VariantError> {
    let mut p = [[0.0f64; 3]; STEPS];
    robot.pen_tip_positions_into(x, &mut p);
    let seg = |i: usize| {
        let d: f64 = (0..3).map(|a| (p[i + 1][a] - p[i][a]).powi(2)).sum();
        d.sqrt()
    };
    let total: f64 = (0..STEPS - 1).filter(|&i| down(x, i)).map(seg).sum();
    if total <= 0.0 {
        return Err(VariantError::NoPenDown);
    }
    let keep = total * (1.0 - share.clamp(0.0, 1.0));
    let mut out: Vec<Waypoint> = Vec::with_capacity(STEPS + 2);
    let mut drawn = 0.0;
    let mut cut = None;
    for i in 0..STEPS - 1 {
        out.push(x[i]);
        if !down(x, i) {
            continue;
        }
        let s = seg(i);
        if drawn + s >= keep {
            // Stop inside this segment, at the interpolated joints.
            let t = if s > 0.0 { (keep - drawn) / s } else { 0.0 };
            let q: Vec<f64> = (0..robot.joints())
                .map(|j| f64::from(x[i][j]) + t * (f64::from(x[i + 1][j]) - f64::from(x[i][j])))
                .collect();
            cut = Some(q);
            break;
        }
        drawn += s;
    }
    let q = cut.unwrap_or_else(|| {
        let last = x[STEPS - 1];
        (0..robot.joints()).map(|j| f64::from(last[j])).collect()
    });
    out.push(robot.waypoint(&q, 1.0));
    let qv = crate::kinematics::joint_vector(&q);
    let mut target = robot.pen_tip(&qv);
    target.translation.z += LIFT;
    let lifted = robot.ik(&target, &qv, &IkOptions::default())?;
    out.push(robot.waypoint(&lifted, 0.0));
    Ok(preprocess_with(robot, &out)?)
}

/// `x` drawn mirrored left-right about the centre of its pen-down path (the canvas's
/// "right" is the base frame's −y, so the mirror is about a plane of constant base y),
/// every pose re-solved by IK seeded with the previous one, the tool orientation kept. The
/// first waypoint (where the plan starts) stays where it is.
pub fn mirrored(robot: &Robot, x: &Resampled) -> Result<Resampled, VariantError> {
    mirror(robot, x, |i| i > 0)
}

/// The pen-down runs (strokes) of `x`: the step ranges where the pen is down.
pub fn strokes(x: &Resampled) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut start = None;
    for (i, w) in x.iter().enumerate() {
        match (w[TOOL] > 0.5, start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                out.push(s..i);
                start = None;
            }
            _ => {}
        }
    }
    if let Some(s) = start {
        out.push(s..STEPS);
    }
    out
}

/// `x` with only its stroke `k` ([`strokes`]) mirrored about the centre of the whole
/// pen-down path, as [`mirrored`] mirrors every pose: a drawing with one stroke the wrong
/// way round.
pub fn mirrored_stroke(robot: &Robot, x: &Resampled, k: usize) -> Result<Resampled, VariantError> {
    let run = strokes(x).get(k).cloned().ok_or(VariantError::NoPenDown)?;
    mirror(robot, x, |i| run.contains(&i))
}

/// `x` with the poses of the steps `which` selects mirrored (see [`mirrored`]).
fn mirror(
    robot: &Robot,
    x: &Resampled,
    which: impl Fn(usize) -> bool,
) -> Result<Resampled, VariantError> {
    let mut p = [[0.0f64; 3]; STEPS];
    robot.pen_tip_positions_into(x, &mut p);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (q, w) in p.iter().zip(x.iter()) {
        if w[TOOL] > 0.5 {
            lo = lo.min(q[1]);
            hi = hi.max(q[1]);
        }
    }
    if !lo.is_finite() {
        return Err(VariantError::NoPenDown);
    }
    let c = 0.5 * (lo + hi);
    let options = IkOptions::default();
    let mut out: Vec<Waypoint> = Vec::with_capacity(STEPS);
    let mut seed = robot.joints_of(&x[0]);
    for (i, w) in x.iter().enumerate() {
        if !which(i) {
            out.push(*w);
            seed = robot.joints_of(w);
            continue;
        }
        let mut target = robot.pen_tip(&robot.joints_of(w));
        target.translation.y = 2.0 * c - target.translation.y;
        seed = robot.ik(&target, &seed, &options)?;
        out.push(robot.waypoint(&seed, w[TOOL]));
    }
    Ok(preprocess_with(robot, &out)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::default_panda;
    use crate::pen::pen_path_with;
    use crate::preprocess::preprocess;

    /// A plan of the Panda drawing an "L" on the canvas (two pen-down strokes), solved by IK.
    fn ell() -> Resampled {
        let robot = default_panda();
        let mut seed = crate::kinematics::joint_vector(&crate::kinematics::READY_POSE);
        let start = robot.pen_tip(&seed);
        let mut wps = Vec::new();
        // (dx, dy, dz, pen): above the start, down, a stroke along +x, lift, a stroke along -y.
        let path: Vec<([f64; 3], f32)> = {
            let mut v = vec![([0.0, 0.0, 0.02], 0.0), ([0.0, 0.0, 0.0], 1.0)];
            for k in 1..=10 {
                v.push(([0.004 * f64::from(k), 0.0, 0.0], 1.0));
            }
            v.push(([0.04, 0.0, 0.02], 0.0));
            v.push(([0.0, 0.0, 0.02], 0.0));
            v.push(([0.0, 0.0, 0.0], 1.0));
            for k in 1..=5 {
                v.push(([0.0, -0.004 * f64::from(k), 0.0], 1.0));
            }
            v.push(([0.0, -0.02, 0.02], 0.0));
            v
        };
        for (d, pen) in path {
            let mut t = start;
            t.translation.x += d[0];
            t.translation.y += d[1];
            t.translation.z += d[2] - 0.1;
            seed = robot
                .ik(&t, &seed, &IkOptions::default())
                .expect("reachable");
            wps.push(robot.waypoint(&seed, pen));
        }
        preprocess(&wps).expect("a valid plan")
    }

    /// Pen-down path length (m). Resampling loses up to a step of it at each pen change (a
    /// segment with one end up counts as up), so lengths compare to 6 %.
    fn pen_down_length(x: &Resampled) -> f64 {
        let p = pen_path_with(default_panda(), x);
        (0..STEPS - 1)
            .filter(|&i| down(x, i))
            .map(|i| f64::from((p[i + 1][0] - p[i][0]).hypot(p[i + 1][1] - p[i][1])))
            .sum()
    }

    #[test]
    fn a_truncated_plan_draws_the_share_it_keeps_and_ends_lifted() {
        let x = ell();
        let full = pen_down_length(&x);
        for share in [0.1, 0.25, 0.5] {
            let t = truncated(default_panda(), &x, share).expect("a near miss");
            let kept = pen_down_length(&t);
            let want = full * (1.0 - share);
            assert!(
                (kept - want).abs() < 0.06 * full,
                "share {share}: kept {kept:.4} m of {full:.4}, want {want:.4}"
            );
            assert_eq!(t[STEPS - 1][TOOL], 0.0, "the pen ends up");
        }
    }

    #[test]
    fn a_mirrored_plan_draws_the_reflection_of_the_pen_path() {
        let x = ell();
        let m = mirrored(default_panda(), &x).expect("a near miss");
        let (a, b) = (
            pen_path_with(default_panda(), &x),
            pen_path_with(default_panda(), &m),
        );
        // The same pen-down length (to the resampling's step at each pen change); the drawing's "right" (canvas x) reflected about its centre:
        // the first stroke (along base +x, canvas "up") stays, the second (base -y, canvas
        // "right") now goes left.
        let (la, lm) = (pen_down_length(&x), pen_down_length(&m));
        assert!((la - lm).abs() < 0.06 * la, "{la} -> {lm}");
        let span = |p: &[[f32; 3]; STEPS]| {
            let xs: Vec<f32> = p.iter().filter(|q| q[2] > 0.5).map(|q| q[0]).collect();
            let lo = xs.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = xs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            (lo, hi)
        };
        let ((alo, ahi), (blo, bhi)) = (span(&a), span(&b));
        assert!(((ahi - alo) - (bhi - blo)).abs() < 1e-3, "same width");
        // The last pen-down point: right of the centre before, left of it after.
        let last = |p: &[[f32; 3]; STEPS]| p.iter().rev().find(|q| q[2] > 0.5).copied().unwrap();
        let (la, lb) = (last(&a), last(&b));
        let c = 0.5 * (alo + ahi);
        assert!(
            la[0] > c + 0.005 && lb[0] < c - 0.005,
            "{la:?} -> {lb:?} about {c}"
        );
    }

    #[test]
    fn one_stroke_mirrored_moves_that_stroke_only() {
        let x = ell();
        let runs = strokes(&x);
        assert_eq!(runs.len(), 2, "{runs:?}");
        let m = mirrored_stroke(default_panda(), &x, 1).expect("a near miss");
        let (a, b) = (
            pen_path_with(default_panda(), &x),
            pen_path_with(default_panda(), &m),
        );
        // The first stroke (along canvas "up") is where it was, to a resampling step; the
        // second went right (canvas +x) and now goes left.
        let first = |p: &[[f32; 3]; STEPS]| p.iter().find(|q| q[2] > 0.5).copied().unwrap();
        assert!(
            (first(&a)[0] - first(&b)[0]).abs() < 2e-3,
            "{:?} {:?}",
            first(&a),
            first(&b)
        );
        let second = |p: &[[f32; 3]; STEPS], x: &Resampled| {
            let r = strokes(x)[1].clone();
            p[r.end - 1][0] - p[r.start][0]
        };
        let (da, db) = (second(&a, &x), second(&b, &m));
        assert!(da > 0.015 && db < -0.015, "second stroke: {da} -> {db}");
        assert!(
            mirrored_stroke(default_panda(), &x, 2).is_err(),
            "no third stroke"
        );
    }

    #[test]
    fn a_plan_without_pen_down_has_no_near_miss() {
        let mut x = ell();
        for w in x.iter_mut() {
            w[TOOL] = 0.0;
        }
        assert!(matches!(
            truncated(default_panda(), &x, 0.2),
            Err(VariantError::NoPenDown)
        ));
        assert!(matches!(
            mirrored(default_panda(), &x),
            Err(VariantError::NoPenDown)
        ));
    }
}
