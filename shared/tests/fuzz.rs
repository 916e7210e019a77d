//! Property tests ("fuzzing" on stable Rust) of everything that decodes untrusted planner
//! input: class-name fields, free-text fields, wire codes, flat trajectory buffers and their
//! validation. Every input must give a typed error or a value that satisfies the contract;
//! nothing may panic. Case counts are per property (see `docs/reliability.md`).

use guardian_shared::trajectory::{
    InvalidKind, JointLimits, MAX_WAYPOINTS, MIN_WAYPOINTS, STEPS, TOOL, Waypoint, from_flat,
    resample, split_flat, to_flat, validate,
};
use guardian_shared::wire::{
    ClassNameError, LimitKind, MAX_CLASS_NAME, NAME_BYTES, Op, ReasonCode, ResponseHeader, Status,
    VerdictCode, decode_class_name, decode_code, decode_text, encode_class_name, encode_text,
    validate_class_name,
};
use guardian_shared::workcell::{GeometryFeature, WorkcellKind};
use proptest::prelude::*;

const CASES: u32 = 10_000;

/// The Panda's joints and published limits (the models crate owns the robot; the contract is
/// robot-independent, so any limits exercise it).
const JOINTS: usize = 7;
const CHANNELS: usize = JOINTS + 1;
const Q_MIN: [f64; JOINTS] = [
    -2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973,
];
const Q_MAX: [f64; JOINTS] = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973];

fn limits() -> JointLimits {
    JointLimits::new(Q_MIN.to_vec(), Q_MAX.to_vec()).unwrap()
}

/// A value in `[lo, hi]`, both ends included, on a grid of a millionth of the range.
/// (proptest 1.12's own float-range sampler can fail its internal assertion
/// `self.low - result < initial.step` on such ranges, which made this suite flaky.)
fn in_range(lo: f32, hi: f32) -> impl Strategy<Value = f32> + Clone {
    (0u32..=1_000_000).prop_map(move |u| (lo + (hi - lo) * (u as f32 / 1e6)).clamp(lo, hi))
}

/// Any f32 bit pattern (NaN payloads, infinities, subnormals) half of the time, otherwise a
/// value near the joint ranges so that valid trajectories are generated too.
fn value() -> impl Strategy<Value = f32> {
    prop_oneof![
        any::<u32>().prop_map(f32::from_bits),
        in_range(-3.2, 3.8),
        Just(0.0f32),
        Just(1.0f32),
    ]
}

/// A waypoint that is valid most of the time, with a chance of one broken channel.
fn waypoint() -> impl Strategy<Value = Waypoint> {
    let joints: Vec<_> = (0..JOINTS)
        .map(|j| in_range(Q_MIN[j] as f32, Q_MAX[j] as f32).boxed())
        .collect();
    (
        joints,
        prop::bool::ANY,
        prop::option::weighted(0.05, (0..CHANNELS, value())),
    )
        .prop_map(|(q, pen, broken)| {
            let mut w = guardian_shared::trajectory::waypoint(&q, if pen { 1.0 } else { 0.0 });
            if let Some((c, v)) = broken {
                w[if c == JOINTS { TOOL } else { c }] = v;
            }
            w
        })
}

/// The contract, written independently of `validate`.
fn oracle(w: &[Waypoint]) -> Option<(InvalidKind, usize)> {
    if w.len() < MIN_WAYPOINTS {
        return Some((InvalidKind::TooFewWaypoints, w.len()));
    }
    if w.len() > MAX_WAYPOINTS {
        return Some((InvalidKind::TooManyWaypoints, w.len()));
    }
    for (i, p) in w.iter().enumerate() {
        if p.iter().any(|v| v.is_nan() || v.is_infinite()) {
            return Some((InvalidKind::NonFinite, i));
        }
        if (0..JOINTS).any(|j| !(Q_MIN[j]..=Q_MAX[j]).contains(&f64::from(p[j]))) {
            return Some((InvalidKind::JointOutOfLimits, i));
        }
        if !(p[TOOL] == 0.0 || p[TOOL] == 1.0) {
            return Some((InvalidKind::ToolOutOfRange, i));
        }
    }
    None
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(CASES))]

    /// Any 64 bytes in a name field: a typed error, or a name that is 1..=63 bytes of UTF-8
    /// without control characters and re-encodes to exactly the same field.
    #[test]
    fn any_name_field_decodes_to_a_valid_name_or_a_typed_error(
        bytes in prop::collection::vec(
            prop_oneof![any::<u8>(), Just(0u8), 0x20u8..0x7f], NAME_BYTES)
    ) {
        let mut field = [0u8; NAME_BYTES];
        field.copy_from_slice(&bytes);
        match decode_class_name(&field) {
            Ok(name) => {
                prop_assert!(!name.is_empty() && name.len() <= MAX_CLASS_NAME);
                prop_assert!(!name.chars().any(char::is_control));
                prop_assert_eq!(encode_class_name(name), Ok(field));
            }
            Err(e) => {
                // The same bytes re-read by an independent rule must indeed be invalid.
                let len = field.iter().position(|&b| b == 0).unwrap_or(NAME_BYTES);
                let valid = len > 0
                    && len <= MAX_CLASS_NAME
                    && field[len..].iter().all(|&b| b == 0)
                    && std::str::from_utf8(&field[..len])
                        .is_ok_and(|s| !s.chars().any(char::is_control));
                prop_assert!(!valid, "{e} for a valid field {field:?}");
            }
        }
    }

    /// Hostile names offered by a planner: huge, control characters, NUL inside, empty,
    /// any Unicode. Accepted exactly when 1..=63 bytes without control characters.
    #[test]
    fn hostile_names_are_rejected_with_a_typed_error(
        name in prop_oneof![
            any::<String>(),
            "[\\x00-\\x1f\\x7f\\u{80}-\\u{9f}a-z]{0,80}",
            "[a-z\\u{10000}-\\u{10ffff}]{0,40}",
            (1usize..100_000).prop_map(|n| "x".repeat(n)),
            Just(String::new()),
            Just("a\0b".to_string()),
        ]
    ) {
        let ok = !name.is_empty() && name.len() <= MAX_CLASS_NAME
            && !name.chars().any(char::is_control);
        match encode_class_name(&name) {
            Ok(field) => {
                prop_assert!(ok);
                prop_assert_eq!(decode_class_name(&field), Ok(name.as_str()));
            }
            Err(e) => {
                prop_assert!(!ok);
                let expected = if name.is_empty() {
                    matches!(e, ClassNameError::Empty)
                } else if name.len() > MAX_CLASS_NAME {
                    matches!(e, ClassNameError::TooLong { len, .. } if len == name.len())
                } else {
                    matches!(e, ClassNameError::ControlCharacter { index } if name[index..].starts_with(|c: char| c.is_control()))
                };
                prop_assert!(expected, "{e:?} for {name:?}");
                prop_assert_eq!(validate_class_name(&name), Err(e));
            }
        }
    }

    /// Free text is cut at a character boundary and always keeps a terminating NUL; any
    /// bytes decode (lossily) without panicking.
    #[test]
    fn text_fields_never_overflow(text in any::<String>(), bytes in prop::collection::vec(any::<u8>(), 0..200)) {
        let field: [u8; 128] = encode_text(&text);
        prop_assert_eq!(field[127], 0);
        let back = decode_text(&field);
        prop_assert!(text.starts_with(&back), "{back:?} is not a prefix of {text:?}");
        let _ = decode_text(&bytes);
    }

    /// Every u32 either decodes to the code with that value or to nothing.
    #[test]
    fn any_code_decodes_or_is_rejected(v in prop_oneof![0u32..20, any::<u32>()]) {
        prop_assert_eq!(decode_code::<Op>(v).map(|o| o as u32), (1..=6).contains(&v).then_some(v));
        prop_assert_eq!(decode_code::<Status>(v).map(|o| o as u32), (v <= 10).then_some(v));
        prop_assert_eq!(decode_code::<VerdictCode>(v).map(|o| o as u32), (v <= 2).then_some(v));
        prop_assert_eq!(decode_code::<ReasonCode>(v).map(|o| o as u32), (v <= 6).then_some(v));
        prop_assert_eq!(decode_code::<LimitKind>(v).map(|o| o as u32), (1..=3).contains(&v).then_some(v));
        prop_assert_eq!(decode_code::<WorkcellKind>(v).map(|o| o as u32), (1..=6).contains(&v).then_some(v));
        prop_assert_eq!(decode_code::<GeometryFeature>(v).map(|o| o as u32), (1..=13).contains(&v).then_some(v));
        let r = ResponseHeader { invalid_kind: v, ..ResponseHeader::default() };
        prop_assert_eq!(r.invalid().map(|k| k as u32), (1..=6).contains(&v).then_some(v));
    }

    /// A flat buffer of any length and channel count: a typed error, or waypoints that are
    /// exactly the buffer's rows and satisfy the contract.
    #[test]
    fn any_flat_buffer_is_validated_or_rejected(
        data in prop::collection::vec(value(), 0..200),
        channels in prop_oneof![Just(CHANNELS), any::<usize>(), 0usize..16],
    ) {
        match from_flat(&data, channels, &limits()) {
            Ok(w) => {
                prop_assert_eq!(channels, CHANNELS);
                prop_assert_eq!(w.len() * CHANNELS, data.len());
                let flat = to_flat(&w, JOINTS);
                prop_assert!(flat.iter().zip(&data).all(|(a, b)| a.to_bits() == b.to_bits()));
                prop_assert_eq!(oracle(&w), None);
            }
            Err(e) => {
                if channels != CHANNELS || data.len() % CHANNELS != 0 {
                    prop_assert_eq!(e.kind, InvalidKind::WrongChannelCount);
                } else {
                    let w = split_flat(&data, CHANNELS, JOINTS).unwrap();
                    prop_assert_eq!(oracle(&w), Some((e.kind, e.index as usize)));
                }
            }
        }
    }

    /// Mostly-valid trajectories with occasional broken values: `validate` reports exactly
    /// the first problem the contract names, and valid ones resample to valid model input.
    #[test]
    fn validation_matches_the_contract_and_valid_input_resamples_within_limits(
        w in prop::collection::vec(waypoint(), 0..300),
        steps in prop::collection::vec(0.0f64..0.05, 300),
    ) {
        let got = validate(&w, &limits()).err().map(|e| (e.kind, e.index as usize));
        prop_assert_eq!(got, oracle(&w));
        if got.is_none() {
            let mut cum = Vec::with_capacity(w.len());
            let mut s = 0.0;
            for d in &steps[..w.len()] {
                cum.push(s);
                s += d;
            }
            let x = resample(&w, &cum, JOINTS);
            prop_assert_eq!(x.len(), STEPS);
            for p in &x {
                prop_assert!(p[TOOL] == 0.0 || p[TOOL] == 1.0);
                for j in 0..JOINTS {
                    let q = f64::from(p[j]);
                    // Interpolation stays inside the limits (up to f32 rounding).
                    prop_assert!(q >= Q_MIN[j] - 1e-6 && q <= Q_MAX[j] + 1e-6, "{p:?}");
                }
            }
        }
    }
}

/// Counts at and around the limits, including sizes far beyond any buffer.
#[test]
fn waypoint_counts_at_and_beyond_the_limits() {
    let ok = guardian_shared::trajectory::waypoint(&[0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0], 0.0);
    for n in [0, 1, 2, MAX_WAYPOINTS, MAX_WAYPOINTS + 1, 3 * MAX_WAYPOINTS] {
        let w = vec![ok; n];
        let got = validate(&w, &limits())
            .err()
            .map(|e| (e.kind, e.index as usize));
        assert_eq!(got, oracle(&w), "{n} waypoints");
    }
}
