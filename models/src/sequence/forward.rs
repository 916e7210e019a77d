//! The fast path: the exact network of [`crate::net`] in plain Rust, with each
//! convolution as one GEMM from the `gemm` crate (AVX-512 / AVX2 / SSE kernels chosen at run
//! time, so the binary stays portable) whose left operand is the time-padded layer input
//! read with overlapping rows (no im2col copy), ReLU fused into the pooling, and all
//! intermediate buffers kept in a reusable [`Scratch`] (no allocation per call once the
//! scratch has grown to the largest batch seen).
//!
//! The daemon serves with it, and training runs it too: the forward keeps every layer's
//! input and output in the [`Scratch`], from which [`crate::sequence::backward`] computes the backward
//! with the same GEMM. candle's [`Net`] is the reference path: a test checks both agree to
//! 1e-5 relative error, on random inputs with random weights and with the shipped model.
//! The arithmetic is generic over [`Real`] (`f32`; `f64` for gradient checks).
//!
//! The one `unsafe` block in this crate is the call into `gemm::gemm`, which takes raw
//! pointers; `gemm_strided` checks every operand's extent first. It is here because of a measured
//! need: see `docs/performance.md`.

#[cfg(feature = "train")]
use crate::net::Net;
use crate::net::NetConfig;
#[cfg(feature = "train")]
use candle_core::{DType, Device, Tensor};

/// Building or running the fast path failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FastNetError {
    /// The configuration is not one the network supports.
    #[error("unsupported network config: {0}")]
    Config(String),
    /// A parameter tensor has the wrong length.
    #[error("parameter `{name}`: expected {expected} values, got {got}")]
    ParamLength {
        /// Parameter name.
        name: String,
        /// Expected number of values.
        expected: usize,
        /// Number given.
        got: usize,
    },
    /// Reading the weights out of candle failed.
    #[cfg(feature = "train")]
    #[error("reading weights: {0}")]
    Candle(#[from] candle_core::Error),
    /// An input or output buffer does not match `batch`, the time length and the config.
    #[error("{what}: expected {expected} values, got {got}")]
    Shape {
        /// Which buffer.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Given length.
        got: usize,
    },
    /// The time length is too short for the pooling layers.
    #[error("time length {len} is too short for {pools} pooling layers")]
    TooShort {
        /// Time steps given.
        len: usize,
        /// Pooling layers of the network.
        pools: usize,
    },
}

/// Element type of the fast path: `f32` for serving and training, `f64` for the gradient
/// checks against finite differences. The arithmetic is the same code for both.
pub trait Real:
    num_traits::Float + Default + std::iter::Sum + std::fmt::Debug + Send + Sync + 'static
{
}
impl Real for f32 {}
impl Real for f64 {}

/// One convolution layer: `w [k*c_in, c_out]` (row `j*c_in + c` = tap `j` of channel `c`).
#[derive(Debug, Clone)]
pub(crate) struct Conv<T> {
    pub(crate) c_in: usize,
    pub(crate) c_out: usize,
    pub(crate) w: Vec<T>,
    pub(crate) b: Vec<T>,
}

/// The embedding network with its weights in plain `Vec`s (`f32` unless stated).
#[derive(Debug, Clone)]
pub struct FastNet<T = f32> {
    config: NetConfig,
    pub(crate) kernel: usize,
    pub(crate) convs: Vec<Conv<T>>,
    pub(crate) fc_w: Vec<T>,
    pub(crate) fc_b: Vec<T>,
}

/// Reusable intermediate buffers of a forward pass, kept per layer so that
/// [`FastNet::backward`](crate::sequence::backward) can read them. Grows to the largest batch seen, then
/// never allocates.
#[derive(Debug, Clone)]
pub struct Scratch<T = f32> {
    /// Per layer: its input, time-padded (see [`FastNet::forward`]).
    pub(crate) inputs: Vec<Vec<T>>,
    /// Per layer: its convolution output before ReLU, one row per padded input row
    /// (`batch * (l + 2 pad) - 2 pad` rows; the rows between two sequences are unused).
    pub(crate) outputs: Vec<Vec<T>>,
    /// Global mean and max over time of the last layer, `[batch, 2 * c_last]`.
    pub(crate) pooled: Vec<T>,
    /// The network output of the last forward, `[batch, embed_dim]`.
    pub(crate) emb: Vec<T>,
    /// Per sequence: the L2 norm the output was divided by.
    pub(crate) norms: Vec<T>,
    /// `(batch, len)` of the last forward.
    pub(crate) shape: (usize, usize),
    /// The input map of the picture layer being computed (picture networks only).
    pub(crate) map: Vec<T>,
}

impl<T> Default for Scratch<T> {
    fn default() -> Self {
        Self {
            inputs: Vec::new(),
            outputs: Vec::new(),
            pooled: Vec::new(),
            emb: Vec::new(),
            norms: Vec::new(),
            shape: (0, 0),
            map: Vec::new(),
        }
    }
}

pub(crate) fn grow<T: Real>(v: &mut Vec<T>, n: usize) -> &mut [T] {
    if v.len() < n {
        v.resize(n, T::zero());
    }
    &mut v[..n]
}

/// `v` as `T` (exact for every value an `f32` or `f64` network holds).
pub(crate) fn real<T: Real>(v: f64) -> T {
    T::from(v).unwrap_or_else(T::nan)
}

#[cfg(feature = "train")]
impl FastNet<f32> {
    /// Copy the weights of a candle network.
    pub fn from_net(net: &Net) -> Result<Self, FastNetError> {
        let params = net
            .params()
            .iter()
            .map(|t| t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>())
            .collect::<candle_core::Result<Vec<_>>>()?;
        Self::from_params(net.config().clone(), params)
    }

    /// The weights as a candle network (for training and for the reference path).
    pub fn to_net(&self) -> candle_core::Result<Net> {
        let tensors = self
            .config
            .param_shapes()
            .into_iter()
            .zip(self.params())
            .map(|((_, shape), p)| Tensor::from_slice(p, shape, &Device::Cpu))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Net::new(self.config.clone(), tensors)
    }
}

impl<T: Real> FastNet<T> {
    /// Build from flat parameters in [`NetConfig::param_shapes`] order.
    pub fn from_params(config: NetConfig, params: Vec<Vec<T>>) -> Result<Self, FastNetError> {
        config.check().map_err(FastNetError::Config)?;
        let shapes = config.param_shapes();
        if shapes.len() != params.len() {
            return Err(FastNetError::Config(format!(
                "expected {} parameter tensors, got {}",
                shapes.len(),
                params.len()
            )));
        }
        for ((name, shape), p) in shapes.iter().zip(&params) {
            let expected: usize = shape.iter().product();
            if p.len() != expected {
                return Err(FastNetError::ParamLength {
                    name: name.clone(),
                    expected,
                    got: p.len(),
                });
            }
        }
        let mut it = params.into_iter();
        let mut convs = Vec::with_capacity(config.channels.len());
        let mut c_in = config.in_channels();
        for &c_out in &config.channels {
            let (Some(w), Some(b)) = (it.next(), it.next()) else {
                return Err(FastNetError::Config(
                    "missing convolution parameters".into(),
                ));
            };
            convs.push(Conv { c_in, c_out, w, b });
            c_in = c_out;
        }
        let (Some(fc_w), Some(fc_b)) = (it.next(), it.next()) else {
            return Err(FastNetError::Config("missing fc parameters".into()));
        };
        Ok(Self {
            kernel: config.kernel,
            config,
            convs,
            fc_w,
            fc_b,
        })
    }

    /// Deterministic initial weights of `config` for `seed` (the values of
    /// [`NetConfig::init`], as `T`; feature `train`).
    #[cfg(any(test, feature = "train"))]
    pub fn random(config: NetConfig, seed: u64) -> Result<Self, FastNetError> {
        let params = config
            .init(seed)
            .into_iter()
            .map(|(_, _, d)| d.into_iter().map(|v| real(f64::from(v))).collect())
            .collect();
        Self::from_params(config, params)
    }

    /// The architecture.
    pub fn config(&self) -> &NetConfig {
        &self.config
    }

    /// Turn test-time reverse averaging on or off (see [`NetConfig::reverse_average`]): an
    /// inference option that changes no weight.
    pub fn set_reverse_average(&mut self, on: bool) {
        self.config.reverse_average = on;
    }

    /// Set the test-time views (see [`NetConfig::test_views`]): an inference option that
    /// changes no weight.
    pub fn set_test_views(&mut self, views: &[crate::net::TestView]) {
        self.config.test_views = views.to_vec();
    }

    /// The parameters, in [`NetConfig::param_shapes`] order.
    pub fn params(&self) -> Vec<&[T]> {
        let mut out = Vec::with_capacity(2 * self.convs.len() + 2);
        for c in &self.convs {
            out.push(c.w.as_slice());
            out.push(c.b.as_slice());
        }
        out.push(&self.fc_w);
        out.push(&self.fc_b);
        out
    }

    /// The parameters, mutable (an optimiser's view), in [`NetConfig::param_shapes`] order.
    pub fn params_mut(&mut self) -> Vec<&mut [T]> {
        let mut out = Vec::with_capacity(2 * self.convs.len() + 2);
        for c in &mut self.convs {
            out.push(c.w.as_mut_slice());
            out.push(c.b.as_mut_slice());
        }
        out.push(&mut self.fc_w);
        out.push(&mut self.fc_b);
        out
    }

    /// Floating-point operations (multiply and add counted separately) of one forward pass
    /// of one sequence of `len` steps: convolutions and the output layer.
    pub fn flops(&self, len: usize) -> u64 {
        if self.config.features.is_picture() {
            return self.picture_flops();
        }
        let mut l = len as u64;
        let mut total = 0u64;
        let n = self.convs.len();
        for (i, c) in self.convs.iter().enumerate() {
            total += 2 * l * (self.kernel * c.c_in) as u64 * c.c_out as u64;
            if i + 1 < n {
                l /= 2;
            }
        }
        let last = self.convs.last().map_or(0, |c| c.c_out) as u64;
        total + 2 * (2 * last) * self.config.embed_dim as u64
    }

    /// Check that an input of `x_len` values and an output of `out_len` values fit `batch`
    /// sequences of `len` steps.
    pub(crate) fn check_io(
        &self,
        x_len: usize,
        out_len: usize,
        batch: usize,
        len: usize,
    ) -> Result<(), FastNetError> {
        let (f, e) = (self.config.in_channels(), self.config.embed_dim);
        if x_len != batch * len * f {
            return Err(FastNetError::Shape {
                what: "input",
                expected: batch * len * f,
                got: x_len,
            });
        }
        if out_len != batch * e {
            return Err(FastNetError::Shape {
                what: "output",
                expected: batch * e,
                got: out_len,
            });
        }
        Ok(())
    }

    /// Embed `batch` feature sequences `x [batch, len, in_channels]` (row-major) into
    /// `out [batch, embed_dim]`, exactly as [`Net::forward`] does. `scratch` keeps every
    /// layer's input and output for [`FastNet::backward`].
    pub fn forward(
        &self,
        x: &[T],
        batch: usize,
        len: usize,
        scratch: &mut Scratch<T>,
        out: &mut [T],
    ) -> Result<(), FastNetError> {
        self.check_io(x.len(), out.len(), batch, len)?;
        if self.config.features.is_picture() {
            let pixels = self.config.features.steps();
            if len != pixels {
                return Err(FastNetError::Shape {
                    what: "picture",
                    expected: pixels,
                    got: len,
                });
            }
            scratch.shape = (0, 0);
            if batch == 0 {
                return Ok(());
            }
            return self.forward_picture(x, batch, scratch, out);
        }
        let (f, e) = (self.config.in_channels(), self.config.embed_dim);
        let pools = self.convs.len() - 1;
        if len >> pools == 0 {
            return Err(FastNetError::TooShort { len, pools });
        }
        scratch.shape = (0, 0);
        if batch == 0 {
            return Ok(());
        }
        let k = self.kernel;
        let pad = k / 2;
        let n_layers = self.convs.len();
        let Scratch {
            inputs,
            outputs,
            pooled,
            emb,
            norms,
            shape,
            ..
        } = scratch;
        inputs.resize_with(n_layers, Vec::new);
        outputs.resize_with(n_layers, Vec::new);
        // Layer inputs are kept time-padded: sequence `b` occupies rows
        // `b * (l + 2 pad) ..`, its `pad` first and last rows zero. The `k` taps of every
        // channel of output step `t` are then the `k * c` consecutive values from row
        // `b * (l + 2 pad) + t`, so the convolution is one GEMM whose left operand rows
        // overlap (row stride `c`, width `k * c`): no im2col copy. The `2 pad` rows between
        // two sequences produce output rows that are ignored.
        pad_rows(
            grow(&mut inputs[0], batch * (len + 2 * pad) * f),
            x,
            batch,
            len,
            pad,
            f,
        );
        let mut l = len;
        for (i, conv) in self.convs.iter().enumerate() {
            let (c, o) = (conv.c_in, conv.c_out);
            let lp = l + 2 * pad;
            let rows = batch * lp - 2 * pad;
            let (done, rest) = inputs.split_at_mut(i + 1);
            let h = &done[i][..batch * lp * c];
            // y = bias + taps · W
            let y = grow(&mut outputs[i], rows * o);
            for row in y.chunks_exact_mut(o) {
                row.copy_from_slice(&conv.b);
            }
            conv_rows(rows, o, k * c, h, c, &conv.w, y)?;
            if i + 1 < n_layers {
                // ReLU + max pool of 2 (a trailing odd step is dropped); relu(max) = max(relu),
                // into the next layer's padded input.
                let half = l / 2;
                let hp = half + 2 * pad;
                let next_in = grow(&mut rest[0], batch * hp * o);
                for b in 0..batch {
                    let seq = &mut next_in[b * hp * o..(b + 1) * hp * o];
                    seq[..pad * o].fill(T::zero());
                    seq[(pad + half) * o..].fill(T::zero());
                    for t in 0..half {
                        let r0 = (b * lp + 2 * t) * o;
                        let (y0, y1) = y[r0..r0 + 2 * o].split_at(o);
                        let d = (pad + t) * o;
                        for ((v, a), c) in seq[d..d + o].iter_mut().zip(y0).zip(y1) {
                            *v = a.max(*c).max(T::zero());
                        }
                    }
                }
                l = half;
            } else {
                // ReLU, then mean and max over time, concatenated.
                let p = grow(pooled, batch * 2 * o);
                let inv = T::one() / real(l as f64);
                for b in 0..batch {
                    let (mean, max) = p[b * 2 * o..(b + 1) * 2 * o].split_at_mut(o);
                    mean.fill(T::zero());
                    max.fill(T::neg_infinity());
                    for t in 0..l {
                        let row = &y[(b * lp + t) * o..(b * lp + t + 1) * o];
                        for ((m, x), v) in mean.iter_mut().zip(max.iter_mut()).zip(row) {
                            let v = v.max(T::zero());
                            *m = *m + v;
                            *x = x.max(v);
                        }
                    }
                    for m in mean.iter_mut() {
                        *m = *m * inv;
                    }
                }
                for row in out.chunks_exact_mut(e) {
                    row.copy_from_slice(&self.fc_b);
                }
                gemm_strided(
                    batch,
                    e,
                    2 * o,
                    out,
                    (p, 2 * o, 1),
                    (&self.fc_w, e, 1),
                    true,
                )?;
            }
        }
        l2_normalize_rows(self.config.l2_normalize, out, e, grow(norms, batch));
        grow(emb, batch * e).copy_from_slice(out);
        *shape = (batch, len);
        Ok(())
    }
}

/// Divide every row of `e` values of `out` by its L2 norm (with `l2`; otherwise leave it),
/// writing the norm each row was divided by (1 without `l2`) to `norms`: the network's last
/// step, shared by the sequence and the picture network.
pub(crate) fn l2_normalize_rows<T: Real>(l2: bool, out: &mut [T], e: usize, norms: &mut [T]) {
    if !l2 {
        norms.fill(T::one());
        return;
    }
    let eps = real::<T>(1e-12);
    for (row, n) in out.chunks_exact_mut(e).zip(norms.iter_mut()) {
        let norm = (row.iter().map(|v| *v * *v).sum::<T>() + eps).sqrt();
        for v in row.iter_mut() {
            *v = *v / norm;
        }
        *n = norm;
    }
}

/// Copy `batch` sequences of `len` rows of `c` values from `x` into `h` with `pad` zero rows
/// before and after each.
pub(crate) fn pad_rows<T: Real>(
    h: &mut [T],
    x: &[T],
    batch: usize,
    len: usize,
    pad: usize,
    c: usize,
) {
    let lp = len + 2 * pad;
    for (seq, src) in h[..batch * lp * c]
        .chunks_exact_mut(lp * c)
        .zip(x.chunks_exact(len * c))
    {
        seq[..pad * c].fill(T::zero());
        seq[pad * c..(pad + len) * c].copy_from_slice(src);
        seq[(pad + len) * c..].fill(T::zero());
    }
}

/// `dst [m, n] (+)= a [m, k] · b [k, n]`, all row-major and contiguous; with `accumulate`
/// the product is added to `dst`, otherwise it replaces it. Single-threaded (batch-1 serving
/// is fastest on one core here).
pub fn sgemm(
    m: usize,
    n: usize,
    k: usize,
    a: &[f32],
    b: &[f32],
    dst: &mut [f32],
    accumulate: bool,
) -> Result<(), FastNetError> {
    gemm_strided(m, n, k, dst, (a, k, 1), (b, n, 1), accumulate)
}

/// The convolution's GEMM: `dst [m, n] += a · b` where row `r` of `a` is the `k` values
/// from `a[r * lda]` (`lda < k`: overlapping rows, the taps of one output step).
pub(crate) fn conv_rows<T: Real>(
    m: usize,
    n: usize,
    k: usize,
    a: &[T],
    lda: usize,
    b: &[T],
    dst: &mut [T],
) -> Result<(), FastNetError> {
    gemm_strided(m, n, k, dst, (a, lda, 1), (b, n, 1), true)
}

/// `dst [m, n] (+)= A · B` with `dst` row-major and contiguous, and each operand given as
/// `(values, row stride, column stride)`: element `(i, j)` of `A` is `a[i * rs + j * cs]`.
/// Rows may overlap and either operand may be a transposed view. With `accumulate` the
/// product is added to `dst`, otherwise it replaces it. Single-threaded.
pub(crate) fn gemm_strided<T: Real>(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [T],
    (a, a_rs, a_cs): (&[T], usize, usize),
    (b, b_rs, b_cs): (&[T], usize, usize),
    accumulate: bool,
) -> Result<(), FastNetError> {
    let check = |what, expected: usize, got: usize| {
        if got < expected {
            Err(FastNetError::Shape {
                what,
                expected,
                got,
            })
        } else {
            Ok(())
        }
    };
    let extent = |rows: usize, cols: usize, rs: usize, cs: usize| {
        if rows == 0 || cols == 0 {
            0
        } else {
            (rows - 1) * rs + (cols - 1) * cs + 1
        }
    };
    check("gemm lhs", extent(m, k, a_rs, a_cs), a.len())?;
    check("gemm rhs", extent(k, n, b_rs, b_cs), b.len())?;
    check("gemm dst", m * n, dst.len())?;
    if m == 0 || n == 0 {
        return Ok(());
    }
    if k == 0 {
        if !accumulate {
            dst[..m * n].fill(T::zero());
        }
        return Ok(());
    }
    let stride = |s: usize| isize::try_from(s).map_err(|_| FastNetError::Config("stride".into()));
    let (a_rs, a_cs, b_rs, b_cs, n_rs) = (
        stride(a_rs)?,
        stride(a_cs)?,
        stride(b_rs)?,
        stride(b_cs)?,
        stride(n)?,
    );
    // SAFETY: every element gemm reads of `a` is at `i * a_rs + p * a_cs` for i < m, p < k,
    // of `b` at `p * b_rs + j * b_cs` for p < k, j < n, and it writes `dst` at `i * n + j`:
    // all within the extents checked above (rows of `a` may overlap; gemm only reads them).
    // `dst` is borrowed mutably, so it aliases neither input. gemm neither keeps the
    // pointers nor reads past those extents; `T` is `f32` or `f64`, both supported by gemm.
    #[allow(unsafe_code)]
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n_rs,
            accumulate,
            a.as_ptr(),
            a_cs,
            a_rs,
            b.as_ptr(),
            b_cs,
            b_rs,
            T::one(),
            T::one(),
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    Ok(())
}

// Against the candle reference (feature `train`, on in the workspace's test run).
#[cfg(all(test, feature = "train"))]
pub(crate) mod tests {
    use super::*;
    use crate::features::FeatureKind;
    use candle_core::{Device, Tensor};
    use guardian_shared::trajectory::STEPS;
    use rand::{Rng, SeedableRng};

    /// `||a - b|| / ||b||` (L2 over the whole slices).
    /// Relative L2 error of `a` against `b`.
    pub(crate) fn rel_err(a: &[f32], b: &[f32]) -> f64 {
        assert_eq!(a.len(), b.len());
        let num: f64 = a
            .iter()
            .zip(b)
            .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
            .sum();
        let den: f64 = b.iter().map(|y| f64::from(*y).powi(2)).sum();
        (num / den.max(1e-30)).sqrt()
    }

    /// Fast forward vs candle's `Net::forward` on random inputs, per sample.
    fn compare(config: NetConfig, seed: u64, batch: usize, len: usize) -> f64 {
        let net = Net::random(config.clone(), seed, DType::F32).expect("net");
        let fast = FastNet::from_net(&net).expect("fast net");
        let f = config.in_channels();
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed + 100);
        let x: Vec<f32> = (0..batch * len * f)
            .map(|_| rng.random_range(-1.5..1.5))
            .collect();
        let want = net
            .forward(&Tensor::from_vec(x.clone(), (batch, len, f), &Device::Cpu).expect("t"))
            .expect("candle forward")
            .flatten_all()
            .expect("flat")
            .to_vec1::<f32>()
            .expect("vec");
        let mut got = vec![0.0f32; batch * config.embed_dim];
        let mut scratch = Scratch::default();
        fast.forward(&x, batch, len, &mut scratch, &mut got)
            .expect("fast forward");
        // Twice with the same scratch: reused buffers must not leak state between calls.
        let mut again = vec![0.0f32; batch * config.embed_dim];
        fast.forward(&x, batch, len, &mut scratch, &mut again)
            .expect("fast forward");
        assert_eq!(got, again);
        got.chunks_exact(config.embed_dim)
            .zip(want.chunks_exact(config.embed_dim))
            .map(|(g, w)| rel_err(g, w))
            .fold(0.0, f64::max)
    }

    #[test]
    fn matches_candle_on_random_weights_and_inputs() {
        let configs = [
            NetConfig::default(),
            NetConfig::tiny_joints(),
            NetConfig {
                features: FeatureKind::Pen,
                channels: vec![32, 64, 64, 96],
                kernel: 7,
                embed_dim: 128,
                l2_normalize: false,
                reverse_average: false,
                test_views: Vec::new(),
            },
            NetConfig {
                features: FeatureKind::Pen,
                channels: vec![16],
                kernel: 1,
                embed_dim: 20,
                l2_normalize: true,
                reverse_average: false,
                test_views: Vec::new(),
            },
        ];
        for (i, config) in configs.into_iter().enumerate() {
            for (batch, len) in [(1, STEPS), (3, STEPS), (2, 37)] {
                let e = compare(config.clone(), i as u64, batch, len);
                assert!(
                    e <= 1e-5,
                    "config {i} batch {batch} len {len}: relative error {e:e}"
                );
            }
        }
    }

    #[test]
    fn refuses_bad_shapes() {
        let fast =
            FastNet::from_net(&Net::random(NetConfig::default(), 1, DType::F32).unwrap()).unwrap();
        let mut s = Scratch::default();
        let mut out = vec![0.0; 128];
        let err = fast
            .forward(&[0.0; 10], 1, STEPS, &mut s, &mut out)
            .unwrap_err();
        assert!(
            matches!(err, FastNetError::Shape { what: "input", .. }),
            "{err}"
        );
        let x = vec![0.0; 2 * 7];
        let err = fast.forward(&x, 1, 2, &mut s, &mut out).unwrap_err();
        assert!(matches!(err, FastNetError::TooShort { .. }), "{err}");
        let x = vec![0.0; STEPS * 7];
        let err = fast
            .forward(&x, 1, STEPS, &mut s, &mut out[..5])
            .unwrap_err();
        assert!(
            matches!(err, FastNetError::Shape { what: "output", .. }),
            "{err}"
        );
        let err = FastNet::from_params(NetConfig::default(), vec![vec![0.0; 3]]).unwrap_err();
        assert!(matches!(err, FastNetError::Config(_)), "{err}");
        let mut params: Vec<Vec<f32>> = NetConfig::default()
            .init(0)
            .into_iter()
            .map(|(_, _, d)| d)
            .collect();
        params[1].pop();
        let err = FastNet::from_params(NetConfig::default(), params).unwrap_err();
        assert!(matches!(err, FastNetError::ParamLength { .. }), "{err}");
    }

    #[test]
    fn flops_of_the_default_net() {
        let fast =
            FastNet::from_net(&Net::random(NetConfig::default(), 1, DType::F32).unwrap()).unwrap();
        // 128x35x64 + 64x320x128 + 32x640x128 multiply-adds, fc 256x128.
        let want = 2 * (128 * 35 * 64 + 64 * 320 * 128 + 32 * 640 * 128 + 256 * 128);
        assert_eq!(fast.flops(STEPS), want);
    }
}
