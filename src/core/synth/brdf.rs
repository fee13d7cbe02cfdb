//! The renderer's reflectance models, seen by the orthographic camera looking down -z
//! (view vector v = (0, 0, 1)): a diffuse base (Lambertian or Oren–Nayar) and an optional
//! specular lobe (Blinn–Phong, GGX Cook–Torrance or Ward).
//!
//! Values are in pixel units: a unit light (irradiance 1 at normal incidence) on a
//! Lambertian pixel gives albedo · n·l, i.e. π · BRDF · n·l, so a specular BRDF f_s adds
//! π · f_s · n·l.

use crate::core::vec3::{dot, normalise};
use std::f64::consts::PI;

/// A specular lobe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Specular {
    /// Blinn–Phong: strength · (n·h)^shininess (an empirical lobe, not energy-bounded).
    BlinnPhong { strength: f64, shininess: f64 },
    /// Cook–Torrance microfacets: GGX (Trowbridge–Reitz) distribution of width `alpha`
    /// (= roughness²), Smith shadowing-masking, Schlick Fresnel with normal-incidence
    /// reflectance `f0` (0.04 for a dielectric coat of index 1.5).
    CookTorrance { alpha: f64, f0: f64 },
    /// Ward's isotropic Gaussian lobe in the Ward–Dür normalisation (Dür 2006: the
    /// 1/sqrt(n·l n·v) of Ward's 1992 form becomes 1/(n·l n·v), which keeps the lobe's
    /// albedo at most `strength`): strength · exp(−tan²θ_h / alpha²) / (4π alpha² n·l n·v),
    /// `alpha` the RMS slope of the microfacets.
    Ward { alpha: f64, strength: f64 },
}

/// The diffuse base under the specular lobe.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Diffuse {
    /// albedo · n·l.
    #[default]
    Lambert,
    /// Oren–Nayar's qualitative model of a rough diffuse surface: V-groove facets whose
    /// slopes have standard deviation `sigma` (radians). Brighter than Lambert towards
    /// the light's side at grazing angles, flatter overall (retro-reflection).
    OrenNayar { sigma: f64 },
}

impl Diffuse {
    /// The factor on Lambert's n·l for unit normal `n` and unit light `l` (n·l > 0): 1 for
    /// Lambert, A + B · max(0, cos(φ_l − φ_v)) · sin α · tan β for Oren–Nayar.
    pub(super) fn factor(&self, n: [f64; 3], l: [f64; 3]) -> f64 {
        match *self {
            Self::Lambert => 1.0,
            Self::OrenNayar { sigma } => oren_nayar(n, l, [0.0, 0.0, 1.0], sigma),
        }
    }
}

/// Oren–Nayar's qualitative factor A + B · max(0, cos Δφ) · sin α · tan β, with α, β the
/// larger and smaller of the light's and the view's angles to `n`.
fn oren_nayar(n: [f64; 3], l: [f64; 3], v: [f64; 3], sigma: f64) -> f64 {
    let s2 = sigma * sigma;
    let a = 1.0 - 0.5 * s2 / (s2 + 0.33);
    let b = 0.45 * s2 / (s2 + 0.09);
    let (nl, nv) = (dot(n, l).clamp(-1.0, 1.0), dot(n, v).clamp(-1.0, 1.0));
    if nl <= 0.0 || nv <= 0.0 {
        return a;
    }
    // The azimuths' cosine from the projections onto the tangent plane; either projection
    // vanishing (light or view along n) makes β = 0 or α's partner 0, so the term is 0.
    let lt = [l[0] - nl * n[0], l[1] - nl * n[1], l[2] - nl * n[2]];
    let vt = [v[0] - nv * n[0], v[1] - nv * n[1], v[2] - nv * n[2]];
    let norms = (dot(lt, lt) * dot(vt, vt)).sqrt();
    if norms < 1e-12 {
        return a;
    }
    let cos_dphi = (dot(lt, vt) / norms).max(0.0);
    let (ti, tr) = (nl.acos(), nv.acos());
    let (alpha, beta) = (ti.max(tr), ti.min(tr));
    a + b * cos_dphi * alpha.sin() * beta.tan()
}

impl Specular {
    /// The lobe's pixel value for unit normal `n` and unit light `l` (n·l > 0).
    pub(super) fn value(&self, n: [f64; 3], l: [f64; 3]) -> f64 {
        match *self {
            Self::BlinnPhong {
                strength,
                shininess,
            } => {
                let h = [l[0], l[1], l[2] + 1.0];
                let hl = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
                let ndh = (n[0] * h[0] + n[1] * h[1] + n[2] * h[2]) / hl;
                strength * ndh.max(0.0).powf(shininess)
            }
            Self::CookTorrance { alpha, f0 } => {
                PI * cook_torrance(n, l, [0.0, 0.0, 1.0], alpha, f0) * dot(n, l)
            }
            Self::Ward { alpha, strength } => {
                PI * ward(n, l, [0.0, 0.0, 1.0], alpha, strength) * dot(n, l)
            }
        }
    }
}

/// The Cook–Torrance BRDF D·G·F / (4 n·l n·v), 0 when either direction is below the
/// surface.
pub(super) fn cook_torrance(n: [f64; 3], l: [f64; 3], v: [f64; 3], alpha: f64, f0: f64) -> f64 {
    let (nl, nv) = (dot(n, l), dot(n, v));
    if nl <= 0.0 || nv <= 0.0 {
        return 0.0;
    }
    let h = normalise([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
    let fresnel = f0 + (1.0 - f0) * (1.0 - dot(v, h).clamp(0.0, 1.0)).powi(5);
    ggx(dot(n, h), alpha) * smith_g1(nl, alpha) * smith_g1(nv, alpha) * fresnel / (4.0 * nl * nv)
}

/// The Ward–Dür BRDF, 0 when either direction is below the surface.
pub(super) fn ward(n: [f64; 3], l: [f64; 3], v: [f64; 3], alpha: f64, strength: f64) -> f64 {
    let (nl, nv) = (dot(n, l), dot(n, v));
    if nl <= 0.0 || nv <= 0.0 {
        return 0.0;
    }
    let h = normalise([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
    let nh = dot(n, h);
    if nh <= 0.0 {
        return 0.0;
    }
    let tan2 = (1.0 - nh * nh).max(0.0) / (nh * nh);
    let a2 = alpha * alpha;
    strength * (-tan2 / a2).exp() / (4.0 * PI * a2 * nl * nv)
}

/// The GGX normal distribution D(h) for cos θ_h = `nh`; ∫ D(h) (n·h) dω_h = 1.
pub(super) fn ggx(nh: f64, alpha: f64) -> f64 {
    if nh <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let d = nh * nh * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

/// Smith's masking for GGX, one direction at cos θ = `c`.
fn smith_g1(c: f64, alpha: f64) -> f64 {
    let a2 = alpha * alpha;
    2.0 * c / (c + (a2 + (1.0 - a2) * c * c).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∫ over the upper hemisphere of f(direction) dω, by the midpoint rule in (θ, φ).
    fn hemisphere(f: impl Fn([f64; 3]) -> f64) -> f64 {
        let (nt, np) = (2000, 400);
        let (dt, dp) = (0.5 * PI / nt as f64, 2.0 * PI / np as f64);
        let mut sum = 0.0;
        for i in 0..nt {
            let t = (i as f64 + 0.5) * dt;
            for j in 0..np {
                let p = (j as f64 + 0.5) * dp;
                let d = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
                sum += f(d) * t.sin() * dt * dp;
            }
        }
        sum
    }

    const N: [f64; 3] = [0.0, 0.0, 1.0];

    #[test]
    fn ggx_distribution_is_normalised() {
        for alpha in [0.05, 0.09, 0.3] {
            let total = hemisphere(|h| ggx(h[2], alpha) * h[2]);
            assert!((total - 1.0).abs() < 0.01, "alpha {alpha}: {total}");
        }
    }

    #[test]
    fn lobe_reflects_at_most_the_light_it_receives() {
        // Even a perfect mirror coat (f0 = 1) returns no more than it receives, from any
        // view; the masking term makes it lose some at grazing views.
        for alpha in [0.05, 0.09, 0.3] {
            for view_deg in [0.0f64, 30.0, 60.0, 80.0] {
                let t = view_deg.to_radians();
                let v = [t.sin(), 0.0, t.cos()];
                let albedo = hemisphere(|l| cook_torrance(N, l, v, alpha, 1.0) * l[2]);
                assert!(
                    albedo <= 1.0 && albedo > 0.5,
                    "{alpha} {view_deg}: {albedo}"
                );
            }
        }
    }

    #[test]
    fn ward_lobe_reflects_about_its_strength() {
        // The Ward–Dür normalisation: a lobe of strength 1 returns close to all it
        // receives at normal view, and never more, at any width.
        for alpha in [0.05, 0.15, 0.3] {
            for view_deg in [0.0f64, 30.0, 60.0] {
                let t = view_deg.to_radians();
                let v = [t.sin(), 0.0, t.cos()];
                let albedo = hemisphere(|l| ward(N, l, v, alpha, 1.0) * l[2]);
                assert!(
                    albedo <= 1.0 && albedo > 0.8,
                    "{alpha} {view_deg}: {albedo}"
                );
            }
        }
    }

    #[test]
    fn ward_lobe_peaks_at_the_mirror_direction_and_widens_with_alpha() {
        let tilt = 20f64.to_radians();
        let n = [tilt.sin(), 0.0, tilt.cos()];
        let value = |alpha: f64, deg: f64| {
            let a = deg.to_radians();
            Specular::Ward {
                alpha,
                strength: 0.5,
            }
            .value(n, [a.sin(), 0.0, a.cos()])
        };
        for alpha in [0.1, 0.3] {
            let best = (0..=800)
                .map(|i| i as f64 * 0.1)
                .max_by(|a, b| value(alpha, *a).total_cmp(&value(alpha, *b)))
                .unwrap();
            assert!((best - 40.0).abs() < 1.5, "alpha {alpha}: peak at {best}°");
        }
        let falloff = |alpha| value(alpha, 55.0) / value(alpha, 40.0);
        // 15° off the mirror direction the half vector is 7.5° off n.
        assert!(
            falloff(0.1) < 0.25 && falloff(0.3) > 0.7,
            "{} {}",
            falloff(0.1),
            falloff(0.3)
        );
    }

    #[test]
    fn oren_nayar_is_lambert_at_zero_roughness_and_flatter_when_rough() {
        let at = |deg: f64| {
            let a = deg.to_radians();
            [a.sin(), 0.0, a.cos()]
        };
        let tilt = 40f64.to_radians();
        let n = [tilt.sin(), 0.0, tilt.cos()];
        for deg in [-30.0, 0.0, 30.0, 60.0] {
            let f = Diffuse::OrenNayar { sigma: 0.0 }.factor(n, at(deg));
            assert!((f - 1.0).abs() < 1e-12, "{deg}: {f}");
        }
        let rough = Diffuse::OrenNayar { sigma: 0.4 };
        // Facing the camera, light from the view side: the groove term is 0, only A.
        assert!((rough.factor(N, at(30.0)) - (1.0 - 0.5 * 0.16 / 0.49)).abs() < 1e-12);
        // A tilted facet lit from beside the camera (same azimuth as the view) gains on
        // Lambert's share; lit from the far side it keeps only A.
        let near = rough.factor(n, at(10.0));
        let far = rough.factor(n, at(75.0));
        assert!(near > far, "near {near}, far {far}");
        assert!((far - rough.factor(N, at(30.0))).abs() < 1e-12, "{far}");
    }

    #[test]
    fn lobe_peaks_at_the_mirror_direction() {
        let alpha = 0.09;
        let v = [0.0, 0.0, 1.0];
        // A tilted surface seen from above: light mirrored about n is at twice the tilt.
        let tilt = 20f64.to_radians();
        let n = [tilt.sin(), 0.0, tilt.cos()];
        let value = |deg: f64| {
            let a = deg.to_radians();
            cook_torrance(n, [a.sin(), 0.0, a.cos()], v, alpha, 0.04)
                * dot(n, [a.sin(), 0.0, a.cos()])
        };
        let best = (0..=800)
            .map(|i| i as f64 * 0.1)
            .max_by(|a, b| value(*a).total_cmp(&value(*b)))
            .unwrap();
        assert!((best - 40.0).abs() < 1.0, "peak at {best}°");
        assert!(value(40.0) > 20.0 * value(60.0), "a narrow lobe");
    }
}
