//! `shaders/linear_f16.wgsl` and `shaders/linear_coop.wgsl`: the fused linear layer of
//! `linear.wgsl` (same params, bindings and epilogue) with f16 weights and f16 inputs (each row
//! standardised first under `norm`, then rounded), summed in f32. `linear_coop` (16 × 16 tiles)
//! and `linear_coop8` (8 × 8) run it on the tensor cores through cooperative matrices;
//! `linear_f16` is the same rounding on any adapter with `SHADER_F16` (lavapipe in CI), and the
//! engine's f16 path where no cooperative matrices are offered.
//! [`Precision::F16`](crate::Precision) runs a layer this way where [`fits`] holds, on every
//! adapter alike, so that what lavapipe measures of f16's quality is what a card runs.

use super::Pipeline;
use super::linear::LinearParams;
use crate::shaders::Shader;
use crate::{CooperativeF16, Error, GpuContext, Precision, Result};

/// Which f16 kernel computes a layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearF16Kernel {
    /// `linear_f16`: one invocation per 4 outputs of a row.
    Rowwise,
    /// `linear_coop` (16 × 16 tiles: 32 rows × 96 outputs a workgroup) or `linear_coop8` (8 × 8:
    /// 16 × 48), a workgroup of one subgroup, on cooperative matrices.
    Coop(CooperativeF16),
}

impl LinearF16Kernel {
    pub fn entry(self) -> &'static str {
        match self {
            Self::Rowwise => "linear_f16",
            Self::Coop(c) if c.tile == 16 => "linear_coop",
            Self::Coop(_) => "linear_coop8",
        }
    }

    fn shader(self) -> Shader {
        match self {
            Self::Rowwise => Shader::LinearF16,
            Self::Coop(_) => Shader::LinearCoop,
        }
    }

    fn workgroup_size(self) -> u32 {
        match self {
            Self::Rowwise => super::WORKGROUP,
            Self::Coop(c) => c.lanes,
        }
    }

    /// Rows and outputs of one cooperative workgroup: 2 × 6 tiles.
    pub fn coop_block(c: CooperativeF16) -> (u32, u32) {
        (2 * c.tile, 6 * c.tile)
    }

    /// The kernel of `ctx`'s f16 layers: on the tensor cores where it has them.
    pub fn for_context(ctx: &GpuContext) -> Self {
        ctx.cooperative().map_or(Self::Rowwise, Self::Coop)
    }

    /// Invocations of one dispatch over `p`.
    pub fn threads(self, p: &LinearParams) -> u32 {
        match self {
            Self::Rowwise => p.rows * p.out_dim.div_ceil(4),
            Self::Coop(c) => {
                let (rows, outs) = Self::coop_block(c);
                p.rows.div_ceil(rows) * p.out_dim.div_ceil(outs) * c.lanes
            }
        }
    }
}

/// Whether a layer runs in f16 under [`Precision::F16`]: inputs and outputs multiples of 16
/// (the cooperative tiles'). The embeddings (3 inputs) and the head (3 outputs) stay f32.
pub fn fits(p: &LinearParams) -> bool {
    p.in_dim > 0 && p.out_dim > 0 && p.in_dim.is_multiple_of(16) && p.out_dim.is_multiple_of(16)
}

/// `values` as f16 (round to nearest even), little-endian, zero-padded to whole 4 bytes (a
/// storage binding's size is a multiple of 4).
pub fn to_f16_bytes(values: &[f32]) -> Vec<u8> {
    let mut bytes: Vec<u8> = values
        .iter()
        .flat_map(|&v| half::f16::from_f32(v).to_le_bytes())
        .collect();
    bytes.resize(bytes.len().div_ceil(4) * 4, 0);
    bytes
}

/// A compiled f16 linear kernel.
#[derive(Debug)]
pub struct LinearF16 {
    pub pipeline: Pipeline,
    pub kernel: LinearF16Kernel,
}

impl LinearF16 {
    /// `kernel` on `ctx`, which must have been opened with [`Precision::F16`] (and, for
    /// [`LinearF16Kernel::Coop`], on an adapter with cooperative f16 matrices).
    pub fn new(ctx: &GpuContext, kernel: LinearF16Kernel) -> Result<Self> {
        if ctx.precision() != Precision::F16 {
            return Err(Error::Device(format!(
                "{}: the context was opened for f32 (ContextOptions::precision)",
                kernel.entry()
            )));
        }
        let opened = match kernel {
            LinearF16Kernel::Rowwise => None,
            LinearF16Kernel::Coop(c) => Some(c),
        };
        if let Some(c) = opened.filter(|&c| ctx.cooperative() != Some(c)) {
            return Err(Error::Device(format!(
                "{}: the device was not opened with {c:?} (adapter {})",
                kernel.entry(),
                ctx.describe()
            )));
        }
        let lanes = f64::from(kernel.workgroup_size());
        let constants: &[(&str, f64)] = match kernel {
            LinearF16Kernel::Rowwise => &[],
            LinearF16Kernel::Coop(_) => &[("COOP_LANES", lanes)],
        };
        Ok(Self {
            pipeline: Pipeline::with_constants(
                ctx,
                kernel.shader(),
                kernel.entry(),
                kernel.workgroup_size(),
                constants,
            ),
            kernel,
        })
    }

    /// As [`super::linear::Linear::run_fused`], `w` given in f32 and stored as f16.
    pub fn run_fused(
        &self,
        ctx: &GpuContext,
        p: LinearParams,
        x: &[f32],
        w: &[f32],
        b: &[f32],
        y: &[f32],
    ) -> Result<Vec<f32>> {
        let w = to_f16_bytes(w);
        let threads = self.kernel.threads(&p);
        super::linear::run_once(ctx, &self.pipeline, p, threads, (x, &w, b), y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_layers_of_whole_tiles_run_in_f16() {
        assert!(fits(&LinearParams::new(10, 96, 288)));
        assert!(fits(&LinearParams::new(1, 384, 96)));
        assert!(!fits(&LinearParams::new(10, 3, 96)));
        assert!(!fits(&LinearParams::new(10, 96, 3)));
        assert!(!fits(&LinearParams::new(10, 40, 96)));
    }

    #[test]
    fn f16_bytes_round_to_nearest_and_pad_to_words() {
        let bytes = to_f16_bytes(&[1.0, -2.0, 65504.0]);
        assert_eq!(bytes.len(), 8);
        assert_eq!(&bytes[..2], &0x3c00u16.to_le_bytes());
        assert_eq!(&bytes[2..4], &0xc000u16.to_le_bytes());
        assert_eq!(&bytes[4..6], &0x7bffu16.to_le_bytes());
        assert_eq!(&bytes[6..], &[0, 0]);
        // 1 + 2⁻¹¹ is halfway between 1 and 1 + 2⁻¹⁰: to the even one, 1.
        assert_eq!(
            &to_f16_bytes(&[1.0 + 2f32.powi(-11)])[..2],
            &0x3c00u16.to_le_bytes()
        );
    }

    #[test]
    fn coop_threads_cover_whole_blocks() {
        let p = LinearParams::new(33, 96, 288);
        // 16 × 16 tiles: 2 row blocks of 32 × 3 output blocks of 96, a subgroup of 32 each.
        let nvidia = LinearF16Kernel::Coop(CooperativeF16 {
            tile: 16,
            lanes: 32,
        });
        assert_eq!(nvidia.threads(&p), 2 * 3 * 32);
        assert_eq!(nvidia.entry(), "linear_coop");
        // 8 × 8 tiles: 3 row blocks of 16 × 6 output blocks of 48, a subgroup of 8 each.
        let lavapipe = LinearF16Kernel::Coop(CooperativeF16 { tile: 8, lanes: 8 });
        assert_eq!(lavapipe.threads(&p), 3 * 6 * 8);
        assert_eq!(lavapipe.entry(), "linear_coop8");
        assert_eq!(LinearF16Kernel::Rowwise.threads(&p), 33 * 72);
    }
}
