//! `road eval --suite forecasting`: minSceneADE, minSceneFDE, miss rate, prediction time and
//! NFE per simulated step on validation scenes, beside a constant-velocity baseline.

use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use road_cpu::{CpuEngine, FastCpuEngine};
use road_data::{SceneWindow, Split, WindowConfig};
use road_model::batch::SceneInput;
use road_rollout::{RolloutScene, StepEngine, rollout_seeded, stream_seed};
use road_sim::controllers::constant_velocity;
use road_sim::metrics::{BOOTSTRAP_RESAMPLES, Estimate, bootstrap_ratio, scene_metrics};

use super::common::{EvalArgs, SceneSelection, progress, select_scenes};
use crate::commands::load_cache;
use crate::commands::sample::Engine;

#[derive(Debug, Default, Clone, serde::Serialize)]
struct Totals {
    model: String,
    scenes: usize,
    ade_sum: f64,
    fde_sum: f64,
    missed: usize,
    agents: usize,
    secs: f64,
    samples: usize,
    nfe_per_step: f64,
    /// Every evaluated scene's figures (for the bootstrap intervals and `road compare`).
    per_scene: Vec<SceneRow>,
    /// Filled in before the report: the figures with 95 % bootstrap intervals over scenes.
    min_scene_ade_m: Option<Estimate>,
    min_scene_fde_m: Option<Estimate>,
    miss_rate: Option<Estimate>,
}

/// One evaluated scene: its validation window (what `road compare` pairs on) and figures.
#[derive(Debug, Clone, Copy, serde::Serialize)]
struct SceneRow {
    window: usize,
    #[serde(flatten)]
    metrics: road_sim::metrics::SceneMetrics,
}

impl Totals {
    /// The headline figures with their 95 % bootstrap intervals over scenes.
    fn estimate(&mut self) {
        let seed = 0x5eed;
        let per = |f: fn(&road_sim::metrics::SceneMetrics) -> (f64, f64)| {
            bootstrap_ratio(
                &self
                    .per_scene
                    .iter()
                    .map(|r| f(&r.metrics))
                    .collect::<Vec<_>>(),
                seed,
            )
        };
        self.min_scene_ade_m = Some(per(|m| (m.min_scene_ade_m, 1.0)));
        self.min_scene_fde_m = Some(per(|m| (m.min_scene_fde_m, 1.0)));
        self.miss_rate = Some(per(|m| (m.missed_agents as f64, m.agents as f64)));
    }
}

fn truth_of(window: &SceneWindow, reference: usize, steps: usize) -> Vec<Vec<Option<[f64; 2]>>> {
    (0..window.agents)
        .map(|a| {
            (1..=steps)
                .map(|t| {
                    window
                        .state(a, reference + t)
                        .map(|s| window.frame.to_metres([s[0], s[1]]))
                })
                .collect()
        })
        .collect()
}

pub fn run(args: EvalArgs) -> Result<ExitCode> {
    let window_config = WindowConfig::default();
    let ds = load_cache(&args.cache, Split::Validation)?;
    let reference = window_config.reference_step;
    let steps = window_config.window_steps - reference - 1; // 30
    let sample_count = args.samples.unwrap_or(6);
    let SceneSelection { scenes, eligible } = select_scenes(&ds, &args, |_| true);
    anyhow::ensure!(
        !scenes.is_empty(),
        "no validation scene has {} agents or more",
        args.min_agents
    );
    eprintln!(
        "forecasting suite: {} of {eligible} eligible scenes (top {} locations, ≥ {} agents at the last observed step), {} samples each, {steps} steps",
        scenes.len(),
        args.top_locations,
        args.min_agents,
        sample_count
    );
    let windows: Vec<SceneWindow> = scenes
        .iter()
        .map(|&i| ds.window(i))
        .collect::<Result<_, _>>()?;
    let mut results = Vec::new();

    // Constant velocity: one deterministic sample.
    let started = Instant::now();
    let mut cv = Totals {
        model: "constant velocity".into(),
        ..Totals::default()
    };
    for (&window, w) in scenes.iter().zip(&windows) {
        let samples = vec![
            (0..w.agents)
                .map(|a| {
                    let pose = |t: usize| road_sim::window_pose(w, a, t);
                    let last = pose(reference).expect("agents are present at the reference step");
                    let previous = pose(reference - 1).unwrap_or(last);
                    constant_velocity(previous, last, steps)
                        .into_iter()
                        .map(|p| [p.x_m, p.y_m])
                        .collect::<Vec<_>>()
                })
                .collect::<Vec<_>>(),
        ];
        accumulate(
            &mut cv,
            window,
            &scene_metrics(
                &samples,
                &truth_of(w, reference, steps),
                args.miss_threshold_m,
            ),
        );
    }
    cv.secs = started.elapsed().as_secs_f64();
    cv.samples = windows.len();
    results.push(cv);

    let ctx = match args.engine {
        Engine::Gpu => Some(road_gpu::GpuContext::new(
            &crate::commands::gpu_options::context_options()?,
        )?),
        Engine::Cpu | Engine::Candle => None,
    };
    for dir in &args.checkpoints {
        let loaded = road_model::checkpoint::load(dir, &candle_core::Device::Cpu)?;
        let run =
            &crate::commands::engine::with_planner(&loaded.meta.run, args.planner.as_deref())?;
        let n = run.planner.obs_slots;
        let gpu_model = match &ctx {
            Some(ctx) => Some(road_gpu::engine::GpuDenoiser::from_checkpoint(ctx, dir)?),
            None => None,
        };
        let mut totals = Totals {
            model: run.name.clone(),
            ..Totals::default()
        };
        let mut nfe_total = 0u64;
        let started = Instant::now();
        let bar = indicatif::ProgressBar::new(windows.len() as u64);
        bar.set_message(run.name.clone());
        if args.figure_scenes > 0 {
            std::fs::create_dir_all(&args.figures)
                .with_context(|| format!("cannot create {}", args.figures.display()))?;
        }
        let batch_scenes = args.batch_scenes.max(1);
        for (c, chunk) in windows.chunks(batch_scenes).enumerate() {
            let batch: Vec<RolloutScene> = chunk
                .iter()
                .flat_map(|w| {
                    let history = SceneInput::from_window(w, reference + 1 - n, n, &run.model);
                    std::iter::repeat_n(RolloutScene { history }, sample_count)
                })
                .collect();
            let mut cpu_engine;
            let mut fast_engine;
            let mut gpu_engine;
            let engine: &mut dyn StepEngine = match (&ctx, &gpu_model) {
                (Some(ctx), Some(model)) => {
                    gpu_engine = road_gpu::step_engine::GpuStepEngine::new(ctx, model);
                    &mut gpu_engine
                }
                _ if args.engine == Engine::Candle => {
                    cpu_engine = CpuEngine::new(&loaded.model);
                    &mut cpu_engine
                }
                _ => {
                    fast_engine = FastCpuEngine::new(&loaded.model)?;
                    &mut fast_engine
                }
            };
            // Each sample's noise stream is named by its scene in the dataset and its index, so
            // a scene samples the same futures whatever the chunking (`--batch-scenes`).
            let seeds: Vec<u64> = (0..chunk.len())
                .flat_map(|k| {
                    let scene_stream = stream_seed(args.seed, scenes[c * batch_scenes + k] as u64);
                    (0..sample_count).map(move |s| stream_seed(scene_stream, s as u64))
                })
                .collect();
            let out = rollout_seeded(engine, &run.planner, &batch, steps, &seeds)?;
            nfe_total += out.nfe;
            for (k, w) in chunk.iter().enumerate() {
                let samples: Vec<Vec<Vec<[f64; 2]>>> = (0..sample_count)
                    .map(|s| {
                        let states = &out.states[k * sample_count + s];
                        (0..w.agents)
                            .map(|a| {
                                (0..steps)
                                    .map(|t| {
                                        let i = 3 * (a * steps + t);
                                        w.frame.to_metres([states[i], states[i + 1]])
                                    })
                                    .collect()
                            })
                            .collect()
                    })
                    .collect();
                let index = c * batch_scenes + k;
                accumulate(
                    &mut totals,
                    scenes[index],
                    &scene_metrics(
                        &samples,
                        &truth_of(w, reference, steps),
                        args.miss_threshold_m,
                    ),
                );
                if index < args.figure_scenes {
                    draw_forecast(&args.figures, &run.name, index, w, &samples, reference)?;
                }
            }
            bar.inc(chunk.len() as u64);
            progress(&bar, &run.name, windows.len(), started);
        }
        bar.finish_and_clear();
        totals.secs = started.elapsed().as_secs_f64();
        totals.samples = windows.len() * sample_count;
        let chunks = windows.len().div_ceil(args.batch_scenes.max(1)) as f64;
        totals.nfe_per_step = nfe_total as f64 / chunks / steps as f64;
        results.push(totals);
    }

    out!(
        "forecasting, INTERACTION validation: {} scenes, {} joint samples, {steps} steps after 10 observed; engine {:?}",
        windows.len(),
        sample_count,
        args.engine
    );
    out!(
        "| model | minSceneADE (m) [95 % CI] | minSceneFDE (m) [95 % CI] | miss rate [95 % CI] | time per sample (s) | NFE per simulated step |"
    );
    out!("|---|---:|---:|---:|---:|---:|");
    for r in &mut results {
        r.estimate();
        let show = |e: Option<Estimate>| e.map_or_else(String::new, |e| format!("{e:.3}"));
        out!(
            "| {} | {} | {} | {} | {:.3} | {:.1} |",
            r.model,
            show(r.min_scene_ade_m),
            show(r.min_scene_fde_m),
            show(r.miss_rate),
            r.secs / r.samples.max(1) as f64,
            r.nfe_per_step
        );
    }
    out!("(intervals: 95 % percentile bootstrap over scenes, {BOOTSTRAP_RESAMPLES} resamples)");
    if let Some(path) = &args.json {
        let json = serde_json::json!({ "suite": "forecasting", "scenes": windows.len(), "eligible_scenes": eligible, "samples": sample_count, "results": results });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(ExitCode::SUCCESS)
}

/// Paper style: map, 1 s history blue, logged future grey, every sample's prediction orange.
fn draw_forecast(
    dir: &std::path::Path,
    model: &str,
    index: usize,
    w: &SceneWindow,
    samples: &[Vec<Vec<[f64; 2]>>],
    reference: usize,
) -> Result<()> {
    use crate::plot::{
        HISTORY, LOGGED, PREDICTED, Stroke, scene_png, window_map_strokes, window_path_strokes,
        window_point_m,
    };
    let mut strokes = window_map_strokes(w);
    strokes.extend(window_path_strokes(w, reference..w.steps, LOGGED, 2));
    for sample in samples {
        for (a, path) in sample.iter().enumerate() {
            strokes.push(Stroke {
                points: w
                    .state(a, reference)
                    .map(|s| window_point_m(w, s))
                    .into_iter()
                    .chain(path.iter().map(|p| (p[0], p[1])))
                    .collect(),
                color: PREDICTED,
                width: 1,
            });
        }
    }
    strokes.extend(window_path_strokes(w, 0..reference + 1, HISTORY, 3));
    let file = format!(
        "forecasting-{}-{index:02}.png",
        model.replace(|c: char| !c.is_ascii_alphanumeric(), "-")
    );
    scene_png(
        &dir.join(file),
        &strokes,
        700,
        (w.frame.origin_m[0], w.frame.origin_m[1]),
        45.0,
    )
}

fn accumulate(t: &mut Totals, window: usize, m: &road_sim::metrics::SceneMetrics) {
    if m.agents == 0 {
        return;
    }
    t.scenes += 1;
    t.ade_sum += m.min_scene_ade_m;
    t.fde_sum += m.min_scene_fde_m;
    t.missed += m.missed_agents;
    t.agents += m.agents;
    t.per_scene.push(SceneRow {
        window,
        metrics: *m,
    });
}
