//! One pixel's albedo-scaled normal `g = ρ n` from its observations under its own light
//! vectors (near lights give every pixel different ones): least squares over the lit
//! observations, with attached shadows (`g·l ≤ 0`) and outliers (highlights above, cast
//! shadows below the fit by more than three robust deviations) left out.

use crate::core::lambert::invert3;

/// The fit of one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fit {
    /// `ρ n`; zero when fewer than three observations are usable.
    pub g: [f32; 3],
    /// RMS of (observed − re-rendered) over the observations kept.
    pub rms: f32,
    /// Observations kept.
    pub kept: usize,
}

/// Cauchy re-weightings before the outliers are cut, at most.
const REWEIGHTS: usize = 6;
/// The re-weightings stop once no component of `g` moves by more than this (of full
/// scale): the fit has settled far below the noise.
const SETTLED: f32 = 1e-5;
/// Robust deviations beyond which an observation is an outlier.
const OUTLIER_DEVIATIONS: f32 = 3.0;
/// Lights a pixel's buffers hold on the stack; larger rigs use the heap.
const ON_STACK: usize = 64;

/// Fit `obs[k] ≈ max(0, g · lights[k])` (values in [0, 1]); `dark` is the level at and
/// below which an observation is taken as shadow, `floor` the smallest deviation the
/// outlier test trusts (the noise). `keep` is scratch of the lights' length.
///
/// Least squares first, then Cauchy-weighted refits (a highlight pulls a plain fit
/// towards itself and hides among its residuals; down-weighting large residuals lets the
/// fit leave it), then observations in attached shadow or beyond [`OUTLIER_DEVIATIONS`]
/// robust deviations are cut and the rest fitted plainly.
pub fn fit(lights: &[[f32; 3]], obs: &[f32], dark: f32, floor: f32, keep: &mut [bool]) -> Fit {
    let n = obs.len();
    let (mut weight_stack, mut residual_stack) = ([0f32; ON_STACK], [0f32; ON_STACK]);
    let (mut weight_heap, mut residual_heap) = (Vec::new(), Vec::new());
    let (weight, residuals) = if n <= ON_STACK {
        (&mut weight_stack[..n], &mut residual_stack[..n])
    } else {
        weight_heap.resize(n, 0f32);
        residual_heap.resize(n, 0f32);
        (&mut weight_heap[..], &mut residual_heap[..])
    };
    for (w, &o) in weight.iter_mut().zip(obs) {
        *w = if o > dark { 1.0 } else { 0.0 };
    }
    let Some(mut g) = solve(lights, obs, weight) else {
        return Fit {
            g: [0.0; 3],
            rms: 0.0,
            kept: 0,
        };
    };
    // When the plain fit leaves every lit observation lit and within the outlier limit
    // at the noise floor, nothing is an outlier: the cut would keep them all, and the
    // plain fit is the answer (most pixels of a matte surface).
    let clean = OUTLIER_DEVIATIONS * floor;
    let plain = (lights.iter().zip(obs)).all(|(l, &o)| {
        let p = dot(g, *l);
        o <= dark || (p > 0.0 && (o - p).abs() <= clean)
    });
    if plain {
        return kept_fit(lights, obs, dark, g, keep);
    }
    let mut scale = floor;
    for round in 0..=REWEIGHTS {
        let mut m = 0;
        for (l, (&o, &wt)) in lights.iter().zip(obs.iter().zip(weight.iter())) {
            let p = dot(g, *l);
            if o > dark && p > 0.0 && wt > 0.0 {
                residuals[m] = (o - p).abs();
                m += 1;
            }
        }
        if m < 3 {
            break;
        }
        scale = (1.4826 * median(&mut residuals[..m])).max(floor);
        if round == REWEIGHTS {
            break;
        }
        let c = 2.385 * scale;
        for (wt, (l, &o)) in weight.iter_mut().zip(lights.iter().zip(obs)) {
            let p = dot(g, *l);
            *wt = if o > dark && p > 0.0 {
                1.0 / (1.0 + ((o - p) / c).powi(2))
            } else {
                0.0
            };
        }
        match solve(lights, obs, weight) {
            Some(next) => {
                let moved = (0..3).map(|k| (next[k] - g[k]).abs()).fold(0f32, f32::max);
                g = next;
                // The scale of the last residuals stands: g moved far below it.
                if moved <= SETTLED {
                    break;
                }
            }
            None => break,
        }
    }
    let limit = OUTLIER_DEVIATIONS * scale;
    for (k, (l, &o)) in lights.iter().zip(obs).enumerate() {
        let p = dot(g, *l);
        keep[k] = o > dark && p > 0.0 && (o - p).abs() <= limit;
        weight[k] = if keep[k] { 1.0 } else { 0.0 };
    }
    if let Some(next) = solve(lights, obs, weight) {
        g = next;
    }
    let (rms, kept) = rms_of(lights, obs, g, keep);
    Fit { g, rms, kept }
}

/// The plain fit `g` of every lit observation (above `dark`), all kept.
fn kept_fit(lights: &[[f32; 3]], obs: &[f32], dark: f32, g: [f32; 3], keep: &mut [bool]) -> Fit {
    for (k, &o) in keep.iter_mut().zip(obs) {
        *k = o > dark;
    }
    let (rms, kept) = rms_of(lights, obs, g, keep);
    Fit { g, rms, kept }
}

/// RMS of (observed − re-rendered) over the kept observations, and their count.
fn rms_of(lights: &[[f32; 3]], obs: &[f32], g: [f32; 3], keep: &[bool]) -> (f32, usize) {
    let (mut sum, mut kept) = (0f32, 0usize);
    for (k, (l, &o)) in lights.iter().zip(obs).enumerate() {
        if keep[k] {
            let r = o - dot(g, *l).max(0.0);
            sum += r * r;
            kept += 1;
        }
    }
    let rms = if kept > 0 {
        (sum / kept as f32).sqrt()
    } else {
        0.0
    };
    (rms, kept)
}

/// Weighted least squares; None with fewer than three weighted observations or when
/// singular. The normal equations are summed in f32 (at most a few hundred terms of
/// order one) and solved in f64.
fn solve(lights: &[[f32; 3]], obs: &[f32], weight: &[f32]) -> Option<[f32; 3]> {
    let (mut xx, mut xy, mut xz, mut yy, mut yz, mut zz) = (0f32, 0f32, 0f32, 0f32, 0f32, 0f32);
    let mut b = [0f32; 3];
    let mut n = 0;
    for ((l, &o), &wt) in lights.iter().zip(obs).zip(weight) {
        if wt <= 0.0 {
            continue;
        }
        n += 1;
        let [x, y, z] = l.map(|v| v * wt);
        xx += x * l[0];
        xy += x * l[1];
        xz += x * l[2];
        yy += y * l[1];
        yz += y * l[2];
        zz += z * l[2];
        b[0] += x * o;
        b[1] += y * o;
        b[2] += z * o;
    }
    if n < 3 {
        return None;
    }
    let [xx, xy, xz, yy, yz, zz] = [xx, xy, xz, yy, yz, zz].map(f64::from);
    let m = [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]];
    let inv = invert3(&m)?;
    let b = b.map(f64::from);
    Some([0, 1, 2].map(|r| (0..3).map(|c| inv[r][c] * b[c]).sum::<f64>() as f32))
}

/// The median of a few values (the upper one of an even count): the value whose rank
/// holds the middle, found by counting (branch-free inner loops, which for the dozens a
/// pixel has beat sorting or a general selection).
fn median(v: &mut [f32]) -> f32 {
    let k = v.len() / 2;
    if v.len() > ON_STACK {
        return *v.select_nth_unstable_by(k, f32::total_cmp).1;
    }
    for &x in v.iter() {
        let (mut less, mut equal) = (0usize, 0usize);
        for &y in v.iter() {
            less += usize::from(y < x);
            equal += usize::from(y == x);
        }
        if less <= k && k < less + equal {
            return x;
        }
    }
    v[k]
}

#[inline(always)]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eight lights, one in attached shadow, one a highlight, one a cast shadow: the fit
    /// leaves those out and finds g exactly.
    #[test]
    fn shadows_and_highlights_are_left_out() {
        let g = [0.2f32, -0.1, 0.6];
        let lights: Vec<[f32; 3]> = (0..8)
            .map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 8.0;
                [0.7 * a.cos(), 0.7 * a.sin(), 0.7]
            })
            .chain([[-1.0, 0.0, 0.1]])
            .collect();
        let mut obs: Vec<f32> = lights.iter().map(|l| dot(g, *l).max(0.0)).collect();
        obs[2] += 0.5; // a highlight
        obs[5] = 0.0; // a cast shadow
        let mut keep = vec![false; lights.len()];
        let f = fit(&lights, &obs, 0.002, 0.001, &mut keep);
        assert_eq!(f.kept, 6, "{keep:?}");
        assert!((0..3).all(|k| (f.g[k] - g[k]).abs() < 1e-5), "{:?}", f.g);
    }
}
