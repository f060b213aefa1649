//! `road bench …`: throughput benchmarks that print a table (and JSON on request). Each one
//! measures a baseline in the same run.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Result;
use clap::{Args, Subcommand};
use rand::SeedableRng;
use road_data::{Split, WindowConfig};
use road_gpu::proxies::flops_per_evaluation;
use road_model::RunConfig;
use road_model::checkpoint::DataIdentity;
use road_model::model::{Mode, edm_loss};
use road_model::train::{Trainer, sample_batch};
use road_sched::{PlannerSpec, SceneSpec, Scheduler};

use crate::commands::load_cache;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Training throughput (scene-samples/s) of run configs on the dataset caches, with the
    /// forward-only (no gradient) throughput of the same batches as the baseline.
    Train(TrainBenchArgs),
    /// Scheduler overhead per scene-step for many live scenes, against recomputing every
    /// step's σ vectors from the schedule (no tables) as the baseline.
    Sched(SchedBenchArgs),
    /// Batched denoiser steps (one Heun step, 2 evaluations) of real validation scenes on the
    /// WGSL engine (the adapter wgpu picks) side by side with the candle CPU reference:
    /// scene-steps/s, ms per batched step, FLOPs per scene-step and achieved FLOP/s, and the
    /// engine's proxies per evaluation (dispatches, bytes of their bindings, work computed over
    /// the scenes' own), which need no GPU to measure.
    Engine(EngineBenchArgs),
    /// Serving: B validation scenes ticking together through the scheduler and the rollout
    /// driver (windows on the engine, only emitted slots read back), with scenes joining (a
    /// fresh warm-up) every few ticks, against the same scenes in lockstep as the baseline.
    Serve(ServeBenchArgs),
    /// A soak: N scene create/tick/close cycles against a `road serve` child process; its
    /// resident memory, open file descriptors and threads before, after a warm-up (the
    /// baseline) and along the way.
    Soak(crate::commands::soak::SoakBenchArgs),
    /// What refused input costs the others: one scene ticking at 10 Hz, then the same while
    /// another session floods the server with oversized creations; the scene's round trips,
    /// the server's resident memory, and what became of the floods.
    Flood(crate::commands::flood::FloodBenchArgs),
    /// The server's protocol decoders and checks on generated inputs (arbitrary bytes,
    /// arbitrary JSON, mutated valid messages): inputs run, outcomes by error code, panics.
    Fuzz(crate::commands::fuzz::FuzzBenchArgs),
}

#[derive(Debug, Args)]
pub struct ServeBenchArgs {
    /// Checkpoint (its planner is what every scene runs, unless `--planner`); the shipped
    /// default's by default.
    #[arg(long, default_value = "models/road20-wide4")]
    pub checkpoint: PathBuf,
    /// Run every scene under this planner of `configs/planners.toml` instead of the
    /// checkpoint's own (e.g. `road20-nearfit-lanes-guarded-k10`: fewer sampler steps).
    #[arg(long)]
    pub planner: Option<String>,
    /// Scenes served together.
    #[arg(long, num_args = 1.., default_values_t = [8usize, 64])]
    pub scenes: Vec<usize>,
    /// Timed ticks after the first (the initial warm-up of every scene is not timed).
    #[arg(long, default_value_t = 12)]
    pub ticks: usize,
    /// In the joining run, one scene restarts (a new session: rebuilt window, warm-up) every
    /// this many ticks.
    #[arg(long, default_value_t = 3)]
    pub join_every: usize,
    /// `cpu`, `gpu` or both (default).
    #[arg(long, value_enum, num_args = 1.., default_values_t = [crate::commands::sample::Engine::Candle, crate::commands::sample::Engine::Cpu, crate::commands::sample::Engine::Gpu])]
    pub engines: Vec<crate::commands::sample::Engine>,
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
    #[arg(long)]
    pub json: bool,
    /// The whole front end instead: `road serve` in this process on loopback, one client
    /// thread per scene over zenoh, the procedural roundabout (no dataset needed); round-trip
    /// latency beside the engine compute of the same ticks (the server's pools: the fast CPU
    /// engine, scenes batched per round).
    #[arg(long)]
    pub zenoh: bool,
    /// With `--zenoh`: each client puts its ego on its own clock at this rate, as an ego stack
    /// does (phases spread evenly over the period), instead of as soon as it has the NPCs.
    #[arg(long, requires = "zenoh")]
    pub rate_hz: Option<f64>,
    /// With `--zenoh`: the server's engine (`road serve --engine`).
    #[arg(long, value_enum, requires = "zenoh", default_value_t = crate::commands::serve::ServeEngineArg::Cpu)]
    pub server_engine: crate::commands::serve::ServeEngineArg,
}

#[derive(Debug, Args)]
pub struct EngineBenchArgs {
    /// Checkpoint folders to measure.
    #[arg(long, num_args = 1.., default_values = ["models/road20-wide4", "models/road20"])]
    pub checkpoints: Vec<PathBuf>,
    /// Scenes per batched step.
    #[arg(long, num_args = 1.., default_values_t = [1usize, 8, 64, 512])]
    pub batches: Vec<usize>,
    /// Timed repetitions per measurement (after one warm-up step).
    #[arg(long, default_value_t = 2)]
    pub reps: usize,
    /// The largest batch the candle CPU reference is timed at (its columns are empty above):
    /// at thousands of scenes one of its steps takes minutes, which a lent GPU machine cannot
    /// spare. Default: every batch.
    #[arg(long)]
    pub cpu_max_batch: Option<usize>,
    /// The linear layers' kernels to time, each a GPU row of the same run: `rowwise`, `tiled`,
    /// `blocked` or `auto` (per layer on hardware: blocked for large layers, tiled for middle
    /// ones, row-wise for small; row-wise on software adapters).
    #[arg(long, num_args = 1.., default_values = ["auto"], value_parser = parse_linear_kernel)]
    pub linear_kernels: Vec<Option<road_gpu::kernels::linear::LinearKernel>>,
    /// The polyline encoder's kernels to time, each a GPU row per linear kernel:
    /// `per-polyline`, `blocked` or `auto` (blocked where the shape fits).
    #[arg(long, num_args = 1.., default_values = ["auto"], value_parser = parse_polyline_kernel)]
    pub polyline_kernels: Vec<Option<road_gpu::kernels::polyline::PolylineKernel>>,
    /// Whether the engine packs scenes of mixed agent counts (several small scenes' agents in
    /// one sub-batch scene): `on` (the default: from as many moving scenes as the adapter's rule
    /// says), `eager` (from 2 on any adapter, as lavapipe's rule: to measure a card's), or `off`
    /// (one batch padded to the most agents), each a GPU row.
    #[arg(long, num_args = 1.., default_values = ["on"], value_parser = ["on", "eager", "off"])]
    pub packing: Vec<String>,
    /// How a block's layers between attentions run, each a GPU row: `wide-chains` (one
    /// `residual_chain` dispatch each: output projection, MLP, the next layer, on the wide tile
    /// of 32–64 rows where the model has one; the engine's default), `chains` (the same on the
    /// narrow tile of 8 rows, `ContextOptions::wide_chains` off) or `layers` (a dispatch per
    /// layer, `ContextOptions::residual_chains` off).
    #[arg(long, num_args = 1.., default_values = ["wide-chains"], value_parser = ["chains", "wide-chains", "layers"])]
    pub fusion: Vec<String>,
    /// Whether an evaluation keeps the map's keys (agent maps, every block's map k, v) of the
    /// one before while what they are made from holds (`kept`, the default:
    /// `ContextOptions::keep_map_keys`) or makes them every time (`remade`), each a GPU row.
    /// Every timed step is a tick's first (its anchors moved since the last), so that a Heun
    /// step makes them once; a tick's later steps, which keep them too, are not timed.
    #[arg(long, num_args = 1.., default_values = ["kept"], value_parser = ["kept", "remade"])]
    pub map_keys: Vec<String>,
    /// How the kernels are compiled, each a GPU row per linear kernel: `checked` (wgpu's
    /// runtime checks, the default) or `unchecked` (`ContextOptions::unchecked_shaders`).
    #[arg(long, num_args = 1.., default_values = ["checked"], value_parser = ["checked", "unchecked"])]
    pub shader_checks: Vec<String>,
    /// The linear layers' arithmetic, each a GPU row per other setting: `f32` (the default)
    /// or `f16` (the blocks' layers with f16 inputs and weights, f32 sums; on the tensor cores
    /// where the adapter offers cooperative matrices, layer by layer: the chains are f32).
    #[arg(long, num_args = 1.., default_values = ["f32"])]
    pub precisions: Vec<road_gpu::Precision>,
    /// Under f16, whether the layers run on the tensor cores where the adapter offers
    /// cooperative matrices (`on`, the default) or `linear_f16` everywhere (`off`: the same
    /// rounding without them), each a GPU row per f16 row.
    #[arg(long, num_args = 1.., default_values = ["on"], value_parser = ["on", "off"])]
    pub tensor_cores: Vec<String>,
    /// Also time each GPU step kernel by kernel (one evaluation and the Euler update, each
    /// dispatch waited for alone): where the device time goes.
    #[arg(long)]
    pub profile: bool,
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
    #[arg(long)]
    pub json: bool,
}

/// An engine row's GPU setting: its linear kernel, the polyline kernel when one was named,
/// `unchecked` when its kernels were compiled without wgpu's runtime checks, and `one batch`
/// when its scenes were not packed.
fn gpu_setting(row: &serde_json::Value) -> String {
    let mut setting = row["linear_kernel"].as_str().unwrap_or("").to_string();
    match row["polyline_kernel"].as_str() {
        Some("auto") | None => {}
        Some(polyline) => setting += &format!(", {polyline}"),
    }
    if row["shader_checks"].as_str() == Some("unchecked") {
        setting += ", unchecked";
    }
    match row["packing"].as_str() {
        Some("off") => setting += ", one batch",
        Some("eager") => setting += ", packed eagerly",
        _ => {}
    }
    match row["fusion"].as_str() {
        Some("layers") => setting += ", layer by layer",
        // The wide tile is the default: the narrow one is named.
        Some("chains") => setting += ", narrow chains",
        _ => {}
    }
    if row["map_keys"].as_str() == Some("remade") {
        setting += ", map keys remade";
    }
    if let Some(f16) = row["precision"].as_str().filter(|p| *p != "f32") {
        setting += &format!(", {f16}");
        if row["tensor_cores"].as_bool() == Some(true) {
            setting += " (tensor cores)";
        }
    }
    setting
}

fn parse_polyline_kernel(
    s: &str,
) -> Result<Option<road_gpu::kernels::polyline::PolylineKernel>, String> {
    if s == "auto" {
        return Ok(None);
    }
    s.parse().map(Some)
}

fn parse_linear_kernel(s: &str) -> Result<Option<road_gpu::kernels::linear::LinearKernel>, String> {
    if s == "auto" {
        return Ok(None);
    }
    s.parse().map(Some)
}

#[derive(Debug, Args)]
pub struct TrainBenchArgs {
    /// Run configs to measure.
    #[arg(long, num_args = 1.., default_values = ["configs/road20.toml", "configs/road20-wide4.toml"])]
    pub configs: Vec<PathBuf>,
    /// Optimiser steps timed per config (after one warm-up step).
    #[arg(long, default_value_t = 10)]
    pub steps: u64,
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct SchedBenchArgs {
    /// Live scene counts to measure.
    #[arg(long, num_args = 1.., default_values_t = [1usize, 64, 512, 4096])]
    pub scenes: Vec<usize>,
    /// Simulated steps per scene.
    #[arg(long, default_value_t = 50)]
    pub ticks: usize,
    #[arg(long)]
    pub json: bool,
}

pub fn run(cmd: BenchCommand) -> Result<ExitCode> {
    match cmd {
        BenchCommand::Train(args) => train_bench(&args),
        BenchCommand::Sched(args) => sched_bench(&args),
        BenchCommand::Engine(args) => engine_bench(&args),
        BenchCommand::Serve(args) if args.zenoh => {
            let rows = crate::commands::zenoh_bench::run(
                &args.checkpoint,
                args.server_engine.resolve(),
                &args.scenes,
                args.ticks,
                args.rate_hz,
            )?;
            if args.json {
                out!("{}", serde_json::to_string_pretty(&rows)?);
            } else {
                crate::commands::zenoh_bench::print(&rows);
            }
            Ok(())
        }
        BenchCommand::Serve(args) => serve_bench(&args),
        BenchCommand::Soak(args) => crate::commands::soak::run(&args),
        BenchCommand::Flood(args) => crate::commands::flood::run(&args),
        BenchCommand::Fuzz(args) => return crate::commands::fuzz::run(&args),
    }
    .map(|()| ExitCode::SUCCESS)
}

fn train_bench(args: &TrainBenchArgs) -> Result<()> {
    let train = load_cache(&args.cache, Split::Train)?;
    let validation = load_cache(&args.cache, Split::Validation)?;
    let threads = std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "default".into());
    let mut rows = Vec::new();
    for path in &args.configs {
        let mut run: RunConfig = crate::config::load(Some(path), &[])?;
        run.train.val_batches = 1;
        let identity = DataIdentity {
            train_cache: "bench".into(),
            train_windows: train.len(),
            validation_windows: validation.len(),
            source: "bench".into(),
        };
        let mut trainer = Trainer::new(run.clone(), &validation, identity, None)?;
        trainer.train_step(&train)?; // warm-up
        let started = Instant::now();
        for _ in 0..args.steps {
            trainer.train_step(&train)?;
        }
        let train_secs = started.elapsed().as_secs_f64();
        // Baseline: the same work without gradients or optimiser (batch building + forward).
        let model = trainer.ema_model()?;
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let started = Instant::now();
        let mut batch_secs = 0.0;
        let buckets = run
            .train
            .bucket_by_agents
            .then(|| road_model::train::AgentBuckets::new(&train));
        for _ in 0..args.steps {
            let t = Instant::now();
            let batch = sample_batch(
                &run,
                &train,
                run.train.batch_scenes,
                buckets.as_ref(),
                &mut rng,
                &candle_core::Device::Cpu,
            )?;
            batch_secs += t.elapsed().as_secs_f64();
            let map = model.encode_map(&batch.map, Mode::Infer)?;
            edm_loss(&model, &batch, &map, Mode::Infer)?;
        }
        let forward_secs = started.elapsed().as_secs_f64();
        let samples = (args.steps * run.train.batch_scenes as u64) as f64;
        rows.push(serde_json::json!({
            "config": run.name,
            "parameters": trainer.parameter_count(),
            "batch_scenes": run.train.batch_scenes,
            "window_slots": run.model.window_slots,
            "train_samples_per_sec": samples / train_secs,
            "train_ms_per_step": 1e3 * train_secs / args.steps as f64,
            "forward_only_samples_per_sec": samples / forward_secs,
            "batch_building_share": batch_secs / forward_secs.max(1e-9),
        }));
    }
    if args.json {
        out!(
            "{}",
            serde_json::to_string_pretty(
                &serde_json::json!({ "rayon_threads": threads, "hardware": crate::commands::train::hardware(), "rows": rows })
            )?
        );
    } else {
        out!(
            "training throughput, candle CPU, RAYON_NUM_THREADS={threads}, {}",
            crate::commands::train::hardware()
        );
        out!(
            "| config | parameters | batch | W | train samples/s | ms/step | forward-only samples/s (baseline) |"
        );
        out!("|---|---:|---:|---:|---:|---:|---:|");
        for r in &rows {
            out!(
                "| {} | {} | {} | {} | {:.1} | {:.0} | {:.1} |",
                r["config"].as_str().unwrap_or(""),
                r["parameters"],
                r["batch_scenes"],
                r["window_slots"],
                r["train_samples_per_sec"].as_f64().unwrap_or(0.0),
                r["train_ms_per_step"].as_f64().unwrap_or(0.0),
                r["forward_only_samples_per_sec"].as_f64().unwrap_or(0.0)
            );
        }
    }
    Ok(())
}

fn sched_bench(args: &SchedBenchArgs) -> Result<()> {
    let spec = PlannerSpec::default(); // RoAD-20, K = 40
    let mut rows = Vec::new();
    for &scenes in &args.scenes {
        // The scheduler: tables, batches, outcomes.
        let mut sched = Scheduler::with_capacity(scenes);
        let pid = sched.add_planner("road20", spec.clone())?;
        let ids: Vec<_> = (0..scenes)
            .map(|_| {
                sched.admit(SceneSpec {
                    planner: pid,
                    external_agents: vec![],
                })
            })
            .collect::<Result<_, _>>()?;
        let mut outcomes = Vec::with_capacity(scenes);
        let mut checksum = 0.0f64;
        let mut scene_steps = 0u64;
        let started = Instant::now();
        for _ in 0..args.ticks {
            for &id in &ids {
                sched.request_tick(id)?;
            }
            while sched.next_batch(scenes)? > 0 {
                let batch = sched.batch();
                scene_steps += batch.len() as u64;
                for item in batch {
                    let plan = sched.step_plan(item);
                    checksum += f64::from(plan.sigma_next[spec.obs_slots]);
                }
                sched.complete_batch();
            }
            outcomes.clear();
            sched.take_outcomes(&mut outcomes);
        }
        let sched_secs = started.elapsed().as_secs_f64();
        // Baseline: per item, compute σ_cur/σ_next for the whole window from the schedule.
        let started = Instant::now();
        let mut baseline_checksum = 0.0f64;
        let k = spec.steps_per_diffusion;
        let f = spec.future_slots;
        for tick in 0..args.ticks {
            let (stage_steps, profile): (usize, fn(usize, usize, f64) -> f64) = if tick == 0 {
                (k, road_sched::edm::warmup_u)
            } else {
                (k / f, road_sched::edm::rolling_u)
            };
            for step in 0..stage_steps {
                for _ in 0..scenes {
                    let tau_next = 1.0 - (step + 1) as f64 / stage_steps as f64;
                    let sigma_next: Vec<f64> = (0..f)
                        .map(|slot| spec.edm.sigma(profile(slot, f, tau_next.max(0.0))))
                        .collect();
                    baseline_checksum += sigma_next[0];
                }
            }
        }
        let baseline_secs = started.elapsed().as_secs_f64();
        std::hint::black_box((checksum, baseline_checksum));
        rows.push(serde_json::json!({
            "scenes": scenes,
            "scene_steps": scene_steps,
            "scheduler_ns_per_scene_step": 1e9 * sched_secs / scene_steps as f64,
            "baseline_ns_per_scene_step": 1e9 * baseline_secs / scene_steps as f64,
        }));
    }
    if args.json {
        out!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        out!(
            "scheduler overhead, RoAD-20 (K = 40), {} simulated steps per scene, {}",
            args.ticks,
            crate::commands::train::hardware()
        );
        out!(
            "| live scenes | scene-steps | scheduler ns per scene-step | baseline ns (σ recomputed) |"
        );
        out!("|---:|---:|---:|---:|");
        for r in &rows {
            out!(
                "| {} | {} | {:.0} | {:.0} |",
                r["scenes"],
                r["scene_steps"],
                r["scheduler_ns_per_scene_step"].as_f64().unwrap_or(0.0),
                r["baseline_ns_per_scene_step"].as_f64().unwrap_or(0.0)
            );
        }
    }
    Ok(())
}

/// One batch of `road bench engine`: `shape` = (scenes, agents, polylines) and its inputs.
struct BenchBatch<'a> {
    shape: (usize, usize, usize),
    features: &'a [f32],
    map: &'a [f32],
    map_valid: &'a [f32],
    x: &'a [f32],
    valid: &'a [f32],
    sigma_cur: &'a [f32],
    sigma_next: &'a [f32],
}

impl BenchBatch<'_> {
    /// Seconds a Heun step of the batch takes on `engine`: prepared, loaded, one step to warm
    /// up, then the mean of `reps` steps, `before_step` before each (and the warm-up).
    fn time_steps<E: road_rollout::StepEngine>(
        &self,
        engine: &mut E,
        reps: usize,
        wait: &dyn Fn() -> Result<()>,
        before_step: fn(&mut E),
    ) -> Result<f64> {
        let (b, a, p) = self.shape;
        engine.prepare(b, a, self.features, p, self.map, self.map_valid)?;
        engine.load(self.x, self.valid)?;
        before_step(engine);
        engine.step(self.sigma_cur, self.sigma_next, true)?;
        wait()?;
        let started = Instant::now();
        for _ in 0..reps {
            before_step(engine);
            engine.step(self.sigma_cur, self.sigma_next, true)?;
        }
        wait()?;
        Ok(started.elapsed().as_secs_f64() / reps as f64)
    }
}

fn engine_bench(args: &EngineBenchArgs) -> Result<()> {
    use road_cpu::CpuEngine;
    use road_model::batch::SceneInput;
    let validation = load_cache(&args.cache, Split::Validation)?;
    // One context per map-key, fusion, packing, shader-check, polyline and linear kernel and
    // precision setting compared.
    let mut settings = Vec::new();
    for (map_keys, fusion) in args
        .map_keys
        .iter()
        .flat_map(|k| args.fusion.iter().map(move |f| (k, f)))
    {
        for packing in &args.packing {
            for checks in &args.shader_checks {
                for &polyline_kernel in &args.polyline_kernels {
                    for &linear_kernel in &args.linear_kernels {
                        for &precision in &args.precisions {
                            // Tensor cores on or off matter to f16 rows alone.
                            let tensor_cores: &[String] = match precision {
                                road_gpu::Precision::F32 => &args.tensor_cores[..1],
                                road_gpu::Precision::F16 => &args.tensor_cores,
                            };
                            for cores in tensor_cores {
                                settings.push(road_gpu::ContextOptions {
                                    linear_kernel,
                                    polyline_kernel,
                                    unchecked_shaders: checks == "unchecked",
                                    pack_scenes: packing != "off",
                                    eager_packing: packing == "eager",
                                    residual_chains: fusion != "layers",
                                    wide_chains: fusion == "wide-chains",
                                    keep_map_keys: map_keys == "kept",
                                    precision,
                                    cooperative_matrices: cores == "on",
                                    ..road_gpu::ContextOptions::default()
                                });
                            }
                        }
                    }
                }
            }
        }
    }
    let contexts: Vec<road_gpu::GpuContext> = settings
        .iter()
        .map(road_gpu::GpuContext::new)
        .collect::<Result<_, _>>()?;
    let ctx = &contexts[0];
    let mut rows = Vec::new();
    for dir in &args.checkpoints {
        let loaded = road_model::checkpoint::load(dir, &candle_core::Device::Cpu)?;
        let config = loaded.meta.run.model.clone();
        let gpu_models = contexts
            .iter()
            .map(|ctx| road_gpu::engine::GpuDenoiser::from_checkpoint(ctx, dir))
            .collect::<Result<Vec<_>, _>>()?;
        let tables =
            road_sched::PlannerTables::new(&loaded.meta.run.name, loaded.meta.run.planner.clone())?;
        let stage = if tables.spec.kind == road_sched::PlannerKind::Rolling {
            &tables.rolling
        } else {
            &tables.full
        };
        let plan = stage.step(0);
        for &b in &args.batches {
            // b real scenes (cycling through the validation windows), cropped to the window.
            let scenes: Vec<SceneInput> = (0..b)
                .map(|i| {
                    validation
                        .window((i * 97) % validation.len())
                        .map(|w| SceneInput::from_window(&w, 0, config.window_slots, &config))
                })
                .collect::<Result<_, _>>()?;
            let a = scenes.iter().map(|s| s.agents).max().unwrap_or(1);
            let p = scenes.iter().map(|s| s.polylines).max().unwrap_or(1);
            let (w, q) = (config.window_slots, config.polyline_points);
            let mut feats = vec![0.0f32; b * a * 6];
            let mut map = vec![0.0f32; b * p * q * 2];
            let mut map_valid = vec![0.0f32; b * p];
            let mut x = vec![0.0f32; b * a * w * 3];
            let mut valid = vec![0.0f32; b * a * w];
            for (i, s) in scenes.iter().enumerate() {
                feats[i * a * 6..][..s.agents * 6].copy_from_slice(&s.agent_features);
                map[i * p * q * 2..][..s.polylines * q * 2].copy_from_slice(&s.map);
                map_valid[i * p..][..s.polylines].fill(1.0);
                for agent in 0..s.agents {
                    x[(i * a + agent) * w * 3..][..w * 3]
                        .copy_from_slice(&s.states[agent * w * 3..][..w * 3]);
                    for slot in 0..w {
                        valid[(i * a + agent) * w + slot] =
                            f32::from(u8::from(s.valid[agent * w + slot]));
                    }
                }
            }
            let flops = 2.0
                * scenes
                    .iter()
                    .map(|s| flops_per_evaluation(&config, s.agents, s.polylines))
                    .sum::<f64>()
                / b as f64;
            // Every scene at the same step here; each still gets its own σ row, as in serving.
            let sigma_cur = plan.sigma_cur.repeat(b);
            let sigma_next = plan.sigma_next.repeat(b);
            let batch = BenchBatch {
                shape: (b, a, p),
                features: &feats,
                map: &map,
                map_valid: &map_valid,
                x: &x,
                valid: &valid,
                sigma_cur: &sigma_cur,
                sigma_next: &sigma_next,
            };
            let cpu_secs = if args.cpu_max_batch.is_none_or(|max| b <= max) {
                let mut engine = CpuEngine::new(&loaded.model);
                Some(batch.time_steps(&mut engine, args.reps, &|| Ok(()), |_| {})?)
            } else {
                None
            };
            for (ctx, gpu_model) in contexts.iter().zip(&gpu_models) {
                // What every row holds; the GPU's figures (or why there are none) go in below.
                let mut row = serde_json::json!({
                    "checkpoint": loaded.meta.run.name,
                    "scenes": b,
                    "padded_agents": a,
                    "scene_agents": scenes.iter().map(|s| s.agents).collect::<Vec<_>>(),
                    "linear_kernel": ctx.linear_kernel_setting(),
                    "shader_checks": ctx.shader_checks_setting(),
                    "polyline_kernel": ctx.polyline_kernel_setting(),
                    "packing": match (ctx.pack_scenes(), ctx.eager_packing()) {
                        (false, _) => "off",
                        (true, false) => "on",
                        (true, true) => "eager",
                    },
                    "fusion": ctx.fusion_setting(),
                    "map_keys": if ctx.keep_map_keys() { "kept" } else { "remade" },
                    "precision": ctx.precision().name(),
                    "tensor_cores": ctx.cooperative_f16(),
                    "flops_per_scene_step": flops,
                    "cpu_ms_per_step": cpu_secs.map(|s| s * 1e3),
                    "cpu_scene_steps_per_sec": cpu_secs.map(|s| b as f64 / s),
                    "cpu_gflops": cpu_secs.map(|s| flops * b as f64 / s / 1e9),
                    "profile": serde_json::Value::Null,
                });
                let mut engine = road_gpu::step_engine::GpuStepEngine::new(ctx, gpu_model);
                // A batch the adapter cannot hold is a row saying so, not the end of the run.
                // Each timed step a tick's first: its map keys made again.
                let tick = road_gpu::step_engine::GpuStepEngine::remake_map_keys;
                let gpu_secs =
                    match batch.time_steps(&mut engine, args.reps, &|| Ok(ctx.wait()?), tick) {
                        Ok(secs) => secs,
                        Err(e) => {
                            tracing::warn!(scenes = b, "GPU column skipped: {e:#}");
                            row["gpu_error"] = format!("{e:#}").into();
                            rows.push(row);
                            continue;
                        }
                    };
                // The proxies of issue 40 over the timed steps and the warm-up (all alike):
                // counted as the engine records its dispatches, so fusion moves them by itself.
                let work = engine.take_work();
                // The GPU's work as it computed it: the map keys only where it made them.
                let steps = (args.reps + 1) as f64;
                let gpu_flops = work.useful_flops / steps / b as f64;
                row["gpu_flops_per_scene_step"] = gpu_flops.into();
                row["map_key_evaluations_per_step"] =
                    (work.map_key_evaluations as f64 / steps).into();
                row["gpu_ms_per_step"] = (gpu_secs * 1e3).into();
                row["gpu_scene_steps_per_sec"] = (b as f64 / gpu_secs).into();
                row["gpu_gflops"] = (gpu_flops * b as f64 / gpu_secs / 1e9).into();
                row["dispatches_per_evaluation"] = work.dispatches_per_evaluation().into();
                row["bytes_per_evaluation"] = work.bytes_per_evaluation().into();
                row["computed_over_useful"] = work.computed_over_useful().into();
                if args.profile {
                    let p = engine.profile_step(args.reps)?;
                    let kernels: Vec<serde_json::Value> = p
                        .kernels
                        .iter()
                        .map(|k| {
                            serde_json::json!({
                                "kernel": k.kernel,
                                "dispatches": k.dispatches,
                                "ms_per_step": k.secs_per_step * 1e3,
                            })
                        })
                        .collect();
                    row["profile"] = serde_json::json!({
                        "round_trip_ms": p.round_trip_secs * 1e3,
                        "kernels": kernels,
                    });
                }
                rows.push(row);
            }
        }
    }
    if args.json {
        out!(
            "{}",
            serde_json::to_string_pretty(
                &serde_json::json!({ "adapter": ctx.describe(), "cpu": crate::commands::train::hardware(), "rows": rows })
            )?
        );
        return Ok(());
    }
    out!(
        "engine: one Heun step (2 evaluations) per scene; GPU = {}; CPU = candle on {}",
        ctx.describe(),
        crate::commands::train::hardware()
    );
    out!(
        "| checkpoint | scenes | GPU linear kernel | MFLOP per scene-step: model / GPU | GPU ms/step | GPU scene-steps/s | GPU GFLOP/s | CPU ms/step | CPU scene-steps/s | CPU GFLOP/s | dispatches per evaluation | MB read + written per evaluation | computed ÷ useful |"
    );
    out!("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &rows {
        // The CPU columns are null above --cpu-max-batch, the GPU ones where the adapter could
        // not hold the batch (its error follows the table).
        let num = |k: &str, scale: f64, digits: usize| {
            r[k].as_f64()
                .map_or_else(|| "—".to_string(), |v| format!("{:.digits$}", v * scale))
        };
        out!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            r["checkpoint"].as_str().unwrap_or(""),
            r["scenes"],
            gpu_setting(r),
            format!(
                "{} / {}",
                num("flops_per_scene_step", 1e-6, 1),
                num("gpu_flops_per_scene_step", 1e-6, 1)
            ),
            num("gpu_ms_per_step", 1.0, 1),
            num("gpu_scene_steps_per_sec", 1.0, 1),
            num("gpu_gflops", 1.0, 2),
            num("cpu_ms_per_step", 1.0, 1),
            num("cpu_scene_steps_per_sec", 1.0, 1),
            num("cpu_gflops", 1.0, 2),
            num("dispatches_per_evaluation", 1.0, 1),
            num("bytes_per_evaluation", 1e-6, 1),
            num("computed_over_useful", 1.0, 2)
        );
    }
    out!(
        "(the last three, per evaluation with its share of the sampler update and of a packed or \
         compact sub-batch's row moves: compute dispatches recorded; \
         bytes of their bindings, read-only ones read, read-write ones read and written; work \
         computed at the padded shape over each scene's own, agents with a valid slot; \
         the model's MFLOP make the map's keys in both evaluations, the GPU's where it made them: \
         each timed step is a tick's first, its second evaluation keeps the first's keys unless \
         `--map-keys remade`)"
    );
    for r in rows.iter().filter(|r| r["gpu_error"].is_string()) {
        out!(
            "\n{} at {} scenes ({}): no GPU figures: {}",
            r["checkpoint"].as_str().unwrap_or(""),
            r["scenes"],
            gpu_setting(r),
            r["gpu_error"].as_str().unwrap_or("")
        );
    }
    for r in rows.iter().filter(|r| !r["profile"].is_null()) {
        out!(
            "\nprofile: {} at {} scenes, {} (each dispatch waited for alone; one empty submission: {:.3} ms)",
            r["checkpoint"].as_str().unwrap_or(""),
            r["scenes"],
            gpu_setting(r),
            r["profile"]["round_trip_ms"].as_f64().unwrap_or(0.0)
        );
        out!("| kernel | dispatches | ms per evaluation + Euler update |");
        out!("|---|---:|---:|");
        for k in r["profile"]["kernels"].as_array().into_iter().flatten() {
            out!(
                "| {} | {} | {:.3} |",
                k["kernel"].as_str().unwrap_or(""),
                k["dispatches"],
                k["ms_per_step"].as_f64().unwrap_or(0.0)
            );
        }
    }
    Ok(())
}

fn serve_bench(args: &ServeBenchArgs) -> Result<()> {
    use road_rollout::{RolloutDriver, RolloutScene, TimedEngine};

    use crate::commands::engine::{Engine, EngineChoice, Engines};
    let validation = load_cache(&args.cache, Split::Validation)?;
    let reference = WindowConfig::default().reference_step;
    anyhow::ensure!(args.join_every > 0, "--join-every must be at least 1");
    let mut rows = Vec::new();
    for &engine_kind in &args.engines {
        let choice = EngineChoice::from(engine_kind);
        let engines = Engines::load(&args.checkpoint, choice)?;
        let run =
            &crate::commands::engine::with_planner(&engines.cpu.meta.run, args.planner.as_deref())?;
        let n = run.planner.obs_slots;
        for &b in &args.scenes {
            let scenes: Vec<RolloutScene> = (0..b)
                .map(|i| {
                    validation
                        .window((i * 97) % validation.len())
                        .map(|w| RolloutScene {
                            history: road_model::batch::SceneInput::from_window(
                                &w,
                                reference + 1 - n,
                                n,
                                &run.model,
                            ),
                        })
                })
                .collect::<Result<_, _>>()?;
            for joining in [false, true] {
                let mut engine = engines.engine()?;
                let mut rng = rand::rngs::StdRng::seed_from_u64(0);
                let mut driver = RolloutDriver::new(
                    engine.as_dyn(),
                    &run.planner,
                    &scenes,
                    args.ticks + 1,
                    &mut rng,
                )?;
                driver.tick(engine.as_dyn(), &mut |_, _, _| Ok(()))?; // every scene's warm-up, untimed
                if let Engine::Gpu(gpu) = &mut engine {
                    gpu.take_work();
                }
                // The time inside the engine, so that a tick splits into it and the host's.
                let mut timed = TimedEngine::new(engine.as_dyn());
                let nfe_before_of = (0..b)
                    .map(|i| driver.scene_nfe(i))
                    .collect::<road_model::Result<Vec<u64>>>()?;
                let nfe_before: u64 = nfe_before_of.iter().sum();
                let started = Instant::now();
                for t in 0..args.ticks {
                    if joining && t % args.join_every == 0 {
                        driver.switch_scene_planner((t / args.join_every) % b, &run.planner)?;
                    }
                    driver.tick(&mut timed, &mut |_, _, _| Ok(()))?;
                }
                let secs = started.elapsed().as_secs_f64();
                let engine_secs = timed.take_spent().as_secs_f64();
                // The GPU's proxies over the timed ticks (issue 40), as `road bench engine`'s.
                let proxies = match &mut engine {
                    Engine::Gpu(gpu) => {
                        let work = gpu.take_work();
                        serde_json::json!({
                            "dispatches_per_evaluation": work.dispatches_per_evaluation(),
                            "bytes_per_evaluation": work.bytes_per_evaluation(),
                            "computed_over_useful": work.computed_over_useful(),
                            "map_key_share": work.map_key_evaluations as f64 / work.evaluations.max(1) as f64,
                        })
                    }
                    _ => serde_json::Value::Null,
                };
                // Useful work: each scene's evaluations times its multiply-adds (agents with
                // any valid slot; with agent maps, each query attends to its K polylines).
                let mut flops = 0.0;
                for (i, scene) in scenes.iter().enumerate() {
                    let history = &scene.history;
                    let agents = (0..history.agents)
                        .filter(|&a| {
                            history.valid[a * history.slots..(a + 1) * history.slots]
                                .iter()
                                .any(|&v| v)
                        })
                        .count();
                    let polylines = run
                        .model
                        .agent_map
                        .as_ref()
                        .map_or(history.polylines, |m| m.polylines);
                    let evaluations = driver.scene_nfe(i)? - nfe_before_of[i];
                    flops +=
                        evaluations as f64 * flops_per_evaluation(&run.model, agents, polylines);
                }
                let nfe = (0..b)
                    .map(|i| driver.scene_nfe(i))
                    .sum::<road_model::Result<u64>>()?
                    - nfe_before;
                rows.push(serde_json::json!({
                    "engine": engines.describe(),
                    "scenes": b,
                    "mode": if joining { format!("a scene joins every {} ticks", args.join_every) } else { "lockstep".into() },
                    "ms_per_tick": secs * 1e3 / args.ticks as f64,
                    "scene_ticks_per_sec": (b * args.ticks) as f64 / secs,
                    "nfe_per_scene_tick": nfe as f64 / (b * args.ticks) as f64,
                    "gflop_per_sec": flops / secs / 1e9,
                    // Inside the engine (kernels, uploads, readbacks) and around it (the
                    // driver's bookkeeping, the planner's smoothing): issue 40's host share.
                    "engine_ms_per_tick": engine_secs * 1e3 / args.ticks as f64,
                    "host_ms_per_tick": (secs - engine_secs) * 1e3 / args.ticks as f64,
                    "host_share": (secs - engine_secs) / secs,
                    "gpu_proxies": proxies,
                }));
            }
        }
    }
    if args.json {
        out!(
            "{}",
            serde_json::to_string_pretty(
                &serde_json::json!({ "checkpoint": args.checkpoint, "planner": args.planner, "cpu": crate::commands::train::hardware(), "rows": rows })
            )?
        );
        return Ok(());
    }
    out!(
        "serve: {}{} ({} ticks timed after every scene's warm-up); CPU = {}",
        args.checkpoint.display(),
        args.planner
            .as_deref()
            .map(|p| format!(" under planner {p}"))
            .unwrap_or_default(),
        args.ticks,
        crate::commands::train::hardware()
    );
    out!(
        "| engine | scenes | mode | ms per tick | scene-ticks/s | scenes at 10 Hz (scene-ticks/s ÷ 10) | this B in real time (tick ≤ 100 ms) | NFE per scene-tick | GFLOP/s (useful work) | host share |"
    );
    out!("|---|---:|---|---:|---:|---:|---|---:|---:|---:|");
    for r in &rows {
        let f = |k: &str| r[k].as_f64().unwrap_or(0.0);
        out!(
            "| {} | {} | {} | {:.1} | {:.1} | {:.1} | {} | {:.1} | {:.1} | {:.1} % |",
            r["engine"].as_str().unwrap_or(""),
            r["scenes"],
            r["mode"].as_str().unwrap_or(""),
            f("ms_per_tick"),
            f("scene_ticks_per_sec"),
            f("scene_ticks_per_sec") / 10.0,
            if f("ms_per_tick") <= 100.0 {
                "yes"
            } else {
                "no"
            },
            f("nfe_per_scene_tick"),
            f("gflop_per_sec"),
            f("host_share") * 100.0
        );
    }
    out!(
        "(GFLOP/s: the denoiser's multiply-adds ×2 of every evaluation (`flops_per_evaluation`: \
         projections, attention, MLP, the agent maps' point encoder and keys; the pair features \
         not counted, and the encoder and keys counted every evaluation although the fast CPU \
         engine memoises them per anchor and the GPU engine keeps them while the anchors hold: \
         the model's work served, not the work computed) over the timed ticks; host \
         share: the tick's time outside the engine's calls (kernels, uploads, readbacks), i.e. \
         the rollout driver's bookkeeping and the planner's smoothing; this bench runs no \
         closed loop, so the guards and infraction checks are not in it)"
    );
    Ok(())
}
