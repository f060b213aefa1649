//! The GPU engine's context options for every command that runs it, from the environment:
//! `ROAD_GPU_PRECISION` sets its arithmetic as `WGPU_ADAPTER_NAME` picks its adapter, and
//! `ROAD_GPU_MAP_KEYS` whether it keeps the map's keys between evaluations.

use anyhow::Result;
use road_gpu::ContextOptions;

/// The variable that sets the GPU engine's arithmetic for every command that runs it
/// (`f32`, the default, or `f16`: `road_gpu::Precision`), as `WGPU_ADAPTER_NAME` picks its
/// adapter.
pub const PRECISION_VAR: &str = "ROAD_GPU_PRECISION";

/// The variable that says whether the GPU engine keeps the map's keys from one evaluation to
/// the next while what they are made from holds (`kept`, the default) or makes them every
/// evaluation (`remade`: `ContextOptions::keep_map_keys` off), to time one against the other.
pub const MAP_KEYS_VAR: &str = "ROAD_GPU_MAP_KEYS";

/// The GPU engine's context options: the defaults, with `ROAD_GPU_PRECISION` and
/// `ROAD_GPU_MAP_KEYS` if set.
pub fn context_options() -> Result<ContextOptions> {
    let precision = match std::env::var(PRECISION_VAR) {
        Ok(value) => parse_precision(&value)?,
        Err(std::env::VarError::NotPresent) => road_gpu::Precision::F32,
        Err(e) => anyhow::bail!("{PRECISION_VAR}: {e}"),
    };
    let keep_map_keys = match std::env::var(MAP_KEYS_VAR) {
        Ok(value) => parse_map_keys(&value)?,
        Err(std::env::VarError::NotPresent) => true,
        Err(e) => anyhow::bail!("{MAP_KEYS_VAR}: {e}"),
    };
    Ok(ContextOptions {
        precision,
        keep_map_keys,
        ..ContextOptions::default()
    })
}

/// `ROAD_GPU_MAP_KEYS`'s value: whether the keys are kept; the error names the variable.
fn parse_map_keys(value: &str) -> Result<bool> {
    match value {
        "kept" => Ok(true),
        "remade" => Ok(false),
        other => anyhow::bail!("{MAP_KEYS_VAR}={other}: expected kept or remade"),
    }
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

    #[test]
    fn map_key_settings_parse_and_a_bad_one_names_the_variable() {
        assert!(parse_map_keys("kept").unwrap());
        assert!(!parse_map_keys("remade").unwrap());
        let err = parse_map_keys("never").unwrap_err().to_string();
        assert!(err.contains("ROAD_GPU_MAP_KEYS=never"), "{err}");
        assert!(err.contains("expected kept or remade"), "{err}");
    }
}
