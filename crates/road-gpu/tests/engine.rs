//! The WGSL denoiser and Heun step against the candle reference, on real validation scenes
//! (`ROAD_DATA`, else `../shared/data/interaction`), with one per-slot σ vector per scene.

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{Device, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use road_data::{Dataset, SourceSet, Split, WindowConfig};
use road_gpu::engine::{DenoiseInputs, GpuDenoiser};
use road_gpu::kernels::linear::LinearKernel;
use road_gpu::{ContextOptions, GpuContext, Tolerance};
use road_model::batch::{Batch, SceneInput, collate, normal_vec, task_sigma};
use road_model::checkpoint::{self, CheckpointMeta, DataIdentity};
use road_model::config::TaskKind;
use road_model::model::{self, Denoiser, Mode};
use road_model::{ModelConfig, RunConfig};

/// Parity tolerance of the whole denoiser: f32 sums in another order through every block.
const WHOLE_MODEL: Tolerance = Tolerance {
    rel: 1e-4,
    abs: 1e-5,
};
/// The whole denoiser with its blocks' layers in f16: each rounding moves an input or weight by
/// up to 2⁻¹¹ of it (5·10⁻⁴), through two blocks of the test model. Measured on the lavapipe
/// here (2026-11-30): largest difference 7.1·10⁻⁴ on outputs up to 7.1 (f32: 10⁻⁵); the
/// tolerance leaves about 3× for a card's other order of sums.
const F16_WHOLE_MODEL: Tolerance = Tolerance {
    rel: 2e-3,
    abs: 2e-3,
};
/// Rollouts chain dozens of evaluations and Heun steps: differences grow along the way.
const ROLLOUT: Tolerance = Tolerance {
    rel: 1e-3,
    abs: 1e-4,
};

fn context() -> GpuContext {
    context_with(None)
}

/// As [`context`], with the linear layers' kernel named instead of picked by adapter.
fn context_with(linear_kernel: Option<LinearKernel>) -> GpuContext {
    context_with_checks(linear_kernel, false)
}

/// As [`context_with`], the kernels compiled without wgpu's runtime checks when `unchecked`.
fn context_with_checks(linear_kernel: Option<LinearKernel>, unchecked: bool) -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        linear_kernel,
        unchecked_shaders: unchecked,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

/// As [`context`], every evaluation making the map's keys (`keep_map_keys` off): the
/// reference of the kept keys, which must change no state.
fn context_remaking_map_keys() -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        keep_map_keys: false,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

/// Rollouts by `run` with the map's keys kept (`ctx`'s default) and remade every evaluation:
/// the same states and plans to the bit, with fewer keys made when kept (`what` names the
/// rollout in a failure).
fn kept_map_keys_change_nothing<T: PartialEq + std::fmt::Debug>(
    ctx: &GpuContext,
    dir: &std::path::Path,
    what: &str,
    run: impl Fn(&mut road_gpu::step_engine::GpuStepEngine<'_>) -> T,
) -> T {
    use road_gpu::step_engine::GpuStepEngine;
    assert!(ctx.keep_map_keys());
    let gpu = GpuDenoiser::from_checkpoint(ctx, dir).unwrap();
    let mut kept = GpuStepEngine::new(ctx, &gpu);
    let kept_out = run(&mut kept);
    let kept_work = kept.take_work();
    let remaking = context_remaking_map_keys();
    let gpu = GpuDenoiser::from_checkpoint(&remaking, dir).unwrap();
    let mut remade = GpuStepEngine::new(&remaking, &gpu);
    let remade_out = run(&mut remade);
    let remade_work = remade.take_work();
    assert_eq!(
        kept_out, remade_out,
        "{what}: kept map keys changed a state"
    );
    assert_eq!(kept_work.evaluations, remade_work.evaluations, "{what}");
    assert_eq!(
        remade_work.map_key_evaluations, remade_work.evaluations,
        "{what}"
    );
    assert!(
        kept_work.map_key_evaluations < kept_work.evaluations,
        "{what}: {} of {} evaluations made the map keys",
        kept_work.map_key_evaluations,
        kept_work.evaluations
    );
    assert!(
        kept_work.traffic.dispatches < remade_work.traffic.dispatches,
        "{what}"
    );
    kept_out
}

fn validation_set() -> Dataset {
    let dir = road_data::testing::interaction_dir();
    Dataset::build(
        &SourceSet::discover(&dir).unwrap(),
        Split::Validation,
        &WindowConfig::default(),
    )
    .unwrap()
}

/// A seeded road20-shaped model saved as a checkpoint (small hidden size keeps CI quick).
fn checkpoint_dir(config: &ModelConfig, name: &str) -> (PathBuf, Denoiser) {
    let (varmap, model) = model::init_seeded(config, &Device::Cpu, 42).unwrap();
    // Agent pairs' weights start at zero: random here, so that the comparisons exercise them.
    let mut rng = rand::rngs::StdRng::seed_from_u64(43);
    for (name, var) in varmap.data().lock().unwrap().iter() {
        if name.contains(".pair_") {
            let values: Vec<f32> = (0..var.elem_count())
                .map(|_| rng.random_range(-0.5f32..0.5))
                .collect();
            var.set(&Tensor::from_vec(values, var.dims(), &Device::Cpu).unwrap())
                .unwrap();
        }
    }
    let dir = std::env::temp_dir().join(format!("road-gpu-engine-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tensors: HashMap<String, Tensor> = varmap
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    checkpoint::save_tensors(&tensors, &dir.join(checkpoint::WEIGHTS_FILE)).unwrap();
    let run = RunConfig {
        model: config.clone(),
        ..RunConfig::default()
    };
    CheckpointMeta {
        run,
        data: DataIdentity {
            train_cache: "none".into(),
            train_windows: 0,
            validation_windows: 0,
            source: "test".into(),
        },
        step: 0,
        parameters: 0,
        wall_secs: 0.0,
        hardware: "test".into(),
        validation_loss: None,
        untrained_validation_loss: None,
    }
    .save(&dir)
    .unwrap();
    (dir, model)
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

/// Three real scenes of different agent counts, padded into one batch, each with its own σ[W].
fn batch(ds: &Dataset, config: &ModelConfig) -> Batch {
    let mut rng = StdRng::seed_from_u64(5);
    let scenes: Vec<SceneInput> = [17usize, 400, 2500]
        .iter()
        .map(|&i| {
            SceneInput::from_window(
                &ds.window(i % ds.len()).unwrap(),
                0,
                config.window_slots,
                config,
            )
        })
        .collect();
    assert!(
        scenes
            .iter()
            .map(|s| s.agents)
            .collect::<std::collections::HashSet<_>>()
            .len()
            > 1,
        "scenes of different sizes"
    );
    let sigma: Vec<Vec<f32>> = (0..scenes.len())
        .map(|_| task_sigma(&mut rng, config, 10, TaskKind::Rolling, 0.3, 0.5))
        .collect();
    let noise: Vec<Vec<f32>> = scenes
        .iter()
        .map(|s| normal_vec(&mut rng, s.agents * s.slots * 3))
        .collect();
    collate(&scenes, &sigma, Some(&noise), &Device::Cpu).unwrap()
}

fn test_config() -> ModelConfig {
    ModelConfig {
        hidden: 32,
        heads: 2,
        blocks: 2,
        ..ModelConfig::default()
    }
}

#[test]
fn whole_denoiser_matches_candle_on_real_validation_scenes() {
    whole_denoiser_matches_candle(&test_config(), "denoiser");
}

/// The agent frame (relative features in, rotated output out), with one agent missing at the
/// anchor slot so that the scene-frame fallback runs too.
#[test]
fn whole_denoiser_with_an_agent_frame_matches_candle() {
    let config = ModelConfig {
        agent_frame: Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 2.0,
            residual_scale: None,
            max_anchor_sigma: None,
        }),
        ..test_config()
    };
    whole_denoiser_matches_candle(&config, "denoiser-frame");
}

/// The constant-velocity reference (residual denoising at σ·scale, the last observed step as
/// features), with the same agent missing at the anchor slot.
#[test]
fn whole_denoiser_with_a_constant_velocity_reference_matches_candle() {
    let config = ModelConfig {
        agent_frame: Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: Some(40.0),
            max_anchor_sigma: None,
        }),
        ..test_config()
    };
    whole_denoiser_matches_candle(&config, "denoiser-residual");
}

/// Agent maps: each agent's 8 nearest polylines in its frame, picked on the device from the
/// anchors of the evaluated `x`.
#[test]
fn whole_denoiser_with_agent_maps_matches_candle() {
    whole_denoiser_matches_candle(&agent_map_config(), "denoiser-agent-map");
}

/// Agent pairs: agent attention in the pair kernel, features from the evaluated `x`.
#[test]
fn whole_denoiser_with_agent_pairs_matches_candle() {
    whole_denoiser_matches_candle(&agent_pairs_config(), "denoiser-agent-pairs");
}

/// The agent maps' encoder run 64 polylines at a time (as large batches run it to fit one
/// buffer binding) gives what one pass gives.
#[test]
fn whole_denoiser_with_the_map_encoder_in_chunks_matches_candle() {
    let ctx = GpuContext::new(&ContextOptions {
        validation: true,
        map_encoder_chunk_bytes: 1,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"));
    let config = agent_map_config();
    let b = batch(&validation_set(), &config);
    let (scenes, agents, _, _) = b.x_noisy.dims4().unwrap();
    let polylines = scenes * agents * config.agent_map.as_ref().unwrap().polylines;
    assert!(
        polylines > 2 * 64,
        "{polylines} agent-map polylines: too few for 3 chunks"
    );
    whole_denoiser_matches_candle_on(&ctx, &config, "denoiser-map-chunks");
}

/// Every linear kernel in the whole denoiser, whichever this adapter picks (a hardware GPU
/// picks by layer size, lavapipe too, with other thresholds), with the default
/// checkpoint's features.
#[test]
fn whole_denoiser_matches_candle_with_every_linear_kernel() {
    // Each kernel checked, and the blocked one (with every other kernel) also compiled without
    // wgpu's runtime checks, as `ContextOptions::unchecked_shaders` runs them.
    let settings = LinearKernel::ALL
        .map(|kernel| (kernel, false))
        .into_iter()
        .chain([(LinearKernel::Blocked, true)]);
    for (kernel, unchecked) in settings {
        let ctx = context_with_checks(Some(kernel), unchecked);
        assert_eq!(ctx.linear_kernel_setting(), kernel.entry());
        assert_eq!(ctx.unchecked_shaders(), unchecked);
        whole_denoiser_matches_candle_on(
            &ctx,
            &agent_pairs_config(),
            &format!(
                "denoiser-{}-{}",
                kernel.entry(),
                ctx.shader_checks_setting()
            ),
        );
    }
}

/// The blocks layer by layer (`ContextOptions::residual_chains` off), the variant the chains
/// are timed against, with the default checkpoint's features.
#[test]
fn whole_denoiser_matches_candle_layer_by_layer() {
    let ctx = GpuContext::new(&ContextOptions {
        validation: true,
        residual_chains: false,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"));
    assert_eq!(ctx.fusion_setting(), "layers");
    whole_denoiser_matches_candle_on(&ctx, &agent_pairs_config(), "denoiser-layers");
}

/// The residual chains on the narrow tile (`ContextOptions::wide_chains` off: 8 rows a
/// workgroup, blocks of 4 × 4, weights read one float at a time), with the default checkpoint's
/// features; the default options run the wide tile where the model has one (checked here too).
#[test]
fn whole_denoiser_matches_candle_on_the_narrow_chain_tile() {
    let config = agent_pairs_config();
    let default = context();
    assert_eq!(default.fusion_setting(), "wide-chains");
    let (dir, _) = checkpoint_dir(&config, "denoiser-chain-tiles");
    let gpu = GpuDenoiser::from_checkpoint(&default, &dir).unwrap();
    let tile = gpu
        .wide_chain_tile()
        .expect("the test model has a wide chain tile");
    assert!(tile.wide_blocks && tile.rows >= 16, "{tile:?}");
    let settings = gpu.settings_for(&default, 4096);
    assert!(
        settings.residual_chains && settings.wide_chains,
        "{settings:?}"
    );
    let ctx = GpuContext::new(&ContextOptions {
        validation: true,
        wide_chains: false,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"));
    assert_eq!(ctx.fusion_setting(), "chains");
    whole_denoiser_matches_candle_on(&ctx, &config, "denoiser-narrow-chains");
}

/// Under [`road_gpu::Precision::F16`] (the blocks' layers with f16 inputs and weights, f32
/// sums: `linear_coop` on a card that offers it, `linear_f16` here) the default checkpoint's
/// features stay within [`F16_WHOLE_MODEL`] of candle's f32.
#[test]
fn whole_denoiser_in_f16_stays_near_candle() {
    let ctx = GpuContext::new(&ContextOptions {
        validation: true,
        precision: road_gpu::Precision::F16,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("the f16 tests need an adapter with SHADER_F16: {e}"));
    assert_eq!(ctx.precision(), road_gpu::Precision::F16);
    whole_denoiser_within(&ctx, &agent_pairs_config(), "denoiser-f16", F16_WHOLE_MODEL);
}

fn agent_pairs_config() -> ModelConfig {
    ModelConfig {
        agent_pairs: Some(road_model::AgentPairs {
            direction_scale_m: 10.0,
            near_scale_m: 5.0,
            far_scale_m: 20.0,
        }),
        ..agent_map_config()
    }
}

fn agent_map_config() -> ModelConfig {
    ModelConfig {
        agent_frame: Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: Some(40.0),
            max_anchor_sigma: None,
        }),
        agent_map: Some(road_model::AgentMap { polylines: 8 }),
        ..test_config()
    }
}

fn whole_denoiser_matches_candle(config: &ModelConfig, name: &str) {
    whole_denoiser_matches_candle_on(&context(), config, name);
}

fn whole_denoiser_matches_candle_on(ctx: &GpuContext, config: &ModelConfig, name: &str) {
    whole_denoiser_within(ctx, config, name, WHOLE_MODEL);
}

/// The GPU denoiser on `ctx` against candle's on real validation scenes, within `tolerance`.
fn whole_denoiser_within(ctx: &GpuContext, config: &ModelConfig, name: &str, tolerance: Tolerance) {
    let (dir, reference) = checkpoint_dir(config, name);
    let gpu = GpuDenoiser::from_checkpoint(ctx, &dir).unwrap();
    let ds = validation_set();
    let mut b = batch(&ds, config);
    if let Some(frame) = &config.agent_frame {
        // Scene 0, agent 1: not valid at the anchor slot (its other slots stay valid).
        let mut valid = flat(&b.valid);
        let w = config.window_slots;
        valid[w + frame.anchor_slot] = 0.0;
        b.valid = Tensor::from_vec(valid, b.valid.shape(), &Device::Cpu).unwrap();
    }
    let (scenes, agents, _, _) = b.x_noisy.dims4().unwrap();
    let polylines = b.map_valid.dim(1).unwrap();

    let map_tokens = reference.encode_map(&b.map, Mode::Infer).unwrap();
    let want = flat(
        &reference
            .denoise(
                &b.x_noisy,
                &b.sigma,
                &b.valid,
                &b.agent_features,
                &map_tokens,
                &b.map_valid,
                Mode::Infer,
            )
            .unwrap(),
    );

    let map = gpu
        .encode_map(ctx, scenes, polylines, &flat(&b.map), &flat(&b.map_valid))
        .unwrap();
    let (x, sigma, valid, features) = (
        flat(&b.x_noisy),
        flat(&b.sigma),
        flat(&b.valid),
        flat(&b.agent_features),
    );
    let inputs = DenoiseInputs {
        scenes,
        agents,
        x: &x,
        sigma: &sigma,
        valid: &valid,
        agent_features: &features,
    };
    let got = gpu.denoise(ctx, &inputs, &map).unwrap();
    if std::env::var_os("ROAD_PRINT_ERRORS").is_some() {
        let worst = got
            .iter()
            .zip(&want)
            .map(|(g, w)| (g - w).abs())
            .fold(0.0f32, f32::max);
        let scale = want.iter().map(|w| w.abs()).fold(0.0f32, f32::max);
        eprintln!("{name}: largest difference {worst} (largest output {scale})");
    }
    if let Err(m) = tolerance.check(&got, &want) {
        panic!("denoiser on {}: {m}", ctx.describe());
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A rolling step of each scene's own σ `[B, W]`: σ_next one K-th (K = 40) lower in u, the
/// observed slots unchanged, slot 10 landing on 0.
fn rolling_step(config: &ModelConfig, sigma_cur: &[f32], w: usize) -> Vec<f32> {
    let edm = config.edm;
    sigma_cur
        .iter()
        .enumerate()
        .map(|(i, &s)| match i % w {
            slot if slot < 10 => s,
            10 => 0.0,
            _ => edm.sigma(edm.u_of_sigma(f64::from(s)) - 1.0 / 40.0) as f32,
        })
        .collect()
}

/// One Heun step (both evaluations and the update on the GPU) against the same step computed
/// from candle's evaluations.
#[test]
fn heun_step_matches_the_reference() {
    let ctx = context();
    let config = test_config();
    let (dir, reference) = checkpoint_dir(&config, "heun");
    let gpu = GpuDenoiser::from_checkpoint(&ctx, &dir).unwrap();
    let ds = validation_set();
    let b = batch(&ds, &config);
    let (scenes, agents, w, _) = b.x_noisy.dims4().unwrap();
    let polylines = b.map_valid.dim(1).unwrap();
    let sigma_cur = flat(&b.sigma);
    let sigma_next = rolling_step(&config, &sigma_cur, w);
    let eval_sigma: Vec<f32> = sigma_cur
        .iter()
        .zip(&sigma_next)
        .map(|(&s, &n)| if n > 0.0 { n } else { s })
        .collect();
    let map_tokens = reference.encode_map(&b.map, Mode::Infer).unwrap();
    let d = |x: &Tensor, sigma: &[f32]| {
        let s = Tensor::from_vec(sigma.to_vec(), (scenes, w), &Device::Cpu).unwrap();
        flat(
            &reference
                .denoise(
                    x,
                    &s,
                    &b.valid,
                    &b.agent_features,
                    &map_tokens,
                    &b.map_valid,
                    Mode::Infer,
                )
                .unwrap(),
        )
    };
    let x = flat(&b.x_noisy);
    let d1 = d(&b.x_noisy, &sigma_cur);
    let slot_sigma = |e: usize| {
        let token = e / 3;
        let (slot, scene) = (token % w, token / (w * agents));
        (sigma_cur[scene * w + slot], sigma_next[scene * w + slot])
    };
    let x_e: Vec<f32> = (0..x.len())
        .map(|e| {
            let (s, n) = slot_sigma(e);
            if s == n {
                x[e]
            } else {
                x[e] + (n - s) * (x[e] - d1[e]) / s
            }
        })
        .collect();
    let d2 = d(
        &Tensor::from_vec(x_e.clone(), (scenes, agents, w, 3), &Device::Cpu).unwrap(),
        &eval_sigma,
    );
    let want: Vec<f32> = (0..x.len())
        .map(|e| {
            let (s, n) = slot_sigma(e);
            if s == n || n == 0.0 {
                x_e[e]
            } else {
                x[e] + (n - s) * 0.5 * ((x[e] - d1[e]) / s + (x_e[e] - d2[e]) / n)
            }
        })
        .collect();

    let map = gpu
        .encode_map(&ctx, scenes, polylines, &flat(&b.map), &flat(&b.map_valid))
        .unwrap();
    let (valid, features) = (flat(&b.valid), flat(&b.agent_features));
    let inputs = DenoiseInputs {
        scenes,
        agents,
        x: &x,
        sigma: &sigma_cur,
        valid: &valid,
        agent_features: &features,
    };
    let device_batch = gpu.upload_batch(&ctx, &inputs).unwrap();
    let got = gpu
        .heun_step(
            &ctx,
            &device_batch,
            &map,
            &sigma_cur,
            &sigma_next,
            true,
            true,
        )
        .unwrap()
        .unwrap();
    if let Err(m) = WHOLE_MODEL.check(&got, &want) {
        panic!("Heun step on {}: {m}", ctx.describe());
    }
    // Observed slots (σ unchanged) are untouched exactly.
    for e in 0..x.len() {
        let (s, n) = slot_sigma(e);
        if s == n {
            assert_eq!(got[e], x[e]);
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// One multistep step (the evaluation, the Euler update and `multistep_correct` on the GPU)
/// against the CPU reference (`road_rollout::heun`) over candle's evaluation, with a previous
/// estimate and γ per scene and slot (0 for observations and every fourth slot).
#[test]
fn multistep_step_matches_the_reference() {
    use road_gpu::sampler_step::StepRule;
    use road_rollout::heun::{heun_update, multistep_correct};
    let ctx = context();
    let config = test_config();
    let (dir, reference) = checkpoint_dir(&config, "multistep");
    let gpu = GpuDenoiser::from_checkpoint(&ctx, &dir).unwrap();
    let ds = validation_set();
    let b = batch(&ds, &config);
    let (scenes, agents, w, _) = b.x_noisy.dims4().unwrap();
    let polylines = b.map_valid.dim(1).unwrap();
    let sigma_cur = flat(&b.sigma);
    let sigma_next = rolling_step(&config, &sigma_cur, w);
    let mut rng = StdRng::seed_from_u64(12);
    let gamma: Vec<f32> = (0..scenes * w)
        .map(|i| {
            let slot = i % w;
            if slot < 10 || slot % 4 == 0 {
                0.0
            } else {
                rng.random_range(0.05f32..0.6)
            }
        })
        .collect();
    let x = flat(&b.x_noisy);
    let previous: Vec<f32> = x
        .iter()
        .map(|v| 0.5 * v + rng.random_range(-0.2f32..0.2))
        .collect();
    let map_tokens = reference.encode_map(&b.map, Mode::Infer).unwrap();
    let (mut want, d1) = heun_update(&x, agents, w, &sigma_cur, &sigma_next, false, |x, sigma| {
        let x = Tensor::from_vec(x.to_vec(), (scenes, agents, w, 3), &Device::Cpu)?;
        let s = Tensor::from_vec(sigma.to_vec(), (scenes, w), &Device::Cpu)?;
        Ok(flat(&reference.denoise(
            &x,
            &s,
            &b.valid,
            &b.agent_features,
            &map_tokens,
            &b.map_valid,
            Mode::Infer,
        )?))
    })
    .unwrap();
    let euler = want.clone();
    multistep_correct(&mut want, &d1, &previous, &gamma, agents, w);

    let map = gpu
        .encode_map(&ctx, scenes, polylines, &flat(&b.map), &flat(&b.map_valid))
        .unwrap();
    let (valid, features) = (flat(&b.valid), flat(&b.agent_features));
    let inputs = DenoiseInputs {
        scenes,
        agents,
        x: &x,
        sigma: &sigma_cur,
        valid: &valid,
        agent_features: &features,
    };
    let device_batch = gpu.upload_batch(&ctx, &inputs).unwrap();
    let mut plan = gpu.heun_plan(&ctx, &device_batch, &map).unwrap();
    let previous_buffer = road_gpu::kernels::storage_buffer(&ctx, "previous", (x.len() * 4) as u64);
    ctx.queue
        .write_buffer(&previous_buffer, 0, bytemuck::cast_slice(&previous));
    plan.run_rule(
        &ctx,
        &device_batch,
        &sigma_cur,
        &sigma_next,
        StepRule::Multistep { gamma: &gamma },
        None,
        |enc, kept| enc.copy_buffer_to_buffer(&previous_buffer, 0, kept, 0, (x.len() * 4) as u64),
        |_, _| {},
    )
    .unwrap();
    let bytes = road_gpu::kernels::read_back(&ctx, &device_batch.x, (x.len() * 4) as u64).unwrap();
    let got: &[f32] = bytemuck::cast_slice(&bytes);
    if let Err(m) = WHOLE_MODEL.check(got, &want) {
        panic!("multistep step on {}: {m}", ctx.describe());
    }
    // The correction matters here: the Euler step alone is far outside the tolerance.
    assert!(WHOLE_MODEL.check(&euler, &want).is_err());
    std::fs::remove_dir_all(&dir).ok();
}

/// `road sample --engine gpu|cpu`: the same rollout driver and seed give the same futures.
#[test]
fn gpu_and_cpu_rollouts_agree_for_a_seed() {
    use road_cpu::rollout;
    use road_gpu::step_engine::GpuStepEngine;
    use road_rollout::{RolloutScene, rollout_with};
    use road_sched::{PlannerKind, PlannerSpec};
    let ctx = context();
    let config = test_config();
    let (dir, reference) = checkpoint_dir(&config, "rollout");
    let gpu = GpuDenoiser::from_checkpoint(&ctx, &dir).unwrap();
    let ds = validation_set();
    let scenes: Vec<RolloutScene> = [3usize, 1200]
        .iter()
        .map(|&i| RolloutScene {
            history: SceneInput::from_window(&ds.window(i).unwrap(), 0, 10, &config),
        })
        .collect();
    for spec in [
        PlannerSpec {
            steps_per_diffusion: 10,
            ..PlannerSpec::default()
        },
        PlannerSpec {
            kind: PlannerKind::Mpc,
            steps_per_diffusion: 10,
            replan_every: Some(3),
            ..PlannerSpec::default()
        },
        PlannerSpec {
            steps_per_diffusion: 10,
            sampler: road_sched::Sampler::Multistep,
            ..PlannerSpec::default()
        },
    ] {
        let cpu = rollout(&reference, &spec, &scenes, 6, &mut StdRng::seed_from_u64(8)).unwrap();
        let on_gpu = rollout_with(
            &mut GpuStepEngine::new(&ctx, &gpu),
            &spec,
            &scenes,
            6,
            &mut StdRng::seed_from_u64(8),
        )
        .unwrap();
        assert_eq!(cpu.nfe, on_gpu.nfe);
        for (c, g) in cpu.states.iter().zip(&on_gpu.states) {
            if let Err(m) = ROLLOUT.check(g, c) {
                panic!("{:?} rollout ({:?}): {m}", spec.kind, spec.sampler);
            }
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Serving: scenes at different phases and planners share every batched step (per-scene σ
/// rows, idle scenes holding still, plans turned at emissions); the GPU engine agrees with the
/// candle reference.
#[test]
fn mixed_phase_batches_agree_with_the_reference() {
    mixed_phase_batches_agree(&test_config(), "mixed");
}

/// The same with agent maps: compact sub-batches carry each scene's polylines.
#[test]
fn mixed_phase_batches_with_agent_maps_agree_with_the_reference() {
    mixed_phase_batches_agree(&agent_map_config(), "mixed-agent-map");
}

/// The same with agent pairs: compact sub-batches' pair features come from their own states.
#[test]
fn mixed_phase_batches_with_agent_pairs_agree_with_the_reference() {
    mixed_phase_batches_agree(&agent_pairs_config(), "mixed-agent-pairs");
}

fn mixed_phase_batches_agree(config: &ModelConfig, name: &str) {
    use road_cpu::CpuEngine;
    use road_gpu::step_engine::GpuStepEngine;
    use road_rollout::{RolloutDriver, RolloutScene, StepEngine};
    use road_sched::{PlannerKind, PlannerSpec};
    let ctx = context();
    let config = config.clone();
    let (dir, reference) = checkpoint_dir(&config, name);
    let gpu = GpuDenoiser::from_checkpoint(&ctx, &dir).unwrap();
    let ds = validation_set();
    let scenes: Vec<RolloutScene> = [3usize, 1200, 2500]
        .iter()
        .map(|&i| RolloutScene {
            history: SceneInput::from_window(&ds.window(i).unwrap(), 0, 10, &config),
        })
        .collect();
    let rolling = PlannerSpec {
        steps_per_diffusion: 10,
        ..PlannerSpec::default()
    };
    let mpc = PlannerSpec {
        kind: PlannerKind::Mpc,
        replan_every: Some(2),
        ..rolling.clone()
    };
    let multistep = PlannerSpec {
        sampler: road_sched::Sampler::Multistep,
        ..rolling.clone()
    };
    // Per scene: its emitted states, then its plans (every scene reports them).
    let run = |engine: &mut dyn StepEngine| -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
        let mut driver =
            RolloutDriver::new(engine, &rolling, &scenes, 5, &mut StdRng::seed_from_u64(4))
                .unwrap();
        for i in 0..scenes.len() {
            driver.request_plans(i, true).unwrap();
        }
        let mut out: Vec<Vec<f32>> = vec![Vec::new(); scenes.len()];
        let mut plans: Vec<Vec<f32>> = vec![Vec::new(); scenes.len()];
        for t in 0..5 {
            if t == 1 {
                driver.switch_scene_planner(2, &mpc).unwrap();
            }
            if t == 2 {
                // Its warm-up runs beside the others' shorter ticks: compact sub-batches.
                driver.switch_scene_planner(1, &multistep).unwrap();
            }
            let which: &[usize] = if t == 3 { &[0, 2] } else { &[0, 1, 2] };
            driver
                .tick_scenes(engine, which, &mut |i, e, plan_turns| {
                    out[i].extend_from_slice(e);
                    // From tick 2 on, agent 0's plan turns about its new position (as the
                    // lane guard's `turn_plan` does), the window's and the kept estimate's.
                    if t >= 2 {
                        plan_turns[..4].copy_from_slice(&[e[0], e[1], 0.3, 0.1]);
                    }
                    Ok(())
                })
                .unwrap();
            for &i in which {
                let (_, plan) = driver.plan(i).expect("requested");
                plans[i].extend_from_slice(plan);
            }
        }
        (out, plans)
    };
    let (cpu, cpu_plans) = run(&mut CpuEngine::new(&reference));
    let (on_gpu, gpu_plans) = run(&mut GpuStepEngine::new(&ctx, &gpu));
    kept_map_keys_change_nothing(&ctx, &dir, name, |engine| run(engine));
    for (i, (c, g)) in cpu.iter().zip(&on_gpu).enumerate() {
        if let Err(m) = ROLLOUT.check(g, c) {
            panic!("scene {i}: {m}");
        }
    }
    for (i, (c, g)) in cpu_plans.iter().zip(&gpu_plans).enumerate() {
        assert!(!c.is_empty(), "scene {i} has plans");
        if let Err(m) = ROLLOUT.check(g, c) {
            panic!("scene {i}'s plans: {m}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Scenes of mixed agent counts step packed (several scenes' agents in one sub-batch scene) in a
/// model without agent maps or pairs: its plain agent attention keeps packed scenes apart and
/// its scene-frame map tokens are each agent's own scene's. The same rollouts as the CPU
/// reference, at less padded work than one batch at the most agents.
#[test]
fn packed_batches_of_scene_frame_maps_agree_with_the_reference() {
    packed_rollouts_agree(&test_config(), "packed-scene-frame", 40, |i| i * 131, 5);
}

/// Scenes of mixed agent counts packed (several scenes' agents in one sub-batch scene,
/// attending apart and picking from their own maps): the same rollouts as the CPU reference,
/// at a quarter over their own work where one batch at the most agents computes half again.
/// Eight validation scenes, as `road bench engine`'s 8-scene row.
#[test]
fn packed_batches_agree_with_the_reference() {
    packed_rollouts_agree(&agent_pairs_config(), "packed", 8, |i| i * 613 + 7, 6);
}

/// `count` validation windows (window `pick(i) % len` for scene i) of mixed agent counts,
/// rolled out 3 ticks by the GPU engine, which packs them, and by the CPU reference (`seed`):
/// the same states within the rollout tolerance, at most 1.25 computed over useful where one
/// batch at the most agents computes over 1.5, and as many evaluations as one batch.
fn packed_rollouts_agree(
    config: &ModelConfig,
    name: &str,
    count: usize,
    pick: impl Fn(usize) -> usize,
    seed: u64,
) {
    use road_cpu::CpuEngine;
    use road_gpu::proxies::flops_per_evaluation;
    use road_gpu::step_engine::GpuStepEngine;
    use road_rollout::{RolloutDriver, RolloutScene, StepEngine};
    use road_sched::PlannerSpec;
    let ctx = context();
    let (dir, reference) = checkpoint_dir(config, name);
    let gpu = GpuDenoiser::from_checkpoint(&ctx, &dir).unwrap();
    let ds = validation_set();
    let scenes: Vec<RolloutScene> = (0..count)
        .map(|i| RolloutScene {
            history: SceneInput::from_window(
                &ds.window(pick(i) % ds.len()).unwrap(),
                0,
                10,
                config,
            ),
        })
        .collect();
    let counts: Vec<usize> = scenes.iter().map(|s| s.history.agents).collect();
    let (most_agents, most_polylines) = (
        *counts.iter().max().unwrap(),
        scenes.iter().map(|s| s.history.polylines).max().unwrap(),
    );
    let padded: f64 =
        scenes.len() as f64 * flops_per_evaluation(config, most_agents, most_polylines);
    let own: f64 = scenes
        .iter()
        .map(|s| flops_per_evaluation(config, s.history.agents, s.history.polylines))
        .sum();
    assert!(
        padded / own > 1.5,
        "the scenes' agent counts {counts:?} should be mixed enough to pack"
    );
    let planner = PlannerSpec {
        steps_per_diffusion: 10,
        ..PlannerSpec::default()
    };
    let run = |engine: &mut dyn StepEngine| -> Vec<Vec<f32>> {
        let mut driver = RolloutDriver::new(
            engine,
            &planner,
            &scenes,
            3,
            &mut StdRng::seed_from_u64(seed),
        )
        .unwrap();
        let all: Vec<usize> = (0..scenes.len()).collect();
        let mut out: Vec<Vec<f32>> = vec![Vec::new(); scenes.len()];
        for _ in 0..3 {
            driver
                .tick_scenes(engine, &all, &mut |i, e, _| {
                    out[i].extend_from_slice(e);
                    Ok(())
                })
                .unwrap();
        }
        out
    };
    let cpu = run(&mut CpuEngine::new(&reference));
    let mut engine = GpuStepEngine::new(&ctx, &gpu);
    let on_gpu = run(&mut engine);
    kept_map_keys_change_nothing(&ctx, &dir, name, |engine| run(engine));
    for (i, (c, g)) in cpu.iter().zip(&on_gpu).enumerate() {
        if let Err(m) = ROLLOUT.check(g, c) {
            panic!("scene {i} ({} agents): {m}", counts[i]);
        }
    }
    let work = engine.take_work();
    let ratio = work.computed_over_useful();
    assert!(
        ratio <= 1.25,
        "computed over useful {ratio:.2}: one batch at the most agents would be {:.2}",
        padded / own
    );
    // An evaluation is the batch's, however it was packed: as many as one batch has.
    let one_batch = GpuContext::new(&ContextOptions {
        validation: true,
        pack_scenes: false,
        ..ContextOptions::default()
    })
    .unwrap();
    let gpu = GpuDenoiser::from_checkpoint(&one_batch, &dir).unwrap();
    let mut unpacked = GpuStepEngine::new(&one_batch, &gpu);
    run(&mut unpacked);
    assert_eq!(work.evaluations, unpacked.take_work().evaluations);
    std::fs::remove_dir_all(&dir).ok();
}
