//! Many scenes, each in its own phase; batches of denoising work for one engine step.
//!
//! The caller's loop: `admit` scenes, `request_tick` the ones that need their next state,
//! then repeatedly form a batch (`next_batch`, read with `batch` and `step_plan`), run one
//! batched denoiser step for its items, and `complete_batch`; finished ticks appear in `take_outcomes`. Nothing allocates on that loop
//! once the internal buffers have grown to the number of live scenes.

use std::collections::VecDeque;

use crate::plan::{PlannerSpec, PlannerTables, StageKind, StepPlan, WindowUpdate};
use crate::{Error, Result};

/// Index of a planner registered with [`Scheduler::add_planner`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PlannerId(pub u32);

/// A live scene. Ids are never reused while the scheduler lives (the generation changes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SceneId {
    index: u32,
    generation: u32,
}

impl SceneId {
    /// Dense index, stable while the scene lives; engines key per-scene buffers by it.
    pub fn index(self) -> usize {
        self.index as usize
    }
}

impl std::fmt::Display for SceneId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "scene {}#{}", self.index, self.generation)
    }
}

/// What a scene needs when it is admitted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneSpec {
    pub planner: PlannerId,
    /// Agents (rows of the scene) whose states come from outside, such as the ego: the engine
    /// denoises their slots like any other but overwrites them with the reported states.
    pub external_agents: Vec<u32>,
}

/// One scene's share of a batched denoiser step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WorkItem {
    pub scene: SceneId,
    pub planner: PlannerId,
    pub stage: StageKind,
    pub step: u32,
    /// True on the first step of a stage: the engine prepares the window (fresh noise after a
    /// shift or rebuild) before evaluating.
    pub stage_start: bool,
}

/// A finished tick: the caller reads `emit_future_slot` of the window as every agent's next
/// state, then applies `then` to the window.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TickOutcome {
    pub scene: SceneId,
    /// 0-based tick number of this scene.
    pub tick: u64,
    pub emit_future_slot: usize,
    pub then: WindowUpdate,
    /// Model evaluations this tick cost.
    pub nfe: u32,
}

/// Counters of one scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SceneStats {
    pub ticks: u64,
    pub nfe: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Waiting for `request_tick`.
    Idle,
    /// Running `stage`; `step` is the next step to hand out.
    InStage {
        stage: StageKind,
        step: u32,
        tick_nfe: u32,
    },
    /// One-shot horizon spent.
    Exhausted,
}

#[derive(Debug)]
struct SceneEntry {
    generation: u32,
    live: bool,
    planner: PlannerId,
    external_agents: Vec<u32>,
    phase: Phase,
    in_batch: bool,
    stats: SceneStats,
}

/// Holds every scene's noise state and forms the batches.
#[derive(Debug, Default)]
pub struct Scheduler {
    planners: Vec<(String, PlannerTables)>,
    scenes: Vec<SceneEntry>,
    free: Vec<u32>,
    /// Scenes with denoising steps pending, in the order they will be batched.
    ready: VecDeque<u32>,
    batch: Vec<WorkItem>,
    outcomes: Vec<TickOutcome>,
    live: usize,
}

impl Scheduler {
    pub fn new() -> Self {
        Self::default()
    }

    /// Preallocates for `scenes` live scenes.
    pub fn with_capacity(scenes: usize) -> Self {
        Self {
            scenes: Vec::with_capacity(scenes),
            ready: VecDeque::with_capacity(scenes),
            batch: Vec::with_capacity(scenes),
            outcomes: Vec::with_capacity(scenes),
            ..Self::default()
        }
    }

    /// Registers a planner under `name` (validated) and precomputes its stage tables.
    pub fn add_planner(&mut self, name: &str, spec: PlannerSpec) -> Result<PlannerId> {
        if self.planners.iter().any(|(n, _)| n == name) {
            return Err(Error::DuplicatePlanner(name.to_owned()));
        }
        let tables = PlannerTables::new(name, spec)?;
        self.planners.push((name.to_owned(), tables));
        Ok(PlannerId(self.planners.len() as u32 - 1))
    }

    pub fn planner(&self, id: PlannerId) -> Result<&PlannerTables> {
        self.planners
            .get(id.0 as usize)
            .map(|(_, t)| t)
            .ok_or(Error::UnknownPlanner(id.0))
    }

    pub fn planner_by_name(&self, name: &str) -> Option<PlannerId> {
        self.planners
            .iter()
            .position(|(n, _)| n == name)
            .map(|i| PlannerId(i as u32))
    }

    /// Number of live scenes.
    pub fn live_scenes(&self) -> usize {
        self.live
    }

    /// Scenes with denoising work pending (including those in the current batch).
    pub fn pending_scenes(&self) -> usize {
        self.ready.len() + self.batch.len()
    }

    pub fn admit(&mut self, spec: SceneSpec) -> Result<SceneId> {
        self.planner(spec.planner)?;
        let entry_for = |generation| SceneEntry {
            generation,
            live: true,
            planner: spec.planner,
            external_agents: spec.external_agents.clone(),
            phase: Phase::Idle,
            in_batch: false,
            stats: SceneStats::default(),
        };
        let index = match self.free.pop() {
            Some(index) => {
                let e = &mut self.scenes[index as usize];
                *e = entry_for(e.generation.wrapping_add(1));
                index
            }
            None => {
                self.scenes.push(entry_for(0));
                self.scenes.len() as u32 - 1
            }
        };
        self.live += 1;
        Ok(SceneId {
            index,
            generation: self.scenes[index as usize].generation,
        })
    }

    fn entry(&self, id: SceneId) -> Result<&SceneEntry> {
        match self.scenes.get(id.index as usize) {
            Some(e) if e.live && e.generation == id.generation => Ok(e),
            _ => Err(Error::UnknownScene(id.to_string())),
        }
    }

    fn entry_mut(&mut self, id: SceneId) -> Result<&mut SceneEntry> {
        match self.scenes.get_mut(id.index as usize) {
            Some(e) if e.live && e.generation == id.generation => Ok(e),
            _ => Err(Error::UnknownScene(id.to_string())),
        }
    }

    pub fn external_agents(&self, id: SceneId) -> Result<&[u32]> {
        Ok(&self.entry(id)?.external_agents)
    }

    pub fn scene_planner(&self, id: SceneId) -> Result<PlannerId> {
        Ok(self.entry(id)?.planner)
    }

    pub fn stats(&self, id: SceneId) -> Result<SceneStats> {
        Ok(self.entry(id)?.stats)
    }

    /// Removes a scene. A scene in the current batch cannot leave until the batch completes.
    pub fn retire(&mut self, id: SceneId) -> Result<SceneStats> {
        let e = self.entry_mut(id)?;
        if e.in_batch {
            return Err(Error::SceneInBatch(id.to_string()));
        }
        e.live = false;
        let stats = e.stats;
        if matches!(e.phase, Phase::InStage { .. }) {
            self.ready.retain(|&i| i != id.index);
        }
        self.free.push(id.index);
        self.live -= 1;
        Ok(stats)
    }

    /// Asks for a scene's next state. Ticks that need no model evaluation (an MPC plan being
    /// executed, one-shot open loop) finish at once and show up in [`Self::take_outcomes`].
    pub fn request_tick(&mut self, id: SceneId) -> Result<()> {
        let planner = self.entry(id)?.planner;
        let e = &self.scenes[id.index as usize];
        match e.phase {
            Phase::InStage { .. } => return Err(Error::TickInProgress(id.to_string())),
            Phase::Exhausted => return Err(Error::HorizonExhausted(id.to_string())),
            Phase::Idle => {}
        }
        let tick = e.stats.ticks;
        let program = self.planners[planner.0 as usize]
            .1
            .spec
            .tick_program(tick)
            .ok_or_else(|| Error::HorizonExhausted(id.to_string()))?;
        match program.stage {
            Some(stage) => {
                self.scenes[id.index as usize].phase = Phase::InStage {
                    stage,
                    step: 0,
                    tick_nfe: 0,
                };
                self.ready.push_back(id.index);
            }
            None => {
                let e = &mut self.scenes[id.index as usize];
                e.stats.ticks += 1;
                if program.then == WindowUpdate::Exhausted {
                    e.phase = Phase::Exhausted;
                }
                self.outcomes.push(TickOutcome {
                    scene: id,
                    tick,
                    emit_future_slot: program.emit_future_slot,
                    then: program.then,
                    nfe: 0,
                });
            }
        }
        Ok(())
    }

    /// Forms the next batch: up to `max_items` scenes' next denoising step, each scene at most
    /// once; returns how many. Read it with [`Self::batch`]. The previous batch must have been
    /// completed.
    pub fn next_batch(&mut self, max_items: usize) -> Result<usize> {
        if !self.batch.is_empty() {
            return Err(Error::BatchInFlight);
        }
        while self.batch.len() < max_items {
            let Some(index) = self.ready.pop_front() else {
                break;
            };
            let e = &mut self.scenes[index as usize];
            let Phase::InStage { stage, step, .. } = e.phase else {
                unreachable!("only scenes in a stage are queued");
            };
            e.in_batch = true;
            self.batch.push(WorkItem {
                scene: SceneId {
                    index,
                    generation: e.generation,
                },
                planner: e.planner,
                stage,
                step,
                stage_start: step == 0,
            });
        }
        Ok(self.batch.len())
    }

    /// The current batch (empty once completed).
    pub fn batch(&self) -> &[WorkItem] {
        &self.batch
    }

    /// The noise levels of one work item's step.
    pub fn step_plan(&self, item: &WorkItem) -> StepPlan<'_> {
        self.planners[item.planner.0 as usize]
            .1
            .stage(item.stage)
            .step(item.step as usize)
    }

    /// Marks the current batch as evaluated: each scene moves one step on, and scenes whose
    /// stage ended finish their tick.
    pub fn complete_batch(&mut self) {
        for i in 0..self.batch.len() {
            let item = self.batch[i];
            let tables = &self.planners[item.planner.0 as usize].1;
            let table = tables.stage(item.stage);
            let step_nfe = u32::from(table.step(item.step as usize).nfe);
            let e = &mut self.scenes[item.scene.index as usize];
            e.in_batch = false;
            let Phase::InStage {
                stage,
                step,
                tick_nfe,
            } = e.phase
            else {
                unreachable!("batched scenes are in a stage");
            };
            let tick_nfe = tick_nfe + step_nfe;
            e.stats.nfe += u64::from(step_nfe);
            if (step as usize) + 1 < table.steps() {
                e.phase = Phase::InStage {
                    stage,
                    step: step + 1,
                    tick_nfe,
                };
                self.ready.push_back(item.scene.index);
                continue;
            }
            let tick = e.stats.ticks;
            let program = tables
                .spec
                .tick_program(tick)
                .expect("a running tick has a program");
            e.stats.ticks += 1;
            e.phase = if program.then == WindowUpdate::Exhausted {
                Phase::Exhausted
            } else {
                Phase::Idle
            };
            self.outcomes.push(TickOutcome {
                scene: item.scene,
                tick,
                emit_future_slot: program.emit_future_slot,
                then: program.then,
                nfe: tick_nfe,
            });
        }
        self.batch.clear();
    }

    /// Moves finished ticks into `out` (appending), oldest first.
    pub fn take_outcomes(&mut self, out: &mut Vec<TickOutcome>) {
        out.append(&mut self.outcomes);
    }
}
