// Elementwise steps of the denoiser: the output preconditioning.

struct Params {
    count: u32,      // tokens
    slots: u32,      // W
    per_slot: u32,   // elements per (scene, slot) row of x: 3 for states
    agents: u32,     // A
    sigma_data: f32,
    anchor_slot: u32, // precondition_output: the agent frame's anchor slot, or NO_FRAME
    heading_scale: f32, // precondition_output with an agent frame: state units per radian
    residual_scale: f32, // precondition_output: the constant-velocity reference's scale, 0 without
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
    _pad4: u32,
}

const NO_FRAME: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;     // [B, A, W, 3]
@group(0) @binding(2) var<storage, read> f: array<f32>;     // F [B, A, W, 3]
@group(0) @binding(3) var<storage, read> sigma: array<f32>; // [B, W]
@group(0) @binding(4) var<storage, read> valid: array<f32>; // [B, A, W]
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

fn flat_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 64u;
}

// D(x; σ) of every token: `precondition_token` of `gather_token` (common/precondition.wgsl,
// prepended); one invocation per token (`count` tokens).
@compute @workgroup_size(64)
fn precondition_output(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let token = flat_index(gid, groups); // (b, a, w)
    if (token >= params.count) {
        return;
    }
    let t = gather_token(token, vec3<f32>(f[token * 3u], f[token * 3u + 1u], f[token * 3u + 2u]));
    let d = precondition_token(t, params.sigma_data, params.heading_scale, params.residual_scale);
    out[token * 3u] = d.x;
    out[token * 3u + 1u] = d.y;
    out[token * 3u + 2u] = d.z;
}
