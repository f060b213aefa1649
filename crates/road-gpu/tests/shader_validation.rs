//! Every `.wgsl` file under `shaders/` parses and validates with naga (no GPU needed), and every
//! one is embedded by `road_gpu::shaders`.

use std::path::{Path, PathBuf};

use road_gpu::shaders::Shader;

fn shader_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders")
}

fn wgsl_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in
        std::fs::read_dir(dir).unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
    {
        let path = entry.unwrap().path();
        if path.is_dir() {
            wgsl_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "wgsl") {
            out.push(path);
        }
    }
}

fn validate(name: &str, source: &str) {
    let module = naga::front::wgsl::parse_str(source)
        .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
}

#[test]
fn every_shader_file_validates() {
    let mut files = Vec::new();
    wgsl_files(&shader_dir(), &mut files);
    assert!(
        !files.is_empty(),
        "no shaders found under {}",
        shader_dir().display()
    );
    for path in &files {
        let source = std::fs::read_to_string(path).unwrap();
        // Helpers under shaders/common/ are prepended to kernel files (`Shader::includes`):
        // validated with them.
        if path.parent().is_some_and(|p| p.ends_with("common")) {
            continue;
        }
        let name = path.file_name().unwrap().to_string_lossy();
        let includes = Shader::ALL
            .iter()
            .find(|s| s.file_name() == name)
            .map_or(&[][..], |s| s.includes());
        validate(
            &path.display().to_string(),
            &format!("{}{source}", includes.concat()),
        );
    }
}

#[test]
fn every_kernel_file_is_embedded() {
    let mut files = Vec::new();
    wgsl_files(&shader_dir(), &mut files);
    for path in files
        .iter()
        .filter(|p| !p.parent().is_some_and(|p| p.ends_with("common")))
    {
        let name = path.file_name().unwrap().to_string_lossy();
        let shader = Shader::ALL.iter().find(|s| s.file_name() == name);
        let shader =
            shader.unwrap_or_else(|| panic!("{name} is not listed in road_gpu::shaders::Shader"));
        assert_eq!(
            shader.source(),
            format!(
                "{}{}",
                shader.includes().concat(),
                std::fs::read_to_string(path).unwrap()
            ),
            "{name} embedded copy differs"
        );
    }
}

/// Every entry point of every kernel family, with its helpers, also goes through naga's SPIR-V
/// writer as wgpu's Vulkan backend runs it (override constants at their defaults, one entry
/// point a module, SPIR-V 1.6 with indices clamped and loops bounded): the cooperative-matrix
/// family, which CI's lavapipe cannot compile (it offers no cooperative matrices), is at least
/// written out here, not first on a lent GPU.
#[test]
fn every_kernel_family_writes_spirv() {
    for shader in Shader::ALL {
        let source = shader.source();
        let name = shader.file_name();
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
        let info = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
        // As wgpu's Vulkan backend on a Vulkan 1.3 device without robust buffer access 2:
        // indices clamped, loops bounded.
        let restrict = naga::proc::BoundsCheckPolicy::Restrict;
        let options = naga::back::spv::Options {
            lang_version: (1, 6),
            bounds_check_policies: naga::proc::BoundsCheckPolicies {
                index: restrict,
                buffer: restrict,
                image_load: restrict,
                binding_array: naga::proc::BoundsCheckPolicy::Unchecked,
            },
            force_loop_bounding: true,
            ..naga::back::spv::Options::default()
        };
        for entry in &module.entry_points {
            let stage = (naga::ShaderStage::Compute, entry.name.as_str());
            let constants = naga::back::PipelineConstants::default();
            let (module, info) = naga::back::pipeline_constants::process_overrides(
                &module,
                &info,
                Some(stage),
                &constants,
            )
            .unwrap_or_else(|e| panic!("{name} {}: overrides: {e}", entry.name));
            let pipeline = naga::back::spv::PipelineOptions {
                shader_stage: naga::ShaderStage::Compute,
                entry_point: entry.name.clone(),
            };
            let words = naga::back::spv::write_vec(&module, &info, &options, Some(&pipeline))
                .unwrap_or_else(|e| panic!("{name} {}: SPIR-V: {e}", entry.name));
            assert!(words.len() > 5, "{name} {}: empty SPIR-V", entry.name);
            // For a look with `spirv-val --target-env vulkan1.3` where SPIR-V tools are installed.
            if let Some(dir) = std::env::var_os("ROAD_SPIRV_OUT") {
                let path = Path::new(&dir).join(format!("{}.spv", entry.name));
                std::fs::write(&path, bytemuck::cast_slice::<u32, u8>(&words)).unwrap();
            }
        }
    }
}
