//! The server's settings. The zenoh session's own config (json5 file and the zenoh examples'
//! flags) is [`ZenohArgs`], shared with the clients.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

pub use road_client::ZenohArgs;

/// The checkpoint (a folder under `models/`) of requests that name none: RoAD-20 with agent maps,
/// agent pairs and the constant-velocity residual at width 96: the best of the shipped ones
/// (`docs/results.md`).
pub const DEFAULT_CHECKPOINT: &str = "road20-wide4";
/// The initialiser `CreateScene.populate` uses when the request names none: trained to draw
/// whole vehicles around given ones (issue 39), embedded in the binary.
pub const DEFAULT_INITIALISER: &str = "road20-init";

/// What a server allows and where it records. `Default` is what `road serve` runs with.
#[derive(Debug, Clone)]
pub struct ServeConfig {
    /// Key expressions live under this prefix.
    pub prefix: String,
    /// Live scenes at most; a creation beyond is refused.
    pub capacity: usize,
    /// Payloads larger than this are refused unread.
    pub max_payload_bytes: usize,
    /// After publishing tick t − 1 the server waits this long for tick t's ego, then lets the
    /// model drive the external agents for tick t (flagged in the reply). Zero: wait forever.
    pub late_ego_deadline: Duration,
    /// A scene whose client has said nothing for this long since the server last gave it
    /// something to answer is closed (`client_silent`), whatever the model drove meanwhile.
    pub idle_timeout: Duration,
    /// A scene whose external agents the model drove this many ticks in a row for want of
    /// the client's ego is closed (`client_silent`).
    pub max_consecutive_late_ticks: u64,
    /// Ticks a scene may run at most (and the default of a request's `max_ticks`).
    pub max_ticks: u64,
    /// Agents per scene at most (the windows the model was trained on held 32).
    pub max_agents: usize,
    /// An external agent moving faster than this between two ticks is refused.
    pub max_external_speed_mps: f64,
    /// Where scenes are recorded (`scene-<id>.mcap`); `None`: not recorded.
    pub record_dir: Option<PathBuf>,
    /// Recordings write out their chunk at least this often.
    pub flush_interval: Duration,
    /// The checkpoints' folder (`None`: only the embedded default) and the checkpoint a
    /// request without `checkpoint` gets.
    pub models_dir: Option<PathBuf>,
    pub default_checkpoint: String,
    /// The initialiser of `populate` requests that name none (`populate.initialiser`), used
    /// where it fits the scene's checkpoint; `None`: their placement refined by the scene's
    /// checkpoint only.
    pub default_initialiser: Option<String>,
    /// Map files the server was started with, by the name a request uses (`map.file`).
    pub map_files: Vec<(String, PathBuf)>,
    /// Where the live view (a Foxglove WebSocket server, [`crate::live`]) listens; `None`: no
    /// live view. Port 0 takes any free port ([`crate::ServerHandle::foxglove_addr`]).
    pub foxglove_listen: Option<SocketAddr>,
    /// The engine every pool runs on.
    pub engine: ServeEngine,
    /// The GPU engine's arithmetic (`road_gpu::Precision`; the CLI's `ROAD_GPU_PRECISION`).
    pub gpu_precision: road_gpu::Precision,
}

/// What the pools' denoiser runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ServeEngine {
    /// The fast CPU engine on every core: the lowest latency for a few scenes.
    #[default]
    Cpu,
    /// The WGSL kernels on the GPU wgpu picks (lavapipe without one): more scenes per machine
    /// where a GPU is present (an H100 served 2.2× 16 Xeon cores at 16 scenes and 7.6× at 512,
    /// `docs/benchmarks.md`).
    Gpu,
}

impl ServeConfig {
    /// The defaults, with checkpoints from `models_dir` (see [`crate::models::find_models_dir`]).
    pub fn new(models_dir: Option<PathBuf>) -> Self {
        Self {
            prefix: road_protocol::DEFAULT_PREFIX.into(),
            capacity: 256,
            max_payload_bytes: 8 << 20,
            late_ego_deadline: Duration::from_millis(1000),
            idle_timeout: Duration::from_secs(30),
            max_consecutive_late_ticks: 300,
            max_ticks: 6_000,
            max_agents: road_data::WindowConfig::default().max_agents,
            max_external_speed_mps: 70.0,
            record_dir: None,
            flush_interval: Duration::from_secs(1),
            models_dir,
            default_checkpoint: DEFAULT_CHECKPOINT.into(),
            default_initialiser: Some(DEFAULT_INITIALISER.into()),
            map_files: Vec::new(),
            foxglove_listen: None,
            engine: ServeEngine::Cpu,
            gpu_precision: road_gpu::Precision::F32,
        }
    }

    pub fn validate(&self) -> crate::Result<()> {
        let bad = |m: String| Err(crate::Error::Config(m));
        if self.prefix.trim_matches('/').is_empty() || self.prefix.contains(['*', '$', '?', '#']) {
            return bad(format!(
                "prefix {:?} is not a plain key expression",
                self.prefix
            ));
        }
        if self.capacity == 0 {
            return bad("capacity must be at least 1".into());
        }
        if self.max_payload_bytes < 1024 {
            return bad(format!(
                "max_payload_bytes {} is below 1024",
                self.max_payload_bytes
            ));
        }
        if self.max_ticks == 0 {
            return bad("max_ticks must be at least 1".into());
        }
        if self.flush_interval.is_zero() || self.flush_interval > Duration::from_secs(1) {
            return bad(format!(
                "flush_interval {:?} must be in (0, 1 s]",
                self.flush_interval
            ));
        }
        if !self.max_external_speed_mps.is_finite() || self.max_external_speed_mps <= 0.0 {
            return bad(format!(
                "max_external_speed_mps {} must be positive",
                self.max_external_speed_mps
            ));
        }
        Ok(())
    }
}
