//! Mirror reflection on the sphere: the light direction a highlight at an image point
//! stands for, for an orthographic or a perspective (pinhole) camera.
//!
//! Frame: x = column right, y = row down, z towards the camera; pixel centres at integers.

use super::circle::Circle;
use crate::core::vec3::{dot, normalise};

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

    /// The unit ball's centre, camera at the origin (pinhole), from its outline: the
    /// silhouette of a ball is the cone of half-angle α around the ray to its centre, at θ
    /// from the axis, and its image an ellipse ([`cone_of`]). The ellipse's centre is not
    /// the image of the ball's centre (it lies beyond, by 2 px at 140 px off the axis of a
    /// 576 px lens for a ball 140 px across: 3° of light direction), and its semi-axes
    /// differ (by 3 % there: 1.5 % of the ball's distance).
    fn centre(&self, circle: &Circle) -> Option<[f64; 3]> {
        let Self::Perspective {
            focal_px,
            principal,
        } = *self
        else {
            return None;
        };
        let (ox, oy) = (circle.cx - principal[0], circle.cy - principal[1]);
        let len = (ox * ox + oy * oy).sqrt();
        let (theta, alpha) = cone_of(focal_px, len, circle.r)?;
        let to_centre = if len > 1e-9 {
            let k = focal_px * theta.tan() / len;
            self.ray(principal[0] + k * ox, principal[1] + k * oy)?
        } else {
            self.ray(circle.cx, circle.cy)?
        };
        Some(to_centre.map(|v| v / alpha.sin()))
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

/// The angle θ of a ball's centre from the optical axis and the half-angle α of its
/// silhouette cone, for the ellipse it images to under a pinhole of focal length `focal`
/// px: centre `len` px from the principal point, mean semi-axis `r` px (what a circle
/// fitted to it measures). The cone's edges in the plane of the axis image at
/// f·tan(θ ∓ α) (the semi-axis along it and the centre), its width across is
/// f·sin α / √(cos²θ − sin²α); solved by Newton's method from the circle's own angles.
/// None where no cone in front of the camera images so.
fn cone_of(focal: f64, len: f64, r: f64) -> Option<(f64, f64)> {
    let image = |theta: f64, alpha: f64| -> [f64; 2] {
        let (near, far) = (focal * (theta - alpha).tan(), focal * (theta + alpha).tan());
        let across = focal * alpha.sin() / (theta.cos().powi(2) - alpha.sin().powi(2)).sqrt();
        [0.5 * (near + far), 0.5 * (0.5 * (far - near) + across)]
    };
    let mut x = [len.atan2(focal), r.atan2(focal.hypot(len))];
    let step = 1e-7;
    for _ in 0..30 {
        let y = image(x[0], x[1]);
        let res = [len - y[0], r - y[1]];
        if res.iter().all(|v| v.abs() <= 1e-9 * (1.0 + r)) {
            break;
        }
        let (dt, da) = (image(x[0] + step, x[1]), image(x[0], x[1] + step));
        let j = [
            [(dt[0] - y[0]) / step, (da[0] - y[0]) / step],
            [(dt[1] - y[1]) / step, (da[1] - y[1]) / step],
        ];
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        if !(det.is_finite() && det.abs() > 1e-12) {
            return None;
        }
        x[0] += (res[0] * j[1][1] - j[0][1] * res[1]) / det;
        x[1] += (j[0][0] * res[1] - res[0] * j[1][0]) / det;
    }
    let (theta, alpha) = (x[0], x[1]);
    (alpha > 0.0 && theta + alpha < std::f64::consts::FRAC_PI_2 && alpha.is_finite())
        .then_some((theta, alpha))
}

/// `d` (a ray travelling towards the surface) reflected about unit normal `n`.
fn reflect(d: [f64; 3], n: [f64; 3]) -> [f64; 3] {
    let k = 2.0 * dot(d, n);
    normalise([d[0] - k * n[0], d[1] - k * n[1], d[2] - k * n[2]])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ball's silhouette traced ray by ray through a pinhole: its outline's centre and
    /// mean semi-axis give back the ball's direction and angular size.
    #[test]
    fn the_cone_of_an_off_axis_ball_is_recovered_from_its_ellipse() {
        let f = 576.0;
        for (centre, radius) in [([138.24, 3.0, -576.0], 69.12), ([0.0, 0.0, -400.0], 50.0)] {
            let dist = dot(centre, centre).sqrt();
            let hits = |x: f64, y: f64| {
                let d = normalise([x, y, -f]);
                let b = dot(d, centre);
                b * b - (dist * dist - radius * radius) >= 0.0
            };
            // Extents along the line from the principal point and across it, 0.01 px.
            let u = if centre[0].hypot(centre[1]) > 0.0 {
                let l = centre[0].hypot(centre[1]);
                [centre[0] / l, centre[1] / l]
            } else {
                [1.0, 0.0]
            };
            let along: Vec<f64> = (-40000..40000)
                .map(|i| f64::from(i) * 0.01)
                .filter(|&t| hits(t * u[0], t * u[1]))
                .collect();
            let (lo, hi) = (along[0], along[along.len() - 1]);
            let mid = 0.5 * (lo + hi);
            let across: Vec<f64> = (-20000..20000)
                .map(|i| f64::from(i) * 0.01)
                .filter(|&s| hits(mid * u[0] - s * u[1], mid * u[1] + s * u[0]))
                .collect();
            let r = 0.25 * (hi - lo) + 0.25 * (across[across.len() - 1] - across[0]);
            let (theta, alpha) = cone_of(f, mid, r).unwrap();
            let true_theta = centre[0].hypot(centre[1]).atan2(-centre[2]);
            let true_alpha = (radius / dist).asin();
            assert!(
                (theta - true_theta).abs() < 2e-4,
                "θ {theta} vs {true_theta}"
            );
            assert!(
                (alpha / true_alpha - 1.0).abs() < 2e-3,
                "α {alpha} vs {true_alpha}"
            );
        }
    }

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
        // The outline's circle as a fit to it measures: the ellipse's centre and mean
        // semi-axis (the silhouette cone, half-angle β, at θ from the axis).
        let beta = (1.0 / dot(c, c).sqrt()).asin();
        let theta = c[0].hypot(c[1]).atan2(-c[2]);
        let u = [c[0] / c[0].hypot(c[1]), c[1] / c[0].hypot(c[1])];
        let (near, far) = (f * (theta - beta).tan(), f * (theta + beta).tan());
        let across = f * beta.sin() / (theta.cos().powi(2) - beta.sin().powi(2)).sqrt();
        let mid = 0.5 * (near + far);
        let circle = Circle {
            cx: principal[0] + mid * u[0],
            cy: principal[1] + mid * u[1],
            r: 0.5 * (0.5 * (far - near) + across),
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
