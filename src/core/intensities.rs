//! Unknown light intensities from the object itself (semi-calibrated photometric stereo,
//! after Cho et al., "Semi-calibrated photometric stereo", 2016), linear and in one step.
//!
//! Each pixel says `I_k x_k = b · l̂_k` for its kept observations, with `x_k = 1/e_k` the
//! inverse intensities, `l̂_k` the unit-intensity light vectors and `b = ρ n`. Eliminating
//! `b` by least squares leaves `P D x = 0`, with `D = diag(I)` and `P` the projector onto
//! the complement of the pixel's light matrix; over all pixels, `x` is the eigenvector of
//! `M = Σ D P D` with the smallest eigenvalue (up to scale: intensities and albedo share
//! one). Near lights give every pixel its own `l̂`, which the sum takes as it comes.
//!
//! The object must show normals of enough kinds: every pixel of a plane says the same,
//! and leaves a smallest eigenvalue that is not alone (several intensity sets explain it
//! equally); the intensities are then refused rather than guessed.

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::core::lambert::invert3;

/// The second-smallest eigenvalue of `M` must be at least this many times the smallest
/// for the smallest one's eigenvector to be the answer: noise lifts both alike, an object
/// that identifies the intensities lifts only the second.
const MIN_GAP: f64 = 2.0;
/// [`Gram::sum_in_runs`] splits its items into at most this many runs: a bound on the
/// sums held at once (`k²` each) and runs enough for the threads.
const RUNS: usize = 32;

/// One light's estimated intensity, as reports list it.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Estimated {
    pub name: String,
    pub intensity: f64,
}

/// `M = Σ D P D` over the pixels added, `k × k`, row-major.
#[derive(Debug, Clone)]
pub struct Gram {
    k: usize,
    m: Vec<f64>,
}

impl Gram {
    pub fn new(k: usize) -> Self {
        Self {
            k,
            m: vec![0.0; k * k],
        }
    }

    /// The Gram of items `0..len`, `add_run` adding a run of them to a Gram of its own:
    /// the runs are fixed by `len` alone and summed in order, so the sums (and what is
    /// estimated from them) are the same to the bit however many threads run.
    pub fn sum_in_runs<F>(k: usize, len: usize, add_run: F) -> Self
    where
        F: Fn(Range<usize>, &mut Gram) + Sync,
    {
        let run = len.div_ceil(RUNS).max(1);
        let runs: Vec<Gram> = (0..len.div_ceil(run))
            .into_par_iter()
            .map(|i| {
                let mut gram = Gram::new(k);
                add_run(i * run..((i + 1) * run).min(len), &mut gram);
                gram
            })
            .collect();
        runs.into_iter().fold(Gram::new(k), Gram::merge)
    }

    /// One pixel: its unit-intensity light vectors, observations and which it keeps.
    pub fn add(&mut self, lights: &[[f32; 3]], obs: &[f32], keep: &[bool]) {
        let kept: Vec<usize> = (0..self.k).filter(|&i| keep[i]).collect();
        // Three observations fit any b exactly: no information on the intensities.
        if kept.len() < 4 {
            return;
        }
        let a: Vec<[f64; 3]> = kept.iter().map(|&i| lights[i].map(f64::from)).collect();
        let mut ata = [[0f64; 3]; 3];
        for r in &a {
            for i in 0..3 {
                for j in 0..3 {
                    ata[i][j] += r[i] * r[j];
                }
            }
        }
        let Some(g) = invert3(&ata) else { return };
        let ga: Vec<[f64; 3]> = (a.iter())
            .map(|r| [0, 1, 2].map(|i| (0..3).map(|j| g[i][j] * r[j]).sum()))
            .collect();
        for (s, &i) in kept.iter().enumerate() {
            for (t, &j) in kept.iter().enumerate() {
                let proj = f64::from(u8::from(s == t))
                    - (a[s][0] * ga[t][0] + a[s][1] * ga[t][1] + a[s][2] * ga[t][2]);
                self.m[i * self.k + j] += f64::from(obs[i]) * f64::from(obs[j]) * proj;
            }
        }
    }

    pub fn merge(mut self, other: Gram) -> Gram {
        for (a, b) in self.m.iter_mut().zip(other.m) {
            *a += b;
        }
        self
    }

    /// The intensities (mean 1) of the smallest eigenvector, by inverse iteration from
    /// `start`; None when it is not of one sign (some light never explained), when `M` is
    /// empty, or when the object does not tell the intensities apart ([`MIN_GAP`]).
    pub fn intensities(&self, start: &[f64]) -> Option<Vec<f64>> {
        let k = self.k;
        let trace: f64 = (0..k).map(|i| self.m[i * k + i]).sum();
        if trace <= 0.0 {
            return None;
        }
        let x = self.smallest(&self.m, trace, start.iter().map(|e| 1.0 / e).collect())?;
        // The next eigenvalue: the smallest once x's is lifted past every other.
        let mut deflated = self.m.clone();
        for i in 0..k {
            for j in 0..k {
                deflated[i * k + j] += trace * x[i] * x[j];
            }
        }
        let ones = vec![1.0; k];
        let y = self.smallest(&deflated, trace, ones)?;
        if self.rayleigh(&self.m, &y) < MIN_GAP * self.rayleigh(&self.m, &x) {
            return None;
        }
        let sign = x.iter().sum::<f64>().signum();
        if x.iter().any(|v| v * sign <= 0.0) {
            return None;
        }
        let e: Vec<f64> = x.iter().map(|v| 1.0 / (v * sign)).collect();
        let mean = e.iter().sum::<f64>() / k as f64;
        Some(e.iter().map(|v| v / mean).collect())
    }

    /// The unit eigenvector of `m` (`k × k`, trace `trace`) with the smallest eigenvalue,
    /// by inverse iteration from `x`.
    fn smallest(&self, m: &[f64], trace: f64, mut x: Vec<f64>) -> Option<Vec<f64>> {
        let k = self.k;
        let mut shifted = m.to_vec();
        for i in 0..k {
            shifted[i * k + i] += 1e-9 * trace / k as f64;
        }
        let chol = cholesky(&shifted, k)?;
        for _ in 0..50 {
            x = solve_cholesky(&chol, k, &x);
            let norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !(norm.is_finite() && norm > 0.0) {
                return None;
            }
            x.iter_mut().for_each(|v| *v /= norm);
        }
        Some(x)
    }

    /// `xᵀ m x` for a unit `x`.
    fn rayleigh(&self, m: &[f64], x: &[f64]) -> f64 {
        let k = self.k;
        (0..k)
            .map(|i| x[i] * (0..k).map(|j| m[i * k + j] * x[j]).sum::<f64>())
            .sum()
    }
}

/// Lower-triangular `L` with `L Lᵀ = a` (`k × k`, row-major); None if not positive definite.
fn cholesky(a: &[f64], k: usize) -> Option<Vec<f64>> {
    let mut l = vec![0f64; k * k];
    for i in 0..k {
        for j in 0..=i {
            let s: f64 = a[i * k + j] - (0..j).map(|p| l[i * k + p] * l[j * k + p]).sum::<f64>();
            if i == j {
                if s <= 0.0 {
                    return None;
                }
                l[i * k + i] = s.sqrt();
            } else {
                l[i * k + j] = s / l[j * k + j];
            }
        }
    }
    Some(l)
}

/// `x` with `L Lᵀ x = b`.
fn solve_cholesky(l: &[f64], k: usize, b: &[f64]) -> Vec<f64> {
    let mut y = vec![0f64; k];
    for i in 0..k {
        y[i] = (b[i] - (0..i).map(|p| l[i * k + p] * y[p]).sum::<f64>()) / l[i * k + i];
    }
    let mut x = vec![0f64; k];
    for i in (0..k).rev() {
        x[i] = (y[i] - (i + 1..k).map(|p| l[p * k + i] * x[p]).sum::<f64>()) / l[i * k + i];
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Six unit directions around the view axis, 32° off it.
    fn six_lights() -> Vec<[f32; 3]> {
        (0..6)
            .map(|k| {
                let a = k as f32;
                let v = [0.5 * a.cos(), 0.5 * a.sin(), 0.8];
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                v.map(|c| c / n)
            })
            .collect()
    }

    /// The sum over many pixels is the same to the bit on one thread and on four: the
    /// runs, not the threads' stealing, decide the order of the additions.
    #[test]
    fn the_sum_in_runs_does_not_depend_on_the_threads() {
        let dirs = six_lights();
        let pixel = |i: usize| {
            let (u, v) = (
                (i % 97) as f32 / 130.0 - 0.37,
                (i / 97) as f32 / 130.0 - 0.37,
            );
            let n = [u, v, (1.0 - u * u - v * v).sqrt()];
            let obs: Vec<f32> = (dirs.iter().enumerate())
                .map(|(k, l)| (0.6 + 0.01 * k as f32) * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]))
                .collect();
            obs
        };
        let sum = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                Gram::sum_in_runs(6, 97 * 97, |run, gram| {
                    for i in run {
                        gram.add(&dirs, &pixel(i), &[true; 6]);
                    }
                })
            })
        };
        let (one, four) = (sum(1), sum(4));
        let bits = |g: &Gram| g.m.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&one), bits(&four));
        assert!(one.m.iter().any(|&v| v != 0.0));
    }

    /// Six distant lights of different brightness over a hemisphere of normals: the
    /// intensities come back exactly (up to their mean).
    #[test]
    fn intensities_of_a_noiseless_sphere() {
        let dirs = six_lights();
        let e = [1.0, 1.2, 0.8, 0.9, 1.1, 1.0];
        let mut gram = Gram::new(6);
        for i in 0..400 {
            let (u, v) = ((i % 20) as f32 / 25.0 - 0.4, (i / 20) as f32 / 25.0 - 0.4);
            let n = [u, v, (1.0 - u * u - v * v).sqrt()];
            let obs: Vec<f32> = (dirs.iter().zip(e))
                .map(|(l, e)| e as f32 * 0.7 * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]))
                .collect();
            gram.add(&dirs, &obs, &[true; 6]);
        }
        let got = gram.intensities(&[1.0; 6]).unwrap();
        let mean = e.iter().sum::<f64>() / 6.0;
        for (g, e) in got.iter().zip(e) {
            assert!((g - e / mean).abs() < 1e-4, "{got:?}");
        }
    }

    /// A tilted plane (one normal everywhere) with a little noise says nothing about the
    /// intensities: refused, not guessed.
    #[test]
    fn a_plane_does_not_identify_the_intensities() {
        let dirs = six_lights();
        let n = [0.1f32, -0.2, 0.97];
        let mut gram = Gram::new(6);
        for i in 0..400 {
            let obs: Vec<f32> = (dirs.iter().enumerate())
                .map(|(k, l)| {
                    let noise = 1e-3 * (((i * 7 + k * 13) % 17) as f32 / 8.0 - 1.0);
                    0.7 * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]) + noise
                })
                .collect();
            gram.add(&dirs, &obs, &[true; 6]);
        }
        assert!(gram.intensities(&[1.0; 6]).is_none());
    }
}
