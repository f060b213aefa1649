// The map's polyline encoder (docs/checkpoint.md, step 3), one workgroup per polyline, so that
// its per-point activations never leave workgroup memory:
//   e[q, :] = relu(W_point · point[q] + b_point + point_embedding[q, :])   (points, Q × D)
//   token   = layer_norm(max_q (W_mix · e[q, :] + b_mix))                    (ln_map_out)
// Points are staged in chunks of a multiple of 4 that fit CHUNK_FLOATS, so any Q fits;
// D ≤ MAX_HIDDEN. Each invocation owns outputs lid, lid + 64, … and computes each for 4 points
// at a time: one load of w serves 4 products, as in the row-wise linear kernel.

struct Params {
    polylines: u32,
    points: u32, // Q
    hidden: u32, // D
    eps: f32,
}

const CHUNK_FLOATS: u32 = 2048u; // staged point embeddings: [points per chunk, D]
const MAX_HIDDEN: u32 = 512u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> points: array<f32>;    // [n, Q, 2]
// W_point [D, 2] | b_point [D] | point_embedding [Q, D]
@group(0) @binding(2) var<storage, read> embed: array<f32>;
@group(0) @binding(3) var<storage, read> mix_w: array<f32>;     // [D, D]
@group(0) @binding(4) var<storage, read> mix_b: array<f32>;     // [D]
@group(0) @binding(5) var<storage, read> gamma: array<f32>;     // [D]
@group(0) @binding(6) var<storage, read> beta: array<f32>;      // [D]
@group(0) @binding(7) var<storage, read_write> tokens: array<f32>; // [n, D]

var<workgroup> staged: array<f32, 2048>;  // [CHUNK_FLOATS]: e of a chunk of points
var<workgroup> pooled: array<f32, 512>;   // [MAX_HIDDEN]: the running max of W_mix · e + b

@compute @workgroup_size(64)
fn encode_polylines(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let poly = wid.x + wid.y * groups.x;
    // Uniform across the workgroup: the grid may hold more groups than polylines.
    if (poly >= params.polylines) {
        return;
    }
    let d_count = params.hidden;
    let q_count = params.points;
    let b_point = 2u * d_count;
    let pe = b_point + d_count;
    for (var o = lid; o < d_count; o += 64u) {
        pooled[o] = -3.0e38;
    }
    workgroupBarrier();
    let per_chunk = max(CHUNK_FLOATS / d_count / 4u * 4u, 4u);
    for (var q0 = 0u; q0 < q_count; q0 += per_chunk) {
        let chunk = min(per_chunk, q_count - q0);
        // Point by point, so that no index is divided (integer division is slow on lavapipe).
        for (var i = 0u; i < chunk; i++) {
            let q = q0 + i;
            let p = 2u * (poly * q_count + q);
            for (var d = lid; d < d_count; d += 64u) {
                let v = embed[2u * d] * points[p] + embed[2u * d + 1u] * points[p + 1u]
                    + embed[b_point + d] + embed[pe + q * d_count + d];
                staged[i * d_count + d] = max(v, 0.0);
            }
        }
        workgroupBarrier();
        // No two invocations write one pooled entry. Points past the chunk's end read stale
        // staged values (inside the array: per_chunk · D ≤ CHUNK_FLOATS) and are not pooled.
        for (var o = lid; o < d_count; o += 64u) {
            var m = pooled[o];
            for (var q = 0u; q < chunk; q += 4u) {
                var acc = vec4<f32>(mix_b[o]);
                for (var k = 0u; k < d_count; k++) {
                    let e = q * d_count + k;
                    acc += mix_w[o * d_count + k] * vec4<f32>(
                        staged[e],
                        staged[e + d_count],
                        staged[e + 2u * d_count],
                        staged[e + 3u * d_count],
                    );
                }
                for (var j = 0u; j < 4u; j++) {
                    if (q + j < chunk) {
                        m = max(m, acc[j]);
                    }
                }
            }
            pooled[o] = m;
        }
        workgroupBarrier();
    }
    // The layer norm: every invocation reads the statistics from workgroup memory (two passes,
    // as the layer norm elsewhere), then writes its outputs.
    let n = f32(d_count);
    var sum = 0.0;
    for (var k = 0u; k < d_count; k++) {
        sum += pooled[k];
    }
    let mean = sum / n;
    var sq = 0.0;
    for (var k = 0u; k < d_count; k++) {
        let c = pooled[k] - mean;
        sq += c * c;
    }
    let inv = inverseSqrt(sq / n + params.eps);
    for (var o = lid; o < d_count; o += 64u) {
        tokens[poly * d_count + o] = (pooled[o] - mean) * inv * gamma[o] + beta[o];
    }
}
