//! Picking and holding the engine a command runs a checkpoint on: the WGSL kernels (`road-gpu`),
//! the fast CPU engine or the candle reference (`road-model`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use road_cpu::{CpuEngine, FastCpuEngine};
use road_gpu::GpuContext;
use road_gpu::engine::GpuDenoiser;
use road_gpu::step_engine::GpuStepEngine;
use road_model::checkpoint::{self, LoadedModel};
use road_model::config::RunConfig;
use road_rollout::StepEngine;

/// What the user asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum EngineChoice {
    /// A hardware GPU when wgpu finds one, else the fast CPU engine.
    Auto,
    /// The fast CPU engine (every core).
    Cpu,
    /// The candle reference (what every engine is tested against).
    Candle,
    /// The WGSL kernels (lavapipe without a GPU).
    Gpu,
}

impl From<crate::commands::sample::Engine> for EngineChoice {
    fn from(e: crate::commands::sample::Engine) -> Self {
        use crate::commands::sample::Engine as E;
        match e {
            E::Cpu => EngineChoice::Cpu,
            E::Candle => EngineChoice::Candle,
            E::Gpu => EngineChoice::Gpu,
        }
    }
}

/// `model` with the adapter's tuning (`road_gpu::tune::attach`: cached, or timed once on a
/// hardware adapter).
fn tuned(ctx: &GpuContext, mut model: GpuDenoiser) -> GpuDenoiser {
    let attached = road_gpu::tune::attach(ctx, &mut model);
    tracing::debug!(?attached, "GPU kernels' tuning");
    model
}

/// A checkpoint loaded for the CPU engines and, when the GPU engine was chosen, uploaded to
/// the adapter.
pub struct Engines {
    pub cpu: LoadedModel,
    pub gpu: Option<(GpuContext, GpuDenoiser)>,
    /// Without a GPU: the candle reference rather than the fast CPU engine.
    pub candle: bool,
}

impl Engines {
    /// A checkpoint folder.
    pub fn load(dir: &Path, choice: EngineChoice) -> Result<Self> {
        let cpu = checkpoint::load(dir, &candle_core::Device::Cpu)?;
        Self::with(cpu, choice, |ctx, _| {
            Ok(GpuDenoiser::from_checkpoint(ctx, dir)?)
        })
    }

    /// A checkpoint folder, or the checkpoint embedded in the binary when `dir` names the
    /// embedded default (`models/road20-wide4`) and holds no checkpoint (a binary run outside
    /// the repository).
    pub fn load_or_embedded(dir: &Path, choice: EngineChoice) -> Result<Self> {
        let embedded = dir.file_name()
            == Some(std::ffi::OsStr::new(road_serve::models::embedded::NAME))
            && !dir.join("config.toml").is_file();
        if embedded {
            tracing::info!(
                "{} not found: running the checkpoint embedded in the binary",
                dir.display()
            );
            Self::load_embedded(choice)
        } else {
            Self::load(dir, choice)
        }
        .with_context(|| {
            format!(
                "cannot load the checkpoint {} (run from the repository root, or pass its folder)",
                dir.display()
            )
        })
    }

    /// The checkpoint embedded in the binary (`road_serve::models::embedded`).
    pub fn load_embedded(choice: EngineChoice) -> Result<Self> {
        use road_serve::models::embedded;
        let origin = PathBuf::from(format!("<embedded {}>", embedded::NAME));
        let cpu = checkpoint::load_from_memory(
            &origin,
            embedded::CONFIG_TOML,
            embedded::WEIGHTS,
            &candle_core::Device::Cpu,
        )?;
        Self::with(cpu, choice, |ctx, cpu| {
            Ok(GpuDenoiser::from_memory(ctx, cpu, embedded::WEIGHTS)?)
        })
    }

    /// `cpu`, and the GPU denoiser `upload` makes when `choice` asks for one.
    fn with(
        cpu: LoadedModel,
        choice: EngineChoice,
        upload: impl Fn(&GpuContext, &LoadedModel) -> Result<GpuDenoiser>,
    ) -> Result<Self> {
        let gpu = match choice {
            EngineChoice::Cpu | EngineChoice::Candle => None,
            EngineChoice::Gpu => {
                let ctx = GpuContext::new(&crate::commands::gpu_options::context_options()?)?;
                let model = tuned(&ctx, upload(&ctx, &cpu)?);
                Some((ctx, model))
            }
            EngineChoice::Auto => {
                match GpuContext::new(&crate::commands::gpu_options::context_options()?) {
                    Ok(ctx) if !ctx.is_software() => {
                        let model = tuned(&ctx, upload(&ctx, &cpu)?);
                        Some((ctx, model))
                    }
                    Ok(ctx) => {
                        tracing::info!(
                            adapter = %ctx.describe(),
                            "software adapter only: running the fast CPU engine instead"
                        );
                        None
                    }
                    Err(e) => {
                        tracing::info!("no GPU adapter ({e}): running the fast CPU engine");
                        None
                    }
                }
            }
        };
        Ok(Self {
            cpu,
            gpu,
            candle: choice == EngineChoice::Candle,
        })
    }

    /// A fresh engine over the loaded model.
    pub fn engine(&self) -> Result<Engine<'_>> {
        Ok(match &self.gpu {
            Some((ctx, model)) => Engine::Gpu(Box::new(GpuStepEngine::new(ctx, model))),
            None if self.candle => Engine::Candle(Box::new(CpuEngine::new(&self.cpu.model))),
            None => Engine::Cpu(Box::new(FastCpuEngine::new(&self.cpu.model)?)),
        })
    }

    pub fn describe(&self) -> String {
        match &self.gpu {
            Some((ctx, _)) => match (ctx.precision(), ctx.cooperative_f16()) {
                (road_gpu::Precision::F32, _) => format!("WGSL on {}", ctx.info.name),
                (road_gpu::Precision::F16, true) => {
                    format!("WGSL f16 (tensor cores) on {}", ctx.info.name)
                }
                (road_gpu::Precision::F16, false) => format!("WGSL f16 on {}", ctx.info.name),
            },
            None if self.candle => "the candle CPU reference".into(),
            None => "the fast CPU engine".into(),
        }
    }
}

/// One engine, any kind.
pub enum Engine<'a> {
    Cpu(Box<FastCpuEngine<'a>>),
    Candle(Box<CpuEngine<'a>>),
    Gpu(Box<GpuStepEngine<'a>>),
}

impl Engine<'_> {
    pub fn as_dyn(&mut self) -> &mut dyn StepEngine {
        match self {
            Engine::Cpu(e) => e.as_mut(),
            Engine::Candle(e) => e.as_mut(),
            Engine::Gpu(e) => e.as_mut(),
        }
    }
}

/// `run` under the planner `name` of the binary's `configs/planners.toml` instead of its own
/// (`None`: as it is), shown as `run [name]`: what `--planner` gives `road eval` and `road demo`,
/// so that planners are compared on one checkpoint without copying it.
pub fn with_planner(run: &RunConfig, name: Option<&str>) -> Result<RunConfig> {
    let mut run = run.clone();
    let Some(name) = name else {
        return Ok(run);
    };
    let planners = road_serve::models::planners()?;
    let planner = planners.get(name).with_context(|| {
        format!(
            "unknown planner `{name}`; configs/planners.toml has: {}",
            planners.keys().cloned().collect::<Vec<_>>().join(", ")
        )
    })?;
    let checkpoint = run.name.clone();
    // The same rule as `road serve`'s scene creation: the model was trained on n observed slots.
    anyhow::ensure!(
        planner.obs_slots == run.planner.obs_slots,
        "planner `{name}` does not fit checkpoint {checkpoint}: it observes {} steps, the \
         checkpoint {}",
        planner.obs_slots,
        run.planner.obs_slots
    );
    run.planner = planner.clone();
    run.name = format!("{checkpoint} [{name}]");
    run.validate().map_err(|reason| {
        anyhow::anyhow!("planner `{name}` does not fit checkpoint {checkpoint}: {reason}")
    })?;
    Ok(run)
}
