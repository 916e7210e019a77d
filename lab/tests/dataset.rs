//! Dataset generation on real shared drawings: shapes, determinism, pen-down samples for
//! every stroke, the character survives (FK of the samples lies on the strokes), the file
//! round trip, and the whole shared set converting with no IK failure.

use std::path::{Path, PathBuf};

use guardian_omniglot::dataset::{
    ConvertError, Dataset, LoadDatasetError, convert_strokes, generate, generate_files,
};
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::{DrawingFile, Point, Stroke, read_strokes, scan};
use guardian_robot::kinematics::joints_of;
use guardian_shared::trajectory::{InvalidKind, MAX_WAYPOINTS, SLOTS, STEPS, TOOL};
use nalgebra::Vector3;

/// `<workspace root>/../shared/omniglot/strokes`.
fn shared_strokes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/omniglot/strokes")
}

/// A few drawings per alphabet: the first three files of each, plus up to three drawings
/// with dots (one-point strokes).
fn few_per_alphabet() -> Vec<DrawingFile> {
    let all = scan(&[shared_strokes()]).expect("shared strokes");
    let mut picked: Vec<DrawingFile> = Vec::new();
    for group in all.chunk_by(|a, b| a.alphabet == b.alphabet) {
        picked.extend(group.iter().take(3).cloned());
    }
    let dotted = all
        .iter()
        .filter(|f| !picked.contains(f))
        .filter(|f| read_strokes(&f.path).is_ok_and(|s| s.iter().any(|s| s.len() == 1)))
        .take(3)
        .cloned()
        .collect::<Vec<_>>();
    picked.extend(dotted);
    picked.sort();
    picked
}

fn pen_down_runs(sample: &[[f32; SLOTS]]) -> usize {
    let mut runs = 0;
    let mut prev = 0.0;
    for s in sample {
        if s[TOOL] == 1.0 && prev != 1.0 {
            runs += 1;
        }
        prev = s[TOOL];
    }
    runs
}

/// Distance from `p` to the polyline of the stroke on the canvas.
fn distance_to_strokes(p: &Vector3<f64>, strokes: &[Stroke], g: &Geometry) -> f64 {
    let mut best = f64::INFINITY;
    for s in strokes {
        let pts: Vec<Vector3<f64>> = s.iter().map(|q| g.motor_to_base(q.x, q.y)).collect();
        best = best.min((p - pts[0]).norm());
        for w in pts.windows(2) {
            let d = w[1] - w[0];
            let t = if d.norm_squared() > 0.0 {
                ((p - w[0]).dot(&d) / d.norm_squared()).clamp(0.0, 1.0)
            } else {
                0.0
            };
            best = best.min((p - (w[0] + d * t)).norm());
        }
    }
    best
}

fn check_samples(ds: &Dataset, files: &[DrawingFile]) {
    let g = &ds.geometry;
    let panda = ds.robot().expect("the data set's robot loads");
    assert_eq!(ds.len(), files.len());
    for (i, f) in files.iter().enumerate() {
        let strokes = read_strokes(&f.path).expect("read");
        let sample = &ds.trajectories[i];
        assert_eq!(
            pen_down_runs(sample),
            strokes.len(),
            "{}: one pen-down run per stroke",
            f.path.display()
        );
        for s in sample.iter().filter(|s| s[TOOL] == 1.0) {
            let p = panda.pen_tip_position(&joints_of(s));
            assert!(
                (p.z - g.canvas_z).abs() < 1e-4,
                "{}: pen-down off the canvas",
                f.path.display()
            );
            let d = distance_to_strokes(&p, &strokes, g);
            assert!(
                d < 2e-4,
                "{}: pen-down sample {d} m from the strokes",
                f.path.display()
            );
        }
        for s in sample.iter().filter(|s| s[TOOL] == 0.0) {
            let p = panda.pen_tip_position(&joints_of(s));
            assert!(p.z > g.canvas_z - 1e-4, "pen-up sample below the canvas");
        }
        assert_eq!(ds.classes[ds.labels[i] as usize], f.class_name());
        assert_eq!(ds.alphabets[ds.alphabet_ids[i] as usize], f.alphabet);
        assert_eq!(ds.drawer_ids[i], i64::from(f.drawer));
    }
}

#[test]
fn a_few_drawings_per_alphabet_convert_deterministically() {
    let files = few_per_alphabet();
    let g = Geometry::default();
    let (ds, report) = generate_files(&files, &g, &|| {}).expect("generate");
    assert_eq!(report.files, files.len());
    assert_eq!(
        report.converted,
        files.len(),
        "skipped: {:?}",
        report.skipped
    );
    assert_eq!(report.ik_failures, 0);
    assert!(report.max_fk_error <= 1e-4, "{}", report.max_fk_error);
    assert!(report.min_limit_margin > 0.0);
    assert_eq!(ds.trajectories[0].len(), STEPS);
    assert_eq!(ds.alphabets.len(), 6);
    check_samples(&ds, &files);

    // Same input -> byte-identical file.
    let bytes = ds.to_bytes().expect("bytes");
    let (again, _) = generate_files(&files, &g, &|| {}).expect("generate again");
    assert_eq!(bytes, again.to_bytes().expect("bytes"));

    // File round trip, readable by the safetensors crate with the agreed names and shapes.
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("few.safetensors");
    ds.save(&path).expect("save");
    assert_eq!(std::fs::read(&path).expect("read"), bytes);
    assert_eq!(Dataset::load(&path).expect("load"), ds);
    let st = safetensors::SafeTensors::deserialize(&bytes).expect("safetensors");
    let n = files.len();
    assert_eq!(st.tensor("trajectories").expect("t").shape(), [n, STEPS, 8]);
    assert_eq!(
        st.tensor("trajectories").expect("t").dtype(),
        safetensors::Dtype::F32
    );
    for name in ["labels", "alphabet_ids", "drawer_ids"] {
        let t = st.tensor(name).expect(name);
        assert_eq!((t.shape(), t.dtype()), (&[n][..], safetensors::Dtype::I64));
    }
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).expect("metadata");
    let meta = meta.metadata().clone().expect("__metadata__");
    let geometry: Geometry = serde_json::from_str(&meta["geometry"]).expect("geometry json");
    assert_eq!(geometry, g);
    assert!(meta["generator"].starts_with("guardian-lab "));
    let classes: Vec<String> = serde_json::from_str(&meta["classes"]).expect("classes json");
    assert_eq!(classes, ds.classes);

    // A truncated file is a typed error.
    assert!(matches!(
        Dataset::from_bytes(&bytes[..bytes.len() - 4]),
        Err(LoadDatasetError::Format(_))
    ));
}

/// Both shipped robots draw every shared drawing: no IK failure, FK error <= 0.1 mm, no
/// joint-limit violation, every pen-down sample on the canvas and on the strokes.
#[test]
fn the_whole_shared_set_converts_without_ik_failure_for_both_robots() {
    let files = scan(&[shared_strokes()]).expect("scan");
    for robot in ["panda", "ur5e"] {
        let g = Geometry::for_robot(robot).expect("geometry");
        let (ds, report) = generate(&[shared_strokes()], &g, &|| {}).expect("generate");
        assert_eq!(report.files, 3660);
        assert_eq!(
            report.converted, 3660,
            "{robot}: skipped: {:?}",
            report.skipped
        );
        assert_eq!(report.ik_failures, 0);
        assert!(
            report.max_fk_error <= 1e-4,
            "{robot}: max FK error {} m",
            report.max_fk_error
        );
        assert!(
            report.min_limit_margin > 0.0,
            "{robot}: margin {}",
            report.min_limit_margin
        );
        assert_eq!(ds.classes.len(), 183);
        assert_eq!(ds.classes[0], "Balinese/character01");
        assert_eq!(ds.robot.name, robot);
        check_samples(&ds, &files);
        if robot == "ur5e" {
            // On disk: 6 joints + the tool; the file round-trips.
            let bytes = ds.to_bytes().expect("bytes");
            let st = safetensors::SafeTensors::deserialize(&bytes).expect("safetensors");
            assert_eq!(
                st.tensor("trajectories").expect("t").shape(),
                [3660, STEPS, 7]
            );
            assert_eq!(Dataset::from_bytes(&bytes).expect("load"), ds);
            assert_eq!(ds.robot().expect("robot").joints(), 6);
        }
    }
}

#[test]
fn very_long_drawings_are_widened_or_rejected() {
    let solver = PathSolver::new(&Geometry::default()).expect("home pose");
    // 40 strokes across the canvas: about 4 m of pen path, more than MAX_WAYPOINTS points at
    // the default spacing, so the spacing is widened.
    let zigzag: Stroke = (0..=40)
        .map(|i| Point {
            x: if i % 2 == 0 { 10.0 } else { 90.0 },
            y: -50.0,
            t: 0.0,
        })
        .collect();
    let c = convert_strokes(&solver, &[zigzag]).expect("widened path converts");
    assert!(c.dense.waypoints.len() <= MAX_WAYPOINTS);
    assert!(c.dense.waypoints.len() > MAX_WAYPOINTS / 2);
    // More distinct raw points than MAX_WAYPOINTS: rejected by the shared validation.
    let many: Stroke = (0..5000)
        .map(|i| Point {
            x: 10.0 + f64::from(i % 80),
            y: -20.0 - f64::from(i / 80) * 0.5,
            t: 0.0,
        })
        .collect();
    match convert_strokes(&solver, &[many]) {
        Err(ConvertError::Invalid(e)) => assert_eq!(e.kind, InvalidKind::TooManyWaypoints),
        other => panic!(
            "expected TooManyWaypoints, got {:?}",
            other.map(|c| c.dense.waypoints.len())
        ),
    }
}
