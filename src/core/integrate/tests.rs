//! Accuracy tests against analytic surfaces (pixel units), plus edge cases and timings.

use super::*;
use ndarray::{Array2, Array3};
use std::time::Instant;

/// Analytic surface: height and its derivatives (dz/dx, dz/dy) at (x = col, y = row).
type Surface = dyn Fn(f64, f64) -> (f64, f64, f64);

/// Exact unit normals of `s` on an `h × w` grid (zero off the mask).
fn normals_of(s: &Surface, mask: &Array2<bool>) -> Array3<f32> {
    let (h, w) = mask.dim();
    let mut n = Array3::zeros((h, w, 3));
    for r in 0..h {
        for c in 0..w {
            if !mask[(r, c)] {
                continue;
            }
            let (_, zx, zy) = s(c as f64, r as f64);
            let len = (zx * zx + zy * zy + 1.0).sqrt();
            n[(r, c, 0)] = (-zx / len) as f32;
            n[(r, c, 1)] = (-zy / len) as f32;
            n[(r, c, 2)] = (1.0 / len) as f32;
        }
    }
    n
}

fn heights_of(s: &Surface, h: usize, w: usize) -> Array2<f64> {
    Array2::from_shape_fn((h, w), |(r, c)| s(c as f64, r as f64).0)
}

/// Depth RMS over `region` after removing the mean offset over `region`.
fn rms(z: &Array2<f32>, truth: &Array2<f64>, region: &Array2<bool>) -> f64 {
    let pts: Vec<f64> = z
        .iter()
        .zip(truth)
        .zip(region)
        .filter(|&(_, &m)| m)
        .map(|((&z, &t), _)| f64::from(z) - t)
        .collect();
    let mean = pts.iter().sum::<f64>() / pts.len() as f64;
    (pts.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / pts.len() as f64).sqrt()
}

fn gaussians(x: f64, y: f64) -> (f64, f64, f64) {
    let mut out = (0.0, 0.0, 0.0);
    for (a, cx, cy, s) in [
        (14.0, 50.0, 60.0, 15.0),
        (-8.0, 88.0, 40.0, 11.0),
        (6.0, 75.0, 95.0, 20.0),
    ] {
        let (dx, dy) = (x - cx, y - cy);
        let g = a * (-(dx * dx + dy * dy) / (2.0 * s * s)).exp();
        out.0 += g;
        out.1 += -g * dx / (s * s);
        out.2 += -g * dy / (s * s);
    }
    out
}

fn periodic(x: f64, y: f64) -> (f64, f64, f64) {
    use std::f64::consts::PI;
    let (kx, ky) = (2.0 * PI / 128.0, 4.0 * PI / 128.0);
    (
        12.0 * (kx * x).cos() * (ky * y).sin() + 5.0 * (kx * (x + y)).sin(),
        -12.0 * kx * (kx * x).sin() * (ky * y).sin() + 5.0 * kx * (kx * (x + y)).cos(),
        12.0 * ky * (kx * x).cos() * (ky * y).cos() + 5.0 * kx * (kx * (x + y)).cos(),
    )
}

fn disc(h: usize, w: usize, cx: f64, cy: f64, rad: f64) -> Array2<bool> {
    Array2::from_shape_fn((h, w), |(r, c)| {
        (c as f64 - cx).powi(2) + (r as f64 - cy).powi(2) < rad * rad
    })
}

fn hemisphere(cx: f64, cy: f64, rad: f64) -> impl Fn(f64, f64) -> (f64, f64, f64) {
    move |x, y| {
        let (dx, dy) = (x - cx, y - cy);
        let z = (rad * rad - dx * dx - dy * dy).max(1e-9).sqrt();
        (z, -dx / z, -dy / z)
    }
}

fn run(s: &Surface, mask: &Array2<bool>, method: Integration) -> (Array2<f32>, f64) {
    let (h, w) = mask.dim();
    let (p, q) = gradients(&normals_of(s, mask), mask);
    let z = integrate(&p, &q, mask, method);
    assert!(z.iter().all(|v| v.is_finite()));
    let e = rms(&z, &heights_of(s, h, w), mask);
    (z, e)
}

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
fn curl_is_zero_for_surfaces_and_two_for_rotation() {
    let full = Array2::from_elem((64, 64), true);
    let (p, q) = gradients(&normals_of(&gaussians, &full), &full);
    let c = curl(&p, &q, &full);
    let max = c.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(max < 1e-3, "curl of a surface {max}");

    // p = −y, q = x: dp/dy − dq/dx = −2 everywhere inside.
    let p = Array2::from_shape_fn((20, 30), |(r, _)| -(r as f32));
    let q = Array2::from_shape_fn((20, 30), |(_, c)| c as f32);
    let mask = Array2::from_elem((20, 30), true);
    let c = curl(&p, &q, &mask);
    for r in 0..19 {
        for col in 0..29 {
            assert!((c[(r, col)] + 2.0).abs() < 1e-5);
        }
    }
    assert_eq!(c[(19, 3)], 0.0);
    assert_eq!(c[(3, 29)], 0.0);
    // A neighbour off the mask → 0.
    let mut holey = mask.clone();
    holey[(5, 5)] = false;
    let c = curl(&p, &q, &holey);
    assert_eq!(c[(4, 4)], 0.0);
    assert_eq!(c[(5, 5)], 0.0);
    assert!((c[(6, 6)] + 2.0).abs() < 1e-5);
}

/// `curl` and `rhs` form each pixel's weight once; they must give exactly what
/// `edge_slope` per edge gives.
#[test]
fn curl_and_rhs_match_edge_slopes_bitwise() {
    use poisson::edge_slope;
    let (h, w) = (37, 53);
    let mut seed = 99u64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % 10_000) as f32 / 500.0 - 10.0
    };
    let p = Array2::from_shape_fn((h, w), |_| rnd());
    let q = Array2::from_shape_fn((h, w), |_| rnd());
    let mask = Array2::from_shape_fn((h, w), |(r, c)| (r * 7 + c * 3) % 11 != 0);
    let g = |r: usize, c: usize| [p[(r, c)], q[(r, c)]];
    let on = |r: usize, c: usize| r < h && c < w && mask[(r, c)];
    let got = curl(&p, &q, &mask);
    let m: Vec<bool> = mask.iter().copied().collect();
    let b = poisson::rhs(
        &MaskStencil::new(&m, h, w),
        p.as_slice().unwrap(),
        q.as_slice().unwrap(),
    );
    for r in 0..h {
        for c in 0..w {
            let inside = on(r, c) && on(r, c + 1) && on(r + 1, c) && on(r + 1, c + 1);
            let want = if inside {
                let dpy = edge_slope(g(r + 1, c), g(r + 1, c + 1), 0)
                    - edge_slope(g(r, c), g(r, c + 1), 0);
                let dqx = edge_slope(g(r, c + 1), g(r + 1, c + 1), 1)
                    - edge_slope(g(r, c), g(r + 1, c), 1);
                dpy - dqx
            } else {
                0.0
            };
            assert_eq!(got[(r, c)].to_bits(), want.to_bits(), "curl at ({r}, {c})");
            // Edges into (r, c) minus edges out of it, each weighted 1 between mask pixels.
            let mut sum = 0.0f64;
            if on(r, c) {
                if c > 0 && on(r, c - 1) {
                    sum += f64::from(edge_slope(g(r, c - 1), g(r, c), 0));
                }
                if on(r, c + 1) {
                    sum -= f64::from(edge_slope(g(r, c), g(r, c + 1), 0));
                }
                if r > 0 && on(r - 1, c) {
                    sum += f64::from(edge_slope(g(r - 1, c), g(r, c), 1));
                }
                if on(r + 1, c) {
                    sum -= f64::from(edge_slope(g(r, c), g(r + 1, c), 1));
                }
            }
            assert!(
                (f64::from(b[r * w + c]) - sum).abs() < 1e-5,
                "rhs at ({r}, {c})"
            );
        }
    }
}

#[test]
fn gradients_clamp_grazing_normals() {
    let mut n = Array3::zeros((1, 3, 3));
    n[(0, 0, 0)] = 1.0; // grazing: nz = 0
    n[(0, 1, 0)] = -0.6;
    n[(0, 1, 2)] = 0.8;
    n[(0, 2, 0)] = f32::NAN;
    let mask = Array2::from_elem((1, 3), true);
    let (p, q) = gradients(&n, &mask);
    assert!((p[(0, 0)] + 1.0 / MIN_NZ).abs() < 1e-3);
    assert!((p[(0, 1)] - 0.75).abs() < 1e-6);
    assert_eq!(p[(0, 2)], 0.0);
    assert!(q.iter().all(|&v| v == 0.0));
    let off = Array2::from_elem((1, 3), false);
    let (p, _) = gradients(&n, &off);
    assert!(p.iter().all(|&v| v == 0.0));
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

/// Peak resident memory of this process so far (Linux), in MiB.
fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The 128-px test bumps scaled up to an `n`-px frame (same slopes).
fn scaled_bumps(n: usize) -> impl Fn(f64, f64) -> (f64, f64, f64) {
    let k = n as f64 / 128.0;
    move |x, y| {
        let (z, zx, zy) = gaussians(x / k, y / k);
        (z * k, zx, zy)
    }
}

/// 2048² timings, best of 7 interleaved rounds (the machine may be shared):
/// `cargo test --release --lib integrate -- --ignored --nocapture`.
#[test]
#[ignore]
fn timings_2048() {
    let n = 2048;
    let rad = 0.45 * n as f64;
    let c = n as f64 / 2.0;
    let s = hemisphere(c, c, rad);
    let bumps = scaled_bumps(n);
    let full = Array2::from_elem((n, n), true);
    let mask = disc(n, n, c, c, 0.95 * rad);
    let (pf, qf) = gradients(&normals_of(&bumps, &full), &full);
    let (pd, qd) = gradients(&normals_of(&s, &mask), &mask);
    type Run<'a> = (
        &'a str,
        &'a Array2<f32>,
        &'a Array2<f32>,
        &'a Array2<bool>,
        Integration,
    );
    let runs: [Run; 4] = [
        (
            "frankot-chellappa, full frame",
            &pf,
            &qf,
            &full,
            Integration::FrankotChellappa,
        ),
        (
            "poisson, full frame (DCT)",
            &pf,
            &qf,
            &full,
            Integration::Poisson,
        ),
        (
            "frankot-chellappa, disc mask",
            &pd,
            &qd,
            &mask,
            Integration::FrankotChellappa,
        ),
        (
            "poisson, disc mask (MG-PCG)",
            &pd,
            &qd,
            &mask,
            Integration::Poisson,
        ),
    ];
    let mut best = [f64::INFINITY; 4];
    let mut rms_of = [0.0; 4];
    for round in 0..7 {
        for (i, &(_, p, q, m, method)) in runs.iter().enumerate() {
            let t = Instant::now();
            let z = integrate(p, q, m, method);
            best[i] = best[i].min(t.elapsed().as_secs_f64() * 1e3);
            if round == 0 {
                let truth = if i < 2 {
                    heights_of(&bumps, n, n)
                } else {
                    heights_of(&s, n, n)
                };
                rms_of[i] = rms(&z, &truth, m);
            }
        }
    }
    let m: Vec<bool> = mask.iter().copied().collect();
    let st = MaskStencil::new(&m, n, n);
    let mut b = poisson::rhs(&st, pd.as_slice().unwrap(), qd.as_slice().unwrap());
    Components::new(&m, n, n).remove_means(&mut b);
    let (_, stats) = poisson::solve_pcg(&st, b, NEVER);
    eprintln!(
        "2048² on {} rayon threads, best of 7:",
        rayon::current_num_threads()
    );
    for (i, (name, ..)) in runs.iter().enumerate() {
        eprintln!(
            "  {name:<32} {:>6.0} ms   depth rms {:.4} px",
            best[i], rms_of[i]
        );
    }
    eprintln!(
        "  poisson / FC on the disc: {:.2}×   {stats:?}",
        best[3] / best[2]
    );
    eprintln!("  peak RSS {:.0} MiB", peak_rss_mib().unwrap_or(f64::NAN));
}

/// 4096² disc: time, iterations and peak memory of the masked solver.
#[test]
#[ignore]
fn timings_4096() {
    let n = 4096;
    let rad = 0.45 * n as f64;
    let c = n as f64 / 2.0;
    let s = hemisphere(c, c, rad);
    let mask = disc(n, n, c, c, 0.95 * rad);
    let (p, q) = gradients(&normals_of(&s, &mask), &mask);
    let before = peak_rss_mib().unwrap_or(f64::NAN);
    let t = Instant::now();
    let z = integrate(&p, &q, &mask, Integration::Poisson);
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let after = peak_rss_mib().unwrap_or(f64::NAN);
    let err = rms(&z, &heights_of(&s, n, n), &mask);
    eprintln!(
        "4096² disc poisson: {ms:.0} ms, depth rms {err:.4} px, peak RSS {before:.0} → {after:.0} MiB"
    );
    let t = Instant::now();
    let _ = integrate(&p, &q, &mask, Integration::FrankotChellappa);
    eprintln!("4096² disc FC: {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let m: Vec<bool> = mask.iter().copied().collect();
    let st = MaskStencil::new(&m, n, n);
    let mut b = poisson::rhs(&st, p.as_slice().unwrap(), q.as_slice().unwrap());
    Components::new(&m, n, n).remove_means(&mut b);
    let t = Instant::now();
    let (_, stats) = poisson::solve_pcg(&st, b, NEVER);
    eprintln!(
        "4096² PCG alone: {:.0} ms, {stats:?}",
        t.elapsed().as_secs_f64() * 1e3
    );
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

/// The rendered 2048² sphere set (`$PHOTOSTEREO_SET`, default `/tmp/set2048`, from
/// `photostereo render`), reconstructed with the default options: normals and auto mask.
fn rendered_set() -> Option<(Array3<f32>, Array2<bool>)> {
    let dir = std::env::var("PHOTOSTEREO_SET").unwrap_or_else(|_| "/tmp/set2048".into());
    let dir = std::path::Path::new(&dir);
    let set = crate::core::intake::load_dir(
        dir,
        crate::core::intake::DirMask::Folder,
        &Default::default(),
    )
    .ok()?;
    let rec =
        crate::core::reconstruct(&set, &Default::default(), &mut crate::core::RunToEnd).ok()?;
    Some((rec.normals, rec.mask))
}

/// Where the job's `integrate` stage spends its time on the rendered set (best of 5):
/// `cargo test --release --lib timings_rendered_set -- --ignored --nocapture`.
#[test]
#[ignore]
fn timings_rendered_set() {
    let Some((normals, mask)) = rendered_set() else {
        eprintln!("no rendered set: skipped");
        return;
    };
    let (h, w) = mask.dim();
    let m: Vec<bool> = mask.iter().copied().collect();
    // The first round runs on fresh pages, as the job does (its arrays are new to the
    // process); later rounds reuse freed memory.
    let (mut first, mut best) = ([0.0; 8], [f64::INFINITY; 8]);
    let mut stats = None;
    for round in 0..5 {
        let mut lap = Instant::now();
        let mut t = |k: usize| {
            let ms = lap.elapsed().as_secs_f64() * 1e3;
            best[k] = best[k].min(ms);
            if round == 0 {
                first[k] = ms;
            }
            lap = Instant::now();
        };
        let (p, q) = gradients(&normals, &mask);
        t(0);
        let c = curl(&p, &q, &mask);
        t(1);
        std::hint::black_box(&c);
        let z = integrate(&p, &q, &mask, Integration::Poisson);
        t(2);
        std::hint::black_box(&z);
        let (ps, qs) = (p.as_slice().unwrap(), q.as_slice().unwrap());
        let comps = Components::new(&m, h, w);
        t(3);
        let st = MaskStencil::new(&m, h, w);
        t(4);
        let mut b = poisson::rhs(&st, ps, qs);
        comps.remove_means(&mut b);
        t(5);
        let (z, s) = poisson::solve_pcg(&st, b, NEVER);
        t(6);
        std::hint::black_box(&z);
        stats = Some(s);
    }
    let names = [
        "gradients",
        "curl",
        "integrate (poisson)",
        "  of which components",
        "  of which stencil",
        "  of which rhs",
        "  of which PCG",
    ];
    eprintln!(
        "rendered set {h}×{w}, {} mask pixels, first round / best of 5:",
        m.iter().filter(|&&v| v).count()
    );
    for ((name, ms), cold) in names.iter().zip(best).zip(first) {
        eprintln!("  {name:<24} {cold:>6.1} / {ms:>6.1} ms");
    }
    eprintln!("  {:?}", stats.unwrap());
}

/// Height error of CG stopped after `k` iterations, against a solve converged to f32
/// round-off, on the 2048² disc, the full frame, a holey disc and the rendered set:
/// `cargo test --release --lib pcg_error_by_iteration -- --ignored --nocapture`.
#[test]
#[ignore]
fn pcg_error_by_iteration() {
    let n = 2048;
    let rad = 0.45 * n as f64;
    let c = n as f64 / 2.0;
    let sphere = hemisphere(c, c, rad);
    let bumps = scaled_bumps(n);
    let disc_mask = disc(n, n, c, c, 0.95 * rad);
    let full = Array2::from_elem((n, n), true);
    let mut seed = 12345u64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % 1000) as f64 / 1000.0
    };
    let holey = Array2::from_shape_fn((n, n), |(r, c)| disc_mask[(r, c)] && rnd() < 0.9);
    type Case = (String, Array2<f32>, Array2<f32>, Array2<bool>);
    let mut cases: Vec<Case> = Vec::new();
    for (name, s, mask) in [
        ("disc, sphere", &sphere as &Surface, &disc_mask),
        ("full frame, bumps", &bumps, &full),
        ("disc with 10% holes, sphere", &sphere, &holey),
    ] {
        let (p, q) = gradients(&normals_of(s, mask), mask);
        cases.push((name.into(), p, q, mask.clone()));
    }
    if let Some((normals, mask)) = rendered_set() {
        let (p, q) = gradients(&normals, &mask);
        cases.push(("rendered set, auto mask".into(), p, q, mask));
    }
    for (name, p, q, mask) in &cases {
        let (h, w) = mask.dim();
        let m: Vec<bool> = mask.iter().copied().collect();
        let comps = Components::new(&m, h, w);
        let st = MaskStencil::new(&m, h, w);
        let mut b = poisson::rhs(&st, p.as_slice().unwrap(), q.as_slice().unwrap());
        comps.remove_means(&mut b);
        // Past ~1e-8, f32 round-off makes CG drift away again: stop the reference earlier.
        let (mut exact, s) = poisson::solve_pcg_until(&st, b.clone(), 3e-7, 60, NEVER);
        comps.remove_means(&mut exact);
        let count = m.iter().filter(|&&v| v).count() as f64;
        eprintln!("{name}: reference {s:?}");
        let (_, at_tol) = poisson::solve_pcg(&st, b.clone(), NEVER);
        eprintln!(
            "  stops at TOL = {:.0e} after {} iterations",
            poisson::TOL,
            at_tol.iterations
        );
        for k in 1..=12 {
            let (mut z, s) = poisson::solve_pcg_until(&st, b.clone(), 0.0, k, NEVER);
            comps.remove_means(&mut z);
            let (mut e2, mut emax) = (0.0f64, 0.0f64);
            for i in 0..h * w {
                if m[i] {
                    let d = f64::from(z[i] - exact[i]);
                    e2 += d * d;
                    emax = emax.max(d.abs());
                }
            }
            eprintln!(
                "  {k:>2} iterations: rel residual {:.1e}, height error rms {:.5} px, max {:.4} px",
                s.rel_residual,
                (e2 / count).sqrt(),
                emax
            );
        }
    }
}

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
