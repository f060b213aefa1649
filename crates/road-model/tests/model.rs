//! The denoiser and its training on small in-memory scenes.

mod common;

use candle_core::{Device, Tensor};
use rand::{SeedableRng, rngs::StdRng};
use road_data::Split;
use road_model::batch::{SceneInput, collate, normal_vec};
use road_model::checkpoint;
use road_model::model::{self, Mode, edm_loss};
use road_model::train::{Trainer, sample_batch, sample_scenes};
use road_model::{RunConfig, TrainConfig};
use road_sched::EdmSchedule;

use common::{dataset, identity, run_config, temp_dir};

#[test]
fn preconditioning_tensors_match_the_scheduler() {
    let run = run_config();
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 1).unwrap();
    let edm = EdmSchedule::default();
    let sigmas = [0.002f32, 0.1, 0.5, 3.0, 80.0];
    let sigma = Tensor::from_vec(sigmas.to_vec(), (1, 5), &Device::Cpu).unwrap();
    let (skip, out, inp, noise) = model.preconditioning(&sigma).unwrap();
    let flat = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let (skip, out, inp, noise) = (flat(skip), flat(out), flat(inp), flat(noise));
    for (i, &s) in sigmas.iter().enumerate() {
        let p = edm.preconditioning(f64::from(s));
        for (got, want) in [
            (skip[i], p.c_skip),
            (out[i], p.c_out),
            (inp[i], p.c_in),
            (noise[i], p.c_noise),
        ] {
            assert!(
                (f64::from(got) - want).abs() <= 1e-6 + 1e-5 * want.abs(),
                "σ = {s}: {got} vs {want}"
            );
        }
    }
}

/// Perturbing everything of an invalid agent (its states, size, type, noise) leaves every
/// valid agent's output bit-identical.
#[test]
fn an_invalid_agent_never_influences_a_valid_one() {
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 2).unwrap();
    let window = ds.window(2).unwrap();
    let mut scene = SceneInput::from_window(&window, 10, run.model.window_slots, &run.model);
    // Add an agent that is invalid everywhere, then vary its inputs.
    let w = scene.slots;
    scene.agents += 1;
    scene.states.extend(vec![0.3f32; w * 3]);
    scene.valid.extend(vec![false; w]);
    scene.agent_features.extend([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
    let sigma = vec![vec![0.7f32; w]];
    let mut rng = StdRng::seed_from_u64(3);
    let noise = vec![normal_vec(&mut rng, scene.agents * w * 3)];
    let run_once = |scene: &SceneInput, noise: &[Vec<f32>]| -> Vec<f32> {
        let batch = collate(
            std::slice::from_ref(scene),
            &sigma,
            Some(noise),
            &Device::Cpu,
        )
        .unwrap();
        let map = model.encode_map(&batch.map, Mode::Infer).unwrap();
        let out = model
            .denoise(
                &batch.x_noisy,
                &batch.sigma,
                &batch.valid,
                &batch.agent_features,
                &map,
                &batch.map_valid,
                Mode::Infer,
            )
            .unwrap();
        let valid_agents = scene.agents - 1;
        out.narrow(1, 0, valid_agents)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    let before = run_once(&scene, &noise);
    let last = scene.agents - 1;
    let mut perturbed = scene.clone();
    for v in &mut perturbed.states[last * w * 3..] {
        *v = 1e3;
    }
    perturbed.agent_features[last * 6..].copy_from_slice(&[9.0, -9.0, 0.0, 0.0, 1.0, 0.0]);
    let mut noise2 = noise.clone();
    for v in &mut noise2[0][last * w * 3..] {
        *v = -5.0;
    }
    let after = run_once(&perturbed, &noise2);
    assert_eq!(before, after);
    // And the valid agents themselves do interact (the test would be vacuous otherwise).
    let mut moved = scene.clone();
    moved.states[0] += 0.5;
    assert_ne!(run_once(&moved, &noise)[3 * w..], before[3 * w..]);
}

/// The loss written on `F` is EDM's `λ(σ)·|D − x0|²` of the denoiser itself, for the scene
/// frame, the agent frame and the constant-velocity residual: training optimises what
/// sampling uses.
#[test]
fn the_loss_is_the_weighted_error_of_the_denoiser_for_every_parameterisation() {
    let frames = [
        None,
        Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 2.0,
            residual_scale: None,
            max_anchor_sigma: None,
        }),
        Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: Some(40.0),
            max_anchor_sigma: None,
        }),
    ];
    let ds = dataset(Split::Train);
    for frame in frames {
        let mut run = run_config();
        run.model.agent_frame = frame.clone();
        let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 4).unwrap();
        let mut rng = StdRng::seed_from_u64(5);
        let batch = sample_batch(&run, &ds, 4, None, &mut rng, &Device::Cpu).unwrap();
        let map = model.encode_map(&batch.map, Mode::Infer).unwrap();
        let loss = edm_loss(&model, &batch, &map, Mode::Infer)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        let d = model
            .denoise(
                &batch.x_noisy,
                &batch.sigma,
                &batch.valid,
                &batch.agent_features,
                &map,
                &batch.map_valid,
                Mode::Infer,
            )
            .unwrap();
        let (b, a, w, _) = d.dims4().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let (d, x0, sigma, valid) = (
            flat(&d),
            flat(&batch.x0),
            flat(&batch.sigma),
            flat(&batch.valid),
        );
        let sd = 0.5f64;
        let (mut sum, mut count) = (0f64, 0f64);
        for token in 0..b * a * w {
            if valid[token] == 0.0 {
                continue;
            }
            let s = f64::from(sigma[(token / (a * w)) * w + token % w]);
            let lambda = (s * s + sd * sd) / (s * sd).powi(2);
            for c in 0..3 {
                let e = f64::from(d[3 * token + c]) - f64::from(x0[3 * token + c]);
                sum += lambda * e * e;
                count += 1.0;
            }
        }
        let want = sum / count;
        assert!(
            (f64::from(loss) - want).abs() < 2e-3 * want,
            "{frame:?}: loss {loss} against λ·|D − x0|² {want}"
        );
    }
}

#[test]
fn one_training_step_lowers_the_loss_on_a_fixed_batch() {
    one_training_step_lowers_the_loss(run_config());
}

/// The agent maps' path (pick, frame, encoder, per-agent attention) is differentiable too.
#[test]
fn one_training_step_with_agent_maps_lowers_the_loss() {
    one_training_step_lowers_the_loss(agent_map_run_config());
}

/// [`run_config`] with an agent frame (constant-velocity reference) and agent maps.
fn agent_map_run_config() -> RunConfig {
    let mut run = run_config();
    run.model.agent_frame = Some(road_model::AgentFrame {
        anchor_slot: 9,
        relative_scale: 1.0,
        residual_scale: Some(40.0),
        max_anchor_sigma: None,
    });
    run.model.agent_map = Some(road_model::AgentMap { polylines: 1 });
    run
}

/// The agent pairs' path is differentiable, down to their (zero-initialised) weights.
#[test]
fn one_training_step_with_agent_pairs_lowers_the_loss() {
    let mut run = agent_map_run_config();
    run.model.agent_pairs = Some(road_model::AgentPairs {
        direction_scale_m: 10.0,
        near_scale_m: 5.0,
        far_scale_m: 20.0,
    });
    let ds = dataset(Split::Train);
    let (varmap, model) = model::init_seeded(&run.model, &Device::Cpu, 4).unwrap();
    let mut rng = StdRng::seed_from_u64(5);
    let batch = sample_batch(&run, &ds, 4, None, &mut rng, &Device::Cpu).unwrap();
    let map = model.encode_map(&batch.map, Mode::Train).unwrap();
    let loss = edm_loss(&model, &batch, &map, Mode::Train).unwrap();
    let grads = loss.backward().unwrap();
    let vars = varmap.data().lock().unwrap();
    for name in ["blocks.0.agents.pair_k", "blocks.0.agents.pair_v"] {
        let g = grads
            .get(vars[name].as_tensor())
            .unwrap_or_else(|| panic!("no gradient for {name}"));
        let norm = g
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(norm > 0.0, "{name}: zero gradient");
    }
    drop(vars);
    one_training_step_lowers_the_loss(run);
}

fn one_training_step_lowers_the_loss(run: RunConfig) {
    let ds = dataset(Split::Train);
    let (varmap, model) = model::init_seeded(&run.model, &Device::Cpu, 4).unwrap();
    let mut rng = StdRng::seed_from_u64(5);
    let batch = sample_batch(&run, &ds, 4, None, &mut rng, &Device::Cpu).unwrap();
    let loss_of = || {
        let map = model.encode_map(&batch.map, Mode::Train).unwrap();
        edm_loss(&model, &batch, &map, Mode::Train).unwrap()
    };
    let loss = loss_of();
    let before = loss.to_scalar::<f32>().unwrap();
    let grads = loss.backward().unwrap();
    for var in varmap.all_vars() {
        if let Some(g) = grads.get(var.as_tensor()) {
            var.set(&(var.as_tensor() - (g * 1e-2).unwrap()).unwrap())
                .unwrap();
        }
    }
    let after = loss_of().to_scalar::<f32>().unwrap();
    assert!(after < before, "loss {before} → {after}");
}

/// Training overfits a tiny dataset: the validation loss (same scenes) falls well below the
/// untrained model's.
#[test]
fn the_model_overfits_a_tiny_dataset() {
    // A short EMA, so that the evaluated weights follow 300 steps.
    let run = RunConfig {
        train: TrainConfig {
            steps: 300,
            ema_decay: 0.9,
            ..run_config().train
        },
        ..run_config()
    };
    let ds = dataset(Split::Train);
    let mut trainer = Trainer::new(run, &ds, identity(), None).unwrap();
    let untrained = trainer.untrained_validation_loss().unwrap();
    let dir = temp_dir("overfit");
    trainer.run_until(&ds, &dir, 300, "test", |_| {}).unwrap();
    let trained = trainer.validate().unwrap();
    assert!(
        trained < 0.5 * untrained,
        "validation loss {untrained} → {trained}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `D(x; σ)` of a batch's noisy states, flattened.
fn denoise_flat(m: &road_model::Denoiser, batch: &road_model::batch::Batch) -> Vec<f32> {
    let map = m.encode_map(&batch.map, Mode::Infer).unwrap();
    m.denoise(
        &batch.x_noisy,
        &batch.sigma,
        &batch.valid,
        &batch.agent_features,
        &map,
        &batch.map_valid,
        Mode::Infer,
    )
    .unwrap()
    .flatten_all()
    .unwrap()
    .to_vec1::<f32>()
    .unwrap()
}

/// Save → load gives the same weights bit for bit, and a checkpoint whose tensors do not
/// match its config is refused with a clear error.
#[test]
fn checkpoints_round_trip_exactly_and_refuse_mismatches() {
    let run = run_config();
    let ds = dataset(Split::Train);
    let mut trainer = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    let dir = temp_dir("ckpt");
    trainer.run_until(&ds, &dir, 3, "test", |_| {}).unwrap();
    let saved =
        checkpoint::load_tensors(&dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu).unwrap();
    let loaded = checkpoint::load(&dir, &Device::Cpu).unwrap();
    assert_eq!(loaded.meta.step, 3);
    let ema = trainer.ema_model().unwrap();
    let mut rng = StdRng::seed_from_u64(9);
    let batch = sample_batch(&run, &ds, 2, None, &mut rng, &Device::Cpu).unwrap();
    let eval = |m: &road_model::Denoiser| denoise_flat(m, &batch);
    assert_eq!(eval(&loaded.model), eval(&ema));
    assert!(!saved.is_empty());

    // A config with another width no longer matches the tensors.
    let mut meta = loaded.meta.clone();
    meta.run.model.hidden = 32;
    meta.save(&dir).unwrap();
    let err = checkpoint::load(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("weights do not match the config") && err.contains("weights.safetensors"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A run that adds agent pairs to a checkpoint's config starts from its weights, the new pair
/// weights at zero: the same denoiser as the checkpoint's until it trains.
#[test]
fn a_run_that_gains_agent_pairs_starts_as_the_checkpoint_it_comes_from() {
    let mut run = run_config();
    run.model.agent_frame = Some(road_model::AgentFrame {
        anchor_slot: 9,
        relative_scale: 1.0,
        residual_scale: Some(40.0),
        max_anchor_sigma: None,
    });
    let ds = dataset(Split::Train);
    let dir = temp_dir("init-from-pairs");
    let mut first = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    first.run_until(&ds, &dir, 3, "test", |_| {}).unwrap();

    let mut next = run.clone();
    next.model.agent_pairs = Some(road_model::AgentPairs {
        direction_scale_m: 10.0,
        near_scale_m: 5.0,
        far_scale_m: 20.0,
    });
    next.train.init_from = Some(dir.clone());
    let second = Trainer::new(next.clone(), &ds, identity(), None).unwrap();
    let loaded = checkpoint::load(&dir, &Device::Cpu).unwrap().model;
    let started = second.ema_model().unwrap();
    assert!(started.blocks_have_agent_pairs());
    let mut rng = StdRng::seed_from_u64(9);
    let batch = sample_batch(&next, &ds, 2, None, &mut rng, &Device::Cpu).unwrap();
    let (a, b) = (
        denoise_flat(&started, &batch),
        denoise_flat(&loaded, &batch),
    );
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-5, "outputs differ by {worst}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A run that adds blocks to a checkpoint's config (more depth) starts from its weights, the
/// new blocks' residual branches at zero: the same denoiser as the checkpoint's until it
/// trains, and a first step that moves the new blocks.
#[test]
fn a_run_that_gains_blocks_starts_as_the_checkpoint_it_comes_from() {
    let run = run_config();
    let ds = dataset(Split::Train);
    let dir = temp_dir("init-from-blocks");
    let mut first = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    first.run_until(&ds, &dir, 3, "test", |_| {}).unwrap();

    let mut next = run.clone();
    next.model.blocks = run.model.blocks + 2;
    next.train.init_from = Some(dir.clone());
    let mut second = Trainer::new(next.clone(), &ds, identity(), None).unwrap();
    let loaded = checkpoint::load(&dir, &Device::Cpu).unwrap().model;
    let started = second.ema_model().unwrap();
    let mut rng = StdRng::seed_from_u64(9);
    let batch = sample_batch(&next, &ds, 2, None, &mut rng, &Device::Cpu).unwrap();
    let worst_difference = |a: &road_model::Denoiser, b: &road_model::Denoiser| {
        denoise_flat(a, &batch)
            .iter()
            .zip(&denoise_flat(b, &batch))
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    let worst = worst_difference(&started, &loaded);
    assert!(worst < 1e-5, "outputs differ by {worst}");

    // Zero output projections still receive gradients: one step moves the new blocks' own.
    let trained_dir = temp_dir("init-from-blocks-trained");
    second
        .run_until(&ds, &trained_dir, 1, "test", |_| {})
        .unwrap();
    let tensors =
        checkpoint::load_tensors(&trained_dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu)
            .unwrap();
    let newest = format!("blocks.{}.mlp_out.weight", next.model.blocks - 1);
    let moved: f32 = tensors[&newest]
        .abs()
        .unwrap()
        .sum_all()
        .unwrap()
        .to_scalar()
        .unwrap();
    assert!(moved > 0.0, "{newest} stayed at zero");
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&trained_dir).ok();
}

/// `train.init_from` starts a run from another checkpoint's EMA weights, and refuses one
/// whose tensors do not fit, naming the file.
#[test]
fn a_run_can_start_from_another_checkpoint_s_weights() {
    let run = run_config();
    let ds = dataset(Split::Train);
    let dir = temp_dir("init-from");
    let mut first = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    first.run_until(&ds, &dir, 3, "test", |_| {}).unwrap();
    let saved =
        checkpoint::load_tensors(&dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu).unwrap();

    let mut next = run.clone();
    next.train.init_from = Some(dir.clone());
    let second = Trainer::new(next.clone(), &ds, identity(), None).unwrap();
    assert_eq!(second.step, 0);
    let started = second.ema_model().unwrap();
    let fresh = Trainer::new(run, &ds, identity(), None).unwrap();
    assert!(
        second.untrained_validation_loss().unwrap() < fresh.untrained_validation_loss().unwrap(),
        "the starting loss is the trained weights'"
    );
    let loaded = checkpoint::load(&dir, &Device::Cpu).unwrap().model;
    let mut rng = StdRng::seed_from_u64(9);
    let batch = sample_batch(&next, &ds, 2, None, &mut rng, &Device::Cpu).unwrap();
    let eval = |m: &road_model::Denoiser| denoise_flat(m, &batch);
    assert_eq!(eval(&started), eval(&loaded));
    assert!(!saved.is_empty());

    next.model.hidden = 32;
    let err = Trainer::new(next, &ds, identity(), None)
        .unwrap_err()
        .to_string();
    assert!(err.contains("weights.safetensors"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `train.init_from` across planners whose windows differ: a RoAD-20 checkpoint (W = 20)
/// starts an AR run (W = 11) and a one-shot run (W = 40); the slot embedding keeps the rows
/// the windows share and repeats the last one past the checkpoint's window, and every other
/// tensor is the checkpoint's.
#[test]
fn a_run_can_start_from_a_checkpoint_with_another_window() {
    use road_sched::{PlannerKind, PlannerSpec};
    let run = run_config();
    let ds = dataset(Split::Train);
    let dir = temp_dir("init-from-window");
    let mut first = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    first.run_until(&ds, &dir, 2, "test", |_| {}).unwrap();
    let saved =
        checkpoint::load_tensors(&dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu).unwrap();
    let rows = |t: &Tensor| t.to_vec2::<f32>().unwrap();
    let from = rows(&saved["slot_embedding"]);
    assert_eq!(from.len(), 20);

    for (kind, future_slots) in [(PlannerKind::Autoregressive, 1), (PlannerKind::OneShot, 30)] {
        let mut next = run.clone();
        next.planner = PlannerSpec {
            kind,
            future_slots,
            ..run.planner.clone()
        };
        next.model.window_slots = next.planner.obs_slots + future_slots;
        next.train.init_from = Some(dir.clone());
        let trainer = Trainer::new(next.clone(), &ds, identity(), None).unwrap();
        let out = temp_dir(&format!("init-from-window-{future_slots}"));
        trainer.save(&out, 0.0, "test").unwrap();
        let started =
            checkpoint::load_tensors(&out.join(checkpoint::WEIGHTS_FILE), &Device::Cpu).unwrap();
        let slots = rows(&started["slot_embedding"]);
        assert_eq!(slots.len(), next.model.window_slots);
        for (slot, row) in slots.iter().enumerate() {
            assert_eq!(
                row,
                &from[slot.min(from.len() - 1)],
                "{kind:?}: slot {slot}"
            );
        }
        for (name, tensor) in &saved {
            if name != "slot_embedding" {
                let diff = (tensor - &started[name])
                    .unwrap()
                    .abs()
                    .unwrap()
                    .max_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap();
                assert_eq!(diff, 0.0, "{kind:?}: {name} is the checkpoint's");
            }
        }
        std::fs::remove_dir_all(&out).ok();
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Stopping and resuming gives exactly the weights of an uninterrupted run.
#[test]
fn resume_continues_exactly() {
    let run = run_config();
    let ds = dataset(Split::Train);
    let straight_dir = temp_dir("straight");
    let mut straight = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    straight
        .run_until(&ds, &straight_dir, 6, "test", |_| {})
        .unwrap();

    let split_dir = temp_dir("split");
    let mut first = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    first.run_until(&ds, &split_dir, 3, "test", |_| {}).unwrap();
    let mut second = Trainer::new(run, &ds, identity(), Some(&split_dir)).unwrap();
    assert_eq!(second.step, 3);
    second
        .run_until(&ds, &split_dir, 6, "test", |_| {})
        .unwrap();

    let a = checkpoint::load_tensors(&straight_dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu)
        .unwrap();
    let b =
        checkpoint::load_tensors(&split_dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu).unwrap();
    for (name, t) in &a {
        let x = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let y = b[name].flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(x, y, "{name} differs after resume");
    }
    std::fs::remove_dir_all(&straight_dir).ok();
    std::fs::remove_dir_all(&split_dir).ok();
}

/// Data-parallel shards (uneven ones included) give the whole batch's loss and gradients.
#[test]
fn sharded_gradients_equal_the_whole_batch_gradients() {
    let ds = dataset(Split::Train);
    let gradients = |workers: usize| {
        let mut run = run_config();
        run.train.workers = workers;
        let draw = sample_scenes(&run, &ds, 5, None, &mut StdRng::seed_from_u64(3)).unwrap();
        let mut trainer = Trainer::new(run, &ds, identity(), None).unwrap();
        let (loss, grads) = trainer.loss_and_gradients(&draw).unwrap();
        (loss, grads, trainer.variable_names().to_vec())
    };
    let (whole_loss, whole, names) = gradients(1);
    for workers in [2, 3, 8] {
        let (loss, sharded, _) = gradients(workers);
        assert!(
            (loss - whole_loss).abs() <= 1e-6 * whole_loss.abs().max(1.0),
            "{workers} workers: loss {loss} against {whole_loss}"
        );
        for ((name, a), b) in names.iter().zip(&whole).zip(&sharded) {
            let (a, b) = (
                a.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                b.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            );
            let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-3);
            for (x, y) in a.iter().zip(&b) {
                assert!(
                    (x - y).abs() <= 1e-4 * scale,
                    "{workers} workers: gradient of {name} {y} against {x}"
                );
            }
        }
    }
}

/// [`agent_map_run_config`] with agent pairs and the initialisation task on every draw.
fn initialisation_run_config() -> RunConfig {
    let mut run = agent_map_run_config();
    run.model.agent_pairs = Some(road_model::AgentPairs {
        direction_scale_m: 10.0,
        near_scale_m: 5.0,
        far_scale_m: 20.0,
    });
    if let Some(frame) = run.model.agent_frame.as_mut() {
        frame.max_anchor_sigma = Some(0.1);
    }
    run.train.initialisation_task_prob = 1.0;
    run.validate().unwrap();
    run
}

/// σ per agent whose rows are all alike is σ per slot, to the bit, in the denoiser and the loss.
#[test]
fn sigma_per_agent_with_equal_rows_is_sigma_per_slot() {
    let run = initialisation_run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 6).unwrap();
    let w = run.model.window_slots;
    let window = ds.window(2).unwrap();
    let scene = SceneInput::from_window(&window, 10, w, &run.model);
    let per_slot: Vec<f32> = (0..w).map(|slot| 0.01 + 0.3 * slot as f32).collect();
    let per_agent: Vec<f32> = per_slot.repeat(scene.agents);
    let mut rng = StdRng::seed_from_u64(7);
    let noise = vec![normal_vec(&mut rng, scene.agents * w * 3)];
    let scenes = [scene];
    let a = collate(&scenes, &[per_slot], Some(&noise), &Device::Cpu).unwrap();
    let b = collate(&scenes, &[per_agent], Some(&noise), &Device::Cpu).unwrap();
    assert_eq!(a.sigma.dims(), &[1, w]);
    assert_eq!(b.sigma.dims(), &[1, scenes[0].agents, w]);
    assert_eq!(denoise_flat(&model, &a), denoise_flat(&model, &b));
    let loss = |batch| {
        let map = model.encode_map(&a.map, Mode::Infer).unwrap();
        edm_loss(&model, batch, &map, Mode::Infer)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    assert_eq!(loss(&a), loss(&b));
}

/// `max_anchor_sigma` changes nothing while every anchor is observed below it, and drops the
/// frame of an agent whose anchor slot is noisier (its output then differs from the same
/// weights' without the bound).
#[test]
fn an_anchor_noisier_than_the_bound_is_no_frame() {
    let run = initialisation_run_config();
    let mut unbounded = run.model.clone();
    if let Some(frame) = unbounded.agent_frame.as_mut() {
        frame.max_anchor_sigma = None;
    }
    let ds = dataset(Split::Train);
    let (_, bounded_model) = model::init_seeded(&run.model, &Device::Cpu, 8).unwrap();
    let (_, unbounded_model) = model::init_seeded(&unbounded, &Device::Cpu, 8).unwrap();
    let w = run.model.window_slots;
    let window = ds.window(2).unwrap();
    let scene = SceneInput::from_window(&window, 10, w, &run.model);
    let agents = scene.agents;
    let mut rng = StdRng::seed_from_u64(9);
    let noise = vec![normal_vec(&mut rng, agents * w * 3)];
    // Agent 0 drawn at σ (its anchor too), the others observed.
    let rows = |drawn: f32| -> Vec<f32> {
        (0..agents * w)
            .map(|k| if k < w || k % w >= 10 { drawn } else { 0.002 })
            .collect()
    };
    let batch = |drawn| {
        collate(
            std::slice::from_ref(&scene),
            &[rows(drawn)],
            Some(&noise),
            &Device::Cpu,
        )
    };
    let below = batch(0.05).unwrap();
    assert_eq!(
        denoise_flat(&bounded_model, &below),
        denoise_flat(&unbounded_model, &below)
    );
    let above = batch(0.5).unwrap();
    let (with_bound, without) = (
        denoise_flat(&bounded_model, &above),
        denoise_flat(&unbounded_model, &above),
    );
    let agent0_moved = with_bound[..w * 3]
        .iter()
        .zip(&without[..w * 3])
        .any(|(a, b)| a != b);
    assert!(agent0_moved, "agent 0's frame was kept above the bound");
}

/// The initialisation task keeps some agents' observations and draws every other slot at one σ.
#[test]
fn the_initialisation_task_draws_whole_agents_around_kept_ones() {
    let run = initialisation_run_config();
    let ds = dataset(Split::Train);
    let w = run.model.window_slots;
    let mut rng = StdRng::seed_from_u64(10);
    let mut kept_any = false;
    for _ in 0..40 {
        let draw = sample_scenes(&run, &ds, 2, None, &mut rng).unwrap();
        for (input, sigma) in draw.inputs.iter().zip(&draw.sigma) {
            assert_eq!(sigma.len(), input.agents * w);
            let drawn = sigma[input.agents * w - 1];
            let mut drawn_agents = 0;
            for agent in 0..input.agents {
                let row = &sigma[agent * w..(agent + 1) * w];
                assert!(row[10..].iter().all(|&s| s == drawn), "{row:?}");
                if row[..10].iter().all(|&s| s == drawn) {
                    drawn_agents += 1;
                } else {
                    kept_any = true;
                    let most = run.model.edm.sigma(run.train.augmentation_ratio) as f32;
                    assert!(
                        row[..10].iter().all(|&s| s == row[0] && s <= most),
                        "{row:?}"
                    );
                }
            }
            assert!(drawn_agents >= 1);
        }
        let batch = draw.collate(0..draw.len(), &Device::Cpu).unwrap();
        assert_eq!(batch.sigma.dims().len(), 3);
    }
    assert!(kept_any, "no agent kept in 80 scenes");
    one_training_step_lowers_the_loss(run);
}
