// Token and map-point embeddings of the denoiser (docs/checkpoint.md, "The forward pass").

struct Params {
    scenes: u32,
    agents: u32,
    slots: u32,
    hidden: u32,
    sigma_data: f32,
    polylines: u32,
    points: u32,
    // The agent frame's anchor slot (ModelConfig::agent_frame), NO_FRAME without one.
    anchor_slot: u32,
    heading_scale: f32,   // state units per radian
    relative_scale: f32,  // multiplier of the relative features after c_in
    // The constant-velocity reference's scale (AgentFrame::residual_scale), 0 without one.
    residual_scale: f32,
    _pad1: u32,
}

const NO_FRAME: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;

// embed_tokens: h[b, a, w, :] = W_state · (c_in · x · valid) + b_state
//                              + W_noise · c_noise + b_noise + agent[b, a, :] + slot[w, :]
//                              (+ W_rel · rel + b_rel with an agent frame: rel = the state
//                              relative to the agent's anchor state, rotated into the anchor's
//                              heading, times c_in · relative_scale · valid · anchor_valid, and
//                              anchor_valid; model.rs `AnchorFrame`). With a constant-velocity
//                              reference the rotated displacement is y = s · (x − reference) at
//                              c_in(σ·s), and two more features: the last observed step, rotated,
//                              times s.
@group(0) @binding(1) var<storage, read> x: array<f32>;          // [B, A, W, 3]
@group(0) @binding(2) var<storage, read> sigma: array<f32>;      // [B, W]
@group(0) @binding(3) var<storage, read> valid: array<f32>;      // [B, A, W]
@group(0) @binding(4) var<storage, read> agent: array<f32>;      // [B, A, D] (embed_agent output)
@group(0) @binding(5) var<storage, read> w_state: array<f32>;    // [D, 3] then b_state [D], w_noise [D], b_noise [D], slot [W, D] (, w_rel [D, 4 or 6], b_rel [D])
@group(0) @binding(6) var<storage, read_write> h: array<f32>;    // [B, A, W, D]

@compute @workgroup_size(64)
fn embed_tokens(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = gid.x + gid.y * groups.x * 64u;
    let d_count = params.hidden;
    if (index >= params.scenes * params.agents * params.slots * d_count) {
        return;
    }
    let d = index % d_count;
    let token = index / d_count; // (b, a, w)
    let w = token % params.slots;
    let b = token / (params.slots * params.agents);
    let a = (token / params.slots) % params.agents;
    let s = sigma[b * params.slots + w];
    let sd = params.sigma_data;
    let c_in = inverseSqrt(s * s + sd * sd);
    let c_noise = log(s) * 0.25;
    let scale = c_in * valid[token];
    let xb = token * 3u;
    // Packed small weights: w_state [D, 3] | b_state [D] | w_noise [D] | b_noise [D] | slot [W, D].
    let b_state = 3u * d_count;
    let w_noise = b_state + d_count;
    let b_noise = w_noise + d_count;
    let slot = b_noise + d_count;
    var acc = w_state[3u * d] * x[xb] * scale + w_state[3u * d + 1u] * x[xb + 1u] * scale + w_state[3u * d + 2u] * x[xb + 2u] * scale;
    acc += w_state[b_state + d];
    acc += w_state[w_noise + d] * c_noise + w_state[b_noise + d];
    acc += agent[(b * params.agents + a) * d_count + d];
    acc += w_state[slot + w * d_count + d];
    if (params.anchor_slot != NO_FRAME) {
        let anchor = (token / params.slots) * params.slots + params.anchor_slot;
        let anchor_valid = valid[anchor];
        let xa = vec3<f32>(x[anchor * 3u], x[anchor * 3u + 1u], x[anchor * 3u + 2u]) * anchor_valid;
        let heading_rad = xa.z / params.heading_scale;
        let cs = cos(heading_rad);
        let sn = sin(heading_rad);
        var dx = x[xb] - xa.x;
        var dy = x[xb + 1u] - xa.y;
        var dh = x[xb + 2u] - xa.z;
        var k = c_in * params.relative_scale * valid[token] * anchor_valid;
        var width = 4u;
        var step_forward = 0.0;
        var step_left = 0.0;
        if (params.residual_scale > 0.0) {
            let rs = params.residual_scale;
            let previous = anchor - 1u;
            let both = valid[previous] * anchor_valid;
            let step_x = (x[anchor * 3u] - x[previous * 3u]) * both;
            let step_y = (x[anchor * 3u + 1u] - x[previous * 3u + 1u]) * both;
            let t = f32(w) - f32(params.anchor_slot);
            dx = (dx - t * step_x) * rs;
            dy = (dy - t * step_y) * rs;
            dh = dh * rs;
            let s_y = s * rs;
            k = inverseSqrt(s_y * s_y + sd * sd) * params.relative_scale * valid[token] * anchor_valid;
            width = 6u;
            step_forward = (cs * step_x + sn * step_y) * rs;
            step_left = (cs * step_y - sn * step_x) * rs;
        }
        let w_rel = slot + params.slots * d_count;
        let b_rel = w_rel + width * d_count;
        let row = w_rel + width * d;
        acc += w_state[row] * (cs * dx + sn * dy) * k
            + w_state[row + 1u] * (cs * dy - sn * dx) * k
            + w_state[row + 2u] * dh * k
            + w_state[row + 3u] * anchor_valid
            + w_state[b_rel + d];
        if (width == 6u) {
            acc += w_state[row + 4u] * step_forward + w_state[row + 5u] * step_left;
        }
    }
    h[index] = acc;
}
