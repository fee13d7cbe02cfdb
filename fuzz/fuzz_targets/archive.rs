//! The service's zip reader (`archive` part) on arbitrary bytes: never panics, never
//! writes outside its output directory or past its caps.

#![no_main]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use photostereo::service::{Config, unpack_archive};

struct Scratch {
    _dir: tempfile::TempDir,
    zip: PathBuf,
    out: PathBuf,
    config: Config,
}

fn scratch() -> &'static Scratch {
    static SCRATCH: OnceLock<Scratch> = OnceLock::new();
    SCRATCH.get_or_init(|| {
        // RAM-backed when available: every input is written out and unpacked.
        let shm = Path::new("/dev/shm");
        let dir = if shm.is_dir() {
            tempfile::tempdir_in(shm)
        } else {
            tempfile::tempdir()
        }
        .expect("a scratch directory");
        let mut config = Config::new(dir.path());
        config.max_parts = 16;
        config.max_unpacked_bytes = 1 << 20;
        config.max_images = 8;
        config.max_pixels = 1 << 16;
        Scratch {
            zip: dir.path().join("in.zip"),
            out: dir.path().join("out"),
            config,
            _dir: dir,
        }
    })
}

fn used_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok()?.metadata().ok())
                .map(|m| m.len())
                .sum()
        })
        .unwrap_or(0)
}

fuzz_target!(|data: &[u8]| {
    let s = scratch();
    std::fs::write(&s.zip, data).expect("write the input");
    let _ = std::fs::remove_dir_all(&s.out);
    std::fs::create_dir(&s.out).expect("a fresh output directory");
    let result = unpack_archive(&s.zip, &s.out, &s.config);
    // Only flat files named by the service, within the byte budget.
    for entry in std::fs::read_dir(&s.out).expect("list the output") {
        let entry = entry.expect("an entry");
        let name = entry.file_name().to_string_lossy().into_owned();
        assert!(
            (name.len() == 7 && name.ends_with(".img")) || name == "mask.img",
            "unexpected output file {name:?}"
        );
        assert!(entry.file_type().expect("a file type").is_file());
    }
    assert!(used_bytes(&s.out) <= s.config.max_unpacked_bytes);
    match result {
        Ok((images, table)) => {
            assert!(images.len() <= s.config.max_images);
            assert!(table.len() as u64 <= s.config.max_unpacked_bytes);
        }
        Err(e) => assert!(e.status().is_client_error(), "{e}"),
    }
});
