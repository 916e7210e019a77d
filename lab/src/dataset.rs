//! `guardian-lab dataset`: Omniglot strokes to a dataset file of a robot's joint plans
//! (`guardian_omniglot::dataset`).

use std::path::{Path, PathBuf};

use guardian_models::embedder::Embedder;
use guardian_omniglot::dataset::{Dataset, generate_files_with};
use guardian_omniglot::path::Geometry;
use guardian_omniglot::strokes::{self, StrokePrep};

/// `guardian-lab dataset`: convert Omniglot strokes to a dataset file.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Stroke root(s) in the official layout (<root>/<Alphabet>/characterNN/NNNN_DD.txt),
    /// e.g. ../shared/omniglot/strokes or strokes_background/; repeat for several roots.
    #[arg(long = "strokes", required = true)]
    pub strokes: Vec<PathBuf>,
    /// Output safetensors file (written to FILE.tmp, then renamed).
    #[arg(long)]
    pub out: PathBuf,
    /// Geometry as a JSON file (kebab-case keys of `Geometry`); default: the guide's.
    #[arg(long, conflicts_with = "robot")]
    pub geometry: Option<PathBuf>,
    /// The robot that draws: a built-in name (panda, ur5e) or a robot description file;
    /// its pen, home seed and canvas come from its description (default: panda).
    #[arg(long)]
    pub robot: Option<String>,
    /// Simplify every stroke (Ramer-Douglas-Peucker, tolerance in motor units) before it is
    /// converted, as the recovered alphabets were; 0.65 gives the official files the
    /// recovered files' density (docs/report, 2026-12-05).
    #[arg(long)]
    pub simplify: Option<f64>,
    /// Drop one-point strokes (dots) before conversion, as the recovered files lack them.
    #[arg(long)]
    pub drop_dots: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Run `guardian-lab dataset`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    use anyhow::Context as _;
    let geometry = match &args.geometry {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            serde_json::from_str(&text).with_context(|| format!("parsing {}", p.display()))?
        }
        None => match &args.robot {
            Some(r) => Geometry::for_robot(r)?,
            None => Geometry::default(),
        },
    };
    anyhow::ensure!(
        args.simplify.is_none_or(|e| e.is_finite() && e >= 0.0),
        "--simplify must be a finite tolerance >= 0"
    );
    let prep = StrokePrep {
        simplify: args.simplify,
        drop_dots: args.drop_dots,
    };
    let files = strokes::scan(&args.strokes)?;
    let bar = if args.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(files.len() as u64)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} drawings ({per_sec}, eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let (dataset, report) = generate_files_with(&files, &geometry, prep, &|| bar.inc(1))?;
    bar.finish_and_clear();
    dataset.save(&args.out)?;
    eprintln!(
        "threads:              {}\n\
         robot:                {}\n\
         drawings read:        {}\n\
         converted:            {}\n\
         skipped:              {}\n\
         IK failures:          {}\n\
         max FK error:         {:.3e} m\n\
         min joint margin:     {:.4} rad (limit violations: {})\n\
         dense waypoints:      {} ({:.0} per drawing)\n\
         elapsed:              {:.3} s\n\
         drawings/s:           {:.0}\n\
         stroke preparation:   {}\n\
         classes / alphabets:  {} / {}\n\
         written:              {}",
        rayon::current_num_threads(),
        dataset.robot,
        report.files,
        report.converted,
        report.skipped.len(),
        report.ik_failures,
        report.max_fk_error,
        report.min_limit_margin,
        usize::from(report.min_limit_margin < 0.0),
        report.dense_waypoints,
        report.dense_waypoints as f64 / report.converted.max(1) as f64,
        report.elapsed.as_secs_f64(),
        report.drawings_per_second(),
        serde_json::to_string(&prep)?,
        dataset.classes.len(),
        dataset.alphabets.len(),
        args.out.display(),
    );
    for s in &report.skipped {
        eprintln!("skipped {}: {}", s.path.display(), s.reason);
    }
    Ok(())
}

/// The model file at `path`, checked to serve the robot that drew `data`'s trajectories
/// ([`Dataset::robot`]; its forward kinematics gives the pen paths).
pub fn model_for(data: &Dataset, path: &Path) -> anyhow::Result<Embedder> {
    use anyhow::Context as _;
    let model = Embedder::load(path).with_context(|| format!("loading {}", path.display()))?;
    model.serves(&data.robot()?)?;
    Ok(model)
}
