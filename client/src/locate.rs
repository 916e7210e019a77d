//! Finding the daemon's admin socket without being told its path ([`AdminClient::locate`]).

use std::os::unix::fs::{FileTypeExt, MetadataExt};
use std::path::{Path, PathBuf};

use guardian_shared::wire::DEFAULT_ADMIN_SOCKET;

use crate::{AdminClient, ClientConfig};

/// The environment variable that names the admin socket outright.
pub const ADMIN_SOCKET_ENV: &str = "GUARDIAN_ADMIN_SOCKET";

/// Where the quick-start daemon (no config, started in a checkout) puts its admin socket,
/// relative to its working directory.
pub const QUICK_START_ADMIN_SOCKET: &str = "guardiand-state/admin.sock";

/// No admin socket was found; every place looked at, with what was there.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "no admin socket found for service {service:?} (is guardiand running? else name the socket with --admin-socket or ${ADMIN_SOCKET_ENV}); looked at: {}",
    .looked.iter().map(|(p, what)| format!("{} ({what})", p.display())).collect::<Vec<_>>().join("; ")
)]
pub struct LocateAdminError {
    /// The daemon's service name.
    pub service: String,
    /// The places looked at, in order, and what was found there.
    pub looked: Vec<(PathBuf, String)>,
}

impl AdminClient {
    /// The admin client of the daemon that [`crate::Client::connect`] with `config` would
    /// reach, each call waiting at most `config.timeout`. The socket is, in this order:
    /// 1. `$GUARDIAN_ADMIN_SOCKET`, if set (taken as given);
    /// 2. the socket named by the daemon's locator file
    ///    ([`guardian_shared::ipc::admin_locator_path`] of `config`'s iceoryx2 root path,
    ///    prefix and service name), which every running daemon writes — trusted only if it
    ///    belongs to the caller or to root;
    /// 3. [`DEFAULT_ADMIN_SOCKET`], the installed layout's socket;
    /// 4. [`QUICK_START_ADMIN_SOCKET`] in the working directory.
    ///
    /// A socket must exist to be chosen; the error lists every place and what was there.
    pub fn locate(config: &ClientConfig) -> Result<Self, LocateAdminError> {
        if let Some(p) = std::env::var_os(ADMIN_SOCKET_ENV).filter(|v| !v.is_empty()) {
            return Ok(Self::new(PathBuf::from(p), config.timeout));
        }
        let mut looked = Vec::new();
        match guardian_shared::ipc::iceoryx2_config(
            config.iceoryx2_root_path.as_deref(),
            config.iceoryx2_prefix.as_deref(),
        ) {
            Ok(ic) => {
                let file = guardian_shared::ipc::admin_locator_path(&ic, &config.service_name);
                match read_locator(&file) {
                    Ok(socket) => match is_socket(&socket) {
                        Ok(()) => return Ok(Self::new(socket, config.timeout)),
                        Err(what) => {
                            looked.push((file, format!("names {}: {what}", socket.display())))
                        }
                    },
                    Err(what) => looked.push((file, what)),
                }
            }
            Err(e) => looked.push((PathBuf::from("(locator file)"), e.to_string())),
        }
        let mut fixed = vec![PathBuf::from(DEFAULT_ADMIN_SOCKET)];
        fixed.push(
            std::path::absolute(QUICK_START_ADMIN_SOCKET)
                .unwrap_or_else(|_| QUICK_START_ADMIN_SOCKET.into()),
        );
        for socket in fixed {
            match is_socket(&socket) {
                Ok(()) => return Ok(Self::new(socket, config.timeout)),
                Err(what) => looked.push((socket, what)),
            }
        }
        Err(LocateAdminError {
            service: config.service_name.clone(),
            looked,
        })
    }
}

fn is_socket(p: &Path) -> Result<(), String> {
    match std::fs::metadata(p) {
        Ok(m) if m.file_type().is_socket() => Ok(()),
        Ok(_) => Err("not a socket".into()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err("absent".into()),
        Err(e) => Err(e.to_string()),
    }
}

/// The socket a locator file names, if the file is trustworthy: owned by the caller or
/// root (another user could otherwise point an admin at a socket of theirs).
fn read_locator(file: &Path) -> Result<PathBuf, String> {
    let meta = match std::fs::symlink_metadata(file) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err("absent: no daemon with these iceoryx2 settings wrote one".into());
        }
        Err(e) => return Err(e.to_string()),
    };
    let me = rustix::process::geteuid().as_raw();
    if !meta.is_file() {
        return Err("not a regular file: ignored".into());
    }
    if meta.uid() != me && meta.uid() != 0 {
        return Err(format!(
            "owned by uid {}, neither this user ({me}) nor root: ignored",
            meta.uid()
        ));
    }
    let text = std::fs::read_to_string(file).map_err(|e| e.to_string())?;
    let line = text.lines().next().unwrap_or_default().trim();
    if !line.starts_with('/') {
        return Err(format!("does not name an absolute path: {line:?}"));
    }
    Ok(PathBuf::from(line))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locator_files_name_sockets_and_bad_ones_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("l.socket");
        assert!(read_locator(&f).unwrap_err().starts_with("absent"));
        std::fs::write(&f, "/run/x/admin.sock\n").unwrap();
        assert_eq!(read_locator(&f).unwrap(), Path::new("/run/x/admin.sock"));
        std::fs::write(&f, "relative.sock\n").unwrap();
        assert!(read_locator(&f).unwrap_err().contains("absolute"));
        assert_eq!(is_socket(&f).unwrap_err(), "not a socket");
        assert_eq!(is_socket(&dir.path().join("none")).unwrap_err(), "absent");
        let sock = dir.path().join("s.sock");
        let _l = std::os::unix::net::UnixListener::bind(&sock).unwrap();
        assert_eq!(is_socket(&sock), Ok(()));
    }
}
