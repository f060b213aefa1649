//! The engine's proxies (`road bench engine`'s `dispatches_per_evaluation`,
//! `bytes_per_evaluation`, `computed_over_useful`) on the adapter at hand (lavapipe in CI):
//! counted as dispatches are recorded, equal to the sum of their bindings, stable from step to
//! step, and padding counted as computed but not useful; and what the step engine does to save
//! them (row moves skipped, the sampler's step fused, a round's readback in one wait) changes
//! no result.

use road_gpu::engine::{DenoiseInputs, GpuDenoiser};
use road_gpu::kernels::Dispatch;
use road_gpu::proxies::{Work, flops_per_evaluation, map_key_flops};
use road_gpu::step_engine::GpuStepEngine;
use road_gpu::{ContextOptions, GpuContext};
use road_model::ModelConfig;
use road_rollout::StepEngine;

mod common;
use common::{config, denoiser};

/// Scenes, agents and polylines of the padded test batch.
const SCENES: usize = 3;
const AGENTS: usize = 4;
const POLYLINES: usize = 6;

fn context() -> GpuContext {
    context_with_chains(true)
}

/// As [`context`], the blocks run as residual chains or (`false`) layer by layer.
fn context_with_chains(residual_chains: bool) -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        residual_chains,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

/// As [`context`], scenes of mixed agent counts never packed: one batch padded.
fn context_unpacked() -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        pack_scenes: false,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

/// A padded batch, host side: `agents[i]` valid agents and `polylines[i]` valid polylines of
/// scene i, the rest padding.
struct Scenes {
    features: Vec<f32>,  // [B, A, 6]
    map: Vec<f32>,       // [B, P, Q, 2]
    map_valid: Vec<f32>, // [B, P]
    x: Vec<f32>,         // [B, A, W, 3]
    valid: Vec<f32>,     // [B, A, W]
}

fn scenes(config: &ModelConfig, agents: [usize; SCENES], polylines: [usize; SCENES]) -> Scenes {
    let (w, q) = (config.window_slots, config.polyline_points);
    let wave = |i: usize, scale: f32| ((i as f32) * 0.37).sin() * scale;
    let mut valid = vec![0.0f32; SCENES * AGENTS * w];
    let mut map_valid = vec![0.0f32; SCENES * POLYLINES];
    for b in 0..SCENES {
        valid[b * AGENTS * w..][..agents[b] * w].fill(1.0);
        map_valid[b * POLYLINES..][..polylines[b]].fill(1.0);
    }
    Scenes {
        features: (0..SCENES * AGENTS * 6).map(|i| wave(i, 1.0)).collect(),
        map: (0..SCENES * POLYLINES * q * 2)
            .map(|i| wave(i, 2.0))
            .collect(),
        map_valid,
        x: (0..SCENES * AGENTS * w * 3).map(|i| wave(i, 1.5)).collect(),
        valid,
    }
}

/// Every scene's σ `[B, W]` one step down, or (`idle`) held.
fn sigma_rows(config: &ModelConfig, idle: &[usize]) -> (Vec<f32>, Vec<f32>) {
    let w = config.window_slots;
    let cur = vec![2.0f32; SCENES * w];
    let next = (0..SCENES * w)
        .map(|i| if idle.contains(&(i / w)) { 2.0 } else { 1.5 })
        .collect();
    (cur, next)
}

fn engine_on<'a>(ctx: &'a GpuContext, gpu: &'a GpuDenoiser, s: &Scenes) -> GpuStepEngine<'a> {
    let mut engine = GpuStepEngine::new(ctx, gpu);
    engine
        .prepare(SCENES, AGENTS, &s.features, POLYLINES, &s.map, &s.map_valid)
        .unwrap();
    engine.load(&s.x, &s.valid).unwrap();
    engine
}

fn bytes(dispatches: &[Dispatch]) -> u64 {
    dispatches
        .iter()
        .map(|d| d.bytes_read() + d.bytes_written())
        .sum()
}

/// Dispatch and byte counts: positive, the same for two steps of the same batch, half for a
/// step without its second evaluation, and equal to the sum of the plan's dispatches' bindings,
/// which for the head and the Euler update are checked by hand (layer by layer, where the head
/// is a dispatch of its own).
#[test]
fn dispatches_and_bytes_are_the_bindings_of_the_recorded_dispatches() {
    let ctx = context_with_chains(false);
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let s = scenes(&config, [AGENTS; SCENES], [POLYLINES; SCENES]);
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);

    let mut engine = engine_on(&ctx, &gpu, &s);
    let mut heun_step = |second: bool| -> Work {
        engine.step(&sigma_cur, &sigma_next, second).unwrap();
        engine.take_work()
    };
    let first = heun_step(true);
    let again = heun_step(true);
    let euler_only = heun_step(false);
    assert_eq!(first, again, "the same batch, the same counts");
    assert_eq!(first.evaluations, 2);
    assert_eq!(euler_only.evaluations, 1);
    assert!(first.traffic.dispatches > 0 && first.traffic.bytes_written > 0);
    assert!(first.traffic.bytes_read > first.traffic.bytes_written);
    assert_eq!(
        first.dispatches_per_evaluation(),
        euler_only.dispatches_per_evaluation(),
        "both evaluations and their updates record alike"
    );

    // The same batch through a Heun plan: its counts are the sums over its dispatch lists.
    let inputs = DenoiseInputs {
        scenes: SCENES,
        agents: AGENTS,
        x: &s.x,
        sigma: &sigma_cur,
        valid: &s.valid,
        agent_features: &s.features,
    };
    let batch = gpu.upload_batch(&ctx, &inputs).unwrap();
    let map = gpu
        .encode_map(&ctx, SCENES, POLYLINES, &s.map, &s.map_valid)
        .unwrap();
    let mut plan = gpu.heun_plan(&ctx, &batch, &map).unwrap();
    plan.run(&ctx, &batch, &sigma_cur, &sigma_next, true)
        .unwrap();
    let traffic = plan.take_traffic();
    let (euler, correct) = (plan.euler_dispatches(), plan.correct_dispatches());
    assert_eq!(traffic.dispatches as usize, euler.len() + correct.len());
    assert_eq!(traffic.bytes(), bytes(euler) + bytes(correct));
    assert_eq!(
        traffic, first.traffic,
        "the engine records the plan's dispatches"
    );
    assert_eq!(euler_only.traffic.dispatches as usize, euler.len());
    assert_eq!(euler_only.traffic.bytes(), bytes(euler));

    // By hand. The head (`ln_out` in its prologue, γ and β folded into its weights; the last
    // linear layer): 48 bytes of params, x [T, D], w [3, D], b [3] read; y [T, 3] read and
    // written.
    let (w, d) = (config.window_slots as u64, config.hidden as u64);
    let tokens = (SCENES * AGENTS) as u64 * w;
    let head = euler
        .iter()
        .rev()
        .find(|d| d.label().starts_with("linear"))
        .unwrap();
    assert_eq!(
        head.bytes_read(),
        48 + 4 * (tokens * d + 3 * d + 3 + tokens * 3)
    );
    assert_eq!(head.bytes_written(), 4 * tokens * 3);
    // The Euler update: params, x, D₁ [B, A, W, 3], σ_cur, σ_next [B, W] read; x_e read and
    // written.
    let update = euler.last().unwrap();
    assert_eq!(update.label(), "heun_euler");
    let (states, sigma) = (4 * tokens * 3, 4 * SCENES as u64 * w);
    assert_eq!(update.bytes_read(), 16 + 3 * states + 2 * sigma);
    assert_eq!(update.bytes_written(), states);
}

/// Work computed over useful: 1 when every scene fills the batch's agents and polylines; above
/// 1 by exactly the padding when they do not; idle scenes of a step are computed, not useful.
/// (Scenes never packed: `packing_computes_the_packed_scenes`.)
#[test]
fn computed_over_useful_counts_the_padding() {
    let ctx = context_unpacked();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let f = |agents, polylines| flops_per_evaluation(&config, agents, polylines);
    let ratio = |agents: [usize; SCENES], polylines: [usize; SCENES], idle: &[usize]| {
        let s = scenes(&config, agents, polylines);
        let mut engine = engine_on(&ctx, &gpu, &s);
        let (sigma_cur, sigma_next) = sigma_rows(&config, idle);
        engine.step(&sigma_cur, &sigma_next, true).unwrap();
        let work = engine.take_work();
        assert_eq!(work.evaluations, 2);
        work.computed_over_useful()
    };

    let full = ratio([AGENTS; SCENES], [POLYLINES; SCENES], &[]);
    assert!((full - 1.0).abs() < 1e-12, "no padding: {full}");

    // Mixed: 4, 2 and 1 agents, 6, 3 and 6 polylines, padded to 4 × 6.
    let (agents, polylines) = ([4, 2, 1], [6, 3, 6]);
    let mixed = ratio(agents, polylines, &[]);
    let useful: f64 = (0..SCENES).map(|i| f(agents[i], polylines[i])).sum();
    let want = SCENES as f64 * f(AGENTS, POLYLINES) / useful;
    assert!(mixed > 1.0, "padding: {mixed}");
    assert!((mixed - want).abs() < 1e-9 * want, "{mixed} against {want}");

    // Only scene 1 moves: a compact sub-batch of one scene at 4 agents (its 2 rounded up).
    let one = ratio(agents, polylines, &[0, 2]);
    let want = f(AGENTS, POLYLINES) / f(2, 3);
    assert!((one - want).abs() < 1e-9 * want, "{one} against {want}");
}

/// Packed (lavapipe packs from two moving scenes): 4, 2 and 1 agents padded to 4 step as the
/// scene of 4 and one scene holding the 2 and the 1 (or one scene of 8, whichever computes
/// less), with the dispatches of one batch and the packed rows' moves (counted with them);
/// scenes that fill the batch are not packed.
#[test]
fn packing_computes_the_packed_scenes() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let f = |agents| flops_per_evaluation(&config, agents, POLYLINES);
    let step = |agents: [usize; SCENES]| {
        let s = scenes(&config, agents, [POLYLINES; SCENES]);
        let mut engine = engine_on(&ctx, &gpu, &s);
        let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);
        engine.step(&sigma_cur, &sigma_next, true).unwrap();
        engine.take_work()
    };
    let full = step([AGENTS; SCENES]);
    assert!((full.computed_over_useful() - 1.0).abs() < 1e-12);
    let mixed = step([4, 2, 1]);
    let useful = f(4) + f(2) + f(1);
    let want = (2.0 * f(4)).min(f(8)) / useful;
    let got = mixed.computed_over_useful();
    assert!((got - want).abs() < 1e-9 * want, "{got} against {want}");
    assert!(
        got < 0.8 * 3.0 * f(4) / useful,
        "less than the padded batch"
    );
    // The moves, once a step: three gathers (states and flags; agent embeddings; map data and
    // flags: one dispatch per row map and kind) and one scatter (states and the kept estimate).
    assert_eq!(mixed.evaluations, full.evaluations);
    assert_eq!(mixed.traffic.dispatches, full.traffic.dispatches + 3 + 1);
}

/// A packed sub-batch gathers the agent embeddings and maps only when they change: its next
/// step moves states and flags alone, and a scene's new map (`prepare_scene`) brings them back.
#[test]
fn packed_steps_gather_agent_embeddings_and_maps_only_when_they_change() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let s = scenes(&config, [4, 2, 1], [POLYLINES; SCENES]);
    let mut engine = engine_on(&ctx, &gpu, &s);
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);
    let step = |engine: &mut GpuStepEngine<'_>| {
        engine.step(&sigma_cur, &sigma_next, true).unwrap();
        engine.take_work()
    };
    let first = step(&mut engine);
    let again = step(&mut engine);
    assert_eq!(again.evaluations, first.evaluations);
    assert_eq!(again.traffic.dispatches, first.traffic.dispatches - 2);
    assert!(again.traffic.bytes() < first.traffic.bytes());
    let (a, q) = (AGENTS, config.polyline_points);
    engine
        .prepare_scene(
            1,
            &s.features[a * 6..2 * a * 6],
            &s.map[POLYLINES * q * 2..2 * POLYLINES * q * 2],
            &s.map_valid[POLYLINES..2 * POLYLINES],
        )
        .unwrap();
    let changed = step(&mut engine);
    assert_eq!(changed.traffic, first.traffic);
}

/// The map's keys (the agent maps' pick and encoder, every block's map k, v: 3 dispatches
/// here) are made only when what they are made from changed: a Heun step whose σ moves the
/// anchor slot makes them in both evaluations; one that leaves it (as a tick's observed slots)
/// in its first only; the next such step in neither; a load brings them back. Their work is
/// counted only where made.
#[test]
fn map_keys_are_made_only_when_their_inputs_change() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let s = scenes(&config, [AGENTS; SCENES], [POLYLINES; SCENES]);
    let mut engine = engine_on(&ctx, &gpu, &s);
    let w = config.window_slots;
    let anchor = config.agent_frame.as_ref().unwrap().anchor_slot;
    let (sigma_cur, moving) = sigma_rows(&config, &[]);
    let mut held = moving.clone();
    for b in 0..SCENES {
        held[b * w + anchor] = sigma_cur[b * w + anchor];
    }
    let step = |engine: &mut GpuStepEngine<'_>, sigma_next: &[f32]| {
        engine.step(&sigma_cur, sigma_next, true).unwrap();
        engine.take_work()
    };
    let both = step(&mut engine, &moving);
    engine.load(&s.x, &s.valid).unwrap();
    let first = step(&mut engine, &held);
    let neither = step(&mut engine, &held);
    engine.load(&s.x, &s.valid).unwrap();
    let reloaded = step(&mut engine, &held);
    assert_eq!(
        [both, first, neither, reloaded].map(|w| w.map_key_evaluations),
        [2, 1, 0, 1]
    );
    let keys = 3;
    assert_eq!(first.traffic.dispatches, both.traffic.dispatches - keys);
    assert_eq!(
        neither.traffic.dispatches,
        both.traffic.dispatches - 2 * keys
    );
    assert_eq!(reloaded.traffic, first.traffic);
    let key_flops = SCENES as f64 * map_key_flops(&config, AGENTS, POLYLINES);
    let saved = both.computed_flops - neither.computed_flops;
    assert!(
        (saved - 2.0 * key_flops).abs() < 1e-9 * saved,
        "{saved} against {key_flops}"
    );
    assert_eq!(neither.computed_flops, neither.useful_flops);
}

/// Residual chains: per evaluation the agent maps' pick and encoder, every block's map k, v at
/// once, the embedding with the first q, k, v (one chain), then per block three chains, each
/// making the attention before it (over time, over agents with the pair features, over the
/// map), the last of which makes the
/// first evaluation's Euler step too (a Heun step's second
/// evaluation adds its correction: half a dispatch an evaluation; a multistep step none); layer
/// by layer the embedding, the first q, k, v and 11 per block (the map k, v of every block still
/// at once), the head, the preconditioning, the update (and the multistep correction).
/// Fewer bytes too: the MLP's hidden layer and the head's F stay on chip. The last chain (the
/// head's) writes the residual stream, D(x; σ) and the Euler step's x_e, nothing else.
#[test]
fn residual_chains_cut_the_dispatches_and_bytes_of_an_evaluation() {
    let config = config();
    let s = scenes(&config, [AGENTS; SCENES], [POLYLINES; SCENES]);
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);
    let gamma = vec![0.5f32; sigma_cur.len()];
    let (mut per_setting, mut multistep) = (Vec::new(), Vec::new());
    for chains in [true, false] {
        let ctx = context_with_chains(chains);
        let gpu = denoiser(&ctx, &config);
        let mut engine = engine_on(&ctx, &gpu, &s);
        engine.step(&sigma_cur, &sigma_next, true).unwrap();
        per_setting.push(engine.take_work());
        // The multistep sampler's step (the server's default): one evaluation, the Euler step
        // and its correction, all in the last chain.
        engine
            .step_multistep(&sigma_cur, &sigma_next, &gamma)
            .unwrap();
        multistep.push(engine.take_work());
    }
    let (chains, layers) = (per_setting[0], per_setting[1]);
    let blocks = config.blocks as f64;
    assert_eq!(chains.dispatches_per_evaluation(), 4.0 + 3.0 * blocks + 0.5);
    assert_eq!(
        layers.dispatches_per_evaluation(),
        4.0 + 11.0 * blocks + 3.0
    );
    assert_eq!(multistep[0].dispatches_per_evaluation(), 4.0 + 3.0 * blocks);
    assert_eq!(
        multistep[1].dispatches_per_evaluation(),
        4.0 + 11.0 * blocks + 4.0
    );
    assert!(
        chains.bytes_per_evaluation() < layers.bytes_per_evaluation(),
        "chains {} B, layers {} B",
        chains.bytes_per_evaluation(),
        layers.bytes_per_evaluation()
    );
    assert_eq!(chains.computed_flops, layers.computed_flops);

    let ctx = context();
    let gpu = denoiser(&ctx, &config);
    let inputs = DenoiseInputs {
        scenes: SCENES,
        agents: AGENTS,
        x: &s.x,
        sigma: &sigma_cur,
        valid: &s.valid,
        agent_features: &s.features,
    };
    let batch = gpu.upload_batch(&ctx, &inputs).unwrap();
    let map = gpu
        .encode_map(&ctx, SCENES, POLYLINES, &s.map, &s.map_valid)
        .unwrap();
    let plan = gpu.heun_plan(&ctx, &batch, &map).unwrap();
    let euler = plan.euler_dispatches();
    let head = euler.last().unwrap();
    assert_eq!(head.label(), "residual_chain");
    let tokens = (SCENES * AGENTS * config.window_slots) as u64;
    assert_eq!(
        head.bytes_written(),
        4 * (tokens * config.hidden as u64 + 2 * tokens * 3)
    );
}

/// A server's pool holds hundreds of padded scenes and steps a few at a time: the whole batch's
/// activations are made only for a step that runs it in place, so a pool larger than the
/// adapter binds still steps its few moving scenes (a software adapter binds 128 MiB: a
/// `road serve --engine gpu` pool of 256 scenes × 32 agents failed at load before). A step of
/// the whole pool then says why it cannot run, where it cannot.
#[test]
fn a_pool_larger_than_the_adapter_binds_steps_its_few_moving_scenes() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let (w, q, d) = (config.window_slots, config.polyline_points, config.hidden);
    // q, k, v of the whole pool: past the adapter's largest binding.
    let max_binding = ctx.device.limits().max_storage_buffer_binding_size as usize;
    let (agents, polylines) = (32, 2);
    let scenes = (max_binding / (3 * agents * w * d * 4) + 1).min(4096);
    let tokens = scenes * agents * w;
    let mut engine = GpuStepEngine::new(&ctx, &gpu);
    let features = vec![0.1f32; scenes * agents * 6];
    let map: Vec<f32> = (0..scenes * polylines * q * 2)
        .map(|i| (i % 17) as f32 * 0.1)
        .collect();
    let map_valid = vec![1.0f32; scenes * polylines];
    engine
        .prepare(scenes, agents, &features, polylines, &map, &map_valid)
        .unwrap();
    let x: Vec<f32> = (0..tokens * 3).map(|i| ((i % 23) as f32) * 0.05).collect();
    // Full scenes: a step of them all runs the pool in place.
    let valid = vec![1.0f32; tokens];
    engine.load(&x, &valid).unwrap();
    let sigma_cur = vec![2.0f32; scenes * w];
    let mut sigma_next = sigma_cur.clone();
    sigma_next[..w].fill(1.5);
    engine.step(&sigma_cur, &sigma_next, true).unwrap();
    assert_eq!(engine.take_work().evaluations, 2);
    if 3 * tokens * d * 4 > max_binding {
        let every = vec![1.5f32; scenes * w];
        let err = engine
            .step(&sigma_cur, &every, true)
            .unwrap_err()
            .to_string();
        assert!(err.contains("use smaller batches"), "{err}");
    }
}

/// The profile of a batch whose steps all ran in compact sub-batches (the whole batch's plan
/// not made by a step): made for the profile.
#[test]
fn a_batch_stepped_only_in_compact_sub_batches_is_profiled() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let s = scenes(&config, [AGENTS; SCENES], [POLYLINES; SCENES]);
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[1, 2]);
    let mut engine = engine_on(&ctx, &gpu, &s);
    engine.step(&sigma_cur, &sigma_next, false).unwrap();
    let profile = engine.profile_step(1).unwrap();
    assert!(
        profile.kernels.iter().any(|k| k.kernel == "residual_chain"),
        "{:?}",
        profile.kernels.iter().map(|k| k.kernel).collect::<Vec<_>>()
    );
}

/// What a packed step skips it does not need: after a scene's new map and agents
/// (`prepare_scene`), the packed sub-batch that gathered the old ones steps exactly as an
/// engine prepared with the new ones from the start.
#[test]
fn a_packed_step_after_a_scenes_new_map_uses_the_new_map() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let agents = [4, 2, 1];
    let old = scenes(&config, agents, [POLYLINES; SCENES]);
    // Scene 1's map and agents' features replaced.
    let mut new = scenes(&config, agents, [POLYLINES; SCENES]);
    let (a, q) = (AGENTS, config.polyline_points);
    let map_rows = POLYLINES * q * 2;
    for (i, v) in new.map[map_rows..2 * map_rows].iter_mut().enumerate() {
        *v = ((i as f32) * 0.11).cos() * 3.0;
    }
    for (i, v) in new.features[a * 6..2 * a * 6].iter_mut().enumerate() {
        *v = ((i as f32) * 0.23).cos();
    }
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);
    let denoised = |engine: &mut GpuStepEngine<'_>| {
        engine.step(&sigma_cur, &sigma_next, true).unwrap();
        let mut out = vec![0.0f32; SCENES * AGENTS * config.window_slots * 3];
        engine.read_denoised(&[0, 1, 2], &mut out).unwrap();
        out
    };
    let mut kept = engine_on(&ctx, &gpu, &old);
    denoised(&mut kept);
    kept.prepare_scene(
        1,
        &new.features[a * 6..2 * a * 6],
        &new.map[map_rows..2 * map_rows],
        &new.map_valid[POLYLINES..2 * POLYLINES],
    )
    .unwrap();
    kept.load(&new.x, &new.valid).unwrap();
    let after = denoised(&mut kept);
    let mut fresh = engine_on(&ctx, &gpu, &new);
    let want = denoised(&mut fresh);
    assert_eq!(after, want);
    let mut stale = engine_on(&ctx, &gpu, &old);
    assert_ne!(denoised(&mut stale), want, "scene 1's new map matters");
}

/// The fused Euler step corrects by γ (the multistep sampler's): a Heun step after a multistep
/// one must not (its γ is 0), so it moves the windows exactly as on a fresh engine.
#[test]
fn a_heun_step_after_a_multistep_one_has_no_multistep_correction() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let s = scenes(&config, [AGENTS; SCENES], [POLYLINES; SCENES]);
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);
    let w = config.window_slots;
    let slots: Vec<Option<usize>> = (0..SCENES).map(|b| Some(w - 1 - b)).collect();
    let heun = |engine: &mut GpuStepEngine<'_>| {
        engine.step(&sigma_cur, &sigma_next, false).unwrap();
        let mut out = vec![0.0f32; SCENES * AGENTS * 3];
        engine.read_emitted(&slots, &mut out).unwrap();
        out
    };
    let mut after_multistep = engine_on(&ctx, &gpu, &s);
    let gamma = vec![0.5f32; sigma_cur.len()];
    after_multistep
        .step_multistep(&sigma_cur, &sigma_next, &gamma)
        .unwrap();
    after_multistep.load(&s.x, &s.valid).unwrap();
    let got = heun(&mut after_multistep);
    let want = heun(&mut engine_on(&ctx, &gpu, &s));
    assert_eq!(got, want);
}

/// A round's readback in one submission and wait (`read_emitted_and_denoised`) reads what
/// `read_emitted` and `read_denoised` read apart, and refuses a scene past the batch by name.
#[test]
fn emitted_states_and_plans_read_together_match_their_reads_apart() {
    let ctx = context();
    let config = config();
    let gpu = denoiser(&ctx, &config);
    let s = scenes(&config, [AGENTS; SCENES], [POLYLINES; SCENES]);
    let (sigma_cur, sigma_next) = sigma_rows(&config, &[]);
    let mut engine = engine_on(&ctx, &gpu, &s);
    engine.step(&sigma_cur, &sigma_next, true).unwrap();
    let w = config.window_slots;
    let slots = [Some(w - 1), None, Some(3)];
    let plans = [2, 0];
    let per_scene = AGENTS * w * 3;
    let (mut emitted, mut denoised) = (
        vec![0.0f32; SCENES * AGENTS * 3],
        vec![0.0f32; 2 * per_scene],
    );
    engine
        .read_emitted_and_denoised(&slots, &mut emitted, &plans, &mut denoised)
        .unwrap();
    let (mut emitted_apart, mut denoised_apart) = (emitted.clone(), denoised.clone());
    engine.read_emitted(&slots, &mut emitted_apart).unwrap();
    engine.read_denoised(&plans, &mut denoised_apart).unwrap();
    assert_eq!(emitted, emitted_apart);
    assert_eq!(denoised, denoised_apart);
    assert!(
        denoised.iter().any(|&v| v != 0.0),
        "a step's plans are read"
    );
    let err = engine
        .read_emitted_and_denoised(&slots, &mut emitted, &[SCENES], &mut denoised[..per_scene])
        .unwrap_err();
    assert!(
        err.to_string().contains(&format!("scene {SCENES}")),
        "{err}"
    );
}
