//! `guardian-lab kfold` end to end on real strokes of both shared roots (two official, two
//! recovered alphabets, a few characters each), with a schedule of a few steps: every fold
//! model is trained without its held-out alphabets, every held-out alphabet gets episode
//! and cross-fitted go / no-go rows, the report names every alphabet, and a second run
//! measures and trains nothing again.

use std::path::{Path, PathBuf};

use clap::Parser;
use guardian_lab::eval::kfold::{self, Row};
use guardian_omniglot::dataset::generate_files;
use guardian_omniglot::path::Geometry;
use guardian_omniglot::strokes::scan;

mod common;
use common::first_characters;

fn shared(root: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/omniglot")
        .join(root)
}

#[derive(Debug, Parser)]
struct Cli {
    #[command(flatten)]
    args: kfold::Args,
}

fn rows(out: &Path) -> Vec<Row> {
    std::fs::read_to_string(out.join("results.jsonl"))
        .expect("results")
        .lines()
        .map(|l| serde_json::from_str(l).expect("row"))
        .collect()
}

#[test]
fn kfold_trains_measures_and_reports_every_held_out_alphabet_once() {
    let roots = [shared("strokes"), shared("recovered")];
    let all = scan(&roots).expect("both shared roots");
    let files = first_characters(
        &all,
        &[("Latin", 6), ("Greek", 6), ("Futurama", 6), ("Keble", 6)],
    );
    let (data, report) = generate_files(&files, &Geometry::default(), &|| {}).expect("generate");
    assert_eq!(report.converted, files.len());
    let dir = tempfile::tempdir().expect("tempdir");
    let dataset = dir.path().join("data.safetensors");
    data.save(&dataset).expect("save");
    let out = dir.path().join("kfold");
    let strokes = format!("{},{}", roots[0].display(), roots[1].display());
    let cli = Cli::try_parse_from([
        "kfold",
        "--dataset",
        dataset.to_str().expect("utf-8 path"),
        "--strokes",
        &strokes,
        "--out",
        out.to_str().expect("utf-8 path"),
        "--folds",
        "2",
        "--steps-per-epoch",
        "2",
        "--epochs",
        "1",
        "--train-args",
        "--fault-variants 1",
        "--episodes",
        "50",
        "--sources",
        "6",
        "--calib-reps",
        "2",
        "--reps",
        "1",
        "--threads",
        "2",
    ])
    .expect("parse");
    kfold::run(&cli.args).expect("kfold runs");

    // The dense alphabets are dealt first: one per fold.
    let folds: Vec<Vec<String>> =
        serde_json::from_slice(&std::fs::read(out.join("folds.json")).expect("folds")).unwrap();
    assert_eq!(folds, [["Greek", "Futurama"], ["Latin", "Keble"]]);
    for (k, fold) in folds.iter().enumerate() {
        for branch in ["seq", "pic"] {
            let cfg: serde_json::Value = serde_json::from_slice(
                &std::fs::read(out.join(format!("fold-{k}/{branch}/train-config.json")))
                    .expect("train config"),
            )
            .unwrap();
            let trained: Vec<String> =
                serde_json::from_value(cfg["train-alphabets"].clone()).expect("train alphabets");
            assert_eq!(trained.len(), 2, "{trained:?}");
            assert!(
                trained.iter().all(|a| !fold.contains(a)),
                "fold {k} {branch} trained on a held-out alphabet: {trained:?}"
            );
            let val = cfg["val-alphabets"].as_array().map_or(0, Vec::len);
            assert_eq!(val, 0, "no validation alphabet is used for model selection");
        }
        assert!(out.join(format!("fold-{k}/crossfit-bank.gcb")).exists());
    }

    let first = rows(&out);
    for a in ["Latin", "Greek", "Futurama", "Keble"] {
        let ep: Vec<&Row> = first
            .iter()
            .filter(|r| r.alphabet == a && r.kind == "episodes" && r.model == "fold")
            .collect();
        // Six classes: 2-way only (10- and 20-way need more classes).
        assert_eq!(ep.len(), 1, "{a}: {ep:?}");
        assert_eq!((ep[0].way, ep[0].shot), (Some(2), Some(1)));
        assert!(ep[0].value > 0.0 && ep[0].value <= 1.0, "{:?}", ep[0]);
        assert_eq!(ep[0].dense, a == "Latin" || a == "Greek");
        let out_rows: Vec<&Row> = first
            .iter()
            .filter(|r| r.alphabet == a && r.kind == "outliers")
            .collect();
        assert_eq!(out_rows.len(), 1, "{a}");
        let frr = out_rows[0].figures["genuine-false-reject"];
        assert!((0.0..=1.0).contains(&frr), "{frr}");
        assert!((0.0..=1.0).contains(&out_rows[0].value));
    }
    let text = std::fs::read_to_string(out.join("REPORT.md")).expect("report");
    for a in ["Latin", "Greek", "Futurama", "Keble"] {
        assert!(text.contains(&format!("| {a} |")), "{a} missing:\n{text}");
    }

    // A second run finds everything done: no new rows, no model trained again.
    let model = out.join("fold-0/model.safetensors");
    let before = std::fs::metadata(&model).unwrap().modified().unwrap();
    kfold::run(&cli.args).expect("kfold runs again");
    assert_eq!(rows(&out), first);
    assert_eq!(
        std::fs::metadata(&model).unwrap().modified().unwrap(),
        before
    );

    // A fold model kept without its training runs (e.g. from another machine) is measured
    // as it is: its branches are not trained again.
    for branch in ["seq", "pic"] {
        std::fs::remove_dir_all(out.join(format!("fold-1/{branch}"))).expect("remove branch");
    }
    kfold::run(&cli.args).expect("kfold runs with fused fold models only");
    assert_eq!(rows(&out), first);
    assert!(!out.join("fold-1/seq").exists() && !out.join("fold-1/pic").exists());
}
