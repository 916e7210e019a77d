//! Helpers shared by the lab's integration tests.
#![allow(dead_code)] // each test crate uses its own subset

use guardian_lab::train::{LossKind, TrainConfig};
use guardian_models::features::FeatureKind;
use guardian_models::net::NetConfig;
use guardian_omniglot::strokes::DrawingFile;

/// A tiny pen-feature network (16-32 channels).
pub fn tiny_net() -> NetConfig {
    NetConfig {
        features: FeatureKind::Pen,
        channels: vec![16, 32],
        kernel: 5,
        embed_dim: guardian_models::embedder::EMBED_DIM,
        l2_normalize: true,
        reverse_average: false,
        test_views: Vec::new(),
    }
}

/// The training configuration of the pipeline tests: a tiny network, Latin / Greek.
pub fn tiny_config() -> TrainConfig {
    TrainConfig {
        net: tiny_net(),
        loss: LossKind::BatchAll,
        margin: 0.2,
        train_alphabets: vec!["Latin".into()],
        val_alphabets: vec!["Greek".into()],
        p_classes: 6,
        k_samples: 4,
        steps_per_epoch: 5,
        max_epochs: 2,
        schedule: guardian_lab::train::Schedule::Plateau,
        lr: 3e-3,
        weight_decay: 1e-4,
        plateau_patience: 3,
        lr_factor: 0.5,
        min_lr: 1e-5,
        early_stop_patience: 10,
        augment: true,
        reverse_augment: true,
        seed: 1,
        val_episodes: 50,
        fault_share: 0.0,
        fault_variants: 0,
        fault_weight: 0.0,
        fault_margin: 0.0,
        fault_kinds: Vec::new(),
        fault_margin_for: Vec::new(),
        class_augment: false,
        symmetry_quantile: 0.0,
        proxy_lr_scale: 1.0,
    }
}

/// Every drawing of the first `n` characters of each `(alphabet, n)` among `all` (a scan).
pub fn first_characters(all: &[DrawingFile], alphabets: &[(&str, usize)]) -> Vec<DrawingFile> {
    let mut files = Vec::new();
    for &(alphabet, n) in alphabets {
        let mut classes: Vec<String> = all
            .iter()
            .filter(|f| f.alphabet == alphabet)
            .map(|f| f.class_name())
            .collect();
        classes.dedup();
        classes.truncate(n);
        files.extend(
            all.iter()
                .filter(|f| classes.contains(&f.class_name()))
                .cloned(),
        );
    }
    files
}
