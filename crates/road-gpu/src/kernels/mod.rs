//! Compute kernels, one module per shader family. Each `run` method is the one-shot form used by
//! tests and self-tests (upload, dispatch, read back); `encode` records into an existing
//! command encoder so that the engine can chain kernels without readbacks.

pub mod agent_map;
pub mod agent_pairs;
pub mod attention;
pub mod compact;
pub mod edm;
pub mod linear;
pub mod linear_f16;
pub mod polyline;
pub mod residual_chain;
pub mod window;

use wgpu::util::DeviceExt;

use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// Threads per workgroup of the kernels here (`@workgroup_size(64)`), unless a pipeline is
/// made with another ([`Pipeline::with_workgroup_size`]).
pub const WORKGROUP: u32 = 64;
/// Most workgroups along one dispatch dimension (the WebGPU default limit).
const MAX_GROUPS_X: u32 = 65_535;

/// How a shader reads or writes one of its bindings, as the shader declares it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BindingAccess {
    /// `var<uniform>` or `var<storage, read>`.
    Read,
    /// `var<storage, read_write>`: counted as read and written.
    ReadWrite,
}

/// `(binding, access)` of every group-0 buffer `shader` declares, reflected by naga: what a
/// dispatch's traffic counts ([`Traffic`]). A source naga cannot parse (which wgpu would refuse
/// anyway) declares nothing, and its bindings count as read and written.
fn declared_access(shader: Shader) -> Vec<(u32, BindingAccess)> {
    let module = match naga::front::wgsl::parse_str(shader.source()) {
        Ok(module) => module,
        Err(e) => {
            tracing::warn!(
                shader = shader.file_name(),
                "cannot reflect the bindings: {e}"
            );
            return Vec::new();
        }
    };
    module
        .global_variables
        .iter()
        .filter_map(|(_, var)| {
            let binding = var.binding.as_ref().filter(|b| b.group == 0)?;
            let access = match var.space {
                naga::AddressSpace::Uniform => BindingAccess::Read,
                naga::AddressSpace::Storage { access }
                    if !access.contains(naga::StorageAccess::STORE) =>
                {
                    BindingAccess::Read
                }
                naga::AddressSpace::Storage { .. } => BindingAccess::ReadWrite,
                _ => return None,
            };
            Some((binding.binding, access))
        })
        .collect()
}

/// Bytes of a bound buffer range: its size, or the rest of the buffer from its offset.
fn bound_bytes(resource: &wgpu::BindingResource<'_>) -> u64 {
    match resource {
        wgpu::BindingResource::Buffer(b) => b
            .size
            .map_or_else(|| b.buffer.size().saturating_sub(b.offset), |s| s.get()),
        _ => 0,
    }
}

/// What recorded dispatches cost in launches and memory traffic: the proxies of
/// `road bench engine` that need no GPU to measure. Every binding counts at the size of its
/// bound range: read-only storage and uniforms as read, read-write storage as read and written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Traffic {
    pub dispatches: u64,
    pub bytes_read: u64,
    pub bytes_written: u64,
}

impl Traffic {
    /// Counts one recorded dispatch.
    pub fn count(&mut self, d: &Dispatch) {
        self.dispatches += 1;
        self.bytes_read += d.bytes_read;
        self.bytes_written += d.bytes_written;
    }

    /// Bytes read and written.
    pub fn bytes(&self) -> u64 {
        self.bytes_read + self.bytes_written
    }
}

impl std::ops::AddAssign for Traffic {
    fn add_assign(&mut self, other: Self) {
        self.dispatches += other.dispatches;
        self.bytes_read += other.bytes_read;
        self.bytes_written += other.bytes_written;
    }
}

/// `shader` compiled without wgpu's runtime checks ([`crate::ContextOptions::unchecked_shaders`]).
#[allow(unsafe_code)]
fn unchecked_module(ctx: &GpuContext, shader: Shader) -> wgpu::ShaderModule {
    // SAFETY: every kernel of `shaders/` bounds its indices by the sizes in its params and its
    // loops by those sizes, and divides only by sizes the engine sets non-zero; the tolerance
    // tests run the whole denoiser this way too.
    unsafe {
        ctx.device.create_shader_module_trusted(
            shader.module_descriptor(),
            wgpu::ShaderRuntimeChecks::unchecked(),
        )
    }
}

/// A compiled entry point and its bind group layout.
#[derive(Debug)]
pub struct Pipeline {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    label: &'static str,
    /// `(binding, access)` as the shader declares them.
    access: Vec<(u32, BindingAccess)>,
    /// The entry point's `@workgroup_size`: a dispatch of `threads` runs
    /// `threads / workgroup_size` workgroups.
    workgroup_size: u32,
}

impl Pipeline {
    pub fn new(ctx: &GpuContext, shader: Shader, entry: &'static str) -> Self {
        Self::with_workgroup_size(ctx, shader, entry, WORKGROUP)
    }

    /// An entry point whose `@workgroup_size` is `workgroup_size` rather than [`WORKGROUP`].
    pub fn with_workgroup_size(
        ctx: &GpuContext,
        shader: Shader,
        entry: &'static str,
        workgroup_size: u32,
    ) -> Self {
        Self::with_constants(ctx, shader, entry, workgroup_size, &[])
    }

    /// An entry point with its override `constants` set (name, value), whose
    /// `@workgroup_size` they make `workgroup_size`.
    pub fn with_constants(
        ctx: &GpuContext,
        shader: Shader,
        entry: &'static str,
        workgroup_size: u32,
        constants: &[(&str, f64)],
    ) -> Self {
        let module = if ctx.unchecked_shaders() {
            unchecked_module(ctx, shader)
        } else {
            ctx.device.create_shader_module(shader.module_descriptor())
        };
        let pipeline = ctx
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants,
                    ..Default::default()
                },
                cache: None,
            });
        let layout = pipeline.get_bind_group_layout(0);
        Self {
            pipeline,
            layout,
            label: entry,
            access: declared_access(shader),
            workgroup_size,
        }
    }

    /// Records one dispatch of `threads` invocations: binding 0 is the uniform `params`, the
    /// storage buffers follow in order (bindings 1, 2, ...).
    pub fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        buffers: &[&wgpu::Buffer],
        threads: u32,
    ) {
        let resources: Vec<wgpu::BindingResource<'_>> =
            buffers.iter().map(|b| b.as_entire_binding()).collect();
        self.encode_resources(ctx, encoder, params, &resources, threads);
    }

    /// As [`Self::encode`], with resources (such as sub-ranges of the weights buffer).
    pub fn encode_resources(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        resources: &[wgpu::BindingResource<'_>],
        threads: u32,
    ) {
        let bound: Vec<(u32, wgpu::BindingResource<'_>)> = resources
            .iter()
            .enumerate()
            .map(|(i, r)| (i as u32 + 1, r.clone()))
            .collect();
        self.encode_bound(ctx, encoder, params, &bound, threads);
    }

    /// As [`Self::encode`], with explicit binding numbers: for entry points of a shared module
    /// that use only some of its bindings.
    pub fn encode_bound(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        bound: &[(u32, wgpu::BindingResource<'_>)],
        threads: u32,
    ) {
        let dispatch = self.prepare(ctx, params, bound, threads);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(self.label),
            timestamp_writes: None,
        });
        dispatch.record(&mut pass);
    }

    /// [`Self::prepare`] with storage buffers at bindings 1, 2, ...
    pub fn prepare_buffers(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        buffers: &[&wgpu::Buffer],
        threads: u32,
    ) -> Dispatch {
        let bound: Vec<(u32, wgpu::BindingResource<'_>)> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| (i as u32 + 1, b.as_entire_binding()))
            .collect();
        self.prepare(ctx, params, &bound, threads)
    }

    /// [`Self::prepare`] with resources at bindings 1, 2, ...
    pub fn prepare_resources(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        resources: &[wgpu::BindingResource<'_>],
        threads: u32,
    ) -> Dispatch {
        let bound: Vec<(u32, wgpu::BindingResource<'_>)> = resources
            .iter()
            .enumerate()
            .map(|(i, r)| (i as u32 + 1, r.clone()))
            .collect();
        self.prepare(ctx, params, &bound, threads)
    }

    /// A dispatch with its bind group made once, to be recorded any number of times.
    pub fn prepare(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        bound: &[(u32, wgpu::BindingResource<'_>)],
        threads: u32,
    ) -> Dispatch {
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: params.as_entire_binding(),
        }];
        entries.extend(
            bound
                .iter()
                .map(|(binding, resource)| wgpu::BindGroupEntry {
                    binding: *binding,
                    resource: resource.clone(),
                }),
        );
        let (mut bytes_read, mut bytes_written) = (0, 0);
        for entry in &entries {
            let bytes = bound_bytes(&entry.resource);
            let access = self
                .access
                .iter()
                .find(|(binding, _)| *binding == entry.binding)
                .map_or(BindingAccess::ReadWrite, |&(_, access)| access);
            bytes_read += bytes;
            if access == BindingAccess::ReadWrite {
                bytes_written += bytes;
            }
        }
        let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(self.label),
            layout: &self.layout,
            entries: &entries,
        });
        let groups = threads.div_ceil(self.workgroup_size).max(1);
        let groups = if groups <= MAX_GROUPS_X {
            (groups, 1)
        } else {
            (MAX_GROUPS_X, groups.div_ceil(MAX_GROUPS_X))
        };
        Dispatch {
            pipeline: self.pipeline.clone(),
            bind_group,
            groups,
            label: self.label,
            bytes_read,
            bytes_written,
        }
    }

    /// Uploads `inputs`, runs once into a fresh output of `out_len` floats, reads it back.
    pub fn run_once(
        &self,
        ctx: &GpuContext,
        params: &[u8],
        inputs: &[&[f32]],
        out_len: usize,
        threads: u32,
    ) -> Result<Vec<f32>> {
        let params = upload(ctx, "params", params, wgpu::BufferUsages::UNIFORM);
        let input_buffers: Vec<wgpu::Buffer> = inputs
            .iter()
            .map(|data| {
                upload(
                    ctx,
                    "input",
                    bytemuck::cast_slice(data),
                    wgpu::BufferUsages::STORAGE,
                )
            })
            .collect();
        let out_bytes = (out_len * 4) as u64;
        let out = storage_buffer(ctx, "output", out_bytes);
        let mut buffers: Vec<&wgpu::Buffer> = input_buffers.iter().collect();
        buffers.push(&out);
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some(self.label),
            });
        self.encode(ctx, &mut encoder, &params, &buffers, threads);
        ctx.queue.submit([encoder.finish()]);
        if out_len == 0 {
            return Ok(Vec::new());
        }
        let bytes = read_back(ctx, &out, out_bytes)?;
        Ok(bytemuck::cast_slice::<u8, f32>(&bytes).to_vec())
    }
}

/// One prepared dispatch: pipeline, bind group (which keeps its buffers alive) and grid.
#[derive(Debug, Clone)]
pub struct Dispatch {
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    groups: (u32, u32),
    /// The entry point it runs (what a profile groups by).
    label: &'static str,
    /// Bytes its bindings read (every binding's bound range) and write (the read-write ones').
    bytes_read: u64,
    bytes_written: u64,
}

impl Dispatch {
    pub fn label(&self) -> &'static str {
        self.label
    }

    /// Bytes of its bindings read: every binding's bound range, the uniform params included.
    pub fn bytes_read(&self) -> u64 {
        self.bytes_read
    }

    /// Bytes of its bindings written: the bound ranges of its read-write storage bindings.
    pub fn bytes_written(&self) -> u64 {
        self.bytes_written
    }

    pub fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.dispatch_workgroups(self.groups.0, self.groups.1, 1);
    }

    /// [`Self::record`], counted in `traffic`: the engine's steps record through this, so that
    /// its dispatch and byte counts follow whatever kernels it runs.
    pub fn record_counted(&self, pass: &mut wgpu::ComputePass<'_>, traffic: &mut Traffic) {
        self.record(pass);
        traffic.count(self);
    }
}

/// Records dispatches in order into one compute pass (wgpu orders their memory accesses).
pub fn record_all(encoder: &mut wgpu::CommandEncoder, label: &str, dispatches: &[Dispatch]) {
    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some(label),
        timestamp_writes: None,
    });
    for d in dispatches {
        d.record(&mut pass);
    }
}

/// `count` rows of `floats` values of `buffer` from row `first`, as a binding (the offset must
/// meet the adapter's storage offset alignment: 256 bytes at most).
pub(crate) fn rows_of(
    buffer: &wgpu::Buffer,
    first: usize,
    count: usize,
    floats: usize,
) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer,
        offset: (first * floats * 4) as u64,
        size: std::num::NonZeroU64::new((count * floats * 4) as u64),
    })
}

/// A read-write storage buffer that can be copied out.
pub fn storage_buffer(ctx: &GpuContext, label: &str, bytes: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(4),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// A buffer holding `data`; empty data still gets 4 bytes (bindings cannot be empty).
pub fn upload(
    ctx: &GpuContext,
    label: &str,
    data: &[u8],
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    let padded;
    let contents = if data.is_empty() {
        padded = [0u8; 4];
        &padded[..]
    } else {
        data
    };
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage,
        })
}

/// Copies `bytes` of `source` back to the CPU (blocking).
pub fn read_back(ctx: &GpuContext, source: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>> {
    read_back_range(ctx, source, 0, bytes)
}

/// `bytes` of `source` from byte `offset` (both multiples of 4), read back to the host.
pub fn read_back_range(
    ctx: &GpuContext,
    source: &wgpu::Buffer,
    offset: u64,
    bytes: u64,
) -> Result<Vec<u8>> {
    read_back_ranges(ctx, source, &[(offset, bytes)])
}

/// Several `(offset, bytes)` ranges of `source`, concatenated: copied into one staging buffer in
/// one submission and mapped once.
pub fn read_back_ranges(
    ctx: &GpuContext,
    source: &wgpu::Buffer,
    ranges: &[(u64, u64)],
) -> Result<Vec<u8>> {
    let encoder = ctx
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("readback"),
        });
    let copies: Vec<(&wgpu::Buffer, u64, u64)> =
        ranges.iter().map(|&(at, len)| (source, at, len)).collect();
    read_back_after(ctx, encoder, &copies)
}

/// `(source, offset, bytes)` ranges, concatenated, read back after the commands already in
/// `encoder`: copied into one staging buffer, submitted with them, mapped once (one wait).
pub fn read_back_after(
    ctx: &GpuContext,
    mut encoder: wgpu::CommandEncoder,
    copies: &[(&wgpu::Buffer, u64, u64)],
) -> Result<Vec<u8>> {
    let bytes: u64 = copies.iter().map(|c| c.2).sum();
    let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: bytes.max(4),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut at = 0;
    for &(source, offset, len) in copies {
        encoder.copy_buffer_to_buffer(source, offset, &staging, at, len);
        at += len;
    }
    ctx.queue.submit([encoder.finish()]);
    if bytes == 0 {
        return Ok(Vec::new());
    }
    let (tx, rx) = std::sync::mpsc::channel();
    staging
        .slice(..bytes)
        .map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
    ctx.wait()?;
    rx.recv()
        .map_err(|e| Error::Readback(e.to_string()))?
        .map_err(|e| Error::Readback(e.to_string()))?;
    let data = staging
        .slice(..bytes)
        .get_mapped_range()
        .map_err(|e| Error::Readback(e.to_string()))?
        .to_vec();
    staging.unmap();
    Ok(data)
}
