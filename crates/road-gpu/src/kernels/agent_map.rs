//! `shaders/agent_map.wgsl`: every agent's own map (`model.agent_map`), its nearest polylines
//! in its anchor frame. CPU reference: `road_model::agent_map::{anchors_of, agent_maps}`
//! (what both CPU engines run).

use bytemuck::{Pod, Zeroable};

use super::{Pipeline, read_back, storage_buffer, upload};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// Most polylines per scene the kernel picks from (its private arrays).
pub const MAX_POLYLINES: usize = 128;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct AgentMapParams {
    /// Agent rows B·A.
    pub rows: u32,
    pub agents: u32,
    pub slots: u32,
    pub anchor_slot: u32,
    /// Polylines P per scene (≤ [`MAX_POLYLINES`]).
    pub polylines: u32,
    /// Points Q per polyline.
    pub points: u32,
    /// Polylines K per agent (≤ P).
    pub picked: u32,
    pub heading_scale: f32,
}

impl AgentMapParams {
    pub fn check(&self) -> Result<()> {
        if self.polylines as usize > MAX_POLYLINES || self.picked > self.polylines {
            return Err(Error::Input(format!(
                "agent maps: {} polylines per agent of {} per scene (the kernel takes at most \
                 {MAX_POLYLINES} per scene)",
                self.picked, self.polylines
            )));
        }
        Ok(())
    }
}

#[derive(Debug)]
pub struct AgentMap(pub Pipeline);

impl AgentMap {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::AgentMap, "pick_agent_maps"))
    }

    /// `x [B, A, W, 3]`, `valid [B, A, W]`, `map [M, P, Q, 2]`, `map_valid [M, P]`,
    /// `agent_scene [B·A]` (each agent row's map scene, `< M`) → (`points [B·A, K, Q, 2]`,
    /// `valid [B·A, K]`).
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: AgentMapParams,
        x: &[f32],
        valid: &[f32],
        map: &[f32],
        map_valid: &[f32],
        agent_scene: &[u32],
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        p.check()?;
        let map_scenes = map_valid.len() / (p.polylines as usize).max(1);
        if agent_scene.len() != p.rows as usize
            || agent_scene.iter().any(|&s| s as usize >= map_scenes)
        {
            return Err(Error::Input(format!(
                "agent maps: {} agent scenes for {} rows, each below the {map_scenes} map scenes",
                agent_scene.len(),
                p.rows
            )));
        }
        let params = upload(
            ctx,
            "params",
            bytemuck::bytes_of(&p),
            wgpu::BufferUsages::UNIFORM,
        );
        let inputs: Vec<wgpu::Buffer> =
            [x, valid, map, map_valid, bytemuck::cast_slice(agent_scene)]
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
        let picked = (p.rows * p.picked) as u64;
        let points_bytes = picked * u64::from(p.points) * 2 * 4;
        let out_points = storage_buffer(ctx, "agent map points", points_bytes);
        let out_valid = storage_buffer(ctx, "agent map valid", picked * 4);
        let mut buffers: Vec<&wgpu::Buffer> = inputs.iter().collect();
        buffers.extend([&out_points, &out_valid]);
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("agent maps"),
            });
        self.0.encode(ctx, &mut encoder, &params, &buffers, p.rows);
        ctx.queue.submit([encoder.finish()]);
        let floats = |bytes: Vec<u8>| bytemuck::cast_slice::<u8, f32>(&bytes).to_vec();
        Ok((
            floats(read_back(ctx, &out_points, points_bytes)?),
            floats(read_back(ctx, &out_valid, picked * 4)?),
        ))
    }
}
