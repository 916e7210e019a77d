//! The decision rule (see the module docs of [`crate::bank`]), written once: nearest-class
//! search, [`is_wrong_task`] and [`is_outlier`], [`ClassBank::decide`] and the geometry step.

use guardian_shared::wire::{CheckAnswer, CheckVerdict, NoGo};
use guardian_shared::workcell::GeometryFeature;

use super::distance::{Distances, distance};
use super::{ClassBank, Neighbour};
use guardian_robot::geometry::{self, PlanGeometry};
use guardian_robot::place::{self, PlaceRule, PlaceScore, PlaceSignature};

/// Step 2 of the rule: another class, at distance `nearest_other`, is nearer than the
/// claimed one (at `claimed`) by more than the wrong-task `tolerance`.
pub fn is_wrong_task(claimed: f32, nearest_other: f32, tolerance: f32) -> bool {
    nearest_other + tolerance < claimed
}

/// Step 3 of the rule: the claimed class is farther than its `threshold` (or the distance
/// is not a number).
pub fn is_outlier(claimed: f32, threshold: f32) -> bool {
    claimed.is_nan() || claimed > threshold
}

/// The decision of [`ClassBank::decide`].
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// The trajectory is the class it claims to be.
    Go,
    /// Another class is nearer than the claimed one.
    WrongTask {
        /// The nearest class.
        nearest: String,
    },
    /// The claimed class is nearest but farther than its threshold.
    Outlier,
    /// The embedding fits the claimed class, but the plan draws in another place, size,
    /// stroke count or direction than every enrolled example.
    GeometryMismatch {
        /// The feature farthest from the enrolled examples (relative to its spread).
        feature: GeometryFeature,
    },
    /// The claimed class is not enrolled.
    UnknownClass,
}

/// A decision with the numbers behind it.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// Go or why not.
    pub outcome: Outcome,
    /// Distance to the claimed prototype (`None` if the class is unknown).
    pub claimed_distance: Option<f32>,
    /// Threshold used for the claimed class.
    pub threshold: Option<f32>,
    /// `threshold - claimed_distance`.
    pub margin: Option<f32>,
    /// Distance to the nearest other class minus `claimed_distance`.
    pub gap: Option<f32>,
    /// The k nearest classes, nearest first.
    pub nearest: Vec<Neighbour>,
    /// Geometry score against the claimed class (`None`: check not applicable).
    pub geometry_score: Option<f32>,
    /// Geometry threshold (`None`: check not applicable).
    pub geometry_threshold: Option<f32>,
    /// The feature behind `geometry_score`.
    pub geometry_feature: Option<GeometryFeature>,
}

impl Decision {
    /// A decision on an enrolled class: distance `d` to it, its `threshold`, the distance
    /// to the nearest other class that competed (if any), the `nearest` classes; no
    /// geometry numbers yet.
    fn measured(
        outcome: Outcome,
        d: f32,
        threshold: f32,
        other: Option<f32>,
        nearest: Vec<Neighbour>,
    ) -> Self {
        Self {
            outcome,
            claimed_distance: Some(d),
            threshold: Some(threshold),
            margin: Some(threshold - d),
            gap: other.map(|o| o - d),
            nearest,
            geometry_score: None,
            geometry_threshold: None,
            geometry_feature: None,
        }
    }

    /// The claimed class is not enrolled: no numbers, the `nearest` classes.
    fn unknown_class(nearest: Vec<Neighbour>) -> Self {
        Self {
            outcome: Outcome::UnknownClass,
            claimed_distance: None,
            threshold: None,
            margin: None,
            gap: None,
            nearest,
            geometry_score: None,
            geometry_threshold: None,
            geometry_feature: None,
        }
    }

    /// The decision as the wire carries it: the one conversion from the bank's decision to
    /// the response (the client's `Verdict::from_response` is the one conversion back; a
    /// test in `daemon/tests/verdict.rs` holds the two together). The nearest classes
    /// travel as the response's entries, not in the header.
    pub fn answer(&self) -> CheckAnswer {
        let verdict = match &self.outcome {
            Outcome::Go => CheckVerdict::Go,
            Outcome::WrongTask { .. } => CheckVerdict::NoGo(NoGo::WrongTask),
            Outcome::Outlier => CheckVerdict::NoGo(NoGo::Outlier),
            Outcome::GeometryMismatch { feature } => {
                CheckVerdict::NoGo(NoGo::GeometryMismatch(*feature))
            }
            Outcome::UnknownClass => CheckVerdict::NoGo(NoGo::UnknownClass),
        };
        CheckAnswer {
            verdict,
            claimed_distance: self.claimed_distance,
            threshold: self.threshold,
            margin: self.margin,
            gap: self.gap,
            geometry_score: self.geometry_score,
            geometry_threshold: self.geometry_threshold,
            geometry_feature: self.geometry_feature,
        }
    }
}

impl ClassBank {
    /// Every class with its distance to `query`, nearest first (ties by name).
    pub fn ranked(&self, query: &[f32]) -> Vec<Neighbour> {
        self.ranked_refs(query, usize::MAX)
            .into_iter()
            .map(|(distance, name)| Neighbour {
                name: name.to_owned(),
                distance,
            })
            .collect()
    }

    /// The first `m` entries of [`ClassBank::ranked`] (all with `usize::MAX`), without
    /// copying the names.
    fn ranked_refs(&self, query: &[f32], m: usize) -> Vec<(f32, &str)> {
        let mut v: Vec<(f32, &str)> = Vec::with_capacity(self.classes.len());
        pulp::Arch::new().dispatch(Distances {
            bank: self,
            query,
            out: &mut v,
        });
        // Names are unique, so the order is total and unstable sorting is deterministic.
        let order = |a: &(f32, &str), b: &(f32, &str)| a.0.total_cmp(&b.0).then(a.1.cmp(b.1));
        if m < v.len() {
            if m > 0 {
                v.select_nth_unstable_by(m - 1, order);
            }
            v.truncate(m);
        }
        v.sort_unstable_by(order);
        v
    }

    /// The `k` nearest classes to `query`, nearest first.
    pub fn nearest(&self, query: &[f32], k: usize) -> Vec<Neighbour> {
        let mut v = self.ranked(query);
        v.truncate(k);
        v
    }

    /// Apply the decision rule (see the module docs) to `query` claiming class `claimed`.
    pub fn decide(&self, query: &[f32], claimed: &str, k: usize) -> Decision {
        // The k nearest, and at least two: the nearest class other than the claimed one is
        // among the first two.
        let ranked = self.ranked_refs(query, k.max(1) + 1);
        let nearest: Vec<Neighbour> = ranked
            .iter()
            .take(k)
            .map(|&(distance, name)| Neighbour {
                name: name.to_owned(),
                distance,
            })
            .collect();
        let Some(class) = self.classes.get(claimed) else {
            return Decision::unknown_class(nearest);
        };
        let d = distance(query, &class.prototype);
        let threshold = class.threshold.unwrap_or(self.default_threshold);
        let other = ranked.iter().find(|n| n.1 != claimed);
        let outcome = match other {
            Some(&(od, name)) if is_wrong_task(d, od, self.wrong_task_tolerance) => {
                Outcome::WrongTask {
                    nearest: name.to_owned(),
                }
            }
            _ if is_outlier(d, threshold) => Outcome::Outlier,
            _ => Outcome::Go,
        };
        Decision::measured(outcome, d, threshold, other.map(|o| o.0), nearest)
    }

    /// Geometry score of `g` against class `name` and the deciding feature, with the
    /// threshold; `None` if the check does not apply (no geometry calibration, unknown
    /// class, or a class without descriptors).
    pub fn geometry_score(
        &self,
        g: &PlanGeometry,
        name: &str,
    ) -> Option<(f32, GeometryFeature, f32)> {
        let cal = self.geometry_calibration.as_ref()?;
        let class = self.classes.get(name).filter(|c| c.has_geometry())?;
        let (s, f) = geometry::score(g, &class.geometry, &cal.scales)?;
        Some((s, f, cal.threshold))
    }

    /// [`ClassBank::decide`], then the geometry check (step 4 of the module docs) for a plan
    /// whose embedding decision is go. The geometry numbers are filled in whenever the check
    /// applies.
    pub fn decide_with_geometry(
        &self,
        query: &[f32],
        geometry: Option<&PlanGeometry>,
        claimed: &str,
        k: usize,
    ) -> Decision {
        let mut d = self.decide(query, claimed, k);
        if let Some((s, f, t)) = geometry.and_then(|g| self.geometry_score(g, claimed)) {
            d.geometry_score = Some(s);
            d.geometry_threshold = Some(t);
            d.geometry_feature = Some(f);
            if d.outcome == Outcome::Go && geometry::is_geometry_no_go(s, t) {
                d.outcome = Outcome::GeometryMismatch { feature: f };
            }
        }
        d
    }

    /// The place score of `plan` against class `name` under `rule` (`None` for a class not
    /// enrolled). A class without place signatures cannot say where it happens: its score
    /// is infinite, so an anchored deployment never passes a plan on it.
    pub fn place_score(
        &self,
        plan: &PlaceSignature,
        name: &str,
        rule: &PlaceRule,
    ) -> Option<PlaceScore> {
        let class = self.classes.get(name)?;
        let unplaced = PlaceScore {
            excess: f32::INFINITY,
            point: None,
            deviation: f32::INFINITY,
        };
        if !class.has_place() {
            return Some(unplaced);
        }
        Some(place::score(plan, &class.place, rule).unwrap_or(unplaced))
    }

    /// Every class with its distance to `query`, the classes in the plan's place (under
    /// `rule`) first, each part nearest first: what identify answers in an anchored
    /// deployment, so a plan is named after a task that happens where it does.
    pub fn ranked_in_place(
        &self,
        query: &[f32],
        plan: &PlaceSignature,
        rule: &PlaceRule,
    ) -> Vec<Neighbour> {
        self.ranked_with_place(query, plan, rule)
            .into_iter()
            .map(|(n, _, _)| n)
            .collect()
    }

    /// [`ClassBank::ranked_in_place`], each class with its place score and whether it is
    /// in the plan's place (every class's place scored once).
    fn ranked_with_place(
        &self,
        query: &[f32],
        plan: &PlaceSignature,
        rule: &PlaceRule,
    ) -> Vec<(Neighbour, Option<PlaceScore>, bool)> {
        let (mut inside, outside): (Vec<_>, Vec<_>) = self
            .ranked(query)
            .into_iter()
            .map(|n| {
                let score = self.place_score(plan, &n.name, rule);
                let here = score.is_some_and(|s| !rule.is_other_place(s.excess));
                (n, score, here)
            })
            .partition(|(_, _, here)| *here);
        inside.extend(outside);
        inside
    }

    /// The decision rule of an anchored deployment (see the crate docs): a plan must be its
    /// claimed class in shape and in place. Only classes in the plan's place compete for
    /// wrong task; then a plan in another place than its class's examples is a
    /// [`Outcome::GeometryMismatch`] on [`GeometryFeature::Place`] (before the outlier step:
    /// the place is the plainer reason), with the
    /// place excess (m) as the geometry score and the rule's tolerance as its threshold.
    /// The nearest classes are those of [`ClassBank::ranked_in_place`].
    pub fn decide_in_place(
        &self,
        query: &[f32],
        plan: &PlaceSignature,
        rule: &PlaceRule,
        claimed: &str,
        k: usize,
    ) -> Decision {
        let ranked = self.ranked_with_place(query, plan, rule);
        let nearest: Vec<Neighbour> = ranked.iter().take(k).map(|(n, ..)| n.clone()).collect();
        // The claimed class's place score, from the ranking (scored once).
        let claimed_score = ranked
            .iter()
            .find(|(n, ..)| n.name == claimed)
            .and_then(|(_, s, _)| *s);
        let (Some(class), Some(score)) = (self.classes.get(claimed), claimed_score) else {
            return Decision::unknown_class(nearest);
        };
        let d = distance(query, &class.prototype);
        let threshold = class.threshold.unwrap_or(self.default_threshold) * rule.shape;
        // The nearest other class in the plan's place (ranked puts those first).
        let other = ranked
            .iter()
            .find(|(n, _, here)| *here && n.name != claimed)
            .map(|(n, ..)| n);
        let outcome = match other {
            Some(o) if is_wrong_task(d, o.distance, self.wrong_task_tolerance) => {
                Outcome::WrongTask {
                    nearest: o.name.clone(),
                }
            }
            // Another place is the plain, physical reason: said before the shape's.
            _ if rule.is_other_place(score.excess) => Outcome::GeometryMismatch {
                feature: GeometryFeature::Place,
            },
            _ if is_outlier(d, threshold) => Outcome::Outlier,
            _ => Outcome::Go,
        };
        Decision {
            geometry_score: Some(score.excess),
            geometry_threshold: Some(rule.tolerance),
            geometry_feature: Some(GeometryFeature::Place),
            ..Decision::measured(outcome, d, threshold, other.map(|o| o.distance), nearest)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pick-and-place signature to bin `bin` (bins 6 cm apart along x), the part `dy` off.
    fn to_bin(bin: usize, dy: f64) -> PlaceSignature {
        let start = [0.4, 0.0, 0.4];
        let pick = [0.5, 0.2 + dy, 0.1];
        let place = [0.4 + 0.06 * bin as f64, -0.2, 0.1];
        let up = [place[0], place[1], 0.2];
        let mut pos = vec![];
        let mut tool = vec![];
        for (a, b, on) in [
            (start, pick, false),
            (pick, place, true),
            (place, up, false),
        ] {
            for i in 1..=8 {
                let t = f64::from(i) / 8.0;
                pos.push([0, 1, 2].map(|d| a[d] + t * (b[d] - a[d])));
                tool.push(on);
            }
        }
        PlaceSignature::of_path(&pos, &tool).unwrap()
    }

    /// Three tasks of one shape (the same embedding), each to its own bin.
    fn cell() -> ClassBank {
        let mut b = ClassBank::new(2, "m", 0.5);
        for bin in 0..3 {
            let e = vec![vec![1.0, 0.0], vec![1.0, 0.01], vec![0.99, 0.0]];
            let place: Vec<PlaceSignature> = [-0.015, 0.0, 0.015]
                .iter()
                .map(|&dy| to_bin(bin, dy))
                .collect();
            b.enroll_placed(&format!("bin{bin}"), &e, &[], &[], &place)
                .unwrap();
        }
        b
    }

    #[test]
    fn in_a_cell_the_place_decides_between_tasks_of_one_shape() {
        let b = cell();
        let rule = PlaceRule::DEFAULT;
        let q = [1.0, 0.005];
        // Genuine: go, although two other classes have the same shape.
        let d = b.decide_in_place(&q, &to_bin(1, 0.01), &rule, "bin1", 3);
        assert_eq!(d.outcome, Outcome::Go, "{d:?}");
        assert_eq!(d.nearest[0].name, "bin1");
        assert_eq!(d.geometry_feature, Some(GeometryFeature::Place));
        assert!(d.geometry_score.unwrap() <= rule.tolerance);
        assert_eq!(
            b.ranked_in_place(&q, &to_bin(2, 0.0), &rule)[0].name,
            "bin2"
        );
        // The same motion to the neighbouring bin: no-go on the place, with its excess.
        let d = b.decide_in_place(&q, &to_bin(2, 0.0), &rule, "bin1", 3);
        assert_eq!(
            d.outcome,
            Outcome::GeometryMismatch {
                feature: GeometryFeature::Place
            }
        );
        assert!(d.geometry_score.unwrap() > 0.03, "{d:?}");
        // The answer on the wire says so.
        let a = d.answer();
        assert_eq!(
            a.verdict,
            CheckVerdict::NoGo(NoGo::GeometryMismatch(GeometryFeature::Place))
        );
        // Not enrolled; enrolled without place signatures: never a go.
        let d = b.decide_in_place(&q, &to_bin(1, 0.0), &rule, "nope", 3);
        assert_eq!(d.outcome, Outcome::UnknownClass);
        let mut b = b;
        b.enroll("unplaced", &[vec![1.0, 0.005]]).unwrap();
        let d = b.decide_in_place(&q, &to_bin(1, 0.0), &rule, "unplaced", 3);
        assert!(
            matches!(d.outcome, Outcome::GeometryMismatch { .. }),
            "{d:?}"
        );
    }
}
