//! The demo's cases: a first look at the shipped guardian on real drawings.
//!
//! Against a running `guardiand` with its shipped defaults (workcell rules on, shipped model
//! and default bank), through the planner client library: enroll three Latin characters
//! (Latin is not in the default bank) from five drawers each as `demo-latin-NN`, then send
//! genuine and faulty plans converted from Omniglot strokes by the dataset code (IK along the
//! Cartesian pen path) and compare each verdict with the expected one. The demo classes are
//! forgotten at the end unless asked to keep them.

use guardian_robot::kinematics::PANDA_JOINTS;
use std::path::{Path, PathBuf};
use std::time::Instant;

use guardian_client::{CheckError, Client, Decision, EnrollError, NoGoReason, Trajectory, Verdict};
use guardian_shared::trajectory::Waypoint;
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::Serialize;

use guardian_omniglot::corrupt::{Fault, corrupt_joints};
use guardian_omniglot::dataset::{ConvertError, convert_strokes};
use guardian_omniglot::path::{Geometry, PathSolver, SolvePathError};
use guardian_omniglot::strokes::{
    DrawingFile, Point, ReadStrokesError, Stroke, read_strokes, scan,
};

/// The Latin characters enrolled as demo classes.
pub const LATIN: [u32; 3] = [1, 13, 18];
/// Drawers (1-based Omniglot drawer numbers) whose drawings are enrolled.
pub const ENROLL_DRAWERS: [u32; 5] = [1, 2, 3, 4, 5];
/// The drawer of the genuine checks (not enrolled).
pub const CHECK_DRAWER: u32 = 6;
/// The drawer of the faulty plans and the wrong-task drawing (not enrolled).
pub const FAULT_DRAWER: u32 = 7;
/// The Greek character checked against the shipped default bank, and its drawer.
pub const GREEK: (u32, u32) = (1, 20);
/// A class name the demo never enrolls.
pub const NEVER_ENROLLED: &str = "demo-latin-never";
/// The joint offset of the joint-offset fault (rad).
pub const JOINT_OFFSET: f64 = 0.1;
/// How far the moved drawing is moved on the canvas (m).
pub const SHIFT: f64 = 0.06;

/// What the demo needs besides the client.
#[derive(Debug, Clone)]
pub struct Options {
    /// Omniglot stroke root (`<root>/<Alphabet>/characterNN/NNNN_DD.txt`).
    pub strokes: PathBuf,
    /// Keep the demo classes enrolled afterwards.
    pub keep: bool,
}

/// The name of the demo class of Latin character `n`.
pub fn class_name(n: u32) -> String {
    format!("demo-latin-{n:02}")
}

/// The kind of answer a case gets (or is expected to get).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Outcome {
    /// Go.
    Go,
    /// No-go: another class is nearer.
    WrongTask,
    /// No-go: farther than the claimed class's threshold.
    Outlier,
    /// No-go: the class is not enrolled.
    UnknownClass,
    /// No-go: the trajectory failed validation.
    Invalid,
    /// No-go: a workcell rule.
    Workcell,
    /// No-go: the plan geometry differs from the enrolled examples.
    Geometry,
    /// A no-go reason this demo does not know.
    OtherNoGo,
    /// The request failed (no verdict).
    Error,
}

impl Outcome {
    /// Kebab-case name.
    pub fn name(self) -> &'static str {
        match self {
            Outcome::Go => "go",
            Outcome::WrongTask => "wrong-task",
            Outcome::Outlier => "outlier",
            Outcome::UnknownClass => "unknown-class",
            Outcome::Invalid => "invalid",
            Outcome::Workcell => "workcell",
            Outcome::Geometry => "geometry",
            Outcome::OtherNoGo => "no-go",
            Outcome::Error => "error",
        }
    }

    /// The outcome of a verdict.
    pub fn of(v: &Verdict) -> Self {
        match &v.decision {
            Decision::Go => Outcome::Go,
            Decision::NoGo { reason } => match reason {
                NoGoReason::WrongTask { .. } => Outcome::WrongTask,
                NoGoReason::Outlier => Outcome::Outlier,
                NoGoReason::UnknownClass => Outcome::UnknownClass,
                NoGoReason::InvalidTrajectory { .. } => Outcome::Invalid,
                NoGoReason::Workcell { .. } => Outcome::Workcell,
                NoGoReason::GeometryMismatch { .. } => Outcome::Geometry,
                _ => Outcome::OtherNoGo,
            },
        }
    }
}

/// One line of the demo table.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// What is sent.
    pub case: String,
    /// The claimed class.
    pub claimed: String,
    /// The expected outcome.
    pub expected: Outcome,
    /// The outcome received.
    pub got: Outcome,
    /// The verdict with its reason detail (or the error).
    pub verdict: String,
    /// Distance to the claimed class prototype.
    pub distance: Option<f32>,
    /// The claimed class's threshold.
    pub threshold: Option<f32>,
    /// The plan-geometry score and threshold, when the geometry check applied.
    pub geometry: Option<(f32, f32)>,
    /// Client round trip of the check (us).
    pub round_trip_us: f64,
    /// `got == expected`.
    pub as_expected: bool,
}

/// The demo's result.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// One row per case, in the order sent.
    pub rows: Vec<Row>,
    /// Remarks on how the cases were made (drawers, shift direction, default bank).
    pub notes: Vec<String>,
    /// The demo classes left enrolled (empty unless `keep`).
    pub kept: Vec<String>,
}

impl Report {
    /// Number of rows as expected.
    pub fn as_expected(&self) -> usize {
        self.rows.iter().filter(|r| r.as_expected).count()
    }

    /// Every row as expected.
    pub fn all_as_expected(&self) -> bool {
        self.as_expected() == self.rows.len()
    }

    /// The table, notes and the "N/N as expected" line.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let opt = |x: Option<f32>| x.map_or("-".to_string(), |v| format!("{v:.3}"));
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{:<33} {:<17} {:<14} {:<52} {:>9} {:>9} {:>10}",
            "case", "claimed", "expected", "verdict", "distance", "threshold", "round trip"
        );
        for r in &self.rows {
            let _ = writeln!(
                s,
                "{:<33} {:<17} {:<14} {:<52} {:>9} {:>9} {:>7.0} us{}",
                r.case,
                r.claimed,
                r.expected.name(),
                r.verdict,
                opt(r.distance),
                opt(r.threshold),
                r.round_trip_us,
                if r.as_expected { "" } else { "  <- unexpected" }
            );
        }
        let _ = writeln!(s, "{}/{} as expected", self.as_expected(), self.rows.len());
        for n in &self.notes {
            let _ = writeln!(s, "note: {n}");
        }
        s
    }
}

/// The demo could not run (a verdict that differs from the expected one is not an error:
/// it is a row of the [`Report`]).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DemoError {
    /// The stroke data is unreadable.
    #[error("stroke data: {0}")]
    Strokes(#[from] ReadStrokesError),
    /// A drawing is not in the stroke data.
    #[error("{root}: no drawing {alphabet}/character{character:02} drawer {drawer}")]
    MissingDrawing {
        /// The stroke root.
        root: PathBuf,
        /// Alphabet.
        alphabet: String,
        /// Character number.
        character: u32,
        /// Drawer number.
        drawer: u32,
    },
    /// The path solver could not be built.
    #[error("path solver: {0}")]
    Solver(#[from] SolvePathError),
    /// A drawing could not be converted to a joint path.
    #[error("{path}: {source}")]
    Convert {
        /// The stroke file.
        path: PathBuf,
        /// Why.
        source: ConvertError,
    },
    /// Enrolling a demo class failed.
    #[error("enroll {class}: {source}")]
    Enroll {
        /// The class.
        class: String,
        /// Why.
        source: EnrollError,
    },
    /// The daemon serves another robot than the Panda the demo (and its default bank) is
    /// for.
    #[error(
        "the demo draws with the Panda and checks its default bank; the daemon serves {served}"
    )]
    WrongRobot {
        /// The robot the daemon serves.
        served: String,
    },
    /// The daemon's status could not be read.
    #[error("status: {0}")]
    Status(CheckError),
    /// Forgetting a demo class failed.
    #[error("forget {class}: {source}")]
    Forget {
        /// The class.
        class: String,
        /// Why.
        source: CheckError,
    },
}

struct Drawings {
    root: PathBuf,
    files: Vec<DrawingFile>,
    solver: PathSolver,
}

impl Drawings {
    fn file(&self, alphabet: &str, character: u32, drawer: u32) -> Result<&DrawingFile, DemoError> {
        let ch = format!("character{character:02}");
        self.files
            .iter()
            .find(|f| f.alphabet == alphabet && f.character == ch && f.drawer == drawer)
            .ok_or_else(|| DemoError::MissingDrawing {
                root: self.root.clone(),
                alphabet: alphabet.into(),
                character,
                drawer,
            })
    }

    fn strokes(
        &self,
        alphabet: &str,
        character: u32,
        drawer: u32,
    ) -> Result<(PathBuf, Vec<Stroke>), DemoError> {
        let f = self.file(alphabet, character, drawer)?;
        Ok((f.path.clone(), read_strokes(&f.path)?))
    }

    fn solve(&self, path: &Path, strokes: &[Stroke]) -> Result<Vec<Waypoint>, DemoError> {
        convert_strokes(&self.solver, strokes)
            .map(|c| c.dense.waypoints)
            .map_err(|source| DemoError::Convert {
                path: path.to_path_buf(),
                source,
            })
    }

    /// The dense joint path a planner would send for one drawing.
    fn plan(
        &self,
        alphabet: &str,
        character: u32,
        drawer: u32,
    ) -> Result<Vec<Waypoint>, DemoError> {
        let (path, strokes) = self.strokes(alphabet, character, drawer)?;
        self.solve(&path, &strokes)
    }
}

fn centre(strokes: &[Stroke]) -> [f64; 2] {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for p in strokes.iter().flatten() {
        lo = [lo[0].min(p.x), lo[1].min(p.y)];
        hi = [hi[0].max(p.x), hi[1].max(p.y)];
    }
    [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0]
}

/// The direction along a canvas axis (unit vector in motor coordinates) in which to move
/// the drawing by `shift_units`: among the directions that keep it on the canvas, the one
/// that takes its centre farthest, along one axis, from the nearest centre of the enrolled
/// drawings (`enrolled`), as the geometry score measures each feature against the nearest
/// example; if none keeps it on the canvas, the least overflow. Also returns how far
/// (m) the moved drawing reaches beyond the canvas edge (0 if inside).
fn shift_direction(
    strokes: &[Stroke],
    enrolled: &[[f64; 2]],
    g: &Geometry,
    shift_units: f64,
) -> ([f64; 2], f64) {
    let half = g.canvas_side / 2.0;
    let c = centre(strokes);
    // (overflow, -distance to the nearest enrolled centre): smaller is better.
    let mut best = ([1.0, 0.0], (f64::INFINITY, 0.0));
    for d in [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]] {
        let mut over: f64 = 0.0;
        for p in strokes.iter().flatten() {
            let b = g.motor_to_base(p.x + d[0] * shift_units, p.y + d[1] * shift_units);
            let dx = (b.x - g.canvas_center[0]).abs() - half;
            let dy = (b.y - g.canvas_center[1]).abs() - half;
            over = over.max(dx).max(dy);
        }
        let moved = [c[0] + d[0] * shift_units, c[1] + d[1] * shift_units];
        let near = (0..2)
            .map(|a| {
                enrolled
                    .iter()
                    .map(|e| (e[a] - moved[a]).abs())
                    .fold(f64::INFINITY, f64::min)
            })
            .fold(0.0, f64::max);
        let key = (over.max(0.0), -near);
        if key.0 < best.1.0 || (key.0 == best.1.0 && key.1 < best.1.1) {
            best = (d, key);
        }
    }
    (best.0, best.1.0)
}

pub type Case = (String, Trajectory, String, Outcome);

/// Run the demo's cases against the daemon behind `client`.
pub fn run_cases(client: &Client, opts: &Options) -> Result<Report, DemoError> {
    let served = client.status().map_err(DemoError::Status)?.robot;
    if served.name != "panda" || served.joints as usize != PANDA_JOINTS {
        return Err(DemoError::WrongRobot {
            served: format!("{} ({} joints)", served.name, served.joints),
        });
    }
    let geometry = Geometry::default();
    let d = Drawings {
        root: opts.strokes.clone(),
        files: scan(std::slice::from_ref(&opts.strokes))?,
        solver: PathSolver::new(&geometry)?,
    };
    let names: Vec<String> = LATIN.iter().map(|&c| class_name(c)).collect();
    let mut notes = Vec::new();

    // A clean start: classes kept by an earlier `--keep` run would get more examples.
    forget_all(client, &names)?;
    for (&c, name) in LATIN.iter().zip(&names) {
        let mut examples = Vec::new();
        for &drawer in &ENROLL_DRAWERS {
            examples.push(Trajectory::from_waypoints(
                &d.plan("Latin", c, drawer)?,
                PANDA_JOINTS,
            ));
        }
        client
            .enroll(name, &examples)
            .map_err(|source| DemoError::Enroll {
                class: name.clone(),
                source,
            })?;
    }
    notes.push(format!(
        "enrolled {} from Latin drawers {:?}; genuine checks use drawer {CHECK_DRAWER}, \
         the other cases drawer {FAULT_DRAWER}",
        names.join(", "),
        ENROLL_DRAWERS
    ));

    let mut cases: Vec<Case> = Vec::new();
    for (&c, name) in LATIN.iter().zip(&names) {
        cases.push((
            format!("genuine Latin {c:02} drawer {CHECK_DRAWER}"),
            Trajectory::from_waypoints(&d.plan("Latin", c, CHECK_DRAWER)?, PANDA_JOINTS),
            name.clone(),
            Outcome::Go,
        ));
    }
    let (a, b) = (LATIN[0], LATIN[1]);
    cases.push((
        format!("Latin {a:02} claimed as {b:02}"),
        Trajectory::from_waypoints(&d.plan("Latin", a, FAULT_DRAWER)?, PANDA_JOINTS),
        names[1].clone(),
        Outcome::WrongTask,
    ));
    cases.push((
        "never-enrolled class".into(),
        Trajectory::from_waypoints(&d.plan("Latin", a, FAULT_DRAWER)?, PANDA_JOINTS),
        NEVER_ENROLLED.into(),
        Outcome::UnknownClass,
    ));

    let c = LATIN[2];
    let (path, strokes) = d.strokes("Latin", c, FAULT_DRAWER)?;
    let genuine = d.solve(&path, &strokes)?;

    // The fault generator's joint offset: 0.05 + 0.15 x severity rad on a random joint
    // (seeded), so severity 1/3 is 0.1 rad.
    let severity = (JOINT_OFFSET - 0.05) / 0.15;
    let offset = corrupt_joints(
        d.solver.robot(),
        Fault::JointOffset,
        severity,
        &genuine,
        &mut StdRng::seed_from_u64(7),
    );
    let joint = (0..PANDA_JOINTS)
        .find(|&j| offset.iter().zip(&genuine).any(|(o, g)| o[j] != g[j]))
        .map_or("a joint".to_string(), |j| format!("joint {}", j + 1));
    cases.push((
        format!("{joint} offset {JOINT_OFFSET} rad"),
        Trajectory::from_waypoints(&offset, PANDA_JOINTS),
        names[2].clone(),
        Outcome::Workcell,
    ));

    // Moved on the canvas: the strokes shifted (motor coordinates map affinely onto the
    // canvas plane) and re-solved by IK, as the fault generators do.
    let units = SHIFT / geometry.metres_per_motor_unit;
    let mut enrolled = Vec::new();
    for &drawer in &ENROLL_DRAWERS {
        enrolled.push(centre(&d.strokes("Latin", c, drawer)?.1));
    }
    let (dir, over) = shift_direction(&strokes, &enrolled, &geometry, units);
    let moved: Vec<Stroke> = strokes
        .iter()
        .map(|s| {
            s.iter()
                .map(|p| Point {
                    x: p.x + dir[0] * units,
                    y: p.y + dir[1] * units,
                    t: p.t,
                })
                .collect()
        })
        .collect();
    // Motor +y -> base +x, motor +x -> base -y.
    let base = [dir[1] * SHIFT * 100.0, -dir[0] * SHIFT * 100.0];
    cases.push((
        format!("moved {:.0} cm on the canvas", SHIFT * 100.0),
        Trajectory::from_waypoints(&d.solve(&path, &moved)?, PANDA_JOINTS),
        names[2].clone(),
        Outcome::Geometry,
    ));
    notes.push(format!(
        "the moved drawing is Latin {c:02} drawer {FAULT_DRAWER} shifted by ({:.1}, {:.1}) cm \
         in the base frame (the canvas-axis direction, among those that keep it on the \
         canvas, farthest from where the enrolled drawers drew) and re-solved by IK; {}",
        base[0],
        base[1],
        if over > 0.0 {
            format!("it reaches {:.1} mm beyond the canvas edge", over * 1000.0)
        } else {
            "it stays on the canvas".to_string()
        }
    ));

    let mut w = genuine.clone();
    w[10][2] = f32::NAN;
    cases.push((
        "NaN joint value".into(),
        Trajectory::from_waypoints(&w, PANDA_JOINTS),
        names[2].clone(),
        Outcome::Invalid,
    ));
    let mut w = genuine.clone();
    w[20][3] = 0.5;
    cases.push((
        "joint 4 beyond limit".into(),
        Trajectory::from_waypoints(&w, PANDA_JOINTS),
        names[2].clone(),
        Outcome::Invalid,
    ));
    let seven: Vec<f32> = genuine
        .iter()
        .flat_map(|w| w[..PANDA_JOINTS].to_vec())
        .collect();
    cases.push((
        "7 channels".into(),
        Trajectory::from_flat(seven, PANDA_JOINTS),
        names[2].clone(),
        Outcome::Invalid,
    ));
    cases.push((
        "1 waypoint".into(),
        Trajectory::from_waypoints(&genuine[..1], PANDA_JOINTS),
        names[2].clone(),
        Outcome::Invalid,
    ));

    let (g, gd) = GREEK;
    let greek = format!("Greek/character{g:02}");
    cases.push((
        format!("Greek {g:02} drawer {gd}, default bank"),
        Trajectory::from_waypoints(&d.plan("Greek", g, gd)?, PANDA_JOINTS),
        greek.clone(),
        Outcome::Go,
    ));
    notes.push(format!(
        "{greek} is a class of the shipped default bank, which enrolled 5 random drawers of \
         it; drawer {gd} may be one of them"
    ));

    let rows = cases.into_iter().map(|c| check_case(client, c)).collect();

    let kept = if opts.keep {
        names
    } else {
        forget_all(client, &names)?;
        Vec::new()
    };
    Ok(Report { rows, notes, kept })
}

/// Check one case and time its round trip: its table row.
pub fn check_case(client: &Client, (case, t, claimed, expected): Case) -> Row {
    let start = Instant::now();
    let result = client.check(&t, &claimed);
    let round_trip_us = start.elapsed().as_secs_f64() * 1e6;
    let (got, verdict, distance, threshold, geometry) = match &result {
        Ok(v) => (
            Outcome::of(v),
            verdict_text(v),
            v.claimed_distance,
            v.threshold,
            v.geometry_score.zip(v.geometry_threshold),
        ),
        Err(e) => (Outcome::Error, format!("ERROR {e}"), None, None, None),
    };
    Row {
        case,
        claimed,
        expected,
        got,
        verdict,
        distance,
        threshold,
        geometry,
        round_trip_us,
        as_expected: got == expected,
    }
}

/// Forget `names` (those not enrolled are no error).
pub fn forget_all(client: &Client, names: &[String]) -> Result<(), DemoError> {
    for name in names {
        match client.forget(name) {
            Ok(()) | Err(CheckError::UnknownClass { .. }) => {}
            Err(source) => {
                return Err(DemoError::Forget {
                    class: name.clone(),
                    source,
                });
            }
        }
    }
    Ok(())
}

/// What both demos (drawings, cell) take on the command line besides their own options:
/// the daemon to reach, and how to report.
#[derive(Debug, clap::Args)]
pub struct Session {
    /// Request-response service name of the daemon.
    #[arg(long, default_value = guardian_shared::wire::DEFAULT_SERVICE_NAME)]
    pub service: String,
    /// Per-request timeout in milliseconds.
    #[arg(long, default_value_t = 2000)]
    pub timeout_ms: u64,
    /// iceoryx2 root path (must match the daemon's config).
    #[arg(long)]
    pub iceoryx2_root_path: Option<PathBuf>,
    /// iceoryx2 prefix (must match the daemon's config).
    #[arg(long)]
    pub iceoryx2_prefix: Option<String>,
    /// Print JSON instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Keep the demo classes enrolled afterwards.
    #[arg(long)]
    pub keep: bool,
}

impl Session {
    /// Connect to the daemon; `hint` says how to start it.
    pub fn connect(&self, hint: &str) -> anyhow::Result<Client> {
        use anyhow::Context as _;
        Client::connect(guardian_client::ClientConfig {
            service_name: self.service.clone(),
            timeout: std::time::Duration::from_millis(self.timeout_ms),
            iceoryx2_root_path: self.iceoryx2_root_path.clone(),
            iceoryx2_prefix: self.iceoryx2_prefix.clone(),
        })
        .with_context(|| format!("cannot connect to guardiand (is it running? {hint})"))
    }
}

/// Print `report` (JSON or the table) and fail if a case was not as expected: how both
/// demos end.
pub fn finish(report: &Report, json: bool) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string_pretty(report)?);
    } else {
        print!("{}", report.table());
    }
    if !report.all_as_expected() {
        anyhow::bail!(
            "{} of {} cases not as expected",
            report.rows.len() - report.as_expected(),
            report.rows.len()
        );
    }
    Ok(())
}

/// The verdict with its reason detail, as one line.
pub fn verdict_text(v: &Verdict) -> String {
    v.decision.to_string()
}
