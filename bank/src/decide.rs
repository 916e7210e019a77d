//! The decision rule (see the module docs of [`crate::bank`]), written once: nearest-class
//! search, [`is_wrong_task`] and [`is_outlier`], [`ClassBank::decide`] and the geometry step.

use guardian_shared::verdict::{self, Decision, NoGoReason, Verdict};
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

/// A verdict on an enrolled class: distance `d` to it, its `threshold`, the distance to the
/// nearest other class that competed (if any), the `nearest` classes; no geometry numbers
/// yet.
fn measured(
    bank: &ClassBank,
    claimed: &str,
    outcome: Decision,
    d: f32,
    threshold: f32,
    other: Option<f32>,
    nearest: Vec<Neighbour>,
) -> Verdict {
    Verdict {
        claimed_distance: Some(d),
        threshold: Some(threshold),
        margin: Some(threshold - d),
        gap: other.map(|o| o - d),
        ..bare(bank, claimed, nearest, outcome)
    }
}

/// `decision` without numbers (as for a class not enrolled), with the `nearest` classes.
fn bare(bank: &ClassBank, claimed: &str, nearest: Vec<Neighbour>, decision: Decision) -> Verdict {
    Verdict {
        nearest: nearest
            .into_iter()
            .map(|n| verdict::Neighbour {
                threshold: bank.threshold(&n.name).unwrap_or(f32::NAN),
                class: n.name,
                distance: n.distance,
            })
            .collect(),
        ..Verdict::new(decision, claimed, &bank.model_version, bank.generation())
    }
}

/// No-go for `reason`.
fn no_go(reason: NoGoReason) -> Decision {
    Decision::NoGo { reason }
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
    pub fn decide(&self, query: &[f32], claimed: &str, k: usize) -> Verdict {
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
            return bare(self, claimed, nearest, no_go(NoGoReason::UnknownClass));
        };
        let d = distance(query, &class.prototype);
        let threshold = class.threshold.unwrap_or(self.default_threshold);
        let other = ranked.iter().find(|n| n.1 != claimed);
        let outcome = match other {
            Some(&(od, name)) if is_wrong_task(d, od, self.wrong_task_tolerance) => {
                no_go(NoGoReason::WrongTask {
                    nearest: name.to_owned(),
                })
            }
            _ if is_outlier(d, threshold) => no_go(NoGoReason::Outlier),
            _ => Decision::Go,
        };
        measured(
            self,
            claimed,
            outcome,
            d,
            threshold,
            other.map(|o| o.0),
            nearest,
        )
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
    ) -> Verdict {
        let mut d = self.decide(query, claimed, k);
        if let Some((s, f, t)) = geometry.and_then(|g| self.geometry_score(g, claimed)) {
            d.geometry_score = Some(s);
            d.geometry_threshold = Some(t);
            d.geometry_feature = Some(f);
            if d.is_go() && geometry::is_geometry_no_go(s, t) {
                d.decision = no_go(NoGoReason::GeometryMismatch {
                    feature: f,
                    score: s,
                    threshold: t,
                });
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
    /// [`NoGoReason::GeometryMismatch`] on [`GeometryFeature::Place`] (before the outlier step:
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
    ) -> Verdict {
        let ranked = self.ranked_with_place(query, plan, rule);
        let nearest: Vec<Neighbour> = ranked.iter().take(k).map(|(n, ..)| n.clone()).collect();
        // The claimed class's place score, from the ranking (scored once).
        let claimed_score = ranked
            .iter()
            .find(|(n, ..)| n.name == claimed)
            .and_then(|(_, s, _)| *s);
        let (Some(class), Some(score)) = (self.classes.get(claimed), claimed_score) else {
            return bare(self, claimed, nearest, no_go(NoGoReason::UnknownClass));
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
                no_go(NoGoReason::WrongTask {
                    nearest: o.name.clone(),
                })
            }
            // Another place is the plain, physical reason: said before the shape's.
            _ if rule.is_other_place(score.excess) => no_go(NoGoReason::GeometryMismatch {
                feature: GeometryFeature::Place,
                score: score.excess,
                threshold: rule.tolerance,
            }),
            _ if is_outlier(d, threshold) => no_go(NoGoReason::Outlier),
            _ => Decision::Go,
        };
        let other = other.map(|o| o.distance);
        Verdict {
            geometry_score: Some(score.excess),
            geometry_threshold: Some(rule.tolerance),
            geometry_feature: Some(GeometryFeature::Place),
            ..measured(self, claimed, outcome, d, threshold, other, nearest)
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
        assert_eq!(d.decision, Decision::Go, "{d:?}");
        assert_eq!(d.nearest[0].class, "bin1");
        assert_eq!(d.geometry_feature, Some(GeometryFeature::Place));
        assert!(d.geometry_score.unwrap() <= rule.tolerance);
        assert_eq!(
            b.ranked_in_place(&q, &to_bin(2, 0.0), &rule)[0].name,
            "bin2"
        );
        // The same motion to the neighbouring bin: no-go on the place, with its excess.
        let d = b.decide_in_place(&q, &to_bin(2, 0.0), &rule, "bin1", 3);
        assert!(
            matches!(
                d.reason(),
                Some(NoGoReason::GeometryMismatch {
                    feature: GeometryFeature::Place,
                    ..
                })
            ),
            "{d:?}"
        );
        assert!(d.geometry_score.unwrap() > 0.03, "{d:?}");
        // Its reason carries the excess and the tolerance.
        assert_eq!(
            d.reason(),
            Some(&NoGoReason::GeometryMismatch {
                feature: GeometryFeature::Place,
                score: d.geometry_score.unwrap(),
                threshold: rule.tolerance,
            })
        );
        // Not enrolled; enrolled without place signatures: never a go.
        let d = b.decide_in_place(&q, &to_bin(1, 0.0), &rule, "nope", 3);
        assert_eq!(d.reason(), Some(&NoGoReason::UnknownClass));
        let mut b = b;
        b.enroll("unplaced", &[vec![1.0, 0.005]]).unwrap();
        let d = b.decide_in_place(&q, &to_bin(1, 0.0), &rule, "unplaced", 3);
        assert!(
            matches!(d.reason(), Some(NoGoReason::GeometryMismatch { .. })),
            "{d:?}"
        );
    }
}
