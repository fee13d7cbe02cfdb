//! The sphere's outline in the image: the type every stage of the calibration shares.

use serde::Serialize;

/// The sphere's outline in the image, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Circle {
    pub cx: f64,
    pub cy: f64,
    pub r: f64,
}
