//! The sets: the types of a calibration capture ([`ChromeSet`]) and of the room's static
//! lights ([`RoomLight`]), the usual capture and its variants, and the room lights.

use super::super::sensor::Rng;
use crate::core::vec3::normalise;

/// A calibration capture: the frame, the balls, the lights and the camera.
#[derive(Debug, Clone)]
pub struct ChromeSet {
    pub width: usize,
    pub height: usize,
    /// The first ball's centre (column, row; pixel centres at integers) and radius, pixels.
    pub centre: [f64; 2],
    pub radius: f64,
    /// Unit light directions (x right, y down, z towards the camera). With
    /// `light_positions`, the directions from the first ball's centre (not rendered).
    pub lights: Vec<[f64; 3]>,
    /// Each light's highlight level as a fraction of full scale (above 1 it clips).
    pub highlight: Vec<f64>,
    /// Angular radius of each light at infinity (a uniform disc), degrees.
    pub light_radius_deg: f64,
    /// Per-light angular radii, degrees, instead of `light_radius_deg`.
    pub light_radius_deg_each: Option<Vec<f64>>,
    /// Brightness of the room the ball reflects and of the backdrop around it, as
    /// fractions of full scale.
    pub room: f64,
    pub backdrop: f64,
    /// A bright diffuse object beside the ball and a streak from another fixture.
    pub distractors: bool,
    /// Bright things at infinity the balls mirror in every image, whichever light is on.
    pub room_lights: Vec<RoomLight>,
    /// Near lights: each light's centre in the frame above (pixels), instead of a
    /// direction at infinity; the same length as `lights`.
    pub light_positions: Option<Vec<[f64; 3]>>,
    /// Radius of each near light (a sphere), pixels.
    pub light_size: f64,
    /// More balls, (centre, radius) in pixels, rendered like the first.
    pub extra_balls: Vec<([f64; 2], f64)>,
    /// A pinhole camera this far above the plane z = 0 (and of this focal length, pixels),
    /// its principal point at the image centre; None: orthographic. The chrome balls only
    /// (the matte sphere is rendered orthographically).
    pub camera_distance: Option<f64>,
    pub bit_depth: u8,
    pub noise_sigma: f64,
    pub black_level: f64,
    pub seed: u64,
}

/// A static bright patch of the room (a lamp, a window) at infinity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoomLight {
    /// Towards its centre (need not be unit).
    pub direction: [f64; 3],
    /// Angular radius of a disc, or the half width of a window, degrees.
    pub radius_deg: f64,
    /// Its level in the mirror as a fraction of full scale (above 1 it clips).
    pub level: f64,
    /// A window: its half height, degrees (its sides horizontal and vertical as seen
    /// from the ball); None for a disc.
    pub half_height_deg: Option<f64>,
}

impl ChromeSet {
    /// The usual capture: 24 lights from 10° to 80° off the view axis (the last ones at
    /// grazing elevation, highlights near 0.64 of the radius), every third clipping, on an
    /// off-centre ball with distractors.
    pub fn standard(bit_depth: u8, seed: u64) -> Self {
        let lights = super::super::lights::light_rings(24, 10.0, 80.0);
        let highlight = levels(lights.len());
        Self {
            width: 320,
            height: 240,
            centre: [187.3, 109.6],
            radius: 93.4,
            lights,
            highlight,
            light_radius_deg: 1.8,
            light_radius_deg_each: None,
            room: 0.22,
            backdrop: 0.45,
            distractors: true,
            room_lights: Vec::new(),
            light_positions: None,
            light_size: 0.0,
            extra_balls: Vec::new(),
            camera_distance: None,
            bit_depth,
            noise_sigma: 0.004,
            black_level: 0.01,
            seed,
        }
    }

    /// A ball filling most of the frame (its outline 2–20 px from the border), dark on a
    /// dark backdrop, with 3° lights.
    pub fn filling(bit_depth: u8, seed: u64) -> Self {
        Self {
            width: 256,
            height: 224,
            centre: [129.6, 112.3],
            radius: 109.2,
            light_radius_deg: 3.0,
            room: 0.05,
            backdrop: 0.03,
            ..Self::standard(bit_depth, seed)
        }
    }

    /// `standard` with 20 lights in a room as real ones are: a small ceiling lamp that
    /// clips in every image (1.5°, level 3, 21° from the nearest light) and a window
    /// behind the ball on the upper left (20° × 14°, level 0.8, mirrored near the rim).
    pub fn real_room(bit_depth: u8, seed: u64) -> Self {
        let lights = super::super::lights::light_rings(20, 10.0, 80.0);
        Self {
            highlight: levels(lights.len()),
            lights,
            room_lights: vec![
                RoomLight::disc([0.65, -0.5, 0.57], 1.5, 3.0),
                // 100° off the view axis: beyond every light, so never on a highlight.
                RoomLight::window([-0.925, -0.337, -0.174], 10.0, 7.0, 0.8),
            ],
            ..Self::standard(bit_depth, seed)
        }
    }

    /// Two balls side by side (radii ~70 px, centres 240 px apart in a 480×240 frame)
    /// under 16 near lights on a hemisphere of radius `distance_in_ball_diameters` × the
    /// first ball's diameter centred between them (elevations 20°–75°, azimuths on a
    /// golden-angle spiral turned so that neither ball hides a light from the other, down
    /// to 1 diameter), each 1.5° across seen from the middle.
    pub fn near_dome(bit_depth: u8, seed: u64, distance_in_ball_diameters: f64) -> Self {
        let (centre, radius) = ([120.4, 119.6], 70.3);
        let second = ([359.7, 120.3], 69.6);
        let mid = [
            0.5 * (centre[0] + second.0[0]),
            0.5 * (centre[1] + second.0[1]),
        ];
        let reach = distance_in_ball_diameters * 2.0 * radius;
        let positions: Vec<[f64; 3]> = (0..16)
            .map(|i| {
                let elevation = (20.0 + 55.0 * i as f64 / 15.0f64).to_radians();
                let azimuth = (110.0 + 137.50776 * i as f64).to_radians();
                [
                    mid[0] + reach * elevation.cos() * azimuth.cos(),
                    mid[1] + reach * elevation.cos() * azimuth.sin(),
                    reach * elevation.sin(),
                ]
            })
            .collect();
        let lights = positions
            .iter()
            .map(|p| normalise([p[0] - centre[0], p[1] - centre[1], p[2]]))
            .collect::<Vec<_>>();
        Self {
            width: 480,
            height: 240,
            centre,
            radius,
            highlight: levels(lights.len()),
            lights,
            light_positions: Some(positions),
            light_size: reach * 1.5f64.to_radians().sin(),
            extra_balls: vec![second],
            ..Self::standard(bit_depth, seed)
        }
    }

    /// Eight images all lit from the same direction (levels as `standard`'s): nothing to
    /// calibrate from.
    pub fn all_same_light(bit_depth: u8, seed: u64) -> Self {
        let lights = vec![normalise([0.35, -0.25, 0.9]); 8];
        Self {
            highlight: levels(lights.len()),
            lights,
            ..Self::standard(bit_depth, seed)
        }
    }

    /// Every ball, (centre, radius), the first one first.
    pub fn balls(&self) -> Vec<([f64; 2], f64)> {
        std::iter::once((self.centre, self.radius))
            .chain(self.extra_balls.iter().copied())
            .collect()
    }

    /// The true light directions from ball `ball`'s centre (`lights` for lights at
    /// infinity) and each light's intensity there relative to the first ball's centre.
    pub fn truth_from(&self, ball: usize) -> Vec<([f64; 3], f64)> {
        let Some(positions) = &self.light_positions else {
            return self.lights.iter().map(|&l| (l, 1.0)).collect();
        };
        let (c, _) = self.balls()[ball];
        positions
            .iter()
            .map(|p| {
                let to = [p[0] - c[0], p[1] - c[1], p[2]];
                let first = [p[0] - self.centre[0], p[1] - self.centre[1], p[2]];
                let squared = |v: [f64; 3]| v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
                // Inverse-square falloff.
                (normalise(to), squared(first) / squared(to))
            })
            .collect()
    }
}

impl RoomLight {
    pub fn disc(direction: [f64; 3], radius_deg: f64, level: f64) -> Self {
        Self {
            direction,
            radius_deg,
            level,
            half_height_deg: None,
        }
    }

    /// A window `2 half_width_deg` wide and `2 half_height_deg` tall.
    pub fn window(
        direction: [f64; 3],
        half_width_deg: f64,
        half_height_deg: f64,
        level: f64,
    ) -> Self {
        Self {
            direction,
            radius_deg: half_width_deg,
            level,
            half_height_deg: Some(half_height_deg),
        }
    }
}

/// Highlight levels: 0.75–2.6, every third clipping.
fn levels(count: usize) -> Vec<f64> {
    (0..count)
        .map(|i| [0.75, 0.9, 2.5][i % 3] + 0.02 * (i % 5) as f64)
        .collect()
}

/// Relative light intensities for a matte set, 0.6–1.4, reproducible from `seed`.
pub fn matte_intensities(count: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng::new(seed);
    (0..count).map(|_| 0.6 + 0.8 * rng.uniform()).collect()
}
