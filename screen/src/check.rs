//! One check of a plan, the same wherever it runs (the daemon, the lab, the benches):
//! workcell inspection (validation, resampling, workcell rules) → embedding, with the pen
//! path computed once → plan geometry from that path → the bank's decision.
//!
//! The robot and its workcell are one value, a [`Station`], resolved once (the daemon
//! builds it from its configuration at start and on reload) and passed to every stage that
//! needs them; the embedder holds the network only.
//!
//! A check has two stages so that a micro-batch can share one forward pass while each plan
//! is still decided against the bank as it stands when its turn comes: [`prepare`] (or
//! [`prepare_batch`]) runs everything that depends only on the plan, [`decide`] everything
//! that depends on the bank. [`check`] is both for one plan. Identify ([`embed_plan`]) and
//! enroll ([`enrollment`]) enter the same pipeline with the workcell rules off. Plans that
//! are resampled already (the lab's data sets) enter at the embedding stage
//! ([`embed_resampled`]); their plan geometry comes from the same pen path
//! ([`Embedded::geometry`]). Every trajectory is validated once, by the inspection.
//!
//! A station whose cell is anchored ([`Cell::anchored`]) also takes each plan's place
//! signature (its tool path in the base frame, `guardian_robot::place`) in [`prepare`],
//! [`embed_plan`] and [`enrollment`], and decides with the bank's place rule
//! ([`ClassBank::decide_in_place`]) instead of the canvas geometry; its region rules (allowed
//! and keep-out boxes) are checked with the workcell rules.

use guardian_shared::trajectory::{InvalidTrajectory, Resampled, STEPS, Waypoint};
use guardian_shared::workcell::{Workcell, WorkcellViolation};

use guardian_bank::{ClassBank, Example};
use guardian_models::embedder::{EmbedError, Embedder, Embedding};
use guardian_robot::cell::Cell;
use guardian_robot::geometry::PlanGeometry;
use guardian_robot::kinematics::Robot;
use guardian_robot::pen::PenPoint;
use guardian_robot::place::PlaceSignature;
use guardian_robot::workcell::{self, Inspection};
use guardian_shared::verdict::{NoGoReason, Verdict};

/// The robot served and the workcell it works in: what a check needs of the physical
/// world, resolved once.
#[derive(Debug, Clone)]
pub struct Station {
    robot: Robot,
    workcell: Workcell,
    cell: Cell,
}

impl Station {
    /// `robot` working under `workcell`'s rules.
    pub fn new(robot: Robot, workcell: Workcell) -> Self {
        Self {
            robot,
            workcell,
            cell: Cell::NONE,
        }
    }

    /// The published Panda with the default pen, in the paper's workcell (rules on).
    pub fn panda() -> Self {
        Self::new(
            guardian_robot::kinematics::default_panda().clone(),
            Workcell::default(),
        )
    }

    /// The robot.
    pub fn robot(&self) -> &Robot {
        &self.robot
    }

    /// The workcell rules.
    pub fn workcell(&self) -> &Workcell {
        &self.workcell
    }

    /// The same robot under other workcell rules.
    pub fn with_workcell(self, workcell: Workcell) -> Self {
        Self { workcell, ..self }
    }

    /// The same robot and workcell in `cell` (its region rules and anchoring).
    pub fn with_cell(self, cell: Cell) -> Self {
        Self { cell, ..self }
    }

    /// The cell's rules.
    pub fn cell(&self) -> &Cell {
        &self.cell
    }

    /// The place signature of a resampled plan, if the cell is anchored.
    fn place_of(&self, x: &Resampled) -> Option<PlaceSignature> {
        self.cell
            .anchored
            .then(|| PlaceSignature::of_plan(&self.robot, x))
    }
}

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
    /// The plan's place signature (only for an anchored station).
    pub place: Option<PlaceSignature>,
}

impl Embedded {
    /// The plan geometry of the pen path (`None` if the pen never touches the canvas).
    pub fn geometry(&self) -> Option<PlanGeometry> {
        workcell::plan_geometry_of_path(&self.path)
    }
}

/// Inspect `waypoints` against `station`'s robot and rules: the early outcome, or the
/// inspection to embed.
fn inspect(station: &Station, waypoints: &[Waypoint]) -> Result<Inspection, Prepared> {
    let inspection =
        workcell::inspect_in(&station.robot, &station.workcell, &station.cell, waypoints)
            .map_err(Prepared::Invalid)?;
    match inspection.violation {
        Some(v) => Err(Prepared::Workcell(v)),
        None => Ok(inspection),
    }
}

/// Inspect and embed one plan. An embedding failure is an error, never a verdict.
pub fn prepare(
    embedder: &Embedder,
    station: &Station,
    waypoints: &[Waypoint],
) -> Result<Prepared, EmbedError> {
    let inspection = match inspect(station, waypoints) {
        Ok(i) => i,
        Err(early) => return Ok(early),
    };
    let (embedding, path) = embedder.embed_with_pen_path(&station.robot, &inspection.resampled)?;
    let place = station.place_of(&inspection.resampled);
    Ok(Prepared::Embedded(Box::new(Embedded {
        embedding,
        path,
        place,
    })))
}

/// The embedding stage alone, for plans of `robot` that are already resampled (the lab's
/// data sets hold resampled plans, so there is nothing to inspect first): `xs` in one
/// forward pass, each with the pen path its features came from.
pub fn embed_resampled(
    embedder: &Embedder,
    robot: &Robot,
    xs: &[Resampled],
) -> Result<Vec<Embedded>, EmbedError> {
    let mut paths = vec![[[0.0f32; 3]; STEPS]; xs.len()];
    let embeddings = embedder.embed_batch_with_pen_paths(robot, xs, &mut paths)?;
    Ok(embeddings
        .into_iter()
        .zip(paths)
        .map(|(embedding, path)| Embedded {
            embedding,
            path,
            place: None,
        })
        .collect())
}

/// [`prepare`] for several plans, embedding the ones that pass inspection in one forward
/// pass. If that pass fails, each plan is embedded alone, so an error belongs to the plan
/// that caused it.
pub fn prepare_batch(
    embedder: &Embedder,
    station: &Station,
    plans: &[&[Waypoint]],
) -> Vec<Result<Prepared, EmbedError>> {
    let inspected: Vec<Result<Inspection, Prepared>> =
        plans.iter().map(|w| inspect(station, w)).collect();
    let xs: Vec<_> = inspected
        .iter()
        .filter_map(|i| i.as_ref().ok().map(|i| i.resampled))
        .collect();
    let batch = if xs.len() >= 2 {
        embed_resampled(embedder, &station.robot, &xs)
            .ok()
            .map(|mut es| {
                for (e, x) in es.iter_mut().zip(&xs) {
                    e.place = station.place_of(x);
                }
                es
            })
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
                None => prepare(embedder, station, w),
            },
        })
        .collect()
}

/// Decide a prepared plan claiming class `claimed` against `bank`, with the `k` nearest
/// classes: the verdict the daemon sends. A plan stopped before the embedding (invalid,
/// workcell rule: absolute, no model involved) is a no-go without numbers. The plan
/// geometry is computed from the pen path only when the bank can use it. At an anchored
/// `station` the place rule decides instead of the plan geometry (a plan prepared without
/// its place signature is never in place).
pub fn decide(
    bank: &ClassBank,
    station: &Station,
    prepared: &Prepared,
    claimed: &str,
    k: usize,
) -> Verdict {
    let early = |reason: NoGoReason| {
        Verdict::early(claimed, reason, bank.model_version(), bank.generation())
    };
    match prepared {
        Prepared::Invalid(inv) => early((*inv).into()),
        Prepared::Workcell(v) => early((*v).into()),
        Prepared::Embedded(e) if station.cell.anchored => {
            let none = PlaceSignature {
                tools: Vec::new(),
                points: Vec::new(),
            };
            bank.decide_in_place(
                &e.embedding,
                e.place.as_ref().unwrap_or(&none),
                &station.cell.place,
                claimed,
                k,
            )
        }
        Prepared::Embedded(e) => {
            let geometry = bank.geometry_calibration().and_then(|_| e.geometry());
            bank.decide_with_geometry(&e.embedding, geometry.as_ref(), claimed, k)
        }
    }
}

/// Check one plan: [`prepare`], then [`decide`].
pub fn check(
    embedder: &Embedder,
    bank: &ClassBank,
    station: &Station,
    waypoints: &[Waypoint],
    claimed: &str,
    k: usize,
) -> Result<Verdict, EmbedError> {
    Ok(decide(
        bank,
        station,
        &prepare(embedder, station, waypoints)?,
        claimed,
        k,
    ))
}

/// Validate, resample and embed one plan of `station`'s robot with the workcell rules off
/// (identify: which classes a plan is nearest to, wherever it is drawn). `Ok(Err(_))`: the
/// trajectory is invalid; `Err(_)`: the network failed (never a verdict).
pub fn embed_plan(
    embedder: &Embedder,
    station: &Station,
    waypoints: &[Waypoint],
) -> Result<Result<Embedded, InvalidTrajectory>, EmbedError> {
    let x = match workcell::inspect_with(&station.robot, &Workcell::OFF, waypoints) {
        Ok(i) => i.resampled,
        Err(inv) => return Ok(Err(inv)),
    };
    let (embedding, path) = embedder.embed_with_pen_path(&station.robot, &x)?;
    let place = station.place_of(&x);
    Ok(Ok(Embedded {
        embedding,
        path,
        place,
    }))
}

/// What an enrollment adds to a class: per example its embedding, its kept plan and (only
/// if every example draws on the canvas) its geometry descriptor.
#[derive(Debug, Clone)]
pub struct Enrollment {
    /// One embedding per example.
    pub embeddings: Vec<Vec<f32>>,
    /// One descriptor per example, or none.
    pub geometry: Vec<PlanGeometry>,
    /// The resampled plans, kept so that the class survives a new model.
    pub examples: Vec<Example>,
    /// One place signature per example at an anchored station, else none.
    pub place: Vec<PlaceSignature>,
}

/// An enrollment's examples could not be embedded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EnrollmentError {
    /// Example `index` failed validation (the first one that did).
    #[error("example {index}: {source}")]
    Invalid {
        /// Its position in the request.
        index: u32,
        /// What is wrong.
        source: InvalidTrajectory,
    },
    /// The network failed.
    #[error(transparent)]
    Embed(#[from] EmbedError),
}

/// Validate and resample every example of `station`'s robot (rules off, as for identify),
/// then embed them as [`crate::reembed::enrollment`] does (the same function a re-embedding
/// for a new model uses).
pub fn enrollment(
    embedder: &Embedder,
    station: &Station,
    plans: &[Vec<Waypoint>],
) -> Result<Enrollment, EnrollmentError> {
    let mut xs = Vec::with_capacity(plans.len());
    for (i, t) in plans.iter().enumerate() {
        let x = workcell::inspect_with(&station.robot, &Workcell::OFF, t).map_err(|source| {
            EnrollmentError::Invalid {
                index: u32::try_from(i).unwrap_or(u32::MAX),
                source,
            }
        })?;
        xs.push(x.resampled);
    }
    let (embeddings, geometry) = crate::reembed::enrollment(embedder, &station.robot, &xs)?;
    let joints = station.robot.joints();
    let examples = xs
        .iter()
        .map(|x| Example::from_resampled(x, joints))
        .collect();
    let place = xs.iter().filter_map(|x| station.place_of(x)).collect();
    Ok(Enrollment {
        embeddings,
        geometry,
        examples,
        place,
    })
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
        let off = Station::panda().with_workcell(Workcell::OFF);
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
