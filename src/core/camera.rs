//! The pinhole camera `{fx, fy, cx, cy}` (pixels) and where it comes from: a `K.txt`
//! (3 × 3, as the field ships it), a `camera.json`, or `fx,fy,cx,cy` text.
//!
//! Frame (docs: the project's conventions): the camera sits at the origin, pixel `(u, v)`
//! (0-based, centres at integers) sees the ray `((u − cx)/fx, (v − cy)/fy, −1)`, and a
//! point at depth `D` (along the optical axis, positive) is `D` times that ray.

use std::ops::RangeInclusive;
use std::path::Path;

use serde::de::{self, MapAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize};
use utoipa::ToSchema;
use utoipa::openapi::schema::{ObjectBuilder, OneOfBuilder, Type};
use utoipa::openapi::{Ref, RefOr, Schema};

/// Focal lengths accepted, in pixels: below 1 px nothing is a camera; past 1e7 px a lens
/// is orthographic to within f32 and the perspective maths loses its precision.
pub const FOCAL_PX: RangeInclusive<f64> = 1.0..=1e7;

/// The camera files a folder (or an upload) may carry, in the order they are looked for.
pub const FILES: [&str; 2] = ["camera.json", "K.txt"];

/// A pinhole camera in pixels: pixel (u, v) sees the ray ((u − cx)/fx, (v − cy)/fy, −1)
/// from the camera at the origin (x right, y down, z towards the camera).
// Deserialising does not check it: `Pinhole::check` it against its image.
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
        Self::file_in(dir).map(|path| Self::read(&path)).transpose()
    }

    /// The camera file in `dir` that [`Pinhole::in_folder`] reads, if any.
    pub fn file_in(dir: &Path) -> Option<std::path::PathBuf> {
        FILES.iter().map(|n| dir.join(n)).find(|p| p.is_file())
    }

    /// Refuses what no image's camera can be: focal lengths outside [`FOCAL_PX`] (NaN
    /// included), a principal point that is not finite.
    pub fn check_values(&self) -> Result<(), CameraError> {
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !FOCAL_PX.contains(&f) {
                return bad(format!(
                    "{name} must be a focal length of {} to {:e} pixels, got {f}",
                    FOCAL_PX.start(),
                    FOCAL_PX.end()
                ));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return bad(format!("{name} must be a finite number of pixels, got {v}"));
            }
        }
        Ok(())
    }

    /// Refuses a camera that cannot have taken a `width × height` image: what
    /// [`Pinhole::check_values`] refuses, or a principal point outside the image.
    pub fn check(&self, width: usize, height: usize) -> Result<(), CameraError> {
        self.check_values()?;
        let inside = |v: f64, n: usize| (-0.5..=n as f64 - 0.5).contains(&v);
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

/// The `camera` option in either form: `{fx, fy, cx, cy}`, or text [`Pinhole::parse`]
/// reads (a K.txt's nine numbers, `fx,fy,cx,cy`); null for none. For
/// `#[serde(deserialize_with)]`; the values are checked by [`Pinhole::check_values`].
pub fn deserialize_option<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Pinhole>, D::Error> {
    d.deserialize_any(EitherForm)
}

struct EitherForm;

impl<'de> Visitor<'de> for EitherForm {
    type Value = Option<Pinhole>;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str(
            "a camera: {\"fx\", \"fy\", \"cx\", \"cy\"} in pixels, or the text of a K.txt (3 × 3) or fx,fy,cx,cy",
        )
    }

    fn visit_unit<E>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_none<E>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_some<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_any(self)
    }

    fn visit_str<E: de::Error>(self, text: &str) -> Result<Self::Value, E> {
        Pinhole::parse(text)
            .map(Some)
            .map_err(|CameraError(e)| E::custom(e))
    }

    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<Self::Value, A::Error> {
        Pinhole::deserialize(de::value::MapAccessDeserializer::new(map)).map(Some)
    }
}

/// The OpenAPI schema of the `camera` option's two forms.
pub fn option_schema() -> RefOr<Schema> {
    let text = ObjectBuilder::new()
        .schema_type(Type::String)
        .description(Some(
            "A K.txt's text (3 × 3, zero skew, last row 0 0 1) or `fx,fy,cx,cy`, in pixels",
        ));
    OneOfBuilder::new()
        .item(ObjectBuilder::new().schema_type(Type::Null))
        .item(Ref::from_schema_name("Pinhole"))
        .item(text)
        .description(Some(
            "A pinhole camera in pixels: `{fx, fy, cx, cy}`, or the text of a K.txt (3 × 3) or \
             `fx,fy,cx,cy`. With one, normals stay in the camera frame and the surface is depth \
             along the optical axis (depth.png, depth.exr, points.ply; the mesh unprojected \
             through it); without one, orthographic heights in pixels. An upload's K.txt or \
             camera.json (part `camera`, or a file in the archive) is used when this is absent.",
        ))
        .into()
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
    fn the_option_takes_an_object_or_text_and_refuses_anything_else() {
        #[derive(Deserialize, Debug)]
        struct Holder {
            #[serde(default, deserialize_with = "deserialize_option")]
            camera: Option<Pinhole>,
        }
        let read = |json: &str| serde_json::from_str::<Holder>(json).map(|h| h.camera);
        let want = Pinhole {
            fx: 80.0,
            fy: 90.0,
            cx: 31.5,
            cy: 20.0,
        };
        let object = r#"{"camera": {"fx": 80, "fy": 90, "cx": 31.5, "cy": 20}}"#;
        assert_eq!(read(object).unwrap(), Some(want));
        assert_eq!(read(r#"{"camera": "80,90,31.5,20"}"#).unwrap(), Some(want));
        let k = r#"{"camera": "80 0 31.5\n0 90 20\n0 0 1\n"}"#;
        assert_eq!(read(k).unwrap(), Some(want));
        assert_eq!(read(r#"{"camera": null}"#).unwrap(), None);
        assert_eq!(read("{}").unwrap(), None);
        for (bad, needle) in [
            (r#"{"camera": 7}"#, "fx,fy,cx,cy"),
            (r#"{"camera": "80,90"}"#, "got 2 numbers"),
            (
                r#"{"camera": {"fx": 80, "fy": 90, "cx": 1}}"#,
                "missing field `cy`",
            ),
            (r#"{"camera": {"fx": 1, "fx": 2}}"#, "duplicate field `fx`"),
            (
                r#"{"camera": {"fx": 80, "fy": 90, "cx": 1, "cy": 1, "k": 0}}"#,
                "unknown field",
            ),
        ] {
            let e = read(bad).unwrap_err().to_string();
            assert!(e.contains(needle), "{bad}: {e}");
        }
    }

    #[test]
    fn values_no_camera_has_are_refused_before_the_image_is_known() {
        let ok = Pinhole::centred(80.0, 64, 64);
        assert!(ok.check_values().is_ok());
        let e = |k: Pinhole| k.check_values().unwrap_err().0;
        assert!(e(Pinhole { fx: 1e8, ..ok }).contains("fx must be a focal length"));
        assert!(e(Pinhole { fy: f64::NAN, ..ok }).contains("fy"));
        assert!(
            e(Pinhole {
                cx: f64::INFINITY,
                ..ok
            })
            .contains("cx must be a finite")
        );
        // Far outside the image is still a camera, just not this image's.
        let far = Pinhole { cx: 500.0, ..ok };
        assert!(far.check_values().is_ok() && far.check(64, 64).is_err());
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
