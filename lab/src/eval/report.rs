//! `guardian-lab report`: a markdown report with PNG plots for a trained model on held-out
//! alphabets — accuracy vs N for the model and the baselines (paper Fig. 5), 10-way-1-shot
//! CMC curves (Fig. 6), per-class precision/recall/F1 and a confusion matrix on a 10-class
//! sample (Figs. 7-8), intra- vs inter-class distance distributions for raw trajectories, the
//! untrained and the trained network (Fig. 4), and the training curves.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use guardian_models::embedder::Embedder;
use plotters::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::IndexedRandom;

use crate::cli::DatasetArgs;
use crate::eval::{self, EpisodeSpec, Pool, Scorer};
use crate::train::EpochMetrics;
use guardian_omniglot::dataset::Dataset;

/// `guardian-lab report`: markdown report with plots for a trained model.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Trained embedder (triplet model).
    #[arg(long)]
    pub model: PathBuf,
    /// The dataset.
    #[command(flatten)]
    pub data: DatasetArgs,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Held-out alphabets to evaluate on, comma-separated (default: every alphabet).
    #[arg(long, value_delimiter = ',')]
    pub alphabets: Vec<String>,
    /// Siamese baseline model (default: `siamese.safetensors` beside `--model`; skipped if
    /// absent).
    #[arg(long)]
    pub siamese_model: Option<PathBuf>,
    /// Training metrics (default: `metrics.jsonl` beside `--model`; skipped if absent).
    #[arg(long)]
    pub metrics: Option<PathBuf>,
    /// Episodes per point.
    #[arg(long, default_value_t = 2000)]
    pub episodes: usize,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Force test-time reverse averaging on for the models.
    #[arg(long)]
    pub reverse_average: bool,
}

const COLORS: [RGBColor; 4] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(150, 150, 150),
];

/// A longer palette for plots with many series (ROC curves of every fault).
const MANY_COLORS: [RGBColor; 12] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
    RGBColor(0, 0, 0),
    RGBColor(255, 200, 0),
];

fn draw_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow::anyhow!("drawing: {e:?}")
}

/// Line plot of several named series over x.
fn line_plot(
    path: &Path,
    title: &str,
    xlabel: &str,
    ylabel: &str,
    series: &[(String, Vec<(f64, f64)>)],
    y_range: std::ops::Range<f64>,
) -> anyhow::Result<()> {
    let root = BitMapBackend::new(path, (900, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err)?;
    let (x0, x1) = series
        .iter()
        .flat_map(|(_, v)| v.iter().map(|p| p.0))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(x), b.max(x))
        });
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 24))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(x0..x1.max(x0 + 1.0), y_range)
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc(xlabel)
        .y_desc(ylabel)
        .draw()
        .map_err(draw_err)?;
    for (i, (name, pts)) in series.iter().enumerate() {
        let c = if series.len() > COLORS.len() {
            MANY_COLORS[i % MANY_COLORS.len()]
        } else {
            COLORS[i % COLORS.len()]
        };
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), c.stroke_width(2)))
            .map_err(draw_err)?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
            .map_err(draw_err)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::LowerLeft)
        .draw()
        .map_err(draw_err)?;
    root.present().map_err(draw_err)?;
    Ok(())
}

/// Histograms of same-class vs different-class distances, one panel per method.
fn distance_plot(path: &Path, panels: &[(String, Vec<f64>, Vec<f64>)]) -> anyhow::Result<()> {
    histogram_plot(
        path,
        panels,
        "squared distance",
        ["same class", "different class"],
        (1200, 420),
    )
}

/// Histograms of two score sets per panel.
fn histogram_plot(
    path: &Path,
    panels: &[(String, Vec<f64>, Vec<f64>)],
    xlabel: &str,
    labels: [&str; 2],
    size: (u32, u32),
) -> anyhow::Result<()> {
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err)?;
    let areas = root.split_evenly((1, panels.len()));
    for (area, (name, intra, inter)) in areas.iter().zip(panels) {
        let max = intra
            .iter()
            .chain(inter.iter())
            .fold(0.0f64, |a, &b| a.max(b))
            .max(1e-9);
        let bins = 40;
        let hist = |v: &[f64]| -> Vec<f64> {
            let mut h = vec![0.0; bins];
            for &x in v {
                let b = ((x / max) * bins as f64).floor() as usize;
                h[b.min(bins - 1)] += 1.0 / v.len().max(1) as f64;
            }
            h
        };
        let (hi, hx) = (hist(intra), hist(inter));
        let ymax = hi.iter().chain(hx.iter()).fold(0.0f64, |a, &b| a.max(b)) * 1.1;
        let mut chart = ChartBuilder::on(area)
            .caption(name, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(45)
            .build_cartesian_2d(0.0..max, 0.0..ymax.max(1e-3))
            .map_err(draw_err)?;
        chart
            .configure_mesh()
            .x_desc(xlabel)
            .y_desc("fraction")
            .draw()
            .map_err(draw_err)?;
        for (h, c, label) in [(&hi, COLORS[0], labels[0]), (&hx, COLORS[1], labels[1])] {
            let w = max / bins as f64;
            chart
                .draw_series(h.iter().enumerate().map(|(i, &y)| {
                    Rectangle::new(
                        [(i as f64 * w, 0.0), ((i + 1) as f64 * w, y)],
                        c.mix(0.5).filled(),
                    )
                }))
                .map_err(draw_err)?
                .label(label)
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 15, y + 5)], c.mix(0.5).filled())
                });
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(draw_err)?;
    }
    root.present().map_err(draw_err)?;
    Ok(())
}

/// ROC curves (one plot per method, every fault at moderate severity) and score
/// histograms (genuine vs faulty, one panel per fault at moderate severity, scores clipped
/// at 3; the calibrated threshold is 1) from `guardian-lab outliers` scores.
/// `raw` yields per method its name, its genuine scores and its faulty scores per
/// `fault@severity`.
pub fn outlier_plots<'a>(
    dir: &Path,
    raw: impl IntoIterator<
        Item = (
            &'a str,
            &'a [f32],
            &'a std::collections::BTreeMap<String, Vec<f32>>,
        ),
    >,
) -> anyhow::Result<()> {
    for (method, genuine, faulty) in raw {
        let mut series = Vec::new();
        let mut panels = Vec::new();
        for (key, v) in faulty {
            if !key.ends_with("@50") {
                continue;
            }
            let name = key.trim_end_matches("@50").to_owned();
            let roc = crate::eval::metrics::roc_curve(genuine, v);
            let step = (roc.len() / 150).max(1);
            let mut pts: Vec<(f64, f64)> = roc.iter().step_by(step).copied().collect();
            pts.push((1.0, 1.0));
            series.push((name.clone(), pts));
            let clip = |x: &f32| f64::from(*x).min(3.0);
            panels.push((
                name,
                genuine.iter().map(clip).collect(),
                v.iter().map(clip).collect(),
            ));
        }
        line_plot(
            &dir.join(format!("roc-{method}.png")),
            &format!("{method}: ROC, moderate severity"),
            "false-positive rate (genuine rejected)",
            "true-positive rate (faulty caught)",
            &series,
            0.0..1.0,
        )?;
        for (i, chunk) in panels.chunks(4).enumerate() {
            histogram_plot(
                &dir.join(format!("scores-{method}-{i}.png")),
                chunk,
                "score (no-go above 1)",
                ["genuine", "faulty"],
                (1400, 380),
            )?;
        }
    }
    Ok(())
}

/// Per-class precision/recall/F1 bars.
fn prf_plot(path: &Path, names: &[String], prf: &[(f64, f64, f64)]) -> anyhow::Result<()> {
    let root = BitMapBackend::new(path, (1100, 520)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err)?;
    let n = names.len();
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Per-class precision / recall / F1, 10-way-1-shot",
            ("sans-serif", 22),
        )
        .margin(15)
        .x_label_area_size(90)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..n as f64, 0.0..1.05)
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_labels(4 * n)
        .x_label_formatter(&|x| {
            // One label per class, at the left edge of its group of bars.
            if (x - x.round()).abs() > 1e-6 {
                return String::new();
            }
            names
                .get(x.round() as usize)
                .map(|s| short(s))
                .unwrap_or_default()
        })
        .disable_x_mesh()
        .draw()
        .map_err(draw_err)?;
    for (k, label) in ["precision", "recall", "F1"].iter().enumerate() {
        let c = COLORS[k];
        chart
            .draw_series(prf.iter().enumerate().map(|(i, v)| {
                let y = [v.0, v.1, v.2][k];
                let x0 = i as f64 + 0.1 + 0.27 * k as f64;
                Rectangle::new([(x0, 0.0), (x0 + 0.25, y)], c.filled())
            }))
            .map_err(draw_err)?
            .label(*label)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 15, y + 5)], c.filled()));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::LowerRight)
        .draw()
        .map_err(draw_err)?;
    root.present().map_err(draw_err)?;
    Ok(())
}

fn short(class: &str) -> String {
    // "Alphabet/characterNN" -> "Alph../cNN"
    let (a, c) = class.split_once('/').unwrap_or(("", class));
    let a: String = a.chars().take(6).collect();
    format!("{a}/{}", c.trim_start_matches("character"))
}

/// Confusion matrix heat map (rows true, columns predicted, row-normalised).
fn confusion_plot(path: &Path, names: &[String], m: &[Vec<usize>]) -> anyhow::Result<()> {
    let n = names.len();
    let root = BitMapBackend::new(path, (760, 700)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Confusion matrix, 10-way-1-shot (rows: true class)",
            ("sans-serif", 20),
        )
        .margin(15)
        .x_label_area_size(80)
        .y_label_area_size(110)
        .build_cartesian_2d((0..n).into_segmented(), (0..n).into_segmented())
        .map_err(draw_err)?;
    let label = |v: &SegmentValue<usize>, flip: bool| match v {
        SegmentValue::CenterOf(i) if *i < n => {
            let i = if flip { n.saturating_sub(i + 1) } else { *i };
            names.get(i).map(|s| short(s)).unwrap_or_default()
        }
        _ => String::new(),
    };
    chart
        .configure_mesh()
        .x_labels(n)
        .y_labels(n)
        .x_label_formatter(&|v| label(v, false))
        .y_label_formatter(&|v| label(v, true))
        .disable_mesh()
        .draw()
        .map_err(draw_err)?;
    chart
        .draw_series((0..n).flat_map(|r| {
            let total: usize = m[r].iter().sum();
            (0..n).map(move |c| {
                let v = m[r][c] as f64 / total.max(1) as f64;
                let shade = (255.0 * (1.0 - v)) as u8;
                let y = n - 1 - r;
                Rectangle::new(
                    [
                        (SegmentValue::Exact(c), SegmentValue::Exact(y)),
                        (SegmentValue::Exact(c + 1), SegmentValue::Exact(y + 1)),
                    ],
                    RGBColor(shade, shade, 255).filled(),
                )
            })
        }))
        .map_err(draw_err)?;
    chart
        .draw_series((0..n).flat_map(|r| {
            (0..n).map(move |c| {
                Text::new(
                    m[r][c].to_string(),
                    (SegmentValue::CenterOf(c), SegmentValue::CenterOf(n - 1 - r)),
                    ("sans-serif", 14).into_font().color(&BLACK),
                )
            })
        }))
        .map_err(draw_err)?;
    root.present().map_err(draw_err)?;
    Ok(())
}

/// Same-class and different-class squared distances over a sample of pairs.
fn pair_distances(v: &[Vec<f32>], labels: &[u32], pairs: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let idx: Vec<usize> = (0..v.len()).collect();
    let (mut intra, mut inter) = (Vec::new(), Vec::new());
    // All same-class pairs are rare; sample them per class.
    let n_classes = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
    let mut by_class = vec![Vec::new(); n_classes];
    for (i, &l) in labels.iter().enumerate() {
        by_class[l as usize].push(i);
    }
    let d = |a: usize, b: usize| -> f64 {
        v[a].iter()
            .zip(&v[b])
            .map(|(x, y)| f64::from((x - y) * (x - y)))
            .sum()
    };
    while intra.len() < pairs {
        let Some(c) = by_class.choose(&mut rng) else {
            break;
        };
        if c.len() < 2 {
            continue;
        }
        let p: Vec<&usize> = c.choose_multiple(&mut rng, 2).collect();
        intra.push(d(*p[0], *p[1]));
    }
    while inter.len() < pairs {
        let p: Vec<&usize> = idx.choose_multiple(&mut rng, 2).collect();
        if p.len() < 2 {
            break;
        }
        if labels[*p[0]] != labels[*p[1]] {
            inter.push(d(*p[0], *p[1]));
        }
    }
    (intra, inter)
}

/// Run `guardian-lab report`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let data = Dataset::load(&args.data.dataset)?;
    let pool = Pool::new(&data, &args.alphabets)?;
    let model = crate::dataset::model_for(&data, &args.model)?;
    let siamese_path = args
        .siamese_model
        .clone()
        .unwrap_or_else(|| args.model.with_file_name("siamese.safetensors"));
    let siamese = if siamese_path.exists() {
        Some(crate::dataset::model_for(&data, &siamese_path)?)
    } else {
        None
    };
    let metrics_path = args
        .metrics
        .clone()
        .unwrap_or_else(|| args.model.with_file_name("metrics.jsonl"));

    let emb = pool.embed(&model)?;
    let siam_emb = siamese.as_ref().map(|s| pool.embed(s)).transpose()?;
    let raw = eval::standardised_raw(&pool.xs, pool.joints);
    let max_way = pool.class_names.len().min(20);
    let mut md = String::new();
    writeln!(md, "# Few-shot report: model `{}`\n", model.version())?;
    writeln!(
        md,
        "Dataset `{}`; evaluation alphabets {:?} ({} classes, {} drawings); {} episodes per \
         point, seed {}. Accuracy ± half-width of the 95% CI. Generated by:\n\n```\n\
         guardian-lab report --model {} --dataset {} --out {} --alphabets {} --siamese-model {} \
         --metrics {} --episodes {} --seed {}\n```\n",
        args.data.dataset.display(),
        pool.alphabets,
        pool.class_names.len(),
        pool.xs.len(),
        args.episodes,
        args.seed,
        args.model.display(),
        args.data.dataset.display(),
        args.out.display(),
        pool.alphabets.join(","),
        siamese_path.display(),
        metrics_path.display(),
        args.episodes,
        args.seed
    )?;
    writeln!(md, "Architecture: `{}`\n", model.config_json())?;

    // Accuracy vs N.
    let mut methods: Vec<(&str, Scorer<'_>)> = vec![("triplet", Scorer::Prototype(&emb))];
    if let Some(e) = &siam_emb {
        methods.push(("siamese", Scorer::Prototype(e)));
    }
    methods.push(("1-NN raw", Scorer::Nearest(&raw)));
    methods.push(("random", Scorer::Random));
    let ways: Vec<usize> = (2..=max_way).collect();
    let mut table: Vec<(String, Vec<eval::EpisodeResult>)> = Vec::new();
    for (name, scorer) in methods.iter_mut() {
        let mut rows = Vec::new();
        for &way in &ways {
            let spec = EpisodeSpec {
                way,
                shot: 1,
                episodes: args.episodes,
                seed: args.seed,
            };
            rows.push(eval::run_episodes(&pool.labels, &spec, scorer)?);
        }
        table.push((name.to_string(), rows));
    }
    let series: Vec<(String, Vec<(f64, f64)>)> = table
        .iter()
        .map(|(n, rows)| {
            (
                n.clone(),
                rows.iter().map(|r| (r.way as f64, r.accuracy)).collect(),
            )
        })
        .collect();
    line_plot(
        &args.out.join("accuracy-vs-way.png"),
        "N-way-1-shot accuracy on held-out alphabets",
        "N (classes per episode)",
        "accuracy",
        &series,
        0.0..1.02,
    )?;
    writeln!(
        md,
        "## Accuracy vs N (1-shot)\n\n![accuracy vs N](accuracy-vs-way.png)\n"
    )?;
    write!(md, "| N |")?;
    for (n, _) in &table {
        write!(md, " {n} |")?;
    }
    writeln!(md)?;
    writeln!(md, "|---|{}", "---|".repeat(table.len()))?;
    for (i, way) in ways.iter().enumerate() {
        write!(md, "| {way} |")?;
        for (_, rows) in &table {
            write!(md, " {:.4} ± {:.4} |", rows[i].accuracy, rows[i].ci95)?;
        }
        writeln!(md)?;
    }
    writeln!(md)?;

    // CMC 10-way-1-shot.
    let way10 = 10.min(max_way);
    let cmc_series: Vec<(String, Vec<(f64, f64)>)> = table
        .iter()
        .filter_map(|(n, rows)| {
            rows.iter().find(|r| r.way == way10).map(|r| {
                (
                    n.clone(),
                    r.cmc
                        .iter()
                        .enumerate()
                        .map(|(k, &c)| ((k + 1) as f64, c))
                        .collect(),
                )
            })
        })
        .collect();
    line_plot(
        &args.out.join("cmc-10way.png"),
        &format!("CMC, {way10}-way-1-shot"),
        "rank",
        "fraction with true class at rank <= r",
        &cmc_series,
        0.0..1.02,
    )?;
    writeln!(md, "## CMC, {way10}-way-1-shot\n\n![CMC](cmc-10way.png)\n")?;
    writeln!(
        md,
        "| method | rank 1 | rank 2 | rank 3 | rank 5 |\n|---|---|---|---|---|"
    )?;
    for (n, rows) in &table {
        if let Some(r) = rows.iter().find(|r| r.way == way10) {
            let at = |k: usize| r.cmc.get(k - 1).map_or(f64::NAN, |v| *v);
            writeln!(
                md,
                "| {n} | {:.4} | {:.4} | {:.4} | {:.4} |",
                at(1),
                at(2),
                at(3),
                at(5)
            )?;
        }
    }
    writeln!(md)?;

    // 10-class sample: per-class P/R/F1 and confusion matrix.
    let mut rng = StdRng::seed_from_u64(args.seed ^ 0xC1A55);
    let all: Vec<u32> = (0..pool.class_names.len() as u32).collect();
    let mut sample: Vec<u32> = all.choose_multiple(&mut rng, way10).copied().collect();
    sample.sort_unstable();
    let sub_idx: Vec<usize> = (0..pool.labels.len())
        .filter(|&i| sample.contains(&pool.labels[i]))
        .collect();
    let sub_labels: Vec<u32> = sub_idx
        .iter()
        .map(|&i| {
            sample
                .iter()
                .position(|&c| c == pool.labels[i])
                .unwrap_or(0) as u32
        })
        .collect();
    let sub_emb: Vec<Vec<f32>> = sub_idx.iter().map(|&i| emb[i].clone()).collect();
    let names: Vec<String> = sample
        .iter()
        .map(|&c| pool.class_names[c as usize].clone())
        .collect();
    let spec = EpisodeSpec {
        way: way10,
        shot: 1,
        episodes: args.episodes.max(2000),
        seed: args.seed,
    };
    let r = eval::run_episodes(&sub_labels, &spec, &mut Scorer::Prototype(&sub_emb))?;
    let mut conf = vec![vec![0usize; way10]; way10];
    for &(t, p) in &r.predictions {
        conf[t as usize][p as usize] += 1;
    }
    let prf: Vec<(f64, f64, f64)> = (0..way10)
        .map(|c| {
            let tp = conf[c][c] as f64;
            let pred: usize = (0..way10).map(|r| conf[r][c]).sum();
            let truth: usize = conf[c].iter().sum();
            let p = tp / (pred.max(1) as f64);
            let rc = tp / (truth.max(1) as f64);
            let f = if p + rc > 0.0 {
                2.0 * p * rc / (p + rc)
            } else {
                0.0
            };
            (p, rc, f)
        })
        .collect();
    prf_plot(&args.out.join("per-class-prf.png"), &names, &prf)?;
    confusion_plot(&args.out.join("confusion.png"), &names, &conf)?;
    writeln!(
        md,
        "## Per-class precision / recall / F1 and confusion ({way10} sampled classes, \
         {way10}-way-1-shot, {} episodes, accuracy {:.4} ± {:.4})\n\n\
         ![per-class](per-class-prf.png)\n\n![confusion](confusion.png)\n",
        spec.episodes, r.accuracy, r.ci95
    )?;
    writeln!(md, "| class | precision | recall | F1 |\n|---|---|---|---|")?;
    for (n, v) in names.iter().zip(&prf) {
        writeln!(md, "| {n} | {:.3} | {:.3} | {:.3} |", v.0, v.1, v.2)?;
    }
    writeln!(md)?;

    // Distances before and after training.
    let untrained = model
        .configs()
        .into_iter()
        .map(|c| Embedder::random_with(c.clone(), 1))
        .collect::<Result<Vec<_>, _>>()?;
    let untrained = Embedder::fuse(&untrained)?;
    let emb0 = pool.embed(&untrained)?;
    let mut panels = Vec::new();
    for (name, v) in [
        ("raw trajectories (standardised)", &raw),
        ("untrained network", &emb0),
        ("trained network", &emb),
    ] {
        let (a, b) = pair_distances(v, &pool.labels, 5000, args.seed);
        panels.push((name.to_string(), a, b));
    }
    distance_plot(&args.out.join("distances.png"), &panels)?;
    writeln!(
        md,
        "## Same-class vs different-class distances\n\n![distances](distances.png)\n\n\
         AUC = probability that a random same-class pair is closer than a random \
         different-class pair (5,000 pairs each):\n\n| space | mean same | mean different | AUC |\n|---|---|---|---|"
    )?;
    for (name, a, b) in &panels {
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        writeln!(
            md,
            "| {name} | {:.4} | {:.4} | {:.4} |",
            mean(a),
            mean(b),
            crate::eval::metrics::pair_auc(a, b)
        )?;
    }
    writeln!(md)?;

    // Training curves.
    if let Ok(text) = std::fs::read_to_string(&metrics_path) {
        let rows: Vec<EpochMetrics> = text
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect();
        if !rows.is_empty() {
            let ymax = rows
                .iter()
                .flat_map(|r| [r.train_loss, r.val_loss])
                .fold(0.0f64, f64::max)
                * 1.1;
            line_plot(
                &args.out.join("training-loss.png"),
                "Training curves: loss",
                "epoch",
                "loss",
                &[
                    (
                        "train loss".into(),
                        rows.iter()
                            .map(|r| (r.epoch as f64, r.train_loss))
                            .collect(),
                    ),
                    (
                        "val loss".into(),
                        rows.iter().map(|r| (r.epoch as f64, r.val_loss)).collect(),
                    ),
                ],
                0.0..ymax.max(1e-3),
            )?;
            line_plot(
                &args.out.join("training-accuracy.png"),
                "Training curves: validation 5-way-1-shot accuracy",
                "epoch",
                "accuracy",
                &[(
                    "val 5-way-1-shot".into(),
                    rows.iter()
                        .map(|r| (r.epoch as f64, r.val_acc_5way1shot))
                        .collect(),
                )],
                0.0..1.02,
            )?;
            let secs: f64 = rows.iter().map(|r| r.seconds).sum();
            let tps = rows.iter().map(|r| r.triplets_per_s).sum::<f64>() / rows.len() as f64;
            let sps = rows.iter().map(|r| r.samples_per_s).sum::<f64>() / rows.len() as f64;
            writeln!(
                md,
                "## Training curves\n\n![loss](training-loss.png)\n\n![accuracy](training-accuracy.png)\n\n\
                 {} epochs, {:.0} s in total (from `{}`); mean {:.0} samples/s, {:.0} mined triplets/s.\n",
                rows.len(),
                secs,
                metrics_path.display(),
                sps,
                tps
            )?;
        }
    }
    let md_path = args.out.join("few-shot.md");
    std::fs::write(&md_path, md).with_context(|| format!("writing {}", md_path.display()))?;
    let summary: Vec<serde_json::Value> = table
        .iter()
        .map(|(n, rows)| {
            serde_json::json!({
                "method": n,
                "accuracy_by_way": rows.iter().map(|r| (r.way, r.accuracy, r.ci95)).collect::<Vec<_>>(),
            })
        })
        .collect();
    println!("{}", serde_json::to_string(&summary)?);
    eprintln!("wrote {}", md_path.display());
    Ok(())
}
