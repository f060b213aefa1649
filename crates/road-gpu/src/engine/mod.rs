//! The denoiser `D(x; σ)` of a checkpoint in WGSL kernels, for many scenes at once, each with
//! its own per-slot noise vector σ[W]. Weights are uploaded once into one buffer (each tensor
//! at an aligned offset); map tokens are computed once per scene set, or, with agent maps, each
//! agent's own from its anchor (`agent_map.wgsl`). The map's keys (those tokens' k, v of every
//! block) are made by an evaluation only when the maps or, with agent maps, the anchors changed
//! since the last one ([`PreparedEvaluation::map_keys`], kept by `sampler_step::HeunPlan`).
//!
//! The forward pass is the one of `docs/checkpoint.md`, kernel by kernel (the agents'
//! `embed_agent` ran once on upload): with agent maps `pick_agent_maps` and the polyline
//! encoder → `linear` map k/v of every block at once → `embed_chain` (the token embedding, then
//! block 0's q/k/v behind its layer norm, one layer of 3·D outputs) → per block three
//! `residual_chain`s, each making the attention before it itself (`ChainParams::attend`): over
//! time (each agent's W slots of `qkv`; the output projection into the residual stream, the
//! agents' q/k/v into `agents_qkv`), over agents (the agents of the row's scene at its slot,
//! with the pair features; output, the map's q into `map_q`), over the map (from `map_q` and the
//! kept keys; output, the MLP, the next block's q/k/v into `qkv` or the head with
//! `precondition_output`'s math and the sampler's update): 13.5 dispatches an evaluation of
//! road20-wide4 with its share of a Heun step's update, 12 where its second evaluation keeps the
//! first's map keys. A chain never writes a buffer it attends from: other workgroups read it in
//! the same dispatch. With `ContextOptions::residual_chains` off (or D past the chain's tile)
//! the embedding is `embed_tokens`, every attention an `attention` (or `pair_attention`), and
//! each layer a `linear` of its own (norm, ReLU and residual add fused in), and the head's
//! output goes through `precondition_output`. The sampler steps around it are in
//! `sampler_step`.

use std::collections::HashMap;
use std::path::Path;

use bytemuck::{Pod, Zeroable};
use road_model::ModelConfig;

use crate::kernels::agent_map::AgentMapParams;
use crate::kernels::agent_pairs::PairAttentionParams;
use crate::kernels::attention::{AttentionParams, MAX_HEAD_DIM, SceneMode, TokenLayout};
use crate::kernels::linear::{Linear, LinearKernel, LinearParams};
use crate::kernels::linear_f16::{LinearF16, LinearF16Kernel};
use crate::kernels::polyline::{PolylineEncoder, PolylineKernel, PolylineParams};
use crate::kernels::residual_chain::{ChainParams, ChainTile, MAX_HIDDEN, ResidualChain};
use crate::kernels::{Dispatch, Pipeline, read_back, record_all, rows_of, storage_buffer, upload};
use crate::shaders::Shader;
pub use crate::tuning::EvalSettings;

mod scratch;
mod weights;

use crate::{Error, GpuContext, Result};
pub(crate) use scratch::Scratch;
use scratch::{PolylineScratch, part_floats};
use weights::{CHAIN_BIAS, CHAIN_WEIGHT, F16_WEIGHT, MAP_KV_ALL, Slice};

const LN_EPS: f32 = 1e-5;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct EmbedParams {
    scenes: u32,
    agents: u32,
    slots: u32,
    hidden: u32,
    sigma_data: f32,
    polylines: u32,
    points: u32,
    anchor_slot: u32,
    heading_scale: f32,
    relative_scale: f32,
    /// `AgentFrame::residual_scale`, 0 without a constant-velocity reference.
    residual_scale: f32,
    _pad: u32,
}

/// `anchor_slot` of the kernels' params when the model has no agent frame.
const NO_FRAME: u32 = u32::MAX;

/// The kernels' `residual_scale`: 0 without a constant-velocity reference.
fn residual_scale(c: &road_model::ModelConfig) -> f32 {
    c.agent_frame
        .as_ref()
        .and_then(|f| f.residual_scale)
        .map_or(0.0, |s| s as f32)
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ElementwiseParams {
    count: u32,
    slots: u32,
    per_slot: u32,
    agents: u32,
    sigma_data: f32,
    anchor_slot: u32,
    heading_scale: f32,
    /// `AgentFrame::residual_scale`, 0 without a constant-velocity reference.
    residual_scale: f32,
    _pad: [u32; 4],
}

/// Whether a model's rows fit the residual chain's tile.
fn fits_chain(c: &ModelConfig) -> bool {
    c.hidden <= MAX_HIDDEN as usize
}

/// The layers of one residual chain (`residual_chain.wgsl`), by checkpoint name.
#[derive(Debug, Clone, Copy)]
struct ChainLayers<'a> {
    /// The attention's output projection.
    output: &'a str,
    /// The MLP's two layers.
    mlp: Option<(&'a str, &'a str)>,
    /// The next layer (behind its folded norm), its outputs and outputs per part.
    next: Option<(&'a str, usize, usize)>,
    /// On the wide tile (`EvalSettings::wide_chains`), else the narrow one.
    wide: bool,
}

/// The attention a residual chain makes before its output projection (`ChainParams::attend`),
/// its queries being the chain's `att` input (from offset 0): the map's (every block's k, v in
/// `map_kv`, each agent row's K polylines or, `key_mode` 1, its scene's P) or time's (the k, v
/// parts of `qkv`, each agent's W slots); k at `k_off`, v at `v_off` floats, each key row's
/// flag, each agent row's map scene.
/// Over agents (`key_mode` 2), `states` are the evaluation's x, which the pair features (with
/// `pairs`: the block's pair weights and the scales) are made from.
#[derive(Debug, Clone)]
struct ChainAttention<'a> {
    /// The queries `[T, D]`, bound as the chain's `att`.
    queries: wgpu::BindingResource<'a>,
    /// The keys and values, k at `k_off`, v at `v_off` floats into the binding.
    map_kv: wgpu::BindingResource<'a>,
    k_off: usize,
    v_off: usize,
    key_valid: &'a wgpu::Buffer,
    agent_scene: &'a wgpu::Buffer,
    keys: u32,
    key_mode: u32,
    /// A: agent rows per batch scene.
    agents: u32,
    states: Option<&'a wgpu::Buffer>,
    pairs: Option<ChainPairs<'a>>,
}

/// The pair features of a chain's agent attention: the block's `pair_k`, `pair_v` `[D, 6]` and
/// the model's pair scales and anchor slot.
#[derive(Debug, Clone)]
struct ChainPairs<'a> {
    pair_k: wgpu::BindingResource<'a>,
    pair_v: wgpu::BindingResource<'a>,
    params: PairAttentionParams,
}

/// What the head's residual chain preconditions with: the evaluation's `x [B, A, W, 3]`,
/// `σ [B, W]` and `valid [B, A, W]`.
#[derive(Debug, Clone, Copy)]
struct Precondition<'a> {
    x: &'a wgpu::Buffer,
    sigma: &'a wgpu::Buffer,
    valid: &'a wgpu::Buffer,
    agents: usize,
    update: Option<SamplerUpdate<'a>>,
}

/// The sampler's step an evaluation's last residual chain makes from its D (`heun_euler`, then
/// `multistep_correct` where γ ≠ 0): `σ_next [B, W]`, the step's `x_e [B, A, W, 3]` (written),
/// `D_prev [B, A, W, 3]` and `γ [B, W]`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SamplerUpdate<'a> {
    pub(crate) sigma_next: &'a wgpu::Buffer,
    pub(crate) x_e: &'a wgpu::Buffer,
    pub(crate) previous: &'a wgpu::Buffer,
    pub(crate) gamma: &'a wgpu::Buffer,
}

/// What [`GpuDenoiser::prepare_denoise_with_update`] prepared, beyond the dispatches.
#[derive(Debug, Clone)]
pub(crate) struct PreparedEvaluation {
    /// Whether the last residual chain makes the sampler's step.
    pub(crate) fused_update: bool,
    /// The dispatches (indices into the list) that make the map's keys: with agent maps the
    /// pick and the polyline encoder, and every block's map k, v where one layer makes them
    /// all (`map_kv_all`). An evaluation whose map inputs are those of the last one leaves them
    /// out ([`crate::sampler_step::HeunPlan`]); their outputs stay in the scratch.
    pub(crate) map_keys: std::ops::Range<usize>,
    /// Whether the keys follow the windows (agent maps pick from each agent's anchor state),
    /// or only the maps.
    pub(crate) keys_follow_anchors: bool,
}

/// What a linear layer fuses with its neighbours (`linear.wgsl`), each a dispatch saved.
#[derive(Debug, Clone, Copy, Default)]
struct Fused {
    /// ReLU after the bias.
    relu: bool,
    /// Add into `y` (the residual stream) instead of overwriting it.
    residual: bool,
    /// The layer norm before the layer, in its prologue (its γ, β folded into the layer's
    /// weights on upload).
    norm: bool,
    /// Outputs per part of `y` (0: one part): stacked projections into separate tensors.
    part: usize,
}

impl Fused {
    fn residual() -> Self {
        Self {
            residual: true,
            ..Self::default()
        }
    }
}

/// Part `index` (`len` floats) of a buffer split into parts `stride` floats apart.
fn part_of(
    buffer: &wgpu::Buffer,
    index: usize,
    stride: usize,
    len: usize,
) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer,
        offset: (index * stride * 4) as u64,
        size: std::num::NonZeroU64::new((len.max(1) * 4) as u64),
    })
}

/// Every pipeline of the engine, compiled once.
#[derive(Debug)]
pub(crate) struct Pipelines {
    linear_rowwise: Linear,
    linear_tiled: Linear,
    linear_blocked: Linear,
    /// The f16 layers' kernel, under [`crate::Precision::F16`].
    linear_f16: Option<LinearF16>,
    attention: Pipeline,
    embed_tokens: Pipeline,
    precondition_output: Pipeline,
    encode_polylines: PolylineEncoder,
    encode_polylines_blocked: PolylineEncoder,
    pub(crate) heun_euler: Pipeline,
    pub(crate) heun_correct: Pipeline,
    pub(crate) multistep_correct: Pipeline,
    pick_agent_maps: Pipeline,
    pair_attention: Pipeline,
    /// The residual chains on the narrow tile (8 rows a workgroup).
    residual_chain: ResidualChain,
    /// On the wide tile (32–64 rows, vec4 weights), where the model's widths and the device's
    /// workgroup memory allow ([`ChainTile::wide`]).
    residual_chain_wide: Option<ResidualChain>,
    /// A batch's rows into and out of compact sub-batches (`GpuStepEngine`).
    pub(crate) compact_rows: crate::kernels::compact::CompactRows,
}

impl Pipelines {
    /// The chain kernels of the wide tile or the narrow one; an error where the wide tile was
    /// asked for and this model or device has none.
    fn chain_kernel(&self, wide: bool) -> Result<&ResidualChain> {
        if !wide {
            return Ok(&self.residual_chain);
        }
        self.residual_chain_wide.as_ref().ok_or_else(|| {
            Error::Input(
                "wide residual chains need D a multiple of 8 and M of 4, and a tile of at \
                 least 16 rows within the device's workgroup memory"
                    .into(),
            )
        })
    }

    fn new(ctx: &GpuContext, config: &ModelConfig) -> Result<Self> {
        let (d, m) = (
            config.hidden as u32,
            (config.hidden * config.mlp_ratio) as u32,
        );
        let wide_tile =
            ChainTile::wide(d, m, ctx.device.limits().max_compute_workgroup_storage_size);
        let residual_chain_wide = match wide_tile.filter(|_| fits_chain(config)) {
            Some(tile) => Some(ResidualChain::with_tile(ctx, tile)?),
            None => None,
        };
        let linear_f16 = match ctx.precision() {
            crate::Precision::F32 => None,
            crate::Precision::F16 => Some(LinearF16::new(ctx, LinearF16Kernel::for_context(ctx))?),
        };
        Ok(Self {
            linear_rowwise: Linear::with_kernel(ctx, LinearKernel::Rowwise),
            linear_tiled: Linear::with_kernel(ctx, LinearKernel::Tiled),
            linear_blocked: Linear::with_kernel(ctx, LinearKernel::Blocked),
            linear_f16,
            attention: Pipeline::new(ctx, Shader::Attention, "attention"),
            embed_tokens: Pipeline::new(ctx, Shader::Embed, "embed_tokens"),
            precondition_output: Pipeline::new(ctx, Shader::Elementwise, "precondition_output"),
            encode_polylines: PolylineEncoder::new(ctx, PolylineKernel::PerPolyline),
            encode_polylines_blocked: PolylineEncoder::new(ctx, PolylineKernel::Blocked),
            heun_euler: Pipeline::new(ctx, Shader::Heun, "heun_euler"),
            heun_correct: Pipeline::new(ctx, Shader::Heun, "heun_correct"),
            multistep_correct: Pipeline::new(ctx, Shader::Heun, "multistep_correct"),
            pick_agent_maps: Pipeline::new(ctx, Shader::AgentMap, "pick_agent_maps"),
            pair_attention: Pipeline::new(ctx, Shader::AgentPairs, "pair_attention"),
            residual_chain: ResidualChain::with_tile(ctx, ChainTile::narrow(d.min(MAX_HIDDEN)))?,
            residual_chain_wide,
            compact_rows: crate::kernels::compact::CompactRows::new(ctx),
        })
    }
}

/// The map of a set of scenes, on the GPU: scene-frame tokens, or (agent maps) the polylines
/// every evaluation picks each agent's own from.
#[derive(Debug)]
pub struct MapTokens {
    /// `[B, P, per_polyline]`: tokens (`D`) or points (`Q · 2`).
    pub(crate) data: wgpu::Buffer,
    pub(crate) valid: wgpu::Buffer, // [B, P]
    pub scenes: usize,
    pub polylines: usize,
    pub(crate) per_polyline: usize,
    /// Agent maps: the polylines K each agent picks (`≤ polylines`).
    pub(crate) picked: Option<usize>,
}

/// Inputs of one batched evaluation, host side.
#[derive(Debug, Clone, Copy)]
pub struct DenoiseInputs<'a> {
    pub scenes: usize,
    pub agents: usize,
    /// `[B, A, W, 3]`.
    pub x: &'a [f32],
    /// `[B, W]`, every entry > 0.
    pub sigma: &'a [f32],
    /// `[B, A, W]`, 1 = valid.
    pub valid: &'a [f32],
    /// `[B, A, 6]`.
    pub agent_features: &'a [f32],
}

/// Device buffers of one batched evaluation.
#[derive(Debug)]
pub struct DeviceBatch {
    pub scenes: usize,
    pub agents: usize,
    pub x: wgpu::Buffer,
    pub sigma: wgpu::Buffer,
    pub valid: wgpu::Buffer,
    pub agent_embedding: wgpu::Buffer, // [B, A, D]
    /// `[B·A]` u32: each agent row's own scene, whose map it picks from and whose agents alone
    /// it attends to. A plain batch's row of scene b holds b ([`plain_agent_scenes`]); a packed
    /// one (several scenes' agents in one of its scenes: `step_engine`) the scene of its map.
    pub agent_scene: wgpu::Buffer,
}

/// `agent_scene` of a plain batch of `scenes × agents`: row a of scene b holds b.
pub fn plain_agent_scenes(scenes: usize, agents: usize) -> Vec<u32> {
    (0..scenes * agents).map(|r| (r / agents) as u32).collect()
}

/// A checkpoint's denoiser on the GPU.
#[derive(Debug)]
pub struct GpuDenoiser {
    pub config: ModelConfig,
    weights: wgpu::Buffer,
    slices: HashMap<String, Slice>,
    pub(crate) pipelines: Pipelines,
    /// The adapter's tuned choices for this model (`crate::tuning`), if attached.
    tuning: Option<crate::tuning::TuneTable>,
}

impl GpuDenoiser {
    /// Loads `config.toml` and `weights.safetensors` of a checkpoint folder.
    pub fn from_checkpoint(ctx: &GpuContext, dir: &Path) -> Result<Self> {
        let loaded = road_model::checkpoint::load(dir, &candle_core::Device::Cpu)
            .map_err(Error::CheckpointLoad)?;
        let path = dir.join(road_model::checkpoint::WEIGHTS_FILE);
        let tensors = road_model::checkpoint::load_tensors(&path, &candle_core::Device::Cpu)
            .map_err(Error::CheckpointLoad)?;
        Self::from_tensors(ctx, &loaded.meta.run.model, tensors)
    }

    /// A checkpoint held in memory (a binary's embedded default): `loaded` is it as
    /// `road_model::checkpoint::load_from_memory` checked it, `weights` the bytes of its
    /// `weights.safetensors`.
    pub fn from_memory(
        ctx: &GpuContext,
        loaded: &road_model::checkpoint::LoadedModel,
        weights: &[u8],
    ) -> Result<Self> {
        let tensors = candle_core::safetensors::load_buffer(weights, &candle_core::Device::Cpu)
            .map_err(|e| Error::Checkpoint(format!("embedded weights: {e}")))?;
        Self::from_tensors(ctx, &loaded.meta.run.model, tensors)
    }

    fn from_tensors(
        ctx: &GpuContext,
        config: &ModelConfig,
        tensors: HashMap<String, candle_core::Tensor>,
    ) -> Result<Self> {
        let mut host = HashMap::new();
        for (name, t) in tensors {
            let values = t
                .flatten_all()
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| Error::Checkpoint(format!("{name}: {e}")))?;
            host.insert(name, values);
        }
        Self::new(ctx, config, &host)
    }

    /// Uploads named f32 tensors (checkpoint names, see `docs/checkpoint.md`).
    pub fn new(
        ctx: &GpuContext,
        config: &ModelConfig,
        tensors: &HashMap<String, Vec<f32>>,
    ) -> Result<Self> {
        let d = config.hidden;
        if config.agent_map.is_some()
            && config.map_polylines > crate::kernels::agent_map::MAX_POLYLINES
        {
            return Err(Error::Checkpoint(format!(
                "agent maps pick from at most {} polylines per scene on the GPU, the model \
                 takes {}",
                crate::kernels::agent_map::MAX_POLYLINES,
                config.map_polylines
            )));
        }
        if d / config.heads > MAX_HEAD_DIM as usize {
            return Err(Error::Checkpoint(format!(
                "head size {} exceeds the kernel's {MAX_HEAD_DIM}",
                d / config.heads
            )));
        }
        let (weights, slices) = weights::lay_out(ctx, config, tensors)?;
        if ctx.residual_chains() && !fits_chain(config) {
            tracing::info!(
                hidden = d,
                "hidden width past the residual chain's tile: layers run one by one"
            );
        }
        Ok(Self {
            config: config.clone(),
            weights,
            slices,
            pipelines: Pipelines::new(ctx, config)?,
            tuning: None,
        })
    }

    fn w(&self, name: &str) -> Result<wgpu::BindingResource<'_>> {
        let s = self
            .slices
            .get(name)
            .ok_or_else(|| Error::Checkpoint(format!("missing tensor `{name}`")))?;
        Ok(wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.weights,
            offset: s.offset,
            size: std::num::NonZeroU64::new(s.size),
        }))
    }

    /// How an evaluation of `tokens` tokens runs on `ctx`: as the adapter's tuning chose for
    /// that size ([`Self::set_tuning`]), else as the context's options say; layer by layer
    /// wherever the model's rows do not fit the chain.
    pub fn settings_for(&self, ctx: &GpuContext, tokens: usize) -> EvalSettings {
        let mut settings = match &self.tuning {
            Some(table) => table.settings_for(tokens),
            None => EvalSettings {
                residual_chains: ctx.residual_chains(),
                wide_chains: ctx.wide_chains(),
                linear_kernel: ctx.named_linear_kernel(),
            },
        };
        // The chains run f32 only: under f16 the layers run one by one.
        settings.residual_chains &=
            fits_chain(&self.config) && ctx.precision() == crate::Precision::F32;
        // The wide tile where this model and device have it, else the narrow one.
        settings.wide_chains &=
            settings.residual_chains && self.pipelines.residual_chain_wide.is_some();
        settings
    }

    /// Runs every evaluation as `tuning` chose for its size (`crate::tuning`), or (`None`) as the
    /// context's options say.
    pub fn set_tuning(&mut self, tuning: Option<crate::tuning::TuneTable>) {
        self.tuning = tuning;
    }

    /// The wide chain tile this denoiser can run on, if its model and device have one.
    pub fn wide_chain_tile(&self) -> Option<ChainTile> {
        self.pipelines.residual_chain_wide.as_ref().map(|k| k.tile)
    }

    /// The tuning this denoiser runs by, if any.
    pub fn tuning(&self) -> Option<&crate::tuning::TuneTable> {
        self.tuning.as_ref()
    }

    /// The one range of the weights buffer holding the chain copies of `layers` (weights
    /// transposed, biases), and each tensor's offset into it in floats.
    fn weight_range(
        &self,
        layers: &[&str],
    ) -> Result<(wgpu::BindingResource<'_>, HashMap<String, u32>)> {
        let names = layers
            .iter()
            .flat_map(|layer| [CHAIN_WEIGHT, CHAIN_BIAS].map(|kind| format!("{layer}.{kind}")));
        let mut found = Vec::new();
        for name in names {
            let slice = *self
                .slices
                .get(&name)
                .ok_or_else(|| Error::Checkpoint(format!("missing tensor `{name}`")))?;
            found.push((name, slice));
        }
        let start = found.iter().map(|(_, s)| s.offset).min().unwrap_or(0);
        // Ending on a whole vec4 (the chains bind the weights as `array<vec4<f32>>`; the
        // buffer is padded to one).
        let end = found
            .iter()
            .map(|(_, s)| s.offset + s.size)
            .max()
            .unwrap_or(4)
            .div_ceil(16)
            * 16;
        let offsets = found
            .into_iter()
            .map(|(name, s)| (name, ((s.offset - start) / 4) as u32))
            .collect();
        let range = wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.weights,
            offset: start,
            size: std::num::NonZeroU64::new(end - start),
        });
        Ok((range, offsets))
    }

    /// One residual chain over `rows` tokens: `h += att · W_oᵀ + b_o`, the MLP, and the next
    /// layer into `y` (its parts `part_stride` floats apart); with `precondition`, the next
    /// layer is the head and `y` receives `D(x; σ)` of the batch.
    #[allow(clippy::too_many_arguments)]
    fn chain(
        &self,
        ctx: &GpuContext,
        ops: &mut Vec<Dispatch>,
        layers: ChainLayers<'_>,
        (att, h, y): (&wgpu::Buffer, &wgpu::Buffer, wgpu::BindingResource<'_>),
        rows: usize,
        part_stride: usize,
        precondition: Option<Precondition<'_>>,
        attend: Option<ChainAttention<'_>>,
    ) -> Result<()> {
        let c = &self.config;
        let kernel = self.pipelines.chain_kernel(layers.wide)?;
        let mut names = vec![layers.output];
        names.extend(layers.mlp.iter().flat_map(|(a, b)| [*a, *b]));
        names.extend(layers.next.iter().map(|n| n.0));
        let (range, at) = self.weight_range(&names)?;
        let offset = |layer: &str, kind: &str| {
            let kind = if kind == "weight" {
                CHAIN_WEIGHT
            } else {
                CHAIN_BIAS
            };
            at[&format!("{layer}.{kind}")]
        };
        let mut p = ChainParams {
            rows: rows as u32,
            d: c.hidden as u32,
            eps: LN_EPS,
            o_w: offset(layers.output, "weight"),
            o_b: offset(layers.output, "bias"),
            anchor_slot: NO_FRAME,
            ..ChainParams::default()
        };
        if let Some((first, second)) = layers.mlp {
            p.m = (c.hidden * c.mlp_ratio) as u32;
            (p.w1, p.b1) = (offset(first, "weight"), offset(first, "bias"));
            (p.w2, p.b2) = (offset(second, "weight"), offset(second, "bias"));
        }
        if let Some((next, outputs, part)) = layers.next {
            (p.next_w, p.next_b) = (offset(next, "weight"), offset(next, "bias"));
            p.next_out = outputs as u32;
            p.part = part as u32;
            p.part_stride = part_stride as u32;
        }
        // Unread without preconditioning: one float of `att` each keeps the layout (of `h` for
        // the written `x_e`: a buffer bound read-only may not be written in the same dispatch).
        let unread = || rows_of(att, 0, 1, 1);
        let unwritten = || rows_of(h, 0, 1, 1);
        let (sigma_next, x_e, previous, gamma) = match precondition.and_then(|pre| pre.update) {
            Some(u) => {
                p.update = 1;
                (
                    u.sigma_next.as_entire_binding(),
                    u.x_e.as_entire_binding(),
                    u.previous.as_entire_binding(),
                    u.gamma.as_entire_binding(),
                )
            }
            None => (unread(), unwritten(), unread(), unread()),
        };
        let (x, sigma, valid) = match precondition {
            Some(pre) => {
                p.precondition = 1;
                p.slots = c.window_slots as u32;
                p.agents = pre.agents as u32;
                p.sigma_data = c.edm.sigma_data as f32;
                p.anchor_slot = c
                    .agent_frame
                    .as_ref()
                    .map_or(NO_FRAME, |f| f.anchor_slot as u32);
                p.heading_scale = c.heading_scale as f32;
                p.residual_scale = residual_scale(c);
                (
                    pre.x.as_entire_binding(),
                    pre.sigma.as_entire_binding(),
                    pre.valid.as_entire_binding(),
                )
            }
            None => (unread(), unread(), unread()),
        };
        // The attention's bindings: the layout has them whether the chain attends or not.
        let (mut states, mut queries) = (None, None);
        let (map_kv, key_valid, agent_scene, pair_k, pair_v) = match attend {
            Some(a) => {
                let heads = c.heads as u32;
                p.attend = 1;
                p.slots = c.window_slots as u32;
                p.agents = a.agents;
                p.heads = heads;
                p.head_dim = c.hidden as u32 / heads;
                p.scale = 1.0 / (p.head_dim as f32).sqrt();
                p.keys = a.keys;
                p.key_mode = a.key_mode;
                (p.k_off, p.v_off) = (a.k_off as u32, a.v_off as u32);
                states = a.states;
                queries = Some(a.queries);
                let (pair_k, pair_v) = match a.pairs {
                    Some(pairs) => {
                        p.pairs = 1;
                        p.anchor_slot = pairs.params.anchor_slot;
                        p.heading_scale = pairs.params.heading_scale;
                        p.direction = pairs.params.direction;
                        p.near = pairs.params.near;
                        p.far = pairs.params.far;
                        (pairs.pair_k, pairs.pair_v)
                    }
                    None => (unread(), unread()),
                };
                (
                    a.map_kv,
                    a.key_valid.as_entire_binding(),
                    a.agent_scene.as_entire_binding(),
                    pair_k,
                    pair_v,
                )
            }
            None => (unread(), unread(), unread(), unread(), unread()),
        };
        kernel.tile.check(&p)?;
        let params = Self::params(ctx, &p);
        let resources = [
            range,
            queries.unwrap_or_else(|| att.as_entire_binding()),
            h.as_entire_binding(),
            y,
            x,
            sigma,
            valid,
            sigma_next,
            x_e,
            previous,
            gamma,
        ];
        let mut bound: Vec<(u32, wgpu::BindingResource<'_>)> = resources
            .into_iter()
            .enumerate()
            .map(|(i, r)| (i as u32 + 1, r))
            .collect();
        bound.extend([
            (14, map_kv),
            (15, key_valid),
            (16, agent_scene),
            (17, pair_k),
            (18, pair_v),
        ]);
        if let Some(states) = states {
            // Agent attention's pair features read the evaluation's states (a chain that
            // attends over agents never preconditions, which binds them too).
            bound[4].1 = states.as_entire_binding();
        }
        ops.push(
            kernel
                .pipeline
                .prepare(ctx, &params, &bound, kernel.tile.threads(&p)),
        );
        Ok(())
    }

    /// Scratch activations for an evaluation of `scenes × agents` on `map`, as
    /// [`Self::settings_for`] runs it.
    pub(crate) fn scratch(
        &self,
        ctx: &GpuContext,
        scenes: usize,
        agents: usize,
        map: &MapTokens,
    ) -> Result<Scratch> {
        let tokens = scenes * agents * self.config.window_slots;
        let chains = self.settings_for(ctx, tokens).residual_chains;
        Scratch::new(ctx, &self.config, (scenes, agents), map, chains)
    }

    pub(crate) fn params<T: Pod>(ctx: &GpuContext, p: &T) -> wgpu::Buffer {
        upload(
            ctx,
            "params",
            bytemuck::bytes_of(p),
            wgpu::BufferUsages::UNIFORM,
        )
    }

    /// One linear layer `layer` (its `.weight`, `.bias`) of `(rows, in, out)`, fused as `fused`
    /// says: `x [rows, in]` → `y` (`[rows, out]`, or its parts), by `kernel` (`None`: chosen by
    /// the layer's size, [`LinearKernel::choose`]).
    #[allow(clippy::too_many_arguments)]
    fn linear(
        &self,
        ctx: &GpuContext,
        ops: &mut Vec<Dispatch>,
        kernel: Option<LinearKernel>,
        layer: &str,
        x: &wgpu::Buffer,
        y: wgpu::BindingResource<'_>,
        (rows, in_dim, out_dim): (usize, usize, usize),
        fused: Fused,
    ) -> Result<()> {
        let part = if fused.part == 0 { out_dim } else { fused.part };
        let p = LinearParams {
            relu: u32::from(fused.relu),
            residual: u32::from(fused.residual),
            norm: u32::from(fused.norm),
            eps: LN_EPS,
            part: part as u32,
            part_stride: part_floats(ctx, rows * part) as u32,
            ..LinearParams::new(rows, in_dim, out_dim)
        };
        let params = Self::params(ctx, &p);
        let f16 =
            (self.pipelines.linear_f16.as_ref()).filter(|_| crate::kernels::linear_f16::fits(&p));
        if let Some(f16) = f16 {
            let resources = [
                x.as_entire_binding(),
                self.w(&format!("{layer}.weight.{F16_WEIGHT}"))?,
                self.w(&format!("{layer}.bias"))?,
                y,
            ];
            ops.push(f16.pipeline.prepare_resources(
                ctx,
                &params,
                &resources,
                f16.kernel.threads(&p),
            ));
            return Ok(());
        }
        let resources = [
            x.as_entire_binding(),
            self.w(&format!("{layer}.weight"))?,
            self.w(&format!("{layer}.bias"))?,
            y,
        ];
        let linear = match LinearKernel::choose(kernel, ctx.is_software(), &p) {
            LinearKernel::Rowwise => &self.pipelines.linear_rowwise,
            LinearKernel::Tiled => &self.pipelines.linear_tiled,
            LinearKernel::Blocked => &self.pipelines.linear_blocked,
        };
        ops.push(linear.pipeline.prepare_resources(
            ctx,
            &params,
            &resources,
            p.threads(linear.kernel),
        ));
        Ok(())
    }

    /// The map of `scenes` scenes: `map [B, P, Q, 2]` (normalised), `map_valid [B, P]`:
    /// scene-frame tokens, or the polylines themselves for a model with agent maps.
    pub fn encode_map(
        &self,
        ctx: &GpuContext,
        scenes: usize,
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<MapTokens> {
        let d = self.config.hidden;
        let q = self.config.polyline_points;
        assert_eq!(map.len(), scenes * polylines * q * 2, "map is [B, P, Q, 2]");
        assert_eq!(map_valid.len(), scenes * polylines, "map_valid is [B, P]");
        // COPY_DST: a scene joining a running batch overwrites its rows (`GpuStepEngine`'s
        // `prepare_scene`).
        let usage = wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST;
        let points = upload(ctx, "map.points", bytemuck::cast_slice(map), usage);
        let valid = upload(ctx, "map.valid", bytemuck::cast_slice(map_valid), usage);
        if let Some(spec) = &self.config.agent_map {
            if polylines > crate::kernels::agent_map::MAX_POLYLINES {
                return Err(Error::Input(format!(
                    "{polylines} polylines per scene: agent maps pick from at most {}",
                    crate::kernels::agent_map::MAX_POLYLINES
                )));
            }
            return Ok(MapTokens {
                data: points,
                valid,
                scenes,
                polylines,
                per_polyline: q * 2,
                picked: Some(road_model::agent_map::polylines_per_agent(
                    spec.polylines,
                    polylines,
                )),
            });
        }
        let encoder = PolylineScratch::new(ctx, scenes * polylines, q, d);
        let mut ops = Vec::new();
        self.prepare_polyline_encoder(ctx, &mut ops, &points, &encoder)?;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("map") });
        record_all(&mut enc, "map", &ops);
        ctx.queue.submit([enc.finish()]);
        Ok(MapTokens {
            data: encoder.tokens,
            valid,
            scenes,
            polylines,
            per_polyline: d,
            picked: None,
        })
    }

    /// The polyline encoder's dispatches (`docs/checkpoint.md`, step 3): `points [n, Q, 2]` →
    /// `scratch.tokens [n, D]`.
    fn prepare_polyline_encoder(
        &self,
        ctx: &GpuContext,
        ops: &mut Vec<Dispatch>,
        points: &wgpu::Buffer,
        scratch: &PolylineScratch,
    ) -> Result<()> {
        let (n, q, d) = (scratch.polylines, scratch.points, self.config.hidden);
        for first in (0..n).step_by(scratch.chunk) {
            let rows = scratch.chunk.min(n - first);
            let p = PolylineParams {
                polylines: rows as u32,
                points: q as u32,
                hidden: d as u32,
                eps: LN_EPS,
            };
            p.check()?;
            let params = Self::params(ctx, &p);
            let resources = [
                rows_of(points, first, rows, q * 2),
                self.w("packed.map_points")?,
                self.w("map_mix.weight")?,
                self.w("map_mix.bias")?,
                self.w("ln_map_out.weight")?,
                self.w("ln_map_out.bias")?,
                rows_of(&scratch.tokens, first, rows, d),
            ];
            let encoder = match ctx.polyline_kernel_for(&p) {
                PolylineKernel::PerPolyline => &self.pipelines.encode_polylines,
                PolylineKernel::Blocked => &self.pipelines.encode_polylines_blocked,
            };
            ops.push(encoder.pipeline.prepare_resources(
                ctx,
                &params,
                &resources,
                p.threads(encoder.kernel),
            ));
        }
        Ok(())
    }

    /// Uploads one evaluation's inputs and embeds the agents' static features.
    pub fn upload_batch(
        &self,
        ctx: &GpuContext,
        inputs: &DenoiseInputs<'_>,
    ) -> Result<DeviceBatch> {
        let (b, a, w) = (inputs.scenes, inputs.agents, self.config.window_slots);
        assert_eq!(inputs.x.len(), b * a * w * 3, "x is [B, A, W, 3]");
        assert_eq!(inputs.sigma.len(), b * w, "sigma is [B, W]");
        assert_eq!(inputs.valid.len(), b * a * w, "valid is [B, A, W]");
        assert_eq!(
            inputs.agent_features.len(),
            b * a * 6,
            "agent features are [B, A, 6]"
        );
        let usage = wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_DST
            | wgpu::BufferUsages::COPY_SRC;
        let x = upload(ctx, "x", bytemuck::cast_slice(inputs.x), usage);
        let sigma = upload(ctx, "sigma", bytemuck::cast_slice(inputs.sigma), usage);
        let valid = upload(ctx, "valid", bytemuck::cast_slice(inputs.valid), usage);
        let agent_embedding = self.embed_agents(ctx, inputs.agent_features, b * a)?;
        let agent_scene = upload(
            ctx,
            "agent scene",
            bytemuck::cast_slice(&plain_agent_scenes(b, a)),
            usage,
        );
        Ok(DeviceBatch {
            scenes: b,
            agents: a,
            x,
            sigma,
            valid,
            agent_embedding,
            agent_scene,
        })
    }

    /// The agents' static embedding `[rows, D]` of their features `[rows, 6]`, submitted.
    pub(crate) fn embed_agents(
        &self,
        ctx: &GpuContext,
        features: &[f32],
        rows: usize,
    ) -> Result<wgpu::Buffer> {
        let d = self.config.hidden;
        let features = upload(
            ctx,
            "agent features",
            bytemuck::cast_slice(features),
            wgpu::BufferUsages::STORAGE,
        );
        let agent_embedding = storage_buffer(ctx, "agent embedding", (rows * d * 4) as u64);
        let mut ops = Vec::new();
        self.linear(
            ctx,
            &mut ops,
            ctx.named_linear_kernel(),
            "embed_agent",
            &features,
            agent_embedding.as_entire_binding(),
            (rows, 6, d),
            Fused::default(),
        )?;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("agents"),
            });
        record_all(&mut enc, "agents", &ops);
        ctx.queue.submit([enc.finish()]);
        Ok(agent_embedding)
    }

    /// Prepares the dispatches of `D(x; σ)` for the batch into `out` (`[B, A, W, 3]`), reading
    /// `x` and `sigma` from the given buffers (so that a sampler can evaluate at intermediate
    /// states) and working in `scratch`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn prepare_denoise(
        &self,
        ctx: &GpuContext,
        ops: &mut Vec<Dispatch>,
        batch: &DeviceBatch,
        x: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        map: &MapTokens,
        scratch: &Scratch,
        out: &wgpu::Buffer,
    ) -> Result<()> {
        self.prepare_denoise_with_update(ctx, ops, batch, (x, sigma), map, scratch, out, None)?;
        Ok(())
    }

    /// [`Self::prepare_denoise`], and `update`, the sampler's step from its D, in the last
    /// residual chain where the evaluation ends in one: whether it did (else the caller
    /// records the step's own dispatches), and which of the dispatches make the map's keys.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn prepare_denoise_with_update(
        &self,
        ctx: &GpuContext,
        ops: &mut Vec<Dispatch>,
        batch: &DeviceBatch,
        (x, sigma): (&wgpu::Buffer, &wgpu::Buffer),
        map: &MapTokens,
        scratch: &Scratch,
        out: &wgpu::Buffer,
        update: Option<SamplerUpdate<'_>>,
    ) -> Result<PreparedEvaluation> {
        let c = &self.config;
        let (b, a, w, d) = (batch.scenes, batch.agents, c.window_slots, c.hidden);
        // Each agent row reads its own scene's map (`agent_scene`: agent maps pick from it,
        // scene-frame map tokens are attended in it), which a packed batch holds apart from
        // its scenes.
        let tokens = b * a * w;
        let m = d * c.mlp_ratio;
        let Scratch {
            h,
            qkv,
            agents_qkv,
            token_part,
            att,
            map_q,
            hidden,
            mkv,
            key_part,
            f,
            agent_maps,
            map_kv_all,
        } = scratch;
        let (token_part, key_part) = (*token_part, *key_part);

        let p = EmbedParams {
            scenes: b as u32,
            agents: a as u32,
            slots: w as u32,
            hidden: d as u32,
            sigma_data: c.edm.sigma_data as f32,
            polylines: 0,
            points: 0,
            anchor_slot: c
                .agent_frame
                .as_ref()
                .map_or(NO_FRAME, |f| f.anchor_slot as u32),
            heading_scale: c.heading_scale as f32,
            relative_scale: c
                .agent_frame
                .as_ref()
                .map_or(1.0, |f| f.relative_scale as f32),
            residual_scale: residual_scale(c),
            _pad: 0,
        };
        let settings = self.settings_for(ctx, tokens);
        let chains = settings.residual_chains;
        if !chains {
            // With chains the embedding is made by the first layer's chain (`embed_chain`).
            let params = Self::params(ctx, &p);
            let resources = [
                x.as_entire_binding(),
                sigma.as_entire_binding(),
                batch.valid.as_entire_binding(),
                batch.agent_embedding.as_entire_binding(),
                self.w("packed.embed")?,
                h.as_entire_binding(),
            ];
            ops.push(self.pipelines.embed_tokens.prepare_resources(
                ctx,
                &params,
                &resources,
                (tokens * d) as u32,
            ));
        }

        // The map's keys: with agent maps the pick and the encoder, then (`map_kv_all`) every
        // block's k, v; contiguous, so that an evaluation keeping them leaves them out.
        let keys_start = ops.len();
        // Agent maps: every agent's polylines, picked from its anchor in this `x`, encoded.
        if let (Some(k), Some(maps), Some(frame)) = (map.picked, agent_maps, &c.agent_frame) {
            let p = AgentMapParams {
                rows: (b * a) as u32,
                agents: a as u32,
                slots: w as u32,
                anchor_slot: frame.anchor_slot as u32,
                polylines: map.polylines as u32,
                points: c.polyline_points as u32,
                picked: k as u32,
                heading_scale: c.heading_scale as f32,
            };
            p.check()?;
            let params = Self::params(ctx, &p);
            ops.push(self.pipelines.pick_agent_maps.prepare_buffers(
                ctx,
                &params,
                &[
                    x,
                    &batch.valid,
                    &map.data,
                    &map.valid,
                    &batch.agent_scene,
                    &maps.points,
                    &maps.valid,
                ],
                p.rows,
            ));
            self.prepare_polyline_encoder(ctx, ops, &maps.points, &maps.encoder)?;
        }

        let heads = c.heads as u32;
        let head_dim = (d / c.heads) as u32;
        let (a32, w32, b32) = (a as u32, w as u32, b as u32);
        let time = TokenLayout {
            inner_count: 1,
            outer_stride: w32,
            inner_stride: 0,
            token_stride: 1,
        };
        let agents = TokenLayout {
            inner_count: w32,
            outer_stride: a32 * w32,
            inner_stride: 1,
            token_stride: w32,
        };
        let scale = 1.0 / (head_dim as f32).sqrt();
        let base = AttentionParams {
            groups: 0,
            heads,
            head_dim,
            queries: 0,
            keys: 0,
            scale,
            scene_agents: a32,
            scene_mode: SceneMode::None as u32,
            q_layout: time,
            kv_layout: time,
            mask_layout: time,
        };
        // The map's keys: each agent's own polylines, or the scene's.
        let (keys, key_rows) = match (agent_maps, map.picked) {
            (Some(maps), Some(k)) => (&maps.encoder.tokens, b * a * k),
            _ => (&map.data, map.scenes * map.polylines),
        };
        if *map_kv_all {
            // Every block's map k, v in one layer: part 2i is block i's k, 2i + 1 its v.
            self.linear(
                ctx,
                ops,
                settings.linear_kernel,
                MAP_KV_ALL,
                keys,
                mkv.as_entire_binding(),
                (key_rows, d, 2 * c.blocks * d),
                Fused {
                    part: d,
                    ..Fused::default()
                },
            )?;
        }
        let map_keys = keys_start..ops.len();
        let keys_follow_anchors = map.picked.is_some() && agent_maps.is_some();
        let qkv_of = |i: usize, part: &str| {
            (
                format!("blocks.{i}.{part}.qkv"),
                Fused {
                    norm: true,
                    part: d,
                    ..Fused::default()
                },
            )
        };
        if chains {
            // The embedding and the first q, k, v in one chain; each chain writes the next
            // attention's after it.
            let (layer, _) = qkv_of(0, "time");
            let (range, at) = self.weight_range(&[&layer])?;
            let chain = ChainParams {
                rows: tokens as u32,
                d: d as u32,
                eps: LN_EPS,
                next_w: at[&format!("{layer}.{CHAIN_WEIGHT}")],
                next_b: at[&format!("{layer}.{CHAIN_BIAS}")],
                next_out: (3 * d) as u32,
                part: d as u32,
                part_stride: token_part as u32,
                slots: p.slots,
                agents: p.agents,
                anchor_slot: p.anchor_slot,
                sigma_data: p.sigma_data,
                heading_scale: p.heading_scale,
                residual_scale: p.residual_scale,
                relative_scale: p.relative_scale,
                ..ChainParams::default()
            };
            let kernel = self.pipelines.chain_kernel(settings.wide_chains)?;
            kernel.tile.check(&chain)?;
            let params = Self::params(ctx, &chain);
            let bound = crate::kernels::residual_chain::embed_bindings(
                (range, self.w("packed.embed")?),
                h,
                qkv.as_entire_binding(),
                (x, sigma, &batch.valid, &batch.agent_embedding),
            );
            ops.push(
                kernel
                    .embed
                    .prepare(ctx, &params, &bound, kernel.tile.threads(&chain)),
            );
        }
        for i in 0..c.blocks {
            let blk = format!("blocks.{i}");
            for (part, attn) in [
                (
                    "time",
                    AttentionParams {
                        groups: b32 * a32,
                        queries: w32,
                        keys: w32,
                        ..base
                    },
                ),
                (
                    "agents",
                    AttentionParams {
                        groups: b32 * w32,
                        queries: a32,
                        keys: a32,
                        q_layout: agents,
                        kv_layout: agents,
                        mask_layout: agents,
                        scene_mode: SceneMode::AgentsOfOneScene as u32,
                        ..base
                    },
                ),
            ] {
                if !chains {
                    // The layer norm and q, k, v: one layer of 3·D outputs into qkv's parts.
                    let (layer, fused) = qkv_of(i, part);
                    self.linear(
                        ctx,
                        ops,
                        settings.linear_kernel,
                        &layer,
                        h,
                        qkv.as_entire_binding(),
                        (tokens, d, 3 * d),
                        fused,
                    )?;
                }
                let [q, k, v] = [0, 1, 2].map(|j| part_of(qkv, j, token_part, tokens * d));
                if chains {
                    // Made by the chain below (`ChainParams::attend`): over time from `qkv`,
                    // over agents from `agents_qkv`, which the time chain wrote.
                } else if part == "agents" && c.agent_pairs.is_some() {
                    // Agent pairs: their features from this `x`, in the pair kernel.
                    let pairs = PairAttentionParams::of(c, b, a)?;
                    let params = Self::params(ctx, &pairs);
                    let resources = [
                        q,
                        k,
                        v,
                        batch.valid.as_entire_binding(),
                        x.as_entire_binding(),
                        self.w(&format!("{blk}.agents.pair_k"))?,
                        self.w(&format!("{blk}.agents.pair_v"))?,
                        batch.agent_scene.as_entire_binding(),
                        att.as_entire_binding(),
                    ];
                    ops.push(self.pipelines.pair_attention.prepare_resources(
                        ctx,
                        &params,
                        &resources,
                        pairs.threads(),
                    ));
                } else {
                    let params = Self::params(ctx, &attn);
                    let resources = [
                        q,
                        k,
                        v,
                        batch.valid.as_entire_binding(),
                        batch.agent_scene.as_entire_binding(),
                        att.as_entire_binding(),
                    ];
                    ops.push(self.pipelines.attention.prepare_resources(
                        ctx,
                        &params,
                        &resources,
                        attn.threads(),
                    ));
                }
                let output = format!("{blk}.{part}.o");
                if chains {
                    // The output projection, then the next layer: after time attention (which
                    // this chain makes, over each agent's W slots of `qkv`) the agents' q, k, v
                    // into `agents_qkv`; after agent attention the map's q into `map_q`, which
                    // the map's chain attends from. Neither may go into a buffer the chain
                    // reads: other workgroups read it in the same dispatch.
                    if part == "time" {
                        let next = qkv_of(i, "agents").0;
                        let layers = ChainLayers {
                            wide: settings.wide_chains,
                            output: &output,
                            mlp: None,
                            next: Some((&next, 3 * d, d)),
                        };
                        let attend = ChainAttention {
                            queries: part_of(qkv, 0, token_part, tokens * d),
                            map_kv: rows_of(qkv, 1, 2, token_part),
                            k_off: 0,
                            v_off: token_part,
                            key_valid: &batch.valid,
                            agent_scene: &batch.agent_scene,
                            keys: w32,
                            key_mode: 0,
                            agents: a32,
                            states: None,
                            pairs: None,
                        };
                        let io = (qkv, h, agents_qkv.as_entire_binding());
                        self.chain(ctx, ops, layers, io, tokens, token_part, None, Some(attend))?;
                    } else {
                        let next = format!("{blk}.map.q");
                        let layers = ChainLayers {
                            wide: settings.wide_chains,
                            output: &output,
                            mlp: None,
                            next: Some((&next, d, d)),
                        };
                        // Over the agents of each scene at each slot, their own packed scene's
                        // only, with the pair features where the model has them.
                        let pairs = match c.agent_pairs {
                            Some(_) => Some(ChainPairs {
                                pair_k: self.w(&format!("{blk}.agents.pair_k"))?,
                                pair_v: self.w(&format!("{blk}.agents.pair_v"))?,
                                params: PairAttentionParams::of(c, b, a)?,
                            }),
                            None => None,
                        };
                        let attend = ChainAttention {
                            queries: part_of(agents_qkv, 0, token_part, tokens * d),
                            map_kv: rows_of(agents_qkv, 1, 2, token_part),
                            k_off: 0,
                            v_off: token_part,
                            key_valid: &batch.valid,
                            agent_scene: &batch.agent_scene,
                            keys: a32,
                            key_mode: 2,
                            agents: a32,
                            states: Some(x),
                            pairs,
                        };
                        let io = (agents_qkv, h, map_q.as_entire_binding());
                        self.chain(ctx, ops, layers, io, tokens, token_part, None, Some(attend))?;
                    }
                } else {
                    // The output projection adds into the residual stream.
                    self.linear(
                        ctx,
                        ops,
                        settings.linear_kernel,
                        &output,
                        att,
                        h.as_entire_binding(),
                        (tokens, d, d),
                        Fused::residual(),
                    )?;
                }
            }
            // Map cross-attention: queries [B, A·W, D], keys [B, P, D]; with agent maps each
            // agent's W queries [B·A, W, D] to its own keys [B·A, K, D].
            if !chains {
                self.linear(
                    ctx,
                    ops,
                    settings.linear_kernel,
                    &format!("{blk}.map.q"),
                    h,
                    part_of(qkv, 0, token_part, tokens * d),
                    (tokens, d, d),
                    Fused {
                        norm: true,
                        ..Fused::default()
                    },
                )?;
            }
            let kv_part = if *map_kv_all {
                2 * i
            } else {
                self.linear(
                    ctx,
                    ops,
                    settings.linear_kernel,
                    &format!("{blk}.map.kv"),
                    keys,
                    mkv.as_entire_binding(),
                    (key_rows, d, 2 * d),
                    Fused {
                        part: d,
                        ..Fused::default()
                    },
                )?;
                0
            };
            let (attn, key_valid) = match (agent_maps, map.picked) {
                (Some(maps), Some(k)) => {
                    let k = k as u32;
                    let attn = AttentionParams {
                        groups: b32 * a32,
                        queries: w32,
                        keys: k,
                        q_layout: time,
                        kv_layout: TokenLayout::contiguous(k),
                        mask_layout: TokenLayout::contiguous(k),
                        ..base
                    };
                    (attn, &maps.valid)
                }
                _ => {
                    // Each agent's tokens attend to its own scene's polylines (`agent_scene`:
                    // a packed batch holds several scenes' maps apart from its scenes).
                    let pl = map.polylines as u32;
                    let attn = AttentionParams {
                        groups: b32 * a32,
                        queries: w32,
                        keys: pl,
                        q_layout: time,
                        kv_layout: TokenLayout::contiguous(pl),
                        mask_layout: TokenLayout::contiguous(pl),
                        scene_mode: SceneMode::KeysOfTheAgentsScene as u32,
                        ..base
                    };
                    (attn, &map.valid)
                }
            };
            // With chains the map's chain attends itself (`ChainParams::attend`).
            let attend = ChainAttention {
                queries: map_q.as_entire_binding(),
                map_kv: rows_of(mkv, kv_part, 2, key_part),
                k_off: 0,
                v_off: key_part,
                key_valid,
                agent_scene: &batch.agent_scene,
                keys: attn.keys,
                key_mode: u32::from(attn.scene_mode == SceneMode::KeysOfTheAgentsScene as u32),
                agents: a32,
                states: None,
                pairs: None,
            };
            if !chains {
                let params = Self::params(ctx, &attn);
                let resources = [
                    part_of(qkv, 0, token_part, tokens * d),
                    part_of(mkv, kv_part, key_part, key_rows * d),
                    part_of(mkv, kv_part + 1, key_part, key_rows * d),
                    key_valid.as_entire_binding(),
                    batch.agent_scene.as_entire_binding(),
                    att.as_entire_binding(),
                ];
                ops.push(self.pipelines.attention.prepare_resources(
                    ctx,
                    &params,
                    &resources,
                    attn.threads(),
                ));
            }
            let (map_o, mlp_in, mlp_out) = (
                format!("{blk}.map.o"),
                format!("{blk}.mlp_in"),
                format!("{blk}.mlp_out"),
            );
            if chains {
                // The map's output projection and the MLP, then the next block's q, k, v, or
                // after the last block the head and the output preconditioning.
                let last = i + 1 == c.blocks;
                let next = if last {
                    "head".to_string()
                } else {
                    qkv_of(i + 1, "time").0
                };
                let layers = ChainLayers {
                    wide: settings.wide_chains,
                    output: &map_o,
                    mlp: Some((&mlp_in, &mlp_out)),
                    next: Some(if last {
                        (&next, 3, 3)
                    } else {
                        (&next, 3 * d, d)
                    }),
                };
                // Its input is the map's q, from which it attends.
                let attend = Some(attend);
                if last {
                    let precondition = Precondition {
                        x,
                        sigma,
                        valid: &batch.valid,
                        agents: a,
                        update,
                    };
                    let io = (map_q, h, out.as_entire_binding());
                    self.chain(ctx, ops, layers, io, tokens, 0, Some(precondition), attend)?;
                } else {
                    let io = (map_q, h, qkv.as_entire_binding());
                    self.chain(ctx, ops, layers, io, tokens, token_part, None, attend)?;
                }
                continue;
            }
            self.linear(
                ctx,
                ops,
                settings.linear_kernel,
                &map_o,
                att,
                h.as_entire_binding(),
                (tokens, d, d),
                Fused::residual(),
            )?;
            // MLP: the layer norm and ReLU fused into its first layer, the residual into its
            // second.
            self.linear(
                ctx,
                ops,
                settings.linear_kernel,
                &mlp_in,
                h,
                hidden.as_entire_binding(),
                (tokens, d, m),
                Fused {
                    relu: true,
                    norm: true,
                    ..Fused::default()
                },
            )?;
            self.linear(
                ctx,
                ops,
                settings.linear_kernel,
                &mlp_out,
                hidden,
                h.as_entire_binding(),
                (tokens, m, d),
                Fused::residual(),
            )?;
        }
        let prepared = |fused_update| PreparedEvaluation {
            fused_update,
            map_keys: map_keys.clone(),
            keys_follow_anchors,
        };
        if chains {
            // The last block's chain made the sampler's step too.
            return Ok(prepared(update.is_some() && c.blocks > 0));
        }
        self.linear(
            ctx,
            ops,
            settings.linear_kernel,
            "head",
            h,
            f.as_entire_binding(),
            (tokens, d, 3),
            Fused {
                norm: true,
                ..Fused::default()
            },
        )?;
        let p = ElementwiseParams {
            count: tokens as u32,
            slots: w32,
            per_slot: 3,
            agents: a32,
            sigma_data: c.edm.sigma_data as f32,
            anchor_slot: c
                .agent_frame
                .as_ref()
                .map_or(NO_FRAME, |f| f.anchor_slot as u32),
            heading_scale: c.heading_scale as f32,
            residual_scale: residual_scale(c),
            _pad: [0; 4],
        };
        let params = Self::params(ctx, &p);
        ops.push(self.pipelines.precondition_output.prepare_buffers(
            ctx,
            &params,
            &[x, f, sigma, &batch.valid, out],
            p.count,
        ));
        Ok(prepared(false))
    }

    /// One evaluation, read back: `D(x; σ)` as `[B, A, W, 3]`.
    pub fn denoise(
        &self,
        ctx: &GpuContext,
        inputs: &DenoiseInputs<'_>,
        map: &MapTokens,
    ) -> Result<Vec<f32>> {
        let batch = self.upload_batch(ctx, inputs)?;
        let len = (inputs.x.len() * 4) as u64;
        let out = storage_buffer(ctx, "denoised", len);
        let scratch = self.scratch(ctx, batch.scenes, batch.agents, map)?;
        let mut ops = Vec::new();
        self.prepare_denoise(
            ctx,
            &mut ops,
            &batch,
            &batch.x,
            &batch.sigma,
            map,
            &scratch,
            &out,
        )?;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("denoise"),
            });
        record_all(&mut enc, "denoise", &ops);
        ctx.queue.submit([enc.finish()]);
        let bytes = read_back(ctx, &out, len)?;
        Ok(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec())
    }
}
