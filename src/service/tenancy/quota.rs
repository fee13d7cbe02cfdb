//! Per-tenant quotas: what one tenant may hold and submit, so that it cannot crowd out
//! the others. The limits are `Config`'s `tenant_*` settings; a refusal is a 429 problem
//! naming the limit, with Retry-After.
//!
//! Jobs queued or running at once and stored bytes are counted by the repo (the durable
//! truth, and the insert re-checks the first atomically); submissions per minute are
//! counted here, in memory, over a sliding window.

use std::collections::{HashMap, VecDeque};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The window of the submission rate.
const WINDOW: Duration = Duration::from_secs(60);

/// Which limit refused a request (the `limit` label of the refusal counter).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Limit {
    ActiveJobs,
    SubmissionsPerMinute,
    StoredBytes,
}

impl Limit {
    pub fn as_str(self) -> &'static str {
        match self {
            Limit::ActiveJobs => "active_jobs",
            Limit::SubmissionsPerMinute => "submissions_per_minute",
            Limit::StoredBytes => "stored_bytes",
        }
    }
}

/// Each tenant's submissions of the last minute.
pub struct SubmissionRate {
    per_minute: usize,
    recent: Mutex<HashMap<String, VecDeque<Instant>>>,
}

impl SubmissionRate {
    /// `per_minute` 0: no limit.
    pub fn new(per_minute: usize) -> Self {
        Self {
            per_minute,
            recent: Mutex::new(HashMap::new()),
        }
    }

    /// Count a submission of `tenant` now, or say how long until one is allowed.
    pub fn admit(&self, tenant: &str) -> Result<(), Duration> {
        self.admit_at(tenant, Instant::now())
    }

    fn admit_at(&self, tenant: &str, now: Instant) -> Result<(), Duration> {
        if self.per_minute == 0 {
            return Ok(());
        }
        let mut recent = self.recent.lock().unwrap_or_else(|p| p.into_inner());
        // Forget tenants that have been quiet for the whole window.
        recent.retain(|_, times| times.back().is_some_and(|t| now - *t < WINDOW));
        let times = recent.entry(tenant.to_string()).or_default();
        while times.front().is_some_and(|t| now - *t >= WINDOW) {
            times.pop_front();
        }
        if times.len() >= self.per_minute {
            let oldest = *times.front().expect("a full window is not empty");
            return Err(WINDOW - (now - oldest));
        }
        times.push_back(now);
        Ok(())
    }

    pub fn per_minute(&self) -> usize {
        self.per_minute
    }
}

/// Whole seconds to wait, at least 1 (Retry-After).
pub fn retry_secs(wait: Duration) -> u64 {
    wait.as_secs_f64().ceil().max(1.0) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_slides_per_tenant() {
        let rate = SubmissionRate::new(2);
        let t0 = Instant::now();
        assert!(rate.admit_at("a", t0).is_ok());
        assert!(rate.admit_at("a", t0 + Duration::from_secs(10)).is_ok());
        let wait = rate
            .admit_at("a", t0 + Duration::from_secs(20))
            .unwrap_err();
        assert_eq!(wait, Duration::from_secs(40));
        assert_eq!(retry_secs(wait), 40);
        assert!(rate.admit_at("b", t0 + Duration::from_secs(20)).is_ok());
        assert!(rate.admit_at("a", t0 + Duration::from_secs(60)).is_ok());
        assert!(SubmissionRate::new(0).admit("a").is_ok());
        assert_eq!(retry_secs(Duration::from_millis(10)), 1);
    }
}
