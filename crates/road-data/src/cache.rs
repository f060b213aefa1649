//! One binary cache file per split, so that training never re-parses CSV.
//!
//! Layout (little endian):
//! ```text
//! magic "ROADDSET" (8) | format version u32 | payload length u64 | payload CRC-32 u32 | payload
//! ```
//! The payload is the [`Dataset`] in postcard. A wrong magic, a truncated file or a checksum
//! mismatch is "corrupt"; another format version, window config or set of source files is
//! "stale".

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::dataset::{Dataset, WindowConfig};
use crate::sources::{SourceSet, Split};
use crate::{Error, Result};

pub const MAGIC: &[u8; 8] = b"ROADDSET";
/// Bump on any change to the payload's types, or to what the parser makes of the same files
/// (2: lanelets driven the way their bounds' sides say, `crate::map`; 3: maps carry their
/// priority rules, `crate::rules`).
pub const FORMAT_VERSION: u32 = 3;
const HEADER_BYTES: usize = 8 + 4 + 8 + 4;

/// `DIR/train.roadds` or `DIR/validation.roadds`.
pub fn cache_path(dir: &Path, split: Split) -> PathBuf {
    dir.join(format!("{}.roadds", split.name()))
}

/// Writes atomically (temporary file, then rename).
pub fn save(dataset: &Dataset, path: &Path) -> Result<()> {
    let payload = postcard::to_stdvec(dataset).map_err(|e| Error::CorruptCache {
        path: path.to_owned(),
        reason: format!("cannot encode: {e}"),
    })?;
    let mut bytes = Vec::with_capacity(HEADER_BYTES + payload.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    bytes.extend_from_slice(&payload);
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let tmp = path.with_extension("roadds.tmp");
    let mut file = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    file.write_all(&bytes)
        .and_then(|()| file.sync_all())
        .map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// Reads and verifies a cache file (format, length, checksum).
pub fn load(path: &Path) -> Result<Dataset> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode(&bytes, path)
}

pub fn decode(bytes: &[u8], path: &Path) -> Result<Dataset> {
    let corrupt = |reason: String| Error::CorruptCache {
        path: path.to_owned(),
        reason,
    };
    if bytes.len() < HEADER_BYTES || &bytes[..8] != MAGIC {
        return Err(corrupt("not a road dataset cache (bad magic)".into()));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if version != FORMAT_VERSION {
        return Err(Error::StaleCache {
            path: path.to_owned(),
            reason: format!(
                "written in format version {version}, this build reads version {FORMAT_VERSION}"
            ),
        });
    }
    let len = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes")) as usize;
    let crc = u32::from_le_bytes(bytes[20..24].try_into().expect("4 bytes"));
    let payload = &bytes[HEADER_BYTES..];
    if payload.len() != len {
        return Err(corrupt(format!(
            "payload is {} bytes, header says {len} (truncated?)",
            payload.len()
        )));
    }
    if crc32fast::hash(payload) != crc {
        return Err(corrupt("checksum mismatch".into()));
    }
    postcard::from_bytes(payload).map_err(|e| corrupt(format!("cannot decode: {e}")))
}

/// Loads a cache and checks that it was built with `config` from exactly `sources`' files
/// (names and sizes); either check can be skipped with `None`.
pub fn load_checked(
    path: &Path,
    split: Split,
    config: Option<&WindowConfig>,
    sources: Option<&SourceSet>,
) -> Result<Dataset> {
    let dataset = load(path)?;
    let stale = |reason: String| {
        Err(Error::StaleCache {
            path: path.to_owned(),
            reason,
        })
    };
    if dataset.split != split {
        return stale(format!(
            "holds the {} split, expected {split}",
            dataset.split
        ));
    }
    if let Some(config) = config {
        if &dataset.config != config {
            return stale(format!(
                "built with window config {:?}, expected {config:?}",
                dataset.config
            ));
        }
    }
    if let Some(sources) = sources {
        if dataset.sources != sources.split(split) {
            return stale(format!(
                "built from {} files that differ from the {} files now in {}",
                dataset.sources.len(),
                sources.split(split).len(),
                sources.root.display()
            ));
        }
    }
    Ok(dataset)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::BuildReport;
    use crate::map::LaneletMap;
    use crate::tracks::{AgentType, Recording, Track};

    fn tiny() -> Dataset {
        let map = LaneletMap::parse(&crate::map::tests::fixture_osm(), Path::new("f.osm"), "FIX")
            .unwrap();
        let track = Track {
            track_id: 7,
            agent_type: AgentType::Car,
            length_m: 4.0,
            width_m: 1.8,
            first_frame: 1,
            states: vec![[1.0, 2.0, 0.3]; 5],
        };
        Dataset {
            split: Split::Train,
            config: WindowConfig::default(),
            sources: vec![],
            maps: vec![map],
            recordings: vec![Recording {
                location: "FIX".into(),
                file: "t.csv".into(),
                tracks: vec![track],
                first_frame: 1,
                last_frame: 5,
            }],
            recording_map: vec![0],
            windows: vec![crate::dataset::WindowRef {
                recording: 0,
                start_frame: 1,
                origin_m: [1.0, 2.0],
                agents: vec![0],
                polylines: vec![0, 1],
            }],
            report: BuildReport {
                files: 1,
                windows: 1,
                ..BuildReport::default()
            },
        }
    }

    /// `name` in a folder of its own (tests run in parallel), which [`remove_temp`] removes.
    fn temp(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("road-cache-test-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn remove_temp(path: &Path) {
        let _ = std::fs::remove_dir_all(path.parent().unwrap());
    }

    #[test]
    fn round_trip_is_exact() {
        let path = temp("rt.roadds");
        let ds = tiny();
        save(&ds, &path).unwrap();
        let back = load_checked(&path, Split::Train, Some(&WindowConfig::default()), None).unwrap();
        assert_eq!(
            postcard::to_stdvec(&back).unwrap(),
            postcard::to_stdvec(&ds).unwrap()
        );
        assert_eq!(back.window(0).unwrap(), ds.window(0).unwrap());
        remove_temp(&path);
    }

    #[test]
    fn corruption_and_staleness_are_clear_errors() {
        let path = temp("bad.roadds");
        save(&tiny(), &path).unwrap();
        let good = std::fs::read(&path).unwrap();

        let mut flipped = good.clone();
        let last = flipped.len() - 3;
        flipped[last] ^= 0x40;
        assert!(
            decode(&flipped, &path)
                .unwrap_err()
                .to_string()
                .contains("checksum mismatch")
        );

        let err = decode(&good[..good.len() - 10], &path)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("truncated") && err.contains("bad.roadds"),
            "{err}"
        );

        assert!(
            decode(b"hello world, not a cache at all", &path)
                .unwrap_err()
                .to_string()
                .contains("bad magic")
        );

        let mut old = good.clone();
        old[8..12].copy_from_slice(&0u32.to_le_bytes());
        let err = decode(&old, &path).unwrap_err().to_string();
        assert!(
            err.contains("stale") && err.contains("road data build"),
            "{err}"
        );

        let other = WindowConfig {
            window_steps: 20,
            ..WindowConfig::default()
        };
        let err = load_checked(&path, Split::Train, Some(&other), None)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("stale") && err.contains("window config"),
            "{err}"
        );
        let err = load_checked(&path, Split::Validation, None, None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("train split"), "{err}");
        remove_temp(&path);
    }
}
