//! Tests that must run alone: memory measured in this process (VmRSS, VmHWM) or against one
//! large calibration, and thousands of connections against the real binary with its probes'
//! latencies and its memory. A program of their own, so that no other program's tests run
//! beside them (Cargo runs test programs one after another), and its tests take turns
//! ([`ONE_AT_A_TIME`]) so that none runs beside another.

#[path = "../binserver/mod.rs"]
mod binserver;
#[path = "../common/mod.rs"]
mod common;

mod bands_memory;
mod calibration_memory;
mod connections;
mod memory;

/// Held by each test of this program while it runs.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());
