//! `road-sched`: the rolling-diffusion noise scheduler (math doc: "Noise schedule", "The window",
//! "Sampling", "The planners").
//!
//! Pure CPU code that knows nothing of models, GPUs or networks:
//! - [`edm`]: σ(u), EDM preconditioning and loss weights, the warm-up / rolling / full profiles;
//! - [`plan`]: planner specs (RoAD-W, AR, DJINN-F MPC-X, one-shot) and their per-step σ tables;
//! - [`scheduler`]: many scenes, each in its own phase, batched into work items.

pub mod edm;
pub mod plan;
pub mod scheduler;

pub use edm::{EdmSchedule, Preconditioning};
pub use plan::{
    COURSE_MIN_SPEED_MPS, CollisionGuard, DEADLOCK_RELEASE_HOLD_SECS, GiveWay, JerkTracking,
    LaneAnticipation, LaneGuard, MAX_GUARD_HORIZON_STEPS, MAX_JERK_TRACKING_AHEAD,
    MAX_LANE_GUARD_LOOKAHEAD_M, MAX_PLAN_SMOOTHING_STEPS, PlannerKind, PlannerSpec, PlannerTables,
    Sampler, StageKind, StageTable, StallRelease, StepPlan, StuckRemoval, TickProgram,
    WindowUpdate,
};
pub use scheduler::{PlannerId, SceneId, SceneSpec, SceneStats, Scheduler, TickOutcome, WorkItem};

/// Errors of the scheduler.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("invalid planner: {reason} (planner `{name}`)")]
    InvalidPlanner { name: String, reason: String },
    #[error("a planner with this name is already registered: `{0}`")]
    DuplicatePlanner(String),
    #[error("no planner with id {0}")]
    UnknownPlanner(u32),
    #[error("no live scene with this id: {0}")]
    UnknownScene(String),
    #[error("a tick is already in progress: {0}")]
    TickInProgress(String),
    #[error("the one-shot horizon is spent; the scene cannot tick again: {0}")]
    HorizonExhausted(String),
    #[error("the scene is in the batch being evaluated; complete the batch first: {0}")]
    SceneInBatch(String),
    #[error("the previous batch has not been completed")]
    BatchInFlight,
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
