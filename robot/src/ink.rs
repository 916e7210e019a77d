//! A plan's ink: where its pen draws on the canvas, as polylines, and how far one plan's ink
//! is from another's.
//!
//! The embedder and the plan geometry both summarise a plan; neither sees *which part* of a
//! drawing is there. A plan stopped early is close to its class in both (it draws most of
//! the right thing in the right place), and one drawn mirrored keeps its size, place and
//! stroke count. Ink compares the drawings point by point, whatever the stroke order and
//! direction: the **ink distance** of plan `P` to example `E` is the larger of
//!
//! - *missing*: the `q`-quantile, over `E`'s pen-down points, of the distance to `P`'s ink
//!   (a part of the example the plan does not draw), and
//! - *extra*: the same over `P`'s points to `E`'s ink (a part the plan draws and the example
//!   does not),
//!
//! a quantile form of the modified Hausdorff distance used for one-shot character matching
//! (Dubuisson and Jain, 1994). The distances are to the polylines (segments between
//! consecutive pen-down points), so a sparse sampling of a straight stroke costs nothing.
//!
//! Only the lab uses it (`guardian-lab outliers --ink`): as a step of the decision it caught
//! +0.017 of the truncated and +0.013 of the mirrored plans on unseen alphabets, too little
//! to bring it into the daemon (`docs/report/log-2026-12-07.md`). Re-ranking the nearest
//! classes of a one-shot episode by ink added +0.003 to the K-fold's 20-way 1-shot
//! accuracy; that option was measured at commit `430890d` and removed again (same log).

use crate::pen::PenPoint;

/// The ink of one plan: its pen-down points (x, y in metres), grouped in strokes.
#[derive(Debug, Clone, PartialEq)]
pub struct Ink {
    points: Vec<[f32; 2]>,
    /// Index into `points` where each stroke starts (ascending, first 0).
    starts: Vec<usize>,
}

impl Ink {
    /// The ink of a pen path (`None` if the pen never touches the canvas).
    pub fn of_path(path: &[PenPoint]) -> Option<Self> {
        let mut points = Vec::new();
        let mut starts = Vec::new();
        let mut down = false;
        for p in path {
            if p[2] > 0.5 {
                if !down {
                    starts.push(points.len());
                }
                points.push([p[0], p[1]]);
                down = true;
            } else {
                down = false;
            }
        }
        (!points.is_empty()).then_some(Self { points, starts })
    }

    /// The pen-down points.
    pub fn points(&self) -> &[[f32; 2]] {
        &self.points
    }

    /// Every coordinate finite.
    pub fn is_finite(&self) -> bool {
        self.points.iter().flatten().all(|v| v.is_finite())
    }

    /// The same ink moved so that its bounding box is centred on the origin.
    pub fn centred(&self) -> Self {
        let mut lo = [f32::INFINITY; 2];
        let mut hi = [f32::NEG_INFINITY; 2];
        for p in &self.points {
            for a in 0..2 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let c = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
        Self {
            points: self
                .points
                .iter()
                .map(|p| [p[0] - c[0], p[1] - c[1]])
                .collect(),
            starts: self.starts.clone(),
        }
    }

    /// Each stroke as a slice of points.
    fn strokes(&self) -> impl Iterator<Item = &[[f32; 2]]> {
        let ends = self
            .starts
            .iter()
            .skip(1)
            .copied()
            .chain([self.points.len()]);
        self.starts
            .iter()
            .zip(ends)
            .map(|(&s, e)| &self.points[s..e])
    }

    /// Squared distance of `p` to the nearest point of the ink (its segments and isolated
    /// points).
    fn squared_distance(&self, p: [f32; 2]) -> f32 {
        let mut best = f32::INFINITY;
        for s in self.strokes() {
            if s.len() == 1 {
                best = best.min(sq(p, s[0]));
            }
            for w in s.windows(2) {
                best = best.min(sq(p, segment_nearest(p, w[0], w[1])));
            }
        }
        best
    }

    /// The `q`-quantile of the distances of this ink's points to `other`'s ink.
    pub fn uncovered_by(&self, other: &Ink, q: f32) -> f32 {
        let mut d: Vec<f32> = self
            .points
            .iter()
            .map(|&p| other.squared_distance(p))
            .collect();
        quantile(&mut d, q).sqrt()
    }
}

/// The ink distance of `plan` to `example` (see the module docs): the larger of what of the
/// example the plan leaves undrawn and what it draws beyond it, each as the `q`-quantile of
/// point-to-ink distances (m). A coordinate that is not finite gives NaN.
pub fn distance(plan: &Ink, example: &Ink, q: f32) -> f32 {
    if !(plan.is_finite() && example.is_finite()) {
        return f32::NAN;
    }
    let missing = example.uncovered_by(plan, q);
    let extra = plan.uncovered_by(example, q);
    missing.max(extra)
}

/// The ink score of `plan` against a class's enrolled examples: the distance to the nearest
/// example (a plan is consistent if some enrolled example drew like it). `None` without
/// examples.
pub fn score(plan: &Ink, examples: &[Ink], q: f32) -> Option<f32> {
    examples
        .iter()
        .map(|e| distance(plan, e, q))
        .reduce(|a, b| {
            if a.is_nan() || b.is_nan() {
                f32::NAN
            } else {
                a.min(b)
            }
        })
}

fn sq(a: [f32; 2], b: [f32; 2]) -> f32 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

fn segment_nearest(p: [f32; 2], a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let ap = [p[0] - a[0], p[1] - a[1]];
    let len = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len > 0.0 {
        ((ap[0] * ab[0] + ap[1] * ab[1]) / len).clamp(0.0, 1.0)
    } else {
        0.0
    };
    [a[0] + t * ab[0], a[1] + t * ab[1]]
}

/// The `q`-quantile (nearest rank) of `v`, reordering it; NaN if any value is NaN.
fn quantile(v: &mut [f32], q: f32) -> f32 {
    if v.is_empty() || v.iter().any(|x| x.is_nan()) {
        return f32::NAN;
    }
    let k = ((q.clamp(0.0, 1.0) * v.len() as f32).ceil() as usize).clamp(1, v.len()) - 1;
    *v.select_nth_unstable_by(k, f32::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(strokes: &[&[[f32; 2]]]) -> Vec<PenPoint> {
        let mut out = Vec::new();
        for s in strokes {
            out.push([s[0][0], s[0][1], 0.0]);
            out.extend(s.iter().map(|p| [p[0], p[1], 1.0]));
            out.push([s[s.len() - 1][0], s[s.len() - 1][1], 0.0]);
        }
        out
    }

    fn line(from: [f32; 2], to: [f32; 2], n: usize) -> Vec<[f32; 2]> {
        (0..n)
            .map(|i| {
                let t = i as f32 / (n - 1) as f32;
                [
                    from[0] + t * (to[0] - from[0]),
                    from[1] + t * (to[1] - from[1]),
                ]
            })
            .collect()
    }

    #[test]
    fn the_same_drawing_in_another_order_is_at_distance_zero() {
        let a = line([0.0, 0.0], [0.04, 0.0], 9);
        let b = line([0.0, 0.0], [0.0, 0.04], 9);
        let mut b_rev = b.clone();
        b_rev.reverse();
        let one = Ink::of_path(&path(&[&a, &b])).unwrap();
        let other = Ink::of_path(&path(&[&b_rev, &a])).unwrap();
        assert!(distance(&one, &other, 1.0) < 1e-6);
        // Sampled differently along the same lines: still on the ink.
        let sparse = Ink::of_path(&path(&[&line([0.0, 0.0], [0.04, 0.0], 2), &b])).unwrap();
        assert!(distance(&sparse, &one, 1.0) < 1e-6);
    }

    #[test]
    fn a_drawing_stopped_early_misses_the_rest_of_its_example() {
        let a = line([0.0, 0.0], [0.04, 0.0], 9);
        let b = line([0.0, 0.0], [0.0, 0.04], 9);
        let whole = Ink::of_path(&path(&[&a, &b])).unwrap();
        let stopped = Ink::of_path(&path(&[&a, &b[..5]])).unwrap();
        // Nothing extra: every point of the stopped plan lies on the example.
        assert!(stopped.uncovered_by(&whole, 1.0) < 1e-6);
        // The last 2 cm of the vertical stroke are missing.
        assert!((whole.uncovered_by(&stopped, 1.0) - 0.02).abs() < 1e-6);
        assert!((distance(&stopped, &whole, 1.0) - 0.02).abs() < 1e-6);
        // The quantile ignores the worst points: 4 of 18 are past the end.
        assert!(distance(&stopped, &whole, 0.75) < 0.02);
    }

    #[test]
    fn a_mirrored_drawing_is_far_and_the_nearest_example_counts() {
        // An "L" and its mirror image about the vertical axis through its centre.
        let l = [
            line([0.0, 0.04], [0.0, 0.0], 9),
            line([0.0, 0.0], [0.04, 0.0], 9),
        ];
        let m = [
            line([0.04, 0.04], [0.04, 0.0], 9),
            line([0.04, 0.0], [0.0, 0.0], 9),
        ];
        let l = Ink::of_path(&path(&[&l[0], &l[1]])).unwrap();
        let m = Ink::of_path(&path(&[&m[0], &m[1]])).unwrap();
        assert!((distance(&m, &l, 1.0) - 0.04).abs() < 1e-6);
        assert_eq!(score(&m, &[l.clone(), m.clone()], 1.0), Some(0.0));
        assert_eq!(score(&m, &[], 1.0), None);
    }

    #[test]
    fn no_ink_and_not_a_number_are_told_apart() {
        assert_eq!(Ink::of_path(&[[0.0, 0.0, 0.0]; 4]), None);
        let a = Ink::of_path(&path(&[&line([0.0, 0.0], [0.04, 0.0], 3)])).unwrap();
        let bad = Ink::of_path(&[[f32::NAN, 0.0, 1.0], [0.01, 0.0, 1.0]]).unwrap();
        assert!(distance(&a, &bad, 0.9).is_nan());
        assert!(score(&a, &[a.clone(), bad], 0.9).unwrap().is_nan());
    }

    #[test]
    fn centring_moves_the_box_to_the_origin() {
        let a = Ink::of_path(&path(&[&line([0.5, 0.2], [0.54, 0.22], 5)])).unwrap();
        let c = a.centred();
        assert!((c.points()[0][0] + 0.02).abs() < 1e-6);
        assert!((c.points()[4][1] - 0.01).abs() < 1e-6);
    }
}
