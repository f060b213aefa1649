//! The GPU engine's context options for every command that runs it, from the environment:
//! `ROAD_GPU_PRECISION` sets its arithmetic as `WGPU_ADAPTER_NAME` picks its adapter.

use anyhow::Result;
use road_gpu::ContextOptions;

/// The variable that sets the GPU engine's arithmetic for every command that runs it
/// (`f32`, the default, or `f16`: `road_gpu::Precision`), as `WGPU_ADAPTER_NAME` picks its
/// adapter.
pub const PRECISION_VAR: &str = "ROAD_GPU_PRECISION";

/// The GPU engine's context options: the defaults, with `ROAD_GPU_PRECISION` if set.
pub fn context_options() -> Result<ContextOptions> {
    let precision = match std::env::var(PRECISION_VAR) {
        Ok(value) => parse_precision(&value)?,
        Err(std::env::VarError::NotPresent) => road_gpu::Precision::F32,
        Err(e) => anyhow::bail!("{PRECISION_VAR}: {e}"),
    };
    Ok(ContextOptions {
        precision,
        ..ContextOptions::default()
    })
}

/// `ROAD_GPU_PRECISION`'s value; the error names the variable.
fn parse_precision(value: &str) -> Result<road_gpu::Precision> {
    value
        .parse()
        .map_err(|e: String| anyhow::anyhow!("{PRECISION_VAR}={value}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn precisions_parse_and_a_bad_one_names_the_variable() {
        assert_eq!(parse_precision("f16").unwrap(), road_gpu::Precision::F16);
        assert_eq!(parse_precision("f32").unwrap(), road_gpu::Precision::F32);
        let err = parse_precision("bf16").unwrap_err().to_string();
        assert!(err.contains("ROAD_GPU_PRECISION=bf16"), "{err}");
        assert!(err.contains("expected f32 or f16"), "{err}");
    }
}
