//! A fleet of real `guardiand` processes over Zenoh on loopback (explicit
//! `tcp/127.0.0.1:<port>` endpoints, scouting off; separate state directories and iceoryx2
//! roots): an enroll on one member is served by the others; a member killed while the
//! others change the bank converges when it returns; two members enrolling the same class
//! concurrently end identical; a remote check over Zenoh gets the local verdict, a remote
//! enroll is refused; forged, replayed, truncated and other-robot records are refused,
//! logged, and leave every bank unchanged. Functional deadlines only; the delays are
//! printed (the figures come from `benches/fleet.rs`).

use std::process::Command;
use std::time::{Duration, Instant};

use guardian_client::{CheckError, EnrollError, Trajectory};
use guardian_fleet::SigningKey;
use guardian_fleet::keys::read_signing_key;
use guardian_fleet::record::{Change, Record, Unsigned};
use guardian_shared::wire::{Op, RequestHeader, Status};
use guardian_tests::fleet::{CONVERGE, Fleet, examples, has, keygen};
use guardian_tests::harness::{self, traj};

/// The verdict details every member gives one trajectory: identical banks answer
/// bit-identical distances.
fn answers(f: &Fleet, running: &[usize], t: &Trajectory, class: &str) -> Vec<(bool, u32)> {
    running
        .iter()
        .map(|&i| {
            let v = f.client(i).check(t, class).expect("check");
            (v.is_go(), v.claimed_distance.map_or(0, f32::to_bits))
        })
        .collect()
}

#[test]
fn three_members_replicate_catch_up_and_converge() {
    let began = Instant::now();
    let phase = |what: &str| eprintln!("[{:>6.2} s] {what}", began.elapsed().as_secs_f64());
    let mut f = Fleet::new(3);
    phase("keys made");
    for i in 0..3 {
        f.start(i);
    }
    phase("3 members started");
    let all = [0, 1, 2];
    // Warm-up: the first enroll also waits for the Zenoh links to come up.
    f.admin(0)
        .enroll("warmup", &examples(5, 0..3))
        .expect("enroll");
    f.converge(&all, |c| has(c, "warmup", 3));
    phase("warm-up replicated");

    // An enroll on A is served by B and C: the delay until each answers it, per round,
    // from the admin request and from its acknowledgment (the record is published before).
    let mut delays = Vec::new();
    let mut after_ack = Vec::new();
    let (admin, clients) = (f.admin(0), [f.client(1), f.client(2)]);
    for round in 0..5u32 {
        let class = format!("task{round}");
        let t0 = Instant::now();
        admin
            .enroll(&class, &examples(round % 3, 0..3))
            .expect("enroll");
        let ack = t0.elapsed();
        for (i, c) in clients.iter().enumerate() {
            while !c
                .classes()
                .expect("classes")
                .iter()
                .any(|x| x.name == class)
            {
                assert!(
                    t0.elapsed() < CONVERGE,
                    "member {} never served {class}",
                    i + 1
                );
                std::thread::sleep(Duration::from_micros(200));
            }
            delays.push(t0.elapsed());
            after_ack.push(t0.elapsed().saturating_sub(ack));
        }
    }
    delays.sort();
    after_ack.sort();
    eprintln!(
        "replication delay (enroll on A -> served by B/C), {} samples: from the request median {:?} max {:?}; from A's acknowledgment median {:?} max {:?}",
        delays.len(),
        delays[delays.len() / 2],
        delays[delays.len() - 1],
        after_ack[after_ack.len() / 2],
        after_ack[after_ack.len() - 1]
    );
    // B and C answer a check exactly as A does.
    let probe = traj(1, 9);
    let a = answers(&f, &all, &probe, "task1");
    assert!(a.windows(2).all(|w| w[0] == w[1]), "{a:?}");

    phase("5 rounds replicated");
    // C is killed; A and B change the bank meanwhile; C restarts and converges.
    let c = f.members[2].daemon.as_mut().expect("running");
    let _ = c.child.kill();
    let _ = c.child.wait();
    f.members[2].daemon = None;
    f.admin(0)
        .enroll("while-c-down", &examples(2, 0..2))
        .expect("enroll");
    f.admin(1).forget("warmup").expect("forget");
    f.admin(1)
        .enroll("task0", &examples(0, 3..5))
        .expect("enroll");
    let ab = f.converge(&[0, 1], |c| {
        has(c, "while-c-down", 2) && !c.iter().any(|x| x.name == "warmup") && has(c, "task0", 5)
    });
    phase("A and B changed the bank while C was down");
    f.start(2);
    phase("C restarted");
    let abc = f.converge(&all, |c| c == ab.as_slice());
    phase("C caught up");
    assert_eq!(abc, ab);
    assert!(
        f.log(2).contains("fleet change applied"),
        "C caught up through its peers:\n{}",
        f.log(2)
    );

    // Two members enroll the same new class concurrently, with different examples: every
    // member ends with one and the same class.
    let (a0, a1) = (f.admin(0), f.admin(1));
    let t = std::thread::spawn(move || a0.enroll("contested", &examples(0, 0..3)));
    let r1 = a1.enroll("contested", &examples(2, 0..4));
    t.join().expect("thread").expect("enroll on A");
    r1.expect("enroll on B");
    let last = f.converge(&all, |c| c.iter().any(|x| x.name == "contested"));
    let contested = last.iter().find(|x| x.name == "contested").expect("class");
    assert!(
        contested.examples == 3 || contested.examples == 4,
        "{contested:?}"
    );
    phase("concurrent enrolls converged");
    // Identical banks: the same distances everywhere, and the same fleet position.
    let probe = traj(2, 9);
    let a = answers(&f, &all, &probe, "contested");
    assert!(a.windows(2).all(|w| w[0] == w[1]), "{a:?}");
    let start = Instant::now();
    loop {
        let positions: Vec<_> = all
            .iter()
            .map(|&i| f.client(i).status().expect("status").fleet)
            .collect();
        if positions.windows(2).all(|w| w[0] == w[1]) && positions[0].len() >= 2 {
            eprintln!("fleet position on every member: {:?}", positions[0]);
            break;
        }
        assert!(start.elapsed() < CONVERGE, "{positions:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
    phase("fleet positions equal");
    // guardianctl status prints it.
    let out = Command::new(harness::ctl_bin())
        .args(["--service", &f.members[0].setup.service])
        .arg("--iceoryx2-root-path")
        .arg(f.members[0].setup.dir.path().join("iox"))
        .args(["--iceoryx2-prefix", &f.members[0].setup.prefix, "status"])
        .output()
        .expect("guardianctl");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("fleet"),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    phase("guardianctl status shows the fleet position");
    drop(f);
    phase("members stopped");
}

/// `replicas = 2`: an enroll or forget on A is answered once B and C hold it, so each
/// serves the change the moment A's admin hears "done"; with C down the answer is
/// `Unreplicated` after `replica-timeout-ms`, saying how many peers hold it, and the change
/// is in effect on A and B; C gets it when it comes back.
#[test]
fn with_replicas_an_answered_change_is_held_by_the_peers() {
    let mut f = Fleet::new(3);
    for m in &mut f.members {
        m.setup
            .extra
            .push_str("replicas = 2\nreplica-timeout-ms = 1500\n");
    }
    for i in 0..3 {
        f.start(i);
    }
    // Until the Zenoh links are up an enroll may be answered Unreplicated.
    let start = Instant::now();
    let mut unreplicated = 0;
    loop {
        match f.admin(0).enroll("warmup", &examples(5, 0..3)) {
            Ok(_) => break,
            Err(EnrollError::Request(CheckError::Unreplicated { .. }))
                if start.elapsed() < CONVERGE =>
            {
                unreplicated += 1
            }
            Err(e) => panic!("warm-up enroll: {e}"),
        }
    }
    eprintln!("warm-up: {unreplicated} enrolls answered Unreplicated before the links were up");
    let serves = |f: &Fleet, i: usize, class: &str| {
        f.client(i)
            .classes()
            .expect("classes")
            .iter()
            .any(|c| c.name == class)
    };
    let admin = f.admin(0);
    let mut waited = Vec::new();
    for round in 0..5u32 {
        let class = format!("held{round}");
        let t0 = Instant::now();
        admin
            .enroll(&class, &examples(round % 3, 0..3))
            .expect("enroll");
        waited.push(t0.elapsed());
        for i in [1, 2] {
            assert!(
                serves(&f, i, &class),
                "member {i} does not serve {class} when A answers its enroll"
            );
        }
    }
    admin.forget("held0").expect("forget");
    for i in [1, 2] {
        assert!(
            !serves(&f, i, "held0"),
            "member {i} still serves a class A forgot"
        );
    }
    waited.sort();
    eprintln!(
        "enroll answered after both peers held it: median {:?}, max {:?}",
        waited[waited.len() / 2],
        waited[waited.len() - 1]
    );

    // C down: the answer says the change is here and on one peer of the two required.
    let c = f.members[2].daemon.as_mut().expect("running");
    let _ = c.child.kill();
    let _ = c.child.wait();
    f.members[2].daemon = None;
    let t0 = Instant::now();
    let e = admin
        .enroll("c-down", &examples(1, 0..3))
        .expect_err("C is down: two peers cannot hold it");
    let after = t0.elapsed();
    match &e {
        EnrollError::Request(CheckError::Unreplicated { message }) => assert!(
            message.contains("held by 1 of the 2 peers required"),
            "{message}"
        ),
        other => panic!("expected Unreplicated, got {other:?}"),
    }
    assert!(
        after >= Duration::from_millis(1500),
        "answered after {after:?}"
    );
    eprintln!("with C down: answered Unreplicated after {after:?}: {e}");
    assert!(serves(&f, 0, "c-down") && serves(&f, 1, "c-down"));
    assert!(
        f.log(0).contains("not acknowledged by enough peers"),
        "{}",
        f.log(0)
    );
    // C comes back and catches up.
    f.start(2);
    f.converge(&[0, 1, 2], |c| c.iter().any(|x| x.name == "c-down"));
}

/// Publish raw bytes on the fleet's record key from an outside session connected to every
/// member (peers do not route for each other: a fleet is a full mesh).
fn inject(f: &Fleet, bytes: Vec<u8>) {
    let endpoints: Vec<String> = f
        .members
        .iter()
        .map(|m| format!("tcp/127.0.0.1:{}", m.port))
        .collect();
    let session = guardian_fleet::node::open_session(&[], &endpoints).expect("session");
    // Let the links come up and the subscriptions propagate, then publish.
    std::thread::sleep(Duration::from_millis(500));
    guardian_fleet::node::put(&session, &format!("guardian/{}/records", f.name), bytes)
        .expect("put");
    std::thread::sleep(Duration::from_millis(200));
}

/// Wait until member `i` logged a refusal with `reason`.
fn wait_refusal(f: &Fleet, i: usize, reason: &str, before: usize) {
    let start = Instant::now();
    loop {
        let n = f
            .log(i)
            .lines()
            .filter(|l| l.contains("fleet record refused") && l.contains(reason))
            .count();
        if n > before {
            return;
        }
        assert!(
            start.elapsed() < CONVERGE,
            "member {i} never refused a {reason:?} record:\n{}",
            f.log(i)
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn refusals(f: &Fleet, i: usize, reason: &str) -> usize {
    f.log(i)
        .lines()
        .filter(|l| l.contains("fleet record refused") && l.contains(reason))
        .count()
}

#[test]
fn remote_checks_and_bad_records() {
    let mut f = Fleet::new(2);
    f.start(0);
    f.start(1);
    let both = [0, 1];
    for c in 0..3u32 {
        f.admin(0)
            .enroll(&format!("task{c}"), &examples(c, 0..3))
            .expect("enroll");
    }
    // task0 again: its first record is superseded (kept in A's store file until compaction).
    f.admin(0)
        .enroll("task0", &examples(0, 3..5))
        .expect("enroll");
    let bank = f.converge(&both, |c| has(c, "task0", 5) && has(c, "task2", 3));

    // A remote check on B gets B's local verdict, for a genuine and a wrong-task plan.
    let remote = f.remote(1, f.caller_key.clone());
    let local = f.client(1);
    for (t, class) in [
        (traj(1, 9), "task1"),
        (traj(2, 9), "task0"),
        (traj(0, 8), "nope"),
    ] {
        let r = remote.check(&t, class).expect("remote check");
        let l = local.check(&t, class).expect("local check");
        assert_eq!(
            (&r.decision, r.claimed_distance, &r.nearest),
            (&l.decision, l.claimed_distance, &l.nearest)
        );
    }
    // B's verdict record has the three remote checks, marked as remote (the same as its
    // three local ones otherwise), the wrong-task one with its plan kept.
    let record = f.members[1].setup.state_dir().join("verdicts.sqlite");
    let started = Instant::now();
    let remote_rows = loop {
        let out = Command::new(harness::ctl_bin())
            .args(["--json", "verdicts", "--record"])
            .arg(&record)
            .output()
            .expect("run guardianctl verdicts");
        let rows: Vec<serde_json::Value> = if out.status.success() {
            serde_json::from_slice(&out.stdout).expect("JSON rows")
        } else {
            Vec::new()
        };
        let remote: Vec<serde_json::Value> = rows
            .into_iter()
            .filter(|r| {
                r["client"]
                    .as_str()
                    .is_some_and(|c| c.starts_with("remote:"))
            })
            .collect();
        if remote.len() >= 3 || started.elapsed() > Duration::from_secs(20) {
            break remote;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut claimed: Vec<&str> = remote_rows
        .iter()
        .map(|r| r["claimed"].as_str().unwrap_or(""))
        .collect();
    claimed.sort_unstable();
    assert_eq!(claimed, ["nope", "task0", "task1"], "{remote_rows:?}");
    let wrong = remote_rows
        .iter()
        .find(|r| r["claimed"] == "task0")
        .expect("the wrong-task check");
    assert_eq!(wrong["verdict"], "no-go", "{wrong}");
    assert_eq!(wrong["plan_kept"], true, "{wrong}");
    let ranking = remote.identify(&traj(2, 7)).expect("identify");
    assert_eq!(
        ranking.nearest,
        local.identify(&traj(2, 7)).expect("identify").nearest
    );
    let status = remote.status().expect("status");
    assert_eq!(status.classes, bank.len() as u32);
    assert!(!status.fleet.is_empty(), "{status:?}");
    // Loopback round trips, beside the local ones (figures: benches/fleet.rs).
    let time = |f: &dyn Fn()| {
        let mut v: Vec<Duration> = (0..20)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed()
            })
            .collect();
        v.sort();
        v[v.len() / 2]
    };
    let probe = traj(1, 9);
    let zenoh = time(&|| {
        remote.check(&probe, "task1").expect("check");
    });
    let iox = time(&|| {
        local.check(&probe, "task1").expect("check");
    });
    eprintln!("check round trip median: zenoh {zenoh:?}, iceoryx2 {iox:?}");

    // A remote caller never enrolls or forgets.
    let (h, payload) = {
        let t = traj(0, 1);
        let h = RequestHeader::encode(Op::Enroll, Some("intruder"), t.channels(), &[t.len()])
            .expect("header");
        (h, t.as_flat().to_vec())
    };
    let (r, _) = remote.raw(h, &payload).expect("answered");
    assert_eq!(r.status, Status::NotPermitted as u32);
    let h = RequestHeader::encode(Op::Forget, Some("task0"), 0, &[]).expect("header");
    let (r, _) = remote.raw(h, &[]).expect("answered");
    assert_eq!(r.status, Status::NotPermitted as u32);
    // A caller whose key is not configured is refused.
    let stranger = f.keys.path().join("stranger.key");
    keygen(&stranger);
    match f.remote(1, stranger).check(&probe, "task1") {
        Err(CheckError::NotPermitted { message }) => {
            assert!(message.contains("not a configured caller"), "{message}")
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    assert_eq!(f.banks(&both), vec![bank.clone(), bank.clone()]);

    let version = |i: usize| f.client(i).status().expect("status").bank_version;
    let versions = [version(0), version(1)];
    let a_key = read_signing_key(&f.members[0].key).expect("key");
    let robot = {
        let s = f.client(0).status().expect("status").robot;
        format!("{}/{}/{}", s.name, s.joints, s.urdf_sha256)
    };
    let model = f.client(0).status().expect("status").model_version;
    let record = |key: &SigningKey, class: &str, robot: &str, lamport: u64| {
        Record::sign(
            Unsigned {
                fleet: f.name.clone(),
                robot: robot.to_owned(),
                model: model.clone(),
                class: class.to_owned(),
                change: Change::Forget,
                lamport,
            },
            key,
        )
    };

    // Signed by a key no member trusts.
    let stranger = SigningKey::from_bytes(&[42; 32]);
    let before = [
        refusals(&f, 0, "unknown key"),
        refusals(&f, 1, "unknown key"),
    ];
    inject(
        &f,
        record(&stranger, "task1", &robot, 1_000).bytes().to_vec(),
    );
    wait_refusal(&f, 0, "unknown key", before[0]);
    wait_refusal(&f, 1, "unknown key", before[1]);

    // A replayed old record: task0's first enroll, superseded by its second.
    let store = std::fs::read(f.members[0].setup.state_dir().join("fleet.records")).expect("store");
    let first = {
        let body = &store[b"guardian-fleet-records 1\n".len()..];
        let len = u32::from_le_bytes([body[0], body[1], body[2], body[3]]) as usize;
        body[36..36 + len].to_vec()
    };
    assert_eq!(Record::decode(&first).expect("record").class(), "task0");
    let before = [refusals(&f, 0, "stale"), refusals(&f, 1, "stale")];
    inject(&f, first.clone());
    wait_refusal(&f, 0, "stale", before[0]);
    wait_refusal(&f, 1, "stale", before[1]);

    // A replay of the record each member holds for task0 (the store's last frame).
    let last = {
        let mut at = b"guardian-fleet-records 1\n".len();
        let mut last = Vec::new();
        while at < store.len() {
            let len = u32::from_le_bytes([store[at], store[at + 1], store[at + 2], store[at + 3]])
                as usize;
            last = store[at + 36..at + 36 + len].to_vec();
            at += 36 + len;
        }
        last
    };
    assert_eq!(Record::decode(&last).expect("record").class(), "task0");
    let before = [refusals(&f, 0, "duplicate"), refusals(&f, 1, "duplicate")];
    inject(&f, last);
    wait_refusal(&f, 0, "duplicate", before[0]);
    wait_refusal(&f, 1, "duplicate", before[1]);

    // A truncated record.
    let good = record(&a_key, "task2", &robot, 10_000);
    let before = [refusals(&f, 0, "malformed"), refusals(&f, 1, "malformed")];
    inject(&f, good.bytes()[..good.bytes().len() - 10].to_vec());
    wait_refusal(&f, 0, "malformed", before[0]);
    wait_refusal(&f, 1, "malformed", before[1]);

    // A record signed by a trusted key, for another robot.
    let before = [
        refusals(&f, 0, "other robot"),
        refusals(&f, 1, "other robot"),
    ];
    let other = "ur5e/6/0000000000000000000000000000000000000000000000000000000000000000";
    inject(&f, record(&a_key, "task2", other, 10_001).bytes().to_vec());
    wait_refusal(&f, 0, "other robot", before[0]);
    wait_refusal(&f, 1, "other robot", before[1]);

    // Nothing changed anywhere.
    assert_eq!(f.banks(&both), vec![bank.clone(), bank]);
    assert_eq!([version(0), version(1)], versions);
}

/// Member `i` was killed by its armed fault point: wait for its exit (SIGKILL) and drop it.
fn wait_killed(f: &mut Fleet, i: usize, point: &str) {
    let d = f.members[i].daemon.as_mut().expect("running");
    let status = d.wait_exit();
    let log = d.log();
    assert!(
        log.contains("fault point reached") && log.contains(point),
        "member {i} did not stop at {point} ({status}):\n{log}"
    );
    use std::os::unix::process::ExitStatusExt;
    assert_eq!(status.signal(), Some(9), "killed by SIGKILL:\n{log}");
    f.members[i].daemon = None;
}

/// Wait until every member in `running` reports the same fleet position and bank digest.
fn equal_positions(f: &Fleet, running: &[usize]) {
    let start = Instant::now();
    loop {
        let p = f.positions(running);
        if p.windows(2).all(|w| w[0] == w[1]) && p[0].1.is_some() {
            return;
        }
        assert!(start.elapsed() < CONVERGE, "positions differ: {p:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The enrolling member killed (SIGKILL, at a fault point) at every step of the admin path
/// — after its fleet record is appended, after the bank journalled the change, after the
/// record was published — never splits the fleet: after its restart both members serve
/// the change, with the same position and bank digest. The same for a forget. Before the
/// record was made durable ahead of the bank's journal, the kill after the journal left
/// the class on A alone, for good (issue 39).
#[test]
fn a_kill_at_every_step_of_the_admin_path_converges() {
    use guardian_daemon::faults::{AFTER_JOURNAL, ENV, FLEET_AFTER_PUBLISH, FLEET_AFTER_RECORD};
    let mut f = Fleet::new(2);
    f.start(0);
    f.start(1);
    let both = [0, 1];
    f.admin(0)
        .enroll("warmup", &examples(0, 0..2))
        .expect("enroll");
    f.converge(&both, |c| has(c, "warmup", 2));
    for (n, point) in [FLEET_AFTER_RECORD, AFTER_JOURNAL, FLEET_AFTER_PUBLISH]
        .into_iter()
        .enumerate()
    {
        f.stop(0);
        f.start_with_env(0, &[(ENV, point.to_owned())]);
        let class = format!("crash{n}");
        let answer = f.admin(0).enroll(&class, &examples(n as u32 % 3, 0..3));
        assert!(
            answer.is_err(),
            "{point}: a killed member answered {answer:?}"
        );
        wait_killed(&mut f, 0, point);
        f.start(0);
        let bank = f.converge(&both, |c| has(c, &class, 3));
        equal_positions(&f, &both);
        eprintln!(
            "{point}: converged with {} classes; A's start: {}",
            bank.len(),
            f.log(0)
                .lines()
                .filter(|l| l.contains("applied fleet records") || l.contains("incomplete"))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    // A forget, killed after its record: forgotten on both after the restart.
    f.stop(0);
    f.start_with_env(0, &[(ENV, FLEET_AFTER_RECORD.to_owned())]);
    assert!(f.admin(0).forget("warmup").is_err());
    wait_killed(&mut f, 0, FLEET_AFTER_RECORD);
    f.start(0);
    f.converge(&both, |c| {
        !c.iter().any(|x| x.name == "warmup") && c.len() == 3
    });
    equal_positions(&f, &both);
}

/// Two members that hold the same records but serve different banks (B started with a
/// default bank A does not have: a class no record covers, another global threshold) report
/// the same per-signer position but different bank digests; forgetting the extra class
/// leaves the thresholds apart, and the digests stay different.
#[test]
fn members_with_different_banks_report_different_positions() {
    let mut f = Fleet::new(2);
    let extra = f.members[1].setup.dir.path().join("extra-default.gcb");
    harness::random_bank(&f.members[1].setup.model, 1, 2, 5)
        .save(&extra)
        .expect("save bank");
    f.members[1].setup.default_bank = Some(extra);
    f.start(0);
    f.start(1);
    f.admin(0)
        .enroll("shared", &examples(1, 0..3))
        .expect("enroll");
    let start = Instant::now();
    while !has(&f.client(1).classes().expect("classes"), "shared", 3) {
        assert!(start.elapsed() < CONVERGE, "B never served the class");
        std::thread::sleep(Duration::from_millis(20));
    }
    let p = f.positions(&[0, 1]);
    assert_eq!(p[0].0, p[1].0, "same records, same per-signer position");
    assert!(p[0].1.is_some() && p[1].1.is_some(), "{p:?}");
    assert_ne!(p[0].1, p[1].1, "different banks, different digests: {p:?}");
    // B forgets the extra class through its admin path (a record): the same classes, but
    // "shared" is decided with another global threshold on B — still different digests.
    f.admin(1).forget("base0000").expect("forget");
    let start = Instant::now();
    loop {
        let p = f.positions(&[0, 1]);
        let (a, b) = (
            f.client(0).classes().unwrap(),
            f.client(1).classes().unwrap(),
        );
        if p[0].0 == p[1].0 && a.len() == 1 && b.len() == 1 {
            assert_ne!(a[0].threshold, b[0].threshold, "{a:?} {b:?}");
            assert_ne!(
                p[0].1, p[1].1,
                "different thresholds, different digests: {p:?}"
            );
            break;
        }
        assert!(start.elapsed() < CONVERGE, "{p:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}
