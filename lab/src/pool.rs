//! The unlabelled drawing pool (`../shared/omniglot/unlabelled/drawings.jsonl`, its README):
//! reading it, converting it through the dataset's robot pipeline, finding and leaving out
//! the copies of labelled drawings (a fold's test and validation alphabets), and the two ways
//! training learns from it — pseudo-labels (clusters of the pool under a given embedder) and
//! self-supervision (every drawing a class of its own, seen in two augmented views).
//!
//! The pool file is a [`Dataset`] with one alphabet `unlabelled` and one class
//! `unlabelled/pool` (every label 0, so the dataset invariants hold), the drawing's 0-based
//! line in `drawings.jsonl` as its drawer id, and a `pool` metadata entry ([`PoolInfo`]):
//! which alphabets' copies were left out, how many per alphabet, at which tolerance.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use guardian_models::embedder::{Embedder, Embedding};
use guardian_shared::trajectory::Resampled;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::dataset::{self, ConvertError, Dataset, convert_strokes};
use crate::path::{Geometry, PathSolver, SolvePathError};
use crate::strokes::{self, Point, Stroke};

/// Where the unlabelled drawings are, relative to the repository root.
pub const DEFAULT_UNLABELLED: &str = "../shared/omniglot/unlabelled/drawings.jsonl";

/// Alphabet name of pool drawings in a pool file.
pub const POOL_ALPHABET: &str = "unlabelled";

/// Points per stroke of a [`Shape`].
pub const SHAPE_POINTS: usize = 16;

/// When a pool drawing is a copy of its nearest labelled drawing (distances:
/// [`Shape::distance`], drawings scaled to a longest side of 1): nearer than `tolerance`,
/// or nearer than `loose_tolerance` and at most `ratio` times the distance of the second
/// nearest labelled drawing (a copy is much nearer to its original than to the other drawers'
/// drawings of its character; a look-alike from another alphabet is about as near to several).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct CopyRule {
    /// A copy at any ratio below this distance.
    pub tolerance: f32,
    /// Largest distance of a copy.
    pub loose_tolerance: f32,
    /// Largest nearest / second-nearest distance ratio between the two tolerances.
    pub ratio: f32,
}

/// Chosen on the shared data (all six labelled alphabets against the pool, 2026-12-02;
/// `guardian-lab pool` prints the distribution as `distance-by-ratio`): 94% of the 3,375
/// pool drawings nearer than 0.02 to a labelled drawing are at most half as near to the
/// second nearest; between 0.02 and 0.05 the ~300 drawings with a ratio <= 0.5 stand apart
/// from ~1,200 look-alikes with ratios of 0.5-1, and the distance alone shows no empty gap.
/// Result: 3,673 removed, 3,308 of the 3,660 labelled drawings with exactly one copy, 258
/// with none found.
impl Default for CopyRule {
    fn default() -> Self {
        Self {
            tolerance: 0.02,
            loose_tolerance: 0.05,
            ratio: 0.5,
        }
    }
}

impl CopyRule {
    /// Is a drawing at `nearest` from its nearest labelled drawing and `second` from the
    /// second nearest a copy?
    pub fn is_copy(&self, nearest: f32, second: f32) -> bool {
        nearest <= self.tolerance
            || (nearest <= self.loose_tolerance && nearest <= self.ratio * second)
    }
}

/// Candidates of the copy search: the point distance ([`Shape::point_distance`]) within
/// which a labelled drawing is a candidate (copies are seen up to ~0.12).
pub const PREFILTER_DISTANCE: f32 = 0.25;

/// Candidates of the copy search refined by [`Shape::distance`], nearest first.
pub const PREFILTER_CANDIDATES: usize = 8;

/// One unlabelled drawing.
#[derive(Debug, Clone, PartialEq)]
pub struct PoolDrawing {
    /// The `id` field (e.g. `train/17`; no label).
    pub id: String,
    /// Strokes in drawing order; `t` is the point's running number in the drawing (the file
    /// has no time column, and nothing downstream reads `t`).
    pub strokes: Vec<Stroke>,
}

/// Reading the pool failed; every variant names the file (and line).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReadPoolError {
    /// The file could not be read.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A line is not `{"id": ..., "strokes": [[[x, y], ...], ...]}`.
    #[error("{}:{line}: {source}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The JSON error.
        source: serde_json::Error,
    },
    /// A coordinate is not finite.
    #[error("{}:{line}: non-finite coordinate", path.display())]
    NonFinite {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
    },
    /// A drawing without any point.
    #[error("{}:{line}: empty drawing (no points)", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Line {
    id: String,
    strokes: Vec<Vec<[f64; 2]>>,
}

/// Parse the text of `drawings.jsonl` (`path` only names errors). Blank lines are skipped but
/// counted, so drawing `i` of the result is not always line `i + 1`; empty strokes are
/// dropped.
pub fn parse_pool(text: &str, path: &Path) -> Result<Vec<PoolDrawing>, ReadPoolError> {
    let lines: Vec<(usize, &str)> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .collect();
    lines
        .par_iter()
        .map(|&(i, l)| {
            let line = i + 1;
            let raw: Line = serde_json::from_str(l).map_err(|source| ReadPoolError::Json {
                path: path.to_path_buf(),
                line,
                source,
            })?;
            let mut t = 0.0;
            let mut out: Vec<Stroke> = Vec::with_capacity(raw.strokes.len());
            for s in raw.strokes.iter().filter(|s| !s.is_empty()) {
                let mut stroke = Vec::with_capacity(s.len());
                for &[x, y] in s {
                    if !x.is_finite() || !y.is_finite() {
                        return Err(ReadPoolError::NonFinite {
                            path: path.to_path_buf(),
                            line,
                        });
                    }
                    stroke.push(Point { x, y, t });
                    t += 1.0;
                }
                out.push(stroke);
            }
            if out.is_empty() {
                return Err(ReadPoolError::Empty {
                    path: path.to_path_buf(),
                    line,
                });
            }
            Ok(PoolDrawing {
                id: raw.id,
                strokes: out,
            })
        })
        .collect()
}

/// Read `drawings.jsonl`.
pub fn read_pool(path: &Path) -> Result<Vec<PoolDrawing>, ReadPoolError> {
    let text = std::fs::read_to_string(path).map_err(|source| ReadPoolError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_pool(&text, path)
}

/// Figures of a pool conversion.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ConvertReport {
    /// Drawings given.
    pub drawings: usize,
    /// Converted.
    pub converted: usize,
    /// IK failures.
    pub ik_failures: usize,
    /// Other failures (the dense path failed the shared validation, e.g. too many points).
    pub other_failures: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// Convert every drawing through the dataset pipeline ([`convert_strokes`], rayon), in order.
pub fn convert_pool(
    drawings: &[&[Stroke]],
    geometry: &Geometry,
) -> Result<(Vec<Result<Resampled, ConvertError>>, ConvertReport), SolvePathError> {
    let t0 = Instant::now();
    let solver = PathSolver::new(geometry)?;
    let out: Vec<Result<Resampled, ConvertError>> = drawings
        .par_iter()
        .map(|s| convert_strokes(&solver, s).map(|c| c.sample))
        .collect();
    let mut report = ConvertReport {
        drawings: drawings.len(),
        ..Default::default()
    };
    for r in &out {
        match r {
            Ok(_) => report.converted += 1,
            Err(ConvertError::Ik(_)) => report.ik_failures += 1,
            Err(_) => report.other_failures += 1,
        }
    }
    report.seconds = t0.elapsed().as_secs_f64();
    Ok((out, report))
}

/// A drawing's shape with position and size removed: the bounding box of all points centred
/// at the origin, its longest side scaled to 1, every stroke (in order) resampled to
/// [`SHAPE_POINTS`] points uniform in arc length. One-point strokes are left out when the
/// drawing has longer ones (the stroke-3 conversion upstream lost them: a labelled drawing
/// with a dot matches its pool copy without it). Two drawings compare only with the same
/// number of strokes.
#[derive(Debug, Clone, PartialEq)]
pub struct Shape {
    /// `strokes * SHAPE_POINTS` points.
    points: Vec<[f32; 2]>,
}

impl Shape {
    /// The shape of `strokes` (at least one point; `None` otherwise).
    pub fn new(strokes: &[Stroke]) -> Option<Self> {
        let long: Vec<Stroke> = strokes.iter().filter(|s| s.len() >= 2).cloned().collect();
        let strokes = if long.is_empty() { strokes } else { &long[..] };
        let all = || strokes.iter().flatten();
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for p in all() {
            x0 = x0.min(p.x);
            x1 = x1.max(p.x);
            y0 = y0.min(p.y);
            y1 = y1.max(p.y);
        }
        if x0 > x1 {
            return None;
        }
        let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        let side = (x1 - x0).max(y1 - y0);
        let scale = if side > 0.0 { 1.0 / side } else { 1.0 };
        let mut points = Vec::with_capacity(strokes.len() * SHAPE_POINTS);
        for s in strokes.iter().filter(|s| !s.is_empty()) {
            let pts: Vec<[f64; 2]> = s
                .iter()
                .map(|p| [(p.x - cx) * scale, (p.y - cy) * scale])
                .collect();
            resample(&pts, &mut points);
        }
        Some(Self { points })
    }

    /// Number of strokes.
    pub fn strokes(&self) -> usize {
        self.points.len() / SHAPE_POINTS
    }

    /// RMS distance between corresponding points (same arc-length fraction of the same
    /// stroke); `None` for different stroke counts. Cheap, but sensitive to where along a
    /// stroke the points fall: the prefilter of [`Shape::distance`].
    pub fn point_distance(&self, other: &Self) -> Option<f32> {
        (self.points.len() == other.points.len()).then(|| self.sq_within(other, f32::MAX).sqrt())
    }

    /// The copy distance: symmetric RMS distance of every point of one drawing to the same
    /// stroke of the other as a polyline (so a stroke simplified or re-sampled elsewhere
    /// along its length still matches its original); `None` for different stroke counts.
    pub fn distance(&self, other: &Self) -> Option<f32> {
        if self.points.len() != other.points.len() {
            return None;
        }
        let mut sum = 0.0f32;
        for (a, b) in self
            .points
            .chunks(SHAPE_POINTS)
            .zip(other.points.chunks(SHAPE_POINTS))
        {
            for (x, y) in [(a, b), (b, a)] {
                for p in x {
                    sum += to_polyline_sq(p, y);
                }
            }
        }
        Some((sum / (2 * self.points.len()).max(1) as f32).sqrt())
    }

    /// Mean squared point distance, or something above `bound` as soon as the partial sum
    /// shows it exceeds `bound` (same stroke count assumed).
    fn sq_within(&self, other: &Self, bound: f32) -> f32 {
        let n = self.points.len().max(1) as f32;
        let limit = bound * n;
        let mut sum = 0.0f32;
        for (a, b) in self
            .points
            .chunks(SHAPE_POINTS)
            .zip(other.points.chunks(SHAPE_POINTS))
        {
            for (p, q) in a.iter().zip(b) {
                sum += (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2);
            }
            if sum > limit {
                return f32::MAX;
            }
        }
        sum / n
    }
}

/// Squared distance of `p` to the polyline `line`.
fn to_polyline_sq(p: &[f32; 2], line: &[[f32; 2]]) -> f32 {
    let mut best = f32::MAX;
    for w in line.windows(2) {
        let (a, b) = (w[0], w[1]);
        let (vx, vy) = (b[0] - a[0], b[1] - a[1]);
        let len = vx * vx + vy * vy;
        let t = if len > 0.0 {
            (((p[0] - a[0]) * vx + (p[1] - a[1]) * vy) / len).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let (dx, dy) = (p[0] - a[0] - t * vx, p[1] - a[1] - t * vy);
        best = best.min(dx * dx + dy * dy);
    }
    best
}

/// Append `SHAPE_POINTS` points uniform in arc length along `pts` (a dot repeats its point).
fn resample(pts: &[[f64; 2]], out: &mut Vec<[f32; 2]>) {
    let mut cum = Vec::with_capacity(pts.len());
    let mut total = 0.0;
    cum.push(0.0);
    for w in pts.windows(2) {
        total += ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2)).sqrt();
        cum.push(total);
    }
    let mut j = 0;
    for k in 0..SHAPE_POINTS {
        if total <= 0.0 {
            out.push([pts[0][0] as f32, pts[0][1] as f32]);
            continue;
        }
        let s = total * k as f64 / (SHAPE_POINTS - 1) as f64;
        while j + 2 < cum.len() && cum[j + 1] < s {
            j += 1;
        }
        let seg = cum[j + 1] - cum[j];
        let f = if seg > 0.0 {
            ((s - cum[j]) / seg).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let p = [
            pts[j][0] + f * (pts[j + 1][0] - pts[j][0]),
            pts[j][1] + f * (pts[j + 1][1] - pts[j][1]),
        ];
        out.push([p[0] as f32, p[1] as f32]);
    }
}

/// The shapes of labelled drawings, bucketed by stroke count, for nearest-shape queries.
#[derive(Debug, Clone, Default)]
pub struct ShapeIndex {
    buckets: BTreeMap<usize, Vec<(usize, Shape)>>,
    len: usize,
}

impl ShapeIndex {
    /// Index `shapes` (their positions are the ids [`ShapeIndex::nearest`] returns).
    pub fn new(shapes: Vec<Shape>) -> Self {
        let len = shapes.len();
        let mut buckets: BTreeMap<usize, Vec<(usize, Shape)>> = BTreeMap::new();
        for (i, s) in shapes.into_iter().enumerate() {
            buckets.entry(s.strokes()).or_default().push((i, s));
        }
        Self { buckets, len }
    }

    /// Number of indexed shapes.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True if nothing is indexed.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The nearest indexed shape with the same stroke count by [`Shape::distance`]: (id,
    /// distance). Candidates are the [`PREFILTER_CANDIDATES`] nearest by
    /// [`Shape::point_distance`] within [`PREFILTER_DISTANCE`]; `None` without any.
    pub fn nearest(&self, s: &Shape) -> Option<(usize, f32)> {
        self.nearest_two(s).map(|(i, d, _)| (i, d))
    }

    /// [`ShapeIndex::nearest`] and the distance of the second nearest (infinite if none).
    pub fn nearest_two(&self, s: &Shape) -> Option<(usize, f32, f32)> {
        let bound = PREFILTER_DISTANCE * PREFILTER_DISTANCE;
        let mut cand: Vec<(f32, usize, &Shape)> = self
            .buckets
            .get(&s.strokes())?
            .iter()
            .filter_map(|(i, r)| {
                let d = s.sq_within(r, bound);
                (d <= bound).then_some((d, *i, r))
            })
            .collect();
        cand.sort_by(|a, b| a.0.total_cmp(&b.0));
        cand.truncate(PREFILTER_CANDIDATES);
        let mut refined: Vec<(usize, f32)> = cand
            .into_iter()
            .filter_map(|(_, i, r)| s.distance(r).map(|d| (i, d)))
            .collect();
        refined.sort_by(|a, b| a.1.total_cmp(&b.1));
        let second = refined.get(1).map_or(f32::INFINITY, |x| x.1);
        refined.first().map(|&(i, d)| (i, d, second))
    }
}

/// A labelled drawing the pool is checked against.
#[derive(Debug, Clone)]
pub struct LabelledShape {
    /// Its alphabet.
    pub alphabet: String,
    /// Its class name `Alphabet/characterNN`.
    pub class: String,
    /// Its drawer.
    pub drawer: u32,
    /// Its shape.
    pub shape: Shape,
}

/// Read the labelled drawings of `alphabets` under `roots` as shapes.
pub fn labelled_shapes(
    roots: &[PathBuf],
    alphabets: &[String],
) -> Result<Vec<LabelledShape>, strokes::ReadStrokesError> {
    let files: Vec<strokes::DrawingFile> = strokes::scan(roots)?
        .into_iter()
        .filter(|f| alphabets.contains(&f.alphabet))
        .collect();
    files
        .par_iter()
        .filter_map(|f| match strokes::read_strokes(&f.path) {
            Ok(s) => Shape::new(&s).map(|shape| {
                Ok(LabelledShape {
                    alphabet: f.alphabet.clone(),
                    class: f.class_name(),
                    drawer: f.drawer,
                    shape,
                })
            }),
            Err(e) => Some(Err(e)),
        })
        .collect()
}

/// For every pool shape, the nearest labelled shape (same stroke count), its distance and
/// the distance of the second nearest (infinite if there is none).
pub fn nearest_labelled(
    pool: &[Shape],
    labelled: &[LabelledShape],
) -> Vec<Option<(usize, f32, f32)>> {
    let index = ShapeIndex::new(labelled.iter().map(|l| l.shape.clone()).collect());
    pool.par_iter().map(|s| index.nearest_two(s)).collect()
}

/// Counts of a distance distribution in logarithmic bins (for choosing the tolerance).
#[derive(Debug, Clone, Serialize)]
pub struct DistanceHistogram {
    /// Upper edges of the bins.
    pub upper: Vec<f32>,
    /// Drawings per bin (the last bin is everything above the last edge but one).
    pub counts: Vec<usize>,
    /// Pool drawings with no labelled drawing of the same stroke count.
    pub no_candidate: usize,
}

/// Histogram of nearest distances in bins with edges 0.001 · 2^(k/2).
pub fn histogram(nearest: &[Option<(usize, f32, f32)>]) -> DistanceHistogram {
    let upper: Vec<f32> = (0..24)
        .map(|k| 0.001 * 2f32.powf(k as f32 / 2.0))
        .chain([f32::INFINITY])
        .collect();
    let mut counts = vec![0; upper.len()];
    let mut no_candidate = 0;
    for n in nearest {
        match n {
            Some((_, d, _)) => {
                let b = upper.iter().position(|u| d <= u).unwrap_or(upper.len() - 1);
                counts[b] += 1;
            }
            None => no_candidate += 1,
        }
    }
    DistanceHistogram {
        upper,
        counts,
        no_candidate,
    }
}

/// What a pool file records about itself (`pool` metadata entry).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub struct PoolInfo {
    /// Drawings in the unlabelled file.
    pub drawings_read: usize,
    /// Alphabets whose copies were left out.
    pub excluded_alphabets: Vec<String>,
    /// Copies left out, per excluded alphabet (a pool drawing counts for the alphabet of its
    /// nearest labelled drawing).
    pub copies_removed: BTreeMap<String, usize>,
    /// The copy rule.
    pub copy_rule: CopyRule,
    /// Drawings that failed conversion (IK or validation) and are not in the file.
    pub conversion_failures: usize,
}

/// The report of `guardian-lab pool`.
#[derive(Debug, Clone, Serialize)]
pub struct PoolReport {
    /// Drawings read.
    pub drawings_read: usize,
    /// Labelled drawings of the excluded alphabets compared against.
    pub labelled_drawings: usize,
    /// Copy rule used.
    pub copy_rule: CopyRule,
    /// Copies removed per excluded alphabet.
    pub copies_removed: BTreeMap<String, usize>,
    /// Copies removed in all.
    pub copies_removed_total: usize,
    /// Labelled drawings with 0, 1, 2, ... copies in the pool.
    pub copies_per_labelled: Vec<usize>,
    /// Nearest-labelled distance over the pool.
    pub nearest_distance: DistanceHistogram,
    /// Pool drawings by nearest-labelled distance (rows: below 0.01, 0.02, ..., 0.06, 0.08,
    /// 0.10, above) and ratio to the second nearest (columns: below 0.3, 0.5, 0.6, 0.7, 0.8,
    /// 0.9, above).
    pub distance_by_ratio: Vec<Vec<usize>>,
    /// Conversion of the drawings kept.
    pub conversion: ConvertReport,
    /// Drawings in the written pool.
    pub pool_size: usize,
    /// Wall-clock seconds in all.
    pub seconds: f64,
}

/// The copies found by [`find_copies`].
#[derive(Debug, Clone)]
pub struct Copies {
    /// Per pool drawing: is it a copy.
    pub is_copy: Vec<bool>,
    /// Copies per alphabet (of the nearest labelled drawing).
    pub per_alphabet: BTreeMap<String, usize>,
    /// Labelled drawings with 0, 1, 2, ... copies.
    pub per_labelled: Vec<usize>,
    /// Per pool drawing: nearest labelled drawing, its distance, second-nearest distance.
    pub nearest: Vec<Option<(usize, f32, f32)>>,
}

/// Which pool drawings are copies of `labelled` drawings under `rule`.
pub fn find_copies(pool: &[Shape], labelled: &[LabelledShape], rule: &CopyRule) -> Copies {
    let nearest = nearest_labelled(pool, labelled);
    let mut per_alphabet: BTreeMap<String, usize> = BTreeMap::new();
    let mut copies_of = vec![0usize; labelled.len()];
    let is_copy: Vec<bool> = nearest
        .iter()
        .map(|n| match n {
            Some((i, d, d2)) if rule.is_copy(*d, *d2) => {
                *per_alphabet
                    .entry(labelled[*i].alphabet.clone())
                    .or_default() += 1;
                copies_of[*i] += 1;
                true
            }
            _ => false,
        })
        .collect();
    let mut per_labelled = vec![0usize; copies_of.iter().max().map_or(1, |m| m + 1)];
    for c in copies_of {
        per_labelled[c] += 1;
    }
    Copies {
        is_copy,
        per_alphabet,
        per_labelled,
        nearest,
    }
}

fn distance_by_ratio(nearest: &[Option<(usize, f32, f32)>]) -> Vec<Vec<usize>> {
    let rows = [
        0.01,
        0.02,
        0.03,
        0.04,
        0.05,
        0.06,
        0.08,
        0.10,
        f32::INFINITY,
    ];
    let cols = [0.3, 0.5, 0.6, 0.7, 0.8, 0.9, f32::INFINITY];
    let mut out = vec![vec![0; cols.len()]; rows.len()];
    for &(_, d, d2) in nearest.iter().flatten() {
        let r = rows.iter().position(|&u| d < u).unwrap_or(rows.len() - 1);
        let c = cols
            .iter()
            .position(|&u| d / d2 < u)
            .unwrap_or(cols.len() - 1);
        out[r][c] += 1;
    }
    out
}

/// Building a pool failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BuildPoolError {
    /// The unlabelled file.
    #[error(transparent)]
    Read(#[from] ReadPoolError),
    /// The labelled stroke files.
    #[error(transparent)]
    Strokes(#[from] strokes::ReadStrokesError),
    /// The geometry.
    #[error(transparent)]
    Geometry(#[from] SolvePathError),
    /// An excluded alphabet has no labelled drawing.
    #[error("alphabet {0:?} has no drawing under the stroke roots")]
    UnknownAlphabet(String),
    /// Writing the file.
    #[error(transparent)]
    Save(#[from] dataset::SaveDatasetError),
}

/// Read the pool, leave out the copies of `exclude` alphabets' drawings (under `roots`),
/// convert the rest; returns the pool dataset, its info and the report.
pub fn build_pool(
    unlabelled: &Path,
    roots: &[PathBuf],
    exclude: &[String],
    rule: &CopyRule,
    geometry: &Geometry,
) -> Result<(Dataset, PoolInfo, PoolReport), BuildPoolError> {
    let t0 = Instant::now();
    let drawings = read_pool(unlabelled)?;
    let labelled = if exclude.is_empty() {
        Vec::new()
    } else {
        labelled_shapes(roots, exclude)?
    };
    for a in exclude {
        if !labelled.iter().any(|l| &l.alphabet == a) {
            return Err(BuildPoolError::UnknownAlphabet(a.clone()));
        }
    }
    let shapes: Vec<Shape> = drawings
        .par_iter()
        .map(|d| Shape::new(&d.strokes).unwrap_or(Shape { points: Vec::new() }))
        .collect();
    let copies = find_copies(&shapes, &labelled, rule);
    let hist = histogram(&copies.nearest);
    let by_ratio = distance_by_ratio(&copies.nearest);
    let (is_copy, mut per_alphabet, per_labelled) =
        (copies.is_copy, copies.per_alphabet, copies.per_labelled);
    for a in exclude {
        per_alphabet.entry(a.clone()).or_default();
    }
    let kept: Vec<usize> = (0..drawings.len()).filter(|&i| !is_copy[i]).collect();
    let strokes: Vec<&[Stroke]> = kept.iter().map(|&i| &drawings[i].strokes[..]).collect();
    let (converted, conversion) = convert_pool(&strokes, geometry)?;
    let mut data = Dataset {
        trajectories: Vec::with_capacity(kept.len()),
        labels: Vec::new(),
        alphabet_ids: Vec::new(),
        drawer_ids: Vec::new(),
        classes: vec![format!("{POOL_ALPHABET}/pool")],
        alphabets: vec![POOL_ALPHABET.to_string()],
        geometry: geometry.clone(),
        generator: dataset::generator_name(),
        robot: guardian_models::kinematics::RobotRecord::of(&geometry.robot()?),
    };
    for (&i, r) in kept.iter().zip(converted) {
        if let Ok(x) = r {
            data.trajectories.push(x);
            data.labels.push(0);
            data.alphabet_ids.push(0);
            data.drawer_ids.push(i as i64);
        }
    }
    let total = per_alphabet.values().sum();
    let info = PoolInfo {
        drawings_read: drawings.len(),
        excluded_alphabets: exclude.to_vec(),
        copies_removed: per_alphabet.clone(),
        copy_rule: *rule,
        conversion_failures: conversion.ik_failures + conversion.other_failures,
    };
    let report = PoolReport {
        drawings_read: drawings.len(),
        labelled_drawings: labelled.len(),
        copy_rule: *rule,
        copies_removed: per_alphabet,
        copies_removed_total: total,
        copies_per_labelled: per_labelled,
        nearest_distance: hist,
        distance_by_ratio: by_ratio,
        conversion,
        pool_size: data.len(),
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok((data, info, report))
}

/// The dataset file bytes of `data` with `info` as its `pool` metadata entry.
pub fn pool_bytes(data: &Dataset, info: &PoolInfo) -> Result<Vec<u8>, dataset::SaveDatasetError> {
    let bytes = data.to_bytes()?;
    let bad = |what: &str| dataset::SaveDatasetError::Io {
        path: PathBuf::from("<pool>"),
        source: std::io::Error::other(what.to_string()),
    };
    let n = u64::from_le_bytes(bytes[..8].try_into().map_err(|_| bad("short"))?) as usize;
    let mut header: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&bytes[8..8 + n]).map_err(|_| bad("header"))?;
    let info_text = serde_json::to_string(info).map_err(|_| bad("info"))?;
    if let Some(serde_json::Value::Object(meta)) = header.get_mut("__metadata__") {
        meta.insert("pool".into(), serde_json::Value::String(info_text));
    }
    let mut h = serde_json::to_string(&header)
        .map_err(|_| bad("header"))?
        .into_bytes();
    h.resize(h.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + h.len() + bytes.len() - 8 - n);
    out.extend_from_slice(&(h.len() as u64).to_le_bytes());
    out.extend_from_slice(&h);
    out.extend_from_slice(&bytes[8 + n..]);
    Ok(out)
}

/// Write a pool file atomically.
pub fn save_pool(
    data: &Dataset,
    info: &PoolInfo,
    path: &Path,
) -> Result<(), dataset::SaveDatasetError> {
    dataset::write_atomic(path, &pool_bytes(data, info)?)
}

/// The `pool` metadata entry of a dataset file (`None` if it has none or it does not parse).
pub fn pool_info(bytes: &[u8]) -> Option<PoolInfo> {
    let (_, meta) = safetensors::SafeTensors::read_metadata(bytes).ok()?;
    serde_json::from_str(meta.metadata().as_ref()?.get("pool")?).ok()
}

/// How training uses the pool.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum PoolMode {
    /// Not at all.
    #[default]
    None,
    /// Clusters of the pool under a given embedder are classes ([`pseudo_labels`]).
    Pseudo,
    /// Every pool drawing is a class of two identical members: augmentation makes two views.
    Ssl,
}

/// Clustering for pseudo-labels: mutual `k` nearest neighbours whose squared embedding
/// distance is at most `threshold` are linked; the connected components of at least
/// `min_size` drawings are classes. A component larger than `max_size` is split again with
/// the threshold × 0.8 (up to 8 times), and dropped if still too large.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct ClusterParams {
    /// Neighbours per drawing.
    pub k: usize,
    /// Largest squared distance of a link.
    pub threshold: f32,
    /// Smallest cluster kept.
    pub min_size: usize,
    /// Largest cluster kept (an Omniglot class has 20 drawers).
    pub max_size: usize,
}

/// The threshold was chosen on the pool without Greek and Korean copies, clustered with the
/// shipped model: the copies of the other four alphabets' drawings in it (known classes)
/// are 0.89 / 0.89 / 0.91 / 0.87 / 0.87 pure at thresholds 0.05 / 0.10 / 0.15 / 0.20 / 0.25
/// (775 clusters of 8,245 drawings at 0.15); those alphabets were in its training or
/// validation, so the purity is optimistic for unseen ones.
impl Default for ClusterParams {
    fn default() -> Self {
        Self {
            k: 10,
            threshold: 0.15,
            min_size: 4,
            max_size: 40,
        }
    }
}

/// The `k` nearest neighbours of every embedding (squared distances, nearest first, itself
/// excluded), by blocked matrix products.
pub fn knn(emb: &[Embedding], k: usize) -> candle_core::Result<Vec<Vec<(u32, f32)>>> {
    let n = emb.len();
    let d = emb.first().map_or(0, |e| e.len());
    let flat: Vec<f32> = emb.iter().flatten().copied().collect();
    let all = Tensor::from_vec(flat, (n, d), &Device::Cpu)?;
    let norms: Vec<f32> = emb.iter().map(|e| e.iter().map(|v| v * v).sum()).collect();
    let all_t = all.t()?.contiguous()?;
    let mut out = Vec::with_capacity(n);
    const BLOCK: usize = 512;
    for start in (0..n).step_by(BLOCK) {
        let len = BLOCK.min(n - start);
        let dots = all
            .narrow(0, start, len)?
            .matmul(&all_t)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let rows: Vec<Vec<(u32, f32)>> = dots
            .par_chunks(n)
            .enumerate()
            .map(|(r, row)| {
                let i = start + r;
                // The k best so far, nearest first (insertion into a short sorted list).
                let mut best: Vec<(u32, f32)> = Vec::with_capacity(k + 1);
                for (j, &dot) in row.iter().enumerate() {
                    let d = (norms[i] + norms[j] - 2.0 * dot).max(0.0);
                    if j == i || (best.len() == k && d >= best[k - 1].1) || k == 0 {
                        continue;
                    }
                    let at = best.partition_point(|x| x.1 <= d);
                    best.insert(at, (j as u32, d));
                    best.truncate(k);
                }
                best
            })
            .collect();
        out.extend(rows);
    }
    Ok(out)
}

/// What a clustering gave.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ClusterStats {
    /// Drawings clustered.
    pub drawings: usize,
    /// Clusters kept.
    pub clusters: usize,
    /// Drawings in kept clusters.
    pub clustered: usize,
    /// Kept clusters by size: `[4-5, 6-10, 11-20, 21-40, >40]` (with the default bounds).
    pub sizes: BTreeMap<String, usize>,
    /// Components below `min_size` (singletons included).
    pub too_small: usize,
    /// Components still above `max_size` after splitting, dropped.
    pub too_large_dropped: usize,
    /// Drawings in dropped too-large components.
    pub too_large_drawings: usize,
    /// Median squared distance to the nearest neighbour.
    pub median_nn_sq_dist: f32,
    /// Median squared distance to the k-th neighbour.
    pub median_kth_sq_dist: f32,
}

fn find(parent: &mut [usize], mut x: usize) -> usize {
    while parent[x] != x {
        parent[x] = parent[parent[x]];
        x = parent[x];
    }
    x
}

/// Components of `nodes` under the `edges` with weight <= `threshold`; oversize ones split
/// recursively with a lower threshold.
fn components(
    nodes: &[usize],
    edges: &[(usize, usize, f32)],
    threshold: f32,
    params: &ClusterParams,
    depth: usize,
    out: &mut Vec<Vec<usize>>,
    stats: &mut ClusterStats,
) {
    let pos: BTreeMap<usize, usize> = nodes.iter().enumerate().map(|(p, &n)| (n, p)).collect();
    let mut parent: Vec<usize> = (0..nodes.len()).collect();
    for &(a, b, w) in edges {
        if w <= threshold
            && let (Some(&pa), Some(&pb)) = (pos.get(&a), pos.get(&b))
        {
            let (ra, rb) = (find(&mut parent, pa), find(&mut parent, pb));
            if ra != rb {
                parent[ra] = rb;
            }
        }
    }
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (p, &node) in nodes.iter().enumerate() {
        let r = find(&mut parent, p);
        groups.entry(r).or_default().push(node);
    }
    for g in groups.into_values() {
        if g.len() < params.min_size {
            stats.too_small += 1;
        } else if g.len() <= params.max_size {
            out.push(g);
        } else if depth < 8 {
            let sub: Vec<(usize, usize, f32)> = edges
                .iter()
                .filter(|e| e.2 <= threshold && g.binary_search(&e.0).is_ok())
                .copied()
                .collect();
            components(&g, &sub, threshold * 0.8, params, depth + 1, out, stats);
        } else {
            stats.too_large_dropped += 1;
            stats.too_large_drawings += g.len();
        }
    }
}

/// Pseudo-classes of `emb` (groups of indices, each sorted, groups by first member).
pub fn cluster(
    emb: &[Embedding],
    params: &ClusterParams,
) -> candle_core::Result<(Vec<Vec<usize>>, ClusterStats)> {
    Ok(cluster_knn(&knn(emb, params.k)?, params))
}

/// [`cluster`] on precomputed neighbours ([`knn`] with at least `params.k`; extra ones are
/// ignored).
pub fn cluster_knn(
    nn_all: &[Vec<(u32, f32)>],
    params: &ClusterParams,
) -> (Vec<Vec<usize>>, ClusterStats) {
    let nn: Vec<&[(u32, f32)]> = nn_all.iter().map(|r| &r[..params.k.min(r.len())]).collect();
    let mut edges = Vec::new();
    for (i, row) in nn.iter().enumerate() {
        for &(j, d) in row.iter() {
            let j = j as usize;
            if i < j && nn[j].iter().any(|&(x, _)| x as usize == i) {
                edges.push((i, j, d));
            }
        }
    }
    let median = |mut v: Vec<f32>| {
        v.sort_by(f32::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f32::NAN)
    };
    let mut stats = ClusterStats {
        drawings: nn.len(),
        median_nn_sq_dist: median(nn.iter().filter_map(|r| r.first().map(|x| x.1)).collect()),
        median_kth_sq_dist: median(nn.iter().filter_map(|r| r.last().map(|x| x.1)).collect()),
        ..Default::default()
    };
    let nodes: Vec<usize> = (0..nn.len()).collect();
    let mut groups = Vec::new();
    components(
        &nodes,
        &edges,
        params.threshold,
        params,
        0,
        &mut groups,
        &mut stats,
    );
    groups.sort();
    stats.clusters = groups.len();
    stats.clustered = groups.iter().map(Vec::len).sum();
    for g in &groups {
        let key = match g.len() {
            0..=5 => "4-5",
            6..=10 => "6-10",
            11..=20 => "11-20",
            21..=40 => "21-40",
            _ => ">40",
        };
        *stats.sizes.entry(key.to_string()).or_default() += 1;
    }
    (groups, stats)
}

/// Embed the pool with `model` and cluster it ([`cluster`]).
pub fn pseudo_labels(
    model: &Embedder,
    pool: &Dataset,
    params: &ClusterParams,
) -> Result<(Vec<Vec<usize>>, ClusterStats), PseudoLabelError> {
    let emb = embed_pool(model, pool)?;
    Ok(cluster(&emb, params)?)
}

/// Embeddings of every pool drawing.
pub fn embed_pool(model: &Embedder, pool: &Dataset) -> Result<Vec<Embedding>, PseudoLabelError> {
    let robot =
        crate::dataset::Dataset::robot(pool).map_err(|e| PseudoLabelError::Robot(e.to_string()))?;
    let chunks: Vec<&[Resampled]> = pool.trajectories.chunks(256).collect();
    let parts: Vec<Vec<Embedding>> = chunks
        .par_iter()
        .map(|c| model.embed_batch(&robot, c))
        .collect::<Result<_, _>>()?;
    Ok(parts.into_iter().flatten().collect())
}

/// Pseudo-labelling failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PseudoLabelError {
    /// Embedding.
    #[error("embedding the pool: {0}")]
    Embed(#[from] guardian_models::embedder::EmbedError),
    /// The neighbour search.
    #[error("neighbour search: {0}")]
    Candle(#[from] candle_core::Error),
    /// The pool's robot could not be loaded.
    #[error("the pool's robot: {0}")]
    Robot(String),
}

/// The classes a training run adds from the pool: pseudo-label clusters, or (SSL) every
/// drawing alone (the caller doubles it into two views).
pub fn training_groups(
    pool: &Dataset,
    mode: PoolMode,
    model: Option<&Embedder>,
    params: &ClusterParams,
) -> Result<(Vec<Vec<usize>>, Option<ClusterStats>), PseudoLabelError> {
    match (mode, model) {
        (PoolMode::None, _) => Ok((Vec::new(), None)),
        (PoolMode::Ssl, _) => Ok(((0..pool.len()).map(|i| vec![i, i]).collect(), None)),
        (PoolMode::Pseudo, Some(m)) => {
            let (g, s) = pseudo_labels(m, pool, params)?;
            Ok((g, Some(s)))
        }
        (PoolMode::Pseudo, None) => Ok((Vec::new(), None)),
    }
}

/// `guardian-lab pool`: build a fold's unlabelled pool.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// The unlabelled drawings (JSON lines).
    #[arg(long, default_value = DEFAULT_UNLABELLED)]
    pub unlabelled: PathBuf,
    /// Labelled stroke root(s) the excluded alphabets are read from.
    #[arg(long = "strokes", default_value = "../shared/omniglot/strokes")]
    pub strokes: Vec<PathBuf>,
    /// Alphabets whose drawings' copies are left out of the pool (a fold's test and
    /// validation alphabets), comma-separated.
    #[arg(long, value_delimiter = ',')]
    pub exclude_alphabets: Vec<String>,
    /// Copy rule: a copy at any ratio below this distance (shapes with the longest side 1).
    #[arg(long, default_value_t = CopyRule::default().tolerance)]
    pub copy_tolerance: f32,
    /// Copy rule: largest distance of a copy (with `--copy-ratio`).
    #[arg(long, default_value_t = CopyRule::default().loose_tolerance)]
    pub copy_loose_tolerance: f32,
    /// Copy rule: largest nearest / second-nearest ratio between the two tolerances.
    #[arg(long, default_value_t = CopyRule::default().ratio)]
    pub copy_ratio: f32,
    /// Output pool file (a dataset file).
    #[arg(long)]
    pub out: PathBuf,
    /// Also cluster the written pool with this model and print the cluster statistics for
    /// every `--cluster-thresholds` value (for choosing the pseudo-label parameters).
    #[arg(long)]
    pub cluster_model: Option<PathBuf>,
    /// Squared-distance thresholds to print cluster statistics for.
    #[arg(long, value_delimiter = ',', default_value = "0.15")]
    pub cluster_thresholds: Vec<f32>,
    /// Neighbours per drawing for the cluster statistics.
    #[arg(long, default_value_t = ClusterParams::default().k)]
    pub cluster_k: usize,
}

/// The labelled class of every pool drawing of `data` that is a copy of a labelled drawing
/// of an alphabet under `roots` not in `exclude` (`None` for the others).
fn copy_classes(
    unlabelled: &Path,
    roots: &[PathBuf],
    exclude: &[String],
    data: &Dataset,
) -> anyhow::Result<Vec<Option<String>>> {
    let alphabets: Vec<String> = strokes::scan(roots)?
        .into_iter()
        .map(|f| f.alphabet)
        .filter(|a| !exclude.contains(a))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let labelled = labelled_shapes(roots, &alphabets)?;
    let drawings = read_pool(unlabelled)?;
    let shapes: Vec<Shape> = data
        .drawer_ids
        .iter()
        .map(|&i| {
            usize::try_from(i)
                .ok()
                .and_then(|i| drawings.get(i))
                .and_then(|d| Shape::new(&d.strokes))
                .unwrap_or(Shape { points: Vec::new() })
        })
        .collect();
    let found = find_copies(&shapes, &labelled, &CopyRule::default());
    Ok(found
        .nearest
        .iter()
        .zip(&found.is_copy)
        .map(|(n, &c)| n.filter(|_| c).map(|(l, _, _)| labelled[l].class.clone()))
        .collect())
}

/// Purity of clusters against the known classes of some members: over the clusters with at
/// least two known members, the fraction of known members in their cluster's majority class;
/// also how many such clusters, their known members, and the known drawings not clustered.
fn purity(groups: &[Vec<usize>], truth: &[Option<String>]) -> serde_json::Value {
    let (mut clusters, mut known, mut majority) = (0, 0, 0);
    let mut clustered = vec![false; truth.len()];
    for g in groups {
        let mut count: BTreeMap<&str, usize> = BTreeMap::new();
        for &i in g {
            clustered[i] = true;
            if let Some(c) = &truth[i] {
                *count.entry(c).or_default() += 1;
            }
        }
        let n: usize = count.values().sum();
        if n >= 2 {
            clusters += 1;
            known += n;
            majority += count.values().max().copied().unwrap_or(0);
        }
    }
    let unclustered = truth
        .iter()
        .zip(&clustered)
        .filter(|(t, c)| t.is_some() && !**c)
        .count();
    serde_json::json!({
        "clusters-with-known": clusters,
        "known-members": known,
        "purity": majority as f64 / known.max(1) as f64,
        "known-not-clustered": unclustered,
    })
}

/// Run `guardian-lab pool`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let geometry = Geometry::default();
    let (data, info, report) = build_pool(
        &args.unlabelled,
        &args.strokes,
        &args.exclude_alphabets,
        &CopyRule {
            tolerance: args.copy_tolerance,
            loose_tolerance: args.copy_loose_tolerance,
            ratio: args.copy_ratio,
        },
        &geometry,
    )?;
    save_pool(&data, &info, &args.out)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    if let Some(m) = &args.cluster_model {
        let model = data.embedder(m)?;
        let t0 = Instant::now();
        let emb = embed_pool(&model, &data)?;
        let nn = knn(&emb, args.cluster_k)?;
        // Ground truth for a purity figure: the pool drawings that are copies of labelled
        // drawings of the alphabets not excluded (still in the pool), by class.
        let truth = copy_classes(
            &args.unlabelled,
            &args.strokes,
            &args.exclude_alphabets,
            &data,
        )?;
        for &threshold in &args.cluster_thresholds {
            let params = ClusterParams {
                k: args.cluster_k,
                threshold,
                ..Default::default()
            };
            let (groups, stats) = cluster_knn(&nn, &params);
            println!(
                "{}",
                serde_json::json!({"params": params, "stats": stats,
                    "purity": purity(&groups, &truth),
                    "seconds": t0.elapsed().as_secs_f64()})
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stroke(points: &[(f64, f64)]) -> Stroke {
        points
            .iter()
            .map(|&(x, y)| Point { x, y, t: 0.0 })
            .collect()
    }

    #[test]
    fn shapes_ignore_position_size_and_point_spacing_but_not_order() {
        let a = vec![
            stroke(&[(10.0, -10.0), (30.0, -10.0), (30.0, -40.0)]),
            stroke(&[(10.0, -20.0), (20.0, -30.0)]),
        ];
        // Shifted, scaled by 1.7, the first stroke with extra points on its segments, a
        // dot added (dropped, as upstream lost them).
        let b = vec![
            stroke(&[(50.0, -50.0), (67.0, -50.0), (84.0, -50.0), (84.0, -101.0)]),
            stroke(&[(50.0, -67.0), (67.0, -84.0)]),
            stroke(&[(60.0, -60.0)]),
        ];
        let (sa, sb) = (Shape::new(&a).unwrap(), Shape::new(&b).unwrap());
        assert_eq!(sb.strokes(), 2);
        assert!(sa.distance(&sb).unwrap() < 1e-5);
        // Strokes in the other order are another shape.
        let c = vec![a[1].clone(), a[0].clone()];
        assert!(sa.distance(&Shape::new(&c).unwrap()).unwrap() > 0.1);
        // Different stroke counts never compare.
        assert_eq!(sa.distance(&Shape::new(&a[..1]).unwrap()), None);
        let index = ShapeIndex::new(vec![Shape::new(&c).unwrap(), sa.clone()]);
        assert_eq!(index.nearest(&sb).map(|n| n.0), Some(1));
    }

    #[test]
    fn the_copy_rule_uses_the_ratio_only_between_the_tolerances() {
        let r = CopyRule::default();
        assert!(r.is_copy(0.01, 0.011));
        assert!(r.is_copy(0.04, 0.09));
        assert!(!r.is_copy(0.04, 0.07));
        assert!(!r.is_copy(0.06, f32::INFINITY));
    }

    #[test]
    fn clusters_are_mutual_neighbour_components_within_the_size_bounds() {
        let mut emb = Vec::new();
        for c in 0..3 {
            for i in 0..6 {
                let mut e = [0.0f32; guardian_models::embedder::EMBED_DIM];
                e[c] = 1.0;
                e[10] = 0.01 * i as f32;
                emb.push(e);
            }
        }
        // A lone far point.
        let mut e = [0.0f32; guardian_models::embedder::EMBED_DIM];
        e[20] = 5.0;
        emb.push(e);
        let params = ClusterParams {
            k: 5,
            threshold: 0.1,
            min_size: 4,
            max_size: 40,
        };
        let (groups, stats) = cluster(&emb, &params).unwrap();
        assert_eq!(
            groups,
            vec![
                (0..6).collect::<Vec<_>>(),
                (6..12).collect(),
                (12..18).collect()
            ]
        );
        assert_eq!(stats.clustered, 18);
        assert_eq!(stats.too_small, 1);
        // Too large: with max size 5 the groups are split further, then dropped.
        let (groups, stats) = cluster(
            &emb,
            &ClusterParams {
                max_size: 5,
                ..params
            },
        )
        .unwrap();
        assert!(groups.iter().all(|g| g.len() <= 5));
        assert!(stats.too_large_dropped + stats.too_small > 1);
    }
}
