//! The verdict is declared once per layer and converted once each way: the bank's
//! `Decision` goes on the wire by `Decision::answer` (+ `encode_check`), and the client reads
//! it back by `Verdict::from_response`. This test holds the two conversions together: every
//! outcome, with and without each number, comes back as the same verdict.

use guardian_bank::{Decision, Neighbour, Outcome};
use guardian_client::{Decision as ClientDecision, NoGoReason, Verdict};
use guardian_shared::wire::{
    ClassEntry, Op, RequestHeader, ResponseHeader, encode_check, encode_class_name, encode_text,
};
use guardian_shared::workcell::GeometryFeature;

/// The response a daemon writes for `d` answering a check that claimed `claimed`.
fn response(d: &Decision, claimed: &str) -> (ResponseHeader, Vec<ClassEntry>) {
    let mut h = RequestHeader::new(11, Op::Check);
    h.class_name = encode_class_name(claimed).unwrap();
    let mut r = ResponseHeader::answering(&h);
    encode_check(&mut r, &d.answer());
    let entries = d
        .nearest
        .iter()
        .map(|n| ClassEntry {
            name: encode_text(&n.name),
            distance: n.distance,
            threshold: 0.5,
            examples: 3,
            calibrated: 1,
        })
        .collect();
    (r, entries)
}

fn decision(outcome: Outcome, numbers: Option<f32>) -> Decision {
    let geometry = matches!(outcome, Outcome::GeometryMismatch { .. });
    Decision {
        outcome,
        claimed_distance: numbers,
        threshold: numbers.map(|v| v + 0.25),
        margin: numbers.map(|_| 0.25),
        gap: numbers.map(|v| -v),
        nearest: vec![
            Neighbour {
                name: "other".into(),
                distance: 0.125,
            },
            Neighbour {
                name: "claimed".into(),
                distance: 0.5,
            },
        ],
        geometry_score: geometry.then_some(4.5),
        geometry_threshold: geometry.then_some(3.0),
        geometry_feature: geometry.then_some(GeometryFeature::StartX),
    }
}

#[test]
fn every_decision_comes_back_from_the_wire_as_the_same_verdict() {
    let outcomes = [
        Outcome::Go,
        Outcome::WrongTask {
            nearest: "other".into(),
        },
        Outcome::Outlier,
        Outcome::GeometryMismatch {
            feature: GeometryFeature::StartX,
        },
        Outcome::UnknownClass,
    ];
    for outcome in outcomes {
        for numbers in [Some(0.75f32), None] {
            let d = decision(outcome.clone(), numbers);
            let (r, entries) = response(&d, "claimed");
            let v: Verdict = Verdict::from_response(&r, &entries, "claimed")
                .unwrap_or_else(|e| panic!("{outcome:?}: {e}"));
            let want = match &d.outcome {
                Outcome::Go => ClientDecision::Go,
                Outcome::WrongTask { nearest } => ClientDecision::NoGo {
                    reason: NoGoReason::WrongTask {
                        nearest: nearest.clone(),
                    },
                },
                Outcome::Outlier => ClientDecision::NoGo {
                    reason: NoGoReason::Outlier,
                },
                Outcome::GeometryMismatch { feature } => ClientDecision::NoGo {
                    reason: NoGoReason::GeometryMismatch {
                        feature: *feature,
                        score: 4.5,
                        threshold: 3.0,
                    },
                },
                Outcome::UnknownClass => ClientDecision::NoGo {
                    reason: NoGoReason::UnknownClass,
                },
            };
            assert_eq!(v.decision, want, "{outcome:?}");
            assert_eq!(v.is_go(), d.outcome == Outcome::Go);
            assert_eq!(v.claimed_class, "claimed");
            assert_eq!(
                (v.claimed_distance, v.threshold, v.margin, v.gap),
                (d.claimed_distance, d.threshold, d.margin, d.gap),
                "{outcome:?} {numbers:?}"
            );
            assert_eq!(
                (v.geometry_score, v.geometry_threshold),
                (d.geometry_score, d.geometry_threshold)
            );
            let names: Vec<&str> = v.nearest.iter().map(|n| n.class.as_str()).collect();
            assert_eq!(names, ["other", "claimed"]);
            assert_eq!(v.nearest[0].distance, 0.125);
        }
    }
}

/// A response that answers another check (class not echoed) is a protocol error, not a
/// verdict.
#[test]
fn a_response_to_another_check_is_refused() {
    let d = decision(Outcome::Go, Some(0.1));
    let (r, entries) = response(&d, "claimed");
    let e = Verdict::from_response(&r, &entries, "something-else").unwrap_err();
    assert!(e.to_string().contains("echo"), "{e}");
}
