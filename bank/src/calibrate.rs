//! Calibration: the thresholds, wrong-task tolerance and per-class scale chosen from genuine
//! plans of validation classes, and the geometry threshold.

use guardian_shared::workcell::GEOMETRY_FEATURES;
use serde::{Deserialize, Serialize};

use super::DEFAULT_THRESHOLD;
use super::decide::is_wrong_task;

/// How a threshold was calibrated.
///
/// The bank-level record (see [`ClassBank::apply_calibration`]) also carries the numbers
/// that derive thresholds for classes enrolled later: `class_scale` (a class with at least
/// [`MIN_CLASS_CALIBRATION`] examples gets `class_scale * class_spread`) and
/// `wrong_task_tolerance` (how much nearer another class must be to call a wrong task).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// Method name, e.g. `"quantile"`.
    pub method: String,
    /// Number of samples the threshold was derived from.
    pub samples: u32,
    /// Target false-reject (or other) rate the method aimed at, if any.
    pub target_rate: Option<f32>,
    /// Free text: data set, date, model version.
    pub note: String,
    /// Global threshold chosen by the calibration (bank-level record).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub global_threshold: Option<f32>,
    /// Per-class threshold = `class_scale * class_spread(embeddings)` (bank-level record).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub class_scale: Option<f32>,
    /// Wrong-task tolerance chosen by the calibration (bank-level record).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wrong_task_tolerance: Option<f32>,
    /// False-reject rate measured on the calibration data with the chosen numbers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured_rate: Option<f32>,
}

/// A class needs at least this many enrolled examples for its own (spread-scaled)
/// threshold; below it uses the bank's global threshold.
pub const MIN_CLASS_CALIBRATION: usize = 3;

/// Spread of a class: root mean square of the leave-one-out distances (each example to the
/// mean of the others). `None` below [`MIN_CLASS_CALIBRATION`] examples.
pub fn class_spread(embeddings: &[Vec<f32>]) -> Option<f32> {
    let n = embeddings.len();
    if n < MIN_CLASS_CALIBRATION {
        return None;
    }
    let dim = embeddings[0].len();
    let sum = embeddings.iter().fold(vec![0.0f64; dim], |mut acc, e| {
        for (a, &v) in acc.iter_mut().zip(e) {
            *a += f64::from(v);
        }
        acc
    });
    let mut sq = 0.0f64;
    for e in embeddings {
        let d2: f64 = e
            .iter()
            .zip(&sum)
            .map(|(&v, &s)| {
                let rest = (s - f64::from(v)) / (n - 1) as f64;
                (f64::from(v) - rest).powi(2)
            })
            .sum();
        sq += d2;
    }
    Some(((sq / n as f64).sqrt()) as f32)
}

/// The smallest score `t` among `scores` such that at most `allowed` scores exceed it
/// (`None` for no scores; 0 if every score may be rejected).
pub fn threshold_allowing(scores: &[f32], allowed: usize) -> Option<f32> {
    if scores.is_empty() {
        return None;
    }
    if allowed >= scores.len() {
        return Some(0.0);
    }
    let mut s: Vec<f32> = scores.to_vec();
    s.sort_by(f32::total_cmp);
    Some(s[s.len() - 1 - allowed])
}

/// One genuine plan scored against a bank it belongs to: distance to its own class, to the
/// nearest other class, and the spread of its class.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GenuineScore {
    /// Distance to the claimed (true) class prototype.
    pub claimed: f32,
    /// Distance to the nearest other prototype, if any.
    pub nearest_other: Option<f32>,
    /// [`class_spread`] of the claimed class, if it has enough examples.
    pub spread: Option<f32>,
}

impl GenuineScore {
    /// The embedding decision as one number: `max(d_c / t_c, d_c / (d_o + tol))` with the
    /// calibration's class threshold `t_c` (`class_scale × spread`, else the global one) and
    /// wrong-task tolerance; `> 1` exactly when [`super::ClassBank::decide`] answers no-go (the
    /// continuous form of [`super::is_wrong_task`] or [`super::is_outlier`]; a test in
    /// `bank` holds the two together).
    pub fn normalised(&self, cal: &Calibration) -> f32 {
        let global = cal.global_threshold.unwrap_or(DEFAULT_THRESHOLD);
        let t = match (cal.class_scale, self.spread) {
            (Some(k), Some(s)) => k * s,
            _ => global,
        };
        let tol = cal.wrong_task_tolerance.unwrap_or(0.0);
        let a = self.claimed / t.max(1e-12);
        let b = self
            .nearest_other
            .map_or(0.0, |o| self.claimed / (o + tol).max(1e-12));
        a.max(b)
    }
}

/// The geometry check's calibration, stored in the bank (see [`crate::geometry`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometryCalibration {
    /// Pooled within-class spread of every feature (validation alphabet), in
    /// [`GeometryFeature::ALL`] order.
    pub scales: [f32; GEOMETRY_FEATURES],
    /// A plan whose geometry score exceeds this is a [`NoGoReason::GeometryMismatch`](guardian_shared::verdict::NoGoReason::GeometryMismatch).
    pub threshold: f32,
    /// Combined false-reject target (embedding and geometry together).
    pub target_rate: f32,
    /// Genuine plans the threshold was chosen from.
    pub samples: u32,
    /// Combined false-reject rate (embedding or geometry) on the calibration data.
    pub measured_rate: f32,
    /// Free text: data, split of the budget.
    pub note: String,
}

/// Choose the geometry threshold for genuine calibration plans already scored by the
/// embedding calibration `cal`: of the budget `floor(target_rate × n)`, what the embedding
/// rule has not used goes to the geometry score, on the plans the embedding accepts.
/// `geometry[i]` is the geometry score of `scores[i]` (`None`: no descriptor, never rejected
/// by geometry). `None` if there are no scores or the rate is not in `[0, 1)`.
pub fn calibrate_geometry(
    scores: &[GenuineScore],
    geometry: &[Option<f32>],
    cal: &Calibration,
    target_rate: f32,
    scales: [f32; GEOMETRY_FEATURES],
    note: &str,
) -> Option<GeometryCalibration> {
    if scores.is_empty() || scores.len() != geometry.len() || !(0.0..1.0).contains(&target_rate) {
        return None;
    }
    let n = scores.len();
    let budget = (f64::from(target_rate) * n as f64).floor() as usize;
    let emb_rejected: Vec<bool> = scores.iter().map(|s| s.normalised(cal) > 1.0).collect();
    let used = emb_rejected.iter().filter(|&&r| r).count();
    let kept: Vec<f32> = geometry
        .iter()
        .zip(&emb_rejected)
        .filter(|(_, r)| !**r)
        .filter_map(|(g, _)| *g)
        // A NaN score is always a no-go: it sorts above every threshold.
        .map(|g| if g.is_nan() { f32::INFINITY } else { g })
        .collect();
    let threshold = threshold_allowing(&kept, budget.saturating_sub(used))
        .unwrap_or(f32::MAX)
        .max(f32::MIN_POSITIVE);
    let rejected = geometry
        .iter()
        .zip(&emb_rejected)
        .filter(|(g, r)| {
            **r || g.is_some_and(|g| guardian_robot::geometry::is_geometry_no_go(g, threshold))
        })
        .count();
    Some(GeometryCalibration {
        scales,
        threshold,
        target_rate,
        samples: u32::try_from(n).unwrap_or(u32::MAX),
        measured_rate: rejected as f32 / n as f32,
        note: note.to_owned(),
    })
}

/// Choose the wrong-task tolerance, the global threshold and the per-class scale so that at
/// most `target_rate` of the genuine plans are rejected by [`super::ClassBank::decide`].
///
/// Half of the budget goes to wrong-task rejections (tolerance = the `1 - target/2`
/// quantile of `claimed - nearest_other`, at least 0); what is left of the budget after
/// the wrong-task rejections goes to the distance threshold (global: on `claimed`; per
/// class: on `claimed / spread`). `None` if there are no scores or the rate is not in
/// `[0, 1)`.
pub fn calibrate(scores: &[GenuineScore], target_rate: f32, note: &str) -> Option<Calibration> {
    if scores.is_empty() || !(0.0..1.0).contains(&target_rate) {
        return None;
    }
    let n = scores.len();
    let budget = (f64::from(target_rate) * n as f64).floor() as usize;
    let gaps: Vec<f32> = scores
        .iter()
        .filter_map(|s| s.nearest_other.map(|o| s.claimed - o))
        .collect();
    let tol = threshold_allowing(&gaps, budget / 2)
        .unwrap_or(0.0)
        .max(0.0);
    let wrong = |s: &GenuineScore| {
        s.nearest_other
            .is_some_and(|o| is_wrong_task(s.claimed, o, tol))
    };
    let wrong_n = scores.iter().filter(|s| wrong(s)).count();
    let left = budget.saturating_sub(wrong_n);
    let kept: Vec<&GenuineScore> = scores.iter().filter(|s| !wrong(s)).collect();
    let d: Vec<f32> = kept.iter().map(|s| s.claimed).collect();
    let global = threshold_allowing(&d, left).unwrap_or(DEFAULT_THRESHOLD);
    let ratios: Vec<f32> = kept
        .iter()
        .filter_map(|s| s.spread.filter(|&v| v > 0.0).map(|v| s.claimed / v))
        .collect();
    let with_spread = scores.iter().filter(|s| s.spread.is_some()).count();
    let class_scale = if ratios.is_empty() {
        None
    } else {
        let b = (f64::from(target_rate) * with_spread as f64).floor() as usize;
        let w = with_spread - ratios.len();
        threshold_allowing(&ratios, b.saturating_sub(w))
    };
    let rejected = wrong_n + d.iter().filter(|&&v| v > global).count();
    Some(Calibration {
        method: "genuine-quantile".into(),
        samples: u32::try_from(n).unwrap_or(u32::MAX),
        target_rate: Some(target_rate),
        note: note.to_owned(),
        global_threshold: Some(global),
        class_scale,
        wrong_task_tolerance: Some(tol),
        measured_rate: Some(rejected as f32 / n as f32),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_shared::workcell::GEOMETRY_FEATURES;

    /// The calibration counts a NaN geometry score as a reject (the rule's NaN answer,
    /// `guardian_robot::geometry::is_geometry_no_go`).
    #[test]
    fn a_nan_geometry_score_counts_as_a_reject() {
        // Calibration: 10 genuine plans, none rejected by the embedding, one with a NaN
        // geometry score and a budget of one reject: the NaN plan takes the budget, so the
        // threshold keeps every finite score and the measured rate counts the NaN once.
        let scores = vec![
            GenuineScore {
                claimed: 0.1,
                nearest_other: None,
                spread: None,
            };
            10
        ];
        let mut geometry: Vec<Option<f32>> = (1..=9).map(|i| Some(i as f32)).collect();
        geometry.push(Some(f32::NAN));
        let cal = Calibration {
            method: "t".into(),
            samples: 10,
            target_rate: None,
            note: String::new(),
            global_threshold: Some(1.0),
            class_scale: None,
            wrong_task_tolerance: None,
            measured_rate: None,
        };
        let g = calibrate_geometry(&scores, &geometry, &cal, 0.1, [1.0; GEOMETRY_FEATURES], "t")
            .unwrap();
        assert_eq!(g.threshold, 9.0);
        assert!((g.measured_rate - 0.1).abs() < 1e-6, "{}", g.measured_rate);
    }
}
