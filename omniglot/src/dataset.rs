//! The robot-drawn Omniglot dataset: generation (strokes -> dense joint path -> the shared
//! [`preprocess`](guardian_robot::preprocess::preprocess_with)) and the safetensors file.
//!
//! File layout: tensors `trajectories` f32 [N, 128, 8], `labels` i64 [N] (class index),
//! `alphabet_ids` i64 [N], `drawer_ids` i64 [N]; `__metadata__` JSON strings `classes`
//! (`Alphabet/characterNN` in label order), `alphabets`, `geometry` and `generator`. The
//! header is written with a fixed key order, so the same input gives a byte-identical file.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use guardian_robot::kinematics::{Robot, RobotRecord};
use guardian_robot::preprocess::preprocess_with;
use guardian_shared::trajectory::{InvalidTrajectory, Resampled, SLOTS, STEPS, TOOL};
use rayon::prelude::*;
use serde::Serialize;

use crate::path::{DensePath, Geometry, PathPoint, PathSolver, SolvePathError};
use crate::strokes::{self, ReadStrokesError, Stroke, StrokePrep};

/// Converting one drawing failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConvertError {
    /// The stroke file is unreadable or malformed.
    #[error(transparent)]
    Read(#[from] ReadStrokesError),
    /// Inverse kinematics failed along the path.
    #[error(transparent)]
    Ik(#[from] SolvePathError),
    /// The dense joint path failed the shared trajectory validation.
    #[error("dense path rejected: {0}")]
    Invalid(#[from] InvalidTrajectory),
}

/// Where the Omniglot stroke file of each dataset drawing is, by class name and drawer (from
/// a scan of the stroke roots): the way back from a dataset sample to the strokes it was
/// drawn from, for corrupting it.
#[derive(Debug, Clone, Default)]
pub struct StrokeIndex(BTreeMap<(String, i64), PathBuf>);

impl StrokeIndex {
    /// Index every drawing under `roots` (see [`strokes::scan`]).
    pub fn scan(roots: &[PathBuf]) -> Result<Self, ReadStrokesError> {
        Ok(Self(
            strokes::scan(roots)?
                .into_iter()
                .map(|f| ((f.class_name(), i64::from(f.drawer)), f.path))
                .collect(),
        ))
    }

    /// The strokes of drawing `i` of `data`; `None` if its file is not indexed or unreadable.
    pub fn strokes_of(&self, data: &Dataset, i: usize) -> Option<Vec<Stroke>> {
        let class = usize::try_from(*data.labels.get(i)?)
            .ok()
            .and_then(|c| data.classes.get(c))?;
        let path = self.0.get(&(class.clone(), *data.drawer_ids.get(i)?))?;
        strokes::read_strokes(path).ok()
    }
}

/// One converted drawing.
#[derive(Debug, Clone)]
pub struct Converted {
    /// The Cartesian pen path that was solved.
    pub path: Vec<PathPoint>,
    /// The dense joint path (what a planner would send).
    pub dense: DensePath,
    /// The model input: 128 waypoints of the robot's joints and the tool.
    pub sample: Resampled,
}

/// Strokes -> Cartesian path -> IK -> dense waypoints -> shared preprocessing.
pub fn convert_strokes(solver: &PathSolver, strokes: &[Stroke]) -> Result<Converted, ConvertError> {
    let (path, dense) = solver.solve_strokes(strokes)?;
    let sample = preprocess_with(solver.robot(), &dense.waypoints)?;
    Ok(Converted {
        path,
        dense,
        sample,
    })
}

/// The dataset in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// One 128-step trajectory per drawing (the robot's joints and the tool; on disk
    /// `[N, 128, joints + 1]`).
    pub trajectories: Vec<Resampled>,
    /// Class index per drawing (into `classes`).
    pub labels: Vec<i64>,
    /// Alphabet index per drawing (into `alphabets`).
    pub alphabet_ids: Vec<i64>,
    /// Drawer number (DD) per drawing.
    pub drawer_ids: Vec<i64>,
    /// Class names `Alphabet/characterNN`, sorted by alphabet then character.
    pub classes: Vec<String>,
    /// Alphabet names, sorted.
    pub alphabets: Vec<String>,
    /// Geometry used to generate it.
    pub geometry: Geometry,
    /// Generator name and version.
    pub generator: String,
    /// The robot that drew the trajectories (files without a `robot` record: the Panda).
    pub robot: RobotRecord,
}

/// A skipped drawing and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    /// The stroke file.
    pub path: PathBuf,
    /// Human-readable reason.
    pub reason: String,
    /// True if the reason is an IK failure.
    pub ik_failure: bool,
}

/// Figures from one generation run.
#[derive(Debug, Clone, PartialEq)]
pub struct GenerateReport {
    /// Stroke files found.
    pub files: usize,
    /// Drawings in the dataset.
    pub converted: usize,
    /// Drawings left out, with reasons (unreadable, malformed, IK failure, invalid path).
    pub skipped: Vec<Skipped>,
    /// How many of the skipped drawings were IK failures.
    pub ik_failures: usize,
    /// Largest pen-tip error of a stored dense waypoint (m).
    pub max_fk_error: f64,
    /// Smallest joint-limit margin of a stored dense waypoint (rad).
    pub min_limit_margin: f64,
    /// Dense waypoints solved in total.
    pub dense_waypoints: usize,
    /// Wall-clock time of the conversion.
    pub elapsed: Duration,
}

impl GenerateReport {
    /// Converted drawings per second.
    pub fn drawings_per_second(&self) -> f64 {
        self.files as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }
}

/// Generation failed as a whole (per-drawing problems are [`Skipped`] instead).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GenerateError {
    /// The stroke roots could not be scanned.
    #[error(transparent)]
    Scan(#[from] ReadStrokesError),
    /// The geometry has no home pose.
    #[error(transparent)]
    Geometry(#[from] SolvePathError),
}

/// The generator identification stored in every file.
pub fn generator_name() -> String {
    format!("guardian-lab {}", env!("CARGO_PKG_VERSION"))
}

/// Convert every drawing under `roots` (rayon, all cores; `progress` is called once per
/// finished drawing from any thread). Output order is sorted by alphabet, character,
/// drawer, independent of scheduling.
pub fn generate(
    roots: &[PathBuf],
    geometry: &Geometry,
    progress: &(dyn Fn() + Sync),
) -> Result<(Dataset, GenerateReport), GenerateError> {
    let files = strokes::scan(roots)?;
    generate_files(&files, geometry, progress)
}

/// [`generate`] for an explicit list of files (from [`strokes::scan`], possibly filtered).
pub fn generate_files(
    files: &[strokes::DrawingFile],
    geometry: &Geometry,
    progress: &(dyn Fn() + Sync),
) -> Result<(Dataset, GenerateReport), GenerateError> {
    generate_files_with(files, geometry, StrokePrep::default(), progress)
}

/// [`generate_files`] with the strokes of every drawing passed through `prep` first.
pub fn generate_files_with(
    files: &[strokes::DrawingFile],
    geometry: &Geometry,
    prep: StrokePrep,
    progress: &(dyn Fn() + Sync),
) -> Result<(Dataset, GenerateReport), GenerateError> {
    let start = Instant::now();
    let solver = PathSolver::new(geometry)?;
    let alphabets: Vec<String> = files
        .iter()
        .map(|f| f.alphabet.clone())
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let classes: Vec<String> = files
        .iter()
        .map(|f| f.class_name())
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let results: Vec<Result<Converted, ConvertError>> = files
        .par_iter()
        .map(|f| {
            let r = strokes::read_strokes(&f.path)
                .map_err(ConvertError::from)
                .and_then(|s| convert_strokes(&solver, &prep.apply(s)));
            progress();
            r
        })
        .collect();
    let mut dataset = Dataset {
        trajectories: Vec::with_capacity(files.len()),
        labels: Vec::with_capacity(files.len()),
        alphabet_ids: Vec::with_capacity(files.len()),
        drawer_ids: Vec::with_capacity(files.len()),
        classes,
        alphabets,
        geometry: geometry.clone(),
        generator: generator_name(),
        robot: RobotRecord::of(solver.robot()),
    };
    let mut report = GenerateReport {
        files: files.len(),
        converted: 0,
        skipped: Vec::new(),
        ik_failures: 0,
        max_fk_error: 0.0,
        min_limit_margin: f64::INFINITY,
        dense_waypoints: 0,
        elapsed: Duration::ZERO,
    };
    for (file, result) in files.iter().zip(results) {
        match result {
            Ok(c) => {
                let label = dataset.classes.binary_search(&file.class_name());
                let alphabet = dataset.alphabets.binary_search(&file.alphabet);
                let (Ok(label), Ok(alphabet)) = (label, alphabet) else {
                    continue; // unreachable: both lists are built from `files`
                };
                dataset.trajectories.push(c.sample);
                dataset.labels.push(label as i64);
                dataset.alphabet_ids.push(alphabet as i64);
                dataset.drawer_ids.push(i64::from(file.drawer));
                report.converted += 1;
                report.max_fk_error = report.max_fk_error.max(c.dense.max_fk_error);
                report.min_limit_margin = report.min_limit_margin.min(c.dense.min_limit_margin);
                report.dense_waypoints += c.dense.waypoints.len();
            }
            Err(e) => {
                let ik_failure = matches!(e, ConvertError::Ik(_));
                report.ik_failures += usize::from(ik_failure);
                report.skipped.push(Skipped {
                    path: file.path.clone(),
                    reason: e.to_string(),
                    ik_failure,
                });
            }
        }
    }
    report.elapsed = start.elapsed();
    Ok((dataset, report))
}

/// Writing a dataset failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SaveDatasetError {
    /// Creating, writing or renaming the file failed.
    #[error("{}: cannot write: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The per-drawing vectors have different lengths.
    #[error("inconsistent dataset: {what} has {got} entries, expected {expected}")]
    Inconsistent {
        /// Which vector.
        what: &'static str,
        /// Entries found.
        got: usize,
        /// Entries expected (number of trajectories).
        expected: usize,
    },
}

/// Reading a dataset failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadDatasetError {
    /// The file could not be read.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Not a valid safetensors file.
    #[error("not a safetensors file: {0}")]
    Format(String),
    /// A tensor is missing.
    #[error("tensor {name} is missing")]
    MissingTensor {
        /// Tensor name.
        name: &'static str,
    },
    /// A tensor has the wrong dtype or shape.
    #[error("tensor {name}: expected {expected}, got {got}")]
    Tensor {
        /// Tensor name.
        name: &'static str,
        /// What was expected.
        expected: String,
        /// What was found.
        got: String,
    },
    /// A metadata entry is missing.
    #[error("metadata {key} is missing")]
    MissingMetadata {
        /// The key.
        key: &'static str,
    },
    /// A metadata entry is not the expected JSON.
    #[error("metadata {key}: {source}")]
    BadMetadata {
        /// The key.
        key: &'static str,
        /// The JSON error.
        source: serde_json::Error,
    },
    /// An index points outside `classes` or `alphabets`.
    #[error("{what} index {index} out of range (len {len})")]
    IndexOutOfRange {
        /// Which index.
        what: &'static str,
        /// The value.
        index: i64,
        /// The list length.
        len: usize,
    },
}

/// A named alphabet is not in the dataset.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("alphabet {name:?} is not in the dataset (has {known:?})")]
pub struct UnknownAlphabet {
    /// The name asked for.
    pub name: String,
    /// The dataset's alphabets.
    pub known: Vec<String>,
}

impl Dataset {
    /// Indices of the named alphabets (error if one is unknown).
    pub fn alphabet_ids(&self, names: &[String]) -> Result<Vec<i64>, UnknownAlphabet> {
        names
            .iter()
            .map(|n| {
                self.alphabets
                    .iter()
                    .position(|a| a == n)
                    .map(|p| p as i64)
                    .ok_or_else(|| UnknownAlphabet {
                        name: n.clone(),
                        known: self.alphabets.clone(),
                    })
            })
            .collect()
    }

    /// Number of drawings.
    pub fn len(&self) -> usize {
        self.trajectories.len()
    }

    /// True if there is no drawing.
    pub fn is_empty(&self) -> bool {
        self.trajectories.is_empty()
    }

    /// The robot that drew the trajectories, loaded from the geometry's robot and checked
    /// against the file's record (name, joints, URDF checksum), with the geometry's pen.
    pub fn robot(&self) -> Result<Robot, crate::path::SolvePathError> {
        let robot = self.geometry.robot()?;
        if !self.robot.matches(&robot) {
            return Err(crate::path::SolvePathError::Robot(format!(
                "the data set was drawn by {} but {:?} loads as {}",
                self.robot,
                self.geometry.robot,
                RobotRecord::of(&robot)
            )));
        }
        Ok(robot)
    }

    fn check(&self) -> Result<(), SaveDatasetError> {
        let n = self.trajectories.len();
        for (what, got) in [
            ("labels", self.labels.len()),
            ("alphabet_ids", self.alphabet_ids.len()),
            ("drawer_ids", self.drawer_ids.len()),
        ] {
            if got != n {
                return Err(SaveDatasetError::Inconsistent {
                    what,
                    got,
                    expected: n,
                });
            }
        }
        Ok(())
    }

    /// Serialise to safetensors bytes (deterministic).
    pub fn to_bytes(&self) -> Result<Vec<u8>, SaveDatasetError> {
        self.check()?;
        let n = self.len();
        let mut metadata = BTreeMap::new();
        metadata.insert("alphabets", json(&self.alphabets));
        metadata.insert("classes", json(&self.classes));
        metadata.insert("generator", self.generator.clone());
        metadata.insert("geometry", json(&self.geometry));
        metadata.insert("robot", json(&self.robot));
        let joints = self.robot.joints;
        let channels = joints + 1;
        // I64 tensors first (8-byte aligned), then f32, each group by name.
        let i64_tensors: [(&str, &[i64]); 3] = [
            ("alphabet_ids", &self.alphabet_ids),
            ("drawer_ids", &self.drawer_ids),
            ("labels", &self.labels),
        ];
        let mut header = serde_json::Map::new();
        header.insert(
            "__metadata__".into(),
            serde_json::to_value(&metadata).unwrap_or_default(),
        );
        let mut offset = 0usize;
        let mut entries: Vec<(String, serde_json::Value)> = Vec::new();
        for (name, data) in i64_tensors {
            let len = data.len() * 8;
            entries.push((
                name.into(),
                serde_json::json!({"dtype": "I64", "shape": [n], "data_offsets": [offset, offset + len]}),
            ));
            offset += len;
        }
        let tlen = n * STEPS * channels * 4;
        entries.push((
            "trajectories".into(),
            serde_json::json!({"dtype": "F32", "shape": [n, STEPS, channels], "data_offsets": [offset, offset + tlen]}),
        ));
        offset += tlen;
        for (k, v) in entries {
            header.insert(k, v);
        }
        let mut header_bytes = serde_json::to_string(&header)
            .unwrap_or_default()
            .into_bytes();
        header_bytes.resize(header_bytes.len().next_multiple_of(8), b' ');
        let mut out = Vec::with_capacity(8 + header_bytes.len() + offset);
        out.extend_from_slice(&(header_bytes.len() as u64).to_le_bytes());
        out.extend_from_slice(&header_bytes);
        for (_, data) in i64_tensors {
            for v in data {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        for t in &self.trajectories {
            for w in t {
                for v in w[..joints].iter().chain(std::iter::once(&w[TOOL])) {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        Ok(out)
    }

    /// Write to `path` atomically (a temporary file beside it, then rename).
    pub fn save(&self, path: &Path) -> Result<(), SaveDatasetError> {
        write_atomic(path, &self.to_bytes()?)
    }

    /// Read a dataset file.
    pub fn load(path: &Path) -> Result<Self, LoadDatasetError> {
        let bytes = std::fs::read(path).map_err(|source| LoadDatasetError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }

    /// Parse safetensors bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, LoadDatasetError> {
        let st = safetensors::SafeTensors::deserialize(bytes)
            .map_err(|e| LoadDatasetError::Format(e.to_string()))?;
        let (_, meta) = safetensors::SafeTensors::read_metadata(bytes)
            .map_err(|e| LoadDatasetError::Format(e.to_string()))?;
        let meta = meta.metadata().clone().unwrap_or_default();
        let get = |key: &'static str| {
            meta.get(key)
                .ok_or(LoadDatasetError::MissingMetadata { key })
        };
        fn parse<T: serde::de::DeserializeOwned>(
            key: &'static str,
            text: &str,
        ) -> Result<T, LoadDatasetError> {
            serde_json::from_str(text)
                .map_err(|source| LoadDatasetError::BadMetadata { key, source })
        }
        let classes: Vec<String> = parse("classes", get("classes")?)?;
        let alphabets: Vec<String> = parse("alphabets", get("alphabets")?)?;
        let geometry: Geometry = parse("geometry", get("geometry")?)?;
        let generator = get("generator")?.clone();
        // Files from before robot records are the Panda's.
        let robot: RobotRecord = match meta.get("robot") {
            Some(text) => parse("robot", text)?,
            None => RobotRecord::panda(),
        };
        let joints = robot.joints;
        let channels = joints + 1;

        let traj = tensor(&st, "trajectories", safetensors::Dtype::F32)?;
        let shape = traj.shape().to_vec();
        if shape.len() != 3 || shape[1] != STEPS || shape[2] != channels || channels > SLOTS {
            return Err(LoadDatasetError::Tensor {
                name: "trajectories",
                expected: format!(
                    "shape [N, {STEPS}, {channels}] ({} joints + tool)",
                    robot.name
                ),
                got: format!("{shape:?}"),
            });
        }
        let n = shape[0];
        let values: Vec<f32> = traj
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let trajectories: Vec<Resampled> = values
            .chunks_exact(STEPS * channels)
            .map(|t| {
                let mut r = [[0.0f32; SLOTS]; STEPS];
                for (s, w) in r.iter_mut().zip(t.chunks_exact(channels)) {
                    s[..joints].copy_from_slice(&w[..joints]);
                    s[TOOL] = w[joints];
                }
                r
            })
            .collect();
        let ints = |name: &'static str| -> Result<Vec<i64>, LoadDatasetError> {
            let t = tensor(&st, name, safetensors::Dtype::I64)?;
            if t.shape() != [n] {
                return Err(LoadDatasetError::Tensor {
                    name,
                    expected: format!("shape [{n}]"),
                    got: format!("{:?}", t.shape()),
                });
            }
            Ok(t.data()
                .chunks_exact(8)
                .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
                .collect())
        };
        let labels = ints("labels")?;
        let alphabet_ids = ints("alphabet_ids")?;
        let drawer_ids = ints("drawer_ids")?;
        for (what, ids, len) in [
            ("label", &labels, classes.len()),
            ("alphabet id", &alphabet_ids, alphabets.len()),
        ] {
            if let Some(&index) = ids.iter().find(|&&i| i < 0 || i as usize >= len) {
                return Err(LoadDatasetError::IndexOutOfRange { what, index, len });
            }
        }
        Ok(Self {
            trajectories,
            labels,
            alphabet_ids,
            drawer_ids,
            classes,
            alphabets,
            geometry,
            generator,
            robot,
        })
    }
}

fn tensor<'a>(
    st: &'a safetensors::SafeTensors<'a>,
    name: &'static str,
    dtype: safetensors::Dtype,
) -> Result<safetensors::tensor::TensorView<'a>, LoadDatasetError> {
    let t = st
        .tensor(name)
        .map_err(|_| LoadDatasetError::MissingTensor { name })?;
    if t.dtype() != dtype {
        return Err(LoadDatasetError::Tensor {
            name,
            expected: format!("dtype {dtype:?}"),
            got: format!("dtype {:?}", t.dtype()),
        });
    }
    Ok(t)
}

/// JSON text of a plain value (strings, lists, the geometry: serialisation cannot fail).
fn json<T: Serialize + ?Sized>(value: &T) -> String {
    serde_json::to_string(value).unwrap_or_default()
}

/// Write `bytes` to `path` atomically: a temporary file beside it, then a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), SaveDatasetError> {
    let io = |source| SaveDatasetError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, bytes).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}
