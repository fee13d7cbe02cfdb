//! `GET /v1/jobs/{id}/events`: a job's changes as a server-sent event stream.
//!
//! The stream reads the job's record from the repo every `event_interval` and sends an
//! event only when status, stage or progress changed, so it works the same whichever
//! process runs the job and sends at most a few events a second. The first event is the
//! job as it is now, so a late subscriber needs no separate `GET`.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::Stream;
use uuid::Uuid;

use crate::service::error::ApiError;
use crate::service::problem::Problem;
use crate::service::repo::{JobRecord, JobStatus};
use crate::service::views::JobView;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::extract::{JobId, owned_job};
use crate::service::state::AppState;
use crate::service::tenancy::Caller;

/// One server-sent event as a client parses it (documents the stream's shape; the stream
/// itself is written by axum's `Event`).
#[derive(utoipa::ToSchema)]
#[allow(dead_code)]
pub struct StreamEvent {
    /// `job` or `deleted`.
    event: String,
    /// `job`: a JobView as JSON; `deleted`: `{"id": ...}`.
    data: String,
}

/// Comment lines sent while nothing changes, so that proxies keep the connection open.
const KEEP_ALIVE: Duration = Duration::from_secs(15);

/// `GET /v1/jobs/{id}/events`.
pub(crate) fn routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::default().routes(routes!(job_events))
}

/// Follow a job: one event per change of status, stage or progress.
///
/// A `text/event-stream`. Each `job` event's data is the job as `GET /v1/jobs/{id}`
/// answers it; the first is sent at once (the current state). The stream ends after an
/// event with a finished status (succeeded, failed or cancelled), or after a `deleted`
/// event (data `{"id": ...}`) when the job is removed. Comment lines keep an idle
/// connection alive.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/events",
    tag = "jobs",
    params(("id" = Uuid, Path, description = "Job id")),
    responses(
        (status = 200, description = "Server-sent events: `event: job` with a JobView as data, one per change; `event: deleted` when the job is removed. Ends after a finished status",
            body = StreamEvent, content_type = "text/event-stream"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job (or another tenant's)", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn job_events(
    State(state): State<AppState>,
    caller: Caller,
    JobId(id): JobId,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    // The owner is checked once: a job's tenant never changes.
    let first = owned_job(&state, &caller, id).await?;
    let follow = Follow {
        interval: state.config().event_interval,
        state,
        id,
        next: Some(first),
        last: None,
        done: false,
    };
    let stream = futures_util::stream::unfold(follow, |mut f| async move {
        let event = f.next_event().await?;
        Some((Ok(event), f))
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(KEEP_ALIVE)))
}

/// What a stream has sent so far.
struct Follow {
    state: AppState,
    id: Uuid,
    interval: Duration,
    /// A record read but not yet compared (the first one).
    next: Option<JobRecord>,
    /// Status, stage and progress of the last event.
    last: Option<(JobStatus, Option<String>, f64)>,
    done: bool,
}

impl Follow {
    /// Wait for the next change; `None` ends the stream.
    async fn next_event(&mut self) -> Option<Event> {
        if self.done {
            return None;
        }
        loop {
            let record = match self.next.take() {
                Some(r) => Some(r),
                None => {
                    tokio::time::sleep(self.interval).await;
                    if self.state.is_shutting_down() {
                        return None; // the client reconnects to the next server
                    }
                    let id = self.id;
                    match self.state.repo(move |r| r.get(id)).await {
                        Ok(r) => r,
                        Err(e) => {
                            tracing::warn!(job = %id, error = %e.detail(), "event stream");
                            return None;
                        }
                    }
                }
            };
            let Some(record) = record else {
                self.done = true;
                let data = serde_json::json!({ "id": self.id });
                return Some(Event::default().event("deleted").data(data.to_string()));
            };
            let key = (record.status, record.stage.clone(), record.progress);
            if self.last.as_ref() == Some(&key) {
                continue;
            }
            self.done = record.status.is_terminal();
            self.last = Some(key);
            let view = JobView::from_record(record);
            let data = serde_json::to_string(&view).unwrap_or_default();
            return Some(Event::default().event("job").data(data));
        }
    }
}
