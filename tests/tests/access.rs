//! Who can talk to `guardiand`: only processes of the daemon's own uid. iceoryx2 creates its
//! shared-memory segments and files owner-only, so a process of another user can neither
//! connect (send requests) nor open the segments that carry the trajectories.
//!
//! The second user is uid/gid 65534 (nobody), entered with `setpriv`; that needs root. Without
//! root the test says so on stderr and does not run.

use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};

use guardian_client::{Client, ClientConfig, Decision};
use guardian_tests::harness::{self, Daemon, Setup, traj};

const CHILD: &str = "GUARDIAN_ACCESS_CHILD";

/// Every file iceoryx2 created for this deployment: `/dev/shm/<prefix>*` and the files below
/// the root path.
fn iceoryx2_files(setup: &Setup) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir("/dev/shm")
        .expect("/dev/shm")
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(&setup.prefix))
        .map(|e| e.path())
        .collect();
    let mut dirs = vec![setup.dir.path().join("iox")];
    while let Some(dir) = dirs.pop() {
        for e in std::fs::read_dir(&dir).expect("root path").flatten() {
            let ft = e.file_type().expect("file type");
            if ft.is_dir() {
                dirs.push(e.path());
            } else {
                files.push(e.path());
            }
        }
    }
    files.sort();
    files
}

#[test]
fn another_user_can_neither_send_requests_nor_read_trajectories() {
    let me = std::fs::metadata("/proc/self").expect("/proc/self").uid();
    if me != 0 {
        eprintln!(
            "access test not run: switching to a second uid with setpriv needs root (uid {me})"
        );
        return;
    }
    let mut s = Setup::new(50);
    s.extra = "default-threshold = 1e9".into();
    // Make the test directory itself traversable by everyone, so what stops the other user
    // is iceoryx2's own permissions, not the temporary directory's.
    std::fs::set_permissions(s.dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let _d = Daemon::start(&s);
    let client = s.client();
    client
        .enroll("task0", &[traj(0, 1), traj(0, 2)])
        .expect("owner enrolls");
    // A check leaves a request (a trajectory) in the client's payload segment.
    let v = client.check(&traj(0, 3), "task0").expect("owner checks");
    assert_eq!(v.decision, Decision::Go);

    let files = iceoryx2_files(&s);
    let shm: Vec<_> = files.iter().filter(|p| p.starts_with("/dev/shm")).collect();
    assert!(
        shm.len() >= 2,
        "expected the daemon's and the client's segments in /dev/shm: {files:?}"
    );
    // iceoryx2 shares one segment per domain with every user on purpose: the node counter
    // (`<prefix>…node.<version>.global_mgmt`, a few bytes). Everything else is owner-only.
    let shared = |p: &Path| p.to_string_lossy().ends_with(".global_mgmt");
    for f in &files {
        let meta = std::fs::metadata(f).expect("stat");
        let mode = meta.mode();
        if shared(f) {
            assert!(meta.len() <= 4096, "{}: {} bytes", f.display(), meta.len());
        } else {
            assert_eq!(
                mode & 0o077,
                0,
                "{} is accessible to group/others (mode {mode:o})",
                f.display()
            );
        }
    }

    // The second user runs a copy of this test executable in the child role below.
    let list = files
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join("\n");
    let cfg = s.client_config();
    let out = harness::run_as_nobody(
        "second_uid_child",
        &[
            (CHILD, list.as_ref()),
            ("GUARDIAN_ACCESS_SERVICE", cfg.service_name.as_ref()),
            (
                "GUARDIAN_ACCESS_ROOT",
                cfg.iceoryx2_root_path.as_ref().unwrap().as_os_str(),
            ),
            (
                "GUARDIAN_ACCESS_PREFIX",
                cfg.iceoryx2_prefix.as_ref().unwrap().as_ref(),
            ),
        ],
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the second-uid child failed:\n{stdout}\n{stderr}"
    );
    let lines: Vec<&str> = stdout
        .lines()
        .filter(|l| l.starts_with("access:"))
        .collect();
    eprintln!("{}", lines.join("\n"));
    assert!(
        lines.iter().any(|l| l.starts_with("access: uid 65534")),
        "{stdout}"
    );
    assert!(
        lines
            .iter()
            .any(|l| l.starts_with("access: connect") && l.ends_with("denied")),
        "the second user could connect:\n{stdout}"
    );
    for f in &files {
        let line = format!("access: read {}", f.display());
        let l = lines
            .iter()
            .find(|l| l.starts_with(&line))
            .unwrap_or_else(|| panic!("no attempt on {}:\n{stdout}", f.display()));
        if shared(f) {
            assert!(l.ends_with("ALLOWED"), "{l}");
        } else {
            assert!(l.ends_with("denied"), "{l}");
        }
    }
    assert!(
        !lines.iter().any(|l| l.contains("check ALLOWED")),
        "the second user got a verdict:\n{stdout}"
    );

    // The owner keeps being served.
    let v = client.check(&traj(0, 4), "task0").expect("owner checks");
    assert_eq!(v.decision, Decision::Go);
}

/// The second user's side: try to connect and to open every file; print one line per attempt.
/// Run only by the test above, through `setpriv`.
#[test]
#[ignore = "child role of another_user_can_neither_send_requests_nor_read_trajectories"]
fn second_uid_child() {
    let list = std::env::var(CHILD).expect("run by the access test only");
    let uid = std::fs::metadata("/proc/self").expect("/proc/self").uid();
    println!("access: uid {uid}");
    let config = ClientConfig {
        service_name: std::env::var("GUARDIAN_ACCESS_SERVICE").unwrap(),
        timeout: std::time::Duration::from_secs(2),
        iceoryx2_root_path: Some(std::env::var("GUARDIAN_ACCESS_ROOT").unwrap().into()),
        iceoryx2_prefix: Some(std::env::var("GUARDIAN_ACCESS_PREFIX").unwrap()),
    };
    match Client::connect(config) {
        Ok(c) => match c.check(&traj(0, 5), "task0") {
            Ok(v) => println!("access: connect and check ALLOWED: {:?}", v.decision),
            Err(e) => println!("access: connect ALLOWED, check refused ({e})"),
        },
        Err(e) => println!("access: connect ({e}): denied"),
    }
    for f in list.lines().map(Path::new) {
        match std::fs::File::open(f) {
            Ok(_) => println!("access: read {} ALLOWED", f.display()),
            Err(e) if e.kind() == std::io::ErrorKind::PermissionDenied => {
                println!("access: read {}: denied", f.display())
            }
            Err(e) => println!("access: read {}: {e} (not a permission error)", f.display()),
        }
    }
}
