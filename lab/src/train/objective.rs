//! The training objective: the main loss of a batch of embeddings (batch-all triplets, the
//! paper's random triplets, the Siamese baseline's contrastive pairs, or supervised
//! contrastive, or a normalised softmax over class proxies) plus the weighted fault-negative
//! term, and the validation-comparable loss.

use candle_core::{Device, Tensor};
use guardian_models::loss;
use rand::rngs::StdRng;
use rand::seq::IndexedRandom;

use crate::train::config::{LossKind, TrainConfig};

/// The training objective of one batch of embeddings `e [B, embed_dim]` of items: the main
/// loss of `cfg`, plus the fault-negative term (weighted) when the batch has corrupted
/// plans. Returns `(loss to optimise, validation-comparable loss, active fraction, mined
/// triplets)`; the validation-comparable loss takes batch-all's mean over all valid
/// triplets rather than over the active ones (which stays flat as fewer triplets stay
/// active), for both terms. `proxies [classes, embed_dim]` are the class proxies of
/// [`LossKind::NormSoftmax`] (ignored by the other losses). `fault_margins` are the
/// fault-negative margins of the items ([`TrainConfig::fault_margin_of`] their kinds;
/// `None`: `cfg.fault_margin` for every one).
pub fn objective(
    e: &Tensor,
    labels: &[u32],
    sources: &[Option<u32>],
    fault_margins: Option<&[f64]>,
    proxies: Option<&Tensor>,
    cfg: &TrainConfig,
    rng: &mut StdRng,
) -> candle_core::Result<(Tensor, f64, f32, usize)> {
    let (l, active, n) = batch_loss(e, labels, cfg.loss, cfg.margin, proxies, rng)?;
    let lv = f64::from(l.to_scalar::<f32>()?);
    let mut comparable = if cfg.loss == LossKind::BatchAll {
        lv * f64::from(active)
    } else {
        lv
    };
    let mut total = l;
    if cfg.fault_weight > 0.0 && sources.iter().any(Option::is_some) {
        let uniform = vec![cfg.fault_margin; labels.len()];
        let margins = fault_margins.unwrap_or(&uniform);
        let (lf, af, _) = loss::fault_triplet_loss(e, labels, sources, margins)?;
        comparable += cfg.fault_weight * f64::from(lf.to_scalar::<f32>()?) * f64::from(af);
        total = (total + (lf * cfg.fault_weight)?)?;
    }
    Ok((total, comparable, active, n))
}

/// The loss of one batch of embeddings `e [B, embed_dim]` (`proxies`: see [`objective`]).
/// Returns `(loss, active fraction, mined triplets)`.
pub fn batch_loss(
    e: &Tensor,
    labels: &[u32],
    kind: LossKind,
    margin: f64,
    proxies: Option<&Tensor>,
    rng: &mut StdRng,
) -> candle_core::Result<(Tensor, f32, usize)> {
    match kind {
        LossKind::BatchAll => {
            let (l, a) = loss::batch_all_triplet_loss(e, labels, margin)?;
            let n = labels.len();
            let mut valid = 0;
            for i in 0..n {
                let pos = labels
                    .iter()
                    .enumerate()
                    .filter(|&(j, &l)| j != i && l == labels[i])
                    .count();
                valid += pos * labels.iter().filter(|&&l| l != labels[i]).count();
            }
            Ok((l, a, valid))
        }
        LossKind::Triplet => {
            // One random (positive, negative) per anchor.
            let n = labels.len();
            let (mut ai, mut pi, mut ni) = (Vec::new(), Vec::new(), Vec::new());
            for a in 0..n {
                let pos: Vec<u32> = (0..n as u32)
                    .filter(|&j| j as usize != a && labels[j as usize] == labels[a])
                    .collect();
                let neg: Vec<u32> = (0..n as u32)
                    .filter(|&j| labels[j as usize] != labels[a])
                    .collect();
                if let (Some(&p), Some(&q)) = (pos.choose(rng), neg.choose(rng)) {
                    ai.push(a as u32);
                    pi.push(p);
                    ni.push(q);
                }
            }
            let m = ai.len();
            let sel = |v: Vec<u32>| -> candle_core::Result<Tensor> {
                e.index_select(&Tensor::from_vec(v, m, &Device::Cpu)?, 0)
            };
            let (a, p, q) = (sel(ai)?, sel(pi)?, sel(ni)?);
            let l = loss::triplet_loss(&a, &p, &q, margin)?;
            let dp = (&a - &p)?.sqr()?.sum(1)?;
            let dn = (&a - &q)?.sqr()?.sum(1)?;
            let act = ((dp - dn)? + margin)?.relu()?.to_vec1::<f32>()?;
            let frac = act.iter().filter(|&&v| v > 0.0).count() as f32 / m.max(1) as f32;
            Ok((l, frac, m))
        }
        LossKind::Contrastive => {
            let l = loss::contrastive_loss(e, labels, margin)?;
            let n = labels.len();
            Ok((l, 1.0, n * (n - 1) / 2))
        }
        LossKind::Supcon => {
            let (l, anchors) = loss::supcon_loss(e, labels, margin)?;
            Ok((l, anchors as f32 / labels.len().max(1) as f32, anchors))
        }
        LossKind::NormSoftmax => {
            let proxies = proxies.ok_or_else(|| {
                candle_core::Error::Msg("norm-softmax needs the class proxies".into())
            })?;
            let (l, scored) = loss::norm_softmax_loss(e, labels, proxies, margin)?;
            Ok((l, scored as f32 / labels.len().max(1) as f32, scored))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::config::tests::small_config;
    use rand::SeedableRng;

    fn t(rows: &[[f32; 2]]) -> Tensor {
        let v: Vec<f32> = rows.iter().flatten().copied().collect();
        Tensor::from_vec(v, (rows.len(), 2), &Device::Cpu).unwrap()
    }

    /// Two classes on a line and a corrupted plan of class 0 between them.
    fn batch() -> (Tensor, Vec<u32>, Vec<Option<u32>>) {
        let e = t(&[[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [1.1, 0.0], [0.2, 0.0]]);
        (
            e,
            vec![0, 0, 1, 1, u32::MAX],
            vec![None, None, None, None, Some(0)],
        )
    }

    #[test]
    fn batch_all_counts_valid_triplets_and_compares_over_all_of_them() {
        let (e, labels, _) = batch();
        let e = e.narrow(0, 0, 4).unwrap();
        let mut cfg = small_config();
        cfg.loss = LossKind::BatchAll;
        cfg.fault_weight = 0.0;
        // Margin 1: the nearer negatives are inside it, the farther ones outside.
        cfg.margin = 1.0;
        let mut rng = StdRng::seed_from_u64(0);
        let (l, comparable, active, n) =
            objective(&e, &labels[..4], &[None; 4], None, None, &cfg, &mut rng).unwrap();
        // Each of 4 anchors has 1 positive and 2 negatives.
        assert_eq!(n, 8);
        let lv = f64::from(l.to_scalar::<f32>().unwrap());
        assert!((comparable - lv * f64::from(active)).abs() < 1e-9);
        assert!(active > 0.0 && active < 1.0, "{active}");
        assert!(
            comparable < lv,
            "the mean over all valid triplets is below the active mean"
        );
    }

    #[test]
    fn the_fault_term_is_added_only_for_a_batch_with_corrupted_plans() {
        let (e, labels, sources) = batch();
        let mut cfg = small_config();
        cfg.fault_margin = 0.4;
        let mut rng = StdRng::seed_from_u64(0);
        cfg.fault_weight = 0.0;
        let (without, ..) = objective(&e, &labels, &sources, None, None, &cfg, &mut rng).unwrap();
        cfg.fault_weight = 2.0;
        let (with, ..) = objective(&e, &labels, &sources, None, None, &cfg, &mut rng).unwrap();
        let (lf, _, _) = loss::fault_triplet_loss(&e, &labels, &sources, &[0.4; 5]).unwrap();
        let (a, b, f) = (
            without.to_scalar::<f32>().unwrap(),
            with.to_scalar::<f32>().unwrap(),
            lf.to_scalar::<f32>().unwrap(),
        );
        assert!(f > 0.0, "the corrupted plan sits inside the margin");
        assert!((b - (a + 2.0 * f)).abs() < 1e-5, "{b} vs {a} + 2 x {f}");
        // No corrupted plan in the batch: the weight changes nothing.
        let (plain, ..) = objective(&e, &labels, &[None; 5], None, None, &cfg, &mut rng).unwrap();
        assert_eq!(plain.to_scalar::<f32>().unwrap(), a);
        // Margins per item: the fault term of those margins.
        let margins = [0.4, 0.4, 3.0, 0.4, 3.0];
        let (wide, ..) =
            objective(&e, &labels, &sources, Some(&margins), None, &cfg, &mut rng).unwrap();
        let (lf, _, _) = loss::fault_triplet_loss(&e, &labels, &sources, &margins).unwrap();
        let (w, f) = (
            wide.to_scalar::<f32>().unwrap(),
            lf.to_scalar::<f32>().unwrap(),
        );
        assert!((w - (a + 2.0 * f)).abs() < 1e-5, "{w} vs {a} + 2 x {f}");
        assert!(w > b, "a wider margin pushes harder: {w} vs {b}");
    }

    #[test]
    fn random_triplets_take_one_per_anchor_and_contrastive_every_pair() {
        let (e5, labels, _) = batch();
        let e = e5.narrow(0, 0, 4).unwrap();
        let mut rng = StdRng::seed_from_u64(2);
        let (_, frac, n) =
            batch_loss(&e, &labels[..4], LossKind::Triplet, 0.2, None, &mut rng).unwrap();
        assert_eq!(n, 4);
        assert!((0.0..=1.0).contains(&frac));
        // A margin no triplet can meet makes every one active.
        let (_, frac, _) =
            batch_loss(&e, &labels[..4], LossKind::Triplet, 10.0, None, &mut rng).unwrap();
        assert_eq!(frac, 1.0);
        let (_, _, n) =
            batch_loss(&e5, &labels, LossKind::Contrastive, 1.0, None, &mut rng).unwrap();
        assert_eq!(n, 10);
    }
}
