//! Loading the daemon's state: the model named by the configuration and the class bank
//! it serves (persisted, else default, else empty), checked against each other.

use std::path::{Path, PathBuf};
use std::time::Instant;

use guardian_bank::{BankLimits, ClassBank, DEFAULT_THRESHOLD};
use guardian_models::embedder::{EmbedError, Embedder, LoadModelError};
use guardian_robot::kinematics::{PANDA_JOINTS, RobotRecord};
use guardian_screen::check::Station;
use guardian_screen::reembed::ReembedError;

use crate::config::{Config, ConfigError};

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
    #[error("cannot load model {path}: {source}")]
    Model {
        /// The weights file.
        path: PathBuf,
        /// Why.
        source: LoadModelError,
    },
    /// The model cannot embed plans of the configured robot.
    #[error("model {path} cannot serve the configured robot: {source}")]
    ModelRobot {
        /// The weights file.
        path: PathBuf,
        /// Why.
        source: EmbedError,
    },
    /// The bank could not be loaded.
    #[error("cannot load class bank {path}: {source}")]
    Bank {
        /// The bank file.
        path: PathBuf,
        /// Why.
        source: guardian_bank::LoadBankError,
    },
    /// The robot (or its workcell) could not be loaded.
    #[error("cannot load the robot: {0}")]
    Robot(Box<ConfigError>),
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
    /// The bank was built with another model and cannot be embedded again for this one.
    #[error(
        "class bank {path} was built with model {bank_model} ({bank_dim}-d) but the loaded model is {model} ({model_dim}-d), \
         and it cannot be re-embedded: {reason}"
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
        /// Why it cannot be re-embedded, and what the operator can do.
        reason: String,
    },
    /// The re-embedded bank could not be persisted.
    #[error("cannot persist the class bank re-embedded for model {model}: {source}")]
    PersistReembedded {
        /// The new model.
        model: String,
        /// Why.
        source: guardian_bank::SaveBankError,
    },
}

impl From<ConfigError> for LoadStateError {
    fn from(e: ConfigError) -> Self {
        Self::Robot(Box::new(e))
    }
}

/// Whether [`load_bank_with`] may write the bank it re-embedded for a new model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Persist {
    /// Save it atomically as the state bank (the daemon), so the next start does not
    /// re-embed again.
    Yes,
    /// Keep it in memory only (`guardiand --check`).
    No,
}

/// Load the model named by `config` and resolve the robot it names with its workcell rules
/// ([`Config::station`]), once; the model must be able to serve that robot.
pub fn load_model(config: &Config) -> Result<(Embedder, Station), LoadStateError> {
    let station = config.station()?;
    let path = config.model_path();
    let embedder = Embedder::load(&path).map_err(|source| LoadStateError::Model {
        path: path.clone(),
        source,
    })?;
    embedder
        .serves(station.robot())
        .map_err(|source| LoadStateError::ModelRobot { path, source })?;
    Ok((embedder, station))
}

/// Load the bank for `embedder` and `station`'s robot: the persisted one, else the default
/// one, else empty. A bank built with another model is embedded again from its kept
/// examples ([`reembed`]) and saved as the state bank.
pub fn load_bank(
    config: &Config,
    embedder: &Embedder,
    station: &Station,
) -> Result<(ClassBank, BankSource), LoadStateError> {
    load_bank_with(config, embedder, station, Persist::Yes)
}

/// [`load_bank`], persisting a re-embedded bank or not.
pub fn load_bank_with(
    config: &Config,
    embedder: &Embedder,
    station: &Station,
    persist: Persist,
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
            ClassBank::new(guardian_models::embedder::EMBED_DIM, embedder.version(), t),
            BankSource::Empty,
        )
    };
    let path = || match &source {
        BankSource::State(p) | BankSource::Default(p) => p.clone(),
        BankSource::Empty => PathBuf::new(),
    };
    // A bank records the robot its plans came from; a bank file without a record (format
    // <= 2) was made with the Panda. A new, empty bank is the served robot's.
    let served = RobotRecord::of(station.robot());
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
    if bank.dim() != guardian_models::embedder::EMBED_DIM
        || bank.model_version() != embedder.version()
    {
        bank = reembed(config, embedder, station, &bank, &path())?;
        if persist == Persist::Yes {
            let state = config.bank_path();
            bank.save(&state)
                .map_err(|source| LoadStateError::PersistReembedded {
                    model: embedder.version().to_owned(),
                    source,
                })?;
            tracing::info!(bank = %state.display(), "saved the re-embedded class bank");
        }
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

/// Embed `bank` (built with another model) again with `embedder` for `station`'s robot: every class from
/// its kept examples, its thresholds from the calibration of the new model, which is the
/// configured default bank's when that bank was built with the new model (the calibrated
/// default bank shipped with it). Without one, only an uncalibrated bank is re-embedded:
/// another model's thresholds are never kept. Logs what it did.
pub fn reembed(
    config: &Config,
    embedder: &Embedder,
    station: &Station,
    bank: &ClassBank,
    path: &Path,
) -> Result<ClassBank, LoadStateError> {
    let started = Instant::now();
    let mismatch = |reason: String, remedy: &str| LoadStateError::BankModelMismatch {
        path: path.to_owned(),
        bank_model: bank.model_version().to_owned(),
        bank_dim: bank.dim(),
        model: embedder.version().to_owned(),
        model_dim: guardian_models::embedder::EMBED_DIM,
        reason: format!("{reason}; {remedy}"),
    };
    let default = config.default_bank_path();
    let calibrated = match &default {
        Some(p) if p.as_path() != path => match ClassBank::load(p) {
            Ok(b) if b.model_version() == embedder.version() && b.calibration().is_some() => {
                Some(b)
            }
            Ok(_) => None,
            Err(e) => {
                tracing::warn!(default_bank = %p.display(), error = %e, "cannot read the default bank for the new model's calibration");
                None
            }
        },
        _ => None,
    };
    let (out, report) = guardian_screen::reembed::reembedded(
        bank,
        embedder,
        station.robot(),
        calibrated.as_ref(),
    )
    .map_err(|e| match e {
            ReembedError::MissingExamples { .. } => mismatch(
                e.to_string(),
                "re-enroll those classes, or remove the file and re-enroll every class",
            ),
            ReembedError::NoCalibration { .. } => mismatch(
                format!(
                    "{e}; the new model's calibration comes from the configured default bank, \
                     which must be a calibrated bank built with model {} ({})",
                    embedder.version(),
                    default.as_ref().map_or_else(
                        || "none is configured".to_owned(),
                        |p| format!("{} is not", p.display())
                    )
                ),
                "install the default bank shipped with the model (`default-bank`), or go back to the model the bank was built with",
            ),
            other => mismatch(other.to_string(), "remove the file and re-enroll the classes"),
        })?;
    tracing::info!(
        from_model = %report.from_model,
        to_model = %report.to_model,
        classes = report.classes,
        examples = report.examples,
        calibration = report.calibration.as_deref().unwrap_or("none (uncalibrated bank, global default threshold kept)"),
        calibration_bank = %default.as_ref().filter(|_| calibrated.is_some()).map_or_else(String::new, |p| p.display().to_string()),
        ms = started.elapsed().as_millis() as u64,
        bank = %path.display(),
        "re-embedded the class bank for a new model: every class from its enrolled examples, thresholds derived again"
    );
    Ok(out)
}
