//! A set of many images is read in bands and never held whole, and each kind of job
//! peaks within what the service reserves for it. In the `serial` program, so that no
//! other test's allocations move the peaks it measures; its tests take turns with the
//! program's others (`crate::ONE_AT_A_TIME`) for the same reason.

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
    let _turn = crate::ONE_AT_A_TIME.blocking_lock();
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

/// Each kind of job peaks within the bound the service reserves for it (the core's
/// `peak_bytes`): a distant job, a near-light job (a ring of 24 LEDs over a relief plate)
/// and a normal map integrated, each of 2048² (where most of a bound is its per-pixel
/// term), one after the other so that no job's allocations move another's peak.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn each_kind_of_job_peaks_within_what_the_service_reserves() {
    use photostereo::core::intake::{DirMask, Limits};
    use photostereo::core::{
        Options, RunToEnd, near, normalmap, normals_in, pipeline, stream, synth,
    };
    let _turn = crate::ONE_AT_A_TIME.blocking_lock();
    const MB: f64 = (1 << 20) as f64;
    let size = 2048;
    let pixels = (size * size) as u64;
    let dir = tempfile::tempdir().unwrap();
    let rig = synth::ring_relief_of(size, 24);
    let near_set = dir.path().join("near");
    rig.write(&near_set).unwrap();
    // The same images under the best distant table.
    let distant_set = dir.path().join("distant");
    std::fs::create_dir_all(&distant_set).unwrap();
    let mut csv = String::new();
    for l in rig.distant_table() {
        std::fs::copy(near_set.join(&l.name), distant_set.join(&l.name)).unwrap();
        let d = l.direction;
        csv += &format!(
            "{}, {}, {}, {}, {}\n",
            l.name, d[0], d[1], d[2], l.intensity
        );
    }
    std::fs::write(distant_set.join("light_directions.csv"), csv).unwrap();
    let (camera, distance) = (rig.camera, rig.distance);
    drop(rig);

    let scratch = dir.path();
    let limits = Limits::default();
    let open = |set: &std::path::Path| {
        stream::open_dir(set, DirMask::Folder, &limits, scratch).expect("opening the set")
    };
    let check = |name: &str, bound: u64, job: &dyn Fn()| {
        photostereo::core::heap::release_free_heap();
        std::fs::write("/proc/self/clear_refs", "5").expect("resetting the peak");
        let base = peak();
        job();
        let grown = peak().saturating_sub(base);
        eprintln!(
            "{name} {size}²: peak grew by {:.1} MB ({:.1} bytes per pixel); reserved {:.1} MB",
            grown as f64 / MB,
            grown as f64 / pixels as f64,
            bound as f64 / MB
        );
        assert!(
            grown <= bound,
            "a {name} job grew by {:.1} MB, over the {:.1} MB the service reserves",
            grown as f64 / MB,
            bound as f64 / MB
        );
    };
    let options = Options::default();
    check(
        "distant",
        pipeline::peak_bytes(pixels, options.solver),
        &|| {
            let out = scratch.join("out-distant");
            pipeline::run(open(&distant_set), &options, &out, &mut RunToEnd).unwrap();
        },
    );
    check("near", near::peak_bytes(pixels), &|| {
        let out = scratch.join("out-near");
        let mut set = open(&near_set);
        near::run(
            &mut set,
            camera,
            distance,
            None,
            &options,
            &out,
            &mut RunToEnd,
        )
        .unwrap();
    });
    check("normals", normals_in::peak_bytes(pixels), &|| {
        let map = scratch.join("out-distant/normal.png");
        let map = normalmap::read(&map, None, Default::default(), None, &limits).unwrap();
        let settings = normals_in::Settings::of(&options);
        let out = scratch.join("out-normals");
        normals_in::run(map, &settings, &out, &mut RunToEnd).unwrap();
    });
}
