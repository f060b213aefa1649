//! `shaders/compact.wgsl`: a batch's rows gathered into a compact sub-batch and its results
//! scattered back (`GpuStepEngine`'s packed and mixed-phase steps), the regions that share a
//! row map in one dispatch (up to three gathered, two scattered). CPU reference:
//! [`gather_rows_reference`], [`scatter_rows_reference`], region by region.

use bytemuck::{Pod, Zeroable};

use super::{Dispatch, Pipeline, read_back, record_all, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// A sub-batch row no batch row maps to (`row_map`).
pub const NONE: u32 = u32::MAX;

/// Most regions one gather moves (`gather_rows_3`), and one scatter (`scatter_rows_2`).
pub const MAX_GATHERED: usize = 3;
pub const MAX_SCATTERED: usize = 2;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    rows: u32,
    floats: [u32; 3],
}

/// One region a dispatch moves: its source, its destination and floats per row.
pub type Region<'a> = (&'a wgpu::Buffer, &'a wgpu::Buffer, usize);

/// The kernels, compiled once: gathers of 1, 2 and 3 regions, scatters of 1 and 2.
#[derive(Debug)]
pub struct CompactRows {
    gather: [Pipeline; MAX_GATHERED],
    scatter: [Pipeline; MAX_SCATTERED],
}

impl CompactRows {
    pub fn new(ctx: &GpuContext) -> Self {
        let pipeline = |entry| Pipeline::new(ctx, Shader::Compact, entry);
        Self {
            gather: ["gather_rows", "gather_rows_2", "gather_rows_3"].map(pipeline),
            scatter: ["scatter_rows", "scatter_rows_2"].map(pipeline),
        }
    }

    /// For each region `(src, dst, floats)`: `dst [rows, floats]` ← `src`'s row `row_map[r]`
    /// (zeros where [`NONE`]); `row_map [rows]`. One to [`MAX_GATHERED`] regions.
    pub fn prepare_gather(
        &self,
        ctx: &GpuContext,
        row_map: &wgpu::Buffer,
        rows: usize,
        regions: &[Region<'_>],
    ) -> Result<Dispatch> {
        Self::prepare(&self.gather, ctx, row_map, rows, regions)
    }

    /// For each region `(src, dst, floats)`: `dst`'s row `row_map[r]` ← `src [rows, floats]`'s
    /// row r (nothing where [`NONE`]). One to [`MAX_SCATTERED`] regions.
    pub fn prepare_scatter(
        &self,
        ctx: &GpuContext,
        row_map: &wgpu::Buffer,
        rows: usize,
        regions: &[Region<'_>],
    ) -> Result<Dispatch> {
        Self::prepare(&self.scatter, ctx, row_map, rows, regions)
    }

    fn prepare(
        pipelines: &[Pipeline],
        ctx: &GpuContext,
        row_map: &wgpu::Buffer,
        rows: usize,
        regions: &[Region<'_>],
    ) -> Result<Dispatch> {
        let Some(pipeline) = regions.len().checked_sub(1).and_then(|i| pipelines.get(i)) else {
            return Err(Error::Input(format!(
                "a row move of {} regions: the kernels move 1 to {}",
                regions.len(),
                pipelines.len()
            )));
        };
        let mut floats = [0u32; 3];
        for (f, &(_, _, per_row)) in floats.iter_mut().zip(regions) {
            *f = per_row as u32;
        }
        let params = Params {
            rows: rows as u32,
            floats,
        };
        let params = upload(
            ctx,
            "compact params",
            bytemuck::bytes_of(&params),
            wgpu::BufferUsages::UNIFORM,
        );
        let mut bound = vec![(1, row_map.as_entire_binding())];
        for (k, &(src, dst, _)) in regions.iter().enumerate() {
            let k = k as u32;
            bound.push((2 + 2 * k, src.as_entire_binding()));
            bound.push((3 + 2 * k, dst.as_entire_binding()));
        }
        let per_row: usize = regions.iter().map(|&(_, _, f)| f).sum();
        Ok(pipeline.prepare(ctx, &params, &bound, (rows * per_row) as u32))
    }

    /// Runs once on host data, every region `(src, dst_init, floats)` in one dispatch: each
    /// `dst` starts as its `dst_init` (whose length fixes the other side's rows for a scatter);
    /// gather (`scatter == false`) or scatter. Returns each region's `dst`.
    pub fn run(
        &self,
        ctx: &GpuContext,
        scatter: bool,
        row_map: &[u32],
        regions: &[(&[f32], &[f32], usize)],
    ) -> Result<Vec<Vec<f32>>> {
        let usage = wgpu::BufferUsages::STORAGE;
        let map_buffer = upload(ctx, "row map", bytemuck::cast_slice(row_map), usage);
        let buffers: Vec<(wgpu::Buffer, wgpu::Buffer, usize)> = regions
            .iter()
            .map(|&(src, dst_init, floats)| {
                let src = upload(ctx, "src", bytemuck::cast_slice(src), usage);
                let dst = storage_buffer(ctx, "dst", (dst_init.len() * 4) as u64);
                ctx.queue
                    .write_buffer(&dst, 0, bytemuck::cast_slice(dst_init));
                (src, dst, floats)
            })
            .collect();
        let bound: Vec<Region<'_>> = buffers.iter().map(|(s, d, f)| (s, d, *f)).collect();
        let dispatch = if scatter {
            self.prepare_scatter(ctx, &map_buffer, row_map.len(), &bound)?
        } else {
            self.prepare_gather(ctx, &map_buffer, row_map.len(), &bound)?
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
        buffers
            .iter()
            .zip(regions)
            .map(|((_, dst, _), (_, dst_init, _))| {
                let bytes = read_back(ctx, dst, (dst_init.len() * 4) as u64)?;
                Ok(bytemuck::cast_slice(&bytes).to_vec())
            })
            .collect()
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
