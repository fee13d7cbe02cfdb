//! The specular lobe the fit uses: a microfacet lobe with separable Smith shadowing, seen
//! by the orthographic camera looking down −z (v = (0, 0, 1)), its facets' slopes
//! distributed by GGX (Trowbridge–Reitz) or by Beckmann ([`Facets`]). Fresnel is left
//! out: over the angles a fixed camera sees, it moves little and the fitted specular
//! albedo absorbs it.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::core::vec3::dot;

/// How a lobe's microfacet slopes are distributed, which sets how fast the highlight
/// falls off away from its peak. Real surfaces differ: rough plastics and many metals
/// show GGX's long tails (a haze around the highlight), polished, lacquered and glazed
/// surfaces the faster, Gaussian fall-off of Beckmann's distribution (of which Ward's and
/// Blinn–Phong's lobes are close relatives). A lobe of the wrong family misplaces the
/// normal it is fitted with, so the fit tries both.
///
/// Both are parametrised by GGX's width `alpha` (roughness², as renderers and glTF take
/// it), so that one roughness map serves both: a Beckmann lobe of width `alpha` is the one
/// as wide at half its peak as GGX's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum Facets {
    Ggx,
    Beckmann,
}

impl Facets {
    /// The broadest lobe of this family the fit tries, as a roughness (√alpha).
    pub fn max_roughness(self) -> f64 {
        match self {
            Self::Ggx => MAX_GGX_ROUGHNESS,
            Self::Beckmann => (MAX_BECKMANN_SLOPE * BECKMANN_SLOPE).sqrt(),
        }
    }

    /// The lobe of this family and width `alpha` (GGX's, = roughness²) about unit normal
    /// `n`: what does not depend on the light worked out once, as a pixel's fit evaluates
    /// it under every light.
    pub fn about(self, n: [f64; 3], alpha: f64) -> Lobe {
        // Grazing views make the 1/(n·v) factor explode; no pixel of a real object is fit
        // that close to its silhouette.
        let nv = n[2].max(0.05);
        let (width, view) = match self {
            Self::Ggx => {
                let a2 = alpha * alpha;
                (a2, ggx_g1(nv, a2))
            }
            Self::Beckmann => {
                let m = alpha / BECKMANN_SLOPE;
                (m, beckmann_g1(nv, m))
            }
        };
        Lobe {
            facets: self,
            n,
            width,
            // π D G / (4 n·v) = (π D) · G(l) · [G(v) / (4 n·v)]: the bracket does not
            // depend on the light.
            scale: if n[2] > 0.0 { view / (4.0 * nv) } else { 0.0 },
        }
    }
}

/// A lobe about one normal ([`Facets::about`]), ready to be evaluated under any light.
#[derive(Debug, Clone, Copy)]
pub struct Lobe {
    facets: Facets,
    n: [f64; 3],
    /// GGX's alpha², or Beckmann's RMS slope.
    width: f64,
    /// The view's shadowing over 4 n·v; 0 when the camera is below the surface.
    scale: f64,
}

impl Lobe {
    /// The lobe's image value per unit specular albedo and unit irradiance under unit
    /// light `l`: π · D · G / (4 n·v), so that it adds to the diffuse term albedo · n·l as
    /// a Cook–Torrance BRDF times n·l would. Zero when the light or the camera is below
    /// the surface.
    pub fn at(&self, l: [f64; 3]) -> f64 {
        let n = self.n;
        let nl = dot(n, l);
        if nl <= 0.0 || self.scale == 0.0 {
            return 0.0;
        }
        let h = [l[0], l[1], l[2] + 1.0];
        let nh2 = {
            let nh = dot(n, h);
            if nh <= 0.0 {
                return 0.0;
            }
            nh * nh / dot(h, h)
        };
        // π D, and the light's shadowing.
        let (distribution_pi, light) = match self.facets {
            Facets::Ggx => {
                let a2 = self.width;
                let d = nh2 * (a2 - 1.0) + 1.0;
                (a2 / (d * d), ggx_g1(nl, a2))
            }
            Facets::Beckmann => {
                let m2 = self.width * self.width;
                let d = (-(1.0 - nh2) / (nh2 * m2)).exp() / (m2 * nh2 * nh2);
                (d, beckmann_g1(nl, self.width))
            }
        };
        distribution_pi * light * self.scale
    }
}

/// Smith's shadowing of one direction at cosine `x` to the normal over GGX facets of
/// width² `a2`.
fn ggx_g1(x: f64, a2: f64) -> f64 {
    2.0 * x / (x + (a2 + (1.0 - a2) * x * x).sqrt())
}

/// The broadest GGX lobe fitted.
const MAX_GGX_ROUGHNESS: f64 = 0.95;
/// The largest RMS slope of a Beckmann lobe fitted. Past about 0.5 its Gaussian is nearly
/// as broad as the cosine of a diffuse term, and the two with a tilted normal fit a matte
/// pixel's interreflection as well as a highlight: with slopes up to 0.7 on
/// `res/soft-shadows` the lobe was kept at 274 pixels, their normals turned 16° on average,
/// and the mean error rose from 1.72° to 2.07°.
const MAX_BECKMANN_SLOPE: f64 = 0.5;

/// GGX's width over the RMS slope of the Beckmann lobe as wide at half its peak: near the
/// peak GGX falls to half at tan²θ_h = (√2 − 1) alpha², Beckmann at ln 2 · m².
const BECKMANN_SLOPE: f64 = 1.293_595_2;

/// Smith's shadowing of one direction at cosine `x` to the normal over Beckmann facets of
/// RMS slope `m`, in Walter et al.'s rational form (EGSR 2007, within 0.35 % of the
/// exact one).
fn beckmann_g1(x: f64, m: f64) -> f64 {
    let sin = (1.0 - x * x).max(0.0).sqrt();
    if sin <= 0.0 {
        return 1.0;
    }
    let a = x / (m * sin);
    if a >= 1.6 {
        return 1.0;
    }
    (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(deg: f64) -> [f64; 3] {
        let t = deg.to_radians();
        [t.sin(), 0.0, t.cos()]
    }

    /// Each lobe peaks on the mirror direction and narrows as alpha falls.
    #[test]
    fn the_lobe_peaks_at_the_mirror_direction_and_narrows_with_alpha() {
        let n = [0.0, 0.0, 1.0];
        for facets in [Facets::Ggx, Facets::Beckmann] {
            let lobe = |l, alpha| facets.about(n, alpha).at(l);
            for alpha in [0.05, 0.2, 0.5] {
                let peak = lobe(at(0.0), alpha);
                assert!(peak > lobe(at(10.0), alpha), "{facets:?} alpha {alpha}");
                assert!(lobe(at(10.0), alpha) > lobe(at(30.0), alpha));
            }
            let ratio = |alpha| lobe(at(20.0), alpha) / lobe(at(0.0), alpha);
            assert!(ratio(0.05) < ratio(0.2) && ratio(0.2) < ratio(0.5));
            assert_eq!(lobe([0.0, 0.0, -1.0], 0.2), 0.0);
            assert_eq!(facets.about([0.6, 0.0, -0.8], 0.2).at(at(0.0)), 0.0);
        }
    }

    /// Far from the peak GGX's tail keeps orders of magnitude more than Beckmann's of the
    /// same width: what tells the two apart in a pixel's observations.
    #[test]
    fn ggx_has_the_longer_tail() {
        let n = [0.0, 0.0, 1.0];
        let alpha = 0.2;
        let tail = |f: Facets| f.about(n, alpha).at(at(60.0)) / f.about(n, alpha).at(at(0.0));
        assert!(tail(Facets::Ggx) > 100.0 * tail(Facets::Beckmann));
        // Near the peak the two agree to within a few percent, and at half the peak's value
        // they are equally wide.
        let near = |f: Facets| f.about(n, alpha).at(at(4.0)) / f.about(n, alpha).at(at(0.0));
        assert!((near(Facets::Ggx) / near(Facets::Beckmann) - 1.0).abs() < 0.05);
        let narrow = 0.05;
        let half = |f: Facets| {
            let lobe = f.about(n, narrow);
            let peak = lobe.at(at(0.0));
            (1..2000)
                .map(|k| k as f64 * 0.01)
                .find(|&d| lobe.at(at(d)) < 0.5 * peak)
        };
        let (g, b) = (half(Facets::Ggx).unwrap(), half(Facets::Beckmann).unwrap());
        assert!((g - b).abs() <= 0.02 * g, "half widths {g}° and {b}°");
    }
}
