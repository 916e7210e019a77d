//! The training path: the backward pass of [`FastNet`] (written by hand for the fixed
//! architecture: convolutions, ReLU, max pool of 2, global mean and max, linear, L2
//! normalisation) and a data-parallel [`Trainable`] that runs forward and backward on the
//! threads of rayon's pool.
//!
//! Every convolution GEMM of the backward reuses the forward's layout (time-padded rows of
//! the layer input, read as overlapping rows): the weight gradient is `Aᵀ · dY` over the
//! same overlapping rows `A`, and the input gradient is the forward convolution itself,
//! applied to the time-padded output gradient with the kernel flipped in time and
//! transposed. So the arithmetic of the convolution exists once, in [`crate::sequence::forward`].
//!
//! The gradients equal candle's autograd of [`crate::net::Net::forward`] (tests: against
//! finite differences in `f64`, and against candle on real batches). Ties follow candle:
//! ReLU passes the gradient where its input is `>= 0`, and a max passes it to every element
//! equal to the maximum.

use rayon::prelude::*;

use crate::sequence::forward::{
    FastNet, FastNetError, Real, Scratch, conv_rows, gemm_strided, grow,
};

/// Gradients of every parameter, flat, in [`crate::net::NetConfig::param_shapes`] order.
#[derive(Debug, Clone)]
pub struct Grads<T = f32> {
    params: Vec<Vec<T>>,
}

impl<T: Real> Grads<T> {
    /// Zero gradients shaped like `net`'s parameters.
    pub fn zeros_like(net: &FastNet<T>) -> Self {
        Self {
            params: net
                .params()
                .iter()
                .map(|p| vec![T::zero(); p.len()])
                .collect(),
        }
    }

    /// Set every gradient to zero.
    pub fn clear(&mut self) {
        for p in &mut self.params {
            p.fill(T::zero());
        }
    }

    /// The gradients, in parameter order.
    pub fn params(&self) -> &[Vec<T>] {
        &self.params
    }

    /// The gradients, mutable (for the backward passes of this crate).
    pub(crate) fn params_mut(&mut self) -> &mut [Vec<T>] {
        &mut self.params
    }

    /// Add `other` (same shapes) to these gradients.
    fn add(&mut self, other: &Self) {
        for (a, b) in self.params.iter_mut().zip(&other.params) {
            for (x, y) in a.iter_mut().zip(b) {
                *x = *x + *y;
            }
        }
    }
}

/// Reusable buffers of a backward pass.
#[derive(Debug, Clone)]
pub struct BackScratch<T = f32> {
    /// Output gradient of the layer being differentiated, time-padded like a layer input.
    pub(crate) dy: Vec<T>,
    /// Output gradient of the layer below.
    pub(crate) dy_below: Vec<T>,
    /// Gradient of the layer input (the GEMM's rows, sequence by sequence).
    pub(crate) dx: Vec<T>,
    /// Gradient of the pre-normalisation output and of the pooled features.
    pub(crate) du: Vec<T>,
    pub(crate) dpooled: Vec<T>,
    /// Per layer: the kernel flipped in time and transposed, `[k * c_out, c_in]`.
    pub(crate) flipped: Vec<T>,
}

impl<T> Default for BackScratch<T> {
    fn default() -> Self {
        Self {
            dy: Vec::new(),
            dy_below: Vec::new(),
            dx: Vec::new(),
            du: Vec::new(),
            dpooled: Vec::new(),
            flipped: Vec::new(),
        }
    }
}

impl<T: Real> FastNet<T> {
    /// Add to `grads` the gradient of a loss with respect to every parameter, given the
    /// gradient `d_out [batch, embed_dim]` of that loss with respect to the output of the
    /// last [`FastNet::forward`] run with `scratch` (which must not have run since).
    pub fn backward(
        &self,
        scratch: &Scratch<T>,
        d_out: &[T],
        back: &mut BackScratch<T>,
        grads: &mut Grads<T>,
    ) -> Result<(), FastNetError> {
        let (batch, len) = scratch.shape;
        let e = self.config().embed_dim;
        if d_out.len() != batch * e {
            return Err(FastNetError::Shape {
                what: "output gradient",
                expected: batch * e,
                got: d_out.len(),
            });
        }
        if grads.params.len() != 2 * self.convs.len() + 2 {
            return Err(FastNetError::Config(
                "gradients do not match the network".into(),
            ));
        }
        if batch == 0 {
            return Ok(());
        }
        if self.config().features.is_picture() {
            return self.backward_picture(scratch, d_out, back, grads);
        }
        let k = self.kernel;
        let pad = k / 2;
        let n_layers = self.convs.len();
        let BackScratch {
            dy,
            dy_below,
            dx,
            du,
            dpooled,
            flipped,
        } = back;
        let (conv_grads, fc_grads) = grads.params.split_at_mut(2 * n_layers);

        let dp = self.head_backward(scratch, d_out, du, dpooled, fc_grads)?;
        let o = self.convs[n_layers - 1].c_out;
        let p = &scratch.pooled[..batch * 2 * o];

        // Global mean and max over time of relu(y) of the last layer.
        let mut l = len >> (n_layers - 1);
        let lp = l + 2 * pad;
        let y = &scratch.outputs[n_layers - 1];
        let g = grow(dy, batch * lp * o);
        g.fill(T::zero());
        let inv = T::one() / crate::sequence::forward::real(l as f64);
        for b in 0..batch {
            let (dmean, dmax) = dp[b * 2 * o..(b + 1) * 2 * o].split_at(o);
            let max = &p[b * 2 * o + o..(b + 1) * 2 * o];
            for t in 0..l {
                let row = (b * lp + t) * o;
                let yr = &y[row..row + o];
                let gr = &mut g[row + pad * o..row + pad * o + o];
                for ((((gv, yv), dmean), dmax), mx) in
                    gr.iter_mut().zip(yr).zip(dmean).zip(dmax).zip(max)
                {
                    if *yv >= T::zero() {
                        let r = yv.max(T::zero());
                        let mut v = *dmean * inv;
                        if r == *mx {
                            v = v + *dmax;
                        }
                        *gv = v;
                    }
                }
            }
        }

        for i in (0..n_layers).rev() {
            let conv = &self.convs[i];
            let (c, o) = (conv.c_in, conv.c_out);
            let lp = l + 2 * pad;
            let rows = batch * lp - 2 * pad;
            // `dy` holds this layer's output gradient, time-padded (pad zero rows before
            // each sequence, zeros between sequences), as its GEMM rows shifted by pad.
            let g = &dy[..batch * lp * o];
            let g_rows = &g[pad * o..];
            let [dw, db] = &mut conv_grads[2 * i..2 * i + 2] else {
                return Err(FastNetError::Config("missing conv gradients".into()));
            };
            for row in g_rows.chunks_exact(o) {
                for (a, v) in db.iter_mut().zip(row) {
                    *a = *a + *v;
                }
            }
            // dW += Aᵀ · dY, A the overlapping rows of the layer input.
            let h = &scratch.inputs[i][..batch * lp * c];
            gemm_strided(k * c, o, rows, dw, (h, 1, c), (g_rows, o, 1), true)?;
            if i == 0 {
                break;
            }
            // dX = the forward convolution of dY (time-padded) with the flipped kernel:
            // dX[t] = sum_j dY[t + pad - j] W_jᵀ = sum_j' dYpad[t + j'] W_{k-1-j'}ᵀ.
            let wf = grow(flipped, k * o * c);
            for j in 0..k {
                let src = &conv.w[(k - 1 - j) * c * o..(k - j) * c * o];
                for ic in 0..c {
                    for oc in 0..o {
                        wf[(j * o + oc) * c + ic] = src[ic * o + oc];
                    }
                }
            }
            let d = grow(dx, rows * c);
            d.fill(T::zero());
            conv_rows(rows, c, k * o, g, o, wf, d)?;
            // Max pool of 2 after ReLU in the layer below: the gradient goes to each of the
            // two steps equal to the maximum, where its input was >= 0.
            let below = i - 1;
            let lb = len >> below;
            let lpb = lb + 2 * pad;
            let yb = &scratch.outputs[below];
            let gb = grow(dy_below, batch * lpb * c);
            gb.fill(T::zero());
            for b in 0..batch {
                for t in 0..l {
                    let src = &d[(b * lp + t) * c..(b * lp + t + 1) * c];
                    let r0 = (b * lpb + 2 * t) * c;
                    let (y0, y1) = yb[r0..r0 + 2 * c].split_at(c);
                    let (g0, g1) = gb[r0 + pad * c..r0 + pad * c + 2 * c].split_at_mut(c);
                    for ((((v, a), z), ga), gz) in src.iter().zip(y0).zip(y1).zip(g0).zip(g1) {
                        let m = a.max(*z).max(T::zero());
                        if *a >= T::zero() && a.max(T::zero()) == m {
                            *ga = *v;
                        }
                        if *z >= T::zero() && z.max(T::zero()) == m {
                            *gz = *v;
                        }
                    }
                }
            }
            std::mem::swap(dy, dy_below);
            l = lb;
        }
        Ok(())
    }
}

impl<T: Real> FastNet<T> {
    /// The backward of the network's head, shared by the sequence and the picture network:
    /// L2 normalisation, then the output layer `u = p · W + b` (its gradients added to
    /// `fc_grads`). Returns the gradient of the pooled features `p` of the last forward in
    /// `scratch`, `[batch, pooled_features]`, in `dpooled`.
    pub(crate) fn head_backward<'a>(
        &self,
        scratch: &Scratch<T>,
        d_out: &[T],
        du: &mut Vec<T>,
        dpooled: &'a mut Vec<T>,
        fc_grads: &mut [Vec<T>],
    ) -> Result<&'a mut [T], FastNetError> {
        let (batch, _) = scratch.shape;
        let e = self.config().embed_dim;
        let o = self.config().pooled_features();
        let du = grow(du, batch * e);
        l2_backward(self.config().l2_normalize, scratch, d_out, e, du);
        let p = &scratch.pooled[..batch * o];
        let [fc_w, fc_b] = fc_grads else {
            return Err(FastNetError::Config("missing fc gradients".into()));
        };
        for row in du.chunks_exact(e) {
            for (g, v) in fc_b.iter_mut().zip(row) {
                *g = *g + *v;
            }
        }
        // dW += pᵀ · du
        gemm_strided(o, e, batch, fc_w, (p, 1, o), (du, e, 1), true)?;
        // dp = du · Wᵀ
        let dp = grow(dpooled, batch * o);
        gemm_strided(batch, o, e, dp, (du, e, 1), (&self.fc_w, 1, e), false)?;
        Ok(dp)
    }
}

/// The gradient `du` of the output before L2 normalisation from the gradient `d_out` of the
/// normalised output of the last forward in `scratch` (with `l2`; otherwise `d_out`):
/// `e = u / n`, so `du = (de - e (e . de)) / n`.
fn l2_backward<T: Real>(l2: bool, scratch: &Scratch<T>, d_out: &[T], e: usize, du: &mut [T]) {
    if !l2 {
        du.copy_from_slice(d_out);
        return;
    }
    for (((g, d), o), n) in du
        .chunks_exact_mut(e)
        .zip(d_out.chunks_exact(e))
        .zip(scratch.emb.chunks_exact(e))
        .zip(&scratch.norms)
    {
        let dot: T = d.iter().zip(o).map(|(a, b)| *a * *b).sum();
        for ((g, d), o) in g.iter_mut().zip(d).zip(o) {
            *g = (*d - *o * dot) / *n;
        }
    }
}

/// One worker's share of a batch: its forward scratch, backward scratch and gradients.
#[derive(Debug, Clone)]
struct Worker<T> {
    scratch: Scratch<T>,
    back: BackScratch<T>,
    grads: Grads<T>,
    rows: std::ops::Range<usize>,
}

/// A network being trained: its weights and one [`Worker`] per thread of rayon's pool
/// (`RAYON_NUM_THREADS`). A batch is split into contiguous shares, one per worker; each
/// runs the forward and backward of its share, and the shares' gradients are summed.
#[derive(Debug, Clone)]
pub struct Trainable<T = f32> {
    net: FastNet<T>,
    workers: Vec<Worker<T>>,
    grads: Grads<T>,
    len: usize,
}

impl<T: Real> Trainable<T> {
    /// Train `net` with as many workers as rayon has threads.
    pub fn new(net: FastNet<T>) -> Self {
        Self::with_workers(net, rayon::current_num_threads())
    }

    /// Train `net` with `workers` workers (at least one).
    pub fn with_workers(net: FastNet<T>, workers: usize) -> Self {
        let grads = Grads::zeros_like(&net);
        let workers = (0..workers.max(1))
            .map(|_| Worker {
                scratch: Scratch::default(),
                back: BackScratch::default(),
                grads: grads.clone(),
                rows: 0..0,
            })
            .collect();
        Self {
            net,
            workers,
            grads,
            len: 0,
        }
    }

    /// The network with its current weights.
    pub fn net(&self) -> &FastNet<T> {
        &self.net
    }

    /// The network, mutable (for the optimiser).
    pub fn net_mut(&mut self) -> &mut FastNet<T> {
        &mut self.net
    }

    /// Forward `batch` sequences `x [batch, len, in_channels]` into `out [batch,
    /// embed_dim]`, keeping what [`Trainable::backward`] needs.
    pub fn forward(
        &mut self,
        x: &[T],
        batch: usize,
        len: usize,
        out: &mut [T],
    ) -> Result<(), FastNetError> {
        self.net.check_io(x.len(), out.len(), batch, len)?;
        let (f, e) = (self.net.config().in_channels(), self.net.config().embed_dim);
        let n = self.workers.len();
        let share = batch.div_ceil(n).max(1);
        for (w, worker) in self.workers.iter_mut().enumerate() {
            worker.rows = (w * share).min(batch)..((w + 1) * share).min(batch);
        }
        let net = &self.net;
        let mut outs: Vec<&mut [T]> = out.chunks_mut(share * e).collect();
        outs.resize_with(n, || &mut []);
        self.workers
            .par_iter_mut()
            .zip(outs.into_par_iter())
            .try_for_each(|(w, o)| {
                let r = w.rows.clone();
                net.forward(
                    &x[r.start * len * f..r.end * len * f],
                    r.len(),
                    len,
                    &mut w.scratch,
                    o,
                )
            })?;
        self.len = len;
        Ok(())
    }

    /// The gradients of the loss whose gradient with respect to the last forward's output
    /// is `d_out [batch, embed_dim]`.
    pub fn backward(&mut self, d_out: &[T]) -> Result<&Grads<T>, FastNetError> {
        let e = self.net.config().embed_dim;
        let batch: usize = self.workers.iter().map(|w| w.rows.len()).sum();
        if d_out.len() != batch * e {
            return Err(FastNetError::Shape {
                what: "output gradient",
                expected: batch * e,
                got: d_out.len(),
            });
        }
        let net = &self.net;
        self.workers.par_iter_mut().try_for_each(|w| {
            w.grads.clear();
            let r = w.rows.clone();
            net.backward(
                &w.scratch,
                &d_out[r.start * e..r.end * e],
                &mut w.back,
                &mut w.grads,
            )
        })?;
        self.grads.clear();
        for w in &self.workers {
            self.grads.add(&w.grads);
        }
        Ok(&self.grads)
    }

    /// Parameters and the gradients of the last backward, side by side (for an optimiser).
    pub fn params_and_grads(&mut self) -> (Vec<&mut [T]>, &Grads<T>) {
        (self.net.params_mut(), &self.grads)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::FeatureKind;
    use crate::net::NetConfig;
    use rand::{Rng, SeedableRng};

    fn configs() -> Vec<NetConfig> {
        vec![
            NetConfig::tiny_joints(),
            NetConfig {
                features: FeatureKind::Pen,
                channels: vec![3, 4, 5],
                kernel: 5,
                embed_dim: 4,
                l2_normalize: true,
                reverse_average: false,
                test_views: Vec::new(),
            },
            NetConfig {
                features: FeatureKind::Pen,
                channels: vec![6],
                kernel: 1,
                embed_dim: 3,
                l2_normalize: false,
                reverse_average: false,
                test_views: Vec::new(),
            },
        ]
    }

    /// A random network with random (non-zero) biases, in f64.
    fn random_net(config: &NetConfig, seed: u64) -> FastNet<f64> {
        let mut net = FastNet::<f64>::random(config.clone(), seed).expect("net");
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed + 1);
        for p in net.params_mut() {
            for v in p.iter_mut() {
                *v += rng.random_range(-0.1..0.1);
            }
        }
        net
    }

    /// `L = (sum e * target)^2` and its gradient with respect to `e`.
    fn loss_and_grad(e: &[f64], target: &[f64]) -> (f64, Vec<f64>) {
        let s: f64 = e.iter().zip(target).map(|(a, b)| a * b).sum();
        (s * s, target.iter().map(|t| 2.0 * s * t).collect())
    }

    /// Backprop through the whole network (batch > 1, odd lengths whose trailing step the
    /// pooling drops) against central finite differences, in f64, on every parameter.
    #[test]
    fn gradients_match_finite_differences() {
        let mut checked = 0;
        for (ci, config) in configs().into_iter().enumerate() {
            for (batch, len) in [(3, 16), (2, 13)] {
                let net = random_net(&config, 7 + ci as u64);
                let f = config.in_channels();
                let mut rng = rand::rngs::StdRng::seed_from_u64(3 + ci as u64);
                let x: Vec<f64> = (0..batch * len * f)
                    .map(|_| rng.random_range(-1.0..1.0))
                    .collect();
                let target: Vec<f64> = (0..batch * config.embed_dim)
                    .map(|_| rng.random_range(-1.0..1.0))
                    .collect();
                let loss_of = |net: &FastNet<f64>| -> f64 {
                    let mut out = vec![0.0; batch * config.embed_dim];
                    net.forward(&x, batch, len, &mut Scratch::default(), &mut out)
                        .expect("forward");
                    loss_and_grad(&out, &target).0
                };
                let mut scratch = Scratch::default();
                let mut out = vec![0.0; batch * config.embed_dim];
                net.forward(&x, batch, len, &mut scratch, &mut out)
                    .expect("forward");
                let (_, d_out) = loss_and_grad(&out, &target);
                let mut grads = Grads::zeros_like(&net);
                net.backward(&scratch, &d_out, &mut BackScratch::default(), &mut grads)
                    .expect("backward");
                let eps = 1e-6;
                for (pi, g) in grads.params().iter().enumerate() {
                    for (idx, want) in g.iter().enumerate() {
                        let at = |delta: f64| {
                            let mut n = net.clone();
                            n.params_mut()[pi][idx] += delta;
                            loss_of(&n)
                        };
                        let fd = (at(eps) - at(-eps)) / (2.0 * eps);
                        let tol = 1e-6 * (1.0 + fd.abs());
                        assert!(
                            (fd - want).abs() < tol,
                            "config {ci} batch {batch} len {len} param {pi} idx {idx}: \
                             backprop {want} vs finite difference {fd}"
                        );
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 500, "{checked}");
    }

    /// Gradients accumulate: two backward passes into one `Grads` give twice one pass.
    /// And splitting a batch over workers gives the gradients of the whole batch.
    #[test]
    fn workers_and_accumulation_give_the_whole_batch_gradient() {
        let config = configs().remove(1);
        let net = random_net(&config, 2);
        let (batch, len) = (5, 16);
        let f = config.in_channels();
        let mut rng = rand::rngs::StdRng::seed_from_u64(8);
        let x: Vec<f64> = (0..batch * len * f)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let d_out: Vec<f64> = (0..batch * config.embed_dim)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let mut scratch = Scratch::default();
        let mut out = vec![0.0; batch * config.embed_dim];
        net.forward(&x, batch, len, &mut scratch, &mut out)
            .expect("forward");
        let mut once = Grads::zeros_like(&net);
        let mut back = BackScratch::default();
        net.backward(&scratch, &d_out, &mut back, &mut once)
            .expect("backward");
        let mut twice = once.clone();
        net.backward(&scratch, &d_out, &mut back, &mut twice)
            .expect("backward");
        for (a, b) in once.params().iter().zip(twice.params()) {
            for (x, y) in a.iter().zip(b) {
                assert!((2.0 * x - y).abs() <= 1e-12 * (1.0 + y.abs()));
            }
        }
        for workers in [1, 2, 3, 7] {
            let mut t = Trainable::with_workers(net.clone(), workers);
            let mut got = vec![0.0; batch * config.embed_dim];
            t.forward(&x, batch, len, &mut got).expect("forward");
            // The same sums, blocked differently by gemm for another number of rows.
            for (a, b) in got.iter().zip(&out) {
                assert!((a - b).abs() <= 1e-12, "{workers} workers: {a} vs {b}");
            }
            let g = t.backward(&d_out).expect("backward");
            for (a, b) in g.params().iter().zip(once.params()) {
                for (x, y) in a.iter().zip(b) {
                    assert!(
                        (x - y).abs() <= 1e-12 * (1.0 + y.abs()),
                        "{workers} workers: {x} vs {y}"
                    );
                }
            }
        }
    }

    #[test]
    fn refuses_mismatched_gradients() {
        let config = configs().remove(0);
        let net = random_net(&config, 1);
        let f = config.in_channels();
        let mut scratch = Scratch::default();
        let mut out = vec![0.0; 2 * config.embed_dim];
        net.forward(&vec![0.5; 2 * 8 * f], 2, 8, &mut scratch, &mut out)
            .expect("forward");
        let mut grads = Grads::zeros_like(&net);
        let err = net
            .backward(&scratch, &[0.0; 3], &mut BackScratch::default(), &mut grads)
            .unwrap_err();
        assert!(
            matches!(
                err,
                FastNetError::Shape {
                    what: "output gradient",
                    ..
                }
            ),
            "{err}"
        );
        let mut t = Trainable::with_workers(net, 2);
        let err = t.forward(&[0.0; 5], 2, 8, &mut out).unwrap_err();
        assert!(
            matches!(err, FastNetError::Shape { what: "input", .. }),
            "{err}"
        );
    }
}
