//! Checkpoints and planners: where `models/` is, each checkpoint loaded once for the server's
//! life, and the planners of `configs/planners.toml` (embedded, so that the server runs
//! anywhere).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use road_model::checkpoint::{self, LoadedModel};
use road_sched::PlannerSpec;

use crate::{Error, Result};

/// The planners file of the repository, embedded.
const PLANNERS_TOML: &str = include_str!("../../../configs/planners.toml");

/// The models folder: `explicit` (a flag or `ROAD_MODELS`) if given, else `models/` in the
/// working directory, next to the executable, or in one of its ancestors (a cargo
/// `target/<profile>/` build of the repository). The error names every path tried.
pub fn find_models_dir(explicit: Option<&Path>) -> Result<PathBuf> {
    let mut tried = Vec::new();
    if let Some(dir) = explicit {
        if dir.is_dir() {
            return Ok(dir.to_owned());
        }
        return Err(Error::NoModels {
            tried: dir.display().to_string(),
        });
    }
    let mut candidates = vec![PathBuf::from("models")];
    if let Ok(exe) = std::env::current_exe() {
        candidates.extend(exe.ancestors().skip(1).take(4).map(|d| d.join("models")));
    }
    for dir in candidates {
        if dir.join(crate::config::DEFAULT_CHECKPOINT).is_dir()
            || dir.is_dir() && has_checkpoint(&dir)
        {
            return Ok(dir);
        }
        tried.push(dir.display().to_string());
    }
    Err(Error::NoModels {
        tried: tried.join(", "),
    })
}

fn has_checkpoint(dir: &Path) -> bool {
    std::fs::read_dir(dir).is_ok_and(|entries| {
        entries
            .flatten()
            .any(|e| e.path().join("config.toml").is_file())
    })
}

/// The embedded planners by name.
pub fn planners() -> Result<BTreeMap<String, PlannerSpec>> {
    let table: BTreeMap<String, PlannerSpec> = toml::from_str(PLANNERS_TOML)
        .map_err(|e| Error::Config(format!("embedded configs/planners.toml: {e}")))?;
    Ok(table)
}

/// Checkpoints loaded so far. Each stays loaded for the server's life (scenes' engines
/// borrow it), so a name is loaded at most once.
#[derive(Debug)]
pub struct Checkpoints {
    dir: PathBuf,
    loaded: BTreeMap<String, &'static LoadedModel>,
}

impl Checkpoints {
    pub fn new(dir: PathBuf) -> Self {
        Self {
            dir,
            loaded: BTreeMap::new(),
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Whether `name` is a plain folder name (no path tricks from a request).
    pub fn valid_name(name: &str) -> bool {
        !name.is_empty()
            && name.len() <= 64
            && name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.')
            && !name.starts_with('.')
    }

    /// The checkpoint `name` under the models folder, loaded on first use.
    pub fn get(&mut self, name: &str) -> Result<&'static LoadedModel> {
        if let Some(m) = self.loaded.get(name) {
            return Ok(m);
        }
        let path = self.dir.join(name);
        let model = checkpoint::load(&path, &candle_core::Device::Cpu)
            .map_err(|source| Error::Checkpoint { path, source })?;
        // Leaked on purpose: engines borrow the model for as long as scenes run on it, and a
        // checkpoint is loaded once per name for the server's life.
        let model: &'static LoadedModel = Box::leak(Box::new(model));
        self.loaded.insert(name.to_owned(), model);
        Ok(model)
    }

    /// Whether `name` exists as a checkpoint folder (without loading it).
    pub fn exists(&self, name: &str) -> bool {
        Self::valid_name(name) && self.dir.join(name).join("config.toml").is_file()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_planners_parse() {
        let p = planners().unwrap();
        assert_eq!(p["road20"].window_slots(), 20);
        assert!(p.len() >= 4);
    }

    #[test]
    fn names_stay_in_the_folder() {
        assert!(Checkpoints::valid_name("road20"));
        for bad in ["", "../x", "a/b", ".hidden", "x\\y"] {
            assert!(!Checkpoints::valid_name(bad), "{bad}");
        }
    }

    #[test]
    fn a_missing_models_folder_names_the_path() {
        let e = find_models_dir(Some(Path::new("/nonexistent/models"))).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/models"), "{e}");
    }
}
