//! Near lights from several balls. A dome lights the object from a few ball diameters
//! away, so each ball sees a light in its own direction: each ball's highlight is a ray
//! from the point of the ball that shows it, towards the light, and the light sits where
//! the rays of all balls meet (least squares: the point nearest to every ray).
//!
//! Units and frame: the camera frame (x = column right, y = row down, z towards the
//! camera), in ball radii. Orthographic: the origin at the first ball's centre, the balls'
//! centres in one plane facing the camera. Pinhole: the origin at the camera, each ball
//! placed by its circle as in [`Camera::light_at`]. The balls are of one size.

use super::circle::Circle;
use super::mirror::Camera;
use super::sphere::solve3;
use crate::core::vec3::{dot, normalise};

/// A light placed from its rays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightPosition {
    /// Position, ball radii.
    pub position: [f64; 3],
    /// RMS distance of the position from the rays, ball radii.
    pub residual: f64,
    /// Largest angle between two of the rays, degrees: near 0 the rays barely meet and
    /// the distance is poorly known.
    pub spread_deg: f64,
}

/// Rays closer to parallel than this do not place a light.
const MIN_SPREAD_DEG: f64 = 0.05;

/// The ray of one ball's highlight: from the ball point seen at (x, y), along `direction`.
/// `origin` is the first ball's centre (orthographic), `scale` the balls' mean radius in
/// pixels.
pub fn ray(
    camera: &Camera,
    circle: &Circle,
    (x, y): (f64, f64),
    direction: [f64; 3],
    origin: &Circle,
    scale: f64,
) -> Option<([f64; 3], [f64; 3])> {
    match *camera {
        Camera::Orthographic => {
            let (u, v) = ((x - circle.cx) / circle.r, (y - circle.cy) / circle.r);
            let h = 1.0 - u * u - v * v;
            (h >= 0.0).then(|| {
                let point = [
                    (x - origin.cx) / scale,
                    (y - origin.cy) / scale,
                    circle.r * h.sqrt() / scale,
                ];
                (point, direction)
            })
        }
        Camera::Perspective { .. } => camera.surface_point(circle, x, y).map(|p| (p, direction)),
    }
}

/// The point nearest to every ray (origin, unit direction), or None when they are (near)
/// parallel.
pub fn intersect(rays: &[([f64; 3], [f64; 3])]) -> Option<LightPosition> {
    if rays.len() < 2 {
        return None;
    }
    let mut spread = 0.0f64;
    for (i, a) in rays.iter().enumerate() {
        for b in &rays[i + 1..] {
            spread = spread.max(dot(a.1, b.1).clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    if spread < MIN_SPREAD_DEG {
        return None;
    }
    // Σ (I − d dᵀ) x = Σ (I − d dᵀ) o
    let mut m = [[0.0; 3]; 3];
    let mut rhs = [0.0; 3];
    for (o, d) in rays {
        let d = normalise(*d);
        for r in 0..3 {
            for c in 0..3 {
                let p = if r == c { 1.0 } else { 0.0 } - d[r] * d[c];
                m[r][c] += p;
                rhs[r] += p * o[c];
            }
        }
    }
    let x = solve3(m, rhs)?;
    let sq: f64 = rays
        .iter()
        .map(|(o, d)| {
            let d = normalise(*d);
            let w = [x[0] - o[0], x[1] - o[1], x[2] - o[2]];
            let along = dot(w, d);
            dot(w, w) - along * along
        })
        .sum();
    Some(LightPosition {
        position: x,
        residual: (sq.max(0.0) / rays.len() as f64).sqrt(),
        spread_deg: spread,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_from_two_points_meet_at_the_light() {
        let light = [3.0, -2.0, 7.0];
        let rays: Vec<([f64; 3], [f64; 3])> = [[-2.0, 0.0, 0.5], [2.0, 0.3, 0.8]]
            .iter()
            .map(|&o| {
                let d = normalise([light[0] - o[0], light[1] - o[1], light[2] - o[2]]);
                (o, d)
            })
            .collect();
        let p = intersect(&rays).unwrap();
        for k in 0..3 {
            assert!((p.position[k] - light[k]).abs() < 1e-9, "{p:?}");
        }
        assert!(p.residual < 1e-9);
        // Parallel rays place nothing.
        let parallel = [
            ([0.0; 3], [0.0, 0.0, 1.0]),
            ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
        ];
        assert!(intersect(&parallel).is_none());
    }
}
