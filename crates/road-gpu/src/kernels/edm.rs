//! `shaders/edm.wgsl`: EDM preconditioning coefficients per window slot.

use bytemuck::{Pod, Zeroable};

use super::{read_back, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    count: u32,
    sigma_data: f32,
    sigma_min: f32,
    _pad: u32,
}

const WORKGROUP: u32 = 64;

/// The `precondition` kernel, compiled once.
#[derive(Debug)]
pub struct EdmPrecondition {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

impl EdmPrecondition {
    pub fn new(ctx: &GpuContext) -> Self {
        let module = ctx
            .device
            .create_shader_module(Shader::Edm.module_descriptor());
        let pipeline = ctx
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("edm.precondition"),
                layout: None,
                module: &module,
                entry_point: Some("precondition"),
                compilation_options: Default::default(),
                cache: None,
            });
        let layout = pipeline.get_bind_group_layout(0);
        Self { pipeline, layout }
    }

    /// `[count]` noise levels → `[count]` × (c_skip, c_out, c_in, c_noise).
    pub fn run(
        &self,
        ctx: &GpuContext,
        sigma: &[f32],
        sigma_data: f32,
        sigma_min: f32,
    ) -> Result<Vec<[f32; 4]>> {
        let count = sigma.len() as u32;
        let params = Params {
            count,
            sigma_data,
            sigma_min,
            _pad: 0,
        };
        let params_buf = upload(
            ctx,
            "edm.params",
            bytemuck::bytes_of(&params),
            wgpu::BufferUsages::UNIFORM,
        );
        let sigma_buf = upload(
            ctx,
            "edm.sigma",
            bytemuck::cast_slice(sigma),
            wgpu::BufferUsages::STORAGE,
        );
        let out_bytes = u64::from(count) * 16;
        let out_buf = storage_buffer(ctx, "edm.coeffs", out_bytes);
        let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("edm"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: params_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: sigma_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: out_buf.as_entire_binding(),
                },
            ],
        });
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("edm") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("edm"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(count.div_ceil(WORKGROUP), 1, 1);
        }
        ctx.queue.submit([encoder.finish()]);
        if count == 0 {
            return Ok(Vec::new());
        }
        let bytes = read_back(ctx, &out_buf, out_bytes)?;
        Ok(bytemuck::cast_slice::<u8, [f32; 4]>(&bytes).to_vec())
    }
}
