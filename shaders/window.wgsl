// Window updates on the device, so that a tick reads back only what it emits (math doc,
// "The window"). Windows are [B, A, W, 3].
//   window_emitted: out[b, a, :] = x[b, a, slot[b], :]  (0 where slot[b] ≥ W: scene not read)
//   window_shift:   for scenes with shift[b] = 1, after an emission from slot n:
//                   slots move up by one, slot n − 1 = emitted + σ_obs·noise_obs (the emitted
//                   state, possibly overwritten by a controller, joins the observations),
//                   slot W − 1 = σ_max·noise_new (a fresh pure-noise slot); the agent's plan,
//                   slots n … W − 2, turns by its entry of `turns` (position rotated about the
//                   pivot, heading changed: `road_model::sample::turn_plan`); other scenes copy.

struct Params {
    count: u32,     // B · A · W · 3 (shift) or B · A · 3 (emitted)
    slots: u32,     // W
    agents: u32,    // A
    observed: u32,  // n
    obs_sigma: f32,
    sigma_max: f32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;             // [B, A, W, 3]
@group(0) @binding(2) var<storage, read> per_scene: array<u32>;     // [B]: slot (emitted) or shift flag
@group(0) @binding(3) var<storage, read> emitted: array<f32>;       // [B, A, 3] (shift only)
@group(0) @binding(4) var<storage, read> noise: array<f32>;         // [B, A, 6]: obs 3, new 3 (shift only)
@group(0) @binding(5) var<storage, read_write> out: array<f32>;
@group(0) @binding(6) var<storage, read> turns: array<f32>;         // [B, A, 4]: pivot x, y, angle, heading change (shift only)

fn index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 64u;
}

@compute @workgroup_size(64)
fn window_emitted(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = index(gid, groups);
    if (i >= params.count) {
        return;
    }
    let d = i % 3u;
    let agent_row = i / 3u; // b · A + a
    let b = agent_row / params.agents;
    let slot = per_scene[b];
    if (slot >= params.slots) {
        out[i] = 0.0;
        return;
    }
    out[i] = x[(agent_row * params.slots + slot) * 3u + d];
}

@compute @workgroup_size(64)
fn window_shift(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = index(gid, groups);
    if (i >= params.count) {
        return;
    }
    let d = i % 3u;
    let token = i / 3u;
    let s = token % params.slots;
    let agent_row = token / params.slots; // b · A + a
    let b = agent_row / params.agents;
    if (per_scene[b] == 0u) {
        out[i] = x[i];
        return;
    }
    if (s == params.slots - 1u) {
        out[i] = params.sigma_max * noise[agent_row * 6u + 3u + d];
    } else if (s == params.observed - 1u) {
        out[i] = emitted[agent_row * 3u + d] + params.obs_sigma * noise[agent_row * 6u + d];
    } else if (s >= params.observed) {
        out[i] = turned(i + 3u - d, agent_row, d);
    } else {
        out[i] = x[i + 3u];
    }
}

// Component d of the state x[base .. base + 3] turned by agent_row's entry of `turns`; a
// zero turn copies it bit for bit.
fn turned(base: u32, agent_row: u32, d: u32) -> f32 {
    let pivot = vec2<f32>(turns[agent_row * 4u], turns[agent_row * 4u + 1u]);
    let angle = turns[agent_row * 4u + 2u];
    let heading_change = turns[agent_row * 4u + 3u];
    if (angle == 0.0 && heading_change == 0.0) {
        return x[base + d];
    }
    if (d == 2u) {
        return x[base + 2u] + heading_change;
    }
    let delta = vec2<f32>(x[base], x[base + 1u]) - pivot;
    let c = cos(angle);
    let s = sin(angle);
    if (d == 0u) {
        return pivot.x + (c * delta.x - s * delta.y);
    }
    return pivot.y + (s * delta.x + c * delta.y);
}
