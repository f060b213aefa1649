//! The autotuner (issue 40): on the adapter at hand, time one denoiser evaluation of a model
//! under each way the engine can run it (the blocks as residual chains or layer by layer; the
//! linear layers' kernel chosen by size or one variant everywhere) at several batch sizes, and
//! keep the fastest per size. The tables are cached in one JSON file keyed by adapter, driver,
//! the kernels' sources and the model's shapes, so a GPU nobody here has seen gets its best
//! variant from its second start on (`road gpu tune` prints and writes them; `road serve` and
//! `road demo` tune a hardware adapter they have no table for once, and read the table after).

use std::path::PathBuf;
use std::time::Instant;

use road_model::ModelConfig;

use crate::engine::{DenoiseInputs, GpuDenoiser};
use crate::kernels::{record_all, storage_buffer};
use crate::selftest::Inputs;
pub use crate::tuning::{
    Candidate, EvalSettings, LinearChoice, Timing, TuneCache, TuneTable, TunedBatch, adapter_key,
    candidates, kernels_key, model_key,
};
use crate::{Error, GpuContext, Result};

/// Scenes per timed batch on a hardware adapter when nothing else is asked.
pub const HARDWARE_BATCHES: [usize; 5] = [1, 8, 64, 512, 2048];
/// The same on a software adapter (lavapipe takes seconds per evaluation at 64 scenes).
pub const SOFTWARE_BATCHES: [usize; 2] = [1, 8];
/// Agents per timed scene: the padded count of a busy INTERACTION window.
pub const TUNE_AGENTS: usize = 16;

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
        let x = rng.uniform(tokens * 3, 1.0);
        // σ across the schedule's busy range, [0.05, 5.05).
        let sigma: Vec<f32> = rng
            .uniform(scenes * w, 2.5)
            .into_iter()
            .map(|s| s + 2.55)
            .collect();
        let valid = vec![1.0; tokens];
        let features = rng.uniform(scenes * agents * 6, 1.0);
        let map = rng.uniform(scenes * p * q * 2, 1.0);
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
                if candidate.wide_chains && gpu.wide_chain_tile().is_none() {
                    return Err(Error::Device(
                        "no wide chain tile for this model on this device (D a multiple of 8, \
                         M of 4, at least 16 rows within its workgroup memory)"
                            .into(),
                    ));
                }
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
