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

// The same encoder as a blocked matrix product, for hardware GPUs and large batches: a
// workgroup of 192 invocations encodes BLOCK_POLYLINES = min(8, 128 / Q) polylines, their
// points as up to 128 rows of `linear_blocked`'s tiling (8 × 8 outputs per invocation, 96
// outputs per block, the point embedding computed as x is staged), then the max over each
// polyline's points (through workgroup memory), the bias and the layer norm. Needs Q a
// multiple of 4 (an invocation's four consecutive rows lie in one polyline), Q ≤ 128 and
// D ≤ MAX_BLOCKED_HIDDEN; `PolylineParams::blocked_fits` says so, and the engine runs
// `encode_polylines` otherwise.

const MAX_BLOCKED_HIDDEN: u32 = 192u;
const MAX_BLOCK_POLYLINES: u32 = 8u;

// K-chunk staging of x (vec4 0..512: [16 k, 32 row quads]) and of W_mix (512..896: [16 k,
// 24 output quads]); after a block's products, the per-row-quad maxima (0..768: [32 row
// quads, 24 output quads]).
var<workgroup> stage: array<vec4<f32>, 896>;
var<workgroup> pooled_block: array<f32, 1536>; // [MAX_BLOCK_POLYLINES, MAX_BLOCKED_HIDDEN]
var<workgroup> polyline_stats: array<vec2<f32>, 8>; // [MAX_BLOCK_POLYLINES]: (mean, 1/σ)

@compute @workgroup_size(192)
fn encode_polylines_blocked(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let q_count = params.points;
    let d_count = params.hidden;
    let per_block = min(MAX_BLOCK_POLYLINES, 128u / q_count);
    let poly0 = (wid.x + wid.y * groups.x) * per_block;
    // Uniform across the workgroup: the grid may hold more groups than blocks.
    if (poly0 >= params.polylines) {
        return;
    }
    let polylines = min(per_block, params.polylines - poly0);
    let rows = polylines * q_count;
    let b_point = 2u * d_count;
    let pe = b_point + d_count;

    // A row stager's point (invocations 0..127): polyline poly0 + lid / Q, point lid % Q.
    let stages_x = lid < 128u;
    let x_valid = stages_x && lid < rows;
    let q = lid % q_count;
    let p = 2u * ((poly0 + lid / q_count) * q_count + q);
    var px = 0.0;
    var py = 0.0;
    if (x_valid) {
        px = points[p];
        py = points[p + 1u];
    }
    let u = lid - min(lid, 128u); // a weight stager's index (invocations 128..191)
    let rg = lid / 12u;
    let og = lid % 12u;

    for (var out0 = 0u; out0 < d_count; out0 += 96u) {
        var a00 = vec4<f32>(0.0); var a01 = vec4<f32>(0.0);
        var a10 = vec4<f32>(0.0); var a11 = vec4<f32>(0.0);
        var a20 = vec4<f32>(0.0); var a21 = vec4<f32>(0.0);
        var a30 = vec4<f32>(0.0); var a31 = vec4<f32>(0.0);
        var a40 = vec4<f32>(0.0); var a41 = vec4<f32>(0.0);
        var a50 = vec4<f32>(0.0); var a51 = vec4<f32>(0.0);
        var a60 = vec4<f32>(0.0); var a61 = vec4<f32>(0.0);
        var a70 = vec4<f32>(0.0); var a71 = vec4<f32>(0.0);
        for (var k0 = 0u; k0 < d_count; k0 += 16u) {
            if (stages_x) {
                for (var kk = 0u; kk < 16u; kk++) {
                    let k = k0 + kk;
                    var value = 0.0;
                    if (x_valid && k < d_count) {
                        value = max(embed[2u * k] * px + embed[2u * k + 1u] * py
                            + embed[b_point + k] + embed[pe + q * d_count + k], 0.0);
                    }
                    stage[kk * 32u + lid / 4u][lid % 4u] = value;
                }
            } else {
                for (var i = 0u; i < 3u; i++) {
                    let pair = u + 64u * i;
                    let o = pair % 96u;
                    let half = pair / 96u;
                    for (var kk = 0u; kk < 8u; kk++) {
                        let k = half * 8u + kk;
                        var value = 0.0;
                        if (out0 + o < d_count && k0 + k < d_count) {
                            value = mix_w[(out0 + o) * d_count + k0 + k];
                        }
                        stage[512u + k * 24u + o / 4u][o % 4u] = value;
                    }
                }
            }
            workgroupBarrier();
            for (var kk = 0u; kk < 16u; kk++) {
                let xa = stage[kk * 32u + rg];
                let xb = stage[kk * 32u + 16u + rg];
                let wa = stage[512u + kk * 24u + og];
                let wb = stage[512u + kk * 24u + 12u + og];
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
        // Each row quad's maximum (its four rows are points of one polyline), then each
        // polyline's over its Q / 4 row quads, plus the bias.
        stage[rg * 24u + og] = max(max(a00, a10), max(a20, a30));
        stage[rg * 24u + 12u + og] = max(max(a01, a11), max(a21, a31));
        stage[(16u + rg) * 24u + og] = max(max(a40, a50), max(a60, a70));
        stage[(16u + rg) * 24u + 12u + og] = max(max(a41, a51), max(a61, a71));
        workgroupBarrier();
        let quads = q_count / 4u;
        for (var e = lid; e < polylines * 96u; e += 192u) {
            let pl = e / 96u;
            let o = e % 96u;
            if (out0 + o < d_count) {
                var m = -3.0e38;
                for (var r = pl * quads; r < (pl + 1u) * quads; r++) {
                    m = max(m, stage[r * 24u + o / 4u][o % 4u]);
                }
                pooled_block[pl * MAX_BLOCKED_HIDDEN + out0 + o] = m + mix_b[out0 + o];
            }
        }
        workgroupBarrier();
    }
    // The layer norm of each polyline's pooled features (two passes, one invocation each).
    if (lid < polylines) {
        let base = lid * MAX_BLOCKED_HIDDEN;
        let n = f32(d_count);
        var sum = 0.0;
        for (var k = 0u; k < d_count; k++) {
            sum += pooled_block[base + k];
        }
        let mean = sum / n;
        var sq = 0.0;
        for (var k = 0u; k < d_count; k++) {
            let c = pooled_block[base + k] - mean;
            sq += c * c;
        }
        polyline_stats[lid] = vec2<f32>(mean, inverseSqrt(sq / n + params.eps));
    }
    workgroupBarrier();
    for (var e = lid; e < polylines * d_count; e += 192u) {
        let pl = e / d_count;
        let o = e % d_count;
        let stats = polyline_stats[pl];
        tokens[(poly0 + pl) * d_count + o] =
            (pooled_block[pl * MAX_BLOCKED_HIDDEN + o] - stats.x) * stats.y * gamma[o] + beta[o];
    }
}
