//! Threshold calibration for the screen's figures and banks (`guardian-lab bank` and
//! `guardian-lab outliers` use it).
//!
//! Calibration data: the classes of the calibration (validation) alphabets. In each of
//! `reps` rounds every class gets `shots` randomly drawn enrolled drawings; every other
//! drawing of the class is a genuine plan scored against that bank (distance to its class,
//! to the nearest other class, and its class's spread). [`guardian_bank::calibrate`]
//! turns those scores into the global threshold, the wrong-task tolerance and the
//! per-class scale for a target false-reject rate. Cross-fitting pools the genuine scores
//! of fold models on the alphabets each never saw ([`cross_fit`]).

use std::path::PathBuf;

use anyhow::Context as _;
use guardian_bank::{self as bank, Calibration, ClassBank, GenuineScore, GeometryCalibration};
use guardian_robot::geometry::{self, PlanGeometry};
use guardian_robot::kinematics::Robot;
use guardian_shared::trajectory::Resampled;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use crate::eval::Pool;
use guardian_omniglot::dataset::Dataset;

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
        .map(|x| guardian_robot::workcell::plan_geometry(robot, x))
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
        let model = crate::dataset::model_for(data, &p.model)?;
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
