//! Flags and value parsers more than one subcommand takes: the camera, the pixel limit,
//! kebab-case enums, `x,y,z` vectors and circles.

use std::path::Path;

use anyhow::Context;
use clap::Args;
use photostereo::core::intake::Limits;
use photostereo::core::normalmap::Lens;
use serde::de::DeserializeOwned;

/// A pinhole camera, making the surface depth along the optical axis (depth.png,
/// depth.exr, points.ply; the mesh unprojected through it).
#[derive(Args)]
pub(crate) struct CameraArgs {
    /// A pinhole camera: a K.txt (3 × 3) or camera.json file, or fx,fy,cx,cy in pixels.
    /// Without it or --focal-length, `reconstruct` uses the folder's own camera.json or
    /// K.txt, `integrate` no camera (a file beside the map is only noted); without any,
    /// orthographic heights in pixels.
    #[arg(long)]
    pub(crate) camera: Option<String>,
    /// A pinhole camera with this focal length in pixels and its principal point at the
    /// image centre.
    #[arg(long, conflicts_with = "camera")]
    pub(crate) focal_length: Option<f64>,
    /// With a camera: the working distance, the median depth over the mask (metric depth
    /// in its unit); without it depth is relative, median 1.
    #[arg(long, allow_hyphen_values = true)]
    pub(crate) distance: Option<f64>,
}

/// How large a picture is read: as the server's `--max-pixels`, which bounds each image
/// or normal map of a job.
#[derive(Args)]
pub(crate) struct PixelLimit {
    /// Most pixels (width × height) in one image or normal map: larger files are refused
    /// before they are decoded.
    #[arg(long, default_value_t = Limits::default().max_pixels_per_image)]
    pub(crate) max_pixels: u64,
}

impl PixelLimit {
    pub(crate) fn limits(&self) -> Limits {
        Limits {
            max_pixels_per_image: self.max_pixels,
            ..Limits::default()
        }
    }
}

impl CameraArgs {
    /// Where `--camera` / `--focal-length` say the camera comes from, if they are given.
    pub(crate) fn lens(&self) -> anyhow::Result<Option<Lens>> {
        use photostereo::core::camera::Pinhole;
        Ok(match (self.camera.as_deref(), self.focal_length) {
            // A file when one is there, else the four numbers.
            (Some(c), _) if Path::new(c).is_file() => {
                Some(Lens::Pinhole(Pinhole::read(Path::new(c))?))
            }
            (Some(c), _) => Some(Lens::Pinhole(Pinhole::parse(c).with_context(|| {
                format!("--camera {c:?} is neither a file nor fx,fy,cx,cy")
            })?)),
            (None, Some(f)) => Some(Lens::Centred { focal_px: f }),
            (None, None) => None,
        })
    }
}

/// Parse a flag value by the same kebab-case names the JSON options use.
pub(crate) fn kebab<T: DeserializeOwned>(s: &str) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string())).map_err(|e| e.to_string())
}

/// `x,y,z`: three numbers separated by commas.
pub(crate) fn xyz(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts[..] else {
        return Err(format!("expected x,y,z (three numbers), got {s:?}"));
    };
    let num = |v: &str| v.parse::<f64>().map_err(|e| format!("{v:?}: {e}"));
    Ok([num(x)?, num(y)?, num(z)?])
}

/// `cx,cy,r`: a circle in pixels.
pub(crate) fn circle_arg(s: &str) -> Result<[f64; 3], String> {
    xyz(s).map_err(|_| format!("expected cx,cy,r (three numbers, pixels), got {s:?}"))
}
