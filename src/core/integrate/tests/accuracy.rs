//! The integrators' accuracy against analytic surfaces (pixel units): full frame and
//! masked, each connected component its own constant, confidence weighting, and
//! degenerate inputs that must not panic.

use ndarray::{Array2, Array3};

use super::surfaces::*;
use crate::core::integrate::components::Components;
use crate::core::integrate::multigrid::WeightStencil;
use crate::core::integrate::*;
use crate::core::options::Integration;
use crate::core::progress::NEVER;

#[test]
fn full_frame_smooth_surface_accuracy() {
    let full = Array2::from_elem((128, 128), true);
    let (_, poisson) = run(&gaussians, &full, Integration::Poisson);
    let (_, path) = run(&gaussians, &full, Integration::Path);
    let (_, fc) = run(&periodic, &full, Integration::FrankotChellappa);
    let (_, fc_gauss) = run(&gaussians, &full, Integration::FrankotChellappa);
    eprintln!(
        "full 128²: poisson(DCT) {poisson:.5} px, FC periodic {fc:.5} px, \
         FC gaussians {fc_gauss:.5} px, path {path:.5} px"
    );
    assert!(poisson < 0.05, "poisson rms {poisson}");
    assert!(fc < 0.05, "FC rms {fc}");
    assert!(path.is_finite() && path > poisson);
}

#[test]
fn hemisphere_poisson_beats_frankot_chellappa() {
    let (n, rad) = (128, 40.0);
    let s = hemisphere(63.5, 63.5, rad);
    let mask = disc(n, n, 63.5, 63.5, 0.95 * rad);
    let (z, poisson) = run(&s, &mask, Integration::Poisson);
    let (_, fc) = run(&s, &mask, Integration::FrankotChellappa);
    let (_, path) = run(&s, &mask, Integration::Path);
    eprintln!(
        "hemisphere r=40 mask 0.95r: poisson {poisson:.4} px, FC {fc:.4} px, path {path:.4} px"
    );
    assert!(poisson < 0.5, "poisson rms {poisson}");
    assert!(poisson < fc, "poisson {poisson} vs FC {fc}");
    // Background is the lowest height on the mask.
    let low = z
        .iter()
        .zip(&mask)
        .filter(|&(_, &m)| m)
        .map(|(&v, _)| v)
        .fold(f32::INFINITY, f32::min);
    assert_eq!(z[(0, 0)], low);
}

#[test]
fn disjoint_components_get_their_own_constants() {
    let (h, w) = (100, 140);
    let a = hemisphere(35.0, 50.0, 30.0);
    let b = |x: f64, y: f64| {
        let (z, zx, zy) = gaussians(x, y);
        (z + 0.3 * x - 0.2 * y + 40.0, zx + 0.3, zy - 0.2)
    };
    let ma = disc(h, w, 35.0, 50.0, 27.0);
    let mb = Array2::from_shape_fn((h, w), |(r, c)| {
        (75..130).contains(&c) && (20..85).contains(&r)
    });
    let mask = &ma | &mb;
    let s = move |x: f64, y: f64| if x < 70.0 { a(x, y) } else { b(x, y) };
    let (p, q) = gradients(&normals_of(&s, &mask), &mask);
    let m: Vec<bool> = mask.iter().copied().collect();
    assert_eq!(Components::new(&m, h, w).count(), 2);
    let z = integrate(&p, &q, &mask, Integration::Poisson);
    let truth = heights_of(&s, h, w);
    let (ea, eb) = (rms(&z, &truth, &ma), rms(&z, &truth, &mb));
    eprintln!("two components: rms {ea:.4} px (hemisphere), {eb:.4} px (tilted bumps)");
    assert!(ea < 0.5 && eb < 0.1, "{ea} {eb}");
    // Each component has zero mean, so the 40 px offset of the second one is not recovered.
    for region in [&ma, &mb] {
        let (s, n) = z
            .iter()
            .zip(region)
            .filter(|&(_, &m)| m)
            .fold((0.0f64, 0usize), |(s, n), (&v, _)| {
                (s + f64::from(v), n + 1)
            });
        assert!((s / n as f64).abs() < 1e-3);
    }
}

#[test]
fn degenerate_inputs_do_not_panic() {
    let all = [
        Integration::Path,
        Integration::FrankotChellappa,
        Integration::Poisson,
    ];
    for (h, w) in [
        (0, 0),
        (0, 5),
        (1, 1),
        (1, 17),
        (23, 1),
        (1, 700),
        (600, 1),
        (2, 2),
    ] {
        let p = Array2::from_elem((h, w), 0.5f32);
        let q = Array2::from_elem((h, w), -0.25f32);
        for fill in [false, true] {
            let mask = Array2::from_elem((h, w), fill);
            for m in all {
                let z = integrate(&p, &q, &mask, m);
                assert_eq!(z.dim(), (h, w));
                assert!(z.iter().all(|v| v.is_finite()), "{h}×{w} {m:?}");
                if !fill {
                    assert!(z.iter().all(|&v| v == 0.0));
                }
            }
            let wt = Array2::from_elem((h, w), 1.0f32);
            let z = integrate_weighted(&p, &q, &mask, &wt);
            assert!(z.iter().all(|v| v.is_finite()));
            let _ = curl(&p, &q, &mask);
            let _ = gradients(&Array3::zeros((h, w, 3)), &mask);
        }
    }
    // A 1×N ramp is recovered exactly by poisson (masked and full).
    let p = Array2::from_elem((1, 700), 0.5f32);
    let q = Array2::zeros((1, 700));
    for mask in [
        Array2::from_elem((1, 700), true),
        Array2::from_shape_fn((1, 700), |(_, c)| c != 300),
    ] {
        let z = integrate(&p, &q, &mask, Integration::Poisson);
        assert!((z[(0, 699)] - z[(0, 301)] - 0.5 * 398.0).abs() < 1e-2);
        assert!((z[(0, 299)] - z[(0, 0)] - 0.5 * 299.0).abs() < 1e-2);
    }
}

#[test]
fn weighted_poisson_matches_and_down_weights() {
    let (n, rad) = (128, 40.0);
    let s = hemisphere(63.5, 63.5, rad);
    let mask = disc(n, n, 63.5, 63.5, 0.95 * rad);
    let truth = heights_of(&s, n, n);
    let (p, q) = gradients(&normals_of(&s, &mask), &mask);
    let ones = Array2::from_elem((n, n), 1.0f32);
    let zw = integrate_weighted(&p, &q, &mask, &ones);
    let zp = integrate(&p, &q, &mask, Integration::Poisson);
    let diff = zw
        .iter()
        .zip(&zp)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(diff < 1e-3, "uniform weights vs poisson {diff}");

    // Corrupt a patch of gradients; giving it low confidence must reduce the error.
    let (mut pc, mut qc) = (p.clone(), q.clone());
    let mut conf = ones.clone();
    for r in 50..62 {
        for c in 55..70 {
            pc[(r, c)] += 1.5;
            qc[(r, c)] -= 1.0;
            conf[(r, c)] = 0.0;
        }
    }
    let plain = rms(
        &integrate(&pc, &qc, &mask, Integration::Poisson),
        &truth,
        &mask,
    );
    let weighted = rms(&integrate_weighted(&pc, &qc, &mask, &conf), &truth, &mask);
    // The solver itself, with the 1e-3-floored edges of the zero-confidence patch.
    let m: Vec<bool> = mask.iter().copied().collect();
    let st = WeightStencil::from_pixel_weights(&m, conf.as_slice().unwrap(), n, n, MIN_EDGE_WEIGHT);
    let mut b = poisson::rhs(&st, pc.as_slice().unwrap(), qc.as_slice().unwrap());
    Components::new(&m, n, n).remove_means(&mut b);
    let (_, stats) = poisson::solve_pcg(&st, b, NEVER);
    eprintln!("corrupted patch: poisson {plain:.3} px, weighted {weighted:.3} px; {stats:?}");
    assert!(weighted < 0.5 * plain, "{weighted} vs {plain}");
    assert!(stats.rel_residual <= poisson::TOL, "{stats:?}");
}
