//! `shaders/edm.wgsl`: EDM preconditioning coefficients per window slot.

use bytemuck::{Pod, Zeroable};

use super::Pipeline;
use crate::shaders::Shader;
use crate::{GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    count: u32,
    sigma_data: f32,
    sigma_min: f32,
    _pad: u32,
}

/// The `precondition` kernel, compiled once.
#[derive(Debug)]
pub struct EdmPrecondition(Pipeline);

impl EdmPrecondition {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::Edm, "precondition"))
    }

    /// `[count]` noise levels → `[count]` × (c_skip, c_out, c_in, c_noise).
    pub fn run(
        &self,
        ctx: &GpuContext,
        sigma: &[f32],
        sigma_data: f32,
        sigma_min: f32,
    ) -> Result<Vec<[f32; 4]>> {
        let count = sigma.len() as u32;
        let params = Params {
            count,
            sigma_data,
            sigma_min,
            _pad: 0,
        };
        let out = self.0.run_once(
            ctx,
            bytemuck::bytes_of(&params),
            &[sigma],
            sigma.len() * 4,
            count,
        )?;
        Ok(out
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect())
    }
}
