//! Real Omniglot drawings (the shared stroke files, converted to dense Panda joint paths by
//! the dataset library) sent through a real `guardiand`: the daemon must preprocess and
//! embed them exactly as the lab does.

use guardian_robot::kinematics::PANDA_JOINTS;
use std::path::PathBuf;

use guardian_bank::distance;
use guardian_client::Trajectory;
use guardian_models::embedder::Embedder;
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::{character_files, read_strokes};
use guardian_tests::harness;
use guardian_tests::harness::{Daemon, Setup};

fn strokes_dir() -> PathBuf {
    harness::workspace_root().join("../shared/omniglot/strokes")
}

/// Drawing `drawer` (1-based) of `Latin/characterNN`.
fn drawing(character: u32, drawer: u32) -> PathBuf {
    character_files(&strokes_dir(), "Latin", character).expect("character folder")
        [drawer as usize - 1]
        .clone()
}

#[test]
fn real_drawings_are_embedded_exactly_as_the_lab_does() {
    let mut s = Setup::new(21);
    s.extra = "default-threshold = 1e9\nk-nearest = 3".into();
    let _d = Daemon::start(&s);
    let client = s.client();
    let solver = PathSolver::new(&Geometry::default()).expect("solver");
    let embedder = Embedder::load(&s.model).expect("model");

    // Enroll three Latin characters from drawers 1..=4 each.
    let mut prototypes = Vec::new();
    for c in 1..=3u32 {
        let mut examples = Vec::new();
        let mut embs = Vec::new();
        for d in 1..=4 {
            let conv = convert_strokes(&solver, &read_strokes(&drawing(c, d)).unwrap()).unwrap();
            embs.push(
                embedder
                    .embed(guardian_robot::kinematics::default_panda(), &conv.sample)
                    .unwrap()
                    .to_vec(),
            );
            examples.push(Trajectory::from_waypoints(
                &conv.dense.waypoints,
                PANDA_JOINTS,
            ));
        }
        client
            .enroll(&format!("latin{c}"), &examples)
            .expect("enroll");
        let dim = embs[0].len();
        let proto: Vec<f32> = (0..dim)
            .map(|i| (embs.iter().map(|e| f64::from(e[i])).sum::<f64>() / embs.len() as f64) as f32)
            .collect();
        prototypes.push(proto);
    }

    // An unseen drawer: the daemon's distances equal the lab's (same preprocessing, same
    // model), and its verdict follows the decision rule on them.
    for c in 1..=3u32 {
        let conv = convert_strokes(&solver, &read_strokes(&drawing(c, 10)).unwrap()).unwrap();
        let e = embedder
            .embed(guardian_robot::kinematics::default_panda(), &conv.sample)
            .unwrap();
        let t = Trajectory::from_waypoints(&conv.dense.waypoints, PANDA_JOINTS);
        let v = client.check(&t, &format!("latin{c}")).expect("check");
        let expected = distance(&e, &prototypes[c as usize - 1]);
        let got = v.claimed_distance.expect("distance");
        assert!(
            (got - expected).abs() <= 1e-4 * expected.max(1.0),
            "latin{c}: daemon {got}, lab {expected}"
        );
        let nearest = &v.nearest[0].class;
        if *nearest == format!("latin{c}") {
            assert!(v.is_go(), "{v:?}");
        } else {
            assert!(!v.is_go(), "{v:?}");
        }
    }
}
