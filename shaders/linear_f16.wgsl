// The linear layer of `linear.wgsl` in the numerics of the tensor cores' path (`linear_coop.wgsl`)
// on any adapter with `SHADER_F16`: the weights stored as f16, each input n(x) (standardised
// first under `norm`) rounded to f16, the products summed in f32, then the bias and the shared
// epilogue in f32. It serves where the adapter has no cooperative matrices (lavapipe in CI, so
// that the f16 path's quality is measured and tested without a GPU) and for layers whose sizes
// the cooperative kernel does not take. One invocation computes 4 outputs of one row, as `linear`.
// Params, bindings 0, 1, 3, 4, `row_stats` and `store4`: `common/linear_io.wgsl`, prepended.
@group(0) @binding(2) var<storage, read> w: array<f16>; // [out, in]

// v rounded to f16's 11 significant bits, to nearest with ties to even, as an f32: by the bits,
// because `f32(f16(v))` is folded away by some compilers (lavapipe's). Exact in f16's normal
// range; below it (|v| < 2⁻¹⁴) finer than f16's subnormals by at most 2⁻²⁵, and no overflow
// to infinity past 65 504 (standardised rows and the model's activations stay far inside).
fn round_to_f16(v: f32) -> f32 {
    let bits = bitcast<u32>(v);
    let odd = (bits >> 13u) & 1u;
    return bitcast<f32>((bits + 0x0fffu + odd) & 0xffffe000u);
}

@compute @workgroup_size(64)
fn linear_f16(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let quads = (params.out_dim + 3u) / 4u;
    let index = gid.x + gid.y * groups.x * 64u;
    if (index >= params.rows * quads) {
        return;
    }
    let row = index / quads;
    let col0 = (index % quads) * 4u;
    var stats = vec2<f32>(0.0, 1.0); // (mean, 1/σ): the identity without a norm
    if (params.norm == 1u) {
        stats = row_stats(row);
    }
    let x_base = row * params.in_dim;
    // Columns past the end read row 0 of w (valid memory); their results are not written.
    let c1 = select(0u, col0 + 1u, col0 + 1u < params.out_dim);
    let c2 = select(0u, col0 + 2u, col0 + 2u < params.out_dim);
    let c3 = select(0u, col0 + 3u, col0 + 3u < params.out_dim);
    let w0 = col0 * params.in_dim;
    let w1 = c1 * params.in_dim;
    let w2 = c2 * params.in_dim;
    let w3 = c3 * params.in_dim;
    var acc = vec4<f32>(0.0);
    for (var k = 0u; k < params.in_dim; k++) {
        // Rounded as the cooperative kernel stages it: standardised, then to f16.
        let xv = round_to_f16((x[x_base + k] - stats.x) * stats.y);
        let wv = vec4<f32>(vec4<f16>(w[w0 + k], w[w1 + k], w[w2 + k], w[w3 + k]));
        acc += xv * wv;
    }
    acc += vec4<f32>(b[col0], b[c1], b[c2], b[c3]);
    store4(row, col0, acc);
}
