//! Where tests find the INTERACTION data.

use std::path::{Path, PathBuf};

/// `ROAD_DATA`, else `../shared/data/interaction` beside the clone (the development layout).
/// Panics naming the folder when it holds no maps: tests on the data run in CI, so missing data
/// is a failure, not a skip.
pub fn interaction_dir() -> PathBuf {
    let dir = std::env::var_os("ROAD_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/interaction")
        });
    assert!(
        dir.join("maps").is_dir(),
        "INTERACTION data not found at {} (set ROAD_DATA)",
        dir.display()
    );
    dir
}
