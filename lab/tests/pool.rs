//! The unlabelled pool on the real shared data: the reader, the conversion through the robot
//! pipeline, the copies of labelled drawings, pseudo-labels and pool-trained training runs.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use guardian_lab::dataset::{Dataset, generate_files};
use guardian_lab::path::Geometry;
use guardian_lab::pool::{self, ClusterParams, PoolDrawing, PoolMode, ReadPoolError, Shape};
use guardian_lab::strokes::scan;
use guardian_lab::train::{self, LossKind, Prepared, TrainConfig};
use guardian_models::embedder::Embedder;
use guardian_models::features::FeatureKind;
use rand::SeedableRng;
use rand::rngs::StdRng;

mod common;

fn shared() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/omniglot")
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The whole unlabelled file, read once.
fn pool_drawings() -> &'static [PoolDrawing] {
    static POOL: OnceLock<Vec<PoolDrawing>> = OnceLock::new();
    POOL.get_or_init(|| {
        pool::read_pool(&shared().join("unlabelled/drawings.jsonl")).expect("read pool")
    })
}

/// Shapes of the whole pool, once.
fn pool_shapes() -> &'static [Shape] {
    static SHAPES: OnceLock<Vec<Shape>> = OnceLock::new();
    SHAPES.get_or_init(|| {
        pool_drawings()
            .iter()
            .map(|d| Shape::new(&d.strokes).expect("shape"))
            .collect()
    })
}

/// The labelled Latin drawings as shapes, once.
fn latin() -> &'static [pool::LabelledShape] {
    static LATIN: OnceLock<Vec<pool::LabelledShape>> = OnceLock::new();
    LATIN.get_or_init(|| {
        pool::labelled_shapes(&[shared().join("strokes")], &["Latin".to_string()]).expect("latin")
    })
}

#[test]
fn the_reader_reads_every_drawing_and_names_the_bad_line() {
    let d = pool_drawings();
    assert_eq!(d.len(), 30_558);
    let mut ids: Vec<&str> = d.iter().map(|x| x.id.as_str()).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), d.len(), "ids are unique");
    // The README: every drawing re-centred on the bounding-box centre (52.5, -52.5).
    for x in &d[..500] {
        let pts = || x.strokes.iter().flatten();
        let (x0, x1) = pts().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
        let (y0, y1) = pts().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.y), b.max(p.y)));
        assert!(((x0 + x1) / 2.0 - 52.5).abs() < 0.1, "{}: x centre", x.id);
        assert!(((y0 + y1) / 2.0 + 52.5).abs() < 0.1, "{}: y centre", x.id);
        assert!(x.strokes.iter().all(|s| !s.is_empty()));
    }
    let text = "{\"id\":\"a\",\"strokes\":[[[1,2]]]}\n{\"id\":\"b\",\"strokes\":[[[1]]]}\n";
    match pool::parse_pool(text, Path::new("x.jsonl")) {
        Err(ReadPoolError::Json { line, .. }) => assert_eq!(line, 2),
        other => panic!("expected a JSON error on line 2, got {other:?}"),
    }
    let empty = "{\"id\":\"a\",\"strokes\":[[]]}\n";
    assert!(matches!(
        pool::parse_pool(empty, Path::new("x.jsonl")),
        Err(ReadPoolError::Empty { line: 1, .. })
    ));
}

#[test]
fn pool_drawings_convert_through_the_robot_pipeline() {
    let d = &pool_drawings()[..120];
    let strokes: Vec<&[_]> = d.iter().map(|x| &x.strokes[..]).collect();
    let (out, report) = pool::convert_pool(&strokes, &Geometry::default()).expect("convert");
    assert_eq!(out.len(), 120);
    assert_eq!(
        report.converted + report.ik_failures + report.other_failures,
        120
    );
    assert!(report.converted >= 118, "{report:?}");
    // Every converted plan draws: its tool channel is down somewhere and up somewhere.
    for x in out.iter().flatten() {
        let tool = guardian_shared::trajectory::TOOL;
        assert!(x.iter().any(|w| w[tool] > 0.5) && x.iter().any(|w| w[tool] < 0.5));
    }
}

#[test]
fn copies_of_labelled_drawings_are_found() {
    let lat = latin();
    assert_eq!(lat.len(), 26 * 20);
    let rule = pool::CopyRule::default();
    let found = pool::find_copies(pool_shapes(), lat, &rule);
    let copies = found.is_copy.iter().filter(|&&c| c).count();
    let per = &found.per_labelled;
    eprintln!("Latin: {copies} copies; labelled drawings with 0, 1, 2.. copies: {per:?}");
    assert_eq!(found.per_alphabet.get("Latin"), Some(&copies));
    // Most labelled drawings are in the pool exactly once (measured 2026-12-02: 421 of 520;
    // 52 have none, and simple letters, lines and circles also match look-alikes of other
    // alphabets, which the rule removes with them).
    assert!(
        per.get(1).copied().unwrap_or(0) >= lat.len() * 3 / 4,
        "{per:?}"
    );
    assert!(per[0] <= lat.len() / 8, "{per:?}");
    // Few labelled drawings have more than two copies (measured: 23).
    assert!(
        per.iter().skip(3).sum::<usize>() <= lat.len() / 16,
        "{per:?}"
    );
    // A copy is much nearer to its original than to any other drawer's drawing of the same
    // character, except simple shapes (straight strokes drawn alike by several drawers).
    let (mut checked, mut apart) = (0, 0);
    for (i, n) in found.nearest.iter().enumerate() {
        let Some((l, d, _)) = *n else { continue };
        if d > 0.01 || checked >= 50 {
            continue;
        }
        let same_class_other = lat
            .iter()
            .enumerate()
            .filter(|(j, s)| *j != l && s.class == lat[l].class)
            .filter_map(|(_, s)| pool_shapes()[i].distance(&s.shape))
            .fold(f32::MAX, f32::min);
        apart += usize::from(same_class_other > 2.0 * d);
        checked += 1;
    }
    // Measured: 38 of the first 50 copies nearer than 0.01.
    assert!(apart >= 35, "{apart} of {checked}");
    assert_eq!(checked, 50);
}

/// A pool of the copies of eight Latin characters (160 drawings, 20 per character), with
/// the character of each (for checking pseudo-labels), converted once.
fn latin_copies_pool() -> &'static (Dataset, Vec<String>) {
    static POOL: OnceLock<(Dataset, Vec<String>)> = OnceLock::new();
    POOL.get_or_init(|| {
        let lat = latin();
        let mut classes: Vec<&str> = lat.iter().map(|s| s.class.as_str()).collect();
        classes.dedup();
        classes.truncate(8);
        let near = pool::nearest_labelled(pool_shapes(), lat);
        let mut picked = Vec::new();
        let mut truth = Vec::new();
        for (i, n) in near.iter().enumerate() {
            if let Some((l, d, d2)) = n
                && pool::CopyRule::default().is_copy(*d, *d2)
                && classes.contains(&lat[*l].class.as_str())
            {
                picked.push(i);
                truth.push(lat[*l].class.clone());
            }
        }
        let strokes: Vec<&[_]> = picked
            .iter()
            .map(|&i| &pool_drawings()[i].strokes[..])
            .collect();
        let (out, report) = pool::convert_pool(&strokes, &Geometry::default()).expect("convert");
        assert_eq!(report.converted, picked.len());
        let n = picked.len();
        let data = Dataset {
            trajectories: out.into_iter().map(|r| r.expect("converted")).collect(),
            labels: vec![0; n],
            alphabet_ids: vec![0; n],
            drawer_ids: picked.iter().map(|&i| i as i64).collect(),
            classes: vec!["unlabelled/pool".into()],
            alphabets: vec!["unlabelled".into()],
            geometry: Geometry::default(),
            generator: "test".into(),
            robot: guardian_models::kinematics::RobotRecord::panda(),
        };
        (data, truth)
    })
}

#[test]
fn pseudo_labels_of_real_copies_recover_their_characters() {
    let (data, truth) = latin_copies_pool();
    assert!(data.len() >= 140, "{} copies", data.len());
    let model = Embedder::load(&repo().join("models/embedder.safetensors")).expect("model");
    let (groups, stats) =
        pool::pseudo_labels(&model, data, &ClusterParams::default()).expect("cluster");
    eprintln!("{stats:?}");
    assert!(groups.len() >= 5, "{} clusters", groups.len());
    assert!(groups.iter().all(|g| g.len() >= 4 && g.len() <= 40));
    // Purity: most members of a cluster are drawings of one character.
    let (mut majority, mut total) = (0, 0);
    for g in &groups {
        let mut count: BTreeMap<&str, usize> = BTreeMap::new();
        for &i in g {
            *count.entry(truth[i].as_str()).or_default() += 1;
        }
        majority += count.values().max().copied().unwrap_or(0);
        total += g.len();
    }
    assert!(
        majority as f64 >= 0.9 * total as f64,
        "purity {majority}/{total}"
    );
}

/// Five Latin and five Greek characters, 20 drawers each.
fn small_labelled() -> &'static Dataset {
    static DATA: OnceLock<Dataset> = OnceLock::new();
    DATA.get_or_init(|| {
        let all = scan(&[shared().join("strokes")]).expect("strokes");
        let mut files = Vec::new();
        for alphabet in ["Latin", "Greek"] {
            let mut classes: Vec<String> = all
                .iter()
                .filter(|f| f.alphabet == alphabet)
                .map(|f| f.class_name())
                .collect();
            classes.dedup();
            classes.truncate(5);
            files.extend(
                all.iter()
                    .filter(|f| classes.contains(&f.class_name()))
                    .cloned(),
            );
        }
        generate_files(&files, &Geometry::default(), &|| {})
            .expect("generate")
            .0
    })
}

#[test]
fn batches_draw_their_share_of_pool_classes_and_pool_samples_get_no_faults() {
    let data = small_labelled();
    let (pool_data, _) = latin_copies_pool();
    let mut set = Prepared::new(data, &["Latin".to_string()], FeatureKind::Pen).expect("prep");
    let labelled = set.classes();
    let groups: Vec<Vec<usize>> = (0..pool_data.len()).map(|i| vec![i, i]).collect();
    let added = set.add_pool(pool_data, &groups, 0.5).expect("pool");
    assert_eq!(added, pool_data.len());
    assert_eq!(set.pool_classes(), added);
    // Class augmentation after the pool is refused (pool classes are not augmented).
    assert!(
        set.augment_classes(guardian_lab::classaug::SymmetryRule { quantile: 0.1 })
            .is_err()
    );
    let made = set
        .make_faults(data, &shared().join("strokes"), &train::TRAIN_FAULTS, 1, 3)
        .expect("faults");
    assert!(made > 0);
    for i in 0..set.len() {
        let is_pool = set.labels()[i] as usize >= labelled;
        assert!(
            !is_pool || set.faults_of(i) == 0,
            "pool sample {i} has faults"
        );
    }
    let mut rng = StdRng::seed_from_u64(4);
    for _ in 0..20 {
        let (idx, labels) = set.sample_pk(6, 4, &mut rng);
        let mut pool_classes: Vec<u32> = labels
            .iter()
            .copied()
            .filter(|&l| l as usize >= labelled)
            .collect();
        pool_classes.dedup();
        assert_eq!(pool_classes.len(), 3, "{labels:?}");
        let mut lab: Vec<u32> = labels
            .iter()
            .copied()
            .filter(|&l| (l as usize) < labelled)
            .collect();
        lab.dedup();
        assert_eq!(lab.len(), 3);
        // SSL: a pool class is one drawing twice.
        for w in idx.windows(2) {
            if set.labels()[w[0]] as usize >= labelled && set.labels()[w[0]] == set.labels()[w[1]] {
                assert_eq!(set.raw()[w[0]], set.raw()[w[1]]);
            }
        }
        let (items, _) = set.with_faults(&idx, &labels, 1.0, &mut rng);
        assert!(items.len() > idx.len());
    }
}

/// The pool tests' training: the pipeline tests' tiny configuration with batch-all, one
/// short epoch and fewer validation episodes.
fn tiny_config() -> TrainConfig {
    TrainConfig {
        loss: LossKind::BatchAll,
        steps_per_epoch: 4,
        max_epochs: 1,
        val_episodes: 20,
        ..common::tiny_config()
    }
}

#[test]
fn training_runs_with_ssl_and_pseudo_label_pool_classes() {
    let data = small_labelled();
    let (pool_data, _) = latin_copies_pool();
    let dir = tempfile::tempdir().expect("tempdir");
    let pool_path = dir.path().join("pool.safetensors");
    let info = pool::PoolInfo {
        drawings_read: pool_data.len(),
        excluded_alphabets: vec!["Greek".into()],
        copies_removed: BTreeMap::from([("Greek".into(), 0)]),
        copy_rule: pool::CopyRule::default(),
        conversion_failures: 0,
    };
    pool::save_pool(pool_data, &info, &pool_path).expect("save");
    // The pool file is a dataset file that records what was left out.
    assert_eq!(&Dataset::load(&pool_path).expect("load"), pool_data);
    let bytes = std::fs::read(&pool_path).expect("read");
    assert_eq!(pool::pool_info(&bytes), Some(info));

    let mut cfg = tiny_config();
    cfg.pool_mode = PoolMode::Ssl;
    cfg.pool = Some(pool_path.clone());
    cfg.pool_share = 0.5;
    let out = dir.path().join("ssl");
    let s = train::train(data, &cfg, None, &out, false, true).expect("ssl train");
    assert_eq!(s.epochs, 1);
    assert!(s.best_val_loss.is_finite());
    // The run's configuration resumes; another pool share does not.
    cfg.max_epochs = 2;
    assert_eq!(
        train::train(data, &cfg, None, &out, true, true)
            .expect("resume")
            .epochs,
        2
    );
    let mut other = cfg.clone();
    other.pool_share = 0.25;
    assert!(train::train(data, &other, None, &out, true, true).is_err());

    let mut cfg = tiny_config();
    cfg.pool_mode = PoolMode::Pseudo;
    cfg.pool = Some(pool_path);
    cfg.pool_share = 0.5;
    cfg.pseudo_model = Some(repo().join("models/embedder.safetensors"));
    cfg.pseudo_clusters = Some(ClusterParams::default());
    let out = dir.path().join("pseudo");
    let s = train::train(data, &cfg, None, &out, false, true).expect("pseudo train");
    assert_eq!(s.epochs, 1);
    let classes: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("pool-classes.json")).expect("pool-classes.json"),
    )
    .expect("json");
    assert!(classes["groups"].as_array().is_some_and(|g| g.len() >= 5));
    // Without a model, pseudo-labels are refused.
    cfg.pseudo_model = None;
    assert!(train::train(data, &cfg, None, &dir.path().join("x"), false, true).is_err());
}

#[test]
fn old_training_configurations_still_parse_without_pool() {
    let text = std::fs::read_to_string(repo().join("docs/report/train-config.json"))
        .expect("shipped train-config.json");
    let cfg: TrainConfig = serde_json::from_str(&text).expect("parse");
    assert_eq!(cfg.pool_mode, PoolMode::None);
    assert_eq!(cfg.pool, None);
    assert_eq!(cfg.pool_share, 0.0);
}
