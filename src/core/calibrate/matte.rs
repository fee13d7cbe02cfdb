//! Relative light intensities from a matte white sphere under the same lights: with the
//! directions known and the sphere's normals known from its outline, each image is
//! I = k·max(0, n·l) + b over the sphere (Lambertian, b the ambient and black level);
//! k, fitted by least squares over the lit, unclipped pixels well inside the outline,
//! is the light's intensity up to the sphere's albedo, which cancels in k / mean(k).

use ndarray::Array2;

use super::circle::Circle;
use crate::core::vec3::dot;

/// Fraction of the radius used: the rim's pixels mix sphere and backdrop.
const INNER: f64 = 0.9;
/// Smallest n·l used: near the terminator a small direction error moves n·l the most.
const MIN_COSINE: f64 = 0.15;

/// One image's intensity k (up to the sphere's albedo, to be divided by the set's mean),
/// or why it cannot be fitted. `plane` needs to hold the sphere's box at least
/// (`circle` in its coordinates).
pub fn intensity(
    plane: &Array2<u16>,
    l: [f64; 3],
    circle: &Circle,
    clip: u16,
) -> Result<f64, String> {
    let (h, w) = plane.dim();
    // Sums for the 2-parameter least squares I = k s + b.
    let (mut n, mut ss, mut s1, mut si, mut i1) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for r in 0..h {
        for c in 0..w {
            let (u, v) = (
                (c as f64 - circle.cx) / circle.r,
                (r as f64 - circle.cy) / circle.r,
            );
            let rho2 = u * u + v * v;
            if rho2 > INNER * INNER || plane[[r, c]] >= clip {
                continue;
            }
            let s = dot([u, v, (1.0 - rho2).sqrt()], l);
            if s < MIN_COSINE {
                continue;
            }
            let value = plane[[r, c]] as f64 / 65535.0;
            n += 1.0;
            ss += s * s;
            s1 += s;
            si += s * value;
            i1 += value;
        }
    }
    let det = n * ss - s1 * s1;
    if n < 50.0 || det <= 1e-9 * n * n {
        return Err("too few lit, unclipped pixels on the matte sphere".into());
    }
    let slope = (n * si - s1 * i1) / det;
    if slope <= 0.0 {
        return Err("the matte sphere is not brighter where it faces the light".into());
    }
    Ok(slope)
}
