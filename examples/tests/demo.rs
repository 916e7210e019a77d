//! The demo (`examples/demo`) end to end: a real `guardiand` with the shipped defaults (workcell
//! rules on, shipped model, shipped default bank) over real iceoryx2, the demo's real
//! Omniglot drawings; every case must get its expected verdict, and the demo classes are
//! forgotten afterwards (the default bank's classes stay).

#[allow(dead_code)]
#[path = "../demo/cases.rs"]
mod demo;

use demo::{Options, Outcome};
use guardian_tests::harness::{self, Daemon, Setup};

fn shipped_setup(seed: u64) -> Setup {
    let mut s = Setup::new(seed);
    s.workcell_rules = true;
    let models = harness::workspace_root().join("models");
    s.model = models.join("embedder.safetensors");
    // The harness writes `default-bank = ""`; a bank in the state directory is what the
    // daemon loads first, so the shipped default bank goes there.
    std::fs::create_dir_all(s.state_dir()).expect("state dir");
    std::fs::copy(
        models.join("default-bank.gcb"),
        s.state_dir().join("bank.gcb"),
    )
    .expect("copy the shipped default bank");
    s
}

#[test]
fn every_demo_case_is_as_expected_against_the_shipped_defaults() {
    let s = shipped_setup(41);
    let _d = Daemon::start(&s);
    let client = s.client();
    let before = client.classes().expect("classes");
    assert!(
        before.iter().any(|c| c.name == "Greek/character01"),
        "the shipped default bank is loaded"
    );

    let report = demo::run_cases(
        &client,
        &Options {
            strokes: harness::workspace_root().join("../shared/omniglot/strokes"),
            keep: false,
        },
    )
    .expect("demo runs");
    let table = report.table();
    assert!(report.all_as_expected(), "{table}");
    // Every kind of answer the demo promises is really there.
    for kind in [
        Outcome::Go,
        Outcome::WrongTask,
        Outcome::UnknownClass,
        Outcome::Workcell,
        Outcome::Geometry,
        Outcome::Invalid,
    ] {
        assert!(
            report.rows.iter().any(|r| r.got == kind),
            "{kind:?} missing\n{table}"
        );
    }
    assert!(report.kept.is_empty());

    let after = client.classes().expect("classes");
    assert!(
        after.iter().all(|c| !c.name.starts_with("demo-latin-")),
        "demo classes forgotten: {after:?}"
    );
    assert_eq!(after.len(), before.len());

    // The verdict record (issue 43): `guardianctl verdicts --no-go` lists the demo's
    // stops, its wrong-task one with the class it really is.
    let record = s.state_dir().join("verdicts.sqlite");
    let no_go = report.rows.iter().filter(|r| r.got != Outcome::Go).count();
    let rows = harness::recorded_no_go(&record, no_go);
    assert!(
        rows.iter().any(|r| r["reason"] == "wrong-task"
            && r["claimed"] == "demo-latin-13"
            && r["nearest"][0]["class"] == "demo-latin-01"),
        "{rows:#?}"
    );
}

#[test]
fn keep_leaves_the_demo_classes_and_a_second_run_starts_clean() {
    let s = shipped_setup(42);
    let _d = Daemon::start(&s);
    let client = s.client();
    let opts = Options {
        strokes: harness::workspace_root().join("../shared/omniglot/strokes"),
        keep: true,
    };
    let first = demo::run_cases(&client, &opts).expect("demo runs");
    assert!(first.all_as_expected(), "{}", first.table());
    let classes = client.classes().expect("classes");
    for name in &first.kept {
        let c = classes
            .iter()
            .find(|c| &c.name == name)
            .unwrap_or_else(|| panic!("{name} kept: {classes:?}"));
        assert_eq!(c.examples, 5);
    }
    assert_eq!(first.kept.len(), demo::LATIN.len());
    // A second run re-enrolls from scratch (5 examples, not 10) and gets the same answers.
    let second = demo::run_cases(&client, &opts).expect("demo runs again");
    assert!(second.all_as_expected(), "{}", second.table());
    let classes = client.classes().expect("classes");
    for name in &second.kept {
        let c = classes.iter().find(|c| &c.name == name).expect("kept");
        assert_eq!(c.examples, 5);
    }
}
