//! Threshold calibration and the shipped default bank (`guardian-lab bank`).
//!
//! Calibration data: the classes of the calibration (validation) alphabets. In each of
//! `reps` rounds every class gets `shots` randomly drawn enrolled drawings; every other
//! drawing of the class is a genuine plan scored against that bank (distance to its class,
//! to the nearest other class, and its class's spread). [`guardian_models::bank::calibrate`]
//! turns those scores into the global threshold, the wrong-task tolerance and the
//! per-class scale for a target false-reject rate; the bank of the enrolled alphabets is
//! then built with them.

use std::path::PathBuf;

use anyhow::Context as _;
use guardian_models::bank::{
    self, Calibration, ClassBank, Example, GenuineScore, GeometryCalibration,
};
use guardian_models::embedder::Embedder;
use guardian_models::geometry::{self, PlanGeometry};
use guardian_models::kinematics::Robot;
use guardian_shared::trajectory::Resampled;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use serde::Serialize;

use crate::dataset::Dataset;
use crate::eval::Pool;

/// Indices of each dense label, in pool order.
pub fn by_class(labels: &[u32]) -> Vec<Vec<usize>> {
    let n = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
    let mut out = vec![Vec::new(); n];
    for (i, &l) in labels.iter().enumerate() {
        out[l as usize].push(i);
    }
    out
}

/// One random enrollment: `shots` support indices per class (classes with fewer than
/// `shots + 1` drawings are left out) and the remaining indices as queries.
pub fn split(labels: &[u32], shots: usize, rng: &mut StdRng) -> (Vec<Vec<usize>>, Vec<usize>) {
    let mut support = Vec::new();
    let mut queries = Vec::new();
    for mut idx in by_class(labels) {
        if idx.len() <= shots {
            support.push(Vec::new());
            continue;
        }
        idx.shuffle(rng);
        queries.extend_from_slice(&idx[shots..]);
        idx.truncate(shots);
        support.push(idx);
    }
    (support, queries)
}

/// A bank of the classes in `support` (dense label -> indices into `emb`), named by `names`.
pub fn bank_of(
    emb: &[Vec<f32>],
    support: &[Vec<usize>],
    names: &[String],
    model_version: &str,
) -> anyhow::Result<ClassBank> {
    let dim = emb.first().map_or(0, Vec::len);
    let mut b = ClassBank::new(dim, model_version, bank::DEFAULT_THRESHOLD);
    for (l, idx) in support.iter().enumerate() {
        if idx.is_empty() {
            continue;
        }
        let rows: Vec<Vec<f32>> = idx.iter().map(|&i| emb[i].clone()).collect();
        let name = names.get(l).cloned().unwrap_or_else(|| format!("class{l}"));
        b.enroll(&name, &rows)?;
    }
    Ok(b)
}

/// Genuine scores of every non-enrolled drawing over `reps` random enrollments.
pub fn genuine_scores(
    emb: &[Vec<f32>],
    labels: &[u32],
    names: &[String],
    shots: usize,
    reps: usize,
    seed: u64,
) -> anyhow::Result<Vec<GenuineScore>> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut out = Vec::new();
    for _ in 0..reps {
        let (support, queries) = split(labels, shots, &mut rng);
        let b = bank_of(emb, &support, names, "calibration")?;
        for q in queries {
            let l = labels[q] as usize;
            let name = names.get(l).cloned().unwrap_or_else(|| format!("class{l}"));
            let Some(class) = b.class(&name) else {
                continue;
            };
            let ranked = b.ranked(&emb[q]);
            let claimed = bank::distance(&emb[q], &class.prototype);
            let nearest_other = ranked.iter().find(|n| n.name != name).map(|n| n.distance);
            out.push(GenuineScore {
                claimed,
                nearest_other,
                spread: bank::class_spread(&class.embeddings),
            });
        }
    }
    Ok(out)
}

/// Plan geometry of every trajectory of `robot` (`None`: the pen never touches the canvas).
pub fn geometry_of(xs: &[Resampled], robot: &Robot) -> Vec<Option<PlanGeometry>> {
    use rayon::prelude::*;
    xs.par_iter()
        .map(|x| guardian_models::workcell::plan_geometry(robot, x))
        .collect()
}

/// The geometry calibration: pooled per-feature spreads of the calibration classes, then
/// the geometry threshold for the part of the `target_rate` budget the embedding
/// calibration `cal` left, from the genuine plans of `reps` random `shots`-shot enrollments
/// (the same enrollments as [`genuine_scores`] with the same seed, so `scores` line up).
/// `pools` are the calibration sets as (plan geometry, dense labels), in the order their
/// genuine scores were concatenated into `scores` (one set, or one per cross-fitted model).
#[allow(clippy::too_many_arguments)]
pub fn calibrate_geometry_pool(
    scores: &[GenuineScore],
    cal: &Calibration,
    pools: &[(&[Option<PlanGeometry>], &[u32])],
    shots: usize,
    reps: usize,
    target_rate: f32,
    seed: u64,
    note: &str,
) -> anyhow::Result<GeometryCalibration> {
    let groups: Vec<Vec<PlanGeometry>> = pools
        .iter()
        .flat_map(|(geo, labels)| {
            by_class(labels)
                .into_iter()
                .map(|idx| idx.iter().filter_map(|&i| geo[i]).collect())
        })
        .collect();
    let scales =
        geometry::pooled_scales(&groups).context("no geometry spread on the calibration data")?;
    let g: Vec<Option<f32>> = pools
        .iter()
        .flat_map(|(geo, labels)| geometry_scores(geo, labels, shots, reps, seed, &scales))
        .collect();
    anyhow::ensure!(
        g.len() == scores.len(),
        "geometry and embedding scores differ in number"
    );
    bank::calibrate_geometry(scores, &g, cal, target_rate, scales, note)
        .context("geometry calibration failed")
}

/// Geometry scores of the genuine plans of `reps` random `shots`-shot enrollments (the
/// enrollments of [`genuine_scores`] with the same seed, in the same order).
fn geometry_scores(
    geo: &[Option<PlanGeometry>],
    labels: &[u32],
    shots: usize,
    reps: usize,
    seed: u64,
    scales: &[f32; guardian_shared::workcell::GEOMETRY_FEATURES],
) -> Vec<Option<f32>> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut g = Vec::new();
    for _ in 0..reps {
        let (support, queries) = split(labels, shots, &mut rng);
        for q in queries {
            let l = labels[q] as usize;
            if support[l].is_empty() {
                continue;
            }
            let ex: Vec<PlanGeometry> = support[l].iter().filter_map(|&i| geo[i]).collect();
            g.push(geo[q].and_then(|x| geometry::score(&x, &ex, scales).map(|(s, _)| s)));
        }
    }
    g
}

/// One (model, alphabets) pair of a cross-fitted calibration: the model never saw the
/// alphabets (in training, validation or any pool), so its genuine scores on them are what a
/// model of the same recipe scores on tasks it never saw.
#[derive(Debug, Clone, PartialEq)]
pub struct CrossFitPair {
    /// Embedder file.
    pub model: PathBuf,
    /// Alphabets unseen by that model.
    pub alphabets: Vec<String>,
}

impl std::str::FromStr for CrossFitPair {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let (m, a) = s
            .rsplit_once('=')
            .ok_or_else(|| format!("expected MODEL=ALPHABET[+ALPHABET...], got {s:?}"))?;
        let alphabets: Vec<String> = a
            .split('+')
            .filter(|x| !x.is_empty())
            .map(String::from)
            .collect();
        if m.is_empty() || alphabets.is_empty() {
            return Err(format!("expected MODEL=ALPHABET[+ALPHABET...], got {s:?}"));
        }
        Ok(Self {
            model: PathBuf::from(m),
            alphabets,
        })
    }
}

/// Cross-fitted calibration: the genuine embedding scores of every pair (each model on its
/// own unseen alphabets) pooled, calibrated for `target_frr × (1 − geometry_share)`; the
/// geometry check on the same plans with the rest of the budget (its feature spreads pooled
/// over all pairs' classes). The calibration numbers are then used with another model of the
/// same recipe (the shipped one, trained on all those alphabets).
pub fn cross_fit(
    data: &Dataset,
    pairs: &[CrossFitPair],
    shots: usize,
    reps: usize,
    target_frr: f32,
    geometry_share: f32,
    seed: u64,
) -> anyhow::Result<(Calibration, Option<GeometryCalibration>)> {
    anyhow::ensure!(
        !pairs.is_empty(),
        "cross-fitting needs at least one MODEL=ALPHABET pair"
    );
    let mut scores = Vec::new();
    let mut pools = Vec::new();
    let mut names = Vec::new();
    for p in pairs {
        let model = data.embedder(&p.model)?;
        let pool = Pool::new(data, &p.alphabets)?;
        let emb = pool.embed(&model)?;
        scores.extend(genuine_scores(
            &emb,
            &pool.labels,
            &pool.class_names,
            shots,
            reps,
            seed,
        )?);
        names.push(format!("{} on {}", model.version(), p.alphabets.join("+")));
        pools.push(pool);
    }
    let note = format!(
        "cross-fitted: {shots}-shot, {reps} reps, each model on alphabets it never saw: {}",
        names.join(", ")
    );
    let cal = bank::calibrate(&scores, target_frr * (1.0 - geometry_share), &note)
        .with_context(|| format!("cannot calibrate: {} scores", scores.len()))?;
    if geometry_share <= 0.0 {
        return Ok((cal, None));
    }
    let robot = data.robot()?;
    let geos: Vec<Vec<Option<PlanGeometry>>> =
        pools.iter().map(|p| geometry_of(&p.xs, &robot)).collect();
    let sets: Vec<(&[Option<PlanGeometry>], &[u32])> = geos
        .iter()
        .zip(&pools)
        .map(|(g, p)| (g.as_slice(), p.labels.as_slice()))
        .collect();
    let gcal = calibrate_geometry_pool(
        &scores,
        &cal,
        &sets,
        shots,
        reps,
        target_frr,
        seed,
        &format!("{note}; geometry share {geometry_share}"),
    )?;
    Ok((cal, Some(gcal)))
}

/// Calibrate on the pool's embeddings for `target_rate`.
pub fn calibrate_pool(
    emb: &[Vec<f32>],
    pool: &Pool,
    shots: usize,
    reps: usize,
    target_rate: f32,
    seed: u64,
    note: &str,
) -> anyhow::Result<Calibration> {
    let scores = genuine_scores(emb, &pool.labels, &pool.class_names, shots, reps, seed)?;
    bank::calibrate(&scores, target_rate, note).with_context(|| {
        format!(
            "cannot calibrate: {} scores, target {target_rate}",
            scores.len()
        )
    })
}

/// `guardian-lab bank`: calibrate on the validation alphabets and build a class bank.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Embedder.
    #[arg(long, default_value = "models/embedder.safetensors")]
    pub model: PathBuf,
    /// Dataset file.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Alphabets to calibrate on (validation; never the enrolled ones).
    #[arg(long, value_delimiter = ',', default_value = "Latin")]
    pub calib_alphabets: Vec<String>,
    /// Alphabets whose classes are enrolled into the bank.
    #[arg(long, value_delimiter = ',', default_value = "Greek,Korean")]
    pub alphabets: Vec<String>,
    /// Enrolled drawings per class (calibration uses the same number).
    #[arg(long, default_value_t = 5)]
    pub shots: usize,
    /// Target false-reject rate on genuine plans (embedding and geometry together).
    #[arg(long, default_value_t = 0.01)]
    pub target_frr: f32,
    /// Share of the false-reject budget given to the geometry check (the embedding gets
    /// the rest); 0 turns the geometry check off.
    #[arg(long, default_value_t = 0.25)]
    pub geometry_share: f32,
    /// Random enrollments of the calibration alphabets.
    #[arg(long, default_value_t = 20)]
    pub reps: usize,
    /// Seed (calibration enrollments and the enrolled drawings).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output bank file.
    #[arg(long, default_value = "models/default-bank.gcb")]
    pub out: PathBuf,
    /// Cross-fitted calibration instead of `--calib-alphabets`: `MODEL=ALPHABET[+ALPHABET]`
    /// pairs (repeat the option), each model one that never saw its alphabets (the
    /// leave-one-alphabet-out fold models); their genuine scores are pooled and the numbers
    /// used with `--model` ([`cross_fit`]).
    #[arg(long)]
    pub cross_fit: Vec<CrossFitPair>,
    /// Take the calibration (record and geometry calibration) from this bank instead of
    /// calibrating: it must be a calibrated bank built with `--model`. Rebuilds a bank with
    /// the same numbers, e.g. to add the enrolled examples to a bank whose cross-fit fold
    /// models are not at hand.
    #[arg(long, conflicts_with = "cross_fit")]
    pub calibration_from: Option<PathBuf>,
}

/// What `guardian-lab bank` did.
#[derive(Debug, Clone, Serialize)]
pub struct BankSummary {
    /// Model version.
    pub model_version: String,
    /// Classes enrolled.
    pub classes: usize,
    /// The calibration record stored in the bank.
    pub calibration: Calibration,
    /// The geometry calibration stored in the bank.
    pub geometry_calibration: Option<GeometryCalibration>,
    /// Output file.
    pub out: PathBuf,
}

/// The calibration of `guardian-lab bank` on `--calib-alphabets` with the bank's own model.
fn calibrate_on_alphabets(
    args: &Args,
    data: &Dataset,
    model: &Embedder,
) -> anyhow::Result<(Calibration, Option<GeometryCalibration>)> {
    let cpool = Pool::new(data, &args.calib_alphabets)?;
    let cemb = cpool.embed(model)?;
    let note = format!(
        "{}-shot, {} reps on {}; model {}",
        args.shots,
        args.reps,
        args.calib_alphabets.join(","),
        model.version()
    );
    let emb_target = args.target_frr * (1.0 - args.geometry_share);
    let scores = genuine_scores(
        &cemb,
        &cpool.labels,
        &cpool.class_names,
        args.shots,
        args.reps,
        args.seed,
    )?;
    let cal = bank::calibrate(&scores, emb_target, &note)
        .with_context(|| format!("cannot calibrate: {} scores", scores.len()))?;
    let gcal = if args.geometry_share > 0.0 {
        let cgeo = geometry_of(&cpool.xs, &cpool.robot);
        Some(calibrate_geometry_pool(
            &scores,
            &cal,
            &[(cgeo.as_slice(), cpool.labels.as_slice())],
            args.shots,
            args.reps,
            args.target_frr,
            args.seed,
            &format!("{note}; geometry share {}", args.geometry_share),
        )?)
    } else {
        None
    };
    Ok((cal, gcal))
}

/// Run `guardian-lab bank`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let data = Dataset::load(&args.dataset)?;
    let model = data.embedder(&args.model)?;
    anyhow::ensure!(
        (0.0..=1.0).contains(&args.geometry_share),
        "--geometry-share must be in [0, 1]"
    );
    let (cal, gcal) = if let Some(p) = &args.calibration_from {
        let from =
            ClassBank::load(p).with_context(|| format!("--calibration-from {}", p.display()))?;
        anyhow::ensure!(
            from.model_version() == model.version(),
            "--calibration-from {} is a bank of model {}, not of {}",
            p.display(),
            from.model_version(),
            model.version()
        );
        let cal = from
            .calibration()
            .cloned()
            .with_context(|| format!("--calibration-from {} is not calibrated", p.display()))?;
        (cal, from.geometry_calibration().cloned())
    } else if args.cross_fit.is_empty() {
        if args
            .calib_alphabets
            .iter()
            .any(|a| args.alphabets.contains(a))
        {
            anyhow::bail!("calibration and enrolled alphabets overlap");
        }
        calibrate_on_alphabets(args, &data, &model)?
    } else {
        cross_fit(
            &data,
            &args.cross_fit,
            args.shots,
            args.reps,
            args.target_frr,
            args.geometry_share,
            args.seed,
        )?
    };
    let pool = Pool::new(&data, &args.alphabets)?;
    let emb = pool.embed(&model)?;
    let geo = geometry_of(&pool.xs, &pool.robot);
    let mut rng = StdRng::seed_from_u64(args.seed ^ 0x5eed);
    let (support, _) = split(&pool.labels, args.shots, &mut rng);
    let dim = emb.first().map_or(0, Vec::len);
    let mut b = ClassBank::new(dim, model.version(), bank::DEFAULT_THRESHOLD);
    // The bank records the robot that drew its plans: a daemon serving another arm
    // refuses it.
    b.set_robot(data.robot.clone());
    for (l, idx) in support.iter().enumerate() {
        if idx.is_empty() {
            continue;
        }
        let rows: Vec<Vec<f32>> = idx.iter().map(|&i| emb[i].clone()).collect();
        let g: Vec<PlanGeometry> = idx
            .iter()
            .map(|&i| geo[i])
            .collect::<Option<_>>()
            .unwrap_or_default();
        let name = pool
            .class_names
            .get(l)
            .cloned()
            .unwrap_or_else(|| format!("class{l}"));
        // The resampled plans too: a daemon with a new model embeds them again.
        let examples: Vec<Example> = idx
            .iter()
            .map(|&i| Example::from_resampled(&pool.xs[i], data.robot.joints))
            .collect();
        b.enroll_plans(&name, &rows, &g, &examples)?;
    }
    b.apply_calibration(cal.clone());
    b.set_geometry_calibration(gcal.clone());
    b.save(&args.out)?;
    let summary = BankSummary {
        model_version: model.version().to_owned(),
        classes: b.len(),
        calibration: cal,
        geometry_calibration: gcal,
        out: args.out.clone(),
    };
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_keeps_shots_and_queries_apart() {
        let labels: Vec<u32> = (0..30).map(|i| i / 10).collect();
        let mut rng = StdRng::seed_from_u64(1);
        let (support, queries) = split(&labels, 3, &mut rng);
        assert_eq!(support.len(), 3);
        assert!(support.iter().all(|s| s.len() == 3));
        assert_eq!(queries.len(), 21);
        for (l, s) in support.iter().enumerate() {
            assert!(
                s.iter()
                    .all(|&i| labels[i] as usize == l && !queries.contains(&i))
            );
        }
    }

    #[test]
    fn genuine_scores_of_separated_classes_calibrate_to_the_target() {
        // Three tight, far-apart clusters: every genuine plan is nearest its own class.
        let labels: Vec<u32> = (0..60).map(|i| i / 20).collect();
        let emb: Vec<Vec<f32>> = labels
            .iter()
            .enumerate()
            .map(|(i, &l)| {
                vec![
                    l as f32 * 10.0 + (i % 7) as f32 * 0.01,
                    (i % 5) as f32 * 0.01,
                ]
            })
            .collect();
        let names: Vec<String> = (0..3).map(|i| format!("c{i}")).collect();
        let s = genuine_scores(&emb, &labels, &names, 5, 4, 0).unwrap();
        assert_eq!(s.len(), 4 * 3 * 15);
        assert!(s.iter().all(|g| g.nearest_other.unwrap() > g.claimed));
        let c = bank::calibrate(&s, 0.05, "").unwrap();
        assert!(c.measured_rate.unwrap() <= 0.05);
        assert!(c.global_threshold.unwrap() < 1.0);
    }
}
