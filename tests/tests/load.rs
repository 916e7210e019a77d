//! Load: 16 planner threads, each with its own `Client`, send 10,000 checks each to one real
//! `guardiand`. Every answer is matched to its request — the plans and claimed classes vary
//! per request and each (plan, claim) has a known answer taken before the load — with zero
//! lost and zero mismatched responses.

use guardian_robot::kinematics::PANDA_JOINTS;
use std::sync::{Arc, Barrier};

use guardian_client::{Client, Decision, NoGoReason, Trajectory};
use guardian_tests::harness::{Daemon, Expected, Setup, task};

const THREADS: usize = 16;
const PER_THREAD: usize = 10_000;
const CLASSES: u32 = 16;

struct Request {
    plan: Trajectory,
    claim: String,
    expected: Expected,
}

#[test]
fn sixteen_clients_ten_thousand_checks_each_nothing_lost_or_mismatched() {
    let mut s = Setup::new(40);
    s.extra = "default-threshold = 1e9\nk-nearest = 3".into();
    let d = Daemon::start_with_env(&s, &[("RUST_LOG", "info".into())]);
    let client = s.client();
    for c in 0..CLASSES {
        let ex: Vec<Trajectory> = (0..4)
            .map(|dr| Trajectory::from_waypoints(&task(c, dr), PANDA_JOINTS))
            .collect();
        client.enroll(&format!("task{c}"), &ex).expect("enroll");
    }

    // Distinct requests: unseen drawers claiming their own class, the next class and an
    // unknown class, and plans with a NaN at a varying waypoint (the index is echoed).
    let mut requests = Vec::new();
    for c in 0..CLASSES {
        for drawer in 20..24u32 {
            let w = task(c, drawer);
            for claim in [
                format!("task{c}"),
                format!("task{}", (c + 1) % CLASSES),
                format!("unknown{c}"),
            ] {
                let plan = Trajectory::from_waypoints(&w, PANDA_JOINTS);
                let v = client.check(&plan, &claim).expect("reference check");
                requests.push(Request {
                    expected: Expected::of(&v),
                    plan,
                    claim,
                });
            }
            let mut bad = w.clone();
            let at = (c as usize * 5 + drawer as usize) % bad.len();
            bad[at][1] = f32::NAN;
            let plan = Trajectory::from_waypoints(&bad, PANDA_JOINTS);
            let claim = format!("task{c}");
            let v = client.check(&plan, &claim).expect("reference check");
            assert_eq!(
                v.decision,
                Decision::NoGo {
                    reason: NoGoReason::InvalidTrajectory {
                        kind: guardian_client::InvalidKind::NonFinite,
                        index: at as u32
                    }
                }
            );
            requests.push(Request {
                expected: Expected::of(&v),
                plan,
                claim,
            });
        }
    }
    let go = requests
        .iter()
        .filter(|r| r.expected.decision == Decision::Go)
        .count();
    assert!(
        go > 0 && go < requests.len(),
        "{go} go of {}",
        requests.len()
    );
    let before = client.status().expect("status");

    let requests = Arc::new(requests);
    let barrier = Arc::new(Barrier::new(THREADS));
    let handles: Vec<_> = (0..THREADS)
        .map(|t| {
            let (requests, barrier, config) =
                (requests.clone(), barrier.clone(), s.client_config());
            std::thread::spawn(move || {
                let client = Client::connect(config).expect("connect");
                barrier.wait();
                let (mut lost, mut mismatched) = (Vec::new(), 0usize);
                for k in 0..PER_THREAD {
                    let r = &requests[(k * 7 + t * 13) % requests.len()];
                    match client.check(&r.plan, &r.claim) {
                        Ok(v) => mismatched += usize::from(!r.expected.matches(&v)),
                        Err(e) => lost.push(e),
                    }
                }
                (lost, mismatched)
            })
        })
        .collect();
    let mut lost = Vec::new();
    let mut mismatched = 0;
    for h in handles {
        let (l, m) = h.join().expect("client thread");
        lost.extend(l);
        mismatched += m;
    }
    let after = client.status().expect("status");
    let total = (THREADS * PER_THREAD) as u64;
    assert_eq!(lost.len(), 0, "lost: {:?}", &lost[..lost.len().min(5)]);
    assert_eq!(mismatched, 0, "mismatched responses");
    assert_eq!(
        (after.go + after.no_go) - (before.go + before.no_go),
        total,
        "the daemon counted a different number of checks"
    );
    assert_eq!(after.errors, before.errors);
    assert!(!d.log().contains("cannot send response"), "{}", d.log());
}
