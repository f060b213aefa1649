//! `shaders/polyline.wgsl`: the map's polyline encoder in one dispatch, one workgroup per
//! polyline: point embedding, the mixing layer, the max over points and `ln_map_out`, its
//! per-point activations kept in workgroup memory (before: 4 dispatches and two `[n, Q, D]`
//! buffers written and read back).

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, WORKGROUP};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// The largest hidden size the kernel's workgroup memory holds (the shader's `MAX_HIDDEN`).
pub const MAX_HIDDEN: usize = 512;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct PolylineParams {
    pub polylines: u32,
    /// Points per polyline, Q.
    pub points: u32,
    /// D.
    pub hidden: u32,
    /// `ln_map_out`'s.
    pub eps: f32,
}

impl PolylineParams {
    /// A clear error where the shader's workgroup memory is too small.
    pub fn check(&self) -> Result<()> {
        if self.hidden as usize > MAX_HIDDEN {
            return Err(Error::Checkpoint(format!(
                "the polyline encoder holds at most {MAX_HIDDEN} hidden features, the model has {}",
                self.hidden
            )));
        }
        Ok(())
    }

    /// Invocations of one dispatch: a workgroup per polyline.
    pub fn threads(&self) -> u32 {
        self.polylines * WORKGROUP
    }
}

/// The `encode_polylines` kernel, compiled once.
#[derive(Debug)]
pub struct PolylineEncoder(pub Pipeline);

impl PolylineEncoder {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::Polyline, "encode_polylines"))
    }

    /// `points [n, Q, 2]`, `embed` (W_point `[D, 2]` | b_point `[D]` | point embedding
    /// `[Q, D]`), the mixing layer `mix_w [D, D]`, `mix_b [D]`, the layer norm's γ, β `[D]` →
    /// tokens `[n, D]`.
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: PolylineParams,
        points: &[f32],
        embed: &[f32],
        mix_w: &[f32],
        mix_b: &[f32],
        gamma: &[f32],
        beta: &[f32],
    ) -> Result<Vec<f32>> {
        p.check()?;
        self.0.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[points, embed, mix_w, mix_b, gamma, beta],
            (p.polylines * p.hidden) as usize,
            p.threads(),
        )
    }
}
