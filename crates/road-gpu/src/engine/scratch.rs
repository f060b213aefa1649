//! The forward pass's scratch activations: the residual stream, q/k/v, the attention output,
//! the MLP's hidden layer and the head's output (those three only layer by layer), agent
//! attention's q/k/v and the map's q (those two only with residual chains), the map's k/v and,
//! with agent maps, each agent's picked polylines and their tokens. Sized once per batch
//! shape, checked against what the adapter binds.

use road_model::ModelConfig;

use super::MapTokens;
use crate::kernels::storage_buffer;
use crate::{Error, GpuContext, Result};

/// Floats of one part of a split buffer holding `floats`: rounded up so that every part starts
/// at the adapter's storage offset alignment (parts are bound as separate tensors).
pub(super) fn part_floats(ctx: &GpuContext, floats: usize) -> usize {
    let align = (ctx.device.limits().min_storage_buffer_offset_alignment as usize / 4).max(1);
    floats.div_ceil(align) * align
}

/// Scratch activations of one forward pass.
#[derive(Debug)]
pub(crate) struct Scratch {
    pub(super) h: wgpu::Buffer, // [T, D]: the residual stream
    /// `[3, token_part]`: q, k, v `[T, D]` each, from one fused projection.
    pub(super) qkv: wgpu::Buffer,
    /// With residual chains, agent attention's q, k, v (`[3, token_part]`), which the time
    /// chain writes while it attends from `qkv`; one float otherwise.
    pub(super) agents_qkv: wgpu::Buffer,
    /// Floats from one part of `qkv` to the next: `T · D` rounded up to the offset alignment.
    pub(super) token_part: usize,
    /// `[T, D]` layer by layer; one float with chains (they attend on chip).
    pub(super) att: wgpu::Buffer,
    /// `[T, D]` with residual chains: the map's q, which the map's chain attends from (`qkv`
    /// receives the next block's q, k, v in the same dispatch); one float otherwise.
    pub(super) map_q: wgpu::Buffer,
    pub(super) hidden: wgpu::Buffer, // [T, M]
    /// `[2, key_part]`: the map's k, v `[key rows, D]`; with `map_kv_all`, `[2 · blocks,
    /// key_part]`: every block's.
    pub(super) mkv: wgpu::Buffer,
    pub(super) key_part: usize,
    pub(super) f: wgpu::Buffer, // [T, 3]
    pub(super) agent_maps: Option<AgentMapScratch>,
    /// Every block's map k, v are projected at once (when they fit one binding).
    pub(super) map_kv_all: bool,
}

/// The polyline encoder's output for `polylines` polylines of `points` points. It runs
/// `chunk` polylines a dispatch, so that the points of agent maps of large batches (B·A·K
/// polylines) fit one buffer binding.
#[derive(Debug)]
pub(super) struct PolylineScratch {
    pub(super) polylines: usize,
    pub(super) points: usize,
    pub(super) chunk: usize,
    pub(super) tokens: wgpu::Buffer, // [n, D]
}

impl PolylineScratch {
    pub(super) fn new(ctx: &GpuContext, polylines: usize, points: usize, d: usize) -> Self {
        // Chunks of a multiple of 64 polylines: their offsets into the [n, Q, 2] points and the
        // [n, D] tokens are then multiples of 256 bytes, the storage offset alignment.
        let limits = ctx.device.limits();
        let max_bytes = ctx
            .map_encoder_chunk_bytes()
            .min(limits.max_storage_buffer_binding_size)
            .min(limits.max_buffer_size);
        let per_polyline_bytes = (points * 2 * 4).max(1) as u64;
        let chunk = ((max_bytes / per_polyline_bytes) as usize / 64 * 64).max(64);
        let chunk = chunk.min(polylines).max(1);
        Self {
            polylines,
            points,
            chunk,
            tokens: storage_buffer(ctx, "map.tokens", (polylines * d * 4) as u64),
        }
    }
}

/// Every agent's own map of one evaluation: its picked polylines and their tokens.
#[derive(Debug)]
pub(super) struct AgentMapScratch {
    pub(super) points: wgpu::Buffer, // [B·A, K, Q, 2]
    pub(super) valid: wgpu::Buffer,  // [B·A, K]
    pub(super) encoder: PolylineScratch,
}

impl Scratch {
    /// Activations of `scenes × agents` on `map`; `chains`: the blocks run as residual chains
    /// (no MLP hidden layer or head output in memory).
    pub(super) fn new(
        ctx: &GpuContext,
        c: &ModelConfig,
        (scenes, agents): (usize, usize),
        map: &MapTokens,
        chains: bool,
    ) -> Result<Self> {
        let tokens = scenes * agents * c.window_slots;
        let d = c.hidden;
        // The largest activation must fit one buffer binding (the point encoder's per-point
        // activations are chunked to fit): a clear error instead of wgpu's validation panic.
        let (key_rows_needed, point_floats) = match map.picked {
            Some(k) => (
                scenes * agents * k,
                scenes * agents * k * c.polyline_points * 2,
            ),
            None => (map.scenes * map.polylines, 0),
        };
        let largest_bytes = 4
            * (tokens * d * c.mlp_ratio)
                .max(3 * part_floats(ctx, tokens * d))
                .max(2 * part_floats(ctx, key_rows_needed * d))
                .max(point_floats) as u64;
        let limits = ctx.device.limits();
        let max_bytes = limits
            .max_buffer_size
            .min(limits.max_storage_buffer_binding_size);
        if largest_bytes > max_bytes {
            return Err(Error::Input(format!(
                "a batch of {scenes} scenes × {agents} agents needs a {:.0} MiB activation buffer; \
                 this adapter binds at most {:.0} MiB: use smaller batches",
                largest_bytes as f64 / 1048576.0,
                max_bytes as f64 / 1048576.0
            )));
        }
        let buf = |label: &str, floats: usize| storage_buffer(ctx, label, (floats * 4) as u64);
        let (key_rows, agent_maps) = match map.picked {
            None => (map.scenes * map.polylines, None),
            Some(k) => {
                let (rows, q) = (scenes * agents * k, c.polyline_points);
                let maps = AgentMapScratch {
                    points: buf("agent map points", rows * q * 2),
                    valid: buf("agent map valid", rows),
                    encoder: PolylineScratch::new(ctx, rows, q, d),
                };
                (rows, Some(maps))
            }
        };
        let (token_part, key_part) = (part_floats(ctx, tokens * d), part_floats(ctx, key_rows * d));
        let map_kv_all = (2 * c.blocks * key_part * 4) as u64 <= max_bytes;
        let kv_parts = if map_kv_all { 2 * c.blocks } else { 2 };
        // Residual chains keep the MLP's hidden layer, the head's F and every attention's output
        // on chip; they read agent attention's q, k, v and the map's q from buffers of their own.
        let (hidden, f, att, map_q, agents_qkv) = if chains {
            (1, 1, 1, tokens * d, 3 * token_part)
        } else {
            (tokens * d * c.mlp_ratio, tokens * 3, tokens * d, 1, 1)
        };
        Ok(Self {
            h: buf("h", tokens * d),
            qkv: buf("qkv", 3 * token_part),
            agents_qkv: buf("agents qkv", agents_qkv),
            token_part,
            att: buf("attention", att),
            map_q: buf("map q", map_q),
            hidden: buf("mlp", hidden),
            mkv: buf("map kv", kv_parts * key_part),
            key_part,
            f: buf("F", f),
            agent_maps,
            map_kv_all,
        })
    }
}
