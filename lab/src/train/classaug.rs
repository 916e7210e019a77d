//! Class augmentation: every training character under the symmetries of the square
//! (rotated by 0°, 90°, 180°, 270°, each also mirrored) becomes a class of its own, up to
//! 8x the training classes.
//!
//! The transforms act on the pen path in the canvas plane (the pen-tip path from forward
//! kinematics), which is what the network sees: drawing a rotated or mirrored character
//! with the robot gives the rotated or mirrored pen path (the features remove position and
//! size), so no IK is re-solved. The corrupted plans of a drawing (fault negatives) are
//! transformed with it, so a transformed class keeps its own fault negatives.
//!
//! **Symmetric characters.** A transform that maps a character onto itself (an "O" rotated
//! by 180°), or onto another training character (a "p" rotated by 180° is a "d"), would make
//! a class that cannot be told from an existing one; the triplet loss would then push apart
//! drawings of one character. Such transforms are dropped. The test is model-free: every
//! drawing's pen-down path is rasterised (bounding box centred, longest side scaled to the
//! grid, blurred), a class's template is the normalised mean of its drawers' rasters, and a
//! transformed template that is at least as similar (cosine) to some training template as
//! the two halves of one class's drawers typically are to each other ([`SymmetryRule`]) is
//! "the same character".

use guardian_robot::pen::{PenPoint, pen_down_box};
use guardian_shared::trajectory::STEPS;
use serde::{Deserialize, Serialize};

/// One of the eight symmetries of the square: mirror `x -> -x` first (the `M*` variants),
/// then rotate counter-clockwise by the angle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Dihedral {
    /// Identity.
    R0,
    /// Rotation by 90°.
    R90,
    /// Rotation by 180°.
    R180,
    /// Rotation by 270°.
    R270,
    /// Mirror.
    M0,
    /// Mirror, then rotation by 90°.
    M90,
    /// Mirror, then rotation by 180°.
    M180,
    /// Mirror, then rotation by 270°.
    M270,
}

impl Dihedral {
    /// All eight, identity first.
    pub const ALL: [Dihedral; 8] = [
        Dihedral::R0,
        Dihedral::R90,
        Dihedral::R180,
        Dihedral::R270,
        Dihedral::M0,
        Dihedral::M90,
        Dihedral::M180,
        Dihedral::M270,
    ];

    /// The seven non-identity transforms.
    pub fn non_identity() -> &'static [Dihedral] {
        &Self::ALL[1..]
    }

    fn parts(self) -> (bool, u8) {
        match self {
            Dihedral::R0 => (false, 0),
            Dihedral::R90 => (false, 1),
            Dihedral::R180 => (false, 2),
            Dihedral::R270 => (false, 3),
            Dihedral::M0 => (true, 0),
            Dihedral::M90 => (true, 1),
            Dihedral::M180 => (true, 2),
            Dihedral::M270 => (true, 3),
        }
    }

    /// The transform of a point.
    pub fn apply_xy(self, x: f32, y: f32) -> (f32, f32) {
        let (mirror, quarter_turns) = self.parts();
        let x = if mirror { -x } else { x };
        match quarter_turns {
            0 => (x, y),
            1 => (-y, x),
            2 => (-x, -y),
            _ => (y, -x),
        }
    }

    /// Transform a pen path in place (the pen channel is kept).
    pub fn apply(self, path: &mut [PenPoint; STEPS]) {
        for p in path.iter_mut() {
            let (x, y) = self.apply_xy(p[0], p[1]);
            p[0] = x;
            p[1] = y;
        }
    }

    /// The transform of a square `G x G` raster about its centre (row = y, column = x;
    /// the same map as [`Dihedral::apply_xy`] on cell centres).
    fn apply_raster(self, r: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0; GRID * GRID];
        let h = (GRID as f32 - 1.0) / 2.0;
        for row in 0..GRID {
            for col in 0..GRID {
                let (x, y) = (col as f32 - h, row as f32 - h);
                let (u, v) = self.apply_xy(x, y);
                let (c2, r2) = ((u + h).round() as usize, (v + h).round() as usize);
                out[r2 * GRID + c2] = r[row * GRID + col];
            }
        }
        out
    }
}

/// Side of the symmetry rasters (cells).
const GRID: usize = 24;

/// The blurred, unit-norm raster of a path's pen-down part (the whole path if the pen
/// never touches): bounding box centred, longest side spanning the grid.
pub fn raster(path: &[PenPoint; STEPS]) -> Vec<f32> {
    let any_down = path.iter().any(|q| q[2] > 0.5);
    let down = |q: &PenPoint| !any_down || q[2] > 0.5;
    let (lo, hi) = pen_down_box(path);
    let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
    let half = (0.5 * (hi[0] - lo[0]).max(hi[1] - lo[1])).max(1e-6);
    let h = (GRID as f32 - 1.0) / 2.0;
    let cell = |q: [f32; 2]| {
        let x = ((q[0] - centre[0]) / half * h + h)
            .round()
            .clamp(0.0, GRID as f32 - 1.0);
        let y = ((q[1] - centre[1]) / half * h + h)
            .round()
            .clamp(0.0, GRID as f32 - 1.0);
        y as usize * GRID + x as usize
    };
    let mut r = vec![0.0f32; GRID * GRID];
    for w in path.windows(2) {
        let (a, b) = (w[0], w[1]);
        if !(down(&a) && down(&b)) {
            continue;
        }
        // Points along the segment at most a quarter cell apart.
        let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt() / half * h;
        let n = (len * 4.0).ceil().max(1.0) as usize;
        for s in 0..=n {
            let t = s as f32 / n as f32;
            r[cell([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])])] = 1.0;
        }
    }
    // A path with a single pen-down sample is a dot.
    let mut downs = path.iter().filter(|q| down(q));
    if let (Some(q), None) = (downs.next(), downs.next()) {
        r[cell([q[0], q[1]])] = 1.0;
    }
    let r = blur(&blur(&r));
    unit(r)
}

fn blur(r: &[f32]) -> Vec<f32> {
    let mut out = vec![0.0; GRID * GRID];
    for row in 0..GRID {
        for col in 0..GRID {
            let mut s = 0.0;
            for dr in -1i32..=1 {
                for dc in -1i32..=1 {
                    let (rr, cc) = (row as i32 + dr, col as i32 + dc);
                    if (0..GRID as i32).contains(&rr) && (0..GRID as i32).contains(&cc) {
                        s += r[rr as usize * GRID + cc as usize];
                    }
                }
            }
            out[row * GRID + col] = s;
        }
    }
    out
}

fn unit(mut r: Vec<f32>) -> Vec<f32> {
    let n = r.iter().map(|v| v * v).sum::<f32>().sqrt();
    if n > 0.0 {
        r.iter_mut().for_each(|v| *v /= n);
    }
    r
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn template<'a>(rasters: impl Iterator<Item = &'a Vec<f32>>) -> Vec<f32> {
    let mut t = vec![0.0; GRID * GRID];
    for r in rasters {
        t.iter_mut().zip(r).for_each(|(a, b)| *a += b);
    }
    unit(t)
}

/// When a transformed class counts as an existing character.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub struct SymmetryRule {
    /// The quantile of the split-half similarities (each class's even- and odd-numbered
    /// drawers, one template each) used as the threshold: a transformed template at least
    /// this similar to some class's template is that class.
    pub quantile: f64,
}

impl Default for SymmetryRule {
    fn default() -> Self {
        Self { quantile: 0.1 }
    }
}

/// Which transforms of which classes make new classes, and why the others do not.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub struct AugmentPlan {
    /// For every class, the transforms kept (identity not listed).
    pub kept: Vec<Vec<Dihedral>>,
    /// Transforms dropped because the class maps onto itself.
    pub self_symmetric: usize,
    /// Transforms dropped because the class maps onto another class (or onto another kept
    /// transform of a class).
    pub collides: usize,
    /// The similarity threshold used.
    pub threshold: f32,
    /// Pairs of distinct original classes at or above the threshold (a measure of how
    /// strict it is: such pairs would be called "the same character").
    pub original_pairs_above: usize,
    /// Pairs of distinct original classes.
    pub original_pairs: usize,
}

impl AugmentPlan {
    /// Number of new classes.
    pub fn new_classes(&self) -> usize {
        self.kept.iter().map(Vec::len).sum()
    }
}

/// Decide which transforms make new classes. `by_class[c]` lists the pen paths of class
/// `c`'s drawings; `transforms` are the candidate (non-identity) transforms.
pub fn plan(
    by_class: &[Vec<&[PenPoint; STEPS]>],
    transforms: &[Dihedral],
    rule: SymmetryRule,
) -> AugmentPlan {
    let rasters: Vec<Vec<Vec<f32>>> = by_class
        .iter()
        .map(|c| c.iter().map(|p| raster(p)).collect())
        .collect();
    let templates: Vec<Vec<f32>> = rasters.iter().map(|r| template(r.iter())).collect();
    // Split-half similarity of every class with at least two drawings.
    let mut halves: Vec<f32> = rasters
        .iter()
        .filter(|r| r.len() >= 2)
        .map(|r| {
            let even = template(r.iter().step_by(2));
            let odd = template(r.iter().skip(1).step_by(2));
            cosine(&even, &odd)
        })
        .collect();
    halves.sort_by(f32::total_cmp);
    let threshold = if halves.is_empty() {
        1.0
    } else {
        let q = rule.quantile.clamp(0.0, 1.0);
        halves[((halves.len() - 1) as f64 * q).round() as usize]
    };
    let n = templates.len();
    let mut original_pairs_above = 0;
    for i in 0..n {
        for j in i + 1..n {
            if cosine(&templates[i], &templates[j]) >= threshold {
                original_pairs_above += 1;
            }
        }
    }
    let mut kept = vec![Vec::new(); n];
    let (mut self_symmetric, mut collides) = (0, 0);
    // Templates of the classes made so far (originals first), to catch a transform that
    // lands on another transform of the same or another class.
    let mut made: Vec<Vec<f32>> = templates.clone();
    for (c, t) in templates.iter().enumerate() {
        for &d in transforms.iter().filter(|d| **d != Dihedral::R0) {
            let moved = d.apply_raster(t);
            if cosine(&moved, t) >= threshold {
                self_symmetric += 1;
            } else if made.iter().any(|m| cosine(&moved, m) >= threshold) {
                collides += 1;
            } else {
                kept[c].push(d);
                made.push(moved);
            }
        }
    }
    AugmentPlan {
        kept,
        self_symmetric,
        collides,
        threshold,
        original_pairs_above,
        original_pairs: n * n.saturating_sub(1) / 2,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A path drawing the given polyline pen-down, resampled crudely to STEPS points.
    fn polyline(pts: &[[f32; 2]]) -> [PenPoint; STEPS] {
        let mut p = [[0.0f32; 3]; STEPS];
        let segs = pts.len() - 1;
        for (i, q) in p.iter_mut().enumerate() {
            let t = i as f32 / (STEPS - 1) as f32 * segs as f32;
            let s = (t.floor() as usize).min(segs - 1);
            let f = t - s as f32;
            q[0] = pts[s][0] + f * (pts[s + 1][0] - pts[s][0]);
            q[1] = pts[s][1] + f * (pts[s + 1][1] - pts[s][1]);
            q[2] = 1.0;
        }
        p
    }

    #[test]
    fn transforms_form_the_group_of_the_square() {
        let (x, y) = (0.3f32, -0.7f32);
        // Four quarter turns and two mirrors are the identity; all eight images differ.
        let mut seen = Vec::new();
        for d in Dihedral::ALL {
            let (u, v) = d.apply_xy(x, y);
            assert!(
                (u * u + v * v - (x * x + y * y)).abs() < 1e-6,
                "{d:?} keeps lengths"
            );
            assert!(
                !seen
                    .iter()
                    .any(|&(a, b): &(f32, f32)| (a - u).abs() < 1e-6 && (b - v).abs() < 1e-6)
            );
            seen.push((u, v));
        }
        let (u, v) = Dihedral::R90.apply_xy(x, y);
        let (u, v) = Dihedral::R270.apply_xy(u, v);
        assert!((u - x).abs() < 1e-6 && (v - y).abs() < 1e-6);
        // The raster transform is the same map as the point transform.
        let l = polyline(&[[0.0, 0.0], [1.0, 0.0], [1.0, 0.4]]);
        for d in Dihedral::ALL {
            let mut moved = l;
            d.apply(&mut moved);
            let a = raster(&moved);
            let b = d.apply_raster(&raster(&l));
            assert!(cosine(&a, &b) > 0.99, "{d:?}: {}", cosine(&a, &b));
        }
    }

    #[test]
    fn symmetric_and_colliding_transforms_are_dropped() {
        // A plus sign is symmetric under every transform; an "L" under none; "L" mirrored
        // is a "J"-like shape, which exists as its own class here.
        let plus = [[-1.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [0.0, -1.0]];
        let ell = [[0.0, 1.0], [0.0, 0.0], [0.6, 0.0]];
        let jay = [[0.0, 1.0], [0.0, 0.0], [-0.6, 0.0]];
        // Drawers differ by a small rotation.
        let jitter = |pts: &[[f32; 2]], k: usize| -> [PenPoint; STEPS] {
            let a = 0.03 * (k as f32 - 2.5);
            let (c, s) = (a.cos(), a.sin());
            let v: Vec<[f32; 2]> = pts
                .iter()
                .map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1]])
                .collect();
            polyline(&v)
        };
        let classes: Vec<Vec<[PenPoint; STEPS]>> = [&plus[..], &ell[..], &jay[..]]
            .iter()
            .map(|pts| (0..6).map(|k| jitter(pts, k)).collect())
            .collect();
        let by_class: Vec<Vec<&[PenPoint; STEPS]>> =
            classes.iter().map(|c| c.iter().collect()).collect();
        let plan = plan(&by_class, Dihedral::non_identity(), SymmetryRule::default());
        assert!(plan.kept[0].is_empty(), "plus: {:?}", plan.kept[0]);
        // "L" mirrored is the "J" class: dropped; its rotations are new.
        assert!(!plan.kept[1].contains(&Dihedral::M0), "{:?}", plan.kept[1]);
        assert!(plan.kept[1].contains(&Dihedral::R90), "{:?}", plan.kept[1]);
        // The "J"'s transforms are the "L"'s mirrored ones, already made: all dropped.
        assert!(plan.kept[2].is_empty(), "{:?}", plan.kept[2]);
        assert_eq!(plan.self_symmetric, 7);
        assert_eq!(plan.new_classes() + plan.self_symmetric + plan.collides, 21);
    }
}
