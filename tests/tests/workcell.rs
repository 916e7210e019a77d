//! The workcell rules end to end: a real `guardiand` (workcell rules on, as shipped) over
//! real iceoryx2 answers `Go` for a genuine Omniglot plan and the workcell no-go, with the
//! rule and the first offending waypoint, for the same plan with a 0.05 rad joint offset.
//! And the geometry check: with a bank that carries a geometry calibration, classes
//! enrolled through the daemon get descriptors, and the same drawing placed elsewhere on
//! the canvas is answered `GeometryMismatch` naming the centre.

use guardian_bank::{ClassBank, GeometryCalibration};
use guardian_client::{Decision, GeometryFeature, NoGoReason, Trajectory, WorkcellKind};
use guardian_models::embedder::{EMBED_DIM, Embedder};
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::{character_files, read_strokes};
use guardian_robot::kinematics::PANDA_JOINTS;
use guardian_shared::trajectory::Waypoint;
use guardian_tests::harness::{self, Daemon, Setup};

fn drawing(character: u32, drawer: usize) -> Vec<Waypoint> {
    drawing_on(&Geometry::default(), character, drawer)
}

fn drawing_on(geometry: &Geometry, character: u32, drawer: usize) -> Vec<Waypoint> {
    let root = harness::workspace_root().join("../shared/omniglot/strokes");
    let files = character_files(&root, "Latin", character).expect("character folder");
    let solver = PathSolver::new(geometry).expect("solver");
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
        .map(|d| Trajectory::from_waypoints(&drawing(2, d), PANDA_JOINTS))
        .collect();
    client.enroll("latin2", &examples).expect("enroll");

    let genuine = drawing(2, 9);
    let v = client
        .check(
            &Trajectory::from_waypoints(&genuine, PANDA_JOINTS),
            "latin2",
        )
        .expect("check");
    assert_eq!(v.decision, Decision::Go, "{v:?}");

    // Joint 4 (elbow) 0.05 rad further bent on every waypoint: still inside the joint
    // limits, the pen path moves and tilts.
    let mut offset = genuine.clone();
    for w in &mut offset {
        w[3] -= 0.05;
    }
    let v = client
        .check(&Trajectory::from_waypoints(&offset, PANDA_JOINTS), "latin2")
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

#[test]
fn a_drawing_moved_on_the_canvas_gets_the_geometry_no_go() {
    let mut s = Setup::new(32);
    s.extra = "default-threshold = 1e9\nk-nearest = 1".into();
    // A bank with a geometry calibration (the shipped bank's spreads and threshold) and no
    // classes yet, persisted where the daemon looks first.
    let model = Embedder::load(&s.model).expect("model");
    let mut bank = ClassBank::new(EMBED_DIM, model.version(), 1e9);
    bank.set_geometry_calibration(Some(GeometryCalibration {
        scales: [
            0.0069, 0.0065, 0.30, 0.17, 0.17, 0.32, 0.13, 0.15, 0.14, 0.19, 0.10, 0.22,
        ],
        threshold: 7.58,
        target_rate: 0.01,
        samples: 0,
        measured_rate: 0.0,
        note: "test".into(),
    }));
    std::fs::create_dir_all(s.state_dir()).unwrap();
    bank.save(&s.state_dir().join("bank.gcb")).unwrap();
    let _d = Daemon::start(&s);
    let client = s.client();
    let examples: Vec<Trajectory> = (0..5)
        .map(|d| Trajectory::from_waypoints(&drawing(2, d), PANDA_JOINTS))
        .collect();
    client.enroll("latin2", &examples).expect("enroll");

    let v = client
        .check(
            &Trajectory::from_waypoints(&drawing(2, 9), PANDA_JOINTS),
            "latin2",
        )
        .expect("check");
    assert_eq!(v.decision, Decision::Go, "{v:?}");
    let genuine_score = v.geometry_score.expect("geometry applies");
    assert!(genuine_score <= 7.58, "{v:?}");

    // The same drawing 6 cm further along base +x ("up" on the drawing), on the canvas
    // plane with the commanded tool orientation. The workcell rules are off in this setup
    // (`Setup::workcell_rules`), so only the geometry can object.
    let moved = Geometry {
        canvas_center: [0.56, 0.0],
        ..Geometry::default()
    };
    let v = client
        .check(
            &Trajectory::from_waypoints(&drawing_on(&moved, 2, 9), PANDA_JOINTS),
            "latin2",
        )
        .expect("check");
    match &v.decision {
        Decision::NoGo {
            reason:
                NoGoReason::GeometryMismatch {
                    feature,
                    score,
                    threshold,
                },
        } => {
            assert_eq!(*feature, GeometryFeature::CentreY, "{v:?}");
            assert!(score > threshold, "{v:?}");
        }
        other => panic!("expected a geometry mismatch, got {other:?}"),
    }
}
