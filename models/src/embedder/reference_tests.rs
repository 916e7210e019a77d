//! The embedder's fast path against candle's forward pass of the same weights (feature
//! `train`, on in the workspace's test run).

use super::*;
use crate::sequence::forward::tests::rel_err;
use guardian_shared::trajectory::{SLOTS, TOOL};
use rand::{Rng, SeedableRng};

/// Random joint trajectories inside the limits with pen-down runs.
fn trajectories(n: usize, seed: u64) -> Vec<Resampled> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let phase: [f32; 7] = std::array::from_fn(|_| rng.random_range(0.0..6.0));
            let amp: [f32; 7] = std::array::from_fn(|_| rng.random_range(0.0..0.3));
            let mut x = [[0.0f32; SLOTS]; STEPS];
            let centre = [0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.78];
            for (t, w) in x.iter_mut().enumerate() {
                let s = t as f32 / STEPS as f32;
                for j in 0..7 {
                    w[j] = centre[j] + amp[j] * (6.0 * s + phase[j]).sin();
                }
                w[TOOL] = if (t / 20) % 2 == 0 { 1.0 } else { 0.0 };
            }
            x
        })
        .collect()
}

/// The shipped model when it exists, else random weights of the default architecture.
fn shipped_or_random() -> Embedder {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("embedder.safetensors");
    if path.exists() {
        Embedder::load(&path).expect("the shipped model loads")
    } else {
        Embedder::random(11)
    }
}

#[test]
fn embedder_fast_path_matches_candle_reference() {
    let mut embedders = vec![shipped_or_random(), Embedder::random(4)];
    let mut rev = Embedder::random(5);
    rev.set_reverse_average(true);
    embedders.push(rev);
    for config in [
        NetConfig {
            features: FeatureKind::Joints,
            ..NetConfig::default()
        },
        NetConfig {
            features: FeatureKind::Pen,
            ..NetConfig::default()
        },
    ] {
        embedders.push(Embedder::random_with(config, 9).unwrap());
    }
    let mut seq = Embedder::random_with(
        NetConfig {
            embed_dim: EMBED_DIM / 2,
            reverse_average: true,
            ..NetConfig::default()
        },
        12,
    )
    .unwrap();
    seq.set_reverse_average(true);
    let pic = Embedder::random_with(
        NetConfig {
            features: FeatureKind::Picture,
            channels: vec![8, 16],
            kernel: 3,
            embed_dim: EMBED_DIM / 2,
            ..NetConfig::default()
        },
        13,
    )
    .unwrap();
    embedders.push(Embedder::fuse(&[seq, pic]).unwrap());
    // Test-time views on both branches, the sequence's reversed too.
    let mut viewed = embedders.last().unwrap().clone();
    viewed
        .set_test_views(&["r100".parse().unwrap(), "s-80+x60".parse().unwrap()])
        .unwrap();
    embedders.push(viewed);
    let xs = trajectories(5, 2);
    for (i, e) in embedders.iter().enumerate() {
        let want = e
            .embed_batch_reference(guardian_robot::kinematics::default_panda(), &xs)
            .unwrap();
        let got = e
            .embed_batch(guardian_robot::kinematics::default_panda(), &xs)
            .unwrap();
        for (k, (g, w)) in got.iter().zip(&want).enumerate() {
            let err = rel_err(g, w);
            assert!(
                err <= 1e-5,
                "embedder {i} input {k}: relative error {err:e}"
            );
        }
        // Batch 1 through `embed` gives the same as the batched fast path.
        let one = e
            .embed(guardian_robot::kinematics::default_panda(), &xs[3])
            .unwrap();
        assert!(rel_err(&one, &got[3]) <= 1e-6);
    }
}
