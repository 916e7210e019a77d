//! Bad input across real processes: a planner that bypasses the client library (as a C
//! planner would) sends thousands of random and adversarial raw requests over iceoryx2 to a
//! real `guardiand`. Every one is answered (no hang, no crash), an error status never carries
//! a verdict, and `Go` is only ever answered to a well-formed check of an enrolled class;
//! a genuine check still passes afterwards. Hostile class names are rejected with a typed
//! error by the client library and by the daemon.

use std::cell::RefCell;
use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use guardian_client::{CheckError, EnrollError};
use guardian_robot::kinematics::{PANDA_JOINTS, Robot};
use guardian_shared::trajectory::{MAX_WAYPOINTS, from_flat, to_flat};

/// The daemon under test serves the Panda: 7 joints and the tool.
const CHANNELS: usize = PANDA_JOINTS + 1;
use guardian_shared::wire::strategy;
use guardian_shared::wire::{
    self, ClassEntry, ClassNameError, MAX_EXAMPLES, MAX_REQUEST_FLOATS, NAME_BYTES, Op, ReasonCode,
    RequestHeader, ResponseHeader, Status, VerdictCode, decode_class_name, decode_code,
};
use guardian_tests::harness::{Daemon, PATIENCE, RawPlanner, RawPort, Setup, task, traj};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};

/// Random raw requests sent to the daemon (each is one round trip to the real process).
const RANDOM_REQUESTS: u32 = 3_000;

/// A raw planner with one client port (the port drops before the planner's node).
struct Raw {
    port: RawPort,
    planner: RawPlanner,
}

impl Raw {
    fn connect(s: &Setup) -> Self {
        let planner = s.raw_planner();
        Self {
            port: planner.client_port(),
            planner,
        }
    }

    /// Send one request and wait for its response (a hang fails the test).
    fn call(&self, h: &RequestHeader, payload: &[f32]) -> (ResponseHeader, Vec<ClassEntry>) {
        let mut r = self.port.loan_slice_uninit(payload.len()).expect("loan");
        *r.user_header_mut() = *h;
        let pending = r.write_from_slice(payload).send().expect("send");
        self.planner.wake.notify().expect("notify");
        let start = Instant::now();
        loop {
            if let Some(resp) = pending.receive().expect("receive") {
                return (*resp.user_header(), resp.payload().to_vec());
            }
            if !pending.is_connected() {
                // The daemon answers and then drops the request: the answer can arrive
                // between the receive above and this check, so look once more.
                let resp = pending.receive().expect("receive");
                let resp = resp.unwrap_or_else(|| panic!("guardiand dropped the request: {h:?}"));
                return (*resp.user_header(), resp.payload().to_vec());
            }
            assert!(start.elapsed() < PATIENCE, "no response to {h:?}");
            std::thread::sleep(Duration::from_micros(200));
        }
    }
}

fn flat(class: u32, drawer: u32) -> Vec<f32> {
    to_flat(&task(class, drawer), PANDA_JOINTS)
}

fn header(id: u64, op: Op, class: &[u8], waypoints: &[u32]) -> RequestHeader {
    let mut h = RequestHeader::new(id, op);
    h.channels = CHANNELS as u32;
    h.examples = waypoints.len() as u32;
    h.waypoints[..waypoints.len()].copy_from_slice(waypoints);
    h.class_name[..class.len()].copy_from_slice(class);
    h
}

/// Whether `h` is a well-formed check of a class in `enrolled` with a valid trajectory.
fn genuine_check(enrolled: &BTreeSet<String>, h: &RequestHeader, payload: &[f32]) -> bool {
    h.op == Op::Check as u32
        && h.channels == CHANNELS as u32
        && h.examples == 1
        && u64::from(h.waypoints[0]) * CHANNELS as u64 == payload.len() as u64
        && decode_class_name(&h.class_name).is_ok_and(|n| enrolled.contains(n))
        && from_flat(payload, CHANNELS, Robot::panda().limits()).is_ok()
}

/// The invariants of every answer; keeps `enrolled` up to date.
fn judge(
    enrolled: &mut BTreeSet<String>,
    h: &RequestHeader,
    payload: &[f32],
    r: &ResponseHeader,
) -> Result<(), TestCaseError> {
    let genuine = genuine_check(enrolled, h, payload);
    prop_assert_eq!(r.request_id, h.request_id);
    prop_assert_eq!(r.op, h.op);
    prop_assert!(decode_code::<Status>(r.status).is_some(), "{r:?}");
    if r.status != Status::Ok as u32 || h.op != Op::Check as u32 {
        prop_assert_eq!(r.verdict, VerdictCode::None as u32, "{:?}", h);
    }
    if r.verdict == VerdictCode::Go as u32 {
        prop_assert!(genuine, "Go for {h:?}");
    }
    if genuine {
        prop_assert_ne!(r.verdict, VerdictCode::None as u32);
    }
    if r.status == Status::Ok as u32 {
        let name = decode_class_name(&h.class_name).map(str::to_owned);
        if h.op == Op::Enroll as u32 {
            enrolled.insert(name.expect("enrolled under an invalid name"));
        } else if h.op == Op::Forget as u32 {
            enrolled.remove(&name.expect("forgot an invalid name"));
        }
    }
    Ok(())
}

/// Hostile and half-valid requests (`guardian_shared::wire::strategy`): genuine plans of two
/// enrolled tasks (often mutated at one value), random floats or empty payloads.
fn request() -> impl Strategy<Value = (RequestHeader, Vec<f32>)> {
    let genuine = (0u32..2, 0u32..40).prop_map(|(c, d)| flat(c, d));
    strategy::request(
        CHANNELS as u32,
        strategy::name_field(vec!["task0", "task1", "fuzzed"]),
        any::<u32>(),
        strategy::payload(genuine, 200),
    )
}

#[test]
fn thousands_of_random_and_adversarial_raw_requests_never_get_a_go() {
    let mut s = Setup::new(60);
    s.extra = "default-threshold = 1e9".into();
    let d = Daemon::start(&s);
    let client = s.client();
    for c in 0..2u32 {
        let ex: Vec<_> = (0..4).map(|dr| traj(c, dr)).collect();
        client.enroll(&format!("task{c}"), &ex).expect("enroll");
    }
    let raw = Raw::connect(&s);
    let enrolled = RefCell::new(BTreeSet::from(["task0".to_string(), "task1".to_string()]));
    let ask = |h: &RequestHeader, p: &[f32]| -> ResponseHeader {
        let (r, _) = raw.call(h, p);
        judge(&mut enrolled.borrow_mut(), h, p, &r).unwrap_or_else(|e| panic!("{e}"));
        r
    };

    // Adversarial sizes: totals that overflow 64 bits (2 x (2^32 - 1) + 2 waypoints of 2^31
    // channels wrap to exactly 0 floats), more waypoints than allowed, a payload longer
    // than the largest legal request.
    let good = flat(0, 20);
    let n = (good.len() / 8) as u32;
    for op in [Op::Enroll, Op::Check, Op::Identify] {
        let mut h = header(1, op, b"task0", &[u32::MAX, u32::MAX, 2]);
        h.channels = 1 << 31;
        assert_eq!(ask(&h, &[]).status, Status::BadRequest as u32);
        h.channels = u32::MAX;
        h.waypoints[..3].copy_from_slice(&[u32::MAX; 3]);
        assert_ne!(ask(&h, &good).status, Status::Ok as u32);
        let mut h = header(2, op, b"task0", &[u32::MAX]);
        h.channels = u32::MAX;
        assert_ne!(ask(&h, &good).verdict, VerdictCode::Go as u32);
    }
    let many: Vec<f32> = good
        .iter()
        .copied()
        .cycle()
        .take((MAX_WAYPOINTS + 1) * CHANNELS)
        .collect();
    let r = ask(
        &header(3, Op::Check, b"task0", &[MAX_WAYPOINTS as u32 + 1]),
        &many,
    );
    assert_eq!(
        (r.verdict, r.reason, r.invalid_index),
        (
            VerdictCode::NoGo as u32,
            ReasonCode::InvalidTrajectory as u32,
            MAX_WAYPOINTS as u32 + 1
        )
    );
    let r = ask(
        &header(4, Op::Identify, b"", &[MAX_WAYPOINTS as u32 + 1]),
        &many,
    );
    assert_eq!(r.status, Status::InvalidTrajectory as u32);
    let huge = vec![0.0f32; MAX_REQUEST_FLOATS + 8];
    let w = [(MAX_WAYPOINTS + 1) as u32; MAX_EXAMPLES];
    let r = ask(&header(5, Op::Enroll, b"task0", &w), &huge);
    assert_eq!(r.status, Status::BadRequest as u32);
    let r = ask(&header(6, Op::Check, b"task0", &[n]), &huge);
    assert_eq!(r.status, Status::BadRequest as u32);

    // Hostile names on the wire: not UTF-8, control characters, empty, an embedded NUL,
    // all 64 bytes used; on enroll, check and forget.
    let hostile: [&[u8]; 7] = [
        b"\xff\xfe",
        b"\xc3",
        b"a\x1bb",
        b"\x7f",
        b"",
        b"ab\0cd",
        &[b'x'; NAME_BYTES],
    ];
    for (i, name) in hostile.iter().enumerate() {
        for op in [Op::Enroll, Op::Check, Op::Forget] {
            let w: &[u32] = if op == Op::Forget { &[] } else { &[n] };
            let p: &[f32] = if op == Op::Forget { &[] } else { &good };
            let r = ask(&header(10 + i as u64, op, name, w), p);
            assert_eq!(r.status, Status::InvalidClassName as u32, "{name:?} {op:?}");
        }
    }

    // Thousands of random requests; failures shrink to a minimal request.
    let mut runner = TestRunner::new(Config {
        cases: RANDOM_REQUESTS,
        failure_persistence: None,
        ..Config::default()
    });
    runner
        .run(&request(), |(h, p)| {
            let (r, _) = raw.call(&h, &p);
            judge(&mut enrolled.borrow_mut(), &h, &p, &r)
        })
        .unwrap();

    // Still serving, and a genuine check still gets its go. Random enrolls may have put
    // drawings of character 1 under any name (task0 included), and a nearer other class is a
    // no-go: forget every class and enroll task1 afresh.
    for c in client.classes().expect("classes") {
        client.forget(&c.name).expect("forget");
    }
    let ex: Vec<_> = (0..4).map(|dr| traj(1, dr)).collect();
    client.enroll("task1", &ex).expect("enroll");
    let v = client.check(&traj(1, 33), "task1").expect("check");
    assert!(v.is_go(), "{v:?}");
    let st = client.status().expect("status");
    assert!(st.requests >= u64::from(RANDOM_REQUESTS));
    assert!(!d.log().contains("panicked"), "{}", d.log());
}

/// Through the client library hostile names never reach the daemon: a typed error.
/// A raw planner's hostile name comes back from the daemon as the same typed error.
#[test]
fn hostile_class_names_are_rejected_with_a_typed_error() {
    let mut s = Setup::new(61);
    s.extra = "default-threshold = 1e9".into();
    let _d = Daemon::start(&s);
    let client = s.client();
    let t = traj(0, 1);
    let names = [
        "x".repeat(1 << 20),
        "é".repeat(32),
        String::new(),
        "a\0b".into(),
        "tab\there".into(),
        "\u{1b}[31mred".into(),
        "\u{85}".into(),
    ];
    for name in &names {
        let check = client.check(&t, name);
        assert!(
            matches!(check, Err(CheckError::InvalidClassName(_))),
            "{check:?}"
        );
        let enroll = client.enroll(name, std::slice::from_ref(&t));
        assert!(
            matches!(
                enroll,
                Err(EnrollError::Request(CheckError::InvalidClassName(_)))
            ),
            "{enroll:?}"
        );
        assert!(matches!(
            client.forget(name),
            Err(CheckError::InvalidClassName(_))
        ));
    }
    assert!(matches!(
        client.check(&t, &"x".repeat(64)),
        Err(CheckError::InvalidClassName(ClassNameError::TooLong {
            len: 64,
            max: 63
        }))
    ));
    // Nothing was enrolled.
    assert!(client.classes().expect("classes").is_empty());

    // The daemon's answer to a raw hostile name carries the typed reason.
    let raw = Raw::connect(&s);
    let good = flat(0, 2);
    let (r, _) = raw.call(
        &header(1, Op::Enroll, b"\xff\xfe", &[(good.len() / 8) as u32]),
        &good,
    );
    assert_eq!(r.status, Status::InvalidClassName as u32);
    assert_eq!(
        decode_class_name(&r.class_name),
        Err(ClassNameError::NotUtf8)
    );
    assert!(wire::decode_text(&r.message).contains("UTF-8"));
}
