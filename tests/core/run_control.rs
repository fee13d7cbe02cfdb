//! How a run is stopped: at a stage start (`Progress::enter`) and inside the long stages
//! (`Progress::halted`, polled by the solve, the integration and the writers), which is
//! what lets the service cancel or time out a job without waiting for its current stage.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use photostereo::core::Options;
use photostereo::core::RunError;
use photostereo::core::bands::InMemory;
use photostereo::core::intake::{self, ImageSet, Limits};
use photostereo::core::pipeline;
use photostereo::core::progress::{Progress, Stage};

fn bump() -> ImageSet {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("res")
        .join("bump");
    intake::load_dir(&dir, intake::DirMask::Folder, &Limits::default()).unwrap()
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    match std::fs::read_dir(dir) {
        Ok(entries) => entries.map(|e| e.unwrap().path()).collect(),
        Err(_) => Vec::new(),
    }
}

/// Records the stages entered and the stage current at each poll; halts once `stop_at`
/// has been entered.
struct Recorder {
    stop_at: Option<Stage>,
    entered: Vec<Stage>,
    halt: AtomicBool,
    polls: Mutex<Vec<Stage>>,
}

impl Recorder {
    fn new(stop_at: Option<Stage>) -> Self {
        Self {
            stop_at,
            entered: Vec::new(),
            halt: AtomicBool::new(false),
            polls: Mutex::new(Vec::new()),
        }
    }
}

impl Progress for Recorder {
    fn enter(&mut self, stage: Stage) -> bool {
        self.entered.push(stage);
        if self.stop_at == Some(stage) {
            self.halt.store(true, Ordering::SeqCst);
        }
        true
    }

    fn halted(&self) -> bool {
        if let Some(&current) = self.entered.last() {
            self.polls.lock().unwrap().push(current);
        }
        self.halt.load(Ordering::SeqCst)
    }
}

#[test]
fn a_full_run_enters_every_stage_and_is_polled_inside_the_long_ones() {
    let out = tempfile::tempdir().unwrap();
    let mut p = Recorder::new(None);
    pipeline::run(
        InMemory::new(bump()),
        &Options::default(),
        out.path(),
        &mut p,
    )
    .unwrap();
    assert_eq!(
        p.entered,
        [Stage::Solve, Stage::Mask, Stage::Integrate, Stage::Mesh]
    );
    let polls = p.polls.into_inner().unwrap();
    for stage in [Stage::Solve, Stage::Integrate, Stage::Mesh] {
        assert!(
            polls.contains(&stage),
            "no poll during {stage:?}: {polls:?}"
        );
    }
    assert!(out.path().join("result.json").is_file());
}

#[test]
fn halted_as_integration_starts_the_run_writes_nothing_and_is_cancelled() {
    // The pictures that need no heights are written while the integration runs: halted
    // from its start, neither goes on and no artifact (nor result.json) appears.
    let out = tempfile::tempdir().unwrap();
    let mut p = Recorder::new(Some(Stage::Integrate));
    let r = pipeline::run(
        InMemory::new(bump()),
        &Options::default(),
        out.path(),
        &mut p,
    );
    assert!(matches!(r, Err(RunError::Cancelled)), "{r:?}");
    assert_eq!(p.entered, [Stage::Solve, Stage::Mask, Stage::Integrate]);
    assert_eq!(files_in(out.path()), Vec::<PathBuf>::new());
}

#[test]
fn halted_during_the_solve_the_run_is_cancelled_before_the_mask() {
    let mut p = Recorder::new(Some(Stage::Solve));
    let r = pipeline::reconstruct(&bump(), &Options::default(), &mut p);
    assert!(matches!(r, Err(RunError::Cancelled)), "{r:?}");
    assert_eq!(p.entered, [Stage::Solve]);
}

#[test]
fn a_stage_start_refused_stops_the_run() {
    let out = tempfile::tempdir().unwrap();
    let mut entered = Vec::new();
    let r = pipeline::run(
        InMemory::new(bump()),
        &Options::default(),
        out.path(),
        &mut |s: Stage| {
            entered.push(s);
            s != Stage::Mesh
        },
    );
    assert!(matches!(r, Err(RunError::Cancelled)), "{r:?}");
    assert_eq!(entered.last(), Some(&Stage::Mesh));
    assert!(!out.path().join("result.json").exists());
}
