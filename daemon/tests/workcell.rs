//! The workcell rules end to end: a real `guardiand` (workcell rules on, as shipped) over
//! real iceoryx2 answers `Go` for a genuine Omniglot plan and the workcell no-go, with the
//! rule and the first offending waypoint, for the same plan with a 0.05 rad joint offset.

mod common;

use std::path::PathBuf;

use common::{Daemon, Setup};
use guardian_client::{Decision, NoGoReason, Trajectory, WorkcellKind};
use guardian_lab::dataset::convert_strokes;
use guardian_lab::path::{Geometry, PathSolver};
use guardian_lab::strokes::read_strokes;
use guardian_shared::trajectory::Waypoint;

fn drawing(character: u32, drawer: usize) -> Vec<Waypoint> {
    let dir = common::workspace_root()
        .join("../shared/omniglot/strokes/Latin")
        .join(format!("character{character:02}"));
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    let solver = PathSolver::new(&Geometry::default()).expect("solver");
    convert_strokes(&solver, &read_strokes(&files[drawer]).unwrap())
        .unwrap()
        .dense
        .waypoints
}

#[test]
fn a_joint_offset_plan_gets_the_workcell_no_go_and_the_genuine_plan_goes() {
    let mut s = Setup::new(31);
    s.workcell_rules = true;
    // One class, a threshold no genuine plan reaches: only the workcell can say no.
    s.extra = "default-threshold = 1e9\nk-nearest = 1".into();
    let _d = Daemon::start(&s);
    let client = s.client();
    let examples: Vec<Trajectory> = (0..4)
        .map(|d| Trajectory::from_waypoints(&drawing(2, d)))
        .collect();
    client.enroll("latin2", &examples).expect("enroll");

    let genuine = drawing(2, 9);
    let v = client
        .check(&Trajectory::from_waypoints(&genuine), "latin2")
        .expect("check");
    assert_eq!(v.decision, Decision::Go, "{v:?}");

    // Joint 4 (elbow) 0.05 rad further bent on every waypoint: still inside the joint
    // limits, the pen path moves and tilts.
    let mut offset = genuine.clone();
    for w in &mut offset {
        w[3] -= 0.05;
    }
    let v = client
        .check(&Trajectory::from_waypoints(&offset), "latin2")
        .expect("check");
    assert_eq!(
        v.decision,
        Decision::NoGo {
            reason: NoGoReason::Workcell {
                kind: WorkcellKind::ToolOrientation,
                index: 0
            }
        },
        "{v:?}"
    );
    assert!(!v.is_go());
}
