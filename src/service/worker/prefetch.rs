//! The first pass over an upload's images ([`stream::prescan`]: each decoded once into an
//! unlinked scratch file beside the stored inputs) while the rest of it arrives, so that
//! its job only reads the bands back and decodes nothing.
//!
//! Purely an optimisation: the inputs are still written and committed as before, and a job
//! without a prefetched set (after a restart, when no slot was free, for archives) scans
//! them from disk. What is held in memory is the sampled rows (about 12 000 pixels an
//! image), never the planes; the decoded images are on disk, freed with the set. A slot is
//! held from the first image until the job takes the scans or the set is dropped; at most
//! `decode_ahead` sets exist at once.

use std::collections::HashMap;
use std::fs::File;
use std::path::Path;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use uuid::Uuid;

use crate::core::intake::Limits;
use crate::core::stream::{self, Prescanned};

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// The slots, and the sets of accepted jobs waiting for their worker.
pub struct Prefetcher {
    slots: Arc<Semaphore>,
    size: usize,
    parked: Mutex<HashMap<Uuid, Prefetch>>,
    limits: Limits,
}

impl Prefetcher {
    pub fn new(sets: usize, limits: Limits) -> Self {
        let sets = sets.min(Semaphore::MAX_PERMITS);
        Self {
            slots: Arc::new(Semaphore::new(sets)),
            size: sets,
            parked: Mutex::new(HashMap::new()),
            limits,
        }
    }

    /// A set for a new upload, or `None` when every slot is taken (the job then decodes
    /// from disk).
    pub fn begin(&self) -> Option<Prefetch> {
        let permit = self.slots.clone().try_acquire_owned().ok()?;
        Some(Prefetch {
            shared: Arc::new(Shared {
                state: Mutex::new(State {
                    results: HashMap::new(),
                    pending: 0,
                    dropped: false,
                    permit: Some(permit),
                }),
                settled: Condvar::new(),
            }),
            limits: self.limits,
        })
    }

    /// Keep an accepted job's set until its worker takes it.
    pub fn park(&self, id: Uuid, set: Prefetch) {
        lock(&self.parked).insert(id, set);
    }

    /// The job's set, if one was parked for it.
    pub fn take(&self, id: Uuid) -> Option<Prefetch> {
        lock(&self.parked).remove(&id)
    }

    /// Drop a job's set, if any (the job was cancelled, deleted or refused).
    /// The jobs with a parked set.
    pub fn parked(&self) -> Vec<Uuid> {
        lock(&self.parked).keys().copied().collect()
    }

    pub fn discard(&self, id: Uuid) {
        drop(self.take(id));
    }

    /// Sets held now (being received, waiting for their job, or being taken).
    pub fn held(&self) -> usize {
        self.size - self.slots.available_permits()
    }
}

/// One upload's images being scanned ahead. Dropping it drops what was scanned and frees
/// its slot (scans still running finish into the void).
pub struct Prefetch {
    shared: Arc<Shared>,
    limits: Limits,
}

struct Shared {
    state: Mutex<State>,
    settled: Condvar,
}

struct State {
    /// Stored file name → the scan (`None`: left to the job).
    results: HashMap<String, Option<Prescanned>>,
    /// Scans started and not finished.
    pending: usize,
    dropped: bool,
    permit: Option<OwnedSemaphorePermit>,
}

impl Prefetch {
    /// Start scanning a completely written image on the rayon pool. `file` is its stored
    /// name, `source` the written file (read from its start), `scratch` where its decoded
    /// copy goes (an unlinked file, freed with the scan).
    pub fn start(&self, file: String, source: File, scratch: &Path) {
        lock(&self.shared.state).pending += 1;
        let shared = self.shared.clone();
        let limits = self.limits;
        let scratch = scratch.to_path_buf();
        rayon::spawn(move || {
            let result = if lock(&shared.state).dropped {
                None
            } else {
                // Errors are left to the job, which reports them as without a scan.
                stream::prescan(source, &limits, &scratch)
            };
            let mut state = lock(&shared.state);
            state.pending -= 1;
            if !state.dropped {
                state.results.insert(file, result);
            }
            drop(state);
            shared.settled.notify_all();
        });
    }

    /// Wait for the scans under way, then hand them over (by stored file name) and free
    /// the slot.
    ///
    /// Must not be called from the rayon pool: the scans waited for run there.
    pub fn finish(self) -> HashMap<String, Prescanned> {
        let mut state = lock(&self.shared.state);
        while state.pending > 0 {
            state = self
                .shared
                .settled
                .wait(state)
                .unwrap_or_else(|p| p.into_inner());
        }
        state.permit = None;
        let results = std::mem::take(&mut state.results);
        drop(state); // before `self`, whose drop locks the state too
        results
            .into_iter()
            .filter_map(|(file, r)| Some((file, r?)))
            .collect()
    }
}

impl Drop for Prefetch {
    fn drop(&mut self) {
        let mut state = lock(&self.shared.state);
        state.dropped = true;
        state.results.clear();
        state.permit = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gray_png(path: &std::path::Path, value: u8) {
        image::GrayImage::from_pixel(4, 3, image::Luma([value]))
            .save_with_format(path, image::ImageFormat::Png)
            .unwrap();
    }

    #[test]
    fn slots_are_bounded_and_freed_by_finish_or_drop() {
        let dir = tempfile::tempdir().unwrap();
        let p = Prefetcher::new(1, Limits::default());
        let a = p.begin().expect("a free slot");
        assert!(p.begin().is_none(), "one slot only");
        assert_eq!(p.held(), 1);
        gray_png(&dir.path().join("000.img"), 7);
        std::fs::write(dir.path().join("001.img"), b"not an image").unwrap();
        let open = |f: &str| File::open(dir.path().join(f)).unwrap();
        a.start("000.img".into(), open("000.img"), dir.path());
        a.start("001.img".into(), open("001.img"), dir.path());
        let id = Uuid::new_v4();
        p.park(id, a);
        let results = p.take(id).unwrap().finish();
        assert_eq!(p.held(), 0);
        assert!(results.contains_key("000.img"));
        assert!(!results.contains_key("001.img"), "left to the job");

        let b = p.begin().expect("the slot is free again");
        b.start("000.img".into(), open("000.img"), dir.path());
        p.park(id, b);
        p.discard(id);
        assert_eq!(p.held(), 0);
        assert!(p.take(id).is_none());
    }
}
