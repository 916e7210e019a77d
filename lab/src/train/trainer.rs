//! The training loop: prepare the data (fault negatives, class augmentation), restore or
//! start the checkpoint, run the epochs (batches, objective, one AdamW step each), validate
//! each epoch (loss on fixed batches, 5-way-1-shot accuracy), apply the schedule, and write
//! the metrics, the models and the checkpoint; `guardian-lab train`.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use guardian_models::embedder::Embedder;
use guardian_models::sequence::forward::FastNet;
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};

use crate::eval::{self, EpisodeSpec};
use crate::train::batches::{Item, Prepared};
use crate::train::checkpoint::{
    State, load_opt, load_proxies, read_json, save_opt, save_proxies, write_json,
};
use crate::train::classaug::SymmetryRule;
use crate::train::config::{Args, LossKind, Schedule, TrainConfig};
use crate::train::objective::objective;
use crate::train::optim::{Learner, Proxies};
use crate::train::schedule::{EpochEnd, end_epoch, one_cycle_lr};
use crate::train::{TrainError, io_err};
use guardian_omniglot::dataset::Dataset;

/// One epoch's metrics (one JSONL line).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EpochMetrics {
    /// Epoch (1-based).
    pub epoch: usize,
    /// Mean training loss.
    pub train_loss: f64,
    /// Validation loss (fixed batches; for batch-all, the mean over all valid triplets).
    pub val_loss: f64,
    /// Validation 5-way-1-shot accuracy (fixed episodes).
    pub val_acc_5way1shot: f64,
    /// Learning rate used in this epoch.
    pub lr: f64,
    /// Fraction of active (non-zero) triplets or anchors in training.
    pub active_fraction: f64,
    /// Samples embedded per second in training (forward + backward).
    pub samples_per_s: f64,
    /// Mined triplets per second (one per anchor for batch-hard / triplet).
    pub triplets_per_s: f64,
    /// Wall-clock seconds of the epoch including validation.
    pub seconds: f64,
}

/// What a finished run reports.
#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    /// Epochs run in total.
    pub epochs: usize,
    /// Best validation loss.
    pub best_val_loss: f64,
    /// Wall-clock seconds of training (all sessions of a resumed run).
    pub seconds: f64,
    /// Version of the best model.
    pub model_version: String,
    /// Why training stopped.
    pub stopped: String,
}

/// The fault-negative margin of every item of a batch of `set` (`cfg.fault_margin_of` its
/// kind; a genuine item's is not read).
fn fault_margins(set: &Prepared, items: &[Item], cfg: &TrainConfig) -> Vec<f64> {
    items
        .iter()
        .map(|&it| cfg.fault_margin_of(set.fault_kind(it)))
        .collect()
}

/// Embeddings `[B, embed_dim]` of a feature batch `x [B, STEPS, F]` (no gradient).
pub fn embed(net: &FastNet, x: &Tensor) -> Result<Tensor, TrainError> {
    let (b, l, _) = x.dims3()?;
    let flat = x.flatten_all()?.to_vec1::<f32>()?;
    let e = net.config().embed_dim;
    let mut out = vec![0.0f32; b * e];
    net.forward(&flat, b, l, &mut Default::default(), &mut out)?;
    Ok(Tensor::from_vec(out, (b, e), &Device::Cpu)?)
}

/// Train as configured, writing into `out`. With `resume`, continue from the checkpoint
/// there (the configuration must match). `strokes` are the Omniglot stroke roots the fault
/// negatives are made from (needed only when `cfg.fault_share > 0`).
pub fn train(
    data: &Dataset,
    cfg: &TrainConfig,
    strokes: Option<&[PathBuf]>,
    out: &Path,
    resume: bool,
    quiet: bool,
) -> Result<TrainSummary, TrainError> {
    cfg.check()?;
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    let mut train_set = Prepared::new(data, &cfg.train_alphabets, cfg.net.features)?;
    train_set.set_reverse_augment(cfg.reverse_augment);
    // Without validation alphabets (one-cycle only, see `TrainConfig::check`) an epoch
    // records no validation figures and the last model is kept, as with validation.
    let validate = !cfg.val_alphabets.is_empty();
    let mut val_set = Prepared::new(data, &cfg.val_alphabets, cfg.net.features)?;
    if cfg.fault_share > 0.0 {
        let root = strokes.ok_or_else(|| {
            TrainError::Setup("fault negatives need the Omniglot stroke root".into())
        })?;
        let t0 = Instant::now();
        let kinds = &cfg.fault_kinds;
        let n_train = train_set.make_faults(data, root, kinds, cfg.fault_variants, cfg.seed)?;
        let n_val = if validate {
            val_set.make_faults(data, root, kinds, cfg.fault_variants, cfg.seed ^ 0x7a11)?
        } else {
            0
        };
        if n_train == 0 {
            return Err(TrainError::Setup(format!(
                "no fault negatives could be made from {root:?}"
            )));
        }
        if !quiet {
            eprintln!(
                "fault negatives: {n_train} training and {n_val} validation plans solved in {:.1} s",
                t0.elapsed().as_secs_f64()
            );
        }
    }
    if cfg.class_augment {
        let plan = train_set.augment_classes(SymmetryRule {
            quantile: cfg.symmetry_quantile,
        })?;
        let dropped = plan.self_symmetric + plan.collides;
        if !quiet {
            eprintln!(
                "class augmentation: {} new classes ({} in all); {dropped} transforms dropped \
                 ({} map a character onto itself, {} onto another class; threshold {:.3}, \
                 {} of {} pairs of original classes at or above it)",
                plan.new_classes(),
                train_set.classes(),
                plan.self_symmetric,
                plan.collides,
                plan.threshold,
                plan.original_pairs_above,
                plan.original_pairs
            );
        }
        write_json(&out.join("class-augment.json"), &plan)?;
    }
    if train_set.classes() < cfg.p_classes.min(2) || (validate && val_set.classes() < 5) {
        return Err(TrainError::Setup(format!(
            "too few classes: train {}, val {} (val needs >= 5)",
            train_set.classes(),
            val_set.classes()
        )));
    }

    let config_path = out.join("train-config.json");
    let state_path = out.join("state.json");
    let last_path = out.join("last.safetensors");
    let opt_path = out.join("optimizer.safetensors");
    let best_path = out.join("model.safetensors");
    let metrics_path = out.join("metrics.jsonl");

    let (net, mut state, opt_state) = if resume {
        let saved: TrainConfig = read_json(&config_path)?;
        let mut comparable = TrainConfig {
            max_epochs: cfg.max_epochs,
            ..saved.clone()
        };
        comparable.net.reverse_average = cfg.net.reverse_average;
        if &comparable != cfg {
            return Err(TrainError::Setup(format!(
                "--resume: {} differs from this run's configuration",
                config_path.display()
            )));
        }
        let mut state: State = read_json(&state_path)?;
        // A resumed run may extend the epoch budget.
        if state.finished
            && state.epoch < cfg.max_epochs
            && state.epochs_since_best < cfg.early_stop_patience
        {
            state.finished = false;
        }
        write_json(&config_path, cfg)?;
        let last = Embedder::load(&last_path)?;
        let opt = load_opt(&opt_path)?;
        let [net] = last.nets() else {
            return Err(TrainError::Setup(format!(
                "{} is a fused model, not a training checkpoint",
                last_path.display()
            )));
        };
        let params = net.params().iter().map(|p| p.to_vec()).collect();
        (
            FastNet::from_params(cfg.net.clone(), params)?,
            state,
            Some(opt),
        )
    } else {
        write_json(&config_path, cfg)?;
        let _ = std::fs::remove_file(&metrics_path);
        let net = FastNet::random(cfg.net.clone(), cfg.seed)?;
        let state = State::new(cfg.lr);
        (net, state, None)
    };
    if state.finished {
        let mut best = Embedder::load(&best_path)?;
        if best
            .configs()
            .iter()
            .any(|c| c.reverse_average != cfg.net.reverse_average)
        {
            best.set_reverse_average(cfg.net.reverse_average);
            best.save(&best_path)?;
        }
        return Ok(TrainSummary {
            epochs: state.epoch,
            best_val_loss: state.best_val_loss,
            seconds: state.train_seconds,
            model_version: best.version().to_string(),
            stopped: "already finished".into(),
        });
    }
    let mut learner = Learner::new(net, cfg.weight_decay);
    let resumed = opt_state.is_some();
    if let Some((m, v)) = opt_state {
        learner.optimizer_mut().restore(m, v, state.adam_step)?;
    }
    let proxies_path = out.join("proxies.safetensors");
    if cfg.loss == LossKind::NormSoftmax {
        let (classes, dim) = (train_set.classes(), cfg.net.embed_dim);
        let proxies = if resumed {
            load_proxies(&proxies_path, classes, dim, state.adam_step)?
        } else {
            Proxies::random(classes, dim, cfg.seed ^ 0x9e37_79b9_7f4a_7c15)
        };
        learner = learner.with_proxies(proxies.with_lr_scale(cfg.proxy_lr_scale));
    }

    // Fixed validation batches and episodes.
    let mut vrng = StdRng::seed_from_u64(cfg.seed ^ 0x005e_ed0f_7a11);
    let val_batches: Vec<(Vec<Item>, Vec<u32>)> = (0..if validate { 10 } else { 0 })
        .map(|_| {
            let (idx, labels) = val_set.sample_pk(cfg.p_classes, cfg.k_samples, &mut vrng);
            val_set.with_faults(&idx, &labels, cfg.fault_share, &mut vrng)
        })
        .collect();
    let val_labels: Vec<u32> = val_set.labels().to_vec();
    let val_spec = EpisodeSpec {
        way: 5,
        shot: 1,
        episodes: cfg.val_episodes,
        seed: cfg.seed,
    };

    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new((cfg.max_epochs * cfg.steps_per_epoch) as u64)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} steps ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar.set_position((state.epoch * cfg.steps_per_epoch) as u64);

    let mut metrics_file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&metrics_path)
        .map_err(io_err(&metrics_path))?;
    let mut stopped = "max epochs".to_string();
    while state.epoch < cfg.max_epochs {
        let epoch = state.epoch + 1;
        let t0 = Instant::now();
        // Per-epoch RNG: a resumed run draws the same batches as an uninterrupted one.
        let mut rng =
            StdRng::seed_from_u64(cfg.seed.wrapping_mul(1_000_003).wrapping_add(epoch as u64));
        let (mut loss_sum, mut active_sum, mut samples, mut triplets) = (0.0, 0.0, 0usize, 0usize);
        let total_steps = cfg.max_epochs * cfg.steps_per_epoch;
        for step in 0..cfg.steps_per_epoch {
            if cfg.schedule == Schedule::OneCycle {
                state.lr = one_cycle_lr(
                    cfg.lr,
                    state.epoch * cfg.steps_per_epoch + step,
                    total_steps,
                );
            }
            let (idx, labels) = train_set.sample_pk(cfg.p_classes, cfg.k_samples, &mut rng);
            let (items, labels) = train_set.with_faults(&idx, &labels, cfg.fault_share, &mut rng);
            let x = train_set.batch_items(&items, cfg.augment.then_some(&mut rng))?;
            let sources = train_set.sources(&items);
            let margins = fault_margins(&train_set, &items, cfg);
            let (l, (active, n_trip)) = learner.step(&x, state.lr, |e, proxies| {
                let (l, _, active, n) =
                    objective(e, &labels, &sources, Some(&margins), proxies, cfg, &mut rng)?;
                Ok((l, (active, n)))
            })?;
            loss_sum += f64::from(l);
            active_sum += f64::from(active);
            samples += items.len();
            triplets += n_trip;
            bar.inc(1);
        }
        let train_secs = t0.elapsed().as_secs_f64();
        let train_loss = loss_sum / cfg.steps_per_epoch as f64;

        // Validation (NaN without a validation set: written as null).
        let (mut val_loss, mut val_acc) = (f64::NAN, f64::NAN);
        if validate {
            val_loss = 0.0;
            let mut dummy = StdRng::seed_from_u64(0);
            for (items, labels) in &val_batches {
                let x = val_set.batch_items(items, None)?;
                let sources = val_set.sources(items);
                let margins = fault_margins(&val_set, items, cfg);
                let e = embed(learner.net(), &x)?;
                val_loss +=
                    objective(&e, labels, &sources, Some(&margins), None, cfg, &mut dummy)?.1;
            }
            val_loss /= val_batches.len() as f64;
            let embs = embed_all(learner.net(), &val_set)?;
            val_acc =
                eval::run_episodes(&val_labels, &val_spec, &mut eval::Scorer::Prototype(&embs))?
                    .accuracy;
        }

        let m = EpochMetrics {
            epoch,
            train_loss,
            val_loss,
            val_acc_5way1shot: val_acc,
            lr: state.lr,
            active_fraction: active_sum / cfg.steps_per_epoch as f64,
            samples_per_s: samples as f64 / train_secs,
            triplets_per_s: triplets as f64 / train_secs,
            seconds: t0.elapsed().as_secs_f64(),
        };
        let line = serde_json::to_string(&m).map_err(|e| TrainError::Setup(e.to_string()))?;
        writeln!(metrics_file, "{line}").map_err(io_err(&metrics_path))?;
        bar.set_message(format!(
            "epoch {epoch} train {train_loss:.4} val {val_loss:.4} acc5 {val_acc:.3} lr {:.1e}",
            state.lr
        ));
        if quiet {
            eprintln!("{line}");
        }

        // Best model, schedule, early stopping.
        let current = Embedder::from_trained(&learner.net().to_net()?)?;
        let EpochEnd { keep, stop } = end_epoch(cfg, &mut state, val_loss);
        if keep {
            current.save(&best_path)?;
        }
        state.epoch = epoch;
        state.adam_step = learner.optimizer().steps();
        state.train_seconds += t0.elapsed().as_secs_f64();
        if stop {
            stopped = format!(
                "early stopping after {} epochs without improvement",
                state.epochs_since_best
            );
        }
        state.finished = stop || state.epoch >= cfg.max_epochs;
        current.save(&last_path)?;
        save_opt(&opt_path, learner.optimizer())?;
        if let Some(p) = learner.proxies() {
            save_proxies(&proxies_path, p)?;
        }
        write_json(&state_path, &state)?;
        if stop {
            break;
        }
    }
    bar.finish_and_clear();
    let best = Embedder::load(&best_path)?;
    Ok(TrainSummary {
        epochs: state.epoch,
        best_val_loss: state.best_val_loss,
        seconds: state.train_seconds,
        model_version: best.version().to_string(),
        stopped,
    })
}

/// Embeddings of every sample of a prepared set (no augmentation), in order.
pub fn embed_all(net: &FastNet, set: &Prepared) -> Result<Vec<Vec<f32>>, TrainError> {
    let mut out = Vec::with_capacity(set.len());
    let idx: Vec<usize> = (0..set.len()).collect();
    for chunk in idx.chunks(256) {
        let x = set.batch(chunk, None)?;
        let e = embed(net, &x)?.to_vec2::<f32>()?;
        out.extend(e);
    }
    Ok(out)
}

/// Run `guardian-lab train`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let data = Dataset::load(&args.data.dataset)?;
    let cfg = args.config();
    let validation = if cfg.val_alphabets.is_empty() {
        "without validation (the last model is kept)".to_string()
    } else {
        format!("validating on {:?}", cfg.val_alphabets)
    };
    eprintln!(
        "training on {:?}, {validation}; {} rayon threads",
        cfg.train_alphabets,
        rayon::current_num_threads()
    );
    let summary = train(
        &data,
        &cfg,
        Some(&args.strokes.strokes),
        &args.out,
        args.resume,
        args.quiet,
    )?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_models::features::FeatureKind;
    use guardian_models::net::NetConfig;
    use guardian_shared::trajectory::STEPS;

    #[test]
    fn embeddings_of_a_set_come_in_order_and_match_the_batch_path() {
        let config = NetConfig {
            features: FeatureKind::Pen,
            channels: vec![8, 16],
            kernel: 3,
            ..NetConfig::default()
        };
        let net = FastNet::random(config, 4).expect("net");
        // 300 samples: more than one chunk of 256.
        let n = 300;
        let pen = (0..n)
            .map(|i| {
                std::array::from_fn(|t| {
                    let u = t as f32 / (STEPS - 1) as f32;
                    let a = i as f32 * 0.05;
                    [0.02 * u * a.cos(), 0.02 * u * a.sin() + 0.001 * u * u, 1.0]
                })
            })
            .collect();
        let set = Prepared::from_pen_paths(FeatureKind::Pen, pen, (0..n as u32).collect());
        let all = embed_all(&net, &set).expect("embed all");
        assert_eq!(all.len(), n);
        for i in [0, 1, 255, 256, 299] {
            let one = embed(&net, &set.batch(&[i], None).expect("batch"))
                .expect("embed")
                .to_vec2::<f32>()
                .expect("vec");
            let err = one[0]
                .iter()
                .zip(&all[i])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(err < 1e-5, "sample {i}: {err}");
            let norm: f32 = all[i].iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-4, "L2-normalised: {norm}");
        }
        assert_ne!(all[0], all[1]);
    }
}
