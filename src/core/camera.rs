//! The pinhole camera `{fx, fy, cx, cy}` (pixels) and where it comes from: a `K.txt`
//! (3 × 3, as the field ships it), a `camera.json`, or `fx,fy,cx,cy` text.
//!
//! Frame (docs: the project's conventions): the camera sits at the origin, pixel `(u, v)`
//! (0-based, centres at integers) sees the ray `((u − cx)/fx, (v − cy)/fy, −1)`, and a
//! point at depth `D` (along the optical axis, positive) is `D` times that ray.

use std::ops::RangeInclusive;
use std::path::Path;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// Focal lengths accepted, in pixels: below 1 px nothing is a camera; past 1e7 px a lens
/// is orthographic to within f32 and the perspective maths loses its precision.
pub const FOCAL_PX: RangeInclusive<f64> = 1.0..=1e7;

/// A pinhole camera in pixels. Deserialising does not check it: call [`Pinhole::check`]
/// against the image it belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Pinhole {
    /// Focal length along image columns, pixels.
    pub fx: f64,
    /// Focal length along image rows, pixels.
    pub fy: f64,
    /// Principal point's column (0-based; pixel centres at integers).
    pub cx: f64,
    /// Principal point's row.
    pub cy: f64,
}

/// Why a camera cannot be used; the text names the value at fault.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("camera: {0}")]
pub struct CameraError(pub String);

fn bad<T>(why: impl Into<String>) -> Result<T, CameraError> {
    Err(CameraError(why.into()))
}

impl Pinhole {
    /// `--focal-length f`: square pixels, the principal point at the image's centre.
    pub fn centred(focal_px: f64, width: usize, height: usize) -> Self {
        Self {
            fx: focal_px,
            fy: focal_px,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
        }
    }

    /// A camera from text: a 3 × 3 `K` (nine numbers, whitespace or comma separated, the
    /// last row `0 0 1`), a JSON object `{fx, fy, cx, cy}`, or the four numbers
    /// `fx,fy,cx,cy`.
    pub fn parse(text: &str) -> Result<Self, CameraError> {
        let text = text.trim();
        if text.starts_with('{') {
            return serde_json::from_str(text).or_else(|e| {
                bad(format!(
                    "not a JSON object {{\"fx\", \"fy\", \"cx\", \"cy\"}} in pixels: {e}"
                ))
            });
        }
        let numbers: Vec<f64> = text
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .map(|t| {
                t.parse::<f64>()
                    .or_else(|_| bad(format!("{t:?} is not a number")))
            })
            .collect::<Result<_, _>>()?;
        match numbers[..] {
            [fx, fy, cx, cy] => Ok(Self { fx, fy, cx, cy }),
            [fx, skew, cx, k10, fy, cy, k20, k21, k22] => {
                if skew != 0.0 {
                    return bad(format!(
                        "K has a skew of {skew}; only zero skew is supported"
                    ));
                }
                if k10 != 0.0 || k20 != 0.0 || k21 != 0.0 || k22 != 1.0 {
                    return bad(format!(
                        "K's last two rows must be `0 fy cy` and `0 0 1`, got `{k10} {fy} {cy}` and `{k20} {k21} {k22}`"
                    ));
                }
                Ok(Self { fx, fy, cx, cy })
            }
            _ => bad(format!(
                "expected fx,fy,cx,cy (4 numbers) or a 3 × 3 K (9 numbers), got {} numbers",
                numbers.len()
            )),
        }
    }

    /// A camera file: `K.txt` (or any text form [`Pinhole::parse`] reads) or `camera.json`.
    pub fn read(path: &Path) -> Result<Self, CameraError> {
        let text = std::fs::read_to_string(path)
            .or_else(|e| bad(format!("cannot read {}: {e}", path.display())))?;
        Self::parse(&text).map_err(|CameraError(e)| CameraError(format!("{}: {e}", path.display())))
    }

    /// The camera file a folder carries, if any: `camera.json`, else `K.txt`.
    pub fn in_folder(dir: &Path) -> Result<Option<Self>, CameraError> {
        for name in ["camera.json", "K.txt"] {
            let path = dir.join(name);
            if path.is_file() {
                return Self::read(&path).map(Some);
            }
        }
        Ok(None)
    }

    /// Refuses a camera that cannot have taken a `width × height` image: focal lengths
    /// outside [`FOCAL_PX`], a principal point that is not finite or lies outside the image.
    pub fn check(&self, width: usize, height: usize) -> Result<(), CameraError> {
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !FOCAL_PX.contains(&f) {
                return bad(format!(
                    "{name} must be a focal length of {} to {:e} pixels, got {f}",
                    FOCAL_PX.start(),
                    FOCAL_PX.end()
                ));
            }
        }
        let inside = |v: f64, n: usize| v.is_finite() && (-0.5..=n as f64 - 0.5).contains(&v);
        if !inside(self.cx, width) || !inside(self.cy, height) {
            return bad(format!(
                "the principal point ({}, {}) lies outside the {width} × {height} image; \
                 is K for this image (or for another resolution)?",
                self.cx, self.cy
            ));
        }
        Ok(())
    }

    /// The ray through pixel `(u, v)`, with z component −1 (not unit length).
    #[inline(always)]
    pub fn ray(&self, u: f64, v: f64) -> [f64; 3] {
        [(u - self.cx) / self.fx, (v - self.cy) / self.fy, -1.0]
    }

    /// The camera-frame point at depth `depth` on the ray through pixel `(u, v)`.
    #[inline(always)]
    pub fn unproject(&self, u: f64, v: f64, depth: f64) -> [f64; 3] {
        self.ray(u, v).map(|c| c * depth)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_fields_k_txt_json_and_four_numbers_alike() {
        let k = "3.772e+03 0.0 3.05875e+02\n0.0 3.759e+03 2.55125e+02\n0 0 1\n";
        let want = Pinhole {
            fx: 3772.0,
            fy: 3759.0,
            cx: 305.875,
            cy: 255.125,
        };
        assert_eq!(Pinhole::parse(k), Ok(want));
        assert_eq!(Pinhole::parse("3772, 3759, 305.875, 255.125"), Ok(want));
        let json = r#"{"fx": 3772, "fy": 3759, "cx": 305.875, "cy": 255.125}"#;
        assert_eq!(Pinhole::parse(json), Ok(want));
        assert!(want.check(612, 512).is_ok());
    }

    #[test]
    fn refuses_what_no_camera_is_and_says_why() {
        let err = |t: &str| Pinhole::parse(t).unwrap_err().0;
        assert!(err("1 2 3").contains("got 3 numbers"), "{}", err("1 2 3"));
        assert!(err("1 0.5 3 0 1 2 0 0 1").contains("skew"));
        assert!(err("1 0 3 0 1 2 0 0 2").contains("last two rows"));
        assert!(err("fx=1").contains("not a number"));
        assert!(err(r#"{"fx": 1, "fy": 1, "cx": 1}"#).contains("JSON"));
        let cam = Pinhole::centred(1000.0, 100, 80);
        assert_eq!((cam.cx, cam.cy), (49.5, 39.5));
        let off = Pinhole { cx: 700.0, ..cam };
        assert!(off.check(612, 512).unwrap_err().0.contains("outside"));
        let zero = Pinhole { fx: 0.0, ..cam };
        assert!(zero.check(100, 80).unwrap_err().0.contains("fx"));
        let nan = Pinhole {
            cy: f64::NAN,
            ..cam
        };
        assert!(nan.check(100, 80).is_err());
    }

    #[test]
    fn a_point_unprojected_at_its_depth_lies_on_its_ray() {
        let cam = Pinhole {
            fx: 500.0,
            fy: 400.0,
            cx: 10.0,
            cy: 20.0,
        };
        let x = cam.unproject(60.0, 60.0, 2.0);
        assert_eq!(x, [0.2, 0.2, -2.0]);
    }
}
