//! The behaviour every [`BlobStore`] owes, as one suite: [`run`] takes an empty store
//! and a runtime to drive its downloads on (it is called from a thread outside that
//! runtime, as the store's blocking callers are). The local store's unit tests run it on
//! a directory; `tests/backends/s3.rs` runs it on a real S3 server. What only one store does (the
//! directory's renames, the object store's multipart uploads and partial fetches) stays
//! with that store.

use std::path::Path;

use futures_util::TryStreamExt;
use tokio::runtime::Handle;
use uuid::Uuid;

use super::{BlobStore, MANIFEST_FILE, Served};
use crate::service::repo::ArtifactInfo;

/// Run every check on `store`, which holds nothing yet (each check leaves it so).
pub fn run(store: &dyn BlobStore, rt: &Handle) {
    for (name, check) in [
        ("inputs", inputs as fn(&dyn BlobStore, &Handle)),
        ("outputs", outputs),
        ("partials", partials),
        ("calibrations", calibrations),
    ] {
        eprintln!("store contract: {name}");
        check(store, rt);
    }
}

fn write(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::write(dir.join(name), bytes).unwrap();
}

/// Bytes `range` (all when `None`) of a stored file.
fn read(
    store: &dyn BlobStore,
    rt: &Handle,
    file: Served<'_>,
    range: Option<(u64, u64)>,
) -> Vec<u8> {
    let stream = store.read(file, range.map(|(a, b)| a..b));
    rt.block_on(async {
        let chunks: Vec<_> = stream.await.unwrap().try_collect().await.unwrap();
        chunks.concat()
    })
}

fn info(name: &str, bytes: &[u8]) -> ArtifactInfo {
    ArtifactInfo {
        name: name.into(),
        bytes: bytes.len() as u64,
        etag: "\"e\"".into(),
        key: None,
    }
}

/// A staged upload becomes the job's inputs at commit (the staged copy goes), is fetched
/// back whole, and goes with the job; removing a job twice is no error.
fn inputs(store: &dyn BlobStore, _: &Handle) {
    let id = Uuid::new_v4();
    let staged = store.stage_inputs(id).unwrap();
    assert_eq!(
        std::fs::read_dir(&staged).unwrap().count(),
        0,
        "a fresh directory"
    );
    write(&staged, "000.img", b"x");
    write(&staged, MANIFEST_FILE, b"{}");
    assert!(!store.has_inputs(id).unwrap(), "not before the commit");
    store.commit_inputs(id).unwrap();
    assert!(!staged.exists(), "the staged copy goes once committed");
    assert!(store.has_inputs(id).unwrap());
    let fetched = store.fetch_inputs(id, &|_| false).unwrap();
    assert!(fetched.join("000.img").is_file());
    assert_eq!(std::fs::read(fetched.join("000.img")).unwrap(), b"x");
    assert_eq!(store.job_ids().unwrap(), vec![id]);
    assert!(store.free_bytes().unwrap() > 0);
    store.probe_writable().unwrap();
    store.remove_inputs(id).unwrap();
    assert!(!store.has_inputs(id).unwrap());
    store.remove_job(id).unwrap();
    store.remove_job(id).unwrap();
    assert!(store.job_ids().unwrap().is_empty());
}

/// Staged outputs become the attempt's artifacts at commit: served whole or in part,
/// handed out as local files, and gone once discarded.
fn outputs(store: &dyn BlobStore, rt: &Handle) {
    let id = Uuid::new_v4();
    let out = store.stage_outputs(id).unwrap();
    let (result, normal) = (&b"{\"width\": 4}"[..], &b"\x89PNG not really"[..]);
    write(&out, "result.json", result);
    write(&out, "normal.png", normal);
    let mut artifacts = vec![info("result.json", result), info("normal.png", normal)];
    store.commit_outputs(id, "1", &mut artifacts).unwrap();
    for (a, bytes) in artifacts.iter().zip([result, normal]) {
        let file = Served::Artifact { job: id, info: a };
        assert_eq!(read(store, rt, file, None), bytes, "{}", a.name);
        assert_eq!(
            read(store, rt, file, Some((1, 5))),
            &bytes[1..5],
            "{}",
            a.name
        );
    }
    let local = store
        .local_artifacts(id, &artifacts.iter().collect::<Vec<_>>())
        .unwrap();
    assert_eq!(
        std::fs::read(local.dir().join("normal.png")).unwrap(),
        normal
    );
    drop(local);
    store.discard_outputs(id, "1").unwrap();
    let gone = store.read(
        Served::Artifact {
            job: id,
            info: &artifacts[0],
        },
        None,
    );
    let e = rt
        .block_on(gone)
        .err()
        .expect("a discarded artifact is gone");
    assert!(e.is_not_found(), "{e}");
    assert!(!e.is_unavailable(), "{e}");
    store.remove_job(id).unwrap();
    assert!(store.job_ids().unwrap().is_empty());
}

/// What an interrupted upload or reconstruction left behind goes; the job's committed
/// inputs stay.
fn partials(store: &dyn BlobStore, _: &Handle) {
    let id = Uuid::new_v4();
    let staged = store.stage_inputs(id).unwrap();
    write(&staged, MANIFEST_FILE, b"{}");
    store.commit_inputs(id).unwrap();
    let again = store.stage_inputs(id).unwrap();
    write(&again, "000.img", b"half");
    let out = store.stage_outputs(id).unwrap();
    write(&out, "result.json", b"{");
    store.remove_partials(id).unwrap();
    assert!(!again.exists() && !out.exists());
    assert!(store.has_inputs(id).unwrap());
    store.remove_job(id).unwrap();
    assert!(store.job_ids().unwrap().is_empty());
}

/// A calibration's staged files become its files at commit, are served, and go with it.
fn calibrations(store: &dyn BlobStore, rt: &Handle) {
    let id = Uuid::new_v4();
    let staged = store.stage_calibration(id).unwrap();
    let table = &b"im1.png, 0, 0, 1\n"[..];
    write(&staged, "lights.csv", table);
    store.commit_calibration(id).unwrap();
    assert_eq!(store.calibration_ids().unwrap(), vec![id]);
    let lights = info("lights.csv", table);
    let file = Served::Calibration { id, info: &lights };
    assert_eq!(read(store, rt, file, None), table);
    store.remove_calibration(id).unwrap();
    store.remove_calibration(id).unwrap();
    assert!(store.calibration_ids().unwrap().is_empty());
    // Jobs and calibrations do not meet.
    assert!(store.job_ids().unwrap().is_empty());
}
