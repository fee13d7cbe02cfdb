//! A set of many images is read in bands and never held whole. Its own test binary (as
//! `tests/memory.rs` is), so that no other test's allocations move the peak it measures.

/// Peak resident size of this process (VmHWM), bytes; reset to the current size by
/// writing 5 to /proc/self/clear_refs.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn peak() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .expect("a VmHWM line");
    kb * 1024
}

/// A set of many small images is read in bands: the job's peak stays below what the
/// 16-bit stack alone would take (200 images of 768² are 236 MB of planes; the job's own
/// maps, one band and a row decoder per image come to about half that).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn many_images_reconstruct_without_holding_the_stack() {
    use photostereo::core::intake::{DirMask, Limits};
    use photostereo::core::{Options, RunToEnd, pipeline, stream, synth};
    const MB: u64 = 1 << 20;
    let (size, count) = (768, 200);
    let stack = (size * size * 2 * count) as u64;
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("set");
    let dirs = synth::light_rings(count, 10.0, 60.0);
    synth::write_set(
        &set,
        &synth::Scene::sphere(size),
        &dirs,
        &synth::Capture::default(),
    )
    .unwrap();
    photostereo::core::heap::release_free_heap();
    std::fs::write("/proc/self/clear_refs", "5").expect("resetting the peak");
    let base = peak();
    let opened = stream::open_dir(&set, DirMask::Folder, &Limits::default(), dir.path()).unwrap();
    let out = dir.path().join("out");
    let report = pipeline::run(opened, &Options::default(), &out, &mut RunToEnd).unwrap();
    let grown = peak().saturating_sub(base);
    let mb = |b: u64| b as f64 / MB as f64;
    eprintln!(
        "{count} images of {size}²: peak grew by {:.1} MB; the stack is {:.1} MB",
        mb(grown),
        mb(stack)
    );
    assert_eq!(report.light_count, count);
    assert!(report.object_pixels > size * size / 2);
    assert!(
        grown < stack,
        "the job's peak grew by {:.1} MB, more than the {:.1} MB stack",
        mb(grown),
        mb(stack)
    );
}
