//! Every WGSL file under `shaders/`, embedded. One file per kernel family; naga validates them
//! all in a test (no GPU needed). Helpers under `shaders/common/` are prepended to the families
//! that use them ([`Shader::includes`]): WGSL has no includes of its own.

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
    /// The residual chain: output projection, MLP and the next layer in one kernel.
    ResidualChain,
}

/// `shaders/common/precondition.wgsl`: the output preconditioning of one token.
const PRECONDITION: &str = include_str!("../../../shaders/common/precondition.wgsl");

impl Shader {
    pub const ALL: [Shader; 11] = [
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
        Shader::ResidualChain,
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
            Shader::ResidualChain => "residual_chain.wgsl",
        }
    }

    pub fn source(self) -> &'static str {
        match self {
            Shader::Edm => include_str!("../../../shaders/edm.wgsl"),
            Shader::Linear => include_str!("../../../shaders/linear.wgsl"),
            Shader::Polyline => include_str!("../../../shaders/polyline.wgsl"),
            Shader::Attention => include_str!("../../../shaders/attention.wgsl"),
            Shader::Embed => include_str!("../../../shaders/embed.wgsl"),
            Shader::Elementwise => concat!(
                include_str!("../../../shaders/common/precondition.wgsl"),
                include_str!("../../../shaders/elementwise.wgsl")
            ),
            Shader::Heun => include_str!("../../../shaders/heun.wgsl"),
            Shader::Window => include_str!("../../../shaders/window.wgsl"),
            Shader::AgentMap => include_str!("../../../shaders/agent_map.wgsl"),
            Shader::AgentPairs => include_str!("../../../shaders/agent_pairs.wgsl"),
            Shader::ResidualChain => concat!(
                include_str!("../../../shaders/common/precondition.wgsl"),
                include_str!("../../../shaders/residual_chain.wgsl")
            ),
        }
    }

    /// The helpers of `shaders/common/` prepended to this family's file, in order: its
    /// [`Self::source`] is theirs followed by the file's.
    pub fn includes(self) -> &'static [&'static str] {
        match self {
            Shader::Elementwise | Shader::ResidualChain => &[PRECONDITION],
            _ => &[],
        }
    }

    pub fn module_descriptor(self) -> wgpu::ShaderModuleDescriptor<'static> {
        wgpu::ShaderModuleDescriptor {
            label: Some(self.file_name()),
            source: wgpu::ShaderSource::Wgsl(self.source().into()),
        }
    }
}
