//! The cell demo (`examples/cell`) end to end: a real `guardiand` on the `[cell]` table of
//! `systemd/guardiand-cell.toml` (anchored, its boxes) with the shipped model and default
//! bank, over real iceoryx2; every case must get its expected answer, the place no-go must
//! say so, and the demo classes are forgotten afterwards.

#[allow(dead_code)]
#[path = "../demo/cases.rs"]
mod demo;

#[allow(dead_code)]
#[path = "../cell/cases.rs"]
mod cases;

use demo::Outcome;
use guardian_tests::harness::{self, Daemon, Setup};

/// The `[cell]` table of the shipped cell configuration, as text.
fn cell_table() -> String {
    let path = harness::workspace_root().join("systemd/guardiand-cell.toml");
    let text = std::fs::read_to_string(&path).expect("systemd/guardiand-cell.toml");
    text.lines()
        .skip_while(|l| l.trim() != "[cell]")
        .map(|l| format!("{l}\n"))
        .collect()
}

#[test]
fn the_shipped_cell_config_boxes_the_demos_bin() {
    let table: toml::Table = toml::from_str(&cell_table()).expect("toml");
    let boxes = table["cell"]["keep-out"].as_array().expect("keep-out");
    let corner = |k: &str| -> Vec<f64> {
        boxes[0][k]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_float().unwrap())
            .collect()
    };
    let (lo, hi) = cases::keep_out_box();
    for (got, want) in corner("min")
        .iter()
        .zip(lo)
        .chain(corner("max").iter().zip(hi))
    {
        assert!(
            (got - want).abs() < 1e-3,
            "config {got}, demo {want}: {lo:?} {hi:?}"
        );
    }
}

#[test]
fn every_cell_demo_case_is_as_expected() {
    let mut s = Setup::new(94);
    let root = harness::workspace_root();
    s.model = root.join("models/embedder.safetensors");
    s.default_bank = Some(root.join("models/default-bank.gcb"));
    s.tables.push_str(&cell_table());
    let _d = Daemon::start(&s);
    let client = s.client();
    let report = cases::run_cases(&client, false).expect("demo runs");
    let table = report.table();
    // `cargo test -p guardian-examples --test cell -- --nocapture` shows the demo's table.
    println!("{table}");
    assert!(report.all_as_expected(), "{table}");
    for kind in [Outcome::Go, Outcome::Geometry, Outcome::Workcell] {
        assert!(
            report.rows.iter().any(|r| r.got == kind),
            "{kind:?}\n{table}"
        );
    }
    let wrong_bin = &report.rows[3];
    assert!(wrong_bin.verdict.contains("place:"), "{table}");
    let classes = client.classes().expect("classes");
    assert!(
        classes.iter().all(|c| !c.name.starts_with("cell-")),
        "{classes:?}"
    );
}
