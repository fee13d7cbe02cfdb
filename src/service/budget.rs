//! The process-wide memory budget (`--memory-budget`): every piece of work that holds
//! memory in proportion to its images (a job, a calibration, a re-shade) reserves its
//! estimated peak here before it starts, and gives it back when it ends.
//!
//! A job's worker waits for its reservation before it claims a job, so a job that does
//! not fit stays queued; a calibration waits within its request; a re-shade that does not
//! fit is answered 503 at once. A reservation larger than the whole budget is cut to the
//! budget (it then runs alone), so nothing accepted can wait for ever.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::Notify;

use super::config::Config;
use crate::core::options::Solver;
use crate::core::outputs::shaded_png_capacity;
use crate::core::{near, normals_in, pipeline};

/// The most any job may need: its images (or normal map) at `--max-pixels`, of whichever
/// kind costs most (the core's bounds: `pipeline`, `near` and `normals_in::peak_bytes`).
/// A worker reserves this before it claims a job (it cannot know the job's size or kind
/// before), and cuts it to the job's own bound once the job's inputs are opened.
pub fn job_worst_bytes(config: &Config) -> u64 {
    let pixels = config.max_pixels;
    (pipeline::peak_bytes(pixels, Solver::Glossy))
        .max(near::peak_bytes(pixels))
        .max(normals_in::peak_bytes(pixels))
}

/// A calibration's documented peak, reserved while it computes: the core's bound for
/// images of up to `--max-pixels`, whatever their number.
pub fn calibration_peak_bytes(config: &Config) -> u64 {
    crate::core::calibrate::peak_bytes(config.max_pixels)
}

/// A re-shade of a `width × height` job: the encoded picture, held whole for its ETag
/// (at most the raw 16-bit samples and a little deflate framing, allocated once), the
/// row buffers of the two pictures it reads, and the decoders' state.
pub fn reshade_peak_bytes(width: u64, height: u64) -> u64 {
    shaded_png_capacity(width, height) as u64 + 16 * width + (1 << 20)
}

/// What a reservation is for (its label in /metrics).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Use {
    Job,
    Calibration,
    Reshade,
}

impl Use {
    const ALL: [Use; 3] = [Use::Job, Use::Calibration, Use::Reshade];

    pub fn as_str(self) -> &'static str {
        match self {
            Use::Job => "job",
            Use::Calibration => "calibration",
            Use::Reshade => "reshade",
        }
    }
}

#[derive(Default)]
struct Held {
    total: u64,
    by_use: BTreeMap<Use, u64>,
}

/// The budget: what is reserved, the waiters, and the counters /metrics shows.
pub struct Budget {
    limit: u64,
    held: Mutex<Held>,
    /// Blocking waiters (job workers).
    freed: Condvar,
    /// Async waiters (calibrations).
    freed_async: Notify,
    refusals: [AtomicU64; 3],
    waits: [AtomicU64; 3],
}

fn lock(m: &Mutex<Held>) -> MutexGuard<'_, Held> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Budget {
    pub fn new(limit: u64) -> Arc<Self> {
        Arc::new(Self {
            limit: limit.max(1),
            held: Mutex::new(Held::default()),
            freed: Condvar::new(),
            freed_async: Notify::new(),
            refusals: Default::default(),
            waits: Default::default(),
        })
    }

    pub fn limit(&self) -> u64 {
        self.limit
    }

    /// Bytes not reserved now.
    pub fn free(&self) -> u64 {
        self.limit.saturating_sub(lock(&self.held).total)
    }

    fn take(self: &Arc<Self>, held: &mut Held, what: Use, bytes: u64) -> Option<Reservation> {
        let bytes = bytes.min(self.limit);
        if held.total + bytes > self.limit {
            return None;
        }
        held.total += bytes;
        *held.by_use.entry(what).or_default() += bytes;
        Some(Reservation {
            budget: self.clone(),
            what,
            bytes,
        })
    }

    /// Reserve `bytes` now, or `None` (counted as a refusal).
    pub fn try_reserve(self: &Arc<Self>, what: Use, bytes: u64) -> Option<Reservation> {
        let got = self.take(&mut lock(&self.held), what, bytes);
        if got.is_none() {
            self.refusals[what as usize].fetch_add(1, Ordering::Relaxed);
        }
        got
    }

    /// Reserve `bytes`, waiting on this thread until they fit; `None` once `give_up`
    /// says so (checked at least every 100 ms). A wait is counted.
    pub fn reserve_blocking(
        self: &Arc<Self>,
        what: Use,
        bytes: u64,
        give_up: impl Fn() -> bool,
    ) -> Option<Reservation> {
        let mut held = lock(&self.held);
        let mut counted = false;
        loop {
            if let Some(r) = self.take(&mut held, what, bytes) {
                return Some(r);
            }
            if give_up() {
                return None;
            }
            if !counted {
                counted = true;
                self.waits[what as usize].fetch_add(1, Ordering::Relaxed);
            }
            held = self
                .freed
                .wait_timeout(held, Duration::from_millis(100))
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// Reserve `bytes`, waiting (asynchronously) until they fit. A wait is counted.
    pub async fn reserve(self: &Arc<Self>, what: Use, bytes: u64) -> Reservation {
        let mut counted = false;
        loop {
            let freed = self.freed_async.notified();
            tokio::pin!(freed);
            freed.as_mut().enable();
            if let Some(r) = self.take(&mut lock(&self.held), what, bytes) {
                return r;
            }
            if !counted {
                counted = true;
                self.waits[what as usize].fetch_add(1, Ordering::Relaxed);
            }
            freed.await;
        }
    }

    fn release(&self, what: Use, bytes: u64) {
        let mut held = lock(&self.held);
        held.total -= bytes;
        *held.by_use.entry(what).or_default() -= bytes;
        drop(held);
        self.freed.notify_all();
        self.freed_async.notify_waiters();
    }

    /// Prometheus lines: the budget, what is reserved by use, refusals and waits.
    pub fn render(&self, out: &mut String) {
        let by_use = lock(&self.held).by_use.clone();
        let _ = writeln!(
            out,
            "# HELP photostereo_memory_budget_bytes The process-wide memory budget (--memory-budget).\n# TYPE photostereo_memory_budget_bytes gauge\nphotostereo_memory_budget_bytes {}",
            self.limit
        );
        let _ = writeln!(
            out,
            "# HELP photostereo_memory_reserved_bytes Bytes of the budget reserved now, by use.\n# TYPE photostereo_memory_reserved_bytes gauge"
        );
        for what in Use::ALL {
            let n = by_use.get(&what).copied().unwrap_or(0);
            let _ = writeln!(
                out,
                "photostereo_memory_reserved_bytes{{use=\"{}\"}} {n}",
                what.as_str()
            );
        }
        let counters = [
            (
                "photostereo_memory_refusals_total",
                "Work refused because the memory budget had no room (re-shades: 503).",
                &self.refusals,
            ),
            (
                "photostereo_memory_waits_total",
                "Work that waited for room in the memory budget (a job stays queued meanwhile).",
                &self.waits,
            ),
        ];
        for (name, help, values) in counters {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter");
            for what in Use::ALL {
                let n = values[what as usize].load(Ordering::Relaxed);
                let _ = writeln!(out, "{name}{{use=\"{}\"}} {n}", what.as_str());
            }
        }
    }
}

/// Reserved bytes, given back when dropped.
pub struct Reservation {
    budget: Arc<Budget>,
    what: Use,
    bytes: u64,
}

impl Reservation {
    /// Keep only `bytes` of the reservation (no-op if it holds less).
    pub fn shrink_to(&mut self, bytes: u64) {
        if bytes < self.bytes {
            self.budget.release(self.what, self.bytes - bytes);
            self.bytes = bytes;
        }
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.budget.release(self.what, self.bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reservations_fit_the_budget_and_are_given_back() {
        let b = Budget::new(100);
        let a = b.try_reserve(Use::Job, 60).unwrap();
        assert!(b.try_reserve(Use::Reshade, 50).is_none());
        let mut c = b.try_reserve(Use::Reshade, 40).unwrap();
        assert_eq!(b.free(), 0);
        c.shrink_to(10);
        assert_eq!(b.free(), 30);
        drop(a);
        assert_eq!(b.free(), 90);
        // More than the whole budget: cut to it, so it can run alone.
        drop(c);
        let _all = b.try_reserve(Use::Calibration, 1 << 40).unwrap();
        assert_eq!(b.free(), 0);
        let mut text = String::new();
        b.render(&mut text);
        assert!(
            text.contains("photostereo_memory_budget_bytes 100"),
            "{text}"
        );
        assert!(text.contains("photostereo_memory_reserved_bytes{use=\"calibration\"} 100"));
        assert!(text.contains("photostereo_memory_refusals_total{use=\"reshade\"} 1"));
    }

    #[test]
    fn a_blocked_reservation_waits_until_room_is_freed() {
        let b = Budget::new(100);
        let first = b.try_reserve(Use::Calibration, 80).unwrap();
        let waiter = {
            let b = b.clone();
            std::thread::spawn(move || b.reserve_blocking(Use::Job, 50, || false).is_some())
        };
        std::thread::sleep(Duration::from_millis(50));
        assert!(!waiter.is_finished());
        drop(first);
        assert!(waiter.join().unwrap());
        assert!(
            b.reserve_blocking(Use::Job, 200, || true).is_some(),
            "cut to the budget"
        );
        let full = b.try_reserve(Use::Job, 100).unwrap();
        assert!(b.reserve_blocking(Use::Job, 1, || true).is_none());
        drop(full);
    }
}
