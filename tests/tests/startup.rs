//! Start-up after a kill, across real processes: a `guardiand` SIGKILLed while iceoryx2
//! creates its services leaves a service file "being created" (mode 0600, often zero bytes)
//! that made every later start fail with `HangsInCreation`, or a zero-byte shared-memory
//! segment on which iceoryx2 waited forever. The daemon must remove what a crash of its own
//! left behind, say so, and serve.

use std::os::unix::fs::PermissionsExt;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use guardian_client::Decision;
use guardian_shared::wire::response_event_name;
use guardian_tests::harness::{Daemon, Setup, traj};
use iceoryx2::prelude::*;
use iceoryx2::service::messaging_pattern::MessagingPattern;
use iceoryx2::service::service_hash::ServiceHash;

/// The iceoryx2 config of a test deployment.
fn iox_config(s: &Setup) -> iceoryx2::config::Config {
    let mut ic = iceoryx2::config::Config::default();
    let root = format!("{}/", s.dir.path().join("iox").display());
    ic.global
        .set_root_path(&iceoryx2::prelude::Path::new(root.as_bytes()).unwrap());
    ic.global.prefix = FileName::new(s.prefix.as_bytes()).unwrap();
    ic
}

/// The `*.service` files below the deployment's iceoryx2 root, with their modes.
fn service_files(s: &Setup) -> Vec<(PathBuf, u32, u64)> {
    let dir = s.dir.path().join("iox").join("services");
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return Vec::new();
    };
    let mut out: Vec<_> = entries
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".service"))
        .filter_map(|e| {
            let m = e.metadata().ok()?;
            Some((e.path(), m.permissions().mode() & 0o777, m.len()))
        })
        .collect();
    out.sort();
    out
}

/// The static configuration file of the daemon's response event service, found the way
/// iceoryx2 names it (service hash of the name and pattern, under `<root>/services`).
fn response_event_file(s: &Setup) -> PathBuf {
    let ic = iox_config(s);
    let name = ServiceName::new(&response_event_name(&s.service)).unwrap();
    let hash = ServiceHash::new::<<ipc::Service as iceoryx2::service::Service>::ServiceNameHasher>(
        &name,
        MessagingPattern::Event,
    );
    let suffix = String::from_utf8_lossy(ic.global.service.static_config_storage_suffix.as_bytes())
        .into_owned();
    s.dir.path().join("iox").join("services").join(format!(
        "{}{}{}",
        s.prefix,
        hash.as_str(),
        suffix
    ))
}

/// The half-created file the issue found: zero bytes, mode 0600, for the daemon's response
/// event service. Before the fix every start failed with `HangsInCreation`.
#[test]
fn a_half_created_service_file_left_by_a_kill_is_removed_at_start() {
    let s = Setup::new(90);
    let file = response_event_file(&s);
    // The file is where iceoryx2 keeps it: present (and read-only, created) while a daemon
    // serves.
    {
        let _d = Daemon::start(&s);
        let files = service_files(&s);
        assert!(
            files
                .iter()
                .any(|(p, mode, len)| *p == file && *mode == 0o400 && *len > 0),
            "{} not among {files:?}",
            file.display()
        );
    }
    // A kill between the file's creation and its completion leaves it like this.
    std::fs::create_dir_all(file.parent().unwrap()).unwrap();
    std::fs::write(&file, b"").unwrap();
    std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o600)).unwrap();

    starts_after_removing(&s, "removed a half-created iceoryx2 service file", &file);
}

/// Start `guardiand` over what a kill left: it must log `removal` with the path of `file`,
/// become ready, enroll and check.
fn starts_after_removing(s: &Setup, removal: &str, file: &std::path::Path) {
    let d = Daemon::start(s);
    let log = d.log();
    assert!(
        log.contains(removal) && log.contains(&file.display().to_string()),
        "the removal is not logged with {}:\n{log}",
        file.display()
    );
    let client = s.client();
    client
        .enroll("task0", &[traj(0, 1), traj(0, 2)])
        .expect("enroll after recovery");
    assert_eq!(
        client.check(&traj(0, 3), "task0").expect("check").decision,
        Decision::Go
    );
}

/// The prefix's node-management segment in /dev/shm as a kill between its creation and its
/// sizing leaves it: zero bytes, write-only (iceoryx2 makes it readable once initialised).
/// Before the fix, node creation as root waited for it forever (iceoryx2 0.10 has no
/// timeout for a zero-byte segment), so the daemon never came up; as another user, every
/// start failed.
#[test]
fn an_unsized_shared_memory_segment_left_by_a_kill_is_removed_at_start() {
    let s = Setup::new(92);
    // Where iceoryx2 keeps the segment: found after a normal start, not named by hand.
    drop(Daemon::start(&s));
    let segment = std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .find(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            name.starts_with(&s.prefix) && name.ends_with(".global_mgmt")
        })
        .expect("the prefix's node-management segment in /dev/shm");
    let file = std::fs::File::options().write(true).open(&segment).unwrap();
    file.set_len(0).unwrap();
    file.set_modified(std::time::SystemTime::now() - Duration::from_secs(60))
        .unwrap();
    drop(file);
    std::fs::set_permissions(&segment, std::fs::Permissions::from_mode(0o200)).unwrap();

    starts_after_removing(
        &s,
        "removed an unsized iceoryx2 shared-memory segment",
        &segment,
    );
}

/// SIGKILL `guardiand` at random moments of its start-up (within an undisturbed start's
/// time to READY), over and over: every restart after a kill must come up and serve.
/// Prints the counts for `docs/reliability.md`.
#[test]
fn kills_during_start_up_never_keep_the_daemon_down() {
    const ROUNDS: usize = 40;
    let s = Setup::new(91);
    // Undisturbed starts for the kill window (the quickest of three: the first is cold).
    let ready = (0..3)
        .map(|_| {
            let t = Instant::now();
            let d = Daemon::start(&s);
            let ready = t.elapsed();
            drop(d);
            ready
        })
        .min()
        .unwrap();
    let window_us = (ready.as_micros() as u64).max(1_000);
    let mut rng: u64 = 0x9e37_79b9_7f4a_7c15;
    let (mut killed_before_ready, mut served, mut recovered, mut unsized_segments) = (0, 0, 0, 0);
    for round in 0..ROUNDS {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        let mut d = Daemon::spawn(&s, &[], None);
        std::thread::sleep(Duration::from_micros(rng % window_us));
        if !d.notes().iter().any(|n| n.contains("READY=1")) {
            killed_before_ready += 1;
        }
        d.signal("KILL");
        d.wait_exit();
        drop(d);
        // The restart after the kill must serve.
        let d = Daemon::start(&s);
        if let Err(e) = s.client().status() {
            panic!(
                "round {round}: restart after a kill not served: {e}\n{}",
                d.log()
            );
        }
        served += 1;
        let log = d.log();
        if log.contains("removed a half-created iceoryx2 service file") {
            recovered += 1;
        }
        if log.contains("removed an unsized iceoryx2 shared-memory segment") {
            unsized_segments += 1;
        }
    }
    eprintln!(
        "{ROUNDS} kills during start-up (undisturbed start {ready:?}, kill within it): \
         {killed_before_ready} before READY; restarts served {served} of {ROUNDS}, \
         {recovered} of them after removing a half-created service file, {unsized_segments} after \
         removing an unsized shared-memory segment"
    );
    assert_eq!(served, ROUNDS);
}
