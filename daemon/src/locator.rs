//! Where the admin socket is, for clients that were given no path: the daemon writes the
//! socket's absolute path into a small file at a place every client can compute from what it
//! already knows to reach the daemon — the iceoryx2 root path, prefix and service name
//! ([`guardian_shared::ipc::admin_locator_path`]) — and removes it when it stops.
//! `guardianctl` and the Python `AdminClient` read it (`guardian_client::AdminClient::locate`).

use std::io::Write;
use std::os::unix::fs::{DirBuilderExt, PermissionsExt};
use std::path::{Path, PathBuf};

/// The published locator file; removed on drop if it still names this daemon's socket.
#[derive(Debug)]
pub struct AdminLocator {
    file: PathBuf,
    content: String,
}

impl AdminLocator {
    /// Write the locator of `socket` for the daemon serving `service` under `iceoryx2`.
    /// The directory and the file are owner-only (0700, 0600), like everything else of the
    /// daemon's under its iceoryx2 root path but iceoryx2's node counter: the daemon's own
    /// user and root read it (the quick-start user, and root as the installed admin); an
    /// admin of another uid passes `--admin-socket` or uses the installed default path.
    /// Clients trust a locator only if it belongs to them or to root.
    pub fn publish(
        iceoryx2: &iceoryx2::config::Config,
        service: &str,
        socket: &Path,
    ) -> std::io::Result<Self> {
        let socket = std::path::absolute(socket)?;
        let content = socket
            .to_str()
            .filter(|s| !s.contains('\n'))
            .ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "the socket path is not one line of UTF-8",
                )
            })?
            .to_owned()
            + "\n";
        let file = guardian_shared::ipc::admin_locator_path(iceoryx2, service);
        let dir = file.parent().unwrap_or(Path::new("/"));
        match std::fs::DirBuilder::new().mode(0o700).create(dir) {
            Ok(()) => std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700))?,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e),
        }
        let tmp = file.with_extension(format!("{}.tmp", std::process::id()));
        let write = || -> std::io::Result<()> {
            let mut f = std::fs::File::create(&tmp)?;
            f.set_permissions(std::fs::Permissions::from_mode(0o600))?;
            f.write_all(content.as_bytes())?;
            std::fs::rename(&tmp, &file)
        };
        if let Err(e) = write() {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
        Ok(Self { file, content })
    }

    /// [`Self::publish`], logging instead of failing: without a locator the daemon still
    /// serves; clients then need the socket's path.
    pub fn publish_or_warn(
        iceoryx2: &iceoryx2::config::Config,
        service: &str,
        socket: &Path,
    ) -> Option<Self> {
        match Self::publish(iceoryx2, service, socket) {
            Ok(l) => {
                tracing::debug!(file = %l.file.display(), "admin socket locator written");
                Some(l)
            }
            Err(e) => {
                let file = guardian_shared::ipc::admin_locator_path(iceoryx2, service);
                tracing::warn!(file = %file.display(), error = %e, "cannot write the admin socket locator: clients need --admin-socket");
                None
            }
        }
    }

    /// The locator file.
    pub fn file(&self) -> &Path {
        &self.file
    }
}

impl Drop for AdminLocator {
    fn drop(&mut self) {
        // Another daemon may have replaced it since (then it names that one's socket).
        if std::fs::read_to_string(&self.file).is_ok_and(|c| c == self.content) {
            let _ = std::fs::remove_file(&self.file);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn publishes_the_absolute_socket_path_and_removes_only_its_own_file() {
        let dir = tempfile::tempdir().unwrap();
        let ic = guardian_shared::ipc::iceoryx2_config(Some(dir.path()), Some("lt_")).unwrap();
        let l = AdminLocator::publish(&ic, "svc/a", Path::new("rel/admin.sock")).unwrap();
        let text = std::fs::read_to_string(l.file()).unwrap();
        let expected = std::env::current_dir().unwrap().join("rel/admin.sock");
        assert_eq!(text, format!("{}\n", expected.display()));
        let mode = std::fs::metadata(l.file().parent().unwrap())
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o7777, 0o700, "the locator directory is owner-only");
        let mode = std::fs::metadata(l.file()).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600, "the locator file is owner-only");
        let file = l.file().to_owned();
        drop(l);
        assert!(!file.exists());
        // A newer daemon's locator survives an older one's stop.
        let old = AdminLocator::publish(&ic, "svc/a", Path::new("/x/old.sock")).unwrap();
        let new = AdminLocator::publish(&ic, "svc/a", Path::new("/x/new.sock")).unwrap();
        drop(old);
        assert_eq!(
            std::fs::read_to_string(new.file()).unwrap(),
            "/x/new.sock\n"
        );
    }
}
