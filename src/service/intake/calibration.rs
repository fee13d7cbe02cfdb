//! The calibration's multipart form, read into its staging directory and checked as it
//! streams: the images (one per light) and matte images, the mask or ambient image, the
//! circles, names, ball diameter, focal length and `skip_bad`.

use std::path::Path;

use axum::extract::Multipart;

use super::checks::probe;
use super::form::PartReader;
use super::tap::BodyTap;
use crate::core::calibrate::{self, Circle};
use crate::core::error::InputError;
use crate::core::lights;
use crate::service::config::{Config, MAX_LIGHTS_BYTES};
use crate::service::error::ApiError;
use crate::service::tenancy::idempotency::PartHasher;

/// Longest `circle`, `ball_diameter`, `focal_length` or `skip_bad` part accepted (bytes).
const MAX_VALUE_BYTES: usize = 256;

/// Most `circle` parts (balls in the frame): every ball is a window of every image read,
/// so the count is bounded like the images are.
pub const MAX_CIRCLES: usize = 16;

/// A stored upload image: the caller's file name, the stored file, its size.
pub(crate) struct Stored {
    pub(crate) name: String,
    pub(crate) file: String,
    pub(crate) width: u32,
    pub(crate) height: u32,
}

/// A received calibration form, its images on disk.
#[derive(Default)]
pub(crate) struct Form {
    pub(crate) images: Vec<Stored>,
    pub(crate) matte: Vec<Stored>,
    pub(crate) mask: Option<Stored>,
    pub(crate) ambient: Option<Stored>,
    /// One per ball, the first one first.
    pub(crate) circles: Vec<Circle>,
    pub(crate) ball_diameter: Option<f64>,
    pub(crate) names: Option<Vec<String>>,
    pub(crate) focal_length: Option<f64>,
    pub(crate) skip_bad: Option<bool>,
}

const PARTS: &str =
    "images, names, circle, ball_diameter, mask, ambient, matte, focal_length or skip_bad";

/// Read the multipart body into `dir`, checking what is cheap: the parts, each image's
/// format and dimensions (from its header) against the limits and the first image.
pub(crate) async fn receive(
    config: &Config,
    dir: &Path,
    multipart: &mut Multipart,
    tap: &BodyTap,
    hash: &mut PartHasher,
) -> Result<Form, ApiError> {
    let mut form = Form::default();
    let mut parts = PartReader::new(multipart, config, tap, hash, dir, PARTS);
    while let Some(mut part) = parts.next().await? {
        let name = part.name().to_string();
        match name.as_str() {
            "images" | "matte" => {
                let list = if name == "images" {
                    &form.images
                } else {
                    &form.matte
                };
                if list.len() >= config.max_images {
                    return Err(InputError::TooManyImages {
                        count: list.len() + 1,
                        limit: config.max_images,
                    }
                    .into());
                }
                let image = part.image_name()?;
                let file = format!("{name}{:03}.img", list.len());
                let (head, _) = part.store(&file, Some(&image)).await?;
                let (width, height, _) =
                    probe(part.path(&file), image.clone(), head, config).await?;
                let stored = Stored {
                    name: image,
                    file,
                    width,
                    height,
                };
                if name == "images" {
                    check_size(form.images.first(), &stored)?;
                    form.images.push(stored);
                } else {
                    form.matte.push(stored);
                }
            }
            "mask" | "ambient" => {
                let slot = if name == "mask" {
                    &mut form.mask
                } else {
                    &mut form.ambient
                };
                part.once(slot)?;
                let image = part.file_name_or_part();
                let file = format!("{name}.img");
                let (head, _) = part.store(&file, Some(&image)).await?;
                let (width, height, _) =
                    probe(part.path(&file), image.clone(), head, config).await?;
                *slot = Some(Stored {
                    name: image,
                    file,
                    width,
                    height,
                });
            }
            "names" => {
                part.once(&form.names)?;
                let text = part.text(MAX_LIGHTS_BYTES).await?;
                form.names = Some(parse_names(&text)?);
            }
            "circle" => {
                if form.circles.len() >= MAX_CIRCLES {
                    return Err(ApiError::invalid(format!(
                        "circle: at most {MAX_CIRCLES} circle parts (one per ball) are accepted"
                    )));
                }
                let text = part.text(MAX_VALUE_BYTES).await?;
                form.circles.push(parse_circle(&text)?);
            }
            "ball_diameter" => {
                part.once(&form.ball_diameter)?;
                let text = part.text(MAX_VALUE_BYTES).await?;
                form.ball_diameter = Some(parse_ball_diameter(&text)?);
            }
            "focal_length" => {
                part.once(&form.focal_length)?;
                let text = part.text(MAX_VALUE_BYTES).await?;
                form.focal_length = Some(parse_focal_length(&text)?);
            }
            "skip_bad" => {
                part.once(&form.skip_bad)?;
                let text = part.text(MAX_VALUE_BYTES).await?;
                form.skip_bad = Some(parse_flag(&text)?);
            }
            _ => return Err(part.unknown()),
        }
    }
    if form.images.is_empty() {
        return Err(ApiError::bad_request(
            "no images parts: send each chrome-sphere image as a file part named images (curl -F images=@ball01.png)",
        ));
    }
    if !form.circles.is_empty() && form.mask.is_some() {
        return Err(ApiError::invalid(
            "give the sphere either as a circle or as a mask, not both",
        ));
    }
    // As the CLI's --positions: positions need the rays of two balls at least, given or
    // found (then checked once the calibration has found them).
    if form.ball_diameter.is_some() && (form.circles.len() == 1 || form.mask.is_some()) {
        return Err(ApiError::invalid(
            "ball_diameter needs two balls or more in the frame: send a circle part cx,cy,r for each, or none to have them found",
        ));
    }
    Ok(form)
}

/// Images of a calibration have one size (the core checks it too, after decoding: this
/// answers before the rest of the body is read).
fn check_size(first: Option<&Stored>, img: &Stored) -> Result<(), ApiError> {
    match first {
        Some(f) if (f.width, f.height) != (img.width, img.height) => {
            Err(InputError::SizeMismatch {
                name: img.name.clone(),
                width: img.width,
                height: img.height,
                first: f.name.clone(),
                expected_width: f.width,
                expected_height: f.height,
            }
            .into())
        }
        _ => Ok(()),
    }
}

/// One light name per line (blank lines skipped), each one a light table can hold.
fn parse_names(text: &str) -> Result<Vec<String>, ApiError> {
    text.lines()
        .map(str::trim)
        .enumerate()
        .filter(|(_, l)| !l.is_empty())
        .map(|(i, l)| {
            lights::check_name(l)
                .map(|()| l.to_string())
                .map_err(|why| ApiError::invalid(format!("names, line {}: {why}", i + 1)))
        })
        .collect()
}

/// `cx,cy,r`: three finite numbers, pixels.
fn parse_circle(text: &str) -> Result<Circle, ApiError> {
    let bad = || {
        ApiError::invalid(format!(
            "circle: expected cx,cy,r (three finite numbers, pixels), got {:?}",
            text.trim()
        ))
    };
    let v: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad())?;
    match v[..] {
        [cx, cy, r] if v.iter().all(|x| x.is_finite()) => Ok(Circle { cx, cy, r }),
        _ => Err(bad()),
    }
}

/// The balls' diameter: a positive finite number, in the unit the positions should be in.
fn parse_ball_diameter(text: &str) -> Result<f64, ApiError> {
    match text.trim().parse::<f64>() {
        Ok(d) if d.is_finite() && d > 0.0 => Ok(d),
        _ => Err(ApiError::invalid(format!(
            "ball_diameter must be a positive number (the balls' diameter, in the unit the positions should be in), got {:?}",
            text.trim()
        ))),
    }
}

fn parse_focal_length(text: &str) -> Result<f64, ApiError> {
    match text.trim().parse::<f64>() {
        Ok(f) if calibrate::FOCAL_PX.contains(&f) => Ok(f),
        _ => Err(ApiError::invalid(format!(
            "focal_length must be a number of pixels from {} to {:e} (leave it out for a long lens far away), got {:?}",
            calibrate::FOCAL_PX.start(),
            calibrate::FOCAL_PX.end(),
            text.trim()
        ))),
    }
}

fn parse_flag(text: &str) -> Result<bool, ApiError> {
    match text.trim() {
        "true" | "1" | "yes" => Ok(true),
        "false" | "0" | "no" => Ok(false),
        other => Err(ApiError::invalid(format!(
            "skip_bad must be true or false, got {other:?}"
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_values_are_checked() {
        let c = parse_circle(" 1.5, 2 ,30 ").unwrap();
        assert_eq!((c.cx, c.cy, c.r), (1.5, 2.0, 30.0));
        for bad in ["1,2", "1,2,3,4", "a,b,c", "1,2,inf", ""] {
            assert_eq!(parse_circle(bad).unwrap_err().status(), 422, "{bad}");
        }
        assert_eq!(parse_focal_length("2400").unwrap(), 2400.0);
        for bad in ["0", "-1", "NaN", "x", "inf", "1e10", "0.5"] {
            assert!(parse_focal_length(bad).is_err(), "{bad}");
        }
        assert!(parse_flag("true").unwrap());
        assert!(!parse_flag(" 0 ").unwrap());
        assert!(parse_flag("maybe").is_err());
        assert_eq!(parse_ball_diameter(" 25.4 ").unwrap(), 25.4);
        for bad in ["0", "-1", "NaN", "inf", "1e400", "x", ""] {
            let e = parse_ball_diameter(bad).unwrap_err();
            assert_eq!(e.status(), 422, "{bad}");
        }
    }
}
