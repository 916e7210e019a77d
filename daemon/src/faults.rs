//! Fault points for crash tests (cargo feature `fault-points`; without it every point is a
//! no-op the compiler removes). With the feature, the environment variable
//! `GUARDIAND_FAULT_POINT` names one point; when the daemon reaches it, it logs the point
//! and kills itself with SIGKILL — no destructor, flush or fsync runs, exactly as a
//! `kill -9` at that instant. The crash tests (`tests/tests/fleet.rs`) use it to stop the
//! admin path between its steps deterministically.

/// After a change's fleet record is appended and fsynced, before the bank journals it.
pub const FLEET_AFTER_RECORD: &str = "fleet-after-record";
/// After the bank journalled a change (and its fleet record exists), before it is published.
pub const AFTER_JOURNAL: &str = "after-journal";
/// After a change's fleet record is published, before the admin is answered.
pub const FLEET_AFTER_PUBLISH: &str = "fleet-after-publish";

/// The variable naming the armed fault point.
pub const ENV: &str = "GUARDIAND_FAULT_POINT";

/// Die here with SIGKILL if `point` is the armed fault point.
#[cfg(feature = "fault-points")]
pub fn hit(point: &str) {
    static ARMED: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    let armed = ARMED.get_or_init(|| std::env::var(ENV).ok().filter(|v| !v.is_empty()));
    if armed.as_deref() == Some(point) {
        tracing::error!(point, "fault point reached: killing the daemon (SIGKILL)");
        let _ =
            rustix::process::kill_process(rustix::process::getpid(), rustix::process::Signal::KILL);
        // SIGKILL cannot be caught; this is never reached.
        std::process::abort();
    }
}

/// Without the `fault-points` feature, fault points do nothing.
#[cfg(not(feature = "fault-points"))]
#[inline(always)]
pub fn hit(_point: &str) {}
