//! The records the repo keeps: jobs (with their artifacts, outcome and webhook state),
//! calibrations and remembered answers, the problem a failed job keeps, and the values
//! its methods take and give (leases, admission, what the reaper did).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use uuid::Uuid;

/// Where a job is in its life.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, ToSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum JobStatus {
    /// Accepted and waiting for a worker.
    Queued,
    /// A worker is reconstructing it.
    Running,
    /// Finished; its artifacts can be downloaded.
    Succeeded,
    /// Finished with an error (see `error`).
    Failed,
    /// Stopped by a `DELETE` before it finished.
    Cancelled,
}

impl JobStatus {
    pub const ALL: [JobStatus; 5] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Failed,
        JobStatus::Cancelled,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|j| j.as_str() == s)
    }

    /// Succeeded, failed or cancelled: nothing will change it any more.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobStatus::Succeeded | JobStatus::Failed | JobStatus::Cancelled
        )
    }
}

/// One stored artifact of a finished job.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ArtifactInfo {
    pub name: String,
    pub bytes: u64,
    /// Strong entity tag, quotes included.
    pub etag: String,
    /// Where the store keeps it, when under a name of its own (an object store's
    /// attempt-specific key); none in the data directory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub key: Option<String>,
}

/// A job as the repo stores it. Times are milliseconds since the Unix epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRecord {
    pub id: Uuid,
    /// The tenant that created it (the name, never a key).
    pub tenant: String,
    pub status: JobStatus,
    pub stage: Option<String>,
    pub progress: f64,
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
    pub heartbeat_at: Option<i64>,
    /// How many times a worker has started it (more than 1 after a restart).
    pub attempts: u32,
    pub image_count: u32,
    /// The job's `Options`, as JSON.
    pub options: serde_json::Value,
    pub error: Option<Problem>,
    /// The result summary (from the pipeline's report) once succeeded.
    pub result: Option<serde_json::Value>,
    pub artifacts: Vec<ArtifactInfo>,
    pub callback: Option<Callback>,
}

impl JobRecord {
    /// A freshly accepted job.
    pub fn new_queued(
        id: Uuid,
        tenant: &str,
        now: i64,
        image_count: u32,
        options: serde_json::Value,
    ) -> Self {
        Self {
            id,
            tenant: tenant.to_string(),
            status: JobStatus::Queued,
            stage: None,
            progress: 0.0,
            created_at: now,
            started_at: None,
            finished_at: None,
            heartbeat_at: None,
            attempts: 0,
            image_count,
            options,
            error: None,
            result: None,
            artifacts: Vec::new(),
            callback: None,
        }
    }
}

/// Where a job's end is POSTed, and how that went.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Callback {
    /// The job's `callback_url`.
    pub url: String,
    pub state: CallbackState,
    /// Every delivery attempt, oldest first.
    pub attempts: Vec<CallbackAttempt>,
}

/// `pending` until the job ends and a delivery is answered with 2xx (`delivered`), or the
/// retries run out (`failed`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum CallbackState {
    Pending,
    Delivered,
    Failed,
}

/// One delivery attempt.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CallbackAttempt {
    /// RFC 3339.
    pub at: String,
    /// The receiver's HTTP status, when it answered.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub status: Option<u16>,
    /// Why there was no answer (connection refused, time-out, host not allowed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The answer to a request with an `Idempotency-Key` (see `idempotency`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Remembered {
    /// Hash of the request's parts.
    pub body_hash: String,
    pub status: u16,
    pub body: String,
    pub location: Option<String>,
    /// Milliseconds since the Unix epoch.
    pub created_at: i64,
}

/// A calibration as the repo stores it (see `calibrations`). Times are milliseconds since
/// the Unix epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationRecord {
    pub id: Uuid,
    /// The tenant that created it.
    pub tenant: String,
    pub created_at: i64,
    /// What was measured (circle, lights, quality, skipped images), as JSON.
    pub detail: serde_json::Value,
    /// The light table (`name, x, y, z[, intensity]`), as jobs take it.
    pub table: String,
    /// Its stored files (`lights.csv`, `overlay.png`, `lights.png`, `positions.csv` with
    /// several balls).
    pub artifacts: Vec<ArtifactInfo>,
}

/// How a running job ended.
#[derive(Debug, Clone)]
pub enum Finish {
    Succeeded {
        result: serde_json::Value,
        artifacts: Vec<ArtifactInfo>,
    },
    Failed(Problem),
}

/// A claimed job as its worker holds it. Every write the worker makes about the job
/// carries the token and is refused once the job has ended or another claim has taken it
/// (a fencing token: a worker that lost its lease can never overwrite the one that took
/// over).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Lease {
    pub id: Uuid,
    pub token: i64,
}

/// Whether a new job was recorded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admission {
    Accepted,
    /// Its tenant already has `max_active` jobs queued or running.
    TenantFull,
    /// `max_queued` jobs are waiting, all tenants together.
    QueueFull,
}

/// What the reaper did with running jobs whose lease had expired.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Reaped {
    /// Back in the queue, to run again.
    pub requeued: Vec<Uuid>,
    /// Failed: their lease expired on their last attempt.
    pub failed: Vec<Uuid>,
}

/// An RFC 9457 problem: what went wrong, as a machine-readable `type` and a human `detail`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(example = json!({
    "type": "urn:photostereo:problem:invalid-input",
    "title": "Invalid input",
    "status": 422,
    "detail": "image \"im4.png\" is named in the light table but was not provided"
}))]
pub struct Problem {
    /// A URI naming the kind of problem (`urn:photostereo:problem:<kind>`).
    #[serde(rename = "type")]
    pub kind: String,
    /// A short summary of the kind of problem.
    pub title: String,
    /// The HTTP status code of this kind of problem.
    pub status: u16,
    /// What exactly went wrong, naming the part, file, row or value at fault.
    pub detail: String,
    /// The resource the problem is about, when there is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
}
