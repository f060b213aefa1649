//! `shaders/linear_f16.wgsl` and `shaders/linear_coop.wgsl`: the fused linear layer of
//! `linear.wgsl` (same params, bindings and epilogue) with f16 weights and f16 inputs (each row
//! standardised first under `norm`, then rounded), summed in f32. `linear_coop` runs it on the
//! tensor cores through cooperative matrices; `linear_f16` is the same rounding on any adapter
//! with `SHADER_F16` (lavapipe in CI), and the engine's f16 path where no tensor cores are
//! offered. [`Precision::F16`](crate::Precision) runs a layer this way where [`fits`] holds,
//! on every adapter alike, so that what lavapipe measures of f16's quality is what a card runs.

use super::Pipeline;
use super::linear::LinearParams;
use crate::shaders::Shader;
use crate::{Error, GpuContext, Precision, Result};

/// Which f16 kernel computes a layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearF16Kernel {
    /// `linear_f16`: one invocation per 4 outputs of a row.
    Rowwise,
    /// `linear_coop`: one subgroup of 32 per 32 rows × 96 outputs on cooperative matrices.
    Coop,
}

impl LinearF16Kernel {
    /// Rows and outputs of one `linear_coop` workgroup (`COOP_ROWS`, `COOP_OUTS`).
    pub const COOP_BLOCK: (u32, u32) = (32, 96);
    /// Invocations of one `linear_coop` workgroup: one subgroup.
    pub const COOP_WORKGROUP: u32 = 32;

    pub fn entry(self) -> &'static str {
        match self {
            Self::Rowwise => "linear_f16",
            Self::Coop => "linear_coop",
        }
    }

    fn shader(self) -> Shader {
        match self {
            Self::Rowwise => Shader::LinearF16,
            Self::Coop => Shader::LinearCoop,
        }
    }

    fn workgroup_size(self) -> u32 {
        match self {
            Self::Rowwise => super::WORKGROUP,
            Self::Coop => Self::COOP_WORKGROUP,
        }
    }

    /// The kernel of `ctx`'s f16 layers: on the tensor cores where it has them.
    pub fn for_context(ctx: &GpuContext) -> Self {
        if ctx.cooperative_f16() {
            Self::Coop
        } else {
            Self::Rowwise
        }
    }

    /// Invocations of one dispatch over `p`.
    pub fn threads(self, p: &LinearParams) -> u32 {
        match self {
            Self::Rowwise => p.rows * p.out_dim.div_ceil(4),
            Self::Coop => {
                let (rows, outs) = Self::COOP_BLOCK;
                p.rows.div_ceil(rows) * p.out_dim.div_ceil(outs) * Self::COOP_WORKGROUP
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
        if kernel == LinearF16Kernel::Coop && !ctx.cooperative_f16() {
            return Err(Error::Device(format!(
                "linear_coop: the adapter {} offers no cooperative 16×16×16 f16 matrices with \
                 subgroups of 32 (or they were turned off)",
                ctx.describe()
            )));
        }
        Ok(Self {
            pipeline: Pipeline::with_workgroup_size(
                ctx,
                kernel.shader(),
                kernel.entry(),
                kernel.workgroup_size(),
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
        // 2 row blocks × 3 output blocks, a subgroup each.
        assert_eq!(LinearF16Kernel::Coop.threads(&p), 2 * 3 * 32);
        assert_eq!(LinearF16Kernel::Rowwise.threads(&p), 33 * 72);
    }
}
