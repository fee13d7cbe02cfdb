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

/// Cauchy re-weightings before the outliers are cut.
const REWEIGHTS: usize = 6;
/// Robust deviations beyond which an observation is an outlier.
const OUTLIER_DEVIATIONS: f32 = 3.0;

/// Fit `obs[k] ≈ max(0, g · lights[k])` (values in [0, 1]); `dark` is the level at and
/// below which an observation is taken as shadow, `floor` the smallest deviation the
/// outlier test trusts (the noise). `keep` is scratch of the lights' length.
///
/// Least squares first, then Cauchy-weighted refits (a highlight pulls a plain fit
/// towards itself and hides among its residuals; down-weighting large residuals lets the
/// fit leave it), then observations in attached shadow or beyond [`OUTLIER_DEVIATIONS`]
/// robust deviations are cut and the rest fitted plainly.
pub fn fit(lights: &[[f32; 3]], obs: &[f32], dark: f32, floor: f32, keep: &mut [bool]) -> Fit {
    let mut weight: Vec<f32> = obs
        .iter()
        .map(|&o| if o > dark { 1.0 } else { 0.0 })
        .collect();
    let Some(mut g) = solve(lights, obs, &weight) else {
        return Fit {
            g: [0.0; 3],
            rms: 0.0,
            kept: 0,
        };
    };
    let mut residuals = Vec::with_capacity(obs.len());
    let mut scale = floor;
    for round in 0..=REWEIGHTS {
        residuals.clear();
        for (l, (&o, &wt)) in lights.iter().zip(obs.iter().zip(&weight)) {
            if o > dark && dot(g, *l) > 0.0 && wt > 0.0 {
                residuals.push((o - dot(g, *l)).abs());
            }
        }
        if residuals.len() < 3 {
            break;
        }
        let mid = residuals.len() / 2;
        scale = (1.4826 * *residuals.select_nth_unstable_by(mid, f32::total_cmp).1).max(floor);
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
        match solve(lights, obs, &weight) {
            Some(next) => g = next,
            None => break,
        }
    }
    let limit = OUTLIER_DEVIATIONS * scale;
    for (k, (l, &o)) in lights.iter().zip(obs).enumerate() {
        let p = dot(g, *l);
        keep[k] = o > dark && p > 0.0 && (o - p).abs() <= limit;
        weight[k] = if keep[k] { 1.0 } else { 0.0 };
    }
    if let Some(next) = solve(lights, obs, &weight) {
        g = next;
    }
    let (mut sum, mut kept) = (0f32, 0usize);
    for (k, (l, &o)) in lights.iter().zip(obs).enumerate() {
        if keep[k] {
            let r = o - dot(g, *l).max(0.0);
            sum += r * r;
            kept += 1;
        }
    }
    Fit {
        g,
        rms: if kept > 0 {
            (sum / kept as f32).sqrt()
        } else {
            0.0
        },
        kept,
    }
}

/// Weighted least squares; None with fewer than three weighted observations or when
/// singular.
fn solve(lights: &[[f32; 3]], obs: &[f32], weight: &[f32]) -> Option<[f32; 3]> {
    let mut m = [[0f64; 3]; 3];
    let mut b = [0f64; 3];
    let mut n = 0;
    for ((l, &o), &wt) in lights
        .iter()
        .zip(obs)
        .zip(weight)
        .filter(|(_, w)| **w > 0.0)
    {
        n += 1;
        let wt = f64::from(wt);
        for r in 0..3 {
            b[r] += wt * f64::from(l[r]) * f64::from(o);
            for c in 0..3 {
                m[r][c] += wt * f64::from(l[r]) * f64::from(l[c]);
            }
        }
    }
    if n < 3 {
        return None;
    }
    let inv = invert3(&m)?;
    Some([0, 1, 2].map(|r| (0..3).map(|c| inv[r][c] * b[c]).sum::<f64>() as f32))
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
