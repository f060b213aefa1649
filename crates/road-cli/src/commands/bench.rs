//! `road bench …`: throughput benchmarks that print a table (and JSON on request). Each one
//! measures a baseline in the same run.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use rand::SeedableRng;
use road_data::{Split, WindowConfig, cache};
use road_model::RunConfig;
use road_model::checkpoint::DataIdentity;
use road_model::model::{Mode, edm_loss};
use road_model::train::{Trainer, sample_batch};
use road_sched::{PlannerSpec, SceneSpec, Scheduler};

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Training throughput (scene-samples/s) of run configs on the dataset caches, with the
    /// forward-only (no gradient) throughput of the same batches as the baseline.
    Train(TrainBenchArgs),
    /// Scheduler overhead per scene-step for many live scenes, against recomputing every
    /// step's σ vectors from the schedule (no tables) as the baseline.
    Sched(SchedBenchArgs),
}

#[derive(Debug, Args)]
pub struct TrainBenchArgs {
    /// Run configs to measure.
    #[arg(long, num_args = 1.., default_values = ["configs/road20.toml", "configs/ar.toml", "configs/djinn10.toml"])]
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
    }
    .map(|()| ExitCode::SUCCESS)
}

fn train_bench(args: &TrainBenchArgs) -> Result<()> {
    let window = WindowConfig::default();
    let load = |split| {
        cache::load_checked(
            &cache::cache_path(&args.cache, split),
            split,
            Some(&window),
            None,
        )
    };
    let train = load(Split::Train).context("run `road data build` first")?;
    let validation = load(Split::Validation).context("run `road data build` first")?;
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
        for _ in 0..args.steps {
            let t = Instant::now();
            let batch = sample_batch(
                &run,
                &train,
                run.train.batch_scenes,
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
