//! `guardian-lab outliers`: how well go / no-go catches faulty plans and lets genuine ones
//! through, for guardian and the raw 1-NN and Siamese baselines.
//!
//! Protocol. Calibration: every method is calibrated on the calibration (validation)
//! alphabets exactly like the shipped bank ([`crate::eval::calibration`], target false-reject rate
//! `--target-frr`). Test, on `--alphabets` only, `--reps` rounds: a random quarter of the
//! classes is never enrolled (the unknown tasks); every other class enrolls `--shots`
//! random drawings; its other drawings are the genuine plans. Faulty plans:
//! - wrong task: a genuine plan of an enrolled class claiming another enrolled class —
//!   severity 0.25 the class whose prototype is nearest to the true class's prototype (in
//!   the method's own space), 0.5 a random class of the same alphabet, 1 any random class;
//! - unknown task: a plan of a never-enrolled class claiming an enrolled class (same
//!   severities: nearest enrolled prototype, same alphabet, any);
//! - every [`Fault`] at every severity in [`SEVERITIES`], applied to `--sources` random
//!   test drawings (re-solved through the IK once; a round skips a source enrolled in it)
//!   and claiming the drawing's own class.
//!
//! Embedding score of a plan claiming class c (higher = more suspicious): `max(d_c / t_c,
//! d_c / (d_o + tol))`, with `d_c` the distance to class c, `d_o` to the nearest other
//! class, `t_c` the calibrated threshold and `tol` the wrong-task tolerance; the score
//! exceeds 1 exactly when the bank's embedding rule says no-go. Methods:
//! - `guardian`: the full decision of `guardiand` — workcell rules, embedding and plan
//!   geometry. Its score is the largest of three normalised scores, each > 1 exactly when
//!   its own rule says no-go: the embedding score (calibrated for `(1 − geometry-share) ×
//!   target`), the geometry score divided by its calibrated threshold (the rest of the
//!   budget, [`bank::calibrate_geometry`]), and the workcell score (the largest deviation
//!   over all waypoints and rules, each divided by its tolerance,
//!   [`guardian_robot::workcell::Inspection::score`]);
//! - `guardian-near-miss` (with `--near-misses`): the full decision and a near-miss step.
//!   Every enrolled example's near misses (`guardian_robot::variant`: stopped early,
//!   mirrored) are embedded, a prototype per class and kind; a plan whose distance to its
//!   class exceeds its distance to the nearest near-miss prototype of the class by more than
//!   a tolerance is a no-go. The tolerance takes `--near-miss-share` of the false-reject
//!   budget from the embedding's share (or the geometry's, `--near-miss-from-geometry`):
//!   what the embedding and geometry rules leave of the budget, on the calibration plans
//!   they accept, so the genuine false-reject target is the same as `guardian`'s;
//! - `guardian-ink` (with `--ink`): the full decision and an ink step. Every enrolled
//!   example's ink (its pen-down path, bounding boxes centred with `--ink-centred`) is kept;
//!   a plan whose ink distance to the nearest example (`guardian_robot::ink`: the larger of
//!   what it leaves undrawn and what it draws beyond, as a `--ink-quantile` of point-to-ink
//!   distances) exceeds a tolerance is a no-go. The tolerance takes `--ink-share` of the
//!   budget from the geometry's share (or the embedding's, `--ink-from-embedding`), on the
//!   calibration plans the other rules accept, as for the near-miss step;
//! - `guardian-embedding`: the shipped embedder alone, calibrated for the whole target
//!   (the decision before the workcell and geometry checks existed), for comparison;
//! - `siamese`, `knn`: the baselines.
//!
//! Reported per fault and severity: AUROC of faulty vs
//! genuine scores, TPR at 1 % FPR (threshold at the genuine scores' 99th percentile),
//! detection rate at the calibrated threshold (score > 1); and the genuine false-reject
//! rate at the calibrated threshold.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::Context as _;
use guardian_bank::{self as bank, Calibration, ClassBank, GenuineScore, GeometryCalibration};
use guardian_models::embedder::Embedder;
use guardian_robot::geometry::{self, PlanGeometry};
use guardian_robot::ink::{self, Ink};
use guardian_robot::workcell;
use guardian_screen::check::{self, Embedded};
use guardian_shared::trajectory::Resampled;
use guardian_shared::workcell::Workcell;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::{IndexedRandom, SliceRandom};
use rayon::prelude::*;
use serde::Serialize;

use crate::cli::{DatasetArgs, ScreenArgs, StrokesArgs};
use crate::eval::calibration::split;
use crate::eval::metrics::{auroc, share_above, tpr_at_fpr};
use crate::eval::{Pool, standardised_raw};
use guardian_omniglot::corrupt::{self, Fault, SEVERITIES};
use guardian_omniglot::dataset::{Dataset, StrokeIndex};
use guardian_omniglot::path::PathSolver;
use guardian_omniglot::strokes;

/// How a method measures a query against a class.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The full decision: workcell rules, the shipped embedder (prototypes, calibrated
    /// per-class thresholds) and the per-class plan geometry.
    Guardian,
    /// The shipped embedder alone, calibrated for the whole target.
    GuardianEmbedding,
    /// The full decision and the near-miss step: a plan nearer to a near miss of its class
    /// (the enrolled examples stopped early or mirrored, `--near-misses`) than to the class
    /// by more than a calibrated tolerance is a no-go.
    GuardianNearMiss,
    /// The full decision and the ink step (`--ink`): a plan whose ink is farther from every
    /// enrolled example's than a calibrated tolerance (`guardian_robot::ink`) is a no-go.
    GuardianInk,
    /// The Siamese baseline network, prototypes, calibrated the same way.
    Siamese,
    /// 1-NN on standardised raw trajectories (smallest L2 to a class's enrolled drawings),
    /// global calibrated threshold.
    Knn,
}

impl Method {
    fn prototypes(self) -> bool {
        !matches!(self, Method::Knn)
    }
}

/// A method's vectors for a set of samples.
struct Space<'a> {
    method: Method,
    vecs: &'a [Vec<f32>],
}

/// Per-class state of one enrollment.
struct Enrolled {
    /// Geometry descriptors of the support per class (empty without geometry).
    geometry: Vec<Vec<PlanGeometry>>,
    /// Prototype (prototype methods) per class; empty if the class is not enrolled.
    protos: Vec<Vec<f32>>,
    /// Support vectors per class.
    support: Vec<Vec<Vec<f32>>>,
    spread: Vec<Option<f32>>,
    /// Per class, the prototype of each near miss of its support (empty without near
    /// misses, or where no example had that near miss).
    near: Vec<Vec<Vec<f32>>>,
    /// Per class, the ink of each enrolled example (empty without `--ink`).
    ink: Vec<Vec<Ink>>,
}

/// Mean of `rows` (empty for none).
fn mean_of(rows: &[&Vec<f32>]) -> Vec<f32> {
    let dim = rows.first().map_or(0, |r| r.len());
    let mut m = vec![0.0f32; dim];
    for r in rows {
        for (a, v) in m.iter_mut().zip(r.iter()) {
            *a += v / rows.len() as f32;
        }
    }
    m
}

impl Space<'_> {
    /// Enroll `support`; with `near`, also every near miss (`near[k].1[i]`: the near misses
    /// of kind `k` of sample `i`, none where they could not be made): a prototype per kind
    /// that makes one near miss of a plan, every near miss of the support for a kind that
    /// makes several (one per stroke).
    fn enroll_near(
        &self,
        support: &[Vec<usize>],
        geo: Option<&[Option<PlanGeometry>]>,
        near: Option<&[NearVectors]>,
    ) -> Enrolled {
        let mut e = self.enroll(support, geo);
        if let Some(near) = near {
            e.near = support
                .iter()
                .map(|idx| {
                    let mut out = Vec::new();
                    for (kind, vecs) in near {
                        let rows: Vec<&Vec<f32>> =
                            idx.iter().flat_map(|&i| vecs[i].iter()).collect();
                        if kind.per_stroke() {
                            out.extend(rows.into_iter().cloned());
                        } else if !rows.is_empty() {
                            out.push(mean_of(&rows));
                        }
                    }
                    out
                })
                .collect();
        }
        e
    }

    fn enroll(&self, support: &[Vec<usize>], geo: Option<&[Option<PlanGeometry>]>) -> Enrolled {
        let mut e = Enrolled {
            near: Vec::new(),
            ink: Vec::new(),
            geometry: support
                .iter()
                .map(|idx| {
                    geo.map(|g| idx.iter().filter_map(|&i| g[i]).collect())
                        .unwrap_or_default()
                })
                .collect(),
            protos: Vec::new(),
            support: Vec::new(),
            spread: Vec::new(),
        };
        for idx in support {
            let rows: Vec<Vec<f32>> = idx.iter().map(|&i| self.vecs[i].clone()).collect();
            let proto = mean_of(&rows.iter().collect::<Vec<_>>());
            e.spread.push(if self.method.prototypes() {
                bank::class_spread(&rows)
            } else {
                None
            });
            e.protos.push(proto);
            e.support.push(rows);
        }
        e
    }
}

impl Enrolled {
    /// Distance of `q` to every class (infinite for classes not enrolled).
    fn distances(&self, method: Method, q: &[f32]) -> Vec<f32> {
        (0..self.protos.len())
            .map(|c| {
                if self.support[c].is_empty() {
                    f32::INFINITY
                } else if method.prototypes() {
                    bank::distance(q, &self.protos[c])
                } else {
                    self.support[c]
                        .iter()
                        .map(|s| bank::distance(q, s))
                        .fold(f32::INFINITY, f32::min)
                }
            })
            .collect()
    }

    fn genuine(&self, d: &[f32], c: usize) -> GenuineScore {
        let other = d
            .iter()
            .enumerate()
            .filter(|(i, _)| *i != c)
            .map(|(_, &v)| v)
            .fold(f32::INFINITY, f32::min);
        GenuineScore {
            claimed: d[c],
            nearest_other: other.is_finite().then_some(other),
            spread: self.spread[c],
        }
    }
}

/// The embedding score of a plan (see the module docs); > 1 = no-go.
pub fn score(g: &GenuineScore, cal: &Calibration) -> f32 {
    g.normalised(cal)
}

impl Enrolled {
    /// The near-miss margin of a plan at `q` claiming class `c`: its distance to the class
    /// minus its distance to the nearest near miss of the class (> 0: it resembles a near
    /// miss more than the class). `None` without near misses.
    fn near_miss_margin(&self, q: &[f32], c: usize, form: NearMissForm) -> Option<f32> {
        let near = self.near.get(c).filter(|n| !n.is_empty())?;
        let dn = near
            .iter()
            .map(|p| bank::distance(q, p))
            .fold(f32::INFINITY, f32::min);
        let dc = bank::distance(q, &self.protos[c]);
        Some(match (form, self.spread[c]) {
            (NearMissForm::Spread, Some(s)) if s > 0.0 => (dc - dn) / s,
            (NearMissForm::Ratio, _) => dc / dn.max(1e-12),
            _ => dc - dn,
        })
    }

    /// Enroll the ink of every support plan (`inks[i]`: plan `i`'s ink).
    fn with_ink(mut self, support: &[Vec<usize>], inks: Option<&[Option<Ink>]>) -> Self {
        if let Some(inks) = inks {
            self.ink = support
                .iter()
                .map(|idx| idx.iter().filter_map(|&i| inks[i].clone()).collect())
                .collect();
        }
        self
    }

    /// The ink score of a plan claiming class `c` (`None` without ink).
    fn ink_score(&self, plan: Option<&Ink>, c: usize, q: f32) -> Option<f32> {
        let examples = self.ink.get(c).filter(|e| !e.is_empty())?;
        match plan {
            Some(p) => ink::score(p, examples, q),
            // A plan that draws nothing against a class that draws.
            None => Some(f32::INFINITY),
        }
    }

    /// Raw geometry score of `g` against class `c` (`None` without descriptors).
    fn geometry_score(
        &self,
        g: Option<&PlanGeometry>,
        c: usize,
        scales: &[f32; 12],
    ) -> Option<f32> {
        geometry::score(g?, self.geometry.get(c)?, scales).map(|(s, _)| s)
    }
}

/// The full decision's score: the largest of the normalised embedding, geometry and
/// workcell scores (> 1 = no-go).
fn full_score(
    emb: f32,
    geometry: Option<f32>,
    gcal: Option<&GeometryCalibration>,
    workcell: f32,
) -> f32 {
    let g = match (geometry, gcal) {
        (Some(s), Some(c)) => geometry::normalised_geometry_score(s, c.threshold),
        _ => 0.0,
    };
    emb.max(g).max(workcell)
}

/// An ink score over its tolerance, > 1 exactly when the ink step says no-go (NaN: +inf).
fn ink_normalised(score: f32, tolerance: f32) -> f32 {
    geometry::normalised_geometry_score(score, tolerance.max(f32::MIN_POSITIVE))
}

/// Arguments of `guardian-lab outliers`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Model, test (enrolled) and calibration alphabets, shots, target and seed.
    #[command(flatten)]
    pub screen: ScreenArgs,
    /// The dataset.
    #[command(flatten)]
    pub data: DatasetArgs,
    /// Omniglot stroke root (for the Cartesian corruptions).
    #[command(flatten)]
    pub strokes: StrokesArgs,
    /// Calibration rounds.
    #[arg(long, default_value_t = 20)]
    pub calib_reps: usize,
    /// Test rounds (random enrollments).
    #[arg(long, default_value_t = 5)]
    pub reps: usize,
    /// Test drawings corrupted by every fault and severity.
    #[arg(long, default_value_t = 120)]
    pub sources: usize,
    /// Siamese baseline model (skipped if absent).
    #[arg(long)]
    pub siamese_model: Option<PathBuf>,
    /// Score `guardian` with the calibration records of this bank file (its embedding
    /// calibration and geometry calibration, e.g. the shipped cross-fitted bank) instead of
    /// calibrating on `--calib-alphabets` (the other methods still calibrate there).
    #[arg(long)]
    pub calibration_from: Option<PathBuf>,
    /// Replace the calibrated wrong-task tolerance of the guardian methods by this value
    /// (0: another enrolled class nearer than the claimed one is always no-go), keeping
    /// the calibrated thresholds, to measure what the tolerance buys.
    #[arg(long)]
    pub wrong_task_tolerance: Option<f32>,
    /// Near misses enrolled with every example for the `guardian-near-miss` method:
    /// `truncated:SHARE` (stopped with SHARE of its pen-down path left undrawn), `mirrored`,
    /// `mirrored-stroke` (one per stroke). None: the method is not measured.
    #[arg(long, value_delimiter = ',')]
    pub near_misses: Vec<NearMiss>,
    /// Share of the false-reject budget given to the near-miss step (taken from the
    /// embedding's share, or the geometry's with `--near-miss-from-geometry`).
    #[arg(long, default_value_t = 0.25)]
    pub near_miss_share: f32,
    /// Take the near-miss share from the geometry check's share instead of the embedding's.
    #[arg(long)]
    pub near_miss_from_geometry: bool,
    /// The near-miss score: `margin` (distance to the class minus distance to the nearest
    /// near miss), `spread` (that over the class's spread), `ratio` (the two distances'
    /// ratio).
    #[arg(long, value_enum, default_value_t = NearMissForm::Margin)]
    pub near_miss_form: NearMissForm,
    /// Measure the `guardian-ink` method: the full decision and the ink step.
    #[arg(long)]
    pub ink: bool,
    /// Share of the false-reject budget given to the ink step (taken from the geometry's,
    /// or the embedding's with `--ink-from-embedding`).
    #[arg(long, default_value_t = 0.25)]
    pub ink_share: f32,
    /// Quantile of the point-to-ink distances the ink distance takes.
    #[arg(long, default_value_t = 0.9)]
    pub ink_quantile: f32,
    /// Compare inks with their bounding boxes centred (position left to the geometry).
    #[arg(long)]
    pub ink_centred: bool,
    /// Take the ink share from the embedding's share instead of the geometry's.
    #[arg(long)]
    pub ink_from_embedding: bool,
    /// Directory for ROC curves and score histograms (PNG) and the raw scores (JSON).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object (otherwise a markdown table).
    #[arg(long)]
    pub json: bool,
}

/// A near miss of a plan (`guardian_robot::variant`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NearMiss {
    /// Stopped with this share of its pen-down path undrawn.
    Truncated(f64),
    /// Mirrored left-right.
    Mirrored,
    /// One stroke mirrored left-right (one near miss per stroke).
    MirroredStroke,
}

/// How the near-miss step compares a plan's distance to its class (`d_c`) with its distance
/// to the nearest near miss of the class (`d_n`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum NearMissForm {
    /// `d_c - d_n`.
    Margin,
    /// `(d_c - d_n) / spread` (the class's spread; the margin without one).
    Spread,
    /// `d_c / d_n`.
    Ratio,
}

/// The near misses of one kind for every plan of a pool, embedded.
type NearVectors = (NearMiss, Vec<Vec<Vec<f32>>>);

impl std::str::FromStr for NearMiss {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.split_once(':') {
            None if s == "mirrored" => Ok(Self::Mirrored),
            None if s == "mirrored-stroke" => Ok(Self::MirroredStroke),
            Some(("truncated", v)) => match v.parse::<f64>() {
                Ok(x) if x > 0.0 && x < 1.0 => Ok(Self::Truncated(x)),
                _ => Err(format!("truncated share {v:?} is not in (0, 1)")),
            },
            _ => Err(format!(
                "{s:?}: expected truncated:SHARE, mirrored or mirrored-stroke"
            )),
        }
    }
}

impl NearMiss {
    /// The near misses of `x` that can be made.
    fn of(self, robot: &guardian_robot::kinematics::Robot, x: &Resampled) -> Vec<Resampled> {
        use guardian_robot::variant;
        match self {
            Self::Truncated(share) => variant::truncated(robot, x, share)
                .ok()
                .into_iter()
                .collect(),
            Self::Mirrored => variant::mirrored(robot, x).ok().into_iter().collect(),
            Self::MirroredStroke => (0..variant::strokes(x).len())
                .filter_map(|k| variant::mirrored_stroke(robot, x, k).ok())
                .collect(),
        }
    }

    /// Several near misses per plan, each kept (not averaged over the support).
    fn per_stroke(self) -> bool {
        self == Self::MirroredStroke
    }
}

/// Figures of one fault at one severity.
#[derive(Debug, Clone, Serialize)]
pub struct FaultFigures {
    /// `wrong-task`, `unknown-task` or a [`Fault`] name.
    pub fault: String,
    /// Severity.
    pub severity: f64,
    /// Faulty plans scored.
    pub n: usize,
    /// AUROC faulty vs genuine.
    pub auroc: f64,
    /// TPR at 1 % FPR.
    pub tpr_at_1pct_fpr: f64,
    /// Share of faulty plans with a no-go at the calibrated threshold.
    pub detection: f64,
}

/// One method's results.
#[derive(Debug, Clone, Serialize)]
pub struct MethodReport {
    /// Method.
    pub method: Method,
    /// Its calibration (on the calibration alphabets).
    pub calibration: Calibration,
    /// The geometry calibration (`guardian` only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub geometry_calibration: Option<GeometryCalibration>,
    /// Genuine plans scored.
    pub genuine: usize,
    /// Share of genuine plans with a no-go at the calibrated threshold.
    pub genuine_false_reject: f64,
    /// Per fault and severity.
    pub faults: Vec<FaultFigures>,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct OutliersReport {
    /// Shipped model version.
    pub model_version: String,
    /// Test alphabets.
    pub alphabets: Vec<String>,
    /// Calibration alphabets.
    pub calib_alphabets: Vec<String>,
    /// Shots.
    pub shots: usize,
    /// Test rounds.
    pub reps: usize,
    /// Corrupted sources that solved for every fault / severity, per fault.
    pub sources: BTreeMap<String, usize>,
    /// Per method.
    pub methods: Vec<MethodReport>,
}

type Key = (String, u32); // (fault name, severity x 100)

/// Raw scores of one method: genuine and per fault key.
#[derive(Debug, Default, Clone, Serialize)]
pub struct Scores {
    /// Genuine plan scores.
    pub genuine: Vec<f32>,
    /// Faulty plan scores per `fault@severity`.
    pub faulty: BTreeMap<String, Vec<f32>>,
}

fn pool_data_indices(data: &Dataset, alphabets: &[String]) -> anyhow::Result<Vec<usize>> {
    let ids = data.alphabet_ids(alphabets)?;
    Ok((0..data.len())
        .filter(|&i| ids.contains(&data.alphabet_ids[i]))
        .collect())
}

/// Run `guardian-lab outliers`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let report = measure(args)?;
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{}", markdown(&report));
    }
    Ok(())
}

/// The figures of `guardian-lab outliers` (and the files of `--out`), not printed.
pub fn measure(args: &Args) -> anyhow::Result<OutliersReport> {
    let data = Dataset::load(&args.data.dataset)?;
    // Pen paths by the forward kinematics of the robot that drew the data set.
    let robot = data.robot()?;
    let model = crate::dataset::model_for(&data, &args.screen.model)?;
    args.screen.check_disjoint()?;
    let cpool = Pool::new(&data, &args.screen.calib_alphabets)?;
    let pool = Pool::new(&data, &args.screen.alphabets)?;
    let didx = pool_data_indices(&data, &args.screen.alphabets)?;
    anyhow::ensure!(didx.len() == pool.xs.len(), "pool index mismatch");

    // Corruption sources.
    let index = StrokeIndex::scan(&args.strokes.strokes)?;
    let mut rng = StdRng::seed_from_u64(args.screen.seed);
    let mut order: Vec<usize> = (0..pool.xs.len()).collect();
    order.shuffle(&mut rng);
    order.truncate(args.sources);
    let solver = PathSolver::new(&data.geometry)?;
    let mut jobs = Vec::new();
    for (si, &p) in order.iter().enumerate() {
        for f in Fault::ALL {
            for (k, &s) in SEVERITIES.iter().enumerate() {
                jobs.push((
                    si,
                    p,
                    f,
                    s,
                    args.screen.seed ^ ((si as u64) << 16 | (k as u64) << 8),
                ));
            }
        }
    }
    let source_strokes: Vec<Option<Vec<strokes::Stroke>>> = order
        .iter()
        .map(|&p| index.strokes_of(&data, didx[p]))
        .collect();
    let t0 = std::time::Instant::now();
    let made: Vec<(usize, usize, Fault, f64, Option<Resampled>)> = jobs
        .par_iter()
        .map(|&(si, p, f, s, seed)| {
            let mut r = StdRng::seed_from_u64(seed ^ f as u64);
            let x = source_strokes[si]
                .as_ref()
                .and_then(|st| corrupt::corrupt(&solver, f, s, st, &mut r).ok());
            (si, p, f, s, x)
        })
        .collect();
    let mut sources: BTreeMap<String, usize> = BTreeMap::new();
    for (_, _, f, s, x) in &made {
        if x.is_some() && *s == corrupt::MODERATE {
            *sources.entry(f.name().to_owned()).or_default() += 1;
        }
    }
    eprintln!(
        "{} faulty plans solved of {} in {:.1} s",
        made.iter().filter(|m| m.4.is_some()).count(),
        made.len(),
        t0.elapsed().as_secs_f64()
    );
    let faulty: Vec<(usize, Key, Resampled)> = made
        .into_iter()
        .filter_map(|(_, p, f, s, x)| {
            x.map(|x| (p, (f.name().to_owned(), (s * 100.0).round() as u32), x))
        })
        .collect();
    let fxs: Vec<Resampled> = faulty.iter().map(|f| f.2).collect();

    // Vectors per method: calibration pool, test pool, faulty plans.
    // (method, calibration vectors, test vectors, faulty-plan vectors)
    type Vectors = Vec<Vec<f32>>;
    let mut methods: Vec<(Method, Vectors, Vectors, Vectors)> = Vec::new();
    // The check pipeline's embedding stage (the plans are resampled already): the embeddings
    // and the pen paths the plan geometry comes from.
    let embed = |m: &Embedder, xs: &[Resampled]| -> anyhow::Result<Vec<Embedded>> {
        let mut out = Vec::with_capacity(xs.len());
        for c in xs.chunks(256) {
            out.extend(check::embed_resampled(m, &pool.robot, c)?);
        }
        Ok(out)
    };
    let vectors =
        |es: &[Embedded]| -> Vectors { es.iter().map(|e| e.embedding.to_vec()).collect() };
    let (ec, et, ef) = (
        embed(&model, &cpool.xs)?,
        embed(&model, &pool.xs)?,
        embed(&model, &fxs)?,
    );
    let (gc, gt, gf) = (vectors(&ec), vectors(&et), vectors(&ef));
    methods.push((Method::Guardian, gc.clone(), gt.clone(), gf.clone()));
    if !args.near_misses.is_empty() {
        methods.push((Method::GuardianNearMiss, gc.clone(), gt.clone(), gf.clone()));
    }
    if args.ink {
        methods.push((Method::GuardianInk, gc.clone(), gt.clone(), gf.clone()));
    }
    methods.push((Method::GuardianEmbedding, gc, gt, gf));
    // The near misses of every calibration and test plan, embedded: [kind][plan].
    let near_of = |xs: &[Resampled]| -> anyhow::Result<Vec<NearVectors>> {
        let mut out = Vec::new();
        for k in &args.near_misses {
            let t0 = std::time::Instant::now();
            let made: Vec<Vec<Resampled>> = xs.par_iter().map(|x| k.of(&robot, x)).collect();
            let t1 = t0.elapsed();
            let all: Vec<Resampled> = made.iter().flatten().copied().collect();
            let mut vecs = vectors(&embed(&model, &all)?).into_iter();
            eprintln!(
                "near miss {k:?}: {} of {} plans, made in {:.3} s, embedded in {:.3} s ({} threads)",
                all.len(),
                xs.len(),
                t1.as_secs_f64(),
                (t0.elapsed() - t1).as_secs_f64(),
                rayon::current_num_threads()
            );
            out.push((
                *k,
                made.iter()
                    .map(|m| vecs.by_ref().take(m.len()).collect())
                    .collect(),
            ));
        }
        Ok(out)
    };
    let (cnear, tnear) = (near_of(&cpool.xs)?, near_of(&pool.xs)?);
    // Plan geometry of every plan (from its pen path), workcell score of every test and
    // faulty plan.
    let geo_of = |es: &[Embedded]| -> Vec<Option<PlanGeometry>> {
        es.iter().map(Embedded::geometry).collect()
    };
    let cell = Workcell::default();
    let wc_of = |xs: &[Resampled]| -> Vec<f32> {
        xs.par_iter()
            .map(|x| workcell::inspect_with(&robot, &cell, x).map_or(f32::INFINITY, |i| i.score))
            .collect()
    };
    let (cgeo, tgeo, fgeo) = (geo_of(&ec), geo_of(&et), geo_of(&ef));
    // The ink of every plan, only for the ink step (one `None` per plan otherwise).
    let ink_of = |es: &[Embedded]| -> Vec<Option<Ink>> {
        es.iter()
            .map(|e| {
                let ink = args.ink.then(|| Ink::of_path(&e.path)).flatten()?;
                Some(if args.ink_centred { ink.centred() } else { ink })
            })
            .collect()
    };
    let (cink, tink, fink) = (ink_of(&ec), ink_of(&et), ink_of(&ef));
    let (twc, fwc) = (wc_of(&pool.xs), wc_of(&fxs));
    let scales = {
        let groups: Vec<Vec<PlanGeometry>> = crate::eval::calibration::by_class(&cpool.labels)
            .iter()
            .map(|idx| idx.iter().filter_map(|&i| cgeo[i]).collect())
            .collect();
        geometry::pooled_scales(&groups).context("no geometry spread on the calibration data")?
    };
    if let Some(p) = &args.siamese_model {
        let s = crate::dataset::model_for(&data, p)?;
        methods.push((
            Method::Siamese,
            vectors(&embed(&s, &cpool.xs)?),
            vectors(&embed(&s, &pool.xs)?),
            vectors(&embed(&s, &fxs)?),
        ));
    }
    {
        let all: Vec<Resampled> = cpool
            .xs
            .iter()
            .chain(&pool.xs)
            .chain(&fxs)
            .copied()
            .collect();
        let mut v = standardised_raw(&all, pool.joints);
        let f = v.split_off(cpool.xs.len() + pool.xs.len());
        let t = v.split_off(cpool.xs.len());
        methods.push((Method::Knn, v, t, f));
    }

    let alphabet_of: Vec<&str> = pool
        .class_names
        .iter()
        .map(|n| n.split('/').next().unwrap_or(""))
        .collect();
    let nclass = pool.class_names.len();
    let mut reports = Vec::new();
    let mut raw: BTreeMap<String, Scores> = BTreeMap::new();
    for (method, cv, tv, fv) in &methods {
        let full = matches!(
            method,
            Method::Guardian | Method::GuardianNearMiss | Method::GuardianInk
        );
        let nm = *method == Method::GuardianNearMiss;
        let ik = *method == Method::GuardianInk;
        let nm_share = if nm {
            args.near_miss_share
        } else if ik {
            args.ink_share
        } else {
            0.0
        };
        let space_method = match method {
            Method::GuardianEmbedding | Method::GuardianNearMiss | Method::GuardianInk => {
                Method::Guardian
            }
            m => *m,
        };
        // Calibration.
        let cspace = Space {
            method: space_method,
            vecs: cv,
        };
        let mut crng = StdRng::seed_from_u64(args.screen.seed);
        let mut gs = Vec::new();
        let mut ggeo = Vec::new();
        // The extra step's score of every calibration plan: the near-miss margin, or the
        // ink score for the ink step.
        let mut gnear = Vec::new();
        for _ in 0..args.calib_reps {
            let (support, queries) = split(&cpool.labels, args.screen.shots, &mut crng);
            let e = cspace
                .enroll_near(
                    &support,
                    full.then_some(cgeo.as_slice()),
                    nm.then_some(cnear.as_slice()),
                )
                .with_ink(&support, ik.then_some(cink.as_slice()));
            for q in queries {
                let d = e.distances(space_method, &cv[q]);
                let c = cpool.labels[q] as usize;
                gs.push(e.genuine(&d, c));
                ggeo.push(e.geometry_score(cgeo[q].as_ref(), c, &scales));
                gnear.push(if ik {
                    e.ink_score(cink[q].as_ref(), c, args.ink_quantile)
                } else {
                    e.near_miss_margin(&cv[q], c, args.near_miss_form)
                });
            }
        }
        let emb_target = if full {
            let from_emb =
                if (nm && args.near_miss_from_geometry) || (ik && !args.ink_from_embedding) {
                    0.0
                } else {
                    nm_share
                };
            args.screen.target_frr * (1.0 - args.screen.geometry_share - from_emb)
        } else {
            args.screen.target_frr
        };
        let mut cal = bank::calibrate(&gs, emb_target, &format!("{method:?}"))
            .context("calibration failed")?;
        let from_bank = match (&args.calibration_from, full) {
            (Some(p), true) => {
                let b = ClassBank::load(p).with_context(|| format!("loading {}", p.display()))?;
                let c = b
                    .calibration()
                    .cloned()
                    .with_context(|| format!("{} has no calibration record", p.display()))?;
                cal = c;
                Some(b.geometry_calibration().cloned())
            }
            _ => None,
        };
        if let (
            Some(t),
            Method::Guardian
            | Method::GuardianEmbedding
            | Method::GuardianNearMiss
            | Method::GuardianInk,
        ) = (args.wrong_task_tolerance, method)
        {
            cal.wrong_task_tolerance = Some(t);
        }
        let gcal = if let Some(g) = from_bank {
            g
        } else if full {
            Some(
                bank::calibrate_geometry(
                    &gs,
                    &ggeo,
                    &cal,
                    args.screen.target_frr * (1.0 - nm_share),
                    scales,
                    &format!("geometry share {}", args.screen.geometry_share),
                )
                .context("geometry calibration failed")?,
            )
        } else {
            None
        };
        let gcal = gcal.as_ref();
        // The near-miss (or ink) tolerance: what the embedding and geometry rules leave of
        // the whole budget goes to the near-miss margin (or the ink score), on the plans they
        // accept.
        let near_tol = if nm || ik {
            let budget = (f64::from(args.screen.target_frr) * gs.len() as f64).floor() as usize;
            let mut used = 0;
            let mut kept = Vec::new();
            for ((g, geo), m) in gs.iter().zip(&ggeo).zip(&gnear) {
                let gs_ = full_score(score(g, &cal), *geo, gcal, 0.0);
                if gs_ > 1.0 {
                    used += 1;
                } else if let Some(m) = m {
                    kept.push(*m);
                }
            }
            let t =
                bank::threshold_allowing(&kept, budget.saturating_sub(used)).unwrap_or(f32::MAX);
            eprintln!(
                "{} tolerance {t:.4} ({used} of {} genuine plans rejected before it, budget {budget})",
                if ik { "ink" } else { "near-miss" },
                gs.len()
            );
            Some(t)
        } else {
            None
        };
        // The geometry scales the threshold was chosen with (the calibration alphabets', or
        // the bank's with `--calibration-from`).
        let tscales = gcal.map_or(scales, |g| g.scales);
        // The method's score of a plan claiming class c.
        let plan_score = |e: &Enrolled,
                          q: &[f32],
                          d: &[f32],
                          c: usize,
                          g: Option<&PlanGeometry>,
                          ink: Option<&Ink>,
                          wc: f32| {
            let s = score(&e.genuine(d, c), &cal);
            if !full {
                return s;
            }
            let f = full_score(s, e.geometry_score(g, c, &tscales), gcal, wc);
            if ik {
                return match (near_tol, e.ink_score(ink, c, args.ink_quantile)) {
                    (Some(t), Some(m)) => f.max(ink_normalised(m, t)),
                    _ => f,
                };
            }
            match (near_tol, e.near_miss_margin(q, c, args.near_miss_form)) {
                (Some(t), Some(m)) => f.max(1.0 + (m - t)),
                _ => f,
            }
        };
        // Test rounds.
        let tspace = Space {
            method: space_method,
            vecs: tv,
        };
        let mut sc = Scores::default();
        let mut trng = StdRng::seed_from_u64(args.screen.seed.wrapping_add(1));
        for _ in 0..args.reps {
            let (mut support, queries) = split(&pool.labels, args.screen.shots, &mut trng);
            let mut classes: Vec<usize> = (0..nclass).collect();
            classes.shuffle(&mut trng);
            let unknown: Vec<usize> = classes[..nclass / 4].to_vec();
            for &u in &unknown {
                support[u].clear();
            }
            let e = tspace
                .enroll_near(
                    &support,
                    full.then_some(tgeo.as_slice()),
                    nm.then_some(tnear.as_slice()),
                )
                .with_ink(&support, ik.then_some(tink.as_slice()));
            let enrolled: Vec<usize> = (0..nclass).filter(|c| !support[*c].is_empty()).collect();
            // Nearest enrolled prototype of each class (in this method's space), by the
            // mean of all its drawings for never-enrolled classes.
            let centre = |c: usize| -> Vec<f32> {
                let rows: Vec<&Vec<f32>> = (0..tv.len())
                    .filter(|&i| pool.labels[i] as usize == c)
                    .map(|i| &tv[i])
                    .collect();
                mean_of(&rows)
            };
            let centres: Vec<Vec<f32>> = (0..nclass).map(centre).collect();
            let nearest_other = |c: usize| -> usize {
                enrolled
                    .iter()
                    .copied()
                    .filter(|&o| o != c)
                    .min_by(|&a, &b| {
                        bank::distance(&centres[c], &centres[a])
                            .total_cmp(&bank::distance(&centres[c], &centres[b]))
                    })
                    .unwrap_or(c)
            };
            let pick = |c: usize, sev: u32, r: &mut StdRng| -> usize {
                let others: Vec<usize> = match sev {
                    25 => vec![nearest_other(c)],
                    50 => enrolled
                        .iter()
                        .copied()
                        .filter(|&o| o != c && alphabet_of[o] == alphabet_of[c])
                        .collect(),
                    _ => enrolled.iter().copied().filter(|&o| o != c).collect(),
                };
                others.choose(r).copied().unwrap_or(c)
            };
            let supports: std::collections::HashSet<usize> =
                support.iter().flatten().copied().collect();
            for &q in &queries {
                let c = pool.labels[q] as usize;
                let d = e.distances(space_method, &tv[q]);
                let (g, ink, wc) = (tgeo[q].as_ref(), tink[q].as_ref(), twc[q]);
                if unknown.contains(&c) {
                    for sev in [25u32, 50, 100] {
                        let claim = pick(c, sev, &mut trng);
                        sc.faulty
                            .entry(format!("unknown-task@{sev}"))
                            .or_default()
                            .push(plan_score(&e, &tv[q], &d, claim, g, ink, wc));
                    }
                    continue;
                }
                sc.genuine.push(plan_score(&e, &tv[q], &d, c, g, ink, wc));
                for sev in [25u32, 50, 100] {
                    let claim = pick(c, sev, &mut trng);
                    if claim == c {
                        continue;
                    }
                    sc.faulty
                        .entry(format!("wrong-task@{sev}"))
                        .or_default()
                        .push(plan_score(&e, &tv[q], &d, claim, g, ink, wc));
                }
            }
            for (k, (p, key, _)) in faulty.iter().enumerate() {
                let c = pool.labels[*p] as usize;
                if supports.contains(p) || support[c].is_empty() {
                    continue;
                }
                let d = e.distances(space_method, &fv[k]);
                sc.faulty
                    .entry(format!("{}@{}", key.0, key.1))
                    .or_default()
                    .push(plan_score(
                        &e,
                        &fv[k],
                        &d,
                        c,
                        fgeo[k].as_ref(),
                        fink[k].as_ref(),
                        fwc[k],
                    ));
            }
        }
        let mut figs = Vec::new();
        for (k, v) in &sc.faulty {
            let (name, sev) = k.split_once('@').unwrap_or((k, "0"));
            figs.push(FaultFigures {
                fault: name.to_owned(),
                severity: sev.parse::<f64>().unwrap_or(0.0) / 100.0,
                n: v.len(),
                auroc: auroc(&sc.genuine, v),
                tpr_at_1pct_fpr: tpr_at_fpr(&sc.genuine, v, 0.01),
                detection: share_above(v, 1.0),
            });
        }
        figs.sort_by(|a, b| {
            a.fault
                .cmp(&b.fault)
                .then(a.severity.total_cmp(&b.severity))
        });
        reports.push(MethodReport {
            method: *method,
            calibration: cal.clone(),
            geometry_calibration: gcal.cloned(),
            genuine: sc.genuine.len(),
            genuine_false_reject: share_above(&sc.genuine, 1.0),
            faults: figs,
        });
        let key = serde_json::to_value(method)?
            .as_str()
            .map_or_else(|| format!("{method:?}").to_lowercase(), str::to_owned);
        raw.insert(key, sc);
    }
    let report = OutliersReport {
        model_version: model.version().to_owned(),
        alphabets: args.screen.alphabets.clone(),
        calib_alphabets: args.screen.calib_alphabets.clone(),
        shots: args.screen.shots,
        reps: args.reps,
        sources,
        methods: reports,
    };
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)?;
        std::fs::write(dir.join("scores.json"), serde_json::to_vec(&raw)?)?;
        std::fs::write(
            dir.join("outliers.json"),
            serde_json::to_vec_pretty(&report)?,
        )?;
        crate::eval::report::outlier_plots(
            dir,
            raw.iter()
                .map(|(m, sc)| (m.as_str(), sc.genuine.as_slice(), &sc.faulty)),
        )?;
    }
    Ok(report)
}

/// The report as markdown tables (one per method).
pub fn markdown(r: &OutliersReport) -> String {
    let mut s = String::new();
    for m in &r.methods {
        s.push_str(&format!(
            "\n### {:?} (genuine false-reject {:.4} of {}; calibration target {:?}, measured on calibration {:?})\n\n",
            m.method,
            m.genuine_false_reject,
            m.genuine,
            m.calibration.target_rate,
            m.calibration.measured_rate
        ));
        s.push_str(
            "| fault | severity | n | AUROC | TPR@1%FPR | detection |\n|---|---|---|---|---|---|\n",
        );
        for f in &m.faults {
            s.push_str(&format!(
                "| {} | {} | {} | {:.4} | {:.4} | {:.4} |\n",
                f.fault, f.severity, f.n, f.auroc, f.tpr_at_1pct_fpr, f.detection
            ));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_misses_parse_and_bad_ones_are_refused() {
        let ok = |s: &str| s.parse::<NearMiss>().expect(s);
        assert_eq!(ok("truncated:0.2"), NearMiss::Truncated(0.2));
        assert_eq!(ok("mirrored"), NearMiss::Mirrored);
        assert_eq!(ok("mirrored-stroke"), NearMiss::MirroredStroke);
        for bad in [
            "truncated:0",
            "truncated:1",
            "truncated:x",
            "truncated",
            "shifted",
            "",
        ] {
            assert!(bad.parse::<NearMiss>().is_err(), "{bad:?} parsed");
        }
    }

    /// The near-miss margin is > 0 exactly when the plan is nearer to a near miss of its
    /// class than to the class, in every form (the ratio > 1).
    #[test]
    fn the_near_miss_margin_says_which_the_plan_is_nearer_to() {
        let e = Enrolled {
            geometry: vec![Vec::new()],
            protos: vec![vec![1.0, 0.0]],
            support: vec![vec![vec![1.0, 0.0]]],
            spread: vec![Some(0.5)],
            near: vec![vec![vec![0.0, 1.0], vec![0.0, -1.0]]],
            ink: Vec::new(),
        };
        let near_class = [0.9f32, 0.1];
        let near_miss = [0.1f32, 0.9];
        for form in [NearMissForm::Margin, NearMissForm::Spread] {
            assert!(e.near_miss_margin(&near_class, 0, form).unwrap() < 0.0);
            assert!(e.near_miss_margin(&near_miss, 0, form).unwrap() > 0.0);
        }
        assert!(
            e.near_miss_margin(&near_class, 0, NearMissForm::Ratio)
                .unwrap()
                < 1.0
        );
        assert!(
            e.near_miss_margin(&near_miss, 0, NearMissForm::Ratio)
                .unwrap()
                > 1.0
        );
        let bare = Enrolled {
            near: vec![Vec::new()],
            ..e
        };
        assert_eq!(
            bare.near_miss_margin(&near_miss, 0, NearMissForm::Margin),
            None
        );
    }

    /// The ink step scores a plan against the nearest enrolled example's ink; a plan that
    /// draws nothing against a class that draws is infinitely far, and a class without ink
    /// has no ink score; over the tolerance exactly when the score exceeds it.
    #[test]
    fn the_ink_step_takes_the_nearest_example_and_never_passes_no_ink() {
        let ink = |pts: &[[f32; 2]]| {
            let path: Vec<[f32; 3]> = pts.iter().map(|p| [p[0], p[1], 1.0]).collect();
            Ink::of_path(&path).unwrap()
        };
        let horizontal = ink(&[[0.0, 0.0], [0.04, 0.0]]);
        let vertical = ink(&[[0.0, 0.0], [0.0, 0.04]]);
        let e = Enrolled {
            geometry: vec![Vec::new(), Vec::new()],
            protos: vec![Vec::new(), Vec::new()],
            support: vec![Vec::new(), Vec::new()],
            spread: vec![None, None],
            near: Vec::new(),
            ink: vec![vec![horizontal.clone(), vertical], Vec::new()],
        };
        let shorter = ink(&[[0.0, 0.0], [0.03, 0.0]]);
        let s = e.ink_score(Some(&shorter), 0, 1.0).unwrap();
        assert!((s - 0.01).abs() < 1e-6, "{s}");
        assert_eq!(e.ink_score(Some(&horizontal), 0, 1.0), Some(0.0));
        assert_eq!(e.ink_score(None, 0, 1.0), Some(f32::INFINITY));
        assert_eq!(e.ink_score(Some(&shorter), 1, 1.0), None);
        assert!(ink_normalised(0.011, 0.01) > 1.0);
        assert!(ink_normalised(0.01, 0.01) <= 1.0);
        assert!(ink_normalised(f32::NAN, 0.01) > 1.0);
    }

    #[test]
    fn score_above_one_is_the_bank_decision() {
        let cal = Calibration {
            method: "t".into(),
            samples: 1,
            target_rate: None,
            note: String::new(),
            global_threshold: Some(0.5),
            class_scale: None,
            wrong_task_tolerance: Some(0.1),
            measured_rate: None,
        };
        let g = |c, o| GenuineScore {
            claimed: c,
            nearest_other: Some(o),
            spread: None,
        };
        assert!(score(&g(0.4, 1.0), &cal) <= 1.0);
        assert!(score(&g(0.6, 1.0), &cal) > 1.0);
        assert!(score(&g(0.4, 0.25), &cal) > 1.0);
        assert!(score(&g(0.4, 0.35), &cal) <= 1.0);
    }
}
