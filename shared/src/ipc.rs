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
}
