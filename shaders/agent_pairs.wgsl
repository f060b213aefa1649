// Agent attention with pair features (road_model::config::AgentPairs): multi-head attention
// over the agents of each (scene, slot) whose scores gain (K_hᵀ q) · r_ij and whose outputs gain
// V_h Σ_j a_ij r_ij, where r_ij are the features of key agent j seen from query agent i
// (road_model::agent_pairs::pair_features, computed here from the states on the fly).
//
// Tokens are [B, A, W, D] (q, k, v, out), states [B, A, W, 3], flags [B, A, W]; group n =
// (scene, slot); token l = agent. The pair weights are [D, F] (head h owns rows h·head_dim…).
// Masked keys carry exactly zero weight: invalid ones, and those of another scene where a
// packed batch holds several scenes in one (`agent_scene`, [B·A]: agents attend only to agents
// of their own scene; a plain batch's row a of scene b holds b). A query with no valid key
// yields zeros (as attention.wgsl). One invocation per (group, head, query) with an online
// softmax (common/online_softmax.wgsl, prepended); heads of 16 keep the query and the
// accumulator in registers (as attention.wgsl).

struct Params {
    groups: u32,
    heads: u32,
    head_dim: u32,
    agents: u32,
    slots: u32,
    anchor_slot: u32,
    scale: f32,
    heading_scale: f32,
    // Length scales in state units (road_model::agent_pairs::PairScales).
    direction: f32,
    near: f32,
    far: f32,
    _pad: u32,
}

const MAX_HEAD_DIM: u32 = 64u;
const F: u32 = 6u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> q: array<f32>;
@group(0) @binding(2) var<storage, read> k: array<f32>;
@group(0) @binding(3) var<storage, read> v: array<f32>;
@group(0) @binding(4) var<storage, read> valid: array<f32>;
@group(0) @binding(5) var<storage, read> states: array<f32>;
@group(0) @binding(6) var<storage, read> pair_k: array<f32>;
@group(0) @binding(7) var<storage, read> pair_v: array<f32>;
@group(0) @binding(8) var<storage, read> agent_scene: array<u32>; // [B·A]
@group(0) @binding(9) var<storage, read_write> out: array<f32>;

// Token row of agent `agent` in group (scene, slot).
fn row_of(group: u32, agent: u32) -> u32 {
    let scene = group / params.slots;
    return (scene * params.agents + agent) * params.slots + group % params.slots;
}

// The states as common/pair_features.wgsl reads them.
fn pair_state(i: u32) -> f32 {
    return states[i];
}

fn pair_features(query: u32, key: u32, cos_a: f32, sin_a: f32) -> array<f32, 6> {
    let scales = PairScales(params.heading_scale, params.direction, params.near, params.far);
    return pair_features_of(query, key, cos_a, sin_a, scales);
}

@compute @workgroup_size(64)
fn pair_attention(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = gid.x + gid.y * groups.x * 64u;
    if (index >= params.groups * params.heads * params.agents) {
        return;
    }
    let query = index % params.agents;
    let head = (index / params.agents) % params.heads;
    let group = index / (params.agents * params.heads);
    let d = params.heads * params.head_dim;
    let hd = params.head_dim;
    let q_row = row_of(group, query);
    let q_base = q_row * d + head * hd;

    // The query agent's anchor heading (the scene frame's 0 without an anchor).
    let scene = group / params.slots;
    let anchor_row = (scene * params.agents + query) * params.slots + params.anchor_slot;
    let anchor_heading = states[anchor_row * 3u + 2u] * valid[anchor_row] / params.heading_scale;
    let cos_a = cos(anchor_heading);
    let sin_a = sin(anchor_heading);
    let own_scene = agent_scene[scene * params.agents + query];

    // K_hᵀ q_h.
    var q_pair: array<f32, 6>;
    for (var f = 0u; f < F; f++) {
        var acc = 0.0;
        for (var c = 0u; c < hd; c++) {
            acc += q[q_base + c] * pair_k[(head * hd + c) * F + f];
        }
        q_pair[f] = acc;
    }
    if (hd == 16u) {
        pair_attend16(group, q_row, q_base, head, d, cos_a, sin_a, q_pair, own_scene);
        return;
    }

    var acc: array<f32, MAX_HEAD_DIM>;
    for (var c = 0u; c < hd; c++) {
        acc[c] = 0.0;
    }
    var acc_pair: array<f32, 6>;
    for (var f = 0u; f < F; f++) {
        acc_pair[f] = 0.0;
    }
    var softmax = online_softmax_new();
    for (var j = 0u; j < params.agents; j++) {
        let k_row = row_of(group, j);
        if (!is_key(group, j, k_row, own_scene)) {
            continue;
        }
        var r = pair_features(q_row, k_row, cos_a, sin_a);
        let k_base = k_row * d + head * hd;
        var score = 0.0;
        for (var c = 0u; c < hd; c++) {
            score += q[q_base + c] * k[k_base + c];
        }
        for (var f = 0u; f < F; f++) {
            score += q_pair[f] * r[f];
        }
        score *= params.scale;
        let w = online_softmax_push(&softmax, score);
        for (var c = 0u; c < hd; c++) {
            acc[c] = acc[c] * w.correction + w.weight * v[k_base + c];
        }
        for (var f = 0u; f < F; f++) {
            acc_pair[f] = acc_pair[f] * w.correction + w.weight * r[f];
        }
    }
    let inv = online_softmax_inverse(softmax);
    for (var c = 0u; c < hd; c++) {
        var offset = 0.0;
        for (var f = 0u; f < F; f++) {
            offset += pair_v[(head * hd + c) * F + f] * acc_pair[f];
        }
        out[q_base + c] = (acc[c] + offset) * inv;
    }
}

// Whether agent `agent` (token row `k_row`) of group `group` is a key of a query of scene
// `own_scene`: valid, and of the same scene.
fn is_key(group: u32, agent: u32, k_row: u32, own_scene: u32) -> bool {
    let scene = group / params.slots;
    return valid[k_row] != 0.0 && agent_scene[scene * params.agents + agent] == own_scene;
}

// Four consecutive floats of q, k or v from `i`.
fn q4(i: u32) -> vec4<f32> {
    return vec4<f32>(q[i], q[i + 1u], q[i + 2u], q[i + 3u]);
}
fn k4(i: u32) -> vec4<f32> {
    return vec4<f32>(k[i], k[i + 1u], k[i + 2u], k[i + 3u]);
}
fn v4(i: u32) -> vec4<f32> {
    return vec4<f32>(v[i], v[i + 1u], v[i + 2u], v[i + 3u]);
}

// `pair_attention`'s key loop and output for a head of 16, the query and the accumulator in
// four vec4 registers.
fn pair_attend16(
    group: u32, q_row: u32, q_base: u32, head: u32, d: u32, cos_a: f32, sin_a: f32,
    q_pair: array<f32, 6>, own_scene: u32,
) {
    let q0 = q4(q_base);
    let q1 = q4(q_base + 4u);
    let q2 = q4(q_base + 8u);
    let q3 = q4(q_base + 12u);
    var a0 = vec4<f32>(0.0);
    var a1 = vec4<f32>(0.0);
    var a2 = vec4<f32>(0.0);
    var a3 = vec4<f32>(0.0);
    var acc_pair: array<f32, 6>;
    for (var f = 0u; f < F; f++) {
        acc_pair[f] = 0.0;
    }
    var softmax = online_softmax_new();
    for (var j = 0u; j < params.agents; j++) {
        let k_row = row_of(group, j);
        if (!is_key(group, j, k_row, own_scene)) {
            continue;
        }
        let r = pair_features(q_row, k_row, cos_a, sin_a);
        let k_base = k_row * d + head * 16u;
        var score = dot(q0, k4(k_base)) + dot(q1, k4(k_base + 4u)) + dot(q2, k4(k_base + 8u))
            + dot(q3, k4(k_base + 12u));
        for (var f = 0u; f < F; f++) {
            score += q_pair[f] * r[f];
        }
        score *= params.scale;
        let w = online_softmax_push(&softmax, score);
        a0 = a0 * w.correction + w.weight * v4(k_base);
        a1 = a1 * w.correction + w.weight * v4(k_base + 4u);
        a2 = a2 * w.correction + w.weight * v4(k_base + 8u);
        a3 = a3 * w.correction + w.weight * v4(k_base + 12u);
        for (var f = 0u; f < F; f++) {
            acc_pair[f] = acc_pair[f] * w.correction + w.weight * r[f];
        }
    }
    let inv = online_softmax_inverse(softmax);
    for (var c = 0u; c < 16u; c++) {
        var offset = 0.0;
        for (var f = 0u; f < F; f++) {
            offset += pair_v[(head * 16u + c) * F + f] * acc_pair[f];
        }
        var value = a3[c % 4u];
        if (c < 4u) {
            value = a0[c];
        } else if (c < 8u) {
            value = a1[c % 4u];
        } else if (c < 12u) {
            value = a2[c % 4u];
        }
        out[q_base + c] = (value + offset) * inv;
    }
}
