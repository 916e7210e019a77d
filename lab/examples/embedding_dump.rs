//! The embeddings of one alphabet's drawings by a model, as the plans are and under random
//! augmentations of the pen path (the training augmentations' rotation, shear and scales,
//! seed 7), for `docs/report/posthoc-levers.py`.
//!
//! Usage: `embedding_dump DATASET MODEL ALPHABET OUT AUGMENTATIONS` — OUT is text: a header
//! `samples dim augmentations`, then one line per augmentation and sample: `augmentation
//! label e_0 … e_dim-1` (augmentation 0 is the plan as it is).
use std::io::Write;

use guardian_lab::dataset::Dataset;
use guardian_lab::eval::Pool;
use guardian_models::embedder::{EMBED_DIM, Embedder};
use guardian_models::features::pen_path_with;
use guardian_shared::trajectory::Resampled;
use rand::{Rng, SeedableRng};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        args.len() == 6,
        "usage: embedding_dump DATASET MODEL ALPHABET OUT AUGMENTATIONS"
    );
    let data = Dataset::load(args[1].as_ref())?;
    let model = Embedder::load(args[2].as_ref())?;
    let pool = Pool::new(&data, &[args[3].clone()])?;
    let augmentations: usize = args[5].parse()?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let mut out = std::io::BufWriter::new(std::fs::File::create(&args[4])?);
    writeln!(out, "{} {} {}", pool.xs.len(), EMBED_DIM, augmentations)?;
    let robot = &pool.robot;
    for k in 0..augmentations {
        let (r, shear, sx, sy): (f32, f32, f32, f32) = if k == 0 {
            (0.0, 0.0, 1.0, 1.0)
        } else {
            (
                rng.random_range(-0.2..0.2),
                rng.random_range(-0.2..0.2),
                rng.random_range(0.85..1.15),
                rng.random_range(0.85..1.15),
            )
        };
        let map = |x: &Resampled| {
            let mut p = pen_path_with(robot, x);
            let (c, s) = (r.cos(), r.sin());
            for q in p.iter_mut() {
                let (x, y) = (c * q[0] - s * q[1], s * q[0] + c * q[1]);
                q[0] = (x + shear * y) * sx;
                q[1] = y * sy;
            }
            p
        };
        let mut emb = vec![[0.0f32; EMBED_DIM]; pool.xs.len()];
        model.embed_into_mapped(robot, &pool.xs, &mut emb, map)?;
        for (e, l) in emb.iter().zip(&pool.labels) {
            let values: Vec<String> = e.iter().map(|v| v.to_string()).collect();
            writeln!(out, "{k} {l} {}", values.join(" "))?;
        }
    }
    Ok(())
}
