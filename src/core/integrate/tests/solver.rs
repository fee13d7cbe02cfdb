//! The masked solver: preconditioned CG against the DCT solve, its convergence on a disc
//! and a ragged mask, warm starts and halting.

use ndarray::Array2;

use super::surfaces::*;
use crate::core::integrate::components::Components;
use crate::core::integrate::multigrid::MaskStencil;
use crate::core::integrate::*;
use crate::core::options::Integration;
use crate::core::progress::NEVER;

#[test]
fn masked_pcg_matches_dct_on_full_mask() {
    let (h, w) = (96, 130);
    let full = Array2::from_elem((h, w), true);
    let (p, q) = gradients(&normals_of(&gaussians, &full), &full);
    let m = vec![true; h * w];
    let st = MaskStencil::new(&m, h, w);
    let (ps, qs) = (p.as_slice().unwrap(), q.as_slice().unwrap());
    let b = poisson::rhs(&st, ps, qs);
    let comps = Components::new(&m, h, w);
    let mut direct = poisson::solve_dct(b.clone(), h, w);
    comps.remove_means(&mut direct);
    let mut bb = b;
    comps.remove_means(&mut bb);
    let (mut iter, stats) = poisson::solve_pcg(&st, bb, NEVER);
    comps.remove_means(&mut iter);
    let diff = direct
        .iter()
        .zip(&iter)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    eprintln!("PCG vs DCT on a full 96×130 mask: max |Δz| {diff:.2e} px, {stats:?}");
    assert!(stats.rel_residual <= poisson::TOL, "{stats:?}");
    assert!(stats.iterations <= 20, "{stats:?}");
    assert!(diff < 1e-3, "max diff {diff}");
}

/// The CG system of a hemisphere seen through a 256² disc mask: its stencil and its
/// right-hand side (zero mean on the one component).
fn disc_system() -> (MaskStencil, Vec<f32>) {
    let (n, rad) = (256, 100.0);
    let s = hemisphere(128.0, 120.0, rad);
    let mask = disc(n, n, 128.0, 120.0, 0.95 * rad);
    let (p, q) = gradients(&normals_of(&s, &mask), &mask);
    let m: Vec<bool> = mask.iter().copied().collect();
    let st = MaskStencil::new(&m, n, n);
    let comps = Components::new(&m, n, n);
    let mut b = poisson::rhs(&st, p.as_slice().unwrap(), q.as_slice().unwrap());
    comps.remove_means(&mut b);
    (st, b)
}

#[test]
fn pcg_converges_fast_on_disc() {
    let (st, b) = disc_system();
    let (_, stats) = poisson::solve_pcg(&st, b, NEVER);
    eprintln!("disc 256²: {stats:?}");
    assert!(stats.rel_residual <= poisson::TOL, "{stats:?}");
    assert!(stats.iterations <= 20, "{stats:?}");
}

#[test]
fn warm_started_pcg_meets_the_same_tolerance_in_fewer_iterations() {
    let (st, b) = disc_system();
    let (n, m) = (256, disc(256, 256, 128.0, 120.0, 95.0));
    let m: Vec<bool> = m.iter().copied().collect();
    let comps = Components::new(&m, n, n);
    let (mut cold, cold_stats) = poisson::solve_pcg(&st, b.clone(), NEVER);
    // From its own answer there is nothing left to do.
    let (same, stats) = poisson::solve_pcg_from(&st, b.clone(), cold.clone(), NEVER);
    assert_eq!(stats.iterations, 0, "{stats:?}");
    assert!(stats.rel_residual <= poisson::TOL, "{stats:?}");
    assert_eq!(same, cold);
    // From the answer plus a smooth 0.5 px error (what a re-weighting round leaves): the
    // same tolerance and heights, in fewer iterations than from 0.
    let start: Vec<f32> = (0..n * n)
        .map(|i| {
            let (r, c) = ((i / n) as f32, (i % n) as f32);
            let bump = 0.5 * (r / 20.0).sin() * (c / 30.0).cos();
            if m[i] { cold[i] + bump } else { 0.0 }
        })
        .collect();
    let (mut warm, stats) = poisson::solve_pcg_from(&st, b, start, NEVER);
    eprintln!("disc 256², cold {cold_stats:?}, warm {stats:?}");
    assert!(stats.rel_residual <= poisson::TOL, "{stats:?}");
    assert!(
        stats.iterations < cold_stats.iterations,
        "{stats:?} vs {cold_stats:?}"
    );
    comps.remove_means(&mut cold);
    comps.remove_means(&mut warm);
    let diff = (cold.iter().zip(&warm))
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    eprintln!("max |Δz| {diff:.2e} px");
    assert!(
        diff < 0.01,
        "warm and cold solves differ by up to {diff} px"
    );
}

#[test]
fn pcg_stops_as_soon_as_it_is_halted() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let (st, b) = disc_system();
    // Halted from the start: no iteration at all.
    let (z, stats) = poisson::solve_pcg(&st, b.clone(), &|| true);
    assert_eq!(stats.iterations, 0, "{stats:?}");
    assert!(z.iter().all(|&v| v == 0.0));
    // Halted at the third poll: two iterations, short of the tolerance a full solve meets.
    let polls = AtomicUsize::new(0);
    let (_, stats) = poisson::solve_pcg(&st, b, &|| polls.fetch_add(1, Ordering::SeqCst) >= 2);
    assert_eq!(stats.iterations, 2, "{stats:?}");
    assert!(stats.rel_residual > poisson::TOL, "{stats:?}");
}

/// A ragged mask (25% random holes: thin bridges, isolated pixels, ~90 components):
/// the solver must converge and satisfy the normal equations; heights on a ragged mask
/// of an integrable field are still exact per component.
#[test]
fn ragged_mask_converges() {
    let (h, w) = (150, 173);
    let mut seed = 12345u64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % 1000) as f64 / 1000.0
    };
    let mask = Array2::from_shape_fn((h, w), |_| rnd() < 0.75);
    let s = |x: f64, y: f64| {
        let (z, zx, zy) = gaussians(x * 0.8, y * 0.9);
        (z + 0.1 * x, 0.8 * zx + 0.1, 0.9 * zy)
    };
    let (p, q) = gradients(&normals_of(&s, &mask), &mask);
    let m: Vec<bool> = mask.iter().copied().collect();
    let comps = Components::new(&m, h, w);
    let st = MaskStencil::new(&m, h, w);
    let mut b = poisson::rhs(&st, p.as_slice().unwrap(), q.as_slice().unwrap());
    comps.remove_means(&mut b);
    let (z, stats) = poisson::solve_pcg(&st, b.clone(), NEVER);
    eprintln!("ragged mask: {} components, {stats:?}", comps.count());
    assert!(comps.count() > 50);
    assert!(stats.rel_residual <= poisson::TOL, "{stats:?}");
    assert!(stats.iterations <= 40, "{stats:?}");
    // True residual of the normal equations (its floor is set by storing z in f32).
    let mut az = vec![0f32; h * w];
    multigrid::apply(&st, &z, &mut az);
    let num: f64 = az
        .iter()
        .zip(&b)
        .map(|(&a, &b)| f64::from(a - b).powi(2))
        .sum();
    let den: f64 = b.iter().map(|&b| f64::from(b).powi(2)).sum();
    let true_rel = (num / den).sqrt();
    // The recurrence's residual must be the true one (to within f32 storage of z).
    assert!(true_rel < 2.0 * poisson::TOL, "true residual {true_rel}");
    // Heights match the surface up to one constant per component.
    let truth = heights_of(&s, h, w);
    let mut err: Vec<f32> = (0..h * w)
        .map(|i| {
            if m[i] {
                z[i] - truth[(i / w, i % w)] as f32
            } else {
                0.0
            }
        })
        .collect();
    comps.remove_means(&mut err);
    let n = m.iter().filter(|&&v| v).count() as f64;
    let e = (err.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>() / n).sqrt();
    eprintln!("ragged mask: true relative residual {true_rel:.1e}, depth rms {e:.4} px");
    assert!(e < 0.05, "rms {e}");
    let zi = integrate(&p, &q, &mask, Integration::Poisson);
    assert!(zi.iter().all(|v| v.is_finite()));
}
