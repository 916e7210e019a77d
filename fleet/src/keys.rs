//! Ed25519 keys of a fleet: generation, key files, public keys in hex.
//!
//! A secret key file holds one line, the 32-byte secret seed as 64 lower-case hex digits,
//! and must be readable by its owner only (mode 0600); its public key file (`<path>.pub`)
//! holds the public key the same way. Keys are generated from 32 bytes of `/dev/urandom`,
//! so no random-number crate (and no `rand_core` version) is involved.

use std::io::{Read, Write};
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

pub use ed25519_dalek::{SigningKey, VerifyingKey};

/// Reading, writing or parsing a key failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum KeyError {
    /// A key file could not be read or written.
    #[error("key file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A secret key file may be read by others than its owner.
    #[error(
        "secret key file {path} has mode {mode:o}; it must not be readable by group or others (chmod 600)"
    )]
    Permissions {
        /// The file.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
    },
    /// A key is not 64 hex digits.
    #[error("{what}: expected 64 hex digits, got {got:?}")]
    Hex {
        /// Which key.
        what: String,
        /// What was found (cut to 80 characters).
        got: String,
    },
    /// 32 bytes that are not a valid Ed25519 public key.
    #[error("{what}: not a valid Ed25519 public key")]
    InvalidPublicKey {
        /// Which key.
        what: String,
    },
}

/// Lower-case hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        let _ = write!(s, "{b:02x}");
    }
    s
}

/// 32 bytes from 64 hex digits (surrounding white space ignored).
pub fn unhex32(text: &str, what: &str) -> Result<[u8; 32], KeyError> {
    let t = text.trim();
    let bad = || KeyError::Hex {
        what: what.to_owned(),
        got: t.chars().take(80).collect(),
    };
    if t.len() != 64 || !t.is_ascii() {
        return Err(bad());
    }
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(&t[2 * i..2 * i + 2], 16).map_err(|_| bad())?;
    }
    Ok(out)
}

/// A public key from its 64 hex digits.
pub fn parse_public_key(text: &str, what: &str) -> Result<VerifyingKey, KeyError> {
    let bytes = unhex32(text, what)?;
    VerifyingKey::from_bytes(&bytes).map_err(|_| KeyError::InvalidPublicKey {
        what: what.to_owned(),
    })
}

/// A new signing key from 32 bytes of `/dev/urandom`.
pub fn generate() -> Result<SigningKey, KeyError> {
    let path = Path::new("/dev/urandom");
    let mut seed = [0u8; 32];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut seed))
        .map_err(|source| KeyError::Io {
            path: path.to_owned(),
            source,
        })?;
    Ok(SigningKey::from_bytes(&seed))
}

/// The public key file of the secret key file `path`: `<path>.pub`.
pub fn public_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_os_string();
    name.push(".pub");
    PathBuf::from(name)
}

/// Generate a key pair and write it: the secret to `path` (mode 0600, never overwriting an
/// existing file), the public key to `<path>.pub`. Returns the public key.
pub fn write_key_pair(path: &Path) -> Result<VerifyingKey, KeyError> {
    let key = generate()?;
    let io = |p: &Path| {
        let p = p.to_owned();
        move |source| KeyError::Io { path: p, source }
    };
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .map_err(io(path))?;
    f.write_all(format!("{}\n", hex(&key.to_bytes())).as_bytes())
        .and_then(|()| f.sync_all())
        .map_err(io(path))?;
    let public = key.verifying_key();
    let pub_path = public_path(path);
    std::fs::write(&pub_path, format!("{}\n", hex(public.as_bytes()))).map_err(io(&pub_path))?;
    Ok(public)
}

/// Read a secret key file written by [`write_key_pair`]; refuses a file readable by group
/// or others.
pub fn read_signing_key(path: &Path) -> Result<SigningKey, KeyError> {
    let io = |source| KeyError::Io {
        path: path.to_owned(),
        source,
    };
    let mode = std::fs::metadata(path).map_err(io)?.permissions().mode() & 0o777;
    if mode & 0o077 != 0 {
        return Err(KeyError::Permissions {
            path: path.to_owned(),
            mode,
        });
    }
    let text = std::fs::read_to_string(path).map_err(io)?;
    let seed = unhex32(&text, &format!("secret key file {}", path.display()))?;
    Ok(SigningKey::from_bytes(&seed))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_pair_round_trips_and_is_private() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.key");
        let public = write_key_pair(&path).unwrap();
        let key = read_signing_key(&path).unwrap();
        assert_eq!(key.verifying_key(), public);
        let text = std::fs::read_to_string(public_path(&path)).unwrap();
        assert_eq!(parse_public_key(&text, "pub").unwrap(), public);
        let mode = std::fs::metadata(&path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600);
        // Never overwrites a key.
        assert!(matches!(write_key_pair(&path), Err(KeyError::Io { .. })));
        // Two keys differ.
        assert_ne!(generate().unwrap().to_bytes(), key.to_bytes());
    }

    #[test]
    fn readable_secret_and_bad_hex_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("k");
        write_key_pair(&path).unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
        assert!(matches!(
            read_signing_key(&path),
            Err(KeyError::Permissions { mode: 0o644, .. })
        ));
        assert!(matches!(unhex32("abc", "x"), Err(KeyError::Hex { .. })));
        assert!(matches!(
            unhex32(&"zz".repeat(32), "x"),
            Err(KeyError::Hex { .. })
        ));
        assert!(matches!(
            unhex32(&"é".repeat(32), "x"),
            Err(KeyError::Hex { .. })
        ));
        assert_eq!(unhex32(&"0a".repeat(32), "x").unwrap(), [10u8; 32]);
    }
}
