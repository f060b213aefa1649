//! The autotuner on the adapter at hand (lavapipe in CI): every candidate timed at every batch
//! and the fastest chosen; the cache file round-trips, is keyed by adapter, kernels and model,
//! and names itself when it does not parse; a denoiser runs each evaluation as its table chose.

use std::path::PathBuf;

use road_gpu::engine::DenoiseInputs;
use road_gpu::tune::{self, Attached, Candidate, LinearChoice, TuneCache, TuneTable};
use road_gpu::{ContextOptions, GpuContext, Tolerance};
use road_model::ModelConfig;

mod common;
use common::denoiser;

fn context() -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

/// road20-wide4's features at a small size, with a small map.
fn config() -> ModelConfig {
    ModelConfig {
        map_polylines: 6,
        ..common::config()
    }
}

/// A fresh folder under the system's temporary one.
fn temporary(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("road-tune-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn every_candidate_is_timed_at_every_batch_and_the_fastest_chosen() {
    let ctx = context();
    let config = config();
    let mut gpu = denoiser(&ctx, &config);
    let table = tune::tune(&ctx, &mut gpu, &[2, 1], 3, 1).unwrap();
    assert!(
        gpu.tuning().is_none(),
        "the denoiser's own tuning is restored"
    );
    assert_eq!(table.adapter, tune::adapter_key(&ctx));
    assert_eq!(table.kernels, tune::kernels_key());
    assert_eq!(table.model, tune::model_key(&config));
    let tokens: Vec<usize> = table.batches.iter().map(|b| b.tokens).collect();
    let w = config.window_slots;
    assert_eq!(tokens, vec![3 * w, 2 * 3 * w], "by increasing tokens");
    let every = tune::candidates(&config);
    assert_eq!(
        every.len(),
        10,
        "chains and layers × auto and the three kernels, wide chains × auto and blocked"
    );
    assert_eq!(every.iter().filter(|c| c.wide_chains).count(), 2);
    for batch in &table.batches {
        let timed: Vec<Candidate> = batch.timings.iter().map(|t| t.candidate).collect();
        assert_eq!(timed, every);
        let fastest = batch
            .timings
            .iter()
            .min_by(|a, b| {
                a.ms_per_evaluation
                    .unwrap()
                    .total_cmp(&b.ms_per_evaluation.unwrap())
            })
            .unwrap();
        assert!(batch.timings.iter().all(|t| t.error.is_none()));
        assert_eq!(batch.chosen, fastest.candidate);
    }
    // A model wider than the chain's tile is timed layer by layer only.
    let wide = ModelConfig {
        hidden: 512,
        heads: 8,
        ..config.clone()
    };
    assert!(tune::candidates(&wide).iter().all(|c| !c.residual_chains));
    // One whose widths the wide tile's vec4 reads cannot take gets the narrow tile only.
    let odd = ModelConfig {
        hidden: 36,
        heads: 2,
        ..config.clone()
    };
    let candidates = tune::candidates(&odd);
    assert!(candidates.iter().any(|c| c.residual_chains));
    assert!(candidates.iter().all(|c| !c.wide_chains));
}

/// A cache written before the wide tile existed (no `wide_chains` field) still parses, its
/// choices on the narrow tile.
#[test]
fn a_candidate_without_the_wide_field_is_on_the_narrow_tile() {
    let old: Candidate =
        serde_json::from_str(r#"{"residual_chains": true, "linear_kernel": "blocked"}"#).unwrap();
    assert_eq!(
        old,
        Candidate {
            residual_chains: true,
            wide_chains: false,
            linear_kernel: LinearChoice::Blocked,
        }
    );
}

/// A table that runs every size as `candidate`.
fn table_choosing(ctx: &GpuContext, config: &ModelConfig, candidate: Candidate) -> TuneTable {
    TuneTable {
        adapter: tune::adapter_key(ctx),
        kernels: tune::kernels_key(),
        model: tune::model_key(config),
        batches: vec![tune::TunedBatch {
            scenes: 4,
            agents: 3,
            tokens: 4 * 3 * config.window_slots,
            timings: Vec::new(),
            chosen: candidate,
        }],
    }
}

#[test]
fn the_cache_round_trips_keyed_by_adapter_kernels_and_model() {
    let ctx = context();
    let config = config();
    let dir = temporary("cache");
    let path = dir.join("nested").join("gpu-tune.json");
    assert_eq!(TuneCache::load(&path).unwrap(), TuneCache::default());
    let layers = Candidate {
        residual_chains: false,
        wide_chains: false,
        linear_kernel: LinearChoice::Blocked,
    };
    let chains = Candidate {
        residual_chains: true,
        wide_chains: true,
        linear_kernel: LinearChoice::Auto,
    };
    let mut cache = TuneCache::default();
    cache.insert(table_choosing(&ctx, &config, layers));
    cache.insert(table_choosing(&ctx, &config, chains));
    assert_eq!(cache.tables.len(), 1, "the same key is replaced");
    let other = ModelConfig {
        hidden: 48,
        ..config.clone()
    };
    cache.insert(table_choosing(&ctx, &other, layers));
    cache.save(&path).unwrap();
    let loaded = TuneCache::load(&path).unwrap();
    assert_eq!(loaded, cache);
    assert_eq!(
        loaded.find(&ctx, &config).unwrap().batches[0].chosen,
        chains
    );
    assert_eq!(loaded.find(&ctx, &other).unwrap().batches[0].chosen, layers);
    let unseen = ModelConfig {
        blocks: 5,
        ..config.clone()
    };
    assert!(loaded.find(&ctx, &unseen).is_none());
    let mut stale = loaded.clone();
    stale.tables[0].kernels = "0000000000000000".into();
    stale.tables[1].adapter = "another GPU".into();
    assert!(stale.find(&ctx, &config).is_none(), "other kernels");
    assert!(stale.find(&ctx, &other).is_none(), "another adapter");

    std::fs::write(&path, "{\"tables\": [ {\"adapter\": 3").unwrap();
    let err = TuneCache::load(&path).unwrap_err().to_string();
    assert!(err.contains(&path.display().to_string()), "{err}");
    assert!(err.contains("line 1"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `attach_from` on a software adapter: no table, the defaults; a cached table, that one; a
/// file that does not parse, reported and the defaults.
#[test]
fn attach_takes_the_cached_table_and_leaves_the_defaults_without_one() {
    let ctx = context();
    if !ctx.is_software() {
        // A hardware adapter tunes when it finds no table: checked on lavapipe (CI).
        return;
    }
    let config = config();
    let dir = temporary("attach");
    let path = dir.join("gpu-tune.json");
    let mut gpu = denoiser(&ctx, &config);
    assert_eq!(
        tune::attach_from(&ctx, &mut gpu, Some(path.clone())),
        Attached::Defaults
    );
    assert!(gpu.tuning().is_none());
    let layers = Candidate {
        residual_chains: false,
        wide_chains: false,
        linear_kernel: LinearChoice::Rowwise,
    };
    let mut cache = TuneCache::default();
    cache.insert(table_choosing(&ctx, &config, layers));
    cache.save(&path).unwrap();
    assert_eq!(
        tune::attach_from(&ctx, &mut gpu, Some(path.clone())),
        Attached::Cached(path.clone())
    );
    assert_eq!(gpu.tuning(), cache.find(&ctx, &config));
    std::fs::write(&path, "not json").unwrap();
    let mut fresh = denoiser(&ctx, &config);
    assert_eq!(
        tune::attach_from(&ctx, &mut fresh, Some(path)),
        Attached::Defaults
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A denoiser with a table runs each evaluation as chosen for the nearest timed size: layer by
/// layer when the table says so (more dispatches, the same values as the chains'), the chains
/// on the narrow or the wide tile otherwise (the same dispatches, the same values).
#[test]
fn a_denoiser_runs_as_its_table_chose() {
    let ctx = context();
    let config = config();
    let (scenes, agents, polylines) = (2, 3, 6);
    let (w, q) = (config.window_slots, config.polyline_points);
    let wave = |n: usize, scale: f32| -> Vec<f32> {
        (0..n).map(|i| ((i as f32) * 0.37).sin() * scale).collect()
    };
    let x = wave(scenes * agents * w * 3, 1.5);
    let sigma: Vec<f32> = (0..scenes * w)
        .map(|i| 0.1 + (i % 7) as f32 * 0.5)
        .collect();
    let valid = vec![1.0; scenes * agents * w];
    let features = wave(scenes * agents * 6, 1.0);
    let map = wave(scenes * polylines * q * 2, 2.0);
    let map_valid = vec![1.0; scenes * polylines];
    let inputs = DenoiseInputs {
        scenes,
        agents,
        x: &x,
        sigma: &sigma,
        valid: &valid,
        agent_features: &features,
    };
    let tokens = scenes * agents * w;
    let mut outputs = Vec::new();
    for (residual_chains, wide_chains) in [(true, false), (true, true), (false, false)] {
        let mut gpu = denoiser(&ctx, &config);
        let chosen = Candidate {
            residual_chains,
            wide_chains,
            linear_kernel: LinearChoice::Auto,
        };
        gpu.set_tuning(Some(table_choosing(&ctx, &config, chosen)));
        assert_eq!(gpu.settings_for(&ctx, tokens), chosen.settings());
        // Far from the timed size: still the only row's choice.
        assert_eq!(gpu.settings_for(&ctx, 100 * tokens), chosen.settings());
        let map_tokens = gpu
            .encode_map(&ctx, scenes, polylines, &map, &map_valid)
            .unwrap();
        let batch = gpu.upload_batch(&ctx, &inputs).unwrap();
        let mut plan = gpu.heun_plan(&ctx, &batch, &map_tokens).unwrap();
        plan.run(&ctx, &batch, &sigma, &sigma, false).unwrap();
        let dispatches = plan.take_traffic().dispatches;
        // Chains: the first makes the embedding too, every other its attention, the last the
        // Euler step.
        let expected = if residual_chains {
            4 + 3 * config.blocks
        } else {
            4 + 11 * config.blocks + 3
        };
        assert_eq!(
            dispatches as usize, expected,
            "chains {residual_chains}, wide {wide_chains}"
        );
        outputs.push(gpu.denoise(&ctx, &inputs, &map_tokens).unwrap());
    }
    let tol = Tolerance {
        rel: 1e-4,
        abs: 1e-5,
    };
    for (name, output) in [("narrow", &outputs[0]), ("wide", &outputs[1])] {
        if let Err(m) = tol.check(output, &outputs[2]) {
            panic!("chains on the {name} tile against layers: {m}");
        }
    }
}
