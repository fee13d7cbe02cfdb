//! Circle fits (the sphere's notes, step 4): one radial sub-pixel refinement round along
//! rays from the centre with a Tukey-weighted geometric circle fit, the algebraic (Kåsa)
//! start, and the 3×3 solve they share with the light positions.

use ndarray::Array2;

use super::filter::{bilinear, parabola_peak};
use crate::core::calibrate::circle::Circle;

/// Rays of the refinement (per full turn).
pub(super) const RAYS: usize = 720;

/// Unit direction of ray `k` of [`RAYS`].
pub(super) fn ray_direction(k: usize) -> (f64, f64) {
    let a = k as f64 / RAYS as f64 * std::f64::consts::TAU;
    (a.cos(), a.sin())
}

/// A fitted outline and how well the images support it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutlineFit {
    pub circle: Circle,
    /// Fraction of the refinement's rays that found the outline.
    pub coverage: f64,
    /// RMS distance of the kept outline points from the circle, pixels.
    pub rms: f64,
}

/// One refinement round: the outline's sub-pixel position along each ray within
/// `window` px of `circle`, then a robust circle fit through them.
pub(super) fn refine(
    image: &Array2<f32>,
    circle: Circle,
    window: f64,
    threshold: f32,
) -> Option<OutlineFit> {
    let (h, w) = image.dim();
    let step = 0.25;
    let n = (2.0 * window / step).round() as usize + 1;
    let mut points = Vec::new();
    for k in 0..RAYS {
        let (ux, uy) = ray_direction(k);
        let at = |i: usize| {
            let rho = circle.r - window + i as f64 * step;
            (circle.cx + rho * ux, circle.cy + rho * uy)
        };
        let (x0, y0) = at(0);
        let (x1, y1) = at(n - 1);
        let inside =
            |x: f64, y: f64| x >= 1.0 && y >= 1.0 && x <= (w - 2) as f64 && y <= (h - 2) as f64;
        if !inside(x0, y0) || !inside(x1, y1) {
            continue;
        }
        let samples: Vec<f64> = (0..n)
            .map(|i| {
                let (x, y) = at(i);
                bilinear(image, x, y)
            })
            .collect();
        let deriv: Vec<f64> = (1..n - 1)
            .map(|i| ((samples[i + 1] - samples[i - 1]) / (2.0 * step)).abs())
            .collect();
        let (i, &peak) = deriv.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
        if peak < threshold as f64 || i == 0 || i + 1 == deriv.len() {
            continue;
        }
        let t = parabola_peak(deriv[i - 1], peak, deriv[i + 1]);
        let rho = circle.r - window + (i as f64 + 1.0 + t) * step;
        points.push((circle.cx + rho * ux, circle.cy + rho * uy));
    }
    robust_fit(&points, circle)
}

/// A Tukey-weighted geometric circle fit from `start` through the outline points the rays
/// found (None with fewer than 12), the scale from the residuals' MAD; its coverage is the
/// share of the [`RAYS`] whose point it keeps.
pub(super) fn robust_fit(points: &[(f64, f64)], start: Circle) -> Option<OutlineFit> {
    if points.len() < 12 {
        return None;
    }
    let mut c = start;
    let mut weights = vec![1.0; points.len()];
    for _ in 0..8 {
        let mut res: Vec<f64> = points
            .iter()
            .map(|&(x, y)| ((x - c.cx).hypot(y - c.cy) - c.r).abs())
            .collect();
        let resid = res.clone();
        let mid = res.len() / 2;
        let mad = *res.select_nth_unstable_by(mid, f64::total_cmp).1;
        let cutoff = 4.685 * (1.4826 * mad).max(0.05);
        for (wt, r) in weights.iter_mut().zip(&resid) {
            let u = r / cutoff;
            *wt = if u < 1.0 { (1.0 - u * u).powi(2) } else { 0.0 };
        }
        c = geometric_fit(points, c, &weights);
    }
    let (mut sq, mut kept) = (0.0, 0usize);
    for (&(x, y), &wt) in points.iter().zip(&weights) {
        if wt > 0.0 {
            sq += ((x - c.cx).hypot(y - c.cy) - c.r).powi(2);
            kept += 1;
        }
    }
    Some(OutlineFit {
        circle: c,
        coverage: kept as f64 / RAYS as f64,
        rms: (sq / kept.max(1) as f64).sqrt(),
    })
}

/// Algebraic (Kåsa) circle through points: a start for the geometric fit.
pub(super) fn kasa(points: &[(f64, f64)]) -> Option<Circle> {
    // Minimise Σ (x² + y² + D x + E y + F)².
    let mut m = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for &(x, y) in points {
        let row = [x, y, 1.0];
        let z = -(x * x + y * y);
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += row[i] * row[j];
            }
            b[i] += row[i] * z;
        }
    }
    let [d, e, f] = solve3(m, b)?;
    let (cx, cy) = (-d / 2.0, -e / 2.0);
    let r2 = cx * cx + cy * cy - f;
    (r2 > 0.0).then(|| Circle {
        cx,
        cy,
        r: r2.sqrt(),
    })
}

/// Weighted geometric circle fit (Gauss–Newton on distance − r) from `start`.
pub(super) fn geometric_fit(points: &[(f64, f64)], start: Circle, weights: &[f64]) -> Circle {
    let mut c = start;
    for _ in 0..20 {
        let mut m = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for (&(x, y), &w) in points.iter().zip(weights) {
            if w == 0.0 {
                continue;
            }
            let (dx, dy) = (x - c.cx, y - c.cy);
            let d = dx.hypot(dy).max(1e-9);
            let j = [-dx / d, -dy / d, -1.0];
            let r = d - c.r;
            for i in 0..3 {
                for k in 0..3 {
                    m[i][k] += w * j[i] * j[k];
                }
                b[i] -= w * j[i] * r;
            }
        }
        let Some(delta) = solve3(m, b) else {
            break;
        };
        c = Circle {
            cx: c.cx + delta[0],
            cy: c.cy + delta[1],
            r: c.r + delta[2],
        };
        if delta.iter().all(|d| d.abs() < 1e-6) {
            break;
        }
    }
    c
}

/// Solve a 3×3 system by Cramer's rule; None when singular.
pub(crate) fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |a: [[f64; 3]; 3]| {
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    };
    let d = det(m);
    let scale = m.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    if d.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let mut out = [0.0; 3];
    for (k, o) in out.iter_mut().enumerate() {
        let mut a = m;
        for i in 0..3 {
            a[i][k] = b[i];
        }
        *o = det(a) / d;
    }
    Some(out)
}
