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

@group(0) @binding(1) var<storage, read> x: array<f32>;          // [B, A, W, 3]
@group(0) @binding(2) var<storage, read> sigma: array<f32>;      // [B, W]
@group(0) @binding(3) var<storage, read> valid: array<f32>;      // [B, A, W]
@group(0) @binding(4) var<storage, read> agent: array<f32>;      // [B, A, D] (embed_agent output)
@group(0) @binding(5) var<storage, read> w_state: array<f32>;    // [D, 3] then b_state [D], w_noise [D], b_noise [D], slot [W, D] (, w_rel [D, 4 or 6], b_rel [D])
@group(0) @binding(6) var<storage, read_write> h: array<f32>;    // [B, A, W, D]

fn embed_weight(i: u32) -> f32 {
    return w_state[i];
}

fn agent_embedding(i: u32) -> f32 {
    return agent[i];
}

// embed_tokens: h [B, A, W, D], one value per invocation (common/embed_token.wgsl, prepended).
@compute @workgroup_size(64)
fn embed_tokens(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = gid.x + gid.y * groups.x * 64u;
    let d_count = params.hidden;
    if (index >= params.scenes * params.agents * params.slots * d_count) {
        return;
    }
    let shape = EmbedShape(
        params.agents,
        params.slots,
        d_count,
        params.sigma_data,
        params.anchor_slot,
        params.heading_scale,
        params.relative_scale,
        params.residual_scale,
    );
    h[index] = embed_value(shape, index / d_count, index % d_count);
}
