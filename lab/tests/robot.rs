//! `guardian-lab robot`'s checks on the shipped robots and on a description whose canvas the
//! arm cannot reach.

use guardian_lab::tools::robot::check;
use guardian_models::kinematics::{RobotDescription, UR5E_URDF};

#[test]
fn both_shipped_robots_pass_every_check() {
    for name in ["panda", "ur5e"] {
        let report = check(RobotDescription::named(name).unwrap());
        for c in &report.checks {
            assert!(c.passed, "{name}: {} — {}", c.name, c.figure);
        }
        assert_eq!(report.checks.len(), 5, "{name}");
        let home = report.home.expect("home pose");
        // The home pose holds the pen 2 cm above the canvas centre.
        let p = report.description.robot.pen_tip(&home).translation;
        assert!(
            (p - nalgebra::Vector3::new(0.5, 0.0, 0.17)).norm() < 1e-5,
            "{name}: {p}"
        );
    }
    // The UR5e home is elbow up, as seeded, and well conditioned (measured ~0.23).
    let ur = check(RobotDescription::named("ur5e").unwrap());
    let sv = guardian_lab::tools::robot::smallest_singular_value(
        &ur.description.robot,
        &ur.home.unwrap(),
    );
    assert!(sv > 0.1, "{sv}");
}

#[test]
fn a_canvas_out_of_reach_fails_the_workspace_check() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("ur5e.urdf"), UR5E_URDF).unwrap();
    let far =
        include_str!("../../models/robots/ur5e.toml").replace("canvas-x = 0.5", "canvas-x = 1.5");
    let path = dir.path().join("far.toml");
    std::fs::write(&path, far).unwrap();
    let report = check(RobotDescription::load(&path).unwrap());
    assert!(!report.passed());
    let home = report
        .checks
        .iter()
        .find(|c| c.name.starts_with("home"))
        .unwrap();
    assert!(!home.passed, "{}", home.figure);
    // The chain itself is fine.
    assert!(report.checks[..3].iter().all(|c| c.passed));
}
