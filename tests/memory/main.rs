//! Memory measured in this process (VmRSS, VmHWM) or against one large calibration: a
//! program of its own, so that no other test's allocations move the figures, and its
//! tests take turns ([`ONE_AT_A_TIME`]) for the same reason.

#[path = "../binserver/mod.rs"]
mod binserver;

mod bands_memory;
mod calibration_memory;
mod memory;

/// Held by each test of this program while it runs.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());
