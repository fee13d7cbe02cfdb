//! One pixel's fit of a diffuse term and a microfacet lobe (GGX or Beckmann) with its
//! normal.
//!
//! It starts from the robust solve's Lambertian normal and albedo, picks each lobe
//! family's width from a grid (the albedos are linear given the normal, the family and
//! the width), then refines normal, albedos and width together by Levenberg–Marquardt
//! under Cauchy weights, and keeps the family that explains the pixel best, so that a
//! cast shadow or a mismatched lobe's tail does not pull the normal. The lobe is
//! kept only where it explains the pixel clearly better than the Lambertian fit under the
//! same robust loss, with a penalty for its two extra parameters (Lambertian where nothing
//! more is explained, so matte surfaces keep the robust solve's normals).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::linear::{nonnegative_pair, solve_spd};
use super::lobe::{Facets, Lobe};
use crate::core::vec3::{cross, dot, normalise};

/// One observation of a pixel: the light's unit direction and intensity, and the value
/// seen with the black level removed ([0, 1] units). Shadowed and clipped values are the
/// caller's to leave out.
#[derive(Debug, Clone, Copy)]
pub struct Observation {
    pub light: [f64; 3],
    pub intensity: f64,
    pub value: f64,
}

/// A pixel's material under the lobe model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fitted {
    pub normal: [f64; 3],
    /// Diffuse albedo (as the Lambertian albedo: value = albedo · n·l under a unit light).
    pub diffuse: f64,
    /// Specular albedo: the lobe's scale.
    pub specular: f64,
    /// Roughness, √alpha.
    pub roughness: f64,
    /// The lobe's family.
    pub facets: Facets,
}

impl Fitted {
    /// The value this material shows under `light` (unit) of `intensity`, black level
    /// not included.
    pub fn predict(&self, light: [f64; 3], intensity: f64) -> f64 {
        self.predict_with(&self.lobe(), light, intensity)
    }

    /// [`predict`](Self::predict) with the model's [`lobe`](Self::lobe) worked out: a
    /// pixel's fit evaluates one model under every light.
    fn predict_with(&self, lobe: &Lobe, light: [f64; 3], intensity: f64) -> f64 {
        let [irradiance, specular] = self.terms(lobe, light, intensity);
        self.diffuse * irradiance + self.specular * specular
    }

    /// The prediction's two terms under `light` of `intensity`, whose sum weighted by the
    /// albedos is the prediction (and which are its derivatives by them): the irradiance
    /// `I·n·l` and the lobe `I·lobe`; both 0 when the light is below the surface.
    fn terms(&self, lobe: &Lobe, light: [f64; 3], intensity: f64) -> [f64; 2] {
        let nl = dot(self.normal, light);
        if nl <= 0.0 {
            return [0.0; 2];
        }
        [intensity * nl, intensity * lobe.at(light)]
    }

    /// The specular lobe, ready to be evaluated under any light.
    fn lobe(&self) -> Lobe {
        (self.facets).about(self.normal, self.roughness * self.roughness)
    }
}

/// The lobe an object's pixels share: its family and roughness, fitted on a sample of
/// them. A pixel's few observations of a highlight rarely pin its
/// width down (a lobe narrower than the lights' spacing is seen by one light at most), and
/// a width fitted per pixel overshoots where the next light would show its tail; one
/// material per object is what the images of many pixels do determine.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Material {
    /// The lobe's family: `ggx` or `beckmann`.
    pub facets: Facets,
    /// GGX's roughness (√α; a Beckmann lobe's is that of the GGX lobe as wide at half its
    /// peak).
    pub roughness: f64,
}

/// A shared material's fit is kept where its loss is at most this many σ² per
/// observation (an RMS residual of about twice the noise).
const SHARED_FIT: f64 = 4.0;
/// Brightest observations whose mirror normals start a shared material's fit.
const MIRROR_STARTS: usize = 3;
/// Roughness values the lobe's width is first picked from (mirror-like to broad).
const ROUGHNESS_GRID: [f64; 11] = [
    0.04, 0.06, 0.09, 0.13, 0.18, 0.25, 0.33, 0.43, 0.55, 0.7, 0.85,
];
const MIN_ROUGHNESS: f64 = 0.04;
/// Fewest observations a five-parameter fit is tried on.
const MIN_OBSERVATIONS: usize = 8;
/// A lobe counts as seen where an observation's light gets this share of its peak.
const LOBE_SEEN: f64 = 0.01;
/// A refinement round stops once a step lowers its weighted squares by less than this
/// share: the weights are renewed after it anyway. Without it nearly every round ran all
/// its steps for gains of a few per cent, at 1.6 times the cost; the glossy catalogue
/// (`tests/core/glossy.rs`) is as accurate or more with it.
const STEP_GAIN: f64 = 1e-3;
/// The lobe must lower the robust loss by this factor, beyond its parameters' penalty.
const MIN_GAIN: f64 = 0.8;

/// Fit the lobe model to `obs`, starting from the Lambertian `normal` and `albedo`
/// (the robust solve's), with `noise` the images' noise (σ, [0, 1] units): the shared
/// `material` when given (normal and albedos fitted), and where it does not explain the
/// pixel (another material, or a start too far from the lobe for its fixed width) the
/// family and width that fit the pixel best. `None` when the Lambertian fit explains the
/// pixel as well (or there is too little to fit).
pub fn fit(
    obs: &[Observation],
    normal: [f64; 3],
    albedo: f64,
    noise: f64,
    material: Option<Material>,
) -> Option<Fitted> {
    if obs.len() < MIN_OBSERVATIONS || normal[2] <= 0.0 {
        return None;
    }
    // The Cauchy loss's scale: residuals well beyond it (a cast shadow, a lobe's
    // mismatched tail) weigh little.
    let scale = (3.0 * noise).max(0.004);
    let lambert = Fitted {
        normal,
        diffuse: albedo,
        specular: 0.0,
        roughness: 1.0,
        facets: Facets::Ggx,
    };
    let pixel = Pixel {
        obs,
        normal,
        noise,
        scale,
        lambert_loss: loss(obs, &lambert, scale),
    };
    let shared = material.and_then(|m| pixel.of_material(m));
    shared.or_else(|| pixel.own()).map(|(fitted, _)| fitted)
}

/// One pixel's observations, its Lambertian start and that start's loss.
struct Pixel<'a> {
    obs: &'a [Observation],
    normal: [f64; 3],
    noise: f64,
    scale: f64,
    lambert_loss: f64,
}

impl Pixel<'_> {
    /// The lobe of the shared material `m`, from the Lambertian normal and the normals
    /// that mirror the [`MIRROR_STARTS`] brightest observations' lights into the camera
    /// (with the width fixed, a lobe whose peak falls between the lights is not found
    /// from a start beside it): the two whose albedos fit best are refined.
    fn of_material(&self, m: Material) -> Option<(Fitted, f64)> {
        let mut bright: Vec<&Observation> = self.obs.iter().collect();
        let top = MIRROR_STARTS.min(bright.len());
        if top < bright.len() {
            bright.select_nth_unstable_by(top, |a, b| b.value.total_cmp(&a.value));
        }
        let mut starts: Vec<(f64, Fitted)> = std::iter::once(self.normal)
            .chain(bright[..top].iter().map(|o| mirror_of(o.light)))
            .filter_map(|n| grid_start(self.obs, n, m.facets, &[m.roughness]))
            .collect();
        starts.sort_by(|a, b| a.0.total_cmp(&b.0));
        starts.truncate(2);
        // Kept only where it fits to about the noise: a pixel of another material is
        // often still explained better than by Lambert, with its normal tilted and its
        // diffuse albedo taking the rest of its lobe.
        let most = SHARED_FIT * self.obs.len() as f64 * self.noise.max(1e-4).powi(2);
        self.best_kept(starts, false)
            .filter(|&(_, fitted_loss)| fitted_loss <= most)
    }

    /// The pixel's own lobe. Two starts: the Lambertian normal, and the normal that
    /// mirrors the brightest observation's light into the camera (the lobe's peak), which
    /// is nearer the truth where a strong lobe has pulled the Lambertian fit away. GGX is
    /// refined from both, Beckmann from the one its grid fits better: refining it from
    /// both cost a third more time in the solve and moved no rendered scene's mean error
    /// by 0.01°.
    fn own(&self) -> Option<(Fitted, f64)> {
        let brightest = (self.obs.iter()).max_by(|a, b| a.value.total_cmp(&b.value))?;
        let mirror = mirror_of(brightest.light);
        let starts = |f: Facets| {
            // The grid rises: its widths up to the family's broadest.
            let widths =
                &ROUGHNESS_GRID[..ROUGHNESS_GRID.partition_point(|&r| r <= f.max_roughness())];
            [self.normal, mirror]
                .into_iter()
                .filter_map(move |n| grid_start(self.obs, n, f, widths))
        };
        let beckmann = starts(Facets::Beckmann).min_by(|a, b| a.0.total_cmp(&b.0));
        self.best_kept(starts(Facets::Ggx).chain(beckmann).collect(), true)
    }

    /// The best of `starts` once refined (the width too if `free_width`), with its robust
    /// loss, if it explains the pixel clearly better than the Lambertian fit.
    fn best_kept(&self, starts: Vec<(f64, Fitted)>, free_width: bool) -> Option<(Fitted, f64)> {
        let (obs, scale) = (self.obs, self.scale);
        let (fitted, fitted_loss) = (starts.into_iter())
            .map(|(_, start)| {
                let fitted = refine(obs, start, scale, free_width);
                (fitted, loss(obs, &fitted, scale))
            })
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        // Two more parameters than the Lambertian fit, each worth about σ² ln m of loss
        // at the noise level (BIC).
        let penalty = 2.0 * self.noise.max(1e-4).powi(2) * (obs.len() as f64).ln();
        let alpha = fitted.roughness * fitted.roughness;
        let kept = fitted.specular > 0.0
            && fitted.specular.is_finite()
            && seen(obs, fitted.normal, fitted.facets, alpha)
            && fitted_loss + penalty < MIN_GAIN * self.lambert_loss;
        kept.then_some((fitted, fitted_loss))
    }
}

/// The normal that mirrors light `l` into the camera (+z).
fn mirror_of(l: [f64; 3]) -> [f64; 3] {
    normalise([l[0], l[1], l[2] + 1.0])
}

/// The Cauchy loss Σ c² ln(1 + (r/c)²) of `model` over `obs`.
fn loss(obs: &[Observation], model: &Fitted, scale: f64) -> f64 {
    let c2 = scale * scale;
    let lobe = model.lobe();
    obs.iter()
        .map(|o| {
            let r = model.predict_with(&lobe, o.light, o.intensity) - o.value;
            c2 * (r * r / c2).ln_1p()
        })
        .sum()
}

/// The best of the `widths` (roughness) for `normal` and the lobe family `facets`, with
/// its non-negative albedos (least squares).
fn grid_start(
    obs: &[Observation],
    normal: [f64; 3],
    facets: Facets,
    widths: &[f64],
) -> Option<(f64, Fitted)> {
    let mut best: Option<(f64, Fitted)> = None;
    for &roughness in widths {
        let lobe = facets.about(normal, roughness * roughness);
        let (mut uu, mut uv, mut vv, mut uy, mut vy, mut yy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut brightest = 0f64;
        for o in obs {
            let value = lobe.at(o.light);
            brightest = brightest.max(value);
            let u = o.intensity * dot(normal, o.light).max(0.0);
            let v = o.intensity * value;
            (uu, uv, vv) = (uu + u * u, uv + u * v, vv + v * v);
            (uy, vy, yy) = (uy + u * o.value, vy + v * o.value, yy + o.value * o.value);
        }
        let floor = seen_floor(&lobe, normal);
        if !(floor > 0.0 && brightest >= floor) {
            continue;
        }
        let (a, b) = nonnegative_pair(uu, uv, vv, uy, vy);
        let sse = yy - 2.0 * (a * uy + b * vy) + a * a * uu + 2.0 * a * b * uv + b * b * vv;
        if best.as_ref().is_none_or(|(s, _)| sse < *s) {
            let model = Fitted {
                normal,
                diffuse: a,
                specular: b,
                roughness,
                facets,
            };
            best = Some((sse, model));
        }
    }
    best.filter(|(_, m)| m.specular > 0.0)
}

/// Whether some observation's light falls within the lobe of family `facets` and width
/// `alpha` about `normal`, at [`LOBE_SEEN`] of its peak or more: a lobe no light falls
/// within (a narrow one between the lights) is not in the images, and its specular albedo,
/// fitted to its far tail (Beckmann's falls to nothing), would be anything.
fn seen(obs: &[Observation], normal: [f64; 3], facets: Facets, alpha: f64) -> bool {
    let lobe = facets.about(normal, alpha);
    let floor = seen_floor(&lobe, normal);
    floor > 0.0 && obs.iter().any(|o| lobe.at(o.light) >= floor)
}

/// The value a light must reach under `lobe` (about `normal`) for it to be [`seen`]:
/// [`LOBE_SEEN`] of its peak, the value under the light the camera (+z) sees mirrored at
/// the normal.
fn seen_floor(lobe: &Lobe, normal: [f64; 3]) -> f64 {
    let mirror = [0, 1, 2].map(|k| 2.0 * normal[2] * normal[k] - f64::from(u8::from(k == 2)));
    LOBE_SEEN * lobe.at(mirror)
}

/// Parameters of the refinement: two tangent offsets of the normal from a base, the two
/// albedos and ln alpha.
type Params = [f64; 5];

/// The model of family `facets` at `p` around `base` (with its tangents `t1`, `t2`).
fn model_at(base: &Base, p: &Params, facets: Facets) -> Fitted {
    let n = [0, 1, 2].map(|k| base.n[k] + p[0] * base.t1[k] + p[1] * base.t2[k]);
    let len = dot(n, n).sqrt();
    Fitted {
        normal: n.map(|c| c / len),
        diffuse: p[2],
        specular: p[3],
        roughness: (p[4].exp()).sqrt(),
        facets,
    }
}

struct Base {
    n: [f64; 3],
    t1: [f64; 3],
    t2: [f64; 3],
}

impl Base {
    fn at(n: [f64; 3]) -> Self {
        // Any unit vector not parallel to n gives the tangents.
        let a = if n[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let t1 = normalise(cross(n, a));
        let t2 = cross(n, t1);
        Self { n, t1, t2 }
    }
}

/// Levenberg–Marquardt on the weighted squares, the Cauchy weights renewed from the
/// residuals a few times (iteratively re-weighted least squares); the width is held at
/// the start's unless `free_width`. Each round's steps stop once one lowers the weighted
/// squares by less than [`STEP_GAIN`].
fn refine(obs: &[Observation], start: Fitted, scale: f64, free_width: bool) -> Fitted {
    let facets = start.facets;
    let mut current = start;
    let c2 = scale * scale;
    let mut weights = vec![0.0; obs.len()];
    // The current point's residuals and terms, and a trial's (reused by every step).
    let mut now = Point::new(obs.len());
    let mut trial = Point::new(obs.len());
    let mut jac = vec![[0.0; 5]; obs.len()];
    for _round in 0..3 {
        let lobe = current.lobe();
        for (w, o) in weights.iter_mut().zip(obs) {
            let r = current.predict_with(&lobe, o.light, o.intensity) - o.value;
            *w = 1.0 / (1.0 + r * r / c2);
        }
        let base = Base::at(current.normal);
        let alpha = current.roughness * current.roughness;
        let mut p: Params = [0.0, 0.0, current.diffuse, current.specular, alpha.ln()];
        let mut cost = now.evaluate(obs, &weights, &model_at(&base, &p, facets));
        let mut lambda = 1e-3;
        for _step in 0..8 {
            let (mut jtj, jtr) = normal_equations(
                obs,
                &weights,
                (&base, facets),
                &p,
                &now,
                &mut jac,
                free_width,
            );
            if !free_width {
                // The width's row, column and gradient are 0 (its Jacobian column is): a
                // unit pivot makes its step 0.
                jtj[4][4] = 1.0;
            }
            let mut improved = false;
            let mut converged = false;
            for _try in 0..4 {
                let mut a = jtj;
                for (k, row) in a.iter_mut().enumerate() {
                    row[k] += lambda * jtj[k][k].max(1e-12);
                }
                let Some(delta) = solve_spd(&a, &jtr.map(|v| -v)) else {
                    lambda *= 10.0;
                    continue;
                };
                let mut q = p;
                for k in 0..5 {
                    q[k] += delta[k];
                }
                q[2] = q[2].max(0.0);
                q[3] = q[3].max(0.0);
                q[4] = q[4].clamp(
                    (MIN_ROUGHNESS * MIN_ROUGHNESS).ln(),
                    (facets.max_roughness().powi(2)).ln(),
                );
                let c = trial.evaluate(obs, &weights, &model_at(&base, &q, facets));
                if c < cost {
                    converged = cost - c < STEP_GAIN * cost;
                    (p, cost) = (q, c);
                    std::mem::swap(&mut now, &mut trial);
                    lambda = (lambda / 3.0).max(1e-9);
                    improved = true;
                    break;
                }
                lambda *= 4.0;
            }
            if !improved || converged {
                break;
            }
        }
        current = model_at(&base, &p, facets);
    }
    current
}

/// A model's residuals over the observations, and each observation's two terms
/// ([`Fitted::terms`]).
struct Point {
    residuals: Vec<f64>,
    terms: Vec<[f64; 2]>,
}

impl Point {
    fn new(len: usize) -> Self {
        Self {
            residuals: vec![0.0; len],
            terms: vec![[0.0; 2]; len],
        }
    }

    /// Evaluate `m` over `obs`: the weighted sum of squared residuals.
    fn evaluate(&mut self, obs: &[Observation], weights: &[f64], m: &Fitted) -> f64 {
        let lobe = m.lobe();
        let mut sum = 0.0;
        for (((r, t), o), w) in (self.residuals.iter_mut())
            .zip(&mut self.terms)
            .zip(obs)
            .zip(weights)
        {
            *t = m.terms(&lobe, o.light, o.intensity);
            *r = m.diffuse * t[0] + m.specular * t[1] - o.value;
            sum += w * *r * *r;
        }
        sum
    }
}

/// JᵀWJ and JᵀWr at `p` (evaluated in `at`): the albedos' columns are `at`'s terms, the
/// normal's and (if `free_width`, else 0) the width's by forward differences.
fn normal_equations(
    obs: &[Observation],
    weights: &[f64],
    (base, facets): (&Base, Facets),
    p: &Params,
    at: &Point,
    jac: &mut [[f64; 5]],
    free_width: bool,
) -> ([[f64; 5]; 5], [f64; 5]) {
    for (row, t) in jac.iter_mut().zip(&at.terms) {
        (row[2], row[3], row[4]) = (t[0], t[1], 0.0);
    }
    let columns: &[usize] = if free_width { &[0, 1, 4] } else { &[0, 1] };
    for &k in columns {
        let h = 1e-6 * p[k].abs().max(1e-2);
        let mut q = *p;
        q[k] += h;
        let m = model_at(base, &q, facets);
        let lobe = m.lobe();
        for (row, (o, r)) in jac.iter_mut().zip(obs.iter().zip(&at.residuals)) {
            row[k] = (m.predict_with(&lobe, o.light, o.intensity) - o.value - r) / h;
        }
    }
    let mut jtj = [[0.0; 5]; 5];
    let mut jtr = [0.0; 5];
    for ((row, w), r) in jac.iter().zip(weights).zip(&at.residuals) {
        for a in 0..5 {
            jtr[a] += w * row[a] * r;
            for b in 0..=a {
                jtj[a][b] += w * row[a] * row[b];
            }
        }
    }
    for a in 0..5 {
        for b in a + 1..5 {
            jtj[a][b] = jtj[b][a];
        }
    }
    (jtj, jtr)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lights(count: usize) -> Vec<[f64; 3]> {
        // Two rings, 20° and 45° from the axis.
        (0..count)
            .map(|i| {
                let polar = if i % 2 == 0 { 20f64 } else { 45f64 }.to_radians();
                let az = i as f64 / count as f64 * std::f64::consts::TAU;
                [polar.sin() * az.cos(), polar.sin() * az.sin(), polar.cos()]
            })
            .collect()
    }

    fn observe(truth: &Fitted, lights: &[[f64; 3]]) -> Vec<Observation> {
        lights
            .iter()
            .map(|&l| Observation {
                light: l,
                intensity: 1.0,
                value: truth.predict(l, 1.0),
            })
            .filter(|o| o.value > 0.0)
            .collect()
    }

    fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
        dot(a, b).clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// A broad lobe's pixel: from a Lambertian start several degrees off, the fit finds
    /// the normal, the albedos and the roughness.
    #[test]
    fn a_broad_lobe_is_fitted_with_its_normal() {
        let normal = normalise([0.2, -0.1, 1.0]);
        let truth = Fitted {
            normal,
            diffuse: 0.4,
            specular: 0.3,
            roughness: 0.4,
            facets: Facets::Ggx,
        };
        let obs = observe(&truth, &lights(24));
        let start = normalise([0.28, -0.05, 1.0]);
        let got = fit(&obs, start, 0.5, 0.001, None).expect("the lobe is kept");
        assert!(angle(got.normal, normal) < 0.05, "{got:?}");
        assert!((got.roughness - 0.4).abs() < 0.01, "{got:?}");
        assert!((got.diffuse - 0.4).abs() < 0.005 && (got.specular - 0.3).abs() < 0.01);
    }

    /// A pixel of either lobe family is fitted with its own family, normal and roughness:
    /// the other family's lobe, fitted in its place, would pull the normal.
    #[test]
    fn each_lobe_family_is_fitted_as_itself() {
        for facets in [Facets::Ggx, Facets::Beckmann] {
            let normal = normalise([0.15, 0.1, 1.0]);
            let truth = Fitted {
                normal,
                diffuse: 0.3,
                specular: 0.4,
                roughness: 0.5,
                facets,
            };
            let obs = observe(&truth, &lights(48));
            let start = normalise([0.22, 0.14, 1.0]);
            let got = fit(&obs, start, 0.35, 0.001, None).expect("the lobe is kept");
            assert_eq!(got.facets, facets, "{got:?}");
            assert!(angle(got.normal, normal) < 0.05, "{got:?}");
            assert!((got.roughness - 0.5).abs() < 0.01, "{got:?}");
        }
    }

    /// Given the shared material, a pixel of it is fitted at that width; a pixel of
    /// another material (a broad lobe where the shared one is narrow) still gets its own.
    #[test]
    fn a_shared_material_is_fitted_and_another_falls_back_to_its_own() {
        let normal = normalise([0.1, 0.2, 1.0]);
        let shared = Material {
            facets: Facets::Ggx,
            roughness: 0.3,
        };
        let truth = Fitted {
            normal,
            diffuse: 0.3,
            specular: 0.5,
            roughness: 0.3,
            facets: Facets::Ggx,
        };
        let start = normalise([0.16, 0.15, 1.0]);
        let obs = observe(&truth, &lights(48));
        let got = fit(&obs, start, 0.4, 0.001, Some(shared)).expect("the lobe is kept");
        assert!(angle(got.normal, normal) < 0.05, "{got:?}");
        assert_eq!(got.roughness, 0.3);
        let broad = Fitted {
            roughness: 0.6,
            ..truth
        };
        let obs = observe(&broad, &lights(48));
        let got = fit(&obs, start, 0.4, 0.001, Some(shared)).expect("the lobe is kept");
        assert!(angle(got.normal, normal) < 0.05, "{got:?}");
        assert!((got.roughness - 0.6).abs() < 0.01, "{got:?}");
    }

    /// A Lambertian pixel keeps its Lambertian fit.
    #[test]
    fn a_matte_pixel_is_left_lambertian() {
        let normal = normalise([-0.3, 0.1, 1.0]);
        let truth = Fitted {
            normal,
            diffuse: 0.6,
            specular: 0.0,
            roughness: 0.3,
            facets: Facets::Ggx,
        };
        let obs = observe(&truth, &lights(24));
        assert_eq!(fit(&obs, normal, 0.6, 0.001, None), None);
    }
}
