//! Parallel histograms, and exact order statistics of non-negative floats built on them.
//!
//! For non-negative `f32` (and NaN with its sign bit clear, which sorts last, as in
//! `f32::total_cmp`) the order of the bit patterns is the order of the values. So two
//! histogram passes — over the high 16 bits, then over the low 16 bits within the bin that
//! holds the wanted rank — find the element of any rank exactly, without copying or sorting
//! the millions of values of a 2048² map (the auto mask's albedo percentile, the robust
//! integration's median residual).

use rayon::prelude::*;

/// Items per rayon task.
const CHUNK: usize = 1 << 16;

/// Counts of `key(i)` over `i < len` (keys below `bins`; `None` skips an item), in parallel.
pub(crate) fn histogram(
    len: usize,
    bins: usize,
    key: impl Fn(usize) -> Option<usize> + Sync,
) -> Vec<u64> {
    (0..len.div_ceil(CHUNK))
        .into_par_iter()
        .fold(
            || vec![0u64; bins],
            |mut h, chunk| {
                for i in chunk * CHUNK..len.min((chunk + 1) * CHUNK) {
                    if let Some(k) = key(i) {
                        h[k] += 1;
                    }
                }
                h
            },
        )
        .reduce(
            || vec![0u64; bins],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
                a
            },
        )
}

/// Of the values `value(i)`, `i < len`, that are `Some` (each ≥ +0), the one of 0-based
/// rank `rank(count)` in ascending order, `count` being how many there are; `None` when
/// there are none.
pub(crate) fn nth_nonnegative(
    len: usize,
    value: impl Fn(usize) -> Option<f32> + Sync,
    rank: impl FnOnce(u64) -> u64,
) -> Option<f32> {
    let bits = |i: usize| {
        value(i).map(|v| {
            debug_assert!(v.is_sign_positive(), "{v} is negative");
            v.to_bits()
        })
    };
    let high = histogram(len, 1 << 16, |i| bits(i).map(|b| (b >> 16) as usize));
    let count: u64 = high.iter().sum();
    if count == 0 {
        return None;
    }
    let mut rank = rank(count);
    assert!(rank < count, "rank {rank} of {count} values");
    let (bin, below) = select_bin(&high, rank);
    rank -= below;
    let low = histogram(len, 1 << 16, |i| {
        bits(i)
            .filter(|b| (b >> 16) as usize == bin)
            .map(|b| (b & 0xffff) as usize)
    });
    let (lo, _) = select_bin(&low, rank);
    Some(f32::from_bits(((bin as u32) << 16) | lo as u32))
}

/// The bin holding the element of 0-based `rank`, and how many elements lie below it.
fn select_bin(hist: &[u64], rank: u64) -> (usize, u64) {
    let mut below = 0;
    for (i, &h) in hist.iter().enumerate() {
        if below + h > rank {
            return (i, below);
        }
        below += h;
    }
    unreachable!("rank {rank} is below the histogram's total")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_rank_is_the_sorted_one() {
        // Deterministic pseudo-random values with ties, zeros, +∞ and NaN; some skipped.
        let mut x = 0x9e37_79b9_u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        let special = [0.0, f32::INFINITY, f32::NAN, 1e-40, 0.5, 0.5];
        for len in [1, 2, 9, 1000, 150_000] {
            let values: Vec<Option<f32>> = (0..len)
                .map(|i| match next() % 8 {
                    0 => None,
                    1 => Some(special[i % special.len()]),
                    _ => Some((next() % 50_000) as f32 / 3_000.0),
                })
                .collect();
            let mut sorted: Vec<f32> = values.iter().flatten().copied().collect();
            sorted.sort_by(f32::total_cmp);
            let n = sorted.len() as u64;
            for rank in [0, n / 3, n / 2, n.saturating_sub(1)] {
                let got = nth_nonnegative(
                    len,
                    |i| values[i],
                    |count| {
                        assert_eq!(count, n);
                        rank
                    },
                );
                assert_eq!(
                    got.map(f32::to_bits),
                    sorted.get(rank as usize).map(|v| v.to_bits()),
                    "{len} values, rank {rank}"
                );
            }
        }
        assert_eq!(nth_nonnegative(5, |_| None, |_| 0), None);
    }
}
