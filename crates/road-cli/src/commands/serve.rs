//! `road serve`: the networked NPC server (`road-serve`) over Eclipse Zenoh. With no
//! arguments it runs the default checkpoint `road20-wide4` from `models/` (in the working directory,
//! next to the binary, or `--models` / `ROAD_MODELS`), peer mode with zenoh's defaults, and
//! records every scene under `recordings/`. With `--foxglove ADDR` Foxglove can watch every live
//! scene at `ws://ADDR` (the live view, `docs/protocol.md`). SIGINT and SIGTERM close every
//! scene (and finish its recording) before the process ends.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use road_serve::models::find_models_dir;
use road_serve::{ServeConfig, Server, ZenohArgs};

#[derive(Debug, Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// Key expressions live under this prefix.
    #[arg(long, default_value = road_protocol::DEFAULT_PREFIX)]
    pub prefix: String,
    /// The checkpoints' folder (default: `models/` here or next to the binary).
    #[arg(long, env = "ROAD_MODELS")]
    pub models: Option<PathBuf>,
    /// The checkpoint of requests that name none.
    #[arg(long, default_value = road_serve::config::DEFAULT_CHECKPOINT)]
    pub checkpoint: String,
    /// The initialiser of `populate` requests that name none (`populate.initialiser`): a
    /// checkpoint trained to draw whole vehicles; `none`: placed vehicles are only refined by
    /// the scene's checkpoint.
    #[arg(long, default_value = road_serve::config::DEFAULT_INITIALISER)]
    pub initialiser: String,
    /// Where scenes are recorded (`scene-<id>.mcap`).
    #[arg(long, default_value = "recordings")]
    pub record: PathBuf,
    /// Do not record.
    #[arg(long)]
    pub no_record: bool,
    /// Live scenes at most.
    #[arg(long, default_value_t = 256)]
    pub capacity: usize,
    /// Milliseconds to wait for a tick's ego before the model drives it (flagged); 0 waits
    /// forever.
    #[arg(long, default_value_t = 1000)]
    pub late_ego_ms: u64,
    /// Seconds without a word from a scene's client (since the server last published to it)
    /// before the scene is closed as `client_silent`, whatever the model drove meanwhile.
    #[arg(long, default_value_t = 30.0)]
    pub idle_timeout_s: f64,
    /// Ticks in a row the model may drive a scene's external agents for want of its ego
    /// before the scene is closed as `client_silent`.
    #[arg(long, default_value_t = 300)]
    pub max_late_ticks: u64,
    /// Largest payload accepted, bytes.
    #[arg(long, default_value_t = 8 << 20)]
    pub max_payload_bytes: usize,
    /// A Lanelet2 map requests may name (`map.file`): `NAME=FILE.osm`; repeatable.
    #[arg(long = "map", value_name = "NAME=FILE")]
    pub maps: Vec<String>,
    /// Serve a live view to Foxglove on this address (e.g. `127.0.0.1:8765`; Foxglove opens
    /// `ws://ADDR`): every live scene's map and agent boxes. Off by default.
    #[arg(long, value_name = "ADDR")]
    pub foxglove: Option<SocketAddr>,
    /// What the model runs on: `auto` (the default), the GPU engine where wgpu finds a
    /// hardware GPU and the fast CPU engine otherwise; `cpu`, the fast CPU engine (the lowest
    /// latency for a few scenes); or `gpu`, the WGSL kernels on the GPU wgpu picks (more scenes
    /// per machine: an H100 served 2.2× 16 Xeon cores at 16 scenes and 7.6× at 512, the cores
    /// 2.3× faster at one scene; lavapipe without a GPU, slow).
    #[arg(long, value_enum, default_value_t = ServeEngineArg::Auto)]
    pub engine: ServeEngineArg,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ServeEngineArg {
    Auto,
    Cpu,
    Gpu,
}

impl ServeEngineArg {
    /// The engine to serve on; `auto` looks for a hardware GPU ([`road_gpu::hardware_adapter`]).
    pub fn resolve(self) -> road_serve::ServeEngine {
        match self {
            Self::Cpu => road_serve::ServeEngine::Cpu,
            Self::Gpu => road_serve::ServeEngine::Gpu,
            Self::Auto => auto_engine(road_gpu::hardware_adapter()),
        }
    }
}

/// `--engine auto`'s choice given the hardware GPU found, if any: a GPU service serves on its
/// GPU (in lockstep from 16 scenes an H100 served 2.2–7.6× what 16 cores did, and a scene's
/// tick, 3.8 ms, is well inside its 100 ms), the CPU engine everywhere else (lavapipe is slow).
fn auto_engine(hardware: Option<String>) -> road_serve::ServeEngine {
    match hardware {
        Some(adapter) => {
            tracing::info!(%adapter, "--engine auto: a hardware GPU, the GPU engine");
            road_serve::ServeEngine::Gpu
        }
        None => {
            tracing::info!("--engine auto: no hardware GPU, the fast CPU engine");
            road_serve::ServeEngine::Cpu
        }
    }
}

pub fn run(args: ServeArgs) -> Result<ExitCode> {
    let models = find_models_dir(args.models.as_deref())?;
    let mut config = ServeConfig::new(models);
    let prefix = args.prefix.trim_matches('/').to_owned();
    config.prefix = args.prefix;
    config.default_checkpoint = args.checkpoint;
    config.default_initialiser = (args.initialiser != "none").then_some(args.initialiser);
    config.record_dir = (!args.no_record).then_some(args.record);
    config.capacity = args.capacity;
    config.late_ego_deadline = Duration::from_millis(args.late_ego_ms);
    anyhow::ensure!(
        args.idle_timeout_s.is_finite() && args.idle_timeout_s > 0.0,
        "--idle-timeout-s must be positive, got {}",
        args.idle_timeout_s
    );
    config.idle_timeout = Duration::from_secs_f64(args.idle_timeout_s);
    anyhow::ensure!(
        args.max_late_ticks >= 1,
        "--max-late-ticks {} must be at least 1",
        args.max_late_ticks
    );
    config.max_consecutive_late_ticks = args.max_late_ticks;
    config.max_payload_bytes = args.max_payload_bytes;
    config.foxglove_listen = args.foxglove;
    config.engine = args.engine.resolve();
    config.gpu_precision = crate::commands::gpu_options::context_options()?.precision;
    for item in &args.maps {
        let (name, path) = item
            .split_once('=')
            .with_context(|| format!("--map {item}: expected NAME=FILE"))?;
        config
            .map_files
            .push((name.to_owned(), PathBuf::from(path)));
    }
    let zenoh = args.zenoh.to_config()?;
    let stop = crate::signals::termination()?;
    let server = Server::new(config, zenoh)
        .start()
        .context("cannot start the server")?;
    for endpoint in server.listen_endpoints() {
        out!("road serve: listening on {endpoint}");
    }
    out!(
        "road serve: keys under {prefix}/, zenoh id {}",
        server.session().zid()
    );
    if let Some(addr) = server.foxglove_addr() {
        out!("road serve: Foxglove live view on ws://{addr}");
    }
    while server.is_running() {
        if let Ok(signal) = stop.recv_timeout(Duration::from_millis(200)) {
            tracing::info!("{signal}: closing every scene and its recording");
            server.stop()?;
            return Ok(ExitCode::SUCCESS);
        }
    }
    server.join()?;
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_serves_on_a_hardware_gpu_only() {
        assert_eq!(
            auto_engine(Some("NVIDIA H100 80GB HBM3 (DiscreteGpu, Vulkan)".into())),
            road_serve::ServeEngine::Gpu
        );
        assert_eq!(auto_engine(None), road_serve::ServeEngine::Cpu);
        assert_eq!(ServeEngineArg::Cpu.resolve(), road_serve::ServeEngine::Cpu);
        assert_eq!(ServeEngineArg::Gpu.resolve(), road_serve::ServeEngine::Gpu);
    }
}
