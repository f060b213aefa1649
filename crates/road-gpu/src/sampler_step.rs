//! The per-slot sampler steps of a batch on the GPU, around [`GpuDenoiser`]'s forward pass: a
//! Heun step (EDM Algorithm 1 per slot: the Euler step, then the second evaluation's
//! correction where σ_next > 0) or the multistep sampler's step (the Euler step and its
//! correction against each slot's previous estimate), prepared once per batch shape
//! ([`HeunPlan`]) so that a step only writes σ and submits. An evaluation leaves out the
//! dispatches that make the map's keys where those in the scratch were made from the same
//! inputs ([`MapInputs`]): a Heun step's second evaluation wherever the step leaves the anchor
//! slot, and a tick's later steps. Kernels: `shaders/heun.wgsl`; CPU reference:
//! `road_rollout::heun`.

use bytemuck::{Pod, Zeroable};

use crate::engine::{DeviceBatch, GpuDenoiser, MapTokens, SamplerUpdate};
use crate::kernels::{Dispatch, Traffic, read_back, storage_buffer};
use crate::{Error, GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct HeunParams {
    count: u32,
    slots: u32,
    agents: u32,
    _pad: u32,
}

impl GpuDenoiser {
    /// Everything a Heun step of this batch needs, made once: buffers, bind groups and the
    /// dispatch lists of both evaluations and the updates. Steps then only write σ.
    pub fn heun_plan(
        &self,
        ctx: &GpuContext,
        batch: &DeviceBatch,
        map: &MapTokens,
    ) -> Result<HeunPlan> {
        let (b, a, w) = (batch.scenes, batch.agents, self.config.window_slots);
        let count = b * a * w * 3;
        let len = (count * 4) as u64;
        let sigma = |label| storage_buffer(ctx, label, (b * w * 4) as u64);
        let (sigma_cur, sigma_next, sigma_eval) =
            (sigma("sigma_cur"), sigma("sigma_next"), sigma("sigma_eval"));
        let (first, second, x_e) = (
            storage_buffer(ctx, "D1", len),
            storage_buffer(ctx, "D2", len),
            storage_buffer(ctx, "x_e", len),
        );
        let scratch = self.scratch(ctx, b, a, map)?;
        let p = HeunParams {
            count: count as u32,
            slots: w as u32,
            agents: a as u32,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        let previous = storage_buffer(ctx, "D_prev", len);
        let gamma = storage_buffer(ctx, "gamma", (b * w * 4) as u64);
        // The first evaluation's last residual chain makes the Euler step and the multistep
        // correction (γ = 0 in a Heun step) where the model runs chains: 1–2 dispatches saved.
        let mut euler = Vec::new();
        let update = SamplerUpdate {
            sigma_next: &sigma_next,
            x_e: &x_e,
            previous: &previous,
            gamma: &gamma,
        };
        let first_prepared = self.prepare_denoise_with_update(
            ctx,
            &mut euler,
            batch,
            (&batch.x, &sigma_cur),
            map,
            &scratch,
            &first,
            Some(update),
        )?;
        let fused_update = first_prepared.fused_update;
        if !fused_update {
            euler.push(self.pipelines.heun_euler.prepare_buffers(
                ctx,
                &params,
                &[&batch.x, &first, &sigma_cur, &sigma_next, &x_e],
                p.count,
            ));
        }
        let mut correct = Vec::new();
        let second_prepared = self.prepare_denoise_with_update(
            ctx,
            &mut correct,
            batch,
            (&x_e, &sigma_eval),
            map,
            &scratch,
            &second,
            None,
        )?;
        correct.push(self.pipelines.heun_correct.prepare_buffers(
            ctx,
            &params,
            &[&batch.x, &first, &sigma_cur, &sigma_next, &x_e, &second],
            p.count,
        ));
        // Bindings of heun.wgsl's shared module that multistep_correct reads.
        let multistep = (!fused_update).then(|| {
            self.pipelines.multistep_correct.prepare(
                ctx,
                &params,
                &[
                    (2, first.as_entire_binding()),
                    (5, x_e.as_entire_binding()),
                    (7, previous.as_entire_binding()),
                    (8, gamma.as_entire_binding()),
                ],
                p.count,
            )
        });
        Ok(HeunPlan {
            sigma_cur,
            sigma_next,
            sigma_eval,
            first,
            second,
            last_had_second: false,
            x_e,
            euler,
            correct,
            previous,
            gamma,
            multistep,
            gamma_zero: true,
            map_keys: MapKeys {
                first: first_prepared.map_keys,
                second: second_prepared.map_keys,
                follow_anchors: first_prepared.keys_follow_anchors,
                anchor_slot: self.config.agent_frame.as_ref().map(|f| f.anchor_slot),
                slots: w,
                keep: ctx.keep_map_keys(),
                made_from: None,
            },
            bytes: len,
            sigma_eval_host: vec![0.0; b * w],
            recorded: Traffic::default(),
        })
    }

    /// One Heun step for the whole batch (per-scene σ_cur, σ_next as `[B, W]`): both
    /// evaluations and the update run on the device in one submission; `batch.x` is updated in
    /// place and read back only when `read` is true.
    #[allow(clippy::too_many_arguments)]
    pub fn heun_step(
        &self,
        ctx: &GpuContext,
        batch: &DeviceBatch,
        map: &MapTokens,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
        read: bool,
    ) -> Result<Option<Vec<f32>>> {
        let mut plan = self.heun_plan(ctx, batch, map)?;
        plan.run(ctx, batch, sigma_cur, sigma_next, second_evaluation)?;
        if !read {
            return Ok(None);
        }
        let bytes = read_back(ctx, &batch.x, plan.bytes)?;
        Ok(Some(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec()))
    }
}

/// A batch's Heun step, prepared: see [`GpuDenoiser::heun_plan`].
#[derive(Debug)]
pub struct HeunPlan {
    sigma_cur: wgpu::Buffer,
    sigma_next: wgpu::Buffer,
    sigma_eval: wgpu::Buffer,
    /// D of the first and the second evaluation `[B, A, W, 3]`.
    first: wgpu::Buffer,
    second: wgpu::Buffer,
    /// Whether the last [`HeunPlan::run`] made the second evaluation.
    last_had_second: bool,
    x_e: wgpu::Buffer,
    euler: Vec<Dispatch>,
    correct: Vec<Dispatch>,
    /// The multistep sampler's previous estimate `[B, A, W, 3]` (filled by the caller before
    /// each multistep step), its γ `[B, W]` and its correction (none where the first
    /// evaluation's last chain makes it, γ = 0 then in a Heun step).
    previous: wgpu::Buffer,
    gamma: wgpu::Buffer,
    multistep: Option<Dispatch>,
    /// Whether `gamma` holds zeros (as made): a Heun step after a multistep one writes them.
    gamma_zero: bool,
    /// Which dispatches make the map's keys, and from what the scratch's were made.
    map_keys: MapKeys,
    bytes: u64,
    sigma_eval_host: Vec<f32>,
    /// The dispatches recorded by the runs since [`HeunPlan::take_traffic`].
    recorded: Traffic,
}

/// Counters a [`HeunPlan`]'s caller bumps whenever what the map's keys are made from may have
/// changed outside the plan's own steps: the windows (`x` and `valid`: agent maps pick from
/// each agent's anchor state; loads, shifts, another plan's step that moved an anchor) and the
/// maps (their points and flags, which scene each row reads). Equal counters: the keys a plan
/// made under them still hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapInputs {
    pub windows: u64,
    pub maps: u64,
}

/// What a [`HeunPlan::run_rule`] did with the map's keys.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KeysOutcome {
    /// Evaluations that made the map's keys (the others kept those in the scratch).
    pub made: u64,
    /// Whether the step left what the keys are made from as it was: no anchor state moved
    /// (σ and γ unchanged at the anchor slot of every scene), or the keys follow the maps
    /// alone. Otherwise the caller bumps [`MapInputs::windows`].
    pub inputs_held: bool,
}

/// Which of a plan's dispatches make the map's keys
/// ([`crate::engine::PreparedEvaluation::map_keys`]), and from what its scratch's were made.
#[derive(Debug)]
struct MapKeys {
    first: std::ops::Range<usize>,
    second: std::ops::Range<usize>,
    follow_anchors: bool,
    anchor_slot: Option<usize>,
    /// W: the σ rows' length per scene.
    slots: usize,
    /// `ContextOptions::keep_map_keys`.
    keep: bool,
    /// The inputs the scratch's keys were made from, when the caller named them.
    made_from: Option<MapInputs>,
}

impl MapKeys {
    /// Whether keys made from `made` still hold under `now`.
    fn hold(&self, made: MapInputs, now: MapInputs) -> bool {
        made.maps == now.maps && (!self.follow_anchors || made.windows == now.windows)
    }

    /// Whether a step with these σ (and γ) rows `[B, W]` leaves every anchor state as it is:
    /// the update writes x back unchanged where σ does not change and γ is 0 (`heun.wgsl`,
    /// `residual_chain.wgsl`'s `sampler_update`).
    fn anchors_hold(&self, sigma_cur: &[f32], sigma_next: &[f32], gamma: Option<&[f32]>) -> bool {
        if !self.follow_anchors {
            return true;
        }
        let Some(anchor) = self.anchor_slot else {
            return false;
        };
        (anchor..sigma_cur.len())
            .step_by(self.slots)
            .all(|at| sigma_cur[at] == sigma_next[at] && gamma.is_none_or(|g| g[at] == 0.0))
    }
}

/// `list`'s dispatches but those at the indices `skip`.
fn unskipped(list: &[Dispatch], skip: std::ops::Range<usize>) -> impl Iterator<Item = &Dispatch> {
    let kept = list.iter().enumerate();
    kept.filter(move |(i, _)| !skip.contains(i)).map(|(_, d)| d)
}

/// How a [`HeunPlan`] moves the windows: Heun (EDM Algorithm 1, the Euler step alone without
/// the second evaluation) or the multistep sampler with its γ `[B, W]`.
#[derive(Debug, Clone, Copy)]
pub enum StepRule<'g> {
    Heun { second_evaluation: bool },
    Multistep { gamma: &'g [f32] },
}

impl HeunPlan {
    /// Writes this step's σ (`[B, W]` each) and submits a Heun step.
    pub fn run(
        &mut self,
        ctx: &GpuContext,
        batch: &DeviceBatch,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> Result<()> {
        let rule = StepRule::Heun { second_evaluation };
        self.run_rule(
            ctx,
            batch,
            sigma_cur,
            sigma_next,
            rule,
            None,
            |_, _| {},
            |_, _| {},
        )
        .map(|_| ())
    }

    /// One step under `rule` in one submission: `before(encoder, D_prev)` records first (a
    /// multistep step's caller copies each scene's previous estimate into `D_prev`, `[B, A, W,
    /// 3]`), then the step, then `then(encoder, D)`, D being this step's last denoiser estimate
    /// `[B, A, W, 3]`. `inputs`: the caller's [`MapInputs`] now (none: the first evaluation
    /// makes the map's keys); the second evaluation keeps the first's where the step left the
    /// anchors as they were.
    #[allow(clippy::too_many_arguments)]
    pub fn run_rule(
        &mut self,
        ctx: &GpuContext,
        batch: &DeviceBatch,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        rule: StepRule<'_>,
        inputs: Option<MapInputs>,
        before: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::Buffer),
        then: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::Buffer),
    ) -> Result<KeysOutcome> {
        let expected = self.sigma_eval_host.len();
        if sigma_cur.len() != expected || sigma_next.len() != expected {
            return Err(Error::Input(format!(
                "σ rows of {} and {} values; the batch is [B, W] = {expected}",
                sigma_cur.len(),
                sigma_next.len()
            )));
        }
        let second_evaluation = match rule {
            StepRule::Heun { second_evaluation } => second_evaluation,
            StepRule::Multistep { gamma } => {
                if gamma.len() != expected {
                    return Err(Error::Input(format!(
                        "{} γ values; the batch is [B, W] = {expected}",
                        gamma.len()
                    )));
                }
                ctx.queue
                    .write_buffer(&self.gamma, 0, bytemuck::cast_slice(gamma));
                self.gamma_zero = false;
                false
            }
        };
        if matches!(rule, StepRule::Heun { .. }) && !self.gamma_zero {
            // The fused Euler step corrects where γ ≠ 0: a Heun step has none.
            ctx.queue
                .write_buffer(&self.gamma, 0, &vec![0u8; self.sigma_eval_host.len() * 4]);
            self.gamma_zero = true;
        }
        ctx.queue
            .write_buffer(&self.sigma_cur, 0, bytemuck::cast_slice(sigma_cur));
        ctx.queue
            .write_buffer(&self.sigma_next, 0, bytemuck::cast_slice(sigma_next));
        // The second evaluation's σ: σ_next, or σ_cur where σ_next is 0 (those slots keep
        // their Euler result, so the value there is never read).
        for (e, (&s, &n)) in self
            .sigma_eval_host
            .iter_mut()
            .zip(sigma_cur.iter().zip(sigma_next))
        {
            *e = if n > 0.0 { n } else { s };
        }
        ctx.queue.write_buffer(
            &self.sigma_eval,
            0,
            bytemuck::cast_slice(&self.sigma_eval_host),
        );
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("heun"),
            });
        before(&mut enc, &self.previous);
        // The map's keys: the first evaluation keeps the scratch's where they were made from
        // the same inputs, the second the first's where this step leaves the anchors.
        let keys = &self.map_keys;
        let keep_first = keys.keep
            && inputs
                .zip(keys.made_from)
                .is_some_and(|(now, made)| keys.hold(made, now));
        let gamma = match rule {
            StepRule::Multistep { gamma } => Some(gamma),
            StepRule::Heun { .. } => None,
        };
        let inputs_held = keys.anchors_hold(sigma_cur, sigma_next, gamma);
        let keep_second = keys.keep && inputs_held;
        let none = 0..0;
        let (skip_first, skip_second) = (
            if keep_first {
                keys.first.clone()
            } else {
                none.clone()
            },
            if keep_second {
                keys.second.clone()
            } else {
                none
            },
        );
        let made = u64::from(!keep_first || keys.first.is_empty())
            + u64::from(second_evaluation && (!keep_second || keys.second.is_empty()));
        let after_euler: &[Dispatch] = match rule {
            StepRule::Heun { .. } if second_evaluation => &self.correct,
            StepRule::Heun { .. } => &[],
            StepRule::Multistep { .. } => self.multistep.as_slice(),
        };
        // One pass per dispatch: measured faster on lavapipe than one pass for all of them.
        for d in unskipped(&self.euler, skip_first).chain(unskipped(after_euler, skip_second)) {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("heun"),
                timestamp_writes: None,
            });
            d.record_counted(&mut pass, &mut self.recorded);
        }
        enc.copy_buffer_to_buffer(&self.x_e, 0, &batch.x, 0, self.bytes);
        self.last_had_second = second_evaluation;
        // The scratch's keys are those of the windows now where the step left the anchors
        // (else of the windows before it).
        self.map_keys.made_from = if keep_second { inputs } else { None };
        then(&mut enc, self.denoised());
        ctx.queue.submit([enc.finish()]);
        Ok(KeysOutcome { made, inputs_held })
    }

    /// Forgets what the scratch's map keys were made from: the next step makes them (the
    /// caller changed the rows' maps, or ran the plan's dispatches outside a step).
    pub fn forget_map_keys(&mut self) {
        self.map_keys.made_from = None;
    }

    /// The dispatches of a step without its second evaluation (one evaluation and the Euler
    /// update), in order: what [`crate::profile`] times one by one.
    pub fn euler_dispatches(&self) -> &[Dispatch] {
        &self.euler
    }

    /// The dispatches a Heun step's second evaluation adds (the evaluation and the correction).
    pub fn correct_dispatches(&self) -> &[Dispatch] {
        &self.correct
    }

    /// The dispatches recorded by the runs since the last call, and their binding bytes.
    pub fn take_traffic(&mut self) -> Traffic {
        std::mem::take(&mut self.recorded)
    }

    /// The multistep sampler's previous estimate `D_prev` `[B, A, W, 3]`, which `run_rule`'s
    /// `before` fills.
    pub(crate) fn previous(&self) -> &wgpu::Buffer {
        &self.previous
    }

    /// Both buffers [`Self::denoised`] may return: the first evaluation's estimate and the
    /// second's.
    pub(crate) fn estimates(&self) -> [&wgpu::Buffer; 2] {
        [&self.first, &self.second]
    }

    /// The last run's last denoiser estimate D `[B, A, W, 3]` (the second evaluation's when
    /// it made one).
    pub fn denoised(&self) -> &wgpu::Buffer {
        if self.last_had_second {
            &self.second
        } else {
            &self.first
        }
    }
}
