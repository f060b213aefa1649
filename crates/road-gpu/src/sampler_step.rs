//! The per-slot sampler steps of a batch on the GPU, around [`GpuDenoiser`]'s forward pass: a
//! Heun step (EDM Algorithm 1 per slot: the Euler step, then the second evaluation's
//! correction where σ_next > 0) or the multistep sampler's step (the Euler step and its
//! correction against each slot's previous estimate), prepared once per batch shape
//! ([`HeunPlan`]) so that a step only writes σ and submits. Kernels: `shaders/heun.wgsl`; CPU
//! reference: `road_rollout::heun`.

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
        let fused_update = self.prepare_denoise_with_update(
            ctx,
            &mut euler,
            batch,
            (&batch.x, &sigma_cur),
            map,
            &scratch,
            &first,
            Some(update),
        )?;
        if !fused_update {
            euler.push(self.pipelines.heun_euler.prepare_buffers(
                ctx,
                &params,
                &[&batch.x, &first, &sigma_cur, &sigma_next, &x_e],
                p.count,
            ));
        }
        let mut correct = Vec::new();
        self.prepare_denoise(
            ctx,
            &mut correct,
            batch,
            &x_e,
            &sigma_eval,
            map,
            &scratch,
            &second,
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
    bytes: u64,
    sigma_eval_host: Vec<f32>,
    /// The dispatches recorded by the runs since [`HeunPlan::take_traffic`].
    recorded: Traffic,
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
            |_, _| {},
            |_, _| {},
        )
    }

    /// One step under `rule` in one submission: `before(encoder, D_prev)` records first (a
    /// multistep step's caller copies each scene's previous estimate into `D_prev`, `[B, A, W,
    /// 3]`), then the step, then `then(encoder, D)`, D being this step's last denoiser estimate
    /// `[B, A, W, 3]`.
    #[allow(clippy::too_many_arguments)]
    pub fn run_rule(
        &mut self,
        ctx: &GpuContext,
        batch: &DeviceBatch,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        rule: StepRule<'_>,
        before: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::Buffer),
        then: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::Buffer),
    ) -> Result<()> {
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
        let after_euler: &[Dispatch] = match rule {
            StepRule::Heun { .. } if second_evaluation => &self.correct,
            StepRule::Heun { .. } => &[],
            StepRule::Multistep { .. } => self.multistep.as_slice(),
        };
        // One pass per dispatch: measured faster on lavapipe than one pass for all of them.
        for d in self.euler.iter().chain(after_euler) {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("heun"),
                timestamp_writes: None,
            });
            d.record_counted(&mut pass, &mut self.recorded);
        }
        enc.copy_buffer_to_buffer(&self.x_e, 0, &batch.x, 0, self.bytes);
        self.last_had_second = second_evaluation;
        then(&mut enc, self.denoised());
        ctx.queue.submit([enc.finish()]);
        Ok(())
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
