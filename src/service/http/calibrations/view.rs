//! A calibration as the API shows it: the circle used, the lights with their quality
//! figures, the images left out, links to its files; made from the core's calibration
//! and read back from the stored record.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use uuid::Uuid;

use crate::core::calibrate::{CalibratedLight, Calibration, Highlight};
use crate::service::error::ApiError;
use crate::service::intake::calibration::Form;
use crate::service::repo::CalibrationRecord;
use crate::service::util::rfc3339;

/// A calibration: the circle used, the lights with their quality figures, the images left
/// out, and links to its files.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationView {
    /// The calibration's id (a random UUID); a job's `calibration` part names it.
    pub id: Uuid,
    /// The tenant that created it.
    #[schema(example = "alice")]
    pub tenant: String,
    /// RFC 3339.
    #[schema(example = "2025-11-25T19:34:00.123Z")]
    pub created_at: String,
    #[serde(flatten)]
    pub measured: Measured,
    /// File name → download URL: `lights.csv` (the light table), `overlay.png` (circles
    /// and numbered highlights over the maximum image), `lights.png` (the directions on
    /// the unit hemisphere) and, with several balls, `positions.csv` (the lights'
    /// positions).
    #[schema(example = json!({"lights.csv": "/v1/calibrations/0b6f2a43-3c1e-4c51-9d1e-6c9f3a7d2e10/lights.csv"}))]
    pub files: BTreeMap<String, String>,
    /// This resource's URL.
    pub url: String,
}

/// What a calibration measured (stored as the record's detail).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Measured {
    /// The sphere images' size, pixels.
    pub width: u32,
    pub height: u32,
    /// Sphere images sent (lights found plus images skipped).
    pub image_count: u32,
    /// The pinhole camera's focal length in pixels; null for an orthographic camera.
    pub focal_length: Option<f64>,
    /// The (first) ball's circle: the lights' `direction` and `highlight` are on it.
    pub circle: CircleView,
    /// With several balls (`circle` given more than once, or found when no circle is
    /// given): the other balls' circles, in the order given or, when found, left to right
    /// (the first ball, `circle`, is then the leftmost); empty with one ball.
    #[serde(default)]
    pub more_circles: Vec<CircleView>,
    /// The `ball_diameter` part, when given.
    #[serde(default)]
    pub ball_diameter: Option<f64>,
    /// With several balls, the unit of the lights' `position`: `ball_radii`, or
    /// `ball_diameter` (the unit `ball_diameter` was given in); null with one ball.
    #[serde(default)]
    #[schema(example = "ball_radii")]
    pub position_unit: Option<String>,
    /// With several balls, the origin of the lights' `position` (x = column right, y =
    /// row down, z towards the camera): `first_ball` (its centre; orthographic) or
    /// `camera` (with `focal_length`); null with one ball.
    #[serde(default)]
    #[schema(example = "first_ball")]
    pub position_origin: Option<String>,
    /// One per sphere image with a usable highlight, in upload order.
    pub lights: Vec<LightView>,
    /// Images left out (`skip_bad`), and why.
    pub skipped: Vec<SkippedView>,
}

/// The sphere's circle in pixels (0-based, pixel centres at integers).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct CircleView {
    pub cx: f64,
    pub cy: f64,
    pub r: f64,
    /// `fitted` (to the images' outline), `given` (a `circle` part) or `mask`.
    #[schema(example = "fitted")]
    pub source: String,
    /// For a fitted circle: the fraction of the outline the fit found, and the RMS
    /// distance of its edge points from the circle (pixels).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms: Option<f64>,
}

/// One calibrated light.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct LightView {
    /// The light table's name for it (what the object image must be called).
    #[schema(example = "im1.png")]
    pub name: String,
    /// Its sphere image's file name, and its number (1-based, upload order) in
    /// `overlay.png` and `lights.png`.
    pub image: String,
    pub number: u32,
    /// Unit direction towards the light: x = column right, y = row down, z towards the
    /// camera.
    pub direction: [f64; 3],
    /// Relative intensity (mean 1) from the matte sphere, when `matte` images were sent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intensity: Option<f64>,
    /// Degrees above the image plane, and around it from the x axis (towards y).
    pub elevation_deg: f64,
    pub azimuth_deg: f64,
    pub highlight: HighlightView,
    /// With several balls: its highlight on each of the other balls, in the order of
    /// `more_circles`; empty with one ball.
    #[serde(default)]
    pub more_highlights: Vec<MoreHighlightView>,
    /// With several balls: where the balls' rays towards the light meet, in
    /// `position_unit` from `position_origin`; null with one ball, or when the rays are
    /// (near) parallel (a light far away).
    #[serde(default)]
    pub position: Option<PositionView>,
}

/// A light's highlight on another ball, and the direction it gives from there.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct MoreHighlightView {
    /// Unit direction towards the light from that ball's highlight (as `direction`).
    pub direction: [f64; 3],
    pub highlight: HighlightView,
}

/// A light's position from several balls.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PositionView {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    /// RMS distance of the position from the balls' rays, in `position_unit`: large
    /// against the distance means the highlights disagree.
    pub residual: f64,
    /// Largest angle between two of the rays, degrees: near 0 the distance is poorly
    /// known.
    pub spread_deg: f64,
}

/// The highlight the direction comes from, and how trustworthy it looks.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct HighlightView {
    /// Brightness-weighted centre, pixels (0-based, pixel centres at integers).
    pub x: f64,
    pub y: f64,
    /// Pixels in the blob.
    pub pixels: u64,
    /// Brightest value (fraction of full scale) and whether it is clipped.
    pub peak: f64,
    pub clipped: bool,
    /// Distance of the centre from the sphere's outline, pixels.
    pub rim_distance: f64,
    /// Ratio of the blob's principal axes in direction space (1 = round).
    pub elongation: f64,
    /// The blob's equivalent angular radius, degrees.
    pub radius_deg: f64,
    /// How sure the finder is that this is the light's own highlight, 0..1: it beats
    /// any other candidate clearly, the environment explains little of it, and it has a
    /// few pixels at least. Absent in calibrations stored before it was measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f64>,
}

/// A sphere image left out.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct SkippedView {
    pub image: String,
    pub reason: String,
}

/// A page of calibrations, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationList {
    pub calibrations: Vec<CalibrationView>,
    /// Pass as `cursor` to get the next page; null on the last page.
    pub next_cursor: Option<String>,
}

fn calibration_url(id: Uuid) -> String {
    format!("/v1/calibrations/{id}")
}

impl CalibrationView {
    pub fn from_record(r: CalibrationRecord) -> Result<Self, ApiError> {
        let url = calibration_url(r.id);
        let measured: Measured = serde_json::from_value(r.detail)
            .map_err(|e| ApiError::internal(format!("stored calibration {}: {e}", r.id)))?;
        Ok(Self {
            id: r.id,
            tenant: r.tenant,
            created_at: rfc3339(r.created_at),
            measured,
            files: r
                .artifacts
                .iter()
                .map(|a| (a.name.clone(), format!("{url}/{}", a.name)))
                .collect(),
            url,
        })
    }
}

pub(super) fn measured(
    cal: &Calibration,
    form: &Form,
    w: usize,
    h: usize,
    source: &str,
) -> Measured {
    let c = cal.circle;
    let several = !cal.more_circles.is_empty();
    // Positions are computed in ball radii; a diameter in some unit scales them to it.
    let scale = form.ball_diameter.map_or(1.0, |d| d / 2.0);
    Measured {
        width: w as u32,
        height: h as u32,
        image_count: form.images.len() as u32,
        focal_length: form.focal_length,
        circle: CircleView {
            cx: c.cx,
            cy: c.cy,
            r: c.r,
            source: source.to_string(),
            coverage: cal.outline.as_ref().map(|o| o.coverage),
            rms: cal.outline.as_ref().map(|o| o.rms),
        },
        more_circles: cal
            .more_circles
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let fit = cal.more_outlines.get(k);
                CircleView {
                    cx: c.cx,
                    cy: c.cy,
                    r: c.r,
                    source: source.to_string(),
                    coverage: fit.map(|o| o.coverage),
                    rms: fit.map(|o| o.rms),
                }
            })
            .collect(),
        ball_diameter: form.ball_diameter,
        position_unit: several.then(|| {
            match form.ball_diameter {
                Some(_) => "ball_diameter",
                None => "ball_radii",
            }
            .to_string()
        }),
        position_origin: several.then(|| {
            match cal.camera_is_pinhole {
                true => "camera",
                false => "first_ball",
            }
            .to_string()
        }),
        lights: cal.lights.iter().map(|l| light_view(l, scale)).collect(),
        skipped: cal
            .skipped
            .iter()
            .map(|s| SkippedView {
                image: s.image.clone(),
                reason: s.reason.clone(),
            })
            .collect(),
    }
}

/// A light as the resource shows it, its position (if any) multiplied by `scale`.
fn light_view(l: &CalibratedLight, scale: f64) -> LightView {
    let d = l.highlight.direction;
    LightView {
        name: l.name.clone(),
        image: l.image.clone(),
        number: l.index as u32 + 1,
        direction: d,
        intensity: l.intensity,
        elevation_deg: d[2].clamp(-1.0, 1.0).asin().to_degrees(),
        azimuth_deg: d[1].atan2(d[0]).to_degrees(),
        highlight: highlight_view(&l.highlight),
        more_highlights: l
            .more
            .iter()
            .map(|hl| MoreHighlightView {
                direction: hl.direction,
                highlight: highlight_view(hl),
            })
            .collect(),
        position: l.position.map(|p| PositionView {
            x: scale * p.position[0],
            y: scale * p.position[1],
            z: scale * p.position[2],
            residual: scale * p.residual,
            spread_deg: p.spread_deg,
        }),
    }
}

fn highlight_view(hl: &Highlight) -> HighlightView {
    HighlightView {
        x: hl.x,
        y: hl.y,
        pixels: hl.pixels as u64,
        peak: hl.peak,
        clipped: hl.clipped,
        rim_distance: hl.rim_distance,
        elongation: hl.elongation,
        radius_deg: hl.radius_deg,
        confidence: Some(hl.confidence),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A record stored before several balls were served reads back with none of their
    /// fields, and the view says so.
    #[test]
    fn a_record_stored_before_several_balls_reads_back() {
        let detail = serde_json::json!({
            "width": 320, "height": 240, "image_count": 3, "focal_length": null,
            "circle": {"cx": 1.0, "cy": 2.0, "r": 3.0, "source": "given"},
            "lights": [{"name": "a.png", "image": "a.png", "number": 1,
                "direction": [0.0, 0.0, 1.0], "elevation_deg": 90.0, "azimuth_deg": 0.0,
                "highlight": {"x": 1.0, "y": 2.0, "pixels": 4, "peak": 0.9, "clipped": false,
                    "rim_distance": 3.0, "elongation": 1.0, "radius_deg": 1.0}}],
            "skipped": []
        });
        let m: Measured = serde_json::from_value(detail).unwrap();
        assert!(m.more_circles.is_empty() && m.position_unit.is_none());
        assert!(m.lights[0].more_highlights.is_empty() && m.lights[0].position.is_none());
        let shown = serde_json::to_value(&m).unwrap();
        assert_eq!(shown["more_circles"], serde_json::json!([]));
        assert!(shown["lights"][0]["position"].is_null());
        // And what is stored now round-trips.
        let again: Measured = serde_json::from_value(shown.clone()).unwrap();
        assert_eq!(serde_json::to_value(&again).unwrap(), shown);
    }
}
