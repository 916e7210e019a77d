//! The lab's detection metrics, in one place: AUROC, the ROC curve, the true-positive rate
//! at a false-positive rate (outliers, report) and the pair AUC of distances (report).

use guardian_bank as bank;

/// Area under the ROC curve of `pos` (faulty) vs `neg` (genuine) scores, higher = faulty;
/// ties count one half. `NaN` if either set is empty.
pub fn auroc(neg: &[f32], pos: &[f32]) -> f64 {
    if neg.is_empty() || pos.is_empty() {
        return f64::NAN;
    }
    let mut all: Vec<(f32, bool)> = neg
        .iter()
        .map(|&v| (v, false))
        .chain(pos.iter().map(|&v| (v, true)))
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Rank sum of the positives with mid-ranks for ties.
    let mut rank_sum = 0.0f64;
    let mut i = 0;
    while i < all.len() {
        let mut j = i;
        while j + 1 < all.len() && all[j + 1].0 == all[i].0 {
            j += 1;
        }
        let mid = (i + j) as f64 / 2.0 + 1.0;
        rank_sum += mid * all[i..=j].iter().filter(|x| x.1).count() as f64;
        i = j + 1;
    }
    let (np, nn) = (pos.len() as f64, neg.len() as f64);
    (rank_sum - np * (np + 1.0) / 2.0) / (np * nn)
}

/// True-positive rate at false-positive rate `fpr`: the threshold lets at most
/// `floor(fpr * |neg|)` genuine scores exceed it.
pub fn tpr_at_fpr(neg: &[f32], pos: &[f32], fpr: f64) -> f64 {
    let allowed = (fpr * neg.len() as f64).floor() as usize;
    let Some(t) = bank::threshold_allowing(neg, allowed) else {
        return f64::NAN;
    };
    share_above(pos, t)
}

/// Share of `v` strictly above `t` (`NaN` if empty).
pub fn share_above(v: &[f32], t: f32) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.iter().filter(|&&x| x > t).count() as f64 / v.len() as f64
}

/// ROC curve points (FPR, TPR) at every distinct score, from (0, 0) to (1, 1).
pub fn roc_curve(neg: &[f32], pos: &[f32]) -> Vec<(f64, f64)> {
    let mut t: Vec<f32> = neg.iter().chain(pos).copied().collect();
    t.sort_by(|a, b| b.total_cmp(a));
    t.dedup();
    let mut out = vec![(0.0, 0.0)];
    for th in t {
        out.push((share_above_eq(neg, th), share_above_eq(pos, th)));
    }
    out.push((1.0, 1.0));
    out
}

fn share_above_eq(v: &[f32], t: f32) -> f64 {
    v.iter().filter(|&&x| x >= t).count() as f64 / v.len().max(1) as f64
}

/// Fraction of (same, different) pairs ordered correctly (the AUC of the distance as a
/// same-class detector).
pub fn pair_auc(intra: &[f64], inter: &[f64]) -> f64 {
    let mut s = inter.to_vec();
    s.sort_by(f64::total_cmp);
    let mut good = 0.0;
    for &a in intra {
        good += (s.len() - s.partition_point(|&b| b <= a)) as f64;
    }
    good / (intra.len() * s.len()).max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    #[test]
    fn auroc_of_perfect_random_and_inverted_scorers() {
        let neg: Vec<f32> = (0..500).map(|i| i as f32 / 1000.0).collect();
        let pos: Vec<f32> = (0..500).map(|i| 1.0 + i as f32 / 1000.0).collect();
        assert_eq!(auroc(&neg, &pos), 1.0);
        assert_eq!(auroc(&pos, &neg), 0.0);
        assert_eq!(tpr_at_fpr(&neg, &pos, 0.01), 1.0);
        let mut r = StdRng::seed_from_u64(5);
        let a: Vec<f32> = (0..20_000).map(|_| r.random()).collect();
        let b: Vec<f32> = (0..20_000).map(|_| r.random()).collect();
        let x = auroc(&a, &b);
        assert!((x - 0.5).abs() < 0.01, "{x}");
        // All tied: exactly one half.
        assert_eq!(auroc(&[1.0; 10], &[1.0; 7]), 0.5);
        let roc = roc_curve(&neg, &pos);
        assert_eq!(roc.first(), Some(&(0.0, 0.0)));
        assert_eq!(roc.last(), Some(&(1.0, 1.0)));
    }
}
