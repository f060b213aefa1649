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
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read> c: array<f32>;
@group(0) @binding(4) var<storage, read> e: array<f32>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

fn flat_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 64u;
}

// D(x; σ) of every token: `precondition_token` (common/precondition.wgsl, prepended) over
// a = x [B, A, W, 3], b = F [B, A, W, 3], c = σ [B, W], e = valid [B, A, W]; one invocation per
// token (`count` tokens).
@compute @workgroup_size(64)
fn precondition_output(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let token = flat_index(gid, groups); // (b, a, w)
    if (token >= params.count) {
        return;
    }
    let w = token % params.slots;
    let scene = token / (params.slots * params.agents);
    var t: PreconditionToken;
    t.x = vec3<f32>(a[token * 3u], a[token * 3u + 1u], a[token * 3u + 2u]);
    t.f = vec3<f32>(b[token * 3u], b[token * 3u + 1u], b[token * 3u + 2u]);
    t.sigma = c[scene * params.slots + w];
    t.valid = e[token];
    t.frame = params.anchor_slot != NO_FRAME;
    t.anchor = vec3<f32>(0.0);
    t.anchor_valid = 0.0;
    t.previous = vec3<f32>(0.0);
    t.previous_valid = 0.0;
    t.slots_from_anchor = 0.0;
    if (t.frame) {
        let anchor = (token / params.slots) * params.slots + params.anchor_slot;
        // Read only with a constant-velocity reference, whose anchor slot is ≥ 1; slot 0
        // reads itself rather than past the buffer.
        let previous = select(anchor, anchor - 1u, params.anchor_slot > 0u);
        t.anchor = vec3<f32>(a[anchor * 3u], a[anchor * 3u + 1u], a[anchor * 3u + 2u]);
        t.anchor_valid = e[anchor];
        t.previous = vec3<f32>(a[previous * 3u], a[previous * 3u + 1u], a[previous * 3u + 2u]);
        t.previous_valid = e[previous];
        t.slots_from_anchor = f32(w) - f32(params.anchor_slot);
    }
    let d = precondition_token(t, params.sigma_data, params.heading_scale, params.residual_scale);
    out[token * 3u] = d.x;
    out[token * 3u + 1u] = d.y;
    out[token * 3u + 2u] = d.z;
}
