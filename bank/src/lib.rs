//! guardian-bank: the class bank — a prototype per enrolled task class, its decision
//! threshold, nearest-class search, the go/no-go decision rule, and the bank's on-disk format.
//!
//! The daemon serves from it and the lab builds the shipped default bank and evaluates with
//! it, so serving and evaluation share one decision rule ([`ClassBank::decide`]):
//!
//! 1. the claimed class is not enrolled → [`NoGoReason::UnknownClass`](guardian_shared::verdict::NoGoReason::UnknownClass);
//! 2. another class is nearer than the claimed one by more than the bank's wrong-task
//!    tolerance (0 unless calibrated) → [`NoGoReason::WrongTask`](guardian_shared::verdict::NoGoReason::WrongTask);
//! 3. the distance to the claimed prototype exceeds the class threshold → [`NoGoReason::Outlier`](guardian_shared::verdict::NoGoReason::Outlier);
//! 4. the plan's geometry (position, size, strokes, direction; `guardian_robot::geometry`) is
//!    farther from the class's enrolled examples than the calibrated geometry threshold →
//!    [`NoGoReason::GeometryMismatch`](guardian_shared::verdict::NoGoReason::GeometryMismatch) (only [`ClassBank::decide_with_geometry`], only for
//!    classes whose every example has a descriptor, only in a bank with a geometry
//!    calibration);
//! 5. otherwise [`Decision::Go`](guardian_shared::verdict::Decision::Go).
//!
//! An **anchored** deployment (a cell whose tasks are where they happen) decides with
//! [`ClassBank::decide_in_place`]: only classes whose enrolled examples share the plan's
//! place ([`guardian_robot::place`]) compete in step 2; then, before step 3, a plan in
//! another place than its claimed class's examples is a [`NoGoReason::GeometryMismatch`](guardian_shared::verdict::NoGoReason::GeometryMismatch) on
//! the feature `place`, its score the place excess in metres; step 3 uses the class
//! threshold times the rule's `shape` factor; there is no step 4.
//!
//! Distances are Euclidean between embeddings; a prototype is the mean of a class's enrolled
//! embeddings. A class uses its own calibrated threshold when it has one, else the bank's
//! global default ([`DEFAULT_THRESHOLD`] unless the bank says otherwise).
//!
//! Calibration ([`calibrate`], [`ClassBank::apply_calibration`]) picks, from genuine plans of
//! validation classes, the global threshold, the wrong-task tolerance and a scale for
//! per-class thresholds (`scale * class_spread`, for classes with at least
//! [`MIN_CLASS_CALIBRATION`] examples) so that a target share of genuine plans is rejected.
//! The bank keeps the calibration record and applies the scale to classes enrolled later. The margin is
//! `threshold - d_claimed` (positive = inside) and the gap `d_nearest_other - d_claimed`
//! (positive = the claimed class is the nearest).
//!
//! ## File format (version [`FORMAT_VERSION`])
//! Version 5 adds each class's place signatures (`place`, one per enrolled example, kept for
//! classes enrolled by an anchored deployment); a bank in which no class has one is still
//! written as version 4 or older.
//! Version 4 adds each class's enrolled examples (`examples`, one per embedding: the
//! resampled plans in the robot's joints, [`Example`]), so that a daemon started with a new
//! model embeds them again ([`ClassBank::reembedded`]) instead of refusing the bank. A bank
//! in which no class has examples is still written as version 3 (or 2, without a robot).
//! Version 3 adds the bank's `robot` (name, joints, SHA-256 of its URDF): the arm whose plans
//! were enrolled, so a daemon serving another arm refuses the bank. Versions 1 and 2 have no
//! `robot`: they were made with the Panda ([`ClassBank::robot`] says so), and a bank without
//! a robot is still written as version 2.
//! Version 2 adds the per-class plan-geometry descriptors (`geometry`, one per enrolled
//! example) and the bank's `geometry-calibration`; version 1 files still load (their
//! classes have no descriptors, so the geometry check is off for them).
//! One ASCII header line, `guardian-class-bank <version> sha256:<64 hex>\n`, then a UTF-8 JSON
//! body; the checksum is SHA-256 of the body bytes exactly as stored. Saving is atomic: a
//! temporary file in the target directory, `fsync`, `rename`, `fsync` of the directory.
//! Between snapshots, each enroll or forget is appended to the bank's journal
//! (`journal.rs`: one checksummed record per change, replayed at load).

use guardian_robot::kinematics::RobotRecord;

mod calibrate;
mod decide;
mod distance;
mod examples;
mod file;
mod journal;
mod limits;
mod reembed;

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use guardian_robot::geometry::PlanGeometry;
use guardian_robot::place::PlaceSignature;

pub use calibrate::{
    Calibration, GenuineScore, GeometryCalibration, MIN_CLASS_CALIBRATION, calibrate,
    calibrate_geometry, class_spread, threshold_allowing,
};
pub use decide::{is_outlier, is_wrong_task};
pub use distance::distance;
pub use examples::Example;
pub use file::{LoadBankError, SaveBankError, remove_stale_temporaries};
pub use journal::{Replay, journal_path};
pub use limits::BankLimits;
pub use reembed::{ReembedError, Reembedding};

/// Version of the on-disk format written by [`ClassBank::to_bytes`].
pub const FORMAT_VERSION: u32 = 5;
/// The version written for a bank whose classes hold no place signatures (read by builds
/// before version 5).
pub const FORMAT_VERSION_WITHOUT_PLACE: u32 = 4;
/// The version written for a bank whose classes hold no enrolled examples (read by builds
/// before version 4).
pub const FORMAT_VERSION_WITHOUT_EXAMPLES: u32 = 3;
/// The version written for a bank that records no robot and holds no examples (read by
/// builds before version 3).
pub const FORMAT_VERSION_WITHOUT_ROBOT: u32 = 2;
/// Oldest on-disk format [`ClassBank::from_bytes`] still reads.
pub const OLDEST_FORMAT_VERSION: u32 = 1;
/// Global default decision threshold (Euclidean embedding distance) used until per-class
/// thresholds are calibrated. Provisional: a later calibration replaces it per class.
pub const DEFAULT_THRESHOLD: f32 = 0.5;

/// One enrolled class.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Class {
    /// Every enrolled embedding, in enrollment order.
    pub embeddings: Vec<Vec<f32>>,
    /// Mean of `embeddings`.
    pub prototype: Vec<f32>,
    /// Calibrated threshold for this class; `None` uses the bank default.
    pub threshold: Option<f32>,
    /// How `threshold` was calibrated.
    pub calibration: Option<Calibration>,
    /// Plan-geometry descriptor of every enrolled example, in enrollment order (format 2);
    /// empty when any example has none (a format-1 class), which turns the geometry check
    /// off for the class.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub geometry: Vec<PlanGeometry>,
    /// The resampled plan of every enrolled example, in enrollment order (format 4); empty
    /// when any example has none (enrolled by a build before format 4, or embeddings only),
    /// and then the class cannot be embedded again for a new model.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub examples: Vec<Example>,
    /// The place signature of every enrolled example, in enrollment order (format 5); empty
    /// when any example has none (enrolled by a deployment that is not anchored), and then
    /// an anchored deployment cannot tell the class's place: its plans are refused.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub place: Vec<PlaceSignature>,
}

impl Class {
    /// Every enrolled example has a geometry descriptor.
    pub fn has_geometry(&self) -> bool {
        !self.geometry.is_empty() && self.geometry.len() == self.embeddings.len()
    }

    /// Every enrolled example has a place signature.
    pub fn has_place(&self) -> bool {
        !self.place.is_empty() && self.place.len() == self.embeddings.len()
    }

    /// Every enrolled example's plan is kept: the class can be embedded by another model.
    pub fn has_examples(&self) -> bool {
        !self.examples.is_empty() && self.examples.len() == self.embeddings.len()
    }
}

/// A class and its distance to a query.
#[derive(Debug, Clone, PartialEq)]
pub struct Neighbour {
    /// Class name.
    pub name: String,
    /// Euclidean distance from the query to the class prototype.
    pub distance: f32,
}

/// Enrolling into the bank failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum EnrollError {
    /// No embeddings were given.
    #[error("no examples to enroll")]
    NoExamples,
    /// An embedding has the wrong length.
    #[error("embedding {index} has {got} values, the bank expects {expected}")]
    DimensionMismatch {
        /// Which embedding.
        index: usize,
        /// Bank dimension.
        expected: usize,
        /// Its length.
        got: usize,
    },
    /// Geometry descriptors were given, but not one per embedding.
    #[error("{geometry} geometry descriptors for {embeddings} embeddings")]
    GeometryCount {
        /// Embeddings given.
        embeddings: usize,
        /// Descriptors given.
        geometry: usize,
    },
    /// Place signatures were given, but not one per embedding.
    #[error("{place} place signatures for {embeddings} embeddings")]
    PlaceCount {
        /// Embeddings given.
        embeddings: usize,
        /// Signatures given.
        place: usize,
    },
    /// Examples were given, but not one per embedding.
    #[error("{examples} enrolled examples for {embeddings} embeddings")]
    ExampleCount {
        /// Embeddings given.
        embeddings: usize,
        /// Examples given.
        examples: usize,
    },
    /// An example is a plan of another robot than the bank's.
    #[error("example {index} has {got} joints, the bank's robot {expected}")]
    ExampleJoints {
        /// Which example.
        index: usize,
        /// Joints of the bank's robot (the Panda's 7 if it records none).
        expected: usize,
        /// Joints of the example.
        got: usize,
    },
    /// An embedding (or its geometry descriptor or example) holds NaN or infinity.
    #[error("embedding {index} is not finite")]
    NonFinite {
        /// Which embedding.
        index: usize,
    },
}

/// Prototypes, thresholds and enrolled embeddings of every class.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClassBank {
    dim: usize,
    model_version: String,
    generation: u64,
    default_threshold: f32,
    calibration: Option<Calibration>,
    #[serde(default)]
    wrong_task_tolerance: f32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    geometry_calibration: Option<GeometryCalibration>,
    /// The arm whose plans the bank holds; `None` in banks made before version 3 (the Panda).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    robot: Option<RobotRecord>,
    classes: BTreeMap<String, Class>,
}

impl ClassBank {
    /// An empty bank for embeddings of `dim` values from the model `model_version`.
    pub fn new(dim: usize, model_version: impl Into<String>, default_threshold: f32) -> Self {
        Self {
            dim,
            model_version: model_version.into(),
            generation: 0,
            default_threshold,
            calibration: None,
            wrong_task_tolerance: 0.0,
            geometry_calibration: None,
            robot: None,
            classes: BTreeMap::new(),
        }
    }

    /// The robot the bank's classes were enrolled on, if recorded (banks before format 3
    /// record none: they were made with the Panda).
    pub fn robot(&self) -> Option<&RobotRecord> {
        self.robot.as_ref()
    }

    /// Record the robot the bank's classes are enrolled on (not a change of the classes:
    /// the generation stays).
    pub fn set_robot(&mut self, robot: RobotRecord) {
        self.robot = Some(robot);
    }

    /// Embedding length.
    pub fn dim(&self) -> usize {
        self.dim
    }
    /// Version of the model whose embeddings the bank holds.
    pub fn model_version(&self) -> &str {
        &self.model_version
    }
    /// Increments on every change (enroll, forget, threshold).
    pub fn generation(&self) -> u64 {
        self.generation
    }
    /// Threshold for classes without a calibrated one.
    pub fn default_threshold(&self) -> f32 {
        self.default_threshold
    }
    /// Set the global default threshold.
    pub fn set_default_threshold(&mut self, t: f32) {
        self.default_threshold = t;
        self.generation += 1;
    }
    /// Bank-level calibration record.
    pub fn calibration(&self) -> Option<&Calibration> {
        self.calibration.as_ref()
    }
    /// How much nearer (Euclidean) another class must be than the claimed one for a
    /// [`NoGoReason::WrongTask`](guardian_shared::verdict::NoGoReason::WrongTask); 0 = any strictly nearer class.
    pub fn wrong_task_tolerance(&self) -> f32 {
        self.wrong_task_tolerance
    }
    /// The geometry check's calibration, if the bank has one.
    pub fn geometry_calibration(&self) -> Option<&GeometryCalibration> {
        self.geometry_calibration.as_ref()
    }
    /// Set (or remove) the geometry calibration.
    pub fn set_geometry_calibration(&mut self, g: Option<GeometryCalibration>) {
        self.geometry_calibration = g;
        self.generation += 1;
    }
    /// Names of the classes that do not keep their enrolled examples (they cannot be
    /// embedded again for a new model).
    pub fn classes_without_examples(&self) -> Vec<&str> {
        self.classes
            .iter()
            .filter(|(_, c)| !c.has_examples())
            .map(|(n, _)| n.as_str())
            .collect()
    }
    /// Joints of the robot whose plans the bank holds: its record's, else the Panda's.
    pub fn robot_joints(&self) -> usize {
        self.robot
            .as_ref()
            .map_or(guardian_robot::kinematics::PANDA_JOINTS, |r| r.joints)
    }
    /// Names of the classes without geometry descriptors (the geometry check is off for
    /// them), e.g. classes of a format-1 bank.
    pub fn classes_without_geometry(&self) -> Vec<&str> {
        self.classes
            .iter()
            .filter(|(_, c)| !c.has_geometry())
            .map(|(n, _)| n.as_str())
            .collect()
    }
    /// Apply a calibration: its global threshold (if any) as the default, the wrong-task
    /// tolerance and, if the record has a `class_scale`, a threshold for every class with at
    /// least [`MIN_CLASS_CALIBRATION`] examples (also for classes enrolled later).
    pub fn apply_calibration(&mut self, calibration: Calibration) {
        if let Some(g) = calibration.global_threshold.filter(|g| g.is_finite()) {
            self.default_threshold = g;
        }
        self.wrong_task_tolerance = calibration.wrong_task_tolerance.unwrap_or(0.0).max(0.0);
        self.calibration = Some(calibration);
        let names: Vec<String> = self.classes.keys().cloned().collect();
        for n in names {
            self.recalibrate_class(&n);
        }
        self.generation += 1;
    }
    /// The class threshold the bank's calibration gives `name` (`None`: uses the global one).
    fn recalibrate_class(&mut self, name: &str) {
        let Some(scale) = self.calibration.as_ref().and_then(|c| c.class_scale) else {
            return;
        };
        let target_rate = self.calibration.as_ref().and_then(|c| c.target_rate);
        if let Some(c) = self.classes.get_mut(name) {
            match class_spread(&c.embeddings) {
                Some(spread) => {
                    c.threshold = Some(scale * spread);
                    c.calibration = Some(Calibration {
                        method: "class-spread".into(),
                        samples: u32::try_from(c.embeddings.len()).unwrap_or(u32::MAX),
                        target_rate,
                        note: format!("class_scale {scale} x spread {spread}"),
                        global_threshold: None,
                        class_scale: None,
                        wrong_task_tolerance: None,
                        measured_rate: None,
                    });
                }
                None => {
                    c.threshold = None;
                    c.calibration = None;
                }
            }
        }
    }
    /// Set a class's calibrated threshold; `false` if the class is unknown.
    pub fn set_class_threshold(
        &mut self,
        name: &str,
        threshold: Option<f32>,
        calibration: Option<Calibration>,
    ) -> bool {
        match self.classes.get_mut(name) {
            Some(c) => {
                c.threshold = threshold;
                c.calibration = calibration;
                self.generation += 1;
                true
            }
            None => false,
        }
    }
    /// Number of classes.
    pub fn len(&self) -> usize {
        self.classes.len()
    }
    /// No classes enrolled.
    pub fn is_empty(&self) -> bool {
        self.classes.is_empty()
    }
    /// Classes by name (sorted).
    pub fn classes(&self) -> impl Iterator<Item = (&str, &Class)> {
        self.classes.iter().map(|(n, c)| (n.as_str(), c))
    }
    /// One class.
    pub fn class(&self, name: &str) -> Option<&Class> {
        self.classes.get(name)
    }
    /// The threshold the decision uses for `name`.
    pub fn threshold(&self, name: &str) -> Option<f32> {
        self.classes
            .get(name)
            .map(|c| c.threshold.unwrap_or(self.default_threshold))
    }

    /// Add `embeddings` to class `name` (created if new) and recompute its prototype. The
    /// examples have no geometry descriptors, so the class's geometry check turns off; use
    /// [`ClassBank::enroll_with_geometry`] to keep it.
    pub fn enroll(&mut self, name: &str, embeddings: &[Vec<f32>]) -> Result<&Class, EnrollError> {
        self.enroll_with_geometry(name, embeddings, &[])
    }

    /// Add `embeddings` with their plan-geometry descriptors (one per embedding, or none) to
    /// class `name`. The class keeps descriptors only while every example has one. The
    /// examples' plans are not kept ([`ClassBank::enroll_plans`] keeps them).
    pub fn enroll_with_geometry(
        &mut self,
        name: &str,
        embeddings: &[Vec<f32>],
        geometry: &[PlanGeometry],
    ) -> Result<&Class, EnrollError> {
        self.enroll_plans(name, embeddings, geometry, &[])
    }

    /// Add `embeddings` with their plan-geometry descriptors and their resampled plans
    /// (`examples`; each one per embedding, or none) to class `name`. The class keeps
    /// descriptors and plans only while every example has one.
    pub fn enroll_plans(
        &mut self,
        name: &str,
        embeddings: &[Vec<f32>],
        geometry: &[PlanGeometry],
        examples: &[Example],
    ) -> Result<&Class, EnrollError> {
        self.enroll_placed(name, embeddings, geometry, examples, &[])
    }

    /// [`ClassBank::enroll_plans`] with the examples' place signatures (one per embedding,
    /// or none; an anchored deployment's enrollment). The class keeps signatures only while
    /// every example has one.
    pub fn enroll_placed(
        &mut self,
        name: &str,
        embeddings: &[Vec<f32>],
        geometry: &[PlanGeometry],
        examples: &[Example],
        place: &[PlaceSignature],
    ) -> Result<&Class, EnrollError> {
        if !place.is_empty() && place.len() != embeddings.len() {
            return Err(EnrollError::PlaceCount {
                embeddings: embeddings.len(),
                place: place.len(),
            });
        }
        if let Some(index) = place.iter().position(|p| !p.is_valid()) {
            return Err(EnrollError::NonFinite { index });
        }
        if !examples.is_empty() && examples.len() != embeddings.len() {
            return Err(EnrollError::ExampleCount {
                embeddings: embeddings.len(),
                examples: examples.len(),
            });
        }
        self.check_examples(examples)?;
        if !geometry.is_empty() && geometry.len() != embeddings.len() {
            return Err(EnrollError::GeometryCount {
                embeddings: embeddings.len(),
                geometry: geometry.len(),
            });
        }
        if let Some(index) = geometry.iter().position(|g| !g.is_finite()) {
            return Err(EnrollError::NonFinite { index });
        }
        if embeddings.is_empty() {
            return Err(EnrollError::NoExamples);
        }
        self.check_embeddings(embeddings)?;
        let dim = self.dim;
        let class = self
            .classes
            .entry(name.to_owned())
            .or_insert_with(|| Class {
                embeddings: Vec::new(),
                prototype: vec![0.0; dim],
                threshold: None,
                calibration: None,
                geometry: Vec::new(),
                examples: Vec::new(),
                place: Vec::new(),
            });
        let complete = class.place.len() == class.embeddings.len();
        if complete && !place.is_empty() {
            class.place.extend_from_slice(place);
        } else {
            class.place.clear();
        }
        let complete = class.geometry.len() == class.embeddings.len();
        if complete && !geometry.is_empty() {
            class.geometry.extend_from_slice(geometry);
        } else {
            class.geometry.clear();
        }
        let complete = class.examples.len() == class.embeddings.len();
        if complete && !examples.is_empty() {
            class.examples.extend_from_slice(examples);
        } else {
            class.examples.clear();
        }
        class.embeddings.extend(embeddings.iter().cloned());
        class.prototype = mean(&class.embeddings, dim);
        self.recalibrate_class(name);
        self.generation += 1;
        Ok(&self.classes[name])
    }

    /// Every example a plan of the bank's robot and finite (the error names the first that
    /// is not, by its position).
    fn check_examples(&self, examples: &[Example]) -> Result<(), EnrollError> {
        let joints = self.robot_joints();
        for (index, x) in examples.iter().enumerate() {
            if x.joints() != joints {
                return Err(EnrollError::ExampleJoints {
                    index,
                    expected: joints,
                    got: x.joints(),
                });
            }
            if !x.is_finite() {
                return Err(EnrollError::NonFinite { index });
            }
        }
        Ok(())
    }

    /// Every vector of the bank's dimension and finite (the error names the first that is
    /// not, by its position).
    fn check_embeddings<'a>(
        &self,
        embeddings: impl IntoIterator<Item = &'a Vec<f32>>,
    ) -> Result<(), EnrollError> {
        for (index, e) in embeddings.into_iter().enumerate() {
            if e.len() != self.dim {
                return Err(EnrollError::DimensionMismatch {
                    index,
                    expected: self.dim,
                    got: e.len(),
                });
            }
            if e.iter().any(|v| !v.is_finite()) {
                return Err(EnrollError::NonFinite { index });
            }
        }
        Ok(())
    }

    /// Put class `name` in the state `class` as a whole (a class replicated from another
    /// bank of the same model and robot), after the checks an enroll makes: at least one
    /// embedding, each of the bank's dimension and finite, a prototype of that dimension,
    /// examples of the bank's robot. Returns the class it replaced.
    pub fn put_class(&mut self, name: &str, class: Class) -> Result<Option<Class>, EnrollError> {
        if class.embeddings.is_empty() {
            return Err(EnrollError::NoExamples);
        }
        self.check_embeddings(
            class
                .embeddings
                .iter()
                .chain(std::iter::once(&class.prototype)),
        )?;
        if let Some(index) = class.geometry.iter().position(|g| !g.is_finite()) {
            return Err(EnrollError::NonFinite { index });
        }
        if let Some(index) = class.place.iter().position(|p| !p.is_valid()) {
            return Err(EnrollError::NonFinite { index });
        }
        self.check_examples(&class.examples)?;
        if class.threshold.is_some_and(|t| !t.is_finite() || t < 0.0) {
            return Err(EnrollError::NonFinite { index: 0 });
        }
        let previous = self.classes.insert(name.to_owned(), class);
        self.generation += 1;
        Ok(previous)
    }

    /// Remove a class; returns it if it was enrolled.
    pub fn forget(&mut self, name: &str) -> Option<Class> {
        let c = self.classes.remove(name);
        if c.is_some() {
            self.generation += 1;
        }
        c
    }
}

fn mean(rows: &[Vec<f32>], dim: usize) -> Vec<f32> {
    let mut m = vec![0.0f64; dim];
    for r in rows {
        for (a, &v) in m.iter_mut().zip(r) {
            *a += f64::from(v);
        }
    }
    let n = rows.len().max(1) as f64;
    m.into_iter().map(|v| (v / n) as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::file::hex;
    use super::*;
    use guardian_shared::verdict::{Decision, NoGoReason};
    use guardian_shared::workcell::{GEOMETRY_FEATURES, GeometryFeature};
    use sha2::{Digest, Sha256};
    use std::fs;

    /// The calibration's scores and the bank's decision are one rule: for genuine plans of a
    /// calibrated bank, `normalised > 1` exactly when `decide` answers no-go, and the
    /// calibration's wrong-task count is `decide`'s.
    #[test]
    fn calibration_scores_agree_with_decide() {
        use rand::{Rng, SeedableRng, rngs::StdRng};
        let mut rng = StdRng::seed_from_u64(11);
        let dim = 4;
        let mut b = ClassBank::new(dim, "m", 0.5);
        let mut queries = Vec::new();
        for c in 0..6 {
            let centre: Vec<f32> = (0..dim).map(|_| rng.random_range(-1.0..1.0)).collect();
            let jitter = |rng: &mut StdRng| -> Vec<f32> {
                centre
                    .iter()
                    .map(|v| v + rng.random_range(-0.4..0.4))
                    .collect()
            };
            // Classes 0 and 1 have too few examples for their own threshold.
            let n = if c < 2 { 2 } else { 4 };
            let es: Vec<Vec<f32>> = (0..n).map(|_| jitter(&mut rng)).collect();
            b.enroll(&format!("c{c}"), &es).unwrap();
            for _ in 0..40 {
                queries.push((format!("c{c}"), jitter(&mut rng)));
            }
        }
        let score = |b: &ClassBank, name: &str, q: &[f32]| {
            let class = b.class(name).unwrap();
            GenuineScore {
                claimed: distance(q, &class.prototype),
                nearest_other: b
                    .classes()
                    .filter(|(n, _)| *n != name)
                    .map(|(_, c)| distance(q, &c.prototype))
                    .min_by(f32::total_cmp),
                spread: class_spread(&class.embeddings),
            }
        };
        let scores: Vec<GenuineScore> = queries.iter().map(|(n, q)| score(&b, n, q)).collect();
        let cal = calibrate(&scores, 0.2, "test").unwrap();
        assert!(cal.wrong_task_tolerance.unwrap() >= 0.0);
        b.apply_calibration(cal.clone());
        let (mut no_go, mut wrong) = (0, 0);
        for ((name, q), s) in queries.iter().zip(&scores) {
            let d = b.decide(q, name, 3);
            assert_eq!(
                s.normalised(&cal) > 1.0,
                !d.is_go(),
                "{name}: {s:?} -> {:?}",
                d.decision
            );
            no_go += usize::from(!d.is_go());
            wrong += usize::from(matches!(d.reason(), Some(NoGoReason::WrongTask { .. })));
            let tol = b.wrong_task_tolerance();
            assert_eq!(
                s.nearest_other
                    .is_some_and(|o| is_wrong_task(s.claimed, o, tol)),
                matches!(d.reason(), Some(NoGoReason::WrongTask { .. }))
            );
        }
        assert!(
            no_go > 0 && wrong > 0,
            "the rule is exercised: {no_go} {wrong}"
        );
    }

    fn bank() -> ClassBank {
        let mut b = ClassBank::new(2, "test-model", 1.0);
        b.enroll("a", &[vec![0.0, 0.0], vec![0.0, 2.0]]).unwrap();
        b.enroll("b", &[vec![10.0, 0.0]]).unwrap();
        b
    }

    #[test]
    fn distance_matches_a_double_precision_sum() {
        // Lengths around the 16 partial sums: empty, short, exact multiples, remainders.
        for n in [0usize, 1, 5, 16, 17, 31, 128, 131] {
            let a: Vec<f32> = (0..n)
                .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.13)
                .collect();
            let b: Vec<f32> = (0..n).map(|i| ((i * 17 % 7) as f32 - 3.0) * 0.29).collect();
            let exact = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
                .sum::<f64>()
                .sqrt();
            let d = f64::from(distance(&a, &b));
            assert!(
                (d - exact).abs() <= 1e-6 * exact.max(1.0),
                "{n}: {d} vs {exact}"
            );
            assert_eq!(distance(&a, &a), 0.0);
        }
        // Unequal lengths: pairs up to the shorter.
        assert_eq!(distance(&[3.0, 0.0, 9.0], &[0.0, 4.0]), 5.0);
    }

    #[test]
    fn prototypes_are_means_and_enroll_extends() {
        let mut b = bank();
        assert_eq!(b.class("a").unwrap().prototype, vec![0.0, 1.0]);
        assert_eq!(b.generation(), 2);
        b.enroll("a", &[vec![3.0, 1.0]]).unwrap();
        assert_eq!(b.class("a").unwrap().prototype, vec![1.0, 1.0]);
        assert_eq!(b.class("a").unwrap().embeddings.len(), 3);
        assert_eq!(
            b.enroll("a", &[vec![1.0]]),
            Err(EnrollError::DimensionMismatch {
                index: 0,
                expected: 2,
                got: 1
            })
        );
        assert_eq!(
            b.enroll("a", &[vec![1.0, f32::NAN]]),
            Err(EnrollError::NonFinite { index: 0 })
        );
        assert_eq!(b.enroll("a", &[]), Err(EnrollError::NoExamples));
        assert!(b.forget("a").is_some());
        assert!(b.forget("a").is_none());
        assert_eq!(b.len(), 1);
    }

    #[test]
    fn decision_rule_covers_every_outcome() {
        let mut b = bank();
        let d = b.decide(&[0.0, 1.5], "a", 5);
        assert_eq!(d.decision, Decision::Go);
        assert_eq!(d.claimed_distance, Some(0.5));
        assert_eq!(d.margin, Some(0.5));
        assert!((d.gap.unwrap() - (10.0f32.hypot(1.5) - 0.5)).abs() < 1e-5);
        assert_eq!(d.nearest[0].class, "a");
        let d = b.decide(&[0.0, 1.5], "b", 1);
        assert_eq!(
            d.reason(),
            Some(&NoGoReason::WrongTask {
                nearest: "a".into()
            })
        );
        assert_eq!(d.nearest.len(), 1);
        assert!(d.gap.unwrap() < 0.0);
        let d = b.decide(&[0.0, 3.0], "a", 5);
        assert_eq!(d.reason(), Some(&NoGoReason::Outlier));
        assert!(d.margin.unwrap() < 0.0);
        assert!(b.set_class_threshold("a", Some(2.5), None));
        assert!(b.decide(&[0.0, 3.0], "a", 5).is_go());
        let d = b.decide(&[0.0, 3.0], "zzz", 5);
        assert_eq!(d.reason(), Some(&NoGoReason::UnknownClass));
        assert_eq!(d.nearest.len(), 2);
        // A single class: no gap, decided by threshold only.
        b.forget("b");
        assert_eq!(b.decide(&[0.0, 1.0], "a", 5).gap, None);
    }

    #[test]
    fn file_round_trips_and_detects_corruption() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bank.gcb");
        let b = bank();
        b.save(&path).unwrap();
        assert_eq!(ClassBank::load(&path).unwrap(), b);
        // No temporary file is left behind.
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);

        let bytes = fs::read(&path).unwrap();
        let mut flipped = bytes.clone();
        let last = flipped.len() - 2;
        flipped[last] ^= 0x01;
        assert!(matches!(
            ClassBank::from_bytes(&flipped),
            Err(LoadBankError::ChecksumMismatch { .. })
        ));
        let newer = String::from_utf8(bytes.clone()).unwrap().replacen(
            "guardian-class-bank 2 ",
            "guardian-class-bank 6 ",
            1,
        );
        assert!(matches!(
            ClassBank::from_bytes(newer.as_bytes()),
            Err(LoadBankError::UnsupportedFormat {
                found: 6,
                supported: 5
            })
        ));
        assert!(matches!(
            ClassBank::from_bytes(b"hello\n{}"),
            Err(LoadBankError::BadHeader { .. })
        ));
        // Without a robot record the bank is written as format 2 (the Panda's, readable
        // by older builds); with one as format 3, and the record round-trips.
        assert!(bytes.starts_with(b"guardian-class-bank 2 "));
        assert_eq!(b.robot(), None);
        let mut ur = b.clone();
        let ur5e = guardian_robot::kinematics::RobotDescription::named("ur5e")
            .unwrap()
            .robot;
        ur.set_robot(RobotRecord::of(&ur5e));
        assert_eq!(ur.generation(), b.generation());
        let ur_bytes = ur.to_bytes().unwrap();
        assert!(ur_bytes.starts_with(b"guardian-class-bank 3 "));
        let back = ClassBank::from_bytes(&ur_bytes).unwrap();
        assert!(back.robot().is_some_and(
            |r| r.matches(&ur5e) && !r.matches(&guardian_robot::kinematics::Robot::panda())
        ));
        assert!(matches!(
            ClassBank::load(&dir.path().join("missing")),
            Err(LoadBankError::Io { .. })
        ));
    }

    #[test]
    fn calibration_meets_the_target_false_reject_rate() {
        // 1000 genuine plans: claimed distances 0.001..1.0, nearest other always farther
        // except for 30 confusions.
        let scores: Vec<GenuineScore> = (1..=1000)
            .map(|i| GenuineScore {
                claimed: i as f32 / 1000.0,
                nearest_other: Some(if i % 33 == 0 { 0.0 } else { 2.0 }),
                spread: Some(0.5),
            })
            .collect();
        let c = calibrate(&scores, 0.05, "synthetic").unwrap();
        let tol = c.wrong_task_tolerance.unwrap();
        assert!(tol >= 0.0);
        let rate = c.measured_rate.unwrap();
        assert!((0.04..=0.05).contains(&rate), "{c:?}");
        // Rebuild the decision by hand at the chosen numbers.
        let global = c.global_threshold.unwrap();
        let rejected = scores
            .iter()
            .filter(|s| s.nearest_other.unwrap() + tol < s.claimed || s.claimed > global)
            .count();
        assert!(rejected <= 50, "{rejected}");
        // The per-class scale gives the same budget on claimed / spread.
        let scale = c.class_scale.unwrap();
        let rejected = scores
            .iter()
            .filter(|s| s.nearest_other.unwrap() + tol < s.claimed || s.claimed / 0.5 > scale)
            .count();
        assert!((40..=50).contains(&rejected), "{rejected}");
        // A 0 target rejects none of them.
        let c = calibrate(&scores, 0.0, "").unwrap();
        assert_eq!(c.measured_rate, Some(0.0));
        assert!(calibrate(&[], 0.01, "").is_none());
        assert!(calibrate(&scores, 1.5, "").is_none());
        assert_eq!(threshold_allowing(&[3.0, 1.0, 2.0], 1), Some(2.0));
        assert_eq!(threshold_allowing(&[3.0, 1.0, 2.0], 0), Some(3.0));
    }

    #[test]
    fn calibrated_bank_sets_class_thresholds_on_enroll() {
        let mut b = ClassBank::new(2, "m", 1.0);
        b.enroll("a", &[vec![0.0, 0.0], vec![0.0, 2.0]]).unwrap();
        let cal = Calibration {
            method: "genuine-quantile".into(),
            samples: 10,
            target_rate: Some(0.01),
            note: String::new(),
            global_threshold: Some(0.7),
            class_scale: Some(2.0),
            wrong_task_tolerance: Some(0.25),
            measured_rate: None,
        };
        b.apply_calibration(cal);
        assert_eq!(b.threshold("a"), Some(0.7)); // two examples: global threshold
        assert_eq!(b.wrong_task_tolerance(), 0.25);
        b.enroll("a", &[vec![2.0, 0.0]]).unwrap();
        let spread = class_spread(&b.class("a").unwrap().embeddings).unwrap();
        assert!((b.threshold("a").unwrap() - 2.0 * spread).abs() < 1e-6);
        // The tolerance: another class nearer by less than 0.25 is not a wrong task.
        b.enroll("b", &[vec![10.0, 10.0]]).unwrap();
        let pa = b.class("a").unwrap().prototype.clone();
        let q = [pa[0] + 0.1, pa[1]];
        assert!(b.decide(&q, "a", 2).is_go());
        let bytes = b.to_bytes().unwrap();
        assert_eq!(ClassBank::from_bytes(&bytes).unwrap(), b);
        // Leave-one-out spread of three collinear points 0, 1, 2.
        let s = class_spread(&[vec![0.0], vec![1.0], vec![2.0]]).unwrap();
        assert!((s - (4.5f32 / 3.0).sqrt()).abs() < 1e-6, "{s}");
        assert_eq!(class_spread(&[vec![0.0], vec![1.0]]), None);
    }

    /// A format-1 file exactly as the format-1 code wrote it (header + JSON body).
    fn v1_file() -> Vec<u8> {
        let body = r#"{"dim":2,"model_version":"m","generation":3,"default_threshold":0.5,"calibration":null,"wrong_task_tolerance":0.25,"classes":{"a":{"embeddings":[[0.0,0.0],[0.0,2.0],[2.0,0.0]],"prototype":[0.6666667,0.6666667],"threshold":null,"calibration":null}}}"#;
        let sum = hex(&Sha256::digest(body.as_bytes()));
        format!("guardian-class-bank 1 sha256:{sum}\n{body}").into_bytes()
    }

    fn geo(x: f32) -> PlanGeometry {
        let mut g = [0.0f32; GEOMETRY_FEATURES];
        g[0] = x;
        g[5] = 1.0;
        PlanGeometry(g)
    }

    fn geo_cal(threshold: f32) -> GeometryCalibration {
        GeometryCalibration {
            scales: [0.01; GEOMETRY_FEATURES],
            threshold,
            target_rate: 0.01,
            samples: 10,
            measured_rate: 0.01,
            note: "test".into(),
        }
    }

    #[test]
    fn format_1_banks_load_without_geometry() {
        let mut b = ClassBank::from_bytes(&v1_file()).unwrap();
        assert_eq!(b.len(), 1);
        assert_eq!(b.wrong_task_tolerance(), 0.25);
        assert_eq!(b.classes_without_geometry(), vec!["a"]);
        assert!(b.geometry_calibration().is_none());
        // Even with a geometry calibration, a class without descriptors is not checked.
        b.set_geometry_calibration(Some(geo_cal(1.0)));
        let d = b.decide_with_geometry(&[0.6, 0.6], Some(&geo(5.0)), "a", 1);
        assert_eq!(d.decision, Decision::Go);
        assert_eq!(d.geometry_score, None);
        // Saved again, it is a format-2 file.
        let bytes = b.to_bytes().unwrap();
        assert!(bytes.starts_with(b"guardian-class-bank 2 "));
        assert_eq!(ClassBank::from_bytes(&bytes).unwrap(), b);
    }

    #[test]
    fn geometry_round_trips_and_decides() {
        let mut b = ClassBank::new(2, "m", 1.0);
        b.enroll_with_geometry(
            "a",
            &[vec![0.0, 0.0], vec![0.0, 0.2]],
            &[geo(0.0), geo(0.01)],
        )
        .unwrap();
        b.enroll("b", &[vec![5.0, 5.0]]).unwrap();
        assert_eq!(b.classes_without_geometry(), vec!["b"]);
        b.set_geometry_calibration(Some(geo_cal(2.0)));
        // 0.03 from the nearest example = 2 spreads: inside; 0.05 = 4 spreads: mismatch.
        let d = b.decide_with_geometry(&[0.0, 0.1], Some(&geo(0.025)), "a", 2);
        assert_eq!(d.decision, Decision::Go);
        assert!((d.geometry_score.unwrap() - 1.5).abs() < 1e-4);
        let d = b.decide_with_geometry(&[0.0, 0.1], Some(&geo(0.05)), "a", 2);
        assert!(
            matches!(
                d.reason(),
                Some(NoGoReason::GeometryMismatch {
                    feature: GeometryFeature::CentreX,
                    ..
                })
            ),
            "{d:?}"
        );
        assert_eq!(d.geometry_threshold, Some(2.0));
        // The embedding decision comes first.
        let d = b.decide_with_geometry(&[5.0, 5.0], Some(&geo(0.05)), "a", 2);
        assert!(matches!(d.reason(), Some(NoGoReason::WrongTask { .. })));
        // Round trip through the file format, atomically saved.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bank.gcb");
        b.save(&path).unwrap();
        let back = ClassBank::load(&path).unwrap();
        assert_eq!(back, b);
        assert_eq!(back.class("a").unwrap().geometry.len(), 2);
        // Enrolling without descriptors turns the class's check off.
        b.enroll("a", &[vec![0.1, 0.1]]).unwrap();
        assert!(!b.class("a").unwrap().has_geometry());
        assert_eq!(
            b.enroll_with_geometry("c", &[vec![0.0, 0.0]], &[geo(0.0), geo(1.0)])
                .unwrap_err(),
            EnrollError::GeometryCount {
                embeddings: 1,
                geometry: 2
            }
        );
    }

    #[test]
    fn geometry_calibration_spends_what_the_embedding_left() {
        let cal = calibrate(
            &(1..=1000)
                .map(|i| GenuineScore {
                    claimed: i as f32 / 1000.0,
                    nearest_other: None,
                    spread: None,
                })
                .collect::<Vec<_>>(),
            0.005,
            "",
        )
        .unwrap();
        let scores: Vec<GenuineScore> = (1..=1000)
            .map(|i| GenuineScore {
                claimed: i as f32 / 1000.0,
                nearest_other: None,
                spread: None,
            })
            .collect();
        // Geometry scores independent of the embedding: 0.001 .. 1.0 in another order.
        let geo: Vec<Option<f32>> = (1..=1000)
            .map(|i| Some(((i * 7919) % 1000) as f32 / 1000.0))
            .collect();
        let g =
            calibrate_geometry(&scores, &geo, &cal, 0.01, [0.01; GEOMETRY_FEATURES], "").unwrap();
        assert!(g.measured_rate <= 0.01 && g.measured_rate >= 0.009, "{g:?}");
        assert!(calibrate_geometry(&scores, &geo[1..], &cal, 0.01, g.scales, "").is_none());
    }
}
