//! candle's training step against the PyTorch training path (`scripts/torch_train.py`), on the
//! fixture under `tests/fixtures/torch_train/`:
//!
//! - `dataset.safetensors`: a synthetic dataset built here ([`synthetic_dataset`]), written by
//!   `road_model::torch_export` (the format of `road data export-torch`); the first test checks
//!   that the exporter still writes exactly it;
//! - `run.toml`: the run (the torch-parity fixture's tiny model and random weights as
//!   `init_from`; a large learning rate, weight decay, an active clip, a fast EMA, rotations);
//! - `expected.safetensors`: what the PyTorch script did on two steps: its random draws
//!   (windows, crops, angles, τ, task profiles, u_ca, noise), the collated batches, the losses
//!   and gradients, the gradient norms and learning rates, the weights, AdamW moments and EMA
//!   after both steps, and the learning-rate schedule.
//!
//! Here the same draws go through candle's `SceneInput::from_window`, `rotate`,
//! `task_sigma_of`, `drop_absent_agents` and `collate` (the batches must agree), the
//! `Trainer`'s loss and gradients (the loss to 1e-4 relative, the gradients to 1e-4 of the
//! gradient norm) and `apply_gradients` fed PyTorch's gradients (the state to 1e-4: the
//! optimiser's math alone, free of the gradients' float noise, which Adam's first step turns
//! into a sign for a gradient that is zero in exact arithmetic, such as an attention key bias).
//!
//! Regenerate after a change to the data path, the loss or the optimiser, in both
//! implementations (docs/torch-training.md):
//! ```text
//! ROAD_TORCH_TRAIN_BLESS=1 cargo test -p road-model --test torch_train_parity  # dataset
//! python scripts/torch_train.py make-train-fixture   # expected.safetensors
//! cargo test -p road-model --test torch_train_parity -- --nocapture
//! ```

use std::collections::HashMap;
use std::f32::consts::PI;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use road_data::geometry::Aabb;
use road_data::map::{Lanelet, MapSkips};
use road_data::{AgentType, Dataset, LaneletMap, Recording, Split, Track, WindowConfig};
use road_model::RunConfig;
use road_model::batch::{SceneInput, task_sigma_of};
use road_model::checkpoint::{self, DataIdentity};
use road_model::torch_export::{self, ArrayFile};
use road_model::train::{SceneDraw, Trainer, learning_rate};
use road_sched::edm::{rolling_u, warmup_u};

/// Relative tolerance of the loss, and of the gradients against the gradient norm; absolute
/// tolerance of weights, moments and EMA (all of order one or below).
const TOLERANCE: f64 = 1e-4;
const BLESS: &str = "ROAD_TORCH_TRAIN_BLESS";

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/torch_train")
}

/// A tiny dataset with what the real one has: two recordings on two maps, tracks entering late
/// and leaving early, a heading that crosses ±π, all four agent types, coordinates far from the
/// origin (so the f64 normalisation matters), more agents and polylines than the window keeps.
fn synthetic_dataset() -> Dataset {
    let config = WindowConfig {
        window_steps: 14,
        stride_steps: 3,
        reference_step: 2,
        min_agents: 2,
        max_agents: 5,
        map_radius_m: 60.0,
        polyline_points: 4,
        max_polylines: 8,
        position_scale_m: 40.0,
    };
    let types = [
        AgentType::Car,
        AgentType::Truck,
        AgentType::Bicycle,
        AgentType::Pedestrian,
    ];
    let mut maps = Vec::new();
    let mut recordings = Vec::new();
    for r in 0..2u32 {
        let base = [1000.0 + 300.0 * f64::from(r), -500.0 + 77.7 * f64::from(r)];
        let lanelets = (0..11)
            .map(|l| {
                let lf = f64::from(l);
                let heading = 0.6 * lf + 0.3 * f64::from(r);
                let bend = 0.04 * (lf - 5.0);
                let start = [
                    base[0] + 40.0 * (0.9 * lf).cos() - 5.0,
                    base[1] + 35.0 * (1.3 * lf).sin() + 3.0,
                ];
                let mut centre = vec![start];
                for k in 1..(4 + l as usize % 4) {
                    let h = heading + bend * k as f64;
                    let last = centre[k - 1];
                    let step = 3.0 + 0.5 * k as f64;
                    centre.push([last[0] + step * h.cos(), last[1] + step * h.sin()]);
                }
                let side = |offset: f64| -> Vec<[f64; 2]> {
                    centre
                        .iter()
                        .map(|p| [p[0] - offset * heading.sin(), p[1] + offset * heading.cos()])
                        .collect()
                };
                let (left_m, right_m) = (side(1.7), side(-1.7));
                let bounds = Aabb::of(&[left_m.clone(), right_m.clone()].concat());
                Lanelet {
                    id: 5000 + i64::from(r) * 100 + i64::from(l),
                    subtype: None,
                    left_way: 0,
                    right_way: 0,
                    left_m,
                    right_m,
                    centre_m: centre,
                    successors: vec![],
                    neighbours: vec![],
                    bounds,
                }
            })
            .collect();
        maps.push(LaneletMap {
            location: format!("SYNTH_{r}"),
            lanelets,
            skipped: MapSkips::default(),
            priority_rules: Vec::new(),
        });
        let first_frame = 100 * r + 1;
        let tracks = (0..8u32)
            .map(|j| {
                let jf = j as f32;
                let begin = first_frame + (j * 5) % 9;
                let frames = 4 + (j * 7 + r * 3) % 24;
                // Track 0 turns through ±π; the others head every which way.
                let (heading0, turn) = if j == 0 {
                    (3.0f32, 0.05f32)
                } else {
                    (-2.5 + 0.9 * jf, 0.02 * (jf - 4.0))
                };
                let speed = 2.0 + 1.3 * jf; // m/s
                let mut position = [
                    base[0] as f32 + 12.0 * (1.7 * jf).cos(),
                    base[1] as f32 + 9.0 * (0.8 * jf).sin(),
                ];
                let states = (0..frames)
                    .map(|k| {
                        let raw = heading0 + turn * k as f32;
                        let psi = (raw + PI).rem_euclid(2.0 * PI) - PI;
                        position[0] += speed * 0.1 * psi.cos();
                        position[1] += speed * 0.1 * psi.sin();
                        [position[0], position[1], psi]
                    })
                    .collect();
                Track {
                    track_id: 10 * r + j + 1,
                    agent_type: types[(j + r) as usize % 4],
                    length_m: 3.5 + 0.4 * jf,
                    width_m: 1.6 + 0.05 * jf,
                    first_frame: begin,
                    states,
                }
            })
            .collect::<Vec<_>>();
        let last_frame = tracks.iter().map(Track::last_frame).max().unwrap();
        recordings.push(Recording {
            location: format!("SYNTH_{r}"),
            file: format!("synthetic_{r}.csv"),
            tracks,
            first_frame,
            last_frame,
        });
    }
    Dataset::from_parts(Split::Train, &config, maps, recordings, vec![0, 1]).unwrap()
}

/// The export of the synthetic dataset is the committed one (or, with `ROAD_TORCH_TRAIN_BLESS`,
/// becomes it): the exporter and the dataset builder have not moved under the fixture.
#[test]
fn the_synthetic_export_is_the_fixtures() {
    let ds = synthetic_dataset();
    assert!(ds.len() >= 8, "{} windows", ds.len());
    let fresh = torch_export::dataset_arrays(&ds).unwrap();
    let path = fixture_dir().join("dataset.safetensors");
    if std::env::var_os(BLESS).is_some() {
        let bytes = fresh.save(&path).unwrap();
        println!("wrote {} ({bytes} bytes)", path.display());
        return;
    }
    let committed = ArrayFile::load(&path).unwrap_or_else(|e| panic!("{e}"));
    let mut names: Vec<&String> = fresh.arrays.iter().map(|(n, _)| n).collect();
    names.sort();
    let committed_names: Vec<&String> = committed.arrays.iter().map(|(n, _)| n).collect();
    assert_eq!(names, committed_names);
    for (name, array) in &fresh.arrays {
        assert_eq!(
            Some(array),
            committed.get(name),
            "`{name}` differs from the fixture's"
        );
    }
    assert_eq!(fresh.metadata, committed.metadata);
}

fn expected() -> HashMap<String, Tensor> {
    let path = fixture_dir().join("expected.safetensors");
    checkpoint::load_tensors(&path, &Device::Cpu).unwrap_or_else(|e| panic!("{e}"))
}

fn get<'a>(e: &'a HashMap<String, Tensor>, name: &str) -> &'a Tensor {
    e.get(name)
        .unwrap_or_else(|| panic!("expected.safetensors lacks `{name}`"))
}

fn f32s(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

fn f64s(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap()
}

fn ints(t: &Tensor) -> Vec<i64> {
    t.flatten_all().unwrap().to_vec1::<i64>().unwrap()
}

fn max_abs_difference(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| f64::from((x - y).abs()))
        .fold(0.0, f64::max)
}

fn run_config() -> RunConfig {
    let mut run = RunConfig::load(&fixture_dir().join("run.toml")).unwrap();
    // run.toml names it relative to the workspace root (where the script runs).
    let init = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/torch_parity");
    run.train.init_from = Some(init);
    run
}

/// Step `k`'s scenes from the fixture's draws, through candle's data path; checks each scene's
/// σ row against PyTorch's on the way.
fn draw_of(run: &RunConfig, ds: &Dataset, e: &HashMap<String, Tensor>, k: usize) -> SceneDraw {
    let at = |name: &str| get(e, &format!("step{k}.{name}"));
    let (windows, starts) = (ints(at("window")), ints(at("start")));
    let (angles, taus, u_ca) = (f64s(at("angle")), f64s(at("tau")), f64s(at("u_ca")));
    let warmup = ints(at("warmup"));
    let noise = at("noise"); // [B, A_max, W, 3], each scene's window agents before the drop
    let sigma_torch = at("sigma");
    let w = run.model.window_slots;
    let mut draw = SceneDraw {
        inputs: vec![],
        sigma: vec![],
        noise: vec![],
    };
    for i in 0..windows.len() {
        let window = ds.window(windows[i] as usize).unwrap();
        let mut input = SceneInput::from_window(&window, starts[i] as usize, w, &run.model);
        if run.train.rotation_augmentation {
            input.rotate(angles[i] as f32, run.model.heading_scale as f32);
        }
        let profile = if warmup[i] == 1 { warmup_u } else { rolling_u };
        let sigma = task_sigma_of(&run.model, run.planner.obs_slots, profile, taus[i], u_ca[i]);
        let torch_sigma = f32s(&sigma_torch.get(i).unwrap());
        let difference = max_abs_difference(&sigma, &torch_sigma);
        assert!(
            difference <= 1e-6 * f64::from(sigma.iter().copied().fold(0.0, f32::max)),
            "step {k} scene {i}: σ rows differ by {difference:e}: {sigma:?} vs {torch_sigma:?}"
        );
        let mut eps = f32s(&noise.get(i).unwrap().narrow(0, 0, input.agents).unwrap());
        input.drop_absent_agents(&mut eps);
        draw.inputs.push(input);
        draw.sigma.push(sigma);
        draw.noise.push(eps);
    }
    draw
}

#[test]
fn batches_losses_gradients_and_steps_match_pytorch() {
    let run = run_config();
    let ds = synthetic_dataset();
    let e = expected();
    let data = DataIdentity {
        train_cache: "synthetic".into(),
        train_windows: ds.len(),
        validation_windows: ds.len(),
        source: "tests/torch_train_parity.rs".into(),
    };
    let mut trainer = Trainer::new(run.clone(), &ds, data, None).unwrap();
    let names = trainer.variable_names().to_vec();
    let (mut saw_clip, mut saw_warmup, mut saw_rolling, mut saw_drop) =
        (false, false, false, false);
    let steps = (0..)
        .take_while(|k| e.contains_key(&format!("step{k}.loss")))
        .count();
    assert!(steps >= 2, "the fixture holds {steps} steps");
    for k in 0..steps {
        let at = |name: &str| get(&e, &format!("step{k}.{name}"));
        let draw = draw_of(&run, &ds, &e, k);
        let warmup = ints(at("warmup"));
        saw_warmup |= warmup.contains(&1);
        saw_rolling |= warmup.contains(&0);
        saw_drop |= draw
            .inputs
            .iter()
            .zip(ints(at("window")))
            .any(|(input, w)| input.agents < ds.windows[w as usize].agents.len());

        // (a) The collated batch.
        let batch = draw.collate(0..draw.len(), &Device::Cpu).unwrap();
        for (name, got) in batch.named_tensors() {
            let want = at(name);
            assert_eq!(got.dims(), want.dims(), "step {k} batch `{name}`: shapes");
            let difference = max_abs_difference(&f32s(got), &f32s(want));
            println!("step {k} batch {name:<14} max |candle − torch| = {difference:.2e}");
            assert!(
                difference <= 1e-6,
                "step {k}: the batches' `{name}` differ by {difference:e}"
            );
        }

        // (b) The loss and its gradients at the same weights.
        let (loss, grads) = trainer.loss_and_gradients(&draw).unwrap();
        let torch_loss = f64s(at("loss"))[0];
        let relative = (loss - torch_loss).abs() / torch_loss.abs();
        println!("step {k} loss candle {loss:.7} torch {torch_loss:.7} (relative {relative:.2e})");
        assert!(
            relative <= TOLERANCE,
            "step {k}: losses differ by {relative:e}"
        );
        let grad_norm = f64s(at("grad_norm"))[0];
        let mut worst = 0.0f64;
        let mut torch_grads = Vec::with_capacity(names.len());
        for (name, grad) in names.iter().zip(&grads) {
            let want = at(&format!("grad.{name}"));
            let difference = max_abs_difference(&f32s(grad), &f32s(want));
            worst = worst.max(difference);
            assert!(
                difference <= TOLERANCE * grad_norm,
                "step {k}: the gradients of `{name}` differ by {difference:e} (norm {grad_norm})"
            );
            torch_grads.push(want.clone());
        }
        println!(
            "step {k} gradients: max |candle − torch| = {worst:.2e} (norm {grad_norm:.4}, {:.2e} of it)",
            worst / grad_norm
        );

        // (c) The optimiser step on PyTorch's gradients.
        let (norm, lr) = trainer.apply_gradients(&torch_grads).unwrap();
        assert!(
            (norm - grad_norm).abs() <= 1e-6 * grad_norm,
            "step {k}: gradient norms {norm} vs {grad_norm}"
        );
        let torch_lr = f64s(at("learning_rate"))[0];
        assert!(
            (lr - torch_lr).abs() <= 1e-12 * torch_lr,
            "step {k}: learning rates {lr} vs {torch_lr}"
        );
        saw_clip |= norm > run.train.grad_clip;
    }
    assert!(
        saw_clip && saw_warmup && saw_rolling && saw_drop,
        "the fixture misses a case: clip {saw_clip}, warm-up task {saw_warmup}, rolling task \
         {saw_rolling}, an absent agent dropped {saw_drop}"
    );

    // The state after the steps, as `road train` saves it.
    let dir = std::env::temp_dir().join(format!("road-torch-train-parity-{}", std::process::id()));
    trainer.save(&dir, 0.0, "test").unwrap();
    let state =
        checkpoint::load_tensors(&dir.join(checkpoint::TRAIN_STATE_FILE), &Device::Cpu).unwrap();
    let ema = checkpoint::load_tensors(&dir.join(checkpoint::WEIGHTS_FILE), &Device::Cpu).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    let mut worst: HashMap<&str, f64> = HashMap::new();
    for name in &names {
        for (kind, got) in [
            ("param", &state[&format!("param.{name}")]),
            ("adam_m", &state[&format!("adam_m.{name}")]),
            ("adam_v", &state[&format!("adam_v.{name}")]),
            ("ema", &ema[name]),
        ] {
            let want = get(&e, &format!("after.{kind}.{name}"));
            let difference = max_abs_difference(&f32s(got), &f32s(want));
            let entry = worst.entry(kind).or_default();
            *entry = entry.max(difference);
            assert!(
                difference <= TOLERANCE,
                "after {steps} steps: `{kind}.{name}` differs by {difference:e}"
            );
        }
    }
    println!("after {steps} steps: max |candle − torch| {worst:?}");
    // The steps moved the weights well beyond the tolerance (the comparison sees them).
    let start = checkpoint::load_tensors(
        &run.train
            .init_from
            .as_ref()
            .unwrap()
            .join(checkpoint::WEIGHTS_FILE),
        &Device::Cpu,
    )
    .unwrap();
    let moved = names
        .iter()
        .map(|n| max_abs_difference(&f32s(&state[&format!("param.{n}")]), &f32s(&start[n])))
        .fold(0.0, f64::max);
    assert!(
        moved > 100.0 * TOLERANCE,
        "the steps moved the weights by {moved:e}"
    );
}

#[test]
fn the_learning_rate_schedule_matches_pytorch() {
    let run = run_config();
    let table = f64s(get(&expected(), "learning_rate_table"));
    assert!(
        table.len() as u64 > run.train.steps,
        "the table covers the run"
    );
    for (step, want) in table.iter().enumerate() {
        let got = learning_rate(&run, step as u64);
        assert!(
            (got - want).abs() <= 1e-12 * want,
            "step {step}: learning rate {got} vs {want}"
        );
    }
}
