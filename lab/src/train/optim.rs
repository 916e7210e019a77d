//! The optimiser: AdamW with decoupled weight decay over the flat weights of the fast path
//! (its moments saved for an exact `--resume`), and [`Learner`], which takes one training
//! step: forward on the fast path, the loss and its gradient on the embeddings with candle's
//! autograd, the hand-written backward through the network, one AdamW update.

use candle_core::{Device, Tensor, Var};
use guardian_models::sequence::backward::{Grads, Trainable};
use guardian_models::sequence::forward::FastNet;

use crate::train::TrainError;

/// AdamW with decoupled weight decay whose moments can be saved (for exact `--resume`),
/// over the flat parameters of a [`FastNet`].
pub struct AdamW {
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    step: usize,
    weight_decay: f64,
}

impl AdamW {
    /// Fresh optimiser for the parameters of `net`.
    pub fn new(net: &FastNet, weight_decay: f64) -> Self {
        let lens: Vec<usize> = net.params().iter().map(|p| p.len()).collect();
        Self::for_lens(&lens, weight_decay)
    }

    /// Fresh optimiser for parameter tensors of `lens` elements.
    pub fn for_lens(lens: &[usize], weight_decay: f64) -> Self {
        let m: Vec<Vec<f32>> = lens.iter().map(|&n| vec![0.0; n]).collect();
        Self {
            v: m.clone(),
            m,
            step: 0,
            weight_decay,
        }
    }

    /// The first and second moments, per parameter tensor.
    pub fn moments(&self) -> (&[Vec<f32>], &[Vec<f32>]) {
        (&self.m, &self.v)
    }

    /// Updates taken so far.
    pub fn steps(&self) -> usize {
        self.step
    }

    /// Continue from saved moments after `step` updates (`--resume`); refused unless they
    /// have this optimiser's shapes.
    pub fn restore(
        &mut self,
        m: Vec<Vec<f32>>,
        v: Vec<Vec<f32>>,
        step: usize,
    ) -> Result<(), TrainError> {
        let shapes_match = |saved: &[Vec<f32>], own: &[Vec<f32>]| {
            saved.len() == own.len() && saved.iter().zip(own).all(|(a, b)| a.len() == b.len())
        };
        if !shapes_match(&m, &self.m) || !shapes_match(&v, &self.v) {
            return Err(TrainError::Setup(
                "optimizer checkpoint does not match".into(),
            ));
        }
        self.m = m;
        self.v = v;
        self.step = step;
        Ok(())
    }

    /// One update of `params` (in [`NetConfig::param_shapes`] order) along `grads` (the
    /// same order and shapes) with learning rate `lr`.
    ///
    /// [`NetConfig::param_shapes`]: guardian_models::net::NetConfig::param_shapes
    pub fn step(&mut self, params: Vec<&mut [f32]>, grads: &[Vec<f32>], lr: f64) {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8f32);
        self.step += 1;
        let c1 = (1.0 / (1.0 - f64::powi(b1, self.step as i32))) as f32;
        let c2 = (1.0 / (1.0 - f64::powi(b2, self.step as i32))) as f32;
        let (b1, b2) = (b1 as f32, b2 as f32);
        let (lr, decay) = (lr as f32, (1.0 - lr * self.weight_decay) as f32);
        for (((theta, g), m), v) in params
            .into_iter()
            .zip(grads)
            .zip(&mut self.m)
            .zip(&mut self.v)
        {
            for (((t, g), m), v) in theta.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *m = *m * b1 + g * (1.0 - b1);
                *v = *v * b2 + g * g * (1.0 - b2);
                let upd = (*m * c1) / ((*v * c2).sqrt() + eps);
                *t = *t * decay - upd * lr;
            }
        }
    }
}

/// The class proxies of a [`LossKind::NormSoftmax`] run, `[classes, dim]` row-major, with
/// an AdamW of their own (no weight decay: the loss normalises them), stepped with the
/// network at a multiple of its learning rate ([`Proxies::with_lr_scale`]). They exist
/// only in training: the model file holds the network alone.
///
/// [`LossKind::NormSoftmax`]: crate::train::config::LossKind::NormSoftmax
pub struct Proxies {
    w: Vec<f32>,
    classes: usize,
    dim: usize,
    opt: AdamW,
    grad: Vec<f32>,
    lr_scale: f64,
}

impl Proxies {
    /// Proxies in random directions (uniform in [−1, 1) per coordinate), from `seed`.
    pub fn random(classes: usize, dim: usize, seed: u64) -> Self {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let w = (0..classes * dim)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect();
        Self::from_weights(w, classes, dim)
    }

    /// Saved proxies (a fresh optimiser: [`Proxies::optimizer_mut`] restores its moments).
    pub fn from_weights(w: Vec<f32>, classes: usize, dim: usize) -> Self {
        Self {
            w,
            classes,
            dim,
            opt: AdamW::for_lens(&[classes * dim], 0.0),
            grad: vec![0.0; classes * dim],
            lr_scale: 1.0,
        }
    }

    /// Step them at `scale` times the network's learning rate (1 unless set).
    pub fn with_lr_scale(mut self, scale: f64) -> Self {
        self.lr_scale = scale;
        self
    }

    /// The weights, `[classes, dim]` row-major.
    pub fn weights(&self) -> &[f32] {
        &self.w
    }

    /// `(classes, dim)`.
    pub fn shape(&self) -> (usize, usize) {
        (self.classes, self.dim)
    }

    /// Their optimiser.
    pub fn optimizer(&self) -> &AdamW {
        &self.opt
    }

    /// Their optimiser, to restore its moments.
    pub fn optimizer_mut(&mut self) -> &mut AdamW {
        &mut self.opt
    }
}

/// A network in training: the fast path's weights with a workspace per thread
/// ([`Trainable`]) and its optimiser. One [`Learner::step`] embeds a batch, takes the loss of
/// the embeddings with candle's autograd, backpropagates through the network by hand and
/// updates the weights.
pub struct Learner {
    model: Trainable,
    opt: AdamW,
    emb: Vec<f32>,
    proxies: Option<Proxies>,
}

impl Learner {
    /// Train `net` with AdamW (`weight_decay`), on as many threads as rayon has.
    pub fn new(net: FastNet, weight_decay: f64) -> Self {
        Self {
            opt: AdamW::new(&net, weight_decay),
            model: Trainable::new(net),
            emb: Vec::new(),
            proxies: None,
        }
    }

    /// Train class proxies beside the network (the loss gets them).
    pub fn with_proxies(mut self, proxies: Proxies) -> Self {
        self.proxies = Some(proxies);
        self
    }

    /// The class proxies, if trained.
    pub fn proxies(&self) -> Option<&Proxies> {
        self.proxies.as_ref()
    }

    /// The network with its current weights.
    pub fn net(&self) -> &FastNet {
        self.model.net()
    }

    /// The optimiser.
    pub fn optimizer(&self) -> &AdamW {
        &self.opt
    }

    /// The optimiser, to restore its moments.
    pub fn optimizer_mut(&mut self) -> &mut AdamW {
        &mut self.opt
    }

    /// The gradients of `loss` on the embeddings of `x [B, STEPS, F]` (and on the class
    /// proxies, which `loss` gets when there are some), without updating anything. Returns
    /// the network's gradients, the loss and what `loss` returned besides it.
    pub fn gradients<R>(
        &mut self,
        x: &Tensor,
        loss: impl FnOnce(&Tensor, Option<&Tensor>) -> candle_core::Result<(Tensor, R)>,
    ) -> Result<(&Grads, f32, R), TrainError> {
        let (b, l, _) = x.dims3()?;
        let flat = x.flatten_all()?.to_vec1::<f32>()?;
        let e = self.model.net().config().embed_dim;
        self.emb.resize(b * e, 0.0);
        self.model.forward(&flat, b, l, &mut self.emb)?;
        let emb = Var::from_slice(&self.emb, (b, e), &Device::Cpu)?;
        let proxies = match &self.proxies {
            Some(p) => Some(Var::from_slice(&p.w, (p.classes, p.dim), &Device::Cpu)?),
            None => None,
        };
        let (value, extra) = loss(emb.as_tensor(), proxies.as_ref().map(Var::as_tensor))?;
        let store = value.backward()?;
        if let (Some(p), Some(v)) = (self.proxies.as_mut(), &proxies) {
            match store.get(v.as_tensor()) {
                Some(g) => p.grad = g.flatten_all()?.to_vec1::<f32>()?,
                None => p.grad.iter_mut().for_each(|g| *g = 0.0),
            }
        }
        let d_out = match store.get(emb.as_tensor()) {
            Some(g) => g.flatten_all()?.to_vec1::<f32>()?,
            // The loss does not depend on the embeddings (no valid triplet): zero gradient.
            None => vec![0.0; b * e],
        };
        let value = value.to_scalar::<f32>()?;
        Ok((self.model.backward(&d_out)?, value, extra))
    }

    /// One training step on `x` with learning rate `lr`: gradients of `loss` (see
    /// [`Learner::gradients`]) and one AdamW update. Returns the loss and `loss`'s extra.
    pub fn step<R>(
        &mut self,
        x: &Tensor,
        lr: f64,
        loss: impl FnOnce(&Tensor, Option<&Tensor>) -> candle_core::Result<(Tensor, R)>,
    ) -> Result<(f32, R), TrainError> {
        let (_, value, extra) = self.gradients(x, loss)?;
        let (params, grads) = self.model.params_and_grads();
        self.opt.step(params, grads.params(), lr);
        if let Some(p) = self.proxies.as_mut() {
            let lr = lr * p.lr_scale;
            p.opt
                .step(vec![p.w.as_mut_slice()], std::slice::from_ref(&p.grad), lr);
        }
        Ok((value, extra))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// AdamW's first step moves every weight by about `lr` against its gradient's sign
    /// (bias-corrected moments), after the decoupled decay; a zero gradient only decays.
    #[test]
    fn the_first_adamw_step_is_lr_against_the_gradient_after_decay() {
        let net = FastNet::random(guardian_models::net::NetConfig::default(), 1).expect("net");
        let mut opt = AdamW::new(&net, 0.1);
        let mut w: Vec<Vec<f32>> = opt.moments().0.iter().map(|m| vec![1.0; m.len()]).collect();
        let g: Vec<Vec<f32>> = w
            .iter()
            .map(|x| {
                (0..x.len())
                    .map(|k| match k % 3 {
                        0 => 0.5,
                        1 => -2.0,
                        _ => 0.0,
                    })
                    .collect()
            })
            .collect();
        let lr = 0.01;
        opt.step(w.iter_mut().map(Vec::as_mut_slice).collect(), &g, lr);
        assert_eq!(opt.steps(), 1);
        let decayed = 1.0 - (lr * 0.1) as f32;
        for (x, gx) in w.iter().flatten().zip(g.iter().flatten()) {
            let want = decayed - (lr as f32) * gx.signum() * f32::from(*gx != 0.0);
            assert!((x - want).abs() < 1e-6, "{x} vs {want} (gradient {gx})");
        }
        // The moments are the gradient's, scaled by (1 - beta).
        let (m, v) = opt.moments();
        assert!((m[0][1] - 0.1 * -2.0).abs() < 1e-6);
        assert!((v[0][1] - 0.001 * 4.0).abs() < 1e-6);
    }

    #[test]
    fn moments_of_another_shape_are_refused() {
        let net = FastNet::random(guardian_models::net::NetConfig::default(), 1).expect("net");
        let mut opt = AdamW::new(&net, 0.0);
        let (m, v) = (opt.moments().0.to_vec(), opt.moments().1.to_vec());
        let mut short = m.clone();
        short[0].pop();
        assert!(opt.restore(short, v.clone(), 3).is_err());
        assert_eq!(opt.steps(), 0, "a refused restore changes nothing");
        opt.restore(m, v, 3).expect("same shapes");
        assert_eq!(opt.steps(), 3);
    }
}
