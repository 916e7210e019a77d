//! The learning-rate schedule: ReduceLROnPlateau with early stopping on the validation
//! loss (the best model kept), or a fixed one-cycle schedule (the last model kept).

use crate::train::checkpoint::State;
use crate::train::config::{Schedule, TrainConfig};

/// The one-cycle rate at `step` of `total` for a peak rate `peak` (PyTorch's `OneCycleLR`
/// with `pct_start = 0.05`, `div_factor = 25`, `final_div_factor = 10⁴`, cosine annealing).
pub fn one_cycle_lr(peak: f64, step: usize, total: usize) -> f64 {
    let total = total.max(2) as f64;
    let warm = (0.05 * total).max(1.0);
    let (start, end) = (peak / 25.0, peak / 25.0 / 1e4);
    let s = step as f64;
    let cos = |from: f64, to: f64, frac: f64| {
        to + (from - to) * 0.5 * (1.0 + (std::f64::consts::PI * frac.clamp(0.0, 1.0)).cos())
    };
    if s <= warm {
        cos(start, peak, s / warm)
    } else {
        cos(peak, end, (s - warm) / (total - 1.0 - warm).max(1.0))
    }
}

/// What the schedule decided at the end of an epoch (after [`end_epoch`] updated the state).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EpochEnd {
    /// This epoch's model is the one to keep (`model.safetensors`).
    pub keep: bool,
    /// Training stops here (early stopping).
    pub stop: bool,
}

/// Apply the schedule to `state` at the end of an epoch whose validation loss was
/// `val_loss`: the best loss and the epochs since it, the plateau's learning-rate cut, and
/// early stopping. A NaN validation loss never counts as an improvement.
pub fn end_epoch(cfg: &TrainConfig, state: &mut State, val_loss: f64) -> EpochEnd {
    let keep = if cfg.schedule == Schedule::OneCycle {
        // A fixed schedule keeps its last model; validation is only logged.
        state.best_val_loss = state.best_val_loss.min(val_loss);
        true
    } else if val_loss < state.best_val_loss {
        state.best_val_loss = val_loss;
        state.epochs_since_best = 0;
        true
    } else {
        state.epochs_since_best += 1;
        false
    };
    state.epochs_since_lr_change += 1;
    if cfg.schedule == Schedule::Plateau
        && state.epochs_since_best > 0
        && state.epochs_since_lr_change > cfg.plateau_patience
        && state.epochs_since_best > cfg.plateau_patience
    {
        state.lr = (state.lr * cfg.lr_factor).max(cfg.min_lr);
        state.epochs_since_lr_change = 0;
    }
    let stop =
        cfg.schedule == Schedule::Plateau && state.epochs_since_best >= cfg.early_stop_patience;
    EpochEnd { keep, stop }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::config::tests::small_config;

    #[test]
    fn one_cycle_warms_up_to_the_peak_then_anneals_to_a_tiny_rate() {
        let (peak, total) = (2e-3, 1000);
        let lr: Vec<f64> = (0..total).map(|s| one_cycle_lr(peak, s, total)).collect();
        assert!((lr[0] - peak / 25.0).abs() < 1e-12, "starts at peak / 25");
        // The peak is reached at the end of the 5 % warm-up.
        let top = lr.iter().cloned().fold(0.0, f64::max);
        assert!((top - peak).abs() < 1e-12);
        assert!((lr[50] - peak).abs() < 1e-12);
        assert!(lr[..=50].windows(2).all(|w| w[1] >= w[0]), "warm-up rises");
        assert!(lr[50..].windows(2).all(|w| w[1] <= w[0]), "annealing falls");
        assert!(
            (lr[total - 1] - peak / 25.0 / 1e4).abs() < 1e-12,
            "ends at the floor"
        );
    }

    fn fresh(cfg: &TrainConfig) -> State {
        State::new(cfg.lr)
    }

    #[test]
    fn the_plateau_cuts_the_rate_after_its_patience_and_stops_early() {
        let mut cfg = small_config();
        cfg.plateau_patience = 2;
        cfg.early_stop_patience = 5;
        let mut state = fresh(&cfg);
        assert_eq!(
            end_epoch(&cfg, &mut state, 1.0),
            EpochEnd {
                keep: true,
                stop: false
            }
        );
        let mut cuts = Vec::new();
        let mut stopped_at = None;
        for epoch in 2..=10 {
            let lr = state.lr;
            let end = end_epoch(&cfg, &mut state, 1.5);
            assert!(!end.keep, "a worse loss is not kept");
            if state.lr < lr {
                cuts.push(epoch);
            }
            if end.stop {
                stopped_at = Some(epoch);
                break;
            }
        }
        // Three epochs without improvement, more than the patience of 2: the first cut.
        assert_eq!(cuts, [4]);
        assert_eq!(state.lr, cfg.lr * cfg.lr_factor);
        assert_eq!(stopped_at, Some(6), "5 epochs without improvement");
        assert_eq!(state.best_val_loss, 1.0);
    }

    #[test]
    fn a_nan_validation_loss_is_no_improvement_and_one_cycle_keeps_every_model() {
        let mut cfg = small_config();
        let mut state = fresh(&cfg);
        let end = end_epoch(&cfg, &mut state, f64::NAN);
        assert!(!end.keep);
        assert_eq!(state.epochs_since_best, 1);
        assert_eq!(state.best_val_loss, f64::INFINITY);
        cfg.schedule = Schedule::OneCycle;
        let mut state = fresh(&cfg);
        for loss in [2.0, f64::NAN, 3.0, 1.0] {
            let end = end_epoch(&cfg, &mut state, loss);
            assert!(end.keep && !end.stop);
        }
        assert_eq!(state.best_val_loss, 1.0);
        assert_eq!(
            state.lr, cfg.lr,
            "one-cycle rates are set per step, not here"
        );
    }
}
