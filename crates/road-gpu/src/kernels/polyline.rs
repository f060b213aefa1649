//! `shaders/polyline.wgsl`: the map's polyline encoder in one dispatch: point embedding, the
//! mixing layer, the max over points and `ln_map_out`, its per-point activations kept in
//! workgroup memory (before: 4 dispatches and two `[n, Q, D]` buffers written and read back).
//! Two variants with the same bindings and results: one workgroup per polyline
//! (`encode_polylines`, any shape), and blocks of polylines as a tiled matrix product
//! (`encode_polylines_blocked`, the model's shapes; [`PolylineKernel::choose`]).

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, WORKGROUP};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// The largest hidden size the kernel's workgroup memory holds (the shader's `MAX_HIDDEN`).
pub const MAX_HIDDEN: usize = 512;
/// The largest hidden size the blocked variant holds (`MAX_BLOCKED_HIDDEN`).
pub const MAX_BLOCKED_HIDDEN: u32 = 192;
/// Invocations of one `encode_polylines_blocked` workgroup.
pub const BLOCKED_WORKGROUP: u32 = 192;

/// Which entry point of `polyline.wgsl` encodes the polylines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PolylineKernel {
    /// `encode_polylines`: one workgroup of 64 per polyline, any Q and D ≤ [`MAX_HIDDEN`].
    PerPolyline,
    /// `encode_polylines_blocked`: up to 8 polylines a workgroup of 192, their points the rows
    /// of a tiled matrix product; Q a multiple of 4 up to 128, D ≤ [`MAX_BLOCKED_HIDDEN`].
    Blocked,
}

impl PolylineKernel {
    pub const ALL: [Self; 2] = [Self::PerPolyline, Self::Blocked];

    /// Blocked wherever the shape fits it; it does a polyline's products with 6× fewer loads.
    /// On an H100 (2026-11-26) the per-polyline kernel took half of road20-wide4's step at 512
    /// scenes (its agent maps: 129 k polylines an evaluation).
    pub fn choose(p: &PolylineParams) -> Self {
        if p.blocked_fits() {
            Self::Blocked
        } else {
            Self::PerPolyline
        }
    }

    /// The entry point's name, which is also this variant's name on command lines.
    pub fn entry(self) -> &'static str {
        match self {
            Self::PerPolyline => "encode_polylines",
            Self::Blocked => "encode_polylines_blocked",
        }
    }

    fn workgroup_size(self) -> u32 {
        match self {
            Self::PerPolyline => WORKGROUP,
            Self::Blocked => BLOCKED_WORKGROUP,
        }
    }
}

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

    /// Whether `encode_polylines_blocked` takes this shape: Q a multiple of 4 (an invocation's
    /// four consecutive rows are points of one polyline) up to 128 (a block's rows), D up to
    /// [`MAX_BLOCKED_HIDDEN`] (its pooled features in workgroup memory).
    pub fn blocked_fits(&self) -> bool {
        self.points.is_multiple_of(4)
            && (4..=128).contains(&self.points)
            && self.hidden <= MAX_BLOCKED_HIDDEN
    }

    /// Polylines of one `encode_polylines_blocked` workgroup (the shader's `per_block`).
    pub fn polylines_per_block(&self) -> u32 {
        (128 / self.points.max(1)).clamp(1, 8)
    }

    /// Invocations of one dispatch of `kernel`.
    pub fn threads(&self, kernel: PolylineKernel) -> u32 {
        match kernel {
            PolylineKernel::PerPolyline => self.polylines * WORKGROUP,
            PolylineKernel::Blocked => {
                self.polylines.div_ceil(self.polylines_per_block()) * BLOCKED_WORKGROUP
            }
        }
    }
}

impl std::str::FromStr for PolylineKernel {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "encode_polylines" | "per-polyline" => Ok(Self::PerPolyline),
            "encode_polylines_blocked" | "blocked" => Ok(Self::Blocked),
            other => Err(format!(
                "unknown polyline kernel {other:?}: expected per-polyline (encode_polylines) \
                 or blocked (encode_polylines_blocked)"
            )),
        }
    }
}

/// A `polyline.wgsl` entry point, compiled once.
#[derive(Debug)]
pub struct PolylineEncoder {
    pub pipeline: Pipeline,
    pub kernel: PolylineKernel,
}

impl PolylineEncoder {
    pub fn new(ctx: &GpuContext, kernel: PolylineKernel) -> Self {
        Self {
            pipeline: Pipeline::with_workgroup_size(
                ctx,
                Shader::Polyline,
                kernel.entry(),
                kernel.workgroup_size(),
            ),
            kernel,
        }
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
        if self.kernel == PolylineKernel::Blocked && !p.blocked_fits() {
            return Err(Error::Checkpoint(format!(
                "encode_polylines_blocked takes Q a multiple of 4 up to 128 and D up to \
                 {MAX_BLOCKED_HIDDEN}, not Q = {} and D = {}",
                p.points, p.hidden
            )));
        }
        self.pipeline.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[points, embed, mix_w, mix_b, gamma, beta],
            (p.polylines * p.hidden) as usize,
            p.threads(self.kernel),
        )
    }
}
