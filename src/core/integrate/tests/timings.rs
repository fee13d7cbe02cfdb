//! Ignored measurements (`cargo test --release --lib integrate -- --ignored --nocapture`):
//! timings at 2048² and 4096² and on a rendered set, and CG's height error by iteration.

use std::time::Instant;

use ndarray::{Array2, Array3};

use super::surfaces::*;
use crate::core::integrate::components::Components;
use crate::core::integrate::multigrid::MaskStencil;
use crate::core::integrate::*;
use crate::core::options::Integration;
use crate::core::progress::NEVER;

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
    let rec = crate::core::pipeline::reconstruct(
        &set,
        &Default::default(),
        &mut crate::core::progress::RunToEnd,
    )
    .ok()?;
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
