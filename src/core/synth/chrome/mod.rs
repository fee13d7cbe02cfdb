//! Light-calibration captures: chrome (mirror) spheres photographed once per light by an
//! orthographic camera (or a pinhole, [`ChromeSet::camera_distance`]), and a matte white
//! sphere under the same lights.
//!
//! Each pixel integrates what the ball reflects over its footprint (`SUPERSAMPLE`²
//! samples), so a light of finite angular size leaves a highlight with a real, finite
//! shape: round near the ball's centre, squeezed towards the rim. The environment is a dim
//! room, the light (a disc of `light_radius_deg`, or a small sphere at a 3-D position),
//! static room lights, a bright diffuse object beside the ball and a thin streak from
//! another fixture; with several balls each also mirrors the others. Outside the balls, a
//! textured backdrop (stripes and a checkerboard) lit by the same light.
//!
//! Frame: x = column right, y = row down, z towards the camera, in pixels; the image
//! plane z = 0 passes through every ball's centre. A pinhole camera sits on the axis
//! through the image centre at `camera_distance` above that plane, with that focal length
//! in pixels, so the plane is imaged one unit a pixel and the balls' centres where they
//! are; their outlines are then a little larger, and ellipses off the axis.

mod render;
mod set;
#[cfg(test)]
mod tests;
mod write;

pub use set::matte_intensities;

/// The folder of a set's true lights and circles.
pub const TRUTH: &str = "truth-lights";

/// Samples per pixel side.
const SUPERSAMPLE: usize = 6;

/// Mirror reflectance of the chrome (roughly constant with angle for a metal).
const CHROME: f64 = 0.65;

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
