//! The model file: safetensors with one f32 tensor per parameter and `__metadata__`
//! (format, config, input shape, embedding size, and a SHA-256 over every tensor); loading
//! verifies all of it ([`Embedder::load`]), saving is atomic ([`Embedder::save`]).

use super::*;

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

/// A tensor as the file holds it: name, shape, values.
pub(super) type Named = (String, Vec<usize>, Vec<f32>);

/// The tensor name of parameter `name` of branch `branch` in a file of `branches` networks:
/// unprefixed for a single network (the format every earlier model file has), `b<i>.` for the
/// branches of a fused model.
pub(super) fn tensor_name(branches: usize, branch: usize, name: &str) -> String {
    if branches == 1 {
        name.to_string()
    } else {
        format!("b{branch}.{name}")
    }
}

/// The networks' configs are servable together: each valid, their embeddings fit in
/// [`EMBED_DIM`], and the branches of a fused model are L2-normalised (else the scaling by
/// `1/√branches` would not make their distances comparable).
pub(super) fn check_configs(configs: &[NetConfig]) -> Result<(), LoadModelError> {
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

/// The first feature kind a network config JSON (an object, or an array of them) names that
/// is not a [`FeatureKind`] this build knows.
pub(super) fn unknown_feature_kind(config_json: &str) -> Option<String> {
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

/// SHA-256 (hex) over tensors in name order: name bytes, shape (u64 LE each), f32 LE data.
pub(super) fn checksum<'a>(named: impl Iterator<Item = &'a Named>) -> String {
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
}
