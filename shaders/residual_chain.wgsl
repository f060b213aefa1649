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
// neighbouring weights. A workgroup of 64 holds ROWS rows of a layer's input in workgroup
// memory; each invocation computes blocks of 4 rows × 4 columns of the layer's outputs (16 sums
// in registers, 5 loads per 16 products) and adds them into h itself (no other invocation
// touches those elements). The next layer's input is read back from h, standardised
// once per row. The MLP runs its hidden layer UNITS units at a time (tiny-cuda-nn's pattern).

struct Params {
    rows: u32,        // tokens
    d: u32,           // hidden width D (≤ MAX_D)
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

const ROWS: u32 = 8u;
const MAX_D: u32 = 256u;
const LANES: u32 = 64u;
const UNITS: u32 = 128u; // MLP hidden units a chunk
const NO_FRAME: u32 = 0xffffffffu;
const NO_BIAS: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> weights: array<f32>;
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

var<workgroup> tile: array<f32, 2048>;          // [ROWS, MAX_D]: att, then the rows of h, standardised
var<workgroup> hidden_units: array<f32, 1024>;  // [ROWS, UNITS]: a chunk of MLP units, or F [ROWS, 3]
var<workgroup> tile_stats: array<vec2<f32>, 8>; // [ROWS]: (mean, 1/σ) of each row of the tile

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
    for (var task = lid; task < ROWS * params.heads; task += LANES) {
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
            tile[r * MAX_D + head * hd + c] = (acc[c] + offset) * inv;
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
    for (var i = lid; i < ROWS * d; i += LANES) {
        let r = i / d;
        let k = i % d;
        var value = 0.0;
        if (r < live) {
            value = h[(first + r) * d + k];
        }
        tile[r * MAX_D + k] = value;
    }
    workgroupBarrier();
    if (lid < ROWS) {
        let base = lid * MAX_D;
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
        tile_stats[lid] = vec2<f32>(shift + mean, inverseSqrt(var_ + params.eps));
    }
    workgroupBarrier();
    for (var i = lid; i < ROWS * d; i += LANES) {
        let r = i / d;
        let k = i % d;
        tile[r * MAX_D + k] = (tile[r * MAX_D + k] - tile_stats[r].x) * tile_stats[r].y;
    }
    workgroupBarrier();
}

// A register block of a layer's outputs: 4 rows × 4 consecutive columns. Task t of a layer of
// `outputs` columns takes column group t % groups and row group t / groups, so that
// neighbouring invocations load neighbouring weights and share the tile's rows.
struct Block {
    row: u32,    // first of its 4 rows in the tile
    column: u32, // first of its 4 columns
}

fn block_of(task: u32, outputs: u32) -> Block {
    let groups = (outputs + 3u) / 4u;
    return Block((task / groups) * 4u, (task % groups) * 4u);
}

// Tasks of a layer of `outputs` columns over the tile's ROWS rows.
fn tasks_of(outputs: u32) -> u32 {
    return (ROWS / 4u) * ((outputs + 3u) / 4u);
}

// 4 weights of row `k` of Wᵀ (rows `stride` floats apart) from column `column`; columns from
// `limit` on read the last one (their sums are never stored).
fn weights4(w: u32, k: u32, column: u32, stride: u32, limit: u32) -> vec4<f32> {
    let base = w + k * stride;
    let last = limit - 1u;
    return vec4<f32>(
        weights[base + min(column, last)],
        weights[base + min(column + 1u, last)],
        weights[base + min(column + 2u, last)],
        weights[base + min(column + 3u, last)],
    );
}

// Σ_k tile[r, k] · Wᵀ[k, c] + b[c] of the block's rows r and columns c below `limit` (Wᵀ at
// `w`, [D, ·] with rows `stride` floats apart; b at `b`): 16 sums in registers, 5 loads per 16
// products.
fn tile_block(w: u32, b: u32, blk: Block, stride: u32, limit: u32) -> array<vec4<f32>, 4> {
    var acc: array<vec4<f32>, 4>;
    let row0 = blk.row * MAX_D;
    for (var k = 0u; k < params.d; k++) {
        let wk = weights4(w, k, blk.column, stride, limit);
        acc[0] += tile[row0 + k] * wk;
        acc[1] += tile[row0 + MAX_D + k] * wk;
        acc[2] += tile[row0 + 2u * MAX_D + k] * wk;
        acc[3] += tile[row0 + 3u * MAX_D + k] * wk;
    }
    let bias = weights4(b, 0u, blk.column, stride, limit);
    for (var r = 0u; r < 4u; r++) {
        acc[r] += bias;
    }
    return acc;
}

// Adds a block's sums into h (rows `first + blk.row + r` below `live`, columns below D).
fn add_into_h(blk: Block, sums: array<vec4<f32>, 4>, first: u32, live: u32) {
    let d = params.d;
    for (var r = 0u; r < 4u; r++) {
        let row = blk.row + r;
        if (row < live) {
            for (var j = 0u; j < 4u; j++) {
                let column = blk.column + j;
                if (column < d) {
                    h[(first + row) * d + column] += sums[r][j];
                }
            }
        }
    }
}

// The tile's rows from `first` that hold tokens. Rows past the end stay zero in the tile and
// are never written; every invocation still takes every barrier.
fn live_rows(first: u32) -> u32 {
    if (first >= params.rows) {
        return 0u;
    }
    return min(ROWS, params.rows - first);
}

@compute @workgroup_size(64)
fn residual_chain(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let d = params.d;
    let first = (wid.x + wid.y * groups.x) * ROWS;
    let live = live_rows(first);

    // The output projection: the attention's rows into the tile (read, or with `attend` made
    // here), then each invocation adds its blocks of every row into h (no other invocation
    // touches them).
    if (params.attend == 1u) {
        attention_rows(lid, first, live);
    } else {
        for (var i = lid; i < ROWS * d; i += LANES) {
            let r = i / d;
            let k = i % d;
            var value = 0.0;
            if (r < live) {
                value = att[(first + r) * d + k];
            }
            tile[r * MAX_D + k] = value;
        }
    }
    workgroupBarrier();
    for (var t = lid; t < tasks_of(d); t += LANES) {
        let blk = block_of(t, d);
        add_into_h(blk, tile_block(params.o_w, params.o_b, blk, d, d), first, live);
    }

    // The MLP, UNITS hidden units at a time, each chunk's products added into h.
    if (params.m > 0u) {
        load_standardised(lid, first, live);
        for (var c0 = 0u; c0 < params.m; c0 += UNITS) {
            let chunk = min(UNITS, params.m - c0);
            // The chunk's units: a layer of `chunk` outputs whose weights start at column c0.
            for (var t = lid; t < tasks_of(chunk); t += LANES) {
                let blk = block_of(t, chunk);
                let units = tile_block(params.w1 + c0, params.b1 + c0, blk, params.m, chunk);
                for (var r = 0u; r < 4u; r++) {
                    for (var j = 0u; j < 4u; j++) {
                        if (blk.column + j < chunk) {
                            hidden_units[(blk.row + r) * UNITS + blk.column + j] = max(units[r][j], 0.0);
                        }
                    }
                }
            }
            workgroupBarrier();
            for (var t = lid; t < tasks_of(d); t += LANES) {
                let blk = block_of(t, d);
                var acc: array<vec4<f32>, 4>;
                let row0 = blk.row * UNITS;
                for (var u = 0u; u < chunk; u++) {
                    let wu = weights4(params.w2, c0 + u, blk.column, d, d);
                    acc[0] += hidden_units[row0 + u] * wu;
                    acc[1] += hidden_units[row0 + UNITS + u] * wu;
                    acc[2] += hidden_units[row0 + 2u * UNITS + u] * wu;
                    acc[3] += hidden_units[row0 + 3u * UNITS + u] * wu;
                }
                if (c0 == 0u) {
                    let bias = weights4(params.b2, 0u, blk.column, d, d);
                    for (var r = 0u; r < 4u; r++) {
                        acc[r] += bias;
                    }
                }
                add_into_h(blk, acc, first, live);
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

// The first layer after the token embedding, as a chain: h ← embed(x, σ) (common/
// embed_token.wgsl), then y ← n(h) · W_nextᵀ + b_next into its parts (block 0's q, k, v): the
// embedding and the first layer in one dispatch. The chain's output projection and MLP are not
// run (`m` is 0, `o_w` unread); `slots`, `agents`, `anchor_slot`, `sigma_data`, `heading_scale`,
// `residual_scale` and `relative_scale` describe the embedding, `embed_weights` holds its weights.
@compute @workgroup_size(64)
fn embed_chain(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let d = params.d;
    let first = (wid.x + wid.y * groups.x) * ROWS;
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
    for (var i = lid; i < live * d; i += LANES) {
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
    if (lid < ROWS * 3u) {
        let r = lid / 3u;
        let o = lid % 3u;
        var sum = weights[params.next_b + o];
        for (var k = 0u; k < d; k++) {
            sum += tile[r * MAX_D + k] * weights[params.next_w + k * 3u + o];
        }
        hidden_units[lid] = sum;
    }
    workgroupBarrier();
    if (lid < live) {
        let token = first + lid;
        let f = vec3<f32>(hidden_units[lid * 3u], hidden_units[lid * 3u + 1u], hidden_units[lid * 3u + 2u]);
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
    for (var t = lid; t < tasks_of(params.next_out); t += LANES) {
        let blk = block_of(t, params.next_out);
        let values = tile_block(params.next_w, params.next_b, blk, params.next_out, params.next_out);
        for (var j = 0u; j < 4u; j++) {
            let o = blk.column + j;
            if (o < params.next_out) {
                let base = (o / params.part) * params.part_stride + o % params.part;
                for (var r = 0u; r < 4u; r++) {
                    let row = blk.row + r;
                    if (row < live) {
                        y[base + (first + row) * params.part] = values[r][j];
                    }
                }
            }
        }
    }
}
