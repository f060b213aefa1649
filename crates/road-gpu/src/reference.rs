//! CPU references of the kernels: plain loops in f64, the meaning each kernel must match.

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
