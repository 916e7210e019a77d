//! A new model does not lose enrolled tasks, across real processes: classes enrolled under
//! model A (the shipped model, on the shipped default bank) are served by a daemon restarted
//! with model B, re-embedded from the bank's kept examples, with B's calibration (B's
//! default bank), and it answers every check exactly as a daemon that enrolled the same
//! plans under B from scratch. The re-embedded bank is persisted (the next start does not
//! re-embed), and a bank without examples (an old format) is still refused, clearly.

use std::path::{Path, PathBuf};

use guardian_bank::{Calibration, ClassBank};
use guardian_client::{Client, Trajectory, Verdict};
use guardian_models::embedder::Embedder;
use guardian_robot::kinematics::{Robot, RobotRecord};
use guardian_tests::harness::{self, Daemon, Setup, traj};

/// The classes the operator enrolls under model A: (name, sample class, drawers).
const ENROLLED: [(&str, u32, &[u32]); 3] = [
    ("pick-a", 1, &[0, 1, 2, 3]),
    ("pick-b", 2, &[0, 1, 2]),
    ("place-c", 5, &[1, 2, 3, 4, 5]),
];

fn enroll_all(client: &Client) {
    for (name, class, drawers) in ENROLLED {
        let ex: Vec<Trajectory> = drawers.iter().map(|&d| traj(class, d)).collect();
        client.enroll(name, &ex).expect("enroll");
    }
    // One class extended by a second call.
    client.enroll("pick-a", &[traj(1, 7)]).expect("enroll more");
}

/// Genuine plans, wrong-task plans and a plan of a default-bank class, checked by claim.
fn checks(client: &Client) -> Vec<Verdict> {
    let mut out = Vec::new();
    for (name, class, _) in ENROLLED {
        for d in [10, 11] {
            out.push(client.check(&traj(class, d), name).expect("check"));
        }
        out.push(client.check(&traj(7, 10), name).expect("check"));
    }
    out.push(
        client
            .check(&traj(1, 12), "Greek/character01")
            .expect("check"),
    );
    out
}

fn names(client: &Client) -> Vec<(String, u32)> {
    client
        .classes()
        .expect("classes")
        .into_iter()
        .map(|c| (c.name, c.examples))
        .collect()
}

/// Model B's calibrated default bank, as it would ship with B: the shipped default bank's
/// classes embedded by B, with a calibration of B's own (numbers made up for the test, not
/// A's).
fn default_bank_for(model: &Path, out: &Path) {
    let b = Embedder::load(model).expect("model B");
    let shipped = ClassBank::load(&harness::workspace_root().join("models/default-bank.gcb"))
        .expect("shipped default bank");
    let mut calibration = ClassBank::new(128, b.version(), 0.5);
    calibration.set_robot(RobotRecord::of(&Robot::panda()));
    calibration.apply_calibration(Calibration {
        method: "test".into(),
        samples: 1,
        target_rate: Some(0.01),
        note: format!("made-up calibration of model {}", b.version()),
        global_threshold: Some(0.8),
        class_scale: Some(3.5),
        wrong_task_tolerance: Some(0.05),
        measured_rate: None,
    });
    let (bank, _) = guardian_screen::reembed::reembedded(
        &shipped,
        &b,
        guardian_robot::kinematics::default_panda(),
        Some(&calibration),
    )
    .expect("the shipped default bank keeps its examples");
    bank.save(out).expect("save B's default bank");
}

fn set(s: &mut Setup, model: &Path, default_bank: &Path) {
    s.model = model.to_owned();
    s.default_bank = Some(default_bank.to_owned());
}

#[test]
fn classes_enrolled_under_one_model_are_served_by_the_next_as_if_enrolled_under_it() {
    let mut s = Setup::new(71);
    let shipped_model = harness::workspace_root().join("models/embedder.safetensors");
    let shipped_bank = harness::workspace_root().join("models/default-bank.gcb");
    let model_b: PathBuf = s.dir.path().join("model-b.safetensors");
    Embedder::random(72).save(&model_b).expect("save model B");
    let version_b = Embedder::load(&model_b).unwrap().version().to_owned();
    let bank_b = s.dir.path().join("default-bank-b.gcb");
    default_bank_for(&model_b, &bank_b);
    let state_bank = s.state_dir().join("bank.gcb");

    // Model A: enroll, check, stop.
    set(&mut s, &shipped_model, &shipped_bank);
    let (listed_a, verdicts_a) = {
        let _d = Daemon::start(&s);
        let client = s.client();
        enroll_all(&client);
        (names(&client), checks(&client))
    };
    let version_a = verdicts_a[0].model_version.clone();
    assert_ne!(version_a, version_b);
    assert_eq!(listed_a.len(), 64 + ENROLLED.len());

    // Model B on the same state: re-embedded at start, logged, persisted.
    set(&mut s, &model_b, &bank_b);
    let (listed_b, verdicts_b) = {
        let d = Daemon::start(&s);
        let log = d.log();
        assert!(
            log.contains("re-embedded the class bank for a new model")
                && log.contains(&format!("from_model={version_a}"))
                && log.contains(&format!("to_model={version_b}"))
                && log.contains("classes=67"),
            "{log}"
        );
        // What the daemon logged (shown with --nocapture): classes, models, time taken.
        for line in log.lines().filter(|l| l.contains("re-embedded")) {
            eprintln!("{line}");
        }
        let client = s.client();
        (names(&client), checks(&client))
    };
    assert_eq!(listed_b, listed_a, "the same classes, the same examples");
    let persisted = ClassBank::load(&state_bank).expect("state bank");
    assert_eq!(persisted.model_version(), version_b);
    assert!(
        std::fs::read(&state_bank)
            .unwrap()
            .starts_with(b"guardian-class-bank 4 ")
    );
    for (a, b) in verdicts_a.iter().zip(&verdicts_b) {
        assert_eq!(b.model_version, version_b);
        assert_ne!(a.claimed_distance, b.claimed_distance, "{a:?} vs {b:?}");
    }

    // The next start under B does not re-embed again.
    {
        let d = Daemon::start(&s);
        assert!(!d.log().contains("re-embedded"), "{}", d.log());
        assert_eq!(checks(&s.client()), verdicts_b);
    }

    // A daemon of model B that enrolls the same plans from scratch answers alike.
    std::fs::rename(s.state_dir(), s.dir.path().join("state-reembedded")).unwrap();
    let verdicts_fresh = {
        let _d = Daemon::start(&s);
        let client = s.client();
        enroll_all(&client);
        assert_eq!(names(&client), listed_a);
        checks(&client)
    };
    let strip = |v: &[Verdict]| -> Vec<Verdict> {
        v.iter()
            .map(|x| Verdict {
                bank_version: 0,
                ..x.clone()
            })
            .collect()
    };
    assert_eq!(strip(&verdicts_b), strip(&verdicts_fresh));
    // The checks exercise the decision: some go, some no-go.
    assert!(verdicts_b.iter().any(Verdict::is_go));
    assert!(verdicts_b.iter().any(|v| !v.is_go()));
}

#[test]
fn a_bank_without_examples_is_refused_by_another_model_with_a_clear_message() {
    let mut s = Setup::new(73);
    std::fs::create_dir_all(s.state_dir()).unwrap();
    // Embeddings only, as every bank before format 4: built with this setup's model.
    harness::random_bank(&s.model, 3, 4, 7)
        .save(&s.state_dir().join("bank.gcb"))
        .unwrap();
    let other = s.dir.path().join("other.safetensors");
    Embedder::random(74).save(&other).unwrap();
    s.model = other;
    let out = harness::run_to_exit(&s);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cannot be re-embedded")
            && err.contains("3 of 3 classes keep no enrolled examples")
            && err.contains("re-enroll"),
        "{err}"
    );
}
