//! Every WGSL file under `shaders/`, embedded. One file per kernel family; naga validates them
//! all in a test (no GPU needed).

/// A kernel family and its source file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shader {
    /// EDM preconditioning coefficients per window slot.
    Edm,
}

impl Shader {
    pub const ALL: [Shader; 1] = [Shader::Edm];

    /// File name under `shaders/`.
    pub fn file_name(self) -> &'static str {
        match self {
            Shader::Edm => "edm.wgsl",
        }
    }

    pub fn source(self) -> &'static str {
        match self {
            Shader::Edm => include_str!("../../../shaders/edm.wgsl"),
        }
    }

    pub fn module_descriptor(self) -> wgpu::ShaderModuleDescriptor<'static> {
        wgpu::ShaderModuleDescriptor {
            label: Some(self.file_name()),
            source: wgpu::ShaderSource::Wgsl(self.source().into()),
        }
    }
}
