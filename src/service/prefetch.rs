//! Decoding an upload's images while the rest of it arrives, so that its job starts with
//! the planes ready rather than decoding them again.
//!
//! Purely an optimisation: the inputs are still written and committed as before, and a job
//! without a prefetched set (after a restart, when no slot was free, for archives or colour
//! images) decodes from disk. A slot is held from the first image until the job takes the
//! planes (they are then the job's own memory) or the set is dropped; at most
//! `decode_ahead` sets exist at once.

use std::collections::HashMap;
use std::fs::File;
use std::io::{Read, Seek};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use uuid::Uuid;

use crate::core::InputError;
use crate::core::intake::{self, Decoded, Limits};

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
    pub fn discard(&self, id: Uuid) {
        drop(self.take(id));
    }

    /// Sets held now (being received, waiting for their job, or being taken).
    pub fn held(&self) -> usize {
        self.size - self.slots.available_permits()
    }
}

/// One upload's images being decoded ahead. Dropping it drops what was decoded and frees
/// its slot (decodes still running finish into the void).
pub struct Prefetch {
    shared: Arc<Shared>,
    limits: Limits,
}

struct Shared {
    state: Mutex<State>,
    settled: Condvar,
}

struct State {
    /// Stored file name → the decode's result (`None`: left to the job).
    results: HashMap<String, Option<Result<Decoded, InputError>>>,
    /// Decodes started and not finished.
    pending: usize,
    dropped: bool,
    permit: Option<OwnedSemaphorePermit>,
}

impl Prefetch {
    /// Start decoding a completely written image on the rayon pool. `file` is its stored
    /// name, `name` the light table's name for it (decode errors name it), `source` the
    /// written file (read from its start).
    pub fn start(&self, file: String, name: String, source: File) {
        lock(&self.shared.state).pending += 1;
        let shared = self.shared.clone();
        let limits = self.limits;
        rayon::spawn(move || {
            let result = if lock(&shared.state).dropped {
                None
            } else {
                // Unreadable: left to the job, which reports it under the path it reads.
                read_all(source).and_then(|bytes| intake::predecode(&name, &bytes, &limits))
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

    /// Wait for the decodes under way, then hand the results over (by stored file name)
    /// and free the slot: the planes are now the job's.
    ///
    /// Must not be called from the rayon pool: the decodes waited for run there.
    pub fn finish(self) -> HashMap<String, Result<Decoded, InputError>> {
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

fn read_all(mut file: File) -> Option<Vec<u8>> {
    file.rewind().ok()?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes).ok()?;
    Some(bytes)
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
        a.start("000.img".into(), "a.png".into(), open("000.img"));
        a.start("001.img".into(), "b.png".into(), open("001.img"));
        let id = Uuid::new_v4();
        p.park(id, a);
        let results = p.take(id).unwrap().finish();
        assert_eq!(p.held(), 0);
        assert_eq!(results["000.img"].as_ref().unwrap().plane[[0, 0]], 7 * 257);
        assert!(results["001.img"].is_err());

        let b = p.begin().expect("the slot is free again");
        b.start("000.img".into(), "a.png".into(), open("000.img"));
        p.park(id, b);
        p.discard(id);
        assert_eq!(p.held(), 0);
        assert!(p.take(id).is_none());
    }
}
