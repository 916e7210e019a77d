//! The embedding network as candle tensors (feature `train`): the reference path, written
//! with explicit zero padding + unfold + `matmul` (see the parent module's docs).

use candle_core::{D, DType, Device, Tensor};

use super::NetConfig;

/// The network: a config plus one tensor per parameter (in [`NetConfig::param_shapes`] order).
#[derive(Debug, Clone)]
pub struct Net {
    config: NetConfig,
    params: Vec<Tensor>,
}

impl Net {
    /// Build from tensors in [`NetConfig::param_shapes`] order; shapes are checked.
    pub fn new(config: NetConfig, params: Vec<Tensor>) -> candle_core::Result<Self> {
        let shapes = config.param_shapes();
        if shapes.len() != params.len() {
            candle_core::bail!("expected {} parameters, got {}", shapes.len(), params.len());
        }
        for ((name, shape), t) in shapes.iter().zip(&params) {
            if t.dims() != shape.as_slice() {
                candle_core::bail!("{name}: expected shape {shape:?}, got {:?}", t.dims());
            }
        }
        Ok(Self { config, params })
    }

    /// Random initial network (see [`NetConfig::init`]) as `dtype` tensors on the CPU.
    pub fn random(config: NetConfig, seed: u64, dtype: DType) -> candle_core::Result<Self> {
        let params = config
            .init(seed)
            .into_iter()
            .map(|(_, shape, data)| Tensor::from_vec(data, shape, &Device::Cpu)?.to_dtype(dtype))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Self::new(config, params)
    }

    /// The architecture.
    pub fn config(&self) -> &NetConfig {
        &self.config
    }

    /// The parameter tensors, in [`NetConfig::param_shapes`] order.
    pub fn params(&self) -> &[Tensor] {
        &self.params
    }

    /// Embed a batch of feature sequences `[B, L, F]` (pictures: `[B, side², 1]`) to
    /// `[B, embed_dim]`.
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        if self.config.features.is_picture() {
            return self.forward_picture(x);
        }
        let k = self.config.kernel;
        let n_layers = self.config.channels.len();
        let mut h = x.clone();
        for i in 0..n_layers {
            let w = &self.params[2 * i];
            let b = &self.params[2 * i + 1];
            h = conv1d_same(&h, w, b, k)?.relu()?;
            if i + 1 < n_layers {
                h = max_pool2(&h)?;
            }
        }
        let mean = h.mean(1)?;
        let max = h.max(1)?;
        let pooled = Tensor::cat(&[&mean, &max], 1)?;
        let fc_w = &self.params[2 * n_layers];
        let fc_b = &self.params[2 * n_layers + 1];
        let e = pooled.matmul(fc_w)?.broadcast_add(fc_b)?;
        self.normalized(e)
    }

    /// The embedding `e [B, D]` L2-normalised per row when the config asks for it.
    fn normalized(&self, e: Tensor) -> candle_core::Result<Tensor> {
        if self.config.l2_normalize {
            let norm = (e.sqr()?.sum_keepdim(1)? + 1e-12)?.sqrt()?;
            e.broadcast_div(&norm)
        } else {
            Ok(e)
        }
    }
}

impl Net {
    /// The picture network: per layer a "same" 2D convolution, ReLU and a 2 x 2 max pool
    /// (the gradient goes to the first maximum of each window, as [`crate::picture`]'s
    /// backward does), then the global mean, the output layer and L2 normalisation.
    fn forward_picture(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let k = self.config.kernel;
        let n_layers = self.config.channels.len();
        let (bsz, pixels, _) = x.dims3()?;
        let side = crate::features::PICTURE_SIDE;
        if pixels != side * side {
            candle_core::bail!("a picture has {} pixels, got {pixels}", side * side);
        }
        let mut h = x.reshape((bsz, side, side, 1))?;
        let mut s = side;
        for i in 0..n_layers {
            let w = &self.params[2 * i];
            let b = &self.params[2 * i + 1];
            h = conv2d_same(&h, w, b, k)?;
            let o = w.dim(1)?;
            let half = s / 2;
            // Windows last: [B, s/2, s/2, o, 4], window element dy * 2 + dx.
            let win = h
                .reshape((bsz, half, 2, half, 2, o))?
                .permute((0, 1, 3, 5, 2, 4))?
                .contiguous()?
                .reshape((bsz, half, half, o, 4))?;
            let idx = win.argmax_keepdim(4)?;
            h = win.gather(&idx, 4)?.squeeze(4)?.relu()?;
            s = half;
        }
        let mean = h.mean(2)?.mean(1)?;
        let fc_w = &self.params[2 * n_layers];
        let fc_b = &self.params[2 * n_layers + 1];
        let e = mean.matmul(fc_w)?.broadcast_add(fc_b)?;
        self.normalized(e)
    }
}

/// "Same" 2D convolution: `x [B, H, W, C]`, `w [k*k*C, O]` (row `(dy*k + dx)*C + c` is tap
/// `(dy, dx)` of input channel `c`), `b [O]` -> `[B, H, W, O]`.
pub fn conv2d_same(x: &Tensor, w: &Tensor, b: &Tensor, k: usize) -> candle_core::Result<Tensor> {
    let (bsz, hgt, wid, c) = x.dims4()?;
    let pad = k / 2;
    let xp = x.pad_with_zeros(1, pad, pad)?.pad_with_zeros(2, pad, pad)?;
    let mut taps = Vec::with_capacity(k * k);
    for dy in 0..k {
        for dx in 0..k {
            taps.push(xp.narrow(1, dy, hgt)?.narrow(2, dx, wid)?);
        }
    }
    let unfolded = Tensor::cat(&taps, 3)?.reshape((bsz * hgt * wid, k * k * c))?;
    let out = unfolded.matmul(w)?.broadcast_add(b)?;
    out.reshape((bsz, hgt, wid, w.dim(1)?))
}

/// "Same" 1D convolution over time: `x [B, L, C]`, `w [k*C, O]` (row `j*C + c` is tap `j`
/// of input channel `c`), `b [O]` -> `[B, L, O]`.
pub fn conv1d_same(x: &Tensor, w: &Tensor, b: &Tensor, k: usize) -> candle_core::Result<Tensor> {
    let (bsz, len, c) = x.dims3()?;
    let pad = k / 2;
    let xp = x.pad_with_zeros(1, pad, pad)?;
    let taps = (0..k)
        .map(|j| xp.narrow(1, j, len))
        .collect::<candle_core::Result<Vec<_>>>()?;
    let unfolded = Tensor::cat(&taps, 2)?.reshape((bsz * len, k * c))?;
    let out = unfolded.matmul(w)?.broadcast_add(b)?;
    out.reshape((bsz, len, w.dim(1)?))
}

/// Max pool of 2 over time: `[B, L, C]` -> `[B, L/2, C]` (a trailing odd step is dropped).
pub fn max_pool2(x: &Tensor) -> candle_core::Result<Tensor> {
    let (bsz, len, c) = x.dims3()?;
    let half = len / 2;
    let x = if len % 2 == 1 {
        x.narrow(1, 0, 2 * half)?
    } else {
        x.clone()
    };
    x.reshape((bsz, half, 2, c))?.max(D::Minus2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Var;
    use rand::{Rng, SeedableRng};

    fn small_config() -> NetConfig {
        NetConfig::tiny_joints()
    }

    /// Reference convolution written with loops.
    fn conv_ref(x: &[f64], l: usize, c: usize, w: &[f64], b: &[f64], k: usize) -> Vec<f64> {
        let o = b.len();
        let pad = k / 2;
        let mut out = vec![0.0; l * o];
        for t in 0..l {
            for oc in 0..o {
                let mut s = b[oc];
                for j in 0..k {
                    let tt = t as isize + j as isize - pad as isize;
                    if tt < 0 || tt >= l as isize {
                        continue;
                    }
                    for ic in 0..c {
                        s += x[tt as usize * c + ic] * w[(j * c + ic) * o + oc];
                    }
                }
                out[t * o + oc] = s;
            }
        }
        out
    }

    #[test]
    fn conv_matches_loops() -> candle_core::Result<()> {
        let (l, c, o, k) = (7, 3, 2, 5);
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let x: Vec<f64> = (0..2 * l * c)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let w: Vec<f64> = (0..k * c * o)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let b: Vec<f64> = vec![0.3, -0.2];
        let xt = Tensor::from_vec(x.clone(), (2, l, c), &Device::Cpu)?;
        let wt = Tensor::from_vec(w.clone(), (k * c, o), &Device::Cpu)?;
        let bt = Tensor::from_vec(b.clone(), o, &Device::Cpu)?;
        let got = conv1d_same(&xt, &wt, &bt, k)?
            .flatten_all()?
            .to_vec1::<f64>()?;
        for s in 0..2 {
            let want = conv_ref(&x[s * l * c..(s + 1) * l * c], l, c, &w, &b, k);
            for (g, w) in got[s * l * o..(s + 1) * l * o].iter().zip(&want) {
                assert!((g - w).abs() < 1e-12, "{g} vs {w}");
            }
        }
        Ok(())
    }

    /// Backprop through the whole network (batch > 1) against central finite differences,
    /// in f64. Guards against candle regressions that would silently stop training.
    #[test]
    fn gradients_match_finite_differences() -> candle_core::Result<()> {
        let config = small_config();
        let net = Net::random(config.clone(), 7, DType::F64)?;
        let vars = net
            .params()
            .iter()
            .map(Var::from_tensor)
            .collect::<candle_core::Result<Vec<_>>>()?;
        let f = config.in_channels();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let (bsz, len) = (3, 16);
        let x: Vec<f64> = (0..bsz * len * f)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let x = Tensor::from_vec(x, (bsz, len, f), &Device::Cpu)?;
        let target = Tensor::from_vec(
            (0..bsz * config.embed_dim)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect::<Vec<f64>>(),
            (bsz, config.embed_dim),
            &Device::Cpu,
        )?;
        let loss_of = |params: Vec<Tensor>| -> candle_core::Result<Tensor> {
            let net = Net::new(config.clone(), params)?;
            let e = net.forward(&x)?;
            (e * &target)?.sum_all()?.sqr()
        };
        let loss = loss_of(vars.iter().map(|v| v.as_tensor().clone()).collect())?;
        let grads = loss.backward()?;
        let eps = 1e-6;
        let mut checked = 0;
        for (pi, var) in vars.iter().enumerate() {
            let g = grads
                .get(var.as_tensor())
                .expect("every parameter gets a gradient")
                .flatten_all()?
                .to_vec1::<f64>()?;
            let base = var.as_tensor().flatten_all()?.to_vec1::<f64>()?;
            // A handful of coordinates per parameter.
            for idx in (0..base.len()).step_by((base.len() / 5).max(1)) {
                let eval = |delta: f64| -> candle_core::Result<f64> {
                    let params = vars
                        .iter()
                        .enumerate()
                        .map(|(j, v)| {
                            if j == pi {
                                let mut d = base.clone();
                                d[idx] += delta;
                                Tensor::from_vec(d, v.dims(), &Device::Cpu)
                            } else {
                                Ok(v.as_tensor().clone())
                            }
                        })
                        .collect::<candle_core::Result<Vec<_>>>()?;
                    loss_of(params)?.to_scalar::<f64>()
                };
                let fd = (eval(eps)? - eval(-eps)?) / (2.0 * eps);
                let tol = 1e-5 * (1.0 + fd.abs());
                assert!(
                    (fd - g[idx]).abs() < tol,
                    "param {pi} idx {idx}: backprop {} vs finite difference {fd}",
                    g[idx]
                );
                checked += 1;
            }
        }
        assert!(checked > 20);
        Ok(())
    }
}
