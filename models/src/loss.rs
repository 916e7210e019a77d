//! Metric-learning losses on squared Euclidean distances.
//!
//! * [`triplet_loss`] — the paper's loss on explicit (anchor, positive, negative) triplets:
//!   `mean(max(0, d_p - d_n + margin))`.
//! * [`batch_all_triplet_loss`] — online mining over a batch of labelled embeddings
//!   (class-balanced P x K batches): every valid triplet, averaged over the active ones.
//! * [`fault_triplet_loss`] — fault negatives: corrupted plans made from a class's drawings
//!   pushed farther from the class's anchors than its positives.
//! * [`contrastive_loss`] — the Siamese baseline's pair loss:
//!   `y * d + (1 - y) * max(0, margin - sqrt(d))^2` over all pairs of the batch.
//! * [`supcon_loss`] — the supervised contrastive loss (Khosla et al., 2020) on
//!   L2-normalised embeddings: every anchor's positives against all the other samples of
//!   the batch, a softmax over cosine similarities at a temperature.

use candle_core::{D, Device, Tensor};

/// Squared Euclidean distances between all rows of `e [B, E]` -> `[B, B]` (clamped at 0).
pub fn pairwise_sq_dist(e: &Tensor) -> candle_core::Result<Tensor> {
    let sq = e.sqr()?.sum_keepdim(1)?; // [B, 1]
    let gram = e.matmul(&e.t()?)?; // [B, B]
    let d = sq.broadcast_add(&sq.t()?)?.sub(&(gram * 2.0)?)?;
    d.relu()
}

/// The paper's triplet loss on explicit triplets `[B, E]` each.
pub fn triplet_loss(
    anchor: &Tensor,
    positive: &Tensor,
    negative: &Tensor,
    margin: f64,
) -> candle_core::Result<Tensor> {
    let dp = (anchor - positive)?.sqr()?.sum(D::Minus1)?;
    let dn = (anchor - negative)?.sqr()?.sum(D::Minus1)?;
    ((dp - dn)? + margin)?.relu()?.mean_all()
}

fn masks(
    labels: &[u32],
    device: &Device,
    dtype: candle_core::DType,
) -> candle_core::Result<(Tensor, Tensor)> {
    let b = labels.len();
    let mut pos = vec![0.0f32; b * b];
    let mut neg = vec![0.0f32; b * b];
    for i in 0..b {
        for j in 0..b {
            if i != j && labels[i] == labels[j] {
                pos[i * b + j] = 1.0;
            }
            if labels[i] != labels[j] {
                neg[i * b + j] = 1.0;
            }
        }
    }
    Ok((
        Tensor::from_vec(pos, (b, b), device)?.to_dtype(dtype)?,
        Tensor::from_vec(neg, (b, b), device)?.to_dtype(dtype)?,
    ))
}

/// Batch-all triplet loss: every valid (a, p, n) in the batch, averaged over the triplets
/// with a positive loss. Returns `(loss, fraction of valid triplets that are active)`.
pub fn batch_all_triplet_loss(
    e: &Tensor,
    labels: &[u32],
    margin: f64,
) -> candle_core::Result<(Tensor, f32)> {
    let d = pairwise_sq_dist(e)?;
    let (pos, neg) = masks(labels, e.device(), e.dtype())?;
    let (loss, active, valid) = mean_over_active_triplets(&d, &pos, &neg, margin)?;
    Ok((loss, active as f32 / valid.max(1) as f32))
}

/// `max(0, d[a, p] − d[a, n] + margin · neg[a, n])` over the valid triplets (`pos[a, p]`
/// and `neg[a, n]` not 0; a mask of ones gives every triplet `margin`), averaged over the
/// active ones (a positive loss). Returns `(loss, active triplets, valid triplets)`; the
/// loss is 0 without an active triplet.
///
/// The triplets are enumerated in plain Rust rather than as a `[B, B, B]` tensor (which
/// cost ~100 ms per step of 128 samples in candle's broadcast ops): with the set of active
/// triplets fixed, the loss is linear in `d`, `sum(d * W) + margin` with `W[a, x]` = (active
/// triplets with positive `x`) − (active triplets with negative `x`), over the active count.
/// So value and gradient equal those of the hinge form (a test holds them to it).
fn mean_over_active_triplets(
    d: &Tensor,
    pos: &Tensor,
    neg: &Tensor,
    margin: f64,
) -> candle_core::Result<(Tensor, usize, usize)> {
    let b = d.dim(0)?;
    let f32s = |t: &Tensor| -> candle_core::Result<Vec<f32>> {
        t.flatten_all()?
            .to_dtype(candle_core::DType::F32)?
            .to_vec1::<f32>()
    };
    let (dv, pv, nv) = (f32s(d)?, f32s(pos)?, f32s(neg)?);
    let m = margin as f32;
    let mut w = vec![0.0f64; b * b];
    let (mut active, mut valid) = (0usize, 0usize);
    // The margins of the active triplets, summed: the loss's constant term.
    let mut margins = 0.0f64;
    let mut negs = Vec::with_capacity(b);
    for a in 0..b {
        let row = a * b;
        negs.clear();
        negs.extend((0..b).filter(|&n| nv[row + n] != 0.0));
        for p in (0..b).filter(|&p| pv[row + p] != 0.0) {
            valid += negs.len();
            let dp = dv[row + p];
            let mut count = 0usize;
            for &n in &negs {
                let mn = m * nv[row + n];
                if dp - dv[row + n] + mn > 1e-12 {
                    count += 1;
                    margins += f64::from(mn);
                    w[row + n] -= 1.0;
                }
            }
            w[row + p] += count as f64;
            active += count;
        }
    }
    let scale = 1.0 / active.max(1) as f64;
    let w: Vec<f32> = w.iter().map(|v| (v * scale) as f32).collect();
    let w = Tensor::from_vec(w, (b, b), d.device())?.to_dtype(d.dtype())?;
    let loss = (d * w)?.sum_all()?;
    let loss = if active > 0 {
        (loss + margins * scale)?
    } else {
        loss
    };
    Ok((loss, active, valid))
}

/// Fault-negative triplet loss: every `(a, p, f)` where `a != p` are genuine samples of one
/// class `c` (`sources[a] == sources[p] == None`, `labels[a] == labels[p] == c`) and `f` is
/// a corrupted plan made from a drawing of class `c` (`sources[f] == Some(c)`):
/// `max(0, d(a, p) − d(a, f) + margins[f])`, averaged over the active triplets, so the
/// loss keeps pushing while only a few corrupted plans are still too close (`margins`: one
/// per item, read for corrupted plans only, each > 0). Returns `(loss, fraction of valid
/// triplets that are active, valid triplets)`; a batch without a valid triplet has loss 0.
pub fn fault_triplet_loss(
    e: &Tensor,
    labels: &[u32],
    sources: &[Option<u32>],
    margins: &[f64],
) -> candle_core::Result<(Tensor, f32, usize)> {
    let b = labels.len();
    if sources.len() != b || margins.len() != b {
        candle_core::bail!(
            "{} sources and {} margins for {b} labels",
            sources.len(),
            margins.len()
        );
    }
    for (s, &m) in sources.iter().zip(margins) {
        if s.is_some() && (m.is_nan() || m <= 0.0) {
            candle_core::bail!("a fault negative's margin must be > 0, not {m}");
        }
    }
    let mut pos = vec![0.0f32; b * b];
    let mut fneg = vec![0.0f32; b * b];
    for a in 0..b {
        if sources[a].is_some() {
            continue;
        }
        for j in 0..b {
            if j != a && sources[j].is_none() && labels[j] == labels[a] {
                pos[a * b + j] = 1.0;
            }
            if sources[j] == Some(labels[a]) {
                fneg[a * b + j] = margins[j] as f32;
            }
        }
    }
    let (dev, dt) = (e.device(), e.dtype());
    let pos = Tensor::from_vec(pos, (b, b), dev)?.to_dtype(dt)?;
    let fneg = Tensor::from_vec(fneg, (b, b), dev)?.to_dtype(dt)?;
    let d = pairwise_sq_dist(e)?;
    let (loss, active, n_valid) = mean_over_active_triplets(&d, &pos, &fneg, 1.0)?;
    Ok((loss, active as f32 / n_valid.max(1) as f32, n_valid))
}

/// Contrastive (Siamese) loss over all pairs of the batch: same-class pairs are pulled
/// together (`d`), different-class pairs pushed beyond `margin` in distance
/// (`max(0, margin - sqrt(d))^2`).
pub fn contrastive_loss(e: &Tensor, labels: &[u32], margin: f64) -> candle_core::Result<Tensor> {
    let d = pairwise_sq_dist(e)?;
    let (pos, neg) = masks(labels, e.device(), e.dtype())?;
    let dist = (d.clone() + 1e-9)?.sqrt()?;
    let push = (dist.affine(-1.0, margin)?).relu()?.sqr()?;
    let n_pos = pos.sum_all()?;
    let n_neg = neg.sum_all()?;
    // Balance the two terms: mean over positive pairs + mean over negative pairs.
    let pull = (&d * &pos)?.sum_all()?.broadcast_div(&(n_pos + 1.0)?)?;
    let push = (push * &neg)?.sum_all()?.broadcast_div(&(n_neg + 1.0)?)?;
    pull + push
}

/// Log-softmax of each row of `logits [N, C]`, stabilised by the (constant) row maximum.
fn log_softmax_rows(logits: &Tensor) -> candle_core::Result<Tensor> {
    let max = logits.max_keepdim(1)?.detach();
    let shifted = logits.broadcast_sub(&max)?;
    shifted.broadcast_sub(&shifted.exp()?.sum_keepdim(1)?.log()?)
}

/// Supervised contrastive loss (Khosla et al., 2020, `L_out`) on L2-normalised embeddings
/// `e [B, E]`: with `s = e eᵀ / temperature`, each anchor `i` that has a positive scores
/// `−mean over positives p of log(exp(s_ip) / Σ_{j≠i} exp(s_ij))`; the loss is the mean over
/// those anchors (0 without any). Returns `(loss, anchors with a positive)`.
pub fn supcon_loss(
    e: &Tensor,
    labels: &[u32],
    temperature: f64,
) -> candle_core::Result<(Tensor, usize)> {
    let b = labels.len();
    let s = (e.matmul(&e.t()?)? / temperature)?;
    // Self-similarity is left out of the softmax: a large negative on the diagonal.
    let mut diag = vec![0.0f32; b * b];
    for i in 0..b {
        diag[i * b + i] = -1e4;
    }
    let diag = Tensor::from_vec(diag, (b, b), e.device())?.to_dtype(e.dtype())?;
    let log_prob = log_softmax_rows(&(s + diag)?)?;
    // Weights: 1 / (|P(i)| · anchors) on each positive pair.
    let mut w = vec![0.0f32; b * b];
    let counts: Vec<usize> = (0..b)
        .map(|i| (0..b).filter(|&j| j != i && labels[j] == labels[i]).count())
        .collect();
    let anchors = counts.iter().filter(|&&c| c > 0).count();
    for i in 0..b {
        for j in 0..b {
            if j != i && labels[j] == labels[i] {
                w[i * b + j] = 1.0 / (counts[i] * anchors) as f32;
            }
        }
    }
    let w = Tensor::from_vec(w, (b, b), e.device())?.to_dtype(e.dtype())?;
    Ok(((log_prob * w)?.sum_all()?.neg()?, anchors))
}

/// Normalised softmax over proxies (Zhai & Wu, 2019, "Classification is a strong baseline
/// for deep metric learning"): one learned proxy per training class, `proxies [C, E]`; each
/// item of L2-normalised `e [B, E]` whose label is a class (`< C`; corrupted plans' labels
/// are not) scores `−log softmax_c(cos(e_i, w_c) / temperature)` at its own class, against
/// every class, not only those in the batch. The loss is the mean over those items (0
/// without any). Returns `(loss, items scored)`.
pub fn norm_softmax_loss(
    e: &Tensor,
    labels: &[u32],
    proxies: &Tensor,
    temperature: f64,
) -> candle_core::Result<(Tensor, usize)> {
    let (classes, _) = proxies.dims2()?;
    let rows: Vec<u32> = (0..labels.len() as u32)
        .filter(|&i| (labels[i as usize] as usize) < classes)
        .collect();
    let n = rows.len();
    if n == 0 {
        return Ok((Tensor::zeros((), e.dtype(), e.device())?, 0));
    }
    let e = e.index_select(&Tensor::from_vec(rows.clone(), n, e.device())?, 0)?;
    let norm = (proxies.sqr()?.sum_keepdim(1)? + 1e-12)?.sqrt()?;
    let w = proxies.broadcast_div(&norm)?;
    let log_prob = log_softmax_rows(&(e.matmul(&w.t()?)? / temperature)?)?;
    let target: Vec<u32> = rows.iter().map(|&i| labels[i as usize]).collect();
    let target = Tensor::from_vec(target, (n, 1), e.device())?;
    let picked = log_prob.gather(&target, 1)?;
    Ok(((picked.sum_all()? / n as f64)?.neg()?, n))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(rows: &[[f32; 2]]) -> Tensor {
        let v: Vec<f32> = rows.iter().flatten().copied().collect();
        Tensor::from_vec(v, (rows.len(), 2), &Device::Cpu).unwrap()
    }

    #[test]
    fn distances_and_losses_on_a_known_case() -> candle_core::Result<()> {
        let e = t(&[[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [0.0, 3.0]]);
        let d = pairwise_sq_dist(&e)?.to_vec2::<f32>()?;
        assert_eq!(d[0][1], 1.0);
        assert_eq!(d[0][3], 9.0);
        assert_eq!(d[2][3], 1.0);
        // Explicit triplet: d_p = 1, d_n = 4, margin 0.5 -> 0; margin 4 -> 1.
        let a = t(&[[0.0, 0.0]]);
        let p = t(&[[1.0, 0.0]]);
        let n = t(&[[0.0, 2.0]]);
        assert_eq!(triplet_loss(&a, &p, &n, 0.5)?.to_scalar::<f32>()?, 0.0);
        assert_eq!(triplet_loss(&a, &p, &n, 4.0)?.to_scalar::<f32>()?, 1.0);
        // Batch-all with labels [0, 0, 1, 1] and margin 3.5: active triplets (a,p,n) with
        // d_ap - d_an + 3.5 > 0: (0,1,2)=0.5 (1,0,2)=-0.5 (2,3,0)=0.5 ... average over active ones.
        let (l, _) = batch_all_triplet_loss(&e, &[0, 0, 1, 1], 3.5)?;
        assert!((l.to_scalar::<f32>()? - 0.5).abs() < 1e-6);
        // Contrastive: a perfectly separated batch has zero loss.
        let sep = t(&[[0.0, 0.0], [0.0, 0.0], [5.0, 0.0], [5.0, 0.0]]);
        let l = contrastive_loss(&sep, &[0, 0, 1, 1], 1.0)?.to_scalar::<f32>()?;
        assert!(l.abs() < 1e-3, "{l}");
        Ok(())
    }

    /// Normalised softmax: the proxy's length does not matter, an item at its own proxy
    /// scores less than one at another's, corrupted plans are not scored, and the gradient
    /// reaches the proxies.
    #[test]
    fn norm_softmax_scores_items_against_every_proxy() -> candle_core::Result<()> {
        let e = t(&[[1.0, 0.0], [0.0, 1.0], [0.6, 0.8]]);
        let p = t(&[[2.0, 0.0], [0.0, 0.5], [-1.0, 0.0]]);
        let (at_own, n) = norm_softmax_loss(&e, &[0, 1, u32::MAX], &p, 0.1)?;
        assert_eq!(n, 2);
        let (swapped, _) = norm_softmax_loss(&e, &[1, 0, u32::MAX], &p, 0.1)?;
        let (a, b) = (at_own.to_scalar::<f32>()?, swapped.to_scalar::<f32>()?);
        assert!(a < 1e-3 && b > 5.0, "{a} {b}");
        // By hand for item 0 at class 0: cosines 1, 0, −1 at T 0.1.
        let (l, _) = norm_softmax_loss(&e.narrow(0, 0, 1)?, &[0], &p, 0.1)?;
        let want = -(10f64.exp() / (10f64.exp() + 1.0 + (-10f64).exp())).ln();
        assert!((f64::from(l.to_scalar::<f32>()?) - want).abs() < 1e-5);
        let (none, n) = norm_softmax_loss(&e, &[u32::MAX; 3], &p, 0.1)?;
        assert_eq!((none.to_scalar::<f32>()?, n), (0.0, 0));
        let v = candle_core::Var::from_tensor(&p)?;
        let (l, _) = norm_softmax_loss(&e, &[1, 1, 1], v.as_tensor(), 0.1)?;
        let g = l
            .backward()?
            .get(v.as_tensor())
            .expect("a gradient")
            .to_vec2::<f32>()?;
        assert!(g.iter().flatten().any(|x| x.abs() > 1e-3), "{g:?}");
        Ok(())
    }

    /// The hinge form the loss had as `[B, B, B]` tensors: the reference.
    fn hinge_reference(
        d: &Tensor,
        pos: &Tensor,
        neg: &Tensor,
        margin: f64,
    ) -> candle_core::Result<Tensor> {
        let t = (d.unsqueeze(2)?.broadcast_sub(&d.unsqueeze(1)?)? + margin)?.relu()?;
        let valid = pos.unsqueeze(2)?.broadcast_mul(&neg.unsqueeze(1)?)?;
        let t = (t * &valid)?;
        let active = t
            .flatten_all()?
            .to_vec1::<f64>()?
            .iter()
            .filter(|&&v| v > 1e-12)
            .count();
        t.sum_all()? / (active.max(1) as f64)
    }

    /// Value and gradient (with respect to the embeddings) of the enumerated loss equal the
    /// hinge form on random batches, in f64.
    #[test]
    fn active_triplet_mean_matches_the_hinge_form() -> candle_core::Result<()> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        for (b, margin) in [(12, 0.2), (24, 0.5), (9, 3.0)] {
            let labels: Vec<u32> = (0..b).map(|i| (i % 4) as u32).collect();
            let v: Vec<f64> = (0..b * 6).map(|_| rng.random_range(-1.0..1.0)).collect();
            let e = candle_core::Var::from_vec(v, (b, 6), &Device::Cpu)?;
            let d = pairwise_sq_dist(e.as_tensor())?;
            let (pos, neg) = masks(&labels, &Device::Cpu, candle_core::DType::F64)?;
            let (got, active, valid) = mean_over_active_triplets(&d, &pos, &neg, margin)?;
            let want = hinge_reference(&d, &pos, &neg, margin)?;
            assert!(active > 0 && valid >= active);
            let (gv, wv) = (got.to_scalar::<f64>()?, want.to_scalar::<f64>()?);
            assert!((gv - wv).abs() < 1e-6 * (1.0 + wv.abs()), "{gv} vs {wv}");
            let gg = got
                .backward()?
                .get(e.as_tensor())
                .expect("grad")
                .flatten_all()?;
            let wg = want
                .backward()?
                .get(e.as_tensor())
                .expect("grad")
                .flatten_all()?;
            let diff = (&gg - &wg)?.abs()?.max(0)?.to_scalar::<f64>()?;
            assert!(diff < 1e-6, "gradient differs by {diff}");
        }
        Ok(())
    }

    #[test]
    fn fault_triplet_loss_on_a_known_case() -> candle_core::Result<()> {
        // Class 0: samples 0 and 1 (d 1); sample 2 a corrupted plan of class 0 at d 4 from
        // sample 0 and 5 from sample 1; sample 3 of class 1; sample 4 a corrupted plan of
        // class 1 (no class-1 pair: no triplet).
        let e = t(&[[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [0.0, 3.0], [3.0, 3.0]]);
        let labels = [0, 0, 7, 1, 8];
        let sources = [None, None, Some(0), None, Some(1)];
        // Triplets (0,1,2): 1 - 4 + m; (1,0,2): 1 - 5 + m. m = 3.5 -> 0.5 and 0 -> mean
        // over active = 0.5; m = 5 -> 2 and 1 -> 1.5.
        let (l, active, n) = fault_triplet_loss(&e, &labels, &sources, &[3.5; 5])?;
        assert_eq!(n, 2);
        assert_eq!(active, 0.5);
        assert!((l.to_scalar::<f32>()? - 0.5).abs() < 1e-6);
        let (l, active, _) = fault_triplet_loss(&e, &labels, &sources, &[5.0; 5])?;
        assert_eq!(active, 1.0);
        assert!((l.to_scalar::<f32>()? - 1.5).abs() < 1e-6);
        // A margin per corrupted plan: only sample 2's counts here (genuine ones are not
        // read, sample 4 has no triplet), so 3.5 on it is the first case again.
        let (l, active, _) = fault_triplet_loss(&e, &labels, &sources, &[9.0, 9.0, 3.5, 9.0, 0.1])?;
        assert_eq!(active, 0.5);
        assert!((l.to_scalar::<f32>()? - 0.5).abs() < 1e-6);
        // Far enough: 0. No corrupted plans: no valid triplet, loss 0.
        let (l, _, _) = fault_triplet_loss(&e, &labels, &sources, &[0.5; 5])?;
        assert_eq!(l.to_scalar::<f32>()?, 0.0);
        let (l, _, n) = fault_triplet_loss(&e, &labels, &[None; 5], &[3.5; 5])?;
        assert_eq!((l.to_scalar::<f32>()?, n), (0.0, 0));
        assert!(fault_triplet_loss(&e, &labels, &[None; 4], &[3.5; 5]).is_err());
        assert!(fault_triplet_loss(&e, &labels, &sources, &[3.5; 4]).is_err());
        assert!(fault_triplet_loss(&e, &labels, &sources, &[3.5, 3.5, 0.0, 3.5, 3.5]).is_err());
        Ok(())
    }

    #[test]
    fn supcon_matches_its_definition_on_a_known_case() -> candle_core::Result<()> {
        // Unit vectors: classes 0, 0, 1 and a singleton class 2 (no positive: not an anchor).
        let (c, d) = (0.6f32, 0.8f32);
        let e = t(&[[1.0, 0.0], [c, d], [0.0, 1.0], [-1.0, 0.0]]);
        let labels = [0u32, 0, 1, 1];
        let tau = 0.5;
        let (l, anchors) = supcon_loss(&e, &labels, tau)?;
        assert_eq!(anchors, 4);
        let rows = [[1.0f64, 0.0], [0.6, 0.8], [0.0, 1.0], [-1.0, 0.0]];
        let dot = |i: usize, j: usize| rows[i][0] * rows[j][0] + rows[i][1] * rows[j][1];
        let mut want = 0.0;
        for i in 0..4 {
            let den: f64 = (0..4)
                .filter(|&j| j != i)
                .map(|j| (dot(i, j) / tau).exp())
                .sum();
            let p = (0..4).find(|&j| j != i && labels[j] == labels[i]).unwrap();
            want += -((dot(i, p) / tau).exp() / den).ln() / 4.0;
        }
        let got = f64::from(l.to_scalar::<f32>()?);
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
        // A singleton class is no anchor; a batch without positives has loss 0.
        let (_, anchors) = supcon_loss(&e, &[0, 0, 1, 2], tau)?;
        assert_eq!(anchors, 2);
        let (l, anchors) = supcon_loss(&e, &[0, 1, 2, 3], tau)?;
        assert_eq!((anchors, l.to_scalar::<f32>()?), (0, 0.0));
        // Pulling a positive closer lowers the loss.
        let closer = t(&[[1.0, 0.0], [0.8, c], [0.0, 1.0], [-1.0, 0.0]]);
        let (l2, _) = supcon_loss(&closer, &labels, tau)?;
        assert!(l2.to_scalar::<f32>()? < got as f32);
        Ok(())
    }
}
