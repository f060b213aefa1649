// Multi-head attention with key masks, over strided token layouts, so that attention over
// time ([B, A, W, D]: groups (b, a), tokens w) and over agents (groups (b, w), tokens a) read
// the same tensor without a transpose.
//
// Token rows are D = heads · head_dim floats; head h owns columns h·head_dim ... A group index
// n splits as (n / inner_count, n % inner_count); its first token row is
// (n / inner_count) · outer_stride + (n % inner_count) · inner_stride, and token l adds
// l · token_stride (all in rows). Queries and outputs share one layout, keys and values another,
// key validity (f32, 1 = valid) a third with the same group/token meaning.
//
// Masked keys carry exactly zero weight (as an additive −1e9 bias does after exp in f32).
// One invocation per (group, head, query) with an online softmax; a query with no valid key
// yields zeros (the reference's output there is never read: such tokens are invalid).

struct Layout {
    inner_count: u32,
    outer_stride: u32,
    inner_stride: u32,
    token_stride: u32,
}

struct Params {
    groups: u32,
    heads: u32,
    head_dim: u32,
    queries: u32,
    keys: u32,
    scale: f32,
    _pad0: u32,
    _pad1: u32,
    q_layout: Layout,
    kv_layout: Layout,
    mask_layout: Layout,
}

const MAX_HEAD_DIM: u32 = 64u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> q: array<f32>;
@group(0) @binding(2) var<storage, read> k: array<f32>;
@group(0) @binding(3) var<storage, read> v: array<f32>;
@group(0) @binding(4) var<storage, read> key_valid: array<f32>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

fn row_of(tokens: Layout, group: u32, token: u32) -> u32 {
    return (group / tokens.inner_count) * tokens.outer_stride
        + (group % tokens.inner_count) * tokens.inner_stride
        + token * tokens.token_stride;
}

@compute @workgroup_size(64)
fn attention(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = gid.x + gid.y * groups.x * 64u;
    if (index >= params.groups * params.heads * params.queries) {
        return;
    }
    let query = index % params.queries;
    let head = (index / params.queries) % params.heads;
    let group = index / (params.queries * params.heads);
    let d = params.heads * params.head_dim;
    let hd = params.head_dim;
    let q_base = row_of(params.q_layout, group, query) * d + head * hd;

    var acc: array<f32, MAX_HEAD_DIM>;
    for (var c = 0u; c < hd; c++) {
        acc[c] = 0.0;
    }
    var running_max = -3.0e38;
    var denom = 0.0;
    for (var j = 0u; j < params.keys; j++) {
        if (key_valid[row_of(params.mask_layout, group, j)] == 0.0) {
            continue;
        }
        let k_base = row_of(params.kv_layout, group, j) * d + head * hd;
        var score = 0.0;
        for (var c = 0u; c < hd; c++) {
            score += q[q_base + c] * k[k_base + c];
        }
        score *= params.scale;
        let new_max = max(running_max, score);
        let correction = exp(running_max - new_max);
        let weight = exp(score - new_max);
        denom = denom * correction + weight;
        for (var c = 0u; c < hd; c++) {
            acc[c] = acc[c] * correction + weight * v[k_base + c];
        }
        running_max = new_max;
    }
    let inv = select(0.0, 1.0 / denom, denom > 0.0);
    for (var c = 0u; c < hd; c++) {
        out[q_base + c] = acc[c] * inv;
    }
}
