//! `shaders/agent_pairs.wgsl`: agent attention with pair features (`model.agent_pairs`). CPU
//! reference: [`crate::reference::pair_attention`], on `road_model::agent_pairs::pair_features`
//! (what both CPU engines compute).

use bytemuck::{Pod, Zeroable};

use super::Pipeline;
use crate::kernels::attention::MAX_HEAD_DIM;
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct PairAttentionParams {
    /// Groups B·W (scene, slot).
    pub groups: u32,
    pub heads: u32,
    pub head_dim: u32,
    pub agents: u32,
    pub slots: u32,
    pub anchor_slot: u32,
    /// 1/√head_dim.
    pub scale: f32,
    pub heading_scale: f32,
    /// `road_model::agent_pairs::PairScales` (state units).
    pub direction: f32,
    pub near: f32,
    pub far: f32,
    pub _pad: u32,
}

impl PairAttentionParams {
    /// The agent-attention params of a model with agent pairs for `scenes` scenes of `agents`.
    pub fn of(c: &road_model::ModelConfig, scenes: usize, agents: usize) -> Result<Self> {
        let (Some(pairs), Some(frame)) = (&c.agent_pairs, &c.agent_frame) else {
            return Err(Error::Input(
                "pair attention needs a model with agent_pairs and an agent_frame".into(),
            ));
        };
        let scales =
            road_model::agent_pairs::PairScales::new(pairs, c.position_scale_m, c.heading_scale);
        let head_dim = (c.hidden / c.heads) as u32;
        Ok(Self {
            groups: (scenes * c.window_slots) as u32,
            heads: c.heads as u32,
            head_dim,
            agents: agents as u32,
            slots: c.window_slots as u32,
            anchor_slot: frame.anchor_slot as u32,
            scale: 1.0 / (head_dim as f32).sqrt(),
            heading_scale: scales.heading_scale,
            direction: scales.direction,
            near: scales.near,
            far: scales.far,
            _pad: 0,
        })
    }

    pub fn threads(&self) -> u32 {
        self.groups * self.heads * self.agents
    }

    pub fn scales(&self) -> road_model::agent_pairs::PairScales {
        road_model::agent_pairs::PairScales {
            direction: self.direction,
            near: self.near,
            far: self.far,
            heading_scale: self.heading_scale,
        }
    }
}

#[derive(Debug)]
pub struct PairAttention(pub Pipeline);

impl PairAttention {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::AgentPairs, "pair_attention"))
    }

    /// Runs once: `q`, `k`, `v [B, A, W, D]`, `valid [B, A, W]`, `states [B, A, W, 3]`,
    /// `pair_k`, `pair_v [D, F]`, `agent_scene [B·A]` (agents attend to agents of their own
    /// scene only) → `[B, A, W, D]`.
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: PairAttentionParams,
        q: &[f32],
        k: &[f32],
        v: &[f32],
        valid: &[f32],
        states: &[f32],
        pair_k: &[f32],
        pair_v: &[f32],
        agent_scene: &[u32],
    ) -> Result<Vec<f32>> {
        let rows = (p.groups / p.slots.max(1) * p.agents) as usize;
        if agent_scene.len() != rows {
            return Err(Error::Input(format!(
                "pair attention: {} agent scenes for {rows} agent rows",
                agent_scene.len()
            )));
        }
        if p.head_dim > MAX_HEAD_DIM {
            return Err(Error::Input(format!(
                "head_dim {} exceeds {MAX_HEAD_DIM}",
                p.head_dim
            )));
        }
        self.0.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[
                q,
                k,
                v,
                valid,
                states,
                pair_k,
                pair_v,
                bytemuck::cast_slice(agent_scene),
            ],
            q.len(),
            p.threads(),
        )
    }
}
