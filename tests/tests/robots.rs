//! Any serial arm end to end: a real `guardiand` serving the UR5e (6 joints, 7 channels) over
//! real iceoryx2, with the shipped model and the workcell rules on, enrolls real Omniglot
//! drawings drawn by the UR5e (the lab's IK on the UR5e description), answers `Go` for an
//! unseen drawer of an enrolled class and `WrongTask` for the same plan claimed as another
//! class, refuses a Panda (8-channel) plan with `WrongChannelCount`, and reports its robot.
//! The same drawings drawn by the Panda and sent to a Panda daemon get the same verdicts.

use guardian_client::{Decision, InvalidKind, NoGoReason, Trajectory};
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::{character_files, read_strokes};
use guardian_robot::kinematics::RobotDescription;
use guardian_tests::harness::{self, Daemon, Setup};

/// Dense joint plans of `Latin/characterNN` drawers `drawers` (1-based) drawn by `robot`.
fn plans(robot: &str, character: u32, drawers: &[usize]) -> Vec<Trajectory> {
    let root = harness::workspace_root().join("../shared/omniglot/strokes");
    let files = character_files(&root, "Latin", character).expect("character folder");
    let solver = PathSolver::new(&Geometry::for_robot(robot).expect("geometry")).expect("solver");
    let joints = solver.robot().joints();
    drawers
        .iter()
        .map(|&d| {
            let w = convert_strokes(&solver, &read_strokes(&files[d - 1]).unwrap())
                .unwrap()
                .dense
                .waypoints;
            Trajectory::from_waypoints(&w, joints)
        })
        .collect()
}

/// A daemon serving `robot` with the shipped model and the robot's workcell rules.
fn serve(robot: &str, seed: u64) -> (Setup, Daemon) {
    let mut s = Setup::new(seed);
    s.model = harness::workspace_root().join("models/embedder.safetensors");
    s.workcell_rules = true;
    // No calibration in an empty bank: a generous threshold, so that only the nearest-class
    // rule decides between the enrolled classes.
    s.extra = format!("robot = {robot:?}\ndefault-threshold = 1e9\nk-nearest = 3");
    let d = Daemon::start(&s);
    (s, d)
}

const CLASSES: [u32; 3] = [1, 13, 18];

fn screen_three_classes(robot: &str, seed: u64) {
    let (s, _d) = serve(robot, seed);
    let client = s.client();
    let status = client.status().expect("status");
    let described = RobotDescription::named(robot).unwrap().robot;
    assert_eq!(status.robot.name, robot);
    assert_eq!(status.robot.joints as usize, described.joints());
    assert_eq!(status.robot.urdf_sha256, described.urdf_sha256_hex());

    for c in CLASSES {
        let info = client
            .enroll(&format!("latin{c:02}"), &plans(robot, c, &[1, 2, 3, 4, 5]))
            .expect("enroll");
        assert_eq!(info.examples, 5);
    }
    for c in CLASSES {
        let genuine = &plans(robot, c, &[6])[0];
        let v = client
            .check(genuine, &format!("latin{c:02}"))
            .expect("check");
        assert_eq!(v.decision, Decision::Go, "{robot} latin{c:02}: {v:?}");
    }
    // Latin 01 claimed as 13: the nearest class is 01.
    let v = client
        .check(&plans(robot, 1, &[6])[0], "latin13")
        .expect("check");
    assert_eq!(
        v.decision,
        Decision::NoGo {
            reason: NoGoReason::WrongTask {
                nearest: "latin01".into()
            }
        },
        "{robot}: {v:?}"
    );
}

#[test]
fn a_ur5e_daemon_screens_ur5e_plans() {
    screen_three_classes("ur5e", 61);
}

#[test]
fn a_panda_daemon_screens_the_same_drawings_drawn_by_the_panda() {
    screen_three_classes("panda", 62);
}

#[test]
fn a_ur5e_daemon_refuses_panda_plans() {
    let (s, _d) = serve("ur5e", 63);
    let client = s.client();
    client
        .enroll("latin01", &plans("ur5e", 1, &[1, 2, 3]))
        .expect("enroll");
    // The Panda's plan of the same drawing: 8 channels where the UR5e has 7.
    let panda = &plans("panda", 1, &[6])[0];
    assert_eq!(panda.channels(), 8);
    let v = client.check(panda, "latin01").expect("check");
    assert_eq!(
        v.decision,
        Decision::NoGo {
            reason: NoGoReason::InvalidTrajectory {
                kind: InvalidKind::WrongChannelCount,
                index: 8
            }
        }
    );
    // Enrolling it is refused too, and nothing changes.
    assert!(
        client
            .enroll("latin01", std::slice::from_ref(panda))
            .is_err()
    );
    assert_eq!(client.classes().expect("classes")[0].examples, 3);
    // A UR5e plan whose joint 2 leaves the limits (+-2 pi) is invalid.
    let mut w = plans("ur5e", 1, &[6])[0].as_flat().to_vec();
    w[7 * 10 + 1] = 7.0;
    let v = client
        .check(&Trajectory::from_flat(w, 7), "latin01")
        .expect("check");
    assert_eq!(
        v.decision,
        Decision::NoGo {
            reason: NoGoReason::InvalidTrajectory {
                kind: InvalidKind::JointOutOfLimits,
                index: 10
            }
        }
    );
}

/// `guardiand --check` on a config file: whether it succeeded, and its stderr.
fn check_config(config: &std::path::Path) -> (bool, String) {
    let out = std::process::Command::new(harness::bin())
        .arg("--config")
        .arg(config)
        .arg("--check")
        .output()
        .expect("run guardiand --check");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A UR5e daemon refuses a Panda bank at start, in a real process, with both robots named:
/// the shipped default bank (Panda plans, format 2) and a bank a Panda daemon persisted
/// (format 3, its robot recorded).
#[test]
fn a_ur5e_daemon_refuses_a_panda_bank() {
    let mut s = Setup::new(64);
    s.model = harness::workspace_root().join("models/embedder.safetensors");
    let shipped = harness::workspace_root().join("models/default-bank.gcb");
    s.extra = "robot = \"ur5e\"".into();
    // The harness writes `default-bank = ""`; point it at the shipped bank instead.
    let config = s.write_config();
    let text = std::fs::read_to_string(&config).unwrap().replacen(
        "default-bank = \"\"",
        &format!("default-bank = {:?}", shipped.display().to_string()),
        1,
    );
    std::fs::write(&config, text).unwrap();
    let (ok, err) = check_config(&config);
    assert!(!ok);
    assert!(
        err.contains("holds plans of robot panda") && err.contains("serves ur5e"),
        "{err}"
    );

    // A Panda daemon's persisted bank, then a UR5e daemon on the same state directory.
    let (mut p, mut d) = serve("panda", 65);
    p.client()
        .enroll("latin01", &plans("panda", 1, &[1, 2, 3]))
        .expect("enroll");
    d.signal("TERM");
    assert!(d.wait_exit().success());
    p.extra = "robot = \"ur5e\"".into();
    let (ok, err) = check_config(&p.write_config());
    assert!(!ok);
    assert!(
        err.contains("panda (7 joints") && err.contains("serves ur5e (6 joints"),
        "{err}"
    );
    // The Panda daemon still loads it.
    p.extra = "robot = \"panda\"".into();
    let (ok, err) = check_config(&p.write_config());
    assert!(ok, "{err}");
}
