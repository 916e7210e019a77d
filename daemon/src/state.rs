//! Loading the daemon's state: the model named by the configuration and the class bank
//! it serves (persisted, else default, else empty), checked against each other.

use std::path::PathBuf;

use guardian_models::bank::{BankLimits, ClassBank, DEFAULT_THRESHOLD};
use guardian_models::kinematics::{PANDA_JOINTS, RobotRecord};

use guardian_shared::workcell::Workcell;

use crate::config::Config;
use crate::engine::Engine;

/// Where the bank in use came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BankSource {
    /// The persisted bank in the state directory.
    State(PathBuf),
    /// The shipped or configured default bank.
    Default(PathBuf),
    /// Nothing found; an empty bank.
    Empty,
}

impl std::fmt::Display for BankSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::State(p) => write!(f, "persisted bank {}", p.display()),
            Self::Default(p) => write!(f, "default bank {}", p.display()),
            Self::Empty => write!(f, "empty bank"),
        }
    }
}

/// Loading the model or bank failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadStateError {
    /// The model could not be loaded.
    #[error("cannot load model {path}: {detail}")]
    Model {
        /// The weights file.
        path: PathBuf,
        /// Why.
        detail: String,
    },
    /// The bank could not be loaded.
    #[error("cannot load class bank {path}: {source}")]
    Bank {
        /// The bank file.
        path: PathBuf,
        /// Why.
        source: guardian_models::bank::LoadBankError,
    },
    /// The robot could not be loaded.
    #[error("cannot load the robot: {detail}")]
    Robot {
        /// Why.
        detail: String,
    },
    /// The bank's classes were enrolled on another robot.
    #[error(
        "class bank {path} holds plans of robot {bank_robot} but this daemon serves {robot}; \
         use a bank enrolled on {robot} (or remove the file and re-enroll)"
    )]
    BankRobotMismatch {
        /// The bank file.
        path: PathBuf,
        /// The bank's robot (name, joints, URDF checksum prefix).
        bank_robot: String,
        /// The served robot.
        robot: String,
    },
    /// The bank was built with another model.
    #[error(
        "class bank {path} was built with model {bank_model} ({bank_dim}-d) but the loaded model is {model} ({model_dim}-d); \
         re-enroll the classes or remove the file"
    )]
    BankModelMismatch {
        /// The bank file.
        path: PathBuf,
        /// Model version recorded in the bank.
        bank_model: String,
        /// Its embedding dimension.
        bank_dim: usize,
        /// The loaded model's version.
        model: String,
        /// The loaded model's dimension.
        model_dim: usize,
    },
}

/// Load the model named by `config` for the robot it names, and that robot's workcell
/// rules (its description's defaults with the config's `[workcell]` keys applied); the
/// description is read once for both.
pub fn load_engine(config: &Config) -> Result<(Engine, Workcell), LoadStateError> {
    let path = config.model_path();
    let robot = config
        .robot_description()
        .map_err(|detail| LoadStateError::Robot { detail })?;
    let workcell = config
        .workcell_for(&robot)
        .map_err(|detail| LoadStateError::Robot { detail })?;
    let engine = Engine::load(&path, robot.robot).map_err(|e| LoadStateError::Model {
        path,
        detail: e.to_string(),
    })?;
    Ok((engine, workcell))
}

/// Load the bank for `engine`: the persisted one, else the default one, else empty.
pub fn load_bank(
    config: &Config,
    engine: &Engine,
) -> Result<(ClassBank, BankSource), LoadStateError> {
    let state = config.bank_path();
    let load = |path: &PathBuf| {
        ClassBank::load(path).map_err(|source| LoadStateError::Bank {
            path: path.clone(),
            source,
        })
    };
    let (mut bank, source) = if state.exists() {
        let (bank, replay) =
            ClassBank::load_with_journal(&state).map_err(|source| LoadStateError::Bank {
                path: state.clone(),
                source,
            })?;
        if replay.applied + replay.skipped > 0 {
            tracing::info!(
                applied = replay.applied,
                skipped = replay.skipped,
                journal_bytes = replay.journal_bytes,
                "replayed the bank journal"
            );
        }
        if replay.torn_bytes > 0 {
            tracing::warn!(
                torn_bytes = replay.torn_bytes,
                "ignored a torn last journal record (a change interrupted before it was acknowledged)"
            );
        }
        (bank, BankSource::State(state))
    } else if let Some(p) = config.default_bank_path() {
        (load(&p)?, BankSource::Default(p))
    } else {
        let t = config.default_threshold.unwrap_or(DEFAULT_THRESHOLD);
        (
            ClassBank::new(engine.dim(), engine.version(), t),
            BankSource::Empty,
        )
    };
    let path = || match &source {
        BankSource::State(p) | BankSource::Default(p) => p.clone(),
        BankSource::Empty => PathBuf::new(),
    };
    // A bank records the robot its plans came from; a bank file without a record (format
    // <= 2) was made with the Panda. A new, empty bank is the served robot's.
    let served = RobotRecord::of(engine.robot());
    let compatible = match (bank.robot(), &source) {
        (Some(r), _) => r == &served,
        (None, BankSource::Empty) => true,
        (None, _) => served.name == "panda" && served.joints == PANDA_JOINTS,
    };
    if !compatible {
        return Err(LoadStateError::BankRobotMismatch {
            path: path(),
            bank_robot: bank.robot().map_or_else(
                || "panda (format 2, no record)".to_owned(),
                |r| r.to_string(),
            ),
            robot: served.to_string(),
        });
    }
    bank.set_robot(served);
    if bank.dim() != engine.dim() || bank.model_version() != engine.version() {
        return Err(LoadStateError::BankModelMismatch {
            path: path(),
            bank_model: bank.model_version().to_owned(),
            bank_dim: bank.dim(),
            model: engine.version().to_owned(),
            model_dim: engine.dim(),
        });
    }
    if let Some(t) = config.default_threshold
        && t != bank.default_threshold()
    {
        bank.set_default_threshold(t);
    }
    let without = bank.classes_without_geometry();
    if bank.geometry_calibration().is_none() && !bank.is_empty() {
        tracing::warn!(%source, "class bank has no geometry calibration (format 1 or not calibrated): geometry check off");
    } else if !without.is_empty() {
        tracing::warn!(%source, classes = without.len(), first = without[0], "classes without plan-geometry descriptors (enrolled by format 1): geometry check off for them");
    }
    Ok((bank, source))
}

/// Where the loaded bank already holds more than the configured limits allow. Such a bank
/// is served as it is — the limits bound the bank's growth, and refusing to start would
/// take the screen away from the planners over a setting that makes nothing unsafe — but
/// every enroll that would add to an exceeded count is refused until classes are forgotten,
/// so the daemon says so at start, on reload and in `--check`.
pub fn limit_warnings(bank: &ClassBank, limits: &BankLimits) -> Vec<String> {
    let mut out = Vec::new();
    if bank.len() > limits.max_classes {
        out.push(format!(
            "the bank holds {} classes but max-classes is {}: every enroll of a new class will be refused",
            bank.len(),
            limits.max_classes
        ));
    }
    let over: Vec<&str> = bank
        .classes()
        .filter(|(_, c)| c.embeddings.len() > limits.max_examples_per_class)
        .map(|(n, _)| n)
        .collect();
    if let Some(first) = over.first() {
        out.push(format!(
            "{} classes (first: {first}) hold more examples than max-examples-per-class = {}: enrolls adding to them will be refused",
            over.len(),
            limits.max_examples_per_class
        ));
    }
    let bytes = bank.classes_bytes();
    if bytes > limits.max_bytes {
        out.push(format!(
            "the bank's class data is {bytes} bytes but max-bank-bytes is {}: every enroll will be refused",
            limits.max_bytes
        ));
    }
    out
}
