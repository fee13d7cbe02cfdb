//! The pictures of a reconstruction: the maps they are drawn from, which of them apply,
//! and each encoded into memory or streamed to its file, in parallel.

use std::io::Cursor;
use std::path::Path;

use exr::prelude::{SpecificChannels, Vec2};
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;

use super::encoding::{
    binary_to, exr_image, exr_to, gl_normal, png_to, png16_to, range_png16_to, scalar_exr_to,
    shaded_to,
};
use super::names::GLOSSY_OUTPUTS;
use crate::core::commit::{Committer, WriteSeek};
use crate::core::error::RunError;
use crate::core::progress::Halt;
use crate::core::reconstruction::{Gloss, Reconstruction};
use crate::core::render;

/// The arrays the pictures are drawn from, borrowed from a [`Reconstruction`] or, while
/// the integration still runs, from the surface it starts from (then without heights).
pub struct Maps<'a> {
    pub albedo: &'a Array2<f32>,
    pub albedo_rgb: Option<&'a Array3<f32>>,
    pub normals: &'a Array3<f32>,
    pub mask: &'a Array2<bool>,
    /// None while the integration runs.
    pub curl: Option<&'a Array2<f32>>,
    pub confidence: &'a Array2<f32>,
    pub unreliable: &'a Array2<bool>,
    pub heights: Option<Heights<'a>>,
    /// The `glossy` solver's lobe maps.
    pub gloss: Option<&'a Gloss>,
}

/// Integrated heights (or depth, for the depth pictures) and their range over the mask.
pub struct Heights<'a> {
    pub z: &'a Array2<f32>,
    pub min: f32,
    pub max: f32,
}

impl<'a> Maps<'a> {
    pub fn of(rec: &'a Reconstruction) -> Self {
        Self {
            albedo: &rec.albedo,
            albedo_rgb: rec.albedo_rgb.as_ref(),
            normals: &rec.normals,
            mask: &rec.mask,
            curl: Some(&rec.curl),
            confidence: &rec.confidence,
            unreliable: &rec.unreliable,
            gloss: rec.gloss.as_ref(),
            heights: Some({
                let (min, max) = rec.report.surface_range();
                Heights {
                    z: &rec.heights,
                    min,
                    max,
                }
            }),
        }
    }

    fn heights(&self) -> &Heights<'a> {
        (self.heights.as_ref()).expect("height pictures are encoded after the integration")
    }

    fn curl(&self) -> &'a Array2<f32> {
        self.curl
            .expect("the curl picture is encoded after the integration")
    }
}

/// Whether artifact `name` applies to these maps (`albedo_rgb.png` needs colour, the
/// [`GLOSSY_OUTPUTS`] the `glossy` solver).
pub fn applies(maps: &Maps, name: &str) -> bool {
    match name {
        "albedo_rgb.png" => maps.albedo_rgb.is_some(),
        _ if GLOSSY_OUTPUTS.contains(&name) => maps.gloss.is_some(),
        _ => true,
    }
}

/// Encode one named artifact (mesh files excepted), or None if it does not apply.
pub fn encode(rec: &Reconstruction, name: &str, shading_light: [f64; 3]) -> Option<Vec<u8>> {
    let mut out = Cursor::new(Vec::new());
    match encode_to(&mut out, &Maps::of(rec), name, shading_light) {
        Ok(true) => Some(out.into_inner()),
        Ok(false) => None,
        Err(e) => panic!("encoding {name} into memory cannot fail: {e}"),
    }
}

/// Stream one named artifact (mesh files excepted) into `out`; false when `name` is not
/// a picture this module knows or does not apply.
pub fn encode_to(
    out: &mut dyn WriteSeek,
    maps: &Maps,
    name: &str,
    shading_light: [f64; 3],
) -> std::io::Result<bool> {
    let (rows, cols) = maps.mask.dim();
    let mask = maps.mask;
    let value = |_, v| v;
    let signed = |_, v: f32| (v + 1.0) * 0.5;
    let normal = |k| maps.normals.index_axis(Axis(2), k);
    match name {
        "albedo.png" => png16_to(out, mask, [maps.albedo.view()], value)?,
        "albedo_rgb.png" => {
            let Some(rgb) = maps.albedo_rgb else {
                return Ok(false);
            };
            let planes = [0, 1, 2].map(|k| rgb.index_axis(Axis(2), k));
            png16_to(out, mask, planes, value)?
        }
        "mask.png" => binary_to(out, mask)?,
        "unreliable.png" => binary_to(out, maps.unreliable)?,
        "confidence.png" => png16_to(out, mask, [maps.confidence.view()], value)?,
        "specular.png" | "roughness.png" => {
            let Some(gloss) = maps.gloss else {
                return Ok(false);
            };
            let map = match name {
                "specular.png" => &gloss.specular,
                _ => &gloss.roughness,
            };
            png16_to(out, mask, [map.view()], value)?
        }
        // The OpenGL normal-map frame: y up, so the seed frame's y is flipped.
        "normal.png" => png16_to(out, mask, [0, 1, 2].map(normal), |k, v| {
            signed(k, if k == 1 { -v } else { v })
        })?,
        "normal_x.png" => png16_to(out, mask, [normal(0)], signed)?,
        "normal_y.png" => png16_to(out, mask, [normal(1)], signed)?,
        "normal_z.png" => png16_to(out, mask, [normal(2)], signed)?,
        "height.png" => {
            let Heights { z, min, max } = maps.heights();
            range_png16_to(out, mask, z, *min..=*max, false)?
        }
        "normal.exr" => {
            let n = SpecificChannels::rgb(|p: Vec2<usize>| {
                let [x, y, z] = gl_normal(maps.normals, p.y(), p.x());
                (x, y, z)
            });
            exr_to(out, &exr_image((rows, cols), n))?
        }
        "height.exr" | "depth.exr" => scalar_exr_to(out, maps.heights().z)?,
        "depth.png" => {
            let Heights { z, min, max } = maps.heights();
            range_png16_to(out, mask, z, *min..=*max, true)?
        }
        "needle.png" => png_to(out, &render::needle_map(maps.albedo, maps.normals, mask))?,
        "curl.png" => png_to(out, &render::diverging(maps.curl(), mask))?,
        "shaded.png" => shaded_to(out, maps.albedo, maps.normals, mask, shading_light)?,
        _ => return Ok(false),
    }
    Ok(true)
}

/// Write the picture artifacts `names` in parallel; returns the names written (an
/// artifact that does not apply, such as `albedo_rgb.png` for gray inputs, is skipped, and
/// so is every picture not yet started once `halt` says stop).
pub fn write_pictures(
    maps: &Maps,
    names: &[&str],
    shading_light: [f64; 3],
    dir: &Path,
    commits: &Committer,
    halt: Halt,
) -> Result<Vec<String>, RunError> {
    let written: Vec<Option<String>> = names
        .par_iter()
        .map(|name| {
            if !applies(maps, name) || halt() {
                return Ok(None);
            }
            commits.write(dir, name, &mut |f| {
                encode_to(f, maps, name, shading_light).map(|_| ())
            })?;

            Ok(Some(name.to_string()))
        })
        .collect::<Result<_, RunError>>()?;
    Ok(written.into_iter().flatten().collect())
}
