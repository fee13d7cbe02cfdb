//! The worker pool: the bell idle workers wait on, the jobs they hold with what each one's
//! worker watches for, and the counters. The queue itself is the repo's.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use uuid::Uuid;

use crate::service::repo::Lease;

/// What a running job's worker watches for.
#[derive(Default)]
pub struct RunControl {
    /// A `DELETE` cancelled the job.
    pub(super) cancel: AtomicBool,
    /// The service is stopping: stop and run the job again at the next start.
    pub(super) interrupt: AtomicBool,
    /// The lease is no longer held (it ran out and the job went to another worker):
    /// stop, and record nothing.
    pub(super) lost: AtomicBool,
}

/// A job this instance's worker holds.
struct Held {
    lease: Lease,
    ctl: Arc<RunControl>,
}

struct Bell {
    /// Bumped at every ring, so that a worker can tell whether it was rung since it last
    /// looked at the queue.
    rung: u64,
    closed: bool,
}

/// The worker pool: the bell idle workers wait on, the jobs they hold, and its counters.
/// The queue itself is the repo's: workers claim from it.
pub struct Workers {
    bell: Mutex<Bell>,
    ringing: Condvar,
    running: Mutex<HashMap<Uuid, Held>>,
    running_now: AtomicUsize,
    running_max: AtomicUsize,
    /// Workers claiming or holding a job (from asking the repo until done with it).
    pub(super) busy: AtomicUsize,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Default for Workers {
    fn default() -> Self {
        Self {
            bell: Mutex::new(Bell {
                rung: 0,
                closed: false,
            }),
            ringing: Condvar::new(),
            running: Mutex::new(HashMap::new()),
            running_now: AtomicUsize::new(0),
            running_max: AtomicUsize::new(0),
            busy: AtomicUsize::new(0),
            threads: Mutex::new(Vec::new()),
        }
    }
}

impl Workers {
    /// A job may be waiting: wake the idle workers.
    pub fn ring(&self) {
        lock(&self.bell).rung += 1;
        self.ringing.notify_all();
    }

    pub(super) fn rung(&self) -> u64 {
        lock(&self.bell).rung
    }

    /// Wait until rung after `seen` (at once if it already was), closed, or `timeout`.
    pub(super) fn wait_for_ring(&self, seen: u64, timeout: Duration) {
        let bell = lock(&self.bell);
        let _ = self
            .ringing
            .wait_timeout_while(bell, timeout, |b| b.rung == seen && !b.closed);
    }

    /// Claim no more jobs (those queued stay queued in the repo).
    pub fn close(&self) {
        lock(&self.bell).closed = true;
        self.ringing.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        lock(&self.bell).closed
    }

    pub fn running(&self) -> usize {
        self.running_now.load(Ordering::SeqCst)
    }

    /// The most jobs ever running at once since start.
    pub fn running_max(&self) -> usize {
        self.running_max.load(Ordering::SeqCst)
    }

    /// Workers busy with a job (including one being claimed).
    pub fn busy(&self) -> usize {
        self.busy.load(Ordering::SeqCst)
    }

    /// The leases of the jobs held here.
    pub fn leases(&self) -> Vec<Lease> {
        lock(&self.running).values().map(|h| h.lease).collect()
    }

    /// Ask a running job to stop (within one step of work). False when no worker here
    /// has it (the instance that does hears of it at its next heartbeat).
    pub fn cancel_running(&self, id: Uuid) -> bool {
        self.signal(id, |ctl| &ctl.cancel)
    }

    /// The job's lease is gone: its worker stops and records nothing.
    pub fn lose(&self, id: Uuid) -> bool {
        self.signal(id, |ctl| &ctl.lost)
    }

    fn signal(&self, id: Uuid, flag: impl Fn(&RunControl) -> &AtomicBool) -> bool {
        match lock(&self.running).get(&id) {
            Some(held) => {
                flag(&held.ctl).store(true, Ordering::SeqCst);
                true
            }
            None => false,
        }
    }

    /// Whether a worker here still holds the job (it may be finishing a cancelled one).
    pub fn is_held(&self, id: Uuid) -> bool {
        lock(&self.running).contains_key(&id)
    }

    /// Ask every running job to stop and go back to the queue.
    pub fn interrupt_all(&self) {
        for held in lock(&self.running).values() {
            held.ctl.interrupt.store(true, Ordering::SeqCst);
        }
    }

    pub(super) fn register(&self, lease: Lease) -> Arc<RunControl> {
        let ctl = Arc::new(RunControl::default());
        let held = Held {
            lease,
            ctl: ctl.clone(),
        };
        lock(&self.running).insert(lease.id, held);
        ctl
    }

    pub(super) fn unregister(&self, id: Uuid) {
        lock(&self.running).remove(&id);
    }

    pub(super) fn begin_running(&self) -> RunningGuard<'_> {
        let now = self.running_now.fetch_add(1, Ordering::SeqCst) + 1;
        self.running_max.fetch_max(now, Ordering::SeqCst);
        RunningGuard(self)
    }

    pub(super) fn add_thread(&self, handle: std::thread::JoinHandle<()>) {
        lock(&self.threads).push(handle);
    }

    /// Join the worker threads that have exited (all of them after `close` once their
    /// jobs end).
    pub(super) fn join_finished_threads(&self) {
        let mut threads = lock(&self.threads);
        let (done, alive): (Vec<_>, Vec<_>) = threads.drain(..).partition(|t| t.is_finished());
        *threads = alive;
        drop(threads);
        for t in done {
            let _ = t.join();
        }
    }
}

pub(super) struct RunningGuard<'a>(&'a Workers);

impl Drop for RunningGuard<'_> {
    fn drop(&mut self) {
        self.0.running_now.fetch_sub(1, Ordering::SeqCst);
    }
}
