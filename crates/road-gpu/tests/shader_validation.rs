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
