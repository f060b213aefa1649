//! `shaders/linear.wgsl`: `y = act(x · wᵀ + b)` over the last dimension, in two variants with
//! the same bindings and results: row-wise (no workgroup memory; lavapipe's best, and a GPU's
//! for small layers) and tiled (workgroup-memory tiles; a GPU's best for large layers).
//! [`LinearKernel::choose`] says which one the engine runs for a layer.

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, WORKGROUP};
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

/// Which entry point of `linear.wgsl` computes the layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearKernel {
    /// `linear`: one invocation per 4 outputs of a row, no workgroup memory.
    Rowwise,
    /// `linear_tiled`: one workgroup per 64 rows × 32 outputs, K staged in workgroup memory.
    Tiled,
}

impl LinearKernel {
    /// Rows and outputs of one `linear_tiled` workgroup (the shader's `TILE_ROWS`, `TILE_OUTS`).
    pub const TILE: (u32, u32) = (64, 32);
    /// Fewest tiles for which a hardware GPU runs a layer tiled. On an H100 (2026-11-26,
    /// `docs/benchmarks.md`) tiled lost 1.7× at one scene (3 tiles a layer), tied or lost at 8
    /// scenes (114 tiles for the token layers) and won 1.3–2× from 64 scenes (960 tiles): below
    /// about two tiles per multiprocessor, too few workgroups keep the card busy.
    pub const MIN_TILES_ON_HARDWARE: u32 = 256;

    /// The kernel for one layer: the one named (`ContextOptions::linear_kernel`), else row-wise
    /// on a software adapter, else tiled for layers of at least [`Self::MIN_TILES_ON_HARDWARE`]
    /// tiles.
    pub fn choose(named: Option<Self>, software_adapter: bool, p: &LinearParams) -> Self {
        if let Some(kernel) = named {
            return kernel;
        }
        let (tile_rows, tile_outs) = Self::TILE;
        let tiles = p.rows.div_ceil(tile_rows) * p.out_dim.div_ceil(tile_outs);
        if software_adapter || tiles < Self::MIN_TILES_ON_HARDWARE {
            Self::Rowwise
        } else {
            Self::Tiled
        }
    }

    /// The entry point's name, which is also this variant's name on command lines.
    pub fn entry(self) -> &'static str {
        match self {
            Self::Rowwise => "linear",
            Self::Tiled => "linear_tiled",
        }
    }
}

impl std::str::FromStr for LinearKernel {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "linear" | "rowwise" => Ok(Self::Rowwise),
            "linear_tiled" | "tiled" => Ok(Self::Tiled),
            other => Err(format!(
                "unknown linear kernel {other:?}: expected rowwise (linear) or tiled (linear_tiled)"
            )),
        }
    }
}

impl LinearParams {
    /// Invocations of one dispatch of `kernel`.
    pub fn threads(&self, kernel: LinearKernel) -> u32 {
        match kernel {
            LinearKernel::Rowwise => self.rows * self.out_dim.div_ceil(4),
            LinearKernel::Tiled => {
                let (tile_rows, tile_outs) = LinearKernel::TILE;
                self.rows.div_ceil(tile_rows) * self.out_dim.div_ceil(tile_outs) * WORKGROUP
            }
        }
    }
}

#[derive(Debug)]
pub struct Linear {
    pub pipeline: Pipeline,
    pub kernel: LinearKernel,
}

impl Linear {
    pub fn with_kernel(ctx: &GpuContext, kernel: LinearKernel) -> Self {
        Self {
            pipeline: Pipeline::new(ctx, Shader::Linear, kernel.entry()),
            kernel,
        }
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
        self.pipeline.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[x, w, b],
            (p.rows * p.out_dim) as usize,
            p.threads(self.kernel),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(rows: u32, out_dim: u32) -> LinearParams {
        LinearParams {
            rows,
            in_dim: 96,
            out_dim,
            relu: 0,
        }
    }

    #[test]
    fn large_layers_run_tiled_on_hardware_only() {
        let small = layer(2400, 96); // 8 scenes' tokens: 38 × 3 tiles
        let large = layer(28_800, 96); // their agent maps' points: 450 × 3 tiles
        assert_eq!(
            LinearKernel::choose(None, false, &small),
            LinearKernel::Rowwise
        );
        assert_eq!(
            LinearKernel::choose(None, false, &large),
            LinearKernel::Tiled
        );
        assert_eq!(
            LinearKernel::choose(None, true, &large),
            LinearKernel::Rowwise
        );
        for named in [LinearKernel::Rowwise, LinearKernel::Tiled] {
            for p in [small, large] {
                assert_eq!(LinearKernel::choose(Some(named), false, &p), named);
                assert_eq!(LinearKernel::choose(Some(named), true, &p), named);
            }
        }
    }

    #[test]
    fn names_parse_to_their_kernel() {
        for kernel in [LinearKernel::Rowwise, LinearKernel::Tiled] {
            assert_eq!(kernel.entry().parse::<LinearKernel>(), Ok(kernel));
        }
        assert_eq!("tiled".parse::<LinearKernel>(), Ok(LinearKernel::Tiled));
        let err = "fast".parse::<LinearKernel>().unwrap_err();
        assert!(err.contains("\"fast\""), "{err}");
    }
}
