//! The shipped default bank (`models/default-bank.gcb`, built by `guardian-lab bank`) loads
//! with the shipped model and carries the calibrated thresholds the decision uses.

use guardian_bank::MIN_CLASS_CALIBRATION;
use guardian_daemon::config::Config;
use guardian_daemon::state::{BankSource, LoadStateError, load_bank, load_model};

#[test]
fn shipped_default_bank_matches_the_shipped_model_and_is_calibrated() {
    let state = tempfile::tempdir().unwrap();
    let config = Config {
        state_dir: Some(state.path().to_owned()),
        ..Config::default()
    };
    let (embedder, station) = load_model(&config).unwrap();
    let (bank, source) = load_bank(&config, &embedder, &station).unwrap();
    // The shipped bank predates the robot record: it is the Panda's, and now says so.
    let robot = bank.robot().expect("recorded at load");
    assert_eq!((robot.name.as_str(), robot.joints), ("panda", 7));
    assert!(matches!(source, BankSource::Default(_)), "{source}");
    assert!(!bank.is_empty());
    let cal = bank.calibration().expect("the default bank is calibrated");
    assert_eq!(cal.global_threshold, Some(bank.default_threshold()));
    assert!(cal.class_scale.is_some_and(|s| s > 0.0));
    assert_eq!(cal.wrong_task_tolerance, Some(bank.wrong_task_tolerance()));
    for (name, class) in bank.classes() {
        if class.embeddings.len() >= MIN_CLASS_CALIBRATION {
            let t = class.threshold.expect("per-class threshold");
            assert!(t > 0.0 && t.is_finite(), "{name}: {t}");
            assert_eq!(bank.threshold(name), Some(t));
            // The decision uses the class's own threshold: its prototype itself is a go.
            let d = bank.decide(&class.prototype, name, 3);
            assert_eq!(d.threshold, Some(t));
        }
    }
}

/// A daemon serving the UR5e refuses the shipped bank (Panda plans) with a clear error.
#[test]
fn a_ur5e_daemon_refuses_the_panda_bank() {
    let state = tempfile::tempdir().unwrap();
    let config = Config {
        robot: "ur5e".into(),
        state_dir: Some(state.path().to_owned()),
        ..Config::default()
    };
    let (embedder, station) = load_model(&config).unwrap();
    assert_eq!(station.robot().joints(), 6);
    let e = load_bank(&config, &embedder, &station).unwrap_err();
    assert!(matches!(e, LoadStateError::BankRobotMismatch { .. }), "{e}");
    let text = e.to_string();
    assert!(text.contains("panda") && text.contains("ur5e"), "{text}");
}

/// The shipped default bank keeps every class's enrolled plans, and they are the plans its
/// embeddings came from: the shipped model embeds them to the stored embeddings (so a
/// daemon with a new model re-embeds the very tasks the bank holds).
#[test]
fn shipped_default_bank_keeps_the_plans_its_embeddings_came_from() {
    let state = tempfile::tempdir().unwrap();
    let config = Config {
        state_dir: Some(state.path().to_owned()),
        ..Config::default()
    };
    let (embedder, station) = load_model(&config).unwrap();
    let (bank, _) = load_bank(&config, &embedder, &station).unwrap();
    assert!(bank.classes_without_examples().is_empty());
    let mut worst = 0.0f32;
    for (name, class) in bank.classes() {
        let xs: Vec<_> = class.examples.iter().map(|x| x.to_resampled()).collect();
        let (embeddings, geometry) =
            guardian_screen::reembed::enrollment(&embedder, station.robot(), &xs).unwrap();
        assert_eq!(geometry, class.geometry, "{name}");
        for (e, stored) in embeddings.iter().zip(&class.embeddings) {
            worst = worst.max(guardian_bank::distance(e, stored));
        }
    }
    // The bank was built by the lab's batched embedding; the daemon embeds one plan at a
    // time: the same numbers up to float rounding.
    assert!(worst < 1e-5, "largest distance {worst}");
}
