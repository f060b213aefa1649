//! Whole open-loop rollouts on any engine: every agent is the model's.

use rand::rngs::StdRng;
use road_model::Result;
use road_sched::PlannerSpec;

use crate::driver::{RolloutDriver, batch_seeds};
use crate::engine::{Rollout, RolloutScene, StepEngine};

/// Rolls out `steps` simulated steps of every scene with `planner` on `engine`. The noise draws
/// depend only on `rng`, so two engines given the same seed sample the same futures (to their
/// numerical agreement).
pub fn rollout_with(
    engine: &mut dyn StepEngine,
    planner: &PlannerSpec,
    scenes: &[RolloutScene],
    steps: usize,
    rng: &mut StdRng,
) -> Result<Rollout> {
    let seeds = batch_seeds(rng, scenes.len());
    rollout_seeded(engine, planner, scenes, steps, &seeds)
}

/// [`rollout_with`] with each scene's noise stream seeded by the caller (`seeds[i]` for scene
/// `i`; see `RolloutDriver::with_seeds`).
pub fn rollout_seeded(
    engine: &mut dyn StepEngine,
    planner: &PlannerSpec,
    scenes: &[RolloutScene],
    steps: usize,
    seeds: &[u64],
) -> Result<Rollout> {
    if scenes.is_empty() {
        return Ok(Rollout {
            agents: vec![],
            steps,
            states: vec![],
            nfe: 0,
        });
    }
    let mut driver = RolloutDriver::with_seeds(engine, planner, scenes, seeds, steps)?;
    for _ in 0..steps {
        driver.tick(engine, &mut |_, _, _| Ok(()))?;
    }
    driver.into_rollout()
}
