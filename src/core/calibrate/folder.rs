//! A sphere folder read from disk: its images in name order, the ambient image, the light
//! names (from a light table or `names.txt`), and a sphere mask. The calibration's only
//! file I/O.

use std::path::Path;

use super::error::CalibrationError;
use super::model::CircleSource;
use super::source::{ImageFiles, Source};
use crate::core::error::InputError;
use crate::core::intake::{self, Limits};
use crate::core::layout;

/// Files that name the lights of a sphere folder: the seed's table (only its names are
/// read) or a plain list.
pub const NAMES_FILE: &str = "names.txt";

/// A sphere folder as found: the sphere images (one per light, in name order, read when
/// the calibration reads them), the light names, and the ambient image (the ball with the
/// rig's lights off), if any.
#[derive(Debug, Clone)]
pub struct SphereFolder {
    pub images: ImageFiles,
    pub names: Option<Vec<String>>,
    pub ambient: Option<ImageFiles>,
}

impl SphereFolder {
    /// The ambient image as [`calibrate`](super::calibrate) takes it.
    pub fn ambient_source(&self) -> Option<&dyn Source> {
        self.ambient.as_ref().map(|a| a as &dyn Source)
    }
}

/// Whether an image file is the ambient image: its stem is `ambient` or `ref`
/// (any case), as light-dome software names it.
pub fn is_ambient(name: &str) -> bool {
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    stem.eq_ignore_ascii_case("ambient") || stem.eq_ignore_ascii_case("ref")
}

/// Read a sphere folder: every image file in it, in name order, but the ambient image
/// (`ambient.*` or `ref.*`), and the light names from its `light_directions.csv` /
/// `.json` or `names.txt` (one per image, same order), if any.
pub fn load_dir(dir: &Path) -> Result<SphereFolder, CalibrationError> {
    let mut files = Vec::new();
    let mut ambient_file = None;
    for entry in std::fs::read_dir(dir).map_err(|e| InputError::io(dir, e))? {
        let entry = entry.map_err(|e| InputError::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if entry.path().is_file() && layout::is_image(&name) {
            if is_ambient(&name) {
                if let Some(first) = ambient_file.replace(name.clone()) {
                    return Err(CalibrationError::Names(format!(
                        "{} holds two ambient images, {first} and {name}: keep one",
                        dir.display()
                    )));
                }
            } else {
                files.push(name);
            }
        }
    }
    files.sort();
    let images = image_files(dir, &files)?;
    let ambient = ambient_file.map(|a| ImageFiles::in_dir(dir, &[a], Limits::default()));
    let read = |name: &str| {
        let p = dir.join(name);
        std::fs::read(&p).map_err(|e| InputError::io(&p, e))
    };
    let names = if let Some(table) = [layout::SEED_CSV, layout::SEED_JSON]
        .into_iter()
        .find(|n| dir.join(n).is_file())
    {
        let lights = crate::core::lights::parse_bytes(&read(table)?)?;
        Some(lights.into_iter().map(|l| l.name).collect::<Vec<String>>())
    } else if dir.join(NAMES_FILE).is_file() {
        let text = String::from_utf8(read(NAMES_FILE)?)
            .map_err(|_| CalibrationError::Names(format!("{NAMES_FILE} is not UTF-8 text")))?;
        Some(
            text.lines()
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .map(String::from)
                .collect(),
        )
    } else {
        None
    };
    if let Some(n) = &names
        && n.len() != images.count()
    {
        return Err(CalibrationError::Names(format!(
            "{} in {} lists {} names but the folder has {} sphere images",
            if dir.join(NAMES_FILE).is_file() && !dir.join(layout::SEED_CSV).is_file() {
                NAMES_FILE
            } else {
                "the light table"
            },
            dir.display(),
            n.len(),
            images.count()
        )));
    }
    Ok(SphereFolder {
        images,
        names,
        ambient,
    })
}

fn image_files(dir: &Path, files: &[String]) -> Result<ImageFiles, CalibrationError> {
    let limits = Limits::default();
    if files.len() > limits.max_images {
        return Err(InputError::TooManyImages {
            count: files.len(),
            limit: limits.max_images,
        }
        .into());
    }
    Ok(ImageFiles::in_dir(dir, files, limits))
}

/// The images of a folder (every image file, in name order), e.g. a matte sphere's.
pub fn load_images(dir: &Path) -> Result<ImageFiles, CalibrationError> {
    load_dir(dir).map(|f| f.images)
}

/// Read a sphere mask (non-zero = sphere).
pub fn read_mask(path: &Path) -> Result<CircleSource, CalibrationError> {
    let name = path
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    let bytes = std::fs::read(path).map_err(|e| InputError::io(path, e))?;
    let plane = intake::to_luma16(intake::decode(&name, &bytes, &Limits::default())?);
    Ok(CircleSource::Mask {
        name,
        mask: plane.mapv(|v| v > 0),
    })
}
