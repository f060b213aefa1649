//! Kernels against their CPU references on the adapter present (lavapipe in CI).

use rand::{Rng, SeedableRng};
use road_gpu::kernels::edm::EdmPrecondition;
use road_gpu::{ContextOptions, GpuContext, Tolerance};
use road_sched::EdmSchedule;

/// The test adapter: validation on, `WGPU_BACKEND` / `WGPU_ADAPTER_NAME` honoured, software
/// adapters accepted. No adapter is a failure, not a skip: CI installs lavapipe.
fn context() -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

#[test]
fn edm_preconditioning_matches_the_cpu_reference() {
    let ctx = context();
    eprintln!("adapter: {}", ctx.describe());
    let kernel = EdmPrecondition::new(&ctx);
    let edm = EdmSchedule::default();
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    for count in [1usize, 63, 64, 65, 1000, 4099] {
        // σ over the whole schedule, plus clean slots (σ = 0).
        let sigma: Vec<f32> = (0..count)
            .map(|i| {
                if i % 17 == 3 {
                    0.0
                } else {
                    edm.sigma(rng.random_range(0.0..=1.0)) as f32
                }
            })
            .collect();
        let got = kernel
            .run(&ctx, &sigma, edm.sigma_data as f32, edm.sigma_min as f32)
            .unwrap();
        assert_eq!(got.len(), count);
        let mut expected = Vec::with_capacity(count * 4);
        for &s in &sigma {
            let p = edm.preconditioning(f64::from(s));
            let c_noise = f64::from(s).max(edm.sigma_min).ln() / 4.0;
            expected.extend([
                p.c_skip as f32,
                p.c_out as f32,
                p.c_in as f32,
                c_noise as f32,
            ]);
        }
        let actual: Vec<f32> = got.iter().flatten().copied().collect();
        if let Err(m) = Tolerance::F32.check(&actual, &expected) {
            panic!("count {count}: {m} (σ = {})", sigma[m.index / 4]);
        }
    }
}

fn random(rng: &mut rand::rngs::StdRng, n: usize, scale: f32) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-scale..scale)).collect()
}

#[test]
fn linear_matches_the_cpu_reference_on_random_shapes() {
    use road_gpu::kernels::linear::{Linear, LinearKernel};
    let ctx = context();
    // Every variant, whichever this adapter would pick: a lent GPU runs the blocked and tiled
    // ones.
    for variant in LinearKernel::ALL {
        let kernel = Linear::with_kernel(&ctx, variant);
        linear_matches_on_random_shapes(&ctx, &kernel);
    }
}

fn linear_matches_on_random_shapes(ctx: &GpuContext, kernel: &road_gpu::kernels::linear::Linear) {
    use road_gpu::kernels::linear::LinearParams;
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    // Shapes around the tiled kernel's tile edges (64 rows, 32 outputs, 16 inputs per chunk),
    // the blocked kernel's (128 rows, 96 outputs, 16 inputs per chunk) as well as the model's
    // (96 → 192 → 96, 3 → 96, 96 → 3).
    for (rows, in_dim, out_dim, relu) in [
        (1, 1, 1, false),
        (7, 3, 64, false),
        (130, 64, 64, true),
        (33, 64, 3, false),
        (5, 6, 17, true),
        (300, 128, 64, false),
        (64, 16, 32, false),
        (65, 17, 33, true),
        (200, 96, 192, true),
        (129, 192, 96, false),
        (70, 3, 96, false),
        (63, 96, 3, false),
        (257, 96, 288, true),
        (129, 40, 97, false),
        (384, 384, 96, false),
    ] {
        let x = random(&mut rng, rows * in_dim, 2.0);
        let w = random(&mut rng, out_dim * in_dim, 0.5);
        let b = random(&mut rng, out_dim, 0.5);
        let p = LinearParams {
            relu: u32::from(relu),
            ..LinearParams::new(rows, in_dim, out_dim)
        };
        let got = kernel.run(ctx, p, &x, &w, &b).unwrap();
        let want = road_gpu::reference::linear(&x, &w, &b, rows, in_dim, out_dim, relu);
        // A sum of in_dim products of O(1) terms in another order: its rounding grows with
        // in_dim, which outputs near 0 show.
        let tol = Tolerance {
            abs: Tolerance::F32.abs.max(1e-7 * in_dim as f32),
            ..Tolerance::F32
        };
        if let Err(m) = tol.check(&got, &want) {
            panic!(
                "{:?} linear {rows}×{in_dim}→{out_dim} relu {relu}: {m}",
                kernel.kernel
            );
        }
    }
}

/// One fused linear layer's random case: rows offset from zero (the norm's shift matters),
/// weights, biases, a layer norm's γ and β, parts 8 floats apart beyond their `rows · part` (the
/// gaps must keep their values), `y`'s initial contents and the residual they hold in
/// `[rows, out]` order.
struct FusedCase {
    x: Vec<f32>,
    w: Vec<f32>,
    b: Vec<f32>,
    gamma: Vec<f32>,
    beta: Vec<f32>,
    p: road_gpu::kernels::linear::LinearParams,
    y0: Vec<f32>,
    residual_in: Vec<f32>,
}

impl FusedCase {
    /// `(rows, in, out, part, relu, norm, residual)`.
    fn new(
        rng: &mut rand::rngs::StdRng,
        (rows, in_dim, out_dim, part, relu, norm, residual): (
            usize,
            usize,
            usize,
            usize,
            bool,
            bool,
            bool,
        ),
    ) -> Self {
        use road_gpu::kernels::linear::LinearParams;
        let x: Vec<f32> = random(rng, rows * in_dim, 2.0)
            .iter()
            .map(|v| v + 0.7)
            .collect();
        let w = random(rng, out_dim * in_dim, 0.5);
        let b = random(rng, out_dim, 0.5);
        let gamma = random(rng, in_dim, 1.0);
        let beta = random(rng, in_dim, 1.0);
        let p = LinearParams {
            relu: u32::from(relu),
            residual: u32::from(residual),
            norm: u32::from(norm),
            eps: 1e-5,
            part: part as u32,
            part_stride: (rows * part + 8) as u32,
            ..LinearParams::new(rows, in_dim, out_dim)
        };
        let y0 = random(rng, p.y_len(), 1.0);
        let mut case = Self {
            x,
            w,
            b,
            gamma,
            beta,
            p,
            y0,
            residual_in: Vec::new(),
        };
        case.residual_in = case.gather(&case.y0);
        case
    }

    /// Index of output `(r, o)` in `y`'s parts.
    fn at(&self, r: usize, o: usize) -> usize {
        let (part, stride) = (self.p.part as usize, self.p.part_stride as usize);
        (o / part) * stride + r * part + o % part
    }

    /// `y`'s outputs in `[rows, out]` order.
    fn gather(&self, y: &[f32]) -> Vec<f32> {
        let out = self.p.out_dim as usize;
        (0..self.p.rows as usize * out)
            .map(|i| y[self.at(i / out, i % out)])
            .collect()
    }

    /// Panics unless every gap between `y`'s parts kept its value.
    fn check_gaps(&self, y: &[f32], shape: &str) {
        let (rows, part, stride) = (
            self.p.rows as usize,
            self.p.part as usize,
            self.p.part_stride as usize,
        );
        let parts = (self.p.out_dim as usize).div_ceil(part);
        for j in 0..parts.saturating_sub(1) {
            let gap = j * stride + rows * part..(j + 1) * stride;
            assert_eq!(
                y[gap.clone()],
                self.y0[gap],
                "{shape}: the gap after part {j}"
            );
        }
    }
}

/// The fusions the engine runs (`linear.wgsl`'s prologue and epilogue, and outputs split into
/// parts), each variant against [`road_gpu::reference::linear_fused`]: the layer norm of the
/// rows first (γ, β folded into the weights as the engine folds them), ReLU, the residual
/// added into what `y` held; parts at an aligned stride with the gaps between them untouched.
#[test]
fn fused_linear_matches_the_cpu_reference_on_random_shapes() {
    use road_gpu::kernels::linear::{Linear, LinearKernel, fold_layer_norm};
    let ctx = context();
    let mut rng = rand::rngs::StdRng::seed_from_u64(13);
    // (rows, in, out, part, relu, norm, residual): the engine's q/k/v (3 parts), map k/v
    // (2 parts), MLP (norm + ReLU, then residual), output projections and head, and tile edges.
    for shape in [
        (1, 2, 3, 3, false, true, false),
        (130, 64, 192, 64, false, true, false),
        (65, 32, 64, 32, false, false, false),
        (200, 96, 384, 384, true, true, false),
        (129, 384, 96, 96, false, false, true),
        (63, 96, 3, 3, false, true, false),
        (70, 17, 33, 11, true, true, true),
        (300, 128, 128, 128, false, true, true),
        (257, 96, 288, 96, false, true, false),
        (140, 96, 192, 192, true, true, false),
    ] {
        let (rows, in_dim, out_dim, part, relu, norm, residual) = shape;
        let case = FusedCase::new(&mut rng, shape);
        let want = road_gpu::reference::linear_fused(
            &case.x,
            &case.w,
            &case.b,
            rows,
            in_dim,
            out_dim,
            relu,
            norm.then_some((&case.gamma[..], &case.beta[..], 1e-5)),
            residual.then_some(&case.residual_in[..]),
        );
        // Outputs near 0 come from differences of O(1) terms: the absolute part covers them.
        let tol = Tolerance {
            rel: 1e-4,
            abs: 1e-5,
        };
        let (w, b) = if norm {
            fold_layer_norm(&case.w, &case.b, &case.gamma, &case.beta)
        } else {
            (case.w.clone(), case.b.clone())
        };
        for variant in LinearKernel::ALL {
            let kernel = Linear::with_kernel(&ctx, variant);
            let y = kernel
                .run_fused(&ctx, case.p, &case.x, &w, &b, &case.y0)
                .unwrap();
            let shape = format!(
                "{variant:?} {rows}×{in_dim}→{out_dim} in parts of {part}, relu {relu}, \
                 norm {norm}, residual {residual}"
            );
            if let Err(m) = tol.check(&case.gather(&y), &want) {
                panic!("{shape}: {m}");
            }
            case.check_gaps(&y, &shape);
        }
    }
}

/// The f16 linear kernels (`linear_f16` here; `linear_coop` too where the adapter offers
/// cooperative matrices) with every fusion, against [`road_gpu::reference::linear_f16`]: within
/// f32 rounding of the same layer with its inputs and weights rounded to f16 (the rows fed raw,
/// where the rounding is exactly defined), and within the proven bound of f16's error of the
/// unrounded layer (every shape, the standardised rows too). CI's lavapipe offers `SHADER_F16`:
/// an adapter without it fails here, as one without Vulkan does.
#[test]
fn f16_linear_matches_its_reference_on_random_shapes() {
    use road_gpu::kernels::linear::fold_layer_norm;
    use road_gpu::kernels::linear_f16::{LinearF16, LinearF16Kernel, fits};
    let ctx = GpuContext::new(&ContextOptions {
        validation: true,
        precision: road_gpu::Precision::F16,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("the f16 tests need an adapter with SHADER_F16: {e}"));
    let mut kernels = vec![LinearF16::new(&ctx, LinearF16Kernel::Rowwise).unwrap()];
    if let Some(c) = ctx.cooperative() {
        kernels.push(LinearF16::new(&ctx, LinearF16Kernel::Coop(c)).unwrap());
    }
    eprintln!(
        "adapter: {}; f16 kernels: {:?}",
        ctx.describe(),
        kernels.iter().map(|k| k.kernel).collect::<Vec<_>>()
    );
    let mut rng = rand::rngs::StdRng::seed_from_u64(17);
    // (rows, in, out, part, relu, norm, residual): the engine's f16 layers (q/k/v in 3 parts,
    // map k/v, the MLP, output projections), the cooperative kernel's edges (32 rows, 96
    // outputs, K-chunks of 96, out_dim not a multiple of 96), and a shape only the row-wise
    // kernel takes.
    for shape in [
        (1, 16, 16, 16, false, false, false),
        (33, 96, 288, 96, false, true, false),
        (200, 96, 384, 384, true, true, false),
        (129, 384, 96, 96, false, false, true),
        (64, 96, 192, 96, false, false, false),
        (31, 32, 48, 48, true, false, true),
        (97, 192, 112, 112, false, true, true),
        (7, 40, 20, 20, false, true, false),
    ] {
        let (rows, in_dim, out_dim, _, relu, norm, residual) = shape;
        let case = FusedCase::new(&mut rng, shape);
        // The norm's γ, β folded in as the engine uploads them: the kernels standardise alone.
        let (w, b) = if norm {
            fold_layer_norm(&case.w, &case.b, &case.gamma, &case.beta)
        } else {
            (case.w.clone(), case.b.clone())
        };
        let want = road_gpu::reference::linear_f16(
            &case.x,
            &w,
            &b,
            rows,
            in_dim,
            out_dim,
            relu,
            norm.then_some(1e-5),
            residual.then_some(&case.residual_in[..]),
        );
        for kernel in &kernels {
            if kernel.kernel != LinearF16Kernel::Rowwise && !fits(&case.p) {
                continue; // the engine runs such layers in f32
            }
            let y = kernel
                .run_fused(&ctx, case.p, &case.x, &w, &b, &case.y0)
                .unwrap();
            let got = case.gather(&y);
            let shape = format!(
                "{:?} {rows}×{in_dim}→{out_dim} relu {relu}, norm {norm}, residual {residual}",
                kernel.kernel
            );
            let outputs = got.iter().zip(&want.exact).zip(&want.bound);
            for (i, ((&g, &exact), &bound)) in outputs.enumerate() {
                assert!(
                    (g - exact).abs() <= bound + 1e-5 * exact.abs() + 1e-5,
                    "{shape}: output {i} is {g}, the unrounded layer's {exact}: beyond f16's \
                     bound {bound}"
                );
            }
            if !norm {
                let tol = Tolerance {
                    rel: 1e-4,
                    abs: 1e-7 * in_dim as f32 + 1e-6,
                };
                if let Err(m) = tol.check(&got, &want.rounded) {
                    panic!("{shape} against the rounded layer: {m}");
                }
            }
            case.check_gaps(&y, &shape);
        }
    }
}

/// The fused polyline encoder (point embedding, mixing layer, max over points, layer norm in
/// one workgroup per polyline) on shapes around its edges: one point, points staged in several
/// chunks (Q · D above its 2 048 staged floats), D above the workgroup's 64 invocations, up to
/// its largest (512: chunks of 4 points), Q not a multiple of 4.
#[test]
fn polyline_encoder_matches_the_cpu_reference_on_random_shapes() {
    use road_gpu::kernels::polyline::{PolylineEncoder, PolylineKernel, PolylineParams};
    let ctx = context();
    let encoders = PolylineKernel::ALL.map(|kernel| PolylineEncoder::new(&ctx, kernel));
    let mut rng = rand::rngs::StdRng::seed_from_u64(12);
    // The blocked variant's edges too: a last block of fewer polylines, D over one block of
    // 96 outputs and not a multiple of 16, Q from 4 (8 polylines a block) to 128 (one).
    for (n, q, d) in [
        (1, 1, 2),
        (5, 20, 64),
        (70, 20, 96),
        (3, 30, 160),
        (2, 7, 7),
        (2, 9, 512),
        (13, 20, 192),
        (9, 4, 40),
        (3, 128, 100),
        (17, 12, 97),
    ] {
        let points = random(&mut rng, n * q * 2, 2.0);
        let embed = random(&mut rng, 3 * d + q * d, 0.7);
        let mix_w = random(&mut rng, d * d, 0.3);
        let mix_b = random(&mut rng, d, 0.2);
        let gamma = random(&mut rng, d, 1.0);
        let beta = random(&mut rng, d, 1.0);
        let p = PolylineParams {
            polylines: n as u32,
            points: q as u32,
            hidden: d as u32,
            eps: 1e-5,
        };
        let want = road_gpu::reference::encode_polylines(
            &points,
            &embed,
            &mix_w,
            &mix_b,
            &gamma,
            &beta,
            (n, q, d),
            1e-5,
        );
        // Outputs near 0 come from a difference of O(1) terms: the absolute part covers them.
        let tol = Tolerance {
            rel: 1e-4,
            abs: 1e-5,
        };
        for encoder in &encoders {
            if encoder.kernel == PolylineKernel::Blocked && !p.blocked_fits() {
                let err = encoder
                    .run(&ctx, p, &points, &embed, &mix_w, &mix_b, &gamma, &beta)
                    .unwrap_err();
                assert!(err.to_string().contains("Q = "), "{err}");
                continue;
            }
            let got = encoder
                .run(&ctx, p, &points, &embed, &mix_w, &mix_b, &gamma, &beta)
                .unwrap();
            if let Err(m) = tol.check(&got, &want) {
                panic!(
                    "{:?} polyline encoder {n} × {q} points × {d}: {m}",
                    encoder.kernel
                );
            }
        }
    }
}

#[test]
fn attention_matches_the_cpu_reference_over_every_layout() {
    use road_gpu::kernels::attention::{Attention, AttentionParams, SceneMode, TokenLayout};
    let ctx = context();
    let kernel = Attention::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(13);
    for (b, a, w, heads, head_dim, p) in [
        (1, 1, 1, 1, 4, 1),
        (2, 5, 7, 2, 8, 3),
        (3, 12, 20, 4, 16, 30),
        (1, 32, 11, 4, 16, 9),
    ] {
        let d = heads * head_dim;
        let tokens = b * a * w;
        let h = random(&mut rng, tokens * d, 1.0); // [B, A, W, D], used as q, k and v
        let mut valid: Vec<f32> = (0..tokens)
            .map(|_| f32::from(u8::from(rng.random_bool(0.8))))
            .collect(); // [B, A, W]
        // Agent 0 of scene 0 is absent everywhere.
        valid[..w].fill(0.0);
        let (b, a, w) = (b as u32, a as u32, w as u32);
        let scale = 1.0 / (head_dim as f32).sqrt();
        let time = TokenLayout {
            inner_count: 1,
            outer_stride: w,
            inner_stride: 0,
            token_stride: 1,
        };
        let agents = TokenLayout {
            inner_count: w,
            outer_stride: a * w,
            inner_stride: 1,
            token_stride: w,
        };
        let base = AttentionParams {
            groups: 0,
            heads: heads as u32,
            head_dim: head_dim as u32,
            queries: 0,
            keys: 0,
            scale,
            scene_agents: a,
            scene_mode: SceneMode::None as u32,
            q_layout: time,
            kv_layout: time,
            mask_layout: time,
        };
        // Each agent row's scene: plain (row a of scene b holds b), and packed (each scene's
        // agents split at random into up to three scenes).
        let rows = (b * a) as usize;
        let plain = road_gpu::engine::plain_agent_scenes(b as usize, a as usize);
        let packed: Vec<u32> = (0..rows)
            .map(|r| 3 * (r as u32 / a) + rng.random_range(0..3))
            .collect();
        let agents_of_one_scene = AttentionParams {
            groups: b * w,
            queries: a,
            keys: a,
            q_layout: agents,
            kv_layout: agents,
            mask_layout: agents,
            scene_mode: SceneMode::AgentsOfOneScene as u32,
            ..base
        };
        let cases = [
            (
                "time",
                AttentionParams {
                    groups: b * a,
                    queries: w,
                    keys: w,
                    ..base
                },
                &plain,
            ),
            (
                "agents",
                AttentionParams {
                    scene_mode: SceneMode::None as u32,
                    ..agents_of_one_scene
                },
                &plain,
            ),
            ("agents, plain scenes", agents_of_one_scene, &plain),
            ("agents, packed scenes", agents_of_one_scene, &packed),
        ];
        for (name, params, agent_scene) in cases {
            let got = kernel
                .run(&ctx, params, &h, &h, &h, &valid, agent_scene)
                .unwrap();
            let want = road_gpu::reference::attention(&params, &h, &h, &h, &valid, agent_scene);
            if let Err(m) = Tolerance::F32.check(&got, &want) {
                panic!("{name} attention b{b} a{a} w{w} heads {heads}×{head_dim}: {m}");
            }
        }
        // The plain scenes kept apart are the same as no scenes at all.
        let apart = kernel
            .run(&ctx, agents_of_one_scene, &h, &h, &h, &valid, &plain)
            .unwrap();
        let together = kernel
            .run(&ctx, cases[1].1, &h, &h, &h, &valid, &plain)
            .unwrap();
        assert_eq!(apart, together);
        // Map cross-attention: queries [B, A·W, D], keys [B, P, D], map validity [B, P]; per
        // scene, then per agent over its own scene's map (plain and at random).
        let map = random(&mut rng, b as usize * p * d, 1.0);
        let map_valid: Vec<f32> = (0..b as usize * p)
            .map(|i| f32::from(u8::from(i % 4 != 1)))
            .collect();
        let per_scene = AttentionParams {
            groups: b,
            queries: a * w,
            keys: p as u32,
            q_layout: TokenLayout::contiguous(a * w),
            kv_layout: TokenLayout::contiguous(p as u32),
            mask_layout: TokenLayout::contiguous(p as u32),
            ..base
        };
        let per_agent = AttentionParams {
            groups: b * a,
            queries: w,
            q_layout: time,
            scene_mode: SceneMode::KeysOfTheAgentsScene as u32,
            ..per_scene
        };
        let random_maps: Vec<u32> = (0..rows).map(|_| rng.random_range(0..b)).collect();
        for (name, params, agent_scene) in [
            ("per scene", per_scene, &plain),
            ("per agent, plain", per_agent, &plain),
            ("per agent, packed", per_agent, &random_maps),
        ] {
            let got = kernel
                .run(&ctx, params, &h, &map, &map, &map_valid, agent_scene)
                .unwrap();
            let want =
                road_gpu::reference::attention(&params, &h, &map, &map, &map_valid, agent_scene);
            if let Err(m) = Tolerance::F32.check(&got, &want) {
                panic!("map attention {name} b{b} a{a} w{w} p{p}: {m}");
            }
        }
        // Per agent over plain scenes is per scene.
        let run = |params| {
            kernel
                .run(&ctx, params, &h, &map, &map, &map_valid, &plain)
                .unwrap()
        };
        assert_eq!(run(per_agent), run(per_scene));
    }
}

/// `window.wgsl`: the emitted-slot gather and the shift after an emission, against
/// `road_rollout::{window_emitted, window_shift}` (what the candle engine runs), on
/// random shapes with some scenes not read or not shifted and padded agents.
#[test]
fn window_kernels_match_the_cpu_reference() {
    use road_gpu::kernels::storage_buffer;
    use road_gpu::kernels::window::WindowOps;
    use road_rollout::{ShiftEdit, ShiftShape, window_emitted, window_shift};
    let ctx = context();
    let mut rng = rand::rngs::StdRng::seed_from_u64(21);
    for (b, a, w, n) in [
        (1usize, 1usize, 2usize, 1usize),
        (3, 5, 11, 10),
        (7, 13, 20, 10),
        (70, 4, 40, 10),
    ] {
        let x = random(&mut rng, b * a * w * 3, 3.0);
        let buffer = storage_buffer(&ctx, "x", (x.len() * 4) as u64);
        ctx.queue.write_buffer(&buffer, 0, bytemuck::cast_slice(&x));
        let mut ops = WindowOps::new(&ctx, &buffer, b, a, w);
        // Gather: every third scene not read.
        let slots: Vec<Option<usize>> = (0..b)
            .map(|i| (i % 3 != 2).then(|| rng.random_range(0..w)))
            .collect();
        let mut got = vec![0.0f32; b * a * 3];
        ops.emitted(&ctx, &slots, &mut got).unwrap();
        let mut expected = vec![0.0f32; b * a * 3];
        window_emitted(&x, a, w, &slots, &mut expected);
        assert_eq!(got, expected, "gather {b}×{a}×{w}");
        // Shift: every other scene, with fewer real agents than the padded count.
        let shape = ShiftShape {
            observed: n,
            obs_noise: 0.002,
            sigma_max: 80.0,
        };
        // Every third shifted scene turns no plan; the others turn every other agent's.
        // (scene, emitted, noise, turns)
        type Edit = (usize, Vec<f32>, Vec<f32>, Vec<f32>);
        let edits: Vec<Edit> = (0..b)
            .step_by(2)
            .map(|i| {
                let real = 1 + i % a;
                let turns = if i % 3 == 0 {
                    Vec::new()
                } else {
                    (0..real)
                        .flat_map(|agent| {
                            if agent % 2 == 0 {
                                [
                                    rng.random_range(-2.0..2.0),
                                    rng.random_range(-2.0..2.0),
                                    rng.random_range(-1.2..1.2),
                                    rng.random_range(-0.5..0.5),
                                ]
                            } else {
                                road_rollout::NO_TURN
                            }
                        })
                        .collect()
                };
                (
                    i,
                    random(&mut rng, real * 3, 2.0),
                    random(&mut rng, real * 6, 2.0),
                    turns,
                )
            })
            .collect();
        let list: Vec<road_gpu::kernels::window::ShiftList<'_>> = edits
            .iter()
            .map(|(i, e, z, t)| (*i, e.as_slice(), z.as_slice(), t.as_slice()))
            .collect();
        ops.shift(&ctx, &buffer, &list, shape).unwrap();
        let bytes = road_gpu::kernels::read_back(&ctx, &buffer, (x.len() * 4) as u64).unwrap();
        let got: Vec<f32> = bytemuck::cast_slice(&bytes).to_vec();
        let mut expected = x.clone();
        let per_scene = a * w * 3;
        let valid = vec![1.0f32; a * w];
        for (i, e, z, t) in &edits {
            let edit = ShiftEdit {
                scene: *i,
                emitted: e,
                noise: z,
                valid: &valid,
                turns: t,
            };
            window_shift(&mut expected[i * per_scene..][..per_scene], w, &edit, shape);
        }
        if let Err(m) = Tolerance::F32.check(&got, &expected) {
            panic!("shift {b}×{a}×{w}: {m}");
        }
    }
}

/// Each agent's nearest polylines in its anchor frame: the same pick (padding last, then
/// distance, then index) and the same points as the CPU engines' reference, with agents
/// missing at the anchor slot (scene frame) and scenes of padded polylines.
#[test]
fn agent_maps_match_the_cpu_reference() {
    use road_gpu::kernels::agent_map::{AgentMap, AgentMapParams};
    use road_model::agent_map::{agent_maps, anchors_of, polylines_per_agent};
    let ctx = context();
    let kernel = AgentMap::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(21);
    for (b, a, w, p, q, k) in [
        (1, 1, 3, 1, 2, 4),
        (2, 5, 20, 6, 20, 4),
        (3, 7, 20, 32, 20, 12),
        (2, 3, 4, 128, 3, 128),
    ] {
        let anchor_slot = w / 2;
        let x = random(&mut rng, b * a * w * 3, 1.5);
        let valid: Vec<f32> = (0..b * a * w)
            .map(|_| f32::from(u8::from(rng.random_bool(0.8))))
            .collect();
        let map = random(&mut rng, b * p * q * 2, 1.0);
        let map_valid: Vec<f32> = (0..b * p)
            .map(|i| f32::from(u8::from(i % p < p - p / 3)))
            .collect();
        let k = polylines_per_agent(k, p);
        let params = AgentMapParams {
            rows: (b * a) as u32,
            agents: a as u32,
            slots: w as u32,
            anchor_slot: anchor_slot as u32,
            polylines: p as u32,
            points: q as u32,
            picked: k as u32,
            heading_scale: 0.25,
        };
        let anchors = anchors_of(&x, &valid, w, anchor_slot, 0.25);
        // Each row of scene b picks from map b (a plain batch), then every row from a map
        // scene of its own, at random (a packed batch): the reference on each row's map.
        let plain = road_gpu::engine::plain_agent_scenes(b, a);
        let packed: Vec<u32> = (0..b * a).map(|_| rng.random_range(0..b as u32)).collect();
        for (layout, agent_scene) in [("plain", plain), ("packed", packed)] {
            let (points, flags) = kernel
                .run(&ctx, params, &x, &valid, &map, &map_valid, &agent_scene)
                .unwrap();
            let (mut want_points, mut want_flags) = (Vec::new(), Vec::new());
            for (row, &scene) in agent_scene.iter().enumerate() {
                let scene = scene as usize;
                let (row_points, row_flags) = agent_maps(
                    &anchors[row..row + 1],
                    1,
                    &map[scene * p * q * 2..][..p * q * 2],
                    &map_valid[scene * p..][..p],
                    q,
                    k,
                );
                want_points.extend(row_points);
                want_flags.extend(row_flags);
            }
            assert_eq!(
                flags, want_flags,
                "{layout}: {b}×{a} agents, {p} polylines: flags"
            );
            let tol = Tolerance {
                rel: 1e-4,
                abs: 1e-5,
            };
            if let Err(m) = tol.check(&points, &want_points) {
                panic!("{layout}: {b}×{a} agents, {p} polylines of {q} points, K = {k}: {m}");
            }
        }
    }
    // More polylines than the kernel holds: a clear error, not a wrong pick.
    let too_many = AgentMapParams {
        rows: 1,
        agents: 1,
        slots: 1,
        anchor_slot: 0,
        polylines: 129,
        points: 1,
        picked: 1,
        heading_scale: 0.25,
    };
    let err = kernel
        .run(
            &ctx,
            too_many,
            &[0.0; 3],
            &[1.0],
            &[0.0; 258],
            &[1.0; 129],
            &[0],
        )
        .unwrap_err();
    assert!(err.to_string().contains("128"), "{err}");
    // A row naming a map scene the batch lacks: refused, not read past the map.
    let fits = AgentMapParams {
        polylines: 1,
        ..too_many
    };
    let err = kernel
        .run(&ctx, fits, &[0.0; 3], &[1.0], &[0.0; 2], &[1.0], &[1])
        .unwrap_err();
    assert!(err.to_string().contains("map scenes"), "{err}");
}

/// Agent attention with pair features matches its CPU reference (on the CPU engines'
/// `pair_features`): scenes with agents absent everywhere, absent at the anchor slot (scene
/// frame) and groups with no valid key.
#[test]
fn pair_attention_matches_the_cpu_reference() {
    use road_gpu::kernels::agent_pairs::{PairAttention, PairAttentionParams};
    let ctx = context();
    let kernel = PairAttention::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(23);
    for (b, a, w, heads, head_dim) in [(1, 1, 2, 1, 4), (2, 5, 20, 4, 16), (3, 12, 20, 2, 8)] {
        let d = heads * head_dim;
        let tokens = b * a * w;
        let f = road_model::agent_pairs::PAIR_FEATURES;
        let (q, k, v) = (
            random(&mut rng, tokens * d, 1.0),
            random(&mut rng, tokens * d, 1.0),
            random(&mut rng, tokens * d, 1.0),
        );
        let states = random(&mut rng, tokens * 3, 1.5);
        let mut valid: Vec<f32> = (0..tokens)
            .map(|_| f32::from(u8::from(rng.random_bool(0.8))))
            .collect();
        valid[..w].fill(0.0); // scene 0, agent 0: absent everywhere
        let anchor_slot = w / 2;
        if a > 1 {
            valid[w + anchor_slot] = 0.0; // scene 0, agent 1: no anchor
        }
        let (pair_k, pair_v) = (random(&mut rng, d * f, 0.5), random(&mut rng, d * f, 0.5));
        let params = PairAttentionParams {
            groups: (b * w) as u32,
            heads: heads as u32,
            head_dim: head_dim as u32,
            agents: a as u32,
            slots: w as u32,
            anchor_slot: anchor_slot as u32,
            scale: 1.0 / (head_dim as f32).sqrt(),
            heading_scale: 0.25,
            direction: 0.25,
            near: 0.125,
            far: 0.5,
            _pad: 0,
        };
        // Each scene's agents as one scene (a plain batch), then split at random into up to
        // three packed scenes that attend apart.
        let plain = road_gpu::engine::plain_agent_scenes(b, a);
        let packed: Vec<u32> = (0..b * a)
            .map(|r| (3 * (r / a)) as u32 + rng.random_range(0..3))
            .collect();
        for (layout, agent_scene) in [("plain", plain), ("packed", packed)] {
            let got = kernel
                .run(
                    &ctx,
                    params,
                    &q,
                    &k,
                    &v,
                    &valid,
                    &states,
                    &pair_k,
                    &pair_v,
                    &agent_scene,
                )
                .unwrap();
            let want = road_gpu::reference::pair_attention(
                &params,
                &q,
                &k,
                &v,
                &valid,
                &states,
                &pair_k,
                &pair_v,
                &agent_scene,
            );
            let tol = Tolerance {
                rel: 1e-4,
                abs: 1e-5,
            };
            if let Err(m) = tol.check(&got, &want) {
                panic!(
                    "{layout}: {b} scenes × {a} agents × {w} slots, {heads} heads of {head_dim}: {m}"
                );
            }
        }
    }
}

/// `road gpu selftest`'s kernel checks, which a lent GPU runs before anything is timed, pass
/// here (on lavapipe in CI), each comparing values.
#[test]
fn the_selftest_kernel_checks_pass() {
    let ctx = context();
    let checks = road_gpu::selftest::kernel_checks(&ctx).unwrap();
    for name in [
        "linear",
        "linear_tiled",
        "attention",
        "window_emitted",
        "window_shift",
    ] {
        assert!(
            checks.iter().any(|c| c.name == name),
            "no {name} check among {:?}",
            checks.iter().map(|c| c.name).collect::<Vec<_>>()
        );
    }
    for c in &checks {
        assert!(c.values > 0, "{} compares no values", c.name);
        if let Err(m) = &c.outcome {
            panic!("{}: {m}", c.name);
        }
    }
}

/// Tensors laid one after another in one weights vector, as the engine's weights buffer holds
/// them: each tensor's offset in floats.
struct PackedWeights {
    values: Vec<f32>,
    /// Each tensor at a multiple of 4 floats, as the wide chain tile reads them (and the
    /// engine lays them out); else odd gaps, which the narrow tile takes.
    quads: bool,
}

impl PackedWeights {
    fn new(quads: bool) -> Self {
        Self {
            values: Vec::new(),
            quads,
        }
    }

    fn push(&mut self, tensor: Vec<f32>) -> u32 {
        // A gap before every tensor that must keep out of every sum.
        self.values.push(9.0);
        while self.quads && !self.values.len().is_multiple_of(4) {
            self.values.push(9.0);
        }
        let at = self.values.len() as u32;
        self.values.extend(tensor);
        at
    }
}

/// A chain run's `h`, `y` and `x_e` after.
type ChainRun = (Vec<f32>, Vec<f32>, Vec<f32>);
/// An embedding chain run's `h` and `y` after.
type EmbedRun = (Vec<f32>, Vec<f32>);

/// Each kernel's run of a chain that attends (`ChainParams::attend`), with its name.
fn run_attending(
    ctx: &GpuContext,
    kernels: Vec<(String, &road_gpu::kernels::residual_chain::ResidualChain)>,
    p: road_gpu::kernels::residual_chain::ChainParams,
    inputs: &road_gpu::kernels::residual_chain::ChainInputs<'_>,
    attend: road_gpu::kernels::residual_chain::AttendInputs<'_>,
) -> Vec<(String, ChainRun)> {
    kernels
        .into_iter()
        .map(|(tile, k)| {
            let run = k.run_full(ctx, p, inputs, None, Some(attend)).unwrap();
            (tile, run)
        })
        .collect()
}

/// The wide chain tile for D and M where they allow it, with as many rows as this device's
/// workgroups hold (on lavapipe's 32 KiB: 64 rows at D 16, 32 at D 96, 16 at D 256), and its
/// name for messages.
fn wide_chain(
    ctx: &GpuContext,
    d: usize,
    m: usize,
) -> Option<(String, road_gpu::kernels::residual_chain::ResidualChain)> {
    use road_gpu::kernels::residual_chain::{ChainTile, ResidualChain};
    let bytes = ctx.device.limits().max_compute_workgroup_storage_size;
    let tile = ChainTile::wide(d as u32, m as u32, bytes)?;
    Some((
        format!("wide tile of {} rows", tile.rows),
        ResidualChain::with_tile(ctx, tile).unwrap(),
    ))
}

/// The kernels a chain test runs a shape on: the narrow tile (made once per test) and the
/// wide one where there is one, each with its name.
fn chain_kernels<'a>(
    narrow: &'a road_gpu::kernels::residual_chain::ResidualChain,
    wide: &'a Option<(String, road_gpu::kernels::residual_chain::ResidualChain)>,
) -> Vec<(String, &'a road_gpu::kernels::residual_chain::ResidualChain)> {
    let mut kernels = vec![("narrow tile".to_string(), narrow)];
    kernels.extend(wide.iter().map(|(name, kernel)| (name.clone(), kernel)));
    kernels
}

/// The residual chain (`residual_chain.wgsl`) against [`road_gpu::reference::residual_chain`]:
/// rows around its tile (one, a partial tile, several), hidden widths from 1 to its 256, MLP
/// widths across several chunks and not a multiple of a chunk, no MLP, no next layer, the next
/// layer split into parts with gaps that must keep their values, and the head with the output
/// preconditioning against [`road_gpu::reference::precondition_output`] with and without an
/// agent frame and a constant-velocity reference. Each on the narrow tile (weights at odd
/// offsets) and, where D and M allow, on the wide one (16, 32 and 64 rows among the shapes).
#[test]
fn residual_chain_matches_the_cpu_reference() {
    use road_gpu::kernels::residual_chain::{
        ChainInputs, ChainParams, NO_FRAME, ResidualChain, transpose,
    };
    use road_gpu::reference::{PreconditionShape, precondition_output, residual_chain};
    let ctx = context();
    let kernel = ResidualChain::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(17);
    // (rows, D, M, next outputs, outputs per part)
    for (rows, d, m, next_out, part) in [
        (1, 96, 192, 288, 96),
        (7, 96, 0, 96, 96),
        (9, 16, 32, 48, 16),
        (37, 33, 70, 0, 1),
        (130, 96, 192, 288, 96),
        (17, 256, 512, 256, 256),
        (8, 1, 3, 2, 1),
        (24, 64, 130, 3, 3),
        // The wide tile's last chunk of 4 units: its second quad of weights past the chunk.
        (11, 32, 68, 96, 32),
    ] {
        let o_w_host = random(&mut rng, d * d, 0.3);
        let o_b_host = random(&mut rng, d, 0.3);
        let (w1_host, b1_host, w2_host, b2_host) = (
            random(&mut rng, m * d, 0.3),
            random(&mut rng, m, 0.3),
            random(&mut rng, d * m, 0.3),
            random(&mut rng, d, 0.3),
        );
        let (next_w_host, next_b_host) = (
            random(&mut rng, next_out * d, 0.3),
            random(&mut rng, next_out, 0.3),
        );
        let mut p = ChainParams {
            rows: rows as u32,
            d: d as u32,
            m: m as u32,
            eps: 1e-5,
            next_out: next_out as u32,
            part: part as u32,
            // Parts 5 floats apart beyond their rows · part.
            part_stride: (rows * part + 5) as u32,
            anchor_slot: NO_FRAME,
            ..ChainParams::default()
        };
        let att = random(&mut rng, rows * d, 1.0);
        let h: Vec<f32> = random(&mut rng, rows * d, 1.0)
            .iter()
            .map(|v| v + 0.5)
            .collect();
        let y0 = random(&mut rng, p.y_len(), 1.0);
        let mlp = (m > 0).then_some(((&w1_host[..], &b1_host[..]), (&w2_host[..], &b2_host[..])));
        let next = (next_out > 0).then_some((&next_w_host[..], &next_b_host[..]));
        let (h_want, next_want) =
            residual_chain(&att, &h, rows, d, (&o_w_host, &o_b_host), mlp, next, 1e-5);
        let wide = wide_chain(&ctx, d, m);
        for (tile, kernel) in chain_kernels(&kernel, &wide) {
            // Weights transposed, as the engine uploads a chain's; at odd offsets for the
            // narrow tile, at multiples of 4 for the wide one.
            let mut weights = PackedWeights::new(kernel.tile.wide_blocks);
            p.o_w = weights.push(transpose(&o_w_host, d));
            p.o_b = weights.push(o_b_host.clone());
            p.w1 = weights.push(transpose(&w1_host, m));
            p.b1 = weights.push(b1_host.clone());
            p.w2 = weights.push(transpose(&w2_host, d));
            p.b2 = weights.push(b2_host.clone());
            p.next_w = weights.push(transpose(&next_w_host, next_out));
            p.next_b = weights.push(next_b_host.clone());
            let inputs = ChainInputs {
                weights: &weights.values,
                att: &att,
                h: &h,
                y: &y0,
                x: &[0.0],
                sigma: &[0.0],
                valid: &[0.0],
            };
            let (h_got, y_got) = kernel.run(&ctx, p, &inputs).unwrap();
            let shape =
                format!("{tile}: {rows} rows, D {d}, M {m}, next {next_out} in parts of {part}");
            // Sums of up to D + M products of O(1) terms in another order.
            let tol = Tolerance {
                rel: 1e-4,
                abs: 2e-5,
            };
            if let Err(e) = tol.check(&h_got, &h_want) {
                panic!("{shape}: h: {e}");
            }
            let part_stride = p.part_stride as usize;
            let at = |r: usize, o: usize| (o / part) * part_stride + r * part + o % part;
            let next_got: Vec<f32> = (0..rows * next_out)
                .map(|i| y_got[at(i / next_out, i % next_out)])
                .collect();
            if let Err(e) = tol.check(&next_got, &next_want) {
                panic!("{shape}: next layer: {e}");
            }
            let parts = next_out.div_ceil(part);
            for j in 0..parts.saturating_sub(1) {
                let gap = j * part_stride + rows * part..(j + 1) * part_stride;
                assert_eq!(
                    y_got[gap.clone()],
                    y0[gap],
                    "{shape}: the gap after part {j}"
                );
            }
        }
    }

    // The head and the output preconditioning: 2 scenes × 3 agents × 5 slots, anchor slot 2.
    let (scenes, agents, slots, d, m) = (2, 3, 5, 24, 48);
    let rows = scenes * agents * slots;
    for (frame, residual_scale) in [(false, 0.0), (true, 0.0), (true, 4.0)] {
        let mut weights = PackedWeights::new(true);
        let hosts: Vec<Vec<f32>> = [d * d, d, m * d, m, d * m, d, 3 * d, 3]
            .iter()
            .map(|&n| random(&mut rng, n, 0.3))
            .collect();
        // Weights transposed ([out, in] → [in, out]), biases as they are.
        let outputs = [d, 1, m, 1, d, 1, 3, 1];
        let offsets: Vec<u32> = hosts
            .iter()
            .zip(outputs)
            .map(|(t, out)| weights.push(transpose(t, out)))
            .collect();
        let shape = PreconditionShape {
            slots,
            agents,
            anchor_slot: frame.then_some(2),
            sigma_data: 0.5,
            heading_scale: 2.0,
            residual_scale,
        };
        let p = ChainParams {
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
            next_out: 3,
            part: 3,
            part_stride: (rows * 3) as u32,
            precondition: 1,
            slots: slots as u32,
            agents: agents as u32,
            anchor_slot: if frame { 2 } else { NO_FRAME },
            sigma_data: 0.5,
            heading_scale: 2.0,
            residual_scale: residual_scale as f32,
            ..ChainParams::default()
        };
        let att = random(&mut rng, rows * d, 1.0);
        let h = random(&mut rng, rows * d, 1.0);
        let x = random(&mut rng, rows * 3, 3.0);
        // σ across the schedule, one slot clean; some tokens (an anchor among them) invalid.
        let sigma: Vec<f32> = (0..scenes * slots)
            .map(|i| {
                if i == 3 {
                    0.0
                } else {
                    rng.random_range(0.01..20.0)
                }
            })
            .collect();
        let valid: Vec<f32> = (0..rows)
            .map(|i| if i % 7 == 3 || i == 7 { 0.0 } else { 1.0 })
            .collect();
        let inputs = ChainInputs {
            weights: &weights.values,
            att: &att,
            h: &h,
            y: &vec![0.0; rows * 3],
            x: &x,
            sigma: &sigma,
            valid: &valid,
        };
        let wide = wide_chain(&ctx, d, m);
        for (tile, kernel) in chain_kernels(&kernel, &wide) {
            let (h_got, d_got) = kernel.run(&ctx, p, &inputs).unwrap();
            let (h_want, f) = residual_chain(
                &att,
                &h,
                rows,
                d,
                (&hosts[0], &hosts[1]),
                Some(((&hosts[2], &hosts[3]), (&hosts[4], &hosts[5]))),
                Some((&hosts[6], &hosts[7])),
                1e-5,
            );
            let d_want = precondition_output(&x, &f, &sigma, &valid, shape);
            let tol = Tolerance {
                rel: 1e-4,
                abs: 2e-5,
            };
            let case = format!("{tile}: head, frame {frame}, residual scale {residual_scale}");
            if let Err(e) = tol.check(&h_got, &h_want) {
                panic!("{case}: h: {e}");
            }
            if let Err(e) = tol.check(&d_got, &d_want) {
                panic!("{case}: D(x; σ): {e}");
            }

            // With the sampler's step: the Euler step from the kernel's own D where σ changes
            // (unchanged slots, one landing on 0, some γ 0), then the multistep correction,
            // against `road_rollout::heun`; h and D as without it.
            let sigma_next: Vec<f32> = sigma
                .iter()
                .enumerate()
                .map(|(i, &s)| match i % 4 {
                    0 => s,
                    1 => 0.0,
                    _ => s * 0.7,
                })
                .collect();
            let previous = random(&mut rng, rows * 3, 2.0);
            let gamma: Vec<f32> = (0..scenes * slots)
                .map(|i| {
                    if i % 3 == 0 {
                        0.0
                    } else {
                        rng.random_range(-1.0..1.0)
                    }
                })
                .collect();
            let update = road_gpu::kernels::residual_chain::UpdateInputs {
                sigma_next: &sigma_next,
                previous: &previous,
                gamma: &gamma,
            };
            let with_update = ChainParams { update: 1, ..p };
            let (h_upd, d_upd, x_e_got) = kernel
                .run_with_update(&ctx, with_update, &inputs, Some(update))
                .unwrap();
            assert_eq!(
                (h_upd, &d_upd),
                (h_got, &d_got),
                "{case}: h and D with the update"
            );
            let x_e_want = road_gpu::reference::multistep_step(
                &x,
                &d_got,
                &previous,
                &sigma,
                &sigma_next,
                &gamma,
                agents,
                slots,
            )
            .unwrap();
            // The same operations in the same order; a fused multiply-add may round once less.
            let exact = Tolerance {
                rel: 1e-6,
                abs: 1e-6,
            };
            if let Err(e) = exact.check(&x_e_got, &x_e_want) {
                panic!("{case}: x_e: {e}");
            }
        }
    }
}

/// A chain's shapes outside its tile are refused with the reason, not run.
#[test]
fn residual_chain_refuses_widths_past_its_tile() {
    use road_gpu::kernels::residual_chain::{ChainParams, MAX_HIDDEN};
    let too_wide = ChainParams {
        rows: 8,
        d: MAX_HIDDEN + 1,
        ..ChainParams::default()
    };
    let err = too_wide.check().unwrap_err().to_string();
    assert!(err.contains("257"), "{err}");
    let head_of_two = ChainParams {
        rows: 8,
        d: 16,
        next_out: 2,
        part: 2,
        precondition: 1,
        ..ChainParams::default()
    };
    let err = head_of_two.check().unwrap_err().to_string();
    assert!(err.contains("3 outputs"), "{err}");
}

/// The wide chain tile: as many rows as a device's workgroups hold, as many invocations as
/// blocks of a D-wide layer, none for widths its vec4 reads cannot take; and a layout off the
/// multiples of 4 refused by the field's name, not run.
#[test]
fn the_wide_chain_tile_fits_its_device_and_refuses_unaligned_layouts() {
    use road_gpu::kernels::residual_chain::{ChainParams, ChainTile};
    // road20-wide4 (D 96, M 192) on an H100's 48 KiB: 64 rows, 96 invocations; on lavapipe's
    // 32 KiB, 32 rows.
    let h100 = ChainTile::wide(96, 192, 48 << 10).unwrap();
    assert_eq!((h100.rows, h100.lanes, h100.tile_d), (64, 96, 97));
    assert!(h100.workgroup_bytes() <= 48 << 10);
    let lavapipe = ChainTile::wide(96, 192, 32 << 10).unwrap();
    assert_eq!((lavapipe.rows, lavapipe.lanes), (32, 64));
    // road20-large (D 192): 32 rows on 48 KiB.
    let large = ChainTile::wide(192, 384, 48 << 10).unwrap();
    assert_eq!((large.rows, large.lanes), (32, 96));
    for (d, m, bytes) in [
        (33, 66, 48 << 10),
        (100, 200, 48 << 10),
        (96, 190, 48 << 10),
        (96, 192, 4 << 10),
        (264, 528, 1 << 20),
    ] {
        assert_eq!(
            ChainTile::wide(d, m, bytes),
            None,
            "D {d}, M {m}, {bytes} bytes"
        );
    }
    let p = ChainParams {
        rows: 8,
        d: 96,
        m: 192,
        o_w: 4,
        o_b: 400,
        w1: 4,
        b1: 8,
        w2: 13,
        b2: 16,
        ..ChainParams::default()
    };
    let err = h100.check(&p).unwrap_err().to_string();
    assert!(err.contains("`w2` (13)"), "{err}");
    // The narrow tile takes the same layout.
    ChainTile::narrow(96).check(&p).unwrap();
    let too_wide = ChainParams { d: 104, ..p };
    assert!(
        h100.check(&too_wide)
            .unwrap_err()
            .to_string()
            .contains("104")
    );
}

/// The residual chain that attends itself (`ChainParams::attend`: the map attention of its
/// rows before the output projection) against the CPU references of the attention and of the
/// chain: each agent row's own keys, and (`key_mode` 1) its scene's; invalid keys, an agent
/// (or a map scene) with none valid, heads of 16 and of 8. (The last block's, which attends and
/// preconditions, is checked by every whole-denoiser test against candle.)
#[test]
fn residual_chain_attending_matches_the_cpu_reference() {
    use road_gpu::kernels::attention::{AttentionParams, SceneMode, TokenLayout};
    use road_gpu::kernels::residual_chain::{
        AttendInputs, ChainInputs, ChainParams, NO_FRAME, ResidualChain, transpose,
    };
    use road_gpu::reference::{attention, residual_chain};
    let ctx = context();
    let kernel = ResidualChain::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(23);
    // (agent rows, slots W, D, heads, keys, scene keys: map scenes)
    for (agents, slots, d, heads, keys, map_scenes) in [
        (5, 4, 32, 2, 6, None),
        (3, 7, 48, 6, 12, None),
        (6, 5, 32, 4, 9, Some(2)),
    ] {
        let rows = agents * slots;
        let m = 2 * d;
        let key_rows = map_scenes.map_or(agents * keys, |scenes| scenes * keys);
        let mut weights = PackedWeights::new(true);
        let hosts: Vec<Vec<f32>> = [d * d, d, m * d, m, d * m, d, d * d, d]
            .iter()
            .map(|&n| random(&mut rng, n, 0.3))
            .collect();
        let mut p = ChainParams {
            rows: rows as u32,
            d: d as u32,
            m: m as u32,
            eps: 1e-5,
            next_out: d as u32,
            part: d as u32,
            part_stride: (rows * d) as u32,
            anchor_slot: NO_FRAME,
            attend: 1,
            slots: slots as u32,
            heads: heads as u32,
            head_dim: (d / heads) as u32,
            scale: 1.0 / ((d / heads) as f32).sqrt(),
            keys: keys as u32,
            key_mode: u32::from(map_scenes.is_some()),
            ..ChainParams::default()
        };
        p.o_w = weights.push(transpose(&hosts[0], d));
        p.o_b = weights.push(hosts[1].clone());
        p.w1 = weights.push(transpose(&hosts[2], m));
        p.b1 = weights.push(hosts[3].clone());
        p.w2 = weights.push(transpose(&hosts[4], d));
        p.b2 = weights.push(hosts[5].clone());
        p.next_w = weights.push(transpose(&hosts[6], d));
        p.next_b = weights.push(hosts[7].clone());
        // k then v, 3 floats apart, in one buffer.
        let (k, v) = (
            random(&mut rng, key_rows * d, 1.0),
            random(&mut rng, key_rows * d, 1.0),
        );
        let mut map_kv = vec![7.0; 2];
        p.k_off = map_kv.len() as u32;
        map_kv.extend(&k);
        map_kv.extend([7.0; 3]);
        p.v_off = map_kv.len() as u32;
        map_kv.extend(&v);
        // Every fifth key invalid; agent row 1's (or map scene 1's) all.
        let mut key_valid: Vec<f32> = (0..key_rows).map(|i| f32::from(i % 5 != 2)).collect();
        key_valid[keys..2 * keys].fill(0.0);
        let agent_scene: Vec<u32> = (0..agents as u32)
            .map(|a| map_scenes.map_or(0, |scenes| (a * 7 + 1) % scenes as u32))
            .collect();
        let queries = random(&mut rng, rows * d, 1.0);
        let h: Vec<f32> = random(&mut rng, rows * d, 1.0);
        let y0 = random(&mut rng, p.y_len(), 1.0);
        let inputs = ChainInputs {
            weights: &weights.values,
            att: &queries,
            h: &h,
            y: &y0,
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
        let wide = wide_chain(&ctx, d, m);
        let runs = run_attending(&ctx, chain_kernels(&kernel, &wide), p, &inputs, attend);
        let by_agent = TokenLayout::contiguous(keys as u32);
        let attn = AttentionParams {
            groups: agents as u32,
            heads: heads as u32,
            head_dim: (d / heads) as u32,
            queries: slots as u32,
            keys: keys as u32,
            scale: p.scale,
            scene_agents: agents as u32,
            scene_mode: if map_scenes.is_some() {
                SceneMode::KeysOfTheAgentsScene as u32
            } else {
                SceneMode::None as u32
            },
            q_layout: TokenLayout::contiguous(slots as u32),
            kv_layout: by_agent,
            mask_layout: by_agent,
        };
        let att = attention(&attn, &queries, &k, &v, &key_valid, &agent_scene);
        let layer = |i: usize| (&hosts[i][..], &hosts[i + 1][..]);
        let (h_want, y_want) = residual_chain(
            &att,
            &h,
            rows,
            d,
            layer(0),
            Some((layer(2), layer(4))),
            Some(layer(6)),
            1e-5,
        );
        let tol = Tolerance {
            rel: 1e-4,
            abs: 2e-5,
        };
        for (tile, (h_got, y_got, _)) in &runs {
            let what = format!(
                "{tile}: {agents} agents × {slots}, D {d}, {heads} heads, {keys} keys, \
                 {map_scenes:?}"
            );
            if let Err(e) = tol.check(h_got, &h_want) {
                panic!("{what}: h: {e}");
            }
            if let Err(e) = tol.check(y_got, &y_want) {
                panic!("{what}: next layer: {e}");
            }
        }
    }
}

/// The residual chain attending over agents (`key_mode` 2: the agents of each scene at the
/// row's slot, their own packed scene's only) against the CPU references of the attention
/// (plain, and with the pair features from the states) and of the chain: 2 batch scenes of 4
/// agents over 5 slots, one holding two packed scenes, an invalid agent slot.
#[test]
fn residual_chain_attending_over_agents_matches_the_cpu_reference() {
    use road_gpu::kernels::agent_pairs::PairAttentionParams;
    use road_gpu::kernels::attention::{AttentionParams, SceneMode, TokenLayout};
    use road_gpu::kernels::residual_chain::{
        AttendInputs, ChainInputs, ChainParams, ResidualChain, transpose,
    };
    use road_gpu::reference::{attention, pair_attention, residual_chain};
    let ctx = context();
    let kernel = ResidualChain::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(31);
    let (scenes, agents, slots, d, heads) = (2usize, 4usize, 5usize, 32usize, 2usize);
    let rows = scenes * agents * slots;
    let head_dim = d / heads;
    for pairs in [false, true] {
        let mut weights = PackedWeights::new(true);
        let hosts: Vec<Vec<f32>> = [d * d, d, d * d, d]
            .iter()
            .map(|&n| random(&mut rng, n, 0.3))
            .collect();
        let (q, k, v) = (
            random(&mut rng, rows * d, 1.0),
            random(&mut rng, rows * d, 1.0),
            random(&mut rng, rows * d, 1.0),
        );
        let states = random(&mut rng, rows * 3, 2.0);
        let mut valid = vec![1.0f32; rows];
        valid[(agents + 2) * slots + 3] = 0.0;
        // Scene 1 holds two packed scenes: agents 0, 1 and agents 2, 3.
        let agent_scene: Vec<u32> = vec![0, 0, 0, 0, 1, 1, 2, 2];
        let (pair_k, pair_v) = (random(&mut rng, d * 6, 0.3), random(&mut rng, d * 6, 0.3));
        let scales = (0.25f32, 2.5f32, 1.25f32, 5.0f32);
        let mut p = ChainParams {
            rows: rows as u32,
            d: d as u32,
            eps: 1e-5,
            next_out: d as u32,
            part: d as u32,
            part_stride: (rows * d) as u32,
            attend: 1,
            slots: slots as u32,
            agents: agents as u32,
            heads: heads as u32,
            head_dim: head_dim as u32,
            scale: 1.0 / (head_dim as f32).sqrt(),
            keys: agents as u32,
            key_mode: 2,
            anchor_slot: 2,
            pairs: u32::from(pairs),
            heading_scale: scales.0,
            direction: scales.1,
            near: scales.2,
            far: scales.3,
            ..ChainParams::default()
        };
        p.o_w = weights.push(transpose(&hosts[0], d));
        p.o_b = weights.push(hosts[1].clone());
        p.next_w = weights.push(transpose(&hosts[2], d));
        p.next_b = weights.push(hosts[3].clone());
        let mut map_kv = k.clone();
        p.k_off = 0;
        p.v_off = map_kv.len() as u32;
        map_kv.extend(&v);
        let h = random(&mut rng, rows * d, 1.0);
        let y0 = random(&mut rng, p.y_len(), 1.0);
        let inputs = ChainInputs {
            weights: &weights.values,
            att: &q,
            h: &h,
            y: &y0,
            x: &states,
            sigma: &[0.0],
            valid: &[0.0],
        };
        let attend = AttendInputs {
            map_kv: &map_kv,
            key_valid: &valid,
            agent_scene: &agent_scene,
            pair_k: if pairs { &pair_k } else { &[] },
            pair_v: if pairs { &pair_v } else { &[] },
        };
        let wide = wide_chain(&ctx, d, 0);
        let runs = run_attending(&ctx, chain_kernels(&kernel, &wide), p, &inputs, attend);
        let att = if pairs {
            let pp = PairAttentionParams {
                groups: (scenes * slots) as u32,
                heads: heads as u32,
                head_dim: head_dim as u32,
                agents: agents as u32,
                slots: slots as u32,
                anchor_slot: 2,
                scale: p.scale,
                heading_scale: scales.0,
                direction: scales.1,
                near: scales.2,
                far: scales.3,
                _pad: 0,
            };
            pair_attention(
                &pp,
                &q,
                &k,
                &v,
                &valid,
                &states,
                &pair_k,
                &pair_v,
                &agent_scene,
            )
        } else {
            let layout = TokenLayout {
                inner_count: slots as u32,
                outer_stride: (agents * slots) as u32,
                inner_stride: 1,
                token_stride: slots as u32,
            };
            let ap = AttentionParams {
                groups: (scenes * slots) as u32,
                heads: heads as u32,
                head_dim: head_dim as u32,
                queries: agents as u32,
                keys: agents as u32,
                scale: p.scale,
                scene_agents: agents as u32,
                scene_mode: SceneMode::AgentsOfOneScene as u32,
                q_layout: layout,
                kv_layout: layout,
                mask_layout: layout,
            };
            attention(&ap, &q, &k, &v, &valid, &agent_scene)
        };
        let layer = |i: usize| (&hosts[i][..], &hosts[i + 1][..]);
        let (h_want, y_want) =
            residual_chain(&att, &h, rows, d, layer(0), None, Some(layer(2)), 1e-5);
        let tol = Tolerance {
            rel: 1e-4,
            abs: 2e-5,
        };
        for (tile, (h_got, y_got, _)) in &runs {
            if let Err(e) = tol.check(h_got, &h_want) {
                panic!("{tile}: pairs {pairs}: h: {e}");
            }
            if let Err(e) = tol.check(y_got, &y_want) {
                panic!("{tile}: pairs {pairs}: next layer: {e}");
            }
        }
    }
}

/// The embedding chain (`residual_chain.wgsl`'s `embed_chain`) against the CPU references of the
/// token embedding ([`road_gpu::reference::embed_tokens`]) and of the first layer behind its
/// norm: without an agent frame, with one, with a constant-velocity reference; rows not a
/// multiple of the tile's; invalid slots and an agent without an anchor.
#[test]
fn embed_chain_matches_the_cpu_reference() {
    use road_gpu::kernels::residual_chain::{
        ChainParams, EmbedChainInputs, NO_FRAME, ResidualChain, transpose,
    };
    use road_gpu::reference::{EmbedShape, embed_tokens, linear_fused};
    let ctx = context();
    let kernel = ResidualChain::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(41);
    // (scenes, agents, slots, D, anchor slot, constant-velocity scale)
    for (scenes, agents, slots, d, anchor, residual_scale) in [
        (2, 3, 5, 24, None, 0.0),
        (1, 4, 7, 32, Some(3), 0.0),
        (3, 2, 6, 16, Some(2), 40.0),
        (2, 5, 20, 96, Some(9), 40.0),
    ] {
        let rows = scenes * agents * slots;
        let width = if residual_scale > 0.0 { 6 } else { 4 };
        let packed_len = 6 * d + slots * d + anchor.map_or(0, |_| width * d + d);
        let mut weights = PackedWeights::new(true);
        let packed = random(&mut rng, packed_len, 0.5);
        let next_out = 3 * d;
        let (next_w_host, next_b_host) = (
            random(&mut rng, next_out * d, 0.3),
            random(&mut rng, next_out, 0.3),
        );
        let next_w = weights.push(transpose(&next_w_host, next_out));
        let next_b = weights.push(next_b_host.clone());
        let x = random(&mut rng, rows * 3, 2.0);
        let sigma: Vec<f32> = (0..scenes * slots)
            .map(|_| rng.random_range(0.01f32..10.0))
            .collect();
        // Every seventh slot invalid, and agent 1's anchor (so it has none).
        let mut valid: Vec<f32> = (0..rows).map(|i| f32::from(i % 7 != 3)).collect();
        if let Some(anchor) = anchor {
            valid[slots + anchor] = 0.0;
        }
        let agent = random(&mut rng, scenes * agents * d, 1.0);
        let shape = EmbedShape {
            agents,
            slots,
            hidden: d,
            sigma_data: 0.5,
            anchor_slot: anchor,
            heading_scale: 0.25,
            relative_scale: 1.0,
            residual_scale,
        };
        let p = ChainParams {
            rows: rows as u32,
            d: d as u32,
            eps: 1e-5,
            next_w,
            next_b,
            next_out: next_out as u32,
            part: d as u32,
            part_stride: (rows * d + 3) as u32,
            slots: slots as u32,
            agents: agents as u32,
            anchor_slot: anchor.map_or(NO_FRAME, |a| a as u32),
            sigma_data: 0.5,
            heading_scale: 0.25,
            residual_scale: residual_scale as f32,
            relative_scale: 1.0,
            ..ChainParams::default()
        };
        let inputs = EmbedChainInputs {
            weights: &weights.values,
            embed: &packed,
            x: &x,
            sigma: &sigma,
            valid: &valid,
            agent: &agent,
        };
        let wide = wide_chain(&ctx, d, 0);
        let runs: Vec<(String, EmbedRun)> = chain_kernels(&kernel, &wide)
            .into_iter()
            .map(|(tile, k)| (tile, k.run_embed(&ctx, p, &inputs).unwrap()))
            .collect();
        let h_want = embed_tokens(&shape, &x, &sigma, &valid, &agent, &packed);
        let (ones, zeros) = (vec![1.0; d], vec![0.0; d]);
        let standardise = Some((&ones[..], &zeros[..], 1e-5));
        let next_want = linear_fused(
            &h_want,
            &next_w_host,
            &next_b_host,
            rows,
            d,
            next_out,
            false,
            standardise,
            None,
        );
        let tol = Tolerance {
            rel: 1e-4,
            abs: 2e-5,
        };
        let at = |r: usize, o: usize| (o / d) * p.part_stride as usize + r * d + o % d;
        for (tile, (h_got, y_got)) in &runs {
            let what = format!(
                "{tile}: {scenes} × {agents} × {slots}, D {d}, anchor {anchor:?}, cv \
                 {residual_scale}"
            );
            if let Err(e) = tol.check(h_got, &h_want) {
                panic!("{what}: h: {e}");
            }
            let next_got: Vec<f32> = (0..rows * next_out)
                .map(|i| y_got[at(i / next_out, i % next_out)])
                .collect();
            if let Err(e) = tol.check(&next_got, &next_want) {
                panic!("{what}: first layer: {e}");
            }
        }
    }
}

/// The compact sub-batches' row gathers and scatters match their CPU references exactly, one
/// to three regions of different widths in one dispatch (scatters: one or two): rows mapped in
/// any order, rows mapped to nothing (gathered as zeros, scattered nowhere) and rows mapped past
/// the other side (the kernels bound their own indices: zeros, nothing). Four regions are
/// refused by name.
#[test]
fn compact_rows_match_the_cpu_reference() {
    use road_gpu::kernels::compact::{
        CompactRows, MAX_GATHERED, MAX_SCATTERED, NONE, gather_rows_reference,
        scatter_rows_reference,
    };
    let ctx = context();
    let kernel = CompactRows::new(&ctx);
    let mut rng = rand::rngs::StdRng::seed_from_u64(29);
    for (batch_rows, sub_rows, widths) in [
        (1, 1, &[1usize][..]),
        (7, 5, &[60, 1][..]),
        (40, 64, &[3, 60, 3][..]),
        (300, 257, &[96, 20][..]),
    ] {
        let batch: Vec<Vec<f32>> = widths
            .iter()
            .map(|&f| random(&mut rng, batch_rows * f, 2.0))
            .collect();
        let sub: Vec<Vec<f32>> = widths
            .iter()
            .map(|&f| random(&mut rng, sub_rows * f, 2.0))
            .collect();
        // A permutation's prefix, some rows mapped to nothing, one past the end.
        let mut order: Vec<u32> = (0..batch_rows as u32).collect();
        for i in (1..order.len()).rev() {
            order.swap(i, rng.random_range(0..=i));
        }
        let row_map: Vec<u32> = (0..sub_rows)
            .map(|r| match r % 5 {
                4 => NONE,
                _ if r == sub_rows - 1 && sub_rows > 1 => batch_rows as u32 + 3,
                _ => order.get(r).copied().unwrap_or(NONE),
            })
            .collect();
        let regions = |src: &[Vec<f32>], dst: &[Vec<f32>]| -> Vec<(Vec<f32>, Vec<f32>, usize)> {
            (0..widths.len())
                .map(|k| (src[k].clone(), dst[k].clone(), widths[k]))
                .collect()
        };
        let into_sub = regions(&batch, &sub);
        let gathered = kernel
            .run(&ctx, false, &row_map, &borrowed(&into_sub))
            .unwrap();
        for (k, got) in gathered.iter().enumerate() {
            assert_eq!(
                got,
                &gather_rows_reference(&batch[k], &row_map, widths[k]),
                "gather {batch_rows} → {sub_rows} rows, region {k} of {widths:?}"
            );
        }
        let back = regions(&sub, &batch);
        let back = &back[..widths.len().min(MAX_SCATTERED)];
        let scattered = kernel.run(&ctx, true, &row_map, &borrowed(back)).unwrap();
        for (k, got) in scattered.iter().enumerate() {
            assert_eq!(
                got,
                &scatter_rows_reference(&sub[k], &row_map, &batch[k], widths[k]),
                "scatter {sub_rows} → {batch_rows} rows, region {k} of {widths:?}"
            );
        }
    }
    let one = [1.0f32];
    let too_many = vec![(&one[..], &one[..], 1); MAX_GATHERED + 1];
    let err = kernel
        .run(&ctx, false, &[0], &too_many)
        .unwrap_err()
        .to_string();
    assert!(err.contains("4 regions"), "{err}");
}

/// Host regions as `CompactRows::run` takes them.
fn borrowed(regions: &[(Vec<f32>, Vec<f32>, usize)]) -> Vec<(&[f32], &[f32], usize)> {
    regions
        .iter()
        .map(|(s, d, f)| (&s[..], &d[..], *f))
        .collect()
}
