//! What a calibration takes and gives: where the circle comes from, the settings and
//! memory budget, and the calibration itself (its lights, what
//! was left out, the maximum image for the overlay).

use std::path::PathBuf;

use ndarray::Array2;

use super::circle::Circle;
use super::highlight::Highlight;
use super::mirror::Camera;
use super::positions::LightPosition;
use super::reading::{COARSE_BYTES, CROP_BYTES};
use super::sphere::OutlineFit;

/// Where the sphere's circle comes from.
#[derive(Debug, Clone)]
pub enum CircleSource {
    /// Fitted to the images' outlines: every ball in the frame (see [`balls`](super::balls)).
    Fit,
    Given(Circle),
    /// Several balls in the frame, each its circle: each ball is calibrated, and each
    /// light is placed where the balls' rays meet.
    Balls(Vec<Circle>),
    /// A mask (true = sphere), its circle fitted to the mask's outline.
    Mask {
        name: String,
        mask: Array2<bool>,
    },
}

#[derive(Debug, Clone)]
pub struct Settings {
    pub circle: CircleSource,
    pub camera: Camera,
    /// Leave out images without a usable highlight (reported) instead of failing.
    pub skip_bad: bool,
    /// What the images may hold in memory (see [`reading`](super::reading)): the defaults, unless a test
    /// wants the downscaled and spilled paths on small images.
    pub budget: Budget,
    /// Where images' windows are spilled when they do not fit [`Budget::crop_bytes`]
    /// (unlinked files; default: the system's temporary directory).
    pub scratch: Option<PathBuf>,
}

/// The memory budgets of a calibration (defaults [`COARSE_BYTES`], [`CROP_BYTES`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Budget {
    /// The downscaled copies of the whole set.
    pub coarse_bytes: usize,
    /// The balls' windows of the whole set in memory; past it, spilled.
    pub crop_bytes: usize,
}

impl Default for Budget {
    fn default() -> Self {
        Self {
            coarse_bytes: COARSE_BYTES,
            crop_bytes: CROP_BYTES,
        }
    }
}

/// One calibrated light.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibratedLight {
    /// Position of its sphere image in the set (0-based).
    pub index: usize,
    /// The sphere image's file name and the name the light table gives the light.
    pub image: String,
    pub name: String,
    /// Its highlight on the (first) ball.
    pub highlight: Highlight,
    /// Its highlights on the other balls, in the order of [`Calibration::more_circles`].
    pub more: Vec<Highlight>,
    /// Where the balls' rays meet, with several balls (None when they are parallel).
    pub position: Option<LightPosition>,
    /// Relative intensity from a matte sphere, when fitted.
    pub intensity: Option<f64>,
}

/// An image left out by `skip_bad`, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    pub image: String,
    pub reason: String,
}

/// A calibration: the circle used, the lights, what was left out, and the maximum image
/// (for the overlay).
#[derive(Debug, Clone)]
pub struct Calibration {
    pub circle: Circle,
    /// The other balls' circles, with several balls.
    pub more_circles: Vec<Circle>,
    /// Whether positions are relative to a pinhole camera (else to the first ball).
    pub camera_is_pinhole: bool,
    /// How the outline fit went, when the circle was fitted to the images.
    pub outline: Option<OutlineFit>,
    /// The other balls' outline fits, in the order of `more_circles`, when they were
    /// found in the images; empty when given.
    pub more_outlines: Vec<OutlineFit>,
    /// Round outlines found beside the ball that show no highlight in most images: not
    /// balls, left out.
    pub not_balls: Vec<Circle>,
    pub lights: Vec<CalibratedLight>,
    pub skipped: Vec<Skipped>,
    /// Per pixel, the brightest of the images as the overlay shows it (gamma ½, 8 bits).
    pub max_image: Array2<u8>,
}
