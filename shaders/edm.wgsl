// EDM preconditioning per window slot (Karras et al. 2022; math doc, "Noise schedule").
//
// For every noise level σ (one per scene and window slot):
//   c_skip  = σd² / (σ² + σd²)
//   c_out   = σ·σd / √(σ² + σd²)
//   c_in    = 1 / √(σ² + σd²)
//   c_noise = ln(σ) / 4
// σ = 0 marks a clean slot: its c_noise uses σ_min instead, so that the embedding stays finite.

struct Params {
    count: u32,
    sigma_data: f32,
    sigma_min: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> sigma: array<f32>;          // [count]
@group(0) @binding(2) var<storage, read_write> coeffs: array<vec4<f32>>; // [count] (c_skip, c_out, c_in, c_noise)

@compute @workgroup_size(64)
fn precondition(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.count) {
        return;
    }
    let s = sigma[i];
    let sd = params.sigma_data;
    let denom = s * s + sd * sd;
    let inv_root = inverseSqrt(denom);
    coeffs[i] = vec4<f32>(sd * sd / denom, s * sd * inv_root, inv_root, log(max(s, params.sigma_min)) * 0.25);
}
