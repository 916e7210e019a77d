//! A bank for a new model ([`reembedded`]): every class's enrolled examples embedded again
//! by the new model through [`enrollment`], the same stages a fresh enrollment takes.

use guardian_bank::{ClassBank, Reembedding};
use guardian_models::embedder::{EMBED_DIM, EmbedError, Embedder};
use guardian_robot::geometry::PlanGeometry;
use guardian_robot::kinematics::Robot;
use guardian_shared::trajectory::Resampled;

/// [`reembedded`] failed; the bank is unchanged.
pub type ReembedError = guardian_bank::ReembedError<Box<EmbedError>>;

/// Embeddings and plan-geometry descriptors of resampled plans, as an enrollment computes
/// them (the daemon's enroll and [`reembedded`] share it, so a re-embedded class
/// is exactly what a fresh enrollment of its examples would give). The descriptors are
/// empty unless every plan draws on the canvas.
pub fn enrollment(
    embedder: &Embedder,
    robot: &Robot,
    xs: &[Resampled],
) -> Result<(Vec<Vec<f32>>, Vec<PlanGeometry>), EmbedError> {
    let mut embeddings = Vec::with_capacity(xs.len());
    let mut geometry = Vec::with_capacity(xs.len());
    for x in xs {
        let (e, path) = embedder.embed_with_pen_path(robot, x)?;
        embeddings.push(e.to_vec());
        geometry.push(guardian_robot::workcell::plan_geometry_of_path(&path));
    }
    let geometry = geometry
        .into_iter()
        .collect::<Option<Vec<_>>>()
        .unwrap_or_default();
    Ok((embeddings, geometry))
}

/// `bank` for `embedder`'s model ([`ClassBank::reembedded`]): every class enrolled again
/// from its kept examples by [`enrollment`], with the thresholds of `calibrated` (a bank of
/// that model), for the served `robot`.
pub fn reembedded(
    bank: &ClassBank,
    embedder: &Embedder,
    robot: &Robot,
    calibrated: Option<&ClassBank>,
) -> Result<(ClassBank, Reembedding), ReembedError> {
    bank.reembedded(
        embedder.version(),
        EMBED_DIM,
        robot.joints(),
        calibrated,
        |xs| enrollment(embedder, robot, xs).map_err(Box::new),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_bank::{Calibration, EnrollError, Example, LoadBankError, ReembedError};
    use guardian_robot::kinematics::default_panda as panda;
    use guardian_robot::kinematics::{PANDA_JOINTS, READY_POSE, RobotRecord};
    use guardian_shared::trajectory::{SLOTS, STEPS, TOOL};
    use sha2::{Digest, Sha256};

    /// A Panda plan near the ready pose, varied by `class` and `drawer`.
    fn plan(class: usize, drawer: usize) -> Resampled {
        let mut x = [[0.0f32; SLOTS]; STEPS];
        for (k, w) in x.iter_mut().enumerate() {
            let t = k as f32 / (STEPS - 1) as f32;
            for (j, (q, ready)) in w.iter_mut().zip(READY_POSE).take(PANDA_JOINTS).enumerate() {
                let phase = (class * 7 + j) as f32 * 0.9 + drawer as f32 * 0.05;
                let f = std::f32::consts::TAU * (1.0 + class as f32 * 0.3);
                *q = ready as f32 + 0.2 * (f * t + phase).sin();
            }
            w[TOOL] = f32::from(u8::from(t < 0.8));
        }
        x
    }

    fn calibration(note: &str) -> Calibration {
        Calibration {
            method: "genuine-quantile".into(),
            samples: 100,
            target_rate: Some(0.01),
            note: note.into(),
            global_threshold: Some(0.9),
            class_scale: Some(2.5),
            wrong_task_tolerance: Some(0.2),
            measured_rate: Some(0.01),
        }
    }

    /// A bank of `embedder`'s model with three classes enrolled as the daemon enrolls them,
    /// calibrated with `cal`.
    fn enrolled(embedder: &Embedder, cal: Option<Calibration>) -> ClassBank {
        let mut b = ClassBank::new(EMBED_DIM, embedder.version(), 0.5);
        b.set_robot(RobotRecord::of(panda()));
        if let Some(cal) = cal {
            b.apply_calibration(cal);
        }
        for c in 0..3 {
            let xs: Vec<Resampled> = (0..3 + c).map(|d| plan(c, d)).collect();
            let (e, g) = enrollment(embedder, panda(), &xs).unwrap();
            let ex: Vec<Example> = xs
                .iter()
                .map(|x| Example::from_resampled(x, PANDA_JOINTS))
                .collect();
            b.enroll_plans(&format!("task{c}"), &e, &g, &ex).unwrap();
        }
        // A class enrolled in two calls.
        let more = [plan(0, 9)];
        let (e, g) = enrollment(embedder, panda(), &more).unwrap();
        b.enroll_plans("task0", &e, &g, &[Example::from_resampled(&more[0], 7)])
            .unwrap();
        b
    }

    #[test]
    fn a_reembedded_bank_is_a_fresh_enrollment_under_the_new_model() {
        let a = Embedder::random(1);
        let b_model = Embedder::random(2);
        assert_ne!(a.version(), b_model.version());
        let old = enrolled(&a, Some(calibration("model A")));
        assert!(old.classes().all(|(_, c)| c.has_examples()));
        // Model B's calibrated bank (its own calibration, no classes needed).
        let mut reference = ClassBank::new(128, b_model.version(), 0.5);
        reference.apply_calibration(Calibration {
            global_threshold: Some(1.3),
            class_scale: Some(3.0),
            wrong_task_tolerance: Some(0.1),
            ..calibration("model B")
        });
        let (new, report) = reembedded(&old, &b_model, panda(), Some(&reference)).unwrap();
        assert_eq!(
            (
                report.classes,
                report.examples,
                report.calibration.as_deref()
            ),
            (3, 13, Some("model B"))
        );
        assert_eq!(new.model_version(), b_model.version());
        assert!(new.generation() > old.generation());
        assert_eq!(new.robot(), old.robot());
        // The same plans enrolled afresh in a bank of model B with the same calibration.
        let mut fresh = enrolled(&b_model, None);
        fresh.apply_calibration(reference.calibration().unwrap().clone());
        for ((n, c), (fn_, fc)) in new.classes().zip(fresh.classes()) {
            assert_eq!(n, fn_);
            assert_eq!(c.embeddings, fc.embeddings, "{n}");
            assert_eq!(c.prototype, fc.prototype, "{n}");
            assert_eq!(c.examples, fc.examples, "{n}");
            assert_eq!(c.geometry, fc.geometry, "{n}");
            assert_eq!(new.threshold(n), fresh.threshold(n), "{n}");
            assert_ne!(c.embeddings, old.class(n).unwrap().embeddings, "{n}");
        }
        assert_eq!(new.default_threshold(), 1.3);
        assert_eq!(new.wrong_task_tolerance(), 0.1);
        // Decisions under B: the fresh bank's (the banks' generations differ).
        for d in 0..4 {
            let q = b_model.embed(panda(), &plan(1, 20 + d)).unwrap();
            let (v, f) = (new.decide(&q, "task1", 3), fresh.decide(&q, "task1", 3));
            assert_eq!(v.bank_version, new.generation());
            assert_eq!(
                guardian_shared::verdict::Verdict {
                    bank_version: f.bank_version,
                    ..v
                },
                f
            );
        }
        // Re-embedding with the first model again gives back the original classes.
        let mut ref_a = ClassBank::new(128, a.version(), 0.5);
        ref_a.apply_calibration(calibration("model A"));
        let (back, _) = reembedded(&new, &a, panda(), Some(&ref_a)).unwrap();
        for ((n, c), (_, o)) in back.classes().zip(old.classes()) {
            assert_eq!(c.embeddings, o.embeddings, "{n}");
            assert_eq!(back.threshold(n), old.threshold(n), "{n}");
        }
    }

    #[test]
    fn a_bank_that_cannot_be_reembedded_safely_is_refused() {
        let a = Embedder::random(1);
        let b_model = Embedder::random(2);
        let old = enrolled(&a, Some(calibration("model A")));
        // Calibrated for A, no calibration for B: refused, not kept with A's thresholds.
        assert!(matches!(
            reembedded(&old, &b_model, panda(), None),
            Err(ReembedError::NoCalibration { .. })
        ));
        let uncalibrated_b = ClassBank::new(128, b_model.version(), 0.5);
        assert!(matches!(
            reembedded(&old, &b_model, panda(), Some(&uncalibrated_b)),
            Err(ReembedError::NoCalibration { .. })
        ));
        // A calibration of another model (A's own) is refused.
        assert!(matches!(
            reembedded(&old, &b_model, panda(), Some(&old)),
            Err(ReembedError::CalibrationModel { .. })
        ));
        // An uncalibrated bank keeps its global default threshold.
        let plain = enrolled(&a, None);
        let (new, report) = reembedded(&plain, &b_model, panda(), None).unwrap();
        assert_eq!(report.calibration, None);
        assert_eq!(new.default_threshold(), plain.default_threshold());
        assert!(!new.is_calibrated());
        // A class without examples (an old-format bank): refused, naming it.
        let mut old_format = plain.clone();
        old_format.enroll("legacy", &[vec![0.0; 128]]).unwrap();
        let e = reembedded(&old_format, &b_model, panda(), None).unwrap_err();
        assert!(
            matches!(&e, ReembedError::MissingExamples { classes, total: 4 } if classes == &["legacy"]),
            "{e}"
        );
        assert!(e.to_string().contains("legacy"), "{e}");
        // A bank of UR5e plans and a Panda model: refused.
        let ur5e = guardian_robot::kinematics::RobotDescription::named("ur5e")
            .unwrap()
            .robot;
        let ur_model = Embedder::random(1);
        let mut ur_bank = ClassBank::new(128, ur_model.version(), 0.5);
        ur_bank.set_robot(RobotRecord::of(&ur5e));
        let x = Example::from_resampled(&plan(0, 0), 6);
        let (e6, _) = enrollment(&ur_model, &ur5e, &[x.to_resampled()]).unwrap();
        ur_bank.enroll_plans("u", &e6, &[], &[x]).unwrap();
        assert!(matches!(
            reembedded(&ur_bank, &b_model, &Robot::panda(), None),
            Err(ReembedError::Robot { bank: 6, served: 7 })
        ));
        // Examples of another robot than the bank's are refused at enroll and at load.
        let panda_x = Example::from_resampled(&plan(0, 0), 7);
        assert!(matches!(
            ur_bank.enroll_plans("v", &e6, &[], &[panda_x]),
            Err(EnrollError::ExampleJoints {
                expected: 6,
                got: 7,
                ..
            })
        ));
        let text = String::from_utf8(ur_bank.to_bytes().unwrap()).unwrap();
        let body = text
            .split_once('\n')
            .unwrap()
            .1
            .replace("\"joints\":6", "\"joints\":7");
        let sum: String = Sha256::digest(body.as_bytes())
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let forged = format!("guardian-class-bank 4 sha256:{sum}\n{body}");
        assert!(matches!(
            ClassBank::from_bytes(forged.as_bytes()),
            Err(LoadBankError::Inconsistent { .. })
        ));
    }

    #[test]
    fn examples_round_trip_through_the_snapshot_and_the_journal() {
        let a = Embedder::random(1);
        let bank = enrolled(&a, Some(calibration("model A")));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bank.gcb");
        bank.save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.starts_with(b"guardian-class-bank 4 "));
        let loaded = ClassBank::load(&path).unwrap();
        assert_eq!(loaded, bank);
        assert_eq!(loaded.class("task0").unwrap().examples.len(), 4);
        assert_eq!(
            loaded.class("task2").unwrap().examples[4].to_resampled(),
            plan(2, 4)
        );
        // A change journalled after the snapshot keeps its examples too.
        let mut changed = loaded;
        let xs = [plan(5, 0), plan(5, 1), plan(5, 2)];
        let (e, g) = enrollment(&a, panda(), &xs).unwrap();
        let ex: Vec<Example> = xs.iter().map(|x| Example::from_resampled(x, 7)).collect();
        changed.enroll_plans("task5", &e, &g, &ex).unwrap();
        changed.append_change(&path, "task5").unwrap();
        let (replayed, replay) = ClassBank::load_with_journal(&path).unwrap();
        assert_eq!(replay.applied, 1);
        assert_eq!(replayed, changed);
        assert_eq!(replayed.class("task5").unwrap().examples, ex);
        // Without examples the bank is written as before (format 3 with a robot).
        let mut no_examples = ClassBank::new(2, "m", 0.5);
        no_examples.set_robot(RobotRecord::of(&Robot::panda()));
        no_examples.enroll("x", &[vec![0.0, 1.0]]).unwrap();
        assert!(
            no_examples
                .to_bytes()
                .unwrap()
                .starts_with(b"guardian-class-bank 3 ")
        );
    }
}
