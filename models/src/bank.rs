//! The class bank: a prototype per enrolled task class, its decision threshold, nearest-class
//! search, the go/no-go decision rule, and the bank's on-disk format.
//!
//! The daemon serves from it and the lab builds the shipped default bank and evaluates with
//! it, so serving and evaluation share one decision rule ([`ClassBank::decide`]):
//!
//! 1. the claimed class is not enrolled → [`Outcome::UnknownClass`];
//! 2. another class is nearer than the claimed one by more than the bank's wrong-task
//!    tolerance (0 unless calibrated) → [`Outcome::WrongTask`];
//! 3. the distance to the claimed prototype exceeds the class threshold → [`Outcome::Outlier`];
//! 4. the plan's geometry (position, size, strokes, direction; [`crate::geometry`]) is
//!    farther from the class's enrolled examples than the calibrated geometry threshold →
//!    [`Outcome::GeometryMismatch`] (only [`ClassBank::decide_with_geometry`], only for
//!    classes whose every example has a descriptor, only in a bank with a geometry
//!    calibration);
//! 5. otherwise [`Outcome::Go`].
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
//! Version 2 adds the per-class plan-geometry descriptors (`geometry`, one per enrolled
//! example) and the bank's `geometry-calibration`; version 1 files still load (their
//! classes have no descriptors, so the geometry check is off for them).
//! One ASCII header line, `guardian-class-bank <version> sha256:<64 hex>\n`, then a UTF-8 JSON
//! body; the checksum is SHA-256 of the body bytes exactly as stored. Saving is atomic: a
//! temporary file in the target directory, `fsync`, `rename`, `fsync` of the directory.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use guardian_shared::workcell::{GEOMETRY_FEATURES, GeometryFeature};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::geometry::{self, PlanGeometry};

/// Version of the on-disk format written by [`ClassBank::to_bytes`].
pub const FORMAT_VERSION: u32 = 2;
/// Oldest on-disk format [`ClassBank::from_bytes`] still reads.
pub const OLDEST_FORMAT_VERSION: u32 = 1;
/// Global default decision threshold (Euclidean embedding distance) used until per-class
/// thresholds are calibrated. Provisional: a later calibration replaces it per class.
pub const DEFAULT_THRESHOLD: f32 = 0.5;
const MAGIC: &str = "guardian-class-bank";

/// Accumulators of [`distance`]: independent partial sums, so the sum vectorises.
const DISTANCE_LANES: usize = 16;

/// Euclidean distance between two embeddings of equal length (pairs up to the shorter).
/// Squares are summed in [`DISTANCE_LANES`] interleaved partial sums (element `i` into sum
/// `i % 16`), combined in a fixed order: deterministic, and vectorised by the compiler
/// (one running sum would be a chain of 128 dependent additions).
#[inline(always)]
pub fn distance(a: &[f32], b: &[f32]) -> f32 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f32; DISTANCE_LANES];
    let (ac, bc) = (
        a.chunks_exact(DISTANCE_LANES),
        b.chunks_exact(DISTANCE_LANES),
    );
    let (ar, br) = (ac.remainder(), bc.remainder());
    for (x, y) in ac.zip(bc) {
        for l in 0..DISTANCE_LANES {
            let d = x[l] - y[l];
            acc[l] += d * d;
        }
    }
    for (l, (x, y)) in ar.iter().zip(br).enumerate() {
        let d = x - y;
        acc[l] += d * d;
    }
    // Pairwise combination: 16 -> 8 -> 4 -> 2 -> 1.
    let mut width = DISTANCE_LANES;
    while width > 1 {
        width /= 2;
        for l in 0..width {
            acc[l] += acc[l + width];
        }
    }
    acc[0].sqrt()
}

/// The distance of `query` to every class prototype, in name order, compiled for the widest
/// SIMD instruction set this CPU has (runtime dispatch; the sums are the same on every
/// instruction set, see [`distance`]).
struct Distances<'a, 'b> {
    bank: &'a ClassBank,
    query: &'b [f32],
    out: &'b mut Vec<(f32, &'a str)>,
}

impl pulp::WithSimd for Distances<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        for (n, c) in &self.bank.classes {
            self.out
                .push((distance(self.query, &c.prototype), n.as_str()));
        }
    }
}

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
    /// wrong-task tolerance; `> 1` exactly when [`ClassBank::decide`] answers no-go.
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
    /// A plan whose geometry score exceeds this is a [`Outcome::GeometryMismatch`].
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
        .collect();
    let threshold = threshold_allowing(&kept, budget.saturating_sub(used))
        .unwrap_or(f32::MAX)
        .max(f32::MIN_POSITIVE);
    let rejected = geometry
        .iter()
        .zip(&emb_rejected)
        .filter(|(g, r)| **r || g.is_some_and(|g| g > threshold))
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
/// most `target_rate` of the genuine plans are rejected by [`ClassBank::decide`].
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
    let wrong = |s: &GenuineScore| s.nearest_other.is_some_and(|o| o + tol < s.claimed);
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
}

impl Class {
    /// Every enrolled example has a geometry descriptor.
    pub fn has_geometry(&self) -> bool {
        !self.geometry.is_empty() && self.geometry.len() == self.embeddings.len()
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
    /// An embedding (or its geometry descriptor) holds NaN or infinity.
    #[error("embedding {index} is not finite")]
    NonFinite {
        /// Which embedding.
        index: usize,
    },
}

/// Loading a bank failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadBankError {
    /// The file could not be read.
    #[error("cannot read class bank {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The header line is missing or malformed.
    #[error("not a guardian class bank (bad header line): {detail}")]
    BadHeader {
        /// What was wrong.
        detail: String,
    },
    /// The format version is not supported.
    #[error("class bank format {found} is not supported (this build reads {supported})")]
    UnsupportedFormat {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The body does not match its checksum.
    #[error("class bank checksum mismatch: header says {expected}, body hashes to {found}")]
    ChecksumMismatch {
        /// Checksum from the header.
        expected: String,
        /// Checksum of the body.
        found: String,
    },
    /// The body is not a valid bank document.
    #[error("class bank body does not parse: {0}")]
    Parse(#[from] serde_json::Error),
    /// The document parses but is inconsistent.
    #[error("class bank is inconsistent: {detail}")]
    Inconsistent {
        /// What is wrong.
        detail: String,
    },
}

/// Saving a bank failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SaveBankError {
    /// Writing, syncing or renaming failed.
    #[error("cannot save class bank to {path}: {source}")]
    Io {
        /// The file being written.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Serialisation failed.
    #[error("cannot serialise class bank: {0}")]
    Serialize(#[from] serde_json::Error),
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
            classes: BTreeMap::new(),
        }
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
    /// [`Outcome::WrongTask`]; 0 = any strictly nearer class.
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
    /// class `name`. The class keeps descriptors only while every example has one.
    pub fn enroll_with_geometry(
        &mut self,
        name: &str,
        embeddings: &[Vec<f32>],
        geometry: &[PlanGeometry],
    ) -> Result<&Class, EnrollError> {
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
        for (index, e) in embeddings.iter().enumerate() {
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
            });
        let complete = class.geometry.len() == class.embeddings.len();
        if complete && !geometry.is_empty() {
            class.geometry.extend_from_slice(geometry);
        } else {
            class.geometry.clear();
        }
        class.embeddings.extend(embeddings.iter().cloned());
        class.prototype = mean(&class.embeddings, dim);
        self.recalibrate_class(name);
        self.generation += 1;
        Ok(&self.classes[name])
    }

    /// Remove a class; returns it if it was enrolled.
    pub fn forget(&mut self, name: &str) -> Option<Class> {
        let c = self.classes.remove(name);
        if c.is_some() {
            self.generation += 1;
        }
        c
    }

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
            Some(&(od, name)) if od + self.wrong_task_tolerance < d => Outcome::WrongTask {
                nearest: name.to_owned(),
            },
            _ if d.is_nan() || d > threshold => Outcome::Outlier,
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
            if d.outcome == Outcome::Go && (s > t || s.is_nan()) {
                d.outcome = Outcome::GeometryMismatch { feature: f };
            }
        }
        d
    }

    /// Serialise to the on-disk format (header line + JSON body).
    pub fn to_bytes(&self) -> Result<Vec<u8>, serde_json::Error> {
        let body = serde_json::to_vec(self)?;
        let sum = hex(&Sha256::digest(&body));
        let mut out = format!("{MAGIC} {FORMAT_VERSION} sha256:{sum}\n").into_bytes();
        out.extend_from_slice(&body);
        Ok(out)
    }

    /// Parse the on-disk format, verifying version and checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, LoadBankError> {
        let nl = bytes
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| bad("no header line"))?;
        let header = std::str::from_utf8(&bytes[..nl]).map_err(|_| bad("header is not UTF-8"))?;
        let body = &bytes[nl + 1..];
        let mut parts = header.split(' ');
        if parts.next() != Some(MAGIC) {
            return Err(bad("missing magic"));
        }
        let found: u32 = parts
            .next()
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| bad("missing format version"))?;
        if !(OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&found) {
            return Err(LoadBankError::UnsupportedFormat {
                found,
                supported: FORMAT_VERSION,
            });
        }
        let expected = parts
            .next()
            .and_then(|v| v.strip_prefix("sha256:"))
            .ok_or_else(|| bad("missing checksum"))?
            .to_owned();
        let found_sum = hex(&Sha256::digest(body));
        if found_sum != expected {
            return Err(LoadBankError::ChecksumMismatch {
                expected,
                found: found_sum,
            });
        }
        let bank: ClassBank = serde_json::from_slice(body)?;
        bank.check()?;
        Ok(bank)
    }

    fn check(&self) -> Result<(), LoadBankError> {
        let inconsistent = |detail: String| Err(LoadBankError::Inconsistent { detail });
        if !self.default_threshold.is_finite() {
            return inconsistent("default threshold is not finite".into());
        }
        if !(self.wrong_task_tolerance.is_finite() && self.wrong_task_tolerance >= 0.0) {
            return inconsistent("wrong-task tolerance is not finite and >= 0".into());
        }
        if let Some(g) = &self.geometry_calibration
            && (g.threshold.is_nan() || g.scales.iter().any(|s| !(s.is_finite() && *s > 0.0)))
        {
            return inconsistent("geometry calibration: threshold NaN or scale not > 0".into());
        }
        for (name, c) in &self.classes {
            if c.prototype.len() != self.dim {
                return inconsistent(format!("class {name:?}: prototype length"));
            }
            if c.embeddings.is_empty() {
                return inconsistent(format!("class {name:?}: no embeddings"));
            }
            if c.embeddings.iter().any(|e| e.len() != self.dim) {
                return inconsistent(format!("class {name:?}: embedding length"));
            }
            if c.threshold.is_some_and(|t| !t.is_finite()) {
                return inconsistent(format!("class {name:?}: threshold is not finite"));
            }
            if !c.geometry.is_empty() && c.geometry.len() != c.embeddings.len() {
                return inconsistent(format!("class {name:?}: geometry descriptor count"));
            }
            if c.geometry.iter().any(|g| !g.is_finite()) {
                return inconsistent(format!("class {name:?}: geometry is not finite"));
            }
        }
        Ok(())
    }

    /// Read and verify a bank file.
    pub fn load(path: &Path) -> Result<Self, LoadBankError> {
        let bytes = fs::read(path).map_err(|source| LoadBankError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }

    /// Save atomically: write a temporary file in the same directory, fsync it, rename it
    /// over `path`, fsync the directory. A crash leaves either the old or the new file.
    pub fn save(&self, path: &Path) -> Result<(), SaveBankError> {
        let bytes = self.to_bytes()?;
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
            _ => PathBuf::from("."),
        };
        let file_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "bank".into());
        let tmp = dir.join(format!(
            "{}{}",
            temporary_prefix(&file_name),
            std::process::id()
        ));
        let io = |p: &Path| {
            let p = p.to_owned();
            move |source| SaveBankError::Io { path: p, source }
        };
        let result = (|| {
            let mut f = fs::File::create(&tmp).map_err(io(&tmp))?;
            f.write_all(&bytes).map_err(io(&tmp))?;
            f.sync_all().map_err(io(&tmp))?;
            drop(f);
            fs::rename(&tmp, path).map_err(io(path))?;
            fs::File::open(&dir)
                .and_then(|d| d.sync_all())
                .map_err(io(&dir))?;
            Ok(())
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result
    }
}

/// Name prefix of the temporary files [`ClassBank::save`] writes next to `file_name`.
fn temporary_prefix(file_name: &str) -> String {
    format!(".{file_name}.tmp.")
}

/// Remove temporary files that a [`ClassBank::save`] of `path` killed mid-write left behind
/// (a crash never damages `path` itself, but each crashed writer leaves its temporary).
/// Call it only while no other process saves to `path`. Returns the names removed.
pub fn remove_stale_temporaries(path: &Path) -> std::io::Result<Vec<String>> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let Some(file_name) = path.file_name() else {
        return Ok(Vec::new());
    };
    let prefix = temporary_prefix(&file_name.to_string_lossy());
    let mut removed = Vec::new();
    let entries = match fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(removed),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with(&prefix) && entry.file_type()?.is_file() {
            fs::remove_file(entry.path())?;
            removed.push(name);
        }
    }
    Ok(removed)
}

fn bad(detail: &str) -> LoadBankError {
    LoadBankError::BadHeader {
        detail: detail.to_owned(),
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

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert_eq!(d.outcome, Outcome::Go);
        assert_eq!(d.claimed_distance, Some(0.5));
        assert_eq!(d.margin, Some(0.5));
        assert!((d.gap.unwrap() - (10.0f32.hypot(1.5) - 0.5)).abs() < 1e-5);
        assert_eq!(d.nearest[0].name, "a");
        let d = b.decide(&[0.0, 1.5], "b", 1);
        assert_eq!(
            d.outcome,
            Outcome::WrongTask {
                nearest: "a".into()
            }
        );
        assert_eq!(d.nearest.len(), 1);
        assert!(d.gap.unwrap() < 0.0);
        let d = b.decide(&[0.0, 3.0], "a", 5);
        assert_eq!(d.outcome, Outcome::Outlier);
        assert!(d.margin.unwrap() < 0.0);
        assert!(b.set_class_threshold("a", Some(2.5), None));
        assert_eq!(b.decide(&[0.0, 3.0], "a", 5).outcome, Outcome::Go);
        let d = b.decide(&[0.0, 3.0], "zzz", 5);
        assert_eq!(d.outcome, Outcome::UnknownClass);
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
            "guardian-class-bank 3 ",
            1,
        );
        assert!(matches!(
            ClassBank::from_bytes(newer.as_bytes()),
            Err(LoadBankError::UnsupportedFormat {
                found: 3,
                supported: 2
            })
        ));
        assert!(matches!(
            ClassBank::from_bytes(b"hello\n{}"),
            Err(LoadBankError::BadHeader { .. })
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
        assert_eq!(b.decide(&q, "a", 2).outcome, Outcome::Go);
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
        assert_eq!(d.outcome, Outcome::Go);
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
        assert_eq!(d.outcome, Outcome::Go);
        assert!((d.geometry_score.unwrap() - 1.5).abs() < 1e-4);
        let d = b.decide_with_geometry(&[0.0, 0.1], Some(&geo(0.05)), "a", 2);
        assert_eq!(
            d.outcome,
            Outcome::GeometryMismatch {
                feature: GeometryFeature::CentreX
            }
        );
        assert_eq!(d.geometry_threshold, Some(2.0));
        // The embedding decision comes first.
        let d = b.decide_with_geometry(&[5.0, 5.0], Some(&geo(0.05)), "a", 2);
        assert!(matches!(d.outcome, Outcome::WrongTask { .. }));
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
