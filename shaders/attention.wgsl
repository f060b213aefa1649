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
// Scenes packed into one batch scene (`agent_scene`, [B·A] u32: each agent row's own scene; a
// plain batch's row of scene b holds b): `scene_mode` 1, agents attend only to agents of their
// own scene (agent rows (group / inner_count) · scene_agents + token, for the query's and the
// keys' layouts); `scene_mode` 2, group n is agent row n and its keys are those of group
// agent_scene[n] (the scene-frame map of the agent's own scene). 0: neither.
//
// Masked keys carry exactly zero weight (as an additive −1e9 bias does after exp in f32).
// One invocation per (group, head, query) with an online softmax (common/online_softmax.wgsl,
// prepended); a query with no valid key yields zeros (the reference's output there is never
// read: such tokens are invalid).
// Heads of 16 (every model here) take a path whose query and accumulator are four vec4 in
// registers; other head sizes index an array, which a GPU keeps in local memory.

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
    scene_agents: u32, // A: agent rows per batch scene (scene_mode 1)
    scene_mode: u32,
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
@group(0) @binding(5) var<storage, read> agent_scene: array<u32>; // [B·A]
@group(0) @binding(6) var<storage, read_write> out: array<f32>;

fn row_of(tokens: Layout, group: u32, token: u32) -> u32 {
    return (group / tokens.inner_count) * tokens.outer_stride
        + (group % tokens.inner_count) * tokens.inner_stride
        + token * tokens.token_stride;
}

// The group whose keys, values and key flags a query of `group` reads (`scene_mode` 2: its
// agent's scene's).
fn key_group(group: u32) -> u32 {
    if (params.scene_mode == 2u) {
        return agent_scene[group];
    }
    return group;
}

// Scene mode 1: the scene of agent `token` of `group` under `tokens`' grouping.
fn scene_of(tokens: Layout, group: u32, token: u32) -> u32 {
    return agent_scene[(group / tokens.inner_count) * params.scene_agents + token];
}

// The scene of query `query` of `group` (scene mode 1; 0 otherwise, unread).
fn query_scene(group: u32, query: u32) -> u32 {
    if (params.scene_mode == 1u) {
        return scene_of(params.q_layout, group, query);
    }
    return 0u;
}

// Whether key `j` of `group` (its keys' group `kg`) is a key of a query of scene `own_scene`:
// valid, and (scene mode 1) of that scene.
fn is_key(group: u32, kg: u32, own_scene: u32, j: u32) -> bool {
    if (key_valid[row_of(params.mask_layout, kg, j)] == 0.0) {
        return false;
    }
    return params.scene_mode != 1u || scene_of(params.kv_layout, group, j) == own_scene;
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
    if (hd == 16u) {
        attend16(group, query, q_base, head * hd, d);
        return;
    }
    let kg = key_group(group);
    let own_scene = query_scene(group, query);

    var acc: array<f32, MAX_HEAD_DIM>;
    for (var c = 0u; c < hd; c++) {
        acc[c] = 0.0;
    }
    var softmax = online_softmax_new();
    for (var j = 0u; j < params.keys; j++) {
        if (!is_key(group, kg, own_scene, j)) {
            continue;
        }
        let k_base = row_of(params.kv_layout, kg, j) * d + head * hd;
        var score = 0.0;
        for (var c = 0u; c < hd; c++) {
            score += q[q_base + c] * k[k_base + c];
        }
        score *= params.scale;
        let w = online_softmax_push(&softmax, score);
        for (var c = 0u; c < hd; c++) {
            acc[c] = acc[c] * w.correction + w.weight * v[k_base + c];
        }
    }
    let inv = online_softmax_inverse(softmax);
    for (var c = 0u; c < hd; c++) {
        out[q_base + c] = acc[c] * inv;
    }
}

// Four consecutive floats of q, k or v from `i` (a row's offset: any alignment).
fn q4(i: u32) -> vec4<f32> {
    return vec4<f32>(q[i], q[i + 1u], q[i + 2u], q[i + 3u]);
}
fn k4(i: u32) -> vec4<f32> {
    return vec4<f32>(k[i], k[i + 1u], k[i + 2u], k[i + 3u]);
}
fn v4(i: u32) -> vec4<f32> {
    return vec4<f32>(v[i], v[i + 1u], v[i + 2u], v[i + 3u]);
}

// `attention` for a head of 16: the same online softmax, the query and the accumulator in
// registers. `head_offset` is the head's first column, `d` the row width.
fn attend16(group: u32, query: u32, q_base: u32, head_offset: u32, d: u32) {
    let kg = key_group(group);
    let own_scene = query_scene(group, query);
    let q0 = q4(q_base);
    let q1 = q4(q_base + 4u);
    let q2 = q4(q_base + 8u);
    let q3 = q4(q_base + 12u);
    var a0 = vec4<f32>(0.0);
    var a1 = vec4<f32>(0.0);
    var a2 = vec4<f32>(0.0);
    var a3 = vec4<f32>(0.0);
    var softmax = online_softmax_new();
    for (var j = 0u; j < params.keys; j++) {
        if (!is_key(group, kg, own_scene, j)) {
            continue;
        }
        let k_base = row_of(params.kv_layout, kg, j) * d + head_offset;
        let score = (dot(q0, k4(k_base)) + dot(q1, k4(k_base + 4u))
            + dot(q2, k4(k_base + 8u)) + dot(q3, k4(k_base + 12u))) * params.scale;
        let w = online_softmax_push(&softmax, score);
        a0 = a0 * w.correction + w.weight * v4(k_base);
        a1 = a1 * w.correction + w.weight * v4(k_base + 4u);
        a2 = a2 * w.correction + w.weight * v4(k_base + 8u);
        a3 = a3 * w.correction + w.weight * v4(k_base + 12u);
    }
    let inv = online_softmax_inverse(softmax);
    let r0 = a0 * inv;
    let r1 = a1 * inv;
    let r2 = a2 * inv;
    let r3 = a3 * inv;
    for (var c = 0u; c < 4u; c++) {
        out[q_base + c] = r0[c];
        out[q_base + 4u + c] = r1[c];
        out[q_base + 8u + c] = r2[c];
        out[q_base + 12u + c] = r3[c];
    }
}
