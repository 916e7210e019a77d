//! Euclidean distances between embeddings, and of a query to every prototype of a bank
//! (SIMD, runtime dispatch).

use super::ClassBank;

/// Accumulators of [`distance`]: independent partial sums, so the sum vectorises.
const DISTANCE_LANES: usize = 16;

/// Euclidean distance between two embeddings of equal length (pairs up to the shorter).
/// Squares are summed in [`DISTANCE_LANES`] interleaved partial sums (element `i` into sum
/// `i % 16`), combined in a fixed order: deterministic, and vectorised by the compiler
/// (one running sum would be a chain of 128 dependent additions).
#[inline(always)]
pub fn distance(a: &[f32], b: &[f32]) -> f32 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f32; DISTANCE_LANES];
    let (ac, bc) = (
        a.chunks_exact(DISTANCE_LANES),
        b.chunks_exact(DISTANCE_LANES),
    );
    let (ar, br) = (ac.remainder(), bc.remainder());
    for (x, y) in ac.zip(bc) {
        for l in 0..DISTANCE_LANES {
            let d = x[l] - y[l];
            acc[l] += d * d;
        }
    }
    for (l, (x, y)) in ar.iter().zip(br).enumerate() {
        let d = x - y;
        acc[l] += d * d;
    }
    // Pairwise combination: 16 -> 8 -> 4 -> 2 -> 1.
    let mut width = DISTANCE_LANES;
    while width > 1 {
        width /= 2;
        for l in 0..width {
            acc[l] += acc[l + width];
        }
    }
    acc[0].sqrt()
}

/// The distance of `query` to every class prototype, in name order, compiled for the widest
/// SIMD instruction set this CPU has (runtime dispatch; the sums are the same on every
/// instruction set, see [`distance`]).
pub(super) struct Distances<'a, 'b> {
    pub(super) bank: &'a ClassBank,
    pub(super) query: &'b [f32],
    pub(super) out: &'b mut Vec<(f32, &'a str)>,
}

impl pulp::WithSimd for Distances<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        for (n, c) in &self.bank.classes {
            self.out
                .push((distance(self.query, &c.prototype), n.as_str()));
        }
    }
}
