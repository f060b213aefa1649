//! `road gpu …`: the adapter wgpu picks here, and a kernel self-test against the CPU reference.

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Subcommand;
use road_gpu::kernels::edm::EdmPrecondition;
use road_gpu::{ContextOptions, GpuContext, Tolerance};
use road_sched::EdmSchedule;

#[derive(Debug, Subcommand)]
pub enum GpuCommand {
    /// Print the adapter that would run the kernels and its main limits
    /// (honours WGPU_BACKEND and WGPU_ADAPTER_NAME).
    Info,
    /// Run every kernel on the adapter and compare with its CPU reference.
    Selftest,
}

pub fn run(cmd: GpuCommand) -> Result<ExitCode> {
    let ctx = GpuContext::new(&ContextOptions::default()).context("cannot open a GPU adapter")?;
    match cmd {
        GpuCommand::Info => {
            let l = ctx.device.limits();
            out!("adapter: {}", ctx.describe());
            out!("software adapter: {}", ctx.is_software());
            out!(
                "max storage buffer binding: {} MiB",
                l.max_storage_buffer_binding_size / (1024 * 1024)
            );
            out!(
                "max storage buffers per stage: {}",
                l.max_storage_buffers_per_shader_stage
            );
            out!(
                "max invocations per workgroup: {}",
                l.max_compute_invocations_per_workgroup
            );
            out!(
                "max workgroup storage: {} KiB",
                l.max_compute_workgroup_storage_size / 1024
            );
            out!("features: {:?}", ctx.adapter.features());
            Ok(ExitCode::SUCCESS)
        }
        GpuCommand::Selftest => {
            out!("adapter: {}", ctx.describe());
            let edm = EdmSchedule::default();
            let sigma: Vec<f32> = (0..=1000)
                .map(|i| edm.sigma(f64::from(i) / 1000.0) as f32)
                .collect();
            let got = EdmPrecondition::new(&ctx).run(
                &ctx,
                &sigma,
                edm.sigma_data as f32,
                edm.sigma_min as f32,
            )?;
            let expected: Vec<f32> = sigma
                .iter()
                .flat_map(|&s| {
                    let p = edm.preconditioning(f64::from(s));
                    [
                        p.c_skip as f32,
                        p.c_out as f32,
                        p.c_in as f32,
                        (f64::from(s).max(edm.sigma_min).ln() / 4.0) as f32,
                    ]
                })
                .collect();
            let actual: Vec<f32> = got.iter().flatten().copied().collect();
            match Tolerance::F32.check(&actual, &expected) {
                Ok(()) => {
                    out!(
                        "edm.precondition: ok ({} slots, rel {} abs {})",
                        sigma.len(),
                        Tolerance::F32.rel,
                        Tolerance::F32.abs
                    );
                    Ok(ExitCode::SUCCESS)
                }
                Err(m) => {
                    out!("edm.precondition: FAILED: {m}");
                    Ok(ExitCode::FAILURE)
                }
            }
        }
    }
}
