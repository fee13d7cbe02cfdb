//! Reconstruction options: the one set the CLI flags and the HTTP `options` part both fill.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::camera::{self, Pinhole};
use super::error::InputError;

/// How albedo·normal is solved per pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Solver {
    /// The default. Least squares over the observations a Lambertian model explains:
    /// shadows, highlights and saturated values set aside per pixel, black level
    /// removed; pixels where that model cannot be trusted fall back to `l2` and are
    /// flagged.
    #[default]
    Robust,
    /// Plain least squares over every observation (the seed's "solution 2").
    L2,
    /// Least squares weighted by the intensities themselves, T = diag(i) (the seed's
    /// "solution 1"): down-weights dark observations but biases normals; less accurate.
    Weighted,
    /// `robust`, then, where a pixel shows highlights, a diffuse term and a microfacet
    /// lobe (GGX or Beckmann, whichever explains the pixel better) fitted with the normal:
    /// for glossy surfaces (glazes, varnish, metal), whose highlights then inform the
    /// normal; gives specular albedo and roughness maps.
    Glossy,
}

/// Which pixels are the object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema, Default)]
#[serde(rename_all = "kebab-case")]
pub enum MaskMode {
    /// Threshold the albedo at a level chosen from its histogram, then fill holes.
    #[default]
    Auto,
    /// Every pixel of non-zero albedo is object.
    None,
    /// The caller's mask image (non-zero = object); an error if none was supplied.
    Given,
}

/// How heights are integrated from the gradient field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Integration {
    /// The seed's path integration: down the first column, then along each row.
    Path,
    /// Frankot–Chellappa projection onto integrable surfaces, via FFT, on the full frame.
    FrankotChellappa,
    /// Least-squares (Poisson) integration over the mask only.
    Poisson,
    /// Poisson with each pixel's equations weighted by the solver's confidence: pixels
    /// with few usable observations (fallback normals) follow their neighbours instead of
    /// their own gradients, so they make no spikes.
    WeightedPoisson,
    /// `weighted-poisson`, then re-weighted a few times so that edges whose gradient
    /// disagrees with the surface by far more than is typical (depth steps, the wrong
    /// normals left) are let go: discontinuity-preserving. The default: the most accurate
    /// with the default solver (docs/benchmarks.md).
    #[default]
    RobustPoisson,
    /// Bilateral normal integration: each edge re-weighted from the surface so far by
    /// which side of each pixel the surface continues on; keeps depth steps sharp where
    /// the normals say the surface breaks, and is Poisson on smooth surfaces.
    Bilateral,
}

/// Where the lights' intensities come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Intensities {
    /// The light table's: a light without one has intensity 1, except a light given by
    /// position (an LED), whose unknown intensity is estimated as `estimate` does.
    #[default]
    Table,
    /// Every light's relative intensity (mean 1) estimated from the object itself
    /// (semi-calibrated photometric stereo), whatever the table says; reported in
    /// result.json and written back as `lights.json`, a table `reconstruct` reads. The
    /// object must show normals of several kinds: a plane cannot tell the lights apart,
    /// and is refused.
    Estimate,
}

/// How the mesh's vertex normals are made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema, Default)]
#[serde(rename_all = "kebab-case")]
pub enum MeshNormals {
    /// The photometric normals, sampled at each vertex.
    #[default]
    Photometric,
    /// Normals of the triangulated height map.
    Geometric,
}

/// glTF mesh settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MeshOptions {
    /// Upper bound on vertices; the grid step grows until the mesh fits.
    pub max_vertices: usize,
    /// Take every `step`-th pixel as a vertex (overrides the automatic step when larger).
    pub step: Option<usize>,
    /// Multiplies heights before they become z.
    pub height_scale: f32,
    /// Size of one pixel in metres; when absent, positions are in pixel units.
    pub pixel_size: Option<f64>,
    pub normals: MeshNormals,
}

impl Default for MeshOptions {
    fn default() -> Self {
        Self {
            max_vertices: 500_000,
            step: None,
            height_scale: 1.0,
            pixel_size: None,
            normals: MeshNormals::Photometric,
        }
    }
}

/// Everything a reconstruction can be asked to do differently.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Options {
    pub solver: Solver,
    pub mask: MaskMode,
    pub integration: Integration,
    /// Light direction for `shaded.png` (need not be unit length).
    pub shading_light: [f64; 3],
    pub mesh: MeshOptions,
    /// Largest light-matrix condition number accepted before refusing the set.
    pub max_condition: f64,
    /// Artifact names to write, `"all"` for every one; when absent, the default set:
    /// albedo.png, albedo_rgb.png (colour inputs), mask.png, normal.png, height.png,
    /// confidence.png, specular.png and roughness.png (the glossy solver), shaded.png,
    /// mesh.glb and result.json. A normals job writes only
    /// mask.png, normal.png, height.png and height.exr (under a camera depth.png and
    /// depth.exr), points.ply, mesh.glb and result.json: all of them when absent; naming
    /// another is refused.
    pub outputs: Option<Vec<String>>,
    /// The pinhole camera (see its schema); absent: orthographic.
    #[serde(
        deserialize_with = "camera::deserialize_option",
        skip_serializing_if = "Option::is_none"
    )]
    #[schema(schema_with = camera::option_schema)]
    pub camera: Option<Pinhole>,
    /// With a camera: the working distance, the median depth over the mask in the unit
    /// wanted (metric depth); absent: relative depth, median 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub distance: Option<f64>,
    pub intensities: Intensities,
    /// Also score the solver without ground truth: each quarter of the lights left out
    /// in turn, the rest solved, and the left-out images predicted (`holdout` in
    /// result.json: median relative error, each left-out light's intensity fitted). Four
    /// more solves; needs at least 8 images, lights given as directions.
    pub holdout_lights: bool,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            solver: Solver::default(),
            mask: MaskMode::default(),
            integration: Integration::default(),
            shading_light: [1.0, 2.0, 3.0],
            mesh: MeshOptions::default(),
            max_condition: DEFAULT_MAX_CONDITION,
            outputs: None,
            camera: None,
            distance: None,
            intensities: Intensities::default(),
            holdout_lights: false,
        }
    }
}

impl Options {
    /// Values JSON (or a flag) can carry but a reconstruction cannot use, refused before a
    /// job starts: a zero or non-finite shading light would shade with NaN, a
    /// `height_scale` past the f32 range would even be stored as `null`; a camera no image
    /// can have. (The camera against the images, and the distance, are checked once the
    /// set's own camera file is known: [`Options::check_camera`].)
    pub fn check_values(&self) -> Result<(), InputError> {
        let bad = |why: String| Err(InputError::Options(why));
        let l = self.shading_light;
        let norm = l.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return bad(format!(
                "field `shading_light` must be three finite numbers, not all zero (and not huge), got {l:?}"
            ));
        }
        if !self.mesh.height_scale.is_finite() {
            return bad("field `mesh`: height_scale must be a finite number within ±3.4e38".into());
        }
        if let Some(p) = self.mesh.pixel_size
            && !(p.is_finite() && p > 0.0)
        {
            return bad(format!(
                "field `mesh`: pixel_size must be a positive number of metres, got {p}"
            ));
        }
        if let Some(k) = &self.camera {
            k.check_values().map_err(|camera::CameraError(e)| {
                InputError::Options(format!("field `camera`: {e}"))
            })?;
        }
        Ok(())
    }

    /// The camera against the `width × height` images it is to have taken, and the
    /// distance ([`check_distance`]).
    pub fn check_camera(&self, width: usize, height: usize) -> Result<(), InputError> {
        if let Some(k) = &self.camera {
            k.check(width, height)?;
        }
        check_distance(self.distance, self.camera.as_ref())
    }
}

/// Refuses a working distance (the median depth over the mask) that is not a positive
/// number, or that comes without a camera: orthographic heights have no depth to scale.
pub fn check_distance(distance: Option<f64>, camera: Option<&Pinhole>) -> Result<(), InputError> {
    match (distance, camera) {
        (Some(d), _) if !(d.is_finite() && d > 0.0) => Err(InputError::Options(format!(
            "distance must be a positive number (the median depth over the mask), got {d}"
        ))),
        (Some(_), None) => Err(InputError::Options(
            "distance needs a camera (the `camera` option, --camera or --focal-length, or a \
             K.txt or camera.json with the images): without one the surface is orthographic \
             heights in pixels"
                .into(),
        )),
        _ => Ok(()),
    }
}

/// Past this, noise in the images is amplified more than 100-fold into the normals.
pub const DEFAULT_MAX_CONDITION: f64 = 100.0;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_camera_is_checked_against_the_images_and_a_distance_needs_one() {
        let camera = Some(Pinhole::centred(80.0, 64, 48));
        let with = |camera, distance| Options {
            camera,
            distance,
            ..Options::default()
        };
        assert!(with(camera, Some(5.0)).check_camera(64, 48).is_ok());
        assert!(with(None, None).check_camera(64, 48).is_ok());
        let e = |o: Options| o.check_camera(64, 48).unwrap_err().to_string();
        assert!(e(with(None, Some(5.0))).contains("distance needs a camera"));
        assert!(e(with(camera, Some(0.0))).contains("positive"));
        assert!(e(with(camera, Some(f64::NAN))).contains("positive"));
        // The principal point of a 640 × 480 camera lies outside a 64 × 48 image.
        let large = Some(Pinhole::centred(80.0, 640, 480));
        let outside = e(with(large, None));
        assert!(
            outside.starts_with("camera: the principal point"),
            "{outside}"
        );
        let bad = with(Some(Pinhole::centred(0.5, 64, 48)), None);
        let message = bad.check_values().unwrap_err().to_string();
        assert!(message.contains("field `camera`: fx"), "{message}");
    }

    #[test]
    fn without_a_camera_the_options_serialise_as_before() {
        let json = serde_json::to_value(Options::default()).unwrap();
        assert!(json.get("camera").is_none() && json.get("distance").is_none());
        let camera = Some(Pinhole::centred(80.0, 64, 48));
        let json = serde_json::to_value(Options {
            camera,
            ..Options::default()
        })
        .unwrap();
        assert_eq!(json["camera"]["fx"], 80.0);
        // And what it wrote reads back.
        let back: Options = serde_json::from_value(json).unwrap();
        assert_eq!(back.camera, camera);
    }
}
