//! The inference-side embedder: load/save a trained network, embed resampled trajectories.
//!
//! An embedder holds a network, not a robot: every call names the robot whose forward
//! kinematics turns a trajectory into the pen-tip path the network sees (the daemon's
//! `guardian_screen::Station` owns it), so one trained model screens any arm drawing the same
//! tasks. Models on joint features ([`FeatureKind::Joints`], the paper's baseline) are
//! Panda-only ([`Embedder::serves`]).
//!
//! File format: safetensors with one f32 tensor per parameter and `__metadata__`:
//! `format` (`guardian-embedder/1`), `config` (the [`NetConfig`] as JSON), `input-shape`
//! (`128x8`: the 128 steps of the Panda's 8 channels the format was defined on), `embed-dim`,
//! and `sha256` — a hex SHA-256 over every tensor (in name order:
//! name, shape, little-endian bytes). [`Embedder::load`] refuses a file whose format,
//! shapes or checksum do not match.

use std::cell::RefCell;
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[cfg(feature = "train")]
use candle_core::DType;
#[cfg(all(feature = "train", any(test, feature = "test-support")))]
use candle_core::{Device, Tensor};
use guardian_shared::trajectory::{Resampled, STEPS};
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use sha2::{Digest, Sha256};

use crate::features::{Augment, FeatureKind};
#[cfg(feature = "train")]
use crate::net::Net;
use crate::net::NetConfig;
use crate::sequence::forward::{FastNet, FastNetError, Scratch};
use guardian_robot::kinematics::{PANDA_JOINTS, Robot};
use guardian_robot::pen::{PenPoint, pen_path_with};

pub use crate::net::EMBED_DIM;
pub use file::{FORMAT, LoadModelError, SaveModelError};
use file::{Named, check_configs, checksum, tensor_name};

mod file;

/// How a pen path is computed from a resampled trajectory: [`pen_path_with`] the served robot, or
/// the general-chain reference the tests compare it with. A type parameter rather than a
/// function pointer, so the serving path calls `pen_path` directly.
trait PenPathFn: Fn(&Resampled) -> [PenPoint; STEPS] + Copy {}
impl<F: Fn(&Resampled) -> [PenPoint; STEPS] + Copy> PenPathFn for F {}
/// One embedding.
pub type Embedding = [f32; EMBED_DIM];

/// Embedding failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EmbedError {
    /// The network's forward pass failed.
    #[cfg(feature = "train")]
    #[error("forward pass: {0}")]
    Candle(#[from] candle_core::Error),
    /// An input value is NaN or infinite.
    #[error("input {index} holds a non-finite value")]
    NonFinite {
        /// Index of the input in the batch.
        index: usize,
    },
    /// The fast path refused the input or its buffers.
    #[error("fast forward pass: {0}")]
    Fast(#[from] FastNetError),
    /// `out` does not have one slot per input.
    #[error("output has {got} slots for {expected} inputs")]
    OutputLength {
        /// Inputs given.
        expected: usize,
        /// Output slots given.
        got: usize,
    },
    /// A joint-feature model was asked to serve a robot other than the Panda.
    #[error("a joint-feature model serves the Panda only, not {robot}")]
    JointFeaturesNeedPanda {
        /// The robot asked for.
        robot: String,
    },
    /// An inference option would make a network's config unusable.
    #[error("model config: {0}")]
    Config(String),
    /// The network produced a non-finite embedding.
    #[error("embedding {index} is non-finite")]
    NonFiniteOutput {
        /// Index of the input in the batch.
        index: usize,
    },
}

/// A trained (or random) embedding model with its feature computation. `Send + Sync`.
///
/// A model is one network, or the **branches of a fused model** ([`Embedder::fuse`]): several
/// networks, each with its own view of the pen path (the time sequence of pen features, the
/// picture), whose L2-normalised embeddings are concatenated and scaled by `1/√branches`. The
/// fused embedding is then a unit vector again, and its squared distance between two plans is
/// the mean of the branches' squared distances — the fusion of distances the lab measured,
/// computed by the bank's ordinary arithmetic. An embedding is always [`EMBED_DIM`] wide: the
/// branches' dimensions must sum to at most that, and the rest is zero (which changes no
/// distance).
///
/// The weights live in the fast path's buffers alone ([`FastNet`], loaded straight from the
/// file); a candle network is built from them only on request (feature `train`).
#[derive(Debug, Clone)]
pub struct Embedder {
    nets: Arc<Vec<FastNet>>,
    version: String,
    checksum: String,
}

impl Embedder {
    /// A network with deterministic random weights (the default architecture) for tests
    /// (feature `train`).
    #[cfg(any(test, feature = "train"))]
    pub fn random(seed: u64) -> Self {
        Self::random_with(NetConfig::default(), seed)
            .expect("the default architecture builds; a failure is a bug in this crate")
    }

    /// A network with deterministic random weights for a given architecture (feature
    /// `train`).
    #[cfg(any(test, feature = "train"))]
    pub fn random_with(config: NetConfig, seed: u64) -> Result<Self, LoadModelError> {
        check_configs(std::slice::from_ref(&config))?;
        let params = config.init(seed).into_iter().map(|(_, _, d)| d).collect();
        Ok(Self::from_nets(vec![FastNet::from_params(config, params)?]))
    }

    /// Build from a trained network (the lab's trainer uses this; feature `train`).
    #[cfg(feature = "train")]
    pub fn from_trained(net: &Net) -> Result<Self, LoadModelError> {
        let config = net.config().clone();
        check_configs(std::slice::from_ref(&config))?;
        let params = net
            .params()
            .iter()
            .map(|t| t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>())
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self::from_nets(vec![FastNet::from_params(config, params)?]))
    }

    /// A fused model of the networks of `parts`, in order (see [`Embedder`]): e.g. a
    /// sequence network and a picture network of 64 dimensions each. Its version is the
    /// checksum of the fused file's tensors, so it differs from every part's.
    pub fn fuse(parts: &[Embedder]) -> Result<Self, LoadModelError> {
        let nets: Vec<FastNet> = parts.iter().flat_map(|p| p.nets.iter().cloned()).collect();
        let configs: Vec<NetConfig> = nets.iter().map(|n| n.config().clone()).collect();
        check_configs(&configs)?;
        Ok(Self::from_nets(nets))
    }

    /// The embedder of checked networks; the checksum is that of their tensors under their
    /// names in the file (see [`Embedder::version`]).
    fn from_nets(nets: Vec<FastNet>) -> Self {
        let sum = checksum(Self::named(&nets).iter());
        Self {
            version: version_of(&nets, &sum),
            nets: Arc::new(nets),
            checksum: sum,
        }
    }

    /// Every tensor of `nets` with its name in the file and its shape.
    fn named(nets: &[FastNet]) -> Vec<Named> {
        let mut out = Vec::new();
        for (b, net) in nets.iter().enumerate() {
            for ((name, shape), data) in net.config().param_shapes().into_iter().zip(net.params()) {
                out.push((tensor_name(nets.len(), b, &name), shape, data.to_vec()));
            }
        }
        out
    }

    /// Whether this model can embed plans of `robot`: pen-path models serve any arm; a model
    /// on joint features serves only a 7-joint robot (the Panda whose limits scale them).
    /// Every embedding call checks it.
    pub fn serves(&self, robot: &Robot) -> Result<(), EmbedError> {
        let joints = self
            .nets
            .iter()
            .any(|n| n.config().features == FeatureKind::Joints);
        if joints && robot.joints() != PANDA_JOINTS {
            return Err(EmbedError::JointFeaturesNeedPanda {
                robot: robot.name().to_string(),
            });
        }
        Ok(())
    }

    /// Embed one resampled trajectory of `robot` (fast path, see [`crate::sequence::forward`]).
    pub fn embed(&self, robot: &Robot, x: &Resampled) -> Result<Embedding, EmbedError> {
        let mut out = [[0.0f32; EMBED_DIM]];
        self.embed_into(robot, std::slice::from_ref(x), &mut out)?;
        Ok(out[0])
    }

    /// Embed a batch of resampled trajectories of `robot` (fast path, see [`crate::sequence::forward`]).
    pub fn embed_batch(
        &self,
        robot: &Robot,
        xs: &[Resampled],
    ) -> Result<Vec<Embedding>, EmbedError> {
        let mut out = vec![[0.0f32; EMBED_DIM]; xs.len()];
        self.embed_into(robot, xs, &mut out)?;
        Ok(out)
    }

    /// Embed `xs` into `out` (same length) with the fast path, using per-thread scratch
    /// buffers: after the first call with the largest batch, no allocation.
    pub fn embed_into(
        &self,
        robot: &Robot,
        xs: &[Resampled],
        out: &mut [Embedding],
    ) -> Result<(), EmbedError> {
        self.embed_into_with(
            robot,
            xs,
            out,
            |x: &Resampled| pen_path_with(robot, x),
            None,
        )
    }

    /// [`Embedder::embed`], also returning the pen path ([`guardian_robot::pen::pen_path`]) the
    /// features were computed from, so a caller that needs the path too (the plan geometry)
    /// does not run the forward kinematics of the 128 points a second time.
    pub fn embed_with_pen_path(
        &self,
        robot: &Robot,
        x: &Resampled,
    ) -> Result<(Embedding, [PenPoint; STEPS]), EmbedError> {
        let mut out = [[0.0f32; EMBED_DIM]];
        let mut path = [[[0.0f32; 3]; STEPS]];
        self.embed_into_with(
            robot,
            std::slice::from_ref(x),
            &mut out,
            |x: &Resampled| pen_path_with(robot, x),
            Some(&mut path),
        )?;
        Ok((out[0], path[0]))
    }

    /// [`Embedder::embed_batch`], also writing the pen path of `xs[i]` to `paths[i]` (same
    /// length as `xs`), as [`Embedder::embed_with_pen_path`] does for one trajectory.
    pub fn embed_batch_with_pen_paths(
        &self,
        robot: &Robot,
        xs: &[Resampled],
        paths: &mut [[PenPoint; STEPS]],
    ) -> Result<Vec<Embedding>, EmbedError> {
        if paths.len() != xs.len() {
            return Err(EmbedError::OutputLength {
                expected: xs.len(),
                got: paths.len(),
            });
        }
        let mut out = vec![[0.0f32; EMBED_DIM]; xs.len()];
        self.embed_into_with(
            robot,
            xs,
            &mut out,
            |x: &Resampled| pen_path_with(robot, x),
            Some(paths),
        )?;
        Ok(out)
    }

    /// [`Embedder::embed`] with the pen path through the general kinematic chain
    /// ([`guardian_robot::pen::pen_path_reference`]) instead of the specialised position FK:
    /// the path as it was before the specialised FK, kept as the reference the fast path is
    /// tested against (`lab/tests/embed_equivalence.rs`; feature `test-support`).
    #[cfg(any(test, feature = "test-support"))]
    pub fn embed_reference(&self, robot: &Robot, x: &Resampled) -> Result<Embedding, EmbedError> {
        let mut out = [[0.0f32; EMBED_DIM]];
        self.embed_into_with(
            robot,
            std::slice::from_ref(x),
            &mut out,
            |x: &Resampled| guardian_robot::pen::pen_path_reference_with(robot, x),
            None,
        )?;
        Ok(out[0])
    }

    /// The features come from the pen path `pen_path` computes. With `path` (as long as
    /// `xs`), the pen path of `xs[i]` is written to `path[i]`.
    fn embed_into_with<P: PenPathFn>(
        &self,
        robot: &Robot,
        xs: &[Resampled],
        out: &mut [Embedding],
        pen_path: P,
        path: Option<&mut [[PenPoint; STEPS]]>,
    ) -> Result<(), EmbedError> {
        if out.len() != xs.len() {
            return Err(EmbedError::OutputLength {
                expected: xs.len(),
                got: out.len(),
            });
        }
        self.serves(robot)?;
        if xs.is_empty() {
            return Ok(());
        }
        check_finite(xs)?;
        SCRATCH.with(|cell| match cell.try_borrow_mut() {
            Ok(mut s) => self.embed_fast(xs, out, &mut s, pen_path, path),
            // Re-entered on this thread (cannot happen today): use a fresh scratch.
            Err(_) => self.embed_fast(xs, out, &mut EmbedScratch::default(), pen_path, path),
        })
    }

    /// The pen paths once, then every network on its view of them, each writing its part of
    /// the embedding.
    fn embed_fast<P: PenPathFn>(
        &self,
        xs: &[Resampled],
        out: &mut [Embedding],
        s: &mut EmbedScratch,
        pen_path: P,
        path: Option<&mut [[PenPoint; STEPS]]>,
    ) -> Result<(), EmbedError> {
        if s.paths.len() < xs.len() {
            s.paths.resize(xs.len(), [[0.0; 3]; STEPS]);
        }
        let paths = &mut s.paths[..xs.len()];
        for (p, x) in paths.iter_mut().zip(xs) {
            *p = pen_path(x);
        }
        if let Some(path) = path {
            path.copy_from_slice(paths);
        }
        if s.nets.len() < self.nets.len() {
            s.nets.resize_with(self.nets.len(), Scratch::default);
        }
        let scale = branch_scale(self.nets.len());
        let mut offset = 0;
        for (net, scratch) in self.nets.iter().zip(&mut s.nets) {
            let config = net.config();
            let copies = features_into(config, xs, paths, &mut s.feats);
            let rows = copies * xs.len();
            let d = config.embed_dim;
            if s.raw.len() < rows * d {
                s.raw.resize(rows * d, 0.0);
            }
            let raw = &mut s.raw[..rows * d];
            let kind = config.features;
            net.forward(
                &s.feats[..rows * kind.values()],
                rows,
                kind.steps(),
                scratch,
                raw,
            )?;
            for (o, r) in out.iter_mut().zip(raw.chunks_exact(copies * d)) {
                let o = &mut o[offset..offset + d];
                average_copies(r, d, config.l2_normalize, o);
                if let Some(scale) = scale {
                    for v in o.iter_mut() {
                        *v *= scale;
                    }
                }
            }
            offset += d;
        }
        for (index, o) in out.iter_mut().enumerate() {
            o[offset..].fill(0.0);
            if o.iter().any(|v| !v.is_finite()) {
                return Err(EmbedError::NonFiniteOutput { index });
            }
        }
        Ok(())
    }

    /// Embed a batch with candle's forward pass — the reference the fast path is tested
    /// against (feature `test-support`).
    #[cfg(all(feature = "train", any(test, feature = "test-support")))]
    pub fn embed_batch_reference(
        &self,
        robot: &Robot,
        xs: &[Resampled],
    ) -> Result<Vec<Embedding>, EmbedError> {
        self.serves(robot)?;
        if xs.is_empty() {
            return Ok(Vec::new());
        }
        check_finite(xs)?;
        let paths: Vec<[PenPoint; STEPS]> = xs.iter().map(|x| pen_path_with(robot, x)).collect();
        let mut embs = vec![[0.0f32; EMBED_DIM]; xs.len()];
        let mut offset = 0;
        for net in self.nets.iter() {
            let config = net.config();
            let kind = config.features;
            let d = config.embed_dim;
            let mut feats = Vec::new();
            let copies = features_into(config, xs, &paths, &mut feats);
            let input = Tensor::from_vec(
                feats,
                (copies * xs.len(), kind.steps(), kind.channels()),
                &Device::Cpu,
            )?;
            let mut e = net.to_net()?.forward(&input)?;
            if copies > 1 {
                e = e.reshape((xs.len(), copies, d))?.mean(1)?;
                if config.l2_normalize {
                    let norm = (e.sqr()?.sum_keepdim(1)? + 1e-12)?.sqrt()?;
                    e = e.broadcast_div(&norm)?;
                }
            }
            if let Some(scale) = branch_scale(self.nets.len()) {
                e = (e * f64::from(scale))?;
            }
            let values = e.flatten_all()?.to_vec1::<f32>()?;
            for (index, (o, chunk)) in embs.iter_mut().zip(values.chunks_exact(d)).enumerate() {
                if chunk.iter().any(|v| !v.is_finite()) {
                    return Err(EmbedError::NonFiniteOutput { index });
                }
                o[offset..offset + d].copy_from_slice(chunk);
            }
            offset += d;
        }
        Ok(embs)
    }

    /// The networks: one, or the branches of a fused model in embedding order.
    pub fn nets(&self) -> &[FastNet] {
        &self.nets
    }

    /// The networks' architectures, in embedding order.
    pub fn configs(&self) -> Vec<&NetConfig> {
        self.nets.iter().map(FastNet::config).collect()
    }

    /// Floating-point operations of the networks for one plan (every copy a network reads:
    /// both directions of a reverse-averaged network, its test views).
    pub fn flops(&self) -> u64 {
        self.nets
            .iter()
            .map(|n| {
                let c = n.config();
                c.copies() as u64 * n.flops(c.features.steps())
            })
            .sum()
    }

    /// Stable id: the first 16 hex characters of the SHA-256 over the weights ([`checksum`]);
    /// a model with test-time views ([`NetConfig::test_views`]) has its own, hashed from the
    /// checksum and the views, since its embeddings differ.
    ///
    /// [`checksum`]: Embedder::checksum
    pub fn version(&self) -> &str {
        &self.version
    }

    /// The full SHA-256 over the weights (hex).
    pub fn checksum(&self) -> &str {
        &self.checksum
    }

    /// Turn test-time reverse averaging on or off for every network on the pen features
    /// (see [`NetConfig::reverse_average`]); the weights and the version are unchanged.
    pub fn set_reverse_average(&mut self, on: bool) {
        for net in Arc::make_mut(&mut self.nets) {
            net.set_reverse_average(on);
        }
    }

    /// Set the test-time views of every network on the pen features (see
    /// [`NetConfig::test_views`]; at most [`crate::net::MAX_TEST_VIEWS`]). The weights are
    /// unchanged; the version is that of the weights with these views (see
    /// [`Embedder::version`]).
    pub fn set_test_views(&mut self, views: &[crate::net::TestView]) -> Result<(), EmbedError> {
        let pen = |net: &&mut FastNet| net.config().features != FeatureKind::Joints;
        let mut nets = self.nets.as_ref().clone();
        for net in nets.iter_mut().filter(pen) {
            net.set_test_views(views);
            net.config().check().map_err(EmbedError::Config)?;
        }
        self.nets = Arc::new(nets);
        self.version = version_of(&self.nets, &self.checksum);
        Ok(())
    }

    /// The weights of a single-network model as a candle network (for training and analysis;
    /// feature `train`). `None` for a fused model.
    #[cfg(feature = "train")]
    pub fn net(&self) -> Option<candle_core::Result<Net>> {
        match self.nets.as_slice() {
            [net] => Some(net.to_net()),
            _ => None,
        }
    }
}

/// The version of `nets` whose tensors hash to `checksum`: its first 16 hex characters, or,
/// when a network has test-time views (which change every embedding, so a bank enrolled
/// without them must not pass for one enrolled with them), those of the SHA-256 over the
/// checksum and every network's views.
fn version_of(nets: &[FastNet], checksum: &str) -> String {
    if nets.iter().all(|n| n.config().test_views.is_empty()) {
        return checksum[..16].to_string();
    }
    let mut h = Sha256::new();
    h.update(checksum.as_bytes());
    for net in nets {
        let views = &net.config().test_views;
        h.update((views.len() as u64).to_le_bytes());
        for v in views {
            for x in [v.rotation, v.shear, v.stretch] {
                h.update(x.to_le_bytes());
            }
        }
    }
    h.finalize()[..8]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// What each branch's embedding is multiplied by: `1/√branches` for a fused model (so the
/// concatenation is a unit vector), nothing for a single network.
fn branch_scale(branches: usize) -> Option<f32> {
    (branches > 1).then(|| 1.0 / (branches as f32).sqrt())
}

/// Write the input of a network with `config` for `xs` into `feats` (grown as needed): per
/// trajectory [`NetConfig::copies`] feature sequences (from its pen path in `paths`, or one
/// from its joints): the plan's own path, then each test view, each followed by its reverse
/// with reverse averaging. Returns the number of sequences per trajectory.
fn features_into(
    config: &NetConfig,
    xs: &[Resampled],
    paths: &[[PenPoint; STEPS]],
    feats: &mut Vec<f32>,
) -> usize {
    let kind = config.features;
    let v = kind.values();
    let copies = config.copies();
    let n = copies * xs.len() * v;
    if feats.len() < n {
        feats.resize(n, 0.0);
    }
    let feats = &mut feats[..n];
    let directions: &[bool] = if config.reverse_average {
        &[false, true]
    } else {
        &[false]
    };
    let own = crate::net::TestView::default();
    for ((x, path), out) in xs.iter().zip(paths).zip(feats.chunks_exact_mut(copies * v)) {
        if kind == FeatureKind::Joints {
            crate::features::compute(kind, x, out);
            continue;
        }
        let augments = std::iter::once(&own)
            .chain(&config.test_views)
            .flat_map(|view| directions.iter().map(|&r| Augment::of_view(view, r)));
        for (aug, out) in augments.zip(out.chunks_exact_mut(v)) {
            crate::features::path_features(kind, path, &aug, out);
        }
    }
    copies
}

/// The mean of a plan's `copies` raw embeddings (rows of `raw`, `d` wide) into `out`,
/// re-normalised when the network normalises.
fn average_copies(raw: &[f32], d: usize, l2_normalize: bool, out: &mut [f32]) {
    let copies = raw.len() / d;
    if copies == 1 {
        out.copy_from_slice(raw);
        return;
    }
    out.fill(0.0);
    for r in raw.chunks_exact(d) {
        for (v, x) in out.iter_mut().zip(r) {
            *v += x;
        }
    }
    for v in out.iter_mut() {
        *v /= copies as f32;
    }
    if l2_normalize {
        let norm = (out.iter().map(|v| v * v).sum::<f32>() + 1e-12).sqrt();
        for v in out.iter_mut() {
            *v /= norm;
        }
    }
}

fn check_finite(xs: &[Resampled]) -> Result<(), EmbedError> {
    for (index, x) in xs.iter().enumerate() {
        if x.iter().flatten().any(|v| !v.is_finite()) {
            return Err(EmbedError::NonFinite { index });
        }
    }
    Ok(())
}

/// Per-thread buffers of [`Embedder::embed_into`].
#[derive(Debug, Default)]
struct EmbedScratch {
    paths: Vec<[PenPoint; STEPS]>,
    feats: Vec<f32>,
    raw: Vec<f32>,
    /// One per network of the model.
    nets: Vec<Scratch>,
}

thread_local! {
    static SCRATCH: RefCell<EmbedScratch> = RefCell::new(EmbedScratch::default());
}

/// Squared Euclidean distance between two embeddings.
pub fn sq_dist(a: &Embedding, b: &Embedding) -> f32 {
    a.iter().zip(b.iter()).map(|(x, y)| (x - y) * (x - y)).sum()
}

#[cfg(test)]
mod tests;

/// The embedder's fast path against candle's forward pass of the same weights (feature
/// `train`, on in the workspace's test run).
#[cfg(all(test, feature = "train"))]
mod reference_tests;
