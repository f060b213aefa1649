// The features of a pair of agents (road_model::agent_pairs::pair_features), shared by
// `agent_pairs.wgsl`'s `pair_attention` and `residual_chain.wgsl`'s attending chain: the engine
// prepends this file to both (`road_gpu::shaders`). `pair_features_of` reads the states through
// the including kernel's `pair_state(i)` ([B, A, W, 3] by float).

const PAIR_FEATURES: u32 = 6u;

// Length scales in state units (road_model::agent_pairs::PairScales).
struct PairScales {
    heading_scale: f32,
    direction: f32,
    near: f32,
    far: f32,
}

// Key token `key` seen from query token `query`, in the query agent's anchor frame (its
// heading's cosine and sine).
fn pair_features_of(query: u32, key: u32, cos_a: f32, sin_a: f32, scales: PairScales) -> array<f32, 6> {
    let dx = pair_state(key * 3u) - pair_state(query * 3u);
    let dy = pair_state(key * 3u + 1u) - pair_state(query * 3u + 1u);
    let forward = dx * cos_a + dy * sin_a;
    let left = dy * cos_a - dx * sin_a;
    let distance = sqrt(forward * forward + left * left);
    let squash = 1.0 / (distance + scales.direction);
    let turn = (pair_state(key * 3u + 2u) - pair_state(query * 3u + 2u)) / scales.heading_scale;
    return array<f32, 6>(
        forward * squash,
        left * squash,
        exp(-distance / scales.near),
        exp(-distance / scales.far),
        cos(turn),
        sin(turn),
    );
}
