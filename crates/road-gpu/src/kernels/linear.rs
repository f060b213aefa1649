//! `shaders/linear.wgsl`: `y = act(x · wᵀ + b)` over the last dimension.

use bytemuck::{Pod, Zeroable};

use super::Pipeline;
use crate::shaders::Shader;
use crate::{GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct LinearParams {
    pub rows: u32,
    pub in_dim: u32,
    pub out_dim: u32,
    pub relu: u32,
}

impl LinearParams {
    /// Invocations of one dispatch: one per 4 outputs of a row.
    pub fn threads(&self) -> u32 {
        self.rows * self.out_dim.div_ceil(4)
    }
}

#[derive(Debug)]
pub struct Linear(pub Pipeline);

impl Linear {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::Linear, "linear"))
    }

    /// `x [rows, in]`, `w [out, in]`, `b [out]` → `[rows, out]`.
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: LinearParams,
        x: &[f32],
        w: &[f32],
        b: &[f32],
    ) -> Result<Vec<f32>> {
        self.0.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[x, w, b],
            (p.rows * p.out_dim) as usize,
            p.threads(),
        )
    }
}
