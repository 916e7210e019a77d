//! One dataset drawing as a PNG — the original strokes, the pen tip
//! reconstructed by forward kinematics from the 128 stored joint vectors (pen down solid,
//! pen up dashed), and the joint curves — so a person can see the character survived:
//!
//! ```sh
//! cargo run --release --example plot -- --dataset DATA --index 40 --out drawing.png
//! ```
#![forbid(unsafe_code)]

use std::path::{Path, PathBuf};

use guardian_robot::kinematics::joints_of;
use guardian_shared::trajectory::TOOL;
use plotters::prelude::*;

use guardian_omniglot::dataset::Dataset;
use guardian_omniglot::path::Geometry;
use guardian_omniglot::strokes::{Stroke, read_strokes};

/// The plot's arguments.
#[derive(Debug, Clone, clap::Parser)]
#[command(about = "Plot one drawing of a dataset: strokes, FK pen tip, joint curves")]
struct Args {
    /// Dataset file (from `guardian-lab dataset`).
    #[arg(long)]
    dataset: PathBuf,
    /// Drawing index in the dataset.
    #[arg(long)]
    pub index: usize,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Stroke root(s) holding the original drawing; repeatable.
    #[arg(long = "strokes", default_value = "../shared/omniglot/strokes")]
    pub strokes: Vec<PathBuf>,
}

/// Plotting failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlotError {
    /// The index is past the end of the dataset.
    #[error("index {index} out of range: the dataset has {len} drawings")]
    Index {
        /// Requested index.
        index: usize,
        /// Dataset length.
        len: usize,
    },
    /// The drawing backend failed.
    #[error("drawing {}: {message}", path.display())]
    Draw {
        /// Output file.
        path: PathBuf,
        /// The backend's message.
        message: String,
    },
}

/// Find the stroke file of dataset drawing `index` under the roots.
pub fn find_stroke_file(dataset: &Dataset, index: usize, roots: &[PathBuf]) -> Option<PathBuf> {
    let class = dataset
        .classes
        .get(usize::try_from(*dataset.labels.get(index)?).ok()?)?;
    let suffix = format!("_{:02}.txt", dataset.drawer_ids.get(index)?);
    roots.iter().find_map(|root| {
        let dir = root.join(class);
        let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir)
            .ok()?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        entries.sort();
        entries.into_iter().find(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with(&suffix))
        })
    })
}

/// Base-frame pen-tip position back to Omniglot motor coordinates.
fn base_to_motor(g: &Geometry, x: f64, y: f64) -> (f64, f64) {
    let s = g.metres_per_motor_unit;
    (
        g.motor_center[0] - (y - g.canvas_center[1]) / s,
        g.motor_center[1] + (x - g.canvas_center[0]) / s,
    )
}

/// Draw dataset drawing `index` (with its original `strokes` if given) to a PNG.
pub fn plot_drawing(
    dataset: &Dataset,
    index: usize,
    strokes: Option<&[Stroke]>,
    out: &Path,
) -> Result<(), PlotError> {
    let sample = dataset.trajectories.get(index).ok_or(PlotError::Index {
        index,
        len: dataset.len(),
    })?;
    let draw_err = |e: &dyn std::fmt::Display| PlotError::Draw {
        path: out.to_path_buf(),
        message: e.to_string(),
    };
    let g = &dataset.geometry;
    let robot = dataset.robot().map_err(|e| draw_err(&e))?;
    let joints = robot.joints();
    let tips: Vec<(f64, f64, f64, bool)> = sample
        .iter()
        .map(|s| {
            let p = robot.pen_tip_position(&joints_of(s));
            let (mx, my) = base_to_motor(g, p.x, p.y);
            (mx, my, p.z - g.canvas_z, s[TOOL] == 1.0)
        })
        .collect();

    // A square view around everything drawn, in motor units.
    let mut xs: Vec<f64> = tips.iter().map(|t| t.0).collect();
    let mut ys: Vec<f64> = tips.iter().map(|t| t.1).collect();
    for s in strokes.unwrap_or(&[]) {
        xs.extend(s.iter().map(|p| p.x));
        ys.extend(s.iter().map(|p| p.y));
    }
    let (x0, x1) = min_max(&xs);
    let (y0, y1) = min_max(&ys);
    let half = 0.5 * (x1 - x0).max(y1 - y0) + 5.0;
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let xr = (cx - half)..(cx + half);
    let yr = (cy - half)..(cy + half);

    let class = usize::try_from(dataset.labels.get(index).copied().unwrap_or(-1))
        .ok()
        .and_then(|l| dataset.classes.get(l))
        .map_or("?", String::as_str);
    let drawer = dataset.drawer_ids.get(index).copied().unwrap_or(-1);

    let root = BitMapBackend::new(out, (1500, 520)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| draw_err(&e))?;
    let root = root
        .titled(
            &format!("#{index}  {class}  drawer {drawer}"),
            ("sans-serif", 22),
        )
        .map_err(|e| draw_err(&e))?;
    let panels = root.split_evenly((1, 3));

    // 1. Original strokes.
    {
        let mut chart = ChartBuilder::on(&panels[0])
            .caption("original strokes (motor units)", ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(25)
            .y_label_area_size(35)
            .build_cartesian_2d(xr.clone(), yr.clone())
            .map_err(|e| draw_err(&e))?;
        chart.configure_mesh().draw().map_err(|e| draw_err(&e))?;
        for (k, s) in strokes.unwrap_or(&[]).iter().enumerate() {
            let color = Palette99::pick(k).to_rgba();
            chart
                .draw_series(LineSeries::new(
                    s.iter().map(|p| (p.x, p.y)),
                    color.stroke_width(3),
                ))
                .map_err(|e| draw_err(&e))?;
            chart
                .draw_series(std::iter::once(Circle::new(
                    (s[0].x, s[0].y),
                    4,
                    color.filled(),
                )))
                .map_err(|e| draw_err(&e))?;
        }
    }

    // 2. Pen tip by FK from the 128 joint vectors.
    {
        let mut chart = ChartBuilder::on(&panels[1])
            .caption("pen tip by FK of the 128 samples", ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(25)
            .y_label_area_size(35)
            .build_cartesian_2d(xr, yr)
            .map_err(|e| draw_err(&e))?;
        chart.configure_mesh().draw().map_err(|e| draw_err(&e))?;
        for w in tips.windows(2) {
            let (a, b) = (w[0], w[1]);
            let seg = [(a.0, a.1), (b.0, b.1)];
            if a.3 && b.3 {
                chart
                    .draw_series(LineSeries::new(seg, BLACK.stroke_width(3)))
                    .map_err(|e| draw_err(&e))?;
            } else {
                chart
                    .draw_series(DashedLineSeries::new(
                        seg,
                        4,
                        4,
                        RGBColor(170, 170, 170).into(),
                    ))
                    .map_err(|e| draw_err(&e))?;
            }
        }
        chart
            .draw_series(tips.iter().map(|t| {
                let c = if t.3 {
                    RED.filled()
                } else {
                    RGBColor(150, 150, 150).filled()
                };
                Circle::new((t.0, t.1), 2, c)
            }))
            .map_err(|e| draw_err(&e))?;
    }

    // 3. Joint curves and the tool channel.
    {
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for s in sample {
            for &v in &s[..joints] {
                lo = lo.min(f64::from(v));
                hi = hi.max(f64::from(v));
            }
        }
        lo = lo.min(0.0) - 0.1;
        hi = hi.max(1.0) + 0.1;
        let mut chart = ChartBuilder::on(&panels[2])
            .caption(
                format!("{} joints q1..q{joints} and tool", robot.name()),
                ("sans-serif", 16),
            )
            .margin(10)
            .x_label_area_size(25)
            .y_label_area_size(35)
            .build_cartesian_2d(0f64..(sample.len() - 1) as f64, lo..hi)
            .map_err(|e| draw_err(&e))?;
        chart.configure_mesh().draw().map_err(|e| draw_err(&e))?;
        for j in 0..joints {
            let color = Palette99::pick(j).to_rgba();
            chart
                .draw_series(LineSeries::new(
                    sample
                        .iter()
                        .enumerate()
                        .map(|(k, s)| (k as f64, f64::from(s[j]))),
                    color.stroke_width(2),
                ))
                .map_err(|e| draw_err(&e))?
                .label(format!("q{}", j + 1))
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 15, y)], color.stroke_width(2))
                });
        }
        chart
            .draw_series(LineSeries::new(
                sample
                    .iter()
                    .enumerate()
                    .map(|(k, s)| (k as f64, f64::from(s[TOOL]))),
                BLACK.stroke_width(2),
            ))
            .map_err(|e| draw_err(&e))?
            .label("tool")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 15, y)], BLACK.stroke_width(2)));
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 12))
            .position(SeriesLabelPosition::LowerRight)
            .draw()
            .map_err(|e| draw_err(&e))?;
    }
    root.present().map_err(|e| draw_err(&e))?;
    Ok(())
}

fn min_max(v: &[f64]) -> (f64, f64) {
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if lo.is_finite() && hi.is_finite() {
        (lo, hi)
    } else {
        (0.0, 105.0)
    }
}

/// Load, find the original strokes, plot.
fn main() -> anyhow::Result<()> {
    let args = <Args as clap::Parser>::parse();
    let dataset = Dataset::load(&args.dataset)?;
    let strokes = match find_stroke_file(&dataset, args.index, &args.strokes) {
        Some(p) => Some(read_strokes(&p)?),
        None => {
            eprintln!(
                "original stroke file not found under {:?}; plotting without it",
                args.strokes
            );
            None
        }
    };
    plot_drawing(&dataset, args.index, strokes.as_deref(), &args.out)?;
    eprintln!("wrote {}", args.out.display());
    Ok(())
}
