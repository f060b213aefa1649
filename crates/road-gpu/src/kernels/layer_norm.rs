//! `shaders/layer_norm.wgsl`: layer norm over the last dimension.

use bytemuck::{Pod, Zeroable};

use super::Pipeline;
use crate::shaders::Shader;
use crate::{GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct LayerNormParams {
    pub rows: u32,
    pub dim: u32,
    pub eps: f32,
    pub _pad: u32,
}

#[derive(Debug)]
pub struct LayerNorm(pub Pipeline);

impl LayerNorm {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::LayerNorm, "layer_norm"))
    }

    /// `x [rows, dim]`, `gamma [dim]`, `beta [dim]` → `[rows, dim]`.
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: LayerNormParams,
        x: &[f32],
        gamma: &[f32],
        beta: &[f32],
    ) -> Result<Vec<f32>> {
        self.0.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[x, gamma, beta],
            (p.rows * p.dim) as usize,
            p.rows,
        )
    }
}
