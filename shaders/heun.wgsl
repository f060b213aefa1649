// The samplers' updates with a per-slot σ (math doc, "Sampling"). Each scene has its own
// σ_cur[W] and σ_next[W]. Slots whose σ does not change are left untouched; a slot landing on
// σ = 0 keeps the Euler result.
// Deterministic Heun (EDM Algorithm 1):
//   heun_euler:   x_e = x + (σ_next − σ)·(x − D₁)/σ
//   heun_correct: x'  = x + (σ_next − σ)·½·((x − D₁)/σ + (x_e − D₂)/σ_next)  where σ_next > 0
// with D₁ = D(x; σ) and D₂ = D(x_e; σ_next).
// The multistep sampler (DPM-Solver++(2M), road_sched::Sampler::Multistep), after heun_euler:
//   multistep_correct: x_e += γ·(D₁ − D_prev)  with γ[B, W] from the host (0: no correction)
// where D_prev is each slot's previous estimate, kept by the engine.

struct Params {
    count: u32,   // B · A · W · 3
    slots: u32,   // W
    agents: u32,  // A
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;          // [B, A, W, 3] state before the step
@group(0) @binding(2) var<storage, read> first: array<f32>;      // D₁ = D(x; σ_cur)
@group(0) @binding(3) var<storage, read> sigma_cur: array<f32>;  // [B, W]
@group(0) @binding(4) var<storage, read> sigma_next: array<f32>; // [B, W]
@group(0) @binding(5) var<storage, read_write> out: array<f32>;  // x_e (euler); x_e in, x' out (correct)
@group(0) @binding(6) var<storage, read> second: array<f32>;     // D₂ = D(x_e; σ_next) (correct only)
@group(0) @binding(7) var<storage, read> previous: array<f32>;   // D_prev [B, A, W, 3] (multistep only)
@group(0) @binding(8) var<storage, read> gamma: array<f32>;      // [B, W] (multistep only)

fn sigmas(i: u32) -> vec2<f32> {
    let token = i / 3u;
    let w = token % params.slots;
    let scene = token / (params.slots * params.agents);
    return vec2<f32>(sigma_cur[scene * params.slots + w], sigma_next[scene * params.slots + w]);
}

@compute @workgroup_size(64)
fn heun_euler(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if (i >= params.count) {
        return;
    }
    let s = sigmas(i);
    if (s.x == s.y) {
        out[i] = x[i];
        return;
    }
    out[i] = x[i] + (s.y - s.x) * (x[i] - first[i]) / s.x;
}

@compute @workgroup_size(64)
fn heun_correct(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if (i >= params.count) {
        return;
    }
    let s = sigmas(i);
    if (s.x == s.y || s.y == 0.0) {
        return; // unchanged, or landing on 0: out already holds x_e
    }
    let slope1 = (x[i] - first[i]) / s.x;
    let slope2 = (out[i] - second[i]) / s.y;
    out[i] = x[i] + (s.y - s.x) * 0.5 * (slope1 + slope2);
}

@compute @workgroup_size(64)
fn multistep_correct(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if (i >= params.count) {
        return;
    }
    let token = i / 3u;
    let w = token % params.slots;
    let scene = token / (params.slots * params.agents);
    let g = gamma[scene * params.slots + w];
    if (g != 0.0) {
        out[i] = out[i] + g * (first[i] - previous[i]);
    }
}
