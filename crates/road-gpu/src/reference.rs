//! CPU references of the kernels: plain loops in f64, the meaning each kernel must match.

use crate::kernels::agent_pairs::PairAttentionParams;
use crate::kernels::attention::AttentionParams;

/// `y[r, o] = act(Σ_k x[r, k] · w[o, k] + b[o])`.
pub fn linear(
    x: &[f32],
    w: &[f32],
    b: &[f32],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    relu: bool,
) -> Vec<f32> {
    let mut y = vec![0.0f32; rows * out_dim];
    for r in 0..rows {
        for o in 0..out_dim {
            let mut acc = f64::from(b[o]);
            for k in 0..in_dim {
                acc += f64::from(x[r * in_dim + k]) * f64::from(w[o * in_dim + k]);
            }
            y[r * out_dim + o] = if relu {
                acc.max(0.0) as f32
            } else {
                acc as f32
            };
        }
    }
    y
}

/// Layer norm with the biased variance.
pub fn layer_norm(
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    rows: usize,
    dim: usize,
    eps: f32,
) -> Vec<f32> {
    let mut y = vec![0.0f32; rows * dim];
    for r in 0..rows {
        let row = &x[r * dim..(r + 1) * dim];
        let mean = row.iter().map(|&v| f64::from(v)).sum::<f64>() / dim as f64;
        let var = row
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / dim as f64;
        let inv = 1.0 / (var + f64::from(eps)).sqrt();
        for k in 0..dim {
            y[r * dim + k] = ((f64::from(row[k]) - mean) * inv * f64::from(gamma[k])
                + f64::from(beta[k])) as f32;
        }
    }
    y
}

/// Softmax attention per (group, head, query) over valid keys; zeros where no key is valid.
pub fn attention(
    p: &AttentionParams,
    q: &[f32],
    k: &[f32],
    v: &[f32],
    key_valid: &[f32],
) -> Vec<f32> {
    let d = (p.heads * p.head_dim) as usize;
    let hd = p.head_dim as usize;
    let mut out = vec![0.0f32; q.len()];
    for g in 0..p.groups {
        for h in 0..p.heads as usize {
            for i in 0..p.queries {
                let qb = p.q_layout.row(g, i) as usize * d + h * hd;
                let mut scores = Vec::new();
                for j in 0..p.keys {
                    if key_valid[p.mask_layout.row(g, j) as usize] == 0.0 {
                        continue;
                    }
                    let kb = p.kv_layout.row(g, j) as usize * d + h * hd;
                    let s: f64 = (0..hd)
                        .map(|c| f64::from(q[qb + c]) * f64::from(k[kb + c]))
                        .sum::<f64>()
                        * f64::from(p.scale);
                    scores.push((kb, s));
                }
                if scores.is_empty() {
                    continue;
                }
                let m = scores.iter().map(|s| s.1).fold(f64::NEG_INFINITY, f64::max);
                let z: f64 = scores.iter().map(|s| (s.1 - m).exp()).sum();
                for c in 0..hd {
                    let acc: f64 = scores
                        .iter()
                        .map(|&(kb, s)| (s - m).exp() / z * f64::from(v[kb + c]))
                        .sum();
                    out[qb + c] = acc as f32;
                }
            }
        }
    }
    out
}

/// Agent attention with pair features: per (scene, slot) group, head and query agent, softmax
/// over valid key agents of `(q·k + (K_hᵀ q)·r) · scale`, output `Σ a (v + V_h r)`, with `r` of
/// `road_model::agent_pairs::pair_features` in the query agent's anchor frame (its state at
/// the anchor slot times its flag there, as `anchors_of`). Zeros where no key is valid.
#[allow(clippy::too_many_arguments)]
pub fn pair_attention(
    p: &PairAttentionParams,
    q: &[f32],
    k: &[f32],
    v: &[f32],
    valid: &[f32],
    states: &[f32],
    pair_k: &[f32],
    pair_v: &[f32],
) -> Vec<f32> {
    use road_model::agent_pairs::{PAIR_FEATURES as F, pair_features};
    let (a, w) = (p.agents as usize, p.slots as usize);
    let hd = p.head_dim as usize;
    let d = p.heads as usize * hd;
    let scenes = p.groups as usize / w;
    let anchors = road_model::agent_map::anchors_of(
        states,
        valid,
        w,
        p.anchor_slot as usize,
        p.heading_scale,
    );
    let row = |scene: usize, agent: usize, slot: usize| (scene * a + agent) * w + slot;
    let mut out = vec![0.0f32; q.len()];
    for scene in 0..scenes {
        for slot in 0..w {
            for h in 0..p.heads as usize {
                for i in 0..a {
                    let qi = row(scene, i, slot);
                    let qb = qi * d + h * hd;
                    let q_pair: Vec<f64> = (0..F)
                        .map(|f| {
                            (0..hd)
                                .map(|c| {
                                    f64::from(q[qb + c]) * f64::from(pair_k[(h * hd + c) * F + f])
                                })
                                .sum()
                        })
                        .collect();
                    let mut scored = Vec::new();
                    for j in 0..a {
                        let kj = row(scene, j, slot);
                        if valid[kj] == 0.0 {
                            continue;
                        }
                        let r = pair_features(
                            &states[3 * qi..3 * qi + 3],
                            anchors[scene * a + i],
                            &states[3 * kj..3 * kj + 3],
                            p.scales(),
                        );
                        let kb = kj * d + h * hd;
                        let s = ((0..hd)
                            .map(|c| f64::from(q[qb + c]) * f64::from(k[kb + c]))
                            .sum::<f64>()
                            + (0..F).map(|f| q_pair[f] * f64::from(r[f])).sum::<f64>())
                            * f64::from(p.scale);
                        scored.push((kb, s, r));
                    }
                    if scored.is_empty() {
                        continue;
                    }
                    let m = scored.iter().map(|s| s.1).fold(f64::NEG_INFINITY, f64::max);
                    let z: f64 = scored.iter().map(|s| (s.1 - m).exp()).sum();
                    let mut mean_pair = [0.0f64; F];
                    for (_, s, r) in &scored {
                        for f in 0..F {
                            mean_pair[f] += (s - m).exp() / z * f64::from(r[f]);
                        }
                    }
                    for c in 0..hd {
                        let value: f64 = scored
                            .iter()
                            .map(|&(kb, s, _)| (s - m).exp() / z * f64::from(v[kb + c]))
                            .sum();
                        let offset: f64 = (0..F)
                            .map(|f| f64::from(pair_v[(h * hd + c) * F + f]) * mean_pair[f])
                            .sum();
                        out[qb + c] = (value + offset) as f32;
                    }
                }
            }
        }
    }
    out
}
