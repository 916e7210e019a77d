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
//! The daemon is the only creator of its own services (the request-response service and
//! its request and response events; planners only open them, and a second daemon on the
//! same service would be refused its server port), so at start a file of one of those
//! services still marked "being created" after iceoryx2's creation timeout was left by a
//! dead creator: it is removed, and the removal is logged.

use std::os::unix::fs::PermissionsExt;
use std::path::PathBuf;
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
    let age = meta
        .modified()
        .ok()
        .and_then(|m| SystemTime::now().duration_since(m).ok())
        .unwrap_or_default();
    Some(age)
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
