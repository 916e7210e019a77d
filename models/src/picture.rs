//! The picture network's fast path: forward (serving and training) and backward (training)
//! of [`FeatureKind::Picture`](crate::features::FeatureKind::Picture) networks, on the same
//! weights and buffers as the sequence network of [`crate::sequence::forward`] and [`crate::sequence::backward`].
//!
//! Layout: a picture is `[side, side]` row-major (one channel), activations are
//! `[batch, s, s, c]` (channels last). A layer is a "same" 2D convolution written as im2col
//! (`cols [batch * s * s, k * k * c_in]`, column `(dy * k + dx) * c_in + c`) and one GEMM
//! with the weights `[k * k * c_in, c_out]`, then ReLU and a 2 x 2 max pool. After the last
//! layer: the global mean over the remaining cells, the output layer and L2 normalisation.
//!
//! The max pool passes its gradient to the **first** maximum of each window (in the order
//! `(0,0), (0,1), (1,0), (1,1)`), as PyTorch does: a blank region of a picture gives four
//! equal values per window, and handing the gradient to all four would multiply it. ReLU
//! passes the gradient where its input is `>= 0`, as candle does. The candle reference
//! ([`crate::net::Net::forward`]) follows the same rules, and the tests hold this code to it
//! and to central finite differences in `f64`.

use crate::features::PICTURE_SIDE;
#[cfg(feature = "train")]
use crate::sequence::backward::{BackScratch, Grads};
use crate::sequence::forward::{
    FastNet, FastNetError, Real, Scratch, gemm_strided, grow, l2_normalize_rows, real,
};

/// Write the im2col rows of `x [batch, s, s, c]` for a `k x k` "same" convolution into
/// `cols [batch * s * s, k * k * c]` (zero outside the picture). The `k` taps of one kernel
/// row are `k * c` consecutive values of the input row, copied at once where they lie inside.
fn im2col<T: Real>(x: &[T], batch: usize, s: usize, c: usize, k: usize, cols: &mut [T]) {
    let pad = k / 2;
    let width = k * k * c;
    for b in 0..batch {
        let img = &x[b * s * s * c..(b + 1) * s * s * c];
        for r in 0..s {
            for q in 0..s {
                let row = &mut cols[((b * s + r) * s + q) * width..][..width];
                for dy in 0..k {
                    let dst = &mut row[dy * k * c..(dy + 1) * k * c];
                    let rr = r + dy;
                    if rr < pad || rr >= s + pad {
                        dst.fill(T::zero());
                        continue;
                    }
                    let line = &img[(rr - pad) * s * c..(rr - pad + 1) * s * c];
                    if q >= pad && q + k - pad <= s {
                        dst.copy_from_slice(&line[(q - pad) * c..(q - pad + k) * c]);
                    } else {
                        for dx in 0..k {
                            let qq = q + dx;
                            let d = &mut dst[dx * c..(dx + 1) * c];
                            if qq < pad || qq >= s + pad {
                                d.fill(T::zero());
                            } else {
                                d.copy_from_slice(&line[(qq - pad) * c..(qq - pad + 1) * c]);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The adjoint of [`im2col`]: add every column value of `dcols` back to the pixel it was
/// copied from, into `dx [batch, s, s, c]` (which is overwritten).
#[cfg(feature = "train")]
fn col2im<T: Real>(dcols: &[T], batch: usize, s: usize, c: usize, k: usize, dx: &mut [T]) {
    let pad = k / 2;
    let width = k * k * c;
    dx[..batch * s * s * c].fill(T::zero());
    for b in 0..batch {
        let img = &mut dx[b * s * s * c..(b + 1) * s * s * c];
        for r in 0..s {
            for q in 0..s {
                let row = &dcols[((b * s + r) * s + q) * width..][..width];
                for dy in 0..k {
                    let rr = r + dy;
                    if rr < pad || rr >= s + pad {
                        continue;
                    }
                    let src = &row[dy * k * c..(dy + 1) * k * c];
                    let line = &mut img[(rr - pad) * s * c..(rr - pad + 1) * s * c];
                    // The taps of this kernel row that fall inside the picture.
                    let lo = pad.saturating_sub(q);
                    let hi = k.min(s + pad - q);
                    let at = (q + lo - pad) * c;
                    for (d, v) in line[at..at + (hi - lo) * c]
                        .iter_mut()
                        .zip(&src[lo * c..hi * c])
                    {
                        *d = *d + *v;
                    }
                }
            }
        }
    }
}

/// Offsets (in cells of an `s`-wide map) of the four elements of a 2 x 2 window, in the
/// order the first maximum is taken.
fn window(s: usize) -> [usize; 4] {
    [0, 1, s, s + 1]
}

impl<T: Real> FastNet<T> {
    /// Floating-point operations of one picture's forward pass.
    pub(crate) fn picture_flops(&self) -> u64 {
        let taps = self.config().taps() as u64;
        let mut s = PICTURE_SIDE as u64;
        let mut total = 0u64;
        for c in &self.convs {
            total += 2 * s * s * taps * c.c_in as u64 * c.c_out as u64;
            s /= 2;
        }
        total + 2 * self.config().pooled_features() as u64 * self.config().embed_dim as u64
    }

    /// [`FastNet::forward`] of a picture network: `x [batch, side², 1]`.
    pub(crate) fn forward_picture(
        &self,
        x: &[T],
        batch: usize,
        scratch: &mut Scratch<T>,
        out: &mut [T],
    ) -> Result<(), FastNetError> {
        let e = self.config().embed_dim;
        let k = self.kernel;
        let n_layers = self.convs.len();
        let Scratch {
            inputs,
            outputs,
            pooled,
            emb,
            norms,
            shape,
            map,
        } = scratch;
        inputs.resize_with(n_layers, Vec::new);
        outputs.resize_with(n_layers, Vec::new);
        let mut s = PICTURE_SIDE;
        for (i, conv) in self.convs.iter().enumerate() {
            let (c, o) = (conv.c_in, conv.c_out);
            let m = batch * s * s;
            let cols = grow(&mut inputs[i], m * k * k * c);
            let src: &[T] = if i == 0 { x } else { &map[..m * c] };
            im2col(src, batch, s, c, k, cols);
            // y = bias + cols · W
            let y = grow(&mut outputs[i], m * o);
            for row in y.chunks_exact_mut(o) {
                row.copy_from_slice(&conv.b);
            }
            gemm_strided(
                m,
                o,
                k * k * c,
                y,
                (cols, k * k * c, 1),
                (&conv.w, o, 1),
                true,
            )?;
            // ReLU + 2 x 2 max pool into the next layer's input map.
            let half = s / 2;
            let next = grow(map, batch * half * half * o);
            let win = window(s);
            for b in 0..batch {
                for r in 0..half {
                    for q in 0..half {
                        let base = (b * s + 2 * r) * s + 2 * q;
                        let dst = &mut next[((b * half + r) * half + q) * o..][..o];
                        let at = |w: usize| &y[(base + win[w]) * o..(base + win[w] + 1) * o];
                        let (y0, y1, y2, y3) = (at(0), at(1), at(2), at(3));
                        for ((((d, a), b1), c1), d1) in
                            dst.iter_mut().zip(y0).zip(y1).zip(y2).zip(y3)
                        {
                            *d = a.max(*b1).max(c1.max(*d1)).max(T::zero());
                        }
                    }
                }
            }
            s = half;
        }
        // Global mean over the remaining cells.
        let o = self.config().pooled_features();
        let cells = s * s;
        let p = grow(pooled, batch * o);
        p.fill(T::zero());
        let inv = T::one() / real(cells as f64);
        for (b, row) in p.chunks_exact_mut(o).enumerate() {
            for cell in 0..cells {
                let src = &map[(b * cells + cell) * o..][..o];
                for (d, v) in row.iter_mut().zip(src) {
                    *d = *d + *v;
                }
            }
            for d in row.iter_mut() {
                *d = *d * inv;
            }
        }
        for row in out.chunks_exact_mut(e) {
            row.copy_from_slice(&self.fc_b);
        }
        gemm_strided(batch, e, o, out, (p, o, 1), (&self.fc_w, e, 1), true)?;
        l2_normalize_rows(self.config().l2_normalize, out, e, grow(norms, batch));
        grow(emb, batch * e).copy_from_slice(out);
        *shape = (batch, PICTURE_SIDE * PICTURE_SIDE);
        Ok(())
    }

    /// [`FastNet::backward`] of a picture network.
    #[cfg(feature = "train")]
    pub(crate) fn backward_picture(
        &self,
        scratch: &Scratch<T>,
        d_out: &[T],
        back: &mut BackScratch<T>,
        grads: &mut Grads<T>,
    ) -> Result<(), FastNetError> {
        let (batch, _) = scratch.shape;
        let k = self.kernel;
        let n_layers = self.convs.len();
        let BackScratch {
            dy,
            dy_below,
            dx,
            du,
            dpooled,
            ..
        } = back;
        let (conv_grads, fc_grads) = grads.params_mut().split_at_mut(2 * n_layers);

        let dp = self.head_backward(scratch, d_out, du, dpooled, fc_grads)?;
        let o = self.config().pooled_features();

        // The global mean: every cell of the last map gets dp / cells.
        let mut s = PICTURE_SIDE >> n_layers;
        let cells = s * s;
        let inv = T::one() / real(cells as f64);
        let dmap = grow(dy_below, batch * cells * o);
        for b in 0..batch {
            for cell in 0..cells {
                for (d, v) in dmap[(b * cells + cell) * o..][..o]
                    .iter_mut()
                    .zip(&dp[b * o..(b + 1) * o])
                {
                    *d = *v * inv;
                }
            }
        }
        for i in (0..n_layers).rev() {
            let conv = &self.convs[i];
            let (c, o) = (conv.c_in, conv.c_out);
            let big = 2 * s;
            let m = batch * big * big;
            // Pool and ReLU: the gradient of each pooled cell goes to the first maximum
            // of its window, where that value is >= 0.
            let y = &scratch.outputs[i][..m * o];
            let g = grow(dy, m * o);
            g.fill(T::zero());
            let win = window(big);
            for b in 0..batch {
                for r in 0..s {
                    for q in 0..s {
                        let base = (b * big + 2 * r) * big + 2 * q;
                        let src = &dy_below[((b * s + r) * s + q) * o..][..o];
                        let at = |w: usize| (base + win[w]) * o;
                        let rows = [at(0), at(1), at(2), at(3)];
                        for (ch, v) in src.iter().enumerate() {
                            let mut pick = rows[0];
                            let mut best = y[pick + ch];
                            for &row in &rows[1..] {
                                let cand = y[row + ch];
                                if cand > best {
                                    best = cand;
                                    pick = row;
                                }
                            }
                            if best >= T::zero() {
                                g[pick + ch] = *v;
                            }
                        }
                    }
                }
            }
            let [dw, db] = &mut conv_grads[2 * i..2 * i + 2] else {
                return Err(FastNetError::Config("missing conv gradients".into()));
            };
            for row in g.chunks_exact(o) {
                for (a, v) in db.iter_mut().zip(row) {
                    *a = *a + *v;
                }
            }
            let width = k * k * c;
            let cols = &scratch.inputs[i][..m * width];
            // dW += colsᵀ · dY
            gemm_strided(width, o, m, dw, (cols, 1, width), (g, o, 1), true)?;
            if i == 0 {
                break;
            }
            // dcols = dY · Wᵀ, then back onto the pixels of the layer input.
            let dcols = grow(dx, m * width);
            gemm_strided(m, width, o, dcols, (g, o, 1), (&conv.w, 1, o), false)?;
            let below = grow(dy_below, m * c);
            col2im(dcols, batch, big, c, k, below);
            s = big;
        }
        Ok(())
    }
}

#[cfg(all(test, feature = "train"))]
mod tests {
    use super::*;
    use crate::features::FeatureKind;
    use crate::net::{Net, NetConfig};
    use candle_core::{DType, Device, Tensor, Var};
    use rand::{Rng, SeedableRng};

    fn config(channels: Vec<usize>, embed_dim: usize) -> NetConfig {
        NetConfig {
            features: FeatureKind::Picture,
            channels,
            kernel: 3,
            embed_dim,
            l2_normalize: true,
            reverse_average: false,
            test_views: Vec::new(),
        }
    }

    /// Pictures with blank regions (ties in the pools) and random strokes.
    fn pictures(batch: usize, seed: u64) -> Vec<f64> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let n = PICTURE_SIDE * PICTURE_SIDE;
        let mut x = vec![0.0f64; batch * n];
        for img in x.chunks_exact_mut(n) {
            for _ in 0..120 {
                let i = rng.random_range(0..n);
                img[i] = rng.random_range(0.05..1.0);
            }
        }
        x
    }

    fn loss_and_grad(net: &FastNet<f64>, x: &[f64], batch: usize, target: &[f64]) -> f64 {
        let e = net.config().embed_dim;
        let mut out = vec![0.0; batch * e];
        net.forward(
            x,
            batch,
            PICTURE_SIDE * PICTURE_SIDE,
            &mut Scratch::default(),
            &mut out,
        )
        .expect("forward");
        out.iter()
            .zip(target)
            .map(|(a, b)| a * b)
            .sum::<f64>()
            .powi(2)
    }

    /// The hand-written backward against central finite differences, in f64, on pictures
    /// with blank regions (where the pools tie).
    #[test]
    fn picture_gradients_match_finite_differences() {
        let cfg = config(vec![3, 4, 5], 6);
        let net = FastNet::<f64>::random(cfg.clone(), 5).expect("net");
        // Non-zero biases, so that blank regions are not exactly zero after ReLU.
        let mut net = net;
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        for (pi, p) in net.params_mut().into_iter().enumerate() {
            if pi % 2 == 1 {
                for v in p.iter_mut() {
                    *v = rng.random_range(-0.2..0.2);
                }
            }
        }
        let batch = 3;
        let x = pictures(batch, 4);
        let target: Vec<f64> = (0..batch * 6)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let e = cfg.embed_dim;
        let mut scratch = Scratch::default();
        let mut out = vec![0.0; batch * e];
        net.forward(
            &x,
            batch,
            PICTURE_SIDE * PICTURE_SIDE,
            &mut scratch,
            &mut out,
        )
        .expect("forward");
        let dot: f64 = out.iter().zip(&target).map(|(a, b)| a * b).sum();
        let d_out: Vec<f64> = target.iter().map(|t| 2.0 * dot * t).collect();
        let mut grads = Grads::zeros_like(&net);
        net.backward(&scratch, &d_out, &mut BackScratch::default(), &mut grads)
            .expect("backward");
        let eps = 1e-6;
        let mut checked = 0;
        for pi in 0..grads.params().len() {
            let len = grads.params()[pi].len();
            for idx in (0..len).step_by((len / 7).max(1)) {
                let at = |delta: f64| {
                    let mut n = net.clone();
                    n.params_mut()[pi][idx] += delta;
                    loss_and_grad(&n, &x, batch, &target)
                };
                let fd = (at(eps) - at(-eps)) / (2.0 * eps);
                let g = grads.params()[pi][idx];
                assert!(
                    (fd - g).abs() < 1e-5 * (1.0 + fd.abs()),
                    "param {pi} idx {idx}: backward {g} vs finite difference {fd}"
                );
                checked += 1;
            }
        }
        assert!(checked > 40, "{checked}");
    }

    /// Forward and gradients equal candle's autograd of the reference network.
    #[test]
    fn picture_net_matches_candle() -> candle_core::Result<()> {
        let cfg = config(vec![4, 6, 8], 5);
        let fast = FastNet::<f64>::random(cfg.clone(), 2).expect("net");
        let batch = 4;
        let x = pictures(batch, 8);
        let e = cfg.embed_dim;
        let mut scratch = Scratch::default();
        let mut out = vec![0.0; batch * e];
        let n = PICTURE_SIDE * PICTURE_SIDE;
        fast.forward(&x, batch, n, &mut scratch, &mut out)
            .expect("forward");
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let d_out: Vec<f64> = (0..batch * e)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let mut grads = Grads::zeros_like(&fast);
        fast.backward(&scratch, &d_out, &mut BackScratch::default(), &mut grads)
            .expect("backward");

        let vars = cfg
            .param_shapes()
            .into_iter()
            .zip(fast.params())
            .map(|((_, shape), p)| Var::from_slice(p, shape, &Device::Cpu))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let net = Net::new(cfg, vars.iter().map(|v| v.as_tensor().clone()).collect())?;
        let xt = Tensor::from_vec(x, (batch, n, 1), &Device::Cpu)?;
        let got = net.forward(&xt)?;
        let want = got.flatten_all()?.to_vec1::<f64>()?;
        for (a, b) in out.iter().zip(&want) {
            assert!((a - b).abs() < 1e-10, "forward {a} vs candle {b}");
        }
        let dt = Tensor::from_vec(d_out, (batch, e), &Device::Cpu)?;
        let loss = (got * dt)?.sum_all()?;
        let store = loss.backward()?;
        for (pi, v) in vars.iter().enumerate() {
            let g = store
                .get(v.as_tensor())
                .expect("a gradient per parameter")
                .to_dtype(DType::F64)?
                .flatten_all()?
                .to_vec1::<f64>()?;
            for (a, b) in grads.params()[pi].iter().zip(&g) {
                assert!(
                    (a - b).abs() < 1e-9 * (1.0 + b.abs()),
                    "param {pi}: {a} vs {b}"
                );
            }
        }
        Ok(())
    }
}
