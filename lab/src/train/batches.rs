//! The training data as batches: the samples of the chosen alphabets with their pen paths,
//! their corrupted plans (fault negatives) and class-augmented transforms ([`Prepared`]);
//! class-balanced P x K batches, fault negatives added to a batch, and the feature tensors
//! with random augmentation.

use std::collections::BTreeMap;
use std::path::PathBuf;

use candle_core::{Device, Tensor};
use guardian_models::features::{self, Augment, FeatureKind};
use guardian_robot::pen::{PenPoint, pen_path_with};
use guardian_shared::trajectory::{Resampled, STEPS};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::train::TrainError;
use crate::train::classaug::{self, AugmentPlan, Dihedral, SymmetryRule};
use guardian_omniglot::corrupt::{self, Fault};
use guardian_omniglot::dataset::{Dataset, StrokeIndex};
use guardian_omniglot::path::PathSolver;

/// Labels of fault negatives in a batch count down from here (one label per corrupted
/// plan, so it is a negative of every genuine sample and the positive of none).
const FAULT_LABEL_TOP: u32 = u32::MAX;

/// One sample of a batch: a genuine drawing, or one of its corrupted plans.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Item {
    /// Sample `i` of the prepared set.
    Genuine(usize),
    /// Corrupted plan `v` of sample `i`.
    Fault(usize, usize),
}

/// The training data in the form the batch sampler needs.
pub struct Prepared {
    kind: FeatureKind,
    /// Pen paths (pen features) or raw inputs (joint features), per sample.
    pen: Vec<[PenPoint; STEPS]>,
    raw: Vec<Resampled>,
    /// Sample indices per class.
    by_class: Vec<Vec<usize>>,
    /// Class label per sample (dense, 0..by_class.len()).
    labels: Vec<u32>,
    /// Dataset index per sample.
    data_index: Vec<usize>,
    /// Pen paths of the corrupted plans of each sample (empty without fault negatives).
    faults: Vec<Vec<[PenPoint; STEPS]>>,
    /// The fault of each of them (`faults[i][v]` was made with `fault_kinds[i][v]`).
    fault_kinds: Vec<Vec<Fault>>,
    /// Time reversal among the augmentations.
    reverse_augment: bool,
}

impl Prepared {
    /// Select the samples of `alphabets` from `data`.
    pub fn new(
        data: &Dataset,
        alphabets: &[String],
        kind: FeatureKind,
    ) -> Result<Self, TrainError> {
        let ids = data
            .alphabet_ids(alphabets)
            .map_err(|e| TrainError::Setup(e.to_string()))?;
        let mut class_map: BTreeMap<i64, usize> = BTreeMap::new();
        let mut by_class: Vec<Vec<usize>> = Vec::new();
        let mut raw = Vec::new();
        let mut labels = Vec::new();
        let mut data_index = Vec::new();
        for i in 0..data.len() {
            if !ids.contains(&data.alphabet_ids[i]) {
                continue;
            }
            let next = class_map.len();
            let c = *class_map.entry(data.labels[i]).or_insert(next);
            if c == by_class.len() {
                by_class.push(Vec::new());
            }
            by_class[c].push(raw.len());
            raw.push(data.trajectories[i]);
            labels.push(c as u32);
            data_index.push(i);
        }
        let pen = if kind != FeatureKind::Joints {
            // Pen paths by the forward kinematics of the robot that drew the data set.
            let robot = data.robot().map_err(|e| TrainError::Setup(e.to_string()))?;
            raw.iter().map(|x| pen_path_with(&robot, x)).collect()
        } else if data.robot.joints != guardian_robot::kinematics::PANDA_JOINTS {
            return Err(TrainError::Setup(format!(
                "joint features are for Panda data sets; this one was drawn by {}",
                data.robot
            )));
        } else {
            Vec::new()
        };
        let faults = vec![Vec::new(); raw.len()];
        let fault_kinds = vec![Vec::new(); raw.len()];
        Ok(Self {
            kind,
            pen,
            raw,
            by_class,
            labels,
            data_index,
            faults,
            fault_kinds,
            reverse_augment: true,
        })
    }

    /// Make `variants` corrupted plans of every sample for fault-negative training: a random
    /// fault of `kinds` at a random severity in [0.25, 1], made on the drawing's
    /// Omniglot strokes (found under `strokes_roots` by class and drawer) and re-solved
    /// through the dataset's IK, exactly as the evaluation's faulty plans are. Deterministic
    /// in `seed`. Returns how many were made (a drawing whose strokes are missing, or a
    /// corruption that cannot be solved, gets fewer).
    pub fn make_faults(
        &mut self,
        data: &Dataset,
        strokes_roots: &[PathBuf],
        kinds: &[Fault],
        variants: usize,
        seed: u64,
    ) -> Result<usize, TrainError> {
        if kinds.is_empty() {
            return Err(TrainError::Setup(
                "no fault kinds to make negatives with".into(),
            ));
        }
        if self.kind == FeatureKind::Joints {
            return Err(TrainError::Setup(
                "fault negatives need pen features".into(),
            ));
        }
        let index = StrokeIndex::scan(strokes_roots)
            .map_err(|e| TrainError::Setup(format!("fault negatives: {e}")))?;
        let solver = PathSolver::new(&data.geometry)
            .map_err(|e| TrainError::Setup(format!("fault negatives: {e}")))?;
        let made: Vec<Vec<([PenPoint; STEPS], Fault)>> = self
            .data_index
            .par_iter()
            .map(|&i| {
                let Some(st) = index.strokes_of(data, i) else {
                    return Vec::new();
                };
                let mut rng = StdRng::seed_from_u64(seed ^ (i as u64).wrapping_mul(0x9e37_79b9));
                let mut out = Vec::with_capacity(variants);
                let mut tries = 0;
                while out.len() < variants && tries < 4 * variants {
                    tries += 1;
                    let fault = kinds[rng.random_range(0..kinds.len())];
                    let severity = rng.random_range(0.25..=1.0);
                    if let Ok(x) = corrupt::corrupt(&solver, fault, severity, &st, &mut rng) {
                        out.push((pen_path_with(solver.robot(), &x), fault));
                    }
                }
                out
            })
            .collect();
        (self.faults, self.fault_kinds) = made
            .into_iter()
            .map(|m| -> (Vec<_>, Vec<_>) { m.into_iter().unzip() })
            .unzip();
        Ok(self.faults.iter().map(Vec::len).sum())
    }

    /// Class augmentation: add the transforms of every class that `plan` keeps as classes
    /// of their own (pen paths and corrupted plans transformed; same dataset indices).
    /// Call after [`Prepared::make_faults`]. Returns the plan.
    pub fn augment_classes(&mut self, rule: SymmetryRule) -> Result<AugmentPlan, TrainError> {
        if self.kind == FeatureKind::Joints {
            return Err(TrainError::Setup(
                "class augmentation needs pen features".into(),
            ));
        }
        let groups: Vec<Vec<&[PenPoint; STEPS]>> = self
            .by_class
            .iter()
            .map(|m| m.iter().map(|&i| &self.pen[i]).collect())
            .collect();
        let plan = classaug::plan(&groups, Dihedral::non_identity(), rule);
        for (c, kept) in plan.kept.iter().enumerate() {
            for &d in kept {
                let label = self.by_class.len() as u32;
                let mut members = Vec::with_capacity(self.by_class[c].len());
                for &i in &self.by_class[c].clone() {
                    let mut p = self.pen[i];
                    d.apply(&mut p);
                    let mut f = self.faults[i].clone();
                    f.iter_mut().for_each(|x| d.apply(x));
                    members.push(self.raw.len());
                    self.pen.push(p);
                    self.raw.push(self.raw[i]);
                    self.faults.push(f);
                    self.fault_kinds.push(self.fault_kinds[i].clone());
                    self.labels.push(label);
                    self.data_index.push(self.data_index[i]);
                }
                self.by_class.push(members);
            }
        }
        Ok(plan)
    }

    /// The source class of every item: `Some(class label)` for a corrupted plan, `None`
    /// for a genuine sample (the `sources` of `loss::fault_triplet_loss`).
    pub fn sources(&self, items: &[Item]) -> Vec<Option<u32>> {
        items
            .iter()
            .map(|it| match *it {
                Item::Genuine(_) => None,
                Item::Fault(i, _) => Some(self.labels[i]),
            })
            .collect()
    }

    /// The fault a corrupted plan was made with (`None` for a genuine sample, or a plan
    /// not made by [`Prepared::make_faults`]).
    pub fn fault_kind(&self, item: Item) -> Option<Fault> {
        match item {
            Item::Genuine(_) => None,
            Item::Fault(i, v) => self.fault_kinds.get(i)?.get(v).copied(),
        }
    }

    /// Number of corrupted plans of sample `i` (0 without fault negatives).
    pub fn faults_of(&self, i: usize) -> usize {
        self.faults.get(i).map_or(0, Vec::len)
    }

    /// The batch `idx` / `labels` with fault negatives added: each sample that has
    /// corrupted plans brings one at random with probability `share`, labelled as a class
    /// of its own. Draws nothing from `rng` when `share` is 0.
    pub fn with_faults(
        &self,
        idx: &[usize],
        labels: &[u32],
        share: f64,
        rng: &mut StdRng,
    ) -> (Vec<Item>, Vec<u32>) {
        let mut items: Vec<Item> = idx.iter().map(|&i| Item::Genuine(i)).collect();
        let mut out = labels.to_vec();
        if share > 0.0 {
            let mut next = FAULT_LABEL_TOP;
            for &i in idx {
                let n = self.faults[i].len();
                if n > 0 && rng.random_bool(share.min(1.0)) {
                    items.push(Item::Fault(i, rng.random_range(0..n)));
                    out.push(next);
                    next -= 1;
                }
            }
        }
        (items, out)
    }

    /// Allow or forbid time reversal among the augmentations (allowed by default).
    pub fn set_reverse_augment(&mut self, on: bool) {
        self.reverse_augment = on;
    }

    /// Number of classes.
    pub fn classes(&self) -> usize {
        self.by_class.len()
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.raw.len()
    }

    /// True if there are no samples.
    pub fn is_empty(&self) -> bool {
        self.raw.is_empty()
    }

    /// Feature tensor `[B, steps, F]` (see [`FeatureKind::steps`]) of samples `idx`, augmented when `rng` is given.
    pub fn batch(&self, idx: &[usize], rng: Option<&mut StdRng>) -> candle_core::Result<Tensor> {
        let items: Vec<Item> = idx.iter().map(|&i| Item::Genuine(i)).collect();
        self.batch_items(&items, rng)
    }

    /// Feature tensor `[B, STEPS, F]` of genuine and corrupted samples, augmented when
    /// `rng` is given.
    pub fn batch_items(
        &self,
        items: &[Item],
        mut rng: Option<&mut StdRng>,
    ) -> candle_core::Result<Tensor> {
        let (steps, c) = (self.kind.steps(), self.kind.channels());
        let mut buf = vec![0.0f32; items.len() * steps * c];
        for (&item, out) in items.iter().zip(buf.chunks_exact_mut(steps * c)) {
            let path = match item {
                Item::Genuine(i) if self.kind == FeatureKind::Joints => {
                    features::compute(self.kind, &self.raw[i], out);
                    continue;
                }
                Item::Genuine(i) => self.pen.get(i),
                Item::Fault(i, v) => self.faults.get(i).and_then(|f| f.get(v)),
            };
            let Some(path) = path else {
                candle_core::bail!("batch item {item:?} is not in the prepared set");
            };
            let aug = match rng.as_deref_mut() {
                Some(r) => random_augment(r, self.reverse_augment),
                None => Augment::default(),
            };
            features::path_features(self.kind, path, &aug, out);
        }
        Tensor::from_vec(buf, (items.len(), steps, c), &Device::Cpu)
    }

    /// A class-balanced batch: `p` classes, `k` samples each (fewer if a class is small).
    pub fn sample_pk(&self, p: usize, k: usize, rng: &mut StdRng) -> (Vec<usize>, Vec<u32>) {
        let mut classes: Vec<usize> = (0..self.by_class.len()).collect();
        classes.shuffle(rng);
        classes.truncate(p);
        let mut idx = Vec::with_capacity(p * k);
        let mut labels = Vec::with_capacity(p * k);
        for &c in &classes {
            let mut members = self.by_class[c].clone();
            members.shuffle(rng);
            for &m in members.iter().take(k) {
                idx.push(m);
                labels.push(self.labels[m]);
            }
        }
        (idx, labels)
    }

    /// A set of pen paths with dense labels, for unit tests (no dataset behind it).
    #[cfg(test)]
    pub(crate) fn from_pen_paths(
        kind: FeatureKind,
        pen: Vec<[PenPoint; STEPS]>,
        labels: Vec<u32>,
    ) -> Self {
        let classes = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
        let mut by_class = vec![Vec::new(); classes];
        for (i, &l) in labels.iter().enumerate() {
            by_class[l as usize].push(i);
        }
        let n = pen.len();
        Self {
            kind,
            pen,
            raw: vec![[[0.0; guardian_shared::trajectory::SLOTS]; STEPS]; n],
            by_class,
            labels,
            data_index: (0..n).collect(),
            faults: vec![Vec::new(); n],
            fault_kinds: vec![Vec::new(); n],
            reverse_augment: true,
        }
    }

    /// The raw inputs.
    pub fn raw(&self) -> &[Resampled] {
        &self.raw
    }

    /// The pen path of every sample (empty for joint features).
    pub fn pen_paths(&self) -> &[[PenPoint; STEPS]] {
        &self.pen
    }

    /// Dense class label per sample.
    pub fn labels(&self) -> &[u32] {
        &self.labels
    }

    /// The data set index of every sample (a transform's source drawing).
    pub fn data_indices(&self) -> &[usize] {
        &self.data_index
    }
}

/// Random augmentation; with `reverse` false the draw for time reversal is made and
/// ignored, so the other augmentations are the same as with it.
fn random_augment(rng: &mut StdRng, reverse: bool) -> Augment {
    Augment {
        rotation: rng.random_range(-0.2..0.2),
        shear: rng.random_range(-0.2..0.2),
        scale_x: rng.random_range(0.85..1.15),
        scale_y: rng.random_range(0.85..1.15),
        reverse: rng.random_bool(0.5) && reverse,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` classes of `k` straight pen-down strokes each (class `c` at angle `c`).
    fn lines(n: usize, k: usize) -> Prepared {
        let mut pen = Vec::new();
        let mut labels = Vec::new();
        for c in 0..n {
            for j in 0..k {
                let a = c as f32 * 0.7;
                let s = 0.01 * (1.0 + j as f32);
                pen.push(std::array::from_fn(|t| {
                    let u = t as f32 / (STEPS - 1) as f32;
                    [s * u * a.cos(), s * u * a.sin(), 1.0]
                }));
                labels.push(c as u32);
            }
        }
        Prepared::from_pen_paths(FeatureKind::Pen, pen, labels)
    }

    #[test]
    fn a_pk_batch_takes_p_distinct_classes_and_k_of_each() {
        let set = lines(10, 6);
        let mut rng = StdRng::seed_from_u64(1);
        let (idx, labels) = set.sample_pk(4, 3, &mut rng);
        assert_eq!(idx.len(), 12);
        let classes: std::collections::BTreeSet<u32> = labels.iter().copied().collect();
        assert_eq!(classes.len(), 4);
        for c in classes {
            let members: Vec<usize> = idx
                .iter()
                .zip(&labels)
                .filter(|&(_, &l)| l == c)
                .map(|(&i, _)| i)
                .collect();
            assert_eq!(members.len(), 3);
            assert!(members.iter().all(|&i| set.labels()[i] == c));
            let distinct: std::collections::BTreeSet<usize> = members.iter().copied().collect();
            assert_eq!(distinct.len(), 3, "distinct drawings");
        }
        // More classes than the set has: every class, once.
        let (_, labels) = set.sample_pk(20, 2, &mut rng);
        assert_eq!(labels.len(), 20);
    }

    #[test]
    fn fault_negatives_join_a_batch_with_labels_of_their_own() {
        let mut set = lines(3, 2);
        let (idx, labels) = (vec![0, 1, 2, 3], vec![0, 0, 1, 1]);
        // Without corrupted plans, or at share 0, the batch is unchanged and nothing is drawn.
        let mut rng = StdRng::seed_from_u64(5);
        let (items, out) = set.with_faults(&idx, &labels, 1.0, &mut rng);
        assert_eq!(out, labels);
        assert!(items.iter().all(|i| matches!(i, Item::Genuine(_))));
        set.faults[1] = vec![set.pen[4]; 3];
        set.faults[2] = vec![set.pen[5]; 2];
        let (items, out) = set.with_faults(&idx, &labels, 0.0, &mut rng);
        assert_eq!((items.len(), out), (4, labels.clone()));
        assert_eq!(
            rng.random::<u64>(),
            StdRng::seed_from_u64(5).random::<u64>()
        );
        // At share 1 every sample with corrupted plans brings one.
        let (items, out) = set.with_faults(&idx, &labels, 1.0, &mut rng);
        assert_eq!(items.len(), 6);
        assert_eq!(&out[4..], [u32::MAX, u32::MAX - 1]);
        assert!(matches!(items[4], Item::Fault(1, v) if v < 3));
        assert!(matches!(items[5], Item::Fault(2, v) if v < 2));
        assert_eq!(set.sources(&items)[4..], [Some(0), Some(1)]);
        assert_eq!(set.sources(&items)[..4], [None; 4]);
        // Their features are the corrupted plan's.
        let x = set.batch_items(&items, None).expect("batch");
        let y = set.batch(&[4, 5], None).expect("batch");
        let (x, y) = (x.to_vec3::<f32>().unwrap(), y.to_vec3::<f32>().unwrap());
        assert_eq!(x[4], y[0]);
        assert_eq!(x[5], y[1]);
        // An item the set does not hold is an error, not a panic.
        assert!(set.batch_items(&[Item::Fault(0, 0)], None).is_err());
    }

    #[test]
    fn augmentation_changes_the_features_and_without_reversal_keeps_the_other_draws() {
        let mut set = lines(2, 2);
        let plain = set.batch(&[0], None).unwrap().to_vec3::<f32>().unwrap();
        let mut rng = StdRng::seed_from_u64(9);
        let aug = set
            .batch(&[0], Some(&mut rng))
            .unwrap()
            .to_vec3::<f32>()
            .unwrap();
        assert_ne!(plain, aug);
        // Reversal off: the same random stream gives the same rotation, shear and scale.
        let a = random_augment(&mut StdRng::seed_from_u64(3), true);
        let b = random_augment(&mut StdRng::seed_from_u64(3), false);
        assert_eq!(
            (a.rotation, a.shear, a.scale_x, a.scale_y),
            (b.rotation, b.shear, b.scale_x, b.scale_y)
        );
        assert!(!b.reverse);
        set.set_reverse_augment(false);
        assert!(!set.reverse_augment);
    }
}
