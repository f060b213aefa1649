//! `road-model`: the DJINN-style scene denoiser in candle (CPU), its training and checkpoints.
//! Sampling is a layer above (`road-rollout`), and so are the engines (`road-cpu`, `road-gpu`).
//!
//! - [`config`]: model, planner and training hyperparameters (`configs/<name>.toml`);
//! - [`batch`]: scene windows → padded tensors, and the training tasks' noise;
//! - [`model`]: the transformer and the EDM loss;
//! - [`train`]: AdamW, EMA, validation, checkpoints and exact resume;
//! - [`checkpoint`]: the on-disk format (`docs/checkpoint.md`);
//! - [`agent_map`], [`agent_pairs`]: agent-centric maps and agent–agent pair features, shared
//!   by every engine;
//! - [`plan_turn`]: a plan turned with a correction of its agent's state;
//! - [`torch_export`]: the datasets as flat arrays for the PyTorch training path
//!   (`docs/torch-training.md`).

pub mod agent_map;
pub mod agent_pairs;
pub mod batch;
pub mod checkpoint;
pub mod config;
pub mod fused;
pub mod model;
pub mod plan_turn;
pub mod torch_export;
pub mod train;

use std::path::{Path, PathBuf};

pub use config::{AgentFrame, AgentMap, AgentPairs, ModelConfig, RunConfig, TrainConfig};
pub use model::{Denoiser, MapTokens, Mode};

/// Errors of the model layer, and of the engine layers above it (`road-rollout`, `road-cpu`,
/// `road-gpu`), whose `StepEngine` calls return them.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("tensor operation failed: {0}")]
    Tensor(#[from] candle_core::Error),
    #[error(transparent)]
    Data(#[from] DataError),
    #[error("cannot read or write {path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("bad config: {reason} ({path})")]
    Config { path: PathBuf, reason: String },
    #[error("bad checkpoint: {reason} ({path})")]
    Checkpoint { path: PathBuf, reason: String },
    #[error("engine failed: {0}")]
    Engine(String),
    #[error("training worker {worker} failed: {message}")]
    Worker { worker: usize, message: String },
    #[error("training diverged: loss {loss} at step {step}")]
    Diverged { step: u64, loss: f64 },
}

/// Data problems met while training or sampling.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error(transparent)]
    Dataset(#[from] road_data::Error),
    #[error("{0}")]
    Mismatch(String),
}

impl Error {
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_owned(),
            source,
        }
    }

    pub fn data(reason: String) -> Self {
        Self::Data(DataError::Mismatch(reason))
    }
}

impl From<road_sched::Error> for Error {
    fn from(e: road_sched::Error) -> Self {
        Error::data(format!("scheduler: {e}"))
    }
}

impl From<road_data::Error> for Error {
    fn from(e: road_data::Error) -> Self {
        Self::Data(DataError::Dataset(e))
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
