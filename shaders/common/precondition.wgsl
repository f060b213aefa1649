// The denoiser's output preconditioning of one token (docs/checkpoint.md, last step), shared by
// `elementwise.wgsl`'s `precondition_output` and `residual_chain.wgsl`'s head: the engine
// prepends this file to both (`road_gpu::shaders`). `precondition_token` reads no binding;
// `gather_token` reads the including kernel's `x [B, A, W, 3]`, `sigma [B, W]`, `valid
// [B, A, W]` and its params' `slots`, `agents`, `anchor_slot` and `NO_FRAME`.

// D = c_skip · x + c_out · F · valid, with σ the token's slot's. With an agent frame (`frame`),
// F's (x, y) is first rotated from the anchor's heading back to the scene frame (model.rs
// `AnchorFrame::rotate_to_scene`). With a constant-velocity reference r (the anchor moved by
// the last observed step per slot) and scale s > 0: D = r + (c_skip(σs) · s(x − r) +
// c_out(σs) · F · valid) / s; an agent without an anchor keeps r = 0, s = 1.
struct PreconditionToken {
    x: vec3<f32>,          // the token's state
    f: vec3<f32>,          // the network's output F, in the anchor frame when `frame`
    sigma: f32,            // σ of the token's slot
    valid: f32,            // the token's validity
    anchor: vec3<f32>,     // the anchor slot's state of the same agent
    anchor_valid: f32,
    previous: vec3<f32>,   // the slot before the anchor
    previous_valid: f32,
    slots_from_anchor: f32, // the token's slot − the anchor slot
    frame: bool,           // the model has an agent frame
}

fn precondition_token(t: PreconditionToken, sigma_data: f32, heading_scale: f32, residual_scale: f32) -> vec3<f32> {
    var f = t.f;
    var reference = vec3<f32>(0.0);
    var scale = 1.0;
    if (t.frame) {
        let heading_rad = t.anchor.z * t.anchor_valid / heading_scale;
        let cs = cos(heading_rad);
        let sn = sin(heading_rad);
        f = vec3<f32>(cs * t.f.x - sn * t.f.y, sn * t.f.x + cs * t.f.y, t.f.z);
        if (residual_scale > 0.0 && t.anchor_valid > 0.0) {
            scale = residual_scale;
            let step = (t.anchor.xy - t.previous.xy) * t.previous_valid;
            reference = vec3<f32>(t.anchor.xy + t.slots_from_anchor * step, t.anchor.z);
        }
    }
    let s = t.sigma * scale;
    let sd = sigma_data;
    let denom = s * s + sd * sd;
    let y = (t.x - reference) * scale;
    return reference + (sd * sd / denom * y + s * sd * inverseSqrt(denom) * f * t.valid) / scale;
}

// Token `token`'s inputs, with F the network's output for it.
fn gather_token(token: u32, f: vec3<f32>) -> PreconditionToken {
    let w = token % params.slots;
    let scene = token / (params.slots * params.agents);
    var t: PreconditionToken;
    t.x = vec3<f32>(x[token * 3u], x[token * 3u + 1u], x[token * 3u + 2u]);
    t.f = f;
    t.sigma = sigma[scene * params.slots + w];
    t.valid = valid[token];
    t.frame = params.anchor_slot != NO_FRAME;
    t.anchor = vec3<f32>(0.0);
    t.anchor_valid = 0.0;
    t.previous = vec3<f32>(0.0);
    t.previous_valid = 0.0;
    t.slots_from_anchor = 0.0;
    if (t.frame) {
        let anchor = (token / params.slots) * params.slots + params.anchor_slot;
        // Read only with a constant-velocity reference, whose anchor slot is ≥ 1; slot 0 reads
        // itself rather than past the buffer.
        let previous = select(anchor, anchor - 1u, params.anchor_slot > 0u);
        t.anchor = vec3<f32>(x[anchor * 3u], x[anchor * 3u + 1u], x[anchor * 3u + 2u]);
        t.anchor_valid = valid[anchor];
        t.previous = vec3<f32>(x[previous * 3u], x[previous * 3u + 1u], x[previous * 3u + 2u]);
        t.previous_valid = valid[previous];
        t.slots_from_anchor = f32(w) - f32(params.anchor_slot);
    }
    return t;
}
