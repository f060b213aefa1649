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

use road_model::agent_pairs::PAIR_FEATURES;

/// Lanes of the key-parallel loops (one AVX2 register of f32).
const LANES: usize = 8;

const LN_EPS: f32 = 1e-5;

/// Keys and values of attention: key row r holds its key at `k_offset` and its value at
/// `v_offset` (`D` values each).
pub(crate) struct KeysValues<'a> {
    rows: KeyRows<'a>,
    stride: usize,
    k_offset: usize,
    v_offset: usize,
}

/// Where the key rows live: one buffer, or the buffers of the workers that evaluate one scene
/// together (`(end, buffer)` each: the keys below `end` not in an earlier part are rows of
/// `buffer`, indexed as in the whole batch).
enum KeyRows<'a> {
    One(&'a [f32]),
    Parts(&'a [(usize, &'a [f32])]),
}

impl<'a> KeysValues<'a> {
    /// Cross-attention: rows of `[k; v]` from one stacked product, `2D` wide.
    pub(crate) fn side_by_side(kv: &'a [f32], d: usize) -> Self {
        Self {
            rows: KeyRows::One(kv),
            stride: 2 * d,
            k_offset: 0,
            v_offset: d,
        }
    }

    /// Self-attention: rows of `[q; k; v]` from one stacked product, `3D` wide, that one or
    /// several workers computed, each its own range of rows in its own buffer: `(end of the
    /// range, buffer)`, ranges in order.
    pub(crate) fn stacked_parts(parts: &'a [(usize, &'a [f32])], d: usize) -> Self {
        Self {
            rows: KeyRows::Parts(parts),
            stride: 3 * d,
            k_offset: d,
            v_offset: 2 * d,
        }
    }

    /// Key row `key`, from its start to the end of its buffer.
    fn row(&self, key: usize) -> &'a [f32] {
        let data = match self.rows {
            KeyRows::One(data) => data,
            KeyRows::Parts(parts) => {
                let (_, data) = parts
                    .iter()
                    .find(|&&(end, _)| key < end)
                    .expect("a key row beyond the last part");
                data
            }
        };
        &data[key * self.stride..]
    }

    fn width(&self) -> usize {
        self.v_offset.abs_diff(self.k_offset) // keys and values are D wide, side by side
    }
}

/// The pair terms of agent attention (`road_model::config::AgentPairs`) for one group whose
/// queries are some of its candidate keys: `features [queries, candidates, F]`, the position
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

/// `x ← exp(x)` for every `x ≤ 0` of `values` (NaN-free), by [`exp_lanes`]: relative error
/// ≈ 1e-7, arguments below −87 flushed to 0.
pub(crate) fn exp_non_positive(values: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if wide_registers() {
        // SAFETY: as in `attend`: AVX2 and FMA are present.
        #[allow(unsafe_code)]
        unsafe {
            exp_non_positive_avx2_fma(values)
        };
        return;
    }
    exp_non_positive_body::<false>(values);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn exp_non_positive_avx2_fma(values: &mut [f32]) {
    exp_non_positive_body::<true>(values);
}

#[inline(always)]
fn exp_non_positive_body<const FMA: bool>(values: &mut [f32]) {
    let mut chunks = values.chunks_exact_mut(LANES);
    for chunk in chunks.by_ref() {
        exp_lanes::<FMA>(chunk.try_into().expect("LANES wide"));
    }
    let rest = chunks.into_remainder();
    if !rest.is_empty() {
        let mut lanes = [0.0f32; LANES];
        lanes[..rest.len()].copy_from_slice(rest);
        exp_lanes::<FMA>(&mut lanes);
        rest.copy_from_slice(&lanes[..rest.len()]);
    }
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
        let row = kv.row(key);
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
            let keys_t_head = &keys_t[head * dh * padded..][..dh * padded];
            let pair_rows = pairs.is_some().then_some((&q_pair, &pairs_t[..f * padded]));
            let max = match chunks {
                1 => head_scores::<FMA, 1>(qh, keys_t_head, pair_rows, scale, n_keys, scores),
                2 => head_scores::<FMA, 2>(qh, keys_t_head, pair_rows, scale, n_keys, scores),
                3 => head_scores::<FMA, 3>(qh, keys_t_head, pair_rows, scale, n_keys, scores),
                4 => head_scores::<FMA, 4>(qh, keys_t_head, pair_rows, scale, n_keys, scores),
                _ => (0..chunks)
                    .map(|chunk| {
                        head_scores_chunk::<FMA>(
                            qh,
                            keys_t_head,
                            padded,
                            chunk,
                            pair_rows,
                            scale,
                            n_keys,
                            scores,
                        )
                    })
                    .fold(f32::NEG_INFINITY, f32::max),
            };
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
                // Σ_j a_j r_j, a register of keys at a time over the padded rows (padding keys
                // have weight exp(−∞) = 0 and features 0), normalised once at the end.
                let mut mean_pair = [0.0f32; PAIR_FEATURES];
                for (k, acc) in mean_pair.iter_mut().enumerate() {
                    let r = &pairs_t[k * padded..][..padded];
                    let mut lanes = [0.0f32; LANES];
                    for chunk in 0..chunks {
                        let s = &scores[chunk * LANES..][..LANES];
                        let v = &r[chunk * LANES..][..LANES];
                        for l in 0..LANES {
                            lanes[l] = madd::<FMA>(s[l], v[l], lanes[l]);
                        }
                    }
                    *acc = inv * lanes.iter().sum::<f32>();
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

/// One query-head's scores over `CHUNKS · LANES` keys (`padded`), into `scores`, and their
/// maximum: `Σ_c q_c · K[c, j] (+ Σ_k (K_hᵀ q)_k · r[k, j])`, times `scale`; padding keys get
/// −∞. The chunks' accumulators are independent, so the FMAs of one channel overlap instead
/// of waiting on each other.
#[inline(always)]
fn head_scores<const FMA: bool, const CHUNKS: usize>(
    qh: &[f32],
    keys_t_head: &[f32],
    pair_rows: Option<(&[f32; PAIR_FEATURES], &[f32])>,
    scale: f32,
    n_keys: usize,
    scores: &mut [f32],
) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // SAFETY: the FMA build is only reached through the AVX2 + FMA entry points.
        #[allow(unsafe_code)]
        return unsafe {
            avx2::head_scores::<CHUNKS>(qh, keys_t_head, pair_rows, scale, n_keys, scores)
        };
    }
    let padded = CHUNKS * LANES;
    let mut acc = [[0.0f32; LANES]; CHUNKS];
    for (c, &qc) in qh.iter().enumerate() {
        let row = &keys_t_head[c * padded..][..padded];
        for (chunk, acc) in acc.iter_mut().enumerate() {
            for l in 0..LANES {
                acc[l] = madd::<FMA>(qc, row[chunk * LANES + l], acc[l]);
            }
        }
    }
    if let Some((q_pair, pairs_t)) = pair_rows {
        for (k, &qk) in q_pair.iter().enumerate() {
            let row = &pairs_t[k * padded..][..padded];
            for (chunk, acc) in acc.iter_mut().enumerate() {
                for l in 0..LANES {
                    acc[l] = madd::<FMA>(qk, row[chunk * LANES + l], acc[l]);
                }
            }
        }
    }
    let mut max = [f32::NEG_INFINITY; LANES];
    for (chunk, acc) in acc.iter().enumerate() {
        let s = &mut scores[chunk * LANES..][..LANES];
        for l in 0..LANES {
            s[l] = if chunk * LANES + l < n_keys {
                acc[l] * scale
            } else {
                f32::NEG_INFINITY
            };
            max[l] = if s[l] > max[l] { s[l] } else { max[l] };
        }
    }
    max.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b))
}

/// [`head_scores`] for one chunk of a group with more keys than the unrolled versions take.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn head_scores_chunk<const FMA: bool>(
    qh: &[f32],
    keys_t_head: &[f32],
    padded: usize,
    chunk: usize,
    pair_rows: Option<(&[f32; PAIR_FEATURES], &[f32])>,
    scale: f32,
    n_keys: usize,
    scores: &mut [f32],
) -> f32 {
    let mut acc = [0.0f32; LANES];
    for (c, &qc) in qh.iter().enumerate() {
        let k = &keys_t_head[c * padded + chunk * LANES..][..LANES];
        for l in 0..LANES {
            acc[l] = madd::<FMA>(qc, k[l], acc[l]);
        }
    }
    if let Some((q_pair, pairs_t)) = pair_rows {
        for (k, &qk) in q_pair.iter().enumerate() {
            let r = &pairs_t[k * padded + chunk * LANES..][..LANES];
            for l in 0..LANES {
                acc[l] = madd::<FMA>(qk, r[l], acc[l]);
            }
        }
    }
    let s = &mut scores[chunk * LANES..][..LANES];
    let mut max = f32::NEG_INFINITY;
    for l in 0..LANES {
        s[l] = if chunk * LANES + l < n_keys {
            acc[l] * scale
        } else {
            f32::NEG_INFINITY
        };
        max = max.max(s[l]);
    }
    max
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
    #[cfg(target_arch = "x86_64")]
    if FMA && DH == 16 {
        // SAFETY: as in `head_scores`.
        #[allow(unsafe_code)]
        unsafe {
            avx2::weighted_sum_16(weights, inv, values, d, offset, out)
        };
        return;
    }
    // Even and odd keys in separate accumulators: two dependency chains instead of one.
    let mut even = [0.0f32; DH];
    let mut odd = [0.0f32; DH];
    let mut pairs = weights.chunks_exact(2);
    for (i, pair) in pairs.by_ref().enumerate() {
        let j = 2 * i;
        let v0: &[f32; DH] = values[j * d + offset..][..DH].try_into().expect("DH wide");
        let v1: &[f32; DH] = values[(j + 1) * d + offset..][..DH]
            .try_into()
            .expect("DH wide");
        let (w0, w1) = (pair[0] * inv, pair[1] * inv);
        for c in 0..DH {
            even[c] = madd::<FMA>(w0, v0[c], even[c]);
            odd[c] = madd::<FMA>(w1, v1[c], odd[c]);
        }
    }
    if let [last] = pairs.remainder() {
        let j = weights.len() - 1;
        let v: &[f32; DH] = values[j * d + offset..][..DH].try_into().expect("DH wide");
        for c in 0..DH {
            even[c] = madd::<FMA>(last * inv, v[c], even[c]);
        }
    }
    let mut acc = [0.0f32; DH];
    for c in 0..DH {
        acc[c] = even[c] + odd[c];
    }
    out.copy_from_slice(&acc);
}

/// Constants of [`exp_lanes`] (both builds): ln 2 in two parts for an exact range reduction,
/// and Cephes' `expf` polynomial, highest power first.
const LOG2_E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Adding and taking off 1.5·2²³ rounds to the nearest integer without a rounding instruction
/// (SSE2 has none); the integer then sits in the sum's low mantissa bits.
const ROUND: f32 = 12_582_912.0;
const EXP_POLYNOMIAL: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];

/// `x ← exp(x)` lane by lane for `x ≤ 0` (softmax after its maximum is taken off): Cephes'
/// `expf` polynomial (relative error ≈ 1e-7), `exp(−∞) = 0`, arguments below −87 flushed to 0
/// (their weight is below f32's normal range anyway).
#[inline(always)]
fn exp_lanes<const FMA: bool>(x: &mut [f32; LANES]) {
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // SAFETY: the FMA build is only reached through the AVX2 + FMA entry points, which
        // check the CPU at run time.
        #[allow(unsafe_code)]
        unsafe {
            exp_lanes_avx2_fma(x)
        };
        return;
    }
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
    let mut p = [EXP_POLYNOMIAL[0]; LANES];
    for &coefficient in &EXP_POLYNOMIAL[1..] {
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

/// [`exp_lanes`] in AVX2 + FMA registers: the same stages, one instruction each.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
fn exp_lanes_avx2_fma(x: &mut [f32; LANES]) {
    use std::arch::x86_64::*;
    // SAFETY (loads and stores): `x` is 8 f32 wide, what one unaligned 256-bit access reads.
    #[allow(unsafe_code)]
    let v = unsafe { _mm256_loadu_ps(x.as_ptr()) };
    let floor = _mm256_set1_ps(-87.0);
    let flushed = _mm256_cmp_ps::<_CMP_LT_OQ>(v, floor);
    let a = _mm256_max_ps(v, floor);
    let round = _mm256_set1_ps(ROUND);
    let shifted = _mm256_fmadd_ps(a, _mm256_set1_ps(LOG2_E), round);
    let n = _mm256_sub_ps(shifted, round);
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(LN2_HI), a);
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(LN2_LO), r);
    let mut p = _mm256_set1_ps(EXP_POLYNOMIAL[0]);
    for &coefficient in &EXP_POLYNOMIAL[1..] {
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(coefficient));
    }
    let e = _mm256_add_ps(
        _mm256_fmadd_ps(p, _mm256_mul_ps(r, r), r),
        _mm256_set1_ps(1.0),
    );
    let n_bits = _mm256_sub_epi32(_mm256_castps_si256(shifted), _mm256_castps_si256(round));
    let two_n = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
        n_bits,
        _mm256_set1_epi32(127),
    )));
    let out = _mm256_andnot_ps(flushed, _mm256_mul_ps(e, two_n));
    #[allow(unsafe_code)]
    unsafe {
        _mm256_storeu_ps(x.as_mut_ptr(), out)
    };
}

/// The hottest loops of attention in AVX2 + FMA registers, written out: LLVM's vectoriser
/// kept the generic versions' accumulators in scalar lanes and shuffled them every step.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{LANES, PAIR_FEATURES};

    /// 8 f32 from `row[at..at + 8]` (bounds-checked, then one unaligned load).
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn load(row: &[f32], at: usize) -> __m256 {
        let lanes: &[f32; LANES] = row[at..at + LANES].try_into().expect("8 wide");
        // SAFETY: `lanes` is 8 f32, what one unaligned 256-bit load reads.
        #[allow(unsafe_code)]
        unsafe {
            _mm256_loadu_ps(lanes.as_ptr())
        }
    }

    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn store(row: &mut [f32], at: usize, v: __m256) {
        let lanes: &mut [f32; LANES] = (&mut row[at..at + LANES]).try_into().expect("8 wide");
        // SAFETY: as in `load`.
        #[allow(unsafe_code)]
        unsafe {
            _mm256_storeu_ps(lanes.as_mut_ptr(), v)
        }
    }

    /// `super::head_scores`, the same arithmetic.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    pub(super) fn head_scores<const CHUNKS: usize>(
        qh: &[f32],
        keys_t_head: &[f32],
        pair_rows: Option<(&[f32; PAIR_FEATURES], &[f32])>,
        scale: f32,
        n_keys: usize,
        scores: &mut [f32],
    ) -> f32 {
        let padded = CHUNKS * LANES;
        let mut acc = [_mm256_setzero_ps(); CHUNKS];
        for (c, &qc) in qh.iter().enumerate() {
            let row = &keys_t_head[c * padded..][..padded];
            let q = _mm256_set1_ps(qc);
            for (chunk, acc) in acc.iter_mut().enumerate() {
                *acc = _mm256_fmadd_ps(q, load(row, chunk * LANES), *acc);
            }
        }
        if let Some((q_pair, pairs_t)) = pair_rows {
            for (k, &qk) in q_pair.iter().enumerate() {
                let row = &pairs_t[k * padded..][..padded];
                let q = _mm256_set1_ps(qk);
                for (chunk, acc) in acc.iter_mut().enumerate() {
                    *acc = _mm256_fmadd_ps(q, load(row, chunk * LANES), *acc);
                }
            }
        }
        let scale = _mm256_set1_ps(scale);
        for (chunk, &acc) in acc.iter().enumerate() {
            store(scores, chunk * LANES, _mm256_mul_ps(acc, scale));
        }
        for score in &mut scores[n_keys..padded] {
            *score = f32::NEG_INFINITY;
        }
        scores[..padded]
            .iter()
            .fold(f32::NEG_INFINITY, |a, &b| if b > a { b } else { a })
    }

    /// `super::weighted_sum` for 16-wide heads: even and odd keys, low and high halves, in
    /// four registers.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    pub(super) fn weighted_sum_16(
        weights: &[f32],
        inv: f32,
        values: &[f32],
        d: usize,
        offset: usize,
        out: &mut [f32],
    ) {
        let (mut even_lo, mut even_hi) = (_mm256_setzero_ps(), _mm256_setzero_ps());
        let (mut odd_lo, mut odd_hi) = (_mm256_setzero_ps(), _mm256_setzero_ps());
        let mut pairs = weights.chunks_exact(2);
        for (i, pair) in pairs.by_ref().enumerate() {
            let (j0, j1) = (2 * i * d + offset, (2 * i + 1) * d + offset);
            let w0 = _mm256_set1_ps(pair[0] * inv);
            let w1 = _mm256_set1_ps(pair[1] * inv);
            even_lo = _mm256_fmadd_ps(w0, load(values, j0), even_lo);
            even_hi = _mm256_fmadd_ps(w0, load(values, j0 + LANES), even_hi);
            odd_lo = _mm256_fmadd_ps(w1, load(values, j1), odd_lo);
            odd_hi = _mm256_fmadd_ps(w1, load(values, j1 + LANES), odd_hi);
        }
        if let [last] = pairs.remainder() {
            let j = (weights.len() - 1) * d + offset;
            let w = _mm256_set1_ps(last * inv);
            even_lo = _mm256_fmadd_ps(w, load(values, j), even_lo);
            even_hi = _mm256_fmadd_ps(w, load(values, j + LANES), even_hi);
        }
        store(out, 0, _mm256_add_ps(even_lo, odd_lo));
        store(out, LANES, _mm256_add_ps(even_hi, odd_hi));
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
                #[cfg(target_arch = "x86_64")]
                if fma && !wide_registers() {
                    continue;
                }
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
    /// the lane width (1 to 4 chunks of 8, unrolled, and 5, looped) and a key subset (masked
    /// keys left out).
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
            (0..30).collect(),
            (0..33).collect(),
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
