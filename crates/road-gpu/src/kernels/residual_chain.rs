//! `shaders/residual_chain.wgsl`: what a block does between two attentions, in one dispatch
//! whose rows stay in workgroup memory: the attention's output projection added into the
//! residual stream, optionally the MLP (its hidden layer a chunk of units at a time, never in
//! memory),
//! and optionally the next layer behind its layer norm (the next attention's q/k/v, the map's
//! q, or the head with the output preconditioning, and then optionally the sampler's Euler step
//! with the multistep sampler's correction); with `attend` it first makes its rows' attention
//! itself (the queries in `att`, the keys and values bound apart: the map's, or time's). Its `embed_chain`
//! entry makes the token embedding
//! (`shaders/common/embed_token.wgsl`) and the first layer (block 0's q, k, v) the same way. The
//! engine runs them where the layer-by-layer path ran two to six dispatches
//! (`ContextOptions::residual_chains`).
//! The tile's shape is a pipeline's ([`ChainTile`]): narrow (8 rows, blocks of 4 × 4, any
//! layout) or wide (32–64 rows, blocks of 8 × 8, weights read as vec4), which the autotuner
//! chooses between by batch size.

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, read_back, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// Widest hidden width D a chain's tile is made for.
pub const MAX_HIDDEN: u32 = 256;
/// The MLP's hidden units a wide tile holds at a time.
const WIDE_UNITS: u32 = 64;
/// Most invocations of a wide tile's workgroup.
const WIDE_MAX_LANES: u32 = 256;
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

/// The shape of a chain pipeline's tile: the shader's override constants.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChainTile {
    /// Rows (tokens) of one workgroup (`CHAIN_ROWS`).
    pub rows: u32,
    /// Invocations of one workgroup (`CHAIN_LANES`).
    pub lanes: u32,
    /// The MLP's hidden units a chunk (`CHAIN_UNITS`).
    pub units: u32,
    /// Floats from one row of the tile to the next (`TILE_D`): the widest D it holds, odd.
    pub tile_d: u32,
    /// Blocks of 8 × 8 with vec4 weight reads (`WIDE_BLOCKS`), else 4 × 4 read by floats.
    pub wide_blocks: bool,
}

impl ChainTile {
    /// 8 rows, 64 invocations, blocks of 4 × 4: the most workgroups at small batches, any
    /// shape and offsets. Holds D up to `max_d`.
    pub fn narrow(max_d: u32) -> Self {
        Self {
            rows: 8,
            lanes: 64,
            units: 128,
            tile_d: odd_at_least(max_d),
            wide_blocks: false,
        }
    }

    /// The wide tile for a model of hidden width `d` and MLP width `m` on a device whose
    /// workgroups hold `workgroup_bytes`: the most rows of 64, 32 or 16 that fit, blocks of
    /// 8 × 8, as many invocations as blocks of a D-wide layer (a multiple of 32). `None` where
    /// D is not a multiple of 8, M not of 4, D past [`MAX_HIDDEN`], or not even 16 rows fit.
    pub fn wide(d: u32, m: u32, workgroup_bytes: u32) -> Option<Self> {
        if d == 0 || !d.is_multiple_of(8) || !m.is_multiple_of(4) || d > MAX_HIDDEN {
            return None;
        }
        [64, 32, 16].into_iter().find_map(|rows| {
            let blocks = (rows / 8) * (d / 8);
            let tile = Self {
                rows,
                lanes: blocks.div_ceil(32).clamp(1, WIDE_MAX_LANES / 32) * 32,
                units: WIDE_UNITS,
                tile_d: odd_at_least(d),
                wide_blocks: true,
            };
            (tile.workgroup_bytes() <= workgroup_bytes).then_some(tile)
        })
    }

    /// Bytes of workgroup memory a workgroup takes (the shader's `tile`, `hidden_units`,
    /// `tile_stats`).
    pub fn workgroup_bytes(&self) -> u32 {
        4 * self.rows * (self.tile_d + self.units + 1) + 8 * self.rows
    }

    /// Invocations of a dispatch over `p.rows` tokens.
    pub fn threads(&self, p: &ChainParams) -> u32 {
        p.rows.div_ceil(self.rows) * self.lanes
    }

    /// The shader's override constants for this tile.
    fn constants(&self) -> [(&'static str, f64); 5] {
        [
            ("CHAIN_ROWS", f64::from(self.rows)),
            ("CHAIN_LANES", f64::from(self.lanes)),
            ("CHAIN_UNITS", f64::from(self.units)),
            ("TILE_D", f64::from(self.tile_d)),
            ("WIDE_BLOCKS", f64::from(u8::from(self.wide_blocks))),
        ]
    }

    /// `p` on this tile: [`ChainParams::check`], D within the tile and, for wide blocks, every
    /// width, stride and weight offset a multiple of 4 (their vec4 reads).
    pub fn check(&self, p: &ChainParams) -> Result<()> {
        p.check()?;
        if p.d > self.tile_d {
            return Err(Error::Input(format!(
                "hidden width {} past the chain tile's {}",
                p.d, self.tile_d
            )));
        }
        if self.wide_blocks {
            let mut quads = vec![("d", p.d), ("m", p.m), ("o_w", p.o_w), ("o_b", p.o_b)];
            if p.m > 0 {
                quads.extend([("w1", p.w1), ("b1", p.b1), ("w2", p.w2), ("b2", p.b2)]);
            }
            if p.next_out > 0 && p.precondition == 0 {
                quads.extend([
                    ("next_out", p.next_out),
                    ("next_w", p.next_w),
                    ("next_b", p.next_b),
                ]);
            }
            if let Some((name, value)) = quads.into_iter().find(|(_, v)| !v.is_multiple_of(4)) {
                return Err(Error::Input(format!(
                    "the wide chain tile reads weights as vec4: `{name}` ({value}) must be a \
                     multiple of 4"
                )));
            }
        }
        Ok(())
    }
}

/// The least odd number ≥ `n` (rows of the tile that far apart fall in distinct banks).
fn odd_at_least(n: u32) -> u32 {
    n | 1
}

impl ChainParams {
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
/// first layer), compiled once for one tile.
#[derive(Debug)]
pub struct ResidualChain {
    pub pipeline: Pipeline,
    pub embed: Pipeline,
    pub tile: ChainTile,
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
    /// The narrow tile for every D up to [`MAX_HIDDEN`] (its workgroup fits any device).
    pub fn new(ctx: &GpuContext) -> Self {
        let tile = ChainTile::narrow(MAX_HIDDEN);
        Self {
            pipeline: Self::pipeline(ctx, "residual_chain", tile),
            embed: Self::pipeline(ctx, "embed_chain", tile),
            tile,
        }
    }

    /// The kernels for `tile`; an error where the device's workgroups cannot hold it.
    pub fn with_tile(ctx: &GpuContext, tile: ChainTile) -> Result<Self> {
        let limits = ctx.device.limits();
        let available = limits.max_compute_workgroup_storage_size;
        if tile.workgroup_bytes() > available
            || tile.lanes > limits.max_compute_invocations_per_workgroup
        {
            return Err(Error::Device(format!(
                "the chain tile {tile:?} takes {} bytes of workgroup memory and {} \
                 invocations; the device's workgroups hold {available} and {}",
                tile.workgroup_bytes(),
                tile.lanes,
                limits.max_compute_invocations_per_workgroup
            )));
        }
        Ok(Self {
            pipeline: Self::pipeline(ctx, "residual_chain", tile),
            embed: Self::pipeline(ctx, "embed_chain", tile),
            tile,
        })
    }

    fn pipeline(ctx: &GpuContext, entry: &'static str, tile: ChainTile) -> Pipeline {
        Pipeline::with_constants(
            ctx,
            Shader::ResidualChain,
            entry,
            tile.lanes,
            &tile.constants(),
        )
    }

    /// One `embed_chain` dispatch on host data: `(h, y)` after (`h [rows, D]` the embedding,
    /// `y` of `ChainParams::y_len` floats the next layer's parts).
    pub fn run_embed(
        &self,
        ctx: &GpuContext,
        p: ChainParams,
        inputs: &EmbedChainInputs<'_>,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        self.tile.check(&p)?;
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
            read("weights", &in_quads(inputs.weights)),
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
            .encode_bound(ctx, &mut encoder, &params, &bound, self.tile.threads(&p));
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
        self.tile.check(&p)?;
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
        let (weights, att) = (
            read("weights", &in_quads(inputs.weights)),
            read("att", inputs.att),
        );
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
            .encode_bound(ctx, &mut encoder, &params, &bound, self.tile.threads(&p));
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

/// `weights` padded with zeros to whole vec4s (the kernel binds them as `array<vec4<f32>>`).
fn in_quads(weights: &[f32]) -> Vec<f32> {
    let mut padded = weights.to_vec();
    padded.resize(weights.len().div_ceil(4).max(1) * 4, 0.0);
    padded
}
