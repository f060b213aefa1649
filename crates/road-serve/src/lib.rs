//! `road-serve`: the networked NPC server. Ego stacks create scenes over Eclipse Zenoh, put
//! their external agents' poses every tick and get every NPC's next state back; every scene is
//! recorded to MCAP and, with the live view on, shown in Foxglove while it runs.
//!
//! - [`config`]: the server's settings and the zenoh session's config (json5 file plus the
//!   zenoh examples' command-line overrides);
//! - [`models`]: finding `models/`, loading checkpoints once, the planners of
//!   `configs/planners.toml` (embedded);
//! - [`scene`]: a creation request checked field by field and turned into a simulation;
//!   a live scene's tick and its late-ego policy;
//! - [`pool`]: continuous batching: the scenes of one checkpoint and planner share an engine,
//!   one batched Heun round at a time;
//! - [`record`]: one MCAP file per scene (raw protocol messages and `foxglove.SceneUpdate`);
//! - [`recover`]: a recording cut off by a killed server rewritten whole, with its summary
//!   (`road recover`; a server recovers its folder's at start);
//! - `writer`: the thread that records every scene and feeds the live view, so that the
//!   core's rounds never wait on either;
//! - [`live`]: the live view, a Foxglove WebSocket server showing every live scene's map and
//!   agent boxes (`road serve --foxglove ADDR`);
//! - [`server`]: the zenoh front end and the core loop that batches the scenes whose ego has
//!   arrived.
//!
//! The protocol's messages live in `road-protocol` (shared with the clients);
//! `docs/protocol.md` documents them.

pub mod config;
pub mod live;
pub mod models;
pub mod pool;
pub mod record;
pub mod recover;
pub mod scene;
pub mod server;
mod writer;

pub use config::{ServeConfig, ServeEngine, ZenohArgs};
pub use server::{Server, ServerHandle};

/// Errors of the server (setting up, running); bad client input is not an error of the
/// server but an [`road_protocol::ErrorReply`] to the client.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("bad zenoh config: {reason} ({input})")]
    ZenohConfig { input: String, reason: String },
    #[error("no models folder: tried {tried}; pass --models DIR or set ROAD_MODELS")]
    NoModels { tried: String },
    #[error("cannot load checkpoint {path}")]
    Checkpoint {
        path: std::path::PathBuf,
        source: road_model::Error,
    },
    #[error("bad server config: {0}")]
    Config(String),
    #[error("cannot read or write {path}")]
    Io {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("cannot start the Foxglove live view on {addr}")]
    LiveView {
        addr: std::net::SocketAddr,
        source: std::io::Error,
    },
    /// One scene's tick could not be computed (the scene closes; the others go on).
    #[error("scene {scene}: {reason}")]
    SceneFailed { scene: u64, reason: String },
    #[error("recording {path}: {reason}")]
    Record {
        path: std::path::PathBuf,
        reason: String,
    },
    /// A recording that [`recover`] cannot rewrite (not MCAP, damaged, or the new file could
    /// not be written); the file is left as it was.
    #[error("cannot recover {path}: {reason}")]
    Recover {
        path: std::path::PathBuf,
        reason: String,
    },
    /// A recording whose lock another open file holds: a running server is writing it.
    #[error("{path} is being written by a running server (it holds the file's lock); left as is")]
    RecordingInUse { path: std::path::PathBuf },
    #[error(transparent)]
    Sim(#[from] road_sim::Error),
    #[error(transparent)]
    Data(#[from] road_data::Error),
    #[error(transparent)]
    Model(#[from] road_model::Error),
    /// The WGSL engine (`--engine gpu`): no adapter, or a checkpoint it cannot run.
    #[error("GPU engine: {0}")]
    Gpu(#[from] road_gpu::Error),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl From<zenoh::Error> for Error {
    fn from(e: zenoh::Error) -> Self {
        Error::Zenoh(e.to_string())
    }
}
