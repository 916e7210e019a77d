//! One check of a plan, the same wherever it runs (the daemon, the lab, the benches):
//! workcell inspection (validation, resampling, workcell rules) → embedding, with the pen
//! path computed once → plan geometry from that path → the bank's decision.
//!
//! A check has two stages so that a micro-batch can share one forward pass while each plan
//! is still decided against the bank as it stands when its turn comes: [`prepare`] (or
//! [`prepare_batch`]) runs everything that depends only on the plan, [`decide`] everything
//! that depends on the bank. [`check`] is both for one plan. Plans that are resampled
//! already (the lab's data sets) enter at the embedding stage ([`embed_resampled`]); their
//! plan geometry comes from the same pen path ([`Embedded::geometry`]).

use guardian_shared::trajectory::{InvalidTrajectory, Resampled, STEPS, Waypoint};
use guardian_shared::workcell::{Workcell, WorkcellViolation};

use crate::bank::{ClassBank, Decision};
use crate::embedder::{EmbedError, Embedder, Embedding};
use crate::features::PenPoint;
use crate::geometry::PlanGeometry;
use crate::workcell::{self, Inspection};

/// A plan after the stages that do not depend on the bank.
#[derive(Debug, Clone)]
pub enum Prepared {
    /// The trajectory failed validation.
    Invalid(InvalidTrajectory),
    /// The plan breaks a workcell rule (decided before any model runs).
    Workcell(WorkcellViolation),
    /// The plan's embedding and the pen path its features came from.
    Embedded(Box<Embedded>),
}

/// A plan's embedding and the pen path its features came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Embedded {
    /// The embedding.
    pub embedding: Embedding,
    /// The pen path of the resampled plan.
    pub path: [PenPoint; STEPS],
}

impl Embedded {
    /// The plan geometry of the pen path (`None` if the pen never touches the canvas).
    pub fn geometry(&self) -> Option<PlanGeometry> {
        workcell::plan_geometry_of_path(&self.path)
    }
}

/// The outcome of one check.
#[derive(Debug, Clone, PartialEq)]
pub enum PlanCheck {
    /// The trajectory failed validation.
    Invalid(InvalidTrajectory),
    /// The plan breaks a workcell rule.
    Workcell(WorkcellViolation),
    /// The bank's decision (embedding and, where it applies, geometry).
    Decided(Decision),
}

/// Inspect `waypoints` of the embedder's robot against `cell`: the early outcome, or the
/// inspection to embed.
fn inspect(
    embedder: &Embedder,
    cell: &Workcell,
    waypoints: &[Waypoint],
) -> Result<Inspection, Prepared> {
    let inspection =
        workcell::inspect_with(embedder.robot(), cell, waypoints).map_err(Prepared::Invalid)?;
    match inspection.violation {
        Some(v) => Err(Prepared::Workcell(v)),
        None => Ok(inspection),
    }
}

/// Inspect and embed one plan. An embedding failure is an error, never a verdict.
pub fn prepare(
    embedder: &Embedder,
    cell: &Workcell,
    waypoints: &[Waypoint],
) -> Result<Prepared, EmbedError> {
    let inspection = match inspect(embedder, cell, waypoints) {
        Ok(i) => i,
        Err(early) => return Ok(early),
    };
    let (embedding, path) = embedder.embed_with_pen_path(&inspection.resampled)?;
    Ok(Prepared::Embedded(Box::new(Embedded { embedding, path })))
}

/// The embedding stage alone, for plans that are already resampled (the lab's data sets hold
/// resampled plans, so there is nothing to inspect first): `xs` in one forward pass, each
/// with the pen path its features came from.
pub fn embed_resampled(embedder: &Embedder, xs: &[Resampled]) -> Result<Vec<Embedded>, EmbedError> {
    let mut paths = vec![[[0.0f32; 3]; STEPS]; xs.len()];
    let embeddings = embedder.embed_batch_with_pen_paths(xs, &mut paths)?;
    Ok(embeddings
        .into_iter()
        .zip(paths)
        .map(|(embedding, path)| Embedded { embedding, path })
        .collect())
}

/// [`prepare`] for several plans, embedding the ones that pass inspection in one forward
/// pass. If that pass fails, each plan is embedded alone, so an error belongs to the plan
/// that caused it.
pub fn prepare_batch(
    embedder: &Embedder,
    cell: &Workcell,
    plans: &[&[Waypoint]],
) -> Vec<Result<Prepared, EmbedError>> {
    let inspected: Vec<Result<Inspection, Prepared>> =
        plans.iter().map(|w| inspect(embedder, cell, w)).collect();
    let xs: Vec<_> = inspected
        .iter()
        .filter_map(|i| i.as_ref().ok().map(|i| i.resampled))
        .collect();
    let batch = if xs.len() >= 2 {
        embed_resampled(embedder, &xs).ok()
    } else {
        None
    };
    let mut embedded = batch.map(Vec::into_iter);
    inspected
        .into_iter()
        .zip(plans)
        .map(|(i, w)| match i {
            Err(early) => Ok(early),
            Ok(_) => match embedded.as_mut().and_then(Iterator::next) {
                Some(e) => Ok(Prepared::Embedded(Box::new(e))),
                None => prepare(embedder, cell, w),
            },
        })
        .collect()
}

/// Decide a prepared plan claiming class `claimed` against `bank`, with the `k` nearest
/// classes. The plan geometry is computed from the pen path only when the bank can use it.
pub fn decide(bank: &ClassBank, prepared: &Prepared, claimed: &str, k: usize) -> PlanCheck {
    match prepared {
        Prepared::Invalid(inv) => PlanCheck::Invalid(*inv),
        Prepared::Workcell(v) => PlanCheck::Workcell(*v),
        Prepared::Embedded(e) => {
            let geometry = bank.geometry_calibration().and_then(|_| e.geometry());
            PlanCheck::Decided(bank.decide_with_geometry(
                &e.embedding,
                geometry.as_ref(),
                claimed,
                k,
            ))
        }
    }
}

/// Check one plan: [`prepare`], then [`decide`].
pub fn check(
    embedder: &Embedder,
    bank: &ClassBank,
    cell: &Workcell,
    waypoints: &[Waypoint],
    claimed: &str,
    k: usize,
) -> Result<PlanCheck, EmbedError> {
    Ok(decide(
        bank,
        &prepare(embedder, cell, waypoints)?,
        claimed,
        k,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A batch prepares every plan as one-by-one preparation does (embeddings within float
    /// tolerance, pen paths identical), early outcomes included.
    #[test]
    fn a_batch_prepares_like_single_plans() {
        let embedder = Embedder::random(5);
        let home = guardian_shared::trajectory::waypoint(
            &[0.0f32, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785],
            0.0,
        );
        let a: Vec<Waypoint> = (0..40)
            .map(|i| {
                let mut w = home;
                w[0] += i as f32 * 0.002;
                w
            })
            .collect();
        let b: Vec<Waypoint> = a
            .iter()
            .map(|w| {
                let mut w = *w;
                w[1] += 0.01;
                w
            })
            .collect();
        let mut bad = a.clone();
        bad[3][0] = f32::NAN;
        // Joint-space sweeps, not drawings on the canvas: the rules are off.
        let off = Workcell {
            enabled: false,
            ..Workcell::default()
        };
        let plans: Vec<&[Waypoint]> = vec![&a, &bad, &b];
        let batch = prepare_batch(&embedder, &off, &plans);
        for (p, got) in plans.iter().zip(batch) {
            let want = prepare(&embedder, &off, p).unwrap();
            match (got.unwrap(), want) {
                (Prepared::Invalid(x), Prepared::Invalid(y)) => assert_eq!(x, y),
                (Prepared::Embedded(a), Prepared::Embedded(b)) => {
                    assert_eq!(a.path, b.path);
                    for (u, v) in a.embedding.iter().zip(&b.embedding) {
                        assert!((u - v).abs() <= 1e-5);
                    }
                }
                (g, w) => panic!("{g:?} vs {w:?}"),
            }
        }
    }
}
