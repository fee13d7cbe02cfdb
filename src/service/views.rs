//! The job resource as the API shows it: what `GET /v1/jobs/{id}` answers and what a
//! webhook delivers.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use uuid::Uuid;

use crate::core::intensities::Estimated;
use crate::core::normalmap::Counts;
use crate::core::options::Options;
use crate::core::reflectance::Material;

use super::problem::Problem;
use super::repo::{Callback, JobRecord, JobStatus};
use super::util::rfc3339;

/// A job: where it is, and once it has succeeded, what it produced.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobView {
    /// The job's id (a random UUID).
    pub id: Uuid,
    pub status: JobStatus,
    /// The tenant that submitted it (`default` when the server has no API keys).
    #[schema(example = "alice")]
    pub tenant: String,
    /// The stage reached: decode, solve, mask, integrate, outputs or mesh (null before a
    /// worker starts it).
    #[schema(example = "solve")]
    pub stage: Option<String>,
    /// Fraction of the stages done, 0 to 1.
    #[schema(example = 0.5)]
    pub progress: f64,
    /// RFC 3339.
    #[schema(example = "2025-11-25T19:34:00.123Z")]
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    /// How many times a worker has started the job (more than 1 when a restart
    /// interrupted it).
    pub attempts: u32,
    /// The images uploaded (0 for a normals job).
    pub image_count: u32,
    /// The options in force, defaults filled in.
    #[schema(value_type = Options)]
    pub options: serde_json::Value,
    /// Why the job failed (only when `status` is `failed`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<Problem>,
    /// Headline numbers of the reconstruction (only when `status` is `succeeded`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub result: Option<ResultSummary>,
    /// Artifact name → download URL, for every artifact the job produced (only when
    /// `status` is `succeeded`).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(example = json!({"albedo.png": "/v1/jobs/0b6f2a43-3c1e-4c51-9d1e-6c9f3a7d2e10/artifacts/albedo.png"}))]
    pub artifacts: Option<BTreeMap<String, String>>,
    /// The webhook, when the job was submitted with a `callback_url`: its state and
    /// every delivery attempt.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub callback: Option<Callback>,
    /// This resource's URL.
    pub url: String,
}

/// The reconstruction's headline numbers (a subset of `result.json`).
#[derive(Debug, Default, Serialize, Deserialize, ToSchema)]
#[serde(default)]
pub struct ResultSummary {
    pub width: Option<u64>,
    pub height: Option<u64>,
    pub light_count: Option<u64>,
    /// Condition number of the light matrix (1 is ideal).
    pub light_condition_number: Option<f64>,
    /// Lowest height on the object, in pixel units (orthographic).
    pub height_min: Option<f64>,
    /// Highest height on the object, in pixel units (orthographic).
    pub height_max: Option<f64>,
    /// Nearest depth on the object, along the optical axis (under a camera; relative with
    /// median 1, or in the unit of the `distance` option; for a near-light job in the
    /// light table's unit).
    pub depth_min: Option<f64>,
    /// Farthest depth on the object (under a camera).
    pub depth_max: Option<f64>,
    /// RMS of the integrability residual (curl) over the object.
    pub integrability_rms: Option<f64>,
    /// RMS difference between the images and the reconstruction re-rendered under the
    /// same lights.
    pub reprojection_rms: Option<f64>,
    pub object_pixels: Option<u64>,
    pub background_pixels: Option<u64>,
    /// Pixels whose albedo was above 1 and clamped.
    pub clamped_albedo_pixels: Option<u64>,
    /// Mean solve confidence over the object (0 to 1).
    pub confidence_mean: Option<f64>,
    /// Mean number of observations kept per object pixel.
    pub inliers_mean: Option<f64>,
    /// Object pixels with fewer than 3 usable observations.
    pub unreliable_pixels: Option<u64>,
    /// Camera black level the robust solver estimated and removed.
    pub black_level: Option<f64>,
    /// Image noise σ the robust solver estimated.
    pub noise_sigma: Option<f64>,
    /// Normals jobs: what the reader did with each pixel of the normal map (used,
    /// back-facing, renormalised, and why the others are off the mask), as `result.json`.
    pub counts: Option<Counts>,
    /// `near` for a near-light job (its light table gives positions); absent otherwise.
    #[schema(example = "near")]
    pub lights: Option<String>,
    /// Near-light jobs: the alternations of per-pixel solve and depth integration run.
    pub iterations: Option<u64>,
    /// Near-light jobs: whether the normals settled (when false, `result.json`'s notes say
    /// how much they still moved).
    pub converged: Option<bool>,
    /// Near-light jobs: median depth over the mask of the surface recovered, along the
    /// optical axis, in `unit`.
    pub median_depth: Option<f64>,
    /// Near-light jobs: the unit of depth (and of the table's positions and distance), as
    /// the light table gives it; null when it gives none.
    pub unit: Option<String>,
    /// The lights' relative intensities (mean 1) estimated from the object (with the
    /// `intensities: estimate` option, or for LEDs whose table gives none); the
    /// `lights.json` artifact is the light table with them.
    pub estimated_intensities: Option<Vec<Estimated>>,
    /// `glossy` solver: the object pixels whose lobe model was kept (`specular.png` and
    /// `roughness.png` map them; elsewhere the pixel is Lambertian).
    pub glossy_pixels: Option<u64>,
    /// `glossy` solver: RMS residual over those pixels' lit, unclipped observations under
    /// the lobe model.
    pub glossy_residual_rms: Option<f64>,
    /// `glossy` solver: the same under the Lambertian fit the lobe replaced there.
    pub glossy_lambertian_rms: Option<f64>,
    /// `glossy` solver: the lobe the object's pixels shared (fitted at a sample of them);
    /// null where the sample held too few lobes and each pixel fitted its own.
    pub glossy_material: Option<Material>,
}

pub(crate) fn job_url(id: Uuid) -> String {
    format!("/v1/jobs/{id}")
}

impl JobView {
    pub fn from_record(r: JobRecord) -> Self {
        let url = job_url(r.id);
        let succeeded = r.status == JobStatus::Succeeded;
        Self {
            id: r.id,
            status: r.status,
            tenant: r.tenant,
            stage: r.stage,
            progress: if succeeded { 1.0 } else { r.progress },
            created_at: rfc3339(r.created_at),
            started_at: r.started_at.map(rfc3339),
            finished_at: r.finished_at.map(rfc3339),
            attempts: r.attempts,
            image_count: r.image_count,
            options: r.options,
            error: if r.status == JobStatus::Failed {
                r.error
            } else {
                None
            },
            result: succeeded
                .then(|| r.result.and_then(|v| serde_json::from_value(v).ok()))
                .flatten(),
            artifacts: succeeded.then(|| {
                r.artifacts
                    .iter()
                    .map(|a| (a.name.clone(), format!("{url}/artifacts/{}", a.name)))
                    .collect()
            }),
            callback: r.callback,
            url,
        }
    }
}

/// The job resource as JSON, as `GET /v1/jobs/{id}` answers it (what webhooks deliver).
pub(crate) fn job_json(r: JobRecord) -> String {
    serde_json::to_string(&JobView::from_record(r)).unwrap_or_default()
}
