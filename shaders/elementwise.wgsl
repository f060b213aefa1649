// Elementwise steps of the denoiser: the output preconditioning.

struct Params {
    count: u32,      // elements of the main operand
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

// D = c_skip · x + c_out · F · valid. a = x [B, A, W, 3], b = F [B, A, W, 3], c = σ [B, W],
// e = valid [B, A, W]. With an agent frame, F's (x, y) is first rotated from the anchor's
// heading back to the scene frame (model.rs `AnchorFrame::rotate_to_scene`). With a
// constant-velocity reference r (the anchor moved by the last observed step per slot) and
// scale s: D = r + (c_skip(σs) · s(x − r) + c_out(σs) · F · valid) / s; an agent without an
// anchor keeps r = 0, s = 1.
@compute @workgroup_size(64)
fn precondition_output(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    if (i >= params.count) {
        return;
    }
    let token = i / 3u; // (b, a, w)
    let w = token % params.slots;
    let scene = token / (params.slots * params.agents);
    var s = c[scene * params.slots + w];
    let sd = params.sigma_data;
    var f = b[i];
    let component = i % 3u;
    var reference = 0.0;
    var scale = 1.0;
    if (params.anchor_slot != NO_FRAME) {
        let anchor = (token / params.slots) * params.slots + params.anchor_slot;
        let anchor_valid = e[anchor];
        let heading_rad = a[anchor * 3u + 2u] * anchor_valid / params.heading_scale;
        let cs = cos(heading_rad);
        let sn = sin(heading_rad);
        if (component < 2u) {
            let f0 = b[token * 3u];
            let f1 = b[token * 3u + 1u];
            f = select(sn * f0 + cs * f1, cs * f0 - sn * f1, component == 0u);
        }
        if (params.residual_scale > 0.0 && anchor_valid > 0.0) {
            scale = params.residual_scale;
            reference = a[anchor * 3u + component];
            if (component < 2u) {
                let previous = anchor - 1u;
                let step = (a[anchor * 3u + component] - a[previous * 3u + component]) * e[previous];
                reference += (f32(w) - f32(params.anchor_slot)) * step;
            }
        }
    }
    s = s * scale;
    let denom = s * s + sd * sd;
    let y = (a[i] - reference) * scale;
    out[i] = reference + (sd * sd / denom * y + s * sd * inverseSqrt(denom) * f * e[token]) / scale;
}
