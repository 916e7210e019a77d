//! Faulty-plan generators on real Omniglot drawings: every fault at every severity gives a
//! valid trajectory (shared validation: within the joint limits) that differs from the
//! genuine plan.

use std::path::{Path, PathBuf};

use guardian_omniglot::corrupt::{CorruptError, Fault, SEVERITIES, corrupt};
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::read_strokes;
use guardian_shared::trajectory::validate;
use rand::SeedableRng;
use rand::rngs::StdRng;

fn shared_strokes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/omniglot/strokes")
}

fn first_drawing(character: &str) -> PathBuf {
    let dir = shared_strokes().join("Greek").join(character);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    files.remove(0)
}

#[test]
fn every_fault_gives_a_valid_changed_plan() {
    let solver = PathSolver::new(&Geometry::default()).unwrap();
    // A multi-stroke character so that every fault applies.
    let mut strokes = None;
    for c in 1..=24 {
        let s = read_strokes(&first_drawing(&format!("character{c:02}"))).unwrap();
        if s.len() >= 3 {
            strokes = Some(s);
            break;
        }
    }
    let strokes = strokes.expect("a Greek drawing with >= 3 strokes");
    let genuine = convert_strokes(&solver, &strokes).unwrap().sample;
    let mut rng = StdRng::seed_from_u64(7);
    for fault in Fault::ALL {
        let mut prev_change = 0.0f64;
        for &sev in &SEVERITIES {
            let x = corrupt(&solver, fault, sev, &strokes, &mut rng)
                .unwrap_or_else(|e| panic!("{fault:?} at {sev}: {e}"));
            // Inside the robot's limits (validation checks every joint against them).
            validate(&x, solver.robot().limits()).unwrap();
            let change = x
                .iter()
                .zip(&genuine)
                .flat_map(|(a, b)| a.iter().zip(b).map(|(p, q)| f64::from((p - q).abs())))
                .fold(0.0, f64::max);
            assert!(change > 1e-3, "{fault:?} at {sev} left the plan unchanged");
            prev_change = prev_change.max(change);
        }
        assert!(prev_change > 0.0);
    }
    // Not applicable and bad severities are errors, not panics.
    let one = vec![strokes[0].clone()];
    assert!(matches!(
        corrupt(&solver, Fault::MissingStroke, 0.5, &one, &mut rng),
        Err(CorruptError::NotApplicable { .. })
    ));
    assert!(matches!(
        corrupt(&solver, Fault::Rotated, 1.5, &strokes, &mut rng),
        Err(CorruptError::Severity(_))
    ));
}
