//! `robust-poisson`'s re-weighting: it stops once the heights settle, its row-by-row
//! slopes, weights and re-weighted residual match the formed system, and the τ sample's
//! rows.

use ndarray::Array2;

use super::surfaces::*;
use crate::core::arrays::contiguous;
use crate::core::integrate::components::Components;
use crate::core::integrate::methods::poisson_heights;
use crate::core::integrate::multigrid::WeightStencil;
use crate::core::integrate::poisson::largest_change;
use crate::core::integrate::robust_poisson::{Edges, IRLS_ROUNDS, SETTLED, cauchy_weight, irls};
use crate::core::integrate::*;
use crate::core::progress::NEVER;

#[test]
fn robust_poisson_stops_re_weighting_once_heights_settle() {
    let (n, rad) = (128, 40.0);
    let s = hemisphere(63.5, 63.5, rad);
    let mask = disc(n, n, 63.5, 63.5, 0.95 * rad);
    let (p, mut q) = gradients(&normals_of(&s, &mask), &mask);
    let m = contiguous(mask.view());
    let solve = |p: &Array2<f32>, q: &Array2<f32>, settled: f32| {
        let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
        irls(&ps, &qs, &m, n, n, None, settled, NEVER)
    };
    // A smooth surface: the first rounds settle it, and stopping there leaves the heights
    // of all rounds to within the bound.
    let (early, rounds) = solve(&p, &q, SETTLED);
    let (all, every) = solve(&p, &q, -1.0);
    assert_eq!(every, IRLS_ROUNDS);
    assert!(
        rounds < IRLS_ROUNDS,
        "smooth surface ran all {rounds} rounds"
    );
    let apart = largest_change(&early, &all, &m);
    eprintln!("hemisphere: stopped after {rounds} rounds, {apart:.5} px from all rounds");
    assert!(apart <= SETTLED, "{apart} px from running every round");

    // A band of wrong normals (a ridge the gradients invent): its edges are let go round
    // after round, and the heights keep moving, so every round runs.
    for r in 50..78 {
        for c in 60..64 {
            q[[r, c]] += 3.0;
        }
    }
    let (_, rounds) = solve(&p, &q, SETTLED);
    assert_eq!(rounds, IRLS_ROUNDS, "a surface still moving stopped early");
}

#[test]
fn edge_slopes_weights_and_the_re_weighted_residual_match_the_formed_system() {
    use self::poisson::{edge_slope, finite};
    let (n, rad) = (96, 30.0);
    let s = hemisphere(47.5, 47.5, rad);
    let mask = disc(n, n, 47.5, 47.5, 0.95 * rad);
    let (p, mut q) = gradients(&normals_of(&s, &mask), &mask);
    // Wrong normals along a band, so that the Cauchy weights vary across the mask.
    for r in 30..60 {
        q[[r, 45]] += 2.0;
    }
    let m = contiguous(mask.view()).into_owned();
    let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
    let (bx, by) = multigrid::edge_weights(&m, None, n, n, MIN_EDGE_WEIGHT);
    let slopes = |base: &[f32], step: usize, k: usize| -> Vec<f32> {
        (0..n * n)
            .map(|i| {
                let g = |i: usize| [finite(ps[i]), finite(qs[i])];
                if base[i] > 0.0 {
                    edge_slope(g(i), g(i + step), k)
                } else {
                    0.0
                }
            })
            .collect()
    };
    let (gx, gy) = (slopes(&bx, 1, 0), slopes(&by, n, 1));
    // Row by row, each pixel's weight formed once: the same bits as edge by edge.
    let mut rows = poisson::EdgeSlopes::new(n);
    for r in 0..n {
        let i = r * n;
        rows.load(&ps, &qs, &bx[i..i + n], &by[i..i + n], r);
        assert!((gx[i..i + n].iter().zip(&rows.east)).all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!((gy[i..i + n].iter().zip(&rows.south)).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
    let comps = Components::new(&m, n, n);
    let z = poisson_heights(&ps, &qs, &m, n, n, None, NEVER);
    let edges = Edges {
        mask: &m,
        weights: None,
        p: &ps,
        q: &qs,
        w: n,
    };
    for tau in [0.05f32, 0.3, 1e6] {
        // The system formed as a re-weighting round forms it, and its residual at z.
        let weights = |base: &[f32], g: &[f32], step: usize| -> Vec<f32> {
            (0..n * n)
                .map(|i| {
                    if base[i] > 0.0 {
                        cauchy_weight(base[i], z[i + step] - z[i] - g[i], tau)
                    } else {
                        0.0
                    }
                })
                .collect()
        };
        let (wx, wy) = (weights(&bx, &gx, 1), weights(&by, &gy, n));
        let (rx, ry) = edges.reweighted(&z, tau);
        assert!((wx.iter().zip(&rx)).all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!((wy.iter().zip(&ry)).all(|(a, b)| a.to_bits() == b.to_bits()));
        let st = WeightStencil::new(n, n, wx, wy);
        let mut b = poisson::rhs(&st, &ps, &qs);
        comps.remove_means(&mut b);
        let mut az = vec![0f32; n * n];
        multigrid::apply(&st, &z, &mut az);
        let norm = |v: &mut dyn Iterator<Item = f32>| v.map(|x| f64::from(x).powi(2)).sum::<f64>();
        let formed = (norm(&mut b.iter().zip(&az).map(|(b, a)| b - a))
            / norm(&mut b.iter().copied()))
        .sqrt();
        let summed = edges.reweighted_rel_residual(&z, tau);
        eprintln!("τ {tau}: formed {formed:.3e}, summed {summed:.3e}");
        assert!(
            (formed - summed).abs() <= 1e-3 * formed.max(1e-6),
            "τ {tau}: formed {formed:e}, summed {summed:e}"
        );
    }
}

#[test]
fn tau_sample_takes_every_edge_of_every_stride_th_row() {
    use self::poisson::{edge_slope, finite};
    let (n, rad) = (40, 14.0);
    let s = hemisphere(19.5, 19.5, rad);
    let mask = disc(n, n, 19.5, 19.5, 0.95 * rad);
    let (p, mut q) = gradients(&normals_of(&s, &mask), &mask);
    // Residuals that differ row by row, so that taking the wrong rows moves the median.
    for r in 0..n {
        for c in 0..n {
            q[[r, c]] += 0.01 * r as f32;
        }
    }
    let m = contiguous(mask.view()).into_owned();
    let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
    let (bx, by) = multigrid::edge_weights(&m, None, n, n, MIN_EDGE_WEIGHT);
    let z = poisson_heights(&ps, &qs, &m, n, n, None, NEVER);
    let edges = Edges {
        mask: &m,
        weights: None,
        p: &ps,
        q: &qs,
        w: n,
    };
    let g = |i: usize| [finite(ps[i]), finite(qs[i])];
    for stride in [1, 3] {
        // Edge by edge, over rows 0, stride, 2 × stride, …
        let mut abs: Vec<f32> = Vec::new();
        for r in (0..n).step_by(stride) {
            for c in 0..n {
                let i = r * n + c;
                for (base, step, k) in [(&bx, 1, 0), (&by, n, 1)] {
                    if base[i] > 0.0 {
                        abs.push((z[i + step] - z[i] - edge_slope(g(i), g(i + step), k)).abs());
                    }
                }
            }
        }
        abs.sort_by(f32::total_cmp);
        let expected = abs[abs.len() / 2];
        let got = edges.median_abs_residual(&z, stride);
        assert_eq!(
            got.map(f32::to_bits),
            Some(expected.to_bits()),
            "stride {stride}"
        );
    }
}
