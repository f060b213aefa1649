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
// serves 4 products (no workgroup memory: small layers, and lavapipe's below 4 blocks).

// Params, bindings 0, 1, 3, 4, `row_stats` and `store4`: `common/linear_io.wgsl`, prepended.
@group(0) @binding(2) var<storage, read> w: array<f32>;      // [out, in]

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
// (Superseded by `linear_blocked` below, which the engine chooses instead; kept as a variant
// to measure against.)

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

// The same layer blocked for large layers on hardware GPUs: a workgroup of 192 invocations
// computes 128 rows × 96 outputs (the model's widths are multiples of 96 or 32: one block
// spans D = 96, three the q/k/v projection, four the MLP's hidden layer), each invocation
// 8 rows × 8 outputs in registers, so that per staged k it reads 4 vec4 from workgroup memory
// for 64 products. Both tiles are stored k-major as vec4 of consecutive rows or outputs, and an
// invocation's rows and outputs are two quads 64 rows / 48 outputs apart, so that the vec4
// reads of a warp fall in distinct banks.
// Staging: invocations 0..127 each own one row of x (its 16 values of a K-chunk), and with
// `norm` accumulate that row's statistics as they stage it (shifted by the row's first
// value), so that the layer norm costs no pass of its own: the product is taken on x − shift
// and corrected once per output, Σ (x − mean)·w = Σ (x − shift)·w − (mean − shift)·Σ w.
// Invocations 128..191 stage w, each three (output, half of the K-chunk) pairs, and keep
// those outputs' partial Σ w.

const BLOCK_ROWS: u32 = 128u;
const BLOCK_OUTS: u32 = 96u;
const BLOCK_K: u32 = 16u;

var<workgroup> x_block: array<vec4<f32>, 512>;  // [BLOCK_K, BLOCK_ROWS / 4]: x − shift
var<workgroup> w_block: array<vec4<f32>, 384>;  // [BLOCK_K, BLOCK_OUTS / 4]: w transposed
var<workgroup> block_stats: array<vec2<f32>, 128>; // [BLOCK_ROWS]: (mean − shift, 1/σ)
var<workgroup> block_w_sums: array<f32, 192>;   // [2, BLOCK_OUTS]: Σ w over each K-half

@compute @workgroup_size(192)
fn linear_blocked(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let out_blocks = (params.out_dim + BLOCK_OUTS - 1u) / BLOCK_OUTS;
    let row_blocks = (params.rows + BLOCK_ROWS - 1u) / BLOCK_ROWS;
    let block = wid.x + wid.y * groups.x;
    // Uniform across the workgroup: the grid may hold more groups than blocks.
    if (block >= out_blocks * row_blocks) {
        return;
    }
    let row0 = (block / out_blocks) * BLOCK_ROWS;
    let out0 = (block % out_blocks) * BLOCK_OUTS;
    let norm = params.norm == 1u;

    // Staging roles. A row stager's row; a weight stager's three (output, K-half) pairs:
    // pair p = u + 64·i, output p % 96, half p / 96.
    let stages_x = lid < BLOCK_ROWS;
    let u = lid - BLOCK_ROWS; // weight stagers only
    let x_row = row0 + lid;
    let x_valid = stages_x && x_row < params.rows;
    var shift = 0.0;
    if (norm && x_valid) {
        shift = x[x_row * params.in_dim];
    }
    var row_sum = 0.0;
    var row_sq = 0.0;
    var w_sum = vec3<f32>(0.0);

    // This invocation's outputs: rows 4·rg + i and 64 + 4·rg + i, outputs 4·og + j and
    // 48 + 4·og + j (i, j < 4).
    let rg = lid / 12u;
    let og = lid % 12u;
    var a00 = vec4<f32>(0.0); var a01 = vec4<f32>(0.0);
    var a10 = vec4<f32>(0.0); var a11 = vec4<f32>(0.0);
    var a20 = vec4<f32>(0.0); var a21 = vec4<f32>(0.0);
    var a30 = vec4<f32>(0.0); var a31 = vec4<f32>(0.0);
    var a40 = vec4<f32>(0.0); var a41 = vec4<f32>(0.0);
    var a50 = vec4<f32>(0.0); var a51 = vec4<f32>(0.0);
    var a60 = vec4<f32>(0.0); var a61 = vec4<f32>(0.0);
    var a70 = vec4<f32>(0.0); var a71 = vec4<f32>(0.0);

    for (var k0 = 0u; k0 < params.in_dim; k0 += BLOCK_K) {
        if (stages_x) {
            let quad = lid / 4u;
            let lane = lid % 4u;
            for (var kk = 0u; kk < BLOCK_K; kk++) {
                var value = 0.0;
                if (x_valid && k0 + kk < params.in_dim) {
                    value = x[x_row * params.in_dim + k0 + kk] - shift;
                    row_sum += value;
                    row_sq += value * value;
                }
                x_block[kk * (BLOCK_ROWS / 4u) + quad][lane] = value;
            }
        } else {
            for (var i = 0u; i < 3u; i++) {
                let pair = u + 64u * i;
                let o = pair % BLOCK_OUTS;
                let half = pair / BLOCK_OUTS;
                let w_row = (out0 + o) * params.in_dim;
                var sum = 0.0;
                for (var kk = 0u; kk < BLOCK_K / 2u; kk++) {
                    let k = half * (BLOCK_K / 2u) + kk;
                    var value = 0.0;
                    if (out0 + o < params.out_dim && k0 + k < params.in_dim) {
                        value = w[w_row + k0 + k];
                    }
                    sum += value;
                    w_block[k * (BLOCK_OUTS / 4u) + o / 4u][o % 4u] = value;
                }
                w_sum[i] += sum;
            }
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BLOCK_K; kk++) {
            let xa = x_block[kk * (BLOCK_ROWS / 4u) + rg];
            let xb = x_block[kk * (BLOCK_ROWS / 4u) + 16u + rg];
            let wa = w_block[kk * (BLOCK_OUTS / 4u) + og];
            let wb = w_block[kk * (BLOCK_OUTS / 4u) + 12u + og];
            a00 += xa.x * wa; a01 += xa.x * wb;
            a10 += xa.y * wa; a11 += xa.y * wb;
            a20 += xa.z * wa; a21 += xa.z * wb;
            a30 += xa.w * wa; a31 += xa.w * wb;
            a40 += xb.x * wa; a41 += xb.x * wb;
            a50 += xb.y * wa; a51 += xb.y * wb;
            a60 += xb.z * wa; a61 += xb.z * wb;
            a70 += xb.w * wa; a71 += xb.w * wb;
        }
        workgroupBarrier();
    }

    // The statistics and Σ w, shared for the epilogue.
    if (norm) {
        if (stages_x) {
            let n = f32(params.in_dim);
            let mean = row_sum / n;
            let var_ = max(row_sq / n - mean * mean, 0.0);
            block_stats[lid] = vec2<f32>(mean, inverseSqrt(var_ + params.eps));
        } else {
            for (var i = 0u; i < 3u; i++) {
                let pair = u + 64u * i;
                block_w_sums[(pair / BLOCK_OUTS) * BLOCK_OUTS + pair % BLOCK_OUTS] = w_sum[i];
            }
        }
        workgroupBarrier();
    }

    let oa = 4u * og;
    let ob = 48u + 4u * og;
    var bias_a = vec4<f32>(0.0);
    var bias_b = vec4<f32>(0.0);
    var sum_a = vec4<f32>(0.0);
    var sum_b = vec4<f32>(0.0);
    for (var j = 0u; j < 4u; j++) {
        if (out0 + oa + j < params.out_dim) {
            bias_a[j] = b[out0 + oa + j];
        }
        if (out0 + ob + j < params.out_dim) {
            bias_b[j] = b[out0 + ob + j];
        }
        if (norm) {
            sum_a[j] = block_w_sums[oa + j] + block_w_sums[BLOCK_OUTS + oa + j];
            sum_b[j] = block_w_sums[ob + j] + block_w_sums[BLOCK_OUTS + ob + j];
        }
    }
    block_store(row0 + 4u * rg, out0, oa, ob, a00, a01, bias_a, bias_b, sum_a, sum_b, 4u * rg);
    block_store(row0 + 4u * rg + 1u, out0, oa, ob, a10, a11, bias_a, bias_b, sum_a, sum_b, 4u * rg + 1u);
    block_store(row0 + 4u * rg + 2u, out0, oa, ob, a20, a21, bias_a, bias_b, sum_a, sum_b, 4u * rg + 2u);
    block_store(row0 + 4u * rg + 3u, out0, oa, ob, a30, a31, bias_a, bias_b, sum_a, sum_b, 4u * rg + 3u);
    block_store(row0 + 64u + 4u * rg, out0, oa, ob, a40, a41, bias_a, bias_b, sum_a, sum_b, 64u + 4u * rg);
    block_store(row0 + 65u + 4u * rg, out0, oa, ob, a50, a51, bias_a, bias_b, sum_a, sum_b, 65u + 4u * rg);
    block_store(row0 + 66u + 4u * rg, out0, oa, ob, a60, a61, bias_a, bias_b, sum_a, sum_b, 66u + 4u * rg);
    block_store(row0 + 67u + 4u * rg, out0, oa, ob, a70, a71, bias_a, bias_b, sum_a, sum_b, 67u + 4u * rg);
}

// One row of a block's results: the two quads of outputs (out0 + oa.., out0 + ob..), the
// layer norm's correction from the row's statistics (`local_row` of the block), the bias, then
// the shared epilogue.
fn block_store(
    row: u32, out0: u32, oa: u32, ob: u32, acc_a: vec4<f32>, acc_b: vec4<f32>,
    bias_a: vec4<f32>, bias_b: vec4<f32>, sum_a: vec4<f32>, sum_b: vec4<f32>, local_row: u32,
) {
    if (row >= params.rows) {
        return;
    }
    var va = acc_a;
    var vb = acc_b;
    if (params.norm == 1u) {
        let stats = block_stats[local_row];
        va = (va - stats.x * sum_a) * stats.y;
        vb = (vb - stats.x * sum_b) * stats.y;
    }
    if (out0 + oa < params.out_dim) {
        store4(row, out0 + oa, va + bias_a);
    }
    if (out0 + ob < params.out_dim) {
        store4(row, out0 + ob, vb + bias_b);
    }
}
