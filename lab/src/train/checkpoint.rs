//! The resumable checkpoint of a training run: `state.json` (the loop's and the schedule's
//! state), `optimizer.safetensors` (AdamW's moments) and the JSON files of a run, written
//! atomically (a temporary file, then a rename).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::train::optim::{AdamW, Proxies};
use crate::train::{TrainError, io_err};

/// The resumable state (`state.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct State {
    /// Epochs done.
    pub epoch: usize,
    /// The learning rate of the next epoch.
    pub lr: f64,
    /// The best validation loss so far; infinite until an epoch has a finite one. JSON has
    /// no infinity, so it is written as `null` then, and `null` reads back as infinity.
    #[serde(with = "finite_or_null")]
    pub best_val_loss: f64,
    /// Epochs since the best validation loss.
    pub epochs_since_best: usize,
    /// Epochs since the last learning-rate cut.
    pub epochs_since_lr_change: usize,
    /// AdamW steps taken.
    pub adam_step: usize,
    /// Seconds of training over every session of the run.
    pub train_seconds: f64,
    /// The run is done (epoch budget or early stopping).
    pub finished: bool,
}

impl State {
    /// The state before the first epoch, at learning rate `lr`.
    pub fn new(lr: f64) -> Self {
        Self {
            epoch: 0,
            lr,
            best_val_loss: f64::INFINITY,
            epochs_since_best: 0,
            epochs_since_lr_change: 0,
            adam_step: 0,
            train_seconds: 0.0,
            finished: false,
        }
    }
}

/// A loss that may be infinite (no finite loss yet): `null` in JSON, read back as
/// infinity. serde_json writes a non-finite float as `null` but cannot read `null` into an
/// `f64`, which broke `--resume` after a first epoch with a NaN validation loss.
mod finite_or_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_some(v)
        } else {
            s.serialize_none()
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

/// Read a JSON file.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, TrainError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|e| TrainError::Setup(format!("{}: {e}", path.display())))
}

/// Write a JSON file atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), TrainError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| TrainError::Setup(e.to_string()))?;
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, text).map_err(io_err(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

/// Write AdamW's moments (`m0`, `v0`, ... per parameter tensor) atomically.
pub fn save_opt(path: &Path, opt: &AdamW) -> Result<(), TrainError> {
    let (ms, vs) = opt.moments();
    let mut map = HashMap::new();
    for (i, (m, v)) in ms.iter().zip(vs).enumerate() {
        map.insert(
            format!("m{i}"),
            Tensor::from_slice(m, m.len(), &Device::Cpu)?,
        );
        map.insert(
            format!("v{i}"),
            Tensor::from_slice(v, v.len(), &Device::Cpu)?,
        );
    }
    let tmp = path.with_extension("tmp");
    candle_core::safetensors::save(&map, &tmp)?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

/// Write the class proxies of a normalised-softmax run (`w [classes, dim]`) with their
/// optimiser's moments (`m0`, `v0`), atomically.
pub fn save_proxies(path: &Path, proxies: &Proxies) -> Result<(), TrainError> {
    let (ms, vs) = proxies.optimizer().moments();
    let mut map = HashMap::new();
    map.insert(
        "w".to_string(),
        Tensor::from_slice(proxies.weights(), proxies.shape(), &Device::Cpu)?,
    );
    for (k, x) in [("m0", &ms[0]), ("v0", &vs[0])] {
        map.insert(k.to_string(), Tensor::from_slice(x, x.len(), &Device::Cpu)?);
    }
    let tmp = path.with_extension("tmp");
    candle_core::safetensors::save(&map, &tmp)?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

/// Read what [`save_proxies`] wrote: the proxies with their moments restored at `step`
/// updates; refused unless they are `[classes, dim]`.
pub fn load_proxies(
    path: &Path,
    classes: usize,
    dim: usize,
    step: usize,
) -> Result<Proxies, TrainError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let map = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)?;
    let get = |k: &str| -> Result<&Tensor, TrainError> {
        map.get(k)
            .ok_or_else(|| TrainError::Setup(format!("{}: missing {k}", path.display())))
    };
    let w = get("w")?;
    if w.dims() != [classes, dim] {
        return Err(TrainError::Setup(format!(
            "{}: proxies {:?}, this run has {classes} classes of {dim}",
            path.display(),
            w.dims()
        )));
    }
    let mut p = Proxies::from_weights(w.flatten_all()?.to_vec1::<f32>()?, classes, dim);
    let m = get("m0")?.to_vec1::<f32>()?;
    let v = get("v0")?.to_vec1::<f32>()?;
    p.optimizer_mut().restore(vec![m], vec![v], step)?;
    Ok(p)
}

/// AdamW's first and second moments, per parameter tensor.
pub type Moments = (Vec<Vec<f32>>, Vec<Vec<f32>>);

/// Read the moments [`save_opt`] wrote.
pub fn load_opt(path: &Path) -> Result<Moments, TrainError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let map = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)?;
    let n = map.len() / 2;
    let mut m = Vec::with_capacity(n);
    let mut v = Vec::with_capacity(n);
    for i in 0..n {
        let get = |k: String| -> Result<Vec<f32>, TrainError> {
            let t = map
                .get(&k)
                .ok_or_else(|| TrainError::Setup(format!("{}: missing {k}", path.display())))?;
            Ok(t.flatten_all()?.to_vec1::<f32>()?)
        };
        m.push(get(format!("m{i}"))?);
        v.push(get(format!("v{i}"))?);
    }
    Ok((m, v))
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_models::net::NetConfig;
    use guardian_models::sequence::forward::FastNet;

    #[test]
    fn a_state_without_a_finite_validation_loss_round_trips() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("state.json");
        // A run whose every validation loss was NaN: the best stays infinite.
        let mut state = State::new(2e-3);
        state.epoch = 1;
        write_json(&path, &state).expect("write");
        let text = std::fs::read_to_string(&path).expect("read");
        assert!(text.contains("\"best_val_loss\": null"), "{text}");
        let back: State = read_json(&path).expect("a resumed run reads it");
        assert_eq!(back, state);
        assert_eq!(back.best_val_loss, f64::INFINITY);
        // A finite loss is written as a number and read back exactly.
        state.best_val_loss = 0.125;
        write_json(&path, &state).expect("write");
        assert_eq!(read_json::<State>(&path).expect("read"), state);
    }

    #[test]
    fn proxies_round_trip_with_their_moments_and_another_shape_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("proxies.safetensors");
        let mut p = Proxies::random(5, 3, 7);
        p.optimizer_mut()
            .restore(vec![vec![0.5; 15]], vec![vec![0.25; 15]], 4)
            .expect("moments");
        save_proxies(&path, &p).expect("save");
        let q = load_proxies(&path, 5, 3, 4).expect("load");
        assert_eq!(q.weights(), p.weights());
        assert_eq!(q.optimizer().moments(), p.optimizer().moments());
        assert_eq!(q.optimizer().steps(), 4);
        assert!(load_proxies(&path, 6, 3, 4).is_err());
    }

    #[test]
    fn the_optimizer_moments_round_trip_and_a_missing_one_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let net = FastNet::random(NetConfig::default(), 3).expect("net");
        let mut opt = AdamW::new(&net, 1e-4);
        let (m, v): Moments = {
            let (m, v) = opt.moments();
            (
                m.iter()
                    .enumerate()
                    .map(|(i, x)| (0..x.len()).map(|k| (i + k) as f32 * 1e-3).collect())
                    .collect(),
                v.iter().map(|x| vec![0.5; x.len()]).collect(),
            )
        };
        opt.restore(m.clone(), v.clone(), 7).expect("same shapes");
        let path = dir.path().join("optimizer.safetensors");
        save_opt(&path, &opt).expect("save");
        let (m2, v2) = load_opt(&path).expect("load");
        assert_eq!((m2, v2), (m, v));
        // A file without every moment is refused by name.
        let mut map = HashMap::new();
        map.insert(
            "m0".to_string(),
            Tensor::new(&[1f32], &Device::Cpu).expect("t"),
        );
        map.insert(
            "m1".to_string(),
            Tensor::new(&[1f32], &Device::Cpu).expect("t"),
        );
        candle_core::safetensors::save(&map, &path).expect("save");
        let err = load_opt(&path).unwrap_err();
        assert!(err.to_string().contains("missing v0"), "{err}");
    }
}
