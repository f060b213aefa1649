//! The fast CPU engine's hand-written kernels: multi-head attention fused over a group of
//! queries that share their keys, and layer norm. Each is one generic body compiled twice:
//! for AVX2 + FMA (chosen at run time, as `gemm` chooses its kernels) and for the baseline
//! target the binary is built for (SSE2 on x86-64), so that one binary runs everywhere and
//! uses the wide registers where they exist.
//!
//! Attention works key-parallel: a group's keys are gathered once, transposed per channel
//! (`[D, keys]`, padded to a multiple of [`LANES`]), so that a query's scores over 8 keys are
//! 8 lanes of one register and need no horizontal sums; the softmax's `exp` is a polynomial
//! over the same lanes ([`exp_lanes`]).

use crate::agent_pairs::PAIR_FEATURES;

/// Lanes of the key-parallel loops (one AVX2 register of f32).
const LANES: usize = 8;

const LN_EPS: f32 = 1e-5;

/// Keys and values of attention: row r of `data` holds its key at `k_offset` and its value at
/// `v_offset` (`D` values each).
pub(crate) struct KeysValues<'a> {
    data: &'a [f32],
    stride: usize,
    k_offset: usize,
    v_offset: usize,
}

impl<'a> KeysValues<'a> {
    /// Cross-attention: rows of `[k; v]` from one stacked product, `2D` wide.
    pub(crate) fn side_by_side(kv: &'a [f32], d: usize) -> Self {
        Self {
            data: kv,
            stride: 2 * d,
            k_offset: 0,
            v_offset: d,
        }
    }

    /// Self-attention: rows of `[q; k; v]` from one stacked product, `3D` wide.
    pub(crate) fn stacked(qkv: &'a [f32], d: usize) -> Self {
        Self {
            data: qkv,
            stride: 3 * d,
            k_offset: d,
            v_offset: 2 * d,
        }
    }

    fn width(&self) -> usize {
        self.v_offset.abs_diff(self.k_offset) // keys and values are D wide, side by side
    }
}

/// The pair terms of agent attention ([`crate::config::AgentPairs`]) for one group whose
/// queries are also its candidate keys: `features [queries, candidates, F]`, the position
/// among the candidates of each key passed to [`attend`], and the offsets' weights `[D, F]`.
pub(crate) struct PairTerms<'a> {
    pub(crate) features: &'a [f32],
    pub(crate) key_positions: &'a [usize],
    pub(crate) candidates: usize,
    pub(crate) k_weights: &'a [f32],
    pub(crate) v_weights: &'a [f32],
}

/// Buffers [`attend`] keeps from call to call.
#[derive(Debug, Default)]
pub(crate) struct AttentionScratch {
    /// The group's keys, channel-major: `[D, padded keys]`.
    keys_t: Vec<f32>,
    /// The group's values, key-major: `[keys, D]`.
    values: Vec<f32>,
    /// One query's pair features, feature-major: `[F, padded keys]`.
    pairs_t: Vec<f32>,
    /// One query-head's scores, then its weights: `[padded keys]`.
    scores: Vec<f32>,
}

/// Multi-head attention of the query rows `queries` of `q` (row stride `q_stride`, queries at
/// offset 0) over key rows `keys` of `kv`; writes `out [row, D]` for each query row. With
/// `pairs`, each score gains `(K_hᵀ q) · r` and each output `V_h Σ_j a_j r_j` (the candle
/// model's `Attention::forward`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn attend(
    q: &[f32],
    q_stride: usize,
    queries: &[usize],
    kv: &KeysValues<'_>,
    keys: &[usize],
    pairs: Option<&PairTerms<'_>>,
    heads: usize,
    scale: f32,
    scratch: &mut AttentionScratch,
    out: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if wide_registers() {
        // SAFETY: the CPU has AVX2 and FMA (checked at run time just above), the only
        // requirement of a `target_feature` function; its body is the safe generic one.
        #[allow(unsafe_code)]
        unsafe {
            attend_avx2_fma(
                q, q_stride, queries, kv, keys, pairs, heads, scale, scratch, out,
            )
        };
        return;
    }
    attend_body::<false>(
        q, q_stride, queries, kv, keys, pairs, heads, scale, scratch, out,
    );
}

/// `out [n, D] = LN(x [n, D])` with the layer's `weight` and `bias` `[D]`.
pub(crate) fn layer_norm(x: &[f32], weight: &[f32], bias: &[f32], out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if wide_registers() {
        // SAFETY: as in `attend`: AVX2 and FMA are present.
        #[allow(unsafe_code)]
        unsafe {
            layer_norm_avx2_fma(x, weight, bias, out)
        };
        return;
    }
    layer_norm_body::<false>(x, weight, bias, out);
}

/// Whether the AVX2 + FMA versions can run (std caches the CPU's answer).
#[cfg(target_arch = "x86_64")]
fn wide_registers() -> bool {
    std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
fn attend_avx2_fma(
    q: &[f32],
    q_stride: usize,
    queries: &[usize],
    kv: &KeysValues<'_>,
    keys: &[usize],
    pairs: Option<&PairTerms<'_>>,
    heads: usize,
    scale: f32,
    scratch: &mut AttentionScratch,
    out: &mut [f32],
) {
    attend_body::<true>(
        q, q_stride, queries, kv, keys, pairs, heads, scale, scratch, out,
    );
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn layer_norm_avx2_fma(x: &[f32], weight: &[f32], bias: &[f32], out: &mut [f32]) {
    layer_norm_body::<true>(x, weight, bias, out);
}

/// `a · b + c`, fused where the instruction exists (inlined into the FMA build only).
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA { a.mul_add(b, c) } else { a * b + c }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn attend_body<const FMA: bool>(
    q: &[f32],
    q_stride: usize,
    queries: &[usize],
    kv: &KeysValues<'_>,
    keys: &[usize],
    pairs: Option<&PairTerms<'_>>,
    heads: usize,
    scale: f32,
    scratch: &mut AttentionScratch,
    out: &mut [f32],
) {
    let d = kv.width();
    let dh = d / heads;
    let f = PAIR_FEATURES;
    let n_keys = keys.len();
    let chunks = n_keys.div_ceil(LANES);
    let padded = chunks * LANES;
    let AttentionScratch {
        keys_t,
        values,
        pairs_t,
        scores,
    } = scratch;
    keys_t.clear();
    keys_t.resize(d * padded, 0.0);
    values.clear();
    for (j, &key) in keys.iter().enumerate() {
        let row = &kv.data[key * kv.stride..];
        for (c, &k) in row[kv.k_offset..][..d].iter().enumerate() {
            keys_t[c * padded + j] = k;
        }
        values.extend_from_slice(&row[kv.v_offset..][..d]);
    }
    scores.clear();
    scores.resize(padded, 0.0);
    pairs_t.clear();
    pairs_t.resize(f * padded, 0.0);

    for (query_index, &row) in queries.iter().enumerate() {
        let query = &q[row * q_stride..][..d];
        if let Some(p) = pairs {
            let features = &p.features[query_index * p.candidates * f..][..p.candidates * f];
            for (j, &position) in p.key_positions.iter().enumerate() {
                for (k, &r) in features[position * f..][..f].iter().enumerate() {
                    pairs_t[k * padded + j] = r;
                }
            }
        }
        let o = &mut out[row * d..][..d];
        for head in 0..heads {
            let qh = &query[head * dh..][..dh];
            // Scores, 8 keys a register: Σ_c q_c · K[c, j] (+ Σ_k (K_hᵀ q)_k · r[k, j]).
            let mut q_pair = [0.0f32; PAIR_FEATURES];
            if let Some(p) = pairs {
                for (c, &qc) in qh.iter().enumerate() {
                    let weights = &p.k_weights[(head * dh + c) * f..][..f];
                    for (acc, &w) in q_pair.iter_mut().zip(weights) {
                        *acc = madd::<FMA>(qc, w, *acc);
                    }
                }
            }
            let mut max = [f32::NEG_INFINITY; LANES];
            for chunk in 0..chunks {
                let mut acc = [0.0f32; LANES];
                for (c, &qc) in qh.iter().enumerate() {
                    let k: &[f32; LANES] = keys_t[(head * dh + c) * padded + chunk * LANES..]
                        [..LANES]
                        .try_into()
                        .expect("LANES wide");
                    for l in 0..LANES {
                        acc[l] = madd::<FMA>(qc, k[l], acc[l]);
                    }
                }
                if pairs.is_some() {
                    for (k, &qk) in q_pair.iter().enumerate() {
                        let r: &[f32; LANES] = pairs_t[k * padded + chunk * LANES..][..LANES]
                            .try_into()
                            .expect("LANES wide");
                        for l in 0..LANES {
                            acc[l] = madd::<FMA>(qk, r[l], acc[l]);
                        }
                    }
                }
                let s = &mut scores[chunk * LANES..][..LANES];
                for l in 0..LANES {
                    let valid = chunk * LANES + l < n_keys;
                    s[l] = if valid {
                        acc[l] * scale
                    } else {
                        f32::NEG_INFINITY
                    };
                    max[l] = max[l].max(s[l]);
                }
            }
            let max = max.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
            // Softmax weights (padding: exp(−∞) = 0).
            let mut sums = [0.0f32; LANES];
            for chunk in 0..chunks {
                let s: &mut [f32; LANES] = (&mut scores[chunk * LANES..][..LANES])
                    .try_into()
                    .expect("LANES wide");
                for v in s.iter_mut() {
                    *v -= max;
                }
                exp_lanes::<FMA>(s);
                for l in 0..LANES {
                    sums[l] += s[l];
                }
            }
            let inv = 1.0 / sums.iter().sum::<f32>();
            let oh = &mut o[head * dh..][..dh];
            if dh == 16 {
                weighted_sum::<FMA, 16>(&scores[..n_keys], inv, values, d, head * dh, oh);
            } else {
                oh.fill(0.0);
                for (j, &score) in scores[..n_keys].iter().enumerate() {
                    let weight = score * inv;
                    let vh = &values[j * d + head * dh..][..dh];
                    for (acc, &v) in oh.iter_mut().zip(vh) {
                        *acc = madd::<FMA>(weight, v, *acc);
                    }
                }
            }
            if let Some(p) = pairs {
                let mut mean_pair = [0.0f32; PAIR_FEATURES];
                for (k, acc) in mean_pair.iter_mut().enumerate() {
                    let r = &pairs_t[k * padded..][..n_keys];
                    let mut lanes = [0.0f32; LANES];
                    for (j, (&score, &value)) in scores[..n_keys].iter().zip(r).enumerate() {
                        lanes[j % LANES] = madd::<FMA>(score * inv, value, lanes[j % LANES]);
                    }
                    *acc = lanes.iter().sum();
                }
                for (c, acc) in oh.iter_mut().enumerate() {
                    let weights = &p.v_weights[(head * dh + c) * f..][..f];
                    for (&w, &m) in weights.iter().zip(&mean_pair) {
                        *acc = madd::<FMA>(w, m, *acc);
                    }
                }
            }
        }
    }
}

/// `out [DH] = Σ_j (weights_j · inv) · values[j, offset..offset + DH]` (row stride `d`), in
/// registers: the head width known at compile time.
#[inline(always)]
fn weighted_sum<const FMA: bool, const DH: usize>(
    weights: &[f32],
    inv: f32,
    values: &[f32],
    d: usize,
    offset: usize,
    out: &mut [f32],
) {
    let mut acc = [0.0f32; DH];
    for (j, &weight) in weights.iter().enumerate() {
        let weight = weight * inv;
        let v: &[f32; DH] = values[j * d + offset..][..DH].try_into().expect("DH wide");
        for c in 0..DH {
            acc[c] = madd::<FMA>(weight, v[c], acc[c]);
        }
    }
    out.copy_from_slice(&acc);
}

/// `x ← exp(x)` lane by lane for `x ≤ 0` (softmax after its maximum is taken off): Cephes'
/// `expf` polynomial (relative error ≈ 1e-7), `exp(−∞) = 0`, arguments below −87 flushed to 0
/// (their weight is below f32's normal range anyway).
#[inline(always)]
fn exp_lanes<const FMA: bool>(x: &mut [f32; LANES]) {
    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Adding and taking off 1.5·2²³ rounds to the nearest integer without a rounding
    // instruction (SSE2 has none).
    const ROUND: f32 = 12_582_912.0;
    const P: [f32; 6] = [
        1.987_569_1e-4,
        1.398_199_9e-3,
        8.333_452e-3,
        4.166_579_6e-2,
        1.666_666_5e-1,
        5.000_000_1e-1,
    ];
    // One stage at a time over all lanes, branch-free and without float-to-int casts (their
    // NaN handling stops LLVM from vectorising): each loop is one vector instruction or two.
    let mut flushed = [false; LANES];
    let mut a = [0.0f32; LANES];
    for l in 0..LANES {
        flushed[l] = x[l] < -87.0;
        a[l] = if flushed[l] { -87.0 } else { x[l] };
    }
    // The integer n sits in the low bits of `shifted`.
    let mut shifted = [0.0f32; LANES];
    let mut r = [0.0f32; LANES];
    for l in 0..LANES {
        shifted[l] = a[l] * LOG2_E + ROUND;
        let n = shifted[l] - ROUND;
        r[l] = madd::<FMA>(-n, LN2_LO, madd::<FMA>(-n, LN2_HI, a[l]));
    }
    let mut p = [P[0]; LANES];
    for &coefficient in &P[1..] {
        for l in 0..LANES {
            p[l] = madd::<FMA>(p[l], r[l], coefficient);
        }
    }
    for l in 0..LANES {
        let e = madd::<FMA>(p[l], r[l] * r[l], r[l]) + 1.0;
        let n_bits = shifted[l].to_bits().wrapping_sub(ROUND.to_bits());
        let two_n = f32::from_bits(n_bits.wrapping_add(127) << 23);
        x[l] = if flushed[l] { 0.0 } else { e * two_n };
    }
}

#[inline(always)]
fn layer_norm_body<const FMA: bool>(x: &[f32], weight: &[f32], bias: &[f32], out: &mut [f32]) {
    let d = weight.len();
    for (row, o) in x.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
        let mut lanes = [0.0f32; LANES];
        for chunk in row.chunks_exact(LANES) {
            for l in 0..LANES {
                lanes[l] += chunk[l];
            }
        }
        let tail = row.chunks_exact(LANES).remainder();
        let mean = (lanes.iter().sum::<f32>() + tail.iter().sum::<f32>()) / d as f32;
        let mut lanes = [0.0f32; LANES];
        for chunk in row.chunks_exact(LANES) {
            for l in 0..LANES {
                let centred = chunk[l] - mean;
                lanes[l] = madd::<FMA>(centred, centred, lanes[l]);
            }
        }
        let tail: f32 = tail.iter().map(|v| (v - mean) * (v - mean)).sum();
        let var = (lanes.iter().sum::<f32>() + tail) / d as f32;
        let inv = 1.0 / (var + LN_EPS).sqrt();
        for ((o, &v), (&w, &b)) in o.iter_mut().zip(row).zip(weight.iter().zip(bias)) {
            *o = madd::<FMA>((v - mean) * inv, w, b);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The polynomial `exp` against std's over the softmax's range, and its edges.
    #[test]
    fn exp_lanes_matches_std() {
        let mut worst = 0.0f32;
        for i in 0..=87_000 {
            let x = (-(i as f32) * 1e-3).max(-87.0);
            for fma in [false, true] {
                let mut lanes = [x; LANES];
                if fma {
                    exp_lanes::<true>(&mut lanes);
                } else {
                    exp_lanes::<false>(&mut lanes);
                }
                let want = x.exp();
                if want > f32::MIN_POSITIVE {
                    let error = (lanes[0] - want).abs() / want;
                    assert!(error < 5e-7, "exp({x}) = {} against {want}", lanes[0]);
                    worst = worst.max(error);
                }
            }
        }
        assert!(worst < 5e-7, "relative error {worst}");
        let mut edges = [
            0.0,
            -88.0,
            -1e30,
            f32::NEG_INFINITY,
            -0.0,
            -1e-30,
            -86.9,
            -1.0,
        ];
        exp_lanes::<false>(&mut edges);
        assert_eq!(&edges[..5], &[1.0, 0.0, 0.0, 0.0, 1.0]);
        assert!((edges[5] - 1.0).abs() < 1e-7 && edges[6] > 0.0);
    }

    /// Scalar attention (softmax over all keys, per head), the definition the kernel keeps.
    fn attention_reference(
        q: &[f32],
        kv: &[f32],
        keys: &[usize],
        d: usize,
        heads: usize,
        scale: f32,
    ) -> Vec<f32> {
        let dh = d / heads;
        let mut out = vec![0.0; d];
        for head in 0..heads {
            let scores: Vec<f64> = keys
                .iter()
                .map(|&k| {
                    (0..dh)
                        .map(|c| (q[head * dh + c] * kv[k * 2 * d + head * dh + c]) as f64)
                        .sum::<f64>()
                        * scale as f64
                })
                .collect();
            let max = scores.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let weights: Vec<f64> = scores.iter().map(|s| (s - max).exp()).collect();
            let sum: f64 = weights.iter().sum();
            for c in 0..dh {
                out[head * dh + c] = keys
                    .iter()
                    .zip(&weights)
                    .map(|(&k, w)| w / sum * kv[k * 2 * d + d + head * dh + c] as f64)
                    .sum::<f64>() as f32;
            }
        }
        out
    }

    /// Both builds of the kernel against the scalar definition, for key counts on and off
    /// the lane width and a key subset (masked keys left out).
    #[test]
    fn attention_matches_its_definition() {
        let (d, heads) = (64, 4);
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((seed >> 40) as f32 / (1u64 << 24) as f32) * 4.0 - 2.0
        };
        let q: Vec<f32> = (0..3 * d).map(|_| next()).collect();
        let kv: Vec<f32> = (0..33 * 2 * d).map(|_| next()).collect();
        let kv_view = KeysValues::side_by_side(&kv, d);
        for keys in [
            (0..1).collect::<Vec<_>>(),
            (0..8).collect(),
            (0..13).collect(),
            (0..33).filter(|k| k % 3 != 1).collect(),
        ] {
            for fma in [false, true] {
                #[cfg(target_arch = "x86_64")]
                if fma && !wide_registers() {
                    continue;
                }
                #[cfg(not(target_arch = "x86_64"))]
                if fma {
                    continue;
                }
                let mut scratch = AttentionScratch::default();
                let mut out = vec![f32::NAN; 3 * d];
                let args = (&q[..], d, &[0usize, 2][..], &kv_view, &keys[..]);
                if fma {
                    #[cfg(target_arch = "x86_64")]
                    #[allow(unsafe_code)]
                    // SAFETY: AVX2 and FMA checked above.
                    unsafe {
                        attend_avx2_fma(
                            args.0,
                            args.1,
                            args.2,
                            args.3,
                            args.4,
                            None,
                            heads,
                            0.25,
                            &mut scratch,
                            &mut out,
                        )
                    };
                } else {
                    attend_body::<false>(
                        args.0,
                        args.1,
                        args.2,
                        args.3,
                        args.4,
                        None,
                        heads,
                        0.25,
                        &mut scratch,
                        &mut out,
                    );
                }
                for row in [0, 2] {
                    let want = attention_reference(&q[row * d..][..d], &kv, &keys, d, heads, 0.25);
                    for (c, (&got, &want)) in out[row * d..][..d].iter().zip(&want).enumerate() {
                        assert!(
                            (got - want).abs() <= 1e-5 + 1e-5 * want.abs(),
                            "{} keys, fma {fma}, row {row}, channel {c}: {got} against {want}",
                            keys.len()
                        );
                    }
                }
                assert!(out[d..2 * d].iter().all(|v| v.is_nan()), "row 1 untouched");
            }
        }
    }

    #[test]
    fn layer_norm_matches_its_definition() {
        let d = 64;
        let x: Vec<f32> = (0..3 * d)
            .map(|i| ((i * 37 % 101) as f32) * 0.1 - 5.0)
            .collect();
        let weight: Vec<f32> = (0..d).map(|i| 0.5 + i as f32 * 0.01).collect();
        let bias: Vec<f32> = (0..d).map(|i| i as f32 * -0.02).collect();
        let mut out = vec![0.0; 3 * d];
        layer_norm(&x, &weight, &bias, &mut out);
        for row in 0..3 {
            let r = &x[row * d..][..d];
            let mean = r.iter().map(|&v| v as f64).sum::<f64>() / d as f64;
            let var = r.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / d as f64;
            for i in 0..d {
                let want = (r[i] as f64 - mean) / (var + LN_EPS as f64).sqrt() * weight[i] as f64
                    + bias[i] as f64;
                let got = out[row * d + i] as f64;
                assert!(
                    (got - want).abs() < 1e-5,
                    "row {row}, {i}: {got} against {want}"
                );
            }
        }
    }
}
