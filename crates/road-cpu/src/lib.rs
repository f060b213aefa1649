//! `road-cpu`: the CPU engines behind `road_rollout::StepEngine`, beside `road-gpu`'s WGSL one:
//! - [`CpuEngine`]: candle's `Denoiser`, the reference every other engine is held to;
//! - [`FastCpuEngine`]: the same denoiser on [`fast`]'s path for users without a GPU: kept
//!   buffers, `gemm` products with AVX-512 or AVX2 kernels chosen at run time, agent maps
//!   memoised while their anchors stay put, padding skipped, tokens split across helper
//!   threads kept between calls (`fast/workers`), and hand-written attention and layer norm
//!   kernels (`fast_kernels`: one generic body compiled for AVX2 + FMA and for the baseline).
//!
//! Both keep the windows on the host and run `road_rollout::heun`'s sampler steps.

mod engines;
pub mod fast;
mod fast_kernels;

use rand::rngs::StdRng;
use road_model::{Denoiser, Result};
use road_rollout::{Rollout, RolloutScene, rollout_with};
use road_sched::PlannerSpec;

pub use engines::{CpuEngine, FastCpuEngine};

/// Rolls out `steps` simulated steps of every scene with `planner` on the candle reference
/// (open loop: every agent is the model's). `rng` draws all noise.
pub fn rollout(
    model: &Denoiser,
    planner: &PlannerSpec,
    scenes: &[RolloutScene],
    steps: usize,
    rng: &mut StdRng,
) -> Result<Rollout> {
    rollout_with(&mut CpuEngine::new(model), planner, scenes, steps, rng)
}
