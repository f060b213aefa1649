//! The rollout driver's engine on the GPU ([`GpuStepEngine`]): `road-model`'s
//! `StepEngine` over a [`GpuDenoiser`]'s kernels, with the windows kept on the device through a
//! tick's steps, and compacted sub-batches for mixed-phase rounds and for packed scenes
//! (several small scenes' agents in one sub-batch scene, attending apart).

use crate::engine::{DenoiseInputs, DeviceBatch, GpuDenoiser, MapTokens};
use crate::kernels::compact::{NONE, Region};
use crate::kernels::window::ShiftList;
use crate::kernels::{Dispatch, Traffic, read_back_ranges, record_all, storage_buffer};
use crate::proxies::{Work, flops_per_evaluation, map_key_flops};
use crate::sampler_step::{HeunPlan, KeysOutcome, MapInputs, StepRule};
use crate::{Error, GpuContext, Result};

/// When a step packs its moving scenes ([`plan_packing`]; every kernel that mixes agents or
/// reads a scene's map keeps a packed scene's agents apart by `agent_scene`): from `min_moving`
/// of them, when that saves a fifth of the work.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PackRule {
    min_moving: usize,
}

impl PackRule {
    /// lavapipe computes every padded row: from two scenes (8 validation scenes of 3-15 agents
    /// padded to 15 computed 1.98× their own work).
    const SOFTWARE: Self = Self { min_moving: 2 };
    /// A card: below this a step is bound by its launches, not its rows (the H200's 8-scene
    /// step took 4 ms at 1.98× padding), and a packed step adds its gathers and scatters. From
    /// 128, where buckets of scenes of like agent counts (what packing replaced) began to win:
    /// on an H200 (2026-11-30, docs/experiments/bench-2026-11-30-wgsl-engine-h200.md) 64 scenes
    /// in buckets of 16 stepped 20-23 % slower than one batch, 512 scenes 19-33 % faster.
    const HARDWARE: Self = Self { min_moving: 128 };

    fn for_context(ctx: &GpuContext) -> Self {
        if ctx.is_software() || ctx.eager_packing() {
            Self::SOFTWARE
        } else {
            Self::HARDWARE
        }
    }
}

/// One moving scene in a compact sub-batch: its first `rows` agent rows at agent row `offset`
/// of sub-batch scene `slot`. Its map is the sub-batch's map scene of its index in
/// [`Layout::placed`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Placement {
    scene: usize,
    slot: usize,
    offset: usize,
    rows: usize,
}

/// Where a compact sub-batch of `slots` scenes × `agents` agent rows holds the moving scenes.
/// Plain: scene k of the step in slot k ([`Layout::plain`]); packed: several per slot
/// ([`plan_packing`]).
#[derive(Debug, Clone, PartialEq)]
struct Layout {
    slots: usize,
    agents: usize,
    placed: Vec<Placement>,
}

impl Layout {
    /// Each of `active` alone in a sub-batch scene of its first `agents` rows.
    fn plain(active: &[usize], agents: usize) -> Self {
        Self {
            slots: active.len(),
            agents,
            placed: active
                .iter()
                .enumerate()
                .map(|(slot, &scene)| Placement {
                    scene,
                    slot,
                    offset: 0,
                    rows: agents,
                })
                .collect(),
        }
    }

    /// The work computed: the sub-batch's scenes (empty places included) at its agents,
    /// `flops(agents)` each.
    fn cost(&self, flops: &impl Fn(usize) -> f64) -> f64 {
        compact_capacity(self.slots) as f64 * flops(self.agents)
    }

    /// `[capacity·agents]`: each sub-batch agent row's row in the batch (its scene's rows of
    /// `batch_agents` each), [`NONE`] where no scene fills it.
    fn batch_rows(&self, batch_agents: usize) -> Vec<u32> {
        let mut out = vec![NONE; compact_capacity(self.slots) * self.agents];
        for p in &self.placed {
            let rows = &mut out[p.slot * self.agents + p.offset..][..p.rows];
            for (j, row) in rows.iter_mut().enumerate() {
                *row = (p.scene * batch_agents + j) as u32;
            }
        }
        out
    }

    /// `[capacity(placed)]`: each map scene's scene in the batch (placement k's), [`NONE`]
    /// beyond.
    fn map_scenes(&self) -> Vec<u32> {
        let mut out = vec![NONE; compact_capacity(self.placed.len())];
        for (k, p) in self.placed.iter().enumerate() {
            out[k] = p.scene as u32;
        }
        out
    }

    /// `[capacity·agents]`: each agent row's map scene (its placement's index; rows no scene
    /// fills: 0, invalid).
    fn agent_scenes(&self) -> Vec<u32> {
        let mut out = vec![0u32; compact_capacity(self.slots) * self.agents];
        for (k, p) in self.placed.iter().enumerate() {
            out[p.slot * self.agents + p.offset..][..p.rows].fill(k as u32);
        }
        out
    }
}

/// The `active` scenes packed first fit decreasing (most live rows first) into sub-batch
/// scenes of `agents` rows, each holding scenes of one `class` only (`class[k]` of `active[k]`:
/// scenes of like σ rows, since σ is per sub-batch scene).
fn pack_first_fit(
    live_agents: &[usize],
    active: &[usize],
    class: &[usize],
    agents: usize,
) -> Layout {
    let mut order: Vec<usize> = (0..active.len()).collect();
    order.sort_by_key(|&k| (std::cmp::Reverse(live_agents[active[k]]), k));
    // Per slot: its class and rows filled.
    let mut slots: Vec<(usize, usize)> = Vec::new();
    let mut placed = Vec::with_capacity(active.len());
    for k in order {
        let rows = live_agents[active[k]].clamp(1, agents);
        let slot = match slots
            .iter()
            .position(|&(c, filled)| c == class[k] && filled + rows <= agents)
        {
            Some(slot) => slot,
            None => {
                slots.push((class[k], 0));
                slots.len() - 1
            }
        };
        placed.push(Placement {
            scene: active[k],
            slot,
            offset: slots[slot].1,
            rows,
        });
        slots[slot].1 += rows;
    }
    Layout {
        slots: slots.len(),
        agents,
        placed,
    }
}

/// The packing of least work (`flops(agents)` per sub-batch scene) among sub-batch scenes of
/// the most live rows rounded up to 4, up to twice that in steps of 4 (larger ones hold more
/// scenes each but attend over more agents), packed by [`pack_first_fit`].
fn plan_packing(
    live_agents: &[usize],
    active: &[usize],
    class: &[usize],
    flops: &impl Fn(usize) -> f64,
) -> Layout {
    let most = active
        .iter()
        .map(|&i| live_agents[i])
        .max()
        .unwrap_or(1)
        .max(1)
        .next_multiple_of(4);
    (most..=2 * most)
        .step_by(4)
        .map(|agents| pack_first_fit(live_agents, active, class, agents))
        .min_by(|a, b| a.cost(flops).total_cmp(&b.cost(flops)))
        .expect("at least one size")
}

/// Most compact sub-batch shapes kept (each with its buffers and plan: up to a whole batch's
/// memory); beyond, the least recently used is dropped. A step makes at most one.
const MAX_COMPACTS: usize = 12;

/// Most agent rows (scenes × agents) the kept compact sub-batches hold together, in whole
/// batches: a packed sub-batch holds every moving scene, and a pool whose layouts drift (agents
/// leaving, scenes joining) must not keep a dozen of them (at 4 096 scenes each holds gigabytes
/// of activations). Beyond, the least recently used are dropped.
const MAX_COMPACT_ROWS_IN_BATCHES: usize = 2;

/// Scenes of a compact sub-batch holding `scenes`: rounded up to an eighth of the next power
/// of two, so that few shapes are made (each with its own buffers and plan) and at most an
/// eighth of it is empty places.
fn compact_capacity(scenes: usize) -> usize {
    let step = (scenes.next_power_of_two() / 8).max(1);
    scenes.next_multiple_of(step)
}

/// The rollout driver's engine on the GPU: windows stay on the device through a tick's steps
/// and are read back once per tick.
#[derive(Debug)]
pub struct GpuStepEngine<'a> {
    ctx: &'a GpuContext,
    model: &'a GpuDenoiser,
    map: Option<MapTokens>,
    batch: Option<DeviceBatch>,
    plan: Option<HeunPlan>,
    window: Option<crate::kernels::window::WindowOps>,
    /// Each scene's last denoiser estimate `[B, A, W, 3]` (zeros until a step moves it), for
    /// `read_denoised` and the multistep sampler, and the window kernels bound to it (it moves
    /// with each shift).
    denoised: Option<wgpu::Buffer>,
    estimate_window: Option<crate::kernels::window::WindowOps>,
    /// Compacted sub-batches by shape ([`compact_capacity`] scenes × agent rows), made on
    /// first use, at most [`MAX_COMPACTS`].
    compact: Vec<Compact>,
    /// Compact sub-batch steps so far: each sub-batch's `last_use` is one of them.
    compact_uses: u64,
    /// Bumped whenever a scene's agent embeddings or map change (`prepare_scene`): a compact
    /// sub-batch gathers those again only then, or when its row maps change. The maps' count of
    /// the plans' [`MapInputs`].
    fixed_generation: u64,
    /// Bumped whenever the windows may have moved an anchor state (loads, shifts, a step that
    /// moved one): the windows' count of the plans' [`MapInputs`], under which a plan keeps
    /// the map's keys it made.
    windows_generation: u64,
    features: Vec<f32>,
    /// Zeros for the kept estimate's shift (nothing emitted, no noise), grown on demand.
    zeros: Vec<f32>,
    /// `[B]`: one past each scene's last agent row with a valid slot; the rows after it are
    /// padding, which a compact sub-batch leaves out.
    live_agents: Vec<usize>,
    /// `[B]`: each scene's own agents (those with a valid slot) and polylines (valid flags):
    /// the useful work of [`Work`].
    own_agents: Vec<usize>,
    own_polylines: Vec<usize>,
    /// What the steps since the last [`GpuStepEngine::take_work`] computed.
    work: Work,
    scenes: usize,
    agents: usize,
}

impl<'a> GpuStepEngine<'a> {
    pub fn new(ctx: &'a GpuContext, model: &'a GpuDenoiser) -> Self {
        Self {
            ctx,
            model,
            map: None,
            batch: None,
            plan: None,
            window: None,
            denoised: None,
            estimate_window: None,
            compact: Vec::new(),
            compact_uses: 0,
            fixed_generation: 0,
            windows_generation: 0,
            features: Vec::new(),
            zeros: Vec::new(),
            live_agents: Vec::new(),
            own_agents: Vec::new(),
            own_polylines: Vec::new(),
            work: Work::default(),
            scenes: 0,
            agents: 0,
        }
    }

    /// What the steps since the last call did: evaluations, the dispatches recorded and their
    /// binding bytes, the work computed against the moving scenes' own (`road bench engine`'s
    /// proxies, [`crate::proxies`]).
    pub fn take_work(&mut self) -> Work {
        std::mem::take(&mut self.work)
    }

    /// The next step makes the map's keys again, as a tick's first step does after a shift
    /// moved the anchors: for a benchmark that repeats one step on the same windows.
    pub fn remake_map_keys(&mut self) {
        self.windows_generation += 1;
    }
}

/// The work of one step of `evaluations` evaluations, `keys.made` of them making the map's
/// keys, computed at `computed_scenes` × `computed_agents` × `polylines` (a batch or a compact
/// sub-batch, padding included), of which the `active` scenes' own agents and polylines are
/// the useful part.
#[allow(clippy::too_many_arguments)]
fn step_work(
    config: &road_model::ModelConfig,
    evaluations: u64,
    keys: KeysOutcome,
    computed_scenes: usize,
    computed_agents: usize,
    polylines: usize,
    active: &[usize],
    own_agents: &[usize],
    own_polylines: &[usize],
    traffic: Traffic,
) -> Work {
    let (e, kept) = (
        evaluations as f64,
        evaluations.saturating_sub(keys.made) as f64,
    );
    let flops = |agents, polylines| {
        e * flops_per_evaluation(config, agents, polylines)
            - kept * map_key_flops(config, agents, polylines)
    };
    Work {
        evaluations,
        traffic,
        computed_flops: computed_scenes as f64 * flops(computed_agents, polylines),
        useful_flops: active
            .iter()
            .map(|&i| flops(own_agents[i], own_polylines[i]))
            .sum::<f64>(),
        map_key_evaluations: keys.made,
    }
}

/// A compacted sub-batch of `capacity` scenes with its own Heun plan: the moving scenes of a
/// mixed-phase round are gathered in, stepped, and scattered back, so idle scenes cost nothing.
#[derive(Debug)]
struct Compact {
    batch: DeviceBatch,
    /// The moving scenes' maps, one map scene per placement (`Layout::placed`).
    map: MapTokens,
    plan: HeunPlan,
    /// What `batch.agent_scene` holds.
    agent_scenes: Vec<u32>,
    /// `[capacity·agents]` u32: each agent row's row in the batch (`Layout::batch_rows`), and
    /// what it holds.
    batch_rows: wgpu::Buffer,
    batch_rows_held: Vec<u32>,
    /// `[map scenes]` u32: each map scene's scene in the batch (`Layout::map_scenes`), and what
    /// it holds.
    map_scenes: wgpu::Buffer,
    map_scenes_held: Vec<u32>,
    /// Its gathers and scatters, prepared on its first step.
    moves: Option<CompactMoves>,
    /// The engine's `fixed_generation` when the fixed regions were last gathered under the
    /// row maps held now (none: gather them at the next step).
    fixed_gathered: Option<u64>,
    sigma_cur: Vec<f32>,  // [capacity, W]
    sigma_next: Vec<f32>, // [capacity, W]
    gamma: Vec<f32>,      // [capacity, W]
    /// `GpuStepEngine::compact_uses` when it last stepped.
    last_use: u64,
}

/// A compact sub-batch's row moves (`shaders/compact.wgsl`), prepared once: the batch's
/// buffers and the sub-batch's own outlive it (a new scene set clears the sub-batches), so a
/// step makes no uniform buffer or bind group of its own. Regions of one row map move in one
/// dispatch.
#[derive(Debug)]
struct CompactMoves {
    /// States and flags by `batch_rows`, every step of a Heun step; with the kept estimates
    /// into the plan's `D_prev` too, every multistep step (index 1, with a kept estimate).
    gathers: [Dispatch; 2],
    /// Agent embeddings by `batch_rows`, map data and flags by `map_scenes`: only when they or
    /// the row maps changed (`Compact::fixed_gathered`).
    fixed_gathers: Vec<Dispatch>,
    /// States back, and the estimate of the plan's first or (index 1) second evaluation with a
    /// kept one.
    scatters: [Dispatch; 2],
}

impl CompactMoves {
    fn new(
        ctx: &GpuContext,
        model: &GpuDenoiser,
        (batch, map, kept): (&DeviceBatch, &MapTokens, Option<&wgpu::Buffer>),
        compact: &Compact,
    ) -> Result<Self> {
        let rows = &model.pipelines.compact_rows;
        let (w, d) = (model.config.window_slots, model.config.hidden);
        let agent_rows = compact.batch.scenes * compact.batch.agents;
        let (p, c) = (map.polylines, &compact.batch);
        let by_row = |regions: &[Region<'_>]| {
            rows.prepare_gather(ctx, &compact.batch_rows, agent_rows, regions)
        };
        let states = (&batch.x, &c.x, w * 3);
        let flags = (&batch.valid, &c.valid, w);
        let previous = kept.map(|kept| (kept, compact.plan.previous(), w * 3));
        let with_previous: Vec<Region<'_>> = [states, flags].into_iter().chain(previous).collect();
        let gathers = [by_row(&[states, flags])?, by_row(&with_previous)?];
        let fixed_gathers = vec![
            by_row(&[(&batch.agent_embedding, &c.agent_embedding, d)])?,
            rows.prepare_gather(
                ctx,
                &compact.map_scenes,
                compact.map.scenes,
                &[
                    (&map.data, &compact.map.data, p * map.per_polyline),
                    (&map.valid, &compact.map.valid, p),
                ],
            )?,
        ];
        let estimates = compact.plan.estimates();
        let back = |estimate| {
            let mut regions = vec![(&c.x, &batch.x, w * 3)];
            regions.extend(kept.map(|kept| (estimate, kept, w * 3)));
            rows.prepare_scatter(ctx, &compact.batch_rows, agent_rows, &regions)
        };
        Ok(Self {
            gathers,
            fixed_gathers,
            scatters: [back(estimates[0])?, back(estimates[1])?],
        })
    }
}

impl Compact {
    /// `capacity` scenes of `agents` rows and `map_scenes` maps; `like`: the scene set's map
    /// (its polylines and what each holds).
    fn new(
        ctx: &GpuContext,
        model: &GpuDenoiser,
        (capacity, agents, map_scenes): (usize, usize, usize),
        like: &MapTokens,
    ) -> Result<Self> {
        let (w, d) = (model.config.window_slots, model.config.hidden);
        let buffer = |label, floats: usize| storage_buffer(ctx, label, (floats * 4) as u64);
        let batch = DeviceBatch {
            scenes: capacity,
            agents,
            x: buffer("compact.x", capacity * agents * w * 3),
            sigma: buffer("compact.sigma", capacity * w),
            valid: buffer("compact.valid", capacity * agents * w),
            agent_embedding: buffer("compact.agent_embedding", capacity * agents * d),
            agent_scene: buffer("compact.agent_scene", capacity * agents),
        };
        let polylines = like.polylines;
        let map = MapTokens {
            data: buffer(
                "compact.map.data",
                map_scenes * polylines * like.per_polyline,
            ),
            valid: buffer("compact.map.valid", map_scenes * polylines),
            scenes: map_scenes,
            polylines,
            per_polyline: like.per_polyline,
            picked: like.picked,
        };
        let plan = model.heun_plan(ctx, &batch, &map)?;
        Ok(Self {
            batch,
            map,
            plan,
            // Storage buffers start zeroed.
            agent_scenes: vec![0; capacity * agents],
            batch_rows: buffer("compact.batch_rows", capacity * agents),
            batch_rows_held: vec![0; capacity * agents],
            map_scenes: buffer("compact.map_scenes", map_scenes),
            map_scenes_held: vec![0; map_scenes],
            moves: None,
            fixed_gathered: None,
            sigma_cur: vec![1.0; capacity * w],
            sigma_next: vec![1.0; capacity * w],
            gamma: vec![0.0; capacity * w],
            last_use: 0,
        })
    }
}

impl GpuStepEngine<'_> {
    /// The byte ranges of `scenes`' kept estimates `[A, W, 3]` each, for `out_len` floats
    /// read: a clear error for a scene past the batch or a wrong length.
    fn denoised_ranges(
        &self,
        scenes: &[usize],
        out_len: usize,
    ) -> road_model::Result<Vec<(u64, u64)>> {
        let x_len = self.agents * self.model.config.window_slots * 3;
        if let Some(&bad) = scenes.iter().find(|&&s| s >= self.scenes) {
            return Err(road_model::Error::Engine(format!(
                "read_denoised of scene {bad}: the batch has {} scenes",
                self.scenes
            )));
        }
        if out_len != scenes.len() * x_len {
            return Err(road_model::Error::Engine(format!(
                "read_denoised of {} scenes: {out_len} outputs; scenes of {x_len} each",
                scenes.len(),
            )));
        }
        Ok(scenes
            .iter()
            .map(|&s| ((s * x_len * 4) as u64, (x_len * 4) as u64))
            .collect())
    }

    /// Times one evaluation and Euler update of the loaded batch kernel by kernel (see
    /// [`crate::profile`]); the windows move as in `repeats` Euler steps at the last step's σ.
    /// The whole batch's plan is made here if no step ran the batch in place yet.
    pub fn profile_step(&mut self, repeats: usize) -> Result<crate::profile::StepProfile> {
        if self.plan.is_none() {
            let (Some(batch), Some(map)) = (&self.batch, &self.map) else {
                return Err(Error::Input("profile before prepare and load".into()));
            };
            self.plan = Some(self.model.heun_plan(self.ctx, batch, map)?);
        }
        let plan = self.plan.as_mut().expect("made above");
        // The profile runs the first evaluation's dispatches outside a step.
        plan.forget_map_keys();
        crate::profile::profile(self.ctx, plan.euler_dispatches(), repeats)
    }

    /// One step of every scene whose σ row changes, under `rule`; see `StepEngine::step` and
    /// `StepEngine::step_multistep`.
    fn step_rule(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        rule: StepRule<'_>,
    ) -> road_model::Result<()> {
        if self.batch.is_none() || self.map.is_none() {
            return Err(road_model::Error::Engine(
                "step before prepare and load".into(),
            ));
        }
        let (b, w) = (self.scenes, self.model.config.window_slots);
        if sigma_cur.len() != b * w || sigma_next.len() != b * w {
            return Err(road_model::Error::Engine(format!(
                "σ rows: {} and {} values for {b} scenes × {w} slots",
                sigma_cur.len(),
                sigma_next.len()
            )));
        }
        let active: Vec<usize> = (0..b)
            .filter(|&i| sigma_cur[i * w..(i + 1) * w] != sigma_next[i * w..(i + 1) * w])
            .collect();
        if active.is_empty() {
            return Ok(());
        }
        let evaluations = match rule {
            StepRule::Heun {
                second_evaluation: true,
            } => 2,
            _ => 1,
        };
        let row_bytes = (self.agents * w * 3 * 4) as u64;
        // The moving scenes' live agent rows, rounded up to a multiple of 4 so that few
        // sub-batch shapes are made: a server's pool pads every scene to its most agents.
        let a = self.agents;
        let live = active
            .iter()
            .map(|&i| self.live_agents[i])
            .max()
            .unwrap_or(1);
        let a_c = live.next_multiple_of(4).clamp(1, a);
        // The whole batch in place when most of it moves and most of its agent rows are live;
        // else the moving scenes' live rows in a compact sub-batch.
        let in_place = active.len() * 2 > b && a_c * 4 > a * 3;
        // Scenes of mixed agent counts: packed into one compact sub-batch, when that saves
        // enough of the padding.
        let polylines = self.map.as_ref().map_or(0, |m| m.polylines);
        let flops = |agents| flops_per_evaluation(&self.model.config, agents, polylines);
        let unpacked = if in_place {
            b as f64 * flops(a)
        } else {
            compact_capacity(active.len()) as f64 * flops(a_c)
        };
        if let Some(layout) = self.packing(&active, sigma_cur, sigma_next, rule, unpacked) {
            return self.step_compact(&layout, sigma_cur, sigma_next, rule, evaluations);
        }
        if in_place {
            // Its plan is made on the first such step: a server's pool of hundreds of scenes
            // that steps a few at a time never holds the whole batch's activations (they may
            // exceed what a software adapter binds).
            if self.plan.is_none() {
                let (Some(batch), Some(map)) = (&self.batch, &self.map) else {
                    unreachable!("checked above");
                };
                let plan = self
                    .model
                    .heun_plan(self.ctx, batch, map)
                    .map_err(engine_err)?;
                self.plan = Some(plan);
            }
            let (Some(batch), Some(plan), Some(map)) = (&self.batch, &mut self.plan, &self.map)
            else {
                unreachable!("checked and made above");
            };
            // σ rows are per scene: [B, W]; idle scenes hold still. The moved scenes'
            // estimates are kept in the same submission (idle rows were evaluated, not moved).
            let denoised = self.denoised.as_ref();
            let multistep = matches!(rule, StepRule::Multistep { .. });
            let inputs = MapInputs {
                windows: self.windows_generation,
                maps: self.fixed_generation,
            };
            let keys = plan
                .run_rule(
                    self.ctx,
                    batch,
                    sigma_cur,
                    sigma_next,
                    rule,
                    Some(inputs),
                    |enc, previous| {
                        if let (true, Some(kept)) = (multistep, denoised) {
                            enc.copy_buffer_to_buffer(kept, 0, previous, 0, b as u64 * row_bytes);
                        }
                    },
                    |enc, d| {
                        let Some(kept) = denoised else { return };
                        if active.len() == b {
                            enc.copy_buffer_to_buffer(d, 0, kept, 0, b as u64 * row_bytes);
                        } else {
                            for &i in &active {
                                let at = i as u64 * row_bytes;
                                enc.copy_buffer_to_buffer(d, at, kept, at, row_bytes);
                            }
                        }
                    },
                )
                .map_err(engine_err)?;
            if !keys.inputs_held {
                self.windows_generation += 1;
            }
            // Every scene of the batch was evaluated at its padded agents, idle ones too.
            self.work += step_work(
                &self.model.config,
                evaluations,
                keys,
                b,
                a,
                map.polylines,
                &active,
                &self.own_agents,
                &self.own_polylines,
                plan.take_traffic(),
            );
            return Ok(());
        }
        // Few scenes move (others idle in a mixed-phase batch), or few of their agent rows are
        // live: gather those into a compact sub-batch, step it, scatter the states back.
        let layout = Layout::plain(&active, a_c);
        self.step_compact(&layout, sigma_cur, sigma_next, rule, evaluations)
    }

    /// Steps the moving scenes where `layout` places them in a compact sub-batch (made on first
    /// use and kept, the least recently used dropped beyond [`MAX_COMPACTS`] or
    /// [`MAX_COMPACT_ROWS_IN_BATCHES`]): their rows are gathered in, stepped under `rule`, and
    /// scattered back with their estimates.
    fn step_compact(
        &mut self,
        layout: &Layout,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        rule: StepRule<'_>,
        evaluations: u64,
    ) -> road_model::Result<()> {
        let (Some(batch), Some(map)) = (&self.batch, &self.map) else {
            return Err(road_model::Error::Engine(
                "step before prepare and load".into(),
            ));
        };
        let (a, w) = (self.agents, self.model.config.window_slots);
        let a_c = layout.agents;
        let shape = (
            compact_capacity(layout.slots),
            a_c,
            compact_capacity(layout.placed.len()),
        );
        self.compact_uses += 1;
        let shape_of = |c: &Compact| (c.batch.scenes, c.batch.agents, c.map.scenes);
        if !self.compact.iter().any(|c| shape_of(c) == shape) {
            let rows_of = |c: &Compact| c.batch.scenes * c.batch.agents;
            let most_rows = MAX_COMPACT_ROWS_IN_BATCHES * self.scenes * self.agents;
            while !self.compact.is_empty()
                && (self.compact.len() >= MAX_COMPACTS
                    || self.compact.iter().map(rows_of).sum::<usize>() + shape.0 * shape.1
                        > most_rows)
            {
                let oldest = (0..self.compact.len())
                    .min_by_key(|&k| self.compact[k].last_use)
                    .expect("not empty");
                self.compact.swap_remove(oldest);
            }
            let c = Compact::new(self.ctx, self.model, shape, map).map_err(engine_err)?;
            self.compact.push(c);
        }
        let compact = self
            .compact
            .iter_mut()
            .find(|c| shape_of(c) == shape)
            .expect("made above");
        compact.last_use = self.compact_uses;
        for (held, buffer, now, moves_fixed) in [
            (
                &mut compact.agent_scenes,
                &compact.batch.agent_scene,
                layout.agent_scenes(),
                false,
            ),
            (
                &mut compact.batch_rows_held,
                &compact.batch_rows,
                layout.batch_rows(a),
                true,
            ),
            (
                &mut compact.map_scenes_held,
                &compact.map_scenes,
                layout.map_scenes(),
                true,
            ),
        ] {
            if *held != now {
                self.ctx
                    .queue
                    .write_buffer(buffer, 0, bytemuck::cast_slice(&now));
                *held = now;
                if moves_fixed {
                    compact.fixed_gathered = None;
                }
                // Other rows, or rows reading other maps: other keys.
                compact.plan.forget_map_keys();
            }
        }
        let p = map.polylines;
        // Each region's rows gathered in one dispatch: agent rows by `batch_rows` (rows no
        // scene fills come in as zeros: no agent, nor a stale one of an earlier layout), maps
        // by `map_scenes`; the agent embeddings and maps only when they or the maps of rows
        // changed.
        if compact.moves.is_none() {
            let buffers = (batch, map, self.denoised.as_ref());
            let moves = CompactMoves::new(self.ctx, self.model, buffers, compact);
            compact.moves = Some(moves.map_err(engine_err)?);
        }
        let gather_fixed = compact.fixed_gathered != Some(self.fixed_generation);
        if gather_fixed {
            compact.plan.forget_map_keys();
        }
        let inputs = MapInputs {
            windows: self.windows_generation,
            maps: self.fixed_generation,
        };
        let moves = compact.moves.as_ref().expect("made above");
        // σ (and γ) rows per sub-batch scene: a slot's scenes share theirs.
        compact.sigma_cur.fill(1.0);
        compact.sigma_next.fill(1.0);
        compact.gamma.fill(0.0);
        for place in &layout.placed {
            let (i, s) = (place.scene, place.slot);
            compact.sigma_cur[s * w..(s + 1) * w].copy_from_slice(&sigma_cur[i * w..(i + 1) * w]);
            compact.sigma_next[s * w..(s + 1) * w].copy_from_slice(&sigma_next[i * w..(i + 1) * w]);
            if let StepRule::Multistep { gamma } = rule {
                compact.gamma[s * w..(s + 1) * w].copy_from_slice(&gamma[i * w..(i + 1) * w]);
            }
        }
        let compact_rule = match rule {
            StepRule::Multistep { .. } => StepRule::Multistep {
                gamma: &compact.gamma,
            },
            heun => heun,
        };
        // Gathers, the step and the scatters in the plan's one submission; their dispatches
        // are counted with the step's (`dispatches_per_evaluation` includes them).
        let first_estimate: *const wgpu::Buffer = compact.plan.estimates()[0];
        let multistep = matches!(rule, StepRule::Multistep { .. });
        let moved = std::cell::Cell::new(Traffic::default());
        let count = |d: &Dispatch| {
            let mut traffic = moved.get();
            traffic.count(d);
            moved.set(traffic);
        };
        let keys = compact
            .plan
            .run_rule(
                self.ctx,
                &compact.batch,
                &compact.sigma_cur,
                &compact.sigma_next,
                compact_rule,
                Some(inputs),
                |enc, _| {
                    if gather_fixed {
                        moves.fixed_gathers.iter().for_each(count);
                        record_all(enc, "compact gather (fixed)", &moves.fixed_gathers);
                    }
                    // A multistep step's gather brings the kept estimates into `D_prev` too.
                    let gather = &moves.gathers[usize::from(multistep)];
                    count(gather);
                    record_all(enc, "compact gather", std::slice::from_ref(gather));
                },
                |enc, denoised| {
                    // The placed rows back (a scene's rows beyond them hold still), with the
                    // estimate of the plan's first or second evaluation.
                    let which = usize::from(!std::ptr::eq(denoised, first_estimate));
                    let scatter = &moves.scatters[which];
                    count(scatter);
                    record_all(enc, "compact scatter", std::slice::from_ref(scatter));
                },
            )
            .map_err(engine_err)?;
        if !keys.inputs_held {
            self.windows_generation += 1;
        }
        compact.fixed_gathered = Some(self.fixed_generation);
        // The sub-batch's empty places (up to its capacity) and empty rows are computed too.
        let active: Vec<usize> = layout.placed.iter().map(|place| place.scene).collect();
        let mut traffic = compact.plan.take_traffic();
        traffic += moved.get();
        self.work += step_work(
            &self.model.config,
            evaluations,
            keys,
            shape.0,
            a_c,
            p,
            &active,
            &self.own_agents,
            &self.own_polylines,
            traffic,
        );
        Ok(())
    }

    /// The moving scenes packed ([`plan_packing`]) when the model, the context and
    /// [`PackRule`] allow it and that computes at most four fifths of `unpacked` (the work of
    /// the step otherwise taken); else nothing.
    fn packing(
        &self,
        active: &[usize],
        sigma_cur: &[f32],
        sigma_next: &[f32],
        rule: StepRule<'_>,
        unpacked: f64,
    ) -> Option<Layout> {
        if !self.ctx.pack_scenes() || active.len() < PackRule::for_context(self.ctx).min_moving {
            return None;
        }
        let w = self.model.config.window_slots;
        // Scenes share a sub-batch scene only with scenes of the same σ (and γ) rows.
        let mut classes = std::collections::HashMap::<Vec<u32>, usize>::new();
        let class: Vec<usize> = active
            .iter()
            .map(|&i| {
                let mut key: Vec<u32> = sigma_cur[i * w..(i + 1) * w]
                    .iter()
                    .chain(&sigma_next[i * w..(i + 1) * w])
                    .map(|v| v.to_bits())
                    .collect();
                if let StepRule::Multistep { gamma } = rule {
                    key.extend(gamma[i * w..(i + 1) * w].iter().map(|v| v.to_bits()));
                }
                let next = classes.len();
                *classes.entry(key).or_insert(next)
            })
            .collect();
        let polylines = self.map.as_ref().map_or(0, |m| m.polylines);
        let flops = |agents| flops_per_evaluation(&self.model.config, agents, polylines);
        let layout = plan_packing(&self.live_agents, active, &class, &flops);
        (layout.cost(&flops) * 5.0 <= unpacked * 4.0).then_some(layout)
    }
}

/// Agents of a scene's validity `[A, W]` with a valid slot: the scene's own.
fn valid_agents(valid: &[f32], agents: usize) -> usize {
    let w = valid.len() / agents.max(1);
    (0..agents)
        .filter(|&a| valid[a * w..(a + 1) * w].iter().any(|&v| v > 0.0))
        .count()
}

/// One past the last of `agents` agent rows of a scene's validity `[A, W]` with a valid slot
/// (at least 1): the rows after it are padding.
fn live_agent_rows(valid: &[f32], agents: usize) -> usize {
    let w = valid.len() / agents.max(1);
    (0..agents)
        .rev()
        .find(|&a| valid[a * w..(a + 1) * w].iter().any(|&v| v > 0.0))
        .map_or(1, |a| a + 1)
}

fn engine_err(e: Error) -> road_model::Error {
    road_model::Error::Engine(e.to_string())
}

impl road_rollout::StepEngine for GpuStepEngine<'_> {
    fn window_slots(&self) -> usize {
        self.model.config.window_slots
    }

    fn position_scale_m(&self) -> Option<f64> {
        Some(self.model.config.position_scale_m)
    }

    fn heading_scale(&self) -> Option<f64> {
        Some(self.model.config.heading_scale)
    }

    fn prepare(
        &mut self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> road_model::Result<()> {
        self.map = Some(
            self.model
                .encode_map(self.ctx, scenes, polylines, map, map_valid)
                .map_err(engine_err)?,
        );
        self.features = features.to_vec();
        self.windows_generation += 1;
        self.scenes = scenes;
        self.agents = agents;
        self.live_agents = vec![agents; scenes];
        self.own_agents = vec![agents; scenes];
        self.own_polylines = if polylines > 0 {
            map_valid
                .chunks(polylines)
                .map(|flags| flags.iter().filter(|&&v| v > 0.0).count())
                .collect()
        } else {
            vec![0; scenes]
        };
        // A new scene set: the next load makes its batch and plan.
        self.batch = None;
        self.plan = None;
        self.window = None;
        self.denoised = None;
        self.estimate_window = None;
        self.compact.clear();
        Ok(())
    }

    fn prepare_scene(
        &mut self,
        scene: usize,
        features: &[f32],
        map: &[f32],
        map_valid: &[f32],
    ) -> road_model::Result<()> {
        let Some(batch_map) = &self.map else {
            return Err(road_model::Error::Engine(
                "prepare_scene before prepare".into(),
            ));
        };
        let (a, p) = (self.agents, batch_map.polylines);
        let q = self.model.config.polyline_points;
        if scene >= self.scenes
            || features.len() != a * 6
            || map.len() != p * q * 2
            || map_valid.len() != p
        {
            return Err(road_model::Error::Engine(format!(
                "prepare_scene {scene}: {} features, {} map values, {} polyline flags for a \
                 batch of {} scenes × {a} agents × {p} polylines of {q} points",
                features.len(),
                map.len(),
                map_valid.len(),
                self.scenes
            )));
        }
        self.features[scene * a * 6..][..a * 6].copy_from_slice(features);
        self.fixed_generation += 1;
        self.windows_generation += 1;
        self.own_polylines[scene] = map_valid.iter().filter(|&&v| v > 0.0).count();
        // The scene's map as the batch holds it (points with agent maps, else its encoded
        // tokens), encoded alone and copied over its rows.
        let one = self
            .model
            .encode_map(self.ctx, 1, p, map, map_valid)
            .map_err(engine_err)?;
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("prepare scene"),
            });
        let data_bytes = (p * batch_map.per_polyline * 4) as u64;
        enc.copy_buffer_to_buffer(
            &one.data,
            0,
            &batch_map.data,
            scene as u64 * data_bytes,
            data_bytes,
        );
        let valid_bytes = (p * 4) as u64;
        enc.copy_buffer_to_buffer(
            &one.valid,
            0,
            &batch_map.valid,
            scene as u64 * valid_bytes,
            valid_bytes,
        );
        // Before the first load the batch takes every scene's features from the host copy.
        if let Some(batch) = &self.batch {
            let embedding = self
                .model
                .embed_agents(self.ctx, features, a)
                .map_err(engine_err)?;
            let bytes = (a * self.model.config.hidden * 4) as u64;
            enc.copy_buffer_to_buffer(
                &embedding,
                0,
                &batch.agent_embedding,
                scene as u64 * bytes,
                bytes,
            );
        }
        self.ctx.queue.submit([enc.finish()]);
        Ok(())
    }

    fn load(&mut self, windows: &[f32], valid: &[f32]) -> road_model::Result<()> {
        self.windows_generation += 1;
        let v_len = self.agents * self.model.config.window_slots;
        if v_len > 0 {
            self.live_agents = valid
                .chunks(v_len)
                .map(|scene| live_agent_rows(scene, self.agents))
                .collect();
            self.own_agents = valid
                .chunks(v_len)
                .map(|scene| valid_agents(scene, self.agents))
                .collect();
        }
        // Later ticks only overwrite the state: buffers, bind groups and the plan stay.
        if let Some(batch) = &self.batch {
            self.ctx
                .queue
                .write_buffer(&batch.x, 0, bytemuck::cast_slice(windows));
            self.ctx
                .queue
                .write_buffer(&batch.valid, 0, bytemuck::cast_slice(valid));
            if let Some(denoised) = &self.denoised {
                self.ctx
                    .queue
                    .write_buffer(denoised, 0, &vec![0u8; windows.len() * 4]);
            }
            return Ok(());
        }
        if self.map.is_none() {
            return Err(road_model::Error::Engine("load before prepare".into()));
        }
        // σ is written per step into the plan's buffers; the batch's own σ is never read.
        let sigma = vec![1.0f32; self.scenes * self.model.config.window_slots];
        let inputs = DenoiseInputs {
            scenes: self.scenes,
            agents: self.agents,
            x: windows,
            sigma: &sigma,
            valid,
            agent_features: &self.features,
        };
        let batch = self
            .model
            .upload_batch(self.ctx, &inputs)
            .map_err(engine_err)?;
        // The whole batch's plan waits for a step that runs the batch in place (`step_rule`).
        self.plan = None;
        self.window = Some(crate::kernels::window::WindowOps::new(
            self.ctx,
            &batch.x,
            self.scenes,
            self.agents,
            self.model.config.window_slots,
        ));
        // Storage buffers start zeroed.
        let denoised = storage_buffer(self.ctx, "denoised (last)", (windows.len() * 4) as u64);
        self.estimate_window = Some(crate::kernels::window::WindowOps::new(
            self.ctx,
            &denoised,
            self.scenes,
            self.agents,
            self.model.config.window_slots,
        ));
        self.denoised = Some(denoised);
        self.batch = Some(batch);
        Ok(())
    }

    fn load_scene(
        &mut self,
        scene: usize,
        window: &[f32],
        valid: &[f32],
    ) -> road_model::Result<()> {
        let batch = self
            .batch
            .as_ref()
            .ok_or_else(|| road_model::Error::Engine("load_scene before load".into()))?;
        let w = self.model.config.window_slots;
        let (x_len, v_len) = (self.agents * w * 3, self.agents * w);
        if window.len() != x_len || valid.len() != v_len || scene >= self.scenes {
            return Err(road_model::Error::Engine(format!(
                "load_scene {scene}: {} states and {} flags for a batch of {} scenes × {x_len} / {v_len}",
                window.len(),
                valid.len(),
                self.scenes
            )));
        }
        self.live_agents[scene] = live_agent_rows(valid, self.agents);
        self.own_agents[scene] = valid_agents(valid, self.agents);
        self.windows_generation += 1;
        self.ctx.queue.write_buffer(
            &batch.x,
            (scene * x_len * 4) as u64,
            bytemuck::cast_slice(window),
        );
        self.ctx.queue.write_buffer(
            &batch.valid,
            (scene * v_len * 4) as u64,
            bytemuck::cast_slice(valid),
        );
        // A rebuilt window has no estimate yet.
        if let Some(denoised) = &self.denoised {
            self.ctx.queue.write_buffer(
                denoised,
                (scene * x_len * 4) as u64,
                &vec![0u8; x_len * 4],
            );
        }
        Ok(())
    }

    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> road_model::Result<()> {
        self.step_rule(sigma_cur, sigma_next, StepRule::Heun { second_evaluation })
    }

    fn step_multistep(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        gamma: &[f32],
    ) -> road_model::Result<()> {
        self.step_rule(sigma_cur, sigma_next, StepRule::Multistep { gamma })
    }

    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> road_model::Result<()> {
        let window = self
            .window
            .as_mut()
            .ok_or_else(|| road_model::Error::Engine("read_emitted before load".into()))?;
        window.emitted(self.ctx, slots, out).map_err(engine_err)
    }

    fn read_emitted_and_denoised(
        &mut self,
        slots: &[Option<usize>],
        out: &mut [f32],
        scenes: &[usize],
        denoised_out: &mut [f32],
    ) -> road_model::Result<()> {
        let ranges = self.denoised_ranges(scenes, denoised_out.len())?;
        if scenes.is_empty() {
            return self.read_emitted(slots, out);
        }
        let (Some(window), Some(denoised)) = (self.window.as_mut(), self.denoised.as_ref()) else {
            return Err(road_model::Error::Engine(
                "read_emitted_and_denoised before load".into(),
            ));
        };
        // The emitted states and the plans in one submission and one wait.
        let copies: Vec<(&wgpu::Buffer, u64, u64)> = ranges
            .iter()
            .map(|&(at, len)| (denoised, at, len))
            .collect();
        let bytes = window
            .emitted_and(self.ctx, slots, out, &copies)
            .map_err(engine_err)?;
        denoised_out.copy_from_slice(bytemuck::cast_slice(&bytes));
        Ok(())
    }

    fn read_denoised(&mut self, scenes: &[usize], out: &mut [f32]) -> road_model::Result<()> {
        let ranges = self.denoised_ranges(scenes, out.len())?;
        if scenes.is_empty() {
            return Ok(());
        }
        let denoised = self
            .denoised
            .as_ref()
            .ok_or_else(|| road_model::Error::Engine("read_denoised before load".into()))?;
        let bytes = read_back_ranges(self.ctx, denoised, &ranges).map_err(engine_err)?;
        out.copy_from_slice(bytemuck::cast_slice(&bytes));
        Ok(())
    }

    fn shift(
        &mut self,
        edits: &[road_rollout::ShiftEdit<'_>],
        shape: road_rollout::ShiftShape,
    ) -> road_model::Result<()> {
        let (Some(batch), Some(window)) = (&self.batch, &mut self.window) else {
            return Err(road_model::Error::Engine("shift before load".into()));
        };
        let v_len = self.agents * self.model.config.window_slots;
        self.windows_generation += 1;
        let list: Vec<ShiftList<'_>> = edits
            .iter()
            .map(|e| (e.scene, e.emitted, e.noise, e.turns))
            .collect();
        // Both windows' shifts in one submission.
        window
            .prepare_shift(self.ctx, &list, shape)
            .map_err(engine_err)?;
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("window_shift"),
            });
        window.record_shift(&mut encoder, &batch.x);
        // The kept estimate moves with its slots (`road_rollout::estimate_shift`): the
        // same kernel with nothing emitted and no noise, its plan turned as the window's.
        if let (Some(estimate_window), Some(denoised)) = (&mut self.estimate_window, &self.denoised)
        {
            let longest = edits
                .iter()
                .map(|e| e.emitted.len().max(e.noise.len()))
                .max()
                .unwrap_or(0);
            if self.zeros.len() < longest {
                self.zeros.resize(longest, 0.0);
            }
            let zeros = &self.zeros;
            let list: Vec<ShiftList<'_>> = edits
                .iter()
                .map(|e| {
                    let (emitted, noise) = (&zeros[..e.emitted.len()], &zeros[..e.noise.len()]);
                    (e.scene, emitted, noise, e.turns)
                })
                .collect();
            let still = road_rollout::ShiftShape {
                observed: shape.observed,
                obs_noise: 0.0,
                sigma_max: 0.0,
            };
            estimate_window
                .prepare_shift(self.ctx, &list, still)
                .map_err(engine_err)?;
            estimate_window.record_shift(&mut encoder, denoised);
        }
        self.ctx.queue.submit([encoder.finish()]);
        for e in edits {
            if e.valid.len() != v_len {
                return Err(road_model::Error::Engine(format!(
                    "shift of scene {}: {} validity flags, expected {v_len}",
                    e.scene,
                    e.valid.len()
                )));
            }
            self.live_agents[e.scene] = live_agent_rows(e.valid, self.agents);
            self.own_agents[e.scene] = valid_agents(e.valid, self.agents);
            self.ctx.queue.write_buffer(
                &batch.valid,
                (e.scene * v_len * 4) as u64,
                bytemuck::cast_slice(e.valid),
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` scenes whose live agent counts cycle through 3 ..= 23, like the validation windows.
    fn mixed_agents(n: usize) -> Vec<usize> {
        (0..n).map(|i| 3 + (i * 7) % 21).collect()
    }

    /// Each scene placed once, within its slot, apart from the others there, with scenes of
    /// one class only; fewer slots than scenes.
    fn check_layout(layout: &Layout, live: &[usize], active: &[usize], class: &[usize]) {
        let mut scenes: Vec<usize> = layout.placed.iter().map(|p| p.scene).collect();
        scenes.sort_unstable();
        let mut want = active.to_vec();
        want.sort_unstable();
        assert_eq!(scenes, want, "each moving scene once: {layout:?}");
        let mut rows = vec![None; layout.slots * layout.agents];
        for p in &layout.placed {
            assert_eq!(p.rows, live[p.scene], "{p:?}: its live rows");
            assert!(
                p.offset + p.rows <= layout.agents,
                "{p:?} overflows its slot"
            );
            let k = active.iter().position(|&i| i == p.scene).unwrap();
            for row in &mut rows[p.slot * layout.agents + p.offset..][..p.rows] {
                assert!(row.is_none(), "{p:?} overlaps another scene");
                *row = Some(class[k]);
            }
        }
        for slot in rows.chunks(layout.agents) {
            let mut classes: Vec<usize> = slot.iter().flatten().copied().collect();
            classes.dedup();
            assert!(classes.len() <= 1, "one class a slot: {classes:?}");
        }
    }

    #[test]
    fn eight_validation_sized_scenes_pack_into_fewer_scenes_of_like_work() {
        let live = [15, 3, 13, 4, 11, 5, 9, 7];
        let active: Vec<usize> = (0..8).collect();
        let class = vec![0; 8];
        let flops = |agents: usize| agents as f64 * (1.0 + agents as f64 / 100.0);
        let layout = plan_packing(&live, &active, &class, &flops);
        check_layout(&layout, &live, &active, &class);
        let own: f64 = live.iter().map(|&a| flops(a)).sum();
        let padded = 8.0 * flops(15);
        assert!(
            layout.cost(&flops) <= 1.25 * own && padded > 1.5 * own,
            "packed {:.1}, own {own:.1}, padded {padded:.1}: {layout:?}",
            layout.cost(&flops)
        );
        // The agent rows' map scenes: each placement's index over its rows.
        let scenes = layout.agent_scenes();
        for (k, p) in layout.placed.iter().enumerate() {
            let at = p.slot * layout.agents + p.offset;
            assert!(scenes[at..at + p.rows].iter().all(|&s| s == k as u32));
        }
    }

    #[test]
    fn scenes_of_different_sigma_rows_never_share_a_slot() {
        let live = mixed_agents(40);
        let active: Vec<usize> = (0..40).collect();
        let class: Vec<usize> = (0..40).map(|k| k % 3).collect();
        let layout = plan_packing(&live, &active, &class, &|a| a as f64);
        check_layout(&layout, &live, &active, &class);
        assert!(layout.slots < 40, "{layout:?}");
        // One scene: alone, at its live rows rounded up to 4.
        let layout = plan_packing(&[6], &[0], &[0], &|a| a as f64);
        assert_eq!((layout.slots, layout.agents), (1, 8));
    }

    #[test]
    fn five_hundred_mixed_scenes_pack_near_their_own_rows() {
        let live = mixed_agents(512);
        let active: Vec<usize> = (0..512).collect();
        let class = vec![0; 512];
        let rows = |agents: usize| agents as f64;
        let layout = plan_packing(&live, &active, &class, &rows);
        check_layout(&layout, &live, &active, &class);
        let own: usize = live.iter().sum();
        let padded = 512 * 24;
        assert!(
            layout.cost(&rows) <= 1.1 * own as f64 && (padded as f64) > 1.5 * own as f64,
            "{} rows packed, {own} own, {padded} padded",
            layout.cost(&rows)
        );
    }
}
