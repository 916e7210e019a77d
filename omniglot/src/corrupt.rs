//! Faulty-plan generators: corruptions of a genuine drawing plan, each with a severity in
//! (0, 1].
//!
//! Corruptions that change the drawn path are made on the strokes (Omniglot motor
//! coordinates, which map affinely onto the canvas plane, so this is a change of the
//! Cartesian pen path) and re-solved through the dataset's IK ([`convert_strokes`]), so the
//! joint trajectory is one a planner could really produce. Joint-space faults (noise, a
//! constant offset on one joint) are applied to the solved dense joint path and clamped to
//! the joint limits. Every result goes through the same shared preprocessing as the dataset.
//!
//! Wrong-task and unknown-task faults are not corruptions of one plan (another class's
//! genuine plan claims a class); they are drawn by the `outliers` evaluation.

use guardian_robot::kinematics::Robot;
use guardian_robot::preprocess::preprocess_with;
use guardian_shared::trajectory::{Resampled, Waypoint};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::dataset::{ConvertError, convert_strokes};
use crate::path::PathSolver;
use crate::strokes::{Point, Stroke};

/// Severities the evaluation reports: low, moderate, high.
pub const SEVERITIES: [f64; 3] = [0.25, 0.5, 1.0];
/// The "moderate" severity of the targets.
pub const MODERATE: f64 = 0.5;

/// A corruption of a genuine plan.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum Fault {
    /// Gaussian noise on every joint of every waypoint, sigma = 0.03 rad x severity.
    JointNoise,
    /// Constant offset on one random joint, 0.05 + 0.15 x severity rad (0.05–0.2), random sign.
    JointOffset,
    /// Strokes removed: max(1, round(severity x (n - 1))) of n >= 2 strokes.
    MissingStroke,
    /// A straight extra stroke through the drawing, length (0.25 + 0.75 x severity) x the
    /// drawing's larger side.
    ExtraStroke,
    /// Mirrored left-right about the drawing's centre: a share `severity` of the strokes
    /// (at least one; all at 1).
    Mirrored,
    /// Time-reversed: low (< 0.5) reverses the stroke order, moderate (< 1) the direction
    /// of every stroke, high (1) both (the whole plan backwards).
    TimeReversed,
    /// The last 10–30 % of the pen-down points cut (0.1 + 0.2 x severity).
    Truncated,
    /// The drawing moved on the canvas by 4 cm x severity in a random direction.
    Shifted,
    /// Rotated about its centre by (pi / 2) x severity, random sign.
    Rotated,
    /// Scaled about its centre by 1 + 0.6 x severity (or its inverse), random choice.
    Scaled,
}

impl Fault {
    /// Every corruption.
    pub const ALL: [Fault; 10] = [
        Fault::JointNoise,
        Fault::JointOffset,
        Fault::MissingStroke,
        Fault::ExtraStroke,
        Fault::Mirrored,
        Fault::TimeReversed,
        Fault::Truncated,
        Fault::Shifted,
        Fault::Rotated,
        Fault::Scaled,
    ];

    /// Kebab-case name.
    pub fn name(self) -> &'static str {
        match self {
            Fault::JointNoise => "joint-noise",
            Fault::JointOffset => "joint-offset",
            Fault::MissingStroke => "missing-stroke",
            Fault::ExtraStroke => "extra-stroke",
            Fault::Mirrored => "mirrored",
            Fault::TimeReversed => "time-reversed",
            Fault::Truncated => "truncated",
            Fault::Shifted => "shifted",
            Fault::Rotated => "rotated",
            Fault::Scaled => "scaled",
        }
    }

    /// True if the fault is applied to the joint path rather than the Cartesian path.
    pub fn in_joint_space(self) -> bool {
        matches!(self, Fault::JointNoise | Fault::JointOffset)
    }
}

/// Making a faulty plan failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CorruptError {
    /// The fault does not apply to this drawing (e.g. a missing stroke of a one-stroke
    /// drawing).
    #[error("{fault:?} does not apply: {reason}")]
    NotApplicable {
        /// The fault.
        fault: Fault,
        /// Why.
        reason: &'static str,
    },
    /// The severity is outside (0, 1].
    #[error("severity {0} is outside (0, 1]")]
    Severity(f64),
    /// The corrupted path could not be solved or validated.
    #[error(transparent)]
    Convert(#[from] ConvertError),
}

fn bbox(strokes: &[Stroke]) -> ([f64; 2], [f64; 2]) {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for p in strokes.iter().flatten() {
        lo = [lo[0].min(p.x), lo[1].min(p.y)];
        hi = [hi[0].max(p.x), hi[1].max(p.y)];
    }
    (lo, hi)
}

fn centre(strokes: &[Stroke]) -> [f64; 2] {
    let (lo, hi) = bbox(strokes);
    [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0]
}

fn map_points(strokes: &[Stroke], f: impl Fn(&Point) -> Point) -> Vec<Stroke> {
    strokes.iter().map(|s| s.iter().map(&f).collect()).collect()
}

/// The corrupted strokes of a Cartesian fault (`None` for joint-space faults).
pub fn corrupt_strokes<R: Rng>(
    fault: Fault,
    severity: f64,
    strokes: &[Stroke],
    rng: &mut R,
) -> Result<Option<Vec<Stroke>>, CorruptError> {
    if !(severity > 0.0 && severity <= 1.0) {
        return Err(CorruptError::Severity(severity));
    }
    let na = |reason| CorruptError::NotApplicable { fault, reason };
    if strokes.iter().all(Vec::is_empty) {
        return Err(na("empty drawing"));
    }
    let c = centre(strokes);
    let (lo, hi) = bbox(strokes);
    let side = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1.0);
    let out = match fault {
        Fault::JointNoise | Fault::JointOffset => return Ok(None),
        Fault::MissingStroke => {
            let n = strokes.len();
            if n < 2 {
                return Err(na("one stroke"));
            }
            let k = ((severity * (n - 1) as f64).round() as usize).clamp(1, n - 1);
            let mut idx: Vec<usize> = (0..n).collect();
            for i in 0..k {
                let j = rng.random_range(i..n);
                idx.swap(i, j);
            }
            let removed = &idx[..k];
            strokes
                .iter()
                .enumerate()
                .filter(|(i, _)| !removed.contains(i))
                .map(|(_, s)| s.clone())
                .collect()
        }
        Fault::ExtraStroke => {
            let len = (0.25 + 0.75 * severity) * side;
            let a: f64 = rng.random_range(0.0..std::f64::consts::PI);
            let (dx, dy) = (a.cos() * len / 2.0, a.sin() * len / 2.0);
            let t0 = strokes.iter().flatten().map(|p| p.t).fold(0.0, f64::max);
            let mut out = strokes.to_vec();
            out.push(
                (0..=10)
                    .map(|i| {
                        let f = i as f64 / 10.0 * 2.0 - 1.0;
                        Point {
                            x: c[0] + f * dx,
                            y: c[1] + f * dy,
                            t: t0 + 10.0 * i as f64,
                        }
                    })
                    .collect(),
            );
            out
        }
        Fault::Mirrored => {
            let n = strokes.len();
            let k = ((severity * n as f64).round() as usize).clamp(1, n);
            let first = if k == n {
                0
            } else {
                rng.random_range(0..=n - k)
            };
            strokes
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    if (first..first + k).contains(&i) {
                        s.iter()
                            .map(|p| Point {
                                x: 2.0 * c[0] - p.x,
                                ..*p
                            })
                            .collect()
                    } else {
                        s.clone()
                    }
                })
                .collect()
        }
        Fault::TimeReversed => {
            let reverse_order = !(0.5..1.0).contains(&severity);
            let reverse_strokes = severity >= 0.5;
            if strokes.len() < 2 && !reverse_strokes {
                return Err(na("one stroke: stroke order cannot change"));
            }
            let mut out: Vec<Stroke> = strokes.to_vec();
            if reverse_order {
                out.reverse();
            }
            if reverse_strokes {
                for s in &mut out {
                    s.reverse();
                }
            }
            out
        }
        Fault::Truncated => {
            let total: usize = strokes.iter().map(Vec::len).sum();
            let keep = ((1.0 - (0.1 + 0.2 * severity)) * total as f64).round() as usize;
            let keep = keep.max(1);
            let mut left = keep;
            let mut out = Vec::new();
            for s in strokes {
                if left == 0 {
                    break;
                }
                let k = s.len().min(left);
                out.push(s[..k].to_vec());
                left -= k;
            }
            out
        }
        Fault::Shifted => {
            // 4 cm at 1.25 mm per motor unit = 32 units.
            let d = 32.0 * severity;
            let a: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            map_points(strokes, |p| Point {
                x: p.x + d * a.cos(),
                y: p.y + d * a.sin(),
                t: p.t,
            })
        }
        Fault::Rotated => {
            let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
            let a = sign * std::f64::consts::FRAC_PI_2 * severity;
            let (s, co) = a.sin_cos();
            map_points(strokes, |p| {
                let (x, y) = (p.x - c[0], p.y - c[1]);
                Point {
                    x: c[0] + co * x - s * y,
                    y: c[1] + s * x + co * y,
                    t: p.t,
                }
            })
        }
        Fault::Scaled => {
            let mut k = 1.0 + 0.6 * severity;
            if rng.random::<bool>() {
                k = 1.0 / k;
            }
            map_points(strokes, |p| Point {
                x: c[0] + k * (p.x - c[0]),
                y: c[1] + k * (p.y - c[1]),
                t: p.t,
            })
        }
    };
    Ok(Some(out))
}

/// A joint-space fault applied to a dense joint path of `robot` (clamped to its joint
/// limits).
pub fn corrupt_joints<R: Rng>(
    robot: &Robot,
    fault: Fault,
    severity: f64,
    waypoints: &[Waypoint],
    rng: &mut R,
) -> Vec<Waypoint> {
    let (lo, hi, joints) = (robot.q_min(), robot.q_max(), robot.joints());
    let clamp = |j: usize, v: f64| v.clamp(lo[j] + 1e-4, hi[j] - 1e-4) as f32;
    let mut out = waypoints.to_vec();
    match fault {
        Fault::JointNoise => {
            let sigma = 0.03 * severity;
            for w in &mut out {
                for (j, q) in w.iter_mut().take(joints).enumerate() {
                    // Box–Muller.
                    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
                    let u2: f64 = rng.random();
                    let g = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
                    *q = clamp(j, f64::from(*q) + sigma * g);
                }
            }
        }
        Fault::JointOffset => {
            let j = rng.random_range(0..joints);
            let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
            let off = sign * (0.05 + 0.15 * severity);
            for w in &mut out {
                w[j] = clamp(j, f64::from(w[j]) + off);
            }
        }
        _ => {}
    }
    out
}

/// A faulty plan: the genuine drawing `strokes` corrupted by `fault` at `severity`, solved
/// and preprocessed into the model input.
pub fn corrupt<R: Rng>(
    solver: &PathSolver,
    fault: Fault,
    severity: f64,
    strokes: &[Stroke],
    rng: &mut R,
) -> Result<Resampled, CorruptError> {
    match corrupt_strokes(fault, severity, strokes, rng)? {
        Some(s) => Ok(convert_strokes(solver, &s)?.sample),
        None => {
            let genuine = convert_strokes(solver, strokes)?;
            let w = corrupt_joints(
                solver.robot(),
                fault,
                severity,
                &genuine.dense.waypoints,
                rng,
            );
            Ok(preprocess_with(solver.robot(), &w).map_err(ConvertError::from)?)
        }
    }
}
