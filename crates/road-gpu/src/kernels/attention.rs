//! `shaders/attention.wgsl`: masked multi-head attention over strided token layouts.

use bytemuck::{Pod, Zeroable};

use super::Pipeline;
use crate::shaders::Shader;
use crate::{GpuContext, Result};

/// Where group `n`'s token `l` lives, in rows of D floats:
/// `(n / inner_count) · outer_stride + (n % inner_count) · inner_stride + l · token_stride`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
pub struct TokenLayout {
    pub inner_count: u32,
    pub outer_stride: u32,
    pub inner_stride: u32,
    pub token_stride: u32,
}

impl TokenLayout {
    /// Contiguous `[groups, tokens, D]`.
    pub fn contiguous(tokens: u32) -> Self {
        Self {
            inner_count: 1,
            outer_stride: tokens,
            inner_stride: 0,
            token_stride: 1,
        }
    }

    pub fn row(&self, group: u32, token: u32) -> u32 {
        (group / self.inner_count) * self.outer_stride
            + (group % self.inner_count) * self.inner_stride
            + token * self.token_stride
    }
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct AttentionParams {
    pub groups: u32,
    pub heads: u32,
    pub head_dim: u32,
    pub queries: u32,
    pub keys: u32,
    pub scale: f32,
    /// Agent rows per batch scene, for [`SceneMode::AgentsOfOneScene`].
    pub scene_agents: u32,
    /// A [`SceneMode`] as `u32`.
    pub scene_mode: u32,
    pub q_layout: TokenLayout,
    pub kv_layout: TokenLayout,
    pub mask_layout: TokenLayout,
}

/// How packed scenes (several scenes' agents in one batch scene, each agent row tagged with its
/// own scene: `agent_scene`) are kept apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum SceneMode {
    /// Groups do not mix scenes (attention over time, over an agent's own map).
    None = 0,
    /// Agent attention: group `n`'s token `l` is agent row `(n / inner_count) · scene_agents +
    /// l` (for the query's and the keys' layouts); keys of another scene carry no weight.
    AgentsOfOneScene = 1,
    /// Group `n` is agent row `n`; its keys, values and key flags are group `agent_scene[n]`'s
    /// (the scene-frame map of the agent's own scene).
    KeysOfTheAgentsScene = 2,
}

/// Largest head size the kernel's private accumulator holds.
pub const MAX_HEAD_DIM: u32 = 64;

impl AttentionParams {
    pub fn threads(&self) -> u32 {
        self.groups * self.heads * self.queries
    }
}

#[derive(Debug)]
pub struct Attention(pub Pipeline);

impl Attention {
    pub fn new(ctx: &GpuContext) -> Self {
        Self(Pipeline::new(ctx, Shader::Attention, "attention"))
    }

    /// Runs once; the output has the query tensor's size (and layout; rows no query touches
    /// stay 0). `agent_scene`: each agent row's scene (read under a [`SceneMode`] other than
    /// `None`; at least one entry).
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        ctx: &GpuContext,
        p: AttentionParams,
        q: &[f32],
        k: &[f32],
        v: &[f32],
        key_valid: &[f32],
        agent_scene: &[u32],
    ) -> Result<Vec<f32>> {
        assert!(
            p.head_dim <= MAX_HEAD_DIM,
            "head_dim {} exceeds {MAX_HEAD_DIM}",
            p.head_dim
        );
        self.0.run_once(
            ctx,
            bytemuck::bytes_of(&p),
            &[q, k, v, key_valid, bytemuck::cast_slice(agent_scene)],
            q.len(),
            p.threads(),
        )
    }
}
