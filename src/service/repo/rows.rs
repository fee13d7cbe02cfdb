//! Rows as both databases store them: the columns, JSON as text, and the decoding into
//! records that both backends share. A row that does not decode is left out of a listing
//! ([`readable`]), never the cause of a failed list.

use std::sync::atomic::{AtomicU64, Ordering};

use uuid::Uuid;

use super::error::{RepoError, RepoResult};
use super::model::{CalibrationRecord, JobRecord, JobStatus};

/// A job row's columns, in [`RawRecord`]'s order.
pub(super) const COLUMNS: &str = "id, status, stage, progress, created_at, started_at, \
     finished_at, heartbeat_at, attempts, image_count, options, error, result, artifacts, \
     tenant, callback";

/// A calibration row's columns, in [`RawCalibration`]'s order.
pub(super) const CALIBRATION_COLUMNS: &str =
    "id, tenant, created_at, detail, light_table, artifacts";

/// A job row as stored (JSON as text), in either database.
pub(super) struct RawRecord {
    pub(super) id: String,
    pub(super) status: String,
    pub(super) stage: Option<String>,
    pub(super) progress: f64,
    pub(super) created_at: i64,
    pub(super) started_at: Option<i64>,
    pub(super) finished_at: Option<i64>,
    pub(super) heartbeat_at: Option<i64>,
    pub(super) attempts: i64,
    pub(super) image_count: i64,
    pub(super) options: String,
    pub(super) error: Option<String>,
    pub(super) result: Option<String>,
    pub(super) artifacts: Option<String>,
    pub(super) tenant: String,
    pub(super) callback: Option<String>,
}

impl RawRecord {
    /// The row that stores `job`.
    pub(super) fn encode(job: &JobRecord) -> RepoResult<Self> {
        Ok(Self {
            id: job.id.to_string(),
            status: job.status.as_str().to_string(),
            stage: job.stage.clone(),
            progress: job.progress,
            created_at: job.created_at,
            started_at: job.started_at,
            finished_at: job.finished_at,
            heartbeat_at: job.heartbeat_at,
            attempts: i64::from(job.attempts),
            image_count: i64::from(job.image_count),
            options: serde_json::to_string(&job.options)?,
            error: job.error.as_ref().map(serde_json::to_string).transpose()?,
            result: job.result.as_ref().map(serde_json::to_string).transpose()?,
            artifacts: Some(serde_json::to_string(&job.artifacts)?),
            tenant: job.tenant.clone(),
            callback: job
                .callback
                .as_ref()
                .map(serde_json::to_string)
                .transpose()?,
        })
    }

    pub(super) fn decode(self) -> RepoResult<JobRecord> {
        let id = job_id(&self.id)?;
        let status = JobStatus::parse(&self.status)
            .ok_or_else(|| RepoError::new(format!("stored status {:?} of {id}", self.status)))?;
        Ok(JobRecord {
            id,
            tenant: self.tenant,
            status,
            stage: self.stage,
            progress: self.progress,
            created_at: self.created_at,
            started_at: self.started_at,
            finished_at: self.finished_at,
            heartbeat_at: self.heartbeat_at,
            attempts: self.attempts.max(0) as u32,
            image_count: self.image_count.max(0) as u32,
            options: serde_json::from_str(&self.options)?,
            error: self.error.map(|e| serde_json::from_str(&e)).transpose()?,
            result: self.result.map(|r| serde_json::from_str(&r)).transpose()?,
            artifacts: self
                .artifacts
                .map(|a| serde_json::from_str(&a))
                .transpose()?
                .unwrap_or_default(),
            callback: self
                .callback
                .map(|c| serde_json::from_str(&c))
                .transpose()?,
        })
    }
}

/// A stored job id.
pub(super) fn job_id(id: &str) -> RepoResult<Uuid> {
    Uuid::parse_str(id).map_err(|e| RepoError::new(format!("stored job id {id:?}: {e}")))
}

/// The ids of a listing that parse (a row with a broken id is no job to act on).
pub(super) fn uuids<'a>(ids: impl IntoIterator<Item = &'a str>) -> Vec<Uuid> {
    ids.into_iter()
        .filter_map(|s| Uuid::parse_str(s).ok())
        .collect()
}

/// Every status with its count (0 for those no row has), from the (status, count) rows.
pub(super) fn status_counts(rows: &[(String, i64)]) -> Vec<(JobStatus, u64)> {
    JobStatus::ALL
        .iter()
        .map(|s| {
            let n = rows
                .iter()
                .find(|(name, _)| name == s.as_str())
                .map_or(0, |(_, n)| *n as u64);
            (*s, n)
        })
        .collect()
}

/// A calibration row: id, tenant, created_at, detail, light_table, artifacts.
pub(super) type RawCalibration = (String, String, i64, String, String, String);

/// The row that stores `cal`.
pub(super) fn encode_calibration(cal: &CalibrationRecord) -> RepoResult<RawCalibration> {
    Ok((
        cal.id.to_string(),
        cal.tenant.clone(),
        cal.created_at,
        serde_json::to_string(&cal.detail)?,
        cal.table.clone(),
        serde_json::to_string(&cal.artifacts)?,
    ))
}

pub(super) fn decode_calibration(
    (id, tenant, created_at, detail, table, artifacts): RawCalibration,
) -> RepoResult<CalibrationRecord> {
    Ok(CalibrationRecord {
        id: Uuid::parse_str(&id)
            .map_err(|e| RepoError::new(format!("stored calibration id {id:?}: {e}")))?,
        tenant,
        created_at,
        detail: serde_json::from_str(&detail)?,
        table,
        artifacts: serde_json::from_str(&artifacts)?,
    })
}

/// Rows of a listing that could not be decoded since the process started (see
/// [`readable`]).
static UNREADABLE: AtomicU64 = AtomicU64::new(0);

/// How many stored records a listing has left out because they could not be read.
pub fn unreadable_records() -> u64 {
    UNREADABLE.load(Ordering::Relaxed)
}

/// The decoded rows of a listing. A row that does not decode is logged, counted
/// ([`unreadable_records`]) and left out: one bad record never breaks a list.
pub fn readable<T>(decoded: impl IntoIterator<Item = RepoResult<T>>, what: &str) -> Vec<T> {
    decoded
        .into_iter()
        .filter_map(|r| {
            r.map_err(|e| {
                UNREADABLE.fetch_add(1, Ordering::Relaxed);
                tracing::error!(error = %e, "a stored {what} cannot be read; left out of the list");
            })
            .ok()
        })
        .collect()
}
