//! A bank for a new model: every class's enrolled examples embedded again by the new model,
//! its prototypes, geometry descriptors and per-class thresholds derived again, with the
//! calibration constants of the new model (never another model's: a threshold is a distance
//! in one model's embedding space).

use guardian_shared::trajectory::Resampled;

use guardian_robot::geometry::PlanGeometry;

use super::{Calibration, ClassBank, EnrollError};

/// What [`ClassBank::reembedded`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct Reembedding {
    /// The model the bank was built with.
    pub from_model: String,
    /// The model that embedded the examples again.
    pub to_model: String,
    /// Classes embedded again.
    pub classes: usize,
    /// Examples embedded again.
    pub examples: usize,
    /// The calibration the thresholds come from (its note), `None`: the bank is
    /// uncalibrated (global default threshold only), as it was.
    pub calibration: Option<String>,
}

/// [`ClassBank::reembedded`] failed; the bank is unchanged.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReembedError<E> {
    /// Classes that do not keep their enrolled examples (enrolled before bank format 4).
    #[error(
        "{} of {total} classes keep no enrolled examples (enrolled before bank format 4), e.g. {:?}",
        classes.len(), classes.first().map_or("", String::as_str)
    )]
    MissingExamples {
        /// The classes without examples.
        classes: Vec<String>,
        /// Classes in the bank.
        total: usize,
    },
    /// The bank is calibrated, but no calibration of the new model was given.
    #[error(
        "the bank's thresholds are calibrated for model {bank_model} and no calibration for model \
         {model} is available (another model's thresholds would be wrong)"
    )]
    NoCalibration {
        /// The bank's model.
        bank_model: String,
        /// The new model.
        model: String,
    },
    /// The calibration source is another model's.
    #[error("the calibration source is for model {got}, not {expected}")]
    CalibrationModel {
        /// The new model.
        expected: String,
        /// The calibration source's model.
        got: String,
    },
    /// The plans are to be embedded for another robot than the bank's.
    #[error("the bank holds plans of a {bank}-joint robot, the served robot has {served} joints")]
    Robot {
        /// Joints of the bank's robot.
        bank: usize,
        /// Joints of the served robot.
        served: usize,
    },
    /// The new model could not embed an example.
    #[error("class {class:?}: {source}")]
    Embed {
        /// The class.
        class: String,
        /// Why.
        source: E,
    },
    /// An example's embedding could not be enrolled (e.g. not finite).
    #[error("class {class:?}: {source}")]
    Enroll {
        /// The class.
        class: String,
        /// Why.
        source: EnrollError,
    },
}

impl ClassBank {
    /// Whether any threshold of the bank comes from a calibration (the bank-level record,
    /// the geometry calibration or a class's own threshold).
    pub fn is_calibrated(&self) -> bool {
        self.calibration.is_some()
            || self.geometry_calibration.is_some()
            || self.classes.values().any(|c| c.threshold.is_some())
    }

    /// The bank for `embedder`'s model: every class enrolled again, in name order, from its
    /// kept examples (embeddings, prototype and geometry descriptors as a fresh enrollment
    /// of the same plans gives them), with the thresholds of `calibrated`, a bank of that
    /// model (its default threshold, calibration record, wrong-task tolerance and geometry
    /// calibration; per-class thresholds derived from them as for any enrollment). Without
    /// `calibrated`, only an uncalibrated bank can be re-embedded (its global default
    /// threshold is kept). The plans are the served `robot`'s (the bank's robot record is
    /// kept); the generation moves past this bank's.
    ///
    /// `model` and `dim` are the new model's version and embedding length, `robot_joints`
    /// the served robot's joints, and `enrollment` embeds a class's plans as an enrollment
    /// does (the screen's `enrollment`, so a re-embedded class is exactly what a fresh
    /// enrollment of its examples would give).
    pub fn reembedded<E>(
        &self,
        model: &str,
        dim: usize,
        robot_joints: usize,
        calibrated: Option<&ClassBank>,
        mut enrollment: impl FnMut(&[Resampled]) -> Result<(Vec<Vec<f32>>, Vec<PlanGeometry>), E>,
    ) -> Result<(ClassBank, Reembedding), ReembedError<E>> {
        let model = model.to_owned();
        let missing: Vec<String> = self
            .classes_without_examples()
            .into_iter()
            .map(String::from)
            .collect();
        if !missing.is_empty() {
            return Err(ReembedError::MissingExamples {
                classes: missing,
                total: self.len(),
            });
        }
        if robot_joints != self.robot_joints() {
            return Err(ReembedError::Robot {
                bank: self.robot_joints(),
                served: robot_joints,
            });
        }
        if let Some(c) = calibrated
            && c.model_version != model
        {
            return Err(ReembedError::CalibrationModel {
                expected: model,
                got: c.model_version.clone(),
            });
        }
        let calibration: Option<&Calibration> = calibrated.and_then(|c| c.calibration.as_ref());
        if self.is_calibrated() && calibration.is_none() {
            return Err(ReembedError::NoCalibration {
                bank_model: self.model_version.clone(),
                model,
            });
        }
        let mut out = ClassBank::new(
            dim,
            model.clone(),
            calibrated.map_or(self.default_threshold, |c| c.default_threshold),
        );
        out.robot = self.robot.clone();
        if let Some(c) = calibrated {
            if let Some(cal) = &c.calibration {
                out.apply_calibration(cal.clone());
            }
            out.wrong_task_tolerance = c.wrong_task_tolerance;
            out.geometry_calibration = c.geometry_calibration.clone();
        }
        let mut examples = 0;
        for (name, class) in &self.classes {
            let xs: Vec<Resampled> = class.examples.iter().map(|x| x.to_resampled()).collect();
            let (embeddings, geometry) = enrollment(&xs).map_err(|source| ReembedError::Embed {
                class: name.clone(),
                source,
            })?;
            out.enroll_placed(name, &embeddings, &geometry, &class.examples, &class.place)
                .map_err(|source| ReembedError::Enroll {
                    class: name.clone(),
                    source,
                })?;
            examples += xs.len();
        }
        out.generation = self.generation.max(out.generation) + 1;
        let report = Reembedding {
            from_model: self.model_version.clone(),
            to_model: model,
            classes: out.len(),
            examples,
            calibration: calibration.map(|c| c.note.clone()),
        };
        Ok((out, report))
    }
}
