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
    /// The same layers with f16 weights and inputs, f32 sums, on any adapter with `SHADER_F16`.
    LinearF16,
    /// The same on the tensor cores (cooperative matrices): compiled only where offered.
    LinearCoop,
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
    /// The residual chain: output projection, MLP and the next layer in one kernel (or the
    /// token embedding and the first layer).
    ResidualChain,
    /// Compact sub-batches: a batch's rows gathered in and scattered back.
    Compact,
}

/// `shaders/common/precondition.wgsl`: the output preconditioning of one token.
const PRECONDITION: &str = include_str!("../../../shaders/common/precondition.wgsl");
/// `shaders/common/embed_token.wgsl`: one value of the token embedding.
const EMBED_TOKEN: &str = include_str!("../../../shaders/common/embed_token.wgsl");
/// `shaders/common/pair_features.wgsl`: the features of a pair of agents.
const PAIR_FEATURES: &str = include_str!("../../../shaders/common/pair_features.wgsl");
/// `shaders/common/online_softmax.wgsl`: the attention kernels' online softmax.
const ONLINE_SOFTMAX: &str = include_str!("../../../shaders/common/online_softmax.wgsl");
/// `shaders/common/linear_io.wgsl`: the linear kernels' params, bindings and epilogue.
const LINEAR_IO: &str = include_str!("../../../shaders/common/linear_io.wgsl");
/// `shaders/common/enable_f16.wgsl`: `enable f16;`, first in the f16 families.
const ENABLE_F16: &str = include_str!("../../../shaders/common/enable_f16.wgsl");
/// `shaders/common/enable_cooperative_matrix.wgsl`: `enable wgpu_cooperative_matrix;`.
const ENABLE_COOPERATIVE_MATRIX: &str =
    include_str!("../../../shaders/common/enable_cooperative_matrix.wgsl");

impl Shader {
    pub const ALL: [Shader; 14] = [
        Shader::Edm,
        Shader::Linear,
        Shader::LinearF16,
        Shader::LinearCoop,
        Shader::Polyline,
        Shader::Attention,
        Shader::Embed,
        Shader::Elementwise,
        Shader::Heun,
        Shader::Window,
        Shader::AgentMap,
        Shader::AgentPairs,
        Shader::ResidualChain,
        Shader::Compact,
    ];

    /// File name under `shaders/`.
    pub fn file_name(self) -> &'static str {
        match self {
            Shader::Edm => "edm.wgsl",
            Shader::Linear => "linear.wgsl",
            Shader::LinearF16 => "linear_f16.wgsl",
            Shader::LinearCoop => "linear_coop.wgsl",
            Shader::Polyline => "polyline.wgsl",
            Shader::Attention => "attention.wgsl",
            Shader::Embed => "embed.wgsl",
            Shader::Elementwise => "elementwise.wgsl",
            Shader::Heun => "heun.wgsl",
            Shader::Window => "window.wgsl",
            Shader::AgentMap => "agent_map.wgsl",
            Shader::AgentPairs => "agent_pairs.wgsl",
            Shader::ResidualChain => "residual_chain.wgsl",
            Shader::Compact => "compact.wgsl",
        }
    }

    pub fn source(self) -> &'static str {
        match self {
            Shader::Edm => include_str!("../../../shaders/edm.wgsl"),
            Shader::Linear => concat!(
                include_str!("../../../shaders/common/linear_io.wgsl"),
                include_str!("../../../shaders/linear.wgsl")
            ),
            Shader::LinearF16 => concat!(
                include_str!("../../../shaders/common/enable_f16.wgsl"),
                include_str!("../../../shaders/common/linear_io.wgsl"),
                include_str!("../../../shaders/linear_f16.wgsl")
            ),
            Shader::LinearCoop => concat!(
                include_str!("../../../shaders/common/enable_f16.wgsl"),
                include_str!("../../../shaders/common/enable_cooperative_matrix.wgsl"),
                include_str!("../../../shaders/common/linear_io.wgsl"),
                include_str!("../../../shaders/linear_coop.wgsl")
            ),
            Shader::Polyline => include_str!("../../../shaders/polyline.wgsl"),
            Shader::Attention => concat!(
                include_str!("../../../shaders/common/online_softmax.wgsl"),
                include_str!("../../../shaders/attention.wgsl")
            ),
            Shader::Embed => concat!(
                include_str!("../../../shaders/common/embed_token.wgsl"),
                include_str!("../../../shaders/embed.wgsl")
            ),
            Shader::Elementwise => concat!(
                include_str!("../../../shaders/common/precondition.wgsl"),
                include_str!("../../../shaders/elementwise.wgsl")
            ),
            Shader::Heun => include_str!("../../../shaders/heun.wgsl"),
            Shader::Window => include_str!("../../../shaders/window.wgsl"),
            Shader::AgentMap => include_str!("../../../shaders/agent_map.wgsl"),
            Shader::AgentPairs => concat!(
                include_str!("../../../shaders/common/pair_features.wgsl"),
                include_str!("../../../shaders/common/online_softmax.wgsl"),
                include_str!("../../../shaders/agent_pairs.wgsl")
            ),
            Shader::ResidualChain => concat!(
                include_str!("../../../shaders/common/precondition.wgsl"),
                include_str!("../../../shaders/common/embed_token.wgsl"),
                include_str!("../../../shaders/common/pair_features.wgsl"),
                include_str!("../../../shaders/common/online_softmax.wgsl"),
                include_str!("../../../shaders/residual_chain.wgsl")
            ),
            Shader::Compact => include_str!("../../../shaders/compact.wgsl"),
        }
    }

    /// The helpers of `shaders/common/` prepended to this family's file, in order: its
    /// [`Self::source`] is theirs followed by the file's.
    pub fn includes(self) -> &'static [&'static str] {
        match self {
            Shader::Elementwise => &[PRECONDITION],
            Shader::ResidualChain => &[PRECONDITION, EMBED_TOKEN, PAIR_FEATURES, ONLINE_SOFTMAX],
            Shader::AgentPairs => &[PAIR_FEATURES, ONLINE_SOFTMAX],
            Shader::Attention => &[ONLINE_SOFTMAX],
            Shader::Embed => &[EMBED_TOKEN],
            Shader::Linear => &[LINEAR_IO],
            Shader::LinearF16 => &[ENABLE_F16, LINEAR_IO],
            Shader::LinearCoop => &[ENABLE_F16, ENABLE_COOPERATIVE_MATRIX, LINEAR_IO],
            _ => &[],
        }
    }

    /// The device features a module of this family needs beyond WebGPU's core.
    pub fn required_features(self) -> wgpu::Features {
        match self {
            Shader::LinearF16 => wgpu::Features::SHADER_F16,
            Shader::LinearCoop => {
                wgpu::Features::SHADER_F16 | wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX
            }
            _ => wgpu::Features::empty(),
        }
    }

    pub fn module_descriptor(self) -> wgpu::ShaderModuleDescriptor<'static> {
        wgpu::ShaderModuleDescriptor {
            label: Some(self.file_name()),
            source: wgpu::ShaderSource::Wgsl(self.source().into()),
        }
    }
}
