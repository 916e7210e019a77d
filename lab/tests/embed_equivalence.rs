//! The serving path with the specialised pen-tip FK (`kinematics::PositionFk`, block sines
//! and cosines, per-thread buffers) against the path as it was before it (general chain with
//! full frames, `preprocess_reference` + `Embedder::embed_reference`), on real Omniglot
//! plans converted by the dataset library: pen-tip positions agree to 1e-12 m, the resampled
//! input is the same, and embeddings with the shipped model agree to 1e-5 relative, so the
//! shipped `models/embedder.safetensors` and `models/default-bank.gcb` stay valid.

use std::path::{Path, PathBuf};

use guardian_models::embedder::Embedder;
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::{read_strokes, scan};
use guardian_robot::kinematics::{default_panda, joints_of};
use guardian_robot::preprocess::{
    pen_path_lengths, pen_path_lengths_reference, preprocess, preprocess_reference,
};
use guardian_shared::trajectory::Waypoint;

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Dense joint plans of the first `per_alphabet` drawings of every shared alphabet.
fn real_plans(per_alphabet: usize) -> Vec<Vec<Waypoint>> {
    let files = scan(&[workspace_root().join("../shared/omniglot/strokes")]).expect("strokes");
    let solver = PathSolver::new(&Geometry::default()).expect("solver");
    let mut plans = Vec::new();
    for group in files.chunk_by(|a, b| a.alphabet == b.alphabet) {
        // Spread over characters and drawers: every 7th file of the alphabet.
        for f in group.iter().step_by(7).take(per_alphabet) {
            let strokes = read_strokes(&f.path).expect("read");
            let c = convert_strokes(&solver, &strokes).expect("convert");
            plans.push(c.dense.waypoints);
        }
    }
    assert!(
        plans.len() >= 6 * per_alphabet.min(3),
        "{} plans",
        plans.len()
    );
    plans
}

fn shipped_or_random() -> Embedder {
    let path = workspace_root().join("models/embedder.safetensors");
    if path.exists() {
        Embedder::load(&path).expect("shipped model loads")
    } else {
        let mut e = Embedder::random(3);
        e.set_reverse_average(true);
        e
    }
}

#[test]
fn specialised_fk_matches_the_general_chain_on_real_plans() {
    let panda = default_panda();
    assert!(panda.position_fk().is_some());
    let mut worst = 0.0f64;
    let mut worst_len = 0.0f64;
    for plan in real_plans(8) {
        let mut out = vec![[0.0; 3]; plan.len()];
        panda.pen_tip_positions_into(&plan, &mut out);
        for (w, p) in plan.iter().zip(&out) {
            let general = panda.pen_tip_position_general(&joints_of(w));
            let d = ((p[0] - general.x).powi(2)
                + (p[1] - general.y).powi(2)
                + (p[2] - general.z).powi(2))
            .sqrt();
            worst = worst.max(d);
        }
        let fast = pen_path_lengths(&plan);
        let reference = pen_path_lengths_reference(panda, &plan);
        for (a, b) in fast.iter().zip(&reference) {
            worst_len = worst_len.max((a - b).abs());
        }
    }
    eprintln!("worst pen-tip difference {worst:e} m, path length {worst_len:e} m");
    assert!(worst <= 1e-12, "worst pen-tip difference {worst:e} m");
    assert!(
        worst_len <= 1e-10,
        "worst path-length difference {worst_len:e} m"
    );
}

#[test]
fn embeddings_of_real_plans_do_not_change() {
    let embedder = shipped_or_random();
    let panda = default_panda();
    let mut worst_input = 0.0f32;
    let mut worst_rel = 0.0f32;
    let plans = real_plans(8);
    for plan in &plans {
        let x = preprocess(plan).expect("valid plan");
        let x_ref = preprocess_reference(panda, plan).expect("valid plan");
        for (a, b) in x.iter().flatten().zip(x_ref.iter().flatten()) {
            worst_input = worst_input.max((a - b).abs());
        }
        let e = embedder.embed(panda, &x).expect("embed");
        let e_ref = embedder
            .embed_reference(panda, &x_ref)
            .expect("embed reference");
        let diff: f32 = e
            .iter()
            .zip(&e_ref)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f32>()
            .sqrt();
        let norm: f32 = e_ref.iter().map(|v| v * v).sum::<f32>().sqrt();
        worst_rel = worst_rel.max(diff / norm);
    }
    eprintln!(
        "{} plans: worst input difference {worst_input:e} rad, embedding {worst_rel:e} relative",
        plans.len()
    );
    // Resampling positions may move by a few 1e-16 m of path length: at most a rounding
    // step of an f32 joint value.
    assert!(
        worst_input <= 1e-6,
        "worst input difference {worst_input:e} rad"
    );
    assert!(
        worst_rel <= 1e-5,
        "worst relative embedding difference {worst_rel:e} over {} plans",
        plans.len()
    );
}
