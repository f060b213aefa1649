//! The denoiser and its training on small in-memory scenes.

use std::path::Path;

use candle_core::{Device, Tensor};
use rand::{SeedableRng, rngs::StdRng};
use road_data::{AgentType, Dataset, LaneletMap, Recording, Split, Track, WindowConfig};
use road_model::batch::{SceneInput, collate, normal_vec};
use road_model::checkpoint::{self, DataIdentity};
use road_model::model::{self, Mode, edm_loss};
use road_model::train::{Trainer, sample_batch, sample_scenes};
use road_model::{ModelConfig, RunConfig, TrainConfig};
use road_sched::EdmSchedule;

/// Two straight lanes along +x, 4 m wide, 200 m long (lat/lon around (0, 0)).
fn map() -> LaneletMap {
    let deg_per_m = 1.0 / 111_320.0;
    let mut s = String::from("<osm>\n");
    for (row, y) in [0.0, 4.0, 8.0].iter().enumerate() {
        for (col, x) in [0.0, 100.0, 200.0].iter().enumerate() {
            s += &format!(
                "<node id=\"{}\" lat=\"{}\" lon=\"{}\"/>\n",
                100 + row * 10 + col,
                y * deg_per_m,
                x * deg_per_m
            );
        }
    }
    for row in 0..3 {
        s += &format!(
            "<way id=\"{}\"><nd ref=\"{}\"/><nd ref=\"{}\"/><nd ref=\"{}\"/></way>\n",
            row + 1,
            100 + row * 10,
            101 + row * 10,
            102 + row * 10
        );
    }
    for lane in 0..2 {
        s += &format!(
            "<relation id=\"{}\"><member type=\"way\" ref=\"{}\" role=\"left\"/><member type=\"way\" ref=\"{}\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/></relation>\n",
            500 + lane,
            lane + 2,
            lane + 1
        );
    }
    s += "</osm>\n";
    LaneletMap::parse(&s, Path::new("lanes.osm"), "LANES").unwrap()
}

/// Cars driving along the two lanes at different speeds, entering at different times.
fn dataset(split: Split) -> Dataset {
    let mut tracks = Vec::new();
    for i in 0..6u32 {
        let lane_y = if i % 2 == 0 { 2.0 } else { 6.0 };
        let speed = 4.0 + i as f32;
        let first = i * 3;
        let states = (0..60)
            .map(|t| [5.0 + 6.0 * i as f32 + speed * 0.1 * t as f32, lane_y, 0.0])
            .collect();
        tracks.push(Track {
            track_id: i + 1,
            agent_type: AgentType::Car,
            length_m: 4.5,
            width_m: 1.8,
            first_frame: first,
            states,
        });
    }
    let last = tracks.iter().map(Track::last_frame).max().unwrap();
    let recording = Recording {
        location: "LANES".into(),
        file: "synthetic.csv".into(),
        tracks,
        first_frame: 0,
        last_frame: last,
    };
    let config = WindowConfig {
        stride_steps: 3,
        ..WindowConfig::default()
    };
    Dataset::from_parts(split, &config, vec![map()], vec![recording], vec![0]).unwrap()
}

fn run_config() -> RunConfig {
    RunConfig {
        name: "tiny".into(),
        model: ModelConfig {
            hidden: 16,
            heads: 2,
            blocks: 1,
            map_polylines: 8,
            ..ModelConfig::default()
        },
        train: TrainConfig {
            batch_scenes: 4,
            steps: 400,
            learning_rate: 3e-3,
            warmup_steps: 5,
            val_batches: 2,
            val_every_steps: 1000,
            checkpoint_every_secs: 3600,
            ..TrainConfig::default()
        },
        ..RunConfig::default()
    }
}

fn identity() -> DataIdentity {
    DataIdentity {
        train_cache: "memory".into(),
        train_windows: 0,
        validation_windows: 0,
        source: "synthetic".into(),
    }
}

fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("road-model-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

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
        }),
        Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: Some(40.0),
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

/// Reference sampling: every planner that fits the window runs through the scheduler with the
/// NFE of the math doc's table, deterministically for a seed; a trained model follows the
/// logged futures far better than an untrained one.
#[test]
fn reference_sampling_runs_every_planner_and_learns_the_lanes() {
    use road_model::sample::{RolloutScene, rollout};
    use road_sched::{PlannerKind, PlannerSpec};
    let run = RunConfig {
        train: TrainConfig {
            steps: 300,
            ema_decay: 0.9,
            ..run_config().train
        },
        ..run_config()
    };
    let ds = dataset(Split::Train);
    let mut trainer = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    let untrained = trainer.ema_model().unwrap();
    let dir = temp_dir("sampling");
    trainer.run_until(&ds, &dir, 300, "test", |_| {}).unwrap();
    let trained = trainer.ema_model().unwrap();
    std::fs::remove_dir_all(&dir).ok();

    let window = ds.window(3).unwrap();
    let n = 10;
    let history = SceneInput::from_window(&window, 0, n, &run.model);
    let scenes = vec![RolloutScene { history }; 3];
    let steps = 10;
    let planner = |kind, x| PlannerSpec {
        kind,
        steps_per_diffusion: 10,
        replan_every: x,
        ..PlannerSpec::default()
    };
    for (spec, nfe) in [
        (planner(PlannerKind::Rolling, None), 20 + 9 * 2),
        (planner(PlannerKind::Mpc, Some(5)), 2 * 19),
        (planner(PlannerKind::OneShot, None), 19),
    ] {
        let a = rollout(
            &trained,
            &spec,
            &scenes,
            steps,
            &mut StdRng::seed_from_u64(1),
        )
        .unwrap();
        let b = rollout(
            &trained,
            &spec,
            &scenes,
            steps,
            &mut StdRng::seed_from_u64(1),
        )
        .unwrap();
        assert_eq!(a, b, "{:?}: same seed, same samples", spec.kind);
        assert_eq!(a.nfe, nfe, "{:?}", spec.kind);
        assert_eq!(a.states.len(), 3);
        assert_eq!(a.states[0].len(), window.agents * steps * 3);
        assert!(a.states.iter().flatten().all(|v| v.is_finite()));
        assert_ne!(a.states[0], a.states[1], "each scene has its own noise");
    }
    // Average displacement from the logged future (normalised units).
    let ade = |m: &road_model::Denoiser| {
        let r = rollout(
            m,
            &planner(PlannerKind::Rolling, None),
            &scenes,
            steps,
            &mut StdRng::seed_from_u64(2),
        )
        .unwrap();
        let (mut sum, mut count) = (0.0f32, 0);
        for sample in &r.states {
            for a in 0..window.agents {
                for t in 0..steps {
                    if let Some(truth) = window.state(a, n + t) {
                        let k = 3 * (a * steps + t);
                        sum += ((sample[k] - truth[0]).powi(2)
                            + (sample[k + 1] - truth[1]).powi(2))
                        .sqrt();
                        count += 1;
                    }
                }
            }
        }
        sum / count as f32
    };
    let (trained_ade, untrained_ade) = (ade(&trained), ade(&untrained));
    assert!(
        trained_ade < 0.5 * untrained_ade,
        "ADE trained {trained_ade} vs untrained {untrained_ade}"
    );
}

/// The scheduler batches scenes at different phases and under different planners: a scene's
/// samples are the same whether it runs alone or shares every batch with a scene that is in its
/// warm-up while it rolls (each scene has its own σ rows and its own noise stream).
#[test]
fn scenes_at_different_phases_share_batches_without_changing_each_other() {
    use road_model::sample::{CpuEngine, RolloutDriver, RolloutScene};
    use road_sched::{PlannerKind, PlannerSpec};
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 11).unwrap();
    let n = 10;
    let scene = |i: usize| RolloutScene {
        history: SceneInput::from_window(&ds.window(i).unwrap(), 0, n, &run.model),
    };
    let rolling = PlannerSpec {
        steps_per_diffusion: 10,
        ..PlannerSpec::default()
    };
    let mpc = PlannerSpec {
        kind: PlannerKind::Mpc,
        replan_every: Some(2),
        ..rolling.clone()
    };
    let emitted = |driver: &mut RolloutDriver, engine: &mut CpuEngine, which: &[usize]| {
        let mut out: Vec<Vec<f32>> = vec![Vec::new(); driver.scenes()];
        driver
            .tick_scenes(engine, which, &mut |i, e, _| {
                out[i] = e.to_vec();
                Ok(())
            })
            .unwrap();
        out
    };
    // Alone: scene 0 rolls for 6 ticks.
    let mut engine = CpuEngine::new(&model);
    let mut alone = RolloutDriver::new(
        &mut engine,
        &rolling,
        &[scene(0)],
        6,
        &mut StdRng::seed_from_u64(3),
    )
    .unwrap();
    let alone_out: Vec<Vec<f32>> = (0..6)
        .map(|_| emitted(&mut alone, &mut engine, &[0]).swap_remove(0))
        .collect();
    // Together with scene 1, which switches to MPC at tick 2 (a full diffusion while scene 0
    // is in its rolling stages) and skips tick 4.
    let mut engine = CpuEngine::new(&model);
    let mut both = RolloutDriver::new(
        &mut engine,
        &rolling,
        &[scene(0), scene(1)],
        6,
        &mut StdRng::seed_from_u64(3),
    )
    .unwrap();
    for (t, alone_tick) in alone_out.iter().enumerate() {
        if t == 2 {
            both.switch_scene_planner(1, &mpc).unwrap();
        }
        let which: &[usize] = if t == 4 { &[0] } else { &[0, 1] };
        let out = emitted(&mut both, &mut engine, which);
        for (x, y) in out[0].iter().zip(alone_tick) {
            assert!(
                (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                "tick {t}: {x} vs {y}"
            );
        }
    }
    assert_eq!(both.scene_ticks(0), 6);
    assert_eq!(both.scene_ticks(1), 5);
    // Scene 1: the rolling warm-up (20) and one rolling stage (2), then MPC-2 replans at its
    // ticks 2 and 4 (19 each; its tick 3 executes the plan).
    assert_eq!(both.scene_nfe(1).unwrap(), 20 + 2 + 19 + 19);
    assert!(
        both.into_rollout().is_err(),
        "unequal ticks have no common rollout"
    );
}

/// Noise streams named by the caller (`RolloutDriver::with_seeds`, `stream_seed`): a scene
/// samples the same futures alone, first in a batch or second, so that an evaluation's figures
/// do not depend on how its scenes are chunked.
#[test]
fn a_seeded_scene_samples_the_same_wherever_it_sits_in_the_batch() {
    use road_model::sample::{CpuEngine, RolloutScene, rollout_seeded, stream_seed};
    use road_sched::PlannerSpec;
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 11).unwrap();
    let scene = |i: usize| RolloutScene {
        history: SceneInput::from_window(&ds.window(i).unwrap(), 0, 10, &run.model),
    };
    let planner = PlannerSpec {
        steps_per_diffusion: 10,
        ..PlannerSpec::default()
    };
    let (seed_a, seed_b) = (stream_seed(5, 0), stream_seed(5, 1));
    assert_ne!(seed_a, seed_b);
    let run_with = |scenes: &[RolloutScene], seeds: &[u64]| {
        rollout_seeded(&mut CpuEngine::new(&model), &planner, scenes, 4, seeds).unwrap()
    };
    let alone = run_with(&[scene(0)], &[seed_a]);
    let first = run_with(&[scene(0), scene(1)], &[seed_a, seed_b]);
    let second = run_with(&[scene(1), scene(0)], &[seed_b, seed_a]);
    for (name, states) in [("first", &first.states[0]), ("second", &second.states[1])] {
        assert_eq!(states.len(), alone.states[0].len());
        for (x, y) in states.iter().zip(&alone.states[0]) {
            assert!(
                (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                "{name}: {x} vs {y}"
            );
        }
    }
    // Another seed samples another future.
    let other = run_with(&[scene(0)], &[seed_b]);
    assert!(
        other.states[0]
            .iter()
            .zip(&alone.states[0])
            .any(|(x, y)| (x - y).abs() > 1e-3),
        "two seeds gave the same samples"
    );
    // One seed per scene.
    assert!(
        rollout_seeded(
            &mut CpuEngine::new(&model),
            &planner,
            &[scene(0)],
            4,
            &[1, 2]
        )
        .is_err()
    );
}

/// A hook that turns an agent's plan at an emission (`plan_turns` of
/// `road_model::driver::Overrides`) turns that agent's future slots n … W − 2 of the window and
/// of the multistep sampler's kept estimate by `turn_plan`, and nothing else: the other agents,
/// the observed slots and the fresh slot are as without the turn.
#[test]
fn a_turned_plan_turns_only_that_agent_s_future_slots() {
    use road_model::sample::{CpuEngine, RolloutDriver, RolloutScene, StepEngine, turn_plan};
    use road_sched::{PlannerSpec, Sampler};
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 11).unwrap();
    let n = 10;
    let history = SceneInput::from_window(&ds.window(0).unwrap(), 0, n, &run.model);
    let agents = history.agents;
    assert!(agents >= 2, "the test needs two agents");
    let scenes = [RolloutScene { history }];
    let planner = PlannerSpec {
        steps_per_diffusion: 10,
        sampler: Sampler::Multistep,
        ..PlannerSpec::default()
    };
    let turn = [0.3f32, -0.2, 0.5, 0.25];
    let turned_agent = 1;
    // Windows [A, W, 3] and estimates after 3 ticks, the last one turning `turned_agent`'s
    // plan when `turned`.
    let windows_after = |turned: bool| {
        let mut engine = CpuEngine::new(&model);
        let mut driver = RolloutDriver::new(
            &mut engine,
            &planner,
            &scenes,
            3,
            &mut StdRng::seed_from_u64(5),
        )
        .unwrap();
        for t in 0..3 {
            driver
                .tick(&mut engine, &mut |_, _, plan_turns| {
                    if turned && t == 2 {
                        plan_turns[4 * turned_agent..][..4].copy_from_slice(&turn);
                    }
                    Ok(())
                })
                .unwrap();
        }
        let w = engine.window_slots();
        let mut window = vec![0.0f32; agents * w * 3];
        let mut slot = vec![0.0f32; agents * 3];
        for k in 0..w {
            engine.read_emitted(&[Some(k)], &mut slot).unwrap();
            for a in 0..agents {
                window[3 * (a * w + k)..][..3].copy_from_slice(&slot[3 * a..][..3]);
            }
        }
        let mut estimate = vec![0.0f32; agents * w * 3];
        engine.read_denoised(&[0], &mut estimate).unwrap();
        (w, window, estimate)
    };
    let (w, plain_window, plain_estimate) = windows_after(false);
    let (_, turned_window, turned_estimate) = windows_after(true);
    for (what, plain, turned) in [
        ("window", &plain_window, &turned_window),
        ("estimate", &plain_estimate, &turned_estimate),
    ] {
        for a in 0..agents {
            for k in 0..w {
                let mut expected = plain[3 * (a * w + k)..][..3].to_vec();
                if a == turned_agent && (n..w - 1).contains(&k) {
                    turn_plan(&mut expected, &turn);
                    assert_ne!(expected, plain[3 * (a * w + k)..][..3], "{what} slot {k}");
                }
                assert_eq!(
                    turned[3 * (a * w + k)..][..3],
                    expected[..],
                    "{what}: agent {a}, slot {k}"
                );
            }
        }
    }
}
