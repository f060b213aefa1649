// What every linear kernel shares (`linear.wgsl`, `linear_f16.wgsl`, `linear_coop.wgsl`; the
// engine prepends this file to each, `road_gpu::shaders`): the layer's params, its bindings but
// the weights (binding 2, f32 or f16 by family), the rows' statistics of the layer norm
// prologue and the epilogue that stores 4 outputs (ReLU, residual add, parts).

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
