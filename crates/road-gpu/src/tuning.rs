//! The autotuner's tables (`crate::tune` makes them): how each way to run an evaluation timed
//! at each batch size on an adapter, the fastest per size, and the cache file that keeps them
//! per adapter, driver, kernels and model. The engine runs an evaluation as its table chose
//! ([`TuneTable::settings_for`]).

use std::path::Path;

use road_model::ModelConfig;
use serde::{Deserialize, Serialize};

use crate::kernels::linear::LinearKernel;
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// How one evaluation runs: its blocks as residual chains (on the narrow or the wide tile) or
/// layer by layer, and its linear layers' kernel (`None`: chosen per layer by size).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EvalSettings {
    pub residual_chains: bool,
    pub wide_chains: bool,
    pub linear_kernel: Option<LinearKernel>,
}

/// One way to run an evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Candidate {
    /// The blocks as residual chains (`true`) or layer by layer.
    pub residual_chains: bool,
    /// The chains on the wide tile (`ContextOptions::wide_chains`); absent in older caches.
    #[serde(default)]
    pub wide_chains: bool,
    /// The linear layers' kernel, its entry point's name, or `"auto"` (chosen per layer).
    pub linear_kernel: LinearChoice,
}

/// A linear kernel as the cache file names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LinearChoice {
    Auto,
    Rowwise,
    Tiled,
    Blocked,
}

impl LinearChoice {
    fn kernel(self) -> Option<LinearKernel> {
        match self {
            Self::Auto => None,
            Self::Rowwise => Some(LinearKernel::Rowwise),
            Self::Tiled => Some(LinearKernel::Tiled),
            Self::Blocked => Some(LinearKernel::Blocked),
        }
    }

    /// As `road bench engine --linear-kernels` names it.
    fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Rowwise => "rowwise",
            Self::Tiled => "tiled",
            Self::Blocked => "blocked",
        }
    }
}

impl Candidate {
    pub fn settings(self) -> EvalSettings {
        EvalSettings {
            residual_chains: self.residual_chains,
            wide_chains: self.residual_chains && self.wide_chains,
            linear_kernel: self.linear_kernel.kernel(),
        }
    }

    /// `chains, auto` and the like: how `road gpu tune` prints it.
    pub fn describe(self) -> String {
        let fusion = match (self.residual_chains, self.wide_chains) {
            (true, false) => "chains",
            (true, true) => "wide chains",
            (false, _) => "layers",
        };
        format!("{fusion}, {}", self.linear_kernel.name())
    }
}

/// Every candidate the tuner times for a model: chains only where its rows fit the chain's
/// tile; the wide tile (with the linear kernels the large batches it is for choose: by size,
/// or blocked) where its widths allow it (`ChainTile::wide`; a device whose workgroups cannot
/// hold it records the candidate's error).
pub fn candidates(config: &ModelConfig) -> Vec<Candidate> {
    use crate::kernels::residual_chain::{ChainTile, MAX_HIDDEN};
    let fits = config.hidden <= MAX_HIDDEN as usize;
    let wide_fits = ChainTile::wide(
        config.hidden as u32,
        (config.hidden * config.mlp_ratio) as u32,
        u32::MAX,
    )
    .is_some();
    let linear = [
        LinearChoice::Auto,
        LinearChoice::Rowwise,
        LinearChoice::Tiled,
        LinearChoice::Blocked,
    ];
    let mut all = Vec::new();
    for residual_chains in [true, false] {
        if residual_chains && !fits {
            continue;
        }
        for linear_kernel in linear {
            all.push(Candidate {
                residual_chains,
                wide_chains: false,
                linear_kernel,
            });
        }
    }
    if fits && wide_fits {
        for linear_kernel in [LinearChoice::Auto, LinearChoice::Blocked] {
            all.push(Candidate {
                residual_chains: true,
                wide_chains: true,
                linear_kernel,
            });
        }
    }
    all
}

/// One candidate's time at one batch size (the median of its timed evaluations); `error` when
/// the adapter could not run it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    pub candidate: Candidate,
    pub ms_per_evaluation: Option<f64>,
    pub error: Option<String>,
}

/// The candidates timed at one batch size, and the fastest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TunedBatch {
    pub scenes: usize,
    pub agents: usize,
    /// Tokens of the batch (scenes × agents × window slots): what an evaluation is matched by.
    pub tokens: usize,
    pub timings: Vec<Timing>,
    pub chosen: Candidate,
}

/// A model's tuning on one adapter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TuneTable {
    /// [`adapter_key`] of the adapter timed.
    pub adapter: String,
    /// [`kernels_key`] of the kernels timed.
    pub kernels: String,
    /// [`model_key`] of the model timed.
    pub model: String,
    /// By increasing tokens.
    pub batches: Vec<TunedBatch>,
}

impl TuneTable {
    /// The choice for an evaluation of `tokens` tokens: the timed batch nearest in log scale.
    pub fn settings_for(&self, tokens: usize) -> EvalSettings {
        let log = |t: usize| (t.max(1) as f64).ln();
        self.batches
            .iter()
            .min_by(|a, b| {
                let da = (log(a.tokens) - log(tokens)).abs();
                let db = (log(b.tokens) - log(tokens)).abs();
                da.total_cmp(&db)
            })
            .map_or(
                EvalSettings {
                    residual_chains: true,
                    wide_chains: false,
                    linear_kernel: None,
                },
                |batch| batch.chosen.settings(),
            )
    }
}

/// The adapter as the cache keys it: name, vendor and device ids, backend, driver.
pub fn adapter_key(ctx: &GpuContext) -> String {
    let info = &ctx.info;
    format!(
        "{} [{:04x}:{:04x}] {:?} {} {}",
        info.name, info.vendor, info.device, info.backend, info.driver, info.driver_info
    )
}

/// The kernels as the cache keys them: a hash of every shader's source, so that a changed
/// kernel is timed anew.
pub fn kernels_key() -> String {
    // FNV-1a, 64 bits: stable across builds and platforms (std's hasher is not).
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    for shader in Shader::ALL {
        for byte in shader.source().bytes() {
            hash ^= u64::from(byte);
            hash = hash.wrapping_mul(0x0100_0000_01b3);
        }
    }
    format!("{hash:016x}")
}

/// The model's shapes as the cache keys them: what the kernels' work depends on.
pub fn model_key(c: &ModelConfig) -> String {
    format!(
        "D{} heads{} blocks{} mlp{} slots{} points{} polylines{} maps{} pairs{} frame{}",
        c.hidden,
        c.heads,
        c.blocks,
        c.mlp_ratio,
        c.window_slots,
        c.polyline_points,
        c.map_polylines,
        c.agent_map.as_ref().map_or(0, |m| m.polylines),
        u8::from(c.agent_pairs.is_some()),
        u8::from(c.agent_frame.is_some()),
    )
}

/// Every table tuned on this machine: the cache file's contents.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TuneCache {
    pub tables: Vec<TuneTable>,
}

impl TuneCache {
    /// The file at `path`; none yet is an empty cache, a file that does not parse an error
    /// that names it.
    pub fn load(path: &Path) -> Result<Self> {
        let text = match std::fs::read_to_string(path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Self::default()),
            Err(e) => {
                return Err(Error::Input(format!(
                    "cannot read the tuning cache {}: {e}",
                    path.display()
                )));
            }
        };
        serde_json::from_str(&text).map_err(|e| {
            Error::Input(format!(
                "the tuning cache {} does not parse (line {}, column {}): {e}; delete it to \
                 tune anew",
                path.display(),
                e.line(),
                e.column()
            ))
        })
    }

    /// Writes the cache to `path` (its folder made if missing), through a temporary file so
    /// that a reader never sees half of it.
    pub fn save(&self, path: &Path) -> Result<()> {
        let io = |e: std::io::Error| {
            Error::Input(format!(
                "cannot write the tuning cache {}: {e}",
                path.display()
            ))
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::Input(format!("cannot encode the tuning cache: {e}")))?;
        let temporary = path.with_extension("json.partial");
        std::fs::write(&temporary, text).map_err(io)?;
        std::fs::rename(&temporary, path).map_err(io)
    }

    /// The table of `ctx`'s adapter, the current kernels and `config`'s model.
    pub fn find(&self, ctx: &GpuContext, config: &ModelConfig) -> Option<&TuneTable> {
        let (adapter, kernels, model) = (adapter_key(ctx), kernels_key(), model_key(config));
        self.tables
            .iter()
            .find(|t| t.adapter == adapter && t.kernels == kernels && t.model == model)
    }

    /// Adds `table`, replacing the one of the same adapter, kernels and model.
    pub fn insert(&mut self, table: TuneTable) {
        self.tables.retain(|t| {
            (&t.adapter, &t.kernels, &t.model) != (&table.adapter, &table.kernels, &table.model)
        });
        self.tables.push(table);
    }
}
