//! A pick-and-place cell end to end: a real `guardiand` serving an anchored cell (`[cell]
//! anchored = true` with a keep-out box, the shipped model and the shipped bank's
//! calibration) over real iceoryx2. Three bins 6 cm apart are enrolled from five runs each
//! (`guardian-cells`, the project's own IK); another run to its bin goes, the same motion
//! to the neighbouring bin claiming it is refused on its place (with the excess in metres),
//! identify names the bin the run goes to, a run into the keep-out box gets the workcell
//! no-go, and all of it holds after a restart (the place signatures are persisted).

use guardian_cells::{Cell as Runs, Family, FamilyKind};
use guardian_client::{Decision, GeometryFeature, NoGoReason, Trajectory, WorkcellKind};
use guardian_robot::kinematics::PANDA_JOINTS;
use guardian_tests::harness::{self, Daemon, Setup};

#[test]
fn an_anchored_cell_tells_neighbouring_bins_apart_and_keeps_the_tool_out_of_its_box() {
    let family = Family::new(FamilyKind::Bins, 7, 0.06);
    let runs = Runs::default();
    let task = |name: &str| {
        family
            .tasks
            .iter()
            .find(|t| t.name == name)
            .unwrap_or_else(|| panic!("{name}"))
    };
    let run = |name: &str, seed: u64| {
        Trajectory::from_waypoints(&runs.run(task(name), seed).unwrap(), PANDA_JOINTS)
    };
    // A keep-out box over a bin no enrolled task uses (the column of bin-00).
    let boxed = task("bin-00").place;
    let mut s = Setup::new(93);
    let root = harness::workspace_root();
    s.model = root.join("models/embedder.safetensors");
    s.default_bank = Some(root.join("models/default-bank.gcb"));
    s.tables.push_str(&format!(
        "[cell]\nanchored = true\nkeep-out = [{{ min = [{}, {}, 0.0], max = [{}, {}, 0.2] }}]\n",
        boxed.x - 0.02,
        boxed.y - 0.02,
        boxed.x + 0.02,
        boxed.y + 0.02
    ));
    let enrolled = ["bin-10", "bin-11", "bin-12"];
    {
        let _d = Daemon::start(&s);
        let client = s.client();
        for name in enrolled {
            let examples: Vec<Trajectory> = (0..5).map(|d| run(name, d)).collect();
            client.enroll(name, &examples).expect("enroll");
        }
    }
    // A restart: the classes and their places come back from the state directory.
    let _d = Daemon::start(&s);
    let client = s.client();
    for (k, name) in enrolled.iter().enumerate() {
        let genuine = run(name, 100 + k as u64);
        let v = client.check(&genuine, name).expect("check");
        assert_eq!(v.decision, Decision::Go, "{name}: {v:?}");
        let ranking = client.identify(&genuine).expect("identify");
        assert_eq!(ranking.nearest[0].class, *name, "{ranking:?}");
    }
    // The same motion to the neighbouring bin, claiming bin-11: refused on its place.
    let v = client.check(&run("bin-12", 200), "bin-11").expect("check");
    match &v.decision {
        Decision::NoGo {
            reason:
                NoGoReason::GeometryMismatch {
                    feature: GeometryFeature::Place,
                    score,
                    threshold,
                },
        } => assert!(*score > 0.03 && *threshold < *score, "{v:?}"),
        other => panic!("{other:?}"),
    }
    assert!(v.decision.to_string().contains("place:"), "{}", v.decision);
    // Into the keep-out box: the workcell no-go, whatever it claims.
    let v = client.check(&run("bin-00", 300), "bin-10").expect("check");
    assert!(
        matches!(
            v.decision,
            Decision::NoGo {
                reason: NoGoReason::Workcell {
                    kind: WorkcellKind::KeepOut,
                    ..
                }
            }
        ),
        "{v:?}"
    );
    // The bank on disk is format 5 (place signatures kept).
    let bank = std::fs::read(s.state_dir().join("bank.gcb")).expect("bank file");
    assert!(bank.starts_with(b"guardian-class-bank 5 "));
    // The verdict record keeps why: the place excess, the rule and its waypoint.
    let record = s.state_dir().join("verdicts.sqlite");
    let rows = harness::recorded_no_go(&record, 2);
    let message = |r: &serde_json::Value| r["message"].as_str().unwrap_or("").to_owned();
    assert!(
        rows.iter()
            .any(|r| r["reason"] == "geometry-mismatch" && message(r).starts_with("place: ")),
        "{rows:#?}"
    );
    assert!(
        rows.iter()
            .any(|r| r["reason"] == "workcell" && message(r).starts_with("KeepOut at waypoint ")),
        "{rows:#?}"
    );
}
