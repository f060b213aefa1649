//! Checkpoints: a folder with
//! - `config.toml`: [`CheckpointMeta`] (every hyperparameter, data identity, step count);
//! - `weights.safetensors`: the EMA weights inference uses (f32, names = module paths);
//! - `train_state.safetensors`: raw weights and AdamW moments, for `--resume`.
//!
//! The layout is written down in `docs/checkpoint.md`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};

use crate::config::RunConfig;
use crate::model::Denoiser;
use crate::{Error, Result};

pub const META_FILE: &str = "config.toml";
pub const WEIGHTS_FILE: &str = "weights.safetensors";
pub const TRAIN_STATE_FILE: &str = "train_state.safetensors";

/// What identifies the training data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataIdentity {
    pub train_cache: String,
    pub train_windows: usize,
    pub validation_windows: usize,
    pub source: String,
}

/// Everything saved next to the weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointMeta {
    pub run: RunConfig,
    pub data: DataIdentity,
    /// Optimiser steps taken.
    pub step: u64,
    pub parameters: usize,
    pub wall_secs: f64,
    pub hardware: String,
    /// Validation loss of the EMA weights at `step` and of the untrained model.
    pub validation_loss: Option<f64>,
    pub untrained_validation_loss: Option<f64>,
}

impl CheckpointMeta {
    pub fn load(dir: &Path) -> Result<Self> {
        let path = dir.join(META_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let meta: Self = toml::from_str(&text).map_err(|e| Error::Checkpoint {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        meta.run
            .validate()
            .map_err(|reason| Error::Checkpoint { path, reason })?;
        Ok(meta)
    }

    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let path = dir.join(META_FILE);
        let text = toml::to_string_pretty(self).map_err(|e| Error::Checkpoint {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        write_atomic(&path, text.as_bytes())
    }
}

pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// Saves named tensors as safetensors, atomically.
pub fn save_tensors(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<()> {
    let tmp: PathBuf = path.with_extension("tmp");
    candle_core::safetensors::save(tensors, &tmp)?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

pub fn load_tensors(path: &Path, device: &Device) -> Result<HashMap<String, Tensor>> {
    if !path.is_file() {
        return Err(Error::Checkpoint {
            path: path.to_owned(),
            reason: "file not found".into(),
        });
    }
    candle_core::safetensors::load(path, device).map_err(|e| Error::Checkpoint {
        path: path.to_owned(),
        reason: e.to_string(),
    })
}

/// Checks that `tensors` holds exactly the variables of `varmap` with the same shapes.
pub fn check_against(
    varmap: &VarMap,
    tensors: &HashMap<String, Tensor>,
    path: &Path,
) -> Result<()> {
    let missing = check_fit(varmap, tensors, path)?;
    if missing.is_empty() {
        Ok(())
    } else {
        Err(Error::Checkpoint {
            path: path.to_owned(),
            reason: format!(
                "weights do not match the config: {}",
                missing
                    .iter()
                    .map(|name| format!("missing tensor `{name}`"))
                    .collect::<Vec<_>>()
                    .join("; ")
            ),
        })
    }
}

/// Checks that every tensor of `tensors` is one of the config's, with its shape, and returns
/// the config's tensors that `tensors` lacks (sorted): `train.init_from` starts those from
/// their initialisation (a model that gains a part), where loading a checkpoint refuses them.
pub fn check_fit(
    varmap: &VarMap,
    tensors: &HashMap<String, Tensor>,
    path: &Path,
) -> Result<Vec<String>> {
    let vars = varmap.data().lock().expect("var map lock");
    let mut problems = Vec::new();
    let mut missing = Vec::new();
    for (name, var) in vars.iter() {
        match tensors.get(name) {
            None => missing.push(name.clone()),
            Some(t) if t.dims() != var.dims() => problems.push(format!(
                "tensor `{name}` has shape {:?}, the config needs {:?}",
                t.dims(),
                var.dims()
            )),
            Some(_) => {}
        }
    }
    for name in tensors.keys() {
        if !vars.contains_key(name) {
            problems.push(format!("unexpected tensor `{name}`"));
        }
    }
    if missing.len() == vars.len() && !vars.is_empty() {
        problems.push("none of the config's tensors".into());
    }
    missing.sort();
    if problems.is_empty() {
        Ok(missing)
    } else {
        problems.sort();
        Err(Error::Checkpoint {
            path: path.to_owned(),
            reason: format!("weights do not match the config: {}", problems.join("; ")),
        })
    }
}

/// A loaded checkpoint ready for inference.
#[derive(Debug)]
pub struct LoadedModel {
    pub meta: CheckpointMeta,
    pub model: Denoiser,
}

/// Loads `config.toml` and the EMA weights, checking every tensor against the config.
pub fn load(dir: &Path, device: &Device) -> Result<LoadedModel> {
    let meta = CheckpointMeta::load(dir)?;
    let path = dir.join(WEIGHTS_FILE);
    let tensors = load_tensors(&path, device)?;
    build(meta, tensors, &path, device)
}

/// A checkpoint held in memory (a binary's embedded default): the text of its `config.toml`
/// and the bytes of its `weights.safetensors`. `origin` names it in errors, in place of the
/// folder.
pub fn load_from_memory(
    origin: &Path,
    config_toml: &str,
    weights: &[u8],
    device: &Device,
) -> Result<LoadedModel> {
    let meta_path = origin.join(META_FILE);
    let meta: CheckpointMeta = toml::from_str(config_toml).map_err(|e| Error::Checkpoint {
        path: meta_path.clone(),
        reason: e.to_string(),
    })?;
    meta.run.validate().map_err(|reason| Error::Checkpoint {
        path: meta_path,
        reason,
    })?;
    let path = origin.join(WEIGHTS_FILE);
    let tensors =
        candle_core::safetensors::load_buffer(weights, device).map_err(|e| Error::Checkpoint {
            path: path.clone(),
            reason: e.to_string(),
        })?;
    build(meta, tensors, &path, device)
}

fn build(
    meta: CheckpointMeta,
    tensors: HashMap<String, Tensor>,
    path: &Path,
    device: &Device,
) -> Result<LoadedModel> {
    let (varmap, _) = crate::model::init(&meta.run.model, device)?;
    check_against(&varmap, &tensors, path)?;
    let vb = VarBuilder::from_tensors(tensors, DType::F32, device);
    let model = Denoiser::new(&meta.run.model, vb)?;
    Ok(LoadedModel { meta, model })
}
