//! Where a step's device time goes, by kernel: each dispatch is submitted alone and waited for,
//! so its wall time is its device time plus one submission's round trip (which
//! [`StepProfile::round_trip_secs`] measures with an empty submission, so that a reader can
//! tell kernels that take microseconds from the overhead). The pipelined step is faster than the
//! sum: read the shares, not the total.

use std::time::Instant;

use crate::kernels::Dispatch;
use crate::{GpuContext, Result};

/// One entry point's share of a step.
#[derive(Debug, Clone)]
pub struct KernelTime {
    pub kernel: &'static str,
    /// Dispatches of it per step.
    pub dispatches: usize,
    /// Wall seconds per step, the round trips included.
    pub secs_per_step: f64,
}

#[derive(Debug, Clone)]
pub struct StepProfile {
    /// Kernels by time, the longest first.
    pub kernels: Vec<KernelTime>,
    /// One empty submission's wait, which every dispatch's time includes once.
    pub round_trip_secs: f64,
}

/// Runs `dispatches` in order `repeats` times, each alone in its submission.
pub fn profile(ctx: &GpuContext, dispatches: &[Dispatch], repeats: usize) -> Result<StepProfile> {
    let repeats = repeats.max(1);
    let mut kernels: Vec<KernelTime> = Vec::new();
    let submit = |d: Option<&Dispatch>| -> Result<f64> {
        let started = Instant::now();
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("profile"),
            });
        if let Some(d) = d {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(d.label()),
                timestamp_writes: None,
            });
            d.record(&mut pass);
        }
        ctx.queue.submit([encoder.finish()]);
        ctx.wait()?;
        Ok(started.elapsed().as_secs_f64())
    };
    // Warm-up: the first submissions of a pipeline may compile it.
    for d in dispatches {
        submit(Some(d))?;
    }
    let mut round_trip = 0.0;
    for _ in 0..repeats {
        round_trip += submit(None)?;
        for d in dispatches {
            let secs = submit(Some(d))?;
            match kernels.iter_mut().find(|k| k.kernel == d.label()) {
                Some(k) => k.secs_per_step += secs,
                None => kernels.push(KernelTime {
                    kernel: d.label(),
                    dispatches: 0,
                    secs_per_step: secs,
                }),
            }
        }
    }
    for k in &mut kernels {
        k.dispatches = dispatches.iter().filter(|d| d.label() == k.kernel).count();
        k.secs_per_step /= repeats as f64;
    }
    kernels.sort_by(|a, b| b.secs_per_step.total_cmp(&a.secs_per_step));
    Ok(StepProfile {
        kernels,
        round_trip_secs: round_trip / repeats as f64,
    })
}
