//! One light and the table of them, whatever layout the table came in: the records
//! ([`Light`], [`Emitter`], [`Rig`], [`Table`]), one row's light made and checked
//! ([`make_light`]), and the checks every table and light name passes.

use serde::{Deserialize, Serialize};

use crate::core::camera::Pinhole;
use crate::core::error::InputError;

/// Rec. 709 luminance weights for R, G, B.
pub const LUMA_WEIGHTS: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// A light's brightness as a table gives it: one value, or one per colour channel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Intensity {
    One(f64),
    Rgb([f64; 3]),
}

/// One image's light: a unit direction (seed frame) and a relative intensity.
#[derive(Debug, Clone, PartialEq)]
pub struct Light {
    pub name: String,
    /// For a near light, the direction from the scene's centre (on the optical axis at the
    /// working distance) to the light: what a distant table would say.
    pub direction: [f64; 3],
    /// The scalar the solve uses. For an RGB intensity this is the Rec. 709 luminance of
    /// `rgb` (right for a gray image), until intake meets the image in colour: it then
    /// divides each channel by its own intensity and rescales the result by
    /// min(r, g, b), which becomes this value.
    pub intensity: f64,
    /// The per-channel intensities, when the table gives them.
    pub rgb: Option<[f64; 3]>,
    /// Where the light is, when the table gives its position (a near light).
    pub emitter: Option<Emitter>,
}

/// A light at a finite distance: its direction and irradiance change across the scene.
/// Radiance towards a point `X` is `intensity · max(0, −l·axis)^anisotropy / r²` with
/// `r = |position − X|`, `l = (position − X) / r`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Emitter {
    /// Camera frame (x right, y down, z towards the camera; the scene lies at z < 0), in
    /// the table's unit.
    pub position: [f64; 3],
    /// The LED's unit principal direction, towards the scene; None: isotropic.
    pub axis: Option<[f64; 3]>,
    /// μ ≥ 0 of the falloff off the axis (0 without an axis).
    pub anisotropy: f64,
    /// Whether the table gave the intensity; an LED's unknown intensity is estimated
    /// from the object itself.
    pub intensity_known: bool,
}

/// What a near-light table says beside its lights: the camera, the working distance to
/// the object along the optical axis and the unit of positions and distance.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Rig {
    pub camera: Option<Pinhole>,
    pub distance: Option<f64>,
    pub unit: Option<String>,
}

/// A light table with what its top level says.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    pub lights: Vec<Light>,
    pub rig: Rig,
}

impl Table {
    /// Whether any light is given by its position.
    pub fn is_near(&self) -> bool {
        self.lights.iter().any(|l| l.emitter.is_some())
    }
}

impl Light {
    /// The light as the solve sees it: direction scaled by intensity.
    pub fn scaled(&self) -> [f64; 3] {
        self.direction.map(|c| c * self.intensity)
    }
}

/// Longest light table accepted (rows); far above any real rig, it bounds parsing work.
pub const MAX_ROWS: usize = 10_000;

/// What every table must be, whatever its layout: no name twice, at least 3 rows.
pub fn check_table(lights: &[Light]) -> Result<(), InputError> {
    check_duplicates(lights)?;
    if lights.len() < 3 {
        return Err(InputError::TooFewImages {
            count: lights.len(),
        });
    }
    Ok(())
}

/// Longest light name (bytes).
pub const MAX_NAME_BYTES: usize = 255;

/// Whether `name` can be a light's name in a CSV table and read back as itself: not
/// empty, at most [`MAX_NAME_BYTES`], no `,` (the field separator), `#` (a comment), `"`,
/// control characters, or space at either end. The reason, if not.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("a name is empty".into());
    }
    if name.len() > MAX_NAME_BYTES {
        return Err(format!("a name is longer than {MAX_NAME_BYTES} bytes"));
    }
    if let Some(c) = name
        .chars()
        .find(|c| matches!(c, ',' | '#' | '"') || c.is_control())
    {
        return Err(format!(
            "{name:?} contains {c:?}: a light name cannot hold a comma, #, a quote or a control character"
        ));
    }
    if name.trim() != name {
        return Err(format!("{name:?} starts or ends with a space"));
    }
    Ok(())
}

/// Rec. 709 luminance of an RGB intensity: the scalar for a gray image under that light.
pub fn luminance(rgb: [f64; 3]) -> f64 {
    (0..3).map(|c| f64::from(LUMA_WEIGHTS[c]) * rgb[c]).sum()
}

/// One row's light from its parts, checked; `row` (1-based) goes into the error.
pub fn make_light(
    row: usize,
    name: &str,
    v: [f64; 3],
    intensity: Option<Intensity>,
) -> Result<Light, InputError> {
    let bad = |reason: String| InputError::LightRow { row, reason };
    if name.is_empty() {
        return Err(bad("the file name is empty".into()));
    }
    if let Some(c) = v.iter().find(|c| !c.is_finite()) {
        return Err(bad(format!(
            "light vector of {name:?} has a non-finite component ({c})"
        )));
    }
    let norm = v.iter().map(|c| c * c).sum::<f64>().sqrt();
    // Components up to 1e150 square without overflow; anything larger is not a direction.
    if !norm.is_finite() || norm > 1e150 {
        return Err(bad(format!("light vector of {name:?} is too large: {v:?}")));
    }
    if norm < 1e-12 {
        return Err(bad(format!("light vector of {name:?} is zero: {v:?}")));
    }
    let check = |what: &str, i: f64| {
        if !i.is_finite() || i <= 0.0 || i > 1e6 {
            return Err(bad(format!(
                "{what} of {name:?} must be a positive number up to 1e6, got {i}"
            )));
        }
        Ok(i)
    };
    let (intensity, rgb) = match intensity.unwrap_or(Intensity::One(1.0)) {
        Intensity::One(i) => (check("intensity", i)?, None),
        Intensity::Rgb([r, g, b]) => {
            let rgb = [
                check("intensity r", r)?,
                check("intensity g", g)?,
                check("intensity b", b)?,
            ];
            (luminance(rgb), Some(rgb))
        }
    };
    Ok(Light {
        name: name.to_string(),
        direction: v.map(|c| c / norm),
        intensity,
        rgb,
        emitter: None,
    })
}

/// A light given on its own (e.g. for re-shading): three finite numbers, not all zero.
pub fn check_direction(v: [f64; 3]) -> Result<[f64; 3], InputError> {
    make_light(1, "light", v, None)
        .map(|l| l.direction)
        .map_err(|e| match e {
            InputError::LightRow { reason, .. } => InputError::Lights(reason),
            other => other,
        })
}

fn check_duplicates(lights: &[Light]) -> Result<(), InputError> {
    let mut seen = std::collections::HashMap::new();
    for (i, l) in lights.iter().enumerate() {
        if let Some(first) = seen.insert(l.name.as_str(), i + 1) {
            return Err(InputError::DuplicateName {
                name: l.name.clone(),
                first,
                second: i + 1,
            });
        }
    }
    Ok(())
}
