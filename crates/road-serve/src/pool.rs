//! Continuous batching: the live scenes of one checkpoint and planner share one engine and one
//! closed-loop pool ([`ClosedLoop::pool`]). Each core round starts the ticks of the scenes
//! whose ego arrived (or whose deadline passed) and runs one batched Heun round of every tick
//! in progress; a scene publishes as soon as its own tick is done, so a scene in its warm-up
//! (the planner's K steps) takes its extra rounds beside the others without holding them up,
//! and a scene whose ego is late is simply not in the batch.

use std::sync::Arc;

use road_cpu::FastCpuEngine;
use road_data::LaneletMap;
use road_gpu::GpuContext;
use road_gpu::engine::GpuDenoiser;
use road_gpu::step_engine::GpuStepEngine;
use road_model::checkpoint::LoadedModel;
use road_rollout::StepEngine;
use road_sched::PlannerSpec;
use road_sim::closed_loop::{ClosedLoop, ExternalDriver, SceneMap, SceneTick, SimScene};

use crate::Result;

/// Scenes batch together when they run the same checkpoint under the same planner.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct PoolKey {
    pub checkpoint: String,
    pub planner: String,
}

/// What a pool's engine runs on: the fast CPU engine, or the WGSL kernels with the
/// checkpoint's weights already on the GPU.
#[derive(Debug, Clone, Copy)]
pub enum PoolEngine {
    Cpu,
    Gpu(&'static GpuContext, &'static GpuDenoiser),
}

/// One engine and the pool of scenes on it.
pub struct Pool {
    engine: Box<dyn StepEngine + Send>,
    sim: ClosedLoop<'static>,
    /// The server's scene id in each slot of the pool.
    scene_ids: Vec<Option<u64>>,
    finished: Vec<(usize, SceneTick)>,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pool")
            .field("scenes", &self.live_scenes())
            .field("slots", &self.scene_ids.len())
            .finish_non_exhaustive()
    }
}

impl Pool {
    /// An empty pool of `capacity` scenes of at most `agents` agents on `engine` (both give
    /// candle's results to 1e-4; scenes that hold still cost nothing on either, padding nothing
    /// on the CPU).
    pub fn new(
        model: &'static LoadedModel,
        engine: PoolEngine,
        planner: &PlannerSpec,
        capacity: usize,
        agents: usize,
    ) -> Result<Self> {
        let mut engine: Box<dyn StepEngine + Send> = match engine {
            PoolEngine::Cpu => Box::new(FastCpuEngine::new(&model.model)?),
            PoolEngine::Gpu(ctx, gpu_model) => Box::new(GpuStepEngine::new(ctx, gpu_model)),
        };
        let sim = ClosedLoop::pool(
            engine.as_mut(),
            &model.meta.run.model,
            planner,
            capacity,
            agents,
        )?;
        Ok(Self {
            engine,
            sim,
            scene_ids: vec![None; capacity],
            finished: Vec::new(),
        })
    }

    /// Adds the server's scene `id` on `map` (none: an open area); returns its slot.
    pub fn add(
        &mut self,
        id: u64,
        scene: SimScene,
        planner: &PlannerSpec,
        map: Option<Arc<LaneletMap>>,
        steps: usize,
        seed: u64,
    ) -> Result<usize> {
        // The closed loop needs the map for the planner's lane guard (the server still checks
        // off-road itself, from its own copy of the poses).
        let slot = self.sim.add_scene(
            self.engine.as_mut(),
            scene,
            planner,
            map.map(SceneMap::Shared),
            steps,
            seed,
        )?;
        // A served scene's vehicles leave it at the map's edge instead of driving on.
        self.sim.retire_on_exit(slot, true)?;
        self.scene_ids[slot] = Some(id);
        Ok(slot)
    }

    /// Whether the scene in `slot` reports its agents' plans each tick.
    pub fn request_plans(&mut self, slot: usize, on: bool) -> Result<()> {
        Ok(self.sim.request_plans(slot, on)?)
    }

    /// Removes the scene in `slot` (a tick in progress is dropped).
    pub fn remove(&mut self, slot: usize) -> Result<()> {
        self.sim.remove_scene(slot)?;
        self.scene_ids[slot] = None;
        Ok(())
    }

    pub fn live_scenes(&self) -> usize {
        self.sim.live_scenes()
    }

    /// Every agent's pose after the last tick of the scene in `slot`.
    pub fn poses(&self, slot: usize) -> &[road_sim::Pose] {
        self.sim.poses(slot)
    }

    /// A model-driven vehicle joins the scene in `slot` between its ticks; returns its agent
    /// index (a retired agent's, or a new one: [`ClosedLoop::add_agent`]).
    pub fn add_agent(
        &mut self,
        slot: usize,
        vehicle: &road_sim::populate::PlacedVehicle,
    ) -> Result<usize> {
        Ok(self.sim.add_agent(self.engine.as_mut(), slot, vehicle)?)
    }

    /// Where the present agents of the scene in `slot` are, with their sizes.
    pub fn footprints(&self, slot: usize) -> Result<Vec<road_sim::populate::Footprint>> {
        Ok(self.sim.footprints(slot)?)
    }

    /// Starts the next tick of the scene in `slot`.
    pub fn begin_tick(&mut self, slot: usize, external: &mut dyn ExternalDriver) -> Result<()> {
        Ok(self.sim.begin_tick(slot, external)?)
    }

    /// Scenes with a tick in progress: the next round's batch.
    pub fn ticks_in_progress(&self) -> usize {
        self.sim.ticks_in_progress()
    }

    /// One batched round; returns the server's ids of the scenes whose tick finished, with
    /// what the tick did.
    pub fn round(&mut self) -> Result<Vec<(u64, SceneTick)>> {
        self.sim.round(self.engine.as_mut(), &mut self.finished)?;
        Ok(self
            .finished
            .drain(..)
            .filter_map(|(slot, tick)| self.scene_ids[slot].map(|id| (id, tick)))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::embedded;
    use road_data::WindowConfig;
    use road_sim::closed_loop::{Controller, NoExternal};
    use road_sim::procedural::roundabout;

    /// The lane-guard actions of 40 ticks of the procedural roundabout served by a pool of the
    /// embedded default checkpoint under its own planner, with and without the scene's map.
    fn lane_guard_actions(with_map: bool) -> usize {
        let model: &'static LoadedModel = Box::leak(Box::new(
            road_model::checkpoint::load_from_memory(
                std::path::Path::new("embedded"),
                embedded::CONFIG_TOML,
                embedded::WEIGHTS,
                &candle_core::Device::Cpu,
            )
            .unwrap(),
        ));
        let planner = model.meta.run.planner.clone();
        assert!(
            planner.lane_guard.is_some(),
            "the default planner has a lane guard"
        );
        let scene = roundabout(&WindowConfig::default(), planner.obs_slots).unwrap();
        let mut controllers = vec![Controller::Model; scene.window.agents];
        controllers[scene.ego.agent] = Controller::ConstantVelocity;
        let agents = scene.window.agents;
        let mut pool = Pool::new(model, PoolEngine::Cpu, &planner, 1, agents).unwrap();
        let ticks = 40;
        let slot = pool
            .add(
                7,
                SimScene {
                    window: scene.window.clone(),
                    observed_steps: planner.obs_slots,
                    controllers,
                },
                &planner,
                with_map.then(|| Arc::new(scene.map.clone())),
                ticks,
                0,
            )
            .unwrap();
        let mut acted = 0;
        for _ in 0..ticks {
            pool.begin_tick(slot, &mut NoExternal).unwrap();
            let mut done = Vec::new();
            while done.is_empty() {
                done = pool.round().unwrap();
            }
            let (id, tick) = &done[0];
            assert_eq!(*id, 7);
            let counts = road_sim::closed_loop::guard_actions(std::slice::from_ref(tick));
            acted +=
                counts.nudged_towards_lane + counts.steered_to_lane + counts.stopped_at_road_edge;
        }
        acted
    }

    /// A served scene's closed loop has its map, so the planner's lane guard acts (it cannot
    /// without one).
    #[test]
    fn served_scenes_are_lane_guarded() {
        assert!(lane_guard_actions(true) > 0);
        assert_eq!(lane_guard_actions(false), 0);
    }
}
