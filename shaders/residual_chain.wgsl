// The residual chain: what a transformer block does between two attentions, as one kernel
// over a tile of rows (one dispatch instead of up to four; the MLP's hidden layer and the head's
// F never leave the chip):
//   h ← h + att · W_oᵀ + b_o                                  (the attention's output projection)
//   h ← h + W_2 · relu(W_1 · n(h) + b_1) + b_2                (the MLP, when m > 0)
//   y ← n(h) · W_nextᵀ + b_next                               (the next layer, when next_out > 0)
// n is the layer norm with its γ, β folded into the layer after it (as `linear.wgsl`'s `norm`),
// y goes to parts as `linear.wgsl`'s (the next attention's q/k/v) or, with `precondition`, is
// the head's F and the kernel writes D(x; σ) instead (common/precondition.wgsl, prepended).
// Every weight lives in one bound range of the weights buffer, at offsets in floats, transposed
// ([in, out]: the engine transposes them on upload) so that neighbouring invocations load
// neighbouring weights. A workgroup of 64 holds ROWS rows of a layer's input in workgroup
// memory; invocation i owns output columns i, i + 64, ... of every row, so each weight it loads
// serves ROWS products, its sums stay in registers, and it adds them into h itself (no other
// invocation touches those elements). The next layer's input is read back from h, standardised
// once per row. The MLP runs its hidden layer 64 units at a time (tiny-cuda-nn's pattern).

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
    _pad0: u32,
    _pad1: u32,
}

const ROWS: u32 = 8u;
const MAX_D: u32 = 256u;
const LANES: u32 = 64u;
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

var<workgroup> tile: array<f32, 2048>;          // [ROWS, MAX_D]: att, then the rows of h, standardised
var<workgroup> hidden_units: array<f32, 512>;   // [ROWS, LANES]: 64 MLP units, or F [ROWS, 3]
var<workgroup> tile_stats: array<vec2<f32>, 8>; // [ROWS]: (mean, 1/σ) of each row of the tile

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

// Σ_k tile[r, k] · W[o, k] (+ b[o] unless `b` is NO_BIAS) of every row r, for one output o of
// `outputs` (Wᵀ at `w`, [D, outputs]). The 8 sums stay in registers.
fn tile_products(w: u32, b: u32, o: u32, outputs: u32) -> array<f32, 8> {
    var acc: array<f32, 8>;
    for (var k = 0u; k < params.d; k++) {
        let wk = weights[w + k * outputs + o];
        for (var r = 0u; r < ROWS; r++) {
            acc[r] += tile[r * MAX_D + k] * wk;
        }
    }
    if (b != NO_BIAS) {
        let bias = weights[b + o];
        for (var r = 0u; r < ROWS; r++) {
            acc[r] += bias;
        }
    }
    return acc;
}

@compute @workgroup_size(64)
fn residual_chain(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let d = params.d;
    let first = (wid.x + wid.y * groups.x) * ROWS;
    // Rows past the end stay zero in the tile and are never written; every invocation still
    // takes every barrier.
    var live = ROWS;
    if (first >= params.rows) {
        live = 0u;
    } else {
        live = min(ROWS, params.rows - first);
    }

    // The output projection: the attention's rows into the tile, then each invocation adds its
    // columns of every row into h (no other invocation touches them).
    for (var i = lid; i < ROWS * d; i += LANES) {
        let r = i / d;
        let k = i % d;
        var value = 0.0;
        if (r < live) {
            value = att[(first + r) * d + k];
        }
        tile[r * MAX_D + k] = value;
    }
    workgroupBarrier();
    for (var o = lid; o < d; o += LANES) {
        let sums = tile_products(params.o_w, params.o_b, o, d);
        for (var r = 0u; r < live; r++) {
            h[(first + r) * d + o] += sums[r];
        }
    }

    // The MLP, 64 hidden units at a time, each chunk's products added into h.
    if (params.m > 0u) {
        load_standardised(lid, first, live);
        for (var c0 = 0u; c0 < params.m; c0 += LANES) {
            let c = c0 + lid;
            if (c < params.m) {
                let units = tile_products(params.w1, params.b1, c, params.m);
                for (var r = 0u; r < ROWS; r++) {
                    hidden_units[r * LANES + lid] = max(units[r], 0.0);
                }
            } else {
                for (var r = 0u; r < ROWS; r++) {
                    hidden_units[r * LANES + lid] = 0.0;
                }
            }
            workgroupBarrier();
            let chunk = min(LANES, params.m - c0);
            for (var o = lid; o < d; o += LANES) {
                var acc: array<f32, 8>;
                let w_chunk = params.w2 + c0 * d + o;
                for (var u = 0u; u < chunk; u++) {
                    let wu = weights[w_chunk + u * d];
                    for (var r = 0u; r < ROWS; r++) {
                        acc[r] += hidden_units[r * LANES + u] * wu;
                    }
                }
                var bias = 0.0;
                if (c0 == 0u) {
                    bias = weights[params.b2 + o];
                }
                for (var r = 0u; r < live; r++) {
                    h[(first + r) * d + o] += acc[r] + bias;
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
            let w = token % params.slots;
            let scene = token / (params.slots * params.agents);
            var t: PreconditionToken;
            t.x = vec3<f32>(x[token * 3u], x[token * 3u + 1u], x[token * 3u + 2u]);
            t.f = vec3<f32>(hidden_units[lid * 3u], hidden_units[lid * 3u + 1u], hidden_units[lid * 3u + 2u]);
            t.sigma = sigma[scene * params.slots + w];
            t.valid = valid[token];
            t.frame = params.anchor_slot != NO_FRAME;
            t.anchor = vec3<f32>(0.0);
            t.anchor_valid = 0.0;
            t.previous = vec3<f32>(0.0);
            t.previous_valid = 0.0;
            t.slots_from_anchor = 0.0;
            if (t.frame) {
                let anchor = (token / params.slots) * params.slots + params.anchor_slot;
                let previous = anchor - 1u;
                t.anchor = vec3<f32>(x[anchor * 3u], x[anchor * 3u + 1u], x[anchor * 3u + 2u]);
                t.anchor_valid = valid[anchor];
                t.previous = vec3<f32>(x[previous * 3u], x[previous * 3u + 1u], x[previous * 3u + 2u]);
                t.previous_valid = valid[previous];
                t.slots_from_anchor = f32(w) - f32(params.anchor_slot);
            }
            let out = precondition_token(t, params.sigma_data, params.heading_scale, params.residual_scale);
            y[token * 3u] = out.x;
            y[token * 3u + 1u] = out.y;
            y[token * 3u + 2u] = out.z;
        }
        return;
    }
    // The next layer, into its parts (stepped per output as `linear.wgsl`'s `store4`).
    for (var o = lid; o < params.next_out; o += LANES) {
        let values = tile_products(params.next_w, params.next_b, o, params.next_out);
        let base = (o / params.part) * params.part_stride + o % params.part;
        for (var r = 0u; r < live; r++) {
            y[base + (first + r) * params.part] = values[r];
        }
    }
}
