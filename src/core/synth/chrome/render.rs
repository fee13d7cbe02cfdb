//! Rendering: what each ball mirrors, the matte sphere and the backdrop, then the camera.

use ndarray::Array2;
use rayon::prelude::*;

use super::super::sensor::{self, Rng};
use super::set::{ChromeSet, RoomLight};
use crate::core::vec3::{add, cross, dot, normalise, scale, sub};

/// Samples per pixel side.
const SUPERSAMPLE: usize = 6;

/// Mirror reflectance of the chrome (roughly constant with angle for a metal).
const CHROME: f64 = 0.65;

/// Mirror bounces followed between balls before the rest is taken as the dim room.
const BOUNCES: usize = 2;

impl ChromeSet {
    fn max(&self) -> f64 {
        if self.bit_depth == 8 { 255.0 } else { 65535.0 }
    }

    /// One image per light of the chrome balls.
    pub fn render(&self) -> Vec<Array2<u16>> {
        self.check();
        let balls = self.balls();
        let room: Vec<Patch> = self.room_lights.iter().map(Patch::new).collect();
        (0..self.lights.len())
            .into_par_iter()
            .map(|i| {
                let light = self.light(i);
                let img = self.supersampled(|x, y| match self.camera_distance {
                    None => match hit(&balls, x, y) {
                        Some((b, n)) => {
                            let p = [x, y, balls[b].1 * n[2]];
                            let view = Ray {
                                from: b,
                                p,
                                d: reflect(n),
                            };
                            CHROME * self.trace(&balls, view, &light, &room, BOUNCES)
                        }
                        None => self.backdrop_at(x, y, light.towards([x, y, 0.0])),
                    },
                    Some(d) => self.pinhole_sample(&balls, d, (x, y), &light, &room),
                });
                self.expose(img, i)
            })
            .collect()
    }

    /// One image per light of matte white spheres (albedo 0.8, Lambertian) of the same
    /// sizes and places, each light with its intensity (at the first ball's centre for a
    /// near light), on the same backdrop.
    pub fn render_matte(&self, intensities: &[f64]) -> Vec<Array2<u16>> {
        self.check();
        assert!(
            self.camera_distance.is_none(),
            "matte spheres are rendered orthographically"
        );
        let balls = self.balls();
        let count = self.lights.len().min(intensities.len());
        (0..count)
            .into_par_iter()
            .map(|i| {
                let light = self.light(i);
                let falloff = |p: [f64; 3]| match light.position {
                    None => intensities[i],
                    Some(q) => {
                        let first = [q[0] - self.centre[0], q[1] - self.centre[1], q[2]];
                        let to = sub(q, p);
                        intensities[i] * dot(first, first) / dot(to, to)
                    }
                };
                let img = self.supersampled(|x, y| match hit(&balls, x, y) {
                    Some((b, n)) => {
                        let p = [x, y, balls[b].1 * n[2]];
                        let l = light.towards(p);
                        let k = if shadowed(&balls, b, p, l, &light) {
                            0.0
                        } else {
                            falloff(p)
                        };
                        0.02 + 0.6 * k * dot(n, l).max(0.0)
                    }
                    None => self.backdrop_at(x, y, light.towards([x, y, 0.0])),
                });
                self.expose(img, i + 1000)
            })
            .collect()
    }

    /// What the pinhole at `distance` above the image centre sees through image point
    /// (x, y): a ball, mirroring, or the backdrop in the plane z = 0.
    fn pinhole_sample(
        &self,
        balls: &[([f64; 2], f64)],
        distance: f64,
        (x, y): (f64, f64),
        light: &Light,
        room: &[Patch],
    ) -> f64 {
        let (cx, cy) = (
            0.5 * (self.width as f64 - 1.0),
            0.5 * (self.height as f64 - 1.0),
        );
        let eye = Ray {
            from: usize::MAX,
            p: [cx, cy, distance],
            d: normalise([x - cx, y - cy, -distance]),
        };
        match nearest_ball(balls, &eye) {
            Some((b, t)) => {
                let (c, r) = balls[b];
                let p = add(eye.p, scale(eye.d, t));
                let n = scale(sub(p, [c[0], c[1], 0.0]), 1.0 / r);
                let d = sub(eye.d, scale(n, 2.0 * dot(eye.d, n)));
                CHROME * self.trace(balls, Ray { from: b, p, d }, light, room, BOUNCES)
            }
            None => {
                let t = distance / -eye.d[2];
                let p = add(eye.p, scale(eye.d, t));
                self.backdrop_at(p[0], p[1], light.towards([p[0], p[1], 0.0]))
            }
        }
    }

    /// Panics on a set that cannot be rendered.
    fn check(&self) {
        if let Some(p) = &self.light_positions {
            assert_eq!(p.len(), self.lights.len(), "one light position per light");
            for q in p {
                for (c, r) in self.balls() {
                    let gap = (q[0] - c[0]).hypot(q[1] - c[1]).hypot(q[2]) - r;
                    assert!(gap > self.light_size, "light at {q:?} touches a ball");
                }
            }
        }
    }

    fn light(&self, i: usize) -> Light {
        let radius = self
            .light_radius_deg_each
            .as_ref()
            .map_or(self.light_radius_deg, |r| r[i]);
        Light {
            raw: self.lights[i],
            direction: normalise(self.lights[i]),
            position: self.light_positions.as_ref().map(|p| p[i]),
            size: self.light_size,
            level: self.highlight[i],
            cos_radius: radius.to_radians().cos(),
        }
    }

    /// The mean of `f` over each pixel's footprint.
    fn supersampled(&self, f: impl Fn(f64, f64) -> f64 + Sync) -> Array2<f64> {
        let s = SUPERSAMPLE as f64;
        Array2::from_shape_fn((self.height, self.width), |(r, c)| {
            let mut sum = 0.0;
            for j in 0..SUPERSAMPLE {
                for i in 0..SUPERSAMPLE {
                    let x = c as f64 - 0.5 + (i as f64 + 0.5) / s;
                    let y = r as f64 - 0.5 + (j as f64 + 0.5) / s;
                    sum += f(x, y);
                }
            }
            sum / (s * s)
        })
    }

    fn expose(&self, img: Array2<f64>, index: usize) -> Array2<u16> {
        let noise = sensor::Noise {
            black_level: self.black_level,
            read_sigma: self.noise_sigma,
            full_well: Some(20_000.0),
        };
        let mut rng = Rng::new(self.seed.wrapping_mul(1_000_003).wrapping_add(index as u64));
        let shaped = img.insert_axis(ndarray::Axis(2));
        sensor::capture(&shaped, 1.0, noise, self.max(), &mut rng).remove_axis(ndarray::Axis(2))
    }

    /// What a ray leaving ball `ray.from` sees: another ball (mirroring in turn), a near
    /// light, or what lies at infinity, whichever is nearest.
    fn trace(
        &self,
        balls: &[([f64; 2], f64)],
        ray: Ray,
        light: &Light,
        room: &[Patch],
        bounces: usize,
    ) -> f64 {
        let ball = nearest_ball(balls, &ray);
        if let Some(q) = light.position {
            let t = hit_sphere(ray.p, ray.d, q, light.size);
            if t.is_some_and(|t| ball.is_none_or(|(_, tb)| t < tb)) {
                return light.level / CHROME;
            }
        }
        let Some((b, t)) = ball else {
            return self.environment(ray.p, ray.d, light, room);
        };
        if bounces == 0 {
            return 0.7 * self.room;
        }
        let (c, r) = balls[b];
        let p = add(ray.p, scale(ray.d, t));
        let n = scale(sub(p, [c[0], c[1], 0.0]), 1.0 / r);
        let k = 2.0 * dot(ray.d, n);
        let d = sub(ray.d, scale(n, k));
        CHROME * self.trace(balls, Ray { from: b, p, d }, light, room, bounces - 1)
    }

    /// What the balls reflect along unit direction `d` from `p`, beyond them all.
    fn environment(&self, p: [f64; 3], d: [f64; 3], light: &Light, room: &[Patch]) -> f64 {
        if light.position.is_none() && dot(d, light.direction) > light.cos_radius {
            return light.level / CHROME;
        }
        if let Some(patch) = room.iter().find(|r| r.covers(d)) {
            return patch.level / CHROME;
        }
        // A room: walls with soft structure, a darker floor and the dark camera side.
        let mut v = self.room
            * (0.7 + 0.2 * (3.0 * d[0]).sin() * (2.0 * d[1]).cos() - 0.15 * d[1] + 0.1 * d[2]);
        if self.distractors {
            // A white box beside the ball, lit by the light (a ~16° patch).
            let side = normalise([0.93, 0.12, 0.35]);
            if dot(d, side) > 16f64.to_radians().cos() {
                let l = light
                    .position
                    .map_or(light.direction, |q| normalise(sub(q, p)));
                v = 0.55 * (0.5 + 0.5 * dot(l, normalise([-1.0, -0.2, 0.6])));
            }
            // A fluorescent tube: 0.5° thick along 30° of a great circle.
            let (mid, axis) = (normalise([-0.45, -0.55, 0.7]), normalise([0.8, -0.3, 0.3]));
            let plane = normalise(cross(mid, axis));
            if dot(d, plane).abs() < 0.25f64.to_radians().sin()
                && dot(d, mid) > 15f64.to_radians().cos()
            {
                v = 0.9;
            }
        }
        v
    }

    /// The backdrop: stripes and a checkerboard, lit from `l`.
    fn backdrop_at(&self, x: f64, y: f64, l: [f64; 3]) -> f64 {
        let checker = if ((x / 23.0).floor() + (y / 17.0).floor()) as i64 % 2 == 0 {
            1.0
        } else {
            0.6
        };
        let stripes = 0.8 + 0.2 * (x / 4.1 + 0.6 * y / 9.0).sin();
        self.backdrop * checker * stripes * (0.75 + 0.25 * l[2])
    }
}

/// One image's light.
struct Light {
    /// As given in `lights`, and unit.
    raw: [f64; 3],
    direction: [f64; 3],
    /// A near light's centre and radius.
    position: Option<[f64; 3]>,
    size: f64,
    level: f64,
    cos_radius: f64,
}

impl Light {
    /// Towards the light from `p`.
    fn towards(&self, p: [f64; 3]) -> [f64; 3] {
        self.position.map_or(self.raw, |q| normalise(sub(q, p)))
    }
}

/// A room light ready for many look-ups: a disc, or a window in its own frame.
struct Patch {
    centre: [f64; 3],
    across: [f64; 3],
    up: [f64; 3],
    cos_radius: f64,
    /// Tangents of a window's half width and half height.
    window: Option<[f64; 2]>,
    level: f64,
}

impl Patch {
    fn new(l: &RoomLight) -> Self {
        let centre = normalise(l.direction);
        // Horizontal sides: `across` has no y (vertical) part.
        let across = normalise([centre[2], 0.0, -centre[0]]);
        Self {
            centre,
            across,
            up: cross(centre, across),
            cos_radius: l.radius_deg.to_radians().cos(),
            window: l
                .half_height_deg
                .map(|h| [l.radius_deg.to_radians().tan(), h.to_radians().tan()]),
            level: l.level,
        }
    }

    fn covers(&self, d: [f64; 3]) -> bool {
        let along = dot(d, self.centre);
        match self.window {
            None => along > self.cos_radius,
            Some([w, h]) => {
                along > 0.0
                    && dot(d, self.across).abs() < w * along
                    && dot(d, self.up).abs() < h * along
            }
        }
    }
}

/// A ray leaving the surface of ball `from` at `p` along unit `d`.
#[derive(Clone, Copy)]
struct Ray {
    from: usize,
    p: [f64; 3],
    d: [f64; 3],
}

/// The ball seen at image point (x, y) (the nearest to the camera where they overlap)
/// and its unit normal there.
fn hit(balls: &[([f64; 2], f64)], x: f64, y: f64) -> Option<(usize, [f64; 3])> {
    let mut seen: Option<(usize, [f64; 3])> = None;
    for (b, &(c, r)) in balls.iter().enumerate() {
        let (u, v) = ((x - c[0]) / r, (y - c[1]) / r);
        let h = 1.0 - u * u - v * v;
        if h > 0.0 {
            let n = [u, v, h.sqrt()];
            if seen.is_none_or(|(a, m)| r * n[2] > balls[a].1 * m[2]) {
                seen = Some((b, n));
            }
        }
    }
    seen
}

/// The nearest other ball along `ray` and the distance to it.
fn nearest_ball(balls: &[([f64; 2], f64)], ray: &Ray) -> Option<(usize, f64)> {
    let mut nearest: Option<(usize, f64)> = None;
    for (b, &(c, r)) in balls.iter().enumerate() {
        if b == ray.from {
            continue;
        }
        if let Some(t) = hit_sphere(ray.p, ray.d, [c[0], c[1], 0.0], r)
            && nearest.is_none_or(|(_, tn)| t < tn)
        {
            nearest = Some((b, t));
        }
    }
    nearest
}

/// Whether another ball hides the light from `p` on ball `from`, `l` towards it.
fn shadowed(
    balls: &[([f64; 2], f64)],
    from: usize,
    p: [f64; 3],
    l: [f64; 3],
    light: &Light,
) -> bool {
    let Some((_, t)) = nearest_ball(
        balls,
        &Ray {
            from,
            p,
            d: normalise(l),
        },
    ) else {
        return false;
    };
    light
        .position
        .is_none_or(|q| t * t < dot(sub(q, p), sub(q, p)))
}

/// The distance along unit `d` from `p` (outside) to a sphere, if the ray meets it.
fn hit_sphere(p: [f64; 3], d: [f64; 3], c: [f64; 3], r: f64) -> Option<f64> {
    let o = sub(p, c);
    let b = dot(o, d);
    let disc = b * b - (dot(o, o) - r * r);
    let t = -b - disc.max(0.0).sqrt();
    (disc >= 0.0 && t > 0.0).then_some(t)
}

/// The direction the camera sees reflected at a point of normal `n` (view along +z).
fn reflect(n: [f64; 3]) -> [f64; 3] {
    let k = 2.0 * n[2];
    [k * n[0], k * n[1], k * n[2] - 1.0]
}
