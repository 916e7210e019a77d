//! `guardian-lab cell`: how the screen does on manipulation cells it never saw
//! (`guardian-cells` families), anchored (place and shape) against today's decision (shape
//! and canvas geometry only), through the product's own enrollment and check
//! (`guardian_screen::check`) with the shipped model and the shipped default bank's
//! calibration.
//!
//! Protocol, per family kind and per family (seeds from `--seed`; the layout moves, turns
//! and mirrors with the seed): every task enrolls `--shots` runs; `--runs` other runs per
//! task are
//! - **identified** (right when the first class named is the task);
//! - **checked as themselves** (genuine: right when go);
//! - **claimed as the nearest other task** of the family (the neighbouring bin or slot, the
//!   other route or approach: right when no-go), i.e. a run of task `j` claiming task `i`;
//! - with every [`Fault`] (shifted place, missed approach, truncated), claiming their task
//!   (right when no-go).
//!
//! `--calibrate` instead sweeps the place rule on the families drawn (use seeds the report
//! does not use): for each spread factor, the place excess of genuine runs and of runs
//! claiming the nearest other task, the tolerance that rejects at most 0.5 % of genuine
//! runs, and what it detects.

use std::path::PathBuf;

use anyhow::Context as _;
use guardian_bank::ClassBank;
use guardian_cells::{Cell as Runs, Family, FamilyKind, Fault};
use guardian_models::embedder::Embedder;
use guardian_robot::cell::Cell;
use guardian_robot::place::{self, PlaceRule, PlaceSignature};
use guardian_screen::check::{self, Station};
use guardian_shared::trajectory::Waypoint;
use guardian_shared::verdict::NoGoReason;
use guardian_shared::workcell::Workcell;

/// `guardian-lab cell` arguments.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model.
    #[arg(long, default_value = "models/embedder.safetensors")]
    pub model: PathBuf,
    /// The bank whose calibration (thresholds, wrong-task tolerance) the cell's classes
    /// take, as a daemon started with it gives them; its classes stay enrolled beside them.
    #[arg(long, default_value = "models/default-bank.gcb")]
    pub bank: PathBuf,
    /// Family kinds (default: all).
    #[arg(long, value_delimiter = ',')]
    pub kinds: Vec<FamilyKind>,
    /// Families per kind.
    #[arg(long, default_value_t = 5)]
    pub families: u64,
    /// First family seed (the report uses 1000 on; calibrate on others).
    #[arg(long, default_value_t = 1000)]
    pub seed: u64,
    /// Distance between neighbouring bins or pallet slots (m).
    #[arg(long, default_value_t = 0.06)]
    pub spacing: f64,
    /// Runs enrolled per task.
    #[arg(long, default_value_t = 5)]
    pub shots: u64,
    /// Test runs per task.
    #[arg(long, default_value_t = 10)]
    pub runs: u64,
    /// The place rule's spread factor.
    #[arg(long, default_value_t = PlaceRule::DEFAULT.spread)]
    pub place_spread: f32,
    /// The place rule's factor for route points.
    #[arg(long, default_value_t = PlaceRule::DEFAULT.route)]
    pub place_route: f32,
    /// The factor on the class thresholds of the shape rule.
    #[arg(long, default_value_t = PlaceRule::DEFAULT.shape)]
    pub shape_scale: f32,
    /// The place rule's tolerance (m).
    #[arg(long, default_value_t = PlaceRule::DEFAULT.tolerance)]
    pub place_tolerance: f32,
    /// Sweep the place rule instead of reporting (see the module docs).
    #[arg(long)]
    pub calibrate: bool,
}

/// Right answers out of all, per measure.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Count {
    /// Right answers.
    pub right: u64,
    /// All answers.
    pub all: u64,
}

impl Count {
    fn add(&mut self, right: bool) {
        self.right += u64::from(right);
        self.all += 1;
    }

    /// The share right (NaN for none).
    pub fn rate(&self) -> f64 {
        self.right as f64 / self.all as f64
    }
}

/// One decision's figures on a family kind.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Figures {
    /// The first class named is the task.
    pub identify: Count,
    /// A genuine run is go.
    pub genuine_go: Count,
    /// A run of the nearest other task claiming this one is no-go.
    pub wrong_task_no_go: Count,
    /// Per fault, a faulty run is no-go.
    pub faults: Vec<(Fault, Count)>,
    /// Why genuine runs were refused: reason and count.
    pub refused: std::collections::BTreeMap<String, u64>,
    /// The whole check of each genuine run in process (prepare and decide, µs), the two
    /// decisions interleaved run by run.
    pub check_us: Vec<f64>,
}

/// The median of `v` (NaN for none).
fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

impl Figures {
    fn new() -> Self {
        Self {
            faults: Fault::ALL.iter().map(|f| (*f, Count::default())).collect(),
            ..Self::default()
        }
    }
}

/// The stations compared: anchored, and today's (shape and canvas geometry), both with
/// the canvas rules off as in a cell.
fn stations(rule: PlaceRule) -> (Station, Station) {
    let plain = Station::panda().with_workcell(Workcell::OFF);
    let anchored = plain.clone().with_cell(Cell {
        anchored: true,
        place: rule,
        ..Cell::NONE
    });
    (anchored, plain)
}

/// Enroll every task of `family` from `shots` runs into `bank` at `station`.
fn enroll(
    model: &Embedder,
    station: &Station,
    bank: &mut ClassBank,
    runs: &Runs,
    family: &Family,
    shots: u64,
) -> anyhow::Result<()> {
    for (i, task) in family.tasks.iter().enumerate() {
        let plans = (0..shots)
            .map(|d| runs.run(task, run_seed(family, i, d)))
            .collect::<Result<Vec<_>, _>>()?;
        let e = check::enrollment(model, station, &plans)?;
        bank.enroll_placed(
            &class_name(family, i),
            &e.embeddings,
            &e.geometry,
            &e.examples,
            &e.place,
        )?;
    }
    Ok(())
}

fn run_seed(family: &Family, task: usize, run: u64) -> u64 {
    family.seed * 1_000_000 + task as u64 * 1000 + run
}

fn class_name(family: &Family, task: usize) -> String {
    format!(
        "{}-{}/{}",
        family.kind.name(),
        family.seed,
        family.tasks[task].name
    )
}

/// The figures of both decisions (anchored, today's) on the families of `kind`.
pub fn measure(
    model: &Embedder,
    base: &ClassBank,
    kind: FamilyKind,
    args: &Args,
) -> anyhow::Result<(Figures, Figures)> {
    let (anchored, plain) = stations(PlaceRule {
        spread: args.place_spread,
        route: args.place_route,
        shape: args.shape_scale,
        tolerance: args.place_tolerance,
    });
    let runs = Runs::default();
    let (mut a, mut p) = (Figures::new(), Figures::new());
    for seed in args.seed..args.seed + args.families {
        let family = Family::new(kind, seed, args.spacing);
        let mut bank = base.clone();
        enroll(model, &anchored, &mut bank, &runs, &family, args.shots)?;
        let decide = |station: &Station, plan: &[Waypoint], claimed: usize| {
            let name = class_name(&family, claimed);
            // The whole check as the daemon runs it, timed.
            let start = std::time::Instant::now();
            let prepared = check::prepare(model, station, plan)?;
            let verdict = check::decide(&bank, station, &prepared, &name, 5);
            let micros = start.elapsed().as_secs_f64() * 1e6;
            Ok::<_, anyhow::Error>((micros, verdict.reason().map(refusal)))
        };
        for (i, task) in family.tasks.iter().enumerate() {
            let other = family.nearest_other(i);
            for r in args.shots..args.shots + args.runs {
                let plan = runs.run(task, run_seed(&family, i, r))?;
                let wrong = runs.run(&family.tasks[other], run_seed(&family, other, r))?;
                let e = check::embed_plan(model, &anchored, &plan)??;
                let name = class_name(&family, i);
                let rule = &anchored.cell().place;
                let place = e.place.as_ref().context("anchored plans have a place")?;
                a.identify
                    .add(bank.ranked_in_place(&e.embedding, place, rule)[0].name == name);
                p.identify
                    .add(bank.nearest(&e.embedding, 1)[0].name == name);
                for (f, s) in [(&mut a, &anchored), (&mut p, &plain)] {
                    let (micros, why) = decide(s, &plan, i)?;
                    f.check_us.push(micros);
                    f.genuine_go.add(why.is_none());
                    if let Some(why) = why {
                        *f.refused.entry(why).or_default() += 1;
                    }
                    f.wrong_task_no_go.add(decide(s, &wrong, i)?.1.is_some());
                }
                for (k, fault) in Fault::ALL.iter().enumerate() {
                    let bad = runs.faulty(task, *fault, run_seed(&family, i, r))?;
                    a.faults[k].1.add(decide(&anchored, &bad, i)?.1.is_some());
                    p.faults[k].1.add(decide(&plain, &bad, i)?.1.is_some());
                }
            }
        }
    }
    Ok((a, p))
}

/// Place excess of genuine runs and of runs of the nearest other task, under `spread`,
/// over the families of `kind`.
fn excesses(
    model: &Embedder,
    base: &ClassBank,
    kind: FamilyKind,
    args: &Args,
    spread: f32,
    route: f32,
) -> anyhow::Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
    let rule = PlaceRule {
        spread,
        route,
        shape: 1.0,
        tolerance: 1.0,
    };
    let (anchored, _) = stations(rule);
    let runs = Runs::default();
    let (mut genuine, mut wrong, mut shape) = (Vec::new(), Vec::new(), Vec::new());
    for seed in args.seed..args.seed + args.families {
        let family = Family::new(kind, seed, args.spacing);
        let mut bank = base.clone();
        enroll(model, &anchored, &mut bank, &runs, &family, args.shots)?;
        for (i, task) in family.tasks.iter().enumerate() {
            let class = bank
                .class(&class_name(&family, i))
                .context("enrolled")?
                .place
                .clone();
            let other = family.nearest_other(i);
            for r in args.shots..args.shots + args.runs {
                let sig = |plan: Vec<Waypoint>| {
                    let x = guardian_robot::workcell::inspect_with(
                        anchored.robot(),
                        &Workcell::OFF,
                        &plan,
                    )
                    .map(|i| PlaceSignature::of_plan(anchored.robot(), &i.resampled));
                    x.map(|s| place::score(&s, &class, &rule).map_or(f32::NAN, |s| s.excess))
                };
                let plan = runs.run(task, run_seed(&family, i, r))?;
                let d = check::decide(
                    &bank,
                    &anchored,
                    &check::prepare(model, &anchored, &plan)?,
                    &class_name(&family, i),
                    1,
                );
                if let (Some(dist), Some(t)) = (d.claimed_distance, d.threshold) {
                    shape.push(dist / t);
                }
                genuine.push(sig(plan)?);
                let w = runs.run(&family.tasks[other], run_seed(&family, other, r))?;
                wrong.push(sig(w)?);
            }
        }
    }
    Ok((genuine, wrong, shape))
}

/// A refusal's key in the report: the reason, with the nearest class of a wrong task and
/// the feature of a geometry stop (not their numbers, so that refusals add up).
fn refusal(reason: &NoGoReason) -> String {
    match reason {
        NoGoReason::WrongTask { nearest } => format!("WrongTask {{ nearest: {nearest:?} }}"),
        NoGoReason::GeometryMismatch { feature, .. } => {
            format!("GeometryMismatch {{ feature: {feature:?} }}")
        }
        NoGoReason::Outlier => "Outlier".to_owned(),
        NoGoReason::UnknownClass => "UnknownClass".to_owned(),
        other => format!("{other:?}"),
    }
}

/// Run `guardian-lab cell`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let model =
        Embedder::load(&args.model).with_context(|| format!("loading {}", args.model.display()))?;
    let base =
        ClassBank::load(&args.bank).with_context(|| format!("loading {}", args.bank.display()))?;
    let kinds = if args.kinds.is_empty() {
        FamilyKind::ALL.to_vec()
    } else {
        args.kinds.clone()
    };
    println!(
        "cells: model {}, {} families per kind from seed {}, spacing {} m, {} shots, {} runs per task",
        model.version(),
        args.families,
        args.seed,
        args.spacing,
        args.shots,
        args.runs
    );
    if args.calibrate {
        let mut shapes = Vec::new();
        println!(
            "\n| kind | spread | route | genuine excess p99.5 (m) | wrong-task excess p1 (m) | detected at tolerance = p99.5 |"
        );
        println!("|---|---|---|---|---|---|");
        for kind in &kinds {
            for (spread, route) in [1.0f32, 1.5, 2.0]
                .into_iter()
                .flat_map(|s| [1.0f32, 2.0, 3.0].map(|r| (s, r)))
            {
                let (mut g, w, mut shape) = excesses(&model, &base, *kind, args, spread, route)?;
                if (spread, route) == (1.0, 1.0) {
                    shape.sort_by(f32::total_cmp);
                    let k = ((shape.len() as f64 * 0.995).ceil() as usize).clamp(1, shape.len());
                    shapes.push(format!(
                        "- {}: genuine distance / class threshold, p99.5 {:.3}, max {:.3}",
                        kind.name(),
                        shape[k - 1],
                        shape[shape.len() - 1]
                    ));
                }
                g.sort_by(f32::total_cmp);
                let t = g[((g.len() as f64 * 0.995).ceil() as usize).min(g.len()) - 1];
                let mut ws = w.clone();
                ws.sort_by(f32::total_cmp);
                let low = ws[(ws.len() as f64 * 0.01) as usize];
                let caught = w
                    .iter()
                    .filter(|e| {
                        PlaceRule {
                            tolerance: t,
                            ..PlaceRule::DEFAULT
                        }
                        .is_other_place(**e)
                    })
                    .count();
                println!(
                    "| {} | {spread} | {route} | {t:.4} | {low:.4} | {:.3} |",
                    kind.name(),
                    caught as f64 / w.len() as f64
                );
            }
        }
        println!("\nshape rule:");
        for s in shapes {
            println!("{s}");
        }
        return Ok(());
    }
    println!(
        "place rule: spread {}, tolerance {} m\n",
        args.place_spread, args.place_tolerance
    );
    let faults: Vec<&str> = Fault::ALL.iter().map(|f| f.name()).collect();
    println!(
        "| kind | decision | runs | identify | genuine go | wrong task no-go | {} no-go |",
        faults.join(" no-go | ")
    );
    println!("|---|---|---|---|---|---|{}", "---|".repeat(faults.len()));
    let (mut refused, mut timing) = (Vec::new(), Vec::new());
    for kind in &kinds {
        let (a, p) = measure(&model, &base, *kind, args)?;
        for (label, f) in [("anchored", &a), ("today", &p)] {
            let fs: Vec<String> = f
                .faults
                .iter()
                .map(|(_, c)| format!("{:.3}", c.rate()))
                .collect();
            println!(
                "| {} | {label} | {} | {:.3} | {:.3} | {:.3} | {} |",
                kind.name(),
                f.genuine_go.all,
                f.identify.rate(),
                f.genuine_go.rate(),
                f.wrong_task_no_go.rate(),
                fs.join(" | "),
            );
            refused.push(format!("{} {label}: {:?}", kind.name(), f.refused));
        }
        timing.push(format!(
            "- {}: anchored {:.0} us, today {:.0} us, ratio {:.2}",
            kind.name(),
            median(&a.check_us),
            median(&p.check_us),
            median(&a.check_us) / median(&p.check_us)
        ));
    }
    println!("\nwhole check in process, p50 (paired, same runs, this machine):");
    for t in timing {
        println!("{t}");
    }
    println!("\ngenuine runs refused, by reason:");
    for r in refused {
        println!("- {r}");
    }
    Ok(())
}
