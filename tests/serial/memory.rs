//! The job workers give freed memory back to the kernel as each job ends
//! (`release_free_heap`). In the `serial` program, taking its turn with the program's
//! other tests (`crate::ONE_AT_A_TIME`), so no other test's allocations move the resident
//! size it measures.

/// Resident set size of this process, bytes.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn resident() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .expect("a VmRSS line");
    kb * 1024
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn freed_heap_is_returned_to_the_kernel() {
    const MB: u64 = 1 << 20;
    let _turn = crate::ONE_AT_A_TIME.blocking_lock();
    // On a thread of its own, as a job's allocations are: its blocks live in a glibc arena
    // of their own. 64 KiB blocks stay below the mmap threshold, and freeing every other
    // one leaves 32 MiB of holes that no automatic trim of the heap's top can reach.
    std::thread::spawn(|| {
        let blocks: Vec<Vec<u8>> = (0..1024).map(|i| vec![i as u8 | 1; 64 << 10]).collect();
        let full = resident();
        let kept: Vec<Vec<u8>> = (blocks.into_iter().enumerate())
            .filter_map(|(i, b)| (i % 2 == 0).then_some(b))
            .collect();
        let holed = resident();
        photostereo::core::heap::release_free_heap();
        let released = resident();
        let mb = |b: u64| b as f64 / MB as f64;
        eprintln!(
            "resident: {:.1} MB full, {:.1} MB after freeing half, {:.1} MB after the release",
            mb(full),
            mb(holed),
            mb(released)
        );
        assert!(
            holed + 8 * MB > full,
            "freeing alone gave back {:.1} MB: the test no longer sees retained memory",
            mb(full.saturating_sub(holed))
        );
        assert!(
            released + 24 * MB < holed,
            "the release gave back only {:.1} MB of the 32 MiB freed",
            mb(holed.saturating_sub(released))
        );
        drop(kept);
    })
    .join()
    .expect("the allocating thread");
}
