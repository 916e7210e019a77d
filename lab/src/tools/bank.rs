//! `guardian-lab bank`: calibrate the screen's thresholds (on validation alphabets, by
//! cross-fitting fold models, or taken from another bank; [`crate::eval::calibration`]) and
//! build the shipped default class bank from the enrolled alphabets' drawings.

use std::path::PathBuf;

use anyhow::Context as _;
use guardian_bank::{self as bank, Calibration, ClassBank, Example, GeometryCalibration};
use guardian_models::embedder::Embedder;
use guardian_robot::geometry::PlanGeometry;
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::Serialize;

use crate::cli::{DatasetArgs, ScreenArgs};
use crate::eval::Pool;
use crate::eval::calibration::{
    CrossFitPair, calibrate_geometry_pool, cross_fit, genuine_scores, geometry_of, split,
};
use guardian_omniglot::dataset::Dataset;

/// `guardian-lab bank`: calibrate on the validation alphabets and build a class bank.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Model, enrolled and calibration alphabets, shots, target and seed (calibration
    /// enrollments and the enrolled drawings).
    #[command(flatten)]
    pub screen: ScreenArgs,
    /// The dataset.
    #[command(flatten)]
    pub data: DatasetArgs,
    /// Random enrollments of the calibration alphabets.
    #[arg(long, default_value_t = 20)]
    pub reps: usize,
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
    let cpool = Pool::new(data, &args.screen.calib_alphabets)?;
    let cemb = cpool.embed(model)?;
    let note = format!(
        "{}-shot, {} reps on {}; model {}",
        args.screen.shots,
        args.reps,
        args.screen.calib_alphabets.join(","),
        model.version()
    );
    let emb_target = args.screen.target_frr * (1.0 - args.screen.geometry_share);
    let scores = genuine_scores(
        &cemb,
        &cpool.labels,
        &cpool.class_names,
        args.screen.shots,
        args.reps,
        args.screen.seed,
    )?;
    let cal = bank::calibrate(&scores, emb_target, &note)
        .with_context(|| format!("cannot calibrate: {} scores", scores.len()))?;
    let gcal = if args.screen.geometry_share > 0.0 {
        let cgeo = geometry_of(&cpool.xs, &cpool.robot);
        Some(calibrate_geometry_pool(
            &scores,
            &cal,
            &[(cgeo.as_slice(), cpool.labels.as_slice())],
            args.screen.shots,
            args.reps,
            args.screen.target_frr,
            args.screen.seed,
            &format!("{note}; geometry share {}", args.screen.geometry_share),
        )?)
    } else {
        None
    };
    Ok((cal, gcal))
}

/// Run `guardian-lab bank`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let summary = build(args)?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

/// Calibrate and write the bank of `guardian-lab bank`; what was done, not printed.
pub fn build(args: &Args) -> anyhow::Result<BankSummary> {
    let data = Dataset::load(&args.data.dataset)?;
    let model = crate::dataset::model_for(&data, &args.screen.model)?;
    args.screen.check_geometry_share()?;
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
        args.screen.check_disjoint()?;
        calibrate_on_alphabets(args, &data, &model)?
    } else {
        cross_fit(
            &data,
            &args.cross_fit,
            args.screen.shots,
            args.reps,
            args.screen.target_frr,
            args.screen.geometry_share,
            args.screen.seed,
        )?
    };
    let pool = Pool::new(&data, &args.screen.alphabets)?;
    let emb = pool.embed(&model)?;
    let geo = geometry_of(&pool.xs, &pool.robot);
    let mut rng = StdRng::seed_from_u64(args.screen.seed ^ 0x5eed);
    let (support, _) = split(&pool.labels, args.screen.shots, &mut rng);
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
    Ok(summary)
}
