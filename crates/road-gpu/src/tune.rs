//! The autotuner (issue 40): on the adapter at hand, time one denoiser evaluation of a model
//! under each way the engine can run it (the blocks as residual chains or layer by layer; the
//! linear layers' kernel chosen by size or one variant everywhere) at several batch sizes, and
//! keep the fastest per size. The tables are cached in one JSON file keyed by adapter, driver,
//! the kernels' sources and the model's shapes, so a GPU nobody here has seen gets its best
//! variant from its second start on (`road gpu tune` prints and writes them; `road serve` and
//! `road demo` tune a hardware adapter they have no table for once, and read the table after).

use std::path::{Path, PathBuf};
use std::time::Instant;

use road_model::ModelConfig;
use serde::{Deserialize, Serialize};

use crate::engine::{DenoiseInputs, EvalSettings, GpuDenoiser};
use crate::kernels::linear::LinearKernel;
use crate::kernels::{record_all, storage_buffer};
use crate::shaders::Shader;
use crate::{Error, GpuContext, Result};

/// Scenes per timed batch on a hardware adapter when nothing else is asked.
pub const HARDWARE_BATCHES: [usize; 5] = [1, 8, 64, 512, 2048];
/// The same on a software adapter (lavapipe takes seconds per evaluation at 64 scenes).
pub const SOFTWARE_BATCHES: [usize; 2] = [1, 8];
/// Agents per timed scene: the padded count of a busy INTERACTION window.
pub const TUNE_AGENTS: usize = 16;

/// One way to run an evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Candidate {
    /// The blocks as residual chains (`true`) or layer by layer.
    pub residual_chains: bool,
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
            linear_kernel: self.linear_kernel.kernel(),
        }
    }

    /// `chains, auto` and the like: how `road gpu tune` prints it.
    pub fn describe(self) -> String {
        let fusion = if self.residual_chains {
            "chains"
        } else {
            "layers"
        };
        format!("{fusion}, {}", self.linear_kernel.name())
    }
}

/// Every candidate the tuner times for a model: chains only where its rows fit the chain's tile.
pub fn candidates(config: &ModelConfig) -> Vec<Candidate> {
    let fits = config.hidden <= crate::kernels::residual_chain::MAX_HIDDEN as usize;
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

/// A small seeded generator (xorshift64*) for the timed inputs.
struct Inputs(u64);

impl Inputs {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let bits = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 40;
        bits as f32 / (1u64 << 24) as f32
    }

    fn uniform(&mut self, n: usize, low: f32, high: f32) -> Vec<f32> {
        (0..n).map(|_| low + (high - low) * self.next()).collect()
    }
}

/// Times every candidate of [`candidates`] for `gpu`'s model at each of `batches` scenes of
/// `agents` agents (every slot and polyline valid: the kernels' work does not depend on the
/// values), the median of `reps` evaluations each after one untimed, and returns the table.
/// `gpu`'s own tuning is restored afterwards.
pub fn tune(
    ctx: &GpuContext,
    gpu: &mut GpuDenoiser,
    batches: &[usize],
    agents: usize,
    reps: usize,
) -> Result<TuneTable> {
    let before = gpu.tuning().cloned();
    let outcome = time_candidates(ctx, gpu, batches, agents, reps.max(1));
    gpu.set_tuning(before);
    outcome
}

fn time_candidates(
    ctx: &GpuContext,
    gpu: &mut GpuDenoiser,
    batches: &[usize],
    agents: usize,
    reps: usize,
) -> Result<TuneTable> {
    let c = gpu.config.clone();
    let (w, q, p) = (c.window_slots, c.polyline_points, c.map_polylines.max(1));
    let mut rng = Inputs(0x7E57_ED5E);
    let mut tuned = Vec::new();
    for &scenes in batches {
        let tokens = scenes * agents * w;
        let x = rng.uniform(tokens * 3, -1.0, 1.0);
        let sigma = rng.uniform(scenes * w, 0.05, 5.0);
        let valid = vec![1.0; tokens];
        let features = rng.uniform(scenes * agents * 6, -1.0, 1.0);
        let map = rng.uniform(scenes * p * q * 2, -1.0, 1.0);
        let map_valid = vec![1.0; scenes * p];
        let inputs = DenoiseInputs {
            scenes,
            agents,
            x: &x,
            sigma: &sigma,
            valid: &valid,
            agent_features: &features,
        };
        let (batch, map) = match gpu
            .upload_batch(ctx, &inputs)
            .and_then(|b| Ok((b, gpu.encode_map(ctx, scenes, p, &map, &map_valid)?)))
        {
            Ok(uploaded) => uploaded,
            Err(e) => {
                tracing::warn!(scenes, "not tuned at this batch: {e}");
                continue;
            }
        };
        let out = storage_buffer(ctx, "tuned output", (tokens * 3 * 4) as u64);
        let mut timings = Vec::new();
        for candidate in candidates(&c) {
            gpu.set_tuning(Some(fixed(&c, candidate)));
            let timed = (|| -> Result<f64> {
                let scratch = gpu.scratch(ctx, scenes, agents, &map)?;
                let mut ops = Vec::new();
                gpu.prepare_denoise(
                    ctx,
                    &mut ops,
                    &batch,
                    &batch.x,
                    &batch.sigma,
                    &map,
                    &scratch,
                    &out,
                )?;
                let run = || -> Result<()> {
                    let mut enc =
                        ctx.device
                            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                                label: Some("tune"),
                            });
                    record_all(&mut enc, "tune", &ops);
                    ctx.queue.submit([enc.finish()]);
                    ctx.wait()
                };
                run()?;
                let mut ms = Vec::with_capacity(reps);
                for _ in 0..reps {
                    let started = Instant::now();
                    run()?;
                    ms.push(started.elapsed().as_secs_f64() * 1e3);
                }
                ms.sort_by(f64::total_cmp);
                Ok(ms[ms.len() / 2])
            })();
            timings.push(match timed {
                Ok(ms) => Timing {
                    candidate,
                    ms_per_evaluation: Some(ms),
                    error: None,
                },
                Err(e) => Timing {
                    candidate,
                    ms_per_evaluation: None,
                    error: Some(e.to_string()),
                },
            });
        }
        let chosen = timings
            .iter()
            .filter_map(|t| t.ms_per_evaluation.map(|ms| (ms, t.candidate)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, candidate)| candidate);
        let Some(chosen) = chosen else {
            tracing::warn!(scenes, "no candidate ran at this batch: not tuned there");
            continue;
        };
        tuned.push(TunedBatch {
            scenes,
            agents,
            tokens,
            timings,
            chosen,
        });
    }
    if tuned.is_empty() {
        return Err(Error::Input(
            "no batch could be timed: nothing to tune by".into(),
        ));
    }
    tuned.sort_by_key(|b| b.tokens);
    Ok(TuneTable {
        adapter: adapter_key(ctx),
        kernels: kernels_key(),
        model: model_key(&c),
        batches: tuned,
    })
}

/// A table that runs every size as `candidate`: how the tuner times one.
fn fixed(c: &ModelConfig, candidate: Candidate) -> TuneTable {
    TuneTable {
        adapter: String::new(),
        kernels: String::new(),
        model: model_key(c),
        batches: vec![TunedBatch {
            scenes: 1,
            agents: 1,
            tokens: 1,
            timings: Vec::new(),
            chosen: candidate,
        }],
    }
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

/// Where the tuning cache lives: `$ROAD_GPU_TUNE_CACHE`, else `road/gpu-tune.json` in the
/// user's cache folder (`$XDG_CACHE_HOME`, else `~/.cache`); `None` without either.
pub fn cache_path() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("ROAD_GPU_TUNE_CACHE") {
        return Some(PathBuf::from(path));
    }
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .filter(|p| p.is_absolute())
        .or_else(|| std::env::var_os("HOME").map(|home| PathBuf::from(home).join(".cache")))?;
    Some(base.join("road").join("gpu-tune.json"))
}

/// What [`attach`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Attached {
    /// The cache held this adapter's table for the model.
    Cached(PathBuf),
    /// Tuned now (a hardware adapter without a table), and saved when a cache path exists.
    Tuned(Option<PathBuf>),
    /// No table and a software adapter (or tuning failed): the context's options rule.
    Defaults,
}

/// Gives `gpu` its tuning on `ctx`: the cached table if there is one; else, on a hardware
/// adapter, tunes now at [`HARDWARE_BATCHES`] (seconds, once per adapter, driver, kernels and
/// model) and caches the table; on a software adapter (lavapipe) leaves the defaults
/// (`road gpu tune` tunes one on request). A cache file that cannot be read is reported and
/// treated as empty (it is then rewritten). Contexts that name a linear kernel or turn the
/// chains off are the bench's comparisons: they are left as named.
pub fn attach(ctx: &GpuContext, gpu: &mut GpuDenoiser) -> Attached {
    attach_from(ctx, gpu, cache_path())
}

/// [`attach`] with the cache file at `path` (`None`: no cache; a table tuned is not kept).
pub fn attach_from(ctx: &GpuContext, gpu: &mut GpuDenoiser, path: Option<PathBuf>) -> Attached {
    if ctx.named_linear_kernel().is_some() || !ctx.residual_chains() {
        return Attached::Defaults;
    }
    let mut cache = match path.as_deref().map(TuneCache::load) {
        Some(Ok(cache)) => cache,
        Some(Err(e)) => {
            tracing::warn!("{e}: tuning as if it were empty");
            TuneCache::default()
        }
        None => TuneCache::default(),
    };
    if let (Some(table), Some(path)) = (cache.find(ctx, &gpu.config), &path) {
        gpu.set_tuning(Some(table.clone()));
        return Attached::Cached(path.clone());
    }
    if ctx.is_software() {
        return Attached::Defaults;
    }
    tracing::info!(
        adapter = %ctx.describe(),
        "tuning the kernels for this adapter and model (once; `road gpu tune` prints the table)"
    );
    let table = match tune(ctx, gpu, &HARDWARE_BATCHES, TUNE_AGENTS, 3) {
        Ok(table) => table,
        Err(e) => {
            tracing::warn!("tuning failed, running the defaults: {e}");
            return Attached::Defaults;
        }
    };
    gpu.set_tuning(Some(table.clone()));
    cache.insert(table);
    if let Some(path) = &path {
        if let Err(e) = cache.save(path) {
            tracing::warn!("{e}");
            return Attached::Tuned(None);
        }
    }
    Attached::Tuned(path)
}
