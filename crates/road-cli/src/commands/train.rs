//! `road train`: train a denoiser from the dataset caches, with a progress bar, validation,
//! a CSV log and checkpoints; `--resume` continues exactly.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use road_data::{Dataset, SourceSet, Split, WindowConfig, cache};
use road_model::RunConfig;
use road_model::checkpoint::DataIdentity;
use road_model::train::{TrainEvent, Trainer};

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Run config (TOML with [model], [planner], [train]), e.g. configs/road20.toml.
    #[arg(long)]
    pub config: PathBuf,
    /// Per-key override of the run config, e.g. `--set train.batch_scenes=8` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Checkpoint folder; defaults to models/<name>.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Continue the run in the checkpoint folder exactly where it stopped.
    #[arg(long)]
    pub resume: bool,
    /// Stop after this many optimiser steps in total (default: the config's `train.steps`).
    #[arg(long)]
    pub until_step: Option<u64>,
    /// Folder of `train.roadds` / `validation.roadds` (`road data build`); built from
    /// --data into it when absent.
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
    /// Only redraw `loss.png` and rewrite the model card `README.md` from the run folder's
    /// `train_log.csv` and `config.toml`, then exit.
    #[arg(long)]
    pub report_only: bool,
    /// INTERACTION data folder, used when the caches must be built.
    #[arg(long, env = "ROAD_DATA", default_value = "../shared/data/interaction")]
    pub data: PathBuf,
}

/// The data windows a model trains on: `configs/data.toml`'s, lengthened to the model's window
/// where that is longer (DJINN-40's 50 slots need 50-step windows, which cut fewer windows from
/// the recordings, so every other model keeps the 40-step default).
fn training_window(model: &road_model::config::ModelConfig) -> WindowConfig {
    let default = WindowConfig::default();
    WindowConfig {
        window_steps: default.window_steps.max(model.window_slots),
        ..default
    }
}

fn load_or_build(args: &TrainArgs, split: Split, config: &WindowConfig) -> Result<Dataset> {
    let path = cache::cache_path(&args.cache, split);
    if path.is_file() {
        return cache::load_checked(&path, split, Some(config), None).with_context(|| {
            format!(
                "the cache in {} does not fit this model's {}-step windows: pass --cache DIR \
                 (built there when absent)",
                args.cache.display(),
                config.window_steps
            )
        });
    }
    tracing::info!(path = %path.display(), "no cache yet: building it from {}", args.data.display());
    let sources = SourceSet::discover(&args.data)?;
    let ds = Dataset::build(&sources, split, config)?;
    cache::save(&ds, &path)?;
    Ok(ds)
}

pub fn hardware() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    format!("{cpu}, {threads} threads")
}

/// `DIR/loss.png` from `DIR/train_log.csv`: training loss (running mean, blue) and
/// validation loss (orange), log scale.
fn plot_loss(dir: &std::path::Path) -> Result<()> {
    let (train, validation) = crate::plot::read_train_log(&dir.join("train_log.csv"))?;
    crate::plot::loss_png(&dir.join("loss.png"), &train, &validation)
}

/// `DIR/README.md`: the model card, from `config.toml`.
fn write_model_card(dir: &std::path::Path) -> Result<()> {
    let meta = road_model::checkpoint::CheckpointMeta::load(dir)?;
    let r = &meta.run;
    let loss = |v: Option<f64>| v.map_or("not measured".to_owned(), |v| format!("{v:.4}"));
    let card = format!(
        "# {name}: {kind:?} denoiser (RoAD project)\n\n\
A DJINN-style scene denoiser ({params} parameters: D = {d}, {heads} heads, {blocks} blocks, W = {w} slots: \
{n} observed + {f} future) for the `{kind:?}` planner (K = {k}).\n\n\
## Data\n\n\
Derived from the INTERACTION dataset (DR v1.0 recordings; released for non-commercial research use only: \
this model is a derived work under that licence). {source}. Train cache: {train_windows} windows of {window_s} s; \
validation: {val_windows} windows.\n\n\
## Training\n\n\
| | |\n|---|---|\n\
| optimiser steps | {step} of {steps} planned |\n\
| batch | {batch} scenes |\n\
| wall time | {wall:.0} s ({hours:.2} h) |\n\
| hardware (the last session's) | {hardware}; {workers} |\n\
| conditioning augmentation | r = {r}, warm-up task probability β = {beta}{initialisation} |\n\
| validation denoising loss (EMA weights) | {val} |\n\
| same, {start} | {untrained} |\n\n\
The loss is EDM's weighted denoising loss, averaged over valid agent-slots of fixed validation batches \
(`train_log.csv`, `loss.png`). Files: `weights.safetensors` (EMA weights, format in `docs/checkpoint.md`), \
`config.toml` (every hyperparameter); while the run goes on, `train_state.safetensors` (for `road train --resume`; \
not shipped once the schedule is over).\n\n\
## Use\n\n\
```sh\nroad sample --checkpoint models/{name} --scene val:0 --out sample.png\n```\n\n\
## Limits\n\n\
A small model trained briefly on CPUs; the paper's model is far larger and trained for 36 GPU-days. \
Forecasting and reactivity figures (`road eval --suite forecasting|reactivity`) are in `docs/results.md`. \
The wall time adds up every session of the run (resumed across sessions, at times sharing the machine with other \
trainings): it is not this model's alone; `train_log.csv` gives samples/s for each logged step.\n",
        name = r.name,
        workers = match r.train.workers {
            1 => "one training thread".to_owned(),
            n => format!("{n} data-parallel workers, one thread each"),
        },
        kind = r.planner.kind,
        params = meta.parameters,
        d = r.model.hidden,
        heads = r.model.heads,
        blocks = r.model.blocks,
        w = r.model.window_slots,
        n = r.planner.obs_slots,
        f = r.planner.future_slots,
        k = r.planner.steps_per_diffusion,
        source = meta.data.source,
        train_windows = meta.data.train_windows,
        window_s = training_window(&r.model).window_steps as f64 / 10.0,
        val_windows = meta.data.validation_windows,
        step = meta.step,
        steps = r.train.steps,
        batch = r.train.batch_scenes,
        wall = meta.wall_secs,
        hours = meta.wall_secs / 3600.0,
        hardware = meta.hardware,
        r = r.train.augmentation_ratio,
        beta = r.train.warmup_task_prob,
        initialisation = if r.train.initialisation_task_prob > 0.0 {
            format!(
                ", initialisation task probability {} (whole agents drawn from noise around kept \
                 ones; `road_sim::populate::initialise_histories` samples with it; its validation \
                 loss mixes that task in, so it does not compare with other runs')",
                r.train.initialisation_task_prob
            )
        } else {
            String::new()
        },
        val = loss(meta.validation_loss),
        untrained = loss(meta.untrained_validation_loss),
        start = match &r.train.init_from {
            None => "untrained model".to_owned(),
            Some(dir) => format!("at the start (the weights of `{}`)", dir.display()),
        },
    );
    std::fs::write(dir.join("README.md"), card)
        .with_context(|| format!("cannot write the model card in {}", dir.display()))
}

pub fn run(args: TrainArgs) -> Result<ExitCode> {
    let run: RunConfig = crate::config::load(Some(&args.config), &args.overrides)?;
    run.validate()
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("bad run config {}", args.config.display()))?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("models").join(&run.name));
    if args.report_only {
        plot_loss(&out)?;
        write_model_card(&out)?;
        return Ok(ExitCode::SUCCESS);
    }
    let window = training_window(&run.model);
    anyhow::ensure!(
        window.polyline_points == run.model.polyline_points
            && window.position_scale_m == run.model.position_scale_m,
        "model.polyline_points / position_scale_m must equal configs/data.toml's ({}, {})",
        window.polyline_points,
        window.position_scale_m
    );
    let train_set = load_or_build(&args, Split::Train, &window)?;
    let validation_set = load_or_build(&args, Split::Validation, &window)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("models").join(&run.name));
    let data = DataIdentity {
        train_cache: cache::cache_path(&args.cache, Split::Train)
            .display()
            .to_string(),
        train_windows: train_set.len(),
        validation_windows: validation_set.len(),
        source: "INTERACTION DR v1.0 (non-commercial licence), official validation split".into(),
    };
    let mut trainer = Trainer::new(
        run.clone(),
        &validation_set,
        data,
        args.resume.then_some(out.as_path()),
    )
    .with_context(|| format!("cannot start the run in {}", out.display()))?;
    let until = args
        .until_step
        .unwrap_or(run.train.steps)
        .min(run.train.steps);
    eprintln!(
        "training {} ({} parameters) from step {} to {until}; train {} windows, validation {}; untrained validation loss {:?}",
        run.name,
        trainer.parameter_count(),
        trainer.step,
        train_set.len(),
        validation_set.len(),
        trainer.untrained_validation_loss()
    );
    let bar = ProgressBar::new(until);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} ETA {eta} {msg}",
        )
        .expect("valid template"),
    );
    bar.set_position(trainer.step);
    let started = Instant::now();
    let start_step = trainer.step;
    let mut last_val = None;
    trainer.run_until(&train_set, &out, until, &hardware(), |event| match event {
        TrainEvent::Step(r) => {
            let rate = (r.step - start_step) as f64 * run.train.batch_scenes as f64
                / started.elapsed().as_secs_f64();
            bar.set_position(r.step);
            bar.set_message(format!(
                "loss {:.4} val {} lr {:.2e} {rate:.1} samples/s",
                r.loss,
                last_val.map_or("-".into(), |v: f64| format!("{v:.4}")),
                r.learning_rate
            ));
        }
        TrainEvent::Validation { loss, .. } => last_val = Some(*loss),
        TrainEvent::Checkpoint { step, dir } => {
            bar.println(format!("checkpoint at step {step} in {}", dir.display()))
        }
    })?;
    bar.finish();
    plot_loss(&out)?;
    write_model_card(&out)?;
    let secs = started.elapsed().as_secs_f64();
    out!(
        "{}: step {} validation loss {:?} (untrained {:?}); {:.1} samples/s over {:.0} s; checkpoint in {}",
        run.name,
        trainer.step,
        last_val,
        trainer.untrained_validation_loss(),
        (trainer.step - start_step) as f64 * run.train.batch_scenes as f64 / secs,
        secs,
        out.display()
    );
    Ok(ExitCode::SUCCESS)
}
