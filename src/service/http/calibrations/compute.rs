//! A calibration computed from its stored images: the core's `calibrate` run within the
//! request (on the blocking pool), its files written beside the images.

use std::path::Path;

use crate::core::calibrate::{self, Budget, Camera, CircleSource, ImageFiles, Settings, Source};
use crate::core::intake::{Limits, NamedFile};
use crate::service::error::ApiError;
use crate::service::intake::calibration::{Form, Stored};
use crate::service::repo::ArtifactInfo;
use crate::service::util::strong_etag;

use super::view::{Measured, measured};

/// What [`compute`] made: the measured detail, the light table and the stored files.
pub(super) struct Made {
    pub(super) measured: Measured,
    pub(super) table: String,
    pub(super) files: Vec<ArtifactInfo>,
}

/// Calibrate from the stored images (read from their files a few at a time, within
/// `calibrate::peak_bytes(max_pixels)`, spilling to `dir` when needed), and replace the
/// uploads in `dir` with the calibration's files. Blocking.
pub(super) fn compute(dir: &Path, form: Form, limits: &Limits) -> Result<Made, ApiError> {
    let files = |images: &[Stored]| {
        ImageFiles::new(
            images
                .iter()
                .map(|s| NamedFile {
                    name: s.name.clone(),
                    path: dir.join(&s.file),
                })
                .collect(),
            *limits,
        )
    };
    let images = files(&form.images);
    let (circle, source) = match (&form.circles[..], &form.mask) {
        ([c], _) => (CircleSource::Given(*c), "given"),
        ([_, _, ..], _) => (CircleSource::Balls(form.circles.clone()), "given"),
        ([], Some(m)) => {
            let mask = files(std::slice::from_ref(m)).decode_all()?.remove(0);
            (
                CircleSource::Mask {
                    name: mask.name,
                    mask: mask.plane.mapv(|v| v > 0),
                },
                "mask",
            )
        }
        ([], None) => (CircleSource::Fit, "fitted"),
    };
    let (w, h) = (
        form.images[0].width as usize,
        form.images[0].height as usize,
    );
    let camera = match form.focal_length {
        Some(f) => Camera::Perspective {
            focal_px: f,
            principal: [(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0],
        },
        None => Camera::Orthographic,
    };
    let settings = Settings {
        circle,
        camera,
        skip_bad: form.skip_bad.unwrap_or(false),
        budget: Budget::default(),
        scratch: Some(dir.to_path_buf()),
    };
    let ambient = form
        .ambient
        .as_ref()
        .map(|a| files(std::slice::from_ref(a)));
    let mut cal = calibrate::calibrate(
        &images,
        form.names.as_deref(),
        ambient.as_ref().map(|a| a as &dyn Source),
        &settings,
    )?;
    if form.ball_diameter.is_some() && cal.more_circles.is_empty() {
        let c = cal.circle;
        return Err(ApiError::invalid(format!(
            "ball_diameter needs two balls or more in the frame, but one ball was found (centre ({:.1}, {:.1}), radius {:.1} px): send a circle part cx,cy,r for each ball",
            c.cx, c.cy, c.r
        )));
    }
    if !form.matte.is_empty() {
        cal.fit_intensities(&files(&form.matte), &settings)?;
    }
    let uploads = (form.images.iter())
        .chain(&form.matte)
        .chain(&form.mask)
        .chain(&form.ambient);
    for s in uploads {
        std::fs::remove_file(dir.join(&s.file))?;
    }
    let table = cal.table();
    let positions = cal.positions_table(form.ball_diameter);
    let mut files = Vec::new();
    let made = [
        ("lights.csv", table.clone().into_bytes()),
        ("overlay.png", cal.overlay_png()),
        ("lights.png", cal.lights_png()),
    ];
    let with_positions = positions.map(|p| ("positions.csv", p.into_bytes()));
    for (name, bytes) in made.into_iter().chain(with_positions) {
        std::fs::write(dir.join(name), &bytes)?;
        files.push(ArtifactInfo {
            name: name.to_string(),
            bytes: bytes.len() as u64,
            etag: strong_etag(crc32fast::hash(&bytes), bytes.len() as u64),
            key: None,
        });
    }
    let measured = measured(&cal, &form, w, h, source);
    Ok(Made {
        measured,
        table,
        files,
    })
}
