//! `shaders/window.wgsl`: window updates on the device, so that a tick reads back only the
//! emitted slot of each scene. CPU references: `road_rollout::{window_emitted,
//! window_shift}` (what the candle engine runs).

use bytemuck::{Pod, Zeroable};
use road_rollout::ShiftShape;

use super::{Dispatch, Pipeline, record_all, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    count: u32,
    slots: u32,
    agents: u32,
    observed: u32,
    obs_sigma: f32,
    sigma_max: f32,
    _pad0: u32,
    _pad1: u32,
}

/// One scene's shift for [`WindowOps::shift`]: `(scene, emitted [agents, 3], noise
/// [agents, 6], plan turns [agents, 4] or empty)`.
pub type ShiftList<'a> = (usize, &'a [f32], &'a [f32], &'a [f32]);

/// A `per_scene` entry meaning "not read".
const NOT_READ: u32 = u32::MAX;

/// The window kernels bound to one batch's state buffer `x` `[B, A, W, 3]`, with their own
/// staging buffers, made once per scene set.
#[derive(Debug)]
pub struct WindowOps {
    scenes: usize,
    agents: usize,
    slots: usize,
    shift_params: wgpu::Buffer,
    per_scene: wgpu::Buffer,  // [B] u32
    emitted_in: wgpu::Buffer, // [B, A, 3]
    noise: wgpu::Buffer,      // [B, A, 6]
    turns: wgpu::Buffer,      // [B, A, 4]
    emitted_out: wgpu::Buffer,
    scratch: wgpu::Buffer, // [B, A, W, 3]
    gather: Dispatch,
    shift: Dispatch,
    // Host staging, reused.
    per_scene_host: Vec<u32>,
    emitted_host: Vec<f32>,
    noise_host: Vec<f32>,
    turns_host: Vec<f32>,
}

impl WindowOps {
    pub fn new(
        ctx: &GpuContext,
        x: &wgpu::Buffer,
        scenes: usize,
        agents: usize,
        slots: usize,
    ) -> Self {
        let gather_pipeline = Pipeline::new(ctx, Shader::Window, "window_emitted");
        let shift_pipeline = Pipeline::new(ctx, Shader::Window, "window_shift");
        let params = |count: usize| Params {
            count: count as u32,
            slots: slots as u32,
            agents: agents as u32,
            observed: 0,
            obs_sigma: 0.0,
            sigma_max: 0.0,
            _pad0: 0,
            _pad1: 0,
        };
        let uniform = wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST;
        let gather_count = scenes * agents * 3;
        let shift_count = scenes * agents * slots * 3;
        let gather_params = upload(
            ctx,
            "window_emitted params",
            bytemuck::bytes_of(&params(gather_count)),
            uniform,
        );
        let shift_params = upload(
            ctx,
            "window_shift params",
            bytemuck::bytes_of(&params(shift_count)),
            uniform,
        );
        let per_scene = storage_buffer(ctx, "window per scene", (scenes * 4) as u64);
        let emitted_in = storage_buffer(ctx, "window emitted in", (gather_count * 4) as u64);
        let noise = storage_buffer(ctx, "window noise", (scenes * agents * 6 * 4) as u64);
        let turns = storage_buffer(ctx, "window plan turns", (scenes * agents * 4 * 4) as u64);
        let emitted_out = storage_buffer(ctx, "window emitted out", (gather_count * 4) as u64);
        let scratch = storage_buffer(ctx, "window scratch", (shift_count * 4) as u64);
        // The gather reads neither `emitted` (3) nor `noise` (4): its derived layout lacks them.
        let gather = gather_pipeline.prepare(
            ctx,
            &gather_params,
            &[
                (1, x.as_entire_binding()),
                (2, per_scene.as_entire_binding()),
                (5, emitted_out.as_entire_binding()),
            ],
            gather_count as u32,
        );
        let shift = shift_pipeline.prepare_buffers(
            ctx,
            &shift_params,
            &[x, &per_scene, &emitted_in, &noise, &scratch, &turns],
            shift_count as u32,
        );
        Self {
            scenes,
            agents,
            slots,
            shift_params,
            per_scene,
            emitted_in,
            noise,
            turns,
            emitted_out,
            scratch,
            gather,
            shift,
            per_scene_host: vec![0; scenes],
            emitted_host: vec![0.0; gather_count],
            noise_host: vec![0.0; scenes * agents * 6],
            turns_host: vec![0.0; scenes * agents * 4],
        }
    }

    /// Slot `slots[b]` of every scene into `out [B, A, 3]` (zeros where `None`).
    pub fn emitted(
        &mut self,
        ctx: &GpuContext,
        slots: &[Option<usize>],
        out: &mut [f32],
    ) -> Result<()> {
        self.emitted_and(ctx, slots, out, &[])?;
        Ok(())
    }

    /// [`Self::emitted`], and the `(source, offset, bytes)` ranges `also` read back in the
    /// same submission and wait (a round's plans beside its emitted states): their bytes,
    /// concatenated.
    pub fn emitted_and(
        &mut self,
        ctx: &GpuContext,
        slots: &[Option<usize>],
        out: &mut [f32],
        also: &[(&wgpu::Buffer, u64, u64)],
    ) -> Result<Vec<u8>> {
        if slots.len() != self.scenes || out.len() != self.scenes * self.agents * 3 {
            return Err(Error::Input(format!(
                "emitted: {} slots and {} outputs for {} scenes of {} agents",
                slots.len(),
                out.len(),
                self.scenes,
                self.agents
            )));
        }
        for (p, s) in self.per_scene_host.iter_mut().zip(slots) {
            *p = match s {
                Some(s) if *s < self.slots => *s as u32,
                Some(s) => {
                    return Err(Error::Input(format!(
                        "emitted: slot {s} of a {}-slot window",
                        self.slots
                    )));
                }
                None => NOT_READ,
            };
        }
        ctx.queue.write_buffer(
            &self.per_scene,
            0,
            bytemuck::cast_slice(&self.per_scene_host),
        );
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("window_emitted"),
            });
        record_all(
            &mut encoder,
            "window_emitted",
            std::slice::from_ref(&self.gather),
        );
        // The gathered states and `also`, copied after the gather in its submission.
        let emitted_bytes = (out.len() * 4) as u64;
        let mut copies = vec![(&self.emitted_out, 0, emitted_bytes)];
        copies.extend_from_slice(also);
        let mut bytes = super::read_back_after(ctx, encoder, &copies)?;
        let rest = bytes.split_off(emitted_bytes as usize);
        out.copy_from_slice(bytemuck::cast_slice(&bytes));
        Ok(rest)
    }

    /// Shifts the windows of the scenes in `edits` (`(scene, emitted [agents, 3], noise
    /// [agents, 6], plan turns [agents, 4] or empty)`, as `road_rollout::ShiftEdit`) on
    /// the device: `x` → scratch → `x`.
    pub fn shift(
        &mut self,
        ctx: &GpuContext,
        x: &wgpu::Buffer,
        edits: &[ShiftList<'_>],
        shape: ShiftShape,
    ) -> Result<()> {
        self.prepare_shift(ctx, edits, shape)?;
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("window_shift"),
            });
        self.record_shift(&mut encoder, x);
        ctx.queue.submit([encoder.finish()]);
        Ok(())
    }

    /// [`Self::shift`]'s inputs written (the queue's writes land before the next submission).
    pub fn prepare_shift(
        &mut self,
        ctx: &GpuContext,
        edits: &[ShiftList<'_>],
        shape: ShiftShape,
    ) -> Result<()> {
        if shape.observed == 0 || shape.observed >= self.slots {
            return Err(Error::Input(format!(
                "shift: {} observed slots in a {}-slot window",
                shape.observed, self.slots
            )));
        }
        self.per_scene_host.fill(0);
        self.emitted_host.fill(0.0);
        self.noise_host.fill(0.0);
        self.turns_host.fill(0.0);
        for &(scene, emitted, noise, turns) in edits {
            let agents = emitted.len() / 3;
            if scene >= self.scenes
                || agents > self.agents
                || noise.len() != agents * 6
                || !(turns.is_empty() || turns.len() == agents * 4)
            {
                return Err(Error::Input(format!(
                    "shift of scene {scene}: {} emitted values, {} noise draws and {} plan-turn values (batch: {} scenes × {} agents)",
                    emitted.len(),
                    noise.len(),
                    turns.len(),
                    self.scenes,
                    self.agents
                )));
            }
            self.turns_host[scene * self.agents * 4..][..turns.len()].copy_from_slice(turns);
            self.per_scene_host[scene] = 1;
            self.emitted_host[scene * self.agents * 3..][..emitted.len()].copy_from_slice(emitted);
            self.noise_host[scene * self.agents * 6..][..noise.len()].copy_from_slice(noise);
        }
        let params = Params {
            count: (self.scenes * self.agents * self.slots * 3) as u32,
            slots: self.slots as u32,
            agents: self.agents as u32,
            observed: shape.observed as u32,
            obs_sigma: shape.obs_noise,
            sigma_max: shape.sigma_max,
            _pad0: 0,
            _pad1: 0,
        };
        let q = &ctx.queue;
        q.write_buffer(&self.shift_params, 0, bytemuck::bytes_of(&params));
        q.write_buffer(
            &self.per_scene,
            0,
            bytemuck::cast_slice(&self.per_scene_host),
        );
        q.write_buffer(
            &self.emitted_in,
            0,
            bytemuck::cast_slice(&self.emitted_host),
        );
        q.write_buffer(&self.noise, 0, bytemuck::cast_slice(&self.noise_host));
        q.write_buffer(&self.turns, 0, bytemuck::cast_slice(&self.turns_host));
        Ok(())
    }

    /// [`Self::shift`]'s commands on `x` (bound at construction), after [`Self::prepare_shift`].
    pub fn record_shift(&self, encoder: &mut wgpu::CommandEncoder, x: &wgpu::Buffer) {
        record_all(encoder, "window_shift", std::slice::from_ref(&self.shift));
        encoder.copy_buffer_to_buffer(
            &self.scratch,
            0,
            x,
            0,
            (self.scenes * self.agents * self.slots * 3 * 4) as u64,
        );
    }
}
