//! Process faults across real processes: planner processes SIGKILLed with requests in flight
//! while other planners keep checking, and `guardiand` SIGKILLed while planners wait, then
//! restarted on the same service with the planners' `Client` objects kept as they were.

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use guardian_client::{CheckError, Client, ClientConfig, Decision, NoGoReason, Trajectory};
use guardian_tests::harness::{Daemon, PATIENCE, Setup, traj};
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;

/// Environment variable selecting the planner-child role of this test executable.
const CHILD_ENV: &str = "GUARDIAN_FAULTS_CHILD";

fn enroll(client: &Client, classes: &[u32]) {
    for &c in classes {
        let ex: Vec<Trajectory> = (0..4).map(|d| traj(c, d)).collect();
        client.enroll(&format!("task{c}"), &ex).expect("enroll");
    }
}

/// The iceoryx2 config of a test deployment (for looking at its nodes).
fn iox_config(s: &Setup) -> iceoryx2::config::Config {
    let mut ic = iceoryx2::config::Config::default();
    let root = format!("{}/", s.dir.path().join("iox").display());
    ic.global
        .set_root_path(&iceoryx2::prelude::Path::new(root.as_bytes()).unwrap());
    ic.global.prefix = FileName::new(s.prefix.as_bytes()).unwrap();
    ic
}

/// (alive, dead) node ids of a deployment, with the pid that created each dead one.
fn nodes(s: &Setup) -> (usize, Vec<(u128, u32)>) {
    let mut alive = 0;
    let mut dead = Vec::new();
    Node::<ipc::Service>::list(&iox_config(s), |state| {
        match &state {
            NodeState::Alive(_) => alive += 1,
            NodeState::Dead(v) => {
                let id = v.id();
                let pid = id.pid::<ipc::Service>().map_or(0, |p| p.value() as u32);
                dead.push((id.value(), pid));
            }
            _ => {}
        }
        CallbackProgression::Continue
    })
    .expect("list nodes");
    (alive, dead)
}

/// Shared-memory objects of a deployment (`/dev/shm/<prefix>…`).
fn shm_files(s: &Setup) -> BTreeSet<String> {
    std::fs::read_dir("/dev/shm")
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with(&s.prefix))
                .collect()
        })
        .unwrap_or_default()
}

/// The planner child: check back to back forever, announcing the first answer on stdout.
/// Not a test of its own: it does nothing unless started by a test below.
#[test]
fn planner_child_role() {
    let Ok(spec) = std::env::var(CHILD_ENV) else {
        return;
    };
    let mut parts = spec.splitn(3, '|');
    let (service, root, prefix) = (
        parts.next().unwrap().to_owned(),
        parts.next().unwrap().into(),
        parts.next().unwrap().to_owned(),
    );
    let client = Client::connect(ClientConfig {
        service_name: service,
        timeout: Duration::from_secs(30),
        iceoryx2_root_path: Some(root),
        iceoryx2_prefix: Some(prefix),
    })
    .expect("child connect");
    for i in 0u64.. {
        let c = (i % 2) as u32;
        let v = client
            .check(&traj(c, 30 + (i % 10) as u32), &format!("task{c}"))
            .expect("child check");
        assert_eq!(v.decision, Decision::Go);
        if i == 0 {
            println!("child-ready");
        }
    }
}

fn spawn_child(s: &Setup) -> std::process::Child {
    let spec = format!(
        "{}|{}|{}",
        s.service,
        s.dir.path().join("iox").display(),
        s.prefix
    );
    let mut child = Command::new(std::env::current_exe().expect("current exe"))
        .args([
            "planner_child_role",
            "--exact",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_ENV, spec)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn planner child");
    let out = child.stdout.take().expect("stdout");
    let mut lines = BufReader::new(out).lines();
    loop {
        match lines.next() {
            Some(Ok(l)) if l.contains("child-ready") => break,
            Some(Ok(_)) => {}
            _ => panic!("planner child ended before its first answer"),
        }
    }
    // Keep draining so the child never blocks on a full pipe.
    std::thread::spawn(move || for _ in lines {});
    child
}

/// Planner processes are SIGKILLed while they have requests in flight, four at a time, in
/// five rounds: 20 dead clients against a daemon admitting 8 client ports. The surviving
/// planners get every answer right throughout, and afterwards all 8 slots can be taken
/// again, so nothing of the dead clients stays behind in the daemon.
#[test]
fn killed_planners_do_not_disturb_the_others_or_leak_client_slots() {
    const MAX_CLIENTS: usize = 8;
    let mut s = Setup::new(50);
    s.extra = format!("default-threshold = 1e9\nmax-clients = {MAX_CLIENTS}");
    let d = Daemon::start(&s);
    enroll(&s.client(), &[0, 1]);

    let stop = Arc::new(AtomicBool::new(false));
    let answered = Arc::new(AtomicUsize::new(0));
    let survivors: Vec<_> = (0..2u32)
        .map(|t| {
            let (stop, answered, config) = (stop.clone(), answered.clone(), s.client_config());
            std::thread::spawn(move || {
                let client = Client::connect(config).expect("connect");
                let mut errors = Vec::new();
                let mut i = 0u32;
                while !stop.load(Ordering::SeqCst) {
                    // Own class: go; the other class: wrong task.
                    let claim = (t + i) % 2;
                    match client.check(&traj(t, 40 + i % 10), &format!("task{claim}")) {
                        Ok(v) if claim == t => assert_eq!(v.decision, Decision::Go),
                        Ok(v) => assert_eq!(
                            v.decision,
                            Decision::NoGo {
                                reason: NoGoReason::WrongTask {
                                    nearest: format!("task{t}")
                                }
                            }
                        ),
                        Err(e) => errors.push(e),
                    }
                    answered.fetch_add(1, Ordering::SeqCst);
                    i += 1;
                }
                errors
            })
        })
        .collect();

    for round in 0..5 {
        let mut children: Vec<_> = (0..4).map(|_| spawn_child(&s)).collect();
        // Let them run back to back for a moment, then kill them mid-request.
        std::thread::sleep(Duration::from_millis(50 + 30 * round));
        for c in &mut children {
            c.kill().expect("SIGKILL planner child");
        }
        for c in &mut children {
            let status = c.wait().expect("wait child");
            assert_eq!(
                std::os::unix::process::ExitStatusExt::signal(&status),
                Some(9),
                "child exited on its own: {status:?}"
            );
        }
    }
    let before = answered.load(Ordering::SeqCst);
    // The survivors keep being answered after the last kill.
    let start = Instant::now();
    while answered.load(Ordering::SeqCst) < before + 20 {
        assert!(
            start.elapsed() < PATIENCE,
            "survivors stopped getting answers"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    stop.store(true, Ordering::SeqCst);
    for t in survivors {
        let errors = t.join().expect("survivor thread");
        assert!(errors.is_empty(), "survivor errors: {errors:?}");
    }

    // Every client slot can be taken again: the dead planners' ports were reclaimed.
    let clients: Vec<Client> = (0..MAX_CLIENTS)
        .map(|i| {
            Client::connect(s.client_config())
                .unwrap_or_else(|e| panic!("client {i} of {MAX_CLIENTS}: {e}"))
        })
        .collect();
    for (i, c) in clients.iter().enumerate() {
        let v = c.check(&traj(1, 50 + i as u32), "task1").expect("check");
        assert_eq!(v.decision, Decision::Go);
    }
    let (_, dead) = nodes(&s);
    assert!(dead.is_empty(), "dead planner nodes left: {dead:?}");
    let st = clients[0].status().expect("status");
    assert_eq!(st.errors, 0);
    assert!(!d.log().contains("panicked"), "{}", d.log());
}

/// `guardiand` is SIGKILLed while four planner threads have requests in flight: each call
/// comes back with a typed error (timeout, or not serving) within its configured bound,
/// never a verdict. The dead daemon's node and shared memory stay behind until the
/// daemon is restarted on the same service; the restart removes them, and the very same
/// `Client` objects are answered correctly again without reconnecting.
#[test]
fn a_killed_daemon_times_out_clients_and_they_recover_after_a_restart() {
    const THREADS: u32 = 4;
    const TIMEOUT: Duration = Duration::from_millis(750);
    // Up: answers are expected. Dead: the daemon is gone, every call must fail.
    const UP: u8 = 0;
    const DEAD: u8 = 1;
    const RESTARTED: u8 = 2;
    let mut s = Setup::new(51);
    s.extra = "default-threshold = 1e9".into();
    let mut d = Daemon::start(&s);
    enroll(&s.client(), &[0, 1, 2, 3]);

    let phase = Arc::new(AtomicU8::new(UP));
    let stop = Arc::new(AtomicBool::new(false));
    // Per thread: successes in each phase, errors (with how long the call took).
    type Log = (Vec<usize>, Vec<(CheckError, Duration, u8)>);
    let logs: Vec<Arc<Mutex<Log>>> = (0..THREADS)
        .map(|_| Arc::new(Mutex::new((vec![0; 3], Vec::new()))))
        .collect();
    let threads: Vec<_> = (0..THREADS)
        .map(|t| {
            let (phase, stop, log) = (phase.clone(), stop.clone(), logs[t as usize].clone());
            let mut config = s.client_config();
            config.timeout = TIMEOUT;
            std::thread::spawn(move || {
                // One client for the whole test: never recreated.
                let client = Client::connect(config).expect("connect");
                let mut i = 0u32;
                while !stop.load(Ordering::SeqCst) {
                    let p0 = phase.load(Ordering::SeqCst);
                    let start = Instant::now();
                    let r = client.check(&traj(t, 60 + i % 10), &format!("task{t}"));
                    let took = start.elapsed();
                    let p1 = phase.load(Ordering::SeqCst);
                    let mut log = log.lock().unwrap();
                    match r {
                        Ok(v) => {
                            assert_eq!(v.decision, Decision::Go, "thread {t}");
                            assert!(
                                !(p0 == DEAD && p1 == DEAD),
                                "a verdict while the daemon was dead"
                            );
                            log.0[p1 as usize] += 1;
                        }
                        Err(e) => log.1.push((e, took, p1)),
                    }
                    i += 1;
                }
            })
        })
        .collect();
    let wait_for = |what: &str, ok: &dyn Fn() -> bool| {
        let start = Instant::now();
        while !ok() {
            assert!(start.elapsed() < PATIENCE, "timed out waiting for {what}");
            std::thread::sleep(Duration::from_millis(10));
        }
    };
    wait_for("answers before the kill", &|| {
        logs.iter().all(|l| l.lock().unwrap().0[UP as usize] >= 10)
    });
    let shm_before = shm_files(&s);
    let daemon_pid = d.pid();
    d.signal("KILL");
    d.wait_exit();
    phase.store(DEAD, Ordering::SeqCst);
    wait_for("two failed calls per client", &|| {
        logs.iter().all(|l| {
            let l = l.lock().unwrap();
            l.1.iter().filter(|e| e.2 == DEAD).count() >= 2
        })
    });

    // The dead daemon's nodes (the serving loop's and the admin socket's waker) and shared
    // memory are still there.
    let (_, dead) = nodes(&s);
    let mut pids: Vec<_> = dead.iter().map(|d| d.1).collect();
    pids.dedup();
    assert_eq!(pids, [daemon_pid], "dead nodes {dead:?}");
    // Its shared-memory objects (server data segment, connections) outlive it.
    let shm_dead = shm_files(&s);
    assert!(
        shm_before.is_subset(&shm_dead),
        "objects vanished without a cleanup: {:?}",
        shm_before.difference(&shm_dead).collect::<Vec<_>>()
    );

    // Restart on the same service; the clients are left alone.
    // The phase changes before the new daemon starts: it may answer a call that began while
    // no daemon ran, and that answer is a recovery, not a verdict from a dead daemon.
    phase.store(RESTARTED, Ordering::SeqCst);
    let d = Daemon::start(&s);
    wait_for("answers after the restart", &|| {
        logs.iter()
            .all(|l| l.lock().unwrap().0[RESTARTED as usize] >= 10)
    });
    // Same clients, a new daemon: as many objects as before the kill, and the dead
    // daemon's ones are gone (the new daemon's carry new ids).
    let shm_after = shm_files(&s);
    stop.store(true, Ordering::SeqCst);
    for t in threads {
        t.join().expect("client thread");
    }
    let (_, dead) = nodes(&s);
    assert!(dead.is_empty(), "dead nodes after the restart: {dead:?}");
    let removed: Vec<_> = shm_dead.difference(&shm_after).collect();
    assert!(
        !removed.is_empty(),
        "nothing of the dead daemon was removed"
    );
    // Port data segments and connections: the same clients and one server again, so as
    // many as before the kill (event objects are left out: which side creates the shared
    // response event's listener objects depends on timing).
    let ports = |set: &std::collections::BTreeSet<String>| {
        set.iter()
            .filter(|n| n.ends_with(".data") || n.ends_with(".connection"))
            .count()
    };
    assert_eq!(
        ports(&shm_after),
        ports(&shm_before),
        "before {shm_before:?}\nafter {shm_after:?}"
    );

    for (t, log) in logs.iter().enumerate() {
        let log = log.lock().unwrap();
        for (e, took, _) in &log.1 {
            assert!(
                matches!(
                    e,
                    CheckError::Timeout { .. } | CheckError::NotServing { .. }
                ),
                "thread {t}: {e:?}"
            );
            // Functional bound: the configured timeout plus generous scheduling slack.
            assert!(
                *took <= TIMEOUT + Duration::from_secs(10),
                "thread {t}: {took:?}"
            );
        }
    }
    drop(d);
}
