//! The trajectory contract: raw planner waypoints (7 joint positions + 1 tool channel),
//! their validation against the Panda limits, and resampling to the model's fixed input of
//! [`STEPS`] x [`CHANNELS`].

use serde::{Deserialize, Serialize};

/// Number of joints of the serial arm (Franka Emika Panda).
pub const JOINTS: usize = 7;
/// Channels per waypoint: the 7 joint positions (rad) followed by the tool state (0 or 1).
pub const CHANNELS: usize = JOINTS + 1;
/// Index of the tool channel inside a waypoint.
pub const TOOL: usize = JOINTS;
/// Number of samples the model sees, uniform in path length.
pub const STEPS: usize = 128;
/// Fewest waypoints a trajectory may have.
pub const MIN_WAYPOINTS: usize = 2;
/// Most waypoints a trajectory may have.
pub const MAX_WAYPOINTS: usize = 4096;

/// Lower joint limits of the Panda (rad), from the published kinematics.
pub const Q_MIN: [f64; JOINTS] = [
    -2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973,
];
/// Upper joint limits of the Panda (rad), from the published kinematics.
pub const Q_MAX: [f64; JOINTS] = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973];

/// One raw waypoint: `q1..q7` in radians, then the tool channel (1 = pen down, 0 = up).
pub type Waypoint = [f32; CHANNELS];
/// The resampled model input: [`STEPS`] waypoints.
pub type Resampled = [Waypoint; STEPS];

/// What is wrong with a trajectory. The discriminants are stable: they go on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u8)]
#[non_exhaustive]
pub enum InvalidKind {
    /// A value is NaN or infinite.
    NonFinite = 1,
    /// The waypoints do not have [`CHANNELS`] channels.
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

impl InvalidKind {
    /// Decode a wire discriminant.
    pub fn from_u8(v: u8) -> Option<Self> {
        Some(match v {
            1 => Self::NonFinite,
            2 => Self::WrongChannelCount,
            3 => Self::TooFewWaypoints,
            4 => Self::TooManyWaypoints,
            5 => Self::JointOutOfLimits,
            6 => Self::ToolOutOfRange,
            _ => return None,
        })
    }
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

/// Split a flat row-major buffer of `channels`-wide waypoints into [`Waypoint`]s and
/// validate them (see [`validate`]).
pub fn from_flat(data: &[f32], channels: usize) -> Result<Vec<Waypoint>, InvalidTrajectory> {
    if channels != CHANNELS {
        return Err(InvalidTrajectory::new(
            InvalidKind::WrongChannelCount,
            channels,
        ));
    }
    if !data.len().is_multiple_of(CHANNELS) {
        return Err(InvalidTrajectory::new(
            InvalidKind::WrongChannelCount,
            data.len() % CHANNELS,
        ));
    }
    let waypoints: Vec<Waypoint> = data
        .chunks_exact(CHANNELS)
        .map(|c| {
            let mut w = [0.0; CHANNELS];
            w.copy_from_slice(c);
            w
        })
        .collect();
    validate(&waypoints)?;
    Ok(waypoints)
}

/// Check a trajectory: waypoint count within [`MIN_WAYPOINTS`]..=[`MAX_WAYPOINTS`], every
/// value finite, joints inside [`Q_MIN`]..=[`Q_MAX`], tool exactly 0 or 1. The first problem
/// found is reported, count problems before per-waypoint ones.
pub fn validate(waypoints: &[Waypoint]) -> Result<(), InvalidTrajectory> {
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
    // Branch-free pass first (vectorisable): the common case, a valid plan, needs nothing
    // else; otherwise the loop below finds and reports the first problem.
    let all_valid = waypoints.iter().fold(true, |ok, w| {
        let mut good = w[TOOL] == 0.0 || w[TOOL] == 1.0;
        for j in 0..JOINTS {
            // NaN fails both comparisons; infinities fail the limits.
            let q = f64::from(w[j]);
            good &= q >= Q_MIN[j] && q <= Q_MAX[j];
        }
        ok & good
    });
    if all_valid {
        return Ok(());
    }
    for (i, w) in waypoints.iter().enumerate() {
        if w.iter().any(|v| !v.is_finite()) {
            return Err(InvalidTrajectory::new(InvalidKind::NonFinite, i));
        }
        for j in 0..JOINTS {
            let q = f64::from(w[j]);
            if q < Q_MIN[j] || q > Q_MAX[j] {
                return Err(InvalidTrajectory::new(InvalidKind::JointOutOfLimits, i));
            }
        }
        if w[TOOL] != 0.0 && w[TOOL] != 1.0 {
            return Err(InvalidTrajectory::new(InvalidKind::ToolOutOfRange, i));
        }
    }
    Ok(())
}

/// Resample validated waypoints to [`STEPS`] samples uniform in a path length.
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
pub fn resample(waypoints: &[Waypoint], cumulative: &[f64]) -> Resampled {
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
    let mut out = [[0.0f32; CHANNELS]; STEPS];
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
        *sample = sample_in(waypoints, cum, s, above);
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
            let mut w = sample_at(waypoints, cum, mid);
            w[TOOL] = 1.0;
            out[k] = w;
            positions[k] = mid;
        }
    }
    out
}

fn sample_at(waypoints: &[Waypoint], cum: &[f64], s: f64) -> Waypoint {
    // First index whose cumulative length exceeds s.
    sample_in(waypoints, cum, s, cum.partition_point(|&c| c <= s))
}

/// [`sample_at`] given `above`, the number of cumulative lengths `<= s` (the first index
/// whose cumulative length exceeds `s`).
fn sample_in(waypoints: &[Waypoint], cum: &[f64], s: f64, above: usize) -> Waypoint {
    let n = waypoints.len();
    if n == 1 {
        return waypoints[0];
    }
    let hi = above.clamp(1, n - 1);
    let lo = hi - 1;
    let span = cum[hi] - cum[lo];
    let t = if span > 0.0 {
        ((s - cum[lo]) / span).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let mut w = [0.0f32; CHANNELS];
    for j in 0..JOINTS {
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
        [q, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0, tool]
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
            let out = resample(&ws, &cum);
            let span = cum[n - 1] - cum[0];
            for (k, sample) in out.iter().enumerate() {
                let s = cum[0] + span * k as f64 / (STEPS - 1) as f64;
                assert_eq!(*sample, sample_at(&ws, &cum, s), "n {n}, k {k}");
            }
        }
    }

    #[test]
    fn validation_reports_each_kind_with_index() {
        let good = vec![wp(0.0, 0.0), wp(0.1, 1.0), wp(0.2, 0.0)];
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
        assert_eq!(
            from_flat(&[0.0; 14], 7).unwrap_err(),
            InvalidTrajectory {
                kind: InvalidKind::WrongChannelCount,
                index: 7
            }
        );
        assert_eq!(
            from_flat(&[0.0; 17], 8).unwrap_err().kind,
            InvalidKind::WrongChannelCount
        );
        for k in 1..=6u8 {
            assert_eq!(InvalidKind::from_u8(k).map(|k| k as u8), Some(k));
        }
        assert_eq!(InvalidKind::from_u8(0), None);
    }

    #[test]
    fn resample_is_uniform_in_the_given_length() {
        let w = vec![wp(0.0, 0.0), wp(1.0, 0.0), wp(2.0, 0.0)];
        // First segment is 3x longer than the second.
        let out = resample(&w, &[0.0, 3.0, 4.0]);
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
        let out = resample(&w, &[0.0, 10.0, 10.0001, 20.0]);
        let down: Vec<_> = out.iter().filter(|s| s[TOOL] == 1.0).collect();
        assert_eq!(down.len(), 1);
        assert!((down[0][0] - 0.50005).abs() < 1e-4);
    }

    #[test]
    fn zero_length_falls_back_to_index() {
        let w = vec![wp(0.0, 0.0), wp(0.0, 0.0)];
        let out = resample(&w, &[0.0, 0.0]);
        assert!(out.iter().all(|s| s[0] == 0.0));
    }
}
