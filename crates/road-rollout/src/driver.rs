//! The rollout driver: tick-by-tick rollouts of many scenes batched on one engine. The
//! open-loop [`crate::rollout_with`] and the closed loop of `road-sim` run on it, where
//! agents the model does not drive overwrite their emitted states every tick (math doc: "In
//! closed loop the ego agent's slots are overwritten by the states it reports").
//!
//! The scheduler forms the batches: every round, each scene with a tick in progress contributes
//! its own σ rows (its planner, its phase); the others hold still. Each scene draws its noise
//! from its own random stream, so its samples do not depend on which scenes share its batches.
//!
//! Two ways to use it: a fixed set of scenes ([`RolloutDriver::new`], then
//! [`RolloutDriver::tick`] until done), or a pool ([`RolloutDriver::with_capacity`]) that scenes
//! join ([`RolloutDriver::add_scene`]) and leave ([`RolloutDriver::remove_scene`]) while the
//! others run, stepped one scheduler round at a time ([`RolloutDriver::round`]) so that a scene
//! in its warm-up never holds up a scene whose tick needs fewer rounds (a server's continuous
//! batching).

use rand::rngs::StdRng;
use rand::{RngCore, SeedableRng};
use road_sched::{
    PlannerId, PlannerSpec, Sampler, SceneId, SceneSpec, Scheduler, TickOutcome, WindowUpdate,
};

use road_model::batch::{AGENT_FEATURES, normal_vec};
use road_model::{Error, Result};
use road_planner::smoothing::{
    align_heading_to_course, limit_turn_to_radius, smooth_accelerations, smooth_with_plan,
    track_least_jerk,
};

use crate::engine::{Rollout, RolloutScene, StepEngine};
use crate::window::{ShiftEdit, ShiftShape};

/// The caller's hook at each scene's emission, `overrides(scene, emitted, plan_turns)`: called
/// once per ticked scene with the states the model emitted, `emitted [agents·3]` in model
/// units; it may overwrite the agents it drives before they join the observations, and where
/// it corrects an agent's state it may turn that agent's plan with it (`plan_turns
/// [agents·4]`, zeros on entry: [`ShiftEdit::turns`]), so that the window's future slots go
/// on from the corrected state.
pub type Overrides<'a> = dyn FnMut(usize, &mut [f32], &mut [f32]) -> Result<()> + 'a;

/// A scene's window shift, gathered while its emission is handled ([`ShiftEdit`] owned).
struct PendingShift {
    scene: usize,
    emitted: Vec<f32>, // [agents, 3]
    noise: Vec<f32>,   // [agents, 6]
    turns: Vec<f32>,   // [agents, 4], or empty: no plan turns
}

/// Per-scene state in model units. The window lives in the engine; `window` is the host copy
/// built from the history when the window is (re)built, `valid` the window's current validity.
/// A free slot of a pool has no agents.
struct SceneState {
    agents: usize,
    window: Vec<f32>, // [A_max, W, 3]
    valid: Vec<f32>,  // [A_max, W]
    /// Every state so far: observed history then emitted, `[agents][t] → [3]`.
    history: Vec<Vec<[f32; 3]>>,
    history_valid: Vec<Vec<bool>>,
    emitted: Vec<f32>, // [agents, steps, 3]
    /// Whether each tick keeps the model's plan (the denoiser's estimate of the window's
    /// slots after the emitted one).
    wants_plan: bool,
    /// The last tick's plan `[agents, plan_steps, 3]` (model units) when `wants_plan`.
    plan: Vec<f32>,
    plan_steps: usize,
    /// Agents that left the scene ([`RolloutDriver::retire_agent`]): no slot of theirs is
    /// valid from their retirement on, so the engines treat them as padding.
    retired: Vec<bool>,
    /// The scene's static rows as the engine holds them (features `[A_max, 6]`, map, its
    /// flags), kept for agents that join later ([`RolloutDriver::admit_agent`]).
    static_rows: (Vec<f32>, Vec<f32>, Vec<f32>),
}

impl SceneState {
    fn free(a_max: usize, w: usize) -> Self {
        Self {
            agents: 0,
            window: vec![0.0; a_max * w * 3],
            valid: vec![0.0; a_max * w],
            history: Vec::new(),
            history_valid: Vec::new(),
            emitted: Vec::new(),
            wants_plan: false,
            plan: Vec::new(),
            plan_steps: 0,
            retired: Vec::new(),
            static_rows: (Vec::new(), Vec::new(), Vec::new()),
        }
    }

    fn of(scene: &RolloutScene, a_max: usize, w: usize, steps_hint: usize) -> Self {
        let h = &scene.history;
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
        Self {
            agents: h.agents,
            window: vec![0.0; a_max * w * 3],
            valid: vec![0.0; a_max * w],
            history,
            history_valid,
            emitted: Vec::with_capacity(h.agents * steps_hint * 3),
            wants_plan: false,
            plan: Vec::new(),
            plan_steps: 0,
            retired: vec![false; h.agents],
            static_rows: (Vec::new(), Vec::new(), Vec::new()),
        }
    }
}

/// The seed of scene `i`'s noise stream in a driver seeded with `base_seed`.
fn scene_seed(base_seed: u64, i: usize) -> u64 {
    base_seed ^ (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

/// Seeds of `scenes` noise streams drawn from `rng` as [`RolloutDriver::new`] draws them: a
/// scene's stream then depends on its position in the batch and on what `rng` gave before.
pub fn batch_seeds(rng: &mut StdRng, scenes: usize) -> Vec<u64> {
    let base_seed = rng.next_u64();
    (0..scenes).map(|i| scene_seed(base_seed, i)).collect()
}

/// The seed of the noise stream named `stream` in a run seeded `run_seed`: callers that name a
/// stream by what it samples (a scene of the dataset, then a sample of it) get the same samples
/// for it whatever shares its batch, its position there and the batch size. SplitMix64's
/// finaliser over both, so that neighbouring names give unrelated seeds.
pub fn stream_seed(run_seed: u64, stream: u64) -> u64 {
    fn mix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    mix(run_seed ^ mix(stream))
}

/// One emitting scene of a round: its batch row, the first window slot after the emitted one
/// (before the window moves on), and its plan's place among the round's read plans.
struct PlanJob {
    scene: usize,
    from: usize,
    plan: Option<usize>,
    then: WindowUpdate,
}

/// The planner's work on one scene's `emitted` states `[agents, 3]` (model units): smoothing
/// against the model's plan `denoised` (`[A, W, 3]`; empty when not read), least-jerk tracking
/// with its turning circle and heading along the course, acceleration smoothing. Reads only
/// the scene and its planner, so that a round's scenes can be planned on several threads.
/// `scales`: the engine's metres per position unit and units per radian of heading.
fn plan_emitted(
    s: &SceneState,
    planner: &PlannerSpec,
    denoised: &[f32],
    w: usize,
    from: usize,
    (position_scale_m, heading_scale): (Option<f64>, Option<f64>),
    emitted: &mut [f32],
) {
    if let Some(fit) = planner.plan_smoothing_fit() {
        smooth_with_plan(
            &s.history,
            &s.history_valid,
            denoised,
            &s.valid,
            w,
            from,
            fit,
            emitted,
        );
    }
    if let Some(tracking) = planner.jerk_tracking {
        // m/s² → position units per step², where the engine knows the unit.
        let max_acceleration = tracking
            .max_acceleration_mps2
            .zip(position_scale_m)
            .map(|(bound, scale_m)| bound * STEP_SECS * STEP_SECS / scale_m);
        track_least_jerk(
            &s.history,
            &s.history_valid,
            denoised,
            &s.valid,
            w,
            from,
            tracking.ahead,
            tracking.jerk_weight(STEP_SECS),
            max_acceleration,
            heading_scale,
            tracking.max_slip_deg.map(|deg| deg.to_radians().tan()),
            emitted,
        );
        // The turning circle first: slow steps keep it; from 2 m/s the heading then
        // follows the course (a car's body follows its wheels) and does not slide.
        if let (Some(radius_m), Some(scale), Some(scale_m)) =
            (tracking.min_turn_radius_m, heading_scale, position_scale_m)
        {
            limit_turn_to_radius(
                &s.history,
                &s.history_valid,
                emitted,
                scale,
                radius_m / scale_m,
            );
        }
        if let (Some(offset_deg), Some(scale), Some(scale_m)) = (
            tracking.max_course_offset_deg,
            heading_scale,
            position_scale_m,
        ) {
            let min_step = road_sched::COURSE_MIN_SPEED_MPS * STEP_SECS / scale_m;
            align_heading_to_course(
                &s.history,
                &s.history_valid,
                emitted,
                scale,
                min_step,
                offset_deg.to_radians(),
            );
        }
    }
    if let Some(alpha) = planner.acceleration_smoothing {
        // External agents' states replace theirs just below.
        smooth_accelerations(&s.history, &s.history_valid, emitted, alpha as f32);
    }
}

/// σ of a slot that holds still in a batch (any positive value: σ_cur = σ_next skips it).
const IDLE_SIGMA: f32 = 1.0;
/// Seconds per simulated step (the recordings' 10 Hz): the unit of least-jerk tracking's jerk.
const STEP_SECS: f64 = 0.1;
/// Scenes a planner thread takes at least: below twice this a round's planning stays on the
/// driver's thread (a thread's start costs about what planning 5 scenes does).
const SCENES_PER_PLANNER_THREAD: usize = 64;

/// Drives the rollouts of many scenes on one engine; see the module's documentation.
pub struct RolloutDriver {
    n: usize,
    w: usize,
    a_max: usize,
    p_max: usize,
    points: usize,
    obs_noise: f32,
    sigma_max: f32,
    /// One per batch row (scene slot).
    states: Vec<SceneState>,
    rngs: Vec<StdRng>,
    sched: Scheduler,
    /// The scheduler's id of the scene in each slot (`None`: a free slot of a pool).
    ids: Vec<Option<SceneId>>,
    /// Free slots of a pool, the lowest last.
    free: Vec<usize>,
    /// Scheduler slot index → scene.
    scene_of_slot: Vec<usize>,
    planners: Vec<PlannerSpec>,
    /// Planners known to the scheduler, so that scenes joining under one share its tables.
    registered: Vec<(PlannerSpec, PlannerId)>,
    /// Model evaluations per scene under planners switched away from.
    nfe_before: Vec<u64>,
    outcomes: Vec<TickOutcome>,
    /// Scenes whose host window must go to the engine when their next stage starts (new or
    /// rebuilt windows); otherwise the engine's window is the newer one.
    needs_load: Vec<bool>,
    /// Scenes with a tick requested and not yet emitted.
    in_tick: Vec<bool>,
    emitted: Vec<f32>,  // [B, A, 3] read back each tick
    denoised: Vec<f32>, // [scenes, A, W, 3]: the estimates of `denoised_scenes`, read on request
    denoised_scenes: Vec<usize>,
    /// `[agents, 4]`: the emission hook's plan turns of the scene emitting, reused.
    plan_turns: Vec<f32>,
    emit_slots: Vec<Option<usize>>, // [B]
    sigma_cur: Vec<f32>,            // [B, W]: the round's Heun scenes
    sigma_next: Vec<f32>,           // [B, W]
    /// The round's multistep scenes: σ rows and γ `[B, W]` each.
    multistep_sigma_cur: Vec<f32>,
    multistep_sigma_next: Vec<f32>,
    gamma: Vec<f32>,
    /// `[B, W]`: the σ each slot's kept estimate in the engine was made at (0: none), moved
    /// with the window as the engine moves the estimate: the multistep sampler's memory.
    estimate_sigma: Vec<f32>,
    ticks: Vec<usize>,
    /// Threads a round's planning may use, and scenes each takes at least
    /// ([`RolloutDriver::set_planner_threads`]).
    planner_threads: (usize, usize),
}

impl std::fmt::Debug for RolloutDriver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RolloutDriver")
            .field("scenes", &self.live_scenes())
            .field("slots", &self.states.len())
            .field("window_slots", &self.w)
            .field("ticks", &self.ticks)
            .finish_non_exhaustive()
    }
}

impl RolloutDriver {
    /// Prepares `engine` with the scenes' static inputs, builds and loads every first window.
    /// `rng` seeds the scenes' own noise streams ([`batch_seeds`]); `steps_hint` only sizes
    /// buffers.
    pub fn new(
        engine: &mut dyn StepEngine,
        planner: &PlannerSpec,
        scenes: &[RolloutScene],
        steps_hint: usize,
        rng: &mut StdRng,
    ) -> Result<Self> {
        let seeds = batch_seeds(rng, scenes.len());
        Self::with_seeds(engine, planner, scenes, &seeds, steps_hint)
    }

    /// [`Self::new`] with each scene's noise stream seeded by the caller (`seeds[i]` for scene
    /// `i`, [`stream_seed`] for seeds that do not depend on the batch): a scene samples what it
    /// would sample alone with its seed.
    pub fn with_seeds(
        engine: &mut dyn StepEngine,
        planner: &PlannerSpec,
        scenes: &[RolloutScene],
        seeds: &[u64],
        steps_hint: usize,
    ) -> Result<Self> {
        if scenes.is_empty() {
            return Err(Error::data("a rollout needs at least one scene".into()));
        }
        if seeds.len() != scenes.len() {
            return Err(Error::data(format!(
                "{} noise seeds for {} scenes",
                seeds.len(),
                scenes.len()
            )));
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
        let mut driver = Self::empty(engine, planner, b, a_max, p_max, q)?;
        // Static inputs, once: agent features and the map.
        let mut feats = vec![0.0f32; b * a_max * AGENT_FEATURES];
        let mut map = vec![0.0f32; b * p_max * q * 2];
        let mut map_valid = vec![0.0f32; b * p_max];
        for (i, s) in scenes.iter().enumerate() {
            driver.check_scene(i, s, planner)?;
            let (f, m, v) = driver.static_rows(s);
            feats[i * a_max * AGENT_FEATURES..][..a_max * AGENT_FEATURES].copy_from_slice(&f);
            map[i * p_max * q * 2..][..p_max * q * 2].copy_from_slice(&m);
            map_valid[i * p_max..][..p_max].copy_from_slice(&v);
        }
        engine.prepare(b, a_max, &feats, p_max, &map, &map_valid)?;

        for (i, (s, &seed)) in scenes.iter().zip(seeds).enumerate() {
            driver.insert(i, s, planner, seed, steps_hint)?;
        }
        driver.free.clear();
        let packed: Vec<f32> = driver
            .states
            .iter()
            .flat_map(|s| s.window.iter().copied())
            .collect();
        let packed_valid: Vec<f32> = driver
            .states
            .iter()
            .flat_map(|s| s.valid.iter().copied())
            .collect();
        engine.load(&packed, &packed_valid)?;
        driver.needs_load.fill(false);
        Ok(driver)
    }

    /// An empty pool of `capacity` scene slots on `engine`, for scenes of at most `agents`
    /// agents and `polylines` map polylines of `points` points each, under planners with
    /// `planner`'s window, observations and noise (`obs_noise`, σ_max): scenes join with
    /// [`Self::add_scene`]. Padding costs the CPU engines nothing (rows without a valid slot
    /// are skipped, and so are scenes that hold still).
    pub fn with_capacity(
        engine: &mut dyn StepEngine,
        planner: &PlannerSpec,
        capacity: usize,
        agents: usize,
        polylines: usize,
        points: usize,
    ) -> Result<Self> {
        if capacity == 0 || agents == 0 || polylines == 0 || points == 0 {
            return Err(Error::data(format!(
                "a pool needs room: {capacity} scenes × {agents} agents × {polylines} polylines × \
                 {points} points"
            )));
        }
        let mut driver = Self::empty(engine, planner, capacity, agents, polylines, points)?;
        engine.prepare(
            capacity,
            agents,
            &vec![0.0; capacity * agents * AGENT_FEATURES],
            polylines,
            &vec![0.0; capacity * polylines * points * 2],
            &vec![0.0; capacity * polylines],
        )?;
        let (w, a) = (driver.w, agents);
        engine.load(
            &vec![0.0; capacity * a * w * 3],
            &vec![0.0; capacity * a * w],
        )?;
        driver.free = (0..capacity).rev().collect();
        Ok(driver)
    }

    /// The driver's fields for `b` free slots.
    fn empty(
        engine: &dyn StepEngine,
        planner: &PlannerSpec,
        b: usize,
        a_max: usize,
        p_max: usize,
        points: usize,
    ) -> Result<Self> {
        let n = planner.obs_slots;
        let w = planner.window_slots();
        if w != engine.window_slots() {
            return Err(Error::data(format!(
                "planner window {w} ≠ model window {}",
                engine.window_slots()
            )));
        }
        Ok(Self {
            n,
            w,
            a_max,
            p_max,
            points,
            // The noise added to observations (the σ rows tell the model `obs_sigma`).
            obs_noise: planner.obs_noise() as f32,
            sigma_max: planner.edm.sigma_max as f32,
            states: (0..b).map(|_| SceneState::free(a_max, w)).collect(),
            rngs: (0..b).map(|i| StdRng::seed_from_u64(i as u64)).collect(),
            sched: Scheduler::with_capacity(b),
            ids: vec![None; b],
            free: Vec::new(),
            scene_of_slot: vec![usize::MAX; b],
            planners: vec![planner.clone(); b],
            registered: Vec::new(),
            nfe_before: vec![0; b],
            outcomes: Vec::with_capacity(b),
            needs_load: vec![false; b],
            in_tick: vec![false; b],
            emitted: vec![0.0; b * a_max * 3],
            denoised: Vec::new(),
            denoised_scenes: Vec::new(),
            plan_turns: Vec::new(),
            emit_slots: vec![None; b],
            sigma_cur: vec![IDLE_SIGMA; b * w],
            sigma_next: vec![IDLE_SIGMA; b * w],
            multistep_sigma_cur: vec![IDLE_SIGMA; b * w],
            multistep_sigma_next: vec![IDLE_SIGMA; b * w],
            gamma: vec![0.0; b * w],
            estimate_sigma: vec![0.0; b * w],
            ticks: vec![0; b],
            planner_threads: (
                std::thread::available_parallelism().map_or(1, |n| n.get()),
                SCENES_PER_PLANNER_THREAD,
            ),
        })
    }

    /// Up to `threads` threads for a round's planning (smoothing and least-jerk tracking of
    /// each scene's emitted states), each taking at least `min_scenes` scenes; by default
    /// every core, from 2 × [`SCENES_PER_PLANNER_THREAD`] scenes. Results do not depend on it.
    pub fn set_planner_threads(&mut self, threads: usize, min_scenes: usize) {
        self.planner_threads = (threads.max(1), min_scenes.max(1));
    }

    /// Whether `scene` (batch row `i`) fits the driver under `planner`.
    fn check_scene(&self, i: usize, scene: &RolloutScene, planner: &PlannerSpec) -> Result<()> {
        let h = &scene.history;
        if planner.window_slots() != self.w || planner.obs_slots != self.n {
            return Err(Error::data(format!(
                "scene {i}: planner with W = {} and n = {}; the model runs W = {}, n = {}",
                planner.window_slots(),
                planner.obs_slots,
                self.w,
                self.n
            )));
        }
        if planner.obs_noise() as f32 != self.obs_noise
            || planner.edm.sigma_max as f32 != self.sigma_max
        {
            return Err(Error::data(format!(
                "scene {i}: planner with observation noise {} and σ_max {}; the batch's are {} \
                 and {}",
                planner.obs_noise(),
                planner.edm.sigma_max,
                self.obs_noise,
                self.sigma_max
            )));
        }
        if h.slots < self.n {
            return Err(Error::data(format!(
                "scene {i}: {} history steps, the planner observes {}",
                h.slots, self.n
            )));
        }
        if h.points != self.points {
            return Err(Error::data(format!(
                "scene {i}: {} points per polyline, the batch has {}",
                h.points, self.points
            )));
        }
        if h.agents > self.a_max || h.polylines > self.p_max {
            return Err(Error::data(format!(
                "scene {i}: {} agents and {} polylines; the batch takes at most {} agents and \
                 {} polylines",
                h.agents, h.polylines, self.a_max, self.p_max
            )));
        }
        Ok(())
    }

    /// One scene's static rows padded to the batch: features `[A, 6]`, map `[P, Q, 2]` and
    /// its flags `[P]`.
    fn static_rows(&self, scene: &RolloutScene) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let h = &scene.history;
        let mut feats = vec![0.0f32; self.a_max * AGENT_FEATURES];
        let mut map = vec![0.0f32; self.p_max * self.points * 2];
        let mut map_valid = vec![0.0f32; self.p_max];
        feats[..h.agents * AGENT_FEATURES].copy_from_slice(&h.agent_features);
        map[..h.polylines * self.points * 2].copy_from_slice(&h.map);
        map_valid[..h.polylines].fill(1.0);
        (feats, map, map_valid)
    }

    /// The scheduler's planner for `planner`, registered on first use.
    fn planner_id(&mut self, planner: &PlannerSpec) -> Result<PlannerId> {
        if let Some((_, id)) = self.registered.iter().find(|(p, _)| p == planner) {
            return Ok(*id);
        }
        let name = format!("planner-{}", self.registered.len());
        let id = self.sched.add_planner(&name, planner.clone())?;
        self.registered.push((planner.clone(), id));
        Ok(id)
    }

    /// Admits slot `i`'s scene to the scheduler under `planner`.
    fn admit(&mut self, i: usize, planner: PlannerId) -> Result<()> {
        let id = self.sched.admit(SceneSpec {
            planner,
            external_agents: vec![],
        })?;
        if id.index() >= self.scene_of_slot.len() {
            self.scene_of_slot.resize(id.index() + 1, usize::MAX);
        }
        self.scene_of_slot[id.index()] = i;
        self.ids[i] = Some(id);
        Ok(())
    }

    /// Puts `scene` in slot `i`: host state, first window (to be loaded), scheduler entry.
    fn insert(
        &mut self,
        i: usize,
        scene: &RolloutScene,
        planner: &PlannerSpec,
        seed: u64,
        steps_hint: usize,
    ) -> Result<()> {
        let pid = self.planner_id(planner)?;
        self.admit(i, pid)?;
        self.states[i] = SceneState::of(scene, self.a_max, self.w, steps_hint);
        self.states[i].static_rows = self.static_rows(scene);
        self.rngs[i] = StdRng::seed_from_u64(seed);
        self.planners[i] = planner.clone();
        self.rebuild(i);
        self.nfe_before[i] = 0;
        self.ticks[i] = 0;
        self.in_tick[i] = false;
        self.needs_load[i] = true;
        Ok(())
    }

    /// Adds a scene to a pool under `planner` (the pool's W, n and noise), its noise stream
    /// seeded with `seed`: its samples are those it would have alone with that seed, whatever
    /// else runs. Returns its slot, the scene's index from now on. Its first tick takes the
    /// planner's warm-up. Errors when the pool is full or the scene does not fit it.
    pub fn add_scene(
        &mut self,
        engine: &mut dyn StepEngine,
        scene: &RolloutScene,
        planner: &PlannerSpec,
        seed: u64,
    ) -> Result<usize> {
        let Some(&slot) = self.free.last() else {
            return Err(Error::data(format!(
                "the pool is full: {} scenes",
                self.states.len()
            )));
        };
        self.check_scene(slot, scene, planner)?;
        let (feats, map, map_valid) = self.static_rows(scene);
        engine.prepare_scene(slot, &feats, &map, &map_valid)?;
        self.insert(slot, scene, planner, seed, 64)?;
        self.free.pop();
        Ok(slot)
    }

    /// Removes scene `scene` from a pool (a tick in progress is dropped); its slot is free
    /// for the next scene to join.
    pub fn remove_scene(&mut self, scene: usize) -> Result<()> {
        let id = self.live_id(scene)?;
        self.sched.retire(id)?;
        self.scene_of_slot[id.index()] = usize::MAX;
        self.ids[scene] = None;
        self.in_tick[scene] = false;
        self.needs_load[scene] = false;
        self.states[scene] = SceneState::free(self.a_max, self.w);
        self.free.push(scene);
        Ok(())
    }

    fn live_id(&self, scene: usize) -> Result<SceneId> {
        self.ids.get(scene).copied().flatten().ok_or_else(|| {
            Error::data(format!(
                "scene {scene}: no such scene in the rollout ({} slots)",
                self.ids.len()
            ))
        })
    }

    /// Rebuilds scene `i`'s host window from its history with fresh noise from its stream.
    fn rebuild(&mut self, i: usize) {
        rebuild_window(
            &mut self.states[i],
            self.n,
            self.w,
            self.obs_noise,
            self.sigma_max * self.planners[i].noise_temperature() as f32,
            &mut self.rngs[i],
        );
    }

    /// Scene slots (the batch's rows); in a pool, free ones included.
    pub fn scenes(&self) -> usize {
        self.states.len()
    }

    /// Scenes in the rollout now.
    pub fn live_scenes(&self) -> usize {
        self.ids.iter().filter(|id| id.is_some()).count()
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

    /// Whether scene `scene` has a tick requested that has not emitted yet.
    pub fn tick_in_progress(&self, scene: usize) -> bool {
        self.in_tick.get(scene).copied().unwrap_or(false)
    }

    /// The planner scene 0's next tick uses.
    pub fn planner(&self) -> &PlannerSpec {
        &self.planners[0]
    }

    /// Whether scene `scene` keeps the model's plan each tick (see [`Self::plan`]); off
    /// when a scene joins.
    pub fn request_plans(&mut self, scene: usize, on: bool) -> Result<()> {
        self.live_id(scene)?;
        let s = &mut self.states[scene];
        s.wants_plan = on;
        if !on {
            s.plan.clear();
            s.plan_steps = 0;
        }
        Ok(())
    }

    /// Agent `agent` of scene `scene` has left it (driven off the map): from the next window
    /// shift on none of its slots is valid, so the engines treat it as padding and the other
    /// agents no longer attend to it. Its emitted states are meaningless from then on; the
    /// caller holds its last pose. Not undone: a scene's agents keep their indices.
    pub fn retire_agent(&mut self, scene: usize, agent: usize) -> Result<()> {
        let s = self
            .states
            .get_mut(scene)
            .ok_or_else(|| Error::data(format!("no scene {scene} to retire an agent of")))?;
        let flag = s
            .retired
            .get_mut(agent)
            .ok_or_else(|| Error::data(format!("scene {scene} has no agent {agent} to retire")))?;
        *flag = true;
        Ok(())
    }

    /// A vehicle joins scene `scene` between its ticks: `history` its observed states
    /// `[steps ≥ n][3]` (model units, oldest first; fewer steps than the scene's are taken as
    /// invalid before them), `features` its static row `[6]`. It takes the place of a retired
    /// agent when there is one (the lowest index), else a new index while the scene has fewer
    /// agents than the batch takes. Returns its index. The scene's window is rebuilt from the
    /// histories with fresh noise, so its next tick takes the planner's warm-up (the new
    /// vehicle has no plan to roll on from; the others keep their histories); the engine gets
    /// the new static row first. Errors when the scene is full or mid-tick.
    pub fn admit_agent(
        &mut self,
        engine: &mut dyn StepEngine,
        scene: usize,
        history: &[[f32; 3]],
        features: &[f32],
    ) -> Result<usize> {
        let old = self.live_id(scene)?;
        if self.in_tick[scene] {
            return Err(Error::data(format!(
                "scene {scene}: an agent cannot join during a tick"
            )));
        }
        if history.len() < self.n || features.len() != AGENT_FEATURES {
            return Err(Error::data(format!(
                "scene {scene}: a joining agent needs at least {} history steps and {AGENT_FEATURES} \
                 features, got {} and {}",
                self.n,
                history.len(),
                features.len()
            )));
        }
        let a_max = self.a_max;
        let s = &mut self.states[scene];
        let agent = match s.retired.iter().position(|&r| r) {
            Some(a) => a,
            None if s.agents < a_max => s.agents,
            None => {
                return Err(Error::data(format!(
                    "scene {scene}: no room for another agent ({a_max} and none retired)"
                )));
            }
        };
        // The engine first: if it refuses, the scene is as it was.
        let mut feats = s.static_rows.0.clone();
        feats[agent * AGENT_FEATURES..][..AGENT_FEATURES].copy_from_slice(features);
        engine.prepare_scene(scene, &feats, &s.static_rows.1, &s.static_rows.2)?;
        s.static_rows.0 = feats;
        if agent == s.agents {
            // A new index: past ticks' emitted rows get zeros for it.
            let ticks = s.emitted.len() / (3 * s.agents.max(1));
            let mut emitted = Vec::with_capacity((s.agents + 1) * (ticks + 1) * 3);
            for t in 0..ticks {
                emitted.extend_from_slice(&s.emitted[3 * t * s.agents..3 * (t + 1) * s.agents]);
                emitted.extend_from_slice(&[0.0; 3]);
            }
            s.emitted = emitted;
            s.agents += 1;
            s.history.push(Vec::new());
            s.history_valid.push(Vec::new());
            s.retired.push(false);
        }
        // The same length as the others' histories, invalid before its own.
        let len = s
            .history
            .iter()
            .enumerate()
            .filter(|&(a, _)| a != agent)
            .map(|(_, h)| h.len())
            .max()
            .unwrap_or(history.len())
            .max(history.len());
        let pad = len - history.len();
        s.history[agent] = std::iter::repeat_n([0.0; 3], pad)
            .chain(history.iter().copied())
            .collect();
        s.history_valid[agent] = std::iter::repeat_n(false, pad)
            .chain(std::iter::repeat_n(true, history.len()))
            .collect();
        s.retired[agent] = false;
        // The scene starts over in the warm-up, as after a planner switch.
        let planner = self.planners[scene].clone();
        let pid = self.planner_id(&planner)?;
        let stats = self.sched.retire(old)?;
        self.nfe_before[scene] += stats.nfe;
        self.scene_of_slot[old.index()] = usize::MAX;
        self.admit(scene, pid)?;
        self.needs_load[scene] = true;
        self.rebuild(scene);
        Ok(agent)
    }

    /// Scene `scene`'s plan after its last tick: the denoiser's last estimate of the window's
    /// slots after the emitted one, `(steps, [agents, steps, 3])` in model units (the same
    /// units as the emitted states); `None` unless requested and a tick has emitted since.
    /// With a rolling window the far slots are the least certain (their noise was highest).
    pub fn plan(&self, scene: usize) -> Option<(usize, &[f32])> {
        let s = self.states.get(scene)?;
        (s.wants_plan && s.plan_steps > 0).then_some((s.plan_steps, &s.plan[..]))
    }

    /// The planner of scene `scene` (a free slot's: the last one it had).
    pub fn scene_planner(&self, scene: usize) -> Option<&PlannerSpec> {
        self.planners.get(scene)
    }

    /// Switches every scene to `planner`; see [`Self::switch_scene_planner`].
    pub fn switch_planner(&mut self, planner: &PlannerSpec) -> Result<()> {
        for scene in 0..self.states.len() {
            if self.ids[scene].is_some() {
                self.switch_scene_planner(scene, planner)?;
            }
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
        let old = self.live_id(scene)?;
        if self.in_tick[scene] {
            return Err(Error::data(format!(
                "scene {scene}: cannot switch planners during a tick"
            )));
        }
        let pid = self.planner_id(planner)?;
        let stats = self.sched.retire(old)?;
        self.nfe_before[scene] += stats.nfe;
        self.scene_of_slot[old.index()] = usize::MAX;
        self.admit(scene, pid)?;
        self.needs_load[scene] = true;
        self.planners[scene] = planner.clone();
        self.rebuild(scene);
        Ok(())
    }

    /// One simulated step of every scene; see [`Self::tick_scenes`].
    pub fn tick(
        &mut self,
        engine: &mut dyn StepEngine,
        overrides: &mut Overrides<'_>,
    ) -> Result<()> {
        let all: Vec<usize> = (0..self.states.len())
            .filter(|&i| self.ids[i].is_some())
            .collect();
        self.tick_scenes(engine, &all, overrides)
    }

    /// One simulated step of the given scenes, batched on `engine` whatever their planners and
    /// phases: rounds until every one of them has emitted; `overrides` as in [`Overrides`].
    pub fn tick_scenes(
        &mut self,
        engine: &mut dyn StepEngine,
        scenes: &[usize],
        overrides: &mut Overrides<'_>,
    ) -> Result<()> {
        for &i in scenes {
            self.request_tick(i)?;
        }
        let mut waiting: Vec<usize> = scenes.to_vec();
        while !waiting.is_empty() {
            let idle = self.sched.pending_scenes() == 0;
            let done = self.round(engine, overrides)?;
            if idle && done.is_empty() {
                return Err(Error::data(format!(
                    "{} of {} ticked scenes emitted a state",
                    scenes.len() - waiting.len(),
                    scenes.len()
                )));
            }
            waiting.retain(|i| !done.contains(i));
        }
        Ok(())
    }

    /// Asks for scene `scene`'s next state; [`Self::round`] computes it.
    pub fn request_tick(&mut self, scene: usize) -> Result<()> {
        let id = self.live_id(scene)?;
        if self.in_tick[scene] {
            return Err(Error::data(format!(
                "scene {scene}: a tick is already in progress"
            )));
        }
        self.sched.request_tick(id)?;
        self.in_tick[scene] = true;
        Ok(())
    }

    /// Scenes with a tick requested and not yet emitted.
    pub fn ticks_in_progress(&self) -> usize {
        self.in_tick.iter().filter(|&&t| t).count()
    }

    /// One scheduler round: one batched Heun step of every scene with a tick in progress (one
    /// engine call), then the emission of every scene whose tick finished, `overrides` as in
    /// [`Self::tick_scenes`]. Returns the scenes that emitted, in scheduler order.
    pub fn round(
        &mut self,
        engine: &mut dyn StepEngine,
        overrides: &mut Overrides<'_>,
    ) -> Result<Vec<usize>> {
        let w = self.w;
        if self.sched.next_batch(self.states.len())? > 0 {
            let mut second_evaluation = false;
            let (mut heun, mut multistep) = (false, false);
            for item in self.sched.batch() {
                let i = self.scene_of_slot[item.scene.index()];
                let plan = self.sched.step_plan(item);
                let rows = i * w..(i + 1) * w;
                if item.stage_start && self.needs_load[i] {
                    let s = &self.states[i];
                    engine.load_scene(i, &s.window, &s.valid)?;
                    self.needs_load[i] = false;
                    // A loaded window has no estimate yet.
                    self.estimate_sigma[rows.clone()].fill(0.0);
                }
                if self.planners[i].sampler == Sampler::Multistep {
                    self.multistep_sigma_cur[rows.clone()].copy_from_slice(plan.sigma_cur);
                    self.multistep_sigma_next[rows.clone()].copy_from_slice(plan.sigma_next);
                    let kept = &mut self.estimate_sigma[rows.clone()];
                    let gamma = &mut self.gamma[rows];
                    for k in 0..w {
                        let (cur, next) = (plan.sigma_cur[k], plan.sigma_next[k]);
                        gamma[k] = Sampler::multistep_gamma(kept[k], cur, next);
                        // This step's evaluation replaces every slot's estimate.
                        kept[k] = cur;
                    }
                    multistep = true;
                } else {
                    self.sigma_cur[rows.clone()].copy_from_slice(plan.sigma_cur);
                    self.sigma_next[rows].copy_from_slice(plan.sigma_next);
                    second_evaluation |= plan.nfe == 2;
                    heun = true;
                }
            }
            let mut stepped = Ok(());
            if heun {
                stepped = engine.step(&self.sigma_cur, &self.sigma_next, second_evaluation);
            }
            if multistep && stepped.is_ok() {
                stepped = engine.step_multistep(
                    &self.multistep_sigma_cur,
                    &self.multistep_sigma_next,
                    &self.gamma,
                );
            }
            // The batch's scenes hold still in later rounds unless they are in them again.
            for item in self.sched.batch() {
                let i = self.scene_of_slot[item.scene.index()];
                let rows = i * w..(i + 1) * w;
                self.sigma_cur[rows.clone()].fill(IDLE_SIGMA);
                self.sigma_next[rows.clone()].fill(IDLE_SIGMA);
                self.multistep_sigma_cur[rows.clone()].fill(IDLE_SIGMA);
                self.multistep_sigma_next[rows.clone()].fill(IDLE_SIGMA);
                self.gamma[rows].fill(0.0);
            }
            self.sched.complete_batch();
            stepped?;
        }
        self.emit(engine, overrides)
    }

    /// Emits the state of every scene whose tick finished: the tick's only readback, the
    /// overrides, the shift or rebuild of its window.
    fn emit(
        &mut self,
        engine: &mut dyn StepEngine,
        overrides: &mut Overrides<'_>,
    ) -> Result<Vec<usize>> {
        let (n, w, a_max) = (self.n, self.w, self.a_max);
        let position_scale_m = engine.position_scale_m();
        let heading_scale = engine.heading_scale();
        self.outcomes.clear();
        self.sched.take_outcomes(&mut self.outcomes);
        // Outcomes of scenes that left meanwhile are dropped with them.
        let ids = &self.ids;
        let scene_of_slot = &self.scene_of_slot;
        self.outcomes.retain(|o| {
            scene_of_slot
                .get(o.scene.index())
                .is_some_and(|&i| i != usize::MAX && ids[i] == Some(o.scene))
        });
        if self.outcomes.is_empty() {
            return Ok(Vec::new());
        }
        self.emit_slots.fill(None);
        for o in &self.outcomes {
            let i = self.scene_of_slot[o.scene.index()];
            self.emit_slots[i] = Some(n + o.emit_future_slot);
        }
        let shape = ShiftShape {
            observed: n,
            obs_noise: self.obs_noise,
            sigma_max: self.sigma_max,
        };
        // The denoised windows of the scenes whose client or planner needs them, read with the
        // emitted states (one readback a round).
        self.denoised_scenes.clear();
        for o in &self.outcomes {
            let i = self.scene_of_slot[o.scene.index()];
            let planner = &self.planners[i];
            if self.states[i].wants_plan
                || planner.plan_smoothing.is_some()
                || planner.jerk_tracking.is_some()
            {
                self.denoised_scenes.push(i);
            }
        }
        let per_scene = a_max * w * 3;
        self.denoised
            .resize(self.denoised_scenes.len() * per_scene, 0.0);
        engine.read_emitted_and_denoised(
            &self.emit_slots,
            &mut self.emitted,
            &self.denoised_scenes,
            &mut self.denoised,
        )?;
        // Each outcome's scene, its first slot after the emitted one and its plan's place in
        // `denoised` (outcomes come in the order `denoised_scenes` was filled in).
        let mut read = 0;
        let jobs: Vec<PlanJob> = self
            .outcomes
            .iter()
            .map(|o| {
                let i = self.scene_of_slot[o.scene.index()];
                let plan = (self.denoised_scenes.get(read) == Some(&i)).then(|| {
                    read += 1;
                    read - 1
                });
                PlanJob {
                    scene: i,
                    from: n + o.emit_future_slot + 1,
                    plan,
                    then: o.then,
                }
            })
            .collect();
        // The planner's smoothing and tracking of every scene's emitted states: pure per
        // scene, so spread over threads when many scenes emit.
        let mut planned: Vec<Vec<f32>> = jobs
            .iter()
            .map(|job| {
                let agents = self.states[job.scene].agents;
                self.emitted[job.scene * a_max * 3..][..agents * 3].to_vec()
            })
            .collect();
        let scales = (position_scale_m, heading_scale);
        let plan_all = |jobs: &[PlanJob], planned: &mut [Vec<f32>]| {
            for (job, emitted) in jobs.iter().zip(planned) {
                let denoised = job
                    .plan
                    .map_or(&[][..], |k| &self.denoised[k * per_scene..][..per_scene]);
                let planner = &self.planners[job.scene];
                let s = &self.states[job.scene];
                plan_emitted(s, planner, denoised, w, job.from, scales, emitted);
            }
        };
        let (threads, min_scenes) = self.planner_threads;
        let threads = threads.min(jobs.len() / min_scenes).max(1);
        if threads == 1 {
            plan_all(&jobs, &mut planned);
        } else {
            let chunk = jobs.len().div_ceil(threads);
            std::thread::scope(|scope| {
                for (jobs, planned) in jobs.chunks(chunk).zip(planned.chunks_mut(chunk)) {
                    scope.spawn(|| plan_all(jobs, planned));
                }
            });
        }
        let mut shifts: Vec<PendingShift> = Vec::new();
        let mut done = Vec::with_capacity(self.outcomes.len());
        for (job, mut emitted) in jobs.iter().zip(planned) {
            let (i, from) = (job.scene, job.from);
            let s = &mut self.states[i];
            let denoised = job
                .plan
                .map_or(&[][..], |k| &self.denoised[k * per_scene..][..per_scene]);
            if s.wants_plan {
                s.plan_steps = w.saturating_sub(from);
                s.plan.clear();
                for a in 0..s.agents {
                    s.plan
                        .extend_from_slice(&denoised[3 * (a * w + from)..3 * (a * w + w)]);
                }
            }
            self.plan_turns.clear();
            self.plan_turns.resize(s.agents * 4, 0.0);
            overrides(i, &mut emitted, &mut self.plan_turns)?;
            // Most ticks turn nothing: no copy then.
            let turns = if self.plan_turns.iter().any(|&v| v != 0.0) {
                self.plan_turns.clone()
            } else {
                Vec::new()
            };
            for a in 0..s.agents {
                s.history[a].push([emitted[3 * a], emitted[3 * a + 1], emitted[3 * a + 2]]);
                s.history_valid[a].push(!s.retired[a]);
            }
            s.emitted.extend_from_slice(&emitted);
            let rng = &mut self.rngs[i];
            match job.then {
                WindowUpdate::Shift => {
                    let mut noise = normal_vec(rng, s.agents * 6);
                    // The new slot's draws (the last 3 of each agent's 6) at the planner's
                    // temperature; the observation noise stays as it is.
                    let tau = self.planners[i].noise_temperature() as f32;
                    if tau != 1.0 {
                        for agent in noise.chunks_exact_mut(6) {
                            for z in &mut agent[3..] {
                                *z *= tau;
                            }
                        }
                    }
                    // The engine's estimate moves with the slots (`estimate_shift`): so do
                    // the levels it was made at.
                    let kept = &mut self.estimate_sigma[i * w..(i + 1) * w];
                    kept.copy_within(1..w, 0);
                    kept[n - 1] = 0.0;
                    kept[w - 1] = 0.0;
                    // Validity moves with the slots; the joining observation and the new slot
                    // are valid.
                    for a in 0..s.agents {
                        let row = a * w;
                        if s.retired[a] {
                            s.valid[row..row + w].fill(0.0);
                            continue;
                        }
                        s.valid.copy_within(row + 1..row + w, row);
                        s.valid[row + n - 1] = 1.0;
                        s.valid[row + w - 1] = 1.0;
                    }
                    shifts.push(PendingShift {
                        scene: i,
                        emitted,
                        noise,
                        turns,
                    });
                }
                WindowUpdate::Rebuild => {
                    let tau = self.planners[i].noise_temperature() as f32;
                    rebuild_window(s, n, w, self.obs_noise, self.sigma_max * tau, rng);
                    self.needs_load[i] = true;
                }
                WindowUpdate::Hold | WindowUpdate::Exhausted => {}
            }
            self.ticks[i] += 1;
            self.in_tick[i] = false;
            done.push(i);
        }
        if !shifts.is_empty() {
            let edits: Vec<ShiftEdit<'_>> = shifts
                .iter()
                .map(|p| ShiftEdit {
                    scene: p.scene,
                    emitted: &p.emitted,
                    noise: &p.noise,
                    valid: &self.states[p.scene].valid,
                    turns: &p.turns,
                })
                .collect();
            engine.shift(&edits, shape)?;
        }
        Ok(done)
    }

    /// Model evaluations of scene 0 so far (every scene's, when all tick together).
    pub fn nfe(&self) -> Result<u64> {
        self.scene_nfe(0)
    }

    /// Model evaluations of one scene so far.
    pub fn scene_nfe(&self, scene: usize) -> Result<u64> {
        Ok(self.nfe_before[scene] + self.sched.stats(self.live_id(scene)?)?.nfe)
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
/// pure noise of standard deviation `sigma_max` (σ_max times the planner's temperature).
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
                s.valid[k] = if s.retired[a] { 0.0 } else { 1.0 };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use road_model::ModelConfig;
    use road_model::batch::SceneInput;

    use super::*;

    /// An engine that only holds what it is given: enough for the driver to build windows.
    struct HoldingEngine {
        window_slots: usize,
    }

    impl StepEngine for HoldingEngine {
        fn window_slots(&self) -> usize {
            self.window_slots
        }
        fn prepare(
            &mut self,
            _: usize,
            _: usize,
            _: &[f32],
            _: usize,
            _: &[f32],
            _: &[f32],
        ) -> Result<()> {
            Ok(())
        }
        fn load(&mut self, _: &[f32], _: &[f32]) -> Result<()> {
            Ok(())
        }
        fn load_scene(&mut self, _: usize, _: &[f32], _: &[f32]) -> Result<()> {
            Ok(())
        }
        fn step(&mut self, _: &[f32], _: &[f32], _: bool) -> Result<()> {
            Ok(())
        }
        fn read_emitted(&mut self, _: &[Option<usize>], out: &mut [f32]) -> Result<()> {
            out.fill(0.0);
            Ok(())
        }
        fn shift(&mut self, _: &[ShiftEdit<'_>], _: ShiftShape) -> Result<()> {
            Ok(())
        }
    }

    /// `noise_temperature` τ: a window's pure-noise slots start at τ · σ_max · z with the same
    /// draws z, its observations untouched.
    #[test]
    fn noise_temperature_scales_the_pure_noise_of_future_slots() {
        let config = ModelConfig {
            hidden: 16,
            heads: 2,
            blocks: 1,
            map_polylines: 4,
            ..ModelConfig::default()
        };
        let (agents, slots) = (2, config.window_slots);
        let history = SceneInput {
            agents,
            slots: 10,
            states: (0..agents * 10 * 3).map(|i| i as f32 * 0.01).collect(),
            valid: vec![true; agents * 10],
            agent_features: vec![0.5; agents * AGENT_FEATURES],
            polylines: 4,
            points: config.polyline_points,
            map: vec![0.1; 4 * config.polyline_points * 2],
        };
        let scenes = [RolloutScene { history }];
        let window = |tau: Option<f64>| {
            let planner = PlannerSpec {
                noise_temperature: tau,
                ..PlannerSpec::default()
            };
            let mut engine = HoldingEngine {
                window_slots: config.window_slots,
            };
            let driver = RolloutDriver::new(
                &mut engine,
                &planner,
                &scenes,
                4,
                &mut StdRng::seed_from_u64(5),
            )
            .unwrap();
            driver.states[0].window.clone()
        };
        let (hot, cool) = (window(None), window(Some(0.5)));
        for a in 0..agents {
            for slot in 0..slots {
                for d in 0..3 {
                    let k = 3 * (a * slots + slot) + d;
                    let want = if slot < 10 { hot[k] } else { 0.5 * hot[k] };
                    assert_eq!(cool[k], want, "agent {a}, slot {slot}, {d}");
                }
            }
        }
        assert!(hot[3 * 15].abs() > 1.0, "future slots hold noise at σ_max");
    }
}
