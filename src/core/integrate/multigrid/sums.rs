//! Reductions in f64 whose result does not depend on how rayon split the work, so that
//! heights (and so artifacts) are the same from run to run.

use rayon::prelude::*;

/// The sum of `parts` added in index order. Rayon's `sum` adds in an order that depends
/// on how the work was split and stolen, and f64 addition is not associative: heights
/// (and so artifacts) could then differ in their last bits from run to run.
pub(crate) fn ordered_sum(parts: impl IndexedParallelIterator<Item = f64>) -> f64 {
    let parts: Vec<f64> = parts.collect();
    parts.iter().sum()
}

/// `Σ a_i b_i` in f64 with independent partial sums (so it pipelines / vectorises).
#[inline(always)]
pub(crate) fn dot_f64(a: &[f32], b: &[f32]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(&x, &y)| f64::from(x) * f64::from(y))
        .sum();
    for (x, y) in ca.zip(cb) {
        for j in 0..8 {
            acc[j] += f64::from(x[j]) * f64::from(y[j]);
        }
    }
    acc.iter().sum::<f64>() + tail
}
