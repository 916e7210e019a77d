//! The embedding network: a 1D CNN over time (convolution + ReLU + pooling), global mean and
//! max pooling, and a fully connected layer to the embedding.
//!
//! Convolutions are written as explicit zero padding + unfold (`narrow` + `cat`) + `matmul`
//! rather than `candle_nn::conv1d`, whose weight gradients are wrong on CPU for batch > 1 in
//! candle 0.11 (see the engineering guide). Pooling is a `reshape` + `max`, whose backward is
//! exact. This is the reference path: [`crate::sequence::forward`] serves and [`crate::sequence::backward`] trains the
//! same network, and tests hold both to this one (forward and gradients).
//!
//! Layout: input `[B, L, F]` (batch, time, feature channels), activations `[B, L, C]`.

use serde::{Deserialize, Serialize};

use crate::features::FeatureKind;
pub use crate::features::{MAX_TEST_VIEWS, TestView, parse_test_views};

/// Embedding dimension of an [`crate::embedder::Embedder`].
pub const EMBED_DIM: usize = 128;

/// Architecture and preprocessing of an embedder; stored in the model file's metadata.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct NetConfig {
    /// Which features `embed` computes from the resampled joint trajectory.
    pub features: FeatureKind,
    /// Output channels of each convolution layer; every layer but the last is followed by a
    /// max pool of 2 over time.
    pub channels: Vec<usize>,
    /// Convolution kernel size (odd).
    pub kernel: usize,
    /// Embedding dimension (must be [`EMBED_DIM`] for an `Embedder`).
    pub embed_dim: usize,
    /// L2-normalise the embedding (distances then lie in `[0, 4]`).
    pub l2_normalize: bool,
    /// Inference only: embed the trajectory forwards and time-reversed and average the two
    /// embeddings (re-normalised), so the direction a stroke was drawn in matters less.
    /// Pen features only; ignored for joint features.
    #[serde(default)]
    pub reverse_average: bool,
    /// Inference only: test-time augmentation. Besides the plan's own pen path, the network
    /// also embeds these geometric views of it; every view's embedding (and, with
    /// `reverse_average`, every view's reverse) is averaged and re-normalised. Pen features
    /// only (sequence or picture); empty (the default) embeds the plan's own path alone.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub test_views: Vec<TestView>,
}

impl Default for NetConfig {
    fn default() -> Self {
        Self {
            features: FeatureKind::Pen,
            channels: vec![64, 128, 128],
            kernel: 5,
            embed_dim: EMBED_DIM,
            l2_normalize: true,
            reverse_average: false,
            test_views: Vec::new(),
        }
    }
}

impl NetConfig {
    /// The tiny joint-feature network the gradient, fast-path and reference tests share
    /// (two layers of 4 and 5 channels, kernel 3, 6-d embedding).
    #[cfg(all(test, feature = "train"))]
    pub(crate) fn tiny_joints() -> Self {
        Self {
            features: FeatureKind::Joints,
            channels: vec![4, 5],
            kernel: 3,
            embed_dim: 6,
            l2_normalize: true,
            reverse_average: false,
            test_views: Vec::new(),
        }
    }

    /// Sequences the network reads per plan at inference: one per view (the plan's own path
    /// and each test view), twice with reverse averaging.
    pub fn copies(&self) -> usize {
        if self.features == FeatureKind::Joints {
            return 1;
        }
        (1 + self.test_views.len()) * if self.reverse_average { 2 } else { 1 }
    }

    /// Input feature channels.
    pub fn in_channels(&self) -> usize {
        self.features.channels()
    }

    /// Taps of one convolution: `kernel` over time, `kernel²` over a picture.
    pub fn taps(&self) -> usize {
        if self.features.is_picture() {
            self.kernel * self.kernel
        } else {
            self.kernel
        }
    }

    /// Features the output layer reads: the last layer's global mean and max over time for
    /// a sequence, its global mean for a picture.
    pub fn pooled_features(&self) -> usize {
        let last = self.channels.last().copied().unwrap_or(0);
        if self.features.is_picture() {
            last
        } else {
            2 * last
        }
    }

    /// Names and shapes of every parameter, in a fixed order.
    pub fn param_shapes(&self) -> Vec<(String, Vec<usize>)> {
        let mut out = Vec::new();
        let mut c_in = self.in_channels();
        for (i, &c) in self.channels.iter().enumerate() {
            out.push((format!("conv{i}.weight"), vec![self.taps() * c_in, c]));
            out.push((format!("conv{i}.bias"), vec![c]));
            c_in = c;
        }
        out.push((
            "fc.weight".to_string(),
            vec![self.pooled_features(), self.embed_dim],
        ));
        out.push(("fc.bias".to_string(), vec![self.embed_dim]));
        out
    }

    /// Check the config is usable: odd kernel, at least one layer, time length divisible by
    /// the pooling.
    pub fn check(&self) -> Result<(), String> {
        if self.kernel == 0 || self.kernel.is_multiple_of(2) {
            return Err(format!("kernel must be odd, got {}", self.kernel));
        }
        if self.channels.is_empty() || self.channels.contains(&0) {
            return Err("channels must be non-empty and positive".into());
        }
        if self.embed_dim == 0 {
            return Err("embed-dim must be positive".into());
        }
        if !self.test_views.is_empty() && self.features == FeatureKind::Joints {
            return Err("test views need pen features (sequence or picture)".into());
        }
        if self.test_views.len() > MAX_TEST_VIEWS {
            return Err(format!(
                "at most {MAX_TEST_VIEWS} test views, got {}",
                self.test_views.len()
            ));
        }
        if self
            .test_views
            .iter()
            .any(|v| v.stretch.unsigned_abs() >= 500)
        {
            return Err("a test view's stretch must lie within (-500, 500) thousandths".into());
        }
        if self.features.is_picture() {
            // Every layer is followed by a 2 x 2 max pool.
            let side = crate::features::PICTURE_SIDE;
            if side >> self.channels.len() == 0 || !side.is_multiple_of(1 << self.channels.len()) {
                return Err(format!(
                    "{} layers with a 2 x 2 pool each do not fit a {side} x {side} picture",
                    self.channels.len()
                ));
            }
            if self.reverse_average {
                return Err("a picture has no direction: reverse-average must be off".into());
            }
            return Ok(());
        }
        let pools = self.channels.len() - 1;
        if pools > 6 {
            return Err(format!("at most 7 layers, got {}", self.channels.len()));
        }
        Ok(())
    }

    /// Deterministic He-uniform initial weights (biases zero) for `seed` (feature `train`).
    #[cfg(any(test, feature = "train"))]
    pub fn init(&self, seed: u64) -> Vec<(String, Vec<usize>, Vec<f32>)> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        self.param_shapes()
            .into_iter()
            .map(|(name, shape)| {
                let n: usize = shape.iter().product();
                let data = if shape.len() == 2 {
                    let bound = (6.0 / shape[0] as f64).sqrt() as f32;
                    let bound = if name == "fc.weight" {
                        // Glorot for the linear output layer.
                        (6.0 / (shape[0] + shape[1]) as f64).sqrt() as f32
                    } else {
                        bound
                    };
                    (0..n).map(|_| rng.random_range(-bound..bound)).collect()
                } else {
                    vec![0.0; n]
                };
                (name, shape, data)
            })
            .collect()
    }
}

// The candle network: the reference the fast path is tested against, and what training
// builds on (feature `train`; the daemon serves from `crate::sequence::forward` alone).
#[cfg(feature = "train")]
mod reference;
#[cfg(feature = "train")]
pub use reference::{Net, conv1d_same, conv2d_same, max_pool2};
