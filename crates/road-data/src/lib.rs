//! `road-data`: INTERACTION recordings and Lanelet2 maps in, scene windows out.
//!
//! - [`tracks`]: track CSV files (plain or gzip) → [`Recording`]s;
//! - [`map`]: Lanelet2 `.osm` → [`LaneletMap`] (UTM zone 31 minus the projection of (0, 0));
//! - [`rules`]: a map's priority rules (right of way, all-way stops) by lanelet;
//! - [`sources`]: the data folder's layout and the official validation split;
//! - [`dataset`]: scene windows (`[agents, steps, (x, y, heading)]` in a normalised scene frame);
//! - [`cache`]: one versioned, checksummed binary file per split;
//! - [`stats`]: the figures `road data stats` prints.

pub mod cache;
pub mod dataset;
pub mod geometry;
pub mod map;
pub mod sources;
pub mod stats;
pub mod testing;
pub mod tracks;

use std::path::{Path, PathBuf};

pub use dataset::{
    BuildReport, Dataset, SceneFrame, SceneWindow, WindowConfig, WindowRef, wrap_angle,
};
pub use map::{LaneletMap, rules};
pub use sources::{SourceSet, Split};
pub use tracks::{AgentType, Recording, Track};

/// Errors of the data layer. Each names its input last: file and line, element or key.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read or write {path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("malformed track row: {reason} ({path}:{line})")]
    Track {
        path: PathBuf,
        line: u64,
        reason: String,
    },
    #[error("unknown column layout: expected `{expected}`, found `{found}` ({path}:1)")]
    Columns {
        path: PathBuf,
        expected: String,
        found: String,
    },
    #[error("bad map: {reason} ({path}, {element})")]
    Map {
        path: PathBuf,
        element: String,
        reason: String,
    },
    #[error("bad data folder: {reason} ({path})")]
    Layout { path: PathBuf, reason: String },
    #[error("bad validation list: {reason} ({path}:{line})")]
    ValidationList {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("bad config: {reason} ({path})")]
    Config { path: PathBuf, reason: String },
    #[error("corrupt dataset cache: {reason} ({path})")]
    CorruptCache { path: PathBuf, reason: String },
    #[error("stale dataset cache: {reason}; rebuild it with `road data build` ({path})")]
    StaleCache { path: PathBuf, reason: String },
    #[error("no window {index}: the dataset has {len} windows")]
    WindowIndex { index: usize, len: usize },
}

impl Error {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_owned(),
            source,
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
