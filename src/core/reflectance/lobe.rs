//! The specular lobe the fit uses: GGX (Trowbridge–Reitz) microfacets with separable
//! Smith shadowing, seen by the orthographic camera looking down −z (v = (0, 0, 1)).
//! Fresnel is left out: over the angles a fixed camera sees, it moves little and the
//! fitted specular albedo absorbs it.

use crate::core::vec3::dot;
use std::f64::consts::PI;

/// The lobe's image value per unit specular albedo and unit irradiance, for unit normal
/// `n`, unit light `l` and width `alpha` (= roughness²): π · D · G / (4 n·v), so that it
/// adds to the diffuse term albedo · n·l as a Cook–Torrance BRDF times n·l would. Zero
/// when the light or the camera is below the surface.
pub fn ggx_lobe(n: [f64; 3], l: [f64; 3], alpha: f64) -> f64 {
    let nl = dot(n, l);
    // Grazing views make the 1/(n·v) factor explode; no pixel of a real object is fit
    // that close to its silhouette.
    let nv = n[2].max(0.05);
    if nl <= 0.0 || n[2] <= 0.0 {
        return 0.0;
    }
    let h = [l[0], l[1], l[2] + 1.0];
    let hn = dot(h, h).sqrt();
    let nh = dot(n, h) / hn;
    if nh <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let d = nh * nh * (a2 - 1.0) + 1.0;
    let distribution = a2 / (PI * d * d);
    let g1 = |x: f64| 2.0 * x / (x + (a2 + (1.0 - a2) * x * x).sqrt());
    PI * distribution * g1(nl) * g1(nv) / (4.0 * nv)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lobe peaks on the mirror direction and narrows as alpha falls.
    #[test]
    fn the_lobe_peaks_at_the_mirror_direction_and_narrows_with_alpha() {
        let n = [0.0, 0.0, 1.0];
        let at = |deg: f64| {
            let t = deg.to_radians();
            [t.sin(), 0.0, t.cos()]
        };
        for alpha in [0.05, 0.2, 0.5] {
            let peak = ggx_lobe(n, at(0.0), alpha);
            assert!(peak > ggx_lobe(n, at(10.0), alpha), "alpha {alpha}");
            assert!(ggx_lobe(n, at(10.0), alpha) > ggx_lobe(n, at(30.0), alpha));
        }
        let ratio = |alpha| ggx_lobe(n, at(20.0), alpha) / ggx_lobe(n, at(0.0), alpha);
        assert!(ratio(0.05) < ratio(0.2) && ratio(0.2) < ratio(0.5));
        assert_eq!(ggx_lobe(n, [0.0, 0.0, -1.0], 0.2), 0.0);
    }
}
