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

/// The fused linear layer of `linear.wgsl`: `y + act(n(x) · wᵀ + b)` with `n` the layer norm
/// of [`layer_norm`] (`norm`: γ, β, eps) or the identity, `y` the residual (`[rows, out]`, or
/// none: zeros). The output split into parts is a layout only, checked by its test.
#[allow(clippy::too_many_arguments)]
pub fn linear_fused(
    x: &[f32],
    w: &[f32],
    b: &[f32],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    relu: bool,
    norm: Option<(&[f32], &[f32], f32)>,
    residual: Option<&[f32]>,
) -> Vec<f32> {
    let normed;
    let x = match norm {
        Some((gamma, beta, eps)) => {
            normed = layer_norm(x, gamma, beta, rows, in_dim, eps);
            &normed[..]
        }
        None => x,
    };
    let mut y = linear(x, w, b, rows, in_dim, out_dim, relu);
    if let Some(residual) = residual {
        for (y, r) in y.iter_mut().zip(residual) {
            *y = (f64::from(*y) + f64::from(*r)) as f32;
        }
    }
    y
}

/// The f16 linear layer's reference (`linear_f16.wgsl`, `linear_coop.wgsl`), per output of
/// `[rows, out]` (`w`, `b` with any layer norm already folded in; `norm_eps` standardises the
/// rows first; `residual` is added last).
#[derive(Debug, Clone)]
pub struct LinearF16Reference {
    /// The kernels' meaning: inputs (standardised) and weights rounded to f16, sums in f64.
    pub rounded: Vec<f32>,
    /// The same layer in exact arithmetic, nothing rounded: what the f32 path computes.
    pub exact: Vec<f32>,
    /// How far the f16 layer may be from `exact`: each of the two roundings moves a factor by
    /// at most 2⁻¹¹ of it, so a product by at most about 2⁻¹⁰ of it, and the sum by at most
    /// `2⁻¹⁰ · Σ_k |n(x)_k · w_k|` (a bound, not an estimate; ×1.01 for the f32 statistics).
    pub bound: Vec<f32>,
}

/// See [`LinearF16Reference`].
#[allow(clippy::too_many_arguments)]
pub fn linear_f16(
    x: &[f32],
    w: &[f32],
    b: &[f32],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    relu: bool,
    norm_eps: Option<f32>,
    residual: Option<&[f32]>,
) -> LinearF16Reference {
    let round = |v: f64| f64::from(half::f16::from_f64(v).to_f32());
    let normed: Vec<f64> = match norm_eps {
        Some(eps) => {
            let ones = vec![1.0f32; in_dim];
            let zeros = vec![0.0f32; in_dim];
            layer_norm(x, &ones, &zeros, rows, in_dim, eps)
                .into_iter()
                .map(f64::from)
                .collect()
        }
        None => x.iter().map(|&v| f64::from(v)).collect(),
    };
    let mut out = LinearF16Reference {
        rounded: vec![0.0; rows * out_dim],
        exact: vec![0.0; rows * out_dim],
        bound: vec![0.0; rows * out_dim],
    };
    let finish = |v: f64, i: usize| {
        let v = if relu { v.max(0.0) } else { v };
        (v + residual.map_or(0.0, |r| f64::from(r[i]))) as f32
    };
    for r in 0..rows {
        for o in 0..out_dim {
            let (mut rounded, mut exact, mut magnitude) = (f64::from(b[o]), f64::from(b[o]), 0.0);
            for k in 0..in_dim {
                let (xv, wv) = (normed[r * in_dim + k], f64::from(w[o * in_dim + k]));
                rounded += round(xv) * round(wv);
                exact += xv * wv;
                magnitude += (xv * wv).abs();
            }
            let i = r * out_dim + o;
            out.rounded[i] = finish(rounded, i);
            out.exact[i] = finish(exact, i);
            out.bound[i] = (1.01 * magnitude * 2f64.powi(-10)) as f32;
        }
    }
    out
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

/// The map's polyline encoder of `polyline.wgsl` over `n` polylines of `q` points:
/// `layer_norm(max_q (mix_w · relu(W_point · point + b_point + point_embedding[q]) + mix_b))`,
/// `embed` packed as W_point `[D, 2]` | b_point `[D]` | point embedding `[Q, D]`.
#[allow(clippy::too_many_arguments)]
pub fn encode_polylines(
    points: &[f32],
    embed: &[f32],
    mix_w: &[f32],
    mix_b: &[f32],
    gamma: &[f32],
    beta: &[f32],
    (n, q, d): (usize, usize, usize),
    eps: f32,
) -> Vec<f32> {
    let (b_point, pe) = (2 * d, 3 * d);
    let mut embedded = vec![0.0f32; n * q * d];
    for (point, row) in embedded.chunks_exact_mut(d).enumerate() {
        let (x, y) = (
            f64::from(points[2 * point]),
            f64::from(points[2 * point + 1]),
        );
        for (k, e) in row.iter_mut().enumerate() {
            let v = f64::from(embed[2 * k]) * x
                + f64::from(embed[2 * k + 1]) * y
                + f64::from(embed[b_point + k])
                + f64::from(embed[pe + (point % q) * d + k]);
            *e = v.max(0.0) as f32;
        }
    }
    let mixed = linear(&embedded, mix_w, mix_b, n * q, d, d, false);
    let pooled: Vec<f32> = (0..n * d)
        .map(|i| {
            let (poly, o) = (i / d, i % d);
            (0..q)
                .map(|p| mixed[(poly * q + p) * d + o])
                .fold(f32::NEG_INFINITY, f32::max)
        })
        .collect();
    layer_norm(&pooled, gamma, beta, n, d, eps)
}

/// Softmax attention per (group, head, query) over valid keys, packed scenes kept apart as
/// `p.scene_mode` says (`agent_scene`, [`crate::kernels::attention::SceneMode`]); zeros where
/// no key is valid.
pub fn attention(
    p: &AttentionParams,
    q: &[f32],
    k: &[f32],
    v: &[f32],
    key_valid: &[f32],
    agent_scene: &[u32],
) -> Vec<f32> {
    use crate::kernels::attention::SceneMode;
    let d = (p.heads * p.head_dim) as usize;
    let hd = p.head_dim as usize;
    let mode = p.scene_mode;
    let scene_of = |layout: &crate::kernels::attention::TokenLayout, g: u32, token: u32| {
        agent_scene[((g / layout.inner_count) * p.scene_agents + token) as usize]
    };
    let mut out = vec![0.0f32; q.len()];
    for g in 0..p.groups {
        let kg = if mode == SceneMode::KeysOfTheAgentsScene as u32 {
            agent_scene[g as usize]
        } else {
            g
        };
        for h in 0..p.heads as usize {
            for i in 0..p.queries {
                let qb = p.q_layout.row(g, i) as usize * d + h * hd;
                let mut scores = Vec::new();
                for j in 0..p.keys {
                    if key_valid[p.mask_layout.row(kg, j) as usize] == 0.0 {
                        continue;
                    }
                    if mode == SceneMode::AgentsOfOneScene as u32
                        && scene_of(&p.kv_layout, g, j) != scene_of(&p.q_layout, g, i)
                    {
                        continue;
                    }
                    let kb = p.kv_layout.row(kg, j) as usize * d + h * hd;
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
/// the anchor slot times its flag there, as `anchors_of`). Keys of another scene
/// (`agent_scene [B·A]`, a packed batch's) carry no weight. Zeros where no key is valid.
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
    agent_scene: &[u32],
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
                        if valid[kj] == 0.0
                            || agent_scene[scene * a + j] != agent_scene[scene * a + i]
                        {
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

/// A linear layer's weights `[out, in]` and bias `[out]`.
pub type Layer<'a> = (&'a [f32], &'a [f32]);

/// The residual chain of `residual_chain.wgsl` over `rows` rows of width `d`:
/// `h₁ = h + att · W_oᵀ + b_o`; with `mlp` (`W_1 [M, D]`, `b_1`, `W_2 [D, M]`, `b_2`),
/// `h₂ = h₁ + relu(n(h₁) · W_1ᵀ + b_1) · W_2ᵀ + b_2`; with `next` (`[out, D]`, `[out]`), its
/// outputs `n(h₂) · Wᵀ + b` `[rows, out]`. `n` standardises rows (the layer norm with γ, β
/// already folded into the layer after it). Returns `(h₂, next's outputs)`.
#[allow(clippy::too_many_arguments)]
pub fn residual_chain(
    att: &[f32],
    h: &[f32],
    rows: usize,
    d: usize,
    output: Layer<'_>,
    mlp: Option<(Layer<'_>, Layer<'_>)>,
    next: Option<Layer<'_>>,
    eps: f32,
) -> (Vec<f32>, Vec<f32>) {
    let (ones, zeros) = (vec![1.0; d], vec![0.0; d]);
    let standardise = Some((&ones[..], &zeros[..], eps));
    let mut h = linear_fused(att, output.0, output.1, rows, d, d, false, None, Some(h));
    if let Some(((w1, b1), (w2, b2))) = mlp {
        let m = b1.len();
        let hidden = linear_fused(&h, w1, b1, rows, d, m, true, standardise, None);
        h = linear_fused(&hidden, w2, b2, rows, m, d, false, None, Some(&h));
    }
    let next = next.map_or_else(Vec::new, |(w, b)| {
        linear_fused(&h, w, b, rows, d, b.len(), false, standardise, None)
    });
    (h, next)
}

/// The shape and constants of the output preconditioning ([`precondition_output`]).
#[derive(Debug, Clone, Copy)]
pub struct PreconditionShape {
    pub slots: usize,
    pub agents: usize,
    /// The agent frame's anchor slot (≥ 1); `None` without an agent frame.
    pub anchor_slot: Option<usize>,
    pub sigma_data: f64,
    /// State units per radian of heading.
    pub heading_scale: f64,
    /// The constant-velocity reference's scale; 0 without one.
    pub residual_scale: f64,
}

/// `D(x; σ)` from the network's output `f` (`docs/checkpoint.md`'s last step, as
/// `common/precondition.wgsl`): `x`, `f` `[B, A, W, 3]`, `σ [B, W]`, `valid [B, A, W]`.
pub fn precondition_output(
    x: &[f32],
    f: &[f32],
    sigma: &[f32],
    valid: &[f32],
    shape: PreconditionShape,
) -> Vec<f32> {
    let PreconditionShape {
        slots,
        agents,
        anchor_slot,
        sigma_data: sd,
        heading_scale,
        residual_scale,
    } = shape;
    let v = |i: usize| f64::from(valid[i]);
    let state = |token: usize| [0, 1, 2].map(|c| f64::from(x[token * 3 + c]));
    let mut out = vec![0.0f32; x.len()];
    for token in 0..valid.len() {
        let (w, scene) = (token % slots, token / (slots * agents));
        let mut f_token = [0, 1, 2].map(|c| f64::from(f[token * 3 + c]));
        let (mut reference, mut scale) = ([0.0; 3], 1.0);
        if let Some(anchor_slot) = anchor_slot {
            let anchor = token / slots * slots + anchor_slot;
            let (a, p) = (state(anchor), state(anchor - 1));
            let heading_rad = a[2] * v(anchor) / heading_scale;
            let (sn, cs) = heading_rad.sin_cos();
            f_token = [
                cs * f_token[0] - sn * f_token[1],
                sn * f_token[0] + cs * f_token[1],
                f_token[2],
            ];
            if residual_scale > 0.0 && v(anchor) > 0.0 {
                scale = residual_scale;
                let slots_from_anchor = w as f64 - anchor_slot as f64;
                for c in 0..2 {
                    reference[c] = a[c] + slots_from_anchor * (a[c] - p[c]) * v(anchor - 1);
                }
                reference[2] = a[2];
            }
        }
        let s = f64::from(sigma[scene * slots + w]) * scale;
        let denom = s * s + sd * sd;
        let xs = state(token);
        for c in 0..3 {
            let y = (xs[c] - reference[c]) * scale;
            let d = sd * sd / denom * y + s * sd / denom.sqrt() * f_token[c] * v(token);
            out[token * 3 + c] = (reference[c] + d / scale) as f32;
        }
    }
    out
}

/// The shape and constants of [`embed_tokens`] (`common/embed_token.wgsl`'s `EmbedShape`).
#[derive(Debug, Clone, Copy)]
pub struct EmbedShape {
    pub agents: usize,
    pub slots: usize,
    pub hidden: usize,
    pub sigma_data: f64,
    /// The agent frame's anchor slot (≥ 1); `None` without an agent frame.
    pub anchor_slot: Option<usize>,
    /// State units per radian of heading.
    pub heading_scale: f64,
    pub relative_scale: f64,
    /// The constant-velocity reference's scale; 0 without one.
    pub residual_scale: f64,
}

/// The token embedding `h [B·A·W, D]` of `common/embed_token.wgsl` (`embed_tokens` and
/// `embed_chain`), in f64: `x [B, A, W, 3]`, `σ [B, W]`, `valid [B, A, W]`, the agents'
/// embedding `[B·A, D]`, and `packed` = W_state `[D, 3]` | b_state `[D]` | w_noise `[D]` |
/// b_noise `[D]` | slot `[W, D]` (| W_rel `[D, 4 or 6]` | b_rel `[D]` with an agent frame).
pub fn embed_tokens(
    shape: &EmbedShape,
    x: &[f32],
    sigma: &[f32],
    valid: &[f32],
    agent: &[f32],
    packed: &[f32],
) -> Vec<f32> {
    let (a_n, w_n, d_n) = (shape.agents, shape.slots, shape.hidden);
    let wt = |i: usize| f64::from(packed[i]);
    let xs = |token: usize, c: usize| f64::from(x[3 * token + c]);
    let (b_state, w_noise) = (3 * d_n, 4 * d_n);
    let (b_noise, slot) = (5 * d_n, 6 * d_n);
    let tokens = valid.len();
    let mut h = vec![0.0f32; tokens * d_n];
    for token in 0..tokens {
        let w = token % w_n;
        let b = token / (w_n * a_n);
        let s = f64::from(sigma[b * w_n + w]);
        let sd = shape.sigma_data;
        let c_in = 1.0 / (s * s + sd * sd).sqrt();
        let c_noise = s.ln() * 0.25;
        let v = f64::from(valid[token]);
        for d in 0..d_n {
            let mut acc = (0..3)
                .map(|c| wt(3 * d + c) * xs(token, c) * c_in * v)
                .sum::<f64>()
                + wt(b_state + d)
                + wt(w_noise + d) * c_noise
                + wt(b_noise + d)
                + f64::from(agent[(token / w_n) * d_n + d])
                + wt(slot + w * d_n + d);
            if let Some(anchor_slot) = shape.anchor_slot {
                let anchor = (token / w_n) * w_n + anchor_slot;
                let av = f64::from(valid[anchor]);
                let xa = [0, 1, 2].map(|c| xs(anchor, c) * av);
                let heading = xa[2] / shape.heading_scale;
                let (cs, sn) = (heading.cos(), heading.sin());
                let (mut dx, mut dy, mut dh) = (
                    xs(token, 0) - xa[0],
                    xs(token, 1) - xa[1],
                    xs(token, 2) - xa[2],
                );
                let mut k = c_in * shape.relative_scale * v * av;
                let (mut width, mut forward, mut left) = (4, 0.0, 0.0);
                if shape.residual_scale > 0.0 {
                    let rs = shape.residual_scale;
                    let previous = anchor - 1;
                    let both = f64::from(valid[previous]) * av;
                    let step_x = (xs(anchor, 0) - xs(previous, 0)) * both;
                    let step_y = (xs(anchor, 1) - xs(previous, 1)) * both;
                    let t = w as f64 - anchor_slot as f64;
                    dx = (dx - t * step_x) * rs;
                    dy = (dy - t * step_y) * rs;
                    dh *= rs;
                    let s_y = s * rs;
                    k = shape.relative_scale * v * av / (s_y * s_y + sd * sd).sqrt();
                    width = 6;
                    forward = (cs * step_x + sn * step_y) * rs;
                    left = (cs * step_y - sn * step_x) * rs;
                }
                let w_rel = slot + w_n * d_n;
                let b_rel = w_rel + width * d_n;
                let row = w_rel + width * d;
                acc += wt(row) * (cs * dx + sn * dy) * k
                    + wt(row + 1) * (cs * dy - sn * dx) * k
                    + wt(row + 2) * dh * k
                    + wt(row + 3) * av
                    + wt(b_rel + d);
                if width == 6 {
                    acc += wt(row + 4) * forward + wt(row + 5) * left;
                }
            }
            h[token * d_n + d] = acc as f32;
        }
    }
    h
}

/// The multistep sampler's step the residual chain fuses after the head: the Euler step of every
/// slot from σ `[B, W]` to σ_next `[B, W]` with `d [B, A, W, 3]` as its one evaluation
/// (`road_rollout::heun::heun_update`), then the correction against each slot's previous
/// estimate `[B, A, W, 3]` with γ `[B, W]` (`road_rollout::heun::multistep_correct`; γ = 0
/// leaves the Euler step). Returns x_e `[B, A, W, 3]`; shapes that disagree are an error.
#[allow(clippy::too_many_arguments)]
pub fn multistep_step(
    x: &[f32],
    d: &[f32],
    previous: &[f32],
    sigma: &[f32],
    sigma_next: &[f32],
    gamma: &[f32],
    agents: usize,
    slots: usize,
) -> Result<Vec<f32>, String> {
    let (mut x_e, _) =
        road_rollout::heun::heun_update(x, agents, slots, sigma, sigma_next, false, |_, _| {
            Ok(d.to_vec())
        })
        .map_err(|e| e.to_string())?;
    road_rollout::heun::multistep_correct(&mut x_e, d, previous, gamma, agents, slots);
    Ok(x_e)
}
