//! How a run reports its stages and learns that it must stop: shared by the pipeline
//! that drives the stages and the numeric stages that poll it.

use serde::Serialize;

/// Named stages, reported to a progress callback as they start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    Decode,
    /// The held-out-light score, when asked for (timed, not reported as progress: it
    /// runs inside the solve stage).
    Holdout,
    Solve,
    Mask,
    Integrate,
    Outputs,
    Mesh,
}

impl Stage {
    pub fn as_str(self) -> &'static str {
        match self {
            Stage::Decode => "decode",
            Stage::Holdout => "holdout",
            Stage::Solve => "solve",
            Stage::Mask => "mask",
            Stage::Integrate => "integrate",
            Stage::Outputs => "outputs",
            Stage::Mesh => "mesh",
        }
    }
}

/// How a run reports its stages and learns that it must stop.
///
/// `enter` is called as each stage starts; `halted` is polled inside the long stages
/// (each row of the solve, each CG iteration and re-weighting round of the integration,
/// each picture and mesh file), so that a cancelled or timed-out job frees its worker
/// within one step of work instead of one stage. Work cut short is discarded: the run
/// then ends `Cancelled`. Any `FnMut(Stage) -> bool + Sync`
/// closure is a `Progress` that is only asked at stage starts.
pub trait Progress: Sync {
    /// A stage starts; `false` stops the run.
    fn enter(&mut self, stage: Stage) -> bool;
    /// Whether the run must stop now (from any thread).
    fn halted(&self) -> bool {
        false
    }
}

impl<F: FnMut(Stage) -> bool + Sync> Progress for F {
    fn enter(&mut self, stage: Stage) -> bool {
        self(stage)
    }
}

/// A [`Progress`] that reports nothing and never stops the run.
pub struct RunToEnd;

impl Progress for RunToEnd {
    fn enter(&mut self, _: Stage) -> bool {
        true
    }
}

/// A polled stop request for the numeric stages below the pipeline.
pub type Halt<'a> = &'a (dyn Fn() -> bool + Sync);

/// A [`Halt`] that never stops.
pub const NEVER: Halt<'static> = &|| false;
