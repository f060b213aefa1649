//! `road gpu selftest`'s kernel checks: the kernel families against their CPU references on the
//! adapter at hand, on seeded random inputs of the shapes the engine runs (RoAD-20's D = 64,
//! 4 heads, 20 slots, 12 of 32 polylines). A machine lent for a few minutes checks its
//! kernels in one call before anything is timed; the parity tests check the same on lavapipe.

use crate::kernels::agent_map::{AgentMap, AgentMapParams};
use crate::kernels::agent_pairs::{PairAttention, PairAttentionParams};
use crate::kernels::attention::{Attention, AttentionParams, SceneMode, TokenLayout};
use crate::kernels::compact::{CompactRows, NONE, gather_rows_reference, scatter_rows_reference};
use crate::kernels::linear::{Linear, LinearKernel, LinearParams, fold_layer_norm};
use crate::kernels::polyline::{PolylineEncoder, PolylineKernel, PolylineParams};
use crate::kernels::residual_chain::{
    AttendInputs, ChainInputs, ChainParams, ChainTile, EmbedChainInputs, NO_FRAME, ResidualChain,
    transpose,
};
use crate::tolerance::Mismatch;
use crate::{GpuContext, Result, Tolerance, reference};

/// One kernel's comparison.
#[derive(Debug, Clone)]
pub struct KernelCheck {
    pub name: &'static str,
    /// Values compared.
    pub values: usize,
    pub tolerance: Tolerance,
    pub outcome: std::result::Result<(), Mismatch>,
}

/// A small seeded generator (xorshift64*), so that the checks (and the tuner's inputs) need no
/// RNG crate.
pub(crate) struct Inputs(pub(crate) u64);

impl Inputs {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let bits = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 40; // 24 bits
        bits as f32 / (1u64 << 24) as f32
    }

    /// `n` values uniform in `[-scale, scale)`.
    pub(crate) fn uniform(&mut self, n: usize, scale: f32) -> Vec<f32> {
        (0..n).map(|_| (2.0 * self.next() - 1.0) * scale).collect()
    }

    /// `n` validity flags, each 1 with probability `p`.
    fn flags(&mut self, n: usize, p: f32) -> Vec<f32> {
        (0..n)
            .map(|_| if self.next() < p { 1.0 } else { 0.0 })
            .collect()
    }
}

/// Runs every kernel family's check on `ctx` (seeded: the same inputs on every machine).
pub fn kernel_checks(ctx: &GpuContext) -> Result<Vec<KernelCheck>> {
    let mut rng = Inputs(0x5EED_F0AD);
    let tol = Tolerance::F32;
    let loose = Tolerance {
        rel: 1e-4,
        abs: 1e-5,
    };
    let mut checks = Vec::new();
    let (b, a, w, d, heads) = (3usize, 12usize, 20usize, 64usize, 4usize);
    let tokens = b * a * w;

    // linear: the MLP's first layer over every token.
    let (rows, d_in, d_out) = (tokens, d, 2 * d);
    let (x, wt, bias) = (
        rng.uniform(rows * d_in, 1.0),
        rng.uniform(d_out * d_in, 0.2),
        rng.uniform(d_out, 0.1),
    );
    let p = LinearParams {
        relu: 1,
        ..LinearParams::new(rows, d_in, d_out)
    };
    let want = reference::linear(&x, &wt, &bias, rows, d_in, d_out, true);
    // Every variant, whichever the engine uses here.
    for kernel in LinearKernel::ALL {
        let got = Linear::with_kernel(ctx, kernel).run(ctx, p, &x, &wt, &bias)?;
        checks.push(KernelCheck {
            name: kernel.entry(),
            values: got.len(),
            tolerance: loose,
            outcome: loose.check(&got, &want),
        });
    }
    // The same, fused as the engine's output projections and MLP: the layer norm in the
    // prologue, the residual add in the epilogue.
    let (gamma, beta, residual) = (
        rng.uniform(d_in, 1.0),
        rng.uniform(d_in, 0.5),
        rng.uniform(rows * d_out, 1.0),
    );
    let p = LinearParams {
        residual: 1,
        norm: 1,
        eps: 1e-5,
        ..p
    };
    let want = reference::linear_fused(
        &x,
        &wt,
        &bias,
        rows,
        d_in,
        d_out,
        true,
        Some((&gamma, &beta, 1e-5)),
        Some(&residual),
    );
    // γ, β folded into the weights, as the engine uploads them.
    let (wt, bias) = fold_layer_norm(&wt, &bias, &gamma, &beta);
    for kernel in LinearKernel::ALL {
        let got = Linear::with_kernel(ctx, kernel).run_fused(ctx, p, &x, &wt, &bias, &residual)?;
        checks.push(KernelCheck {
            name: match kernel {
                LinearKernel::Rowwise => "linear (norm, residual)",
                LinearKernel::Tiled => "linear_tiled (norm, residual)",
                LinearKernel::Blocked => "linear_blocked (norm, residual)",
            },
            values: got.len(),
            tolerance: loose,
            outcome: loose.check(&got, &want),
        });
    }

    // The residual chain as the engine runs it for a block's map: its map attention (each
    // agent row's 8 keys, some invalid, the queries in `att`), the output projection, the MLP
    // (2·D) and the next block's q, k, v in 3 parts.
    let (d, m) = (d_in, 2 * d_in);
    let keys = 8usize;
    let key_rows = b * a * keys;
    let (k, v) = (
        rng.uniform(key_rows * d, 1.0),
        rng.uniform(key_rows * d, 1.0),
    );
    let key_valid = rng.flags(key_rows, 0.8);
    let map_kv: Vec<f32> = k.iter().chain(&v).copied().collect();
    let agent_scene = vec![0u32; b * a];
    let tensors: Vec<Vec<f32>> = [d * d, d, m * d, m, d * m, d, 3 * d * d, 3 * d]
        .iter()
        .map(|&n| rng.uniform(n, 0.3))
        .collect();
    let (weights, chain) = packed_chain(&tensors, (rows, d, m, 3 * d));
    let p = ChainParams {
        next_out: (3 * d) as u32,
        part: d as u32,
        part_stride: (rows * d) as u32,
        anchor_slot: NO_FRAME,
        attend: 1,
        slots: w as u32,
        heads: heads as u32,
        head_dim: (d / heads) as u32,
        scale: 1.0 / ((d / heads) as f32).sqrt(),
        keys: keys as u32,
        k_off: 0,
        v_off: (key_rows * d) as u32,
        ..chain
    };
    let (queries, h) = (rng.uniform(rows * d, 1.0), rng.uniform(rows * d, 1.0));
    let inputs = ChainInputs {
        weights: &weights,
        att: &queries,
        h: &h,
        y: &vec![0.0; 3 * rows * d],
        x: &[0.0],
        sigma: &[0.0],
        valid: &[0.0],
    };
    let attend = AttendInputs {
        map_kv: &map_kv,
        key_valid: &key_valid,
        agent_scene: &agent_scene,
        pair_k: &[],
        pair_v: &[],
    };
    let chain_kernel = ResidualChain::new(ctx);
    // The wide tile too where this device holds it: its first run on a card is here.
    let wide_kernel = ChainTile::wide(
        d as u32,
        m as u32,
        ctx.device.limits().max_compute_workgroup_storage_size,
    )
    .map(|tile| ResidualChain::with_tile(ctx, tile))
    .transpose()?;
    let (h_got, y_got, _) = chain_kernel.run_full(ctx, p, &inputs, None, Some(attend))?;
    let by_agent = TokenLayout::contiguous(keys as u32);
    let map_attention = AttentionParams {
        groups: (b * a) as u32,
        heads: heads as u32,
        head_dim: (d / heads) as u32,
        queries: w as u32,
        keys: keys as u32,
        scale: p.scale,
        scene_agents: a as u32,
        scene_mode: SceneMode::None as u32,
        q_layout: TokenLayout::contiguous(w as u32),
        kv_layout: by_agent,
        mask_layout: by_agent,
    };
    let att = reference::attention(&map_attention, &queries, &k, &v, &key_valid, &agent_scene);
    let (h_want, next_want) = reference::residual_chain(
        &att,
        &h,
        rows,
        d,
        (&tensors[0], &tensors[1]),
        Some(((&tensors[2], &tensors[3]), (&tensors[4], &tensors[5]))),
        Some((&tensors[6], &tensors[7])),
        1e-5,
    );
    let y_want = into_parts(&next_want, rows, d);
    let got: Vec<f32> = h_got.into_iter().chain(y_got).collect();
    let want: Vec<f32> = h_want.into_iter().chain(y_want).collect();
    checks.push(KernelCheck {
        name: "residual_chain (map attention, output, MLP, next q/k/v)",
        values: got.len(),
        tolerance: loose,
        outcome: loose.check(&got, &want),
    });
    if let Some(wide) = &wide_kernel {
        let (h_got, y_got, _) = wide.run_full(ctx, p, &inputs, None, Some(attend))?;
        let got: Vec<f32> = h_got.into_iter().chain(y_got).collect();
        checks.push(KernelCheck {
            name: "residual_chain, wide tile (map attention, output, MLP, next q/k/v)",
            values: got.len(),
            tolerance: loose,
            outcome: loose.check(&got, &want),
        });
    }

    // The embedding chain: the token embedding (agent frame at slot 9, constant-velocity
    // reference) and block 0's q, k, v behind its norm, in 3 parts.
    let packed = rng.uniform(6 * d + w * d + 6 * d + d, 0.5);
    let (next_w, next_b) = (rng.uniform(3 * d * d, 0.3), rng.uniform(3 * d, 0.3));
    let (x, agent) = (rng.uniform(rows * 3, 2.0), rng.uniform(b * a * d, 1.0));
    let sigma: Vec<f32> = rng.uniform(b * w, 1.0).iter().map(|v| 1.05 + v).collect();
    let valid = rng.flags(rows, 0.9);
    let mut next_weights = transpose(&next_w, 3 * d);
    let next_bias_at = next_weights.len() as u32;
    next_weights.extend(&next_b);
    let p = ChainParams {
        rows: rows as u32,
        d: d as u32,
        eps: 1e-5,
        next_w: 0,
        next_b: next_bias_at,
        next_out: (3 * d) as u32,
        part: d as u32,
        part_stride: (rows * d) as u32,
        slots: w as u32,
        agents: a as u32,
        anchor_slot: 9,
        sigma_data: 0.5,
        heading_scale: 0.25,
        residual_scale: 40.0,
        relative_scale: 1.0,
        ..ChainParams::default()
    };
    let inputs = EmbedChainInputs {
        weights: &next_weights,
        embed: &packed,
        x: &x,
        sigma: &sigma,
        valid: &valid,
        agent: &agent,
    };
    let (h_got, y_got) = chain_kernel.run_embed(ctx, p, &inputs)?;
    let shape = reference::EmbedShape {
        agents: a,
        slots: w,
        hidden: d,
        sigma_data: 0.5,
        anchor_slot: Some(9),
        heading_scale: 0.25,
        relative_scale: 1.0,
        residual_scale: 40.0,
    };
    let h_want = reference::embed_tokens(&shape, &x, &sigma, &valid, &agent, &packed);
    let (ones, zeros) = (vec![1.0; d], vec![0.0; d]);
    let next_want = reference::linear_fused(
        &h_want,
        &next_w,
        &next_b,
        rows,
        d,
        3 * d,
        false,
        Some((&ones, &zeros, 1e-5)),
        None,
    );
    let y_want = into_parts(&next_want, rows, d);
    let got: Vec<f32> = h_got.into_iter().chain(y_got).collect();
    let want: Vec<f32> = h_want.into_iter().chain(y_want).collect();
    checks.push(KernelCheck {
        name: "embed_chain (token embedding, block 0's q/k/v)",
        values: got.len(),
        tolerance: loose,
        outcome: loose.check(&got, &want),
    });
    if let Some(wide) = &wide_kernel {
        let (h_got, y_got) = wide.run_embed(ctx, p, &inputs)?;
        let got: Vec<f32> = h_got.into_iter().chain(y_got).collect();
        checks.push(KernelCheck {
            name: "embed_chain, wide tile (token embedding, block 0's q/k/v)",
            values: got.len(),
            tolerance: loose,
            outcome: loose.check(&got, &want),
        });
    }
    let head_name = "residual_chain (head, preconditioning, sampler step)";
    checks.push(head_chain_check(
        ctx,
        (&chain_kernel, head_name),
        &mut rng,
        &tensors[..6],
        (d, m),
        loose,
    )?);
    if let Some(wide) = &wide_kernel {
        let name = "residual_chain, wide tile (head, preconditioning, sampler step)";
        checks.push(head_chain_check(
            ctx,
            (wide, name),
            &mut rng,
            &tensors[..6],
            (d, m),
            loose,
        )?);
    }
    checks.push(agents_chain_check(
        ctx,
        &mut rng,
        (b, a, w, d, heads),
        loose,
    )?);

    // The polyline encoder over 3 scenes' 32 polylines of 20 points.
    let (n, q) = (3 * 32, 20);
    let (points, embed, mix_w, mix_b, gamma, beta) = (
        rng.uniform(n * q * 2, 2.0),
        rng.uniform(3 * d + q * d, 0.5),
        rng.uniform(d * d, 0.2),
        rng.uniform(d, 0.1),
        rng.uniform(d, 1.0),
        rng.uniform(d, 0.5),
    );
    let p = PolylineParams {
        polylines: n as u32,
        points: q as u32,
        hidden: d as u32,
        eps: 1e-5,
    };
    // Both variants, whichever the engine uses here.
    let want = reference::encode_polylines(
        &points,
        &embed,
        &mix_w,
        &mix_b,
        &gamma,
        &beta,
        (n, q, d),
        1e-5,
    );
    for kernel in PolylineKernel::ALL {
        let got = PolylineEncoder::new(ctx, kernel)
            .run(ctx, p, &points, &embed, &mix_w, &mix_b, &gamma, &beta)?;
        checks.push(KernelCheck {
            name: kernel.entry(),
            values: got.len(),
            tolerance: loose,
            outcome: loose.check(&got, &want),
        });
    }

    // attention, agents layout (groups (scene, slot), tokens agents), random masks.
    let (q, k, v) = (
        rng.uniform(tokens * d, 1.0),
        rng.uniform(tokens * d, 1.0),
        rng.uniform(tokens * d, 1.0),
    );
    let valid = rng.flags(tokens, 0.8);
    let agents = TokenLayout {
        inner_count: w as u32,
        outer_stride: (a * w) as u32,
        inner_stride: 1,
        token_stride: w as u32,
    };
    let head_dim = d / heads;
    let p = AttentionParams {
        groups: (b * w) as u32,
        heads: heads as u32,
        head_dim: head_dim as u32,
        queries: a as u32,
        keys: a as u32,
        scale: 1.0 / (head_dim as f32).sqrt(),
        scene_agents: a as u32,
        scene_mode: SceneMode::AgentsOfOneScene as u32,
        q_layout: agents,
        kv_layout: agents,
        mask_layout: agents,
    };
    // Each scene's agents as two packed scenes (even and odd rows), attending apart.
    let two_per_scene: Vec<u32> = (0..b * a).map(|r| (2 * (r / a) + r % 2) as u32).collect();
    let got = Attention::new(ctx).run(ctx, p, &q, &k, &v, &valid, &two_per_scene)?;
    let want = reference::attention(&p, &q, &k, &v, &valid, &two_per_scene);
    checks.push(KernelCheck {
        name: "attention",
        values: got.len(),
        tolerance: loose,
        outcome: loose.check(&got, &want),
    });

    // pair_attention (agent pairs) on the same tokens, with scene states.
    let states = rng.uniform(tokens * 3, 1.5);
    let f = road_model::agent_pairs::PAIR_FEATURES;
    let (pair_k, pair_v) = (rng.uniform(d * f, 0.5), rng.uniform(d * f, 0.5));
    let p = PairAttentionParams {
        groups: (b * w) as u32,
        heads: heads as u32,
        head_dim: head_dim as u32,
        agents: a as u32,
        slots: w as u32,
        anchor_slot: 9,
        scale: 1.0 / (head_dim as f32).sqrt(),
        heading_scale: 0.25,
        direction: 0.25,
        near: 0.125,
        far: 0.5,
        _pad: 0,
    };
    // Each scene's agents as two packed scenes (even and odd rows), attending apart.
    let agent_scene: Vec<u32> = (0..b * a).map(|r| (2 * (r / a) + r % 2) as u32).collect();
    let got = PairAttention::new(ctx).run(
        ctx,
        p,
        &q,
        &k,
        &v,
        &valid,
        &states,
        &pair_k,
        &pair_v,
        &agent_scene,
    )?;
    let want = reference::pair_attention(
        &p,
        &q,
        &k,
        &v,
        &valid,
        &states,
        &pair_k,
        &pair_v,
        &agent_scene,
    );
    checks.push(KernelCheck {
        name: "pair_attention",
        values: got.len(),
        tolerance: loose,
        outcome: loose.check(&got, &want),
    });

    // pick_agent_maps: 12 of 32 polylines of 20 points per agent.
    let (polylines, points, picked) = (32usize, 20usize, 12usize);
    let map = rng.uniform(b * polylines * points * 2, 1.0);
    let map_valid: Vec<f32> = (0..b * polylines)
        .map(|i| {
            if i % polylines < polylines - 5 {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let p = AgentMapParams {
        rows: (b * a) as u32,
        agents: a as u32,
        slots: w as u32,
        anchor_slot: 9,
        polylines: polylines as u32,
        points: points as u32,
        picked: picked as u32,
        heading_scale: 0.25,
    };
    // Every agent row picks from the map of the scene mirrored to its own (b − 1 − its), as
    // a packed batch's rows pick from their own scenes' maps: the reference on the maps in
    // that order.
    let agent_scene: Vec<u32> = (0..b * a).map(|r| (b - 1 - r / a) as u32).collect();
    let (got_points, got_flags) =
        AgentMap::new(ctx).run(ctx, p, &states, &valid, &map, &map_valid, &agent_scene)?;
    let anchors = road_model::agent_map::anchors_of(&states, &valid, w, 9, 0.25);
    let mirrored = |values: &[f32]| -> Vec<f32> {
        let per_scene = values.len() / b;
        values.chunks(per_scene).rev().flatten().copied().collect()
    };
    let (want_points, want_flags) = road_model::agent_map::agent_maps(
        &anchors,
        a,
        &mirrored(&map),
        &mirrored(&map_valid),
        points,
        picked,
    );
    let mut got = got_points;
    got.extend(got_flags);
    let mut want = want_points;
    want.extend(want_flags);
    checks.push(KernelCheck {
        name: "pick_agent_maps",
        values: got.len(),
        tolerance: loose,
        outcome: loose.check(&got, &want),
    });

    // Compact sub-batch rows: 96 of 200 rows of two regions (96 and 20 floats a row) gathered
    // in one dispatch (some mapped to none), then scattered back over the batch. Copies: exact.
    let batch_rows = 200usize;
    let floats = [96usize, 20];
    let batch = floats.map(|f| rng.uniform(batch_rows * f, 2.0));
    let row_map: Vec<u32> = (0..96u32)
        .map(|r| {
            if r % 7 == 6 {
                NONE
            } else {
                (r * 37 + 11) % 200
            }
        })
        .collect();
    let kernel = CompactRows::new(ctx);
    let empty = floats.map(|f| vec![0.0; row_map.len() * f]);
    let sub = kernel.run(
        ctx,
        false,
        &row_map,
        &[
            (&batch[0], &empty[0], floats[0]),
            (&batch[1], &empty[1], floats[1]),
        ],
    )?;
    let back = kernel.run(
        ctx,
        true,
        &row_map,
        &[
            (&sub[0], &batch[0], floats[0]),
            (&sub[1], &batch[1], floats[1]),
        ],
    )?;
    let got: Vec<f32> = sub.into_iter().chain(back).flatten().collect();
    let gathered = [0, 1].map(|k| gather_rows_reference(&batch[k], &row_map, floats[k]));
    let scattered =
        [0, 1].map(|k| scatter_rows_reference(&gathered[k], &row_map, &batch[k], floats[k]));
    let want: Vec<f32> = gathered.into_iter().chain(scattered).flatten().collect();
    let exact = Tolerance { rel: 0.0, abs: 0.0 };
    checks.push(KernelCheck {
        name: "compact_rows",
        values: got.len(),
        tolerance: exact,
        outcome: exact.check(&got, &want),
    });

    // edm preconditioning of 1 001 noise levels.
    let (sigma_min, sigma_max, sigma_data) = (0.002f64, 80.0f64, 0.5f64);
    let sigma: Vec<f32> = (0..=1000)
        .map(|i| {
            let u = f64::from(i) / 1000.0;
            let r = 1.0 / 7.0;
            (sigma_min.powf(r) + u * (sigma_max.powf(r) - sigma_min.powf(r))).powi(7) as f32
        })
        .collect();
    let got = crate::kernels::edm::EdmPrecondition::new(ctx).run(
        ctx,
        &sigma,
        sigma_data as f32,
        sigma_min as f32,
    )?;
    let got: Vec<f32> = got.iter().flatten().copied().collect();
    let want: Vec<f32> = sigma
        .iter()
        .flat_map(|&s| {
            let s = f64::from(s);
            let denom = s * s + sigma_data * sigma_data;
            [
                (sigma_data * sigma_data / denom) as f32,
                (s * sigma_data / denom.sqrt()) as f32,
                (1.0 / denom.sqrt()) as f32,
                (s.max(sigma_min).ln() / 4.0) as f32,
            ]
        })
        .collect();
    checks.push(KernelCheck {
        name: "edm.precondition",
        values: got.len(),
        tolerance: tol,
        outcome: tol.check(&got, &want),
    });

    checks.extend(window_checks(ctx, &mut rng, b, a, w)?);
    Ok(checks)
}

/// A chain's 8 tensors (`W_o`, `b_o`, `W_1`, `b_1`, `W_2`, `b_2`, `W_next`, `b_next`, each
/// `[out, in]`) packed as the engine uploads them (weights transposed, biases as they are),
/// and the params of `(rows, D, M, next outputs)` pointing at them.
/// A q, k, v layer's outputs `[rows, 3D]` as the chain writes them: parts q, k, v `[rows, D]`
/// each, in that order.
fn into_parts(outputs: &[f32], rows: usize, d: usize) -> Vec<f32> {
    (0..3 * rows * d)
        .map(|i| {
            let (part, row, column) = (i / (rows * d), i % (rows * d) / d, i % d);
            outputs[row * 3 * d + part * d + column]
        })
        .collect()
}

fn packed_chain(
    tensors: &[Vec<f32>],
    (rows, d, m, next_out): (usize, usize, usize, usize),
) -> (Vec<f32>, ChainParams) {
    let mut weights = Vec::new();
    let outputs = [d, 1, m, 1, d, 1, next_out, 1];
    let offsets: Vec<u32> = tensors
        .iter()
        .zip(outputs)
        .map(|(t, out)| {
            let at = weights.len() as u32;
            weights.extend(transpose(t, out));
            at
        })
        .collect();
    let params = ChainParams {
        rows: rows as u32,
        d: d as u32,
        m: m as u32,
        eps: 1e-5,
        o_w: offsets[0],
        o_b: offsets[1],
        w1: offsets[2],
        b1: offsets[3],
        w2: offsets[4],
        b2: offsets[5],
        next_w: offsets[6],
        next_b: offsets[7],
        ..ChainParams::default()
    };
    (weights, params)
}

/// The chain after agent attention as the engine runs it: agent attention with the pair
/// features over the agents of each scene at each slot (scene 1's agents in two packed scenes,
/// some slots invalid), then the output projection and the map's q.
fn agents_chain_check(
    ctx: &GpuContext,
    rng: &mut Inputs,
    (b, a, w, d, heads): (usize, usize, usize, usize, usize),
    tolerance: Tolerance,
) -> Result<KernelCheck> {
    let rows = b * a * w;
    let tensors: Vec<Vec<f32>> = [d * d, d, d * d, d]
        .iter()
        .map(|&n| rng.uniform(n, 0.3))
        .collect();
    let mut weights = Vec::new();
    let mut offsets = Vec::new();
    for (t, out) in tensors.iter().zip([d, 1, d, 1]) {
        offsets.push(weights.len() as u32);
        weights.extend(transpose(t, out));
    }
    let (q, k, v) = (
        rng.uniform(rows * d, 1.0),
        rng.uniform(rows * d, 1.0),
        rng.uniform(rows * d, 1.0),
    );
    let states = rng.uniform(rows * 3, 2.0);
    let valid = rng.flags(rows, 0.9);
    let (pair_k, pair_v) = (rng.uniform(d * 6, 0.3), rng.uniform(d * 6, 0.3));
    let agent_scene: Vec<u32> = (0..b * a)
        .map(|row| {
            let (scene, agent) = (row / a, row % a);
            (2 * scene + usize::from(scene == 1 && agent >= a / 2)) as u32
        })
        .collect();
    let head_dim = d / heads;
    let pairs = PairAttentionParams {
        groups: (b * w) as u32,
        heads: heads as u32,
        head_dim: head_dim as u32,
        agents: a as u32,
        slots: w as u32,
        anchor_slot: 9,
        scale: 1.0 / (head_dim as f32).sqrt(),
        heading_scale: 0.25,
        direction: 2.5,
        near: 1.25,
        far: 5.0,
        _pad: 0,
    };
    let p = ChainParams {
        rows: rows as u32,
        d: d as u32,
        eps: 1e-5,
        o_w: offsets[0],
        o_b: offsets[1],
        next_w: offsets[2],
        next_b: offsets[3],
        next_out: d as u32,
        part: d as u32,
        part_stride: (rows * d) as u32,
        attend: 1,
        slots: w as u32,
        agents: a as u32,
        heads: heads as u32,
        head_dim: head_dim as u32,
        scale: pairs.scale,
        keys: a as u32,
        key_mode: 2,
        k_off: 0,
        v_off: (rows * d) as u32,
        anchor_slot: pairs.anchor_slot,
        pairs: 1,
        heading_scale: pairs.heading_scale,
        direction: pairs.direction,
        near: pairs.near,
        far: pairs.far,
        ..ChainParams::default()
    };
    let h = rng.uniform(rows * d, 1.0);
    let map_kv: Vec<f32> = k.iter().chain(&v).copied().collect();
    let inputs = ChainInputs {
        weights: &weights,
        att: &q,
        h: &h,
        y: &vec![0.0; rows * d],
        x: &states,
        sigma: &[0.0],
        valid: &[0.0],
    };
    let attend = AttendInputs {
        map_kv: &map_kv,
        key_valid: &valid,
        agent_scene: &agent_scene,
        pair_k: &pair_k,
        pair_v: &pair_v,
    };
    let (h_got, y_got, _) =
        ResidualChain::new(ctx).run_full(ctx, p, &inputs, None, Some(attend))?;
    let att = reference::pair_attention(
        &pairs,
        &q,
        &k,
        &v,
        &valid,
        &states,
        &pair_k,
        &pair_v,
        &agent_scene,
    );
    let (h_want, y_want) = reference::residual_chain(
        &att,
        &h,
        rows,
        d,
        (&tensors[0], &tensors[1]),
        None,
        Some((&tensors[2], &tensors[3])),
        1e-5,
    );
    let got: Vec<f32> = h_got.into_iter().chain(y_got).collect();
    let want: Vec<f32> = h_want.into_iter().chain(y_want).collect();
    Ok(KernelCheck {
        name: "residual_chain (agent attention with pair features, output, map q)",
        values: got.len(),
        tolerance,
        outcome: tolerance.check(&got, &want),
    })
}

/// The last block's chain as a Heun or multistep step's first evaluation runs it: output
/// projection and MLP (the weights `block`), the head with the output preconditioning (agent
/// frame, constant-velocity reference), then the sampler's Euler step with the multistep
/// correction: D against the references, x_e against `road_rollout::heun` from the kernel's D.
fn head_chain_check(
    ctx: &GpuContext,
    (kernel, name): (&ResidualChain, &'static str),
    rng: &mut Inputs,
    block: &[Vec<f32>],
    (d, m): (usize, usize),
    loose: Tolerance,
) -> Result<KernelCheck> {
    let (scenes, agents, slots) = (2, 3, 5);
    let rows = scenes * agents * slots;
    let head = (rng.uniform(3 * d, 0.3), rng.uniform(3, 0.3));
    let tensors: Vec<Vec<f32>> = block
        .iter()
        .cloned()
        .chain([head.0.clone(), head.1.clone()])
        .collect();
    let (weights, chain) = packed_chain(&tensors, (rows, d, m, 3));
    let p = ChainParams {
        next_out: 3,
        part: 3,
        part_stride: (rows * 3) as u32,
        precondition: 1,
        slots: slots as u32,
        agents: agents as u32,
        anchor_slot: 2,
        sigma_data: 0.5,
        heading_scale: 2.0,
        residual_scale: 4.0,
        update: 1,
        ..chain
    };
    let (att, h, x) = (
        rng.uniform(rows * d, 1.0),
        rng.uniform(rows * d, 1.0),
        rng.uniform(rows * 3, 3.0),
    );
    let sigma: Vec<f32> = rng
        .uniform(scenes * slots, 1.0)
        .iter()
        .map(|v| 1.5 + v)
        .collect();
    // Unchanged slots, one landing on 0, the rest stepping down; γ 0 in some.
    let sigma_next: Vec<f32> = sigma
        .iter()
        .enumerate()
        .map(|(i, &s)| [s, 0.0, 0.6 * s][i % 3])
        .collect();
    let gamma: Vec<f32> = rng
        .uniform(scenes * slots, 1.0)
        .iter()
        .enumerate()
        .map(|(i, &g)| if i % 4 == 0 { 0.0 } else { g })
        .collect();
    let previous = rng.uniform(rows * 3, 2.0);
    let valid = rng.flags(rows, 0.9);
    let inputs = ChainInputs {
        weights: &weights,
        att: &att,
        h: &h,
        y: &vec![0.0; rows * 3],
        x: &x,
        sigma: &sigma,
        valid: &valid,
    };
    let update = crate::kernels::residual_chain::UpdateInputs {
        sigma_next: &sigma_next,
        previous: &previous,
        gamma: &gamma,
    };
    let (h_got, d_got, x_e_got) = kernel.run_with_update(ctx, p, &inputs, Some(update))?;
    let (h_want, f) = reference::residual_chain(
        &att,
        &h,
        rows,
        d,
        (&block[0], &block[1]),
        Some(((&block[2], &block[3]), (&block[4], &block[5]))),
        Some((&head.0, &head.1)),
        1e-5,
    );
    let shape = reference::PreconditionShape {
        slots,
        agents,
        anchor_slot: Some(2),
        sigma_data: 0.5,
        heading_scale: 2.0,
        residual_scale: 4.0,
    };
    let d_want = reference::precondition_output(&x, &f, &sigma, &valid, shape);
    let x_e_want = reference::multistep_step(
        &x,
        &d_got,
        &previous,
        &sigma,
        &sigma_next,
        &gamma,
        agents,
        slots,
    )
    .map_err(crate::Error::Input)?;
    let got: Vec<f32> = h_got.into_iter().chain(d_got).chain(x_e_got).collect();
    let want: Vec<f32> = h_want.into_iter().chain(d_want).chain(x_e_want).collect();
    Ok(KernelCheck {
        name,
        values: got.len(),
        tolerance: loose,
        outcome: loose.check(&got, &want),
    })
}

/// The window kernels on `b` scenes of `a` agents and `w` slots: the emitted-slot gather (one
/// scene not read) and the shift after an emission (every scene but the last, with fewer real
/// agents than the padded count, the first agent's plan turned, as a lane-guard steer does).
fn window_checks(
    ctx: &GpuContext,
    rng: &mut Inputs,
    b: usize,
    a: usize,
    w: usize,
) -> Result<Vec<KernelCheck>> {
    use crate::kernels::window::{ShiftList, WindowOps};
    use road_rollout::{NO_TURN, ShiftEdit, ShiftShape, window_emitted, window_shift};
    let tol = Tolerance::F32;
    let x = rng.uniform(b * a * w * 3, 3.0);
    let buffer = crate::kernels::storage_buffer(ctx, "selftest window", (x.len() * 4) as u64);
    ctx.queue.write_buffer(&buffer, 0, bytemuck::cast_slice(&x));
    let mut ops = WindowOps::new(ctx, &buffer, b, a, w);
    let slots: Vec<Option<usize>> = (0..b)
        .map(|i| (i + 1 < b).then_some((7 * i + 3) % w))
        .collect();
    let mut got = vec![0.0f32; b * a * 3];
    ops.emitted(ctx, &slots, &mut got)?;
    let mut want = vec![0.0f32; b * a * 3];
    window_emitted(&x, a, w, &slots, &mut want);
    let mut checks = vec![KernelCheck {
        name: "window_emitted",
        values: got.len(),
        tolerance: tol,
        outcome: tol.check(&got, &want),
    }];
    let shape = ShiftShape {
        observed: w / 2,
        obs_noise: 0.002,
        sigma_max: 80.0,
    };
    let real = a - 2;
    // Per shifted scene: emitted [real, 3], noise [real, 6], turns [real, 4].
    let edits: Vec<[Vec<f32>; 3]> = (0..b - 1)
        .map(|_| {
            let mut turns = rng.uniform(real * 4, 1.0);
            for agent in 1..real {
                turns[4 * agent..4 * agent + 4].copy_from_slice(&NO_TURN);
            }
            [
                rng.uniform(real * 3, 2.0),
                rng.uniform(real * 6, 2.0),
                turns,
            ]
        })
        .collect();
    let list: Vec<ShiftList<'_>> = edits
        .iter()
        .enumerate()
        .map(|(i, [e, z, t])| (i, e.as_slice(), z.as_slice(), t.as_slice()))
        .collect();
    ops.shift(ctx, &buffer, &list, shape)?;
    let bytes = crate::kernels::read_back(ctx, &buffer, (x.len() * 4) as u64)?;
    let got: Vec<f32> = bytemuck::cast_slice(&bytes).to_vec();
    let mut want = x;
    let valid = vec![1.0f32; a * w];
    for (i, [e, z, t]) in edits.iter().enumerate() {
        let edit = ShiftEdit {
            scene: i,
            emitted: e,
            noise: z,
            valid: &valid,
            turns: t,
        };
        window_shift(&mut want[i * a * w * 3..][..a * w * 3], w, &edit, shape);
    }
    checks.push(KernelCheck {
        name: "window_shift",
        values: got.len(),
        tolerance: tol,
        outcome: tol.check(&got, &want),
    });
    Ok(checks)
}

/// The f16 linear kernels on `ctx` (opened with [`crate::Precision::F16`]): `linear_f16`, and
/// `linear_coop` (or `linear_coop8`) where the adapter offers cooperative matrices, on the engine's f16 layers
/// (the MLP's first layer behind its norm, with ReLU; its second with the residual add;
/// the q/k/v projection in 3 parts, as one layer here). Fed raw rows, each against the layer
/// with its inputs and weights rounded to f16 (f32 sums: [`Tolerance`]'s 10⁻⁴); behind the
/// norm, against the unrounded layer within f16's proven bound (the largest of
/// [`reference::LinearF16Reference::bound`] over the outputs).
pub fn f16_kernel_checks(ctx: &GpuContext) -> Result<Vec<KernelCheck>> {
    use crate::kernels::linear_f16::{LinearF16, LinearF16Kernel};
    let mut kernels = vec![LinearF16::new(ctx, LinearF16Kernel::Rowwise)?];
    if let Some(c) = ctx.cooperative() {
        kernels.push(LinearF16::new(ctx, LinearF16Kernel::Coop(c))?);
    }
    let mut rng = Inputs(0xF16_5EED);
    let tokens = 3 * 12 * 20;
    let mut checks = Vec::new();
    // ([name under linear_f16, under linear_coop], in, out, relu, norm, residual)
    for (names, d_in, d_out, relu, norm, residual) in [
        (
            [
                "linear_f16 mlp_in (norm, relu)",
                "cooperative mlp_in (norm, relu)",
            ],
            96usize,
            384usize,
            true,
            true,
            false,
        ),
        (
            [
                "linear_f16 mlp_out (residual)",
                "cooperative mlp_out (residual)",
            ],
            384,
            96,
            false,
            false,
            true,
        ),
        (
            ["linear_f16 qkv (raw rows)", "cooperative qkv (raw rows)"],
            96,
            288,
            false,
            false,
            false,
        ),
    ] {
        let x = rng.uniform(tokens * d_in, 1.5);
        let w = rng.uniform(d_out * d_in, 0.2);
        let b = rng.uniform(d_out, 0.1);
        let y0 = rng.uniform(tokens * d_out, 1.0);
        let p = LinearParams {
            relu: u32::from(relu),
            residual: u32::from(residual),
            norm: u32::from(norm),
            eps: 1e-5,
            ..LinearParams::new(tokens, d_in, d_out)
        };
        let want = reference::linear_f16(
            &x,
            &w,
            &b,
            tokens,
            d_in,
            d_out,
            relu,
            norm.then_some(1e-5),
            residual.then_some(&y0[..]),
        );
        let (expected, tolerance) = if norm {
            let bound = want.bound.iter().copied().fold(0.0f32, f32::max);
            (
                want.exact,
                Tolerance {
                    rel: 1e-5,
                    abs: bound + 1e-5,
                },
            )
        } else {
            (
                want.rounded,
                Tolerance {
                    rel: 1e-4,
                    abs: 1e-7 * d_in as f32 + 1e-6,
                },
            )
        };
        for kernel in &kernels {
            let got = kernel.run_fused(ctx, p, &x, &w, &b, &y0)?;
            checks.push(KernelCheck {
                name: match kernel.kernel {
                    LinearF16Kernel::Rowwise => names[0],
                    LinearF16Kernel::Coop(_) => names[1],
                },
                values: got.len(),
                tolerance,
                outcome: tolerance.check(&got, &expected),
            });
        }
    }
    Ok(checks)
}
