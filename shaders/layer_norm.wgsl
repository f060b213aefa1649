// Layer norm over the last dimension: y = (x − mean) / √(var + eps) · gamma + beta,
// with the biased variance (as candle and PyTorch). One invocation per row; two passes.

struct Params {
    rows: u32,
    dim: u32,
    eps: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;      // [rows, dim]
@group(0) @binding(2) var<storage, read> gamma: array<f32>;  // [dim]
@group(0) @binding(3) var<storage, read> beta: array<f32>;   // [dim]
@group(0) @binding(4) var<storage, read_write> y: array<f32>; // [rows, dim]

@compute @workgroup_size(64)
fn layer_norm(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let row = gid.x + gid.y * groups.x * 64u;
    if (row >= params.rows) {
        return;
    }
    let base = row * params.dim;
    let n = f32(params.dim);
    var sum = 0.0;
    for (var k = 0u; k < params.dim; k++) {
        sum += x[base + k];
    }
    let mean = sum / n;
    var sq = 0.0;
    for (var k = 0u; k < params.dim; k++) {
        let c = x[base + k] - mean;
        sq += c * c;
    }
    let inv = inverseSqrt(sq / n + params.eps);
    for (var k = 0u; k < params.dim; k++) {
        y[base + k] = (x[base + k] - mean) * inv * gamma[k] + beta[k];
    }
}
