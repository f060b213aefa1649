//! Every WGSL file under `shaders/`, embedded. One file per kernel family; naga validates them
//! all in a test (no GPU needed).

/// A kernel family and its source file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shader {
    /// EDM preconditioning coefficients per window slot.
    Edm,
    /// Linear layers (+ bias, optional ReLU; layer norm, residual add and split outputs fused).
    Linear,
    /// The map's polyline encoder: points to tokens in one workgroup per polyline.
    Polyline,
    /// Masked multi-head attention over strided token layouts.
    Attention,
    /// Token embeddings of the denoiser.
    Embed,
    /// Output preconditioning.
    Elementwise,
    /// The per-slot Heun step of the sampler.
    Heun,
    /// Window updates on the device: gather the emitted slot, shift after an emission.
    Window,
    /// Agent-centric maps: each agent's nearest polylines in its anchor frame.
    AgentMap,
    /// Agent attention with pair features (relative pose of every pair of agents).
    AgentPairs,
}

impl Shader {
    pub const ALL: [Shader; 10] = [
        Shader::Edm,
        Shader::Linear,
        Shader::Polyline,
        Shader::Attention,
        Shader::Embed,
        Shader::Elementwise,
        Shader::Heun,
        Shader::Window,
        Shader::AgentMap,
        Shader::AgentPairs,
    ];

    /// File name under `shaders/`.
    pub fn file_name(self) -> &'static str {
        match self {
            Shader::Edm => "edm.wgsl",
            Shader::Linear => "linear.wgsl",
            Shader::Polyline => "polyline.wgsl",
            Shader::Attention => "attention.wgsl",
            Shader::Embed => "embed.wgsl",
            Shader::Elementwise => "elementwise.wgsl",
            Shader::Heun => "heun.wgsl",
            Shader::Window => "window.wgsl",
            Shader::AgentMap => "agent_map.wgsl",
            Shader::AgentPairs => "agent_pairs.wgsl",
        }
    }

    pub fn source(self) -> &'static str {
        match self {
            Shader::Edm => include_str!("../../../shaders/edm.wgsl"),
            Shader::Linear => include_str!("../../../shaders/linear.wgsl"),
            Shader::Polyline => include_str!("../../../shaders/polyline.wgsl"),
            Shader::Attention => include_str!("../../../shaders/attention.wgsl"),
            Shader::Embed => include_str!("../../../shaders/embed.wgsl"),
            Shader::Elementwise => include_str!("../../../shaders/elementwise.wgsl"),
            Shader::Heun => include_str!("../../../shaders/heun.wgsl"),
            Shader::Window => include_str!("../../../shaders/window.wgsl"),
            Shader::AgentMap => include_str!("../../../shaders/agent_map.wgsl"),
            Shader::AgentPairs => include_str!("../../../shaders/agent_pairs.wgsl"),
        }
    }

    pub fn module_descriptor(self) -> wgpu::ShaderModuleDescriptor<'static> {
        wgpu::ShaderModuleDescriptor {
            label: Some(self.file_name()),
            source: wgpu::ShaderSource::Wgsl(self.source().into()),
        }
    }
}
