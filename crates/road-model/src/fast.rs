//! The fast CPU inference path: the denoiser's forward pass over plain buffers that are kept
//! from call to call, matrix products through `gemm`'s kernels (AVX2/FMA or AVX-512 chosen at
//! run time), attention fused per group of tokens (`fast_kernels`: no per-head tensors), the
//! map's keys and values computed once per scene set (scene maps) or once per anchor (agent
//! maps, [`AgentMapMemo`]), and the scenes of a batch split across threads that share
//! nothing. [`Denoiser`] (candle) stays the reference: `tests/fast.rs` holds the two to the
//! tolerance the WGSL engine meets.
//!
//! candle spends most of an inference step outside its matrix products here (thread barriers
//! per op, allocation per op, tiny batched products for attention): see `docs/benchmarks.md`.

use std::collections::HashMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use candle_core::Tensor;
use candle_nn::{LayerNorm, Linear};

use crate::agent_map::{MapAnchor, agent_map, polylines_per_agent};
use crate::agent_pairs::{PAIR_FEATURES, PairScales, pair_features};
use crate::config::AgentFrame;
use crate::fast_kernels::{AttentionScratch, KeysValues, PairTerms, attend, layer_norm};
use crate::model::{Attention, Denoiser};
use crate::{Error, Result};

fn host(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.flatten_all()?.to_vec1::<f32>()?)
}

/// `y = x · Wᵀ + b` with `weight [d_out, d_in]` (the checkpoint's layout).
#[derive(Debug, Clone)]
struct Dense {
    weight: Vec<f32>,
    bias: Vec<f32>,
    d_in: usize,
    d_out: usize,
}

impl Dense {
    fn from_linear(layer: &Linear) -> Result<Self> {
        let (d_out, d_in) = layer.weight().dims2()?;
        let bias = match layer.bias() {
            Some(b) => host(b)?,
            None => vec![0.0; d_out],
        };
        Ok(Self {
            weight: host(layer.weight())?,
            bias,
            d_in,
            d_out,
        })
    }

    /// Several layers of the same input stacked into one (`[q; k; v]`): one product.
    fn stack(layers: &[&Linear]) -> Result<Self> {
        let mut out = Dense::from_linear(layers[0])?;
        for layer in &layers[1..] {
            let next = Dense::from_linear(layer)?;
            if next.d_in != out.d_in {
                return Err(Error::data(
                    "stacked layers of different input widths".into(),
                ));
            }
            out.weight.extend(next.weight);
            out.bias.extend(next.bias);
            out.d_out += next.d_out;
        }
        Ok(out)
    }

    /// `out [n, d_out] = x [n, d_in] · Wᵀ + b`.
    fn forward(&self, x: &[f32], n: usize, out: &mut [f32]) {
        for row in out[..n * self.d_out].chunks_exact_mut(self.d_out) {
            row.copy_from_slice(&self.bias);
        }
        matmul_accumulate(out, x, &self.weight, n, self.d_in, self.d_out);
    }

    /// `out [n, d_out] += x [n, d_in] · Wᵀ + b` (residual connections).
    fn forward_add(&self, x: &[f32], n: usize, out: &mut [f32]) {
        for row in out[..n * self.d_out].chunks_exact_mut(self.d_out) {
            for (o, b) in row.iter_mut().zip(&self.bias) {
                *o += b;
            }
        }
        matmul_accumulate(out, x, &self.weight, n, self.d_in, self.d_out);
    }
}

/// `out [m, n] += a [m, k] · bᵀ` for `b [n, k]`, all row-major, on the calling thread.
#[allow(unsafe_code)] // gemm takes raw pointers and strides; the asserts bound them.
fn matmul_accumulate(out: &mut [f32], a: &[f32], b: &[f32], m: usize, k: usize, n: usize) {
    assert!(
        out.len() >= m * n && a.len() >= m * k && b.len() >= n * k,
        "matmul of [{m}, {k}] by [{k}, {n}]: buffers of {}, {} and {}",
        a.len(),
        b.len(),
        out.len()
    );
    if m == 0 || n == 0 || k == 0 {
        return;
    }
    // SAFETY: gemm reads lhs (p, q) at a + p·k + q for p < m, q < k; rhs (q, j) at
    // b + j·k + q (bᵀ) for q < k, j < n; and reads and writes dst (p, j) at out + p·n + j. The
    // assert above keeps every such offset inside its slice, and `out` is borrowed mutably
    // while `a` and `b` are shared borrows, so they cannot alias.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            true,
            a.as_ptr(),
            1,
            k as isize,
            b.as_ptr(),
            k as isize,
            1,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

#[derive(Debug, Clone)]
struct Norm {
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl Norm {
    fn from_layer_norm(ln: &LayerNorm) -> Result<Self> {
        let bias = ln
            .bias()
            .ok_or_else(|| Error::data("layer norm without a bias".into()))?;
        Ok(Self {
            weight: host(ln.weight())?,
            bias: host(bias)?,
        })
    }

    /// `out [n, D] = LN(x [n, D])`.
    fn forward(&self, x: &[f32], out: &mut [f32]) {
        layer_norm(x, &self.weight, &self.bias, out);
    }
}

#[derive(Debug, Clone)]
struct FastBlock {
    ln_time: Norm,
    time_qkv: Dense,
    time_o: Dense,
    ln_agents: Norm,
    agents_qkv: Dense,
    agents_o: Dense,
    /// With agent pairs: the key and value offsets' weights, `[D, F]` each.
    agents_pairs: Option<(Vec<f32>, Vec<f32>)>,
    ln_map: Norm,
    map_q: Dense,
    /// Applied to the map tokens once per scene set: `[k; v]`.
    map_kv: Dense,
    map_o: Dense,
    ln_mlp: Norm,
    mlp_in: Dense,
    mlp_out: Dense,
}

fn qkv(a: &Attention) -> Result<Dense> {
    Dense::stack(&[&a.q, &a.k, &a.v])
}

/// The denoiser's weights for the fast path (a copy of a [`Denoiser`]'s).
#[derive(Debug)]
pub struct FastDenoiser {
    hidden: usize,
    heads: usize,
    slots: usize,
    sigma_data: f32,
    heading_scale: f32,
    agent_frame: Option<AgentFrame>,
    embed_state: Dense,
    embed_noise: Dense,
    embed_agent: Dense,
    embed_relative: Option<Dense>,
    slot_embedding: Vec<f32>, // [W, D]
    blocks: Vec<FastBlock>,
    ln_out: Norm,
    head: Dense,
    /// With an agent map: the polyline encoder and the polylines per agent K wanted.
    agent_map: Option<(PolylineEncoder, usize)>,
    /// With agent pairs: their features' scales.
    pair_scales: Option<PairScales>,
    /// Worker threads a call may use (scenes are split between them).
    threads: usize,
    /// Scratch buffers, one set per worker, kept between calls.
    scratch: Mutex<Vec<Scratch>>,
}

/// What a batch of scenes needs besides the states: computed once per scene set.
#[derive(Debug, Clone, Default)]
pub struct SceneCache {
    pub scenes: usize,
    pub agents: usize,
    pub polylines: usize,
    /// `[B, A, D]`: `embed_agent(features)`.
    agent_embedding: Vec<f32>,
    /// `[B, blocks, P, 2D]`: each block's map keys and values (scene-frame map tokens only).
    map_kv: Vec<f32>,
    /// `[B, P, Q, 2]`: the polylines each agent picks its own from (agent maps only).
    map_points: Vec<f32>,
    /// `[B, P]`.
    map_valid: Vec<f32>,
    /// `[B]`: an identity per scene, new for every scene a cache is built or replaced with
    /// (the agent-map memo's key: a new scene never reuses an old one's maps).
    identities: Vec<u64>,
}

/// The source of [`SceneCache`]'s scene identities.
static NEXT_SCENE_IDENTITY: AtomicU64 = AtomicU64::new(0);

fn new_identities(scenes: usize) -> Vec<u64> {
    let first = NEXT_SCENE_IDENTITY.fetch_add(scenes as u64, Ordering::Relaxed);
    (first..first + scenes as u64).collect()
}

impl SceneCache {
    /// Puts the one scene of `one` (a cache of the same agents and polylines) in place of scene
    /// `scene`: how a scene joins a running batch.
    pub fn replace_scene(&mut self, scene: usize, one: &SceneCache) -> Result<()> {
        if scene >= self.scenes
            || one.scenes != 1
            || one.agents != self.agents
            || one.polylines != self.polylines
        {
            return Err(Error::data(format!(
                "replace scene {scene} of a cache of {} scenes × {} agents × {} polylines by one \
                 of {} × {} × {}",
                self.scenes, self.agents, self.polylines, one.scenes, one.agents, one.polylines
            )));
        }
        fn put(all: &mut [f32], scene: usize, row: &[f32]) {
            if !row.is_empty() {
                all[scene * row.len()..][..row.len()].copy_from_slice(row);
            }
        }
        put(&mut self.agent_embedding, scene, &one.agent_embedding);
        put(&mut self.map_kv, scene, &one.map_kv);
        put(&mut self.map_points, scene, &one.map_points);
        put(&mut self.map_valid, scene, &one.map_valid);
        self.identities[scene] = new_identities(1)[0];
        Ok(())
    }
}

/// The scene's map as [`FastDenoiser::scene_cache`] takes it.
#[derive(Debug, Clone, Copy)]
pub enum SceneMap<'a> {
    /// Scene-frame tokens `[B, P, D]` (the candle model's `encode_map`).
    Tokens(&'a [f32]),
    /// The polylines `[B, P, Q, 2]`, for a model with an agent map.
    Polylines(&'a [f32]),
}

/// The polyline encoder (`Denoiser::encode_polylines`) on plain buffers.
#[derive(Debug, Clone)]
struct PolylineEncoder {
    point: Dense,
    point_embedding: Vec<f32>, // [Q, D]
    mix: Dense,
    ln: Norm,
}

impl PolylineEncoder {
    /// `tokens [n, D]` of `points [n, Q, 2]`; `hidden` and `mixed` are scratch of `n·Q·D`.
    fn forward(
        &self,
        points: &[f32],
        n: usize,
        hidden: &mut Vec<f32>,
        mixed: &mut Vec<f32>,
        tokens: &mut [f32],
    ) {
        let d = self.point.d_out;
        let q = self.point_embedding.len() / d;
        let rows = n * q;
        hidden.resize(rows * d, 0.0);
        mixed.resize(rows * d, 0.0);
        self.point.forward(points, rows, hidden);
        for (row, h) in hidden[..rows * d].chunks_exact_mut(d).enumerate() {
            let e = &self.point_embedding[(row % q) * d..][..d];
            for (v, e) in h.iter_mut().zip(e) {
                *v = (*v + e).max(0.0);
            }
        }
        self.mix.forward(&hidden[..rows * d], rows, mixed);
        // Max over each polyline's points into `hidden` (free again), then the layer norm.
        let pooled = &mut hidden[..n * d];
        for (poly, token) in pooled.chunks_exact_mut(d).enumerate() {
            token.fill(f32::NEG_INFINITY);
            for point in mixed[poly * q * d..][..q * d].chunks_exact(d) {
                for (t, v) in token.iter_mut().zip(point) {
                    *t = t.max(*v);
                }
            }
        }
        self.ln.forward(pooled, &mut tokens[..n * d]);
    }
}

/// Agent maps encoded by earlier calls, by (scene identity, agent index in its scene): an
/// agent's map depends only on its scene's polylines and its anchor (the newest observed
/// state), which stays put for all the denoiser calls of a tick (observed slots keep their σ,
/// so Heun steps leave them unchanged); without the memo the polyline encoder ran for every
/// agent in every call (a quarter of the engine's time).
#[derive(Debug, Default)]
struct AgentMapMemo {
    entries: HashMap<(u64, usize), MemoEntry>,
    free_slabs: Vec<usize>,
    slabs: usize,
    /// K of the slabs (the memo empties when a batch's K differs).
    polylines: usize,
    calls: u64,
}

#[derive(Debug, Clone, Copy)]
struct MemoEntry {
    anchor_bits: [u32; 4],
    slab: usize,
    last_call: u64,
}

/// Calls an unused memo entry survives: longer than a joining scene's warm-up keeps the
/// others waiting.
const MEMO_CALLS_KEPT: u64 = 128;

impl AgentMapMemo {
    /// The slab of `key` and whether it holds the maps of `anchor` already.
    fn slab_for(&mut self, key: (u64, usize), anchor: MapAnchor) -> (usize, bool) {
        let bits = [anchor.x, anchor.y, anchor.cos, anchor.sin].map(f32::to_bits);
        let calls = self.calls;
        if let Some(entry) = self.entries.get_mut(&key) {
            entry.last_call = calls;
            let fresh = entry.anchor_bits == bits;
            entry.anchor_bits = bits;
            return (entry.slab, fresh);
        }
        let slab = self.free_slabs.pop().unwrap_or_else(|| {
            self.slabs += 1;
            self.slabs - 1
        });
        self.entries.insert(
            key,
            MemoEntry {
                anchor_bits: bits,
                slab,
                last_call: calls,
            },
        );
        (slab, false)
    }

    /// Starts a call with `k` polylines per agent; frees the slabs of entries unused for
    /// [`MEMO_CALLS_KEPT`] calls.
    fn start_call(&mut self, k: usize) {
        if k != self.polylines {
            *self = Self {
                polylines: k,
                ..Self::default()
            };
        }
        self.calls += 1;
        let calls = self.calls;
        let free = &mut self.free_slabs;
        self.entries.retain(|_, entry| {
            let kept = calls - entry.last_call <= MEMO_CALLS_KEPT;
            if !kept {
                free.push(entry.slab);
            }
            kept
        });
    }
}

/// Per-worker buffers for `N` tokens (resized, never shrunk).
#[derive(Debug, Default)]
struct Scratch {
    h: Vec<f32>,      // [N, D]
    t: Vec<f32>,      // [N, D]
    qkv: Vec<f32>,    // [N, 3D]
    att: Vec<f32>,    // [N, D]
    hidden: Vec<f32>, // [N, M]
    f: Vec<f32>,      // [N, 3]
    /// Compact agent index → batch agent row (agents with a valid slot only).
    agent_rows: Vec<usize>,
    /// Compact agent index where each scene of the chunk starts (one more entry at the end).
    scene_starts: Vec<usize>,
    /// Batch agent row → compact agent index (`usize::MAX`: not evaluated).
    compact_of: Vec<usize>,
    queries: Vec<usize>,
    keys: Vec<usize>,
    attention: AttentionScratch,
    /// Agent maps: per evaluated agent, its polylines `[K, Q, 2]` in its frame, their flags
    /// `[K]`, the encoder's scratch, the tokens `[K, D]` and each block's `[K, 2D]` keys and
    /// values (`[agents, blocks, K, 2D]`).
    agent_points: Vec<f32>,
    agent_map_valid: Vec<f32>,
    agent_hidden: Vec<f32>,
    agent_mixed: Vec<f32>,
    agent_tokens: Vec<f32>,
    /// Encoded agent maps, a slab each: `agent_map_kv [slabs, blocks, K, 2D]` and
    /// `agent_map_valid [slabs, K]`; `agent_slab[compact agent]` is the one a call reads.
    agent_map_kv: Vec<f32>,
    agent_slab: Vec<usize>,
    agent_map_memo: AgentMapMemo,
    /// The agents whose maps a call encodes: (compact agent, slab, anchor).
    stale_agent_maps: Vec<(usize, usize, MapAnchor)>,
    /// Agent pairs: each evaluated agent's anchor; the pair features of every (scene, slot),
    /// `[agents_s, agents_s, F]` each, from `pair_starts[scene] + slot · agents_s² · F` (the
    /// same in every block); the unmasked keys' positions among a group's queries.
    pair_anchors: Vec<MapAnchor>,
    pair_features: Vec<f32>,
    pair_starts: Vec<usize>,
    key_positions: Vec<usize>,
}

/// One batch of states to denoise: the rows of `scene_ids` in the [`SceneCache`].
#[derive(Debug, Clone, Copy)]
pub struct FastInputs<'a> {
    /// `[B, A, W, 3]`.
    pub x: &'a [f32],
    /// `[B, W]`.
    pub sigma: &'a [f32],
    /// `[B, A, W]`.
    pub valid: &'a [f32],
    /// Batch row b is scene `scene_ids[b]` of the cache.
    pub scene_ids: &'a [usize],
}

impl FastDenoiser {
    /// Copies the weights of `model`; `threads` workers at most per call (≥ 1).
    pub fn new(model: &Denoiser, threads: usize) -> Result<Self> {
        let c = &model.config;
        let blocks = model
            .blocks
            .iter()
            .map(|b| {
                Ok(FastBlock {
                    ln_time: Norm::from_layer_norm(&b.ln_time)?,
                    time_qkv: qkv(&b.time)?,
                    time_o: Dense::from_linear(&b.time.o)?,
                    ln_agents: Norm::from_layer_norm(&b.ln_agents)?,
                    agents_qkv: qkv(&b.agents)?,
                    agents_o: Dense::from_linear(&b.agents.o)?,
                    agents_pairs: match &b.agents.pairs {
                        Some(w) => Some((host(&w.k)?, host(&w.v)?)),
                        None => None,
                    },
                    ln_map: Norm::from_layer_norm(&b.ln_map)?,
                    map_q: Dense::from_linear(&b.map.q)?,
                    map_kv: Dense::stack(&[&b.map.k, &b.map.v])?,
                    map_o: Dense::from_linear(&b.map.o)?,
                    ln_mlp: Norm::from_layer_norm(&b.ln_mlp)?,
                    mlp_in: Dense::from_linear(&b.mlp_in)?,
                    mlp_out: Dense::from_linear(&b.mlp_out)?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            hidden: c.hidden,
            heads: c.heads,
            slots: c.window_slots,
            sigma_data: c.edm.sigma_data as f32,
            heading_scale: c.heading_scale as f32,
            agent_frame: c.agent_frame.clone(),
            embed_state: Dense::from_linear(&model.embed_state)?,
            embed_noise: Dense::from_linear(&model.embed_noise)?,
            embed_agent: Dense::from_linear(&model.embed_agent)?,
            embed_relative: model
                .embed_relative
                .as_ref()
                .map(Dense::from_linear)
                .transpose()?,
            slot_embedding: host(&model.slot_embedding)?,
            blocks,
            ln_out: Norm::from_layer_norm(&model.ln_out)?,
            head: Dense::from_linear(&model.head)?,
            agent_map: match &c.agent_map {
                None => None,
                Some(spec) => Some((
                    PolylineEncoder {
                        point: Dense::from_linear(&model.map_point)?,
                        point_embedding: host(&model.map_point_embedding)?,
                        mix: Dense::from_linear(&model.map_mix)?,
                        ln: Norm::from_layer_norm(&model.ln_map_out)?,
                    },
                    spec.polylines,
                )),
            },
            pair_scales: c
                .agent_pairs
                .as_ref()
                .map(|pairs| PairScales::new(pairs, c.position_scale_m, c.heading_scale)),
            threads: threads.max(1),
            scratch: Mutex::new(Vec::new()),
        })
    }

    /// The static inputs of `scenes` scenes: `features [B, A, 6]`, the map (scene-frame tokens,
    /// or the polylines for a model with an agent map), `map_valid [B, P]`.
    pub fn scene_cache(
        &self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        map: SceneMap<'_>,
        map_valid: &[f32],
    ) -> Result<SceneCache> {
        let d = self.hidden;
        let polylines = map_valid.len() / scenes.max(1);
        let (map_values, per_polyline) = match (map, &self.agent_map) {
            (SceneMap::Tokens(t), None) => (t.len(), d),
            (SceneMap::Polylines(p), Some((encoder, _))) => {
                (p.len(), encoder.point_embedding.len() / d * 2)
            }
            (SceneMap::Tokens(_), Some(_)) | (SceneMap::Polylines(_), None) => {
                return Err(Error::data(
                    "scene cache: a model with an agent map takes the polylines, any other the \
                     scene-frame tokens"
                        .into(),
                ));
            }
        };
        if features.len() != scenes * agents * self.embed_agent.d_in
            || map_values != scenes * polylines * per_polyline
            || map_valid.len() != scenes * polylines
        {
            return Err(Error::data(format!(
                "scene cache of {scenes} scenes × {agents} agents: {} feature values, {map_values} \
                 map values ({per_polyline} per polyline), {} map flags",
                features.len(),
                map_valid.len()
            )));
        }
        let mut agent_embedding = vec![0.0; scenes * agents * d];
        self.embed_agent
            .forward(features, scenes * agents, &mut agent_embedding);
        let (mut map_kv, mut map_points) = (Vec::new(), Vec::new());
        match map {
            SceneMap::Tokens(map_tokens) => {
                let per_block = polylines * 2 * d;
                map_kv = vec![0.0; scenes * self.blocks.len() * per_block];
                for b in 0..scenes {
                    let tokens = &map_tokens[b * polylines * d..][..polylines * d];
                    for (i, block) in self.blocks.iter().enumerate() {
                        let kv = &mut map_kv[(b * self.blocks.len() + i) * per_block..];
                        block
                            .map_kv
                            .forward(tokens, polylines, &mut kv[..per_block]);
                    }
                }
            }
            SceneMap::Polylines(points) => map_points = points.to_vec(),
        }
        Ok(SceneCache {
            scenes,
            agents,
            polylines,
            agent_embedding,
            map_kv,
            map_points,
            map_valid: map_valid.to_vec(),
            identities: new_identities(scenes),
        })
    }

    /// Every evaluated agent's own map (agent-map models): its polylines picked and encoded
    /// in its anchor frame, then each block's keys and values, into the agent's slab of the
    /// scratch's `agent_map_kv [slabs, blocks, K, 2D]` and `agent_map_valid [slabs, K]`
    /// (`agent_slab[compact agent]`); agents whose anchor has not moved since an earlier call
    /// keep their slab as it is ([`AgentMapMemo`]). Returns K.
    fn agent_maps(&self, cache: &SceneCache, inputs: &FastInputs<'_>, s: &mut Scratch) -> usize {
        let Some((encoder, wanted)) = &self.agent_map else {
            return 0;
        };
        let (a, d) = (cache.agents, self.hidden);
        let p = cache.polylines;
        let q = encoder.point_embedding.len() / d;
        let k = polylines_per_agent(*wanted, p);
        let blocks = self.blocks.len();
        let per_block = k * 2 * d;
        s.agent_map_memo.start_call(k);
        s.stale_agent_maps.clear();
        s.agent_slab.clear();
        for (compact, &agent_row) in s.agent_rows.iter().enumerate() {
            let scene = inputs.scene_ids[agent_row / a];
            let key = (cache.identities[scene], agent_row % a);
            let anchor = self.map_anchor(inputs, agent_row);
            let (slab, fresh) = s.agent_map_memo.slab_for(key, anchor);
            s.agent_slab.push(slab);
            if !fresh {
                s.stale_agent_maps.push((compact, slab, anchor));
            }
        }
        let slabs = s.agent_map_memo.slabs;
        s.agent_map_valid.resize(slabs * k, 0.0);
        s.agent_map_kv.resize(slabs * blocks * per_block, 0.0);
        if s.stale_agent_maps.is_empty() {
            return k;
        }
        let n = s.stale_agent_maps.len();
        s.agent_points.resize(n * k * q * 2, 0.0);
        for (i, &(compact, slab, anchor)) in s.stale_agent_maps.iter().enumerate() {
            let scene = inputs.scene_ids[s.agent_rows[compact] / a];
            agent_map(
                anchor,
                &cache.map_points[scene * p * q * 2..][..p * q * 2],
                &cache.map_valid[scene * p..][..p],
                q,
                &mut s.agent_points[i * k * q * 2..][..k * q * 2],
                &mut s.agent_map_valid[slab * k..][..k],
            );
        }
        s.agent_tokens.resize(n * k * d, 0.0);
        encoder.forward(
            &s.agent_points[..n * k * q * 2],
            n * k,
            &mut s.agent_hidden,
            &mut s.agent_mixed,
            &mut s.agent_tokens,
        );
        for (i, &(_, slab, _)) in s.stale_agent_maps.iter().enumerate() {
            let tokens = &s.agent_tokens[i * k * d..][..k * d];
            for (b, block) in self.blocks.iter().enumerate() {
                let kv = &mut s.agent_map_kv[(slab * blocks + b) * per_block..];
                block.map_kv.forward(tokens, k, &mut kv[..per_block]);
            }
        }
        k
    }

    /// `D(x; σ)` of every batch row into `out [B, A, W, 3]`.
    pub fn denoise(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        out: &mut [f32],
    ) -> Result<()> {
        let (a, w) = (cache.agents, self.slots);
        let b = inputs.scene_ids.len();
        if inputs.x.len() != b * a * w * 3
            || inputs.valid.len() != b * a * w
            || inputs.sigma.len() != b * w
            || out.len() != inputs.x.len()
        {
            return Err(Error::data(format!(
                "fast denoise of {b} scenes × {a} agents × {w} slots: {} states, {} flags, {} σ, \
                 {} outputs",
                inputs.x.len(),
                inputs.valid.len(),
                inputs.sigma.len(),
                out.len()
            )));
        }
        if let Some(&bad) = inputs.scene_ids.iter().find(|&&s| s >= cache.scenes) {
            return Err(Error::data(format!(
                "scene {bad} is not in the cache of {} scenes",
                cache.scenes
            )));
        }
        if b == 0 {
            return Ok(());
        }
        let per = b.div_ceil(self.threads.min(b));
        let workers = b.div_ceil(per);
        let mut pool = std::mem::take(&mut *self.scratch.lock().expect("scratch lock"));
        pool.resize_with(workers.max(pool.len()), Scratch::default);
        let chunk = |start: usize, len: usize| FastInputs {
            x: &inputs.x[start * a * w * 3..][..len * a * w * 3],
            sigma: &inputs.sigma[start * w..][..len * w],
            valid: &inputs.valid[start * a * w..][..len * a * w],
            scene_ids: &inputs.scene_ids[start..start + len],
        };
        if workers == 1 {
            self.forward(cache, &chunk(0, b), &mut pool[0], out);
        } else {
            std::thread::scope(|scope| {
                let mut rest = &mut out[..];
                for (i, scratch) in pool.iter_mut().take(workers).enumerate() {
                    let start = i * per;
                    let len = per.min(b - start);
                    let (mine, tail) = rest.split_at_mut(len * a * w * 3);
                    rest = tail;
                    let part = chunk(start, len);
                    scope.spawn(move || self.forward(cache, &part, scratch, mine));
                }
            });
        }
        *self.scratch.lock().expect("scratch lock") = pool;
        Ok(())
    }

    /// The whole forward pass of a chunk of scenes on this thread. Agent rows with no valid
    /// slot (padding, or agents absent from the whole window) are left out: they are masked
    /// as keys everywhere and their output is `c_skip · x` whatever the network says, so
    /// leaving them out changes nothing but the time taken. Masked keys are skipped for the
    /// same reason (their softmax weight is exactly 0 in f32) unless every key of a group is
    /// masked, where the candle model averages over all of them and so does this.
    fn forward(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        s: &mut Scratch,
        out: &mut [f32],
    ) {
        let (a, w, d) = (cache.agents, self.slots, self.hidden);
        let b = inputs.scene_ids.len();
        s.agent_rows.clear();
        s.scene_starts.clear();
        s.compact_of.clear();
        s.compact_of.resize(b * a, usize::MAX);
        for row in 0..b * a {
            if row % a == 0 {
                s.scene_starts.push(s.agent_rows.len());
            }
            if inputs.valid[row * w..(row + 1) * w]
                .iter()
                .any(|&v| v > 0.0)
            {
                s.compact_of[row] = s.agent_rows.len();
                s.agent_rows.push(row);
            }
        }
        s.scene_starts.push(s.agent_rows.len());
        let n = s.agent_rows.len() * w;
        let m = self.blocks.first().map_or(d, |blk| blk.mlp_in.d_out);
        for (buf, len) in [
            (&mut s.h, n * d),
            (&mut s.t, n * d),
            (&mut s.qkv, n * 3 * d),
            (&mut s.att, n * d),
            (&mut s.hidden, n * m),
            (&mut s.f, n * 3),
        ] {
            buf.resize(len.max(buf.len()), 0.0);
        }
        self.embed(cache, inputs, &s.agent_rows, &mut s.h[..n * d]);
        let k = self.agent_maps(cache, inputs, s);
        if let Some(scales) = self.pair_scales {
            s.pair_anchors.clear();
            for &agent_row in &s.agent_rows {
                s.pair_anchors.push(self.map_anchor(inputs, agent_row));
            }
            s.pair_starts.clear();
            let mut len = 0;
            for scene in 0..b {
                s.pair_starts.push(len);
                let agents = s.scene_starts[scene + 1] - s.scene_starts[scene];
                len += w * agents * agents * PAIR_FEATURES;
            }
            s.pair_features.resize(len, 0.0);
            for scene in 0..b {
                let agents = s.scene_starts[scene]..s.scene_starts[scene + 1];
                let per_slot = agents.len() * agents.len() * PAIR_FEATURES;
                for slot in 0..w {
                    slot_pair_features(
                        inputs.x,
                        &s.agent_rows,
                        &s.pair_anchors,
                        agents.clone(),
                        slot,
                        w,
                        scales,
                        &mut s.pair_features[s.pair_starts[scene] + slot * per_slot..][..per_slot],
                    );
                }
            }
        }
        let valid_token = |compact_token: usize| {
            inputs.valid[s.agent_rows[compact_token / w] * w + compact_token % w] > 0.0
        };
        let heads = self.heads;
        let scale = 1.0 / ((d / heads) as f32).sqrt();
        let p = cache.polylines;
        let all_polylines: Vec<usize> = (0..p).collect();
        let agent_polylines: Vec<usize> = (0..k).collect();
        for (block_index, blk) in self.blocks.iter().enumerate() {
            // Time attention: the W slots of each agent.
            blk.ln_time.forward(&s.h[..n * d], &mut s.t[..n * d]);
            blk.time_qkv
                .forward(&s.t[..n * d], n, &mut s.qkv[..n * 3 * d]);
            for agent in 0..s.agent_rows.len() {
                s.queries.clear();
                s.queries.extend(agent * w..(agent + 1) * w);
                unmasked_keys(&s.queries, &valid_token, &mut s.keys);
                let kv = KeysValues::stacked(&s.qkv, d);
                attend(
                    &s.qkv,
                    3 * d,
                    &s.queries,
                    &kv,
                    &s.keys,
                    None,
                    heads,
                    scale,
                    &mut s.attention,
                    &mut s.att,
                );
            }
            blk.time_o
                .forward_add(&s.att[..n * d], n, &mut s.h[..n * d]);

            // Agent attention: the agents of each slot.
            blk.ln_agents.forward(&s.h[..n * d], &mut s.t[..n * d]);
            blk.agents_qkv
                .forward(&s.t[..n * d], n, &mut s.qkv[..n * 3 * d]);
            for scene in 0..b {
                let agents = s.scene_starts[scene]..s.scene_starts[scene + 1];
                for slot in 0..w {
                    s.queries.clear();
                    s.queries
                        .extend(agents.clone().map(|agent| agent * w + slot));
                    unmasked_keys(&s.queries, &valid_token, &mut s.keys);
                    let pairs = match &blk.agents_pairs {
                        Some((k_weights, v_weights)) => {
                            s.key_positions.clear();
                            s.key_positions
                                .extend(s.keys.iter().map(|&key| key / w - agents.start));
                            let per_slot = agents.len() * agents.len() * PAIR_FEATURES;
                            Some(PairTerms {
                                features: &s.pair_features
                                    [s.pair_starts[scene] + slot * per_slot..][..per_slot],
                                key_positions: &s.key_positions,
                                candidates: agents.len(),
                                k_weights,
                                v_weights,
                            })
                        }
                        _ => None,
                    };
                    let kv = KeysValues::stacked(&s.qkv, d);
                    attend(
                        &s.qkv,
                        3 * d,
                        &s.queries,
                        &kv,
                        &s.keys,
                        pairs.as_ref(),
                        heads,
                        scale,
                        &mut s.attention,
                        &mut s.att,
                    );
                }
            }
            blk.agents_o
                .forward_add(&s.att[..n * d], n, &mut s.h[..n * d]);

            // Map cross-attention: every token of a scene to that scene's polylines, or to its
            // agent's own.
            blk.ln_map.forward(&s.h[..n * d], &mut s.t[..n * d]);
            blk.map_q.forward(&s.t[..n * d], n, &mut s.qkv[..n * d]);
            let blocks = self.blocks.len();
            // Query groups: each agent's W tokens (agent maps), or each scene's tokens.
            let groups = if k > 0 {
                s.agent_rows.len()
            } else {
                inputs.scene_ids.len()
            };
            for group in 0..groups {
                s.queries.clear();
                let kv = if k > 0 {
                    s.queries.extend(group * w..(group + 1) * w);
                    let slab = s.agent_slab[group];
                    let flags = &s.agent_map_valid[slab * k..][..k];
                    unmasked_keys(&agent_polylines, &|key| flags[key] > 0.0, &mut s.keys);
                    KeysValues::side_by_side(
                        &s.agent_map_kv[(slab * blocks + block_index) * k * 2 * d..][..k * 2 * d],
                        d,
                    )
                } else {
                    let scene = inputs.scene_ids[group];
                    s.queries
                        .extend(s.scene_starts[group] * w..s.scene_starts[group + 1] * w);
                    unmasked_keys(
                        &all_polylines,
                        &|key| cache.map_valid[scene * p + key] > 0.0,
                        &mut s.keys,
                    );
                    KeysValues::side_by_side(
                        &cache.map_kv[(scene * blocks + block_index) * p * 2 * d..][..p * 2 * d],
                        d,
                    )
                };
                attend(
                    &s.qkv,
                    d,
                    &s.queries,
                    &kv,
                    &s.keys,
                    None,
                    heads,
                    scale,
                    &mut s.attention,
                    &mut s.att,
                );
            }
            blk.map_o.forward_add(&s.att[..n * d], n, &mut s.h[..n * d]);

            // MLP.
            blk.ln_mlp.forward(&s.h[..n * d], &mut s.t[..n * d]);
            blk.mlp_in.forward(&s.t[..n * d], n, &mut s.hidden[..n * m]);
            for v in &mut s.hidden[..n * m] {
                *v = v.max(0.0);
            }
            blk.mlp_out
                .forward_add(&s.hidden[..n * m], n, &mut s.h[..n * d]);
        }
        self.ln_out.forward(&s.h[..n * d], &mut s.t[..n * d]);
        self.head.forward(&s.t[..n * d], n, &mut s.f[..n * 3]);
        self.precondition_output(inputs, a, &s.compact_of, &s.f[..n * 3], out);
    }

    /// Token embeddings `h [agents, W, D]` of the evaluated agent rows (docs/checkpoint.md,
    /// step 2, with the agent frame).
    fn embed(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        agent_rows: &[usize],
        h: &mut [f32],
    ) {
        let (a, w, d) = (cache.agents, self.slots, self.hidden);
        let sd = self.sigma_data;
        for (compact, &agent_row) in agent_rows.iter().enumerate() {
            let (local, agent) = (agent_row / a, agent_row % a);
            let scene = inputs.scene_ids[local];
            let agent_embedding = &cache.agent_embedding[(scene * a + agent) * d..][..d];
            let anchor = self.anchor(inputs, agent_row);
            for slot in 0..w {
                let token = agent_row * w + slot;
                let sigma = inputs.sigma[local * w + slot];
                let c_in = 1.0 / (sigma * sigma + sd * sd).sqrt();
                let c_noise = sigma.ln() * 0.25;
                let valid = inputs.valid[token];
                let x = &inputs.x[3 * token..][..3];
                let scaled = [
                    x[0] * c_in * valid,
                    x[1] * c_in * valid,
                    x[2] * c_in * valid,
                ];
                let row = &mut h[(compact * w + slot) * d..][..d];
                let st = &self.embed_state;
                let nz = &self.embed_noise;
                let slot_row = &self.slot_embedding[slot * d..][..d];
                for i in 0..d {
                    row[i] = st.weight[3 * i] * scaled[0]
                        + st.weight[3 * i + 1] * scaled[1]
                        + st.weight[3 * i + 2] * scaled[2]
                        + st.bias[i]
                        + nz.weight[i] * c_noise
                        + nz.bias[i]
                        + agent_embedding[i]
                        + slot_row[i];
                }
                if let (Some(frame), Some(rel), Some(anchor)) =
                    (&self.agent_frame, &self.embed_relative, &anchor)
                {
                    // The displacement the features rotate, and its c_in: from the anchor in
                    // the scene's units, or the scaled residual at σ·scale.
                    let (d3, c_in_rel) = match anchor.residual_scale {
                        None => (
                            [x[0] - anchor.x, x[1] - anchor.y, x[2] - anchor.heading],
                            c_in,
                        ),
                        Some(scale) => {
                            let r = anchor.reference(slot, self.anchor_slot());
                            let sigma_y = sigma * scale;
                            (
                                [
                                    (x[0] - r[0]) * scale,
                                    (x[1] - r[1]) * scale,
                                    (x[2] - r[2]) * scale,
                                ],
                                1.0 / (sigma_y * sigma_y + sd * sd).sqrt(),
                            )
                        }
                    };
                    let k = c_in_rel * frame.relative_scale as f32 * valid * anchor.valid;
                    let [dx, dy, dh] = d3;
                    let mut features = [0.0f32; 6];
                    features[..4].copy_from_slice(&[
                        (anchor.cos * dx + anchor.sin * dy) * k,
                        (anchor.cos * dy - anchor.sin * dx) * k,
                        dh * k,
                        anchor.valid,
                    ]);
                    if let Some(scale) = frame.residual_scale {
                        let scale = scale as f32;
                        let [sx, sy] = anchor.step;
                        features[4] = (anchor.cos * sx + anchor.sin * sy) * scale;
                        features[5] = (anchor.cos * sy - anchor.sin * sx) * scale;
                    }
                    let width = rel.d_in;
                    for ((r, wr), bias) in row
                        .iter_mut()
                        .zip(rel.weight.chunks_exact(width))
                        .zip(&rel.bias)
                    {
                        *r += wr
                            .iter()
                            .zip(&features[..width])
                            .map(|(w, f)| w * f)
                            .sum::<f32>()
                            + bias;
                    }
                }
            }
        }
    }

    /// The anchor of batch agent row `agent_row` as agent maps and pairs see it (the scene
    /// frame without an agent frame or an anchor).
    fn map_anchor(&self, inputs: &FastInputs<'_>, agent_row: usize) -> MapAnchor {
        self.anchor(inputs, agent_row)
            .map_or(MapAnchor::SCENE, |an| MapAnchor {
                x: an.x,
                y: an.y,
                cos: an.cos,
                sin: an.sin,
            })
    }

    fn anchor_slot(&self) -> usize {
        self.agent_frame.as_ref().map_or(0, |f| f.anchor_slot)
    }

    /// The agent frame's anchor of batch agent row `agent_row` (`None` without a frame).
    fn anchor(&self, inputs: &FastInputs<'_>, agent_row: usize) -> Option<Anchor> {
        let frame = self.agent_frame.as_ref()?;
        let token = agent_row * self.slots + frame.anchor_slot;
        let valid = inputs.valid[token];
        let x = &inputs.x[3 * token..][..3];
        let (x0, y0, heading) = (x[0] * valid, x[1] * valid, x[2] * valid);
        let (sin, cos) = (heading / self.heading_scale).sin_cos();
        let (mut step, mut residual_scale) = ([0.0; 2], None);
        if let Some(scale) = frame.residual_scale {
            // The scene frame (reference 0, scale 1) for an agent without an anchor.
            residual_scale = Some(if valid > 0.0 { scale as f32 } else { 1.0 });
            let both = valid * inputs.valid[token - 1];
            let before = &inputs.x[3 * (token - 1)..][..2];
            step = [(x[0] - before[0]) * both, (x[1] - before[1]) * both];
        }
        Some(Anchor {
            x: x0,
            y: y0,
            heading,
            cos,
            sin,
            valid,
            step,
            residual_scale,
        })
    }

    /// `D = c_skip · x + c_out · F · valid`, `F`'s position part turned back from the agent
    /// frame (docs/checkpoint.md, step 5); with a constant-velocity reference `r` and scale
    /// `s`, `D = r + (c_skip(σs) · s(x − r) + c_out(σs) · F · valid) / s`. Rows left out
    /// (`compact_of` = MAX) have no valid slot, hence no anchor, and `F · valid` = 0.
    fn precondition_output(
        &self,
        inputs: &FastInputs<'_>,
        a: usize,
        compact_of: &[usize],
        f: &[f32],
        out: &mut [f32],
    ) {
        let w = self.slots;
        let sd = self.sigma_data;
        for (agent_row, &compact) in compact_of
            .iter()
            .enumerate()
            .take(inputs.scene_ids.len() * a)
        {
            let anchor = if compact == usize::MAX {
                None
            } else {
                self.anchor(inputs, agent_row)
            };
            let local = agent_row / a;
            for slot in 0..w {
                let token = agent_row * w + slot;
                let x = &inputs.x[3 * token..][..3];
                let (reference, scale) = match &anchor {
                    Some(anchor) if anchor.residual_scale.is_some() => (
                        anchor.reference(slot, self.anchor_slot()),
                        anchor.residual_scale.unwrap_or(1.0),
                    ),
                    _ => ([0.0; 3], 1.0),
                };
                let sigma = inputs.sigma[local * w + slot] * scale;
                let denom = sigma * sigma + sd * sd;
                let c_skip = sd * sd / denom;
                let c_out = sigma * sd / denom.sqrt();
                let o = &mut out[3 * token..][..3];
                if compact == usize::MAX {
                    for c in 0..3 {
                        o[c] = c_skip * x[c];
                    }
                    continue;
                }
                let ct = compact * w + slot;
                let mut ft = [f[3 * ct], f[3 * ct + 1], f[3 * ct + 2]];
                if let Some(anchor) = &anchor {
                    ft = [
                        anchor.cos * ft[0] - anchor.sin * ft[1],
                        anchor.sin * ft[0] + anchor.cos * ft[1],
                        ft[2],
                    ];
                }
                let valid = inputs.valid[token];
                if scale == 1.0 && reference == [0.0; 3] {
                    for c in 0..3 {
                        o[c] = c_skip * x[c] + c_out * ft[c] * valid;
                    }
                } else {
                    for c in 0..3 {
                        let y = (x[c] - reference[c]) * scale;
                        o[c] = reference[c] + (c_skip * y + c_out * ft[c] * valid) / scale;
                    }
                }
            }
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Anchor {
    x: f32,
    y: f32,
    heading: f32,
    cos: f32,
    sin: f32,
    valid: f32,
    /// The last observed step (positions; zero unless both slots are valid).
    step: [f32; 2],
    /// With a constant-velocity reference: its scale (1 for an agent without an anchor).
    residual_scale: Option<f32>,
}

impl Anchor {
    /// The constant-velocity reference at `slot` (zero for an agent without an anchor).
    fn reference(&self, slot: usize, anchor_slot: usize) -> [f32; 3] {
        let t = slot as f32 - anchor_slot as f32;
        [
            self.x + t * self.step[0],
            self.y + t * self.step[1],
            self.heading,
        ]
    }
}

/// The keys of a group that are not masked; all of them when every one is (then every key
/// has the same bias, and softmax weighs them equally, as candle does).
fn unmasked_keys(candidates: &[usize], is_valid: &dyn Fn(usize) -> bool, keys: &mut Vec<usize>) {
    keys.clear();
    keys.extend(candidates.iter().copied().filter(|&k| is_valid(k)));
    if keys.is_empty() {
        keys.extend_from_slice(candidates);
    }
}

/// The pair features of slot `slot` between the evaluated agents `agents` (compact indices,
/// one scene's) into `out [agents, agents, F]`, as [`crate::agent_pairs::pair_features_of`].
#[allow(clippy::too_many_arguments)]
fn slot_pair_features(
    x: &[f32],
    agent_rows: &[usize],
    anchors: &[MapAnchor],
    agents: std::ops::Range<usize>,
    slot: usize,
    slots: usize,
    scales: PairScales,
    out: &mut [f32],
) {
    let f = PAIR_FEATURES;
    let n = agents.len();
    let state = |compact: usize| &x[3 * (agent_rows[compact] * slots + slot)..][..3];
    for (qi, query) in agents.clone().enumerate() {
        for (kj, key) in agents.clone().enumerate() {
            out[(qi * n + kj) * f..][..f].copy_from_slice(&pair_features(
                state(query),
                anchors[query],
                state(key),
                scales,
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn anchor(x: f32) -> MapAnchor {
        MapAnchor {
            x,
            y: 2.0,
            cos: 1.0,
            sin: 0.0,
        }
    }

    /// The memo hands an agent its slab back while its anchor stays put, re-encodes when the
    /// anchor moves or K changes, and frees the slabs of agents it has not seen for
    /// `MEMO_CALLS_KEPT` calls.
    #[test]
    fn agent_map_memo_reuses_and_frees_slabs() {
        let mut memo = AgentMapMemo::default();
        memo.start_call(12);
        assert_eq!(memo.slab_for((7, 0), anchor(1.0)), (0, false));
        assert_eq!(memo.slab_for((7, 1), anchor(1.0)), (1, false));
        memo.start_call(12);
        assert_eq!(memo.slab_for((7, 0), anchor(1.0)), (0, true));
        assert_eq!(
            memo.slab_for((7, 1), anchor(1.5)),
            (1, false),
            "the anchor moved"
        );
        assert_eq!(
            memo.slab_for((8, 0), anchor(1.0)),
            (2, false),
            "another scene"
        );
        for _ in 0..MEMO_CALLS_KEPT {
            memo.start_call(12);
            assert_eq!(memo.slab_for((7, 0), anchor(1.0)), (0, true));
        }
        memo.start_call(12);
        assert_eq!(memo.entries.len(), 1, "two entries unused for too long");
        let (slab, fresh) = memo.slab_for((9, 0), anchor(1.0));
        assert!(slab == 1 || slab == 2, "a freed slab is reused: {slab}");
        assert!(!fresh);
        assert_eq!(memo.slabs, 3);
        memo.start_call(6);
        assert_eq!(memo.slab_for((7, 0), anchor(1.0)), (0, false), "K changed");
        assert_eq!(memo.slabs, 1);
    }
}
