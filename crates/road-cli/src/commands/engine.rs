//! Picking and holding the engine a command runs a checkpoint on: the WGSL kernels (`road-gpu`)
//! or the candle reference (`road-model`).

use std::path::Path;

use anyhow::Result;
use road_gpu::engine::{GpuDenoiser, GpuStepEngine};
use road_gpu::{ContextOptions, GpuContext};
use road_model::checkpoint::{self, LoadedModel};
use road_model::sample::{CpuEngine, StepEngine};

/// What the user asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum EngineChoice {
    /// A hardware GPU when wgpu finds one, else the candle reference.
    Auto,
    Cpu,
    Gpu,
}

/// A checkpoint loaded for the candle reference and, when the GPU engine was chosen, uploaded
/// to the adapter.
pub struct Engines {
    pub cpu: LoadedModel,
    pub gpu: Option<(GpuContext, GpuDenoiser)>,
}

impl Engines {
    pub fn load(dir: &Path, choice: EngineChoice) -> Result<Self> {
        let cpu = checkpoint::load(dir, &candle_core::Device::Cpu)?;
        let gpu = match choice {
            EngineChoice::Cpu => None,
            EngineChoice::Gpu => {
                let ctx = GpuContext::new(&ContextOptions::default())?;
                let model = GpuDenoiser::from_checkpoint(&ctx, dir)?;
                Some((ctx, model))
            }
            EngineChoice::Auto => match GpuContext::new(&ContextOptions::default()) {
                Ok(ctx) if !ctx.is_software() => {
                    let model = GpuDenoiser::from_checkpoint(&ctx, dir)?;
                    Some((ctx, model))
                }
                Ok(ctx) => {
                    tracing::info!(
                        adapter = %ctx.describe(),
                        "software adapter only: running the candle reference instead"
                    );
                    None
                }
                Err(e) => {
                    tracing::info!("no GPU adapter ({e}): running the candle reference");
                    None
                }
            },
        };
        Ok(Self { cpu, gpu })
    }

    /// A fresh engine over the loaded model.
    pub fn engine(&self) -> Engine<'_> {
        match &self.gpu {
            Some((ctx, model)) => Engine::Gpu(Box::new(GpuStepEngine::new(ctx, model))),
            None => Engine::Cpu(CpuEngine::new(&self.cpu.model)),
        }
    }

    pub fn describe(&self) -> String {
        match &self.gpu {
            Some((ctx, _)) => format!("WGSL on {}", ctx.info.name),
            None => "the candle CPU reference".into(),
        }
    }
}

/// One engine, either kind.
pub enum Engine<'a> {
    Cpu(CpuEngine<'a>),
    Gpu(Box<GpuStepEngine<'a>>),
}

impl Engine<'_> {
    pub fn as_dyn(&mut self) -> &mut dyn StepEngine {
        match self {
            Engine::Cpu(e) => e,
            Engine::Gpu(e) => e.as_mut(),
        }
    }
}
