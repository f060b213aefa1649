// Linear layer over the last dimension: y[r, o] = act(Σ_k x[r, k] · w[o, k] + b[o]).
// Weights as stored in the checkpoint: w [out, in] row-major, b [out].
// One invocation computes 4 consecutive outputs of one row, so that each x element it loads
// serves 4 products (lavapipe favours no workgroup memory and several outputs per thread).

struct Params {
    rows: u32,
    in_dim: u32,
    out_dim: u32,
    relu: u32, // 1: ReLU after the bias
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;      // [rows, in]
@group(0) @binding(2) var<storage, read> w: array<f32>;      // [out, in]
@group(0) @binding(3) var<storage, read> b: array<f32>;      // [out]
@group(0) @binding(4) var<storage, read_write> y: array<f32>; // [rows, out]

@compute @workgroup_size(64)
fn linear(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let quads = (params.out_dim + 3u) / 4u;
    let index = gid.x + gid.y * groups.x * 64u;
    if (index >= params.rows * quads) {
        return;
    }
    let row = index / quads;
    let col0 = (index % quads) * 4u;
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
    for (var k = 0u; k < params.in_dim; k++) {
        let xv = x[x_base + k];
        acc += xv * vec4<f32>(w[w0 + k], w[w1 + k], w[w2 + k], w[w3 + k]);
    }
    acc += vec4<f32>(b[col0], b[c1], b[c2], b[c3]);
    if (params.relu == 1u) {
        acc = max(acc, vec4<f32>(0.0));
    }
    let y_base = row * params.out_dim;
    for (var j = 0u; j < 4u; j++) {
        if (col0 + j < params.out_dim) {
            y[y_base + col0 + j] = acc[j];
        }
    }
}

// The same layer for hardware GPUs: a workgroup computes a tile of 64 rows × 32 outputs, staging
// K-chunks of x and w in workgroup memory so that each global load serves 32 (x) or 64 (w)
// products and loads coalesce; each invocation accumulates 8 rows × 4 outputs in registers.
// (The row-wise entry above stays the choice on lavapipe, where workgroup memory and barriers
// cost more than they save.)

const TILE_ROWS: u32 = 64u;
const TILE_OUTS: u32 = 32u;
const TILE_K: u32 = 16u;

var<workgroup> x_tile: array<f32, 1024>;       // [TILE_ROWS, TILE_K]
var<workgroup> w_tile: array<vec4<f32>, 128>;  // [TILE_K, TILE_OUTS / 4]: w transposed

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
        var value = acc[i] + bias;
        if (params.relu == 1u) {
            value = max(value, vec4<f32>(0.0));
        }
        for (var j = 0u; j < 4u; j++) {
            if (o + j < params.out_dim) {
                y[r * params.out_dim + o + j] = value[j];
            }
        }
    }
}
