//! The one verdict type: what a check decides, with the numbers behind it. The bank returns
//! it, the screen completes it, the wire carries it ([`crate::wire::encode_check`] /
//! [`crate::wire::decode_check`]), and the client, the verdict record, the metrics, the page,
//! the gate and the Python binding re-use it.

use serde::Serialize;

use crate::trajectory::{InvalidKind, InvalidTrajectory};
use crate::workcell::{GeometryFeature, WorkcellKind, WorkcellViolation};

/// Go, or no-go with the reason.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "kebab-case", tag = "decision")]
pub enum Decision {
    /// The trajectory is the task it claims to be.
    Go,
    /// It is not.
    NoGo {
        /// Why.
        reason: NoGoReason,
    },
}

/// Why a check answered no-go.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "kebab-case", tag = "reason")]
#[non_exhaustive]
pub enum NoGoReason {
    /// Another enrolled class is nearer than the claimed one.
    WrongTask {
        /// The nearest class.
        nearest: String,
    },
    /// The claimed class is nearest but farther than its threshold.
    Outlier,
    /// The claimed class is not enrolled.
    UnknownClass,
    /// The trajectory failed validation.
    InvalidTrajectory {
        /// What is wrong.
        kind: InvalidKind,
        /// Waypoint index, or the offending count for count/shape errors.
        index: u32,
    },
    /// The plan breaks a workcell rule (decided before any model runs).
    Workcell {
        /// Which rule.
        kind: WorkcellKind,
        /// The first offending waypoint.
        index: u32,
    },
    /// The embedding fits the claimed class, but where, how large or in which direction
    /// the plan draws (or, in an anchored cell, where it happens) differs from every
    /// enrolled example.
    GeometryMismatch {
        /// The feature farthest from the enrolled examples (relative to its spread).
        feature: GeometryFeature,
        /// The plan's geometry score (for [`GeometryFeature::Place`], metres beyond the
        /// enrolled runs).
        score: f32,
        /// The class's geometry threshold (the place tolerance, m).
        threshold: f32,
    },
}

impl NoGoReason {
    /// The reason's name, kebab-case, as the metrics, the record and `guardianctl` write it.
    pub fn name(&self) -> &'static str {
        match self {
            Self::WrongTask { .. } => "wrong-task",
            Self::Outlier => "outlier",
            Self::UnknownClass => "unknown-class",
            Self::InvalidTrajectory { .. } => "invalid-trajectory",
            Self::Workcell { .. } => "workcell",
            Self::GeometryMismatch { .. } => "geometry-mismatch",
        }
    }
}

impl From<InvalidTrajectory> for NoGoReason {
    fn from(inv: InvalidTrajectory) -> Self {
        Self::InvalidTrajectory {
            kind: inv.kind,
            index: inv.index,
        }
    }
}

impl From<WorkcellViolation> for NoGoReason {
    fn from(v: WorkcellViolation) -> Self {
        Self::Workcell {
            kind: v.kind,
            index: v.index,
        }
    }
}

/// One line, as `guardianctl` and the demo (`examples/demo`) print it: `GO`, or `NO-GO` and the
/// reason.
impl std::fmt::Display for Decision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Go => write!(f, "GO"),
            Self::NoGo { reason } => write!(f, "NO-GO {reason}"),
        }
    }
}

/// The reason with its detail, e.g. `wrong task (nearest character07)`.
impl std::fmt::Display for NoGoReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::WrongTask { nearest } => write!(f, "wrong task (nearest {nearest})"),
            Self::Outlier => write!(f, "outlier"),
            Self::UnknownClass => write!(f, "unknown class"),
            Self::InvalidTrajectory { kind, index } => write!(f, "invalid: {kind:?} at {index}"),
            Self::Workcell { kind, index } => write!(f, "workcell: {kind:?} at waypoint {index}"),
            // The place excess is in metres: said in centimetres. Not a number: the plan's
            // tool changes (grasps, releases) are not those of any enrolled run.
            Self::GeometryMismatch {
                feature: GeometryFeature::Place,
                score,
                ..
            } if !score.is_finite() => write!(
                f,
                "place: its grasps and releases are not those of any enrolled run"
            ),
            Self::GeometryMismatch {
                feature: GeometryFeature::Place,
                score,
                threshold,
            } => write!(
                f,
                "place: {:.1} cm beyond the enrolled runs (tolerance {:.1} cm)",
                score * 100.0,
                threshold * 100.0
            ),
            Self::GeometryMismatch {
                feature,
                score,
                threshold,
            } => write!(
                f,
                "geometry: {} (score {score:.2} > {threshold:.2})",
                feature.name()
            ),
        }
    }
}

/// A class and its distance.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Neighbour {
    /// Class name.
    pub class: String,
    /// Euclidean embedding distance to the class prototype.
    pub distance: f32,
    /// The class's decision threshold.
    pub threshold: f32,
}

/// The answer to a check.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Verdict {
    /// Go or no-go with its reason.
    pub decision: Decision,
    /// The class the trajectory claimed.
    pub claimed_class: String,
    /// Distance to the claimed class prototype (none if unknown class or invalid input).
    pub claimed_distance: Option<f32>,
    /// Threshold used for the claimed class.
    pub threshold: Option<f32>,
    /// `threshold - claimed_distance` (positive = inside the class).
    pub margin: Option<f32>,
    /// Distance to the nearest other class minus `claimed_distance` (positive = the claimed
    /// class is the nearest).
    pub gap: Option<f32>,
    /// The k nearest classes, nearest first.
    pub nearest: Vec<Neighbour>,
    /// Geometry score against the claimed class (none when the check does not apply).
    pub geometry_score: Option<f32>,
    /// The claimed class's geometry threshold (none when the check does not apply).
    pub geometry_threshold: Option<f32>,
    /// The feature behind `geometry_score` (none when the check does not apply).
    pub geometry_feature: Option<GeometryFeature>,
    /// Model version that answered.
    pub model_version: String,
    /// Class bank version that answered.
    pub bank_version: u64,
}

impl Verdict {
    /// `decision` on a check that claimed `claimed_class`, answered by the model and bank
    /// versions given, without numbers or nearest classes (set them with struct update).
    pub fn new(
        decision: Decision,
        claimed_class: &str,
        model_version: &str,
        bank_version: u64,
    ) -> Self {
        Self {
            decision,
            claimed_class: claimed_class.to_owned(),
            claimed_distance: None,
            threshold: None,
            margin: None,
            gap: None,
            nearest: Vec::new(),
            geometry_score: None,
            geometry_threshold: None,
            geometry_feature: None,
            model_version: model_version.to_owned(),
            bank_version,
        }
    }

    /// A no-go decided before any distance was computed (invalid trajectory, workcell).
    pub fn early(
        claimed_class: &str,
        reason: impl Into<NoGoReason>,
        model_version: &str,
        bank_version: u64,
    ) -> Self {
        let reason = reason.into();
        Self::new(
            Decision::NoGo { reason },
            claimed_class,
            model_version,
            bank_version,
        )
    }

    /// Whether the answer is `Go`.
    pub fn is_go(&self) -> bool {
        self.decision == Decision::Go
    }

    /// The no-go reason, if any.
    pub fn reason(&self) -> Option<&NoGoReason> {
        match &self.decision {
            Decision::Go => None,
            Decision::NoGo { reason } => Some(reason),
        }
    }

    /// Why a no-go is one, in one line with its numbers (empty for a go): the rule and
    /// waypoint of a workcell stop, the kind and index of an invalid plan, the feature,
    /// score and threshold of a geometry or place stop, distance and threshold of an
    /// outlier. What the verdict record keeps beside the reason.
    pub fn why(&self) -> String {
        let num = |v: Option<f32>| v.map_or("-".to_owned(), |v| format!("{v:.3}"));
        let Some(reason) = self.reason() else {
            return String::new();
        };
        match reason {
            NoGoReason::WrongTask { .. } => format!(
                "nearer class (entry 0) by {} than the claimed one",
                num(self.gap.map(|g| -g))
            ),
            NoGoReason::Outlier => format!(
                "distance {} > threshold {}",
                num(self.claimed_distance),
                num(self.threshold)
            ),
            NoGoReason::UnknownClass => "class not enrolled".to_owned(),
            NoGoReason::InvalidTrajectory { kind, index } => {
                format!("{kind:?} at waypoint {index}")
            }
            NoGoReason::Workcell { kind, index } => format!("{kind:?} at waypoint {index}"),
            NoGoReason::GeometryMismatch {
                feature: GeometryFeature::Place,
                ..
            } => format!(
                "place: {} m beyond the enrolled runs > tolerance {} m",
                num(self.geometry_score),
                num(self.geometry_threshold)
            ),
            NoGoReason::GeometryMismatch { feature, .. } => format!(
                "{}: score {} > threshold {}",
                feature.name(),
                num(self.geometry_score),
                num(self.geometry_threshold)
            ),
        }
    }
}
