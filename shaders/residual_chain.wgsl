// The residual chain: what a transformer block does between two attentions, as one kernel
// over a tile of rows (one dispatch instead of up to four; the MLP's hidden layer and the head's
// F never leave the chip):
//   h ← h + att · W_oᵀ + b_o                                  (the attention's output projection)
//   h ← h + W_2 · relu(W_1 · n(h) + b_1) + b_2                (the MLP, when m > 0)
//   y ← n(h) · W_nextᵀ + b_next                               (the next layer, when next_out > 0)
// n is the layer norm with its γ, β folded into the layer after it (as `linear.wgsl`'s `norm`),
// y goes to parts as `linear.wgsl`'s (the next attention's q/k/v) or, with `precondition`, is
// the head's F and the kernel writes D(x; σ) instead (common/precondition.wgsl, prepended),
// and with `update` also the sampler's step from it (heun.wgsl's `heun_euler`, then its
// `multistep_correct` where γ ≠ 0; γ is 0 in a Heun step): x_e, a dispatch saved. With
// `attend`, att is the attention of the tile's rows, made here from their q (bound as `att`)
// and keys grouped by agent row (the map's kept keys, or the agent's W slots for attention
// over time): the attention's dispatch saved too.
// Every weight lives in one bound range of the weights buffer, at offsets in floats, transposed
// ([in, out]: the engine transposes them on upload) so that neighbouring invocations load
// neighbouring weights. A workgroup of CHAIN_LANES holds CHAIN_ROWS rows of a layer's input in
// workgroup memory; each invocation computes blocks of a layer's outputs in registers and adds
// them into h itself (no other invocation touches those elements). The next layer's input is
// read back from h, standardised once per row. The MLP runs its hidden layer CHAIN_UNITS units
// at a time (tiny-cuda-nn's pattern).
// The tile's shape is set per pipeline by override constants (`ChainTile` on the host):
// - narrow (the default): 8 rows, 64 invocations, blocks of 4 rows × 4 columns (16 sums, 5
//   loads per 16 products), weights read one float at a time at any offset. Few rows a
//   workgroup: the most workgroups at small batches.
// - wide (`WIDE_BLOCKS`): 32 or 64 rows, blocks of 8 rows × 8 columns (64 sums, 8 workgroup
//   reads and two vec4 weight reads per 64 products; linear.wgsl's `linear_blocked` ratio), the
//   weights' rows read as vec4 (offsets, widths and strides multiples of 4, checked on the
//   host). Each weight read from L2 serves 4–8× the rows: the large batches' layout.
// Both keep rows TILE_D floats apart (odd, so that the rows a warp reads at once fall in
// distinct banks) and the hidden units CHAIN_UNITS + 1 apart for the same reason.

struct Params {
    rows: u32,        // tokens
    d: u32,           // hidden width D (≤ TILE_D)
    m: u32,           // the MLP's hidden width (0: no MLP)
    eps: f32,         // the layer norms'
    o_w: u32,         // offsets into `weights` (floats): W_oᵀ [D, D], b_o [D]
    o_b: u32,
    w1: u32,          // W_1ᵀ [D, M], b_1 [M], W_2ᵀ [M, D], b_2 [D]
    b1: u32,
    w2: u32,
    b2: u32,
    next_w: u32,      // W_nextᵀ [D, next_out], b_next [next_out]
    next_b: u32,
    next_out: u32,    // outputs of the next layer (0: none)
    part: u32,        // outputs per part of y
    part_stride: u32, // floats from one part of y to the next
    precondition: u32, // 1: the next layer is the head (3 outputs); write D(x; σ) into y
    slots: u32,       // precondition: W
    agents: u32,      // precondition: A
    anchor_slot: u32, // precondition: the agent frame's anchor slot, or NO_FRAME
    sigma_data: f32,
    heading_scale: f32,
    residual_scale: f32,
    update: u32,      // precondition: 1 also writes x_e (the Euler step, γ-corrected)
    relative_scale: f32, // embed_chain: the agent frame's relative features' multiplier
    attend: u32,      // 1: the attention's rows are made here (`attention_rows`) from their queries in `att`
    heads: u32,       // attend: heads, each of head_dim columns (heads · head_dim = D)
    head_dim: u32,
    scale: f32,       // attend: 1 / √head_dim
    keys: u32,        // attend: keys per agent row (K, its own) or per map scene (P); agents: A
    key_mode: u32,    // attend: 0, agent row n's keys are rows n·keys …; 1, those of its scene agent_scene[n]; 2, the agents of its scene at its slot
    k_off: u32,       // attend: offsets (floats) of the keys' k and v in map_kv
    v_off: u32,
    pairs: u32,       // attend, key_mode 2: 1 adds the agent-pair features (agent_pairs.wgsl) from x
    direction: f32,   // pairs: length scales in state units (heading_scale is the pairs')
    near: f32,
    far: f32,
}

override CHAIN_ROWS: u32 = 8u;    // rows (tokens) of a workgroup
override CHAIN_LANES: u32 = 64u;  // invocations of a workgroup
override CHAIN_UNITS: u32 = 128u; // MLP hidden units a chunk
override TILE_D: u32 = 257u;      // floats from one row of the tile to the next (≥ D)
override WIDE_BLOCKS: bool = false;
const NO_FRAME: u32 = 0xffffffffu;
const NO_BIAS: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> weights: array<vec4<f32>>; // read as floats by `weight`
@group(0) @binding(2) var<storage, read> att: array<f32>;      // [rows, D]
@group(0) @binding(3) var<storage, read_write> h: array<f32>;  // [rows, D]
@group(0) @binding(4) var<storage, read_write> y: array<f32>;  // [parts, part_stride], or D [rows, 3]
@group(0) @binding(5) var<storage, read> x: array<f32>;        // precondition: [rows, 3]
@group(0) @binding(6) var<storage, read> sigma: array<f32>;    // precondition: [B, W]
@group(0) @binding(7) var<storage, read> valid: array<f32>;    // precondition: [rows]
@group(0) @binding(8) var<storage, read> sigma_next: array<f32>;   // update: [B, W]
@group(0) @binding(9) var<storage, read_write> x_e: array<f32>;    // update: [rows, 3]
@group(0) @binding(10) var<storage, read> previous: array<f32>;    // update: D_prev [rows, 3]
@group(0) @binding(11) var<storage, read> gamma: array<f32>;       // update: [B, W]
@group(0) @binding(12) var<storage, read> agent: array<f32>;       // embed_chain: [B, A, D]
@group(0) @binding(13) var<storage, read> embed_weights: array<f32>; // embed_chain: the packed small weights
@group(0) @binding(14) var<storage, read> map_kv: array<f32>;      // attend: k, v [key rows, D] at k_off, v_off (the map's, or qkv's)
@group(0) @binding(15) var<storage, read> key_valid: array<f32>;   // attend: [key rows] (the map's flags, or valid)
@group(0) @binding(16) var<storage, read> agent_scene: array<u32>; // attend: [B·A], each agent row's map scene (key_mode 2: its scene)
@group(0) @binding(17) var<storage, read> pair_k: array<f32>;      // pairs: [D, 6]
@group(0) @binding(18) var<storage, read> pair_v: array<f32>;      // pairs: [D, 6]

// Float i of the weights.
fn weight(i: u32) -> f32 {
    return weights[i / 4u][i % 4u];
}

// The states as common/pair_features.wgsl reads them (x, bound for agent attention's pairs).
fn pair_state(i: u32) -> f32 {
    return x[i];
}

// What common/embed_token.wgsl reads of this kernel's (`embed_chain`).
fn embed_weight(i: u32) -> f32 {
    return embed_weights[i];
}

fn agent_embedding(i: u32) -> f32 {
    return agent[i];
}

// heun.wgsl's `heun_euler` and `multistep_correct` for the three values of `token`, with its
// D(x; σ) `denoised` as those kernels read it back (the same operations in the same order).
fn sampler_update(token: u32, denoised: vec3<f32>) {
    let row = (token / (params.slots * params.agents)) * params.slots + token % params.slots;
    let s = sigma[row];
    let s_next = sigma_next[row];
    let g = gamma[row];
    for (var c = 0u; c < 3u; c++) {
        let i = token * 3u + c;
        var value = x[i];
        if (s != s_next) {
            value = x[i] + (s_next - s) * (x[i] - denoised[c]) / s;
        }
        if (g != 0.0) {
            value = value + g * (denoised[c] - previous[i]);
        }
        x_e[i] = value;
    }
}

var<workgroup> tile: array<f32, CHAIN_ROWS * TILE_D>;  // [CHAIN_ROWS, TILE_D]: att, then the rows of h, standardised
var<workgroup> hidden_units: array<f32, CHAIN_ROWS * (CHAIN_UNITS + 1u)>; // [CHAIN_ROWS, CHAIN_UNITS + 1]: a chunk of MLP units, or F [CHAIN_ROWS, 3]
var<workgroup> tile_stats: array<vec2<f32>, CHAIN_ROWS>; // [CHAIN_ROWS]: (mean, 1/σ) of each row of the tile

// Floats from one row of `hidden_units` to the next.
fn hidden_stride() -> u32 {
    return CHAIN_UNITS + 1u;
}

// The attention of the tile's rows (as `attention.wgsl`'s and `agent_pairs.wgsl`'s: one (row,
// head) a task, an online softmax (common/online_softmax.wgsl, prepended) over the row's valid
// keys, zeros where none is valid) into the tile; rows past `live` zero. The queries are `att`'s
// rows, the keys and values `map_kv`'s, their flags `key_valid`'s. Token t of agent row n = t / W
// at slot t % W reads key rows n·keys + j (`key_mode` 0: over the map, its own polylines; over
// time, keys = W, its own slots), agent_scene[n]·keys + j (1: its scene's map), or (2: over
// agents, keys = A) the agents j of its batch scene at its slot, those of its own packed scene
// (`agent_scene`) only, with the pair features (`pairs`) in its anchor frame.
const MAX_HEAD_DIM: u32 = 64u;

fn attention_rows(lid: u32, first: u32, live: u32) {
    let d = params.d;
    let hd = params.head_dim;
    let scales = PairScales(params.heading_scale, params.direction, params.near, params.far);
    for (var task = lid; task < CHAIN_ROWS * params.heads; task += CHAIN_LANES) {
        let r = task / params.heads;
        let head = task % params.heads;
        var acc: array<f32, MAX_HEAD_DIM>;
        for (var c = 0u; c < hd; c++) {
            acc[c] = 0.0;
        }
        var acc_pair: array<f32, 6>;
        var q_pair: array<f32, 6>;
        for (var f = 0u; f < PAIR_FEATURES; f++) {
            acc_pair[f] = 0.0;
            q_pair[f] = 0.0;
        }
        var softmax = online_softmax_new();
        if (r < live) {
            let token = first + r;
            let agent_row = token / params.slots;
            let slot = token % params.slots;
            let scene = agent_row / params.agents;
            var key0 = agent_row * params.keys;
            if (params.key_mode == 1u) {
                key0 = agent_scene[agent_row] * params.keys;
            }
            let q_base = token * d + head * hd;
            var cos_a = 1.0;
            var sin_a = 0.0;
            if (params.pairs == 1u) {
                // The query agent's anchor heading (the scene frame's 0 without an anchor), and
                // K_hᵀ q_h.
                let anchor_row = agent_row * params.slots + params.anchor_slot;
                let heading = x[anchor_row * 3u + 2u] * key_valid[anchor_row] / params.heading_scale;
                cos_a = cos(heading);
                sin_a = sin(heading);
                for (var f = 0u; f < PAIR_FEATURES; f++) {
                    var sum = 0.0;
                    for (var c = 0u; c < hd; c++) {
                        sum += att[q_base + c] * pair_k[(head * hd + c) * PAIR_FEATURES + f];
                    }
                    q_pair[f] = sum;
                }
            }
            for (var j = 0u; j < params.keys; j++) {
                var key = key0 + j;
                if (params.key_mode == 2u) {
                    key = ((scene * params.agents + j) * params.slots) + slot;
                    if (agent_scene[scene * params.agents + j] != agent_scene[agent_row]) {
                        continue;
                    }
                }
                if (key_valid[key] == 0.0) {
                    continue;
                }
                let k_base = params.k_off + key * d + head * hd;
                let v_base = params.v_off + key * d + head * hd;
                var score = 0.0;
                for (var c = 0u; c < hd; c++) {
                    score += att[q_base + c] * map_kv[k_base + c];
                }
                var pair = array<f32, 6>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
                if (params.pairs == 1u) {
                    pair = pair_features_of(token, key, cos_a, sin_a, scales);
                    for (var f = 0u; f < PAIR_FEATURES; f++) {
                        score += q_pair[f] * pair[f];
                    }
                }
                score *= params.scale;
                let w = online_softmax_push(&softmax, score);
                for (var c = 0u; c < hd; c++) {
                    acc[c] = acc[c] * w.correction + w.weight * map_kv[v_base + c];
                }
                for (var f = 0u; f < PAIR_FEATURES; f++) {
                    acc_pair[f] = acc_pair[f] * w.correction + w.weight * pair[f];
                }
            }
        }
        let inv = online_softmax_inverse(softmax);
        for (var c = 0u; c < hd; c++) {
            var offset = 0.0;
            if (params.pairs == 1u) {
                for (var f = 0u; f < PAIR_FEATURES; f++) {
                    offset += pair_v[(head * hd + c) * PAIR_FEATURES + f] * acc_pair[f];
                }
            }
            tile[r * TILE_D + head * hd + c] = (acc[c] + offset) * inv;
        }
    }
}

// The tile's live rows from h (the rest zero), standardised in place: n(h) as the layer norm's
// prologue (its γ, β folded into the next layer), statistics one row per invocation, shifted
// by the row's first value as `linear.wgsl`'s `row_stats`. h in memory keeps the rows as they
// are for the residual adds. Call from uniform control flow.
fn load_standardised(lid: u32, first: u32, live: u32) {
    // The rows this workgroup's invocations just wrote to h, visible to all of them.
    storageBarrier();
    workgroupBarrier();
    let d = params.d;
    for (var i = lid; i < CHAIN_ROWS * d; i += CHAIN_LANES) {
        let r = i / d;
        let k = i % d;
        var value = 0.0;
        if (r < live) {
            value = h[(first + r) * d + k];
        }
        tile[r * TILE_D + k] = value;
    }
    workgroupBarrier();
    for (var row = lid; row < CHAIN_ROWS; row += CHAIN_LANES) {
        let base = row * TILE_D;
        let n = f32(d);
        let shift = tile[base];
        var sum = 0.0;
        var sq = 0.0;
        for (var k = 0u; k < d; k++) {
            let c = tile[base + k] - shift;
            sum += c;
            sq += c * c;
        }
        let mean = sum / n;
        let var_ = max(sq / n - mean * mean, 0.0);
        tile_stats[row] = vec2<f32>(shift + mean, inverseSqrt(var_ + params.eps));
    }
    workgroupBarrier();
    for (var i = lid; i < CHAIN_ROWS * d; i += CHAIN_LANES) {
        let r = i / d;
        let k = i % d;
        tile[r * TILE_D + k] = (tile[r * TILE_D + k] - tile_stats[r].x) * tile_stats[r].y;
    }
    workgroupBarrier();
}

// A register block of a layer's outputs: 4 rows × 4 consecutive columns (narrow) or 8 × 8
// (wide). Task t of a layer of `outputs` columns takes column group t % groups and row group
// t / groups, so that neighbouring invocations load neighbouring weights and share the tile's
// rows.
struct Block {
    row: u32,    // first of its rows in the tile
    column: u32, // first of its columns
}

// Rows and columns of a block (both the same).
fn block_size() -> u32 {
    return select(4u, 8u, WIDE_BLOCKS);
}

fn block_of(task: u32, outputs: u32) -> Block {
    let size = block_size();
    let groups = (outputs + size - 1u) / size;
    return Block((task / groups) * size, (task % groups) * size);
}

// Tasks of a layer of `outputs` columns over the tile's CHAIN_ROWS rows.
fn tasks_of(outputs: u32) -> u32 {
    let size = block_size();
    return (CHAIN_ROWS / size) * ((outputs + size - 1u) / size);
}

// 4 weights of row `k` of Wᵀ (rows `stride` floats apart) from column `column`; columns from
// `limit` on read the last one (their sums are never stored).
fn weights4(w: u32, k: u32, column: u32, stride: u32, limit: u32) -> vec4<f32> {
    let base = w + k * stride;
    let last = limit - 1u;
    return vec4<f32>(
        weight(base + min(column, last)),
        weight(base + min(column + 1u, last)),
        weight(base + min(column + 2u, last)),
        weight(base + min(column + 3u, last)),
    );
}

// Σ_k tile[r, k] · Wᵀ[k, c] + b[c] of the block's rows r and columns c below `limit` (Wᵀ at
// `w`, [D, ·] with rows `stride` floats apart; b at `b`): 16 sums in registers, 5 loads per 16
// products.
fn tile_block(w: u32, b: u32, blk: Block, stride: u32, limit: u32) -> array<vec4<f32>, 4> {
    var acc: array<vec4<f32>, 4>;
    let row0 = blk.row * TILE_D;
    for (var k = 0u; k < params.d; k++) {
        let wk = weights4(w, k, blk.column, stride, limit);
        acc[0] += tile[row0 + k] * wk;
        acc[1] += tile[row0 + TILE_D + k] * wk;
        acc[2] += tile[row0 + 2u * TILE_D + k] * wk;
        acc[3] += tile[row0 + 3u * TILE_D + k] * wk;
    }
    let bias = weights4(b, 0u, blk.column, stride, limit);
    for (var r = 0u; r < 4u; r++) {
        acc[r] += bias;
    }
    return acc;
}

// The wide blocks' sums: row r's columns in acc[2r] (the first 4) and acc[2r + 1].
// One k of a wide block: rows' inputs x, the weights' two quads wa, wb.
fn wide_step(acc: ptr<function, array<vec4<f32>, 16>>, x: array<f32, 8>, wa: vec4<f32>, wb: vec4<f32>) {
    (*acc)[0] += x[0] * wa; (*acc)[1] += x[0] * wb;
    (*acc)[2] += x[1] * wa; (*acc)[3] += x[1] * wb;
    (*acc)[4] += x[2] * wa; (*acc)[5] += x[2] * wb;
    (*acc)[6] += x[3] * wa; (*acc)[7] += x[3] * wb;
    (*acc)[8] += x[4] * wa; (*acc)[9] += x[4] * wb;
    (*acc)[10] += x[5] * wa; (*acc)[11] += x[5] * wb;
    (*acc)[12] += x[6] * wa; (*acc)[13] += x[6] * wb;
    (*acc)[14] += x[7] * wa; (*acc)[15] += x[7] * wb;
}

// The quads (in vec4s) of row k of Wᵀ at the block's columns; a quad past `limit` (a multiple of
// 4) reads the last one (its sums are never stored).
fn wide_quads(w: u32, k: u32, column: u32, stride: u32, limit: u32) -> array<vec4<f32>, 2> {
    let base = (w + k * stride) / 4u;
    let last = limit / 4u - 1u;
    let q = column / 4u;
    return array<vec4<f32>, 2>(weights[base + min(q, last)], weights[base + min(q + 1u, last)]);
}

// b at the block's columns (and 0 with NO_BIAS), added to every row's sums.
fn wide_bias(acc: ptr<function, array<vec4<f32>, 16>>, b: u32, column: u32, limit: u32) {
    if (b == NO_BIAS) {
        return;
    }
    let bias = wide_quads(b, 0u, column, 0u, limit);
    for (var r = 0u; r < 8u; r++) {
        (*acc)[2u * r] += bias[0];
        (*acc)[2u * r + 1u] += bias[1];
    }
}

// The wide block of `tile_block`: Σ_k tile[r, k] · Wᵀ[k, c] + b[c], 64 sums.
fn wide_tile_block(w: u32, b: u32, blk: Block, stride: u32, limit: u32) -> array<vec4<f32>, 16> {
    var acc: array<vec4<f32>, 16>;
    let row0 = blk.row * TILE_D;
    for (var k = 0u; k < params.d; k++) {
        let wq = wide_quads(w, k, blk.column, stride, limit);
        let x = array<f32, 8>(
            tile[row0 + k], tile[row0 + TILE_D + k],
            tile[row0 + 2u * TILE_D + k], tile[row0 + 3u * TILE_D + k],
            tile[row0 + 4u * TILE_D + k], tile[row0 + 5u * TILE_D + k],
            tile[row0 + 6u * TILE_D + k], tile[row0 + 7u * TILE_D + k],
        );
        wide_step(&acc, x, wq[0], wq[1]);
    }
    wide_bias(&acc, b, blk.column, limit);
    return acc;
}

// The same over a chunk of `units` hidden units (rows of W₂ᵀ from `w`, D apart), b added when
// not NO_BIAS: the MLP's second layer.
fn wide_hidden_block(w: u32, b: u32, blk: Block, units: u32) -> array<vec4<f32>, 16> {
    var acc: array<vec4<f32>, 16>;
    let stride = hidden_stride();
    let row0 = blk.row * stride;
    for (var u = 0u; u < units; u++) {
        let wq = wide_quads(w, u, blk.column, params.d, params.d);
        let x = array<f32, 8>(
            hidden_units[row0 + u], hidden_units[row0 + stride + u],
            hidden_units[row0 + 2u * stride + u], hidden_units[row0 + 3u * stride + u],
            hidden_units[row0 + 4u * stride + u], hidden_units[row0 + 5u * stride + u],
            hidden_units[row0 + 6u * stride + u], hidden_units[row0 + 7u * stride + u],
        );
        wide_step(&acc, x, wq[0], wq[1]);
    }
    wide_bias(&acc, b, blk.column, params.d);
    return acc;
}

// Adds a wide block's sums into h.
fn wide_add_into_h(blk: Block, sums: array<vec4<f32>, 16>, first: u32, live: u32) {
    for (var r = 0u; r < 8u; r++) {
        for (var j = 0u; j < 8u; j++) {
            add_sum(blk.row + r, blk.column + j, sums[2u * r + j / 4u][j % 4u], first, live);
        }
    }
}

// Adds `value` into h at the tile's row `row` (token first + row) and column `column`, when
// the row is below `live` and the column below D.
fn add_sum(row: u32, column: u32, value: f32, first: u32, live: u32) {
    if (row < live && column < params.d) {
        h[(first + row) * params.d + column] += value;
    }
}

// Adds a block's sums into h.
fn add_into_h(blk: Block, sums: array<vec4<f32>, 4>, first: u32, live: u32) {
    for (var r = 0u; r < 4u; r++) {
        for (var j = 0u; j < 4u; j++) {
            add_sum(blk.row + r, blk.column + j, sums[r][j], first, live);
        }
    }
}

// The tile's rows from `first` that hold tokens. Rows past the end stay zero in the tile and
// are never written; every invocation still takes every barrier.
fn live_rows(first: u32) -> u32 {
    if (first >= params.rows) {
        return 0u;
    }
    return min(CHAIN_ROWS, params.rows - first);
}

@compute @workgroup_size(CHAIN_LANES)
fn residual_chain(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let d = params.d;
    let first = (wid.x + wid.y * groups.x) * CHAIN_ROWS;
    let live = live_rows(first);

    // The output projection: the attention's rows into the tile (read, or with `attend` made
    // here), then each invocation adds its blocks of every row into h (no other invocation
    // touches them).
    if (params.attend == 1u) {
        attention_rows(lid, first, live);
    } else {
        for (var i = lid; i < CHAIN_ROWS * d; i += CHAIN_LANES) {
            let r = i / d;
            let k = i % d;
            var value = 0.0;
            if (r < live) {
                value = att[(first + r) * d + k];
            }
            tile[r * TILE_D + k] = value;
        }
    }
    workgroupBarrier();
    for (var t = lid; t < tasks_of(d); t += CHAIN_LANES) {
        let blk = block_of(t, d);
        if (WIDE_BLOCKS) {
            wide_add_into_h(blk, wide_tile_block(params.o_w, params.o_b, blk, d, d), first, live);
        } else {
            add_into_h(blk, tile_block(params.o_w, params.o_b, blk, d, d), first, live);
        }
    }

    // The MLP, CHAIN_UNITS hidden units at a time, each chunk's products added into h.
    if (params.m > 0u) {
        load_standardised(lid, first, live);
        for (var c0 = 0u; c0 < params.m; c0 += CHAIN_UNITS) {
            let chunk = min(CHAIN_UNITS, params.m - c0);
            // The chunk's units: a layer of `chunk` outputs whose weights start at column c0.
            for (var t = lid; t < tasks_of(chunk); t += CHAIN_LANES) {
                let blk = block_of(t, chunk);
                if (WIDE_BLOCKS) {
                    wide_hidden_units(blk, c0, chunk);
                } else {
                    hidden_units_block(blk, c0, chunk);
                }
            }
            workgroupBarrier();
            for (var t = lid; t < tasks_of(d); t += CHAIN_LANES) {
                let blk = block_of(t, d);
                let b2 = select(NO_BIAS, params.b2, c0 == 0u);
                if (WIDE_BLOCKS) {
                    wide_add_into_h(blk, wide_hidden_block(params.w2 + c0 * d, b2, blk, chunk), first, live);
                } else {
                    add_into_h(blk, hidden_block(blk, c0, chunk, b2), first, live);
                }
            }
            workgroupBarrier();
        }
    }

    if (params.next_out == 0u) {
        return;
    }
    load_standardised(lid, first, live);
    if (params.precondition == 1u) {
        head(lid, first, live);
    } else {
        next_parts(lid, first, live);
    }
}

// A narrow block of the MLP's hidden units c0 + … of a chunk of `chunk`, with ReLU, into
// `hidden_units` (units past the chunk not stored).
fn hidden_units_block(blk: Block, c0: u32, chunk: u32) {
    let units = tile_block(params.w1 + c0, params.b1 + c0, blk, params.m, chunk);
    let stride = hidden_stride();
    for (var r = 0u; r < 4u; r++) {
        for (var j = 0u; j < 4u; j++) {
            if (blk.column + j < chunk) {
                hidden_units[(blk.row + r) * stride + blk.column + j] = max(units[r][j], 0.0);
            }
        }
    }
}

// The same for a wide block.
fn wide_hidden_units(blk: Block, c0: u32, chunk: u32) {
    let units = wide_tile_block(params.w1 + c0, params.b1 + c0, blk, params.m, chunk);
    let stride = hidden_stride();
    for (var r = 0u; r < 8u; r++) {
        for (var j = 0u; j < 8u; j++) {
            if (blk.column + j < chunk) {
                hidden_units[(blk.row + r) * stride + blk.column + j] =
                    max(units[2u * r + j / 4u][j % 4u], 0.0);
            }
        }
    }
}

// A narrow block of the MLP's second layer over the chunk of hidden units c0 + … (`chunk` of
// them): Σ_u hidden[r, u] · W₂ᵀ[c0 + u, c], + b₂ unless `b2` is NO_BIAS.
fn hidden_block(blk: Block, c0: u32, chunk: u32, b2: u32) -> array<vec4<f32>, 4> {
    let d = params.d;
    let stride = hidden_stride();
    var acc: array<vec4<f32>, 4>;
    let row0 = blk.row * stride;
    for (var u = 0u; u < chunk; u++) {
        let wu = weights4(params.w2, c0 + u, blk.column, d, d);
        acc[0] += hidden_units[row0 + u] * wu;
        acc[1] += hidden_units[row0 + stride + u] * wu;
        acc[2] += hidden_units[row0 + 2u * stride + u] * wu;
        acc[3] += hidden_units[row0 + 3u * stride + u] * wu;
    }
    if (b2 != NO_BIAS) {
        let bias = weights4(b2, 0u, blk.column, d, d);
        for (var r = 0u; r < 4u; r++) {
            acc[r] += bias;
        }
    }
    return acc;
}

// The first layer after the token embedding, as a chain: h ← embed(x, σ) (common/
// embed_token.wgsl), then y ← n(h) · W_nextᵀ + b_next into its parts (block 0's q, k, v): the
// embedding and the first layer in one dispatch. The chain's output projection and MLP are not
// run (`m` is 0, `o_w` unread); `slots`, `agents`, `anchor_slot`, `sigma_data`, `heading_scale`,
// `residual_scale` and `relative_scale` describe the embedding, `embed_weights` holds its weights.
@compute @workgroup_size(CHAIN_LANES)
fn embed_chain(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let d = params.d;
    let first = (wid.x + wid.y * groups.x) * CHAIN_ROWS;
    let live = live_rows(first);
    let shape = EmbedShape(
        params.agents,
        params.slots,
        d,
        params.sigma_data,
        params.anchor_slot,
        params.heading_scale,
        params.relative_scale,
        params.residual_scale,
    );
    for (var i = lid; i < live * d; i += CHAIN_LANES) {
        let token = first + i / d;
        h[token * d + i % d] = embed_value(shape, token, i % d);
    }
    load_standardised(lid, first, live);
    next_parts(lid, first, live);
}

// The head from the standardised tile (`load_standardised` ran): D(x; σ), and the sampler's step
// with `update`. Call from uniform control flow.
fn head(lid: u32, first: u32, live: u32) {
    let d = params.d;
    // The head's F of every row into workgroup memory, then D(x; σ) a token per invocation.
    for (var i = lid; i < CHAIN_ROWS * 3u; i += CHAIN_LANES) {
        let r = i / 3u;
        let o = i % 3u;
        var sum = weight(params.next_b + o);
        for (var k = 0u; k < d; k++) {
            sum += tile[r * TILE_D + k] * weight(params.next_w + k * 3u + o);
        }
        hidden_units[i] = sum;
    }
    workgroupBarrier();
    for (var r = lid; r < live; r += CHAIN_LANES) {
        let token = first + r;
        let f = vec3<f32>(hidden_units[r * 3u], hidden_units[r * 3u + 1u], hidden_units[r * 3u + 2u]);
        let t = gather_token(token, f);
        let out = precondition_token(t, params.sigma_data, params.heading_scale, params.residual_scale);
        y[token * 3u] = out.x;
        y[token * 3u + 1u] = out.y;
        y[token * 3u + 2u] = out.z;
        if (params.update == 1u) {
            sampler_update(token, out);
        }
    }
}

// The next layer from the standardised tile (`load_standardised` ran), into y's parts (as
// `linear.wgsl`'s `store4`).
fn next_parts(lid: u32, first: u32, live: u32) {
    let outputs = params.next_out;
    for (var t = lid; t < tasks_of(outputs); t += CHAIN_LANES) {
        let blk = block_of(t, outputs);
        if (WIDE_BLOCKS) {
            let values = wide_tile_block(params.next_w, params.next_b, blk, outputs, outputs);
            for (var j = 0u; j < 8u; j++) {
                for (var r = 0u; r < 8u; r++) {
                    store_part(blk, j, r, values[2u * r + j / 4u][j % 4u], first, live);
                }
            }
        } else {
            let values = tile_block(params.next_w, params.next_b, blk, outputs, outputs);
            for (var j = 0u; j < 4u; j++) {
                for (var r = 0u; r < 4u; r++) {
                    store_part(blk, j, r, values[r][j], first, live);
                }
            }
        }
    }
}

// Output `blk.column + j` of row `blk.row + r` into its part of y, when both exist.
fn store_part(blk: Block, j: u32, r: u32, value: f32, first: u32, live: u32) {
    let o = blk.column + j;
    let row = blk.row + r;
    if (o < params.next_out && row < live) {
        let base = (o / params.part) * params.part_stride + o % params.part;
        y[base + (first + row) * params.part] = value;
    }
}
