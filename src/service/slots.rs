//! Slots shared fairly between tenants: `total` slots, of which one tenant may hold at
//! most `per_tenant`, so that whatever one tenant does (many uploads, slow ones), the
//! others always find `total − per_tenant` slots it cannot take. Used for the uploads
//! being received (`--max-uploads`, `--tenant-max-uploads`) and the calibrations being
//! computed (`--workers`, `--tenant-max-calibrations`); re-shades use one with no share
//! (`--max-reshades`).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::Notify;

#[derive(Default)]
struct Taken {
    total: usize,
    by_tenant: HashMap<String, usize>,
    waiting: usize,
}

/// Why no slot was given.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Busy {
    /// Every slot is taken.
    Full,
    /// The tenant holds its share.
    TenantShare,
}

pub struct Slots {
    total: usize,
    per_tenant: usize,
    taken: Mutex<Taken>,
    freed: Notify,
    refused_full: AtomicU64,
    refused_share: AtomicU64,
}

impl Slots {
    pub fn new(total: usize, per_tenant: usize) -> Arc<Self> {
        let total = total.max(1);
        Arc::new(Self {
            total,
            per_tenant: per_tenant.clamp(1, total),
            taken: Mutex::new(Taken::default()),
            freed: Notify::new(),
            refused_full: AtomicU64::new(0),
            refused_share: AtomicU64::new(0),
        })
    }

    fn lock(&self) -> MutexGuard<'_, Taken> {
        self.taken.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn total(&self) -> usize {
        self.total
    }

    pub fn per_tenant(&self) -> usize {
        self.per_tenant
    }

    /// Slots taken now.
    pub fn taken(&self) -> usize {
        self.lock().total
    }

    /// Requests waiting for a slot now ([`take`](Self::take)).
    pub fn waiting(&self) -> usize {
        self.lock().waiting
    }

    fn grab(self: &Arc<Self>, taken: &mut Taken, tenant: &str) -> Result<Slot, Busy> {
        if taken.total >= self.total {
            return Err(Busy::Full);
        }
        let mine = taken.by_tenant.get(tenant).copied().unwrap_or(0);
        if mine >= self.per_tenant {
            return Err(Busy::TenantShare);
        }
        taken.total += 1;
        *taken.by_tenant.entry(tenant.to_string()).or_default() += 1;
        Ok(Slot {
            slots: self.clone(),
            tenant: tenant.to_string(),
        })
    }

    /// A slot for `tenant` now, or why not (counted).
    pub fn try_take(self: &Arc<Self>, tenant: &str) -> Result<Slot, Busy> {
        let got = self.grab(&mut self.lock(), tenant);
        match got {
            Err(Busy::Full) => self.refused_full.fetch_add(1, Ordering::Relaxed),
            Err(Busy::TenantShare) => self.refused_share.fetch_add(1, Ordering::Relaxed),
            Ok(_) => 0,
        };
        got
    }

    /// A slot for `tenant`, waited for. Dropping the future gives up the wait.
    pub async fn take(self: &Arc<Self>, tenant: &str) -> Slot {
        let _waiting = Waiting::new(self);
        loop {
            let freed = self.freed.notified();
            tokio::pin!(freed);
            freed.as_mut().enable();
            if let Ok(slot) = self.grab(&mut self.lock(), tenant) {
                return slot;
            }
            freed.await;
        }
    }

    /// (refused because full, refused for the tenant's share).
    pub fn refusals(&self) -> (u64, u64) {
        (
            self.refused_full.load(Ordering::Relaxed),
            self.refused_share.load(Ordering::Relaxed),
        )
    }
}

/// Counts a waiter while it waits.
struct Waiting<'a>(&'a Slots);

impl<'a> Waiting<'a> {
    fn new(slots: &'a Slots) -> Self {
        slots.lock().waiting += 1;
        Self(slots)
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.lock().waiting -= 1;
    }
}

/// A taken slot, given back when dropped.
pub struct Slot {
    slots: Arc<Slots>,
    tenant: String,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut taken = self.slots.lock();
        taken.total -= 1;
        if let Some(n) = taken.by_tenant.get_mut(&self.tenant) {
            *n -= 1;
            if *n == 0 {
                taken.by_tenant.remove(&self.tenant);
            }
        }
        drop(taken);
        self.slots.freed.notify_waiters();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tenant_holds_at_most_its_share() {
        let s = Slots::new(4, 2);
        let a1 = s.try_take("a").unwrap();
        let _a2 = s.try_take("a").unwrap();
        assert_eq!(s.try_take("a").err(), Some(Busy::TenantShare));
        let _b1 = s.try_take("b").unwrap();
        let _b2 = s.try_take("b").unwrap();
        assert_eq!(s.try_take("c").err(), Some(Busy::Full));
        drop(a1);
        assert!(s.try_take("c").is_ok());
        assert_eq!(s.refusals(), (1, 1));
    }

    #[tokio::test]
    async fn a_waiter_gets_the_slot_given_back() {
        let s = Slots::new(1, 1);
        let held = s.try_take("a").unwrap();
        let waiter = {
            let s = s.clone();
            tokio::spawn(async move {
                let _slot = s.take("b").await;
            })
        };
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        assert_eq!(s.waiting(), 1);
        drop(held);
        waiter.await.unwrap();
        assert_eq!((s.taken(), s.waiting()), (0, 0));
    }
}
