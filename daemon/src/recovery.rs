//! Start-up recovery from what a crash of an earlier `guardiand` left in its iceoryx2 root.
//!
//! iceoryx2 creates a service's static configuration file (`<root>/services/<prefix><hash>
//! .service`) mode 0600 — "being created" — writes it, creates the service's dynamic
//! configuration and only then makes the file read-only (0400): the mark that the service
//! exists. A process killed between those steps leaves the file in its "being created"
//! state (often zero bytes) for good, and every later open or create of that service waits
//! iceoryx2's creation timeout and fails with `HangsInCreation`: a kill during start-up
//! could keep the daemon down. Dead-node cleanup does not remove such a file (the service
//! never came to exist).
//!
//! A kill can also fall between the creation of a **shared-memory segment** (a file in
//! `/dev/shm` named after the deployment's iceoryx2 prefix: a service's dynamic
//! configuration, or the prefix's global node-management segment) and the call that gives
//! it its size. iceoryx2 (0.10) waits for such a zero-byte segment to be sized without a
//! timeout when the opener may open it (root), and fails every open after its creation
//! timeout otherwise: either way every later start of the daemon (and node creation by the
//! planners on the same prefix) stalls or fails. iceoryx2 never maps a segment of zero
//! bytes, and a live creator sizes its segment microseconds after creating it, so at start a
//! segment under the prefix that stays zero bytes until the creation timeout has passed
//! since it was written was left by a dead creator (a younger one, as a restart right after
//! a kill finds, is waited for): it is removed before the daemon's node is created, and the
//! removal is logged ([`remove_unsized_segments`]).
//!
//! The daemon is the only creator of its own services (the request-response service and
//! its request and response events; planners only open them, and a second daemon on the
//! same service would be refused its server port), so at start a file of one of those
//! services still marked "being created" after iceoryx2's creation timeout was left by a
//! dead creator: it is removed, and the removal is logged.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use iceoryx2::prelude::*;
use iceoryx2::service::messaging_pattern::MessagingPattern;
use iceoryx2::service::service_hash::ServiceHash;

use guardian_shared::wire::{request_event_name, response_event_name};

/// The mode iceoryx2 gives a static configuration file while the service is being created.
const BEING_CREATED_MODE: u32 = 0o600;

/// The daemon's own services: its request-response service and its two event services.
pub fn own_services(service_name: &str) -> Vec<(String, MessagingPattern)> {
    vec![
        (service_name.to_owned(), MessagingPattern::RequestResponse),
        (request_event_name(service_name), MessagingPattern::Event),
        (response_event_name(service_name), MessagingPattern::Event),
    ]
}

/// The file in which iceoryx2 keeps the static configuration of service `name` with
/// `pattern` under `config`: `<root path>/<service directory>/<prefix><service hash>
/// <suffix>`. `None` if `name` is not a valid service name.
pub fn static_config_path(
    config: &iceoryx2::config::Config,
    name: &str,
    pattern: MessagingPattern,
) -> Option<PathBuf> {
    let name = ServiceName::new(name).ok()?;
    let hash = ServiceHash::new::<<ipc::Service as iceoryx2::service::Service>::ServiceNameHasher>(
        &name, pattern,
    );
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    let g = &config.global;
    let dir =
        PathBuf::from(text(g.root_path().as_bytes())).join(text(g.service.directory.as_bytes()));
    Some(dir.join(format!(
        "{}{}{}",
        text(g.prefix.as_bytes()),
        hash.as_str(),
        text(g.service.static_config_storage_suffix.as_bytes())
    )))
}

/// Whether `path` is a static configuration file still marked "being created", and how
/// long ago it was last modified.
fn being_created(path: &std::path::Path) -> Option<Duration> {
    let meta = std::fs::symlink_metadata(path).ok()?;
    if !meta.file_type().is_file() || meta.permissions().mode() & 0o777 != BEING_CREATED_MODE {
        return None;
    }
    Some(age(&meta))
}

/// How long ago a file was last modified (zero if unknown or in the future).
fn age(meta: &std::fs::Metadata) -> Duration {
    meta.modified()
        .ok()
        .and_then(|m| SystemTime::now().duration_since(m).ok())
        .unwrap_or_default()
}

/// Remove the static configuration files of the daemon's own services (for `service_name`)
/// that are still marked "being created" once iceoryx2's creation timeout has passed since
/// they were last written (a file younger than that is waited for: a live creator finishes
/// well within it). Returns the files removed, with their sizes; a file that cannot be
/// removed is logged and left.
pub fn remove_half_created_services(
    config: &iceoryx2::config::Config,
    service_name: &str,
) -> Vec<(PathBuf, u64)> {
    let timeout = config.global.creation_timeout;
    let mut removed = Vec::new();
    for (name, pattern) in own_services(service_name) {
        let Some(path) = static_config_path(config, &name, pattern) else {
            continue;
        };
        let start = Instant::now();
        while let Some(age) = being_created(&path) {
            if age < timeout && start.elapsed() < timeout {
                std::thread::sleep((timeout - age).min(Duration::from_millis(50)));
                continue;
            }
            let bytes = std::fs::metadata(&path).map_or(0, |m| m.len());
            match std::fs::remove_file(&path) {
                Ok(()) => removed.push((path.clone(), bytes)),
                Err(e) => tracing::warn!(
                    service = %name,
                    file = %path.display(),
                    error = %e,
                    "cannot remove a half-created iceoryx2 service file"
                ),
            }
            break;
        }
    }
    removed
}

/// Where Linux keeps POSIX shared memory: iceoryx2's segments are files here.
pub const SHM_DIR: &str = "/dev/shm";

/// Remove the zero-byte shared-memory segments of the deployment's iceoryx2 prefix (files in
/// [`SHM_DIR`] whose names start with it) that stay zero bytes until iceoryx2's creation
/// timeout has passed since they were last written: what a process killed between creating
/// a segment and sizing it left (module docs). A younger one is waited for (at most the
/// timeout, once for all: a restart right after a kill finds the segment younger than
/// that), since a live creator sizes it microseconds after creating it. Returns the files
/// removed; a file that cannot be removed is logged and left.
pub fn remove_unsized_segments(config: &iceoryx2::config::Config) -> Vec<PathBuf> {
    let prefix = String::from_utf8_lossy(config.global.prefix.as_bytes()).into_owned();
    remove_unsized_segments_in(Path::new(SHM_DIR), &prefix, config.global.creation_timeout)
}

/// The age of `path` if it is a regular file of zero bytes.
fn unsized_age(path: &Path) -> Option<Duration> {
    let meta = std::fs::symlink_metadata(path).ok()?;
    (meta.file_type().is_file() && meta.len() == 0).then(|| age(&meta))
}

/// [`remove_unsized_segments`] in `dir`, for names starting with `prefix`, zero bytes for
/// `timeout` since they were last written.
fn remove_unsized_segments_in(dir: &Path, prefix: &str, timeout: Duration) -> Vec<PathBuf> {
    let mut removed = Vec::new();
    if prefix.is_empty() {
        return removed;
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return removed;
    };
    let candidates: Vec<(PathBuf, Duration)> = entries
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(prefix))
        .filter_map(|e| {
            let path = e.path();
            unsized_age(&path).map(|a| (path, a))
        })
        .collect();
    let wait = candidates
        .iter()
        .map(|(_, a)| timeout.saturating_sub(*a))
        .max()
        .unwrap_or_default();
    if !wait.is_zero() {
        std::thread::sleep(wait);
    }
    for (path, _) in candidates {
        if unsized_age(&path).is_none_or(|a| a < timeout) {
            continue;
        }
        match std::fs::remove_file(&path) {
            Ok(()) => removed.push(path),
            Err(e) => tracing::warn!(
                file = %path.display(),
                error = %e,
                "cannot remove an unsized iceoryx2 shared-memory segment"
            ),
        }
    }
    removed.sort();
    removed
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Only zero-byte files of the prefix that stay so for the timeout are removed; a young
    /// one is waited for, and kept if it is sized meanwhile.
    #[test]
    fn only_unsized_segments_of_the_prefix_are_removed_after_the_timeout() {
        let dir = tempfile::tempdir().unwrap();
        let old = SystemTime::now() - Duration::from_secs(60);
        let make = |name: &str, bytes: &[u8], modified: Option<SystemTime>| {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).unwrap();
            if let Some(t) = modified {
                std::fs::File::options()
                    .write(true)
                    .open(&path)
                    .unwrap()
                    .set_modified(t)
                    .unwrap();
            }
            path
        };
        let stale = make("gd_node.0_10_0.global_mgmt", b"", Some(old));
        let stale_service = make("gd_abc123.dynamic", b"", Some(old));
        // Left by a kill just before this start: zero bytes, younger than the timeout.
        let young = make("gd_young.dynamic", b"", None);
        // A live creator's: sized while the start waits.
        let sized_later = make("gd_live.dynamic", b"", None);
        let sized = make("gd_sized.dynamic", b"state", Some(old));
        let other = make("other_node.0_10_0.global_mgmt", b"", Some(old));
        std::fs::create_dir(dir.path().join("gd_dir")).unwrap();
        let timeout = Duration::from_millis(600);
        let creator = {
            let path = sized_later.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(100));
                std::fs::write(path, b"sized").unwrap();
            })
        };
        let start = std::time::Instant::now();
        let removed = remove_unsized_segments_in(dir.path(), "gd_", timeout);
        creator.join().unwrap();
        assert!(
            start.elapsed() >= Duration::from_millis(400),
            "the young ones were waited for"
        );
        let mut want = vec![stale.clone(), stale_service.clone(), young.clone()];
        want.sort();
        assert_eq!(removed, want);
        assert!(!stale.exists() && !stale_service.exists() && !young.exists());
        assert!(sized_later.exists() && sized.exists() && other.exists());
        assert!(dir.path().join("gd_dir").is_dir());
        // No prefix, nothing removed (a deployment always has one).
        make("x.dynamic", b"", Some(old));
        assert!(remove_unsized_segments_in(dir.path(), "", Duration::ZERO).is_empty());
    }
}
