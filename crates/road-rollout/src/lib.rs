//! `road-rollout`: the engine-generic rollout layer. The scheduler (`road-sched`) drives the
//! per-slot noise levels, an engine evaluates the denoiser and takes the sampler's step of
//! every slot, and the driver emits, shifts and rebuilds windows:
//! - [`engine`]: what the driver needs of an engine ([`StepEngine`]), and a rollout's parts;
//! - [`driver`]: [`RolloutDriver`], many scenes at any phase and planner batched on one engine,
//!   each with its own noise stream; a fixed set of scenes, or a pool they join and leave;
//! - [`heun`]: the per-slot Heun step and the multistep sampler's correction (the references
//!   of the WGSL `heun` kernels, run by the CPU engines);
//! - [`window`]: the window edits every engine makes the same way (their references);
//! - [`open_loop`]: whole open-loop rollouts on any engine;
//! - [`timed`]: any engine with the time spent inside it summed (the host's share of a tick).
//!
//! The planner's post-processing of emitted states (`road-planner`'s smoothing) is applied
//! here, for every engine. Errors are the model layer's ([`road_model::Error`]).

pub mod driver;
pub mod engine;
pub mod heun;
pub mod open_loop;
pub mod timed;
pub mod window;

pub use driver::{Overrides, RolloutDriver, batch_seeds, stream_seed};
pub use engine::{Rollout, RolloutScene, StepEngine};
pub use open_loop::{rollout_seeded, rollout_with};
pub use timed::TimedEngine;
pub use window::{
    NO_TURN, ShiftEdit, ShiftShape, estimate_shift, turn_plan, window_emitted, window_shift,
};
