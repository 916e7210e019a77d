//! The cell demo's cases (`examples/cell/main.rs`; its test, `examples/tests/cell.rs`,
//! includes this file): a pick-and-place cell with bins 6 cm apart, three tasks enrolled
//! from five demonstrations each, then genuine runs, the same motion to the neighbouring
//! bin, a run into the keep-out box and a plan stopped half way, each with its expected
//! answer. The table, the rows and the checking are the drawing demo's
//! (`examples/demo/cases.rs`).

use guardian_cells::{Cell, Family, FamilyKind, Fault, Task};
use guardian_client::{Client, EnrollError, Trajectory};
use guardian_robot::kinematics::PANDA_JOINTS;

use crate::demo::{Case, Outcome, Report, check_case, forget_all};

/// The family the demo's cell is: its seed and the bins' spacing (m).
pub const FAMILY: (u64, f64) = (7, 0.06);
/// The tasks enrolled (three neighbouring bins).
pub const TASKS: [&str; 3] = ["bin-10", "bin-11", "bin-12"];
/// The bin under the keep-out box of `systemd/guardiand-cell.toml`.
pub const BOXED: &str = "bin-00";
/// Demonstrations enrolled per task.
pub const SHOTS: u64 = 5;

/// The demo's class of task `name`.
pub fn class_name(name: &str) -> String {
    format!("cell-{name}")
}

/// The demo's cell: its family.
pub fn family() -> Family {
    Family::new(FamilyKind::Bins, FAMILY.0, FAMILY.1)
}

/// The keep-out box over [`BOXED`] (base frame, m): ±2 cm around its place, up to 20 cm.
pub fn keep_out_box() -> ([f64; 3], [f64; 3]) {
    let p = task(&family(), BOXED).place;
    ([p.x - 0.02, p.y - 0.02, 0.0], [p.x + 0.02, p.y + 0.02, 0.2])
}

fn task<'a>(family: &'a Family, name: &str) -> &'a Task {
    family
        .tasks
        .iter()
        .find(|t| t.name == name)
        .expect("a task of the family")
}

/// The demo could not run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CellDemoError {
    /// A run could not be solved.
    #[error("solving a run: {0}")]
    Solve(#[from] guardian_cells::CellError),
    /// Enrolling a task failed.
    #[error("enroll {class}: {source}")]
    Enroll {
        /// The class.
        class: String,
        /// Why.
        source: EnrollError,
    },
    /// Forgetting or checking failed.
    #[error(transparent)]
    Demo(#[from] crate::demo::DemoError),
}

/// Enroll the three tasks, send the cases, forget the tasks unless `keep`.
pub fn run_cases(client: &Client, keep: bool) -> Result<Report, CellDemoError> {
    let family = family();
    let cell = Cell::default();
    let plan = |name: &str, seed: u64| -> Result<Trajectory, CellDemoError> {
        let p = cell.run(task(&family, name), seed)?;
        Ok(Trajectory::from_waypoints(&p, PANDA_JOINTS))
    };
    let names: Vec<String> = TASKS.iter().map(|t| class_name(t)).collect();
    forget_all(client, &names)?;
    for (t, class) in TASKS.iter().zip(&names) {
        let examples = (0..SHOTS)
            .map(|d| plan(t, d))
            .collect::<Result<Vec<_>, _>>()?;
        client
            .enroll(class, &examples)
            .map_err(|source| CellDemoError::Enroll {
                class: class.clone(),
                source,
            })?;
    }
    let mut cases: Vec<Case> = Vec::new();
    for (t, class) in TASKS.iter().zip(&names) {
        cases.push((
            format!("genuine run to {t}"),
            plan(t, 100)?,
            class.clone(),
            Outcome::Go,
        ));
    }
    let (a, b) = (class_name(TASKS[1]), TASKS[2]);
    cases.push((
        format!("run to {b} claimed as {}", TASKS[1]),
        plan(b, 101)?,
        a.clone(),
        Outcome::Geometry,
    ));
    cases.push((
        format!("run to {} claimed as {}", TASKS[0], TASKS[1]),
        plan(TASKS[0], 102)?,
        a.clone(),
        Outcome::Geometry,
    ));
    cases.push((
        format!("run into the keep-out box ({BOXED})"),
        plan(BOXED, 103)?,
        class_name(TASKS[0]),
        Outcome::Workcell,
    ));
    let cut = cell.faulty(task(&family, TASKS[1]), Fault::Truncated, 104)?;
    cases.push((
        format!("run to {} stopped half way", TASKS[1]),
        Trajectory::from_waypoints(&cut, PANDA_JOINTS),
        a,
        Outcome::Geometry,
    ));
    let rows = cases.into_iter().map(|c| check_case(client, c)).collect();
    let (lo, hi) = keep_out_box();
    let notes = vec![
        format!(
            "the keep-out box of systemd/guardiand-cell.toml lies over {BOXED}: {lo:.3?} to \
             {hi:.3?} (base frame, m)"
        ),
        format!(
            "cell: guardian-cells bins family seed {}, bins {} m apart; {} enrolled from {SHOTS} \
         runs each (the part up to 1.5 cm and 15 deg elsewhere, heights and planner style \
         varying); the checked runs are other runs",
            FAMILY.0,
            FAMILY.1,
            TASKS.join(", ")
        ),
    ];
    let kept = if keep {
        names
    } else {
        forget_all(client, &names)?;
        Vec::new()
    };
    Ok(Report { rows, notes, kept })
}
