//! `road-gpu`: the denoiser's compute kernels in WGSL, run through wgpu.
//!
//! - [`context`]: adapter selection (GPU, else lavapipe; `WGPU_BACKEND`, `WGPU_ADAPTER_NAME`);
//! - [`engine`]: a checkpoint's denoiser and the Heun step as a chain of kernels, batched;
//! - [`step_engine`]: the rollout driver's engine over them (windows kept on the device);
//! - [`shaders`]: the embedded `shaders/*.wgsl` files;
//! - [`kernels`]: one module per kernel family;
//! - [`profile`]: a step's device time by kernel (for `road bench engine --profile`);
//! - [`proxies`]: dispatches, binding bytes and padding per evaluation (no GPU needed);
//! - [`reference`]: the kernels' CPU references (plain f64 loops);
//! - [`selftest`]: every kernel family against its reference on the adapter at hand;
//! - [`tolerance`]: the relative + absolute tolerance every parity test uses;
//! - [`tune`]: the autotuner: each way to run an evaluation timed per batch size, cached per
//!   adapter;
//! - [`tuning`]: its tables and cache file, by which the engine runs an evaluation.

pub mod context;
pub mod engine;
pub mod kernels;
pub mod profile;
pub mod proxies;
pub mod reference;
pub mod sampler_step;
pub mod selftest;
pub mod shaders;
pub mod step_engine;
pub mod tolerance;
pub mod tune;
pub mod tuning;

pub use context::{
    ContextOptions, CooperativeF16, GpuContext, Precision, cooperative_f16, hardware_adapter,
};
pub use tolerance::Tolerance;

/// Errors of the GPU layer.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("no GPU adapter found: {0}")]
    NoAdapter(&'static str),
    #[error("no adapter matches WGPU_ADAPTER_NAME=`{wanted}`; available: {available}")]
    NoMatchingAdapter { wanted: String, available: String },
    #[error("cannot open the device: {0}")]
    Device(String),
    #[error("waiting for the GPU failed: {0}")]
    Poll(String),
    #[error("reading results back failed: {0}")]
    Readback(String),
    #[error("cannot use the checkpoint: {0}")]
    Checkpoint(String),
    /// The model layer's error names the file; kept as the source so its cause prints too.
    #[error("cannot load the checkpoint")]
    CheckpointLoad(#[source] road_model::Error),
    /// Inputs whose sizes do not match the prepared batch.
    #[error("engine input: {0}")]
    Input(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
