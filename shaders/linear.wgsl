// Linear layer over the last dimension, with its neighbours fused in so that they cost no
// dispatch and no round trip of the activations through memory:
//   y[r, o] (+)= act(Σ_k n(x)[r, k] · w[o, k] + b[o])
// prologue (`norm`): n(x) is x's row standardised, (x − mean) / √(var + eps) with the biased
// variance (as candle): a layer norm whose γ, β the engine folded into w and b on upload;
// otherwise n(x) = x. Epilogue: `relu`, then `residual` adds into y (the block's residual
// stream) instead of overwriting it. Output layout: column o goes to part o / part (the
// fused q/k/v or map k/v projections write their parts as separate [rows, part] tensors,
// `part_stride` floats apart, so that attention binds each as before).
// Weights as stored in the checkpoint: w [out, in] row-major, b [out].
// One invocation computes 4 consecutive outputs of one row, so that each x element it loads
// serves 4 products (lavapipe favours no workgroup memory and several outputs per thread).

struct Params {
    rows: u32,
    in_dim: u32,
    out_dim: u32,
    relu: u32,        // 1: ReLU after the bias
    residual: u32,    // 1: y += result (read y first)
    norm: u32,        // 1: standardise x's rows first
    eps: f32,         // the layer norm's
    part: u32,        // outputs per part (out_dim: one part)
    part_stride: u32, // floats from one part of y to the next (≥ rows · part)
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;      // [rows, in]
@group(0) @binding(2) var<storage, read> w: array<f32>;      // [out, in]
@group(0) @binding(3) var<storage, read> b: array<f32>;      // [out]
@group(0) @binding(4) var<storage, read_write> y: array<f32>; // [out / part, part_stride]

// Mean and 1/√(var + eps) of x's row `row`, in one pass over the row shifted by its first
// value (the shifted-data variance: no cancellation unless the mean is far from that value
// relative to the spread; every invocation of the row pays this pass).
fn row_stats(row: u32) -> vec2<f32> {
    let base = row * params.in_dim;
    let n = f32(params.in_dim);
    let shift = x[base];
    var sum = 0.0;
    var sq = 0.0;
    for (var k = 0u; k < params.in_dim; k++) {
        let c = x[base + k] - shift;
        sum += c;
        sq += c * c;
    }
    let mean = sum / n;
    let var_ = max(sq / n - mean * mean, 0.0);
    return vec2<f32>(shift + mean, inverseSqrt(var_ + params.eps));
}

// The epilogue of 4 consecutive outputs o0.. of `row` (those below out_dim): ReLU, then the
// residual add, each into its part. Parts are stepped, not divided per output: integer
// division is slow on lavapipe.
fn store4(row: u32, o0: u32, value: vec4<f32>) {
    var part = o0 / params.part;
    var column = o0 % params.part;
    for (var j = 0u; j < 4u; j++) {
        if (o0 + j < params.out_dim) {
            var v = value[j];
            if (params.relu == 1u) {
                v = max(v, 0.0);
            }
            let i = part * params.part_stride + row * params.part + column;
            if (params.residual == 1u) {
                v += y[i];
            }
            y[i] = v;
        }
        column += 1u;
        if (column == params.part) {
            column = 0u;
            part += 1u;
        }
    }
}

@compute @workgroup_size(64)
fn linear(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let quads = (params.out_dim + 3u) / 4u;
    let index = gid.x + gid.y * groups.x * 64u;
    if (index >= params.rows * quads) {
        return;
    }
    let row = index / quads;
    let col0 = (index % quads) * 4u;
    // The row's statistics, recomputed by each of its invocations: cheaper on lavapipe than
    // sharing them through workgroup memory and a barrier, and no extra dispatch.
    var stats = vec2<f32>(0.0, 1.0); // (mean, inv): the identity without a norm
    if (params.norm == 1u) {
        stats = row_stats(row);
    }
    var acc = vec4<f32>(0.0);
    let x_base = row * params.in_dim;
    // Columns past the end read row 0 of w (valid memory); their results are not written.
    let c1 = select(0u, col0 + 1u, col0 + 1u < params.out_dim);
    let c2 = select(0u, col0 + 2u, col0 + 2u < params.out_dim);
    let c3 = select(0u, col0 + 3u, col0 + 3u < params.out_dim);
    let w0 = col0 * params.in_dim;
    let w1 = c1 * params.in_dim;
    let w2 = c2 * params.in_dim;
    let w3 = c3 * params.in_dim;
    // Standardised as Σ (x − mean) · w · inv: the inner loop stays a subtraction and a
    // multiply-add, and inv is applied once per output.
    for (var k = 0u; k < params.in_dim; k++) {
        let xv = x[x_base + k] - stats.x;
        acc += xv * vec4<f32>(w[w0 + k], w[w1 + k], w[w2 + k], w[w3 + k]);
    }
    acc *= stats.y;
    acc += vec4<f32>(b[col0], b[c1], b[c2], b[c3]);
    store4(row, col0, acc);
}

// The same layer for hardware GPUs: a workgroup computes a tile of 64 rows × 32 outputs, staging
// K-chunks of x and w in workgroup memory so that each global load serves 32 (x) or 64 (w)
// products and loads coalesce; each invocation accumulates 8 rows × 4 outputs in registers.
// With `norm`, the workgroup first computes its 64 rows' statistics, one row per invocation.
// (The row-wise entry above stays the choice on lavapipe, where workgroup memory and barriers
// cost more than they save.)

const TILE_ROWS: u32 = 64u;
const TILE_OUTS: u32 = 32u;
const TILE_K: u32 = 16u;

var<workgroup> x_tile: array<f32, 1024>;       // [TILE_ROWS, TILE_K]
var<workgroup> w_tile: array<vec4<f32>, 128>;  // [TILE_K, TILE_OUTS / 4]: w transposed
var<workgroup> tile_stats: array<vec2<f32>, 64>; // [TILE_ROWS]: (mean, 1/σ) of each row

@compute @workgroup_size(64)
fn linear_tiled(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let out_tiles = (params.out_dim + TILE_OUTS - 1u) / TILE_OUTS;
    let row_tiles = (params.rows + TILE_ROWS - 1u) / TILE_ROWS;
    let tile = wid.x + wid.y * groups.x;
    // Uniform across the workgroup: the grid may hold more groups than tiles.
    if (tile >= out_tiles * row_tiles) {
        return;
    }
    let row0 = (tile / out_tiles) * TILE_ROWS;
    let out0 = (tile % out_tiles) * TILE_OUTS;
    // This invocation's outputs: rows row0 + 8·rg + i (i < 8), outputs out0 + 4·og + j (j < 4).
    let rg = lid / 8u;
    let og = lid % 8u;

    if (params.norm == 1u) {
        var stats = vec2<f32>(0.0, 1.0);
        if (row0 + lid < params.rows) {
            stats = row_stats(row0 + lid);
        }
        tile_stats[lid] = stats;
        workgroupBarrier();
    }

    var acc: array<vec4<f32>, 8>;
    for (var i = 0u; i < 8u; i++) {
        acc[i] = vec4<f32>(0.0);
    }
    for (var k0 = 0u; k0 < params.in_dim; k0 += TILE_K) {
        // Stage x[row0.., k0..]: 1024 values, 16 per invocation, consecutive k in consecutive
        // invocations; out-of-range entries are zero.
        for (var i = 0u; i < 16u; i++) {
            let e = lid + 64u * i;
            let r = row0 + e / TILE_K;
            let k = k0 + e % TILE_K;
            var value = 0.0;
            if (r < params.rows && k < params.in_dim) {
                value = x[r * params.in_dim + k];
                if (params.norm == 1u) {
                    let s = tile_stats[e / TILE_K];
                    value = (value - s.x) * s.y;
                }
            }
            x_tile[e] = value;
        }
        // Stage w[out0.., k0..] transposed: 512 values, 8 per invocation.
        for (var i = 0u; i < 8u; i++) {
            let e = lid + 64u * i;
            let o = e / TILE_K;
            let kk = e % TILE_K;
            var value = 0.0;
            if (out0 + o < params.out_dim && k0 + kk < params.in_dim) {
                value = w[(out0 + o) * params.in_dim + k0 + kk];
            }
            w_tile[kk * (TILE_OUTS / 4u) + o / 4u][o % 4u] = value;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < TILE_K; kk++) {
            let wv = w_tile[kk * (TILE_OUTS / 4u) + og];
            for (var i = 0u; i < 8u; i++) {
                acc[i] += x_tile[(8u * rg + i) * TILE_K + kk] * wv;
            }
        }
        workgroupBarrier();
    }
    let o = out0 + 4u * og;
    var bias = vec4<f32>(0.0);
    for (var j = 0u; j < 4u; j++) {
        if (o + j < params.out_dim) {
            bias[j] = b[o + j];
        }
    }
    for (var i = 0u; i < 8u; i++) {
        let r = row0 + 8u * rg + i;
        if (r >= params.rows) {
            break;
        }
        store4(r, o, acc[i] + bias);
    }
}
