//! Why a calibration fails: the images, the circle or mask, the names, or the highlights,
//! each error naming the file or value at fault.

use thiserror::Error;

use crate::core::error::InputError;

#[derive(Debug, Error)]
pub enum CalibrationError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error(
        "no sphere found in the images: {0}; give its circle (cx,cy,r in pixels) or a sphere mask"
    )]
    NoSphere(String),
    #[error("circle (centre {cx}, {cy}, radius {r}): {reason}")]
    BadCircle {
        cx: f64,
        cy: f64,
        r: f64,
        reason: String,
    },
    #[error("sphere mask {name:?}: {reason}")]
    Mask { name: String, reason: String },
    #[error("image {name:?}: {reason}")]
    Image { name: String, reason: String },
    #[error(
        "only {usable} of {count} images have a usable highlight, at least 3 are needed; left out: {left_out}"
    )]
    TooFewUsable {
        usable: usize,
        count: usize,
        left_out: String,
    },
    #[error(
        "the {count} images are alike: only {differing} have a highlight the others lack (one light photographed again and again, or the rig's lights did not change between the shots)"
    )]
    AllAlike { differing: usize, count: usize },
    #[error(
        "all {count} lights come out within {spread:.1}° of each other although the images differ: the highlight found is not the rig's light but something the ball shows in every image; add an ambient image of the ball with the rig's lights off (ambient.png) or give --circle"
    )]
    OneDirection { count: usize, spread: f64 },
    #[error("names: {0}")]
    Names(String),
    #[error("matte sphere image {name:?}: {reason}")]
    Matte { name: String, reason: String },
}
