//! `road sample`: sample futures of one validation scene with a checkpoint on the CPU and draw
//! them over the map with the observed history and the logged future.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use rand::SeedableRng;
use road_cpu::rollout;
use road_data::{Dataset, Split, WindowConfig};
use road_model::batch::SceneInput;
use road_model::checkpoint;
use road_rollout::{RolloutScene, rollout_with};

use crate::commands::load_cache;
use crate::plot::{HISTORY, LOGGED, PREDICTED, Stroke, scene_png, window_map_strokes};

#[derive(Debug, Args)]
pub struct SampleArgs {
    /// Checkpoint folder (config.toml + weights.safetensors), e.g. models/road20.
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// `val:<index>` (a validation window) or `val:<LOCATION>/<file>:<start frame>`, e.g.
    /// `val:DR_USA_Roundabout_FT/vehicle_tracks_003.csv.gz:101`.
    #[arg(long, default_value = "val:0")]
    pub scene: String,
    /// Joint samples to draw.
    #[arg(long, default_value_t = 6)]
    pub samples: usize,
    /// Simulated steps (default: the rest of the window after the observations).
    #[arg(long)]
    pub steps: Option<usize>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `cpu` (the candle reference) or `gpu` (the WGSL kernels on the adapter wgpu picks;
    /// lavapipe when there is no GPU). The same seed gives the same samples on both.
    #[arg(long, value_enum, default_value_t = Engine::Cpu)]
    pub engine: Engine,
    #[arg(long, default_value = "sample.png")]
    pub out: PathBuf,
    /// Folder of the dataset caches (`road data build`).
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Engine {
    /// The fast CPU engine (every core).
    Cpu,
    /// The candle reference.
    Candle,
    /// The WGSL kernels (lavapipe without a GPU).
    Gpu,
}

fn find_scene(ds: &Dataset, spec: &str) -> Result<usize> {
    let Some(rest) = spec.strip_prefix("val:") else {
        bail!("scene `{spec}` must start with `val:`");
    };
    if let Ok(index) = rest.parse::<usize>() {
        anyhow::ensure!(
            index < ds.len(),
            "scene `{spec}`: the validation set has {} windows",
            ds.len()
        );
        return Ok(index);
    }
    let (file, frame) = rest
        .rsplit_once(':')
        .with_context(|| format!("scene `{spec}`: expected val:<LOCATION>/<file>:<frame>"))?;
    let frame: u32 = frame
        .parse()
        .with_context(|| format!("scene `{spec}`: bad frame `{frame}`"))?;
    ds.windows
        .iter()
        .position(|w| {
            let r = &ds.recordings[w.recording as usize];
            format!("{}/{}", r.location, r.file) == file && w.start_frame == frame
        })
        .with_context(|| {
            format!("scene `{spec}`: no validation window starts at frame {frame} of {file}")
        })
}

pub fn run(args: SampleArgs) -> Result<ExitCode> {
    let loaded = checkpoint::load(&args.checkpoint, &candle_core::Device::Cpu)?;
    let run = &loaded.meta.run;
    let window_config = WindowConfig::default();
    let ds = load_cache(&args.cache, Split::Validation)?;
    let index = find_scene(&ds, &args.scene)?;
    let window = ds.window(index)?;
    let n = run.planner.obs_slots;
    let reference = window_config.reference_step;
    let start = reference + 1 - n;
    let steps = args.steps.unwrap_or(window.steps - reference - 1);
    let history = SceneInput::from_window(&window, start, n, &run.model);
    let scenes = vec![RolloutScene { history }; args.samples.max(1)];
    let mut rng = rand::rngs::StdRng::seed_from_u64(args.seed);
    let started = Instant::now();
    let out = match args.engine {
        Engine::Candle => rollout(&loaded.model, &run.planner, &scenes, steps, &mut rng)?,
        Engine::Cpu => {
            let mut engine = road_cpu::FastCpuEngine::new(&loaded.model)?;
            rollout_with(&mut engine, &run.planner, &scenes, steps, &mut rng)?
        }
        Engine::Gpu => {
            let ctx = road_gpu::GpuContext::new(&crate::commands::gpu_options::context_options()?)?;
            let model = road_gpu::engine::GpuDenoiser::from_checkpoint(&ctx, &args.checkpoint)?;
            let mut engine = road_gpu::step_engine::GpuStepEngine::new(&ctx, &model);
            rollout_with(&mut engine, &run.planner, &scenes, steps, &mut rng)?
        }
    };
    let secs = started.elapsed().as_secs_f64();

    let to_m = |x: f32, y: f32| {
        let p = window.frame.to_metres([x, y]);
        (p[0], p[1])
    };
    let mut strokes = window_map_strokes(&window);
    for a in 0..window.agents {
        let logged: Vec<(f64, f64)> = (reference..window.steps)
            .filter_map(|t| window.state(a, t))
            .map(|s| to_m(s[0], s[1]))
            .collect();
        strokes.push(Stroke {
            points: logged,
            color: LOGGED,
            width: 2,
        });
    }
    for sample in &out.states {
        for a in 0..window.agents {
            let mut pts = vec![];
            if let Some(s) = window.state(a, reference) {
                pts.push(to_m(s[0], s[1]));
            }
            pts.extend(
                (0..steps)
                    .map(|t| to_m(sample[3 * (a * steps + t)], sample[3 * (a * steps + t) + 1])),
            );
            strokes.push(Stroke {
                points: pts,
                color: PREDICTED,
                width: 1,
            });
        }
    }
    for a in 0..window.agents {
        let hist: Vec<(f64, f64)> = (start..=reference)
            .filter_map(|t| window.state(a, t))
            .map(|s| to_m(s[0], s[1]))
            .collect();
        strokes.push(Stroke {
            points: hist,
            color: HISTORY,
            width: 3,
        });
    }
    scene_png(
        &args.out,
        &strokes,
        900,
        (window.frame.origin_m[0], window.frame.origin_m[1]),
        50.0,
    )?;
    out!(
        "{} {} frame {}: {} agents, {} samples × {steps} steps with {} on {:?} ({} NFE per sample) in {secs:.2} s → {}",
        window.location,
        window.file,
        window.start_frame,
        window.agents,
        scenes.len(),
        run.name,
        args.engine,
        out.nfe,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
