//! Property tests of the daemon's request handling in-process: a [`Screen`] with a
//! random-weights model and three enrolled classes answers arbitrary headers and payloads
//! (any op, channel count, example count, waypoint counts, name bytes, float bit patterns),
//! singly and in micro-batches. Nothing panics, every request gets exactly one response
//! echoing its id, an error status never carries a verdict, and `Go` is answered only to a
//! well-formed check of an enrolled class whose distance is within the threshold.

use guardian_bank::ClassBank;
use guardian_client::samples::task;
use guardian_daemon::screen::Screen;
use guardian_models::embedder::Embedder;
use guardian_robot::kinematics::{PANDA_JOINTS, Robot};
use guardian_screen::check::{self, Station};
use guardian_shared::trajectory::{Waypoint, from_flat};
use guardian_shared::wire::strategy;
use guardian_shared::wire::{
    MAX_EXAMPLES, Op, RequestHeader, ResponseHeader, Status, VerdictCode, decode_class_name,
    decode_code, encode_class_name,
};
use proptest::prelude::*;
use std::sync::{Mutex, OnceLock};

/// Cases per property; each may embed a trajectory with the (debug-profile) model.
const CASES: u32 = 5_000;

const ENROLLED: [&str; 3] = ["task0", "task1", "task2"];

/// The screen serves the Panda: 7 joints and the tool.
const CHANNELS: usize = PANDA_JOINTS + 1;

/// One screen for all cases of a test (building it embeds nine trajectories). Requests
/// may enroll and forget classes; the properties hold for whatever the bank holds.
fn with_screen<T>(f: impl FnOnce(&mut Screen) -> T) -> T {
    static SCREEN: OnceLock<Mutex<(tempfile::TempDir, Screen)>> = OnceLock::new();
    let m = SCREEN.get_or_init(|| {
        let dir = tempfile::tempdir().expect("tempdir");
        let s = screen(dir.path());
        Mutex::new((dir, s))
    });
    let mut g = m.lock().unwrap_or_else(|e| e.into_inner());
    f(&mut g.1)
}

fn screen(dir: &std::path::Path) -> Screen {
    let embedder = Embedder::random(5);
    // The synthetic tasks are joint-space patterns that do not draw on the canvas; the
    // workcell rules would answer every one of them no-go and hide what is tested here.
    let station = Station::panda().with_workcell(guardian_shared::workcell::Workcell::OFF);
    // A huge threshold: every well-formed genuine check would be `Go`, so garbage that got
    // through validation would show up as `Go`.
    let mut bank = ClassBank::new(
        guardian_models::embedder::EMBED_DIM,
        embedder.version(),
        1e9,
    );
    for (c, name) in ENROLLED.iter().enumerate() {
        let es: Vec<Vec<f32>> = (0..3)
            .map(|d| {
                let e = check::embed_plan(&embedder, &station, &task(c as u32, d));
                e.expect("embed").expect("valid").embedding.to_vec()
            })
            .collect();
        bank.enroll(name, &es).expect("enroll");
    }
    Screen::new(embedder, station, bank, dir.join("bank.gcb"), 3)
}

/// A header, often consistent with its payload so that requests reach validation and the
/// model, otherwise arbitrary in every field; payloads are genuine plans of three tasks
/// (often mutated at one value), random floats or empty.
fn request() -> impl Strategy<Value = (RequestHeader, Vec<f32>)> {
    let genuine = (0u32..3, 0u32..40)
        .prop_map(|(c, d)| guardian_shared::trajectory::to_flat(&task(c, d), PANDA_JOINTS));
    strategy::request(
        CHANNELS as u32,
        strategy::name_field(ENROLLED.to_vec()),
        Just(0u32),
        strategy::payload(genuine, 300),
    )
}

/// Whether the request is a well-formed check of a class enrolled in `bank` with a valid
/// trajectory, judged independently of the screen's code path.
fn genuine_check(bank: &ClassBank, h: &RequestHeader, payload: &[f32]) -> bool {
    h.op == Op::Check as u32
        && h.channels == CHANNELS as u32
        && h.examples == 1
        && u64::from(h.waypoints[0]) * CHANNELS as u64 == payload.len() as u64
        && decode_class_name(&h.class_name).is_ok_and(|n| bank.class(n).is_some())
        && from_flat(payload, CHANNELS, Robot::panda().limits()).is_ok()
}

fn assert_sound(
    bank: &ClassBank,
    h: &RequestHeader,
    payload: &[f32],
    r: &ResponseHeader,
) -> Result<(), TestCaseError> {
    let genuine = genuine_check(bank, h, payload);
    prop_assert_eq!(r.request_id, h.request_id);
    prop_assert_eq!(r.op, h.op);
    prop_assert!(decode_code::<Status>(r.status).is_some());
    prop_assert!(decode_code::<VerdictCode>(r.verdict).is_some());
    if r.status != Status::Ok as u32 {
        prop_assert_eq!(r.verdict, VerdictCode::None as u32);
    }
    if h.op != Op::Check as u32 {
        prop_assert_eq!(r.verdict, VerdictCode::None as u32);
    }
    if r.verdict == VerdictCode::Go as u32 {
        prop_assert!(genuine, "Go for garbage: {h:?}");
        prop_assert!(r.claimed_distance.is_finite() && r.claimed_distance <= r.threshold);
    }
    if genuine {
        // Answered with a verdict from the model (enrolled garbage may move prototypes, so
        // wrong-task is possible), never with an error or an invalid-trajectory reason.
        prop_assert_eq!(r.status, Status::Ok as u32);
        prop_assert_ne!(r.verdict, VerdictCode::None as u32);
        prop_assert!(r.reason == 0 || r.reason == 1 || r.reason == 2, "{r:?}");
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(CASES))]

    #[test]
    fn arbitrary_requests_never_panic_and_garbage_is_never_go((h, payload) in request()) {
        with_screen(|s| {
            // Judged against the bank before the request (an enroll may add the class).
            let bank = s.bank().clone();
            let answer = s.handle(&h, &payload);
            let r = answer.response;
            assert_sound(&bank, &h, &payload, &r)?;
            if r.status != Status::Ok as u32 {
                prop_assert!(answer.entries.is_empty());
            }
            // What the observers receive is what the wire says.
            match &answer.check {
                Some(Ok(v)) => {
                    prop_assert_eq!(r.status, Status::Ok as u32);
                    prop_assert_eq!(v.is_go(), r.verdict == VerdictCode::Go as u32);
                }
                Some(Err(f)) => prop_assert_eq!(r.status, f.status() as u32),
                None => prop_assert_ne!(h.op, Op::Check as u32),
            }
            Ok(())
        })?;
    }

    #[test]
    fn arbitrary_micro_batches_answer_each_request_soundly(
        batch in prop::collection::vec(request(), 2..6)
    ) {
        with_screen(|s| {
            let items: Vec<(RequestHeader, &[f32])> =
                batch.iter().map(|(h, p)| (*h, p.as_slice())).collect();
            let before = s.bank().clone();
            let answers = s.handle_batch(&items);
            prop_assert_eq!(answers.len(), batch.len());
            // An enroll or forget inside the batch changes the bank for the requests after
            // it; judge against the bank before and after, Go must be genuine in one.
            let after = s.bank().clone();
            for ((h, p), a) in batch.iter().zip(&answers) {
                let r = &a.response;
                if assert_sound(&before, h, p, r).is_err() {
                    assert_sound(&after, h, p, r)?;
                }
            }
            Ok(())
        })?;
    }
}

/// Header sizes that overflow any 64-bit product or sum, for every op.
#[test]
fn overflowing_sizes_are_bad_requests() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = screen(dir.path());
    let cases: [(u32, [u32; 3]); 4] = [
        // 2 x (2^32 - 1) + 2 waypoints of 2^31 channels: 2^64 floats, 0 modulo 2^64.
        (1 << 31, [u32::MAX, u32::MAX, 2]),
        (u32::MAX, [u32::MAX, u32::MAX, u32::MAX]),
        (u32::MAX, [u32::MAX, 0, 0]),
        (8, [u32::MAX, 1, 1]),
    ];
    for op in 1..=6u32 {
        for (channels, w) in cases {
            let mut h = RequestHeader::new(9, Op::Check);
            h.op = op;
            h.channels = channels;
            h.examples = MAX_EXAMPLES as u32;
            h.waypoints[..3].copy_from_slice(&w);
            h.class_name = encode_class_name("task0").unwrap();
            for examples in [1, 3, MAX_EXAMPLES as u32] {
                h.examples = examples;
                for payload in [&[][..], &[0.0f32; 24][..]] {
                    let r = s.handle(&h, payload).response;
                    assert_ne!(r.verdict, VerdictCode::Go as u32);
                    if op == Op::Enroll as u32 || op == Op::Identify as u32 {
                        assert_ne!(r.status, Status::Ok as u32, "op {op} {h:?}");
                    }
                }
            }
        }
    }
    // A genuine check still passes afterwards.
    let t: Vec<Waypoint> = task(1, 30);
    let mut h = RequestHeader::new(10, Op::Check);
    h.channels = CHANNELS as u32;
    h.examples = 1;
    h.waypoints[0] = t.len() as u32;
    h.class_name = encode_class_name("task1").unwrap();
    let p: Vec<f32> = guardian_shared::trajectory::to_flat(&t, PANDA_JOINTS);
    assert_eq!(s.handle(&h, &p).response.verdict, VerdictCode::Go as u32);
}
