//! Giving freed memory back to the kernel.

/// Hand the allocator's free memory back to the kernel. A job allocates and frees hundreds
/// of MB on many threads, and glibc keeps what each thread's arena freed: an idle server
/// held ~390 MB after a few 2048² jobs, and a 4096² × 96 job's peak varied by 120 MB from
/// run to run with what the solve had left in the arenas when the integration began. Called
/// before the integration, as each service job ends and by the bench before each measured
/// job; a no-op where the allocator is not glibc's.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn release_free_heap() {
    // SAFETY: malloc_trim only returns free allocator memory to the system; no live
    // allocation moves or changes.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn release_free_heap() {}
