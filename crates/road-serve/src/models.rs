//! Checkpoints and planners: where `models/` is, each checkpoint loaded once for the server's
//! life, and the planners of `configs/planners.toml` (embedded, so that the server runs
//! anywhere).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use road_gpu::GpuContext;
use road_gpu::engine::GpuDenoiser;
use road_model::checkpoint::{self, LoadedModel};
use road_sched::PlannerSpec;

use crate::{Error, Result};

/// The planners file of the repository, embedded.
const PLANNERS_TOML: &str = include_str!("../../../configs/planners.toml");

/// The default checkpoint and the initialiser (`CreateScene.populate.initialiser`), embedded
/// in the binary so that `road serve` and `road demo` run wherever the binary is (a `models/`
/// folder found at run time still wins for the same name). The default's name must be
/// [`crate::config::DEFAULT_CHECKPOINT`] (a test checks).
pub mod embedded {
    pub const CONFIG_TOML: &str = include_str!("../../../models/road20-wide4/config.toml");
    pub const WEIGHTS: &[u8] = include_bytes!("../../../models/road20-wide4/weights.safetensors");
    /// The name requests and flags use for it.
    pub const NAME: &str = crate::config::DEFAULT_CHECKPOINT;
    /// The initialiser: trained to draw whole vehicles around given ones.
    pub const INITIALISER_NAME: &str = "road20-init";
    pub const INITIALISER_CONFIG_TOML: &str =
        include_str!("../../../models/road20-init/config.toml");
    pub const INITIALISER_WEIGHTS: &[u8] =
        include_bytes!("../../../models/road20-init/weights.safetensors");

    /// The embedded checkpoint `name`: its config's text and its weights.
    pub fn get(name: &str) -> Option<(&'static str, &'static [u8])> {
        match name {
            NAME => Some((CONFIG_TOML, WEIGHTS)),
            INITIALISER_NAME => Some((INITIALISER_CONFIG_TOML, INITIALISER_WEIGHTS)),
            _ => None,
        }
    }

    /// The embedded checkpoint `name`, loaded on the CPU (as `<embedded NAME>`); `None` when
    /// none is embedded by that name.
    pub fn load(name: &str) -> Option<crate::Result<super::LoadedModel>> {
        let (config_toml, weights) = get(name)?;
        let origin = std::path::PathBuf::from(format!("<embedded {name}>"));
        Some(
            super::checkpoint::load_from_memory(
                &origin,
                config_toml,
                weights,
                &candle_core::Device::Cpu,
            )
            .map_err(|source| crate::Error::Checkpoint {
                path: origin,
                source,
            }),
        )
    }
}

/// The models folder: `explicit` (a flag or `ROAD_MODELS`) if given (an error names it when it
/// is not a folder), else `models/` in the working directory, next to the executable, or in
/// one of its ancestors (a cargo `target/<profile>/` build of the repository); `None` when
/// there is none: the embedded default checkpoint is then the only one.
pub fn find_models_dir(explicit: Option<&Path>) -> Result<Option<PathBuf>> {
    if let Some(dir) = explicit {
        if dir.is_dir() {
            return Ok(Some(dir.to_owned()));
        }
        return Err(Error::NoModels {
            tried: dir.display().to_string(),
        });
    }
    let mut candidates = vec![PathBuf::from("models")];
    if let Ok(exe) = std::env::current_exe() {
        candidates.extend(exe.ancestors().skip(1).take(4).map(|d| d.join("models")));
    }
    let found = candidates.into_iter().find(|dir| {
        dir.join(crate::config::DEFAULT_CHECKPOINT).is_dir() || dir.is_dir() && has_checkpoint(dir)
    });
    if found.is_none() {
        tracing::info!(
            "no models folder here or next to the binary: serving the embedded {}",
            embedded::NAME
        );
    }
    Ok(found)
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
/// borrow it), so a name is loaded at most once; with a GPU context its weights are uploaded
/// once too.
#[derive(Debug)]
pub struct Checkpoints {
    dir: Option<PathBuf>,
    loaded: BTreeMap<String, &'static LoadedModel>,
    gpu: Option<&'static GpuContext>,
    uploaded: BTreeMap<String, &'static GpuDenoiser>,
}

impl Checkpoints {
    /// Checkpoints from the models folder `dir` (if any) and the embedded default.
    pub fn new(dir: Option<PathBuf>) -> Self {
        Self {
            dir,
            loaded: BTreeMap::new(),
            gpu: None,
            uploaded: BTreeMap::new(),
        }
    }

    /// The same, their weights also uploaded to `gpu` when first used ([`Self::gpu_model`]).
    pub fn with_gpu(dir: Option<PathBuf>, gpu: &'static GpuContext) -> Self {
        Self {
            gpu: Some(gpu),
            ..Self::new(dir)
        }
    }

    /// The GPU context and checkpoint `name`'s weights on it (uploaded on first use), or None
    /// without a GPU context.
    pub fn gpu_model(
        &mut self,
        name: &str,
    ) -> Result<Option<(&'static GpuContext, &'static GpuDenoiser)>> {
        let Some(ctx) = self.gpu else {
            return Ok(None);
        };
        if let Some(m) = self.uploaded.get(name) {
            return Ok(Some((ctx, m)));
        }
        let loaded = self.get(name)?;
        let mut model = match self.folder(name) {
            Some(path) => GpuDenoiser::from_checkpoint(ctx, &path)?,
            None => GpuDenoiser::from_memory(ctx, loaded, embedded::WEIGHTS)?,
        };
        // The adapter's tuned kernel choices: cached, or timed once on a hardware adapter.
        let attached = road_gpu::tune::attach(ctx, &mut model);
        tracing::info!(checkpoint = name, ?attached, "GPU kernels' tuning");
        // Leaked for the reason `get` leaks the model: pools borrow it for the server's life.
        let model: &'static GpuDenoiser = Box::leak(Box::new(model));
        self.uploaded.insert(name.to_owned(), model);
        Ok(Some((ctx, model)))
    }

    /// Where checkpoints are looked up, for messages.
    pub fn describe(&self) -> String {
        match &self.dir {
            Some(dir) => format!("{} (and the embedded {})", dir.display(), embedded::NAME),
            None => format!("no models folder; only the embedded {}", embedded::NAME),
        }
    }

    fn folder(&self, name: &str) -> Option<PathBuf> {
        let dir = self.dir.as_ref()?.join(name);
        dir.join("config.toml").is_file().then_some(dir)
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
        let model = match self.folder(name) {
            Some(path) => checkpoint::load(&path, &candle_core::Device::Cpu)
                .map_err(|source| Error::Checkpoint { path, source })?,
            None => match embedded::load(name) {
                Some(loaded) => loaded?,
                None => {
                    return Err(Error::Config(format!(
                        "no checkpoint {name:?}: {}",
                        self.describe()
                    )));
                }
            },
        };
        // Leaked on purpose: engines borrow the model for as long as scenes run on it, and a
        // checkpoint is loaded once per name for the server's life.
        let model: &'static LoadedModel = Box::leak(Box::new(model));
        self.loaded.insert(name.to_owned(), model);
        Ok(model)
    }

    /// Whether `name` is a checkpoint folder or the embedded default (without loading it).
    pub fn exists(&self, name: &str) -> bool {
        Self::valid_name(name) && (self.folder(name).is_some() || embedded::get(name).is_some())
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
    fn the_embedded_default_loads_without_a_models_folder() {
        let mut checkpoints = Checkpoints::new(None);
        assert!(checkpoints.exists(crate::config::DEFAULT_CHECKPOINT));
        assert!(!checkpoints.exists("road20"));
        let model = checkpoints.get(crate::config::DEFAULT_CHECKPOINT).unwrap();
        // The embedded files are the default's own.
        assert_eq!(model.meta.run.name, crate::config::DEFAULT_CHECKPOINT);
        let err = checkpoints.get("road20").unwrap_err().to_string();
        assert!(err.contains("road20") && err.contains("embedded"), "{err}");
    }

    #[test]
    fn a_missing_models_folder_names_the_path() {
        let e = find_models_dir(Some(Path::new("/nonexistent/models"))).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/models"), "{e}");
    }
}
