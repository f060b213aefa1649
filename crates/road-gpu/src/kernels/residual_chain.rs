//! `shaders/residual_chain.wgsl`: what a block does between two attentions, in one dispatch
//! whose rows stay in workgroup memory: the attention's output projection added into the
//! residual stream, optionally the MLP (its hidden layer 64 units at a time, never in memory),
//! and optionally the next layer behind its layer norm (the next attention's q/k/v, the map's
//! q, or the head with the output preconditioning, and then optionally the sampler's Euler step
//! with the multistep sampler's correction); with `attend` it first makes its rows' attention
//! itself (the queries in `att`, the keys and values bound apart: the map's, or time's). Its `embed_chain`
//! entry makes the token embedding
//! (`shaders/common/embed_token.wgsl`) and the first layer (block 0's q, k, v) the same way. The
//! engine runs them where the layer-by-layer path ran two to six dispatches
//! (`ContextOptions::residual_chains`).

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, read_back, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// Rows (tokens) of one workgroup (the shader's `ROWS`).
pub const ROWS: u32 = 8;
/// Widest hidden width D the workgroup's row tile holds (the shader's `MAX_D`).
pub const MAX_HIDDEN: u32 = 256;
/// Invocations of one workgroup.
const LANES: u32 = 64;
/// Widest head the chain's attention holds (the shader's `MAX_HEAD_DIM`).
pub const MAX_HEAD_DIM: u32 = 64;
/// `anchor_slot` without an agent frame.
pub const NO_FRAME: u32 = u32::MAX;

#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct ChainParams {
    pub rows: u32,
    /// The hidden width D.
    pub d: u32,
    /// The MLP's hidden width; 0 without an MLP.
    pub m: u32,
    pub eps: f32,
    /// Offsets into the bound weights (floats) of `W_oᵀ [D, D]`, `b_o [D]`. Every weight is
    /// transposed (`[in, out]`, [`transpose`]), so that neighbouring invocations load
    /// neighbouring weights.
    pub o_w: u32,
    pub o_b: u32,
    /// `W_1ᵀ [D, M]`, `b_1 [M]`, `W_2ᵀ [M, D]`, `b_2 [D]`.
    pub w1: u32,
    pub b1: u32,
    pub w2: u32,
    pub b2: u32,
    /// The next layer, behind the layer norm (γ, β folded in): `Wᵀ [D, next_out]`, `b`.
    pub next_w: u32,
    pub next_b: u32,
    /// Outputs of the next layer; 0 without one.
    pub next_out: u32,
    /// Outputs per part of `y`, and floats from one part to the next (as `LinearParams`).
    pub part: u32,
    pub part_stride: u32,
    /// 1: the next layer is the head (3 outputs) and `y` receives `D(x; σ)`.
    pub precondition: u32,
    pub slots: u32,
    pub agents: u32,
    pub anchor_slot: u32,
    pub sigma_data: f32,
    pub heading_scale: f32,
    pub residual_scale: f32,
    /// 1 (with `precondition`): also the sampler's step into `x_e`, as `heun_euler` then
    /// `multistep_correct` (`shaders/heun.wgsl`; γ = 0 leaves the Euler step).
    pub update: u32,
    /// `embed_chain`: the agent frame's relative features' multiplier.
    pub relative_scale: f32,
    /// 1: the attention's rows are made here, the attention of `att`'s rows (their q) over the
    /// keys and values in the `map_kv` binding (`heads` of `head_dim`, `scale`; `keys` per agent
    /// row, or with `key_mode` 1 per map scene of `agent_scene`; k at `k_off`, v at `v_off`
    /// floats): the map's over its kept keys, or time's over `qkv`'s k and v parts.
    pub attend: u32,
    pub heads: u32,
    pub head_dim: u32,
    pub scale: f32,
    pub keys: u32,
    /// 0: agent row n's keys are rows n·keys + j; 1: those of its map scene; 2: the agents of
    /// its batch scene at its slot (keys = A), of its own packed scene only.
    pub key_mode: u32,
    pub k_off: u32,
    pub v_off: u32,
    /// 1 (key_mode 2): the agent-pair features from `x` (`agent_pairs.wgsl`'s), with these
    /// length scales in state units (`heading_scale` is the pairs').
    pub pairs: u32,
    pub direction: f32,
    pub near: f32,
    pub far: f32,
}

impl ChainParams {
    /// Invocations of one dispatch.
    pub fn threads(&self) -> u32 {
        self.rows.div_ceil(ROWS) * LANES
    }

    /// The shapes the kernel takes: a clear error for the rest.
    pub fn check(&self) -> Result<()> {
        if self.d == 0 || self.d > MAX_HIDDEN {
            return Err(Error::Input(format!(
                "the residual chain holds hidden widths 1..={MAX_HIDDEN}, not {}",
                self.d
            )));
        }
        if self.next_out > 0 && self.part == 0 {
            return Err(Error::Input("a next layer needs outputs per part".into()));
        }
        if self.update == 1 && self.precondition != 1 {
            return Err(Error::Input(
                "the sampler's step follows the preconditioned head only".into(),
            ));
        }
        if self.attend == 1
            && (self.heads == 0
                || self.head_dim > MAX_HEAD_DIM
                || self.heads * self.head_dim != self.d
                || self.keys == 0)
        {
            return Err(Error::Input(format!(
                "the chain's attention needs heads × head dim = D ({} × {} against {}, head \
                 dim ≤ {MAX_HEAD_DIM}) and keys ({})",
                self.heads, self.head_dim, self.d, self.keys
            )));
        }
        if self.attend == 1 && (self.slots == 0 || (self.key_mode == 2 && self.agents == 0)) {
            return Err(Error::Input(
                "the chain's attention needs the window's slots (and, over agents, the agents)"
                    .into(),
            ));
        }
        if self.precondition == 1 && self.next_out != 3 {
            return Err(Error::Input(format!(
                "the preconditioned head has 3 outputs, not {}",
                self.next_out
            )));
        }
        Ok(())
    }

    /// Floats of `y` the next layer writes: every part, the last `rows · part` long.
    pub fn y_len(&self) -> usize {
        if self.next_out == 0 {
            return 0;
        }
        let parts = self.next_out.div_ceil(self.part) as usize;
        (parts - 1) * self.part_stride as usize + (self.rows * self.part) as usize
    }
}

/// The bindings of an `embed_chain` dispatch: the next layer's weights and the packed
/// embedding weights, `h` (written), `y` (written), `x`, `σ`, `valid` and the agents'
/// embedding.
pub fn embed_bindings<'a>(
    (weights, embed): (wgpu::BindingResource<'a>, wgpu::BindingResource<'a>),
    h: &'a wgpu::Buffer,
    y: wgpu::BindingResource<'a>,
    (x, sigma, valid, agent): (
        &'a wgpu::Buffer,
        &'a wgpu::Buffer,
        &'a wgpu::Buffer,
        &'a wgpu::Buffer,
    ),
) -> Vec<(u32, wgpu::BindingResource<'a>)> {
    vec![
        (1, weights),
        (3, h.as_entire_binding()),
        (4, y),
        (5, x.as_entire_binding()),
        (6, sigma.as_entire_binding()),
        (7, valid.as_entire_binding()),
        (12, agent.as_entire_binding()),
        (13, embed),
    ]
}

/// The attention's bindings of a `residual_chain` dispatch (bound whether it attends or
/// not: the kernel's layout has them): keys and values, key flags, agent rows' map scenes.
pub fn attend_bindings<'a>(
    map_kv: &'a wgpu::Buffer,
    key_valid: &'a wgpu::Buffer,
    agent_scene: &'a wgpu::Buffer,
) -> [(u32, wgpu::BindingResource<'a>); 3] {
    [
        (14, map_kv.as_entire_binding()),
        (15, key_valid.as_entire_binding()),
        (16, agent_scene.as_entire_binding()),
    ]
}

/// `w [out, in]` (a checkpoint's layout) as `[in, out]`, the chain's.
pub fn transpose(w: &[f32], out_dim: usize) -> Vec<f32> {
    let in_dim = w.len() / out_dim.max(1);
    assert_eq!(w.len(), out_dim * in_dim, "w is [out, in]");
    (0..in_dim * out_dim)
        .map(|i| w[(i % out_dim) * in_dim + i / out_dim])
        .collect()
}

/// Host inputs of one run of the chain ([`ResidualChain::run`]): the tests' and the
/// self-test's form.
#[derive(Debug, Clone, Copy)]
pub struct ChainInputs<'a> {
    /// Every weight (transposed) and bias at the offsets `ChainParams` names.
    pub weights: &'a [f32],
    /// `[rows, D]`.
    pub att: &'a [f32],
    /// `[rows, D]`: the residual stream before.
    pub h: &'a [f32],
    /// `y`'s contents before (`ChainParams::y_len`, or `[rows, 3]` when preconditioning).
    pub y: &'a [f32],
    /// Preconditioning: `x [rows, 3]`, `σ [B, W]`, `valid [rows]`.
    pub x: &'a [f32],
    pub sigma: &'a [f32],
    pub valid: &'a [f32],
}

/// The attention a chain with `attend` makes ([`ResidualChain::run_full`]): the keys' and
/// values' buffer (`k_off`, `v_off` into it), each key row's flag, each agent row's map scene.
#[derive(Debug, Clone, Copy)]
pub struct AttendInputs<'a> {
    pub map_kv: &'a [f32],
    pub key_valid: &'a [f32],
    pub agent_scene: &'a [u32],
    /// With `pairs`: the pair weights `[D, 6]` (the states are `ChainInputs::x`); else empty.
    pub pair_k: &'a [f32],
    pub pair_v: &'a [f32],
}

/// The sampler's step a chain with `update` makes from its D: `σ_next [B, W]`, `D_prev [rows,
/// 3]`, `γ [B, W]` (its σ is [`ChainInputs::sigma`]).
#[derive(Debug, Clone, Copy)]
pub struct UpdateInputs<'a> {
    pub sigma_next: &'a [f32],
    pub previous: &'a [f32],
    pub gamma: &'a [f32],
}

/// The `residual_chain` kernel and its `embed_chain` entry (the token embedding, then the
/// first layer), compiled once.
#[derive(Debug)]
pub struct ResidualChain {
    pub pipeline: Pipeline,
    pub embed: Pipeline,
}

/// Host inputs of one run of `embed_chain` ([`ResidualChain::run_embed`]): `x [rows, 3]`,
/// `σ [B, W]`, `valid [rows]`, the agents' embedding `[B·A, D]`, the packed small embedding
/// weights (`shaders/common/embed_token.wgsl`); `weights` hold the next layer at its offsets.
#[derive(Debug, Clone, Copy)]
pub struct EmbedChainInputs<'a> {
    pub weights: &'a [f32],
    pub embed: &'a [f32],
    pub x: &'a [f32],
    pub sigma: &'a [f32],
    pub valid: &'a [f32],
    pub agent: &'a [f32],
}

impl ResidualChain {
    pub fn new(ctx: &GpuContext) -> Self {
        Self {
            pipeline: Pipeline::new(ctx, Shader::ResidualChain, "residual_chain"),
            embed: Pipeline::new(ctx, Shader::ResidualChain, "embed_chain"),
        }
    }

    /// One `embed_chain` dispatch on host data: `(h, y)` after (`h [rows, D]` the embedding,
    /// `y` of `ChainParams::y_len` floats the next layer's parts).
    pub fn run_embed(
        &self,
        ctx: &GpuContext,
        p: ChainParams,
        inputs: &EmbedChainInputs<'_>,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        p.check()?;
        let read = |label: &str, data: &[f32]| {
            upload(
                ctx,
                label,
                bytemuck::cast_slice(data),
                wgpu::BufferUsages::STORAGE,
            )
        };
        let params = upload(
            ctx,
            "params",
            bytemuck::bytes_of(&p),
            wgpu::BufferUsages::UNIFORM,
        );
        let h_len = (p.rows * p.d) as usize;
        let (h, y) = (
            storage_buffer(ctx, "h", (h_len * 4) as u64),
            storage_buffer(ctx, "y", (p.y_len().max(1) * 4) as u64),
        );
        let (weights, embed, x, sigma, valid, agent) = (
            read("weights", inputs.weights),
            read("embed", inputs.embed),
            read("x", inputs.x),
            read("sigma", inputs.sigma),
            read("valid", inputs.valid),
            read("agent", inputs.agent),
        );
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("embed chain"),
            });
        let bound = embed_bindings(
            (weights.as_entire_binding(), embed.as_entire_binding()),
            &h,
            y.as_entire_binding(),
            (&x, &sigma, &valid, &agent),
        );
        self.embed
            .encode_bound(ctx, &mut encoder, &params, &bound, p.threads());
        ctx.queue.submit([encoder.finish()]);
        let floats = |bytes: Vec<u8>| bytemuck::cast_slice::<u8, f32>(&bytes).to_vec();
        Ok((
            floats(read_back(ctx, &h, (h_len * 4) as u64)?),
            floats(read_back(ctx, &y, (p.y_len() * 4) as u64)?),
        ))
    }

    /// One dispatch on host data: `(h after, y after)`.
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: ChainParams,
        inputs: &ChainInputs<'_>,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let (h, y, _) = self.run_with_update(ctx, p, inputs, None)?;
        Ok((h, y))
    }

    /// [`Self::run`] with the sampler's step (`p.update`): `(h, y, x_e)` after, `x_e` empty
    /// without `update`.
    pub fn run_with_update(
        &self,
        ctx: &GpuContext,
        p: ChainParams,
        inputs: &ChainInputs<'_>,
        update: Option<UpdateInputs<'_>>,
    ) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        self.run_full(ctx, p, inputs, update, None)
    }

    /// [`Self::run_with_update`] with its own attention (`p.attend`, `att` holding the queries).
    pub fn run_full(
        &self,
        ctx: &GpuContext,
        p: ChainParams,
        inputs: &ChainInputs<'_>,
        update: Option<UpdateInputs<'_>>,
        attend: Option<AttendInputs<'_>>,
    ) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        p.check()?;
        let read = |label: &str, data: &[f32]| {
            upload(
                ctx,
                label,
                bytemuck::cast_slice(data),
                wgpu::BufferUsages::STORAGE,
            )
        };
        let read_write = |label: &str, data: &[f32]| {
            let buffer = storage_buffer(ctx, label, (data.len().max(1) * 4) as u64);
            ctx.queue
                .write_buffer(&buffer, 0, bytemuck::cast_slice(data));
            buffer
        };
        let params = upload(
            ctx,
            "params",
            bytemuck::bytes_of(&p),
            wgpu::BufferUsages::UNIFORM,
        );
        let (weights, att) = (read("weights", inputs.weights), read("att", inputs.att));
        let (h, y) = (read_write("h", inputs.h), read_write("y", inputs.y));
        let (x, sigma, valid) = (
            read("x", inputs.x),
            read("sigma", inputs.sigma),
            read("valid", inputs.valid),
        );
        let none = UpdateInputs {
            sigma_next: &[0.0],
            previous: &[0.0],
            gamma: &[0.0],
        };
        let u = update.unwrap_or(none);
        let x_e_len = if update.is_some() { inputs.x.len() } else { 1 };
        let (sigma_next, previous, gamma) = (
            read("sigma_next", u.sigma_next),
            read("previous", u.previous),
            read("gamma", u.gamma),
        );
        let x_e = storage_buffer(ctx, "x_e", (x_e_len * 4) as u64);
        let (map_kv, key_valid, agent_scene) = match attend {
            Some(a) => (
                read("map_kv", a.map_kv),
                read("key_valid", a.key_valid),
                upload(
                    ctx,
                    "agent_scene",
                    bytemuck::cast_slice(a.agent_scene),
                    wgpu::BufferUsages::STORAGE,
                ),
            ),
            None => (
                read("map_kv", &[0.0]),
                read("key_valid", &[0.0]),
                read("agent_scene", &[0.0]),
            ),
        };
        let or_one = |v: &[f32]| if v.is_empty() { vec![0.0] } else { v.to_vec() };
        let (pair_k, pair_v) = match attend {
            Some(a) => (
                read("pair_k", &or_one(a.pair_k)),
                read("pair_v", &or_one(a.pair_v)),
            ),
            None => (read("pair_k", &[0.0]), read("pair_v", &[0.0])),
        };
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("residual chain"),
            });
        let buffers = [
            &weights,
            &att,
            &h,
            &y,
            &x,
            &sigma,
            &valid,
            &sigma_next,
            &x_e,
            &previous,
            &gamma,
        ];
        let mut bound: Vec<(u32, wgpu::BindingResource<'_>)> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| (i as u32 + 1, b.as_entire_binding()))
            .collect();
        bound.extend(attend_bindings(&map_kv, &key_valid, &agent_scene));
        bound.extend([
            (17, pair_k.as_entire_binding()),
            (18, pair_v.as_entire_binding()),
        ]);
        self.pipeline
            .encode_bound(ctx, &mut encoder, &params, &bound, p.threads());
        ctx.queue.submit([encoder.finish()]);
        let floats = |bytes: Vec<u8>| bytemuck::cast_slice::<u8, f32>(&bytes).to_vec();
        let h_after = floats(read_back(ctx, &h, (inputs.h.len() * 4) as u64)?);
        let y_after = if inputs.y.is_empty() {
            Vec::new()
        } else {
            floats(read_back(ctx, &y, (inputs.y.len() * 4) as u64)?)
        };
        let x_e_after = if update.is_some() {
            floats(read_back(ctx, &x_e, (x_e_len * 4) as u64)?)
        } else {
            Vec::new()
        };
        Ok((h_after, y_after, x_e_after))
    }
}
