//! The iceoryx2 configuration of a guardian deployment, built the same way by the daemon and
//! the client from the two settings that isolate deployments and tests: `global.root-path`
//! and `global.prefix`.

use std::path::{Path, PathBuf};

use iceoryx2::prelude::{FileName, SemanticString, SemanticStringError};

/// An iceoryx2 operation failed: what was being done, with iceoryx2's error as the source.
#[derive(Debug, thiserror::Error)]
#[error("iceoryx2: {what}: {source}")]
pub struct Iceoryx2Error {
    /// What was being done.
    pub what: &'static str,
    /// The iceoryx2 error.
    #[source]
    pub source: Box<dyn std::error::Error + Send + Sync>,
}

impl Iceoryx2Error {
    /// A `map_err` adapter: the iceoryx2 error of doing `what`.
    pub fn during<E: std::error::Error + Send + Sync + 'static>(
        what: &'static str,
    ) -> impl FnOnce(E) -> Self {
        move |e| Self {
            what,
            source: Box::new(e),
        }
    }
}

/// A root path or prefix iceoryx2 does not accept.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Iceoryx2ConfigError {
    /// The root path is not a valid iceoryx2 path.
    #[error("invalid iceoryx2 root path {path:?}: {source}")]
    RootPath {
        /// The path given.
        path: PathBuf,
        /// iceoryx2's reason.
        #[source]
        source: SemanticStringError,
    },
    /// The prefix is not a valid iceoryx2 file name.
    #[error("invalid iceoryx2 prefix {prefix:?}: {source}")]
    Prefix {
        /// The prefix given.
        prefix: String,
        /// iceoryx2's reason.
        #[source]
        source: SemanticStringError,
    },
}

/// The default iceoryx2 configuration with `root_path` (a trailing `/` is added if missing)
/// and `prefix` applied when given.
pub fn iceoryx2_config(
    root_path: Option<&Path>,
    prefix: Option<&str>,
) -> Result<iceoryx2::config::Config, Iceoryx2ConfigError> {
    let mut c = iceoryx2::config::Config::default();
    if let Some(root) = root_path {
        let mut s = root.to_string_lossy().into_owned();
        if !s.ends_with('/') {
            s.push('/');
        }
        let p = iceoryx2::prelude::Path::new(s.as_bytes()).map_err(|source| {
            Iceoryx2ConfigError::RootPath {
                path: root.to_owned(),
                source,
            }
        })?;
        c.global.set_root_path(&p);
    }
    if let Some(prefix) = prefix {
        c.global.prefix =
            FileName::new(prefix.as_bytes()).map_err(|source| Iceoryx2ConfigError::Prefix {
                prefix: prefix.to_owned(),
                source,
            })?;
    }
    Ok(c)
}

/// Directory, inside the iceoryx2 root path, of the files in which daemons name their admin
/// sockets ([`admin_locator_path`]).
pub const ADMIN_LOCATOR_DIR: &str = "guardian-admin";

/// The file in which the daemon serving `service` under the iceoryx2 configuration
/// `config` names its admin socket: `<root-path>/guardian-admin/<prefix>+<service>.socket`,
/// prefix and service name percent-encoded (every byte but ASCII letters, digits, `-`, `.`
/// and `_`), so distinct deployments never share a file. A client that reaches the daemon
/// with the same service name, root path and prefix finds its admin socket there
/// (`docs/guardiand.md`, "Admin endpoint").
pub fn admin_locator_path(config: &iceoryx2::config::Config, service: &str) -> PathBuf {
    let root = String::from_utf8_lossy(config.global.root_path().as_bytes()).into_owned();
    let file = format!(
        "{}+{}.socket",
        percent_encode(config.global.prefix.as_bytes()),
        percent_encode(service.as_bytes())
    );
    PathBuf::from(root).join(ADMIN_LOCATOR_DIR).join(file)
}

fn percent_encode(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len());
    for &b in bytes {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'.' | b'_') {
            s.push(char::from(b));
        } else {
            s.push_str(&format!("%{b:02X}"));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn root_path_and_prefix_are_applied_and_bad_ones_are_typed_errors() {
        let c = iceoryx2_config(Some(Path::new("/tmp/guardian-x")), Some("gx_")).unwrap();
        assert_eq!(c.global.prefix.as_bytes(), b"gx_");
        assert!(matches!(
            iceoryx2_config(None, Some("a/b")),
            Err(Iceoryx2ConfigError::Prefix { .. })
        ));
    }

    #[test]
    fn admin_locator_paths_follow_root_path_prefix_and_service() {
        let c = iceoryx2_config(Some(Path::new("/run/g/iox")), Some("gx_")).unwrap();
        assert_eq!(
            admin_locator_path(&c, "guardian/v4/rpc"),
            Path::new("/run/g/iox/guardian-admin/gx_+guardian%2Fv4%2Frpc.socket")
        );
        // Distinct settings, distinct files; the separator cannot come from either part.
        let other = iceoryx2_config(Some(Path::new("/run/g/iox")), Some("gx_+a")).unwrap();
        assert_ne!(
            admin_locator_path(&other, "b"),
            admin_locator_path(&c, "a+b")
        );
        assert_ne!(
            admin_locator_path(&c, "x"),
            admin_locator_path(
                &iceoryx2_config(Some(Path::new("/run/h")), Some("gx_")).unwrap(),
                "x"
            )
        );
    }
}
