//! The checks a calibration makes of its input and its result: images enough and of one
//! size, a usable circle, lights that do not all point one way; and a light's name made
//! from its image's.

use super::circle::Circle;
use super::error::CalibrationError;
use super::model::CalibratedLight;
use super::source::Source;
use crate::core::error::InputError;
use crate::core::vec3::{dot, normalise};

/// Lights that all come out within this angle of their mean direction are one light, or a
/// reflection that stays put: not a calibration.
pub const MIN_SPREAD_DEG: f64 = 2.0;

/// Refuse lights that all point the same way: the images show one light, or the finder
/// followed something that stays put.
pub(super) fn check_spread(lights: &[CalibratedLight]) -> Result<(), CalibrationError> {
    if lights.len() < 3 {
        return Ok(());
    }
    let mut mean = [0.0; 3];
    for l in lights {
        for k in 0..3 {
            mean[k] += l.highlight.direction[k];
        }
    }
    let mean = normalise(mean);
    let spread = lights
        .iter()
        .map(|l| {
            dot(l.highlight.direction, mean)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        })
        .fold(0.0, f64::max);
    if spread < MIN_SPREAD_DEG {
        return Err(CalibrationError::OneDirection {
            count: lights.len(),
            spread,
        });
    }
    Ok(())
}

/// At least 3 images, all one size; their (width, height).
pub(super) fn check_images(images: &dyn Source) -> Result<(usize, usize), CalibrationError> {
    if images.count() < 3 {
        return Err(InputError::TooFewImages {
            count: images.count(),
        }
        .into());
    }
    let (w, h) = images.size(0)?;
    for k in 1..images.count() {
        let (iw, ih) = images.size(k)?;
        if (iw, ih) != (w, h) {
            return Err(InputError::SizeMismatch {
                name: images.name(k).to_string(),
                width: iw as u32,
                height: ih as u32,
                first: images.name(0).to_string(),
                expected_width: w as u32,
                expected_height: h as u32,
            }
            .into());
        }
    }
    Ok((w, h))
}

/// A circle is usable when its centre lies in the image and its radius is a few pixels
/// at least and not far beyond the frame.
pub(super) fn check_circle(c: &Circle, w: usize, h: usize) -> Result<(), CalibrationError> {
    let bad = |reason: String| CalibrationError::BadCircle {
        cx: c.cx,
        cy: c.cy,
        r: c.r,
        reason,
    };
    if ![c.cx, c.cy, c.r].iter().all(|v| v.is_finite()) {
        return Err(bad("not finite".into()));
    }
    if c.cx < 0.0 || c.cy < 0.0 || c.cx > (w - 1) as f64 || c.cy > (h - 1) as f64 {
        return Err(bad(format!(
            "the centre lies outside the {w}×{h} image (pixel centres 0..{} × 0..{})",
            w - 1,
            h - 1
        )));
    }
    if c.r < 4.0 {
        return Err(bad("the radius is under 4 pixels".into()));
    }
    if c.r > 2.0 * w.max(h) as f64 {
        return Err(bad(format!(
            "the radius is over twice the {w}×{h} image's size"
        )));
    }
    Ok(())
}

/// An image's name as a light's: the characters a light table cannot hold become `_`.
pub(super) fn light_name(image: &str) -> String {
    let mut name = String::new();
    for c in image.chars() {
        let c = if matches!(c, ',' | '#' | '"') || c.is_control() {
            '_'
        } else {
            c
        };
        if name.len() + c.len_utf8() > crate::core::lights::MAX_NAME_BYTES {
            break;
        }
        name.push(c);
    }
    match name.trim() {
        "" => "light".to_string(),
        t => t.to_string(),
    }
}
