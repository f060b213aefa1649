//! The denoiser `D(x; σ)` of a checkpoint in WGSL kernels, for many scenes at once, each with
//! its own per-slot noise vector σ[W]. Weights are uploaded once into one buffer (each tensor
//! at an aligned offset); map tokens are computed once per scene set.
//!
//! The forward pass is the one of `docs/checkpoint.md`, kernel by kernel:
//! `linear` (embed_agent) → `embed_tokens` → per block: `layer_norm`, `linear` q/k/v,
//! `attention` (time, agents, map layouts), `linear` o, `add_in_place`, MLP → `layer_norm`,
//! `linear` head → `precondition_output`.

use std::collections::HashMap;
use std::path::Path;

use bytemuck::{Pod, Zeroable};
use road_model::ModelConfig;

use crate::kernels::attention::{AttentionParams, MAX_HEAD_DIM, TokenLayout};
use crate::kernels::layer_norm::LayerNormParams;
use crate::kernels::linear::LinearParams;
use crate::kernels::{Pipeline, read_back, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

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
    _pad: u32,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ElementwiseParams {
    count: u32,
    slots: u32,
    per_slot: u32,
    agents: u32,
    sigma_data: f32,
    hidden: u32,
    points: u32,
    _pad: u32,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct HeunParams {
    count: u32,
    slots: u32,
    agents: u32,
    _pad: u32,
}

/// Every pipeline of the engine, compiled once.
#[derive(Debug)]
struct Pipelines {
    linear: Pipeline,
    layer_norm: Pipeline,
    attention: Pipeline,
    embed_tokens: Pipeline,
    add_in_place: Pipeline,
    precondition_output: Pipeline,
    embed_map_points: Pipeline,
    max_over_points: Pipeline,
    heun_euler: Pipeline,
    heun_correct: Pipeline,
}

impl Pipelines {
    fn new(ctx: &GpuContext) -> Self {
        Self {
            linear: Pipeline::new(ctx, Shader::Linear, "linear"),
            layer_norm: Pipeline::new(ctx, Shader::LayerNorm, "layer_norm"),
            attention: Pipeline::new(ctx, Shader::Attention, "attention"),
            embed_tokens: Pipeline::new(ctx, Shader::Embed, "embed_tokens"),
            add_in_place: Pipeline::new(ctx, Shader::Elementwise, "add_in_place"),
            precondition_output: Pipeline::new(ctx, Shader::Elementwise, "precondition_output"),
            embed_map_points: Pipeline::new(ctx, Shader::Elementwise, "embed_map_points"),
            max_over_points: Pipeline::new(ctx, Shader::Elementwise, "max_over_points"),
            heun_euler: Pipeline::new(ctx, Shader::Heun, "heun_euler"),
            heun_correct: Pipeline::new(ctx, Shader::Heun, "heun_correct"),
        }
    }
}

/// A tensor's place in the weights buffer (bytes).
#[derive(Debug, Clone, Copy)]
struct Slice {
    offset: u64,
    size: u64,
}

/// Map tokens of a set of scenes, on the GPU.
#[derive(Debug)]
pub struct MapTokens {
    tokens: wgpu::Buffer, // [B, P, D]
    valid: wgpu::Buffer,  // [B, P]
    pub scenes: usize,
    pub polylines: usize,
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
}

/// A checkpoint's denoiser on the GPU.
#[derive(Debug)]
pub struct GpuDenoiser {
    pub config: ModelConfig,
    weights: wgpu::Buffer,
    slices: HashMap<String, Slice>,
    pipelines: Pipelines,
}

impl GpuDenoiser {
    /// Loads `config.toml` and `weights.safetensors` of a checkpoint folder.
    pub fn from_checkpoint(ctx: &GpuContext, dir: &Path) -> Result<Self> {
        let loaded = road_model::checkpoint::load(dir, &candle_core::Device::Cpu)
            .map_err(|e| Error::Checkpoint(e.to_string()))?;
        let path = dir.join(road_model::checkpoint::WEIGHTS_FILE);
        let tensors = road_model::checkpoint::load_tensors(&path, &candle_core::Device::Cpu)
            .map_err(|e| Error::Checkpoint(e.to_string()))?;
        let mut host = HashMap::new();
        for (name, t) in tensors {
            let values = t
                .flatten_all()
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| Error::Checkpoint(format!("{name}: {e}")))?;
            host.insert(name, values);
        }
        Self::new(ctx, &loaded.meta.run.model, &host)
    }

    /// Uploads named f32 tensors (checkpoint names, see `docs/checkpoint.md`).
    pub fn new(
        ctx: &GpuContext,
        config: &ModelConfig,
        tensors: &HashMap<String, Vec<f32>>,
    ) -> Result<Self> {
        let d = config.hidden;
        if d / config.heads > MAX_HEAD_DIM as usize {
            return Err(Error::Checkpoint(format!(
                "head size {} exceeds the kernel's {MAX_HEAD_DIM}",
                d / config.heads
            )));
        }
        let get = |name: &str| -> Result<&Vec<f32>> {
            tensors
                .get(name)
                .ok_or_else(|| Error::Checkpoint(format!("missing tensor `{name}`")))
        };
        // Packed small tensors the embedding kernels read from one binding.
        let mut packed: Vec<(String, Vec<f32>)> = Vec::new();
        let embed: Vec<f32> = [
            get("embed_state.weight")?,
            get("embed_state.bias")?,
            get("embed_noise.weight")?,
            get("embed_noise.bias")?,
            get("slot_embedding")?,
        ]
        .into_iter()
        .flatten()
        .copied()
        .collect();
        packed.push(("packed.embed".into(), embed));
        let map_points: Vec<f32> = [
            get("map_point.weight")?,
            get("map_point.bias")?,
            get("map_point_embedding")?,
        ]
        .into_iter()
        .flatten()
        .copied()
        .collect();
        packed.push(("packed.map_points".into(), map_points));

        let align = u64::from(ctx.device.limits().min_storage_buffer_offset_alignment).max(4);
        let mut blob: Vec<u8> = Vec::new();
        let mut slices = HashMap::new();
        let mut names: Vec<&String> = tensors.keys().collect();
        names.sort();
        for (name, values) in names
            .into_iter()
            .map(|n| (n.clone(), &tensors[n]))
            .chain(packed.iter().map(|(n, v)| (n.clone(), v)))
        {
            let offset = (blob.len() as u64).div_ceil(align) * align;
            blob.resize(offset as usize, 0);
            blob.extend_from_slice(bytemuck::cast_slice(values));
            slices.insert(
                name,
                Slice {
                    offset,
                    size: (values.len() * 4) as u64,
                },
            );
        }
        let weights = upload(ctx, "weights", &blob, wgpu::BufferUsages::STORAGE);
        Ok(Self {
            config: config.clone(),
            weights,
            slices,
            pipelines: Pipelines::new(ctx),
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

    fn params<T: Pod>(ctx: &GpuContext, p: &T) -> wgpu::Buffer {
        upload(
            ctx,
            "params",
            bytemuck::bytes_of(p),
            wgpu::BufferUsages::UNIFORM,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn linear(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        layer: &str,
        x: &wgpu::Buffer,
        y: &wgpu::Buffer,
        rows: usize,
        in_dim: usize,
        out_dim: usize,
        relu: bool,
    ) -> Result<()> {
        let p = LinearParams {
            rows: rows as u32,
            in_dim: in_dim as u32,
            out_dim: out_dim as u32,
            relu: u32::from(relu),
        };
        let params = Self::params(ctx, &p);
        let resources = [
            x.as_entire_binding(),
            self.w(&format!("{layer}.weight"))?,
            self.w(&format!("{layer}.bias"))?,
            y.as_entire_binding(),
        ];
        self.pipelines
            .linear
            .encode_resources(ctx, enc, &params, &resources, p.threads());
        Ok(())
    }

    fn layer_norm(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        name: &str,
        x: &wgpu::Buffer,
        y: &wgpu::Buffer,
        rows: usize,
    ) -> Result<()> {
        let p = LayerNormParams {
            rows: rows as u32,
            dim: self.config.hidden as u32,
            eps: LN_EPS,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        let resources = [
            x.as_entire_binding(),
            self.w(&format!("{name}.weight"))?,
            self.w(&format!("{name}.bias"))?,
            y.as_entire_binding(),
        ];
        self.pipelines
            .layer_norm
            .encode_resources(ctx, enc, &params, &resources, p.rows);
        Ok(())
    }

    fn add(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        from: &wgpu::Buffer,
        into: &wgpu::Buffer,
        count: usize,
    ) {
        let p = ElementwiseParams {
            count: count as u32,
            slots: 0,
            per_slot: 0,
            agents: 0,
            sigma_data: 0.0,
            hidden: 0,
            points: 0,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        let bound = [(1, from.as_entire_binding()), (5, into.as_entire_binding())];
        self.pipelines
            .add_in_place
            .encode_bound(ctx, enc, &params, &bound, p.count);
    }

    /// Map tokens of `scenes` scenes: `map [B, P, Q, 2]` (normalised), `map_valid [B, P]`.
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
        let points = upload(
            ctx,
            "map.points",
            bytemuck::cast_slice(map),
            wgpu::BufferUsages::STORAGE,
        );
        let valid = upload(
            ctx,
            "map.valid",
            bytemuck::cast_slice(map_valid),
            wgpu::BufferUsages::STORAGE,
        );
        let n_points = scenes * polylines * q;
        let embedded = storage_buffer(ctx, "map.embedded", (n_points * d * 4) as u64);
        let mixed = storage_buffer(ctx, "map.mixed", (n_points * d * 4) as u64);
        let pooled = storage_buffer(ctx, "map.pooled", (scenes * polylines * d * 4) as u64);
        let tokens = storage_buffer(ctx, "map.tokens", (scenes * polylines * d * 4) as u64);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("map") });
        let p = ElementwiseParams {
            count: (n_points * d) as u32,
            slots: 0,
            per_slot: 0,
            agents: 0,
            sigma_data: 0.0,
            hidden: d as u32,
            points: q as u32,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        // Bindings a, b and out of the elementwise family (c and e are unused by this entry).
        let bound = [
            (1, points.as_entire_binding()),
            (2, self.w("packed.map_points")?),
            (5, embedded.as_entire_binding()),
        ];
        self.pipelines
            .embed_map_points
            .encode_bound(ctx, &mut enc, &params, &bound, p.count);
        self.linear(
            ctx, &mut enc, "map_mix", &embedded, &mixed, n_points, d, d, false,
        )?;
        let p = ElementwiseParams {
            count: (scenes * polylines * d) as u32,
            hidden: d as u32,
            points: q as u32,
            ..p
        };
        let params = Self::params(ctx, &p);
        let bound = [
            (1, mixed.as_entire_binding()),
            (5, pooled.as_entire_binding()),
        ];
        self.pipelines
            .max_over_points
            .encode_bound(ctx, &mut enc, &params, &bound, p.count);
        self.layer_norm(
            ctx,
            &mut enc,
            "ln_map_out",
            &pooled,
            &tokens,
            scenes * polylines,
        )?;
        ctx.queue.submit([enc.finish()]);
        Ok(MapTokens {
            tokens,
            valid,
            scenes,
            polylines,
        })
    }

    /// Uploads one evaluation's inputs and embeds the agents' static features.
    pub fn upload_batch(
        &self,
        ctx: &GpuContext,
        inputs: &DenoiseInputs<'_>,
    ) -> Result<DeviceBatch> {
        let (b, a, w, d) = (
            inputs.scenes,
            inputs.agents,
            self.config.window_slots,
            self.config.hidden,
        );
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
        let features = upload(
            ctx,
            "agent features",
            bytemuck::cast_slice(inputs.agent_features),
            wgpu::BufferUsages::STORAGE,
        );
        let agent_embedding = storage_buffer(ctx, "agent embedding", (b * a * d * 4) as u64);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("agents"),
            });
        self.linear(
            ctx,
            &mut enc,
            "embed_agent",
            &features,
            &agent_embedding,
            b * a,
            6,
            d,
            false,
        )?;
        ctx.queue.submit([enc.finish()]);
        Ok(DeviceBatch {
            scenes: b,
            agents: a,
            x,
            sigma,
            valid,
            agent_embedding,
        })
    }

    /// Records `D(x; σ)` for the batch into `out` (`[B, A, W, 3]`): `x` and `sigma` are read from
    /// the given buffers so that a sampler can evaluate at intermediate states.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_denoise(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        batch: &DeviceBatch,
        x: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        map: &MapTokens,
        out: &wgpu::Buffer,
    ) -> Result<()> {
        let c = &self.config;
        let (b, a, w, d) = (batch.scenes, batch.agents, c.window_slots, c.hidden);
        assert_eq!(map.scenes, b, "map tokens for another scene count");
        let tokens = b * a * w;
        let m = d * c.mlp_ratio;
        let buf = |label: &str, floats: usize| storage_buffer(ctx, label, (floats * 4) as u64);
        let h = buf("h", tokens * d);
        let t = buf("normed", tokens * d);
        let (q, k, v) = (
            buf("q", tokens * d),
            buf("k", tokens * d),
            buf("v", tokens * d),
        );
        let att = buf("attention", tokens * d);
        let y = buf("y", tokens * d);
        let hidden = buf("mlp", tokens * m);
        let (mk, mv) = (
            buf("map k", map.polylines * b * d),
            buf("map v", map.polylines * b * d),
        );
        let f = buf("F", tokens * 3);

        let p = EmbedParams {
            scenes: b as u32,
            agents: a as u32,
            slots: w as u32,
            hidden: d as u32,
            sigma_data: c.edm.sigma_data as f32,
            polylines: 0,
            points: 0,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        let resources = [
            x.as_entire_binding(),
            sigma.as_entire_binding(),
            batch.valid.as_entire_binding(),
            batch.agent_embedding.as_entire_binding(),
            self.w("packed.embed")?,
            h.as_entire_binding(),
        ];
        self.pipelines.embed_tokens.encode_resources(
            ctx,
            enc,
            &params,
            &resources,
            (tokens * d) as u32,
        );

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
            _pad: [0; 2],
            q_layout: time,
            kv_layout: time,
            mask_layout: time,
        };
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
                        ..base
                    },
                ),
            ] {
                self.layer_norm(ctx, enc, &format!("{blk}.ln_{part}"), &h, &t, tokens)?;
                self.linear(
                    ctx,
                    enc,
                    &format!("{blk}.{part}.q"),
                    &t,
                    &q,
                    tokens,
                    d,
                    d,
                    false,
                )?;
                self.linear(
                    ctx,
                    enc,
                    &format!("{blk}.{part}.k"),
                    &t,
                    &k,
                    tokens,
                    d,
                    d,
                    false,
                )?;
                self.linear(
                    ctx,
                    enc,
                    &format!("{blk}.{part}.v"),
                    &t,
                    &v,
                    tokens,
                    d,
                    d,
                    false,
                )?;
                let params = Self::params(ctx, &attn);
                self.pipelines.attention.encode(
                    ctx,
                    enc,
                    &params,
                    &[&q, &k, &v, &batch.valid, &att],
                    attn.threads(),
                );
                self.linear(
                    ctx,
                    enc,
                    &format!("{blk}.{part}.o"),
                    &att,
                    &y,
                    tokens,
                    d,
                    d,
                    false,
                )?;
                self.add(ctx, enc, &y, &h, tokens * d);
            }
            // Map cross-attention: queries [B, A·W, D], keys [B, P, D].
            let pl = map.polylines as u32;
            self.layer_norm(ctx, enc, &format!("{blk}.ln_map"), &h, &t, tokens)?;
            self.linear(
                ctx,
                enc,
                &format!("{blk}.map.q"),
                &t,
                &q,
                tokens,
                d,
                d,
                false,
            )?;
            self.linear(
                ctx,
                enc,
                &format!("{blk}.map.k"),
                &map.tokens,
                &mk,
                b * map.polylines,
                d,
                d,
                false,
            )?;
            self.linear(
                ctx,
                enc,
                &format!("{blk}.map.v"),
                &map.tokens,
                &mv,
                b * map.polylines,
                d,
                d,
                false,
            )?;
            let attn = AttentionParams {
                groups: b32,
                queries: a32 * w32,
                keys: pl,
                q_layout: TokenLayout::contiguous(a32 * w32),
                kv_layout: TokenLayout::contiguous(pl),
                mask_layout: TokenLayout::contiguous(pl),
                ..base
            };
            let params = Self::params(ctx, &attn);
            self.pipelines.attention.encode(
                ctx,
                enc,
                &params,
                &[&q, &mk, &mv, &map.valid, &att],
                attn.threads(),
            );
            self.linear(
                ctx,
                enc,
                &format!("{blk}.map.o"),
                &att,
                &y,
                tokens,
                d,
                d,
                false,
            )?;
            self.add(ctx, enc, &y, &h, tokens * d);
            // MLP.
            self.layer_norm(ctx, enc, &format!("{blk}.ln_mlp"), &h, &t, tokens)?;
            self.linear(
                ctx,
                enc,
                &format!("{blk}.mlp_in"),
                &t,
                &hidden,
                tokens,
                d,
                m,
                true,
            )?;
            self.linear(
                ctx,
                enc,
                &format!("{blk}.mlp_out"),
                &hidden,
                &y,
                tokens,
                m,
                d,
                false,
            )?;
            self.add(ctx, enc, &y, &h, tokens * d);
        }
        self.layer_norm(ctx, enc, "ln_out", &h, &t, tokens)?;
        self.linear(ctx, enc, "head", &t, &f, tokens, d, 3, false)?;
        let p = ElementwiseParams {
            count: (tokens * 3) as u32,
            slots: w32,
            per_slot: 3,
            agents: a32,
            sigma_data: c.edm.sigma_data as f32,
            hidden: d as u32,
            points: 0,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        self.pipelines.precondition_output.encode(
            ctx,
            enc,
            &params,
            &[x, &f, sigma, &batch.valid, out],
            p.count,
        );
        Ok(())
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
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("denoise"),
            });
        self.encode_denoise(ctx, &mut enc, &batch, &batch.x, &batch.sigma, map, &out)?;
        ctx.queue.submit([enc.finish()]);
        let bytes = read_back(ctx, &out, len)?;
        Ok(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec())
    }

    /// One Heun step on the GPU for the whole batch (per-scene σ_cur[W], σ_next[W]):
    /// both evaluations and the update run on the device, and only the new state is read back
    /// when `read` is true. `batch.x` holds the state and is updated in place.
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
        let (b, a, w) = (batch.scenes, batch.agents, self.config.window_slots);
        let count = b * a * w * 3;
        let len = (count * 4) as u64;
        let sc = upload(
            ctx,
            "sigma_cur",
            bytemuck::cast_slice(sigma_cur),
            wgpu::BufferUsages::STORAGE,
        );
        let sn = upload(
            ctx,
            "sigma_next",
            bytemuck::cast_slice(sigma_next),
            wgpu::BufferUsages::STORAGE,
        );
        // The second evaluation's σ: σ_next, or σ_cur where σ_next is 0 (those slots keep
        // their Euler result, so the value there is never read).
        let eval: Vec<f32> = sigma_cur
            .iter()
            .zip(sigma_next)
            .map(|(&s, &n)| if n > 0.0 { n } else { s })
            .collect();
        let se = upload(
            ctx,
            "sigma_eval",
            bytemuck::cast_slice(&eval),
            wgpu::BufferUsages::STORAGE,
        );
        let d1 = storage_buffer(ctx, "D1", len);
        let x_e = storage_buffer(ctx, "x_e", len);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("heun"),
            });
        self.encode_denoise(ctx, &mut enc, batch, &batch.x, &sc, map, &d1)?;
        let p = HeunParams {
            count: count as u32,
            slots: w as u32,
            agents: a as u32,
            _pad: 0,
        };
        let params = Self::params(ctx, &p);
        self.pipelines.heun_euler.encode(
            ctx,
            &mut enc,
            &params,
            &[&batch.x, &d1, &sc, &sn, &x_e],
            p.count,
        );
        if second_evaluation {
            let d2 = storage_buffer(ctx, "D2", len);
            self.encode_denoise(ctx, &mut enc, batch, &x_e, &se, map, &d2)?;
            self.pipelines.heun_correct.encode(
                ctx,
                &mut enc,
                &params,
                &[&batch.x, &d1, &sc, &sn, &x_e, &d2],
                p.count,
            );
        }
        enc.copy_buffer_to_buffer(&x_e, 0, &batch.x, 0, len);
        ctx.queue.submit([enc.finish()]);
        if !read {
            return Ok(None);
        }
        let bytes = read_back(ctx, &batch.x, len)?;
        Ok(Some(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec()))
    }
}

/// The rollout driver's engine on the GPU: windows stay on the device through a tick's steps
/// and are read back once per tick.
#[derive(Debug)]
pub struct GpuStepEngine<'a> {
    ctx: &'a GpuContext,
    model: &'a GpuDenoiser,
    map: Option<MapTokens>,
    batch: Option<DeviceBatch>,
    features: Vec<f32>,
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
            features: Vec::new(),
            scenes: 0,
            agents: 0,
        }
    }
}

fn engine_err(e: Error) -> road_model::Error {
    road_model::Error::Engine(e.to_string())
}

impl road_model::sample::StepEngine for GpuStepEngine<'_> {
    fn window_slots(&self) -> usize {
        self.model.config.window_slots
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
        self.scenes = scenes;
        self.agents = agents;
        Ok(())
    }

    fn load(&mut self, windows: &[f32], valid: &[f32]) -> road_model::Result<()> {
        // σ of the batch is set per step; the upload's own σ is never read.
        let sigma = vec![1.0f32; self.scenes * self.model.config.window_slots];
        let inputs = DenoiseInputs {
            scenes: self.scenes,
            agents: self.agents,
            x: windows,
            sigma: &sigma,
            valid,
            agent_features: &self.features,
        };
        self.batch = Some(
            self.model
                .upload_batch(self.ctx, &inputs)
                .map_err(engine_err)?,
        );
        Ok(())
    }

    fn step(&mut self, sigma_cur: &[f32], sigma_next: &[f32], nfe: u8) -> road_model::Result<()> {
        let (Some(batch), Some(map)) = (&self.batch, &self.map) else {
            return Err(road_model::Error::Engine(
                "step before prepare and load".into(),
            ));
        };
        // Every scene of the lockstep batch shares this step's σ vector.
        let per_scene =
            |s: &[f32]| -> Vec<f32> { (0..self.scenes).flat_map(|_| s.iter().copied()).collect() };
        self.model
            .heun_step(
                self.ctx,
                batch,
                map,
                &per_scene(sigma_cur),
                &per_scene(sigma_next),
                nfe == 2,
                false,
            )
            .map_err(engine_err)?;
        Ok(())
    }

    fn read(&mut self, windows: &mut [f32]) -> road_model::Result<()> {
        let batch = self
            .batch
            .as_ref()
            .ok_or_else(|| road_model::Error::Engine("read before load".into()))?;
        let bytes =
            read_back(self.ctx, &batch.x, (windows.len() * 4) as u64).map_err(engine_err)?;
        windows.copy_from_slice(bytemuck::cast_slice(&bytes));
        Ok(())
    }
}
