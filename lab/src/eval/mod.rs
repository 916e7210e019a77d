//! Few-shot evaluation: N-way K-shot episodes over the classes of the given alphabets, for
//! the trained embedder and the baselines (uniform random, 1-NN on raw trajectories,
//! Siamese network), with accuracy, its 95% confidence interval and the CMC curve.
//!
//! One episode: draw N distinct classes; for each, K support samples (distinct drawings);
//! draw the query's class uniformly among the N and a query drawing not in its support.
//! Embedding methods score a class by the squared distance from the query to the mean of
//! its K support embeddings (the prototype; with K = 1 the support itself); 1-NN scores a
//! class by the smallest L2 distance to its supports on per-channel standardised raw
//! trajectories; random scores are uniform. The rank of the true class (1 = best) gives
//! accuracy (rank 1) and the CMC curve (rank <= r). The 95% interval is the normal
//! approximation `1.96 * sqrt(p (1 - p) / episodes)` (episodes are independent).
//!
//! Beside the episodes: [`outliers`] (go / no-go on faulty plans), [`calibration`]
//! (thresholds for a target false-reject rate), [`metrics`] (AUROC, TPR at an FPR) and
//! [`report`] (the markdown + PNG report of a model).

pub mod calibration;
pub mod cell;
pub mod kfold;
pub mod metrics;
pub mod outliers;
pub mod report;

use std::path::PathBuf;

use guardian_models::embedder::{EMBED_DIM, Embedder};
use guardian_robot::kinematics::Robot;
use guardian_shared::trajectory::{Resampled, STEPS, TOOL};
use rand::rngs::StdRng;
use rand::seq::IndexedRandom;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use crate::cli::{DatasetArgs, EpisodeArgs};
use guardian_omniglot::dataset::Dataset;

/// Evaluation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EvalError {
    /// Too few classes or samples for the requested episodes.
    #[error("cannot draw {way}-way {shot}-shot episodes: {classes} classes have >= {need} samples")]
    TooFewClasses {
        /// Requested ways.
        way: usize,
        /// Requested shots.
        shot: usize,
        /// Classes with enough samples.
        classes: usize,
        /// Samples a class needs (shot + 1).
        need: usize,
    },
    /// The request is malformed (way < 2, shot < 1, no episodes, unknown alphabet).
    #[error("invalid evaluation request: {0}")]
    Invalid(String),
    /// Embedding failed.
    #[error("embedding: {0}")]
    Embed(#[from] guardian_models::embedder::EmbedError),
}

/// What episodes to draw.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct EpisodeSpec {
    /// Classes per episode (N).
    pub way: usize,
    /// Support samples per class (K).
    pub shot: usize,
    /// Number of episodes.
    pub episodes: usize,
    /// Seed of the episode draw.
    pub seed: u64,
}

impl EpisodeArgs {
    /// The episodes these arguments describe.
    pub fn spec(&self) -> EpisodeSpec {
        EpisodeSpec {
            way: self.way,
            shot: self.shot,
            episodes: self.episodes,
            seed: self.seed,
        }
    }
}

/// Result of a run of episodes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EpisodeResult {
    /// N.
    pub way: usize,
    /// K.
    pub shot: usize,
    /// Episodes run.
    pub episodes: usize,
    /// Fraction of episodes whose true class ranked first.
    pub accuracy: f64,
    /// Half-width of the 95% confidence interval of `accuracy`.
    pub ci95: f64,
    /// `cmc[r - 1]` = fraction of episodes whose true class ranked `<= r`, r = 1..N.
    pub cmc: Vec<f64>,
    /// `(true class, predicted class)` per episode (dense labels of the pool).
    #[serde(skip)]
    pub predictions: Vec<(u32, u32)>,
}

/// How classes are scored against a query (lower is closer).
#[derive(Debug)]
pub enum Scorer<'a> {
    /// Squared distance to the mean of the support embeddings.
    Prototype(&'a [Vec<f32>]),
    /// Smallest squared L2 distance to a support vector (1-NN over the supports).
    Nearest(&'a [Vec<f32>]),
    /// Uniform random scores.
    Random,
}

fn sq(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Run episodes over a pool of samples with dense class labels `labels` (every class in the
/// pool is eligible).
pub fn run_episodes(
    labels: &[u32],
    spec: &EpisodeSpec,
    scorer: &mut Scorer<'_>,
) -> Result<EpisodeResult, EvalError> {
    if spec.way < 2 || spec.shot < 1 || spec.episodes == 0 {
        return Err(EvalError::Invalid(format!(
            "way {} (>= 2), shot {} (>= 1), episodes {} (>= 1)",
            spec.way, spec.shot, spec.episodes
        )));
    }
    let n_classes = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
    let mut by_class: Vec<Vec<usize>> = vec![Vec::new(); n_classes];
    for (i, &l) in labels.iter().enumerate() {
        by_class[l as usize].push(i);
    }
    let eligible: Vec<usize> = (0..n_classes)
        .filter(|&c| by_class[c].len() > spec.shot)
        .collect();
    if eligible.len() < spec.way {
        return Err(EvalError::TooFewClasses {
            way: spec.way,
            shot: spec.shot,
            classes: eligible.len(),
            need: spec.shot + 1,
        });
    }
    let mut rng = StdRng::seed_from_u64(spec.seed);
    let mut rank_counts = vec![0usize; spec.way];
    let mut predictions = Vec::with_capacity(spec.episodes);
    let mut scores = vec![0.0f32; spec.way];
    let mut supports: Vec<Vec<usize>> = vec![Vec::new(); spec.way];
    for _ in 0..spec.episodes {
        let classes: Vec<usize> = eligible
            .choose_multiple(&mut rng, spec.way)
            .copied()
            .collect();
        let target = rng.random_range(0..spec.way);
        let mut query = 0;
        for (ci, &c) in classes.iter().enumerate() {
            let take = if ci == target {
                spec.shot + 1
            } else {
                spec.shot
            };
            let picked: Vec<usize> = by_class[c]
                .choose_multiple(&mut rng, take)
                .copied()
                .collect();
            if ci == target {
                query = picked[spec.shot];
            }
            supports[ci].clear();
            supports[ci].extend_from_slice(&picked[..spec.shot]);
        }
        for (s, sup) in scores.iter_mut().zip(&supports) {
            *s = match scorer {
                Scorer::Random => rng.random::<f32>(),
                Scorer::Prototype(e) => {
                    let q = &e[query];
                    let k = sup.len() as f32;
                    (0..q.len())
                        .map(|d| {
                            let p = sup.iter().map(|&j| e[j][d]).sum::<f32>() / k;
                            (q[d] - p) * (q[d] - p)
                        })
                        .sum()
                }
                Scorer::Nearest(v) => sup
                    .iter()
                    .map(|&j| sq(&v[query], &v[j]))
                    .fold(f32::INFINITY, f32::min),
            };
        }
        let t = scores[target];
        let better = scores.iter().filter(|&&s| s < t).count();
        let ties = scores.iter().filter(|&&s| s == t).count() - 1;
        // Ties are broken uniformly at random.
        let rank = better
            + if ties > 0 {
                rng.random_range(0..=ties)
            } else {
                0
            };
        rank_counts[rank] += 1;
        let best = scores
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))
            .map_or(0, |(i, _)| i);
        let pred = if rank == 0 { target } else { best };
        predictions.push((classes[target] as u32, classes[pred] as u32));
    }
    let e = spec.episodes as f64;
    let mut cmc = Vec::with_capacity(spec.way);
    let mut acc = 0usize;
    for c in &rank_counts {
        acc += c;
        cmc.push(acc as f64 / e);
    }
    let p = cmc[0];
    Ok(EpisodeResult {
        way: spec.way,
        shot: spec.shot,
        episodes: spec.episodes,
        accuracy: p,
        ci95: 1.96 * (p * (1.0 - p) / e).sqrt(),
        cmc,
        predictions,
    })
}

/// Per-channel standardised, flattened raw trajectories of a robot with `joints` joints
/// (the 1-NN baseline's vectors: its joints and the tool per step).
pub fn standardised_raw(xs: &[Resampled], joints: usize) -> Vec<Vec<f32>> {
    // The channels: the joint slots in use, then the tool.
    let slots: Vec<usize> = (0..joints).chain(std::iter::once(TOOL)).collect();
    let channels = slots.len();
    let mut mean = vec![0.0f64; channels];
    let mut var = vec![0.0f64; channels];
    let n = (xs.len() * STEPS).max(1) as f64;
    for x in xs {
        for w in x {
            for (c, &s) in slots.iter().enumerate() {
                mean[c] += f64::from(w[s]) / n;
            }
        }
    }
    for x in xs {
        for w in x {
            for (c, &s) in slots.iter().enumerate() {
                var[c] += (f64::from(w[s]) - mean[c]).powi(2) / n;
            }
        }
    }
    let sd: Vec<f64> = var.iter().map(|v| v.sqrt().max(1e-9)).collect();
    xs.iter()
        .map(|x| {
            x.iter()
                .flat_map(|w| {
                    slots
                        .iter()
                        .enumerate()
                        .map(|(c, &s)| ((f64::from(w[s]) - mean[c]) / sd[c]) as f32)
                })
                .collect()
        })
        .collect()
}

/// The evaluation pool: samples of the given alphabets with dense labels.
#[derive(Debug, Clone)]
pub struct Pool {
    /// Inputs.
    pub xs: Vec<Resampled>,
    /// Dense class label per sample.
    pub labels: Vec<u32>,
    /// Class name per dense label.
    pub class_names: Vec<String>,
    /// Alphabets in the pool.
    pub alphabets: Vec<String>,
    /// Joints of the robot that drew the samples.
    pub joints: usize,
    /// The robot that drew the samples (its forward kinematics gives the pen paths).
    pub robot: Robot,
}

impl Pool {
    /// Samples of `alphabets` (all alphabets if empty).
    pub fn new(data: &Dataset, alphabets: &[String]) -> Result<Self, EvalError> {
        let names: Vec<String> = if alphabets.is_empty() {
            data.alphabets.clone()
        } else {
            alphabets.to_vec()
        };
        let ids = data
            .alphabet_ids(&names)
            .map_err(|e| EvalError::Invalid(e.to_string()))?;
        let mut map = std::collections::BTreeMap::new();
        let mut pool = Pool {
            xs: Vec::new(),
            labels: Vec::new(),
            class_names: Vec::new(),
            alphabets: names,
            joints: data.robot.joints,
            robot: data
                .robot()
                .map_err(|e| EvalError::Invalid(e.to_string()))?,
        };
        for i in 0..data.len() {
            if !ids.contains(&data.alphabet_ids[i]) {
                continue;
            }
            let next = map.len();
            let l = *map.entry(data.labels[i]).or_insert(next);
            if l == pool.class_names.len() {
                let name = usize::try_from(data.labels[i])
                    .ok()
                    .and_then(|c| data.classes.get(c))
                    .cloned()
                    .unwrap_or_default();
                pool.class_names.push(name);
            }
            pool.xs.push(data.trajectories[i]);
            pool.labels.push(l as u32);
        }
        Ok(pool)
    }

    /// Embeddings of every sample by `model`.
    pub fn embed(&self, model: &Embedder) -> Result<Vec<Vec<f32>>, EvalError> {
        let mut out = Vec::with_capacity(self.xs.len());
        for chunk in self.xs.chunks(256) {
            out.extend(
                model
                    .embed_batch(&self.robot, chunk)?
                    .into_iter()
                    .map(|e: [f32; EMBED_DIM]| e.to_vec()),
            );
        }
        Ok(out)
    }
}

/// Which method `eval` scores.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Baseline {
    /// Uniform random ranking.
    Random,
    /// 1-NN on per-channel standardised raw trajectories (L2).
    Knn,
    /// The Siamese (contrastive) network given by `--siamese-model`.
    Siamese,
}

/// `guardian-lab eval`: N-way K-shot episodes on a dataset.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Trained embedder (triplet model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The dataset.
    #[command(flatten)]
    pub data: DatasetArgs,
    /// Alphabets to draw classes from, comma-separated (default: every alphabet).
    #[arg(long, value_delimiter = ',')]
    pub alphabets: Vec<String>,
    /// N-way K-shot episodes and their seed.
    #[command(flatten)]
    pub episodes: EpisodeArgs,
    /// Evaluate a baseline instead of the model.
    #[arg(long, value_enum)]
    pub baseline: Option<Baseline>,
    /// The Siamese model for `--baseline siamese` (default: `siamese.safetensors` beside
    /// `--model`).
    #[arg(long)]
    pub siamese_model: Option<PathBuf>,
    /// Force test-time reverse averaging on (see `NetConfig::reverse_average`).
    #[arg(long)]
    pub reverse_average: bool,
    /// Force test-time reverse averaging off.
    #[arg(long, conflicts_with = "reverse_average")]
    pub no_reverse_average: bool,
    /// Test-time views averaged with the plan's own (see `NetConfig::test_views`),
    /// comma-separated, each `r<mrad>`, `s<shear>`, `x<stretch>` (thousandths), joined by `+`:
    /// e.g. `r100,r-100`; `none` for none. Replaces the model's own.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub test_views: Option<Vec<String>>,
    /// Also report every class as the query's class: its accuracy and the classes it was
    /// taken for, most frequent first (e.g. to see which characters an alphabet confuses).
    #[arg(long)]
    pub per_class: bool,
    /// Print one JSON object (otherwise a short text summary).
    #[arg(long)]
    pub json: bool,
}

/// A full evaluation line.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Method: `triplet`, `siamese`, `knn`, `random`.
    pub method: String,
    /// Model version (embedding methods).
    pub model_version: Option<String>,
    /// Alphabets the classes were drawn from.
    pub alphabets: Vec<String>,
    /// Classes in the pool.
    pub classes: usize,
    /// Seed.
    pub seed: u64,
    /// The result.
    #[serde(flatten)]
    pub result: EpisodeResult,
    /// Every class that was a query's class (`--per-class`), worst first.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub per_class: Vec<ClassResult>,
}

/// The episodes whose query was of one class.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClassResult {
    /// The class's name.
    pub class: String,
    /// Episodes whose query was of this class.
    pub queries: usize,
    /// The fraction of them answered with this class.
    pub accuracy: f64,
    /// Every class answered instead, with the number of these episodes, most frequent
    /// first (ties by name; empty if every answer was right).
    pub confused_with: Vec<(String, usize)>,
}

/// Per query class: accuracy and the wrong answers, worst class first (ties by
/// name). `predictions` are `(true, predicted)` dense labels, `names` their class names.
pub fn per_class(predictions: &[(u32, u32)], names: &[String]) -> Vec<ClassResult> {
    let mut counts: std::collections::BTreeMap<u32, std::collections::BTreeMap<u32, usize>> =
        Default::default();
    for &(t, p) in predictions {
        *counts.entry(t).or_default().entry(p).or_default() += 1;
    }
    let name = |l: u32| {
        names
            .get(l as usize)
            .cloned()
            .unwrap_or_else(|| l.to_string())
    };
    let mut out: Vec<ClassResult> = counts
        .into_iter()
        .map(|(t, answers)| {
            let queries = answers.values().sum::<usize>();
            let right = answers.get(&t).copied().unwrap_or(0);
            let mut confused_with: Vec<(String, usize)> = answers
                .iter()
                .filter(|&(&p, _)| p != t)
                .map(|(&p, &n)| (name(p), n))
                .collect();
            confused_with.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
            ClassResult {
                class: name(t),
                queries,
                accuracy: right as f64 / queries as f64,
                confused_with,
            }
        })
        .collect();
    out.sort_by(|a, b| {
        a.accuracy
            .total_cmp(&b.accuracy)
            .then(a.class.cmp(&b.class))
    });
    out
}

/// Evaluate one method on a pool.
pub fn evaluate(
    pool: &Pool,
    method: Option<Baseline>,
    model: Option<&Embedder>,
    spec: &EpisodeSpec,
) -> Result<EvalReport, EvalError> {
    let (name, version, result) = match method {
        Some(Baseline::Random) => (
            "random",
            None,
            run_episodes(&pool.labels, spec, &mut Scorer::Random)?,
        ),
        Some(Baseline::Knn) => {
            let v = standardised_raw(&pool.xs, pool.joints);
            (
                "knn",
                None,
                run_episodes(&pool.labels, spec, &mut Scorer::Nearest(&v))?,
            )
        }
        Some(Baseline::Siamese) | None => {
            let model = model.ok_or_else(|| EvalError::Invalid("a model is required".into()))?;
            let e = pool.embed(model)?;
            let name = if method.is_some() {
                "siamese"
            } else {
                "triplet"
            };
            (
                name,
                Some(model.version().to_string()),
                run_episodes(&pool.labels, spec, &mut Scorer::Prototype(&e))?,
            )
        }
    };
    Ok(EvalReport {
        method: name.into(),
        model_version: version,
        alphabets: pool.alphabets.clone(),
        classes: pool.class_names.len(),
        seed: spec.seed,
        result,
        per_class: Vec::new(),
    })
}

/// Run `guardian-lab eval`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let data = Dataset::load(&args.data.dataset)?;
    let pool = Pool::new(&data, &args.alphabets)?;
    let mut model = match (args.baseline, &args.model) {
        (Some(Baseline::Siamese), m) => {
            let path = match (&args.siamese_model, m) {
                (Some(p), _) => p.clone(),
                (None, Some(m)) => m.with_file_name("siamese.safetensors"),
                (None, None) => {
                    anyhow::bail!("--baseline siamese needs --siamese-model or --model")
                }
            };
            Some(crate::dataset::model_for(&data, &path)?)
        }
        (None, Some(m)) => Some(crate::dataset::model_for(&data, m)?),
        (None, None) => anyhow::bail!("--model is required unless --baseline random|knn"),
        (Some(_), _) => None,
    };
    if let Some(m) = model
        .as_mut()
        .filter(|_| args.reverse_average || args.no_reverse_average)
    {
        m.set_reverse_average(args.reverse_average);
    }
    if let (Some(m), Some(views)) = (model.as_mut(), &args.test_views) {
        m.set_test_views(
            &guardian_models::net::parse_test_views(views).map_err(anyhow::Error::msg)?,
        )?;
    }
    let spec = args.episodes.spec();
    let mut report = evaluate(&pool, args.baseline, model.as_ref(), &spec)?;
    if args.per_class {
        report.per_class = per_class(&report.result.predictions, &pool.class_names);
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "{} {}-way {}-shot on {:?} ({} classes, {} episodes): accuracy {:.4} ± {:.4}, CMC {:?}",
            report.method,
            spec.way,
            spec.shot,
            report.alphabets,
            report.classes,
            spec.episodes,
            report.result.accuracy,
            report.result.ci95,
            report
                .result
                .cmc
                .iter()
                .map(|c| (c * 1e4).round() / 1e4)
                .collect::<Vec<_>>()
        );
        for c in &report.per_class {
            let with = c.confused_with.first().map_or(String::new(), |(n, k)| {
                format!(", most often taken for {n} ({k})")
            });
            println!("  {}: {:.3} of {}{with}", c.class, c.accuracy, c.queries);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(way: usize, shot: usize, episodes: usize) -> EpisodeSpec {
        EpisodeSpec {
            way,
            shot,
            episodes,
            seed: 3,
        }
    }

    #[test]
    fn random_scores_give_one_over_n() {
        let labels: Vec<u32> = (0..200).map(|i| i / 5).collect();
        let r = run_episodes(&labels, &spec(10, 1, 20_000), &mut Scorer::Random).unwrap();
        assert!((r.accuracy - 0.1).abs() < r.ci95 * 1.5 + 1e-3, "{r:?}");
        assert!((r.cmc[4] - 0.5).abs() < 0.02);
        assert_eq!(*r.cmc.last().unwrap(), 1.0);
    }

    #[test]
    fn exact_duplicates_are_always_found() {
        // Two identical vectors per class, classes far apart: 1-NN and prototypes are exact.
        let labels: Vec<u32> = (0..40).map(|i| i / 2).collect();
        let v: Vec<Vec<f32>> = labels.iter().map(|&l| vec![l as f32, 0.0]).collect();
        let r = run_episodes(&labels, &spec(20, 1, 500), &mut Scorer::Nearest(&v)).unwrap();
        assert_eq!(r.accuracy, 1.0);
        let r = run_episodes(&labels, &spec(5, 1, 500), &mut Scorer::Prototype(&v)).unwrap();
        assert_eq!(r.accuracy, 1.0);
        assert!(r.predictions.iter().all(|(t, p)| t == p));
        // A degenerate scorer (all vectors equal) is at chance, not perfect.
        let same: Vec<Vec<f32>> = labels.iter().map(|_| vec![0.0, 0.0]).collect();
        let r = run_episodes(&labels, &spec(5, 1, 4000), &mut Scorer::Nearest(&same)).unwrap();
        assert!((r.accuracy - 0.2).abs() < 0.03, "{}", r.accuracy);
        // Too few classes.
        assert!(matches!(
            run_episodes(&labels, &spec(25, 1, 10), &mut Scorer::Random),
            Err(EvalError::TooFewClasses { .. })
        ));
        // Shot larger than a class allows.
        assert!(run_episodes(&labels, &spec(5, 2, 10), &mut Scorer::Random).is_err());
    }

    #[test]
    fn per_class_counts_each_query_class_and_its_confusions() {
        let names: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
        // a: 3 of 4 right, once taken for c; b: 1 of 4, taken for a twice and c once;
        // c: 2 of 2. The worst class comes first.
        let p = [
            (0, 0),
            (0, 0),
            (0, 2),
            (0, 0),
            (1, 0),
            (1, 1),
            (1, 2),
            (1, 0),
            (2, 2),
            (2, 2),
        ];
        let class = |c: &str, queries, accuracy, with: &[(&str, usize)]| ClassResult {
            class: c.into(),
            queries,
            accuracy,
            confused_with: with.iter().map(|&(n, k)| (n.into(), k)).collect(),
        };
        assert_eq!(
            per_class(&p, &names),
            [
                class("b", 4, 0.25, &[("a", 2), ("c", 1)]),
                class("a", 4, 0.75, &[("c", 1)]),
                class("c", 2, 1.0, &[]),
            ]
        );
        // Real episodes: every episode is counted once, under its query's class.
        let labels: Vec<u32> = (0..60).map(|i| i / 3).collect();
        let r = run_episodes(&labels, &spec(5, 1, 500), &mut Scorer::Random).unwrap();
        let names: Vec<String> = (0..20).map(|c| format!("c{c}")).collect();
        let pc = per_class(&r.predictions, &names);
        assert_eq!(pc.iter().map(|c| c.queries).sum::<usize>(), 500);
        let right: f64 = pc.iter().map(|c| c.accuracy * c.queries as f64).sum();
        assert!((right / 500.0 - r.accuracy).abs() < 1e-9);
    }
}
