// The online softmax (Milakov & Gimelshein 2018) over a stream of scores, shared by
// `attention.wgsl`, `agent_pairs.wgsl` and `residual_chain.wgsl`'s `attention_rows`: the engine
// prepends this file to all three (`road_gpu::shaders`), so that their results agree bit for
// bit. The caller keeps its own accumulators: for each score pushed it scales them by
// `correction` and adds `weight` times the key's value, then multiplies them by the inverse.
// No binding is read.

// The running maximum of the scores so far and the sum of their exps relative to it.
struct OnlineSoftmax {
    running_max: f32,
    denom: f32,
}

// What one pushed score asks of the accumulators: acc ← acc · correction + weight · value.
struct SoftmaxWeights {
    correction: f32,
    weight: f32,
}

// No score yet: the maximum below any finite score, so that the first push's correction is 0.
fn online_softmax_new() -> OnlineSoftmax {
    return OnlineSoftmax(-3.0e38, 0.0);
}

// Adds `score` (already scaled) to `state`.
fn online_softmax_push(state: ptr<function, OnlineSoftmax>, score: f32) -> SoftmaxWeights {
    let new_max = max((*state).running_max, score);
    let correction = exp((*state).running_max - new_max);
    let weight = exp(score - new_max);
    (*state).denom = (*state).denom * correction + weight;
    (*state).running_max = new_max;
    return SoftmaxWeights(correction, weight);
}

// 1 / Σ exp, or 0 where no score was pushed (a query with no valid key yields zeros).
fn online_softmax_inverse(state: OnlineSoftmax) -> f32 {
    return select(0.0, 1.0 / state.denom, state.denom > 0.0);
}
