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
