//! The trajectory contract: raw planner waypoints (the joint positions of a serial arm of 1 to
//! [`MAX_JOINTS`] joints + 1 tool channel), their validation against the served robot's
//! joint limits ([`JointLimits`]), and resampling to the model's fixed input of [`STEPS`]
//! waypoints.
//!
//! In memory a waypoint has a fixed capacity ([`Waypoint`], [`MAX_JOINTS`] joint slots and
//! the tool at [`TOOL`]): a robot of `n` joints uses slots `0..n`, the others stay 0. Rows
//! stay `Copy` and the request path allocates per plan, not per waypoint, whatever the arm.
//! On the wire and on disk a waypoint is `n + 1` floats, `q1..qn, tool` ([`from_flat`],
//! [`to_flat`]).

use serde::{Deserialize, Serialize};

/// Most joints a served robot may have.
pub const MAX_JOINTS: usize = 16;
/// Slots of an in-memory [`Waypoint`]: [`MAX_JOINTS`] joints, then the tool.
pub const SLOTS: usize = MAX_JOINTS + 1;
/// Index of the tool channel inside an in-memory [`Waypoint`].
pub const TOOL: usize = MAX_JOINTS;
/// Number of samples the model sees, uniform in path length.
pub const STEPS: usize = 128;
/// Fewest waypoints a trajectory may have.
pub const MIN_WAYPOINTS: usize = 2;
/// Most waypoints a trajectory may have.
pub const MAX_WAYPOINTS: usize = 4096;

/// The joint limits of the served robot (rad for revolute joints, m for prismatic ones):
/// its joint count and the range every waypoint must stay in. Built only through
/// [`JointLimits::new`], which checks them.
#[derive(Debug, Clone, PartialEq)]
pub struct JointLimits {
    lower: Vec<f64>,
    upper: Vec<f64>,
}

/// [`JointLimits::new`] refused its input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum LimitsError {
    /// Not 1..=[`MAX_JOINTS`] joints, or lower and upper of different lengths.
    #[error(
        "joint limits for {lower} lower / {upper} upper values; 1..={MAX_JOINTS} joints expected"
    )]
    Count {
        /// Lower limits given.
        lower: usize,
        /// Upper limits given.
        upper: usize,
    },
    /// A limit is not finite or lower > upper.
    #[error("joint {joint}: limits [{lower}, {upper}] are not a finite range")]
    Range {
        /// Joint index (0-based).
        joint: usize,
        /// Lower limit.
        lower: f64,
        /// Upper limit.
        upper: f64,
    },
}

impl JointLimits {
    /// Limits of `lower.len()` joints (1..=[`MAX_JOINTS`]), each a finite `lower <= upper`.
    pub fn new(lower: Vec<f64>, upper: Vec<f64>) -> Result<Self, LimitsError> {
        if lower.len() != upper.len() || lower.is_empty() || lower.len() > MAX_JOINTS {
            return Err(LimitsError::Count {
                lower: lower.len(),
                upper: upper.len(),
            });
        }
        for (joint, (&lo, &hi)) in lower.iter().zip(&upper).enumerate() {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(LimitsError::Range {
                    joint,
                    lower: lo,
                    upper: hi,
                });
            }
        }
        Ok(Self { lower, upper })
    }

    /// Number of joints.
    pub fn joints(&self) -> usize {
        self.lower.len()
    }

    /// Floats per waypoint on the wire: the joints, then the tool.
    pub fn channels(&self) -> usize {
        self.lower.len() + 1
    }

    /// Lower limits, one per joint.
    pub fn lower(&self) -> &[f64] {
        &self.lower
    }

    /// Upper limits, one per joint.
    pub fn upper(&self) -> &[f64] {
        &self.upper
    }
}

/// One raw waypoint in memory: joint positions in slots `0..n` (unused slots 0), the tool
/// channel (1 = pen down, 0 = up) at [`TOOL`].
pub type Waypoint = [f32; SLOTS];
/// The resampled model input: [`STEPS`] waypoints.
pub type Resampled = [Waypoint; STEPS];

/// What is wrong with a trajectory. The discriminants are stable: they go on the wire.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, num_enum::TryFromPrimitive,
)]
#[repr(u8)]
#[non_exhaustive]
pub enum InvalidKind {
    /// A value is NaN or infinite.
    NonFinite = 1,
    /// The waypoints do not have the served robot's channel count (joints + 1).
    WrongChannelCount = 2,
    /// Fewer than [`MIN_WAYPOINTS`] waypoints.
    TooFewWaypoints = 3,
    /// More than [`MAX_WAYPOINTS`] waypoints.
    TooManyWaypoints = 4,
    /// A joint position lies outside the robot's limits.
    JointOutOfLimits = 5,
    /// The tool channel is neither 0 nor 1.
    ToolOutOfRange = 6,
}

/// A trajectory failed validation: what is wrong and where.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error, Serialize, Deserialize)]
#[error("invalid trajectory: {kind:?} at index {index}")]
pub struct InvalidTrajectory {
    /// What is wrong.
    pub kind: InvalidKind,
    /// The waypoint index where it was found; for count and shape errors, the offending
    /// count (waypoints or channels).
    pub index: u32,
}

impl InvalidTrajectory {
    /// `kind` found at `index` (a waypoint index, or the offending count), saturated to
    /// `u32`.
    pub fn new(kind: InvalidKind, index: usize) -> Self {
        Self {
            kind,
            index: u32::try_from(index).unwrap_or(u32::MAX),
        }
    }
}

/// A waypoint of `joints.len()` joints (at most [`MAX_JOINTS`]) and a tool value.
pub fn waypoint(joints: &[f32], tool: f32) -> Waypoint {
    let mut w = [0.0; SLOTS];
    w[..joints.len()].copy_from_slice(joints);
    w[TOOL] = tool;
    w
}

/// Split a flat row-major buffer of `channels`-wide waypoints (`q1..qn, tool`) into
/// [`Waypoint`]s and validate them against `limits` (see [`validate`]); `channels` must be
/// `limits.joints() + 1`.
pub fn from_flat(
    data: &[f32],
    channels: usize,
    limits: &JointLimits,
) -> Result<Vec<Waypoint>, InvalidTrajectory> {
    let waypoints = split_flat(data, channels, limits.joints())?;
    validate(&waypoints, limits)?;
    Ok(waypoints)
}

/// [`from_flat`] without the validation (shape only): for callers that validate later or
/// report the values' problems themselves.
pub fn split_flat(
    data: &[f32],
    channels: usize,
    joints: usize,
) -> Result<Vec<Waypoint>, InvalidTrajectory> {
    if channels != joints + 1 {
        return Err(InvalidTrajectory::new(
            InvalidKind::WrongChannelCount,
            channels,
        ));
    }
    if !data.len().is_multiple_of(channels) {
        return Err(InvalidTrajectory::new(
            InvalidKind::WrongChannelCount,
            data.len() % channels,
        ));
    }
    Ok(data
        .chunks_exact(channels)
        .map(|c| waypoint(&c[..joints], c[joints]))
        .collect())
}

/// The flat row-major form of `waypoints` for a robot of `joints` joints: `joints + 1`
/// floats per waypoint, `q1..qn, tool` (what the wire and the data files carry).
pub fn to_flat(waypoints: &[Waypoint], joints: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(waypoints.len() * (joints + 1));
    for w in waypoints {
        out.extend_from_slice(&w[..joints]);
        out.push(w[TOOL]);
    }
    out
}

/// Check a trajectory: waypoint count within [`MIN_WAYPOINTS`]..=[`MAX_WAYPOINTS`], every
/// value finite, joints inside `limits`, tool exactly 0 or 1. The first problem found is
/// reported, count problems before per-waypoint ones. The slots past the robot's joints
/// are not read here or anywhere else ([`from_flat`] leaves them 0).
pub fn validate(waypoints: &[Waypoint], limits: &JointLimits) -> Result<(), InvalidTrajectory> {
    if waypoints.len() < MIN_WAYPOINTS {
        return Err(InvalidTrajectory::new(
            InvalidKind::TooFewWaypoints,
            waypoints.len(),
        ));
    }
    if waypoints.len() > MAX_WAYPOINTS {
        return Err(InvalidTrajectory::new(
            InvalidKind::TooManyWaypoints,
            waypoints.len(),
        ));
    }
    let joints = limits.joints();
    let (lower, upper) = (limits.lower(), limits.upper());
    // Branch-free pass first (vectorisable): the common case, a valid plan, needs nothing
    // else; otherwise the loop below finds and reports the first problem. The shipped arms'
    // joint counts (6, 7) get a pass with fixed-size limits, fully unrolled.
    let all_valid = match joints {
        6 => all_valid::<6>(waypoints, lower, upper),
        7 => all_valid::<7>(waypoints, lower, upper),
        _ => waypoints.iter().fold(true, |ok, w| {
            let mut good = w[TOOL] == 0.0 || w[TOOL] == 1.0;
            for j in 0..joints {
                // NaN fails both comparisons; infinities fail the limits.
                let q = f64::from(w[j]);
                good &= q >= lower[j] && q <= upper[j];
            }
            ok & good
        }),
    };
    if all_valid {
        return Ok(());
    }
    for (i, w) in waypoints.iter().enumerate() {
        if w[..joints].iter().chain([&w[TOOL]]).any(|v| !v.is_finite()) {
            return Err(InvalidTrajectory::new(InvalidKind::NonFinite, i));
        }
        for j in 0..joints {
            let q = f64::from(w[j]);
            if q < lower[j] || q > upper[j] {
                return Err(InvalidTrajectory::new(InvalidKind::JointOutOfLimits, i));
            }
        }
        if w[TOOL] != 0.0 && w[TOOL] != 1.0 {
            return Err(InvalidTrajectory::new(InvalidKind::ToolOutOfRange, i));
        }
    }
    Ok(())
}

/// Whether every waypoint of an `N`-joint robot is finite, inside the limits and has a tool
/// value of 0 or 1 (branch-free; `lower` and `upper` have `N` values).
#[inline]
fn all_valid<const N: usize>(waypoints: &[Waypoint], lower: &[f64], upper: &[f64]) -> bool {
    let lo: [f64; N] = std::array::from_fn(|j| lower[j]);
    let hi: [f64; N] = std::array::from_fn(|j| upper[j]);
    waypoints.iter().fold(true, |ok, w| {
        let mut good = w[TOOL] == 0.0 || w[TOOL] == 1.0;
        for j in 0..N {
            // NaN fails both comparisons; infinities fail the limits.
            let q = f64::from(w[j]);
            good &= q >= lo[j] && q <= hi[j];
        }
        ok & good
    })
}

/// Resample validated waypoints of a robot with `joints` joints to [`STEPS`] samples uniform
/// in a path length (the slots past `joints` are 0 in the result).
///
/// `cumulative[i]` is the path length from waypoint 0 to waypoint `i` (non-decreasing,
/// same length as `waypoints`); the caller chooses the metric (the lab and the daemon both
/// use the pen-tip path length from forward kinematics). Joints are interpolated linearly;
/// the tool channel is 1 inside a segment only where both of its ends are pen-down. Every
/// maximal run of pen-down waypoints that no sample landed in (a dot, a very short stroke)
/// still gets one pen-down sample: the sample nearest to the run's middle is moved there. If the total length is
/// zero, samples are uniform in waypoint index.
///
/// # Panics
/// If `waypoints` is empty or `cumulative` has a different length (a caller bug; validated
/// input never triggers it).
pub fn resample(waypoints: &[Waypoint], cumulative: &[f64], joints: usize) -> Resampled {
    assert!(!waypoints.is_empty() && waypoints.len() == cumulative.len());
    let n = waypoints.len();
    let total = cumulative[n - 1] - cumulative[0];
    let index_param: Vec<f64>;
    let cum: &[f64] = if total > 0.0 && total.is_finite() {
        cumulative
    } else {
        index_param = (0..n).map(|i| i as f64).collect();
        &index_param
    };
    let start = cum[0];
    let total = cum[n - 1] - start;
    let mut out = [[0.0f32; SLOTS]; STEPS];
    let mut positions = [0.0f64; STEPS];
    // The sample positions increase with k, so the segment index (the first cumulative
    // length above the position, what `sample_at`'s binary search finds) only moves forward:
    // one walk over the waypoints instead of a search per sample.
    let mut above = 0usize;
    for (k, sample) in out.iter_mut().enumerate() {
        let s = start + total * k as f64 / (STEPS - 1) as f64;
        positions[k] = s;
        while above < n && cum[above] <= s {
            above += 1;
        }
        *sample = sample_in(waypoints, cum, s, above, joints);
    }
    // Pen-down runs that received no sample.
    let mut i = 0;
    while i < n {
        if waypoints[i][TOOL] != 1.0 {
            i += 1;
            continue;
        }
        let a = i;
        while i + 1 < n && waypoints[i + 1][TOOL] == 1.0 {
            i += 1;
        }
        let b = i;
        i += 1;
        let (lo, hi) = (cum[a], cum[b]);
        let covered = out
            .iter()
            .zip(positions.iter())
            .any(|(s, &p)| s[TOOL] == 1.0 && p >= lo - 1e-12 && p <= hi + 1e-12);
        if !covered {
            let mid = 0.5 * (lo + hi);
            let k = positions
                .iter()
                .enumerate()
                .min_by(|x, y| (x.1 - mid).abs().total_cmp(&(y.1 - mid).abs()))
                .map_or(0, |(k, _)| k);
            let mut w = sample_at(waypoints, cum, mid, joints);
            w[TOOL] = 1.0;
            out[k] = w;
            positions[k] = mid;
        }
    }
    out
}

fn sample_at(waypoints: &[Waypoint], cum: &[f64], s: f64, joints: usize) -> Waypoint {
    // First index whose cumulative length exceeds s.
    sample_in(waypoints, cum, s, cum.partition_point(|&c| c <= s), joints)
}

/// [`sample_at`] given `above`, the number of cumulative lengths `<= s` (the first index
/// whose cumulative length exceeds `s`).
fn sample_in(waypoints: &[Waypoint], cum: &[f64], s: f64, above: usize, joints: usize) -> Waypoint {
    let n = waypoints.len();
    if n == 1 {
        let mut w = [0.0f32; SLOTS];
        w[..joints].copy_from_slice(&waypoints[0][..joints]);
        w[TOOL] = waypoints[0][TOOL];
        return w;
    }
    let hi = above.clamp(1, n - 1);
    let lo = hi - 1;
    let span = cum[hi] - cum[lo];
    let t = if span > 0.0 {
        ((s - cum[lo]) / span).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let mut w = [0.0f32; SLOTS];
    for j in 0..joints.min(MAX_JOINTS) {
        let a = f64::from(waypoints[lo][j]);
        let b = f64::from(waypoints[hi][j]);
        w[j] = (a + (b - a) * t) as f32;
    }
    w[TOOL] = if t <= 0.0 {
        waypoints[lo][TOOL]
    } else if t >= 1.0 {
        waypoints[hi][TOOL]
    } else {
        // Inside a segment the pen is down only if it is down at both ends.
        waypoints[lo][TOOL].min(waypoints[hi][TOOL])
    };
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wp(q: f32, tool: f32) -> Waypoint {
        waypoint(&[q, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0], tool)
    }

    /// The Panda's limits (the published numbers; the models crate owns the robot).
    fn panda() -> JointLimits {
        JointLimits::new(
            vec![
                -2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973,
            ],
            vec![2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973],
        )
        .unwrap()
    }

    /// The forward walk finds the segments the binary search of `sample_at` finds,
    /// including zero-length segments (repeated cumulative lengths) and the ends.
    #[test]
    fn resampling_walk_matches_the_search_per_sample() {
        for n in [2usize, 3, 7, 128, 129, 300] {
            // Pen up throughout, so the pen-down rule changes nothing.
            let ws: Vec<Waypoint> = (0..n).map(|i| wp(0.01 * i as f32, 0.0)).collect();
            let mut cum = Vec::with_capacity(n);
            let mut total = 0.0f64;
            for i in 0..n {
                // Every third segment has length zero; others vary.
                if i > 0 && i % 3 != 0 {
                    total += 0.001 * (1 + i % 5) as f64;
                }
                cum.push(total);
            }
            let out = resample(&ws, &cum, 7);
            let span = cum[n - 1] - cum[0];
            for (k, sample) in out.iter().enumerate() {
                let s = cum[0] + span * k as f64 / (STEPS - 1) as f64;
                assert_eq!(*sample, sample_at(&ws, &cum, s, 7), "n {n}, k {k}");
            }
        }
    }

    #[test]
    fn validation_reports_each_kind_with_index() {
        let good = vec![wp(0.0, 0.0), wp(0.1, 1.0), wp(0.2, 0.0)];
        let limits = panda();
        let validate = |w: &[Waypoint]| validate(w, &limits);
        assert_eq!(validate(&good), Ok(()));
        let e = |kind, index| Err(InvalidTrajectory { kind, index });
        assert_eq!(validate(&good[..1]), e(InvalidKind::TooFewWaypoints, 1));
        let many = vec![wp(0.0, 0.0); MAX_WAYPOINTS + 1];
        assert_eq!(validate(&many), e(InvalidKind::TooManyWaypoints, 4097));
        let mut bad = good.clone();
        bad[1][3] = f32::NAN;
        assert_eq!(validate(&bad), e(InvalidKind::NonFinite, 1));
        bad[1][3] = f32::INFINITY;
        assert_eq!(validate(&bad), e(InvalidKind::NonFinite, 1));
        let mut bad = good.clone();
        bad[2][3] = 0.0; // joint 4 must be <= -0.0698
        assert_eq!(validate(&bad), e(InvalidKind::JointOutOfLimits, 2));
        let mut bad = good.clone();
        bad[0][TOOL] = 0.5;
        assert_eq!(validate(&bad), e(InvalidKind::ToolOutOfRange, 0));
        // A slot past the robot's joints is not read (a plan's channel count is checked
        // where the flat buffer is split), and resampling leaves it 0.
        let mut extra = good.clone();
        extra[1][7] = f32::NAN;
        assert_eq!(validate(&extra), Ok(()));
        assert!(
            resample(&extra, &[0.0, 1.0, 2.0], 7)
                .iter()
                .all(|w| w[7] == 0.0)
        );
        assert_eq!(
            from_flat(&[0.0; 14], 7, &limits).unwrap_err(),
            InvalidTrajectory {
                kind: InvalidKind::WrongChannelCount,
                index: 7
            }
        );
        assert_eq!(
            from_flat(&[0.0; 17], 8, &limits).unwrap_err().kind,
            InvalidKind::WrongChannelCount
        );
        // The flat form round-trips, and a 6-joint robot takes 7 channels.
        let flat = to_flat(&good, 7);
        assert_eq!(flat.len(), 3 * 8);
        assert_eq!(from_flat(&flat, 8, &limits), Ok(good.clone()));
        let six = JointLimits::new(vec![-6.3; 6], vec![6.3; 6]).unwrap();
        let ws = from_flat(&[0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 1.0].repeat(2), 7, &six).unwrap();
        assert_eq!(ws[1][5], 0.6);
        assert_eq!(ws[1][6], 0.0);
        assert_eq!(ws[1][TOOL], 1.0);
        assert!(JointLimits::new(vec![], vec![]).is_err());
        assert!(JointLimits::new(vec![0.0; 17], vec![1.0; 17]).is_err());
        assert!(JointLimits::new(vec![1.0], vec![0.0]).is_err());
        assert!(JointLimits::new(vec![f64::NAN], vec![0.0]).is_err());
        for k in 1..=6u8 {
            assert_eq!(InvalidKind::try_from(k).ok().map(|k| k as u8), Some(k));
        }
        assert_eq!(InvalidKind::try_from(0).ok(), None);
    }

    #[test]
    fn resample_is_uniform_in_the_given_length() {
        let w = vec![wp(0.0, 0.0), wp(1.0, 0.0), wp(2.0, 0.0)];
        // First segment is 3x longer than the second.
        let out = resample(&w, &[0.0, 3.0, 4.0], 7);
        assert_eq!(out[0][0], 0.0);
        assert!((out[STEPS - 1][0] - 2.0).abs() < 1e-6);
        // Three quarters of the samples fall in the first segment.
        let in_first = out.iter().filter(|s| s[0] <= 1.0).count();
        assert!((95..=97).contains(&in_first), "{in_first}");
    }

    #[test]
    fn a_dot_still_gets_a_pen_down_sample() {
        // A long pen-up travel with a tiny pen-down dot in the middle.
        let w = vec![wp(0.0, 0.0), wp(0.5, 1.0), wp(0.5001, 1.0), wp(1.0, 0.0)];
        let out = resample(&w, &[0.0, 10.0, 10.0001, 20.0], 7);
        let down: Vec<_> = out.iter().filter(|s| s[TOOL] == 1.0).collect();
        assert_eq!(down.len(), 1);
        assert!((down[0][0] - 0.50005).abs() < 1e-4);
    }

    #[test]
    fn zero_length_falls_back_to_index() {
        let w = vec![wp(0.0, 0.0), wp(0.0, 0.0)];
        let out = resample(&w, &[0.0, 0.0], 7);
        assert!(out.iter().all(|s| s[0] == 0.0));
    }
}
