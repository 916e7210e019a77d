//! Training throughput of the embedding network: samples/s of one training step (forward +
//! loss + backward + optimiser; one sample = one embedding forward + backward + its share of
//! the optimiser) for the shipped architecture on batches of 16 classes x 4 real drawings,
//! with 1 and 2 threads:
//!
//! - guardian's training path (`guardian_models::sequence::backward`: hand-written backward on `gemm`,
//!   batch-all triplet loss in candle, AdamW over the flat weights);
//! - the previous path, candle autograd through `Net::forward` (forward + loss + backward;
//!   its optimiser is not timed), measured in the same run;
//! - when `python3 -c "import torch"` works, the same network, batches, loss and optimiser in
//!   PyTorch eager (`train_throughput.py` beside this file, fed the very same batches), and
//!   the ratio `training throughput ratio guardian/pytorch (2 threads): X`.
//!
//! Rounds alternate between the implementations so that each ratio compares figures taken
//! under the same load; the median round is reported.
//!
//! By default every network of the shipped model is measured, with its own architecture as
//! the model file records it (`models/embedder.safetensors`: today the sequence branch on pen
//! features, 32,64,128, kernel 5, and the picture branch, 16,32,64,128, kernel 3, each with
//! a 64-dimensional embedding); `BENCH_ARCH=pen,picture` measures the fourth session's
//! 128-dimensional networks instead (pen 32,64,128; picture 32,64,64,128).
//!
//! `cargo bench -p guardian-lab --bench train_throughput`
//! (`BENCH_STEPS` steps per round, default 40; `BENCH_ROUNDS`, default 3;
//! `BENCH_ARCH`, default `shipped`).

use std::io::Write as _;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use anyhow::Context as _;
use candle_core::{DType, Tensor, Var};
use guardian_lab::train::{Learner, LossKind, Prepared, batch_loss};
use guardian_models::embedder::Embedder;
use guardian_models::features::FeatureKind;
use guardian_models::net::{Net, NetConfig};
use guardian_models::sequence::forward::FastNet;
use guardian_omniglot::dataset::generate_files;
use guardian_omniglot::path::Geometry;
use guardian_omniglot::strokes::scan;
use rand::SeedableRng;
use rand::rngs::StdRng;

const MARGIN: f64 = 0.2;
const LR: f64 = 2e-3;
const WEIGHT_DECAY: f64 = 1e-4;

struct Batch {
    x: Tensor,
    labels: Vec<u32>,
}

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn pool(threads: usize) -> anyhow::Result<rayon::ThreadPool> {
    Ok(rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?)
}

/// guardian's training path: samples/s and the time split of one step (ms).
fn guardian(
    config: &NetConfig,
    batches: &[Batch],
    steps: usize,
    threads: usize,
) -> anyhow::Result<(f64, [f64; 2])> {
    pool(threads)?.install(|| {
        let mut learner = Learner::new(FastNet::random(config.clone(), 1)?, WEIGHT_DECAY);
        let mut rng = StdRng::seed_from_u64(1);
        let (mut samples, mut secs, mut loss_secs) = (0usize, 0.0, 0.0);
        for step in 0..steps + 3 {
            let b = &batches[step % batches.len()];
            let t0 = Instant::now();
            let mut t_loss = 0.0;
            learner.step(&b.x, LR, |e, _| {
                let t = Instant::now();
                let (l, _, _) =
                    batch_loss(e, &b.labels, LossKind::BatchAll, MARGIN, None, &mut rng)?;
                t_loss = t.elapsed().as_secs_f64();
                Ok((l, ()))
            })?;
            if step >= 3 {
                secs += t0.elapsed().as_secs_f64();
                loss_secs += t_loss;
                samples += b.labels.len();
            }
        }
        let per_step = 1e3 * secs / steps as f64;
        Ok((
            samples as f64 / secs,
            [per_step, 1e3 * loss_secs / steps as f64],
        ))
    })
}

/// The previous path: candle autograd through `Net::forward` (no optimiser).
fn candle_autograd(
    config: &NetConfig,
    batches: &[Batch],
    steps: usize,
    threads: usize,
) -> anyhow::Result<f64> {
    pool(threads)?.install(|| {
        let net = Net::random(config.clone(), 1, DType::F32)?;
        let vars: Vec<Var> = net
            .params()
            .iter()
            .map(Var::from_tensor)
            .collect::<Result<_, _>>()?;
        let net = Net::new(
            config.clone(),
            vars.iter().map(|v| v.as_tensor().clone()).collect(),
        )?;
        let mut rng = StdRng::seed_from_u64(1);
        let (mut samples, mut secs) = (0usize, 0.0);
        for step in 0..steps + 1 {
            let b = &batches[step % batches.len()];
            let t0 = Instant::now();
            let e = net.forward(&b.x)?;
            let (l, _, _) = batch_loss(&e, &b.labels, LossKind::BatchAll, MARGIN, None, &mut rng)?;
            let _grads = l.backward()?;
            if step >= 1 {
                secs += t0.elapsed().as_secs_f64();
                samples += b.labels.len();
            }
        }
        Ok(samples as f64 / secs)
    })
}

/// The batches as one little-endian file for the PyTorch reference: a header of u32
/// (batches, batch size, steps, channels), then per batch its f32 features and u32 labels.
fn write_batches(path: &Path, batches: &[Batch]) -> anyhow::Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    let (b, l, c) = batches[0].x.dims3()?;
    for v in [batches.len(), b, l, c] {
        f.write_all(&u32::try_from(v)?.to_le_bytes())?;
    }
    for batch in batches {
        for v in batch.x.flatten_all()?.to_vec1::<f32>()? {
            f.write_all(&v.to_le_bytes())?;
        }
        for v in &batch.labels {
            f.write_all(&v.to_le_bytes())?;
        }
    }
    Ok(f.flush()?)
}

/// Samples/s of the PyTorch reference, or why it did not run.
fn pytorch(
    script: &Path,
    data: &Path,
    config: &NetConfig,
    steps: usize,
    threads: usize,
) -> Result<f64, String> {
    let channels: Vec<String> = config.channels.iter().map(usize::to_string).collect();
    let out = Command::new("python3")
        .arg(script)
        .arg(data)
        .args(["--threads", &threads.to_string()])
        .args(["--steps", &steps.to_string()])
        .args(["--channels", &channels.join(",")])
        .args(["--kernel", &config.kernel.to_string()])
        .args(["--embed-dim", &config.embed_dim.to_string()])
        .args(["--margin", &MARGIN.to_string()])
        .args(["--lr", &LR.to_string()])
        .args(["--weight-decay", &WEIGHT_DECAY.to_string()])
        .args(config.features.is_picture().then_some("--picture"))
        .output()
        .map_err(|e| format!("python3: {e}"))?;
    let text = String::from_utf8_lossy(&out.stdout);
    text.lines()
        .find_map(|l| l.strip_prefix("samples/s ")?.trim().parse().ok())
        .ok_or_else(|| {
            format!(
                "the reference printed no figure: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            )
        })
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    let root = here.join("../../shared/omniglot/strokes");
    let files: Vec<_> = scan(&[root])?
        .into_iter()
        .filter(|f| f.alphabet == "Latin")
        .collect();
    let (data, _) = generate_files(&files, &Geometry::default(), &|| {})?;
    let steps = env_usize("BENCH_STEPS", 40);
    let rounds = env_usize("BENCH_ROUNDS", 3).max(1);
    let arches = std::env::var("BENCH_ARCH").unwrap_or_else(|_| "shipped".into());
    let mut configs = Vec::new();
    for arch in arches.split(',') {
        match arch {
            "shipped" => {
                let model = here.join("../models/embedder.safetensors");
                let shipped = Embedder::load(&model)
                    .with_context(|| format!("BENCH_ARCH=shipped: {}", model.display()))?;
                configs.extend(shipped.configs().into_iter().cloned());
            }
            "pen" => configs.push(NetConfig {
                channels: vec![32, 64, 128],
                ..NetConfig::default()
            }),
            "picture" => configs.push(NetConfig {
                features: FeatureKind::Picture,
                channels: vec![32, 64, 64, 128],
                kernel: 3,
                ..NetConfig::default()
            }),
            other => {
                anyhow::bail!("BENCH_ARCH: unknown architecture {other} (shipped, pen, picture)")
            }
        }
    }
    for config in &configs {
        bench(here, &data, config, steps, rounds)?;
    }
    Ok(())
}

fn bench(
    here: &Path,
    data: &guardian_omniglot::dataset::Dataset,
    config: &NetConfig,
    steps: usize,
    rounds: usize,
) -> anyhow::Result<()> {
    let config = config.clone();
    let kind = config.features;
    let set = Prepared::new(data, &["Latin".to_string()], kind)?;
    let (p, k) = (16, 4);
    let mut rng = StdRng::seed_from_u64(7);
    let batches: Vec<Batch> = (0..8)
        .map(|_| {
            let (idx, labels) = set.sample_pk(p, k, &mut rng);
            let x = set.batch(&idx, Some(&mut rng))?;
            Ok(Batch { x, labels })
        })
        .collect::<anyhow::Result<_>>()?;
    let flops = FastNet::<f32>::random(config.clone(), 1)?.flops(kind.steps());
    println!(
        "network: {kind:?} features ({} channels), channels {:?}, kernel {}, embed {}; forward {:.2} MFLOP per input; batch {p} classes x {k} drawings of real Latin drawings; batch-all loss, margin {MARGIN}; AdamW lr {LR}, weight decay {WEIGHT_DECAY}; {steps} steps x {rounds} rounds",
        config.in_channels(),
        config.channels,
        config.kernel,
        config.embed_dim,
        flops as f64 / 1e6
    );

    let script = here.join("benches/train_throughput.py");
    let torch = Command::new("python3")
        .args(["-c", "import torch"])
        .output()
        .is_ok_and(|o| o.status.success());
    let data_file = std::env::temp_dir().join(format!("guardian-bench-{}.bin", std::process::id()));
    if torch {
        write_batches(&data_file, &batches)?;
    } else {
        println!(
            "PyTorch reference skipped: `python3 -c \"import torch\"` fails (pip install torch)"
        );
    }
    println!(
        "{:>7} {:>12} {:>12} {:>14} {:>12} {:>10} {:>10}",
        "threads", "guardian/s", "step ms", "of which loss", "candle/s", "pytorch/s", "~GFLOP/s"
    );
    for threads in [1, 2] {
        let (mut g, mut c, mut t, mut split) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for _ in 0..rounds {
            let (rate, s) = guardian(&config, &batches, steps, threads)?;
            g.push(rate);
            split.push((rate, s));
            c.push(candle_autograd(
                &config,
                &batches,
                steps.div_ceil(4),
                threads,
            )?);
            if torch {
                match pytorch(&script, &data_file, &config, steps, threads) {
                    Ok(v) => t.push(v),
                    Err(e) => println!("PyTorch reference failed: {e}"),
                }
            }
        }
        let gm = median(g.clone());
        // The time split of the median round.
        split.sort_by(|a, b| a.0.total_cmp(&b.0));
        let step = split[split.len() / 2].1;
        let tm = (!t.is_empty()).then(|| median(t.clone()));
        println!(
            "{threads:>7} {gm:>12.0} {:>12.2} {:>14.2} {:>12.0} {:>10} {:>10.1}",
            step[0],
            step[1],
            median(c.clone()),
            tm.map_or("-".to_string(), |v| format!("{v:.0}")),
            gm * 3.0 * flops as f64 / 1e9
        );
        println!(
            "  rounds: guardian {:?}, candle {:?}, pytorch {:?}",
            g.iter().map(|v| v.round()).collect::<Vec<_>>(),
            c.iter().map(|v| v.round()).collect::<Vec<_>>(),
            t.iter().map(|v| v.round()).collect::<Vec<_>>()
        );
        println!(
            "training throughput ratio guardian/candle-autograd, {kind:?} ({threads} thread{}): {:.2}",
            if threads == 1 { "" } else { "s" },
            gm / median(c)
        );
        if let Some(tm) = tm {
            println!(
                "training throughput ratio guardian/pytorch, {kind:?} ({threads} thread{}): {:.2}",
                if threads == 1 { "" } else { "s" },
                gm / tm
            );
        }
    }
    let _ = std::fs::remove_file(&data_file);
    Ok(())
}
