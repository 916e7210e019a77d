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

use crate::fast::{FastNet, FastNetError, Scratch};
use crate::features::{Augment, FeatureKind};
#[cfg(feature = "train")]
use crate::net::Net;
use crate::net::NetConfig;
use guardian_robot::kinematics::{PANDA_JOINTS, Robot};
use guardian_robot::pen::{PenPoint, pen_path_with};

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

/// A tensor as the file holds it: name, shape, values.
type Named = (String, Vec<usize>, Vec<f32>);

/// The tensor name of parameter `name` of branch `branch` in a file of `branches` networks:
/// unprefixed for a single network (the format every earlier model file has), `b<i>.` for the
/// branches of a fused model.
fn tensor_name(branches: usize, branch: usize, name: &str) -> String {
    if branches == 1 {
        name.to_string()
    } else {
        format!("b{branch}.{name}")
    }
}

/// The networks' configs are servable together: each valid, their embeddings fit in
/// [`EMBED_DIM`], and the branches of a fused model are L2-normalised (else the scaling by
/// `1/√branches` would not make their distances comparable).
fn check_configs(configs: &[NetConfig]) -> Result<(), LoadModelError> {
    let bad = |expected: String, got: String| LoadModelError::BadMetadata {
        key: "config",
        expected,
        got,
    };
    if configs.is_empty() {
        return Err(bad("at least one network".into(), "none".into()));
    }
    for c in configs {
        c.check()
            .map_err(|e| bad("a valid network config".into(), e))?;
        if configs.len() > 1 && !c.l2_normalize {
            return Err(bad(
                "L2-normalised branches in a fused model".into(),
                "a branch without l2-normalize".into(),
            ));
        }
    }
    let dim: usize = configs.iter().map(|c| c.embed_dim).sum();
    if dim > EMBED_DIM {
        return Err(bad(
            format!("embed-dim at most {EMBED_DIM} in all"),
            dim.to_string(),
        ));
    }
    Ok(())
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
        // One network's config (a JSON object), or the branches' of a fused model (an array).
        let config_json = get("config")?;
        let configs: Vec<NetConfig> =
            match serde_json::from_str::<serde_json::Value>(config_json) {
                Ok(serde_json::Value::Array(items)) => items
                    .into_iter()
                    .map(serde_json::from_value)
                    .collect::<Result<_, _>>(),
                _ => serde_json::from_str(config_json).map(|c| vec![c]),
            }
            .map_err(|e| match unknown_feature_kind(config_json) {
                Some(got) => LoadModelError::UnknownFeatureKind { got },
                None => LoadModelError::BadMetadata {
                    key: "config",
                    expected: "a network config or an array of them".into(),
                    got: format!("{config_json} ({e})"),
                },
            })?;
        check_configs(&configs)?;
        let expected_sum = get("sha256")?.to_string();

        let shapes: Vec<Vec<(String, Vec<usize>)>> = configs
            .iter()
            .enumerate()
            .map(|(b, c)| {
                c.param_shapes()
                    .into_iter()
                    .map(|(n, s)| (tensor_name(configs.len(), b, &n), s))
                    .collect()
            })
            .collect();
        for name in st.names() {
            if !shapes.iter().flatten().any(|(n, _)| n == name) {
                return Err(LoadModelError::UnexpectedTensor { name: name.into() });
            }
        }
        let mut named: Vec<Vec<Named>> = Vec::with_capacity(shapes.len());
        for branch in &shapes {
            let mut tensors = Vec::with_capacity(branch.len());
            for (name, shape) in branch {
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
                tensors.push((name.clone(), shape.clone(), data));
            }
            named.push(tensors);
        }
        let got_sum = checksum(named.iter().flatten());
        if got_sum != expected_sum {
            return Err(LoadModelError::ChecksumMismatch {
                expected: expected_sum,
                got: got_sum,
            });
        }
        if let Some((name, _, _)) = named
            .iter()
            .flatten()
            .find(|(_, _, d)| d.iter().any(|v| !v.is_finite()))
        {
            return Err(LoadModelError::NonFinite { name: name.clone() });
        }
        let nets = configs
            .into_iter()
            .zip(named)
            .map(|(c, t)| FastNet::from_params(c, t.into_iter().map(|(_, _, d)| d).collect()))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self::from_nets(nets))
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

    /// The embedder of checked networks; the version is the checksum of their tensors under
    /// their names in the file.
    fn from_nets(nets: Vec<FastNet>) -> Self {
        let sum = checksum(Self::named(&nets).iter());
        Self {
            nets: Arc::new(nets),
            version: sum[..16].to_string(),
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
        let buffers: Vec<(String, Vec<usize>, Vec<u8>)> = Self::named(&self.nets)
            .into_iter()
            .map(|(name, shape, data)| {
                let bytes = data.iter().flat_map(|v| v.to_le_bytes()).collect();
                (name, shape, bytes)
            })
            .collect();
        let views = buffers
            .iter()
            .map(|(name, shape, bytes)| {
                TensorView::new(Dtype::F32, shape.clone(), bytes).map(|v| (name.clone(), v))
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| SaveModelError::Serialize(e.to_string()))?;
        let meta = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("config".to_string(), self.config_json()),
            ("input-shape".to_string(), INPUT_SHAPE.to_string()),
            ("embed-dim".to_string(), EMBED_DIM.to_string()),
            ("sha256".to_string(), self.checksum.clone()),
        ]);
        safetensors::serialize(views, Some(meta))
            .map_err(|e| SaveModelError::Serialize(e.to_string()))
    }

    /// The architecture as the file's `config` records it: one network's config, or the
    /// array of a fused model's.
    pub fn config_json(&self) -> String {
        let result = if let [net] = self.nets.as_slice() {
            serde_json::to_string(net.config())
        } else {
            serde_json::to_string(&self.configs())
        };
        result.expect("a NetConfig always serialises")
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
                if copies == 2 {
                    let (a, b) = r.split_at(d);
                    for ((v, x), y) in o.iter_mut().zip(a).zip(b) {
                        *v = (x + y) / 2.0;
                    }
                    if config.l2_normalize {
                        let norm = (o.iter().map(|v| v * v).sum::<f32>() + 1e-12).sqrt();
                        for v in o.iter_mut() {
                            *v /= norm;
                        }
                    }
                } else {
                    o.copy_from_slice(r);
                }
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
            if copies == 2 {
                e = e.reshape((xs.len(), 2, d))?.mean(1)?;
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

    /// Floating-point operations of the networks for one plan (both directions of a
    /// reverse-averaged network).
    pub fn flops(&self) -> u64 {
        self.nets
            .iter()
            .map(|n| {
                let c = n.config();
                let copies = if c.reverse_average && c.features != FeatureKind::Joints {
                    2
                } else {
                    1
                };
                copies * n.flops(c.features.steps())
            })
            .sum()
    }

    /// Stable id: the first 16 hex characters of the SHA-256 over the weights.
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

/// What each branch's embedding is multiplied by: `1/√branches` for a fused model (so the
/// concatenation is a unit vector), nothing for a single network.
fn branch_scale(branches: usize) -> Option<f32> {
    (branches > 1).then(|| 1.0 / (branches as f32).sqrt())
}

/// Write the input of a network with `config` for `xs` into `feats` (grown as needed): per
/// trajectory one feature sequence (from its pen path in `paths`, or from its joints), or two
/// (forwards, then time-reversed) with reverse averaging. Returns the number of sequences per
/// trajectory.
fn features_into(
    config: &NetConfig,
    xs: &[Resampled],
    paths: &[[PenPoint; STEPS]],
    feats: &mut Vec<f32>,
) -> usize {
    let kind = config.features;
    let v = kind.values();
    let both = config.reverse_average && kind != FeatureKind::Joints;
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
    for ((x, path), out) in xs.iter().zip(paths).zip(feats.chunks_exact_mut(copies * v)) {
        if kind == FeatureKind::Joints {
            crate::features::compute(kind, x, out);
            continue;
        }
        let (fwd, bwd) = out.split_at_mut(v);
        crate::features::path_features(kind, path, &Augment::default(), fwd);
        if both {
            crate::features::path_features(kind, path, &reverse, bwd);
        }
    }
    copies
}

/// The first feature kind a network config JSON (an object, or an array of them) names that
/// is not a [`FeatureKind`] this build knows.
fn unknown_feature_kind(config_json: &str) -> Option<String> {
    let value: serde_json::Value = serde_json::from_str(config_json).ok()?;
    let configs = match value {
        serde_json::Value::Array(items) => items,
        one => vec![one],
    };
    configs.iter().find_map(|c| {
        let features = c.get("features")?;
        let known =
            serde_json::from_value::<crate::features::FeatureKind>(features.clone()).is_ok();
        (!known).then(|| match features.as_str() {
            Some(name) => name.to_string(),
            None => features.to_string(),
        })
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

/// SHA-256 (hex) over tensors in name order: name bytes, shape (u64 LE each), f32 LE data.
fn checksum<'a>(named: impl Iterator<Item = &'a Named>) -> String {
    let mut order: Vec<&Named> = named.collect();
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
            .embed_batch(guardian_robot::kinematics::default_panda(), &xs)
            .unwrap();
        let b = back
            .embed_batch(guardian_robot::kinematics::default_panda(), &xs)
            .unwrap();
        assert_eq!(a, b);
        assert_eq!(
            e.embed(guardian_robot::kinematics::default_panda(), &xs[1])
                .unwrap(),
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
            .embed_batch(guardian_robot::kinematics::default_panda(), &[x, rev])
            .unwrap();
        assert!(sq_dist(&plain[0], &plain[1]) > 1e-6);
        e.set_reverse_average(true);
        let version = e.version().to_string();
        let avg = e
            .embed_batch(guardian_robot::kinematics::default_panda(), &[x, rev])
            .unwrap();
        assert!(sq_dist(&avg[0], &avg[1]) < 1e-8);
        assert_eq!(e.version(), version);
        // The option survives a save/load round trip.
        let back = Embedder::from_bytes(&e.to_bytes().unwrap()).unwrap();
        assert!(back.configs()[0].reverse_average);
        assert_eq!(
            back.embed(guardian_robot::kinematics::default_panda(), &x)
                .unwrap(),
            avg[0]
        );
    }

    /// A model file with one bit of its last weight flipped is refused by its checksum.
    fn assert_a_flipped_bit_is_a_checksum_error(bytes: &[u8]) {
        let mut flipped = bytes.to_vec();
        let n = flipped.len();
        flipped[n - 2] ^= 0x10;
        let err = Embedder::from_bytes(&flipped).unwrap_err();
        assert!(
            matches!(err, LoadModelError::ChecksumMismatch { .. }),
            "{err}"
        );
    }

    /// A 64-dimensional network of `features` with random weights.
    fn branch(features: FeatureKind, seed: u64) -> Embedder {
        let config = NetConfig {
            features,
            channels: vec![8, 16],
            kernel: 3,
            embed_dim: EMBED_DIM / 2,
            ..NetConfig::default()
        };
        Embedder::random_with(config, seed).unwrap()
    }

    #[test]
    fn a_fused_model_concatenates_its_branches_and_averages_their_distances() {
        let panda = guardian_robot::kinematics::default_panda();
        let mut seq = branch(FeatureKind::Pen, 1);
        seq.set_reverse_average(true);
        let pic = branch(FeatureKind::Picture, 2);
        let xs = [sample(0.0), sample(0.7), sample(2.0)];
        let (a, b) = (
            seq.embed_batch(panda, &xs).unwrap(),
            pic.embed_batch(panda, &xs).unwrap(),
        );
        // A branch alone: its 64 values, then zeros.
        assert!(
            a.iter()
                .all(|e| e[EMBED_DIM / 2..].iter().all(|v| *v == 0.0))
        );
        let fused = Embedder::fuse(&[seq.clone(), pic.clone()]).unwrap();
        assert_eq!(fused.nets().len(), 2);
        let f = fused.embed_batch(panda, &xs).unwrap();
        let h = std::f32::consts::FRAC_1_SQRT_2;
        for ((f, a), b) in f.iter().zip(&a).zip(&b) {
            for (got, want) in f.iter().zip(a[..64].iter().chain(&b[..64])) {
                assert!((got - want * h).abs() <= 1e-6, "{got} vs {}", want * h);
            }
            let norm: f32 = f.iter().map(|v| v * v).sum();
            assert!((norm - 1.0).abs() < 1e-4, "{norm}");
        }
        // A fused distance is the mean of the branches' distances.
        for (i, j) in [(0, 1), (0, 2), (1, 2)] {
            let want = (sq_dist(&a[i], &a[j]) + sq_dist(&b[i], &b[j])) / 2.0;
            let got = sq_dist(&f[i], &f[j]);
            assert!((got - want).abs() <= 1e-5, "{got} vs {want}");
            assert!(got > 0.0);
        }
        // The pen path comes out as from a single network.
        let (e, path) = fused.embed_with_pen_path(panda, &xs[1]).unwrap();
        assert_eq!(e, f[1]);
        assert_eq!(path, guardian_robot::pen::pen_path_with(panda, &xs[1]));
        // The file round-trips with both branches, under a version of its own.
        let bytes = fused.to_bytes().unwrap();
        let back = Embedder::from_bytes(&bytes).unwrap();
        assert_eq!(back.version(), fused.version());
        assert_ne!(fused.version(), seq.version());
        assert_ne!(fused.version(), pic.version());
        assert_eq!(back.embed_batch(panda, &xs).unwrap(), f);
        assert_eq!(back.configs()[0].features, FeatureKind::Pen);
        assert!(back.configs()[0].reverse_average);
        assert_eq!(back.configs()[1].features, FeatureKind::Picture);
        // The branch order is part of the model.
        let swapped = Embedder::fuse(&[pic, seq]).unwrap();
        assert_ne!(swapped.version(), fused.version());
        // A flipped bit in a branch is a checksum error.
        assert_a_flipped_bit_is_a_checksum_error(&bytes);
    }

    #[test]
    fn a_fused_model_that_cannot_be_served_is_refused() {
        // Two 128-dimensional networks do not fit one embedding.
        let err = Embedder::fuse(&[Embedder::random(1), Embedder::random(2)]).unwrap_err();
        assert!(
            matches!(&err, LoadModelError::BadMetadata { key: "config", got, .. } if got == "256"),
            "{err}"
        );
        // A branch without L2 normalisation would weigh its distances arbitrarily.
        let raw = Embedder::random_with(
            NetConfig {
                l2_normalize: false,
                embed_dim: 64,
                ..NetConfig::default()
            },
            3,
        )
        .unwrap();
        let err = Embedder::fuse(&[raw.clone(), branch(FeatureKind::Picture, 4)]).unwrap_err();
        assert!(err.to_string().contains("L2-normalised"), "{err}");
        // Alone, the same network is a model of its own.
        assert!(Embedder::fuse(&[raw]).is_ok());
        // A file whose config array names an unknown feature kind is refused by name.
        let fused = Embedder::fuse(&[branch(FeatureKind::Pen, 5), branch(FeatureKind::Picture, 6)])
            .unwrap();
        let bytes = fused.to_bytes().unwrap();
        let edited = edit_header(
            &bytes,
            r#"\"features\":\"picture\""#,
            r#"\"features\":\"sonar\""#,
        );
        match Embedder::from_bytes(&edited).unwrap_err() {
            LoadModelError::UnknownFeatureKind { got } => assert_eq!(got, "sonar"),
            other => panic!("expected UnknownFeatureKind, got {other}"),
        }
    }

    #[test]
    fn corrupt_files_are_refused() {
        let e = Embedder::random(1);
        let bytes = e.to_bytes().unwrap();
        // Truncated.
        let err = Embedder::from_bytes(&bytes[..bytes.len() - 10]).unwrap_err();
        assert!(matches!(err, LoadModelError::Format(_)), "{err}");
        assert_a_flipped_bit_is_a_checksum_error(&bytes);
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
        let kind = serde_json::to_value(model.configs()[0].features).unwrap();
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
}
