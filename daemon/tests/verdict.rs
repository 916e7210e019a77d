//! The verdict is one type (`guardian_shared::verdict::Verdict`): the bank returns it, the
//! daemon writes it on the wire with `encode_check` (its nearest classes as the entries, its
//! versions as the daemon's state), and the client reads it back with
//! `verdict_of_response`. This test holds the two conversions together: every reason, with
//! and without each number, comes back from the wire as the same verdict, field for field.

use std::borrow::Cow;

use guardian_client::{Decision, Neighbour, NoGoReason, Verdict, verdict_of_response};
use guardian_shared::trajectory::{InvalidKind, InvalidTrajectory};
use guardian_shared::wire::{
    ClassEntry, DaemonState, Op, RequestHeader, ResponseHeader, RobotInfo, encode_check,
    encode_class_name, encode_state, encode_text,
};
use guardian_shared::workcell::{GeometryFeature, WorkcellKind, WorkcellViolation};

/// The response a daemon writes for `v` answering a check that claimed `claimed`.
fn response(v: &Verdict, claimed: &str) -> (ResponseHeader, Vec<ClassEntry>) {
    let mut h = RequestHeader::new(11, Op::Check);
    h.class_name = encode_class_name(claimed).unwrap();
    let mut r = ResponseHeader::answering(&h);
    encode_check(&mut r, v);
    encode_state(
        &mut r,
        &DaemonState {
            model_version: Cow::Borrowed(&v.model_version),
            bank_version: v.bank_version,
            class_count: 2,
            uptime_ms: 1,
            requests: 1,
            errors: 0,
            go: 0,
            no_go: 0,
            latency_us: [f32::NAN; 4],
            robot: RobotInfo {
                name: Cow::Borrowed("panda"),
                joints: 7,
                urdf_sha256: [0; 32],
            },
        },
    );
    let entries = v
        .nearest
        .iter()
        .map(|n| ClassEntry {
            name: encode_text(&n.class),
            distance: n.distance,
            threshold: n.threshold,
            examples: 3,
            calibrated: 1,
        })
        .collect();
    (r, entries)
}

fn verdict(reason: Option<NoGoReason>, numbers: Option<f32>) -> Verdict {
    let geometry = matches!(reason, Some(NoGoReason::GeometryMismatch { .. }));
    let early = matches!(
        reason,
        Some(NoGoReason::InvalidTrajectory { .. } | NoGoReason::Workcell { .. })
    );
    let decision = reason.map_or(Decision::Go, |reason| Decision::NoGo { reason });
    let nearest = [("other", 0.125), ("claimed", 0.5)]
        .map(|(class, distance)| Neighbour {
            class: class.into(),
            distance,
            threshold: 0.5,
        })
        .to_vec();
    Verdict {
        decision,
        claimed_class: "claimed".into(),
        claimed_distance: numbers,
        threshold: numbers.map(|v| v + 0.25),
        margin: numbers.map(|_| 0.25),
        gap: numbers.map(|v| -v),
        nearest: if early { Vec::new() } else { nearest },
        geometry_score: geometry.then_some(4.5),
        geometry_threshold: geometry.then_some(3.0),
        geometry_feature: geometry.then_some(GeometryFeature::StartX),
        model_version: "0123456789abcdef".into(),
        bank_version: 42,
    }
}

#[test]
fn every_verdict_comes_back_from_the_wire_as_the_same_verdict() {
    let reasons = [
        None,
        Some(NoGoReason::WrongTask {
            nearest: "other".into(),
        }),
        Some(NoGoReason::Outlier),
        Some(NoGoReason::GeometryMismatch {
            feature: GeometryFeature::StartX,
            score: 4.5,
            threshold: 3.0,
        }),
        Some(NoGoReason::UnknownClass),
        Some(InvalidTrajectory::new(InvalidKind::JointOutOfLimits, 17).into()),
        Some(
            WorkcellViolation {
                kind: WorkcellKind::KeepOut,
                index: 9,
            }
            .into(),
        ),
    ];
    for reason in reasons {
        for numbers in [Some(0.75f32), None] {
            let sent = verdict(reason.clone(), numbers);
            let (r, entries) = response(&sent, "claimed");
            let got = verdict_of_response(&r, &entries, "claimed")
                .unwrap_or_else(|e| panic!("{reason:?}: {e}"));
            assert_eq!(got, sent, "{reason:?} {numbers:?}");
            assert_eq!(got.is_go(), reason.is_none());
        }
    }
}

/// A response that answers another check (class not echoed) is a protocol error, not a
/// verdict.
#[test]
fn a_response_to_another_check_is_refused() {
    let v = verdict(None, Some(0.1));
    let (r, entries) = response(&v, "claimed");
    let e = verdict_of_response(&r, &entries, "something-else").unwrap_err();
    assert!(e.to_string().contains("echo"), "{e}");
}
