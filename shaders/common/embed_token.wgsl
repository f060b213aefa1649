// One value of the denoiser's token embedding (docs/checkpoint.md, "The forward pass"), shared
// by `embed.wgsl`'s `embed_tokens` and `residual_chain.wgsl`'s `embed_chain`: the engine prepends
// this file to both (`road_gpu::shaders`). `embed_value` reads the including kernel's `x [B, A,
// W, 3]`, `sigma [B, W]`, `valid [B, A, W]`, its `NO_FRAME`, and two functions it defines:
// `embed_weight(i)`, the packed small weights (w_state [D, 3] | b_state [D] | w_noise [D] |
// b_noise [D] | slot [W, D] (| w_rel [D, 4 or 6] | b_rel [D])), and `agent_embedding(i)`, the
// agents' `embed_agent` output [B, A, D].
//
// h[b, a, w, d] = W_state · (c_in · x · valid) + b_state + W_noise · c_noise + b_noise
//                 + agent[b, a, :] + slot[w, :]
//                 (+ W_rel · rel + b_rel with an agent frame: rel = the state relative to the
//                 agent's anchor state, rotated into the anchor's heading, times c_in ·
//                 relative_scale · valid · anchor_valid, and anchor_valid; model.rs
//                 `AnchorFrame`). With a constant-velocity reference the rotated displacement is
//                 y = s · (x − reference) at c_in(σ·s), and two more features: the last
//                 observed step, rotated, times s.

struct EmbedShape {
    agents: u32,         // A
    slots: u32,          // W
    hidden: u32,         // D
    sigma_data: f32,
    anchor_slot: u32,    // the agent frame's anchor slot, NO_FRAME without one
    heading_scale: f32,  // state units per radian
    relative_scale: f32, // multiplier of the relative features after c_in
    residual_scale: f32, // the constant-velocity reference's scale, 0 without one
}

// Value d of token `token` = (b, a, w) of the batch.
fn embed_value(shape: EmbedShape, token: u32, d: u32) -> f32 {
    let d_count = shape.hidden;
    let w = token % shape.slots;
    let b = token / (shape.slots * shape.agents);
    let a = (token / shape.slots) % shape.agents;
    let s = sigma[b * shape.slots + w];
    let sd = shape.sigma_data;
    let c_in = inverseSqrt(s * s + sd * sd);
    let c_noise = log(s) * 0.25;
    let scale = c_in * valid[token];
    let xb = token * 3u;
    // Packed small weights: w_state [D, 3] | b_state [D] | w_noise [D] | b_noise [D] | slot [W, D].
    let b_state = 3u * d_count;
    let w_noise = b_state + d_count;
    let b_noise = w_noise + d_count;
    let slot = b_noise + d_count;
    var acc = embed_weight(3u * d) * x[xb] * scale + embed_weight(3u * d + 1u) * x[xb + 1u] * scale + embed_weight(3u * d + 2u) * x[xb + 2u] * scale;
    acc += embed_weight(b_state + d);
    acc += embed_weight(w_noise + d) * c_noise + embed_weight(b_noise + d);
    acc += agent_embedding((b * shape.agents + a) * d_count + d);
    acc += embed_weight(slot + w * d_count + d);
    if (shape.anchor_slot != NO_FRAME) {
        let anchor = (token / shape.slots) * shape.slots + shape.anchor_slot;
        let anchor_valid = valid[anchor];
        let xa = vec3<f32>(x[anchor * 3u], x[anchor * 3u + 1u], x[anchor * 3u + 2u]) * anchor_valid;
        let heading_rad = xa.z / shape.heading_scale;
        let cs = cos(heading_rad);
        let sn = sin(heading_rad);
        var dx = x[xb] - xa.x;
        var dy = x[xb + 1u] - xa.y;
        var dh = x[xb + 2u] - xa.z;
        var k = c_in * shape.relative_scale * valid[token] * anchor_valid;
        var width = 4u;
        var step_forward = 0.0;
        var step_left = 0.0;
        if (shape.residual_scale > 0.0) {
            let rs = shape.residual_scale;
            let previous = anchor - 1u;
            let both = valid[previous] * anchor_valid;
            let step_x = (x[anchor * 3u] - x[previous * 3u]) * both;
            let step_y = (x[anchor * 3u + 1u] - x[previous * 3u + 1u]) * both;
            let t = f32(w) - f32(shape.anchor_slot);
            dx = (dx - t * step_x) * rs;
            dy = (dy - t * step_y) * rs;
            dh = dh * rs;
            let s_y = s * rs;
            k = inverseSqrt(s_y * s_y + sd * sd) * shape.relative_scale * valid[token] * anchor_valid;
            width = 6u;
            step_forward = (cs * step_x + sn * step_y) * rs;
            step_left = (cs * step_y - sn * step_x) * rs;
        }
        let w_rel = slot + shape.slots * d_count;
        let b_rel = w_rel + width * d_count;
        let row = w_rel + width * d;
        acc += embed_weight(row) * (cs * dx + sn * dy) * k
            + embed_weight(row + 1u) * (cs * dy - sn * dx) * k
            + embed_weight(row + 2u) * dh * k
            + embed_weight(row + 3u) * anchor_valid
            + embed_weight(b_rel + d);
        if (width == 6u) {
            acc += embed_weight(row + 4u) * step_forward + embed_weight(row + 5u) * step_left;
        }
    }
    return acc;
}
