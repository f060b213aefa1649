//! Sampling rollouts: the scheduler drives the per-slot noise levels, an engine evaluates the
//! denoiser and takes a deterministic Heun step (EDM Algorithm 1 with a per-slot σ) of every
//! slot, and the driver here emits, shifts and rebuilds windows. The engines: [`CpuEngine`]
//! (candle, the reference every engine must match) and [`FastCpuEngine`] (the CPU path for
//! users without a GPU) in `cpu_engine.rs`, the WGSL engine in `road-gpu`.
//!
//! Many scenes run in lockstep as one batch (each with its own noise); scenes of one call share
//! a planner, so their steps line up.

use rand::rngs::StdRng;
use rand::{RngCore, SeedableRng};
use road_sched::{PlannerSpec, SceneSpec, Scheduler, TickOutcome, WindowUpdate};

use crate::batch::{AGENT_FEATURES, SceneInput, normal_vec};
pub use crate::cpu_engine::{CpuEngine, FastCpuEngine};
use crate::model::Denoiser;
use crate::{Error, Result};

/// One scene to roll out: its observed history (the last `n` slots of `history` are the
/// window's observations) and static features, in model units.
#[derive(Debug, Clone)]
pub struct RolloutScene {
    /// History and map; `history.slots ≥ n`, the newest step last.
    pub history: SceneInput,
}

/// Emitted states of every scene: `[scenes][agents, steps, 3]` in model units.
#[derive(Debug, Clone, PartialEq)]
pub struct Rollout {
    pub agents: Vec<usize>,
    pub steps: usize,
    pub states: Vec<Vec<f32>>,
    /// Model evaluations per scene over the whole rollout.
    pub nfe: u64,
}

/// Per-scene state in model units. The window lives in the engine; `window` is the host copy
/// built from the history when the window is (re)built, `valid` the window's current validity.
struct SceneState {
    agents: usize,
    window: Vec<f32>, // [A_max, W, 3]
    valid: Vec<f32>,  // [A_max, W]
    /// Every state so far: observed history then emitted, `[agents][t] → [3]`.
    history: Vec<Vec<[f32; 3]>>,
    history_valid: Vec<Vec<bool>>,
    emitted: Vec<f32>, // [agents, steps, 3]
}

/// What the rollout driver needs of an engine: static inputs once, then batched Heun steps on
/// device-resident windows, each scene with its own per-slot σ row (scenes at different phases,
/// or under different planners, share a batch; a scene with σ_cur = σ_next everywhere holds
/// still). Windows stay on the device from tick to tick: a scene's window is loaded only when
/// it is (re)built, a tick reads back only the emitted slots, and the shift after an emission
/// happens on the device.
pub trait StepEngine {
    /// W of the model.
    fn window_slots(&self) -> usize;
    /// `features [B, A, 6]`, `map [B, P, Q, 2]`, `map_valid [B, P]`.
    fn prepare(
        &mut self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()>;
    /// Every window `[B, A, W, 3]` and validity `[B, A, W]`, once after `prepare`.
    fn load(&mut self, windows: &[f32], valid: &[f32]) -> Result<()>;
    /// One scene's window `[A, W, 3]` and validity `[A, W]` (at the start of its stage).
    fn load_scene(&mut self, scene: usize, window: &[f32], valid: &[f32]) -> Result<()>;
    /// One Heun step of every scene, σ `[B, W]` per scene and slot (EDM Algorithm 1, per slot).
    /// Without `second_evaluation` every changing slot takes the Euler step.
    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> Result<()>;
    /// Each scene's emitted states `[B, A, 3]` from window slot `slots[b]` (`None`: not read,
    /// zeros): the only readback of a tick.
    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()>;
    /// After an emission, on the device: every scene with an edit shifts its window by one
    /// slot (see [`window_shift`]) and takes the edit's validity `[A, W]`.
    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()>;
}

/// One scene's window shift after an emission.
#[derive(Debug, Clone, Copy)]
pub struct ShiftEdit<'a> {
    pub scene: usize,
    /// The emitted states as they join the observations (controllers' overrides applied),
    /// `[agents, 3]`.
    pub emitted: &'a [f32],
    /// Standard normal draws `[agents, 6]`: observation noise (3), then the new slot's (3).
    pub noise: &'a [f32],
    /// The window's validity after the shift, `[A, W]`.
    pub valid: &'a [f32],
}

/// What a shift needs to know of the planner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShiftShape {
    /// n: observed slots.
    pub observed: usize,
    pub obs_noise: f32,
    pub sigma_max: f32,
}

/// Gathers slot `slots[b]` of every scene's window `[B, A, W, 3]` into `out [B, A, 3]` (zeros
/// where `None`). The reference of the `window_emitted` kernel.
pub fn window_emitted(
    windows: &[f32],
    agents: usize,
    w: usize,
    slots: &[Option<usize>],
    out: &mut [f32],
) {
    for (b, slot) in slots.iter().enumerate() {
        for a in 0..agents {
            let o = &mut out[3 * (b * agents + a)..][..3];
            match slot {
                Some(s) => o.copy_from_slice(&windows[3 * ((b * agents + a) * w + s)..][..3]),
                None => o.fill(0.0),
            }
        }
    }
}

/// The window after an emission from slot n of scene `scene` (`window [A, W, 3]` of that scene):
/// slots move up by one, slot n − 1 = emitted + obs_noise·noise, slot W − 1 = σ_max·noise (agents past
/// `emitted`'s count are padding and untouched but for the move). The reference of the
/// `window_shift` kernel.
pub fn window_shift(window: &mut [f32], w: usize, edit: &ShiftEdit<'_>, shape: ShiftShape) {
    let agents = window.len() / (3 * w);
    let real = edit.emitted.len() / 3;
    for a in 0..agents {
        let row = a * w;
        window.copy_within(3 * (row + 1)..3 * (row + w), 3 * row);
        for d in 0..3 {
            let (e, obs, new) = if a < real {
                (
                    edit.emitted[3 * a + d],
                    edit.noise[6 * a + d],
                    edit.noise[6 * a + 3 + d],
                )
            } else {
                (0.0, 0.0, 0.0)
            };
            window[3 * (row + shape.observed - 1) + d] = e + shape.obs_noise * obs;
            window[3 * (row + w - 1) + d] = shape.sigma_max * new;
        }
    }
}

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
    if scenes.is_empty() {
        return Ok(Rollout {
            agents: vec![],
            steps,
            states: vec![],
            nfe: 0,
        });
    }
    let mut driver = RolloutDriver::new(engine, planner, scenes, steps, rng)?;
    for _ in 0..steps {
        driver.tick(engine, &mut |_, _| Ok(()))?;
    }
    driver.into_rollout()
}

/// Tick-by-tick rollouts of many scenes batched on one engine: the open-loop [`rollout_with`]
/// and the closed loop of `road-sim`, where agents the model does not drive overwrite their
/// emitted states every tick (math doc: "In closed loop the ego agent's slots are overwritten by
/// the states it reports").
///
/// The scheduler forms the batches: every round, each scene with a tick in progress contributes
/// its own σ rows (its planner, its phase); the others hold still. Each scene draws its noise
/// from its own random stream, so its samples do not depend on which scenes share its batches.
pub struct RolloutDriver {
    n: usize,
    w: usize,
    a_max: usize,
    obs_noise: f32,
    sigma_max: f32,
    states: Vec<SceneState>,
    rngs: Vec<StdRng>,
    sched: Scheduler,
    ids: Vec<road_sched::SceneId>,
    /// Scheduler slot index → scene.
    scene_of_slot: Vec<usize>,
    planners: Vec<PlannerSpec>,
    /// Model evaluations per scene under planners switched away from.
    nfe_before: Vec<u64>,
    outcomes: Vec<TickOutcome>,
    /// Scenes whose host window must go to the engine when their next stage starts (new or
    /// rebuilt windows); otherwise the engine's window is the newer one.
    needs_load: Vec<bool>,
    emitted: Vec<f32>,              // [B, A, 3] read back each tick
    emit_slots: Vec<Option<usize>>, // [B]
    sigma_cur: Vec<f32>,            // [B, W]
    sigma_next: Vec<f32>,           // [B, W]
    ticks: Vec<usize>,
    switches: usize,
}

impl std::fmt::Debug for RolloutDriver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RolloutDriver")
            .field("scenes", &self.states.len())
            .field("window_slots", &self.w)
            .field("ticks", &self.ticks)
            .finish_non_exhaustive()
    }
}

/// σ of a slot that holds still in a batch (any positive value: σ_cur = σ_next skips it).
const IDLE_SIGMA: f32 = 1.0;

impl RolloutDriver {
    /// Prepares `engine` with the scenes' static inputs, builds and loads every first window.
    /// `rng` seeds the scenes' own noise streams; `steps_hint` only sizes buffers.
    pub fn new(
        engine: &mut dyn StepEngine,
        planner: &PlannerSpec,
        scenes: &[RolloutScene],
        steps_hint: usize,
        rng: &mut StdRng,
    ) -> Result<Self> {
        let n = planner.obs_slots;
        let w = planner.window_slots();
        if w != engine.window_slots() {
            return Err(Error::data(format!(
                "planner window {w} ≠ model window {}",
                engine.window_slots()
            )));
        }
        if scenes.is_empty() {
            return Err(Error::data("a rollout needs at least one scene".into()));
        }
        let b = scenes.len();
        let a_max = scenes
            .iter()
            .map(|s| s.history.agents)
            .max()
            .unwrap_or(1)
            .max(1);
        let p_max = scenes
            .iter()
            .map(|s| s.history.polylines)
            .max()
            .unwrap_or(1)
            .max(1);
        let q = scenes[0].history.points;
        let sigma_max = planner.edm.sigma_max as f32;
        // The noise added to observations (the σ rows tell the model `obs_sigma`).
        let obs_noise = planner.obs_noise() as f32;

        // Static inputs, once: agent features and the map.
        let mut feats = vec![0.0f32; b * a_max * AGENT_FEATURES];
        let mut map = vec![0.0f32; b * p_max * q * 2];
        let mut map_valid = vec![0.0f32; b * p_max];
        for (i, s) in scenes.iter().enumerate() {
            let h = &s.history;
            if h.slots < n {
                return Err(Error::data(format!(
                    "scene {i}: {} history steps, the planner observes {n}",
                    h.slots
                )));
            }
            if h.points != q {
                return Err(Error::data(format!(
                    "scene {i}: {} points per polyline, scene 0 has {q}",
                    h.points
                )));
            }
            feats[i * a_max * AGENT_FEATURES..][..h.agents * AGENT_FEATURES]
                .copy_from_slice(&h.agent_features);
            map[i * p_max * q * 2..][..h.polylines * q * 2].copy_from_slice(&h.map);
            map_valid[i * p_max..][..h.polylines].fill(1.0);
        }
        engine.prepare(b, a_max, &feats, p_max, &map, &map_valid)?;

        let base_seed = rng.next_u64();
        let mut rngs: Vec<StdRng> = (0..b)
            .map(|i| {
                StdRng::seed_from_u64(
                    base_seed ^ (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
                )
            })
            .collect();
        let mut states: Vec<SceneState> = scenes
            .iter()
            .map(|s| {
                let h = &s.history;
                let history = (0..h.agents)
                    .map(|a| {
                        (0..h.slots)
                            .map(|t| {
                                let k = 3 * (a * h.slots + t);
                                [h.states[k], h.states[k + 1], h.states[k + 2]]
                            })
                            .collect()
                    })
                    .collect();
                let history_valid = (0..h.agents)
                    .map(|a| h.valid[a * h.slots..(a + 1) * h.slots].to_vec())
                    .collect();
                SceneState {
                    agents: h.agents,
                    window: vec![0.0; a_max * w * 3],
                    valid: vec![0.0; a_max * w],
                    history,
                    history_valid,
                    emitted: Vec::with_capacity(h.agents * steps_hint * 3),
                }
            })
            .collect();
        for (s, r) in states.iter_mut().zip(&mut rngs) {
            rebuild_window(s, n, w, obs_noise, sigma_max, r);
        }
        let packed: Vec<f32> = states
            .iter()
            .flat_map(|s| s.window.iter().copied())
            .collect();
        let packed_valid: Vec<f32> = states
            .iter()
            .flat_map(|s| s.valid.iter().copied())
            .collect();
        engine.load(&packed, &packed_valid)?;

        let mut sched = Scheduler::with_capacity(b);
        let pid = sched.add_planner("rollout", planner.clone())?;
        let ids = (0..b)
            .map(|_| {
                sched.admit(SceneSpec {
                    planner: pid,
                    external_agents: vec![],
                })
            })
            .collect::<road_sched::Result<Vec<_>>>()?;
        let mut scene_of_slot = vec![usize::MAX; b];
        for (i, id) in ids.iter().enumerate() {
            if id.index() >= scene_of_slot.len() {
                scene_of_slot.resize(id.index() + 1, usize::MAX);
            }
            scene_of_slot[id.index()] = i;
        }
        Ok(Self {
            n,
            w,
            a_max,
            obs_noise,
            sigma_max,
            states,
            rngs,
            sched,
            ids,
            scene_of_slot,
            planners: vec![planner.clone(); b],
            nfe_before: vec![0; b],
            outcomes: Vec::with_capacity(b),
            needs_load: vec![false; b],
            emitted: vec![0.0; b * a_max * 3],
            emit_slots: vec![None; b],
            sigma_cur: vec![IDLE_SIGMA; b * w],
            sigma_next: vec![IDLE_SIGMA; b * w],
            ticks: vec![0; b],
            switches: 0,
        })
    }

    /// Scenes in the rollout.
    pub fn scenes(&self) -> usize {
        self.states.len()
    }

    /// Agents of scene `scene`.
    pub fn agents(&self, scene: usize) -> usize {
        self.states[scene].agents
    }

    /// Simulated steps of scene 0 so far (every scene's, when all tick together).
    pub fn ticks(&self) -> usize {
        self.ticks[0]
    }

    /// Simulated steps of one scene so far.
    pub fn scene_ticks(&self, scene: usize) -> usize {
        self.ticks[scene]
    }

    /// The planner scene 0's next tick uses.
    pub fn planner(&self) -> &PlannerSpec {
        &self.planners[0]
    }

    /// Switches every scene to `planner`; see [`Self::switch_scene_planner`].
    pub fn switch_planner(&mut self, planner: &PlannerSpec) -> Result<()> {
        for scene in 0..self.states.len() {
            self.switch_scene_planner(scene, planner)?;
        }
        Ok(())
    }

    /// Switches one scene to `planner` from its next tick on. It must run on the same model:
    /// the same window (W) and observations (n). The window is rebuilt from the history (the
    /// last n states, emitted or overwritten) with fresh noise, so the new planner starts with
    /// its warm-up, as a newly admitted scene does, while other scenes go on where they are.
    pub fn switch_scene_planner(&mut self, scene: usize, planner: &PlannerSpec) -> Result<()> {
        if planner.window_slots() != self.w || planner.obs_slots != self.n {
            return Err(Error::data(format!(
                "cannot switch to a planner with W = {} and n = {}: the model runs W = {}, n = {}",
                planner.window_slots(),
                planner.obs_slots,
                self.w,
                self.n
            )));
        }
        let old = self.ids.get(scene).copied().ok_or_else(|| {
            Error::data(format!("scene {scene}: the rollout has {}", self.ids.len()))
        })?;
        self.switches += 1;
        let pid = self
            .sched
            .add_planner(&format!("rollout-{}", self.switches), planner.clone())?;
        let stats = self.sched.retire(old)?;
        self.nfe_before[scene] += stats.nfe;
        self.scene_of_slot[old.index()] = usize::MAX;
        let id = self.sched.admit(SceneSpec {
            planner: pid,
            external_agents: vec![],
        })?;
        if id.index() >= self.scene_of_slot.len() {
            self.scene_of_slot.resize(id.index() + 1, usize::MAX);
        }
        self.scene_of_slot[id.index()] = scene;
        self.ids[scene] = id;
        self.needs_load[scene] = true;
        rebuild_window(
            &mut self.states[scene],
            self.n,
            self.w,
            self.obs_noise,
            self.sigma_max,
            &mut self.rngs[scene],
        );
        self.planners[scene] = planner.clone();
        Ok(())
    }

    /// One simulated step of every scene; see [`Self::tick_scenes`].
    pub fn tick(
        &mut self,
        engine: &mut dyn StepEngine,
        overrides: &mut dyn FnMut(usize, &mut [f32]) -> Result<()>,
    ) -> Result<()> {
        let all: Vec<usize> = (0..self.states.len()).collect();
        self.tick_scenes(engine, &all, overrides)
    }

    /// One simulated step of the given scenes, batched on `engine` whatever their planners and
    /// phases. `overrides(scene, emitted)` is called once per ticked scene with the states the
    /// model emitted, `[agents·3]` in model units, and may overwrite the agents it drives before
    /// they join the observations.
    pub fn tick_scenes(
        &mut self,
        engine: &mut dyn StepEngine,
        scenes: &[usize],
        overrides: &mut dyn FnMut(usize, &mut [f32]) -> Result<()>,
    ) -> Result<()> {
        let b = self.states.len();
        let (n, w, a_max) = (self.n, self.w, self.a_max);
        for &i in scenes {
            let id = *self
                .ids
                .get(i)
                .ok_or_else(|| Error::data(format!("scene {i}: the rollout has {b}")))?;
            self.sched.request_tick(id)?;
        }
        while self.sched.next_batch(b)? > 0 {
            let mut second_evaluation = false;
            for item in self.sched.batch() {
                let i = self.scene_of_slot[item.scene.index()];
                let plan = self.sched.step_plan(item);
                if item.stage_start && self.needs_load[i] {
                    let s = &self.states[i];
                    engine.load_scene(i, &s.window, &s.valid)?;
                    self.needs_load[i] = false;
                }
                self.sigma_cur[i * w..(i + 1) * w].copy_from_slice(plan.sigma_cur);
                self.sigma_next[i * w..(i + 1) * w].copy_from_slice(plan.sigma_next);
                second_evaluation |= plan.nfe == 2;
            }
            engine.step(&self.sigma_cur, &self.sigma_next, second_evaluation)?;
            // The batch's scenes hold still in later rounds unless they are in them again.
            for item in self.sched.batch() {
                let i = self.scene_of_slot[item.scene.index()];
                self.sigma_cur[i * w..(i + 1) * w].fill(IDLE_SIGMA);
                self.sigma_next[i * w..(i + 1) * w].fill(IDLE_SIGMA);
            }
            self.sched.complete_batch();
        }
        self.outcomes.clear();
        self.sched.take_outcomes(&mut self.outcomes);
        if self.outcomes.len() != scenes.len() {
            return Err(Error::data(format!(
                "{} of {} ticked scenes emitted a state",
                self.outcomes.len(),
                scenes.len()
            )));
        }
        // The tick's only readback: each ticked scene's emitted slot.
        self.emit_slots.fill(None);
        for o in &self.outcomes {
            let i = self.scene_of_slot[o.scene.index()];
            self.emit_slots[i] = Some(n + o.emit_future_slot);
        }
        engine.read_emitted(&self.emit_slots, &mut self.emitted)?;
        let shape = ShiftShape {
            observed: n,
            obs_noise: self.obs_noise,
            sigma_max: self.sigma_max,
        };
        // (scene, emitted [agents·3], noise [agents·6]) of the scenes that shift.
        let mut shifts: Vec<(usize, Vec<f32>, Vec<f32>)> = Vec::new();
        for o in &self.outcomes {
            let i = self.scene_of_slot[o.scene.index()];
            let s = &mut self.states[i];
            let mut emitted = self.emitted[i * a_max * 3..][..s.agents * 3].to_vec();
            overrides(i, &mut emitted)?;
            for a in 0..s.agents {
                s.history[a].push([emitted[3 * a], emitted[3 * a + 1], emitted[3 * a + 2]]);
                s.history_valid[a].push(true);
            }
            s.emitted.extend_from_slice(&emitted);
            let rng = &mut self.rngs[i];
            match o.then {
                WindowUpdate::Shift => {
                    let noise = normal_vec(rng, s.agents * 6);
                    // Validity moves with the slots; the joining observation and the new slot
                    // are valid.
                    for a in 0..s.agents {
                        let row = a * w;
                        s.valid.copy_within(row + 1..row + w, row);
                        s.valid[row + n - 1] = 1.0;
                        s.valid[row + w - 1] = 1.0;
                    }
                    shifts.push((i, emitted, noise));
                }
                WindowUpdate::Rebuild => {
                    rebuild_window(s, n, w, self.obs_noise, self.sigma_max, rng);
                    self.needs_load[i] = true;
                }
                WindowUpdate::Hold | WindowUpdate::Exhausted => {}
            }
            self.ticks[i] += 1;
        }
        if !shifts.is_empty() {
            let edits: Vec<ShiftEdit<'_>> = shifts
                .iter()
                .map(|(i, emitted, noise)| ShiftEdit {
                    scene: *i,
                    emitted,
                    noise,
                    valid: &self.states[*i].valid,
                })
                .collect();
            engine.shift(&edits, shape)?;
        }
        Ok(())
    }

    /// Model evaluations of scene 0 so far (every scene's, when all tick together).
    pub fn nfe(&self) -> Result<u64> {
        self.scene_nfe(0)
    }

    /// Model evaluations of one scene so far.
    pub fn scene_nfe(&self, scene: usize) -> Result<u64> {
        Ok(self.nfe_before[scene] + self.sched.stats(self.ids[scene])?.nfe)
    }

    /// The emitted states of every scene, `[scenes][agents, ticks, 3]` in model units. Every
    /// scene must have ticked equally often.
    pub fn into_rollout(self) -> Result<Rollout> {
        let nfe = self.nfe()?;
        let steps = self.ticks[0];
        if self.ticks.iter().any(|&t| t != steps) {
            return Err(Error::data(format!(
                "scenes ticked unequally ({:?}): no common rollout",
                self.ticks
            )));
        }
        Ok(Rollout {
            agents: self.states.iter().map(|s| s.agents).collect(),
            steps,
            states: self
                .states
                .into_iter()
                .map(|s| {
                    // [steps, agents, 3] → [agents, steps, 3]
                    let mut out = vec![0.0; s.agents * steps * 3];
                    for t in 0..steps {
                        for a in 0..s.agents {
                            out[3 * (a * steps + t)..][..3]
                                .copy_from_slice(&s.emitted[3 * (t * s.agents + a)..][..3]);
                        }
                    }
                    out
                })
                .collect(),
            nfe,
        })
    }
}

/// Window from the newest `n` history states (observations plus `obs_noise` · N(0, 1)) and
/// pure noise.
fn rebuild_window(
    s: &mut SceneState,
    n: usize,
    w: usize,
    obs_noise: f32,
    sigma_max: f32,
    rng: &mut StdRng,
) {
    let noise = normal_vec(rng, s.agents * w * 3);
    s.window.fill(0.0);
    s.valid.fill(0.0);
    for a in 0..s.agents {
        let len = s.history[a].len();
        for slot in 0..w {
            let k = a * w + slot;
            if slot < n {
                let t = len - n + slot;
                if s.history_valid[a][t] {
                    for d in 0..3 {
                        s.window[3 * k + d] = s.history[a][t][d] + obs_noise * noise[3 * k + d];
                    }
                    s.valid[k] = 1.0;
                }
            } else {
                for d in 0..3 {
                    s.window[3 * k + d] = sigma_max * noise[3 * k + d];
                }
                s.valid[k] = 1.0;
            }
        }
    }
}

impl From<road_sched::Error> for Error {
    fn from(e: road_sched::Error) -> Self {
        Error::data(format!("scheduler: {e}"))
    }
}
