//! Depth under a pinhole camera: the log-depth formulation, in which every integrator of
//! this module works unchanged.
//!
//! A surface point on pixel `(u, v)`'s ray `d = ((u − cx)/fx, (v − cy)/fy, −1)` at depth
//! `D` is `X = D d`. Its tangent `∂X/∂u = D_u d + D (1/fx, 0, 0)` is orthogonal to the
//! normal `n`, so `(ln D)_u = −n_x / (fx n·d)` and likewise `(ln D)_v = −n_y / (fy n·d)`:
//! the gradients of `ln D` are a plain gradient field, whatever the depth. Integrating
//! `ζ = −fx ln D` rather than `ln D` keeps the integrators' units: `ζ` moves like a
//! height in pixels (`ζ_u ≈ −n_x/n_z` near the axis, exactly the orthographic slope), so
//! their tolerances and step thresholds mean the same. Depth is `exp(−ζ / fx)` up to one
//! scale per connected piece of the mask, which a working distance fixes.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::gradients::MIN_NZ;
use crate::core::camera::Pinhole;

/// Gradients `(ζ_u, ζ_v)` of `ζ = −fx ln D` from camera-frame normals, 0 off the mask.
///
/// Normals are renormalised; where a normal faces the ray at a grazing angle (`−n·d̂ <`
/// [`MIN_NZ`]) or away from the camera it is taken at that bound, which keeps slopes below
/// ~20 as the orthographic [`super::gradients`] does. Zero-length or non-finite normals
/// give zero gradients.
pub fn log_depth_gradients(
    normals: &Array3<f32>,
    mask: &Array2<bool>,
    camera: &Pinhole,
) -> (Array2<f32>, Array2<f32>) {
    let (h, w) = mask.dim();
    assert_eq!(normals.dim(), (h, w, 3), "normals must be (rows, cols, 3)");
    let mut p = Array2::zeros((h, w));
    let mut q = Array2::zeros((h, w));
    let ratio = camera.fx / camera.fy;
    (p.outer_iter_mut().into_par_iter())
        .zip(q.outer_iter_mut().into_par_iter())
        .enumerate()
        .for_each(|(r, (mut p, mut q))| {
            for c in 0..w {
                if !mask[[r, c]] {
                    continue;
                }
                let n = [0, 1, 2].map(|k| f64::from(normals[[r, c, k]]));
                let len = n.iter().map(|v| v * v).sum::<f64>().sqrt();
                if !(len.is_finite() && len > 0.0) {
                    continue;
                }
                let n = n.map(|v| v / len);
                let d = camera.ray(c as f64, r as f64);
                let dl = d.iter().map(|v| v * v).sum::<f64>().sqrt();
                // n·d < 0 for a surface seen from the front.
                let nd = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).min(-f64::from(MIN_NZ) * dl);
                p[c] = (n[0] / nd) as f32;
                q[c] = (ratio * n[1] / nd) as f32;
            }
        });
    (p, q)
}

/// Each pixel's facing weights for [`super::bilateral`] (0 off the mask and for unusable
/// normals), two squared cosines clamped to at least [`MIN_NZ`] as
/// [`log_depth_gradients`] clamps the slopes.
pub struct Facing {
    /// Weighs the pixel's equations: the smaller of its unit normal's cosines to the
    /// viewing ray and to the optical axis (`n_z`). The slopes are `n_x / (n·d)`, so the
    /// ray's cosine makes each equation the well-posed normal form: an occluding contour
    /// off the axis, square to the ray but not to the axis, gets the small weight its
    /// unbounded slopes need (`n_z` alone leaves the rendered scenes' contours 30° off the
    /// axis at full weight, and three times the depth error). Where the two differ, near
    /// contours, the smaller is taken: on the DiLiGenT objects the ray's alone cost a
    /// third more depth error than `n_z` on cat and over half more on harvest
    /// (`docs/benchmarks.md`).
    pub equations: Array2<f32>,
    /// Scales the height differences by which the pixel chooses its side of a step:
    /// `n_z`. With the equations' weight here, a rim that grazes the rays sits at the
    /// floor, never sides, and leaves the object in front hanging on the one behind.
    pub sides: Array2<f32>,
}

/// [`Facing`] for camera-frame `normals` under `camera`.
pub fn facing(normals: &Array3<f32>, mask: &Array2<bool>, camera: &Pinhole) -> Facing {
    let (h, w) = mask.dim();
    assert_eq!(normals.dim(), (h, w, 3), "normals must be (rows, cols, 3)");
    let mut equations = Array2::zeros((h, w));
    let mut sides = Array2::zeros((h, w));
    let floor = f64::from(MIN_NZ);
    (equations.outer_iter_mut().into_par_iter())
        .zip(sides.outer_iter_mut().into_par_iter())
        .enumerate()
        .for_each(|(r, (mut eq, mut side))| {
            for c in 0..w {
                let n = [0, 1, 2].map(|k| f64::from(normals[[r, c, k]]));
                let len = n.iter().map(|v| v * v).sum::<f64>().sqrt();
                if !(mask[[r, c]] && len.is_finite() && len > 0.0) {
                    continue;
                }
                let d = camera.ray(c as f64, r as f64);
                let dl = d.iter().map(|v| v * v).sum::<f64>().sqrt();
                let to_ray = -(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / (len * dl);
                let to_axis = n[2] / len;
                eq[c] = to_ray.min(to_axis).max(floor).powi(2) as f32;
                side[c] = to_axis.max(floor).powi(2) as f32;
            }
        });
    Facing { equations, sides }
}

/// Depth along the optical axis from `ζ` ([`log_depth_gradients`]' integral), NaN off the
/// mask: relative (median 1 over the mask) without `distance`, else scaled so that the
/// median depth over the mask is `distance`.
pub fn depth_from_log(
    zeta: &Array2<f32>,
    mask: &Array2<bool>,
    camera: &Pinhole,
    distance: Option<f64>,
) -> Array2<f32> {
    let fx = camera.fx;
    let mut on: Vec<f64> = (zeta.iter().zip(mask))
        .filter(|(z, m)| **m && z.is_finite())
        .map(|(z, _)| f64::from(*z))
        .collect();
    // The median of exp(−ζ/fx) is exp(−median ζ / fx): take the median of ζ.
    let mid = if on.is_empty() {
        0.0
    } else {
        let k = on.len() / 2;
        *on.select_nth_unstable_by(k, f64::total_cmp).1
    };
    let scale = distance.unwrap_or(1.0);
    let mut depth = Array2::from_elem(mask.dim(), f32::NAN);
    ndarray::Zip::from(&mut depth)
        .and(zeta)
        .and(mask)
        .for_each(|d, &z, &m| {
            if m && z.is_finite() {
                *d = (scale * (-(f64::from(z) - mid) / fx).exp()) as f32;
            }
        });
    depth
}

/// `ζ = −fx ln D` of a positive `depth` on the mask (0 off it and where `depth` is not
/// positive and finite): [`depth_from_log`]'s inverse up to its scale.
pub fn log_from_depth(depth: &Array2<f32>, mask: &Array2<bool>, camera: &Pinhole) -> Array2<f32> {
    let fx = camera.fx;
    let mut zeta = Array2::zeros(mask.dim());
    ndarray::Zip::from(&mut zeta)
        .and(depth)
        .and(mask)
        .for_each(|z, &d, &m| {
            if m && d.is_finite() && d > 0.0 {
                *z = (-fx * f64::from(d).ln()) as f32;
            }
        });
    zeta
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane's normal, seen through any pixel, integrates to the plane's own depths.
    #[test]
    fn a_tilted_plane_comes_back_as_its_depths() {
        let cam = Pinhole {
            fx: 300.0,
            fy: 280.0,
            cx: 20.0,
            cy: 14.0,
        };
        let (h, w) = (30, 40);
        // Plane n·X = −c: points X = D d with D = c / (−n·d).
        let n = {
            let v = [0.3f64, -0.2, 0.9];
            let l = v.iter().map(|x| x * x).sum::<f64>().sqrt();
            v.map(|x| x / l)
        };
        let normals = Array3::from_shape_fn((h, w, 3), |(_, _, k)| n[k] as f32);
        let mask = Array2::from_elem((h, w), true);
        let (p, q) = log_depth_gradients(&normals, &mask, &cam);
        let zeta =
            super::super::integrate(&p, &q, &mask, crate::core::options::Integration::Poisson);
        let depth = depth_from_log(&zeta, &mask, &cam, None);
        let truth = Array2::from_shape_fn((h, w), |(r, c)| {
            let d = cam.ray(c as f64, r as f64);
            1.0 / -(n[0] * d[0] + n[1] * d[1] + n[2] * d[2])
        });
        // Compare shapes: both scaled to median 1.
        let mut t: Vec<f64> = truth.iter().copied().collect();
        let k = t.len() / 2;
        let mid = *t.select_nth_unstable_by(k, f64::total_cmp).1;
        let worst = (depth.iter().zip(truth.iter()))
            .map(|(&d, &t)| (f64::from(d) - t / mid).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-4, "largest relative depth error {worst}");
    }

    /// A contour 30° off the axis, square to its ray while its `n_z` is 0.5, weighs its
    /// equations at the floor but keeps `n_z²` to choose its side; a normal along the ray
    /// there weighs both by `n_z²`, and one along the axis its equations by the ray's
    /// cosine.
    #[test]
    fn an_off_axis_contour_weighs_its_equations_at_the_floor() {
        let off = 100.0 * 30f64.to_radians().tan();
        let cam = Pinhole {
            fx: 100.0,
            fy: 100.0,
            cx: 1.0 - off,
            cy: 0.0,
        };
        let d = cam.ray(1.0, 0.0);
        let dl = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let along = d.map(|v| -v / dl);
        let square = [30f64.to_radians().cos(), 0.0, 30f64.to_radians().sin()];
        let normals = Array3::from_shape_fn((1, 3, 3), |(_, c, k)| match c {
            1 => square[k] as f32,
            2 => along[k] as f32,
            _ => [0.0, 0.0, 1.0][k],
        });
        let mask = Array2::from_elem((1, 3), true);
        let f = facing(&normals, &mask, &cam);
        let floor = MIN_NZ * MIN_NZ;
        assert!(
            (f.equations[[0, 1]] - floor).abs() < 1e-6,
            "{}",
            f.equations[[0, 1]]
        );
        assert!((f.sides[[0, 1]] - 0.25).abs() < 1e-5, "{}", f.sides[[0, 1]]);
        // Pixel 2 sees a ray slightly further off the axis than pixel 1's.
        let nz2 = (along[2] * along[2]) as f32;
        assert!(
            (f.equations[[0, 2]] - nz2).abs() < 1e-3,
            "{}",
            f.equations[[0, 2]]
        );
        assert!((f.sides[[0, 2]] - nz2).abs() < 1e-5);
        // A normal along the axis, seen off it, weighs its equations by the ray's cosine.
        let d0 = cam.ray(0.0, 0.0);
        let cos2 = (1.0 / d0.iter().map(|v| v * v).sum::<f64>()) as f32;
        assert!(
            (f.equations[[0, 0]] - cos2).abs() < 1e-5,
            "{}",
            f.equations[[0, 0]]
        );
        assert_eq!(f.sides[[0, 0]], 1.0);
    }
}
