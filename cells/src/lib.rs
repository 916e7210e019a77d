//! guardian-cells: the tasks of a manipulation cell, to learn and measure on.
//!
//! The Omniglot data are drawings; the people who deploy guardian run cells. This crate
//! generates **task families** of a cell and **demonstrations** of each task that vary as
//! real runs do, written from the physics of the task and solved into joint plans of the
//! served robot with the project's own inverse kinematics (`guardian_robot::kinematics`):
//!
//! | family | tasks differ in |
//! |---|---|
//! | [`FamilyKind::Bins`] | one pick (a conveyor spot), twelve bins on a grid `spacing` apart: the place |
//! | [`FamilyKind::Pallet`] | one pick, a 3 × 3 pallet pattern in two layers: the place, in 3-D |
//! | [`FamilyKind::Routes`] | one pick, one place, an obstacle between: the route around it |
//! | [`FamilyKind::Approaches`] | one insertion point: the direction it is approached from |
//! | [`FamilyKind::Wipe`] | wiping or dispensing: which rectangle is swept, and along which axis |
//! | [`FamilyKind::Mixed`] | each task its own pick, place and route |
//!
//! A task is a pick, a place, a route (via points at transfer height) and the direction
//! the place is approached from. A **run** of a task draws what varies between real runs
//! ([`Variation`]): the part lies up to 1.5 cm elsewhere and up to 15° rotated (the tool
//! turns to grasp it and back to place it straight), the approach, lift, transfer and
//! retreat heights, the start pose, and the planner's style (straight legs, or a smooth
//! transfer arc). The plan: from the start pose to above the part, down, grasp (tool
//! channel 1 from the grasp to the release), lift, transfer through the route, down the
//! approach to the place, release, back out. Waypoints are at most 5 mm apart.
//!
//! [`Fault`]s are what goes wrong in a cell: the place shifted, the approach above the part
//! skipped, the plan stopped half way. The wrong task (the neighbouring bin, the other
//! route or approach) is a run of another task of the family.
//!
//! Families are drawn from a seed: the layout moves, turns and mirrors, so families of
//! other seeds are cells the screen never saw.

use guardian_robot::kinematics::{
    Frame, IkError, IkOptions, JointVector, READY_POSE, Robot, default_panda,
};
use guardian_shared::trajectory::Waypoint;
use nalgebra::{Matrix3, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Largest distance between two consecutive waypoints of a plan (m).
pub const SPACING: f64 = 0.005;

/// A family of tasks of one cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum FamilyKind {
    /// One pick, twelve bins `spacing` apart.
    Bins,
    /// One pick, a 3 × 3 pallet pattern `spacing` apart, two layers.
    Pallet,
    /// One pick, one place, four routes around an obstacle (over it, round its near side,
    /// round its far side, wide round its far side).
    Routes,
    /// One insertion point, five approach directions.
    Approaches,
    /// Wiping or dispensing: three rectangles `spacing` apart (at least 10 cm), each swept
    /// along x or along y.
    Wipe,
    /// Twenty-four tasks, each its own pick, place and route.
    Mixed,
}

impl FamilyKind {
    /// Every kind.
    pub const ALL: [Self; 6] = [
        Self::Bins,
        Self::Pallet,
        Self::Routes,
        Self::Approaches,
        Self::Wipe,
        Self::Mixed,
    ];

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Bins => "bins",
            Self::Pallet => "pallet",
            Self::Routes => "routes",
            Self::Approaches => "approaches",
            Self::Wipe => "wipe",
            Self::Mixed => "mixed",
        }
    }
}

/// One task of a cell.
#[derive(Debug, Clone, PartialEq)]
pub struct Task {
    /// Its name, unique in the family.
    pub name: String,
    /// Where the part lies (tool-tip position at the grasp, m, base frame).
    pub pick: Vector3<f64>,
    /// Where it is put (tool-tip position at the release).
    pub place: Vector3<f64>,
    /// Via points of the transfer, in order (their height is the run's transfer height
    /// plus their own `z`, which is relative).
    pub via: Vec<Vector3<f64>>,
    /// Unit direction of the last move onto the place (straight down: `[0, 0, -1]`).
    pub approach: Vector3<f64>,
    /// A wiping (or dispensing) task instead of a pick-and-place: the tool on while it
    /// sweeps a rectangle centred on `place`.
    pub wipe: Option<Wipe>,
}

/// A wiping or dispensing pattern: a rectangle swept in parallel passes, the tool on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Wipe {
    /// The rectangle's sides along base x and y (m).
    pub size: [f64; 2],
    /// Parallel passes.
    pub passes: usize,
    /// The passes run along base x (else along y).
    pub along_x: bool,
}

/// A family: its kind, seed and tasks; neighbouring tasks are next to each other in
/// [`Family::tasks`] only by construction order, [`Family::nearest_other`] says which is
/// nearest.
#[derive(Debug, Clone, PartialEq)]
pub struct Family {
    /// Kind.
    pub kind: FamilyKind,
    /// Seed it was drawn from.
    pub seed: u64,
    /// Its tasks.
    pub tasks: Vec<Task>,
}

impl Family {
    /// The family of `kind` drawn from `seed`; `spacing` (m) is the distance between
    /// neighbouring bins or pallet slots (the other kinds ignore it).
    pub fn new(kind: FamilyKind, seed: u64, spacing: f64) -> Self {
        let mut rng = StdRng::seed_from_u64(seed ^ 0x9e37_79b9_7f4a_7c15);
        // The layout moves, turns and mirrors with the seed.
        let mirror = if rng.random_bool(0.5) { -1.0 } else { 1.0 };
        let shift = Vector3::new(
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.03..0.03),
            0.0,
        );
        let turn: f64 = rng.random_range(-0.35..0.35);
        let (c, s) = (turn.cos(), turn.sin());
        let at = |x: f64, y: f64, z: f64| Vector3::new(x, mirror * y, z) + shift;
        let pick = at(0.45, 0.22, TABLE);
        let place = at(0.50, -0.20, TABLE);
        // A grid around `place`, turned by `turn`.
        let grid =
            |dx: f64, dy: f64, dz: f64| place + Vector3::new(c * dx - s * dy, s * dx + c * dy, dz);
        let down = Vector3::new(0.0, 0.0, -1.0);
        let task = |name: String, pick, place, via: Vec<Vector3<f64>>, approach| Task {
            name,
            pick,
            place,
            via,
            approach,
            wipe: None,
        };
        let tasks = match kind {
            FamilyKind::Bins => (0..3)
                .flat_map(|r| (0..4).map(move |k| (r, k)))
                .map(|(r, k)| {
                    let p = grid((r as f64 - 1.0) * spacing, (k as f64 - 1.5) * spacing, 0.0);
                    task(format!("bin-{r}{k}"), pick, p, vec![], down)
                })
                .collect(),
            FamilyKind::Pallet => (0..2)
                .flat_map(|l| (0..9).map(move |i| (l, i)))
                .map(|(l, i)| {
                    let (r, k) = (i / 3, i % 3);
                    let p = grid(
                        (r as f64 - 1.0) * spacing,
                        (k as f64 - 1.0) * spacing,
                        0.05 * l as f64,
                    );
                    task(format!("slot-{l}{r}{k}"), pick, p, vec![], down)
                })
                .collect(),
            FamilyKind::Routes => {
                let mid = 0.5 * (pick + place);
                let along = (place - pick).normalize();
                // The side away from the robot's base (the arm cannot bend round near it).
                let mut side = Vector3::new(-along.y, along.x, 0.0);
                if side.x < 0.0 {
                    side = -side;
                }
                let routes = [
                    ("over", Vector3::new(0.0, 0.0, 0.12)),
                    ("near-side", -side * 0.10),
                    ("far-side", side * 0.12),
                    ("far-wide", side * 0.22 + Vector3::new(0.0, 0.0, -0.04)),
                ];
                routes
                    .iter()
                    .map(|(n, off)| {
                        let v = Vector3::new(mid.x, mid.y, 0.0) + off;
                        task(format!("route-{n}"), pick, place, vec![v], down)
                    })
                    .collect()
            }
            FamilyKind::Approaches => {
                let t = std::f64::consts::FRAC_1_SQRT_2;
                let dirs = [
                    ("top", Vector3::new(0.0, 0.0, -1.0)),
                    ("from-front", Vector3::new(-t, 0.0, -t)),
                    ("from-back", Vector3::new(t, 0.0, -t)),
                    ("from-left", Vector3::new(0.0, -t, -t)),
                    ("from-right", Vector3::new(0.0, t, -t)),
                ];
                dirs.iter()
                    .map(|(n, d)| task(format!("insert-{n}"), pick, place, vec![], *d))
                    .collect()
            }
            FamilyKind::Wipe => (0..3)
                .flat_map(|r| [true, false].map(move |x| (r, x)))
                .map(|(r, along_x)| {
                    let centre = grid(0.0, (r as f64 - 1.0) * spacing.max(0.1), 0.0);
                    let mut t = task(
                        format!("wipe-{r}{}", if along_x { "x" } else { "y" }),
                        centre,
                        centre,
                        vec![],
                        if along_x { Vector3::x() } else { Vector3::y() },
                    );
                    t.wipe = Some(Wipe {
                        size: [0.08, 0.06],
                        passes: 4,
                        along_x,
                    });
                    t
                })
                .collect(),
            FamilyKind::Mixed => (0..24)
                .map(|i| {
                    let p = pick
                        + Vector3::new(
                            rng.random_range(-0.08..0.08),
                            rng.random_range(-0.06..0.06),
                            0.0,
                        );
                    let q = place
                        + Vector3::new(
                            rng.random_range(-0.1..0.1),
                            rng.random_range(-0.08..0.08),
                            0.0,
                        );
                    let mid = 0.5 * (p + q);
                    let v = Vector3::new(
                        mid.x + rng.random_range(-0.1..0.1),
                        mid.y,
                        rng.random_range(0.0..0.08),
                    );
                    task(format!("task-{i:02}"), p, q, vec![v], down)
                })
                .collect(),
        };
        Self { kind, seed, tasks }
    }

    /// The other task whose place (then pick, then route) is nearest task `i`'s: the wrong
    /// task a planner most easily sends for it.
    pub fn nearest_other(&self, i: usize) -> usize {
        let key = |t: &Task| {
            let v: f64 = t.via.iter().map(|v| v.norm()).sum();
            (t.place, t.pick, v, t.approach)
        };
        let (p, k, v, a) = key(&self.tasks[i]);
        (0..self.tasks.len())
            .filter(|&j| j != i)
            .min_by(|&x, &y| {
                let d = |j: usize| {
                    let (q, l, w, b) = key(&self.tasks[j]);
                    (q - p).norm() + 1e-3 * (l - k).norm() + 1e-3 * (w - v).abs() + (b - a).norm()
                };
                d(x).total_cmp(&d(y))
            })
            .unwrap_or(i)
    }
}

/// Tool-tip height at a grasp or release on the table (m).
const TABLE: f64 = 0.12;
/// Transfer height (m) before a run's variation.
const TRANSFER: f64 = 0.28;
/// Where the robot starts, before a run's variation.
const START: [f64; 3] = [0.40, 0.0, 0.35];

/// How much real runs of one task differ (every value a half-range of a uniform draw).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Variation {
    /// Where the part lies, radius (m).
    pub part: f64,
    /// How it is rotated (rad); the tool turns to grasp it.
    pub yaw: f64,
    /// Approach, lift and retreat heights and the transfer height (m).
    pub heights: f64,
    /// Where it is put, radius (m).
    pub place: f64,
    /// Start pose (m).
    pub start: f64,
}

impl Default for Variation {
    /// Parts ±1.5 cm and ±15°, heights ±2 cm, place ±3 mm, start ±2 cm.
    fn default() -> Self {
        Self {
            part: 0.015,
            yaw: 15f64.to_radians(),
            heights: 0.02,
            place: 0.003,
            start: 0.02,
        }
    }
}

/// What goes wrong in a run.
#[derive(Debug, Clone, Copy, PartialEq, clap::ValueEnum)]
pub enum Fault {
    /// The place moved by 3 cm in a random horizontal direction.
    ShiftedPlace,
    /// Straight from the start to the part: the approach above it skipped.
    MissedApproach,
    /// The plan stopped half way (its first half sent).
    Truncated,
}

impl Fault {
    /// Every fault.
    pub const ALL: [Self; 3] = [Self::ShiftedPlace, Self::MissedApproach, Self::Truncated];

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Self::ShiftedPlace => "shifted-place",
            Self::MissedApproach => "missed-approach",
            Self::Truncated => "truncated",
        }
    }
}

/// One point of a run's Cartesian path.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PathPoint {
    position: Vector3<f64>,
    yaw: f64,
    tool: bool,
}

/// Solving a run into joints failed.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum CellError {
    /// The start pose has no IK solution.
    #[error("no IK solution for the start pose: {0}")]
    Start(IkError),
    /// A path point has no IK solution from the previous one.
    #[error("IK failed at path point {index} (position {position:?} m): {source}")]
    Ik {
        /// Index into the Cartesian path.
        index: usize,
        /// Its target tool-tip position.
        position: [f64; 3],
        /// The failure.
        source: IkError,
    },
}

/// Runs of tasks for one robot, solved into joint plans.
#[derive(Debug, Clone)]
pub struct Cell {
    robot: Robot,
    variation: Variation,
    options: IkOptions,
    ready: JointVector,
}

impl Default for Cell {
    fn default() -> Self {
        Self::new(default_panda().clone(), Variation::default())
    }
}

impl Cell {
    /// Runs for `robot` (its tool tip is the gripper's centre point) varying by
    /// `variation`; IK starts from the robot's ready pose.
    pub fn new(robot: Robot, variation: Variation) -> Self {
        Self {
            robot,
            variation,
            options: IkOptions {
                position_tolerance: 5e-5,
                orientation_tolerance: 5e-4,
                max_iterations: 300,
                ..IkOptions::default()
            },
            ready: READY_POSE,
        }
    }

    /// The robot.
    pub fn robot(&self) -> &Robot {
        &self.robot
    }

    /// A run of `task`, its variation drawn from `seed` (the same seed, the same plan).
    pub fn run(&self, task: &Task, seed: u64) -> Result<Vec<Waypoint>, CellError> {
        self.solve(&self.path(task, seed, None))
    }

    /// A run of `task` with `fault`.
    pub fn faulty(&self, task: &Task, fault: Fault, seed: u64) -> Result<Vec<Waypoint>, CellError> {
        let mut plan = self.solve(&self.path(task, seed, Some(fault)))?;
        if fault == Fault::Truncated {
            plan.truncate(plan.len().div_ceil(2));
        }
        Ok(plan)
    }

    /// The Cartesian path of a run.
    fn path(&self, task: &Task, seed: u64, fault: Option<Fault>) -> Vec<PathPoint> {
        let v = &self.variation;
        let mut rng = StdRng::seed_from_u64(seed);
        let disc = |rng: &mut StdRng, r: f64| {
            let a: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            let d = r * rng.random_range(0.0f64..1.0).sqrt();
            Vector3::new(d * a.cos(), d * a.sin(), 0.0)
        };
        let h = |rng: &mut StdRng, base: f64| base + rng.random_range(-v.heights..=v.heights);
        let start = Vector3::from(START)
            + Vector3::new(
                rng.random_range(-v.start..=v.start),
                rng.random_range(-v.start..=v.start),
                rng.random_range(-v.start..=v.start),
            );
        if let Some(w) = &task.wipe {
            return wipe_path(task.place, w, start, &mut rng, v, fault);
        }
        let pick = task.pick + disc(&mut rng, v.part);
        let yaw = rng.random_range(-v.yaw..=v.yaw);
        let mut place = task.place + disc(&mut rng, v.place);
        if fault == Some(Fault::ShiftedPlace) {
            let a: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            place += Vector3::new(0.03 * a.cos(), 0.03 * a.sin(), 0.0);
        }
        let above_pick = pick + Vector3::new(0.0, 0.0, h(&mut rng, 0.08));
        let lifted = pick + Vector3::new(0.0, 0.0, h(&mut rng, 0.08));
        let transfer = h(&mut rng, TRANSFER);
        let pre_place = place - task.approach * h(&mut rng, 0.08);
        let retreat = place - task.approach * h(&mut rng, 0.07);
        let curved = rng.random_bool(0.5);

        let mut out = vec![PathPoint {
            position: start,
            yaw: 0.0,
            tool: false,
        }];
        if fault != Some(Fault::MissedApproach) {
            line(&mut out, above_pick, yaw, false);
        }
        line(&mut out, pick, yaw, false);
        // The gripper closes at the part.
        out.last_mut().expect("a point").tool = true;
        line(&mut out, lifted, yaw, true);
        // Transfer through the route at transfer height, turning the part straight.
        let mut via: Vec<Vector3<f64>> = task
            .via
            .iter()
            .map(|p| Vector3::new(p.x, p.y, transfer + p.z))
            .collect();
        let high = |p: Vector3<f64>| Vector3::new(p.x, p.y, transfer.max(p.z));
        via.insert(0, high(lifted));
        via.push(high(pre_place));
        let yaw_at = |k: usize, n: usize| yaw * (1.0 - k as f64 / n as f64);
        if curved && task.via.len() <= 1 {
            // One smooth arc from the lift to above the place, bent through the via point.
            let control = if task.via.is_empty() {
                0.5 * (via[0] + via[1]) + Vector3::new(0.0, 0.0, 0.05)
            } else {
                2.0 * via[1] - 0.5 * (via[0] + via[2])
            };
            let (a, b) = (via[0], via[via.len() - 1]);
            line(&mut out, a, yaw, true);
            bezier(&mut out, a, control, b, yaw, true);
        } else {
            let n = via.len();
            for (k, p) in via.into_iter().enumerate() {
                line(&mut out, p, yaw_at(k, n), true);
            }
        }
        line(&mut out, pre_place, 0.0, true);
        line(&mut out, place, 0.0, true);
        // The gripper opens at the place and backs out along the approach.
        line(&mut out, retreat, 0.0, false);
        out
    }

    /// IK along `path`: the start pose from the ready pose (not recorded), then every point
    /// seeded with the previous solution.
    fn solve(&self, path: &[PathPoint]) -> Result<Vec<Waypoint>, CellError> {
        let first = path.first().expect("a run has points");
        // Reach the start pose from the ready pose in 1 cm steps.
        let from = self.robot.pen_tip_position(&self.ready);
        let n = ((first.position - from).norm() / 0.01).ceil().max(1.0) as usize;
        let mut q = self.ready;
        for i in 1..=n {
            let p = from + (first.position - from) * (i as f64 / n as f64);
            q = self
                .robot
                .ik(&target(p, 0.0), &q, &self.options)
                .map_err(CellError::Start)?;
        }
        let mut state = self.robot.ik_state(&q);
        let mut out = Vec::with_capacity(path.len());
        for (index, p) in path.iter().enumerate() {
            self.robot
                .ik_from(&target(p.position, p.yaw), &mut state, &self.options)
                .map_err(|source| CellError::Ik {
                    index,
                    position: p.position.into(),
                    source,
                })?;
            out.push(self.robot.waypoint(&state.q, f32::from(u8::from(p.tool))));
        }
        Ok(out)
    }
}

/// The Cartesian path of a wiping run: from `start` to above the rectangle's first corner,
/// down, the tool on along parallel passes, the tool off, up. The rectangle lies within
/// the run's place variation of `centre` (3 cm away with [`Fault::ShiftedPlace`]).
fn wipe_path(
    centre: Vector3<f64>,
    w: &Wipe,
    start: Vector3<f64>,
    rng: &mut StdRng,
    v: &Variation,
    fault: Option<Fault>,
) -> Vec<PathPoint> {
    let mut centre = centre
        + Vector3::new(
            rng.random_range(-v.place..=v.place),
            rng.random_range(-v.place..=v.place),
            0.0,
        );
    if fault == Some(Fault::ShiftedPlace) {
        let a: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        centre += Vector3::new(0.03 * a.cos(), 0.03 * a.sin(), 0.0);
    }
    let hover = 0.06 + rng.random_range(-v.heights..=v.heights);
    let retreat = 0.07 + rng.random_range(-v.heights..=v.heights);
    let (main, across) = if w.along_x {
        (
            Vector3::new(w.size[0], 0.0, 0.0),
            Vector3::new(0.0, w.size[1], 0.0),
        )
    } else {
        (
            Vector3::new(0.0, w.size[1], 0.0),
            Vector3::new(w.size[0], 0.0, 0.0),
        )
    };
    let corner = centre - 0.5 * (main + across);
    let up = |p: Vector3<f64>, h: f64| p + Vector3::new(0.0, 0.0, h);
    let mut out = vec![PathPoint {
        position: start,
        yaw: 0.0,
        tool: false,
    }];
    if fault != Some(Fault::MissedApproach) {
        line(&mut out, up(corner, hover), 0.0, false);
    }
    line(&mut out, corner, 0.0, false);
    out.last_mut().expect("a point").tool = true;
    let mut at = corner;
    let step = across / (w.passes.max(2) - 1) as f64;
    for k in 0..w.passes.max(2) {
        let dir = if k % 2 == 0 { main } else { -main };
        at += dir;
        line(&mut out, at, 0.0, true);
        if k + 1 < w.passes.max(2) {
            at += step;
            line(&mut out, at, 0.0, true);
        }
    }
    line(&mut out, up(at, retreat), 0.0, false);
    out
}

/// The tool frame at `position`: tool z straight down, turned by `yaw` about the vertical.
fn target(position: Vector3<f64>, yaw: f64) -> Frame {
    let down = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
    let (c, s) = (yaw.cos(), yaw.sin());
    let turn = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
    Frame {
        rotation: turn * down,
        translation: position,
    }
}

/// Points from the last point of `out` to `to` (included) at most [`SPACING`] apart, the
/// yaw turning evenly to `yaw`.
fn line(out: &mut Vec<PathPoint>, to: Vector3<f64>, yaw: f64, tool: bool) {
    let last = *out.last().expect("a path starts with a point");
    let n = ((to - last.position).norm() / SPACING).ceil().max(1.0) as usize;
    for i in 1..=n {
        let t = i as f64 / n as f64;
        out.push(PathPoint {
            position: last.position + (to - last.position) * t,
            yaw: last.yaw + (yaw - last.yaw) * t,
            tool,
        });
    }
}

/// A quadratic Bézier from `a` (the last point of `out`) through control `c` to `b`.
fn bezier(
    out: &mut Vec<PathPoint>,
    a: Vector3<f64>,
    c: Vector3<f64>,
    b: Vector3<f64>,
    yaw: f64,
    tool: bool,
) {
    let at = |t: f64| a * (1.0 - t) * (1.0 - t) + c * 2.0 * t * (1.0 - t) + b * t * t;
    let rough = (c - a).norm() + (b - c).norm();
    let n = (2.0 * rough / SPACING).ceil().max(1.0) as usize;
    let last_yaw = out.last().map_or(yaw, |p| p.yaw);
    for i in 1..=n {
        let t = i as f64 / n as f64;
        out.push(PathPoint {
            position: at(t),
            yaw: last_yaw + (0.0 - last_yaw) * t,
            tool,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_robot::kinematics::joints_of;
    use guardian_shared::trajectory::TOOL;

    /// Every family solves on the Panda for several seeds; the plans are dense, the tool is
    /// on from the grasp to the release only, and the grasp and release are where the task
    /// says (within the run's variation).
    #[test]
    fn every_family_is_reachable_and_grasps_where_its_task_says() {
        let cell = Cell::default();
        let v = Variation::default();
        for kind in FamilyKind::ALL {
            for seed in [1, 2, 3] {
                let family = Family::new(kind, seed, 0.06);
                for (i, task) in family.tasks.iter().enumerate() {
                    let plan = cell
                        .run(task, 100 + i as u64)
                        .unwrap_or_else(|e| panic!("{} {seed} {}: {e}", kind.name(), task.name));
                    let tool: Vec<bool> = plan.iter().map(|w| w[TOOL] > 0.5).collect();
                    let on = tool.iter().position(|&t| t).unwrap();
                    let off = tool.iter().rposition(|&t| t).unwrap();
                    assert!(tool[on..=off].iter().all(|&t| t), "one grasp");
                    let at = |k: usize| cell.robot().pen_tip_position(&joints_of(&plan[k]));
                    if let Some(w) = &task.wipe {
                        // The tool is on only inside the rectangle, on the table.
                        for k in on..=off {
                            let d = at(k) - task.place;
                            assert!(d.x.abs() <= 0.5 * w.size[0] + v.place + 1e-3, "{d:?}");
                            assert!(d.y.abs() <= 0.5 * w.size[1] + v.place + 1e-3, "{d:?}");
                            assert!(d.z.abs() < 1e-3, "{d:?}");
                        }
                        continue;
                    }
                    let grasp = at(on);
                    let release = at(off);
                    assert!(
                        (grasp - task.pick).norm() <= v.part + 1e-3,
                        "{grasp:?} {:?}",
                        task.pick
                    );
                    assert!((release - task.place).norm() <= v.place + 1e-3);
                    for k in 1..plan.len() {
                        assert!((at(k) - at(k - 1)).norm() <= SPACING + 1e-3);
                    }
                }
            }
        }
    }

    #[test]
    fn runs_are_reproducible_and_differ_between_seeds_and_faults() {
        let cell = Cell::default();
        let family = Family::new(FamilyKind::Bins, 7, 0.06);
        let t = &family.tasks[0];
        assert_eq!(cell.run(t, 1).unwrap(), cell.run(t, 1).unwrap());
        assert_ne!(cell.run(t, 1).unwrap(), cell.run(t, 2).unwrap());
        let whole = cell.run(t, 1).unwrap();
        let cut = cell.faulty(t, Fault::Truncated, 1).unwrap();
        assert_eq!(cut.len(), whole.len().div_ceil(2));
        assert_eq!(cut[..], whole[..cut.len()]);
        assert!(cell.faulty(t, Fault::MissedApproach, 1).unwrap().len() < whole.len());
        let shifted = cell.faulty(t, Fault::ShiftedPlace, 1).unwrap();
        let release = |p: &[Waypoint]| {
            let off = p.iter().rposition(|w| w[TOOL] > 0.5).unwrap();
            cell.robot().pen_tip_position(&joints_of(&p[off]))
        };
        let d = (release(&shifted) - release(&whole)).norm();
        assert!((d - 0.03).abs() < 0.007, "{d}");
        // The nearest other bin is one grid step away.
        let j = family.nearest_other(0);
        let step = (family.tasks[j].place - t.place).norm();
        assert!((step - 0.06).abs() < 1e-9, "{step}");
    }
}
