//! The data folder's layout (INTERACTION DR v1.0) and the official validation split.
//!
//! ```text
//! maps/DR_<LOCATION>.osm
//! recorded_trackfiles/DR_<LOCATION>/vehicle_tracks_NNN.csv[.gz]
//! recorded_trackfiles/validation-set-list_*.txt
//! ```

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Split {
    Train,
    Validation,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Validation => "validation",
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One track file and what identifies its content for staleness checks.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TrackSource {
    pub location: String,
    /// Path relative to the data folder.
    pub relative_path: String,
    pub size_bytes: u64,
}

/// Everything found in a data folder, split.
#[derive(Debug, Clone)]
pub struct SourceSet {
    pub root: PathBuf,
    /// Location → map path.
    pub maps: BTreeMap<String, PathBuf>,
    pub train: Vec<TrackSource>,
    pub validation: Vec<TrackSource>,
    /// Files the validation list names that this copy lacks (`LOCATION/stem`).
    pub missing_validation: Vec<String>,
}

impl SourceSet {
    pub fn discover(root: &Path) -> Result<Self> {
        let layout = |path: &Path, reason: String| Error::Layout {
            path: path.to_owned(),
            reason,
        };
        let maps_dir = root.join("maps");
        let tracks_dir = root.join("recorded_trackfiles");
        for dir in [&maps_dir, &tracks_dir] {
            if !dir.is_dir() {
                return Err(layout(
                    dir,
                    "folder not found: is this an INTERACTION data folder?".into(),
                ));
            }
        }
        let read_dir = |dir: &Path| -> Result<Vec<PathBuf>> {
            let mut entries = std::fs::read_dir(dir)
                .map_err(|e| Error::io(dir, e))?
                .map(|e| e.map(|e| e.path()).map_err(|e| Error::io(dir, e)))
                .collect::<Result<Vec<_>>>()?;
            entries.sort();
            Ok(entries)
        };

        let mut maps = BTreeMap::new();
        for path in read_dir(&maps_dir)? {
            let name = path
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            if let Some(location) = name.strip_suffix(".osm") {
                maps.insert(location.to_owned(), path);
            }
        }

        let list_path = read_dir(&tracks_dir)?
            .into_iter()
            .find(|p| {
                let n = p.file_name().unwrap_or_default().to_string_lossy();
                n.starts_with("validation-set-list") && n.ends_with(".txt")
            })
            .ok_or_else(|| {
                layout(
                    &tracks_dir,
                    "no validation-set-list*.txt: the split cannot be made".into(),
                )
            })?;
        let listed = parse_validation_list(&list_path)?;

        let mut train = Vec::new();
        let mut validation = Vec::new();
        let mut present = BTreeSet::new();
        for dir in read_dir(&tracks_dir)?.into_iter().filter(|p| p.is_dir()) {
            let location = dir
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            for file in read_dir(&dir)? {
                let name = file
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned();
                let Some(stem) = name
                    .strip_suffix(".csv.gz")
                    .or_else(|| name.strip_suffix(".csv"))
                else {
                    continue;
                };
                if !stem.starts_with("vehicle_tracks_") {
                    continue;
                }
                if !maps.contains_key(&location) {
                    return Err(layout(
                        &file,
                        format!("no map for location {location}: expected maps/{location}.osm"),
                    ));
                }
                let size_bytes = std::fs::metadata(&file)
                    .map_err(|e| Error::io(&file, e))?
                    .len();
                let relative_path = file
                    .strip_prefix(root)
                    .unwrap_or(&file)
                    .to_string_lossy()
                    .into_owned();
                let key = (location.clone(), stem.to_owned());
                let source = TrackSource {
                    location: location.clone(),
                    relative_path,
                    size_bytes,
                };
                if listed.contains(&key) {
                    validation.push(source);
                } else {
                    train.push(source);
                }
                present.insert(key);
            }
        }
        let missing_validation: Vec<String> = listed
            .difference(&present)
            .map(|(loc, stem)| format!("{loc}/{stem}"))
            .collect();
        if !missing_validation.is_empty() {
            tracing::warn!(
                count = missing_validation.len(),
                "the validation list names files this copy lacks; they are skipped: {}",
                missing_validation.join(", ")
            );
        }
        Ok(Self {
            root: root.to_owned(),
            maps,
            train,
            validation,
            missing_validation,
        })
    }

    pub fn split(&self, split: Split) -> &[TrackSource] {
        match split {
            Split::Train => &self.train,
            Split::Validation => &self.validation,
        }
    }
}

/// Parses the official list: a location line (`DR_...`) followed by file stems, blocks
/// separated by blank lines.
pub fn parse_validation_list(path: &Path) -> Result<BTreeSet<(String, String)>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_validation_text(&text, path)
}

pub fn parse_validation_text(text: &str, path: &Path) -> Result<BTreeSet<(String, String)>> {
    let mut out = BTreeSet::new();
    let mut location: Option<String> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() {
            location = None;
        } else if line.starts_with("DR_") {
            location = Some(line.to_owned());
        } else if line.starts_with("vehicle_tracks_") || line.starts_with("pedestrian_tracks_") {
            let loc = location.clone().ok_or_else(|| Error::ValidationList {
                path: path.to_owned(),
                line: i + 1,
                reason: format!("file `{line}` before any location line"),
            })?;
            if line.starts_with("vehicle_tracks_") {
                out.insert((loc, line.to_owned()));
            }
        } else {
            return Err(Error::ValidationList {
                path: path.to_owned(),
                line: i + 1,
                reason: format!("unexpected line `{line}`"),
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_list_blocks() {
        let text = "DR_A \nvehicle_tracks_001\nvehicle_tracks_002\n\nDR_B\nvehicle_tracks_000";
        let set = parse_validation_text(text, Path::new("list.txt")).unwrap();
        assert_eq!(set.len(), 3);
        assert!(set.contains(&("DR_A".into(), "vehicle_tracks_002".into())));
        let err = parse_validation_text("vehicle_tracks_001\n", Path::new("list.txt"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("list.txt:1"), "{err}");
        let err = parse_validation_text("DR_A\nhello\n", Path::new("list.txt"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("list.txt:2") && err.contains("hello"), "{err}");
    }
}
