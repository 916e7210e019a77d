//! The bank's on-disk format (header line with checksum + JSON body), loading with checks,
//! and atomic saving.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use super::{
    ClassBank, FORMAT_VERSION, FORMAT_VERSION_WITHOUT_EXAMPLES, FORMAT_VERSION_WITHOUT_PLACE,
    FORMAT_VERSION_WITHOUT_ROBOT, OLDEST_FORMAT_VERSION,
};

const MAGIC: &str = "guardian-class-bank";

/// Loading a bank failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadBankError {
    /// The file could not be read.
    #[error("cannot read class bank {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The header line is missing or malformed.
    #[error("not a guardian class bank (bad header line): {detail}")]
    BadHeader {
        /// What was wrong.
        detail: String,
    },
    /// The format version is not supported.
    #[error("class bank format {found} is not supported (this build reads {supported})")]
    UnsupportedFormat {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The body does not match its checksum.
    #[error("class bank checksum mismatch: header says {expected}, body hashes to {found}")]
    ChecksumMismatch {
        /// Checksum from the header.
        expected: String,
        /// Checksum of the body.
        found: String,
    },
    /// The body is not a valid bank document.
    #[error("class bank body does not parse: {0}")]
    Parse(#[from] serde_json::Error),
    /// The journal next to the snapshot is damaged (not just a torn last record).
    #[error("class bank journal {path} is damaged: {detail}")]
    Journal {
        /// The journal file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The document parses but is inconsistent.
    #[error("class bank is inconsistent: {detail}")]
    Inconsistent {
        /// What is wrong.
        detail: String,
    },
}

/// Saving a bank failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SaveBankError {
    /// Writing, syncing or renaming failed.
    #[error("cannot save class bank to {path}: {source}")]
    Io {
        /// The file being written.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Serialisation failed.
    #[error("cannot serialise class bank: {0}")]
    Serialize(#[from] serde_json::Error),
}

impl ClassBank {
    /// Serialise to the on-disk format (header line + JSON body).
    pub fn to_bytes(&self) -> Result<Vec<u8>, serde_json::Error> {
        let body = serde_json::to_vec(self)?;
        let sum = hex(&Sha256::digest(&body));
        // The oldest version that holds the bank, so older builds keep reading what they can.
        let version = if self.classes.values().any(|c| !c.place.is_empty()) {
            FORMAT_VERSION
        } else if self.classes.values().any(|c| !c.examples.is_empty()) {
            FORMAT_VERSION_WITHOUT_PLACE
        } else if self.robot.is_some() {
            FORMAT_VERSION_WITHOUT_EXAMPLES
        } else {
            FORMAT_VERSION_WITHOUT_ROBOT
        };
        let mut out = format!("{MAGIC} {version} sha256:{sum}\n").into_bytes();
        out.extend_from_slice(&body);
        Ok(out)
    }

    /// Parse the on-disk format, verifying version and checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, LoadBankError> {
        let nl = bytes
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| bad("no header line"))?;
        let header = std::str::from_utf8(&bytes[..nl]).map_err(|_| bad("header is not UTF-8"))?;
        let body = &bytes[nl + 1..];
        let mut parts = header.split(' ');
        if parts.next() != Some(MAGIC) {
            return Err(bad("missing magic"));
        }
        let found: u32 = parts
            .next()
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| bad("missing format version"))?;
        if !(OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&found) {
            return Err(LoadBankError::UnsupportedFormat {
                found,
                supported: FORMAT_VERSION,
            });
        }
        let expected = parts
            .next()
            .and_then(|v| v.strip_prefix("sha256:"))
            .ok_or_else(|| bad("missing checksum"))?
            .to_owned();
        let found_sum = hex(&Sha256::digest(body));
        if found_sum != expected {
            return Err(LoadBankError::ChecksumMismatch {
                expected,
                found: found_sum,
            });
        }
        let bank: ClassBank = serde_json::from_slice(body)?;
        bank.check()?;
        Ok(bank)
    }

    pub(super) fn check(&self) -> Result<(), LoadBankError> {
        let inconsistent = |detail: String| Err(LoadBankError::Inconsistent { detail });
        if !self.default_threshold.is_finite() {
            return inconsistent("default threshold is not finite".into());
        }
        if !(self.wrong_task_tolerance.is_finite() && self.wrong_task_tolerance >= 0.0) {
            return inconsistent("wrong-task tolerance is not finite and >= 0".into());
        }
        if let Some(g) = &self.geometry_calibration
            && (g.threshold.is_nan() || g.scales.iter().any(|s| !(s.is_finite() && *s > 0.0)))
        {
            return inconsistent("geometry calibration: threshold NaN or scale not > 0".into());
        }
        for (name, c) in &self.classes {
            if c.prototype.len() != self.dim {
                return inconsistent(format!("class {name:?}: prototype length"));
            }
            if c.embeddings.is_empty() {
                return inconsistent(format!("class {name:?}: no embeddings"));
            }
            if c.embeddings.iter().any(|e| e.len() != self.dim) {
                return inconsistent(format!("class {name:?}: embedding length"));
            }
            if c.threshold.is_some_and(|t| !t.is_finite()) {
                return inconsistent(format!("class {name:?}: threshold is not finite"));
            }
            if !c.geometry.is_empty() && c.geometry.len() != c.embeddings.len() {
                return inconsistent(format!("class {name:?}: geometry descriptor count"));
            }
            if c.geometry.iter().any(|g| !g.is_finite()) {
                return inconsistent(format!("class {name:?}: geometry is not finite"));
            }
            if !c.examples.is_empty() && c.examples.len() != c.embeddings.len() {
                return inconsistent(format!("class {name:?}: enrolled example count"));
            }
            if c.examples.iter().any(|x| x.joints() != self.robot_joints()) {
                return inconsistent(format!(
                    "class {name:?}: an enrolled example is not a plan of the bank's robot ({} joints)",
                    self.robot_joints()
                ));
            }
            if !c.place.is_empty() && c.place.len() != c.embeddings.len() {
                return inconsistent(format!("class {name:?}: place signature count"));
            }
            if c.place.iter().any(|p| !p.is_valid()) {
                return inconsistent(format!("class {name:?}: a place signature is not valid"));
            }
            if c.examples.iter().any(|x| !x.is_finite()) {
                return inconsistent(format!("class {name:?}: an enrolled example is not finite"));
            }
        }
        Ok(())
    }

    /// Read and verify a bank: the snapshot at `path` and, if there is one, its journal
    /// ([`ClassBank::load_with_journal`]).
    pub fn load(path: &Path) -> Result<Self, LoadBankError> {
        Self::load_with_journal(path).map(|(bank, _)| bank)
    }

    /// Read and verify the snapshot file alone.
    pub(super) fn load_snapshot(path: &Path) -> Result<Self, LoadBankError> {
        let bytes = fs::read(path).map_err(|source| LoadBankError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }

    /// Save atomically: write a temporary file in the same directory, fsync it, rename it
    /// over `path`, fsync the directory. A crash leaves either the old or the new file.
    /// The temporary file is read back and verified before the rename, so a snapshot that
    /// does not load never replaces the old one. Then remove the journal next to `path`
    /// (the snapshot holds the whole bank now): this is also the journal's compaction, and
    /// the journal is kept whenever any step before fails. The file is created mode 0600. A crash before the removal leaves records the new
    /// snapshot already holds, which a load skips by generation.
    pub fn save(&self, path: &Path) -> Result<(), SaveBankError> {
        let bytes = self.to_bytes()?;
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
            _ => PathBuf::from("."),
        };
        let file_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "bank".into());
        let tmp = dir.join(format!(
            "{}{}",
            temporary_prefix(&file_name),
            std::process::id()
        ));
        let io = |p: &Path| {
            let p = p.to_owned();
            move |source| SaveBankError::Io { path: p, source }
        };
        let result = (|| {
            let mut f = create_owner_only(&tmp).map_err(io(&tmp))?;
            f.write_all(&bytes).map_err(io(&tmp))?;
            f.sync_all().map_err(io(&tmp))?;
            drop(f);
            // Nothing is replaced or deleted before the new snapshot is known to be good:
            // read it back and verify it (checksum, consistency, generation) first.
            self.verify_written(&tmp, &bytes)
                .map_err(|detail| io(&tmp)(std::io::Error::other(detail)))?;
            fs::rename(&tmp, path).map_err(io(path))?;
            fs::File::open(&dir)
                .and_then(|d| d.sync_all())
                .map_err(io(&dir))?;
            let journal = super::journal_path(path);
            match fs::remove_file(&journal) {
                Ok(()) => fs::File::open(&dir)
                    .and_then(|d| d.sync_all())
                    .map_err(io(&dir)),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
                Err(e) => Err(io(&journal)(e)),
            }
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result
    }
}

impl ClassBank {
    /// Check that the file at `path` holds exactly `written` and that it loads as this bank
    /// (its checksum, consistency and generation).
    fn verify_written(&self, path: &Path, written: &[u8]) -> Result<(), String> {
        let read = fs::read(path).map_err(|e| format!("cannot read it back: {e}"))?;
        if read != written {
            return Err(format!(
                "read back {} bytes that differ from the {} written",
                read.len(),
                written.len()
            ));
        }
        let loaded = Self::from_bytes(&read).map_err(|e| format!("does not load back: {e}"))?;
        if loaded.generation != self.generation || loaded.classes.len() != self.classes.len() {
            return Err("loads back as another bank".into());
        }
        Ok(())
    }
}

/// Create `path` for writing, readable and writable by its owner only (mode 0600: the bank
/// holds the operator's enrolled plans).
pub(super) fn create_owner_only(path: &Path) -> std::io::Result<fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(path)
}

/// Name prefix of the temporary files [`ClassBank::save`] writes next to `file_name`.
fn temporary_prefix(file_name: &str) -> String {
    format!(".{file_name}.tmp.")
}

/// Remove temporary files that a [`ClassBank::save`] of `path` killed mid-write left behind
/// (a crash never damages `path` itself, but each crashed writer leaves its temporary).
/// Call it only while no other process saves to `path`. Returns the names removed.
pub fn remove_stale_temporaries(path: &Path) -> std::io::Result<Vec<String>> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let Some(file_name) = path.file_name() else {
        return Ok(Vec::new());
    };
    let prefix = temporary_prefix(&file_name.to_string_lossy());
    let mut removed = Vec::new();
    let entries = match fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(removed),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with(&prefix) && entry.file_type()?.is_file() {
            fs::remove_file(entry.path())?;
            removed.push(name);
        }
    }
    Ok(removed)
}

fn bad(detail: &str) -> LoadBankError {
    LoadBankError::BadHeader {
        detail: detail.to_owned(),
    }
}

pub(super) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
