//! The fast CPU inference path: the denoiser's forward pass over plain buffers that are kept
//! from call to call, matrix products through `gemm`'s kernels (AVX2/FMA or AVX-512 chosen at
//! run time), attention fused per group of tokens (`fast_kernels`: no per-head tensors), the
//! map's keys and values computed once per scene set (scene maps) or once per anchor (agent
//! maps, [`AgentMapMemo`]), and the tokens of a batch split evenly across threads kept
//! between calls (the workers meet before each attention stage: `workers`). [`Denoiser`]
//! (candle) stays the reference: `tests/fast.rs` holds the two to the tolerance the WGSL
//! engine meets.
//!
//! candle spends most of an inference step outside its matrix products here (thread barriers
//! per op, allocation per op, tiny batched products for attention): see
//! `docs/experiments/bench-2026-11-23-fast-cpu-engine.md`.

mod workers;

use std::collections::HashMap;
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use candle_core::Tensor;
use candle_nn::{LayerNorm, Linear};

use road_model::agent_map::{MapAnchor, agent_map, polylines_per_agent};
use road_model::agent_pairs::{PAIR_FEATURES, PairScales};
use road_model::config::AgentFrame;
use road_model::model::{Attention, Denoiser};
use road_model::{Error, Result};

use crate::fast_kernels::{
    AttentionScratch, KeysValues, PairTerms, attend, exp_non_positive, layer_norm,
};

use workers::{Exchange, Helpers, Job, Slots};

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

/// The denoiser's forward pass on plain buffers, a batch's tokens split evenly between the
/// calling thread and helper threads kept between calls.
#[derive(Debug)]
pub struct FastDenoiser {
    /// Shared with the helper threads.
    net: Arc<Network>,
    /// Worker threads a call may use (the calling thread and `threads − 1` helpers).
    threads: usize,
    /// Held for a whole call (one call at a time).
    workers: Mutex<Workers>,
}

/// The denoiser's weights for the fast path (a copy of a [`Denoiser`]'s).
#[derive(Debug)]
struct Network {
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
}

/// What a batch of scenes needs besides the states: computed once per scene set.
#[derive(Debug, Clone, Default)]
pub struct SceneCache {
    pub scenes: usize,
    pub agents: usize,
    pub polylines: usize,
    /// Shared with the helper threads of a call (cloning the cache clones the pointer).
    data: Arc<SceneData>,
}

#[derive(Debug, Clone, Default)]
struct SceneData {
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
        let (data, one) = (Arc::make_mut(&mut self.data), &one.data);
        put(&mut data.agent_embedding, scene, &one.agent_embedding);
        put(&mut data.map_kv, scene, &one.map_kv);
        put(&mut data.map_points, scene, &one.map_points);
        put(&mut data.map_valid, scene, &one.map_valid);
        data.identities[scene] = new_identities(1)[0];
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

/// Per-worker buffers; `N` is the batch's evaluated tokens, of which a worker fills its own rows
/// (resized, never shrunk).
#[derive(Debug, Default)]
struct Scratch {
    h: Vec<f32>,      // [N, D]
    t: Vec<f32>,      // [N, D]
    map_q: Vec<f32>,  // [N, D] (self-attention's projections go to the `Exchange`'s slots)
    att: Vec<f32>,    // [N, D]
    hidden: Vec<f32>, // [N, M]
    f: Vec<f32>,      // [N, 3]
    queries: Vec<usize>,
    /// Agent attention's candidate keys (a scene's agents at one slot), before masking.
    candidates: Vec<usize>,
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
    /// `agent_map_valid [slabs, K]`; `agent_slab[i]` is the one the worker's agent i reads.
    agent_map_kv: Vec<f32>,
    agent_slab: Vec<usize>,
    agent_map_memo: AgentMapMemo,
    /// The agents whose maps a call encodes: (compact agent, slab, anchor).
    stale_agent_maps: Vec<(usize, usize, MapAnchor)>,
    /// Agent pairs: each of the worker's agents' anchor; the pair features of every (scene,
    /// slot), `[queries, agents_s, F]` each (the agents of the worker's tokens of that slot by
    /// all of the scene's agents), from `pair_starts[scene · W + slot]` (the same in every
    /// block); the unmasked keys' positions among the scene's agents.
    pair_anchors: Vec<MapAnchor>,
    pair_features: Vec<f32>,
    pair_starts: Vec<usize>,
    key_positions: Vec<usize>,
    pair_rows: PairRows,
}

/// What [`slot_pair_features`] keeps between calls: per key, its heading angle's sine and
/// cosine; per query, its row of proximities.
#[derive(Debug, Default)]
struct PairRows {
    key_sin_cos: Vec<(f32, f32)>,
    near: Vec<f32>,
    far: Vec<f32>,
}

/// The agent rows a call evaluates: those with a valid slot. The others (padding, or agents
/// absent from the whole window) are masked as keys everywhere and their output is
/// `c_skip · x` whatever the network says, so leaving them out changes nothing but the time.
#[derive(Debug, Default)]
struct EvaluatedAgents {
    /// Compact agent index → batch agent row.
    rows: Vec<usize>,
    /// Compact agent index where each scene starts (one more entry at the end).
    scene_starts: Vec<usize>,
    /// Batch agent row → compact agent index (`usize::MAX`: not evaluated).
    compact_of: Vec<usize>,
}

impl EvaluatedAgents {
    /// The evaluated agents of `valid [B, A, W]`.
    fn find(&mut self, valid: &[f32], agents: usize, slots: usize) {
        self.rows.clear();
        self.scene_starts.clear();
        self.compact_of.clear();
        self.compact_of.resize(valid.len() / slots, usize::MAX);
        for (row, flags) in valid.chunks_exact(slots).enumerate() {
            if row % agents == 0 {
                self.scene_starts.push(self.rows.len());
            }
            if flags.iter().any(|&v| v > 0.0) {
                self.compact_of[row] = self.rows.len();
                self.rows.push(row);
            }
        }
        self.scene_starts.push(self.rows.len());
    }

    /// The compact agents of batch row `scene`.
    fn scene(&self, scene: usize) -> Range<usize> {
        self.scene_starts[scene]..self.scene_starts[scene + 1]
    }
}

/// The indices in both ranges.
fn overlap(a: &Range<usize>, b: &Range<usize>) -> Range<usize> {
    let start = a.start.max(b.start);
    start..a.end.min(b.end).max(start)
}

/// The agents with a token in `tokens` (`slots` tokens an agent).
fn agents_of(tokens: &Range<usize>, slots: usize) -> Range<usize> {
    tokens.start / slots..tokens.end.div_ceil(slots)
}

/// The agents whose token of slot `slot` is in `tokens`.
fn agents_at_slot(tokens: &Range<usize>, slot: usize, slots: usize) -> Range<usize> {
    tokens.start.saturating_sub(slot).div_ceil(slots)
        ..tokens.end.saturating_sub(slot).div_ceil(slots)
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

/// What a worker keeps between calls: its buffers and the agents of its last share.
#[derive(Debug, Default)]
struct WorkerState {
    scratch: Scratch,
    agents: EvaluatedAgents,
}

/// The calling thread's own [`WorkerState`], the helper threads (each keeps its own), and
/// every worker's projection slots ([`Exchange`]).
#[derive(Debug)]
struct Workers {
    own: WorkerState,
    helpers: Helpers<WorkerState, Vec<f32>>,
    slots: Arc<[Slots]>,
    /// Output buffers the helpers handed back, for their next jobs.
    spare_outputs: Vec<Vec<f32>>,
    /// Consecutive calls whose workers spent much of their time waiting for each other.
    contended_calls: usize,
    /// Calls left to run on the calling thread alone, after contended ones.
    calls_alone: usize,
    /// How many calls the next fallback runs alone (doubling while contention persists).
    next_calls_alone: usize,
    /// Whether contended calls fall back to the calling thread alone
    /// ([`FastDenoiser::fall_back_when_contended`]); off: every call splits the same way.
    fallback: bool,
}

/// Consecutive contended calls ([`Exchange::contended`]) after which the calls run on the
/// calling thread alone: on a machine whose cores are busy with other work the workers would
/// wait for a core at every meeting (measured: one scene's tick 1.1–10× slower than on one
/// thread). Not one: single calls also wait now and then on a quiet machine (a helper waking
/// up after a pause, page faults).
const CONTENDED_CALLS: usize = 3;

/// Calls run alone after contention: few at first (a helper just woken may share the
/// caller's core for a few milliseconds, until the scheduler moves it), doubling while the
/// contention persists, back to the fewest after a split call without it.
const CALLS_ALONE: Range<usize> = 8..256;

impl Workers {
    fn new(threads: usize) -> Self {
        Self {
            own: WorkerState::default(),
            helpers: Helpers::new(threads - 1),
            slots: (0..threads).map(|_| Slots::default()).collect(),
            spare_outputs: Vec::new(),
            contended_calls: 0,
            calls_alone: 0,
            next_calls_alone: CALLS_ALONE.start,
            fallback: false,
        }
    }
}

/// The part of a batch one worker evaluates: a range of its compact tokens, and the batch
/// tokens whose output it writes.
struct Share<'a> {
    tokens: Range<usize>,
    out_tokens: Range<usize>,
    /// Where it meets the workers that hold the other tokens of its scenes, as worker
    /// `worker`.
    exchange: &'a Exchange,
    worker: usize,
}

/// A copy of a batch's inputs that a helper thread can hold.
struct OwnedInputs {
    x: Vec<f32>,
    sigma: Vec<f32>,
    valid: Vec<f32>,
    scene_ids: Vec<usize>,
}

impl OwnedInputs {
    fn of(inputs: &FastInputs<'_>) -> Self {
        Self {
            x: inputs.x.to_vec(),
            sigma: inputs.sigma.to_vec(),
            valid: inputs.valid.to_vec(),
            scene_ids: inputs.scene_ids.to_vec(),
        }
    }

    fn view(&self) -> FastInputs<'_> {
        FastInputs {
            x: &self.x,
            sigma: &self.sigma,
            valid: &self.valid,
            scene_ids: &self.scene_ids,
        }
    }
}

impl FastDenoiser {
    /// Copies the weights of `model`; `threads` workers at most per call (≥ 1): the calling
    /// thread and `threads − 1` helper threads, started now.
    pub fn new(model: &Denoiser, threads: usize) -> Result<Self> {
        let threads = threads.max(1);
        Ok(Self {
            net: Arc::new(Network::new(model)?),
            threads,
            workers: Mutex::new(Workers::new(threads)),
        })
    }

    /// Whether calls whose workers keep waiting for each other (a machine busy with other
    /// work) fall back to the calling thread alone for a while: faster there (one scene's tick
    /// was measured 1.1–10× slower split), but a call's bits then depend on the machine's load
    /// (one worker rounds differently from two), so a seed no longer reproduces its samples
    /// (issue 41). Off unless asked for.
    pub fn fall_back_when_contended(&self, on: bool) {
        self.workers.lock().expect("workers lock").fallback = on;
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
        self.net
            .scene_cache(scenes, agents, features, map, map_valid)
    }

    /// `D(x; σ)` of every batch row into `out [B, A, W, 3]`.
    pub fn denoise(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        out: &mut [f32],
    ) -> Result<()> {
        let (a, w) = (cache.agents, self.net.slots);
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
        // A call that panicked poisons the lock: its helpers had finished (`Helpers::run`
        // waits for them), but the calling thread's buffers may be half written.
        let mut workers = self.workers.lock().unwrap_or_else(|poisoned| {
            let mut workers = poisoned.into_inner();
            workers.own = WorkerState::default();
            workers
        });
        self.workers.clear_poison();
        self.split_tokens(cache, inputs, &mut workers, out);
        Ok(())
    }

    /// Each worker takes an equal contiguous range of the batch's evaluated tokens (so that
    /// one scene runs on all cores, and a batch of scenes of unequal sizes splits evenly); they
    /// meet before each attention stage ([`Exchange`]). The helpers take the first ranges, the
    /// calling thread the last.
    fn split_tokens(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        workers: &mut Workers,
        out: &mut [f32],
    ) {
        let (a, w) = (cache.agents, self.net.slots);
        let b = inputs.scene_ids.len();
        let Workers {
            own,
            helpers,
            slots,
            spare_outputs,
            contended_calls,
            calls_alone,
            next_calls_alone,
            fallback,
        } = workers;
        own.agents.find(inputs.valid, a, w);
        let agents = &own.agents;
        let tokens = agents.rows.len() * w;
        // No more workers than agents: a share of a few tokens would cost more than it saves.
        let mut count = self.threads.min(agents.rows.len()).max(1);
        if *calls_alone > 0 {
            *calls_alone -= 1;
            count = 1;
        }
        // Worker i takes compact tokens [first(i), first(i + 1)) and writes the output of the
        // batch tokens from its first one's (padding rows go with the tokens before them).
        let first = |i: usize| tokens * i / count;
        let first_output = |i: usize| match i {
            0 => 0,
            i if i == count => b * a * w,
            i => agents.rows[first(i) / w] * w + first(i) % w,
        };
        let exchange = Arc::new(Exchange::new(
            Arc::clone(slots),
            (1..=count).map(first).collect(),
        ));
        let last = count - 1;
        let mut jobs: Vec<Job<WorkerState, Vec<f32>>> = Vec::with_capacity(last);
        if last > 0 {
            // One copy of the (small) batch for all helpers.
            let batch = Arc::new(OwnedInputs::of(inputs));
            for i in 0..last {
                let (net, cache) = (Arc::clone(&self.net), cache.clone());
                let (batch, exchange) = (Arc::clone(&batch), Arc::clone(&exchange));
                let (tokens, out_tokens) =
                    (first(i)..first(i + 1), first_output(i)..first_output(i + 1));
                let mut output = spare_outputs.pop().unwrap_or_default();
                jobs.push(Box::new(move |state: &mut WorkerState| {
                    let _release = exchange.break_on_panic();
                    let inputs = batch.view();
                    // The same agents as the caller's: a few comparisons, no copy to send.
                    state.agents.find(inputs.valid, a, w);
                    output.resize(out_tokens.len() * 3, 0.0);
                    let share = Share {
                        tokens,
                        out_tokens,
                        exchange: &exchange,
                        worker: i,
                    };
                    net.forward(
                        &cache,
                        &inputs,
                        &state.agents,
                        &share,
                        &mut state.scratch,
                        &mut output,
                    );
                    output
                }));
            }
        }
        let own_share = Share {
            tokens: first(last)..first(count),
            out_tokens: first_output(last)..first_output(count),
            exchange: &exchange,
            worker: last,
        };
        let (head, own_out) = out.split_at_mut(own_share.out_tokens.start * 3);
        let started = Instant::now();
        let outputs = helpers.run(jobs, || {
            let _release = exchange.break_on_panic();
            self.net
                .forward(cache, inputs, agents, &own_share, &mut own.scratch, own_out);
        });
        for (i, output) in outputs.into_iter().enumerate() {
            let range = first_output(i) * 3..first_output(i + 1) * 3;
            head[range.clone()].copy_from_slice(&output[..range.len()]);
            spare_outputs.push(output);
        }
        if count == 1 || !*fallback {
            return;
        }
        if exchange.contended(started.elapsed()) {
            *contended_calls += 1;
            if *contended_calls == CONTENDED_CALLS {
                *contended_calls = 0;
                *calls_alone = *next_calls_alone;
                *next_calls_alone = (*next_calls_alone * 2).min(CALLS_ALONE.end);
            }
        } else {
            *contended_calls = 0;
            *next_calls_alone = CALLS_ALONE.start;
        }
    }
}

impl Network {
    fn new(model: &Denoiser) -> Result<Self> {
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
        })
    }

    fn scene_cache(
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
            data: Arc::new(SceneData {
                agent_embedding,
                map_kv,
                map_points,
                map_valid: map_valid.to_vec(),
                identities: new_identities(scenes),
            }),
        })
    }

    /// The own map of each of the compact agents `mine` (agent-map models): its polylines
    /// picked and encoded in its anchor frame, then each block's keys and values, into the
    /// agent's slab of the scratch's `agent_map_kv [slabs, blocks, K, 2D]` and
    /// `agent_map_valid [slabs, K]` (`agent_slab[agent − mine.start]`); agents whose anchor has
    /// not moved since an earlier call keep their slab as it is ([`AgentMapMemo`]). Returns K.
    fn agent_maps(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        agents: &EvaluatedAgents,
        mine: Range<usize>,
        s: &mut Scratch,
    ) -> usize {
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
        for compact in mine {
            let agent_row = agents.rows[compact];
            let scene = inputs.scene_ids[agent_row / a];
            let key = (cache.data.identities[scene], agent_row % a);
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
            let scene = inputs.scene_ids[agents.rows[compact] / a];
            agent_map(
                anchor,
                &cache.data.map_points[scene * p * q * 2..][..p * q * 2],
                &cache.data.map_valid[scene * p..][..p],
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

    /// The forward pass of a worker's share of a batch on this thread: the products, layer
    /// norms and attention queries of its tokens, and the output of its batch tokens. The
    /// buffers are indexed by compact token over the whole batch; a worker fills only its own
    /// rows. Masked keys are skipped (their softmax weight is exactly 0 in f32) unless every
    /// key of a group is masked, where the candle model averages over all of them and so does
    /// this.
    fn forward(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        agents: &EvaluatedAgents,
        share: &Share<'_>,
        s: &mut Scratch,
        out: &mut [f32],
    ) {
        let (w, d) = (self.slots, self.hidden);
        let b = inputs.scene_ids.len();
        let mine = share.tokens.clone();
        let n = mine.len();
        let rows = |width: usize| mine.start * width..mine.end * width;
        // The agents with a token of this worker's (the first and the last may have tokens of
        // the neighbouring workers' too).
        let my_agents = agents_of(&mine, w);
        let all_tokens = agents.rows.len() * w;
        let m = self.blocks.first().map_or(d, |blk| blk.mlp_in.d_out);
        for (buf, width) in [
            (&mut s.h, d),
            (&mut s.t, d),
            (&mut s.map_q, d),
            (&mut s.att, d),
            (&mut s.hidden, m),
            (&mut s.f, 3),
        ] {
            buf.resize((all_tokens * width).max(buf.len()), 0.0);
        }
        self.embed(cache, inputs, agents, mine.clone(), &mut s.h);
        let k = self.agent_maps(cache, inputs, agents, my_agents.clone(), s);
        if let Some(scales) = self.pair_scales {
            s.pair_anchors.clear();
            for &agent_row in &agents.rows[my_agents.clone()] {
                s.pair_anchors.push(self.map_anchor(inputs, agent_row));
            }
            s.pair_starts.clear();
            let mut len = 0;
            for scene in 0..b {
                let candidates = agents.scene(scene);
                for slot in 0..w {
                    s.pair_starts.push(len);
                    let queries = overlap(&candidates, &agents_at_slot(&mine, slot, w));
                    len += queries.len() * candidates.len() * PAIR_FEATURES;
                }
            }
            s.pair_features.resize(len, 0.0);
            for scene in 0..b {
                let candidates = agents.scene(scene);
                for slot in 0..w {
                    let queries = overlap(&candidates, &agents_at_slot(&mine, slot, w));
                    if queries.is_empty() {
                        continue;
                    }
                    let per_slot = queries.len() * candidates.len() * PAIR_FEATURES;
                    let anchors =
                        &s.pair_anchors[queries.start - my_agents.start..][..queries.len()];
                    slot_pair_features(
                        inputs.x,
                        &agents.rows,
                        anchors,
                        queries,
                        candidates.clone(),
                        slot,
                        w,
                        scales,
                        &mut s.pair_rows,
                        &mut s.pair_features[s.pair_starts[scene * w + slot]..][..per_slot],
                    );
                }
            }
        }
        let valid_token = |compact_token: usize| {
            inputs.valid[agents.rows[compact_token / w] * w + compact_token % w] > 0.0
        };
        let heads = self.heads;
        let scale = 1.0 / ((d / heads) as f32).sqrt();
        let p = cache.polylines;
        let all_polylines: Vec<usize> = (0..p).collect();
        let agent_polylines: Vec<usize> = (0..k).collect();
        let exchange = share.exchange;
        for (block_index, blk) in self.blocks.iter().enumerate() {
            // Time attention: the W slots of each agent.
            blk.ln_time.forward(&s.h[rows(d)], &mut s.t[rows(d)]);
            exchange.publish(share.worker, 0, all_tokens * 3 * d, |projections| {
                blk.time_qkv
                    .forward(&s.t[rows(d)], n, &mut projections[rows(3 * d)]);
            });
            {
                let published = exchange.gather(0);
                let parts = published.parts();
                let kv = KeysValues::stacked_parts(&parts, d);
                let my_projections = parts[share.worker].1;
                for agent in my_agents.clone() {
                    let agent_tokens = agent * w..(agent + 1) * w;
                    s.queries.clear();
                    s.queries.extend(overlap(&agent_tokens, &mine));
                    s.candidates.clear();
                    s.candidates.extend(agent_tokens);
                    unmasked_keys(&s.candidates, &valid_token, &mut s.keys);
                    attend(
                        my_projections,
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
            }
            blk.time_o
                .forward_add(&s.att[rows(d)], n, &mut s.h[rows(d)]);

            // Agent attention: the agents of each slot.
            blk.ln_agents.forward(&s.h[rows(d)], &mut s.t[rows(d)]);
            exchange.publish(share.worker, 1, all_tokens * 3 * d, |projections| {
                blk.agents_qkv
                    .forward(&s.t[rows(d)], n, &mut projections[rows(3 * d)]);
            });
            {
                let published = exchange.gather(1);
                let parts = published.parts();
                let kv = KeysValues::stacked_parts(&parts, d);
                let my_projections = parts[share.worker].1;
                for scene in 0..b {
                    let candidates = agents.scene(scene);
                    for slot in 0..w {
                        let queries = overlap(&candidates, &agents_at_slot(&mine, slot, w));
                        if queries.is_empty() {
                            continue;
                        }
                        s.queries.clear();
                        s.queries
                            .extend(queries.clone().map(|agent| agent * w + slot));
                        s.candidates.clear();
                        s.candidates
                            .extend(candidates.clone().map(|agent| agent * w + slot));
                        unmasked_keys(&s.candidates, &valid_token, &mut s.keys);
                        let pairs = match &blk.agents_pairs {
                            Some((k_weights, v_weights)) => {
                                s.key_positions.clear();
                                s.key_positions
                                    .extend(s.keys.iter().map(|&key| key / w - candidates.start));
                                let per_slot = queries.len() * candidates.len() * PAIR_FEATURES;
                                Some(PairTerms {
                                    features: &s.pair_features[s.pair_starts[scene * w + slot]..]
                                        [..per_slot],
                                    key_positions: &s.key_positions,
                                    candidates: candidates.len(),
                                    k_weights,
                                    v_weights,
                                })
                            }
                            _ => None,
                        };
                        attend(
                            my_projections,
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
            }
            blk.agents_o
                .forward_add(&s.att[rows(d)], n, &mut s.h[rows(d)]);

            // Map cross-attention: every token of a scene to that scene's polylines, or to its
            // agent's own.
            blk.ln_map.forward(&s.h[rows(d)], &mut s.t[rows(d)]);
            blk.map_q.forward(&s.t[rows(d)], n, &mut s.map_q[rows(d)]);
            let blocks = self.blocks.len();
            // Query groups: each agent's tokens (agent maps), or each scene's.
            let groups = if k > 0 { my_agents.clone() } else { 0..b };
            for group in groups {
                s.queries.clear();
                let kv = if k > 0 {
                    s.queries
                        .extend(overlap(&(group * w..(group + 1) * w), &mine));
                    let slab = s.agent_slab[group - my_agents.start];
                    let flags = &s.agent_map_valid[slab * k..][..k];
                    unmasked_keys(&agent_polylines, &|key| flags[key] > 0.0, &mut s.keys);
                    KeysValues::side_by_side(
                        &s.agent_map_kv[(slab * blocks + block_index) * k * 2 * d..][..k * 2 * d],
                        d,
                    )
                } else {
                    let scene_agents = agents.scene(group);
                    let scene_tokens = scene_agents.start * w..scene_agents.end * w;
                    s.queries.extend(overlap(&scene_tokens, &mine));
                    if s.queries.is_empty() {
                        continue;
                    }
                    let scene = inputs.scene_ids[group];
                    unmasked_keys(
                        &all_polylines,
                        &|key| cache.data.map_valid[scene * p + key] > 0.0,
                        &mut s.keys,
                    );
                    KeysValues::side_by_side(
                        &cache.data.map_kv[(scene * blocks + block_index) * p * 2 * d..]
                            [..p * 2 * d],
                        d,
                    )
                };
                attend(
                    &s.map_q,
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
            blk.map_o.forward_add(&s.att[rows(d)], n, &mut s.h[rows(d)]);

            // MLP.
            blk.ln_mlp.forward(&s.h[rows(d)], &mut s.t[rows(d)]);
            blk.mlp_in.forward(&s.t[rows(d)], n, &mut s.hidden[rows(m)]);
            for v in &mut s.hidden[rows(m)] {
                *v = v.max(0.0);
            }
            blk.mlp_out
                .forward_add(&s.hidden[rows(m)], n, &mut s.h[rows(d)]);
        }
        self.ln_out.forward(&s.h[rows(d)], &mut s.t[rows(d)]);
        self.head.forward(&s.t[rows(d)], n, &mut s.f[rows(3)]);
        self.precondition_output(inputs, agents, share.out_tokens.clone(), &s.f, out);
    }

    /// Token embeddings `h [compact tokens, D]` of the compact tokens `tokens`
    /// (docs/checkpoint.md, step 2, with the agent frame).
    fn embed(
        &self,
        cache: &SceneCache,
        inputs: &FastInputs<'_>,
        agents: &EvaluatedAgents,
        tokens: Range<usize>,
        h: &mut [f32],
    ) {
        let (a, w, d) = (cache.agents, self.slots, self.hidden);
        let sd = self.sigma_data;
        for compact in agents_of(&tokens, w) {
            let agent_row = agents.rows[compact];
            let (local, agent) = (agent_row / a, agent_row % a);
            let scene = inputs.scene_ids[local];
            let agent_embedding = &cache.data.agent_embedding[(scene * a + agent) * d..][..d];
            let anchor = self.anchor(inputs, agent_row);
            for compact_token in overlap(&(compact * w..(compact + 1) * w), &tokens) {
                let slot = compact_token % w;
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
                let row = &mut h[compact_token * d..][..d];
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
    /// `s`, `D = r + (c_skip(σs) · s(x − r) + c_out(σs) · F · valid) / s`, for the batch
    /// tokens `tokens` (`out` starts at the first). Rows not evaluated (`compact_of` = MAX)
    /// have no valid slot, hence no anchor, and `F · valid` = 0.
    fn precondition_output(
        &self,
        inputs: &FastInputs<'_>,
        agents: &EvaluatedAgents,
        tokens: Range<usize>,
        f: &[f32],
        out: &mut [f32],
    ) {
        let w = self.slots;
        let sd = self.sigma_data;
        let a = agents.compact_of.len() / inputs.scene_ids.len();
        for agent_row in agents_of(&tokens, w) {
            let compact = agents.compact_of[agent_row];
            let anchor = if compact == usize::MAX {
                None
            } else {
                self.anchor(inputs, agent_row)
            };
            let local = agent_row / a;
            for token in overlap(&(agent_row * w..(agent_row + 1) * w), &tokens) {
                let slot = token % w;
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
                let o = &mut out[3 * (token - tokens.start)..][..3];
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

/// The pair features of slot `slot` between the evaluated agents `queries` and
/// `candidates` (compact indices, one scene's; `query_anchors` the queries') into
/// `out [queries, candidates, F]`: `road_model::agent_pairs::pair_features`'s, computed a row at
/// a time. Why not pair by pair: a slot has A² pairs and a tick evaluates every slot 8 times,
/// so the per-pair `sin_cos` and two `exp`s were a fifth of a 16-scene tick. Here each key's
/// heading sine and cosine is taken once (the difference's by the angle-difference identities)
/// and the proximities a register of keys at a time; the results agree with the per-pair
/// function to float rounding (a test).
#[allow(clippy::too_many_arguments)]
fn slot_pair_features(
    x: &[f32],
    agent_rows: &[usize],
    query_anchors: &[MapAnchor],
    queries: Range<usize>,
    candidates: Range<usize>,
    slot: usize,
    slots: usize,
    scales: PairScales,
    rows: &mut PairRows,
    out: &mut [f32],
) {
    let f = PAIR_FEATURES;
    let n = candidates.len();
    let state = |compact: usize| &x[3 * (agent_rows[compact] * slots + slot)..][..3];
    let angle_sin_cos = |compact: usize| (state(compact)[2] / scales.heading_scale).sin_cos();
    rows.key_sin_cos.clear();
    rows.key_sin_cos
        .extend(candidates.clone().map(angle_sin_cos));
    for buf in [&mut rows.near, &mut rows.far] {
        buf.clear();
        buf.resize(n, 0.0);
    }
    for (qi, (query, &anchor)) in queries.zip(query_anchors).enumerate() {
        let q = state(query);
        let (q_sin, q_cos) = angle_sin_cos(query);
        let pair_out = &mut out[qi * n * f..][..n * f];
        for (kj, key) in candidates.clone().enumerate() {
            let k = state(key);
            let (dx, dy) = (k[0] - q[0], k[1] - q[1]);
            let forward = dx * anchor.cos + dy * anchor.sin;
            let left = dy * anchor.cos - dx * anchor.sin;
            let distance = (forward * forward + left * left).sqrt();
            let squash = 1.0 / (distance + scales.direction);
            let (k_sin, k_cos) = rows.key_sin_cos[kj];
            let features = &mut pair_out[kj * f..][..f];
            features[0] = forward * squash;
            features[1] = left * squash;
            // cos and sin of (key angle − query angle).
            features[4] = k_cos * q_cos + k_sin * q_sin;
            features[5] = k_sin * q_cos - k_cos * q_sin;
            rows.near[kj] = -distance / scales.near;
            rows.far[kj] = -distance / scales.far;
        }
        exp_non_positive(&mut rows.near);
        exp_non_positive(&mut rows.far);
        for kj in 0..n {
            pair_out[kj * f + 2] = rows.near[kj];
            pair_out[kj * f + 3] = rows.far[kj];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use road_model::agent_pairs::pair_features;

    fn anchor(x: f32) -> MapAnchor {
        MapAnchor {
            x,
            y: 2.0,
            cos: 1.0,
            sin: 0.0,
        }
    }

    /// The row-at-a-time pair features equal the per-pair function's to float rounding, for
    /// queries that are a part of the candidates, over headings that wrap and distances from
    /// zero to far beyond the proximity scales.
    #[test]
    fn slot_pair_features_match_the_per_pair_function() {
        let (agents, slots, slot) = (9, 4, 2);
        let scales = PairScales {
            direction: 0.25,
            near: 0.125,
            far: 0.5,
            heading_scale: 0.25,
        };
        // x [agents, slots, 3] in scene units; agent rows in reverse to exercise the lookup.
        let x: Vec<f32> = (0..agents * slots * 3)
            .map(|i| ((i as f32 * 0.7311).sin() * 3.0 + (i % 5) as f32 * 0.4) * 0.9)
            .collect();
        let agent_rows: Vec<usize> = (0..agents).rev().collect();
        let (queries, candidates) = (2..6, 0..agents);
        let anchors: Vec<MapAnchor> = queries
            .clone()
            .map(|q| {
                let heading = q as f32 * 1.3 - 2.0;
                MapAnchor {
                    x: 0.0,
                    y: 0.0,
                    cos: heading.cos(),
                    sin: heading.sin(),
                }
            })
            .collect();
        let f = PAIR_FEATURES;
        let mut out = vec![f32::NAN; queries.len() * candidates.len() * f];
        slot_pair_features(
            &x,
            &agent_rows,
            &anchors,
            queries.clone(),
            candidates.clone(),
            slot,
            slots,
            scales,
            &mut PairRows::default(),
            &mut out,
        );
        let state = |c: usize| &x[3 * (agent_rows[c] * slots + slot)..][..3];
        for (qi, q) in queries.enumerate() {
            for (kj, k) in candidates.clone().enumerate() {
                let want = pair_features(state(q), anchors[qi], state(k), scales);
                let got = &out[(qi * candidates.len() + kj) * f..][..f];
                for (g, w) in got.iter().zip(want) {
                    assert!(
                        (g - w).abs() <= 1e-6 + 1e-5 * w.abs(),
                        "{q}→{k}: {got:?} vs {want:?}"
                    );
                }
            }
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
