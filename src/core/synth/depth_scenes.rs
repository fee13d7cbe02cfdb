//! Perspective scenes with depth steps, for the integrators' tests and `res/`: analytic
//! surfaces ray-cast through a [`Pinhole`] camera, with exact depth along the optical axis
//! and exact camera-frame normals of the visible surface.
//!
//! Frame (the project's): x = column right, y = row down, z towards the camera; the camera
//! sits at the origin and pixel `(u, v)` sees the ray `d = ((u − cx)/fx, (v − cy)/fy, −1)`,
//! so the point at ray parameter `t` is `t d` and its depth is `t`. Every scene's camera
//! has `f = 1.2 × size` with the principal point at the centre (rays up to 22.6° off the
//! axis at the edges' midpoints, 30.5° in the corners), and its geometry is given in world
//! units at about 10 units from the camera, so a scene looks the same at every size.
//!
//! Every step ends somewhere. A piece that steps surround on all sides could be moved
//! along its rays (scaled about the camera) without changing its normals or its outline,
//! so no integrator could know its depth; here each piece joins the rest along a crease
//! or a hinge, and the normals fix the depth up to one scale (a test cuts the steps out
//! and finds one piece). Likewise a step between parallel faces, of one height all along,
//! would leave no trace in the normals; these steps change height along their length.
//!
//! | name | surfaces | mask | kind |
//! |---|---|---|---|
//! | `sphere-in-front` | a sphere sunk in a steep plane: blending into it on its left (a crease), in front of it on its right (steps up to ~3.9 units at ~10) | whole frame | steps |
//! | `two-objects` | a sphere and a turned ellipsoid sunk in the same plane at different depths, each like the sphere above (steps up to ~2 units) | whole frame | steps |
//! | `step-plate` | a plate tilted 10° with a panel hinged on it and lifted 20°: steps along its three free edges, from nothing at the hinge to ~1 unit | whole frame | steps |
//! | `sphere` | a sphere 10 units away, radius 3 | the sphere where it faces the ray within 87° | smooth |
//! | `bumps` | a tilted plate with four Gaussian bumps (a height field) | whole frame | smooth |
//!
//! [`ortho_step_plate`] is the step plate's orthographic counterpart (heights in pixels).

use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::scene::Scene;
use crate::core::camera::Pinhole;
use crate::core::integrate::gradients;
use crate::core::integrate::perspective::log_depth_gradients;
use crate::core::vec3::{dot, normalise};

/// A scene with ground truth for integration: what the normals say and what the depth is.
#[derive(Debug, Clone)]
pub struct DepthScene {
    pub name: &'static str,
    /// The camera that sees it; None for an orthographic scene, whose `depth` is a height
    /// in pixels (z towards the camera).
    pub camera: Option<Pinhole>,
    /// Depth along the optical axis (world units), or orthographic heights; NaN off the mask.
    pub depth: Array2<f32>,
    /// Unit camera-frame normals of the visible surface, `(rows, cols, 3)`; zero off the mask.
    pub normals: Array3<f32>,
    pub mask: Array2<bool>,
    /// True for smooth surfaces, false for scenes with depth steps.
    pub smooth: bool,
}

impl DepthScene {
    /// Largest minus smallest depth (or height) over the mask.
    pub fn depth_range(&self) -> f64 {
        let (lo, hi) = (self.depth.iter().zip(&self.mask))
            .filter(|(_, m)| **m)
            .fold((f64::MAX, f64::MIN), |(lo, hi), (&d, _)| {
                (lo.min(f64::from(d)), hi.max(f64::from(d)))
            });
        hi - lo
    }

    /// The gradients the integrators see in the true normals: of `ζ = −fx ln D`
    /// ([`log_depth_gradients`]) under a camera, of the height ([`gradients`]) without.
    pub fn gradients(&self) -> (Array2<f32>, Array2<f32>) {
        match &self.camera {
            Some(camera) => log_depth_gradients(&self.normals, &self.mask, camera),
            None => gradients(&self.normals, &self.mask),
        }
    }

    /// The pixels at a depth step: those with a 4-neighbour across which `ζ` (`−fx ln D`,
    /// or the height) changes by more than a pixel beyond both ends' own slopes
    /// ([`DepthScene::gradients`]); a continuous surface, creased or not, changes it by
    /// something between the two.
    pub fn steps(&self) -> Array2<bool> {
        let (p, q) = self.gradients();
        let zeta = self.depth.mapv(|d| match &self.camera {
            Some(camera) => -camera.fx * f64::from(d).ln(),
            None => f64::from(d),
        });
        let (h, w) = self.mask.dim();
        let mut steps = Array2::from_elem((h, w), false);
        for (r, c) in (0..h).flat_map(|r| (0..w).map(move |c| (r, c))) {
            for ((rr, cc), g) in [((r, c + 1), &p), ((r + 1, c), &q)] {
                let on = rr < h && cc < w && self.mask[[r, c]] && self.mask[[rr, cc]];
                if on && beyond(zeta[[rr, cc]] - zeta[[r, c]], g[[r, c]], g[[rr, cc]]) > 1.0 {
                    steps[[r, c]] = true;
                    steps[[rr, cc]] = true;
                }
            }
        }
        steps
    }

    /// The scene for the renderer, with a gray textured albedo (0.35–0.85): distant
    /// lights shade camera-frame normals the same way under any camera, so the renderer's
    /// Lambertian images hold for it (not its cast shadows or interreflection, which assume
    /// an orthographic height field). `depth` carries this scene's depth (0 off the mask)
    /// and `camera` its camera.
    pub fn to_scene(&self) -> Scene {
        let (h, w) = self.mask.dim();
        let s = w.max(h) as f64;
        let mask = &self.mask;
        Scene {
            width: w,
            height: h,
            depth: Array2::from_shape_fn((h, w), |(r, c)| {
                if mask[[r, c]] {
                    f64::from(self.depth[[r, c]])
                } else {
                    0.0
                }
            }),
            normals: self.normals.mapv(f64::from),
            albedo: Array3::from_shape_fn((h, w, 1), |(r, c, _)| {
                if mask[[r, c]] {
                    let (x, y) = (c as f64 / s, r as f64 / s);
                    0.6 + 0.25 * ((x * 9.0).sin() * (y * 7.0).sin())
                } else {
                    0.0
                }
            }),
            mask: mask.clone(),
            camera: self.camera,
        }
    }
}

/// The camera of every perspective scene here: `f = 1.2 × size`, principal point centred.
fn depth_camera(size: usize) -> Pinhole {
    Pinhole::centred(1.2 * size as f64, size, size)
}

/// The five perspective scenes, `size × size`: the three with depth steps, then the two
/// smooth ones.
pub fn depth_scenes(size: usize) -> Vec<DepthScene> {
    vec![
        sphere_in_front(size),
        two_objects(size),
        step_plate(size),
        lone_sphere(size),
        bumps(size),
    ]
}

/// How far a change `dz` lies outside the interval between the slopes `a` and `b`.
fn beyond(dz: f64, a: f32, b: f32) -> f64 {
    let (lo, hi) = (f64::from(a.min(b)), f64::from(a.max(b)));
    (lo - dz).max(dz - hi).max(0.0)
}

/// The background of `sphere-in-front` and `two-objects`: the plane through
/// `(0, 0, −12)` with this normal, turned 35° about y (nearer on the left) and a little
/// about x. So steep a plane lets a sphere sunk in it show a crease on one side and stand
/// in front of it on the other.
fn steep_normal() -> [f64; 3] {
    let a = 35f64.to_radians();
    normalise([a.sin(), 0.1, a.cos()])
}

fn steep_plane() -> Shape {
    Shape::Plane {
        point: [0.0, 0.0, -12.0],
        normal: steep_normal(),
    }
}

/// The point `h` units in front of the steep plane, off its point at `(x, y)`.
fn off_steep_plane(x: f64, y: f64, h: f64) -> [f64; 3] {
    let n = steep_normal();
    let z = -12.0 - (n[0] * x + n[1] * y) / n[2];
    [x + h * n[0], y + h * n[1], z + h * n[2]]
}

/// `sphere-in-front`: a sphere (radius 2.5) sunk in the steep plane, its centre 0.4 units
/// in front of it, on the axis: it meets the plane at 81° all round, seen as a crease on
/// its left, while on its right its rim stands up to ~3.9 units in front of the plane.
pub fn sphere_in_front(size: usize) -> DepthScene {
    let shapes = [
        steep_plane(),
        Shape::Sphere {
            centre: off_steep_plane(0.0, 0.0, 0.4),
            radius: 2.5,
        },
    ];
    cast("sphere-in-front", size, &shapes, false, 0.0)
}

/// `two-objects`: a sphere (radius 1.6) up and left, nearer, and an ellipsoid (semi-axes
/// 2, 1.3, 1.1, turned 30° about y and 15° about x) down and right, farther, both sunk
/// in the steep plane with their centres 0.3 units in front of it; each blends into it on
/// its left and steps in front of it on its right.
fn two_objects(size: usize) -> DepthScene {
    let shapes = [
        steep_plane(),
        Shape::Sphere {
            centre: off_steep_plane(-1.6, -0.8, 0.3),
            radius: 1.6,
        },
        Shape::Ellipsoid {
            centre: off_steep_plane(1.3, 0.9, 0.3),
            axes: [2.0, 1.3, 1.1],
            frame: mul(
                rotation_y(30f64.to_radians()),
                rotation_x(15f64.to_radians()),
            ),
        },
    ];
    cast("two-objects", size, &shapes, false, 0.0)
}

/// `step-plate`: a plate 10 units away tilted 10° (about the axis (1, 0.5, 0)), with a
/// thin panel (3 × 2.8 units) hinged on it along a line below the centre and lifted 20°
/// towards the camera: the surface is continuous along the hinge and steps along the
/// panel's other three edges, by nothing at the hinge up to ~1 unit at its far edge. The
/// panel covers the camera's foot on the plate, so its underside never shows.
pub fn step_plate(size: usize) -> DepthScene {
    let (plate, panel) = step_plate_frames();
    let origin = [0.0, 0.0, -10.0];
    let shapes = [
        Shape::Plane {
            point: origin,
            normal: column(&plate, 2),
        },
        Shape::Panel {
            origin: [0, 1, 2].map(|k| origin[k] + 1.2 * plate[k][1]),
            frame: panel,
            lo: [-1.6, -2.8],
            hi: [1.4, 0.0],
        },
    ];
    cast("step-plate", size, &shapes, false, 0.0)
}

/// The step plate's axes (as columns) and its panel's: the plate's turned −20° about the
/// plate's own x axis (the hinge), which lifts the panel's far edge towards the camera.
fn step_plate_frames() -> ([[f64; 3]; 3], [[f64; 3]; 3]) {
    let plate = rotation_about(normalise([1.0, 0.5, 0.0]), 10f64.to_radians());
    (plate, mul(plate, rotation_x(-20f64.to_radians())))
}

/// `sphere`: a sphere alone (radius 3, 10 units away, slightly off the axis); the mask is
/// the sphere where it faces the ray at least 0.05 (cosine), as the orthographic sphere
/// stops just inside its rim.
fn lone_sphere(size: usize) -> DepthScene {
    let shapes = [Shape::Sphere {
        centre: [0.3, -0.2, -10.0],
        radius: 3.0,
    }];
    cast("sphere", size, &shapes, true, 0.05)
}

/// `bumps`: the height field `Z = −(10 + 0.08 X − 0.05 Y − Σ Gaussians)` filling the frame
/// (four bumps 0.4–1 units high, slopes below 0.7); no part of it hides another.
fn bumps(size: usize) -> DepthScene {
    let shapes = [Shape::Bumps {
        distance: 10.0,
        tilt: [0.08, -0.05],
        bumps: vec![
            [-1.5, -1.2, 0.9, 0.8],
            [1.6, -0.8, 0.7, 0.6],
            [0.2, 1.5, 1.1, 1.0],
            [-2.2, 2.0, 0.6, 0.4],
        ],
    }];
    cast("bumps", size, &shapes, true, 0.0)
}

/// The step plate seen orthographically, heights in pixels: the plane
/// `z = 0.12 x − 0.08 y` (pixels) with a panel over columns 30 %–70 % and rows 35 %–75 %
/// of the frame, hinged on the plane along its bottom row and rising 0.4 px per row above
/// it towards its top row (0.16 × size there); its edges' walls are vertical (unseen).
pub fn ortho_step_plate(size: usize) -> DepthScene {
    let s = size as f64;
    let plane = |x: f64, y: f64| 0.12 * x - 0.08 * y;
    let lift = |x: f64, y: f64| {
        let on = (0.3 * s..0.7 * s).contains(&x) && (0.35 * s..=0.75 * s).contains(&y);
        if on { 0.4 * (0.75 * s - y) } else { 0.0 }
    };
    let on_panel = |r: usize, c: usize| lift(c as f64, r as f64) > 0.0;
    let (plane_normal, panel_normal) =
        (normalise([-0.12, 0.08, 1.0]), normalise([-0.12, 0.48, 1.0]));
    DepthScene {
        name: "step-plate (orthographic)",
        camera: None,
        depth: Array2::from_shape_fn((size, size), |(r, c)| {
            let (x, y) = (c as f64, r as f64);
            (plane(x, y) + lift(x, y)) as f32
        }),
        normals: Array3::from_shape_fn((size, size, 3), |(r, c, k)| {
            let n = if on_panel(r, c) {
                panel_normal
            } else {
                plane_normal
            };
            n[k] as f32
        }),
        mask: Array2::from_elem((size, size), true),
        smooth: false,
    }
}

/// An analytic surface a ray can meet.
enum Shape {
    /// The infinite plane through `point` with unit `normal` (either side faces the camera).
    Plane {
        point: [f64; 3],
        normal: [f64; 3],
    },
    Sphere {
        centre: [f64; 3],
        radius: f64,
    },
    /// `Σ (p_i / axes_i)² = 1` for `p = frameᵀ (X − centre)`.
    Ellipsoid {
        centre: [f64; 3],
        axes: [f64; 3],
        frame: [[f64; 3]; 3],
    },
    /// The rectangle `lo ≤ (p_x, p_y) ≤ hi`, `p_z = 0`, for `p = frameᵀ (X − origin)`:
    /// a thin panel, either side facing the camera.
    Panel {
        origin: [f64; 3],
        frame: [[f64; 3]; 3],
        lo: [f64; 2],
        hi: [f64; 2],
    },
    /// `Z = −(distance + tilt·(X, Y) − Σ a exp(−|(X, Y) − (x, y)|² / 2σ²))` for bumps
    /// `[x, y, σ, a]`: a height field that must not hide itself along any ray.
    Bumps {
        distance: f64,
        tilt: [f64; 2],
        bumps: Vec<[f64; 4]>,
    },
}

impl Shape {
    /// The nearest point in front of the camera where the ray `d` (z = −1) meets the
    /// surface: `(t, unit normal facing the camera)`, depth `t`.
    fn hit(&self, d: [f64; 3]) -> Option<(f64, [f64; 3])> {
        match self {
            Shape::Plane { point, normal } => plane_hit(*point, *normal, d),
            Shape::Sphere { centre, radius } => {
                let t = nearest_root(
                    dot(d, d),
                    -2.0 * dot(d, *centre),
                    dot(*centre, *centre) - radius * radius,
                )?;
                let x = d.map(|v| v * t);
                Some((t, [0, 1, 2].map(|k| (x[k] - centre[k]) / radius)))
            }
            Shape::Ellipsoid {
                centre,
                axes,
                frame,
            } => {
                // In the ellipsoid's frame scaled to the unit sphere: o + t e.
                let o = transpose_times(frame, centre.map(|v| -v));
                let e = transpose_times(frame, d);
                let (o, e) = (
                    [0, 1, 2].map(|k| o[k] / axes[k]),
                    [0, 1, 2].map(|k| e[k] / axes[k]),
                );
                let t = nearest_root(dot(e, e), 2.0 * dot(o, e), dot(o, o) - 1.0)?;
                // Gradient of Σ p_i² / a_i²: frame (p_i / a_i²) with p_i = (o + t e)_i a_i.
                let g = [0, 1, 2].map(|k| (o[k] + t * e[k]) / axes[k]);
                Some((t, normalise(times(frame, g))))
            }
            Shape::Panel {
                origin,
                frame,
                lo,
                hi,
            } => {
                let (t, n) = plane_hit(*origin, column(frame, 2), d)?;
                let p = transpose_times(frame, [0, 1, 2].map(|k| t * d[k] - origin[k]));
                let inside = (0..2).all(|k| (lo[k]..=hi[k]).contains(&p[k]));
                inside.then_some((t, n))
            }
            Shape::Bumps {
                distance,
                tilt,
                bumps,
            } => {
                // g(X, Y) and its gradient: the surface is Z + distance + g = 0.
                let g = |x: f64, y: f64| {
                    let (mut v, mut gx, mut gy) = (tilt[0] * x + tilt[1] * y, tilt[0], tilt[1]);
                    for &[bx, by, sigma, a] in bumps {
                        let (dx, dy) = (x - bx, y - by);
                        let e = a * (-(dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp();
                        v -= e;
                        gx += e * dx / (sigma * sigma);
                        gy += e * dy / (sigma * sigma);
                    }
                    (v, gx, gy)
                };
                // Newton on f(t) = t − distance − g(t dx, t dy), increasing along the ray.
                let mut t = *distance;
                for _ in 0..100 {
                    let (v, gx, gy) = g(t * d[0], t * d[1]);
                    let slope = 1.0 - (gx * d[0] + gy * d[1]);
                    assert!(slope > 0.1, "the bumps hide themselves along {d:?}");
                    let step = (t - distance - v) / slope;
                    t -= step;
                    if step.abs() < 1e-13 * t {
                        let (_, gx, gy) = g(t * d[0], t * d[1]);
                        return Some((t, normalise([gx, gy, 1.0])));
                    }
                }
                panic!("Newton did not converge along {d:?}")
            }
        }
    }
}

/// A ray's hit: its parameter `t` (the depth) and the unit normal facing the camera.
type Hit = (f64, [f64; 3]);

/// Ray-cast `shapes` through the centred camera of a `size × size` frame: the nearest hit
/// per pixel. Pixels no shape covers, or whose surface faces the ray at a cosine below
/// `min_cos`, are off the mask.
fn cast(
    name: &'static str,
    size: usize,
    shapes: &[Shape],
    smooth: bool,
    min_cos: f64,
) -> DepthScene {
    let camera = depth_camera(size);
    let rows: Vec<Vec<Option<Hit>>> = (0..size)
        .into_par_iter()
        .map(|r| {
            (0..size)
                .map(|c| {
                    let d = camera.ray(c as f64, r as f64);
                    let hit = (shapes.iter())
                        .filter_map(|s| s.hit(d))
                        .min_by(|a, b| a.0.total_cmp(&b.0))?;
                    let facing = -dot(hit.1, d) / dot(d, d).sqrt();
                    (facing >= min_cos).then_some(hit)
                })
                .collect()
        })
        .collect();
    let at = |r: usize, c: usize| rows[r][c];
    DepthScene {
        name,
        camera: Some(camera),
        depth: Array2::from_shape_fn((size, size), |(r, c)| {
            at(r, c).map_or(f32::NAN, |(t, _)| t as f32)
        }),
        normals: Array3::from_shape_fn((size, size, 3), |(r, c, k)| {
            at(r, c).map_or(0.0, |(_, n)| n[k] as f32)
        }),
        mask: Array2::from_shape_fn((size, size), |(r, c)| at(r, c).is_some()),
        smooth,
    }
}

/// Where the ray `d` meets the plane through `point` with unit `normal`, in front of the
/// camera: `(t, the normal turned to face the camera)`.
fn plane_hit(point: [f64; 3], normal: [f64; 3], d: [f64; 3]) -> Option<(f64, [f64; 3])> {
    let nd = dot(normal, d);
    if nd.abs() < 1e-12 {
        return None;
    }
    let t = dot(normal, point) / nd;
    let n = if nd < 0.0 { normal } else { normal.map(|v| -v) };
    (t > 0.0).then_some((t, n))
}

/// The root of `a t² + b t + c` nearest in front (t > 0), if any.
fn nearest_root(a: f64, b: f64, c: f64) -> Option<f64> {
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let (t0, t1) = ((-b - s) / (2.0 * a), (-b + s) / (2.0 * a));
    [t0, t1].into_iter().find(|&t| t > 0.0)
}

/// Column `k` of a matrix stored as rows.
fn column(m: &[[f64; 3]; 3], k: usize) -> [f64; 3] {
    [m[0][k], m[1][k], m[2][k]]
}

/// `m v` (m as rows).
fn times(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    m.map(|row| dot(row, v))
}

/// `mᵀ v`.
fn transpose_times(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|k| dot(column(m, k), v))
}

fn mul(a: [[f64; 3]; 3], b: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    a.map(|row| [0, 1, 2].map(|k| dot(row, column(&b, k))))
}

fn rotation_x(a: f64) -> [[f64; 3]; 3] {
    let (s, c) = a.sin_cos();
    [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
}

fn rotation_y(a: f64) -> [[f64; 3]; 3] {
    let (s, c) = a.sin_cos();
    [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
}

/// Rotation by `a` about unit `axis` (Rodrigues).
fn rotation_about(axis: [f64; 3], a: f64) -> [[f64; 3]; 3] {
    let (s, c) = a.sin_cos();
    let [x, y, z] = axis;
    let t = 1.0 - c;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::integrate::curl;

    fn normal(scene: &DepthScene, r: usize, c: usize) -> [f64; 3] {
        [0, 1, 2].map(|k| f64::from(scene.normals[[r, c, k]]))
    }

    /// The derivative at the middle of five depths one pixel apart (error O(h⁴), so that
    /// the test holds on curved surfaces a few pixels across), if they lie on one smooth
    /// piece: every second difference of the depths below 1e-3 of the middle one (no
    /// step) and of the normals below 0.01 (no crease).
    fn derivative(depths: [f64; 5], normals: [[f64; 3]; 5]) -> Option<f64> {
        let smooth = (1..4).all(|i| {
            let second = |f: &dyn Fn(usize) -> f64| (f(i - 1) - 2.0 * f(i) + f(i + 1)).abs();
            second(&|j| depths[j]) < 1e-3 * depths[2]
                && (0..3).all(|k| second(&|j| normals[j][k]) < 0.01)
        });
        let f = depths;
        smooth.then(|| (f[0] - 8.0 * f[1] + 8.0 * f[3] - f[4]) / 12.0)
    }

    /// The cosines between the normal at `(r, c)` (2 or more pixels inside the frame) and
    /// the surface's tangents along the row and the column, `∂X/∂u = D_u d + D (1/fx, 0, 0)`
    /// and `∂X/∂v = D_v d + D (0, 1/fy, 0)`, from differences of the true depth; None
    /// off one smooth piece or where the surface is seen at a grazing angle (cosine below
    /// 0.3), where the differences say little.
    fn tangent_cosines(scene: &DepthScene, r: usize, c: usize) -> Option<[f64; 2]> {
        let cam = scene.camera.expect("a perspective scene");
        let (d, n) = (cam.ray(c as f64, r as f64), normal(scene, r, c));
        if -dot(n, d) < 0.3 * dot(d, d).sqrt() {
            return None;
        }
        let along = |step: [isize; 2]| {
            let at = |i: usize| {
                let o = i as isize - 2;
                (
                    r.wrapping_add_signed(o * step[0]),
                    c.wrapping_add_signed(o * step[1]),
                )
            };
            let depths = [0, 1, 2, 3, 4].map(|i| f64::from(scene.depth[at(i)]));
            derivative(
                depths,
                [0, 1, 2, 3, 4].map(|i| normal(scene, at(i).0, at(i).1)),
            )
        };
        let (du, dv, z) = (
            along([0, 1])?,
            along([1, 0])?,
            f64::from(scene.depth[[r, c]]),
        );
        let tu = [du * d[0] + z / cam.fx, du * d[1], du * d[2]];
        let tv = [dv * d[0], dv * d[1] + z / cam.fy, dv * d[2]];
        Some([tu, tv].map(|t| dot(n, t) / dot(t, t).sqrt()))
    }

    /// Normals are unit, face the camera, and are orthogonal to the depth's own tangents
    /// wherever the surface is one smooth piece.
    #[test]
    fn normals_are_unit_face_the_camera_and_match_the_depth() {
        for scene in depth_scenes(128) {
            let cam = scene.camera.unwrap();
            let (h, w) = scene.mask.dim();
            let mut checked = 0;
            for (r, c) in (2..h - 2).flat_map(|r| (2..w - 2).map(move |c| (r, c))) {
                if !scene.mask[[r, c]] {
                    continue;
                }
                let n = normal(&scene, r, c);
                assert!((dot(n, n) - 1.0).abs() < 1e-6, "{} {r},{c}", scene.name);
                let d = cam.ray(c as f64, r as f64);
                assert!(dot(n, d) < 0.0, "{} {r},{c} faces away", scene.name);
                if let Some([cu, cv]) = tangent_cosines(&scene, r, c) {
                    let worst = cu.abs().max(cv.abs());
                    assert!(worst < 1e-3, "{} {r},{c}: cos {worst}", scene.name);
                    checked += 1;
                }
            }
            assert!(checked > w * h / 4, "{}: {checked} checked", scene.name);
        }
    }

    /// Every scene here and the orthographic plate at 128², each with its steps.
    fn scenes_and_their_steps() -> Vec<(DepthScene, Array2<bool>)> {
        (depth_scenes(128).into_iter())
            .chain([ortho_step_plate(128)])
            .map(|scene| {
                let steps = scene.steps();
                (scene, steps)
            })
            .collect()
    }

    /// The normals show the steps: across them the true normals' gradients are not a
    /// gradient field (a loop across a step whose height changes along it does not
    /// close); the smooth scenes have neither steps nor such loops.
    #[test]
    fn the_normals_show_the_steps() {
        for (scene, steps) in scenes_and_their_steps() {
            let (p, q) = scene.gradients();
            let curl = curl(&p, &q, &scene.mask);
            let (h, w) = steps.dim();
            // A cell's loop runs through rows r..=r+1 and columns c..=c+1.
            let near_steps = |(r, c): (usize, usize)| {
                let around = ndarray::s![
                    r.saturating_sub(1)..(r + 3).min(h),
                    c.saturating_sub(1)..(c + 3).min(w)
                ];
                steps.slice(around).iter().any(|s| *s)
            };
            let open = (curl.indexed_iter()).filter(|(_, v)| v.abs() > 0.1);
            let (open, at_steps) = open.fold((0, 0), |(n, at), (i, _)| {
                (n + 1, at + usize::from(near_steps(i)))
            });
            let on_steps = steps.iter().filter(|s| **s).count();
            eprintln!(
                "{}: {on_steps} pixels at steps; {open} open cells, {at_steps} at steps",
                scene.name
            );
            if scene.smooth {
                assert_eq!((on_steps, open), (0, 0), "{}", scene.name);
            } else {
                assert!(on_steps > 200 && at_steps > 50, "{}", scene.name);
            }
        }
    }

    /// Every step ends somewhere: without the steps' pixels each scene is one piece, so the
    /// normals fix its depth up to one scale (or offset).
    #[test]
    fn cut_at_its_steps_each_scene_stays_one_piece() {
        for (scene, steps) in scenes_and_their_steps() {
            let (h, w) = steps.dim();
            let keep = Array2::from_shape_fn((h, w), |i| scene.mask[i] && !steps[i]);
            let start = keep
                .indexed_iter()
                .find(|(_, k)| **k)
                .expect("pixels left")
                .0;
            let mut seen = Array2::from_elem((h, w), false);
            seen[start] = true;
            let (mut stack, mut reached) = (vec![start], 0);
            while let Some((r, c)) = stack.pop() {
                reached += 1;
                let next = [
                    (r + 1, c),
                    (r, c + 1),
                    (r.wrapping_sub(1), c),
                    (r, c.wrapping_sub(1)),
                ];
                for n in next {
                    if n.0 < h && n.1 < w && keep[n] && !seen[n] {
                        seen[n] = true;
                        stack.push(n);
                    }
                }
            }
            let left = keep.iter().filter(|k| **k).count();
            assert_eq!(reached, left, "{}: cut into pieces", scene.name);
        }
    }

    #[test]
    fn masks_cover_what_each_scene_says() {
        let sphere = lone_sphere(64);
        let on = sphere.mask.iter().filter(|m| **m).count();
        assert!(
            on < 64 * 64 && on > 64 * 64 / 3,
            "{on} pixels on the sphere"
        );
        for scene in [
            sphere_in_front(64),
            two_objects(64),
            step_plate(64),
            bumps(64),
        ] {
            assert!(
                scene.mask.iter().all(|m| *m),
                "{} fills the frame",
                scene.name
            );
        }
    }

    /// Only the plate and the panel's top show, and the panel's far edge stands in front
    /// of the plate beyond it.
    #[test]
    fn the_step_plate_shows_the_plate_and_the_panels_top() {
        let scene = step_plate(128);
        let (plate, panel) = step_plate_frames();
        let faces = [column(&plate, 2), column(&panel, 2)];
        let mut on_panel = 0;
        for n in scene.normals.rows() {
            let n = [n[0], n[1], n[2]].map(f64::from);
            let is = |f: [f64; 3]| (0..3).all(|k| (n[k] - f[k]).abs() < 1e-6);
            assert!(
                is(faces[0]) || is(faces[1]),
                "neither plate nor panel: {n:?}"
            );
            on_panel += usize::from(is(faces[1]));
        }
        assert!(on_panel > 128 * 128 / 10, "{on_panel} pixels on the panel");
        let column_64 = scene.depth.column(64);
        let jump = (1..128)
            .map(|r| (column_64[r] - column_64[r - 1]).abs())
            .fold(0f32, f32::max);
        assert!(
            jump > 0.5,
            "the far edge stands {jump} in front of the plate"
        );
    }
}
