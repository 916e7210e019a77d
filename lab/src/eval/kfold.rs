//! `guardian-lab kfold`: the whole K-fold-by-alphabet protocol in one command.
//!
//! The alphabets of a dataset are dealt into K folds (the dense alphabets first, so they
//! spread over the folds, then the others, each list sorted by name, round robin). For each
//! fold, both branches of the shipped recipe ([`RECIPE_COMMON`], [`RECIPE_SEQUENCE`],
//! [`RECIPE_PICTURE`]) are trained on the other folds' alphabets only, without a validation
//! alphabet (the one-cycle schedule keeps the last model, so no held-out alphabet is used
//! for model selection), and fused. Then, on every held-out alphabet:
//! - 1-shot 2/10/20-way and 5-shot 20-way within-alphabet episodes ([`SPECS`]);
//! - the go / no-go figures (`outliers`, 5 shots) with a **cross-fitted** calibration: the
//!   fold model's thresholds come from the other folds' models, each scoring the alphabets
//!   it never saw, so neither the fold's model nor its calibration saw the alphabet.
//!
//! Every step is skipped when its output is already there (a finished branch; a fused
//! model, which also skips its branches' training; an evaluated alphabet), and a branch
//! that stopped half-way is resumed from its checkpoint: the command can be stopped and
//! run again. It writes `results.jsonl` (one row per alphabet and measurement) and
//! `REPORT.md` (per alphabet, the dense alphabets apart, per-fold means and their spread)
//! in `--out`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use clap::parser::ValueSource;
use clap::{CommandFactory, FromArgMatches, Parser};
use guardian_models::embedder::Embedder;
use serde::{Deserialize, Serialize};

use crate::cli::{DatasetArgs, ScreenArgs, StrokesArgs};
use crate::eval::calibration::CrossFitPair;
use crate::eval::{EpisodeSpec, Pool, evaluate};
use crate::train::Args as TrainArgs;
use crate::train::config::{FeatureArg, LossKind, Schedule};
use guardian_omniglot::dataset::Dataset;

/// The alphabets with official, dense, real-time stroke files: the drawings closest to a
/// served plan, reported apart.
pub const DENSE_ALPHABETS: [&str; 6] = [
    "Balinese",
    "Early_Aramaic",
    "Greek",
    "Japanese_(katakana)",
    "Korean",
    "Latin",
];

/// One setting of a recipe: the `train` option it sets (its clap id, the field's name) and
/// how it sets the field.
pub type Setting = (&'static str, fn(&mut TrainArgs));

/// What both branches of the shipped recipe train with (`models/MODEL.md`, "How to
/// retrain"): fault negatives, class augmentation, a 64-value embedding, seed 1, the
/// one-cycle schedule.
pub const RECIPE_COMMON: &[Setting] = &[
    ("fault_share", |a| a.fault_share = 1.0),
    ("fault_variants", |a| a.fault_variants = 8),
    ("fault_weight", |a| a.fault_weight = 1.0),
    ("fault_margin", |a| a.fault_margin = 0.4),
    ("class_augment", |a| a.class_augment = true),
    ("embed_dim", |a| a.embed_dim = 64),
    ("seed", |a| a.seed = 1),
    ("schedule", |a| a.schedule = Schedule::OneCycle),
];

/// The sequence branch of the shipped recipe: the supervised contrastive loss (temperature
/// 0.1) over batches of 64 classes x 4 drawings (`models/MODEL.md`, "How to retrain").
pub const RECIPE_SEQUENCE: &[Setting] = &[
    ("channels", |a| a.channels = vec![32, 64, 128]),
    ("reverse_average", |a| a.reverse_average = true),
    ("loss", |a| a.loss = LossKind::Supcon),
    ("margin", |a| a.margin = 0.1),
    ("p_classes", |a| a.p_classes = 64),
];

/// The picture branch of the shipped recipe: the same loss and batches as the sequence
/// branch.
pub const RECIPE_PICTURE: &[Setting] = &[
    ("features", |a| a.features = FeatureArg::Picture),
    ("channels", |a| a.channels = vec![16, 32, 64, 128]),
    ("kernel", |a| a.kernel = 3),
    ("loss", |a| a.loss = LossKind::Supcon),
    ("margin", |a| a.margin = 0.1),
    ("p_classes", |a| a.p_classes = 64),
];

/// The episodes measured on every held-out alphabet: (way, shot).
pub const SPECS: [(usize, usize); 4] = [(2, 1), (10, 1), (20, 1), (20, 5)];

/// The shape faults of the go / no-go targets.
pub const SHAPE_FAULTS: [&str; 5] = [
    "missing-stroke",
    "extra-stroke",
    "mirrored",
    "rotated",
    "truncated",
];

/// `guardian-lab kfold`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// The dataset (every alphabet of it is dealt into the folds).
    #[command(flatten)]
    pub data: DatasetArgs,
    /// Stroke roots of the dataset's drawings (fault negatives and faulty plans).
    #[command(flatten)]
    pub strokes: StrokesArgs,
    /// Output directory (fold models, results, report).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of folds.
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    /// Alphabets dealt first and reported apart (the official, dense ones).
    #[arg(long, value_delimiter = ',', default_values = DENSE_ALPHABETS)]
    pub dense: Vec<String>,
    /// Run only these folds (0-based); the report covers the folds measured so far.
    #[arg(long, value_delimiter = ',')]
    pub only_folds: Vec<usize>,
    /// Optimiser steps per epoch of both branches.
    #[arg(long, default_value_t = 100)]
    pub steps_per_epoch: usize,
    /// Epochs of both branches.
    #[arg(long, default_value_t = 100)]
    pub epochs: usize,
    /// More `train` options for both branches, whitespace-separated (after the recipe's,
    /// so they override it), e.g. "--p-classes 64".
    #[arg(long, allow_hyphen_values = true)]
    pub train_args: Option<String>,
    /// Episodes per measurement.
    #[arg(long, default_value_t = 2000)]
    pub episodes: usize,
    /// Seed of the episodes and of the go / no-go rounds.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Skip the go / no-go figures (episodes only).
    #[arg(long)]
    pub no_outliers: bool,
    /// Also measure the go / no-go figures of the dense alphabets with a calibration
    /// cross-fitted on the dense alphabets alone (rows `dense-calibration`): served plans
    /// are dense.
    #[arg(long)]
    pub dense_calibration: bool,
    /// Faulty-plan sources per alphabet for the go / no-go figures.
    #[arg(long, default_value_t = 200)]
    pub sources: usize,
    /// Calibration rounds (cross-fitted) and test rounds of the go / no-go figures.
    #[arg(long, default_value_t = 20)]
    pub calib_reps: usize,
    /// Test rounds (random enrollments) of the go / no-go figures.
    #[arg(long, default_value_t = 5)]
    pub reps: usize,
    /// Other datasets of the same drawings, `NAME=FILE` (e.g. the dense alphabets simplified
    /// or without dots): every fold model is also measured on its held-out alphabets there.
    #[arg(long)]
    pub variant: Vec<Variant>,
    /// A model to measure on the same episodes beside the fold models (e.g. the previous
    /// shipped model), on the held-out alphabets it was not trained on.
    #[arg(long)]
    pub compare: Option<PathBuf>,
    /// The alphabets `--compare` was trained on (it is not measured there).
    #[arg(long, value_delimiter = ',', default_values = DENSE_ALPHABETS)]
    pub compare_trained_on: Vec<String>,
    /// Rayon threads of the training runs (0: rayon's default).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// `NAME=FILE` of `--variant`.
#[derive(Debug, Clone, PartialEq)]
pub struct Variant {
    /// Name in the results.
    pub name: String,
    /// Dataset file.
    pub file: PathBuf,
}

impl std::str::FromStr for Variant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.split_once('=') {
            Some((n, f)) if !n.is_empty() && !f.is_empty() => Ok(Self {
                name: n.to_owned(),
                file: PathBuf::from(f),
            }),
            _ => Err(format!("expected NAME=FILE, got {s:?}")),
        }
    }
}

/// Deal `alphabets` into `k` folds: the `dense` ones first, then the rest, each sorted by
/// name, round robin. Every alphabet lands in exactly one fold.
pub fn assign_folds(alphabets: &[String], dense: &[String], k: usize) -> Vec<Vec<String>> {
    let mut first: Vec<&String> = alphabets.iter().filter(|a| dense.contains(a)).collect();
    let mut rest: Vec<&String> = alphabets.iter().filter(|a| !dense.contains(a)).collect();
    first.sort();
    rest.sort();
    let mut folds = vec![Vec::new(); k.max(1)];
    for (i, a) in first.into_iter().chain(rest).enumerate() {
        folds[i % k.max(1)].push(a.clone());
    }
    folds
}

/// One measured row of `results.jsonl`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Row {
    /// Fold (0-based).
    pub fold: usize,
    /// Alphabet (held out of the fold's training).
    pub alphabet: String,
    /// One of the dense alphabets.
    pub dense: bool,
    /// `fold` (the fold model), `compare` (the `--compare` model) or a variant's name (the
    /// fold model on that dataset).
    pub model: String,
    /// Model version.
    pub model_version: String,
    /// What: `episodes` or `outliers`.
    pub kind: String,
    /// Episodes: N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub way: Option<usize>,
    /// Episodes: K.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shot: Option<usize>,
    /// Episodes: accuracy; outliers: wrong-task detection.
    pub value: f64,
    /// Episodes: 95 % half-width.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ci95: Option<f64>,
    /// Outliers: genuine false rejects, wrong-task AUROC, shape-fault AUROC at 0.5 by fault.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub figures: BTreeMap<String, f64>,
}

impl Row {
    /// A row of fold `k` on `alphabet` with no figure yet.
    fn blank(k: usize, alphabet: &str, dense: bool, model: &str, kind: &str) -> Self {
        Self {
            fold: k,
            alphabet: alphabet.to_owned(),
            dense,
            model: model.to_owned(),
            model_version: String::new(),
            kind: kind.to_owned(),
            way: None,
            shot: None,
            value: f64::NAN,
            ci95: None,
            figures: BTreeMap::new(),
        }
    }
}

fn fold_dir(out: &Path, k: usize) -> PathBuf {
    out.join(format!("fold-{k}"))
}

/// `train`'s command line: its defaults and the options of `--train-args`.
#[derive(Debug, Parser)]
struct TrainCli {
    #[command(flatten)]
    args: TrainArgs,
}

/// The `train` arguments of one branch of a fold: `guardian-lab train`'s defaults with the
/// options of `--train-args`, the fold's data and schedule, and the shipped recipe
/// ([`RECIPE_COMMON`] and the branch's `recipe`) where `--train-args` does not set the
/// option itself.
pub fn branch_args(
    args: &Args,
    train: &[String],
    recipe: &[Setting],
    out: &Path,
    resume: bool,
) -> anyhow::Result<TrainArgs> {
    // The required options get placeholders, replaced below: every other value is train's
    // own default or given in --train-args.
    let required = [
        "train",
        "--dataset",
        "-",
        "--train-alphabets",
        "-",
        "--out",
        "-",
    ];
    let extra: Vec<&str> = args
        .train_args
        .as_deref()
        .map_or(Vec::new(), |e| e.split_whitespace().collect());
    let matches = TrainCli::command()
        .try_get_matches_from(required.iter().copied().chain(extra))
        .context("--train-args")?;
    let mut a = TrainCli::from_arg_matches(&matches)?.args;
    let given = |id: &str| matches.value_source(id) == Some(ValueSource::CommandLine);
    for (id, set) in RECIPE_COMMON.iter().chain(recipe) {
        if !given(id) {
            set(&mut a);
        }
    }
    a.data = args.data.clone();
    a.train_alphabets = train.to_vec();
    a.out = out.to_path_buf();
    a.quiet = true;
    a.strokes = args.strokes.clone();
    a.steps_per_epoch = args.steps_per_epoch;
    a.epochs = args.epochs;
    a.resume = resume;
    Ok(a)
}

fn finished(dir: &Path) -> bool {
    std::fs::read_to_string(dir.join("state.json")).is_ok_and(|s| {
        serde_json::from_str::<serde_json::Value>(&s)
            .ok()
            .and_then(|v| v.get("finished").and_then(serde_json::Value::as_bool))
            == Some(true)
    })
}

/// Train (or resume, or skip) one branch.
fn train_branch(
    args: &Args,
    train: &[String],
    recipe: &[Setting],
    out: &Path,
) -> anyhow::Result<()> {
    if finished(out) {
        return Ok(());
    }
    let resume = out.join("state.json").exists();
    let train_args = branch_args(args, train, recipe, out, resume)?;
    eprintln!("kfold: train {}", out.display());
    let run = || crate::train::run(&train_args);
    if args.threads > 0 {
        rayon::ThreadPoolBuilder::new()
            .num_threads(args.threads)
            .build()?
            .install(run)
    } else {
        run()
    }
}

/// Fuse the fold's two branches (the sequence served in one pass, as shipped).
fn fuse(dir: &Path) -> anyhow::Result<PathBuf> {
    let out = dir.join("model.safetensors");
    if out.exists() {
        return Ok(out);
    }
    let mut parts = ["seq", "pic"]
        .iter()
        .map(|b| {
            let p = dir.join(b).join("model.safetensors");
            Embedder::load(&p).map_err(|e| anyhow::anyhow!("loading {}: {e}", p.display()))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    parts.iter_mut().for_each(|p| p.set_reverse_average(false));
    Embedder::fuse(&parts)?.save(&out)?;
    Ok(out)
}

/// Episode rows of one model on one alphabet (a spec the alphabet is too small for is left
/// out, with a note on stderr).
fn episode_rows(
    data: &Dataset,
    model: &Embedder,
    alphabet: &str,
    base: &Row,
    args: &Args,
) -> anyhow::Result<Vec<Row>> {
    let pool = Pool::new(data, &[alphabet.to_owned()])?;
    let mut rows = Vec::new();
    for (way, shot) in SPECS {
        let spec = EpisodeSpec {
            way,
            shot,
            episodes: args.episodes,
            seed: args.seed,
        };
        match evaluate(&pool, None, Some(model), &spec) {
            Ok(r) => rows.push(Row {
                way: Some(way),
                shot: Some(shot),
                value: r.result.accuracy,
                ci95: Some(r.result.ci95),
                model_version: model.version().to_owned(),
                ..base.clone()
            }),
            Err(crate::eval::EvalError::TooFewClasses { .. }) => {
                eprintln!("kfold: {alphabet}: too few classes for {way}-way {shot}-shot")
            }
            Err(e) => return Err(e.into()),
        }
    }
    Ok(rows)
}

/// The go / no-go row of fold `k`'s model on `alphabet`, calibrated by cross-fitting: the
/// other folds' models each score their held-out alphabets (only the dense ones with
/// `dense_only`) and the genuine scores are pooled.
fn outlier_row(
    args: &Args,
    folds: &[Vec<String>],
    k: usize,
    alphabet: &str,
    base: &Row,
    dense_only: bool,
) -> anyhow::Result<Row> {
    let dir = fold_dir(&args.out, k);
    let model = dir.join("model.safetensors");
    let bank = dir.join(if dense_only {
        "crossfit-dense-bank.gcb"
    } else {
        "crossfit-bank.gcb"
    });
    // The calibration's settings, the same for the bank and the go / no-go figures.
    let screen = |alphabets: Vec<String>, calib_alphabets: Vec<String>| ScreenArgs {
        model: model.clone(),
        alphabets,
        calib_alphabets,
        shots: 5,
        target_frr: 0.01,
        geometry_share: 0.25,
        seed: args.seed,
    };
    if !bank.exists() {
        let cross_fit = folds
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != k)
            .filter_map(|(j, f)| {
                let alphabets: Vec<String> = f
                    .iter()
                    .filter(|a| !dense_only || args.dense.contains(a))
                    .cloned()
                    .collect();
                (!alphabets.is_empty()).then(|| CrossFitPair {
                    model: fold_dir(&args.out, j).join("model.safetensors"),
                    alphabets,
                })
            })
            .collect();
        let summary = crate::tools::bank::build(&crate::tools::bank::Args {
            // Calibrated by cross-fitting: no calibration alphabets.
            screen: screen(folds[k].clone(), Vec::new()),
            data: args.data.clone(),
            reps: args.calib_reps,
            out: bank.clone(),
            cross_fit,
            calibration_from: None,
        })?;
        std::fs::write(
            bank.with_extension("json"),
            serde_json::to_vec_pretty(&summary)?,
        )?;
    }
    // The other methods of `outliers` calibrate on another alphabet the fold model never
    // saw; the guardian figures use the cross-fitted bank.
    let calib = folds[k]
        .iter()
        .find(|a| *a != alphabet)
        .context("a fold of one alphabet has nothing to calibrate the baselines on")?;
    let report = crate::eval::outliers::measure(&crate::eval::outliers::Args {
        screen: screen(vec![alphabet.to_owned()], vec![calib.clone()]),
        data: args.data.clone(),
        strokes: args.strokes.clone(),
        calib_reps: args.calib_reps,
        reps: args.reps,
        sources: args.sources,
        siamese_model: None,
        calibration_from: Some(bank.clone()),
        wrong_task_tolerance: None,
        near_misses: Vec::new(),
        near_miss_share: 0.25,
        near_miss_from_geometry: false,
        near_miss_form: crate::eval::outliers::NearMissForm::Margin,
        ink: false,
        ink_share: 0.25,
        ink_quantile: 0.9,
        ink_centred: false,
        ink_from_embedding: false,
        out: None,
        json: false,
    })?;
    let g = report
        .methods
        .iter()
        .find(|m| m.method == crate::eval::outliers::Method::Guardian)
        .context("outliers reported no guardian method")?;
    let mut figures = BTreeMap::new();
    figures.insert("genuine-false-reject".to_owned(), g.genuine_false_reject);
    let mut detection = f64::NAN;
    for f in &g.faults {
        // Wrong task at severity 1: the plan claims any other enrolled class (all of one
        // alphabet here); at 0.25 the class whose prototype is nearest to its own.
        if f.fault == "wrong-task" && (f.severity - 1.0).abs() < 1e-9 {
            detection = f.detection;
            figures.insert("wrong-task-auroc".into(), f.auroc);
            figures.insert("wrong-task-tpr-at-1pct-fpr".into(), f.tpr_at_1pct_fpr);
        }
        if f.fault == "wrong-task" && (f.severity - 0.25).abs() < 1e-9 {
            figures.insert("nearest-class-detected".into(), f.detection);
        }
        if SHAPE_FAULTS.contains(&f.fault.as_str()) && (f.severity - 0.5).abs() < 1e-9 {
            figures.insert(format!("{}-auroc@0.5", f.fault), f.auroc);
        }
    }
    anyhow::ensure!(
        detection.is_finite(),
        "outliers reported no wrong-task figure at severity 1"
    );
    Ok(Row {
        kind: "outliers".into(),
        value: detection,
        model_version: report.model_version,
        figures,
        ..base.clone()
    })
}

fn read_rows(path: &Path) -> anyhow::Result<Vec<Row>> {
    match std::fs::read_to_string(path) {
        Ok(text) => text
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| serde_json::from_str(l).with_context(|| format!("{}: {l}", path.display())))
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(e.into()),
    }
}

fn append_rows(path: &Path, rows: &[Row]) -> anyhow::Result<()> {
    use std::io::Write as _;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)?;
    let mut text = String::new();
    for r in rows {
        text.push_str(&serde_json::to_string(r)?);
        text.push('\n');
    }
    f.write_all(text.as_bytes())?;
    f.sync_data()?;
    Ok(())
}

/// Run `guardian-lab kfold`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    anyhow::ensure!(args.folds >= 2, "--folds must be at least 2");
    let data = Dataset::load(&args.data.dataset)?;
    let folds = assign_folds(&data.alphabets, &args.dense, args.folds);
    anyhow::ensure!(
        folds.iter().all(|f| !f.is_empty()),
        "{} alphabets cannot fill {} folds",
        data.alphabets.len(),
        args.folds
    );
    std::fs::create_dir_all(&args.out)?;
    std::fs::write(
        args.out.join("folds.json"),
        serde_json::to_vec_pretty(&folds)?,
    )?;
    let selected: Vec<usize> = (0..args.folds)
        .filter(|k| args.only_folds.is_empty() || args.only_folds.contains(k))
        .collect();
    let results = args.out.join("results.jsonl");
    let done = read_rows(&results)?;
    let have = |k: usize, a: &str, model: &str, kind: &str| {
        done.iter()
            .any(|r| r.fold == k && r.alphabet == a && r.model == model && r.kind == kind)
    };
    let variants = args
        .variant
        .iter()
        .map(|v| Ok((v.name.clone(), Dataset::load(&v.file)?)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let compare = args
        .compare
        .as_ref()
        .map(|p| crate::dataset::model_for(&data, p))
        .transpose()?;

    // Train and measure the episodes of every selected fold.
    for &k in &selected {
        let dir = fold_dir(&args.out, k);
        let train: Vec<String> = data
            .alphabets
            .iter()
            .filter(|a| !folds[k].contains(a))
            .cloned()
            .collect();
        // A fused model is both branches' product: with it there, nothing is trained (a
        // fold model kept without its training runs is measured as it is).
        if !dir.join("model.safetensors").exists() {
            train_branch(args, &train, RECIPE_SEQUENCE, &dir.join("seq"))?;
            train_branch(args, &train, RECIPE_PICTURE, &dir.join("pic"))?;
        }
        let model = crate::dataset::model_for(&data, &fuse(&dir)?)?;
        for a in &folds[k] {
            let base = Row::blank(k, a, args.dense.contains(a), "fold", "episodes");
            let mut rows = Vec::new();
            if !have(k, a, "fold", "episodes") {
                rows.extend(episode_rows(&data, &model, a, &base, args)?);
            }
            if let Some(c) = &compare
                && !args.compare_trained_on.contains(a)
                && !have(k, a, "compare", "episodes")
            {
                let b = Row {
                    model: "compare".into(),
                    ..base.clone()
                };
                rows.extend(episode_rows(&data, c, a, &b, args)?);
            }
            for (name, vdata) in &variants {
                if vdata.alphabets.contains(a) && !have(k, a, name, "episodes") {
                    let b = Row {
                        model: name.clone(),
                        ..base.clone()
                    };
                    rows.extend(episode_rows(vdata, &model, a, &b, args)?);
                }
            }
            append_rows(&results, &rows)?;
        }
        eprintln!("kfold: fold {k} measured ({} alphabets)", folds[k].len());
    }

    // Go / no-go, calibrated by cross-fitting: needs every fold model.
    let all_models =
        (0..args.folds).all(|k| fold_dir(&args.out, k).join("model.safetensors").exists());
    if !args.no_outliers && all_models {
        let kinds: &[(&str, bool)] = if args.dense_calibration {
            &[("fold", false), ("dense-calibration", true)]
        } else {
            &[("fold", false)]
        };
        for &k in &selected {
            for (a, &(label, dense_only)) in folds[k]
                .iter()
                .flat_map(|a| kinds.iter().map(move |kind| (a, kind)))
            {
                if have(k, a, label, "outliers") || (dense_only && !args.dense.contains(a)) {
                    continue;
                }
                let base = Row::blank(k, a, args.dense.contains(a), label, "outliers");
                match outlier_row(args, &folds, k, a, &base, dense_only) {
                    Ok(row) => append_rows(&results, &[row])?,
                    Err(e) => eprintln!("kfold: {a}: no go / no-go figures: {e:#}"),
                }
            }
        }
    } else if !args.no_outliers {
        eprintln!("kfold: go / no-go figures wait for every fold model (cross-fitted calibration)");
    }

    let rows = read_rows(&results)?;
    let report = markdown(&folds, &rows, args);
    std::fs::write(args.out.join("REPORT.md"), &report)?;
    print!("{report}");
    Ok(())
}

fn mean(xs: &[f64]) -> f64 {
    xs.iter().sum::<f64>() / xs.len().max(1) as f64
}

/// The mean over alphabets, then the smallest and largest per-fold mean and the standard
/// deviation of the per-fold means.
fn spread(per_fold: &[f64], all: &[f64]) -> String {
    if per_fold.is_empty() {
        return "-".into();
    }
    let m = mean(per_fold);
    let sd = (per_fold.iter().map(|x| (x - m).powi(2)).sum::<f64>()
        / (per_fold.len().saturating_sub(1)).max(1) as f64)
        .sqrt();
    let lo = per_fold.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = per_fold.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    format!("{:.3} (folds {lo:.3}–{hi:.3}, sd {sd:.3})", mean(all))
}

/// The report: targets first, then every alphabet.
pub fn markdown(folds: &[Vec<String>], rows: &[Row], args: &Args) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let ep = |r: &Row, model: &str, way: usize, shot: usize| {
        r.kind == "episodes" && r.model == model && r.way == Some(way) && r.shot == Some(shot)
    };
    let _ = writeln!(
        s,
        "# K-fold by alphabet: {} folds, {} alphabets\n\n\
         Each fold's model (both branches of the shipped recipe, {} x {} steps, fused) was \
         trained on the other folds' alphabets only; episodes are within one held-out \
         alphabet ({} episodes, seed {}); go / no-go figures are 5-shot with a cross-fitted \
         calibration (the other folds' models on the alphabets they never saw). Each figure \
         is the mean over alphabets, then (in brackets) the lowest and highest of the \
         per-fold means and their standard deviation across folds.\n",
        folds.len(),
        folds.iter().map(Vec::len).sum::<usize>(),
        args.epochs,
        args.steps_per_epoch,
        args.episodes,
        args.seed,
    );
    // Per-fold means of a selection of rows.
    let per_fold = |f: &dyn Fn(&Row) -> bool| -> (Vec<f64>, Vec<f64>) {
        let mut fm = Vec::new();
        let mut all = Vec::new();
        for k in 0..folds.len() {
            let v: Vec<f64> = rows
                .iter()
                .filter(|r| r.fold == k && f(r) && r.value.is_finite())
                .map(|r| r.value)
                .collect();
            if !v.is_empty() {
                fm.push(mean(&v));
            }
            all.extend(v);
        }
        (fm, all)
    };
    let _ = writeln!(s, "## Targets\n");
    let _ = writeln!(s, "| figure | all alphabets | dense alphabets | target |");
    let _ = writeln!(s, "|---|---|---|---|");
    for (way, shot) in SPECS {
        let (fa, aa) = per_fold(&|r| ep(r, "fold", way, shot));
        let (fd, ad) = per_fold(&|r| ep(r, "fold", way, shot) && r.dense);
        let target = if (way, shot) == (20, 1) {
            ">= 0.95"
        } else {
            ""
        };
        let _ = writeln!(
            s,
            "| {way}-way {shot}-shot accuracy, mean of {} / {} alphabets | {} | {} | {target} |",
            aa.len(),
            ad.len(),
            spread(&fa, &aa),
            spread(&fd, &ad)
        );
    }
    let worst = |dense_only: bool| {
        rows.iter()
            .filter(|r| ep(r, "fold", 20, 1) && (!dense_only || r.dense))
            .min_by(|a, b| a.value.total_cmp(&b.value))
            .map_or("-".into(), |r| format!("{:.3} ({})", r.value, r.alphabet))
    };
    let _ = writeln!(
        s,
        "| 20-way 1-shot, worst alphabet | {} | {} | >= 0.85 |",
        worst(false),
        worst(true)
    );
    // A go / no-go figure: its mean over alphabets and its per-fold spread.
    let out_of = |f: &dyn Fn(&Row) -> f64, dense: bool, model: &str| {
        let mut per = Vec::new();
        let mut all = Vec::new();
        for k in 0..folds.len() {
            let v: Vec<f64> = rows
                .iter()
                .filter(|r| {
                    r.fold == k && r.kind == "outliers" && r.model == model && (!dense || r.dense)
                })
                .map(f)
                .filter(|x| x.is_finite())
                .collect();
            if !v.is_empty() {
                per.push(mean(&v));
            }
            all.extend(v);
        }
        spread(&per, &all)
    };
    let out = |f: &dyn Fn(&Row) -> f64, dense: bool| out_of(f, dense, "fold");
    let fig = |name: &'static str| move |r: &Row| r.figures.get(name).copied().unwrap_or(f64::NAN);
    let _ = writeln!(
        s,
        "| 5-shot wrong task detected (cross-fitted) | {} | {} | >= 0.98 |",
        out(&|r: &Row| r.value, false),
        out(&|r: &Row| r.value, true)
    );
    let _ = writeln!(
        s,
        "| 5-shot nearest class claimed, detected | {} | {} | |",
        out(&fig("nearest-class-detected"), false),
        out(&fig("nearest-class-detected"), true)
    );
    let _ = writeln!(
        s,
        "| genuine false rejects | {} | {} | <= 0.01 |",
        out(&fig("genuine-false-reject"), false),
        out(&fig("genuine-false-reject"), true)
    );
    if rows.iter().any(|r| r.model == "dense-calibration") {
        let _ = writeln!(
            s,
            "| … calibrated on the dense alphabets only: wrong task detected | | {} | >= 0.98 |",
            out_of(&|r: &Row| r.value, true, "dense-calibration")
        );
        let _ = writeln!(
            s,
            "| … calibrated on the dense alphabets only: genuine false rejects | | {} | <= 0.01 |",
            out_of(&fig("genuine-false-reject"), true, "dense-calibration")
        );
    }
    let min_shape = |r: &Row| {
        SHAPE_FAULTS
            .iter()
            .filter_map(|f| r.figures.get(&format!("{f}-auroc@0.5")).copied())
            .fold(f64::NAN, f64::min)
    };
    for f in SHAPE_FAULTS {
        let key = format!("{f}-auroc@0.5");
        let g = move |r: &Row| r.figures.get(&key).copied().unwrap_or(f64::NAN);
        let _ = writeln!(
            s,
            "| {f} at severity 0.5, AUROC | {} | {} | >= 0.98 |",
            out(&g, false),
            out(&g, true)
        );
    }
    let _ = writeln!(
        s,
        "| weakest shape fault at 0.5 per alphabet, AUROC | {} | {} | >= 0.98 |",
        out(&min_shape, false),
        out(&min_shape, true)
    );

    // Other models and variants on the same episodes.
    let others: Vec<String> = rows
        .iter()
        .filter(|r| r.model != "fold")
        .map(|r| r.model.clone())
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    if !others.is_empty() {
        let _ = writeln!(
            s,
            "\n## Paired: the fold models against other models and datasets\n\n\
             `compare`: the model `{}` (`--compare`) on the alphabets it was not trained on; a variant: the fold \
             model on another dataset of the same drawings. Same episodes (seed), same \
             alphabets in both columns.\n\n| rows | alphabets | spec | fold model | other | other − fold |\n|---|---|---|---|---|---|",
            rows.iter()
                .find(|r| r.model == "compare")
                .map_or("-", |r| r.model_version.as_str())
        );
        for o in &others {
            for (way, shot) in SPECS {
                let mut a = Vec::new();
                let mut b = Vec::new();
                for r in rows.iter().filter(|r| ep(r, o, way, shot)) {
                    if let Some(f) = rows
                        .iter()
                        .find(|x| ep(x, "fold", way, shot) && x.alphabet == r.alphabet)
                    {
                        a.push(f.value);
                        b.push(r.value);
                    }
                }
                if !a.is_empty() {
                    let _ = writeln!(
                        s,
                        "| {o} | {} | {way}-way {shot}-shot | {:.3} | {:.3} | {:+.3} |",
                        a.len(),
                        mean(&a),
                        mean(&b),
                        mean(&b) - mean(&a)
                    );
                }
            }
        }
    }

    let _ = writeln!(
        s,
        "\n## Every alphabet\n\n| fold | alphabet | dense | 2-way | 10-way | 20-way | 20-way 5-shot | wrong task detected | false rejects | weakest shape AUROC@0.5 |\n|---|---|---|---|---|---|---|---|---|---|"
    );
    for (k, f) in folds.iter().enumerate() {
        for a in f {
            let cell = |way, shot| {
                rows.iter()
                    .find(|r| r.alphabet == *a && ep(r, "fold", way, shot))
                    .map_or("-".into(), |r| format!("{:.3}", r.value))
            };
            let o = rows
                .iter()
                .find(|r| r.alphabet == *a && r.kind == "outliers" && r.model == "fold");
            let _ = writeln!(
                s,
                "| {k} | {a} | {} | {} | {} | {} | {} | {} | {} | {} |",
                if args.dense.contains(a) { "yes" } else { "" },
                cell(2, 1),
                cell(10, 1),
                cell(20, 1),
                cell(20, 5),
                o.map_or("-".into(), |r| format!("{:.3}", r.value)),
                o.and_then(|r| r.figures.get("genuine-false-reject"))
                    .map_or("-".into(), |v| format!("{v:.4}")),
                o.map_or("-".into(), |r| format!("{:.3}", min_shape(r))),
            );
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn folds_spread_the_dense_alphabets_and_cover_every_alphabet_once() {
        let all = names(&["A", "B", "C", "D", "E", "F", "G", "x", "y"]);
        let dense = names(&["x", "y", "G"]);
        let folds = assign_folds(&all, &dense, 3);
        assert_eq!(folds[0], names(&["G", "A", "D"]));
        assert_eq!(folds[1], names(&["x", "B", "E"]));
        assert_eq!(folds[2], names(&["y", "C", "F"]));
        let mut seen: Vec<String> = folds.concat();
        seen.sort();
        let mut want = all.clone();
        want.sort();
        assert_eq!(seen, want);
    }

    /// The typed recipe is the one `models/MODEL.md` ("How to retrain") gives as command
    /// lines, and `--train-args` still overrides it.
    #[test]
    fn the_branch_arguments_are_the_documented_recipe() {
        let args = Args {
            data: DatasetArgs {
                dataset: "d.safetensors".into(),
            },
            strokes: StrokesArgs {
                strokes: vec!["s1".into(), "s2".into()],
            },
            out: "o".into(),
            folds: 5,
            dense: names(&DENSE_ALPHABETS),
            only_folds: vec![],
            steps_per_epoch: 7,
            epochs: 3,
            train_args: None,
            episodes: 10,
            seed: 0,
            no_outliers: true,
            dense_calibration: false,
            sources: 1,
            calib_reps: 1,
            reps: 1,
            variant: vec![],
            compare: None,
            compare_trained_on: vec![],
            threads: 0,
        };
        let train = names(&["A", "B"]);
        let documented = |branch: &str, out: &str| {
            let common = "--fault-share 1.0 --fault-variants 8 --fault-weight 1 --fault-margin 0.4 --class-augment --embed-dim 64 --seed 1";
            let line = format!(
                "train --dataset d.safetensors --train-alphabets A,B --out {out} --quiet \
                 --strokes s1,s2 --schedule one-cycle --steps-per-epoch 7 --epochs 3 {branch} {common}"
            );
            let cli = TrainCli::try_parse_from(line.split_whitespace().filter(|w| *w != "\\"))
                .expect("parses");
            format!("{:?}", cli.args)
        };
        let seq = branch_args(&args, &train, RECIPE_SEQUENCE, Path::new("o/seq"), false).unwrap();
        assert_eq!(
            format!("{seq:?}"),
            documented(
                "--channels 32,64,128 --reverse-average --loss supcon --margin 0.1 --p-classes 64",
                "o/seq"
            )
        );
        let pic = branch_args(&args, &train, RECIPE_PICTURE, Path::new("o/pic"), true).unwrap();
        assert!(pic.resume && pic.class_augment && pic.val_alphabets.is_empty());
        let pic = TrainArgs {
            resume: false,
            ..pic
        };
        assert_eq!(
            format!("{pic:?}"),
            documented(
                "--features picture --channels 16,32,64,128 --kernel 3 --loss supcon --margin 0.1 --p-classes 64",
                "o/pic"
            )
        );
        // --train-args comes last and overrides the recipe.
        let args = Args {
            train_args: Some("--p-classes 32 --kernel 5".into()),
            ..args
        };
        let a = branch_args(&args, &train, RECIPE_PICTURE, Path::new("o/pic"), false).unwrap();
        assert_eq!((a.p_classes, a.kernel, a.embed_dim), (32, 5, 64));
        assert_eq!(a.channels, [16, 32, 64, 128]);
        // Every setting names a train option (else --train-args could not override it).
        let cmd = TrainCli::command();
        for (id, _) in RECIPE_COMMON
            .iter()
            .chain(RECIPE_SEQUENCE)
            .chain(RECIPE_PICTURE)
        {
            assert!(cmd.get_arguments().any(|a| a.get_id() == *id), "{id}");
        }
    }

    #[test]
    fn variants_parse() {
        let v: Variant = "simplified=/d/s.safetensors".parse().expect("parses");
        assert_eq!(v.name, "simplified");
        assert!("nofile=".parse::<Variant>().is_err());
        assert!("plain".parse::<Variant>().is_err());
    }
}
