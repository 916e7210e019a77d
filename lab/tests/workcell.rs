//! Workcell rules and plan geometry on real Omniglot drawings: each rule stays silent on the
//! genuine dense joint path and fires on the same drawing corrupted the way it guards
//! against; the geometry descriptor of a shifted / scaled drawing moves as expected.

use std::path::Path;

use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::{Stroke, character_files, read_strokes};
use guardian_robot::kinematics::default_panda;
use guardian_robot::kinematics::{PANDA_JOINTS, PANDA_Q_MAX, PANDA_Q_MIN};
use guardian_robot::workcell::{inspect, plan_geometry};
use guardian_shared::trajectory::Waypoint;
use guardian_shared::workcell::{GeometryFeature, Workcell, WorkcellKind};

fn drawing(character: u32, drawer: usize) -> Vec<Stroke> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/omniglot/strokes");
    let files = character_files(&root, "Greek", character).unwrap();
    read_strokes(&files[drawer]).unwrap()
}

fn solve(geometry: &Geometry, strokes: &[Stroke]) -> Vec<Waypoint> {
    let solver = PathSolver::new(geometry).unwrap();
    convert_strokes(&solver, strokes).unwrap().dense.waypoints
}

fn violation(ws: &[Waypoint]) -> Option<(WorkcellKind, u32)> {
    inspect(&Workcell::default(), ws)
        .unwrap()
        .violation
        .map(|v| (v.kind, v.index))
}

#[test]
fn genuine_plans_obey_every_rule() {
    for (c, d) in [(1, 0), (5, 3), (12, 7), (20, 19)] {
        let ws = solve(&Geometry::default(), &drawing(c, d));
        let i = inspect(&Workcell::default(), &ws).unwrap();
        assert_eq!(i.violation, None, "character {c} drawer {d}");
        assert!(i.score < 1.0, "{}", i.score);
    }
}

#[test]
fn a_joint_offset_breaks_the_tool_orientation() {
    let ws = solve(&Geometry::default(), &drawing(3, 0));
    for j in 0..PANDA_JOINTS {
        let mut bad = ws.clone();
        for w in &mut bad {
            // 0.05 rad, towards the middle of the joint range so the plan stays valid.
            let mid = 0.5 * (PANDA_Q_MIN[j] + PANDA_Q_MAX[j]) as f32;
            w[j] += if w[j] < mid { 0.05 } else { -0.05 };
        }
        assert_eq!(
            violation(&bad),
            Some((WorkcellKind::ToolOrientation, 0)),
            "joint {}",
            j + 1
        );
    }
    // One waypoint off: reported at its index.
    let mut bad = ws.clone();
    bad[40][5] += 0.01;
    assert_eq!(violation(&bad), Some((WorkcellKind::ToolOrientation, 40)));
}

#[test]
fn drawing_above_the_canvas_breaks_the_pen_height() {
    let g = Geometry {
        canvas_z: 0.15 + 0.005,
        ..Geometry::default()
    };
    let ws = solve(&g, &drawing(3, 0));
    let first_down = ws
        .iter()
        .position(|w| w[guardian_shared::trajectory::TOOL] > 0.5)
        .unwrap() as u32;
    assert_eq!(violation(&ws), Some((WorkcellKind::PenHeight, first_down)));
}

#[test]
fn drawing_beside_the_canvas_is_off_canvas() {
    let g = Geometry {
        canvas_center: [0.50 + 0.15, 0.0],
        ..Geometry::default()
    };
    let ws = solve(&g, &drawing(3, 0));
    assert_eq!(violation(&ws).map(|v| v.0), Some(WorkcellKind::OffCanvas));
}

#[test]
fn travelling_too_high_breaks_the_hover_height() {
    let g = Geometry {
        hover: 0.05,
        lift: 0.05,
        ..Geometry::default()
    };
    let ws = solve(&g, &drawing(3, 0));
    assert_eq!(violation(&ws).map(|v| v.0), Some(WorkcellKind::HoverHeight));
}

#[test]
fn geometry_follows_shift_and_scale() {
    let strokes = drawing(7, 2);
    let base = Geometry::default();
    let g0 = plan_geometry(
        default_panda(),
        &convert_strokes(&PathSolver::new(&base).unwrap(), &strokes)
            .unwrap()
            .sample,
    )
    .unwrap();
    // 1 cm along base +x is 1 cm "up" on the drawing.
    let shifted = Geometry {
        canvas_center: [0.51, 0.0],
        ..base.clone()
    };
    let g1 = plan_geometry(
        default_panda(),
        &convert_strokes(&PathSolver::new(&shifted).unwrap(), &strokes)
            .unwrap()
            .sample,
    )
    .unwrap();
    let dy = g1.get(GeometryFeature::CentreY) - g0.get(GeometryFeature::CentreY);
    let dx = g1.get(GeometryFeature::CentreX) - g0.get(GeometryFeature::CentreX);
    assert!((dy - 0.01).abs() < 5e-4, "{dy}");
    assert!(dx.abs() < 5e-4, "{dx}");
    assert!((g1.get(GeometryFeature::Width) - g0.get(GeometryFeature::Width)).abs() < 0.02);
    // 20 % larger: log sizes and log length grow by ln 1.2, relative start point stays.
    let scaled = Geometry {
        metres_per_motor_unit: base.metres_per_motor_unit * 1.2,
        ..base.clone()
    };
    let g2 = plan_geometry(
        default_panda(),
        &convert_strokes(&PathSolver::new(&scaled).unwrap(), &strokes)
            .unwrap()
            .sample,
    )
    .unwrap();
    for f in [
        GeometryFeature::Width,
        GeometryFeature::Height,
        GeometryFeature::PenDownLength,
    ] {
        let d = g2.get(f) - g0.get(f);
        assert!((d - 1.2f32.ln()).abs() < 0.03, "{f:?}: {d}");
    }
    assert_eq!(
        g2.get(GeometryFeature::Strokes),
        g0.get(GeometryFeature::Strokes)
    );
    assert!((g2.get(GeometryFeature::StartX) - g0.get(GeometryFeature::StartX)).abs() < 0.03);
}
