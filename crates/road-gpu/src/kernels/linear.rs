//! `shaders/linear.wgsl`: `y (+)= act(n(x) · wᵀ + b)` over the last dimension, in three variants
//! with the same bindings and results: row-wise (no workgroup memory; lavapipe's best, and a
//! GPU's for small layers), tiled (64 × 32 workgroup-memory tiles, the first GPU variant) and
//! blocked (128 × 96 blocks of 8 × 8 per invocation, the layer norm's statistics gathered
//! while staging; a GPU's best for large layers).
//! [`LinearKernel::choose`] says which one the engine runs for a layer. Fused into each: the
//! layer norm `n` of the rows (prologue; its γ, β folded into the weights by
//! [`fold_layer_norm`]), the residual add (epilogue) and outputs split into parts (the q/k/v
//! projections as one layer), each saving a dispatch.

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, WORKGROUP, read_back, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct LinearParams {
    pub rows: u32,
    pub in_dim: u32,
    pub out_dim: u32,
    /// 1: ReLU after the bias.
    pub relu: u32,
    /// 1: add into `y` (the residual stream) instead of overwriting it.
    pub residual: u32,
    /// 1: standardise each row of `x` first, `(x − mean) / √(var + eps)`: a layer norm with
    /// its γ, β folded into the weights ([`fold_layer_norm`]).
    pub norm: u32,
    pub eps: f32,
    /// Outputs per part: output `o` goes to part `o / part` of `y`, a `[rows, part]` tensor
    /// `part_stride` floats after the previous one. `out_dim` for an unsplit layer.
    pub part: u32,
    pub part_stride: u32,
    pub _pad: [u32; 3],
}

/// Which entry point of `linear.wgsl` computes the layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearKernel {
    /// `linear`: one invocation per 4 outputs of a row, no workgroup memory.
    Rowwise,
    /// `linear_tiled`: one workgroup per 64 rows × 32 outputs, K staged in workgroup memory.
    Tiled,
    /// `linear_blocked`: one workgroup of 192 per 128 rows × 96 outputs, 8 × 8 per invocation.
    Blocked,
}

impl LinearKernel {
    /// Every variant, in the order command lines list them.
    pub const ALL: [Self; 3] = [Self::Rowwise, Self::Tiled, Self::Blocked];
    /// Rows and outputs of one `linear_tiled` workgroup (the shader's `TILE_ROWS`, `TILE_OUTS`).
    pub const TILE: (u32, u32) = (64, 32);
    /// Rows and outputs of one `linear_blocked` workgroup (`BLOCK_ROWS`, `BLOCK_OUTS`).
    pub const BLOCK: (u32, u32) = (128, 96);
    /// Invocations of one `linear_blocked` workgroup.
    pub const BLOCK_WORKGROUP: u32 = 192;
    /// Fewest blocks for which a hardware GPU runs a layer blocked. On an H100 (2026-11-26,
    /// `docs/benchmarks.md`) blocked won from 8 scenes (19 blocks for the token layers: 1.4×
    /// over row-wise and tiled) and lost 1.5× at one scene (a block a layer).
    pub const MIN_BLOCKS_ON_HARDWARE: u32 = 8;
    /// Fewest blocks for which a software adapter runs a layer blocked. On lavapipe (2 cores,
    /// 2026-11-26) blocked beat row-wise by 24 % (road20-wide4) and 25 % (road20) a Heun step at
    /// 8 scenes, and tied at one scene.
    pub const MIN_BLOCKS_ON_SOFTWARE: u32 = 4;

    /// The kernel for one layer: the one named (`ContextOptions::linear_kernel`), else
    /// blocked for layers of at least [`Self::MIN_BLOCKS_ON_HARDWARE`] blocks on hardware
    /// ([`Self::MIN_BLOCKS_ON_SOFTWARE`] on a software adapter), row-wise below. Tiled is
    /// never the choice: blocked beat it at every batch on the H100.
    pub fn choose(named: Option<Self>, software_adapter: bool, p: &LinearParams) -> Self {
        if let Some(kernel) = named {
            return kernel;
        }
        let (block_rows, block_outs) = Self::BLOCK;
        let blocks = p.rows.div_ceil(block_rows) * p.out_dim.div_ceil(block_outs);
        let least = if software_adapter {
            Self::MIN_BLOCKS_ON_SOFTWARE
        } else {
            Self::MIN_BLOCKS_ON_HARDWARE
        };
        if blocks >= least {
            Self::Blocked
        } else {
            Self::Rowwise
        }
    }

    /// The entry point's name, which is also this variant's name on command lines.
    pub fn entry(self) -> &'static str {
        match self {
            Self::Rowwise => "linear",
            Self::Tiled => "linear_tiled",
            Self::Blocked => "linear_blocked",
        }
    }

    /// The entry point's `@workgroup_size`.
    pub fn workgroup_size(self) -> u32 {
        match self {
            Self::Rowwise | Self::Tiled => WORKGROUP,
            Self::Blocked => Self::BLOCK_WORKGROUP,
        }
    }
}

impl std::str::FromStr for LinearKernel {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "linear" | "rowwise" => Ok(Self::Rowwise),
            "linear_tiled" | "tiled" => Ok(Self::Tiled),
            "linear_blocked" | "blocked" => Ok(Self::Blocked),
            other => Err(format!(
                "unknown linear kernel {other:?}: expected rowwise (linear), tiled \
                 (linear_tiled) or blocked (linear_blocked)"
            )),
        }
    }
}

impl LinearParams {
    /// A plain layer `y = x · wᵀ + b` of `rows` rows (no norm, activation or residual).
    pub fn new(rows: usize, in_dim: usize, out_dim: usize) -> Self {
        Self {
            rows: rows as u32,
            in_dim: in_dim as u32,
            out_dim: out_dim as u32,
            relu: 0,
            residual: 0,
            norm: 0,
            eps: 0.0,
            part: out_dim as u32,
            part_stride: (rows * out_dim) as u32,
            _pad: [0; 3],
        }
    }

    /// Floats of the `y` this layer writes: every part, the last one `rows · part` long.
    pub fn y_len(&self) -> usize {
        let parts = self.out_dim.div_ceil(self.part.max(1)) as usize;
        (parts.saturating_sub(1)) * self.part_stride as usize + (self.rows * self.part) as usize
    }

    /// Invocations of one dispatch of `kernel`.
    pub fn threads(&self, kernel: LinearKernel) -> u32 {
        match kernel {
            LinearKernel::Rowwise => self.rows * self.out_dim.div_ceil(4),
            LinearKernel::Tiled => {
                let (tile_rows, tile_outs) = LinearKernel::TILE;
                self.rows.div_ceil(tile_rows) * self.out_dim.div_ceil(tile_outs) * WORKGROUP
            }
            LinearKernel::Blocked => {
                let (block_rows, block_outs) = LinearKernel::BLOCK;
                self.rows.div_ceil(block_rows)
                    * self.out_dim.div_ceil(block_outs)
                    * LinearKernel::BLOCK_WORKGROUP
            }
        }
    }
}

/// A layer norm (γ, β `[in]`) folded into the linear layer after it (`w [out, in]`, `b [out]`):
/// `LN(x) · wᵀ + b = z · (w ∘ γ)ᵀ + (w · β + b)` with `z` the standardised row, which the
/// kernel's `norm` prologue computes. Done once on upload, so the prologue reads no γ, β.
pub fn fold_layer_norm(w: &[f32], b: &[f32], gamma: &[f32], beta: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let in_dim = gamma.len();
    assert_eq!(beta.len(), in_dim, "β is [in]");
    assert_eq!(w.len(), b.len() * in_dim, "w is [out, in]");
    let folded_w = w
        .chunks_exact(in_dim)
        .flat_map(|row| row.iter().zip(gamma).map(|(w, g)| w * g))
        .collect();
    let folded_b = w
        .chunks_exact(in_dim)
        .zip(b)
        .map(|(row, &b)| {
            let shift: f64 = row
                .iter()
                .zip(beta)
                .map(|(&w, &beta)| f64::from(w) * f64::from(beta))
                .sum();
            (f64::from(b) + shift) as f32
        })
        .collect();
    (folded_w, folded_b)
}

#[derive(Debug)]
pub struct Linear {
    pub pipeline: Pipeline,
    pub kernel: LinearKernel,
}

impl Linear {
    pub fn with_kernel(ctx: &GpuContext, kernel: LinearKernel) -> Self {
        Self {
            pipeline: Pipeline::with_workgroup_size(
                ctx,
                Shader::Linear,
                kernel.entry(),
                kernel.workgroup_size(),
            ),
            kernel,
        }
    }

    /// `x [rows, in]`, `w [out, in]`, `b [out]` → `[rows, out]` (a plain layer: `p` without
    /// residual or parts).
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: LinearParams,
        x: &[f32],
        w: &[f32],
        b: &[f32],
    ) -> Result<Vec<f32>> {
        let y = vec![0.0; (p.rows * p.out_dim) as usize];
        self.run_fused(ctx, p, x, w, b, &y)
    }

    /// Any fusion of `p`: `y` is the output's initial contents (`p.y_len()` floats; added to
    /// when `p.residual` is 1) → `y` after.
    pub fn run_fused(
        &self,
        ctx: &GpuContext,
        p: LinearParams,
        x: &[f32],
        w: &[f32],
        b: &[f32],
        y: &[f32],
    ) -> Result<Vec<f32>> {
        let w = bytemuck::cast_slice(w);
        run_once(ctx, &self.pipeline, p, p.threads(self.kernel), (x, w, b), y)
    }
}

/// One dispatch of a linear kernel family's `pipeline` over `threads` invocations (uploads,
/// dispatch, read-back; the one-shot form of tests and self-tests): `x`, the weights as the
/// family binds them (f32 or f16 bytes), `b`, and `y`'s initial contents (`p.y_len()` floats)
/// → `y` after.
pub(crate) fn run_once(
    ctx: &GpuContext,
    pipeline: &Pipeline,
    p: LinearParams,
    threads: u32,
    (x, w, b): (&[f32], &[u8], &[f32]),
    y: &[f32],
) -> Result<Vec<f32>> {
    assert_eq!(y.len(), p.y_len(), "y holds every part");
    let storage = wgpu::BufferUsages::STORAGE;
    let params = upload(
        ctx,
        "params",
        bytemuck::bytes_of(&p),
        wgpu::BufferUsages::UNIFORM,
    );
    let x = upload(ctx, "x", bytemuck::cast_slice(x), storage);
    let w = upload(ctx, "w", w, storage);
    let b = upload(ctx, "b", bytemuck::cast_slice(b), storage);
    let bytes = (y.len() * 4) as u64;
    let out = storage_buffer(ctx, "y", bytes);
    ctx.queue.write_buffer(&out, 0, bytemuck::cast_slice(y));
    let mut encoder = ctx
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("linear"),
        });
    pipeline.encode(ctx, &mut encoder, &params, &[&x, &w, &b, &out], threads);
    ctx.queue.submit([encoder.finish()]);
    if y.is_empty() {
        return Ok(Vec::new());
    }
    let bytes = read_back(ctx, &out, bytes)?;
    Ok(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(rows: u32, out_dim: u32) -> LinearParams {
        LinearParams::new(rows as usize, 96, out_dim as usize)
    }

    #[test]
    fn layers_run_by_size_and_adapter() {
        let one_scene = layer(60, 96); // one scene's tokens (3 agents): 1 block
        let small = layer(600, 96); // 5 blocks
        let large = layer(2400, 96); // 8 scenes' tokens: 19 blocks
        let choose = |software, p| LinearKernel::choose(None, software, p);
        assert_eq!(choose(false, &one_scene), LinearKernel::Rowwise);
        assert_eq!(choose(false, &small), LinearKernel::Rowwise);
        assert_eq!(choose(false, &large), LinearKernel::Blocked);
        assert_eq!(choose(true, &one_scene), LinearKernel::Rowwise);
        assert_eq!(choose(true, &small), LinearKernel::Blocked);
        assert_eq!(choose(true, &large), LinearKernel::Blocked);
        for named in LinearKernel::ALL {
            for p in [one_scene, small, large] {
                assert_eq!(LinearKernel::choose(Some(named), false, &p), named);
                assert_eq!(LinearKernel::choose(Some(named), true, &p), named);
            }
        }
    }

    #[test]
    fn names_parse_to_their_kernel() {
        for kernel in LinearKernel::ALL {
            assert_eq!(kernel.entry().parse::<LinearKernel>(), Ok(kernel));
        }
        assert_eq!("blocked".parse::<LinearKernel>(), Ok(LinearKernel::Blocked));
        assert_eq!("tiled".parse::<LinearKernel>(), Ok(LinearKernel::Tiled));
        let err = "fast".parse::<LinearKernel>().unwrap_err();
        assert!(err.contains("\"fast\""), "{err}");
    }
}
