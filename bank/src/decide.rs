//! The decision rule (see the module docs of [`crate::bank`]), written once: nearest-class
//! search, [`is_wrong_task`] and [`is_outlier`], [`ClassBank::decide`] and the geometry step.

use guardian_shared::wire::{CheckAnswer, CheckVerdict, NoGo};
use guardian_shared::workcell::GeometryFeature;

use super::distance::{Distances, distance};
use super::{ClassBank, Neighbour};
use guardian_robot::geometry::{self, PlanGeometry};

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
            return Decision {
                outcome: Outcome::UnknownClass,
                claimed_distance: None,
                threshold: None,
                margin: None,
                gap: None,
                nearest,
                geometry_score: None,
                geometry_threshold: None,
                geometry_feature: None,
            };
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
        Decision {
            outcome,
            claimed_distance: Some(d),
            threshold: Some(threshold),
            margin: Some(threshold - d),
            gap: other.map(|o| o.0 - d),
            nearest,
            geometry_score: None,
            geometry_threshold: None,
            geometry_feature: None,
        }
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
}
