//! The checks a submission's parts get before it is accepted, none of which decodes an
//! image: a file's format, dimensions and bit depth from its header, the options, the
//! camera, the light table's names against the images, a near-light job's rig.

use std::collections::HashMap;
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use image::ImageReader;
use serde::Deserialize;

use crate::core::camera::{self, Pinhole};
use crate::core::lights::Light;
use crate::core::near;
use crate::core::normalmap::{self, Convention, NormalMapError};
use crate::core::outputs;
use crate::core::{InputError, Options};
use crate::service::config::Config;
use crate::service::error::ApiError;
use crate::service::store::ManifestEntry;
use crate::service::worker::webhooks::{Target, parse_target};

/// Longest camera file accepted (`camera` part, or a camera file in an archive): a K.txt
/// or camera.json is a few dozen bytes.
pub(crate) const MAX_CAMERA_BYTES: usize = 4096;

/// An image (or a mask, a normal map) stored in the staging directory.
#[derive(Debug, Clone)]
pub(crate) struct StoredImage {
    /// The caller's name for it (what the light table says).
    pub(crate) name: String,
    /// The stored file's name.
    pub(crate) file: String,
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// Bits per sample (8, 16 or 32), as the core will decode it.
    pub(crate) depth: u8,
}

impl StoredImage {
    pub(crate) fn entry(&self) -> ManifestEntry {
        ManifestEntry {
            name: self.name.clone(),
            file: self.file.clone(),
        }
    }
}

/// Recognise the image format from its signature and read its dimensions and bit depth
/// from the header (no decoding), off the async runtime.
pub(crate) async fn probe(
    path: PathBuf,
    name: String,
    head: Vec<u8>,
    config: &Config,
) -> Result<(u32, u32, u8), ApiError> {
    let max_pixels = config.max_pixels;
    Ok(tokio::task::spawn_blocking(move || probe_image(&path, &name, &head, max_pixels)).await??)
}

pub(crate) fn probe_image(
    path: &Path,
    name: &str,
    head: &[u8],
    max_pixels: u64,
) -> Result<(u32, u32, u8), InputError> {
    let (w, h, colour) = read_header(path, name, head, max_pixels)?;
    // Bits per sample of what the decoder will produce (the core's bit depth).
    let depth = 8 * colour.bytes_per_pixel() / colour.channel_count().max(1);
    Ok((w, h, depth))
}

/// A normal map's dimensions and bits per sample (8, 16 or 32) from its header: a 422
/// naming the part's file when it is no normal map (unrecognised, gray), 413 over the
/// pixel limit.
pub(crate) async fn probe_normals(
    path: PathBuf,
    name: String,
    head: Vec<u8>,
    config: &Config,
) -> Result<(u32, u32, u8), ApiError> {
    let max_pixels = config.max_pixels;
    tokio::task::spawn_blocking(move || {
        let (w, h, colour) = read_header(&path, &name, &head, max_pixels).map_err(|e| {
            if e.is_too_large() || matches!(e, InputError::Io { .. }) {
                ApiError::from(e)
            } else {
                NormalMapError::unreadable(&name, e).into()
            }
        })?;
        Ok((w, h, normalmap::bits_of(&name, colour)?))
    })
    .await?
}

/// Recognise a picture from its first bytes `head` and read its dimensions and colour
/// type from the header; refused over `max_pixels`.
fn read_header(
    path: &Path,
    name: &str,
    head: &[u8],
    max_pixels: u64,
) -> Result<(u32, u32, image::ColorType), InputError> {
    use image::ImageDecoder;
    let format = image::guess_format(head).map_err(|_| InputError::UnsupportedFormat {
        name: name.into(),
        reason: "unrecognised file signature".into(),
    })?;
    let file = File::open(path).map_err(|e| InputError::io(path, e))?;
    let decoder = ImageReader::with_format(BufReader::new(file), format)
        .into_decoder()
        .map_err(|e| match e {
            image::ImageError::Unsupported(u) => InputError::UnsupportedFormat {
                name: name.into(),
                reason: u.to_string(),
            },
            other => InputError::Decode {
                name: name.into(),
                reason: other.to_string(),
            },
        })?;
    let (w, h) = decoder.dimensions();
    let colour = decoder.color_type();
    let pixels = u64::from(w) * u64::from(h);
    if pixels > max_pixels {
        return Err(InputError::TooLarge {
            name: name.into(),
            width: w.into(),
            height: h.into(),
            pixels,
            limit: max_pixels,
        });
    }
    Ok((w, h, colour))
}

/// Parse the `options` part; errors name the field at fault.
pub fn parse_options(bytes: &[u8]) -> Result<Options, ApiError> {
    // Straight from the bytes, as the worker reads them back: a `Value` would keep only
    // the last of repeated keys, where this refuses them. The `Value` is built only to
    // explain a refusal.
    let options =
        serde_json::from_slice::<Options>(bytes).map_err(|e| {
            match serde_json::from_slice::<serde_json::Value>(bytes) {
                Ok(value) => InputError::Options(explain_options_error(&value, e)),
                Err(e) => InputError::Options(format!("not valid JSON: {e}")),
            }
        })?;
    if let Some(names) = &options.outputs {
        outputs::check_selection(names)?;
    }
    options.check_values()?;
    Ok(options)
}

/// serde's message, prefixed with the top-level field that fails on its own.
fn explain_options_error(value: &serde_json::Value, err: serde_json::Error) -> String {
    let message = err.to_string();
    if let serde_json::Value::Object(fields) = value {
        for (key, v) in fields {
            let single =
                serde_json::Value::Object(std::iter::once((key.clone(), v.clone())).collect());
            if let Err(e) = Options::deserialize(&single) {
                let e = e.to_string();
                return if e.contains(&format!("`{key}`")) {
                    e
                } else {
                    format!("field `{key}`: {e}")
                };
            }
        }
    }
    message
}

/// The `convention` part: `opengl` (aliases `project`, `benchmark`) or `directx`.
pub(crate) fn parse_convention(bytes: &[u8]) -> Result<Convention, ApiError> {
    let text = String::from_utf8_lossy(bytes).trim().to_string();
    serde_json::from_value(serde_json::Value::String(text.clone())).map_err(|_| {
        ApiError::invalid(format!(
            "convention: {text:?} is not a normal map convention; expected opengl (green up; aliases project, benchmark) or directx (green down)"
        ))
    })
}

/// A camera file's bytes (`what` names it in a refusal): 422 naming the problem.
pub(crate) fn parse_camera(bytes: &[u8], what: &str) -> Result<Pinhole, ApiError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| ApiError::invalid(format!("camera: {what} is not UTF-8 text")))?;
    let named = |camera::CameraError(e)| camera::CameraError(format!("{what}: {e}"));
    let camera = Pinhole::parse(text).and_then(|k| k.check_values().map(|()| k));
    Ok(camera.map_err(|e| InputError::from(named(e)))?)
}

/// An archive's own camera file is the camera unless one was sent (`camera` part or
/// option): the note for `result.json` says which.
pub(crate) fn choose_camera(
    options: &mut Options,
    part: bool,
    name: &str,
    camera: Pinhole,
) -> String {
    if part || options.camera.is_some() {
        return format!("{name} in the archive not used: a camera was sent");
    }
    options.camera = Some(camera);
    format!("camera from {name} in the archive")
}

/// The `camera` part becomes the `camera` option; a 422 when both were sent.
pub(crate) fn take_camera_part(
    options: &mut Options,
    part: Option<Pinhole>,
) -> Result<(), ApiError> {
    if let Some(camera) = part {
        if options.camera.is_some() {
            return Err(ApiError::invalid(
                "send the camera either as the camera part or as the `camera` option, not both",
            ));
        }
        options.camera = Some(camera);
    }
    Ok(())
}

/// Pair the table's rows with the uploaded images, in table order.
pub(crate) fn check_names<'a>(
    lights: &[Light],
    images: &'a [StoredImage],
    config: &Config,
) -> Result<Vec<&'a StoredImage>, ApiError> {
    if lights.len() > config.max_images {
        return Err(InputError::TooManyImages {
            count: lights.len(),
            limit: config.max_images,
        }
        .into());
    }
    let mut by_name: HashMap<&str, (usize, &StoredImage)> = HashMap::new();
    for (i, img) in images.iter().enumerate() {
        if let Some((first, _)) = by_name.insert(img.name.as_str(), (i, img)) {
            return Err(ApiError::invalid(format!(
                "image {:?} was sent twice (image parts {} and {})",
                img.name,
                first + 1,
                i + 1
            )));
        }
    }
    let mut ordered = Vec::with_capacity(lights.len());
    for l in lights {
        match by_name.remove(l.name.as_str()) {
            Some((_, img)) => ordered.push(img),
            None => {
                return Err(InputError::MissingImage {
                    name: l.name.clone(),
                }
                .into());
            }
        }
    }
    if let Some(img) = images
        .iter()
        .find(|i| by_name.contains_key(i.name.as_str()))
    {
        return Err(InputError::UnlistedImage {
            name: img.name.clone(),
        }
        .into());
    }
    Ok(ordered)
}

pub(crate) fn check_sizes(ordered: &[&StoredImage]) -> Result<(), ApiError> {
    let first = ordered[0];
    for img in &ordered[1..] {
        if (img.width, img.height) != (first.width, first.height) {
            return Err(InputError::SizeMismatch {
                name: img.name.clone(),
                width: img.width,
                height: img.height,
                first: first.name.clone(),
                expected_width: first.width,
                expected_height: first.height,
            }
            .into());
        }
        if img.depth != first.depth {
            return Err(InputError::BitDepthMismatch {
                name: img.name.clone(),
                depth: img.depth,
                first: first.name.clone(),
                expected: first.depth,
            }
            .into());
        }
    }
    Ok(())
}

/// Every light of the calibration has its image and every image its light, else a 422
/// listing the names that do not match.
pub(crate) fn check_calibration_names(
    id: &str,
    lights: &[Light],
    images: &[StoredImage],
) -> Result<(), ApiError> {
    let sent: std::collections::HashSet<&str> = images.iter().map(|i| i.name.as_str()).collect();
    let named: std::collections::HashSet<&str> = lights.iter().map(|l| l.name.as_str()).collect();
    let missing: Vec<&str> = (lights.iter().map(|l| l.name.as_str()))
        .filter(|n| !sent.contains(n))
        .collect();
    let unmatched: Vec<&str> = (images.iter().map(|i| i.name.as_str()))
        .filter(|n| !named.contains(n))
        .collect();
    let mut problems = Vec::new();
    if !missing.is_empty() {
        problems.push(format!("no image for its lights {}", missing.join(", ")));
    }
    if !unmatched.is_empty() {
        problems.push(format!(
            "no light in it for the images {}",
            unmatched.join(", ")
        ));
    }
    if problems.is_empty() {
        return Ok(());
    }
    Err(ApiError::invalid(format!(
        "the images do not match the lights of calibration {id} (matched by name): {}",
        problems.join("; ")
    )))
}

/// A near-light job's options name only the fields it takes ([`near::OPTIONS`]) and its
/// `outputs` only what it writes ([`near::check_outputs`]): a 422 naming the first that
/// does not apply.
pub(crate) fn check_near_options(fields: &[String], options: &Options) -> Result<(), ApiError> {
    if let Some(field) = fields.iter().find(|f| !near::OPTIONS.contains(&f.as_str())) {
        return Err(InputError::Options(format!(
            "field `{field}` does not apply to a near-light job, which takes {}",
            near::OPTIONS.join(", ")
        ))
        .into());
    }
    if let Some(names) = &options.outputs {
        near::check_outputs(names)?;
    }
    Ok(())
}

/// Check a `callback_url` against the allow-list (422 naming the problem).
pub(crate) fn check_url(url: &str, allow: &[String]) -> Result<Target, ApiError> {
    parse_target(url, allow).map_err(ApiError::invalid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    use crate::service::intake::form::HEAD_BYTES;

    fn png(w: u32, h: u32) -> Vec<u8> {
        let img = image::GrayImage::from_pixel(w, h, image::Luma([128]));
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    }

    #[test]
    fn probe_reads_dimensions_and_refuses_junk() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x");
        let p = png(5, 3);
        std::fs::write(&path, &p).unwrap();
        assert_eq!(
            probe_image(&path, "x.png", &p[..HEAD_BYTES], 100).unwrap(),
            (5, 3, 8)
        );
        let e = probe_image(&path, "x.png", &p[..HEAD_BYTES], 10).unwrap_err();
        assert!(e.is_too_large());
        std::fs::write(&path, b"GIF89a\x01\x00\x01\x00\x00\x00\x00;").unwrap();
        let e =
            probe_image(&path, "x.gif", b"GIF89a\x01\x00\x01\x00\x00\x00\x00;", 100).unwrap_err();
        assert!(e.is_unsupported_media(), "{e}");
        let e = probe_image(&path, "x.txt", b"hello", 100).unwrap_err();
        assert!(e.is_unsupported_media(), "{e}");
    }

    #[test]
    fn options_errors_name_the_field() {
        let e = parse_options(br#"{"solver": "magic"}"#).unwrap_err();
        assert_eq!(e.status().as_u16(), 422);
        assert!(e.detail().contains("magic"), "{e}");
        let e = parse_options(br#"{"outputs": ["albedo.png", "selfie.jpg"]}"#).unwrap_err();
        assert!(e.detail().contains("selfie.jpg"), "{e}");
        let e = parse_options(br#"{"colour": 1}"#).unwrap_err();
        assert!(e.detail().contains("colour"), "{e}");
        assert!(parse_options(br#"{"integration": "path"}"#).is_ok());
        for (bad, needle) in [
            (r#"{"mesh": {"height_scale": 1e39}}"#, "height_scale"),
            (r#"{"mesh": {"pixel_size": 0}}"#, "pixel_size"),
            (r#"{"mesh": {"pixel_size": -1}}"#, "pixel_size"),
            (r#"{"shading_light": [0, 0, 0]}"#, "shading_light"),
            (r#"{"shading_light": [1e300, 1e300, 1]}"#, "shading_light"),
            // Repeated keys are refused, not resolved to the last one (found by fuzzing).
            (
                r#"{"mask": "none", "mask": "given"}"#,
                "duplicate field `mask`",
            ),
            (
                r#"{"mesh": {"step": 2, "step": 3}}"#,
                "duplicate field `step`",
            ),
            (r#"{"camera": "1 2 3"}"#, "field `camera`"),
            (r#"{"camera": [80, 80, 1, 1]}"#, "field `camera`"),
            (
                r#"{"camera": {"fx": 0.5, "fy": 80, "cx": 1, "cy": 1}}"#,
                "field `camera`: fx must be a focal length",
            ),
        ] {
            let e = parse_options(bad.as_bytes()).unwrap_err();
            assert_eq!(e.status().as_u16(), 422, "{bad}");
            assert!(e.detail().contains(needle), "{bad}: {e}");
        }
    }

    #[test]
    fn ports_outside_1_to_65535_are_refused() {
        let allow = vec!["127.0.0.1".to_string()];
        for bad in ["99999", "65616", "0", "65536", "-1", "80a"] {
            let url = format!("http://127.0.0.1:{bad}/hook");
            if let Err(e) = check_url(&url, &allow) {
                assert_eq!(e.status(), 422, "{url}");
            } else {
                panic!("{url} accepted");
            }
        }
        assert_eq!(
            check_url("http://127.0.0.1:65535/", &allow).unwrap().port,
            65535
        );
        assert_eq!(check_url("http://127.0.0.1:1/", &allow).unwrap().port, 1);
    }

    #[test]
    fn only_allow_listed_http_hosts_pass() {
        let allow = vec!["127.0.0.1".to_string(), "hooks.example.com".to_string()];
        let t = check_url("http://127.0.0.1:9000/hook?x=1", &allow).unwrap();
        assert_eq!(
            (t.host.as_str(), t.port, t.path.as_str()),
            ("127.0.0.1", 9000, "/hook?x=1")
        );
        assert_eq!(
            check_url("http://HOOKS.example.com", &allow).unwrap().port,
            80
        );
        for (url, needle) in [
            ("http://10.0.0.1/x", "allow-list"),
            ("http://127.0.0.2/x", "allow-list"),
            ("http://localhost/x", "allow-list"),
            ("https://127.0.0.1/x", "scheme"),
            ("ftp://127.0.0.1/x", "scheme"),
            ("/relative", "absolute"),
            ("http://user@127.0.0.1/x", "user information"),
            ("not a url", "not a URL"),
        ] {
            let e = check_url(url, &allow).unwrap_err();
            assert_eq!(e.status().as_u16(), 422, "{url}");
            assert!(e.detail().contains(needle), "{url}: {}", e.detail());
        }
        assert!(
            check_url("http://127.0.0.1/x", &[]).is_err(),
            "none by default"
        );
    }
}
