//! Synthetic task classes: random characters of smooth strokes with curls, each drawn by
//! simulated drawers, in Omniglot motor coordinates, so that they go through the same path,
//! IK and preprocessing as the real drawings.
//!
//! A stroke is a turtle path: its heading turns by a curvature made of a few Gaussian bumps
//! along the stroke, so one strong bump draws a curl or a loop. Characters come in
//! **families**: a base character and variants that each change one bump of one stroke (its
//! sign flipped, its strength doubled, a new curl, or a bump removed), so a family's classes
//! differ in one loop or bend — the confusions of the worst leave-one-alphabet-out fold
//! (long single strokes that differ in one curl). A drawer changes every bump, the stroke
//! lengths, starts and headings a little, the whole character by a small random affine map,
//! sometimes the stroke order and sometimes a stroke's direction.

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

use crate::data::strokes::{Point, Stroke};

/// One curvature bump along a stroke.
#[derive(Debug, Clone, Copy)]
struct Bump {
    /// Peak curvature (rad per motor unit), signed.
    amp: f64,
    /// Where along the stroke, as a fraction of its length.
    at: f64,
    /// Width (motor units, standard deviation of the Gaussian).
    width: f64,
}

/// One stroke of a character, before a drawer draws it.
#[derive(Debug, Clone)]
struct StrokeSpec {
    start: [f64; 2],
    heading: f64,
    length: f64,
    bumps: Vec<Bump>,
}

/// A character: its strokes in their canonical order.
#[derive(Debug, Clone)]
struct CharSpec {
    strokes: Vec<StrokeSpec>,
}

fn normal(rng: &mut StdRng) -> f64 {
    // Box–Muller.
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn random_bump(rng: &mut StdRng, strong: bool) -> Bump {
    let width = rng.random_range(3.0..10.0);
    // The heading turned by the bump is amp * width * sqrt(2 pi): a strong bump turns it by
    // 1.2 to 2.2 turns of pi (a curl or a loop), a weak one by up to 0.6 pi (a bend).
    let turn = if strong {
        rng.random_range(1.2..2.2)
    } else {
        rng.random_range(0.15..0.6)
    } * std::f64::consts::PI;
    let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    Bump {
        amp: sign * turn / (width * (std::f64::consts::TAU).sqrt()),
        at: rng.random_range(0.1..0.9),
        width,
    }
}

fn random_character(rng: &mut StdRng) -> CharSpec {
    let n = match rng.random_range(0..100) {
        0..45 => 1,
        45..80 => 2,
        _ => 3,
    };
    let strokes = (0..n)
        .map(|i| {
            // The first stroke is long; the others are marks or bars.
            let length = if i == 0 {
                rng.random_range(60.0..180.0)
            } else {
                rng.random_range(12.0..70.0)
            };
            // About one bump per 30 units of length: long strokes bend and curl repeatedly.
            let most = 1 + (length / 30.0) as usize;
            let bumps = (0..rng.random_range(1..=most))
                .map(|_| {
                    let strong = rng.random_bool(if i == 0 { 0.4 } else { 0.15 });
                    random_bump(rng, strong)
                })
                .collect();
            StrokeSpec {
                start: [rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0)],
                heading: rng.random_range(0.0..std::f64::consts::TAU),
                length,
                bumps,
            }
        })
        .collect();
    CharSpec { strokes }
}

/// A variant of `base` that differs in one bump of one stroke.
fn variant(base: &CharSpec, rng: &mut StdRng) -> CharSpec {
    let mut c = base.clone();
    let s = &mut c.strokes[rng.random_range(0..base.strokes.len())];
    let k = rng.random_range(0..s.bumps.len());
    match rng.random_range(0..4) {
        0 => s.bumps[k].amp = -s.bumps[k].amp,
        1 => s.bumps[k].amp *= 2.0,
        2 if s.bumps.len() > 1 => {
            s.bumps.remove(k);
        }
        _ => s.bumps.push(random_bump(rng, true)),
    }
    c
}

/// The points of one stroke drawn by a drawer (`jitter` scales every perturbation).
fn draw_stroke(s: &StrokeSpec, jitter: f64, rng: &mut StdRng) -> Vec<[f64; 2]> {
    let length = s.length * (1.0 + 0.05 * jitter * normal(rng)).clamp(0.7, 1.3);
    let bumps: Vec<Bump> = s
        .bumps
        .iter()
        .map(|b| Bump {
            amp: b.amp * (1.0 + 0.06 * jitter * normal(rng)),
            at: (b.at + 0.025 * jitter * normal(rng)).clamp(0.0, 1.0),
            width: b.width * (1.0 + 0.06 * jitter * normal(rng)).clamp(0.6, 1.4),
        })
        .collect();
    let mut p = [
        s.start[0] + 2.0 * jitter * normal(rng),
        s.start[1] + 2.0 * jitter * normal(rng),
    ];
    let mut heading = s.heading + 0.08 * jitter * normal(rng);
    let steps = length.ceil().max(2.0) as usize;
    let ds = length / steps as f64;
    let mut out = Vec::with_capacity(steps + 1);
    out.push(p);
    for i in 0..steps {
        let at = (i as f64 + 0.5) * ds;
        let kappa: f64 = bumps
            .iter()
            .map(|b| {
                let z = (at - b.at * length) / b.width;
                b.amp * (-0.5 * z * z).exp()
            })
            .sum();
        heading += kappa * ds;
        p = [p[0] + heading.cos() * ds, p[1] + heading.sin() * ds];
        out.push(p);
    }
    out
}

/// One drawing of `c` by a simulated drawer: the strokes in Omniglot motor coordinates, the
/// character's longest side 40 to 75 units, centred near the canvas centre.
fn draw_character(c: &CharSpec, rng: &mut StdRng) -> Vec<Stroke> {
    let mut strokes: Vec<Vec<[f64; 2]>> =
        c.strokes.iter().map(|s| draw_stroke(s, 1.0, rng)).collect();
    // A small affine map of the whole character: rotation, shear, scales.
    let (rot, shear) = (0.08 * normal(rng), 0.08 * normal(rng));
    let (sx, sy) = (1.0 + 0.08 * normal(rng), 1.0 + 0.08 * normal(rng));
    let (cr, sr) = (rot.cos(), rot.sin());
    for q in strokes.iter_mut().flatten() {
        let (x, y) = (sx * (q[0] + shear * q[1]), sy * q[1]);
        *q = [cr * x - sr * y, sr * x + cr * y];
    }
    // Sometimes another stroke order, sometimes a stroke drawn the other way.
    if strokes.len() > 1 && rng.random_bool(0.25) {
        strokes.shuffle(rng);
    }
    for s in &mut strokes {
        if rng.random_bool(0.15) {
            s.reverse();
        }
    }
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for q in strokes.iter().flatten() {
        for a in 0..2 {
            lo[a] = lo[a].min(q[a]);
            hi[a] = hi[a].max(q[a]);
        }
    }
    let side = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-6);
    let scale = rng.random_range(40.0..75.0) / side;
    let centre = [
        52.5 + rng.random_range(-5.0..5.0),
        -52.5 + rng.random_range(-5.0..5.0),
    ];
    let mid = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
    let mut t = 0.0;
    strokes
        .iter()
        .map(|s| {
            s.iter()
                .map(|q| {
                    t += 10.0;
                    Point {
                        x: centre[0] + (q[0] - mid[0]) * scale,
                        y: centre[1] + (q[1] - mid[1]) * scale,
                        t,
                    }
                })
                .collect()
        })
        .collect()
}

/// What synthetic classes to make: `classes` classes in families of `family` (a base
/// character and `family - 1` one-bump variants), `drawers` drawings each, deterministic in
/// `seed`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Spec {
    /// Classes in all.
    pub classes: usize,
    /// Classes per family.
    pub family: usize,
    /// Drawings per class.
    pub drawers: usize,
    /// Seed of the characters and their drawers.
    pub seed: u64,
}

impl Spec {
    /// The drawings' strokes, per class, per drawer.
    pub fn draw(&self) -> Vec<Vec<Vec<Stroke>>> {
        let family = self.family.max(1);
        let mut out = Vec::with_capacity(self.classes);
        let mut f = 0u64;
        while out.len() < self.classes {
            let mut rng = StdRng::seed_from_u64(self.seed ^ f.wrapping_mul(0x9e37_79b9_7f4a_7c15));
            f += 1;
            let base = random_character(&mut rng);
            let mut members = vec![base.clone()];
            while members.len() < family {
                members.push(variant(&base, &mut rng));
            }
            for c in members.into_iter().take(self.classes - out.len()) {
                out.push(
                    (0..self.drawers)
                        .map(|_| draw_character(&c, &mut rng))
                        .collect(),
                );
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Classes come out as asked, deterministic in the seed, inside the Omniglot image, and
    /// two drawings of one class differ (drawers).
    #[test]
    fn synthetic_classes_are_deterministic_in_the_image_and_drawn_by_different_drawers() {
        let spec = Spec {
            classes: 9,
            family: 4,
            drawers: 5,
            seed: 3,
        };
        let (a, b) = (spec.draw(), spec.draw());
        assert_eq!(a.len(), 9);
        assert!(a.iter().all(|c| c.len() == 5));
        for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
            assert_eq!(x, y);
        }
        for s in a.iter().flatten().flatten().flatten() {
            assert!(
                (0.0..=105.0).contains(&s.x) && (-105.0..=0.0).contains(&s.y),
                "{s:?}"
            );
        }
        assert_ne!(a[0][0], a[0][1]);
        assert_ne!(Spec { seed: 4, ..spec }.draw()[0][0], a[0][0]);
    }
}
