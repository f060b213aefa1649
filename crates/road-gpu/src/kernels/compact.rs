//! `shaders/compact.wgsl`: a batch's rows gathered into a compact sub-batch and its results
//! scattered back (`GpuStepEngine`'s packed and mixed-phase steps), one dispatch per
//! region. CPU reference: [`gather_rows_reference`], [`scatter_rows_reference`].

use bytemuck::{Pod, Zeroable};

use super::{Dispatch, Pipeline, read_back, record_all, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{GpuContext, Result};

/// A sub-batch row no batch row maps to (`row_map`).
pub const NONE: u32 = u32::MAX;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    rows: u32,
    row_floats: u32,
    _pad: [u32; 2],
}

/// Both kernels, compiled once.
#[derive(Debug)]
pub struct CompactRows {
    gather: Pipeline,
    scatter: Pipeline,
}

impl CompactRows {
    pub fn new(ctx: &GpuContext) -> Self {
        Self {
            gather: Pipeline::new(ctx, Shader::Compact, "gather_rows"),
            scatter: Pipeline::new(ctx, Shader::Compact, "scatter_rows"),
        }
    }

    /// `dst [rows, row_floats]` ← `src`'s row `row_map[r]` (zeros where [`NONE`]);
    /// `row_map [rows]`.
    pub fn prepare_gather(
        &self,
        ctx: &GpuContext,
        src: &wgpu::Buffer,
        row_map: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        (rows, row_floats): (usize, usize),
    ) -> Dispatch {
        Self::prepare(&self.gather, ctx, src, row_map, dst, (rows, row_floats))
    }

    /// `dst`'s row `row_map[r]` ← `src [rows, row_floats]`'s row r (nothing where [`NONE`]).
    pub fn prepare_scatter(
        &self,
        ctx: &GpuContext,
        src: &wgpu::Buffer,
        row_map: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        (rows, row_floats): (usize, usize),
    ) -> Dispatch {
        Self::prepare(&self.scatter, ctx, src, row_map, dst, (rows, row_floats))
    }

    fn prepare(
        pipeline: &Pipeline,
        ctx: &GpuContext,
        src: &wgpu::Buffer,
        row_map: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        (rows, row_floats): (usize, usize),
    ) -> Dispatch {
        let params = Params {
            rows: rows as u32,
            row_floats: row_floats as u32,
            _pad: [0; 2],
        };
        let params = upload(
            ctx,
            "compact params",
            bytemuck::bytes_of(&params),
            wgpu::BufferUsages::UNIFORM,
        );
        pipeline.prepare_buffers(
            ctx,
            &params,
            &[src, row_map, dst],
            (rows * row_floats) as u32,
        )
    }

    /// Runs once on host data: `dst` starts as `dst_init` (its length fixes the other side's
    /// rows for a scatter); gather (`scatter == false`) or scatter.
    pub fn run(
        &self,
        ctx: &GpuContext,
        scatter: bool,
        src: &[f32],
        row_map: &[u32],
        dst_init: &[f32],
        row_floats: usize,
    ) -> Result<Vec<f32>> {
        let usage = wgpu::BufferUsages::STORAGE;
        let src_buffer = upload(ctx, "src", bytemuck::cast_slice(src), usage);
        let map_buffer = upload(ctx, "row map", bytemuck::cast_slice(row_map), usage);
        let bytes = (dst_init.len() * 4) as u64;
        let dst = storage_buffer(ctx, "dst", bytes);
        ctx.queue
            .write_buffer(&dst, 0, bytemuck::cast_slice(dst_init));
        let shape = (row_map.len(), row_floats);
        let dispatch = if scatter {
            self.prepare_scatter(ctx, &src_buffer, &map_buffer, &dst, shape)
        } else {
            self.prepare_gather(ctx, &src_buffer, &map_buffer, &dst, shape)
        };
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("compact rows"),
            });
        record_all(
            &mut encoder,
            "compact rows",
            std::slice::from_ref(&dispatch),
        );
        ctx.queue.submit([encoder.finish()]);
        Ok(bytemuck::cast_slice(&read_back(ctx, &dst, bytes)?).to_vec())
    }
}

/// `gather_rows` on the host: `row_map.len()` rows of `row_floats`, each `src`'s mapped row
/// (zeros where [`NONE`] or past `src`).
pub fn gather_rows_reference(src: &[f32], row_map: &[u32], row_floats: usize) -> Vec<f32> {
    row_map
        .iter()
        .flat_map(|&from| {
            (0..row_floats).map(move |c| {
                let at = from as usize * row_floats + c;
                if from == NONE {
                    0.0
                } else {
                    src.get(at).copied().unwrap_or(0.0)
                }
            })
        })
        .collect()
}

/// `scatter_rows` on the host: `dst` with `src`'s row r written over its row `row_map[r]`
/// (skipped where [`NONE`] or past `dst`).
pub fn scatter_rows_reference(
    src: &[f32],
    row_map: &[u32],
    dst: &[f32],
    row_floats: usize,
) -> Vec<f32> {
    let mut out = dst.to_vec();
    for (r, &to) in row_map.iter().enumerate() {
        if to == NONE {
            continue;
        }
        for c in 0..row_floats {
            if let Some(slot) = out.get_mut(to as usize * row_floats + c) {
                *slot = src[r * row_floats + c];
            }
        }
    }
    out
}
