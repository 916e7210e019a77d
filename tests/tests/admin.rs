//! A planner can neither exhaust nor rewrite the bank, across real processes: enrollment past
//! each configured limit is refused with a typed error and changes nothing (also through
//! `guardianctl`, which exits non-zero with the reason); under admin separation the
//! planners' iceoryx2 service refuses enroll and forget while the admin socket serves them;
//! a caller that is not an admin (a second uid) is refused by the socket; malformed admin
//! frames never crash the daemon.

use std::io::{Read, Write};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use guardian_bank::{ClassBank, journal_path};
use guardian_client::{AdminClient, CheckError, Decision, EnrollError, LimitKind, Trajectory};
use guardian_tests::harness::{self, Daemon, Setup, traj};

const CHILD: &str = "GUARDIAN_ADMIN_CHILD_SOCKET";

fn admin_socket(s: &Setup) -> PathBuf {
    s.dir.path().join("admin.sock")
}

fn admin(s: &Setup) -> AdminClient {
    AdminClient::new(admin_socket(s), Duration::from_secs(10))
}

/// What the daemon has persisted: class names with example counts, and the journal's size.
fn persisted(s: &Setup) -> (Vec<(String, usize)>, u64) {
    let path = s.state_dir().join("bank.gcb");
    let (bank, _) = ClassBank::load_with_journal(&path).expect("bank loads");
    let classes = bank
        .classes()
        .map(|(n, c)| (n.to_owned(), c.embeddings.len()))
        .collect();
    let journal = std::fs::metadata(journal_path(&path)).map_or(0, |m| m.len());
    (classes, journal)
}

fn limit_of(r: Result<guardian_client::ClassInfo, EnrollError>) -> guardian_client::Limit {
    match r {
        Err(EnrollError::Request(CheckError::LimitExceeded { limit, .. })) => limit,
        other => panic!("expected a limit error, got {other:?}"),
    }
}

fn write_csv(dir: &Path, name: &str, t: &Trajectory) -> PathBuf {
    let p = dir.join(name);
    let text: String = t
        .as_flat()
        .chunks(8)
        .map(|row| {
            row.iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(",")
                + "\n"
        })
        .collect();
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn enrollment_past_each_limit_is_refused_and_changes_nothing() {
    let mut s = Setup::new(60);
    s.extra = format!(
        "default-threshold = 1e9\nmax-classes = 2\nmax-examples-per-class = 3\n[admin]\nsocket = {:?}\n",
        admin_socket(&s)
    );
    let d = Daemon::start(&s);
    let client = s.client();
    client
        .enroll("task0", &[traj(0, 1), traj(0, 2)])
        .expect("enroll");
    client.enroll("task1", &[traj(1, 1)]).expect("enroll");
    let before = persisted(&s);
    let version = client.status().expect("status").bank_version;

    // A third class.
    let l = limit_of(client.enroll("task2", &[traj(2, 1)]));
    assert_eq!((l.kind, l.max, l.requested), (LimitKind::Classes, 2, 3));
    // A fourth example of task0, also through the admin socket.
    let l = limit_of(client.enroll("task0", &[traj(0, 3), traj(0, 4)]));
    assert_eq!(
        (l.kind, l.max, l.requested),
        (LimitKind::ExamplesPerClass, 3, 4)
    );
    let l = limit_of(admin(&s).enroll("task1", &[traj(1, 2), traj(1, 3), traj(1, 4)]));
    assert_eq!(l.kind, LimitKind::ExamplesPerClass);
    // guardianctl exits non-zero and says why.
    let files: Vec<PathBuf> = (1..=2)
        .map(|i| write_csv(s.dir.path(), &format!("ex{i}.csv"), &traj(2, i)))
        .collect();
    let out = Command::new(harness::ctl_bin())
        .arg("--admin-socket")
        .arg(admin_socket(&s))
        .args(["enroll", "task2"])
        .args(&files)
        .output()
        .expect("run guardianctl");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "guardianctl enroll succeeded: {err}");
    assert!(err.contains("max-classes"), "{err}");
    eprintln!("guardianctl: {}", err.trim());

    // Nothing changed: served classes, bank version, files on disk.
    let st = client.status().expect("status");
    assert_eq!((st.classes, st.bank_version), (2, version));
    assert_eq!(persisted(&s), before);
    // Within the limits enrollment still works.
    client
        .enroll("task0", &[traj(0, 5)])
        .expect("a third example fits");
    drop(d);

    // The size limit: restart with room for half a class more than the bank holds.
    let bytes = {
        let (bank, _) =
            ClassBank::load_with_journal(&s.state_dir().join("bank.gcb")).expect("bank");
        bank.classes_bytes()
    };
    s.extra = format!(
        "default-threshold = 1e9\nmax-bank-bytes = {}\n[admin]\nsocket = {:?}\n",
        bytes + bytes / 4,
        admin_socket(&s)
    );
    let _d = Daemon::start(&s);
    let client = s.client();
    let before = persisted(&s);
    let l = limit_of(client.enroll("task3", &[traj(3, 1), traj(3, 2)]));
    assert_eq!((l.kind, l.max), (LimitKind::BankBytes, bytes + bytes / 4));
    assert!(l.requested > l.max, "{l:?}");
    assert_eq!(client.status().expect("status").classes, 2);
    assert_eq!(persisted(&s), before);
}

#[test]
fn with_admin_separation_planners_cannot_enroll_or_forget_but_admins_can() {
    let mut s = Setup::new(61);
    s.extra = format!(
        "default-threshold = 1e9\n[admin]\nseparation = true\nsocket = {:?}\nuids = [0]\n",
        admin_socket(&s)
    );
    let _d = Daemon::start(&s);
    let planner = s.client();
    let admin = admin(&s);
    let root = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m));
    if root.ok() != Some(0) {
        eprintln!("admin test partly skipped: the admin uid in this test is root");
        return;
    }
    admin
        .enroll("task0", &[traj(0, 1), traj(0, 2)])
        .expect("admin enrolls");
    match planner.enroll("task1", &[traj(1, 1)]) {
        Err(EnrollError::Request(CheckError::NotPermitted { message })) => {
            eprintln!("planner enroll: not permitted: {message}")
        }
        other => panic!("planner enroll: {other:?}"),
    }
    match planner.forget("task0") {
        Err(CheckError::NotPermitted { .. }) => {}
        other => panic!("planner forget: {other:?}"),
    }
    // Check, identify, classes and status stay on iceoryx2.
    let names: Vec<String> = planner
        .classes()
        .expect("classes")
        .into_iter()
        .map(|c| c.name)
        .collect();
    assert_eq!(names, ["task0"]);
    assert_eq!(
        planner.check(&traj(0, 3), "task0").expect("check").decision,
        Decision::Go
    );

    // Malformed admin frames: each is answered or the connection closed; the daemon lives.
    let frames: Vec<Vec<u8>> = vec![
        vec![],
        vec![1, 2],
        0u32.to_le_bytes().to_vec(),
        u32::MAX.to_le_bytes().to_vec(),
        [200u32.to_le_bytes().to_vec(), vec![7; 100]].concat(),
        [152u32.to_le_bytes().to_vec(), vec![0xff; 152]].concat(),
    ];
    for f in &frames {
        let mut c = UnixStream::connect(admin_socket(&s)).expect("connect admin socket");
        c.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let _ = c.write_all(f);
        let _ = c.shutdown(std::net::Shutdown::Write);
        let mut reply = Vec::new();
        let _ = c.read_to_end(&mut reply);
    }
    admin.forget("task0").expect("admin forgets");
    assert!(planner.classes().expect("classes").is_empty());
    assert_eq!(
        admin.forget("task0"),
        Err(CheckError::UnknownClass {
            class: "task0".into()
        })
    );
}

#[test]
fn a_caller_not_in_the_admin_list_is_refused_by_the_admin_socket() {
    let me = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m));
    if me.ok() != Some(0) {
        eprintln!("admin access test not run: switching to a second uid with setpriv needs root");
        return;
    }
    let mut s = Setup::new(62);
    s.extra = format!(
        "default-threshold = 1e9\n[admin]\nseparation = true\nsocket = {:?}\nuids = [0]\n",
        admin_socket(&s)
    );
    // The second user must reach the socket; only the daemon's credential check stops it.
    std::fs::set_permissions(s.dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let _d = Daemon::start(&s);
    admin(&s)
        .enroll("task0", &[traj(0, 1), traj(0, 2)])
        .expect("root enrolls");
    let before = persisted(&s);

    let socket = admin_socket(&s);
    let out = harness::run_as_nobody("second_uid_admin_child", &[(CHILD, socket.as_os_str())]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "child failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<&str> = stdout.lines().filter(|l| l.starts_with("admin:")).collect();
    eprintln!("{}", lines.join("\n"));
    assert!(
        lines.iter().any(|l| l.starts_with("admin: uid 65534")),
        "{stdout}"
    );
    assert!(
        lines
            .iter()
            .any(|l| l.starts_with("admin: enroll not permitted")),
        "{stdout}"
    );
    assert!(
        lines
            .iter()
            .any(|l| l.starts_with("admin: forget not permitted")),
        "{stdout}"
    );
    assert_eq!(persisted(&s), before, "the refused caller changed the bank");
    assert!(_d.log().contains("caller is not an admin"), "{}", _d.log());
}

/// The second user's side. Run only by the test above, through `setpriv`.
#[test]
#[ignore = "child role of a_caller_not_in_the_admin_list_is_refused_by_the_admin_socket"]
fn second_uid_admin_child() {
    let socket = std::env::var(CHILD).expect("run by the admin access test only");
    let uid = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m));
    println!("admin: uid {}", uid.unwrap_or(u32::MAX));
    let admin = AdminClient::new(socket, Duration::from_secs(10));
    match admin.enroll("intruder", &[traj(1, 1)]) {
        Err(EnrollError::Request(CheckError::NotPermitted { message })) => {
            println!("admin: enroll not permitted ({message})")
        }
        other => println!("admin: enroll {other:?}"),
    }
    match admin.forget("task0") {
        Err(CheckError::NotPermitted { message }) => {
            println!("admin: forget not permitted ({message})")
        }
        other => println!("admin: forget {other:?}"),
    }
}

const SLOW_CHILD: &str = "GUARDIAN_ADMIN_SLOW_CHILD_SOCKET";

/// Whether the daemon still holds connection `c` open: no EOF, no bytes waiting.
fn still_open(mut c: &UnixStream) -> bool {
    c.set_nonblocking(true).unwrap();
    let mut b = [0u8; 1];
    let open = matches!(c.read(&mut b), Err(e) if e.kind() == std::io::ErrorKind::WouldBlock);
    c.set_nonblocking(false).unwrap();
    open
}

/// A caller that is not an admin is refused at connect, before any of its frame is read, so
/// it cannot hold the socket; an admin connection that stalls mid-frame delays no other
/// request and is closed at its deadline; both are logged. (Found: a uid-1001 process that
/// announced a frame and sent a byte every 4 s held the socket for 28 s, and a root enroll
/// meanwhile took 27.1 s.)
#[test]
fn a_slow_caller_is_refused_or_cut_off_and_delays_no_other_admin() {
    let me = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m));
    if me.ok() != Some(0) {
        eprintln!("slow admin caller test not run: switching to a second uid needs root");
        return;
    }
    let mut s = Setup::new(63);
    s.extra = format!(
        "default-threshold = 1e9\n[admin]\nseparation = true\nsocket = {:?}\nuids = [0]\n",
        admin_socket(&s)
    );
    std::fs::set_permissions(s.dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let d = Daemon::start(&s);
    let root = admin(&s);
    let timed = |class: &str, drawer: u32| {
        let t = std::time::Instant::now();
        root.enroll(class, &[traj(0, drawer), traj(0, drawer + 1)])
            .expect("root enrolls");
        t.elapsed()
    };
    timed("warm-up", 1);
    let alone = timed("alone", 3);

    // A second uid that announces a whole frame and dribbles one byte a second.
    let socket = admin_socket(&s);
    let child = std::thread::spawn(move || {
        harness::run_as_nobody("second_uid_slow_child", &[(SLOW_CHILD, socket.as_os_str())])
    });
    d.wait_log("refused before reading its request");
    let beside_non_admin = timed("beside-non-admin", 5);
    let out = child.join().expect("child thread");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!(
        "{}",
        stdout
            .lines()
            .filter(|l| l.starts_with("admin:"))
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert!(
        stdout.contains("admin: slow caller answered NotPermitted"),
        "the slow non-admin caller was not refused at once:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let log = d.log();
    assert!(
        log.lines()
            .any(|l| l.contains("refused before reading its request") && l.contains("65534")),
        "{log}"
    );

    // An admin connection that stalls mid-frame: other admins are served meanwhile, and
    // the stalled one is still open after they are answered (it is not what they waited
    // for); it is closed at its deadline and logged.
    let mut slow = UnixStream::connect(admin_socket(&s)).expect("connect");
    slow.write_all(&152u32.to_le_bytes()).unwrap();
    slow.write_all(&[0u8; 10]).unwrap();
    let beside_slow_admin = timed("beside-slow-admin", 7);
    assert!(
        still_open(&slow),
        "the enroll was served only after the stalled connection ended"
    );
    slow.set_read_timeout(Some(harness::PATIENCE)).unwrap();
    let mut rest = Vec::new();
    let _ = slow.read_to_end(&mut rest);
    d.wait_log("not received within");
    eprintln!(
        "root enroll (2 examples) alone {alone:?}, with a dribbling non-admin connection {beside_non_admin:?}, \
         with a stalled admin connection open {beside_slow_admin:?}"
    );
    let names: Vec<(String, usize)> = persisted(&s).0;
    assert_eq!(names.len(), 4, "{names:?}");
}

/// The second user's side of the test above: announce a 152-byte frame, send one byte a
/// second, and report what the daemon answers.
#[test]
#[ignore = "child role of a_slow_caller_is_refused_or_cut_off_and_delays_no_other_admin"]
fn second_uid_slow_child() {
    let socket = std::env::var(SLOW_CHILD).expect("run by the slow caller test only");
    let mut c = UnixStream::connect(&socket).expect("connect");
    let start = std::time::Instant::now();
    let mut w = c.try_clone().expect("clone");
    let dribble = std::thread::spawn(move || {
        let mut sent = 0;
        if w.write_all(&152u32.to_le_bytes()).is_err() {
            return sent;
        }
        for _ in 0..12 {
            if w.write_all(&[0u8]).is_err() {
                break;
            }
            sent += 1;
            std::thread::sleep(Duration::from_secs(1));
        }
        sent
    });
    c.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let mut len = [0u8; 4];
    let answer = c.read_exact(&mut len).and_then(|()| {
        let mut body = vec![0u8; u32::from_le_bytes(len) as usize];
        c.read_exact(&mut body).map(|()| body)
    });
    let ms = start.elapsed().as_millis();
    match answer.map(|b| guardian_shared::wire::admin::decode_response(&b, 0)) {
        Ok(Ok((r, _))) => {
            let status = guardian_shared::wire::decode_failure(&r)
                .ok()
                .flatten()
                .map_or("none".to_string(), |f| {
                    format!("{f:?}")
                        .split([' ', '{'])
                        .next()
                        .unwrap_or("")
                        .to_string()
                });
            println!(
                "admin: slow caller answered {status} (request id {}) after {ms} ms",
                r.request_id
            )
        }
        other => println!("admin: slow caller got no answer after {ms} ms: {other:?}"),
    }
    drop(c);
    let sent = dribble.join().unwrap_or(0);
    println!("admin: slow caller sent {sent} bytes of its frame");
}

/// An enroll or forget whose client gave up waiting (timeout) is not applied by the daemon,
/// and the client reports `OutcomeUnknown` — never a plain failure for a change that then
/// happens. (Found: `guardianctl enroll` exited 1 with `read response: Resource temporarily
/// unavailable` and the daemon applied the enroll ~22 s later.) The daemon is stopped
/// (SIGSTOP) to hold the requests past the clients' timeouts.
#[test]
fn a_change_whose_requester_gave_up_is_not_applied_and_the_client_says_outcome_unknown() {
    let mut s = Setup::new(64);
    let me = std::fs::metadata("/proc/self")
        .map(|m| std::os::unix::fs::MetadataExt::uid(&m))
        .unwrap();
    s.extra = format!(
        "default-threshold = 1e9\n[admin]\nseparation = true\nsocket = {:?}\nuids = [{me}]\n",
        admin_socket(&s)
    );
    let d = Daemon::start(&s);
    admin(&s)
        .enroll("task0", &[traj(0, 1), traj(0, 2)])
        .expect("enroll");
    let impatient = AdminClient::new(admin_socket(&s), Duration::from_millis(300));
    let files: Vec<PathBuf> = (1..=2)
        .map(|i| write_csv(s.dir.path(), &format!("g{i}.csv"), &traj(2, i)))
        .collect();

    d.signal("STOP");
    let enrolled = impatient.enroll("ghost", &[traj(1, 1), traj(1, 2)]);
    let forgot = impatient.forget("task0");
    // guardianctl gives up too, then asks the daemon what became of it.
    let ctl = Command::new(harness::ctl_bin())
        .arg("--admin-socket")
        .arg(admin_socket(&s))
        .args(["--timeout-ms", "300", "enroll", "ghost2"])
        .args(&files)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run guardianctl");
    std::thread::sleep(Duration::from_millis(1500));
    d.signal("CONT");
    let out = ctl.wait_with_output().expect("guardianctl");
    let err = String::from_utf8_lossy(&out.stderr);
    eprintln!("guardianctl: {}", err.trim());

    match &enrolled {
        Err(EnrollError::Request(CheckError::OutcomeUnknown { op, class, .. })) => {
            assert_eq!((*op, class.as_str()), ("enroll", "ghost"))
        }
        other => panic!("enroll: expected an unknown outcome, got {other:?}"),
    }
    match &forgot {
        Err(CheckError::OutcomeUnknown { op, class, .. }) => {
            assert_eq!((*op, class.as_str()), ("forget", "task0"))
        }
        other => panic!("forget: expected an unknown outcome, got {other:?}"),
    }
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("outcome unknown") && err.contains("the enroll was not applied"),
        "{err}"
    );
    // The daemon dropped all three changes: their requesters had gone.
    let start = std::time::Instant::now();
    while d.log().matches("its requester has gone").count() < 3 {
        assert!(start.elapsed() < harness::PATIENCE, "{}", d.log());
        std::thread::sleep(Duration::from_millis(20));
    }
    let names: Vec<String> = admin(&s)
        .classes()
        .expect("classes")
        .into_iter()
        .map(|c| c.name)
        .collect();
    assert_eq!(
        names,
        ["task0"],
        "a change reported as unknown or failed was applied"
    );
    assert_eq!(persisted(&s).0, vec![("task0".to_owned(), 2)]);
}

/// Limits set below what the loaded bank already holds are served as they are, with a
/// warning at start and in `--check` (found: `max-classes = 10` with the 64-class default
/// bank passed silently, and every enroll was refused).
#[test]
fn limits_below_the_loaded_bank_are_warned_at_start_and_in_check() {
    let mut s = Setup::new(65);
    s.extra = "default-threshold = 1e9\n".into();
    {
        let _d = Daemon::start(&s);
        let c = s.client();
        for k in 0..3 {
            c.enroll(&format!("task{k}"), &[traj(k, 1), traj(k, 2)])
                .expect("enroll");
        }
    }
    s.extra = "default-threshold = 1e9\nmax-classes = 2\nmax-examples-per-class = 1\n".into();
    let config = s.write_config();
    let out = Command::new(harness::bin())
        .arg("--config")
        .arg(&config)
        .arg("--check")
        .output()
        .expect("guardiand --check");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    eprintln!("{}", stdout.trim());
    assert!(stdout.contains("ok: "), "{stdout}");
    assert!(
        stdout.contains("warning:") && stdout.contains("holds 3 classes but max-classes is 2"),
        "{stdout}"
    );
    assert!(stdout.contains("max-examples-per-class = 1"), "{stdout}");
    let d = Daemon::start(&s);
    assert!(
        d.log().contains("configured limits below the loaded bank"),
        "{}",
        d.log()
    );
    assert_eq!(s.client().classes().expect("classes").len(), 3);
}

/// guardianctl reads an all-text CSV as a parse error, not as an empty trajectory (found:
/// every non-numeric line before the first numeric one was skipped, and the daemon
/// answered `TooFewWaypoints at 0`). One header line is still allowed.
#[test]
fn guardianctl_refuses_an_all_text_csv() {
    let dir = tempfile::tempdir().unwrap();
    let text = dir.path().join("words.csv");
    std::fs::write(&text, "hello,world\nthis is,not a trajectory\n").unwrap();
    let header = dir.path().join("header.csv");
    std::fs::write(&header, "q1,q2,q3,q4,q5,q6,q7,tool\n").unwrap();
    for (file, expected) in [
        (&text, "2: not a list of numbers"),
        (&header, "no line of numbers (only a header line)"),
    ] {
        let out = Command::new(harness::ctl_bin())
            .arg("--admin-socket")
            .arg(dir.path().join("no-daemon.sock"))
            .args(["enroll", "x"])
            .arg(file)
            .output()
            .expect("run guardianctl");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(err.contains(expected), "{}: {err}", file.display());
    }
}
