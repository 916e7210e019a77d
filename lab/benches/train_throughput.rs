//! Training throughput of the embedding network: samples/s and mined triplets/s for the
//! default architecture and P x K batches, with forward / backward / optimiser time split.
//! Data: a slice of the real shared Omniglot set converted through the dataset generator.
//!
//! `RAYON_NUM_THREADS=2 cargo bench -p guardian-lab --bench train_throughput`
//! (compare with the guide's PyTorch figure, ~770 triplets/s on 2 threads).

use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Var};
use guardian_lab::dataset::generate_files;
use guardian_lab::path::Geometry;
use guardian_lab::strokes::scan;
use guardian_lab::train::{AdamW, LossKind, Prepared, batch_loss};
use guardian_models::features::FeatureKind;
use guardian_models::net::{Net, NetConfig};
use rand::SeedableRng;
use rand::rngs::StdRng;

fn main() -> anyhow::Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/omniglot/strokes");
    let files: Vec<_> = scan(&[root])?
        .into_iter()
        .filter(|f| f.alphabet == "Latin")
        .collect();
    let (data, _) = generate_files(&files, &Geometry::default(), &|| {})?;
    let set = Prepared::new(&data, &["Latin".to_string()], FeatureKind::Pen)?;
    let steps: usize = std::env::var("BENCH_STEPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(30);
    for (loss, p, k) in [
        (LossKind::BatchAll, 16, 4),
        (LossKind::BatchHard, 16, 4),
        (LossKind::Triplet, 16, 4),
    ] {
        let mut config = NetConfig::default();
        if let Ok(c) = std::env::var("BENCH_CHANNELS") {
            config.channels = c.split(',').filter_map(|v| v.parse().ok()).collect();
        }
        let net = Net::random(config.clone(), 1, DType::F32)?;
        let vars: Vec<Var> = net
            .params()
            .iter()
            .map(Var::from_tensor)
            .collect::<Result<_, _>>()?;
        let net = Net::new(config, vars.iter().map(|v| v.as_tensor().clone()).collect())?;
        let mut opt = AdamW::new(vars, 1e-4)?;
        let mut rng = StdRng::seed_from_u64(1);
        let (mut t_data, mut t_fwd, mut t_bwd, mut t_opt) = (0.0, 0.0, 0.0, 0.0);
        let (mut samples, mut triplets) = (0usize, 0usize);
        for step in 0..steps + 3 {
            let t0 = Instant::now();
            let (idx, labels) = set.sample_pk(p, k, &mut rng);
            let x = set.batch(&idx, Some(&mut rng))?;
            let t1 = Instant::now();
            let (l, _, n) = batch_loss(&net, &x, &labels, loss, 0.2, &mut rng)?;
            let _ = l.to_scalar::<f32>()?;
            let t2 = Instant::now();
            let grads = l.backward()?;
            let t3 = Instant::now();
            opt.step(&grads, 1e-3)?;
            let t4 = Instant::now();
            if step >= 3 {
                t_data += (t1 - t0).as_secs_f64();
                t_fwd += (t2 - t1).as_secs_f64();
                t_bwd += (t3 - t2).as_secs_f64();
                t_opt += (t4 - t3).as_secs_f64();
                samples += idx.len();
                triplets += n;
            }
        }
        let total = t_data + t_fwd + t_bwd + t_opt;
        println!(
            "{loss:?} P{p}xK{k} channels {:?}: {:.0} samples/s, {:.0} triplets/s (one per anchor: {:.0}/s); per step data {:.1} ms, forward {:.1} ms, backward {:.1} ms, optimiser {:.1} ms; {} rayon threads",
            net.config().channels,
            samples as f64 / total,
            triplets as f64 / total,
            samples as f64 / total,
            1e3 * t_data / steps as f64,
            1e3 * t_fwd / steps as f64,
            1e3 * t_bwd / steps as f64,
            1e3 * t_opt / steps as f64,
            rayon::current_num_threads()
        );
    }
    Ok(())
}
