//! Mirror reflection on the sphere: the light direction a highlight at an image point
//! stands for, for an orthographic or a perspective (pinhole) camera.
//!
//! Frame: x = column right, y = row down, z towards the camera; pixel centres at integers.

use super::Circle;

/// Focal lengths a pinhole camera may be given (pixels). Past the upper end the view rays
/// across any image of up to 10⁴ pixels differ by under 0.03°, below what a calibration
/// resolves: the orthographic camera is the model there.
pub const FOCAL_PX: std::ops::RangeInclusive<f64> = 1.0..=1e7;

/// The camera that took the sphere images.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Camera {
    /// Parallel view rays along −z (a long lens far away).
    Orthographic,
    /// A pinhole with this focal length in pixels, its principal point at the image
    /// centre ((width − 1) / 2, (height − 1) / 2).
    Perspective { focal_px: f64, principal: [f64; 2] },
}

impl Camera {
    /// The unit direction towards the light that a mirror highlight at (x, y) reflects
    /// into the camera, or None when (x, y) is off the sphere.
    pub fn light_at(&self, circle: &Circle, x: f64, y: f64) -> Option<[f64; 3]> {
        match *self {
            Self::Orthographic => {
                let (u, v) = ((x - circle.cx) / circle.r, (y - circle.cy) / circle.r);
                let h = 1.0 - u * u - v * v;
                (h >= 0.0).then(|| reflect([0.0, 0.0, -1.0], [u, v, h.sqrt()]))
            }
            Self::Perspective { .. } => {
                let c = self.centre(circle)?;
                let p = self.surface_point(circle, x, y)?;
                let d = normalise(p);
                let n = normalise([p[0] - c[0], p[1] - c[1], p[2] - c[2]]);
                Some(reflect(d, n)).filter(|l| l.iter().all(|v| v.is_finite()))
            }
        }
    }

    /// The view ray through pixel (x, y) (pinhole), unit length.
    fn ray(&self, x: f64, y: f64) -> Option<[f64; 3]> {
        match *self {
            Self::Orthographic => None,
            Self::Perspective {
                focal_px,
                principal,
            } => Some(normalise([x - principal[0], y - principal[1], -focal_px])),
        }
    }

    /// The unit ball's centre, camera at the origin (pinhole): on the ray through the
    /// circle's centre, at the distance where it subtends the circle's angular radius,
    /// measured at the edge point across the line from the principal point, where the
    /// outline is least stretched by the projection.
    fn centre(&self, circle: &Circle) -> Option<[f64; 3]> {
        let Self::Perspective { principal, .. } = *self else {
            return None;
        };
        let to_centre = self.ray(circle.cx, circle.cy)?;
        let (ox, oy) = (circle.cx - principal[0], circle.cy - principal[1]);
        let len = (ox * ox + oy * oy).sqrt();
        let (tx, ty) = if len > 1e-9 {
            (-oy / len, ox / len)
        } else {
            (1.0, 0.0)
        };
        let edge = self.ray(circle.cx + circle.r * tx, circle.cy + circle.r * ty)?;
        // atan2 rather than acos: the angle stays exact when it is tiny (long lenses).
        let half_angle = norm(cross(to_centre, edge)).atan2(dot(to_centre, edge));
        let distance = 1.0 / half_angle.sin();
        Some(to_centre.map(|v| v * distance))
    }

    /// The point of the unit ball seen at (x, y), camera at the origin, in ball radii
    /// (pinhole only); None off the ball.
    pub fn surface_point(&self, circle: &Circle, x: f64, y: f64) -> Option<[f64; 3]> {
        let c = self.centre(circle)?;
        let d = self.ray(x, y)?;
        let b = dot(d, c);
        // 1 − (the centre's distance from the ray)²: b² − |c|² + 1 would cancel to noise
        // when the ball is far away in radii.
        let off = [c[0] - b * d[0], c[1] - b * d[1], c[2] - b * d[2]];
        let disc = 1.0 - dot(off, off);
        if disc < 0.0 {
            return None;
        }
        let t = b - disc.sqrt();
        Some(d.map(|v| v * t))
    }

    /// Local scale of the mirror map at (x, y): radians of reflected direction per pixel
    /// along the radius and along the outline (orthographic model; a close enough
    /// stand-in for a perspective camera, used only to judge a blob's shape).
    pub fn scales(circle: &Circle, x: f64, y: f64) -> (f64, f64) {
        let rho = ((x - circle.cx).powi(2) + (y - circle.cy).powi(2)).sqrt() / circle.r;
        let nz = (1.0 - rho * rho).max(0.01).sqrt();
        (2.0 / (circle.r * nz), 2.0 * nz / circle.r)
    }
}

/// `d` (a ray travelling towards the surface) reflected about unit normal `n`.
fn reflect(d: [f64; 3], n: [f64; 3]) -> [f64; 3] {
    let k = 2.0 * dot(d, n);
    normalise([d[0] - k * n[0], d[1] - k * n[1], d[2] - k * n[2]])
}

pub(super) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(v: [f64; 3]) -> f64 {
    dot(v, v).sqrt()
}

pub(super) fn normalise(v: [f64; 3]) -> [f64; 3] {
    let n = dot(v, v).sqrt();
    v.map(|c| c / n)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
        dot(a, b).clamp(-1.0, 1.0).acos().to_degrees()
    }

    #[test]
    fn orthographic_centre_reflects_the_view_and_halfway_normal_the_light() {
        let c = Circle {
            cx: 50.0,
            cy: 40.0,
            r: 20.0,
        };
        let cam = Camera::Orthographic;
        let l = cam.light_at(&c, 50.0, 40.0).unwrap();
        assert!(angle_deg(l, [0.0, 0.0, 1.0]) < 1e-9);
        // A light 60° off axis to the right: highlight where the normal is 30° off axis.
        let x = 50.0 + 20.0 * 30f64.to_radians().sin();
        let l = cam.light_at(&c, x, 40.0).unwrap();
        let want = [60f64.to_radians().sin(), 0.0, 60f64.to_radians().cos()];
        assert!(angle_deg(l, want) < 1e-9, "{l:?}");
        assert!(cam.light_at(&c, 71.0, 40.0).is_none());
    }

    #[test]
    fn perspective_agrees_with_the_reflection_law_and_tends_to_orthographic() {
        // A unit sphere at a known place in front of a pinhole; a point on it facing the
        // camera, the light its mirror shows there (by the reflection law), projected.
        let (f, principal) = (800.0, [320.0, 240.0]);
        let c = [0.9, -0.4, -9.0];
        let n = normalise([0.3, -0.2, 0.9]);
        let p = [c[0] + n[0], c[1] + n[1], c[2] + n[2]];
        assert!(dot(normalise(p), n) < 0.0, "the point faces the camera");
        let l = reflect(normalise(p), n);
        let (x, y) = (
            principal[0] + f * p[0] / -p[2],
            principal[1] + f * p[1] / -p[2],
        );
        // The outline's circle: centre projected, radius from the tangent cone.
        let to_c = normalise(c);
        let beta = (1.0 / dot(c, c).sqrt()).asin();
        let centre = (
            principal[0] + f * c[0] / -c[2],
            principal[1] + f * c[1] / -c[2],
        );
        // The tangential half-width is exact: f·tanβ / cos(axis angle) at the centre's depth.
        let r = f * beta.tan() / to_c[2].abs();
        let circle = Circle {
            cx: centre.0,
            cy: centre.1,
            r,
        };
        let cam = Camera::Perspective {
            focal_px: f,
            principal,
        };
        let got = cam.light_at(&circle, x, y).unwrap();
        let err = angle_deg(got, l);
        assert!(err < 0.3, "perspective error {err}°");
        // Far away with a long lens the two models agree.
        let far = Camera::Perspective {
            focal_px: 1e7,
            principal,
        };
        let circle = Circle {
            cx: 330.0,
            cy: 250.0,
            r: 40.0,
        };
        let a = far.light_at(&circle, 345.0, 238.0).unwrap();
        let b = Camera::Orthographic
            .light_at(&circle, 345.0, 238.0)
            .unwrap();
        assert!(angle_deg(a, b) < 0.01);
    }

    #[test]
    fn very_long_lenses_stay_finite_and_orthographic() {
        let circle = Circle {
            cx: 2900.0,
            cy: 1800.0,
            r: 120.0,
        };
        let ortho = Camera::Orthographic;
        for f in [*FOCAL_PX.end(), 1e10, 1e14] {
            let cam = Camera::Perspective {
                focal_px: f,
                principal: [2895.5, 1930.5],
            };
            for (x, y) in [(2900.0, 1800.0), (2950.0, 1760.0), (2900.0 + 119.0, 1800.0)] {
                let a = cam.light_at(&circle, x, y).expect("on the ball");
                assert!(a.iter().all(|v| v.is_finite()), "f {f}: {a:?}");
                let b = ortho.light_at(&circle, x, y).unwrap();
                assert!(
                    angle_deg(a, b) < 0.05,
                    "f {f} at ({x}, {y}): {}°",
                    angle_deg(a, b)
                );
            }
        }
    }
}
