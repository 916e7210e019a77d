//! Per-class plan geometry: a small descriptor of where, how large and in which direction a
//! plan draws, compared with the enrolled examples of the class it claims.
//!
//! The embedder removes position, size and drawing direction by design (that is what makes
//! few-shot recognition work); this descriptor keeps them. A candidate's **geometry score**
//! is, for every feature `k`, its distance to the nearest enrolled example's value divided
//! by the feature's pooled within-class spread `s_k`, maximised over the features:
//!
//! `score = max_k  min_i |g_k − e_{i,k}| / s_k`
//!
//! (the nearest example rather than the mean, because drawers of one character often differ
//! in stroke order and direction: a plan is consistent if some enrolled example started or
//! drew that way). The pooled spreads come from a validation alphabet (five shots cannot
//! estimate a spread; a pooled scale can), and the threshold on the score is calibrated for a
//! share of the false-reject budget (`bank::calibrate_geometry`).
//!
//! A joint score (one enrolled example for all features: `min_i max_k`, or an RMS over the
//! features) was compared on the training alphabets and rejected: same threshold, same
//! false rejects and detections for `max`, doubled false rejects for RMS
//! (`docs/operating.md`, "Per-feature nearest example").

use guardian_shared::workcell::{GEOMETRY_FEATURES, GeometryFeature};
use serde::{Deserialize, Serialize};

/// Smallest size (m) before taking logarithms (a dot has no width).
const MIN_SIZE: f64 = 1e-3;

/// Descriptor of one plan's drawing, indexed by [`GeometryFeature`] (`ALL[i]` is value `i`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct PlanGeometry(pub [f32; GEOMETRY_FEATURES]);

impl PlanGeometry {
    /// Value of one feature.
    pub fn get(&self, f: GeometryFeature) -> f32 {
        self.0[f as usize - 1]
    }

    /// Describe a pen path: points `(x right, y up)` in metres with their pen-down flag.
    /// `None` if no point is pen-down.
    pub fn from_pen_path(points: impl Iterator<Item = ([f32; 2], bool)>) -> Option<Self> {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        let mut length = 0.0f64;
        let mut strokes = 0u32;
        let mut start: Option<[f64; 2]> = None;
        let mut end = [0.0f64; 2];
        let mut dir = [0.0f64; 2];
        let mut stroke_start = [0.0f64; 2];
        let mut prev: Option<[f64; 2]> = None; // previous point if it was pen-down
        for (p, down) in points {
            let p = [f64::from(p[0]), f64::from(p[1])];
            if !down {
                if let Some(q) = prev {
                    dir[0] += q[0] - stroke_start[0];
                    dir[1] += q[1] - stroke_start[1];
                }
                prev = None;
                continue;
            }
            for a in 0..2 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
            match prev {
                Some(q) => length += (p[0] - q[0]).hypot(p[1] - q[1]),
                None => {
                    strokes += 1;
                    stroke_start = p;
                }
            }
            start.get_or_insert(p);
            end = p;
            prev = Some(p);
        }
        if let Some(q) = prev {
            dir[0] += q[0] - stroke_start[0];
            dir[1] += q[1] - stroke_start[1];
        }
        let start = start?;
        let c = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
        let (w, h) = (hi[0] - lo[0], hi[1] - lo[1]);
        let size = w.max(h).max(MIN_SIZE);
        let length = length.max(MIN_SIZE);
        let v = [
            c[0],
            c[1],
            w.max(MIN_SIZE).ln(),
            h.max(MIN_SIZE).ln(),
            length.ln(),
            f64::from(strokes).ln(),
            (start[0] - c[0]) / size,
            (start[1] - c[1]) / size,
            (end[0] - c[0]) / size,
            (end[1] - c[1]) / size,
            dir[0] / length,
            dir[1] / length,
        ];
        Some(Self(v.map(|x| x as f32)))
    }

    /// All values finite.
    pub fn is_finite(&self) -> bool {
        self.0.iter().all(|v| v.is_finite())
    }
}

/// Geometry score of `g` against a class's enrolled examples (see the module docs) and the
/// feature that decided it. `None` without examples.
pub fn score(
    g: &PlanGeometry,
    examples: &[PlanGeometry],
    scales: &[f32; GEOMETRY_FEATURES],
) -> Option<(f32, GeometryFeature)> {
    if examples.is_empty() {
        return None;
    }
    let mut worst = (f32::NEG_INFINITY, GeometryFeature::CentreX);
    for (k, f) in GeometryFeature::ALL.iter().enumerate() {
        let d = examples
            .iter()
            .map(|e| (g.0[k] - e.0[k]).abs())
            .fold(f32::INFINITY, f32::min)
            / scales[k].max(f32::MIN_POSITIVE);
        let d = if d.is_nan() { f32::INFINITY } else { d };
        if d > worst.0 {
            worst = (d, *f);
        }
    }
    Some(worst)
}

/// The geometry rule, the one place it is written: a plan whose geometry score against its
/// claimed class exceeds the calibrated `threshold` is a no-go, and so is a score that is
/// not a number (a degenerate descriptor is never a pass). The daemon's decision
/// (`guardian_bank::ClassBank::decide_with_geometry`), the calibration
/// (`guardian_bank::calibrate_geometry`) and the lab's figures all use it.
pub fn is_geometry_no_go(score: f32, threshold: f32) -> bool {
    // Only a score that compares at most the threshold passes: NaN compares to nothing.
    !matches!(
        score.partial_cmp(&threshold),
        Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
    )
}

/// `score / threshold` as a continuous score for ROC curves: above 1 exactly when
/// [`is_geometry_no_go`], at most 1 otherwise (a NaN score is +∞).
pub fn normalised_geometry_score(score: f32, threshold: f32) -> f32 {
    let r = score / threshold;
    if is_geometry_no_go(score, threshold) {
        if r.is_nan() {
            f32::INFINITY
        } else {
            r.max(1.0f32.next_up())
        }
    } else {
        r.min(1.0)
    }
}

/// Pooled within-class standard deviation of every feature: `sqrt(Σ_c Σ_i (g − mean_c)² /
/// Σ_c (n_c − 1))` over the groups (classes) with at least two members. Features without
/// spread get a tiny positive scale. `None` if no group has two members.
pub fn pooled_scales(groups: &[Vec<PlanGeometry>]) -> Option<[f32; GEOMETRY_FEATURES]> {
    let mut ss = [0.0f64; GEOMETRY_FEATURES];
    let mut df = 0usize;
    for g in groups.iter().filter(|g| g.len() >= 2) {
        let n = g.len() as f64;
        for (k, acc) in ss.iter_mut().enumerate() {
            let m = g.iter().map(|e| f64::from(e.0[k])).sum::<f64>() / n;
            *acc += g
                .iter()
                .map(|e| (f64::from(e.0[k]) - m).powi(2))
                .sum::<f64>();
        }
        df += g.len() - 1;
    }
    if df == 0 {
        return None;
    }
    Some(ss.map(|s| ((s / df as f64).sqrt() as f32).max(1e-6)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two strokes: a horizontal line, then a vertical one.
    /// One rule, one NaN answer: the rule and its continuous score agree on every value,
    /// NaN included (a no-go), and the calibration counts a NaN score as a reject.
    #[test]
    fn a_nan_geometry_score_is_a_no_go_everywhere() {
        let t = 2.0;
        for (s, expected) in [
            (0.0, false),
            (1.0, false),
            (2.0, false),
            (2.0f32.next_up(), true),
            (3.0, true),
            (f32::INFINITY, true),
            (f32::NAN, true),
        ] {
            let no_go = is_geometry_no_go(s, t);
            assert_eq!(no_go, expected, "{s}");
            assert_eq!(normalised_geometry_score(s, t) > 1.0, no_go, "{s}");
        }
        assert!(is_geometry_no_go(f32::NAN, f32::INFINITY));
        assert_eq!(normalised_geometry_score(f32::NAN, t), f32::INFINITY);
    }

    fn drawing(dx: f32, s: f32, reverse: bool) -> Vec<([f32; 2], bool)> {
        let mut a: Vec<[f32; 2]> = (0..=10).map(|i| [i as f32 * 0.01, 0.0]).collect();
        let mut b: Vec<[f32; 2]> = (0..=5).map(|i| [0.05, i as f32 * 0.01]).collect();
        if reverse {
            a.reverse();
            b.reverse();
        }
        let mut out = Vec::new();
        for p in a {
            out.push(([dx + s * p[0], s * p[1]], true));
        }
        out.push(([dx + 0.03 * s, 0.03 * s], false));
        for p in b {
            out.push(([dx + s * p[0], s * p[1]], true));
        }
        out
    }

    #[test]
    fn descriptor_of_a_known_drawing() {
        let g = PlanGeometry::from_pen_path(drawing(0.0, 1.0, false).into_iter()).unwrap();
        let v = |f| g.get(f);
        assert!((v(GeometryFeature::CentreX) - 0.05).abs() < 1e-6);
        assert!((v(GeometryFeature::CentreY) - 0.025).abs() < 1e-6);
        assert!((v(GeometryFeature::Width) - 0.1f32.ln()).abs() < 1e-5);
        assert!((v(GeometryFeature::Height) - 0.05f32.ln()).abs() < 1e-5);
        assert!((v(GeometryFeature::PenDownLength) - 0.15f32.ln()).abs() < 1e-5);
        assert!((v(GeometryFeature::Strokes) - 2.0f32.ln()).abs() < 1e-6);
        assert!((v(GeometryFeature::StartX) + 0.5).abs() < 1e-5);
        assert!((v(GeometryFeature::EndY) - 0.25).abs() < 1e-5);
        assert!((v(GeometryFeature::DirectionX) - 0.1 / 0.15).abs() < 1e-5);
        assert!((v(GeometryFeature::DirectionY) - 0.05 / 0.15).abs() < 1e-5);
        assert!(PlanGeometry::from_pen_path([([0.0, 0.0], false)].into_iter()).is_none());
    }

    #[test]
    fn shift_scale_and_reversal_move_the_expected_features() {
        let g = PlanGeometry::from_pen_path(drawing(0.0, 1.0, false).into_iter()).unwrap();
        let shifted = PlanGeometry::from_pen_path(drawing(0.02, 1.0, false).into_iter()).unwrap();
        let scaled = PlanGeometry::from_pen_path(drawing(0.0, 1.3, false).into_iter()).unwrap();
        let rev = PlanGeometry::from_pen_path(drawing(0.0, 1.0, true).into_iter()).unwrap();
        let scales = [0.005f32; GEOMETRY_FEATURES];
        let (s, f) = score(&shifted, &[g], &scales).unwrap();
        assert_eq!(f, GeometryFeature::CentreX);
        assert!((s - 4.0).abs() < 1e-3, "{s}");
        let (_, f) = score(&scaled, &[g], &scales).unwrap();
        assert!(
            matches!(
                f,
                GeometryFeature::Width | GeometryFeature::Height | GeometryFeature::PenDownLength
            ),
            "{f:?}"
        );
        assert!(
            (scaled.get(GeometryFeature::Width) - g.get(GeometryFeature::Width) - 1.3f32.ln())
                .abs()
                < 1e-5
        );
        assert!(
            (rev.get(GeometryFeature::DirectionX) + g.get(GeometryFeature::DirectionX)).abs()
                < 1e-6
        );
        assert_eq!(score(&g, &[g], &scales).unwrap().0, 0.0);
        assert!(score(&g, &[], &scales).is_none());
        let p = pooled_scales(&[vec![g, shifted], vec![g]]).unwrap();
        assert!(
            (p[0] - (2.0f32 * 0.01 * 0.01).sqrt()).abs() < 1e-6,
            "{}",
            p[0]
        );
        assert!(pooled_scales(&[vec![g]]).is_none());
    }
}
