//! The inference-side embedder: load/save a trained network, embed resampled trajectories.
//!
//! An embedder holds a network, not a robot: every call names the robot whose forward
//! kinematics turns a trajectory into the pen-tip path the network sees (the daemon's
//! [`crate::check::Station`] owns it), so one trained model screens any arm drawing the same
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

use crate::fast::{FastNet, FastNetError, Scratch};
use crate::features::{Augment, FeatureKind, PenPoint, pen_path_with};
use crate::kinematics::{PANDA_JOINTS, Robot};
#[cfg(feature = "train")]
use crate::net::Net;
use crate::net::NetConfig;

pub use crate::net::EMBED_DIM;

/// How a pen path is computed from a resampled trajectory: [`pen_path_with`] the served robot, or
/// the general-chain reference the tests compare it with. A type parameter rather than a
/// function pointer, so the serving path calls `pen_path` directly.
trait PenPathFn: Fn(&Resampled) -> [PenPoint; STEPS] + Copy {}
impl<F: Fn(&Resampled) -> [PenPoint; STEPS] + Copy> PenPathFn for F {}
/// One embedding.
pub type Embedding = [f32; EMBED_DIM];

/// Value of the `input-shape` metadata key (the file format's, whatever the robot).
const INPUT_SHAPE: &str = "128x8";

/// Value of the `format` metadata key.
pub const FORMAT: &str = "guardian-embedder/1";

/// Loading a model file failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadModelError {
    /// The file could not be read.
    #[error("cannot read model file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The bytes are not a valid safetensors file (truncated, corrupt header, ...).
    #[error("model file is not valid safetensors: {0}")]
    Format(String),
    /// A metadata key is missing.
    #[error("model file lacks metadata key `{key}`")]
    MissingMetadata {
        /// The key.
        key: &'static str,
    },
    /// A metadata value is not what this build understands.
    #[error("model metadata `{key}`: expected {expected}, got {got}")]
    BadMetadata {
        /// The key.
        key: &'static str,
        /// What was expected.
        expected: String,
        /// What the file says.
        got: String,
    },
    /// A parameter tensor is missing.
    #[error("model file lacks tensor `{name}`")]
    MissingTensor {
        /// Tensor name.
        name: String,
    },
    /// The file holds a tensor the architecture does not use.
    #[error("model file has unexpected tensor `{name}`")]
    UnexpectedTensor {
        /// Tensor name.
        name: String,
    },
    /// The network config names a feature kind this build does not know (e.g. one that
    /// was removed: a model trained on it cannot be served).
    #[error("model config names unknown feature kind `{got}`")]
    UnknownFeatureKind {
        /// The kind the file names.
        got: String,
    },
    /// A tensor has the wrong shape or dtype.
    #[error("tensor `{name}`: expected f32 {expected:?}, got {dtype} {got:?}")]
    ShapeMismatch {
        /// Tensor name.
        name: String,
        /// Expected shape.
        expected: Vec<usize>,
        /// Shape in the file.
        got: Vec<usize>,
        /// Dtype in the file.
        dtype: String,
    },
    /// The tensors do not hash to the recorded checksum (flipped bits, edited weights).
    #[error("model checksum mismatch: metadata says {expected}, tensors hash to {got}")]
    ChecksumMismatch {
        /// Checksum in the metadata.
        expected: String,
        /// Checksum of the tensors.
        got: String,
    },
    /// A weight is NaN or infinite.
    #[error("tensor `{name}` holds a non-finite value")]
    NonFinite {
        /// Tensor name.
        name: String,
    },
    /// Building the network failed.
    #[cfg(feature = "train")]
    #[error("building the network: {0}")]
    Candle(#[from] candle_core::Error),
    /// Building the fast path failed.
    #[error("building the fast path: {0}")]
    Fast(#[from] FastNetError),
}

/// Saving a model file failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SaveModelError {
    /// Serialising failed.
    #[error("serialising safetensors: {0}")]
    Serialize(String),
    /// Writing, syncing or renaming failed.
    #[error("writing model file {path}: {source}")]
    Io {
        /// The file being written (the temporary file or the target).
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

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
    /// The network produced a non-finite embedding.
    #[error("embedding {index} is non-finite")]
    NonFiniteOutput {
        /// Index of the input in the batch.
        index: usize,
    },
}

/// A trained (or random) embedding network with its feature computation. `Send + Sync`.
/// The weights live in the fast path's buffers alone ([`FastNet`], loaded straight from the
/// file); a candle network is built from them only on request (feature `train`).
#[derive(Debug, Clone)]
pub struct Embedder {
    fast: Arc<FastNet>,
    version: String,
    checksum: String,
}

impl Embedder {
    /// Load and verify a model file.
    pub fn load(path: &Path) -> Result<Self, LoadModelError> {
        let bytes = std::fs::read(path).map_err(|source| LoadModelError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }

    /// Parse and verify a model from the bytes of a file.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, LoadModelError> {
        let st =
            SafeTensors::deserialize(bytes).map_err(|e| LoadModelError::Format(e.to_string()))?;
        let (_, header) =
            SafeTensors::read_metadata(bytes).map_err(|e| LoadModelError::Format(e.to_string()))?;
        let empty = HashMap::new();
        let meta = header.metadata().as_ref().unwrap_or(&empty);
        let get = |key: &'static str| {
            meta.get(key)
                .map(String::as_str)
                .ok_or(LoadModelError::MissingMetadata { key })
        };
        let format = get("format")?;
        if format != FORMAT {
            return Err(LoadModelError::BadMetadata {
                key: "format",
                expected: FORMAT.into(),
                got: format.into(),
            });
        }
        let input_shape = get("input-shape")?;
        let want_shape = INPUT_SHAPE.to_string();
        if input_shape != want_shape {
            return Err(LoadModelError::BadMetadata {
                key: "input-shape",
                expected: want_shape,
                got: input_shape.into(),
            });
        }
        let embed_dim = get("embed-dim")?;
        if embed_dim != EMBED_DIM.to_string() {
            return Err(LoadModelError::BadMetadata {
                key: "embed-dim",
                expected: EMBED_DIM.to_string(),
                got: embed_dim.into(),
            });
        }
        let config_json = get("config")?;
        let config: NetConfig = serde_json::from_str(config_json).map_err(|e| {
            match unknown_feature_kind(config_json) {
                Some(got) => LoadModelError::UnknownFeatureKind { got },
                None => LoadModelError::BadMetadata {
                    key: "config",
                    expected: "a network config".into(),
                    got: format!("{config_json} ({e})"),
                },
            }
        })?;
        if config.embed_dim != EMBED_DIM {
            return Err(LoadModelError::BadMetadata {
                key: "config",
                expected: format!("embed-dim {EMBED_DIM}"),
                got: config.embed_dim.to_string(),
            });
        }
        config.check().map_err(|e| LoadModelError::BadMetadata {
            key: "config",
            expected: "a valid network config".into(),
            got: e,
        })?;
        let expected_sum = get("sha256")?.to_string();

        let shapes = config.param_shapes();
        for name in st.names() {
            if !shapes.iter().any(|(n, _)| n == name) {
                return Err(LoadModelError::UnexpectedTensor { name: name.into() });
            }
        }
        let mut named: Vec<(String, Vec<usize>, Vec<f32>)> = Vec::with_capacity(shapes.len());
        for (name, shape) in &shapes {
            let view = st
                .tensor(name)
                .map_err(|_| LoadModelError::MissingTensor { name: name.clone() })?;
            if view.dtype() != Dtype::F32 || view.shape() != shape.as_slice() {
                return Err(LoadModelError::ShapeMismatch {
                    name: name.clone(),
                    expected: shape.clone(),
                    got: view.shape().to_vec(),
                    dtype: format!("{:?}", view.dtype()),
                });
            }
            let data: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            named.push((name.clone(), shape.clone(), data));
        }
        let got_sum = checksum(&named);
        if got_sum != expected_sum {
            return Err(LoadModelError::ChecksumMismatch {
                expected: expected_sum,
                got: got_sum,
            });
        }
        if let Some((name, _, _)) = named
            .iter()
            .find(|(_, _, d)| d.iter().any(|v| !v.is_finite()))
        {
            return Err(LoadModelError::NonFinite { name: name.clone() });
        }
        Self::from_named(config, named)
    }

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
        config.check().map_err(|e| LoadModelError::BadMetadata {
            key: "config",
            expected: "a valid network config".into(),
            got: e,
        })?;
        let named = config.init(seed);
        Self::from_named(config, named)
    }

    /// Build from a trained network (the lab's trainer uses this; feature `train`).
    #[cfg(feature = "train")]
    pub fn from_trained(net: &Net) -> Result<Self, LoadModelError> {
        let config = net.config().clone();
        let named = config
            .param_shapes()
            .into_iter()
            .zip(net.params())
            .map(|((name, shape), t)| {
                let data = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
                Ok((name, shape, data))
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        Self::from_named(config, named)
    }

    /// The embedder of named parameters in [`NetConfig::param_shapes`] order: their values
    /// go straight into the fast path's buffers; the version is their checksum.
    fn from_named(
        config: NetConfig,
        named: Vec<(String, Vec<usize>, Vec<f32>)>,
    ) -> Result<Self, LoadModelError> {
        let sum = checksum(&named);
        let params = named.into_iter().map(|(_, _, d)| d).collect();
        Ok(Self {
            fast: Arc::new(FastNet::from_params(config, params)?),
            version: sum[..16].to_string(),
            checksum: sum,
        })
    }

    /// Whether this model can embed plans of `robot`: pen-path models serve any arm; a model
    /// on joint features serves only a 7-joint robot (the Panda whose limits scale them).
    /// Every embedding call checks it.
    pub fn serves(&self, robot: &Robot) -> Result<(), EmbedError> {
        if self.fast.config().features == FeatureKind::Joints && robot.joints() != PANDA_JOINTS {
            return Err(EmbedError::JointFeaturesNeedPanda {
                robot: robot.name().to_string(),
            });
        }
        Ok(())
    }

    /// Write the model atomically: a temporary file beside `path`, fsync, rename.
    pub fn save(&self, path: &Path) -> Result<(), SaveModelError> {
        let bytes = self.to_bytes()?;
        let dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let file_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "model".into());
        let tmp = dir.join(format!(".{file_name}.tmp{}", std::process::id()));
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| SaveModelError::Io { path, source }
        };
        let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        f.write_all(&bytes).map_err(io(&tmp))?;
        f.sync_all().map_err(io(&tmp))?;
        drop(f);
        std::fs::rename(&tmp, path).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            SaveModelError::Io {
                path: path.to_path_buf(),
                source: e,
            }
        })?;
        // Persist the rename itself.
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
        Ok(())
    }

    /// The model file's bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, SaveModelError> {
        let shapes = self.fast.config().param_shapes();
        let mut buffers = Vec::with_capacity(shapes.len());
        for ((name, shape), data) in shapes.into_iter().zip(self.fast.params()) {
            let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
            buffers.push((name, shape, bytes));
        }
        let views = buffers
            .iter()
            .map(|(name, shape, bytes)| {
                TensorView::new(Dtype::F32, shape.clone(), bytes).map(|v| (name.clone(), v))
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| SaveModelError::Serialize(e.to_string()))?;
        let config = serde_json::to_string(self.fast.config())
            .map_err(|e| SaveModelError::Serialize(e.to_string()))?;
        let meta = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("config".to_string(), config),
            ("input-shape".to_string(), INPUT_SHAPE.to_string()),
            ("embed-dim".to_string(), EMBED_DIM.to_string()),
            ("sha256".to_string(), self.checksum.clone()),
        ]);
        safetensors::serialize(views, Some(meta))
            .map_err(|e| SaveModelError::Serialize(e.to_string()))
    }

    /// Embed one resampled trajectory of `robot` (fast path, see [`crate::fast`]).
    pub fn embed(&self, robot: &Robot, x: &Resampled) -> Result<Embedding, EmbedError> {
        let mut out = [[0.0f32; EMBED_DIM]];
        self.embed_into(robot, std::slice::from_ref(x), &mut out)?;
        Ok(out[0])
    }

    /// Embed a batch of resampled trajectories of `robot` (fast path, see [`crate::fast`]).
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

    /// [`Embedder::embed`], also returning the pen path ([`crate::features::pen_path`]) the
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
    /// ([`crate::features::pen_path_reference`]) instead of the specialised position FK:
    /// the path as it was before the specialised FK, kept as the reference the fast path is
    /// tested against (`lab/tests/embed_equivalence.rs`; feature `test-support`).
    #[cfg(any(test, feature = "test-support"))]
    pub fn embed_reference(&self, robot: &Robot, x: &Resampled) -> Result<Embedding, EmbedError> {
        let mut out = [[0.0f32; EMBED_DIM]];
        self.embed_into_with(
            robot,
            std::slice::from_ref(x),
            &mut out,
            |x: &Resampled| crate::features::pen_path_reference_with(robot, x),
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
            Ok(mut s) => self.embed_fast(robot, xs, out, &mut s, pen_path, path),
            // Re-entered on this thread (cannot happen today): use a fresh scratch.
            Err(_) => self.embed_fast(robot, xs, out, &mut EmbedScratch::default(), pen_path, path),
        })
    }

    fn embed_fast<P: PenPathFn>(
        &self,
        robot: &Robot,
        xs: &[Resampled],
        out: &mut [Embedding],
        s: &mut EmbedScratch,
        pen_path: P,
        path: Option<&mut [[PenPoint; STEPS]]>,
    ) -> Result<(), EmbedError> {
        let copies = self.features_into(robot, xs, &mut s.feats, pen_path, path);
        let rows = copies * xs.len();
        let raw = if s.raw.len() < rows * EMBED_DIM {
            s.raw.resize(rows * EMBED_DIM, 0.0);
            &mut s.raw[..]
        } else {
            &mut s.raw[..rows * EMBED_DIM]
        };
        let kind = self.fast.config().features;
        self.fast.forward(
            &s.feats[..rows * kind.values()],
            rows,
            kind.steps(),
            &mut s.net,
            raw,
        )?;
        for (index, (o, r)) in out
            .iter_mut()
            .zip(raw.chunks_exact(copies * EMBED_DIM))
            .enumerate()
        {
            if copies == 2 {
                let (a, b) = r.split_at(EMBED_DIM);
                for ((v, x), y) in o.iter_mut().zip(a).zip(b) {
                    *v = (x + y) / 2.0;
                }
                if self.fast.config().l2_normalize {
                    let norm = (o.iter().map(|v| v * v).sum::<f32>() + 1e-12).sqrt();
                    for v in o.iter_mut() {
                        *v /= norm;
                    }
                }
            } else {
                o.copy_from_slice(r);
            }
            if o.iter().any(|v| !v.is_finite()) {
                return Err(EmbedError::NonFiniteOutput { index });
            }
        }
        Ok(())
    }

    /// Write the network input for `xs` into `feats` (grown as needed): per trajectory one
    /// feature sequence, or two (forwards, then time-reversed) with reverse averaging.
    /// Returns the number of sequences per trajectory.
    /// The pen path comes from `pen_path` ([`crate::features::pen_path`], or the general
    /// kinematic chain for the reference). With `path_out`, the pen path of trajectory `i` is
    /// written to `path_out[i]`.
    fn features_into<P: PenPathFn>(
        &self,
        robot: &Robot,
        xs: &[Resampled],
        feats: &mut Vec<f32>,
        pen_path: P,
        mut path_out: Option<&mut [[PenPoint; STEPS]]>,
    ) -> usize {
        let kind = self.fast.config().features;
        let v = kind.values();
        let both = self.fast.config().reverse_average && kind != FeatureKind::Joints;
        let copies = if both { 2 } else { 1 };
        let n = copies * xs.len() * v;
        if feats.len() < n {
            feats.resize(n, 0.0);
        }
        let feats = &mut feats[..n];
        let reverse = Augment {
            reverse: true,
            ..Augment::default()
        };
        for (i, (x, out)) in xs
            .iter()
            .zip(feats.chunks_exact_mut(copies * v))
            .enumerate()
        {
            let path_slot = path_out.as_deref_mut().and_then(|p| p.get_mut(i));
            if kind == FeatureKind::Joints {
                crate::features::compute(kind, x, out);
                if let Some(p) = path_slot {
                    *p = pen_path_with(robot, x);
                }
                continue;
            }
            let path = pen_path(x);
            if let Some(p) = path_slot {
                *p = path;
            }
            let (fwd, bwd) = out.split_at_mut(v);
            crate::features::path_features(kind, &path, &Augment::default(), fwd);
            if both {
                crate::features::path_features(kind, &path, &reverse, bwd);
            }
        }
        copies
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
        let kind = self.fast.config().features;
        let mut feats = Vec::new();
        let copies = self.features_into(
            robot,
            xs,
            &mut feats,
            |x: &Resampled| pen_path_with(robot, x),
            None,
        );
        let input = Tensor::from_vec(
            feats,
            (copies * xs.len(), kind.steps(), kind.channels()),
            &Device::Cpu,
        )?;
        let mut e = self.fast.to_net()?.forward(&input)?;
        if copies == 2 {
            e = e.reshape((xs.len(), 2, EMBED_DIM))?.mean(1)?;
            if self.fast.config().l2_normalize {
                let norm = (e.sqr()?.sum_keepdim(1)? + 1e-12)?.sqrt()?;
                e = e.broadcast_div(&norm)?;
            }
        }
        let out = e.flatten_all()?.to_vec1::<f32>()?;
        let mut embs = Vec::with_capacity(xs.len());
        for (index, chunk) in out.chunks_exact(EMBED_DIM).enumerate() {
            if chunk.iter().any(|v| !v.is_finite()) {
                return Err(EmbedError::NonFiniteOutput { index });
            }
            let mut e = [0.0f32; EMBED_DIM];
            e.copy_from_slice(chunk);
            embs.push(e);
        }
        Ok(embs)
    }

    /// The fast-path network: the weights.
    pub fn fast(&self) -> &FastNet {
        &self.fast
    }

    /// Stable id: the first 16 hex characters of the SHA-256 over the weights.
    pub fn version(&self) -> &str {
        &self.version
    }

    /// The full SHA-256 over the weights (hex).
    pub fn checksum(&self) -> &str {
        &self.checksum
    }

    /// The architecture.
    pub fn config(&self) -> &NetConfig {
        self.fast.config()
    }

    /// Turn test-time reverse averaging on or off (see [`NetConfig::reverse_average`]); the
    /// weights and the version are unchanged.
    pub fn set_reverse_average(&mut self, on: bool) {
        Arc::make_mut(&mut self.fast).set_reverse_average(on);
    }

    /// The weights as a candle network (for training and analysis; feature `train`).
    #[cfg(feature = "train")]
    pub fn net(&self) -> candle_core::Result<Net> {
        self.fast.to_net()
    }
}

/// The `features` a network config JSON names, if it is not a [`FeatureKind`] this build
/// knows.
fn unknown_feature_kind(config_json: &str) -> Option<String> {
    let value: serde_json::Value = serde_json::from_str(config_json).ok()?;
    let features = value.get("features")?;
    let known = serde_json::from_value::<crate::features::FeatureKind>(features.clone()).is_ok();
    (!known).then(|| match features.as_str() {
        Some(name) => name.to_string(),
        None => features.to_string(),
    })
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
    feats: Vec<f32>,
    raw: Vec<f32>,
    net: Scratch,
}

thread_local! {
    static SCRATCH: RefCell<EmbedScratch> = RefCell::new(EmbedScratch::default());
}

/// Squared Euclidean distance between two embeddings.
pub fn sq_dist(a: &Embedding, b: &Embedding) -> f32 {
    a.iter().zip(b.iter()).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// SHA-256 (hex) over tensors in name order: name bytes, shape (u64 LE each), f32 LE data.
fn checksum(named: &[(String, Vec<usize>, Vec<f32>)]) -> String {
    let mut order: Vec<&(String, Vec<usize>, Vec<f32>)> = named.iter().collect();
    order.sort_by(|a, b| a.0.cmp(&b.0));
    let mut h = Sha256::new();
    for (name, shape, data) in order {
        h.update((name.len() as u64).to_le_bytes());
        h.update(name.as_bytes());
        h.update((shape.len() as u64).to_le_bytes());
        for &d in shape {
            h.update((d as u64).to_le_bytes());
        }
        for v in data {
            h.update(v.to_le_bytes());
        }
    }
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(phase: f32) -> Resampled {
        let mut x = [[0.0f32; guardian_shared::trajectory::SLOTS]; STEPS];
        for (t, w) in x.iter_mut().enumerate() {
            let s = t as f32 / STEPS as f32;
            let row = [
                0.1 * (6.0 * s + phase).sin(),
                0.2 + 0.1 * (4.0 * s + phase).cos(),
                0.0,
                -2.0 + 0.1 * s,
                0.0,
                2.2,
                0.78,
            ];
            *w = guardian_shared::trajectory::waypoint(&row, if t % 40 < 30 { 1.0 } else { 0.0 });
        }
        x
    }

    fn assert_send_sync<T: Send + Sync>() {}

    #[test]
    fn round_trip_is_exact_and_versioned() {
        assert_send_sync::<Embedder>();
        let e = Embedder::random(5);
        assert_eq!(e.version().len(), 16);
        assert_eq!(Embedder::random(5).version(), e.version());
        assert_ne!(Embedder::random(6).version(), e.version());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.safetensors");
        e.save(&path).unwrap();
        let back = Embedder::load(&path).unwrap();
        assert_eq!(back.version(), e.version());
        let xs = [sample(0.0), sample(1.0)];
        let a = e
            .embed_batch(crate::preprocess::default_panda(), &xs)
            .unwrap();
        let b = back
            .embed_batch(crate::preprocess::default_panda(), &xs)
            .unwrap();
        assert_eq!(a, b);
        assert_eq!(
            e.embed(crate::preprocess::default_panda(), &xs[1]).unwrap(),
            a[1]
        );
        let norm: f32 = a[0].iter().map(|v| v * v).sum();
        assert!((norm - 1.0).abs() < 1e-4);
        assert!(sq_dist(&a[0], &a[1]) > 0.0);
        assert_eq!(sq_dist(&a[0], &a[0]), 0.0);
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn reverse_averaging_makes_drawing_direction_irrelevant() {
        let mut e = Embedder::random(3);
        let x = sample(0.3);
        let mut rev = x;
        rev.reverse();
        let plain = e
            .embed_batch(crate::preprocess::default_panda(), &[x, rev])
            .unwrap();
        assert!(sq_dist(&plain[0], &plain[1]) > 1e-6);
        e.set_reverse_average(true);
        let version = e.version().to_string();
        let avg = e
            .embed_batch(crate::preprocess::default_panda(), &[x, rev])
            .unwrap();
        assert!(sq_dist(&avg[0], &avg[1]) < 1e-8);
        assert_eq!(e.version(), version);
        // The option survives a save/load round trip.
        let back = Embedder::from_bytes(&e.to_bytes().unwrap()).unwrap();
        assert!(back.config().reverse_average);
        assert_eq!(
            back.embed(crate::preprocess::default_panda(), &x).unwrap(),
            avg[0]
        );
    }

    #[test]
    fn corrupt_files_are_refused() {
        let e = Embedder::random(1);
        let bytes = e.to_bytes().unwrap();
        // Truncated.
        let err = Embedder::from_bytes(&bytes[..bytes.len() - 10]).unwrap_err();
        assert!(matches!(err, LoadModelError::Format(_)), "{err}");
        // A flipped bit in the last weight.
        let mut flipped = bytes.clone();
        let n = flipped.len();
        flipped[n - 2] ^= 0x10;
        let err = Embedder::from_bytes(&flipped).unwrap_err();
        assert!(
            matches!(err, LoadModelError::ChecksumMismatch { .. }),
            "{err}"
        );
        // Wrong shape: a file for another architecture, relabelled with this config.
        let other = Embedder::random_with(
            NetConfig {
                channels: vec![32, 128, 128],
                ..NetConfig::default()
            },
            1,
        )
        .unwrap();
        let other_bytes = other.to_bytes().unwrap();
        let mut wrong = other_bytes.clone();
        let pat = b"[32,128,128]";
        let at = wrong
            .windows(pat.len())
            .position(|w| w == pat)
            .expect("config in header");
        wrong[at..at + pat.len()].copy_from_slice(b"[64,128,128]");
        // The header length stays the same, so it still parses; the shapes must not pass.
        let err = Embedder::from_bytes(&wrong).unwrap_err();
        assert!(matches!(err, LoadModelError::ShapeMismatch { .. }), "{err}");
        // Not a model at all.
        let err = Embedder::from_bytes(b"hello").unwrap_err();
        assert!(matches!(err, LoadModelError::Format(_)), "{err}");
        let err = Embedder::load(Path::new("/nonexistent/model.safetensors")).unwrap_err();
        assert!(matches!(err, LoadModelError::Read { .. }), "{err}");
    }

    /// `bytes` with the JSON header's `from` replaced by `to` (the header re-padded to 8).
    fn edit_header(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
        let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        let header = std::str::from_utf8(&bytes[8..8 + n]).unwrap();
        assert!(header.contains(from), "{header}");
        let mut header = header.trim_end().replace(from, to).into_bytes();
        header.resize(header.len().next_multiple_of(8), b' ');
        let mut out = (header.len() as u64).to_le_bytes().to_vec();
        out.extend(header);
        out.extend(&bytes[8 + n..]);
        out
    }

    #[test]
    fn a_model_file_with_an_unknown_feature_kind_is_refused() {
        let model = Embedder::random(2);
        let bytes = model.to_bytes().unwrap();
        let kind = serde_json::to_value(model.config().features).unwrap();
        let kind = kind.as_str().unwrap().to_string();
        // The config is a JSON string inside the JSON header, so its quotes are escaped.
        let field = |k: &str| format!(r#"\"features\":\"{k}\""#);
        // The edit itself keeps a loadable file: only the feature kind decides.
        Embedder::from_bytes(&edit_header(&bytes, &field(&kind), &field(&kind)))
            .expect("an unedited config loads");
        // A kind that was removed (pen-down strokes) or never existed is refused, by name.
        for unknown in ["pen-strokes", "sonar"] {
            let edited = edit_header(&bytes, &field(&kind), &field(unknown));
            let err = Embedder::from_bytes(&edited).unwrap_err();
            match &err {
                LoadModelError::UnknownFeatureKind { got } => assert_eq!(got, unknown),
                other => panic!("expected UnknownFeatureKind, got {other}"),
            }
            assert!(err.to_string().contains(unknown), "{err}");
        }
    }
}

/// The embedder's fast path against candle's forward pass of the same weights (feature
/// `train`, on in the workspace's test run).
#[cfg(all(test, feature = "train"))]
mod reference_tests {
    use super::*;
    use crate::fast::tests::rel_err;
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
        let xs = trajectories(5, 2);
        for (i, e) in embedders.iter().enumerate() {
            let want = e
                .embed_batch_reference(crate::preprocess::default_panda(), &xs)
                .unwrap();
            let got = e
                .embed_batch(crate::preprocess::default_panda(), &xs)
                .unwrap();
            for (k, (g, w)) in got.iter().zip(&want).enumerate() {
                let err = rel_err(g, w);
                assert!(
                    err <= 1e-5,
                    "embedder {i} input {k}: relative error {err:e}"
                );
            }
            // Batch 1 through `embed` gives the same as the batched fast path.
            let one = e.embed(crate::preprocess::default_panda(), &xs[3]).unwrap();
            assert!(rel_err(&one, &got[3]) <= 1e-6);
        }
    }
}
