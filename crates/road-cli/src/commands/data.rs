//! `road data …`: statistics and caches of the INTERACTION recordings.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use road_data::stats::{self, LocationStats, MAX_MEDIAN_LANE_DISTANCE_M, SplitStats};
use road_data::{Dataset, SourceSet, Split, WindowConfig, cache};

#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Print files, hours, windows, agents per window, polylines per location and the
    /// projection check (median distance from track points to the nearest lane centre,
    /// which must be under 1.5 m at every location; the exit code is 1 otherwise).
    Stats(StatsArgs),
    /// Parse the recordings once and write one cache file per split (train, validation).
    Build(BuildArgs),
    /// Write the caches as flat arrays for the PyTorch training path
    /// (`scripts/torch_train.py`, docs/torch-training.md): `train.safetensors` and
    /// `validation.safetensors` (tracks, lanelet centre lines, window index: what the caches
    /// store, about their size) and, with `--config`, the run's fixed validation batches
    /// (`validation_batches.safetensors`), so that PyTorch validates on `road train`'s scenes.
    ExportTorch(ExportTorchArgs),
}

#[derive(Debug, Args)]
pub struct ExportTorchArgs {
    /// Folder of `train.roadds` / `validation.roadds` (`road data build`).
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
    /// Output folder (carried to a GPU machine: keep it under `.road-cache/`, git-ignored).
    #[arg(long, default_value = ".road-cache/torch")]
    pub out: PathBuf,
    /// Run config whose fixed validation batches to write too, e.g. configs/road20-wide4.toml.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Per-key override of the run config (as `road train --set`; `train.batch_scenes` and
    /// `train.val_batches` shape the validation batches).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Which splits to export: train, validation or both.
    #[arg(long, value_enum, default_value_t = SplitChoice::Both)]
    pub split: SplitChoice,
}

#[derive(Debug, Args)]
pub struct SourceArgs {
    /// The INTERACTION data folder (with maps/ and recorded_trackfiles/).
    #[arg(long, env = "ROAD_DATA", default_value = "../shared/data/interaction")]
    pub data: PathBuf,
    /// Window config (TOML); the built-in defaults equal configs/data.toml.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Per-key override of the window config, e.g. `--set window_steps=20` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Which splits to read: train, validation or both.
    #[arg(long, value_enum, default_value_t = SplitChoice::Both)]
    pub split: SplitChoice,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SplitChoice {
    Train,
    Validation,
    Both,
}

impl SplitChoice {
    fn splits(self) -> &'static [Split] {
        match self {
            SplitChoice::Train => &[Split::Train],
            SplitChoice::Validation => &[Split::Validation],
            SplitChoice::Both => &[Split::Train, Split::Validation],
        }
    }
}

#[derive(Debug, Args)]
pub struct StatsArgs {
    #[command(flatten)]
    pub source: SourceArgs,
    /// Read the caches in this folder instead of parsing the recordings (they must be
    /// current: same files, same window config).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Print JSON instead of tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct BuildArgs {
    #[command(flatten)]
    pub source: SourceArgs,
    /// Folder for `train.roadds` and `validation.roadds`.
    #[arg(long, default_value = ".road-cache")]
    pub out: PathBuf,
}

pub fn run(cmd: DataCommand) -> Result<ExitCode> {
    match cmd {
        DataCommand::Stats(args) => stats_cmd(&args),
        DataCommand::Build(args) => build_cmd(&args).map(|()| ExitCode::SUCCESS),
        DataCommand::ExportTorch(args) => export_torch_cmd(&args).map(|()| ExitCode::SUCCESS),
    }
}

fn export_torch_cmd(args: &ExportTorchArgs) -> Result<()> {
    use road_model::torch_export;
    let mut total = 0u64;
    let mut validation_set = None;
    for &split in args.split.splits() {
        let path = cache::cache_path(&args.cache, split);
        let ds = cache::load_checked(&path, split, None, None).with_context(|| {
            format!("cannot read the {split} cache (`road data build` writes it)")
        })?;
        let out = args.out.join(format!("{}.safetensors", split.name()));
        let bytes = torch_export::dataset_arrays(&ds)
            .and_then(|file| file.save(&out))
            .with_context(|| format!("cannot export the {split} split to {}", out.display()))?;
        total += bytes;
        out!(
            "{:<10} {:>7} windows {:>4} recordings -> {} ({:.1} MiB)",
            split.name(),
            ds.len(),
            ds.recordings.len(),
            out.display(),
            bytes as f64 / (1024.0 * 1024.0)
        );
        if split == Split::Validation {
            validation_set = Some(ds);
        }
    }
    if let Some(config) = &args.config {
        let run: road_model::RunConfig = crate::config::load(Some(config), &args.overrides)?;
        run.validate()
            .map_err(anyhow::Error::msg)
            .with_context(|| format!("bad run config {}", config.display()))?;
        let ds = validation_set.context(
            "the validation batches need the validation split: leave out --split or pass both",
        )?;
        anyhow::ensure!(
            ds.config.window_steps >= run.model.window_slots
                && ds.config.polyline_points == run.model.polyline_points,
            "the validation cache's windows ({} steps, {} polyline points) do not fit the model \
             of {} ({} slots, {} points)",
            ds.config.window_steps,
            ds.config.polyline_points,
            config.display(),
            run.model.window_slots,
            run.model.polyline_points
        );
        let out = args.out.join("validation_batches.safetensors");
        let bytes = torch_export::validation_batch_arrays(&run, &ds)
            .and_then(|file| file.save(&out))
            .with_context(|| format!("cannot write the validation batches to {}", out.display()))?;
        total += bytes;
        out!(
            "{:<10} {} batches of {} scenes ({}) -> {} ({:.1} MiB)",
            "batches",
            run.train.val_batches,
            run.train.batch_scenes,
            run.name,
            out.display(),
            bytes as f64 / (1024.0 * 1024.0)
        );
    }
    out!(
        "total {:.1} MiB in {}",
        total as f64 / (1024.0 * 1024.0),
        args.out.display()
    );
    Ok(())
}

fn window_config(args: &SourceArgs) -> Result<WindowConfig> {
    let config: WindowConfig = crate::config::load(args.config.as_deref(), &args.overrides)?;
    config
        .validate()
        .map_err(anyhow::Error::msg)
        .context("bad window config")?;
    Ok(config)
}

fn build_split(sources: &SourceSet, split: Split, config: &WindowConfig) -> Result<Dataset> {
    let started = Instant::now();
    let ds = Dataset::build(sources, split, config).with_context(|| {
        format!(
            "cannot build the {split} split from {}",
            sources.root.display()
        )
    })?;
    tracing::info!(%split, files = ds.recordings.len(), windows = ds.len(), secs = started.elapsed().as_secs_f32(), "parsed");
    Ok(ds)
}

fn build_cmd(args: &BuildArgs) -> Result<()> {
    let config = window_config(&args.source)?;
    let sources = SourceSet::discover(&args.source.data)?;
    for &split in args.source.split.splits() {
        let ds = build_split(&sources, split, &config)?;
        let path = cache::cache_path(&args.out, split);
        cache::save(&ds, &path)?;
        let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
        out!(
            "{split:<10} {:>4} files {:>7} windows  -> {} ({:.1} MiB)",
            ds.recordings.len(),
            ds.len(),
            path.display(),
            bytes as f64 / (1024.0 * 1024.0)
        );
        report_skips(&ds);
    }
    Ok(())
}

fn report_skips(ds: &Dataset) {
    let r = &ds.report;
    out!(
        "{:<10} skipped {} windows with fewer than {} agents; dropped {} agents over {} and {} polylines over {}",
        ds.split.name(),
        r.windows_skipped_few_agents,
        ds.config.min_agents,
        r.agents_dropped_over_max,
        ds.config.max_agents,
        r.polylines_dropped_over_max,
        ds.config.max_polylines
    );
    if !r.missing_validation_files.is_empty() {
        out!(
            "{:<10} validation list names {} files absent here: {}",
            ds.split.name(),
            r.missing_validation_files.len(),
            r.missing_validation_files.join(", ")
        );
    }
}

fn load_datasets(args: &StatsArgs, config: &WindowConfig) -> Result<Vec<Dataset>> {
    match &args.cache {
        Some(dir) => {
            let sources = SourceSet::discover(&args.source.data).ok();
            args.source
                .split
                .splits()
                .iter()
                .map(|&split| {
                    let path = cache::cache_path(dir, split);
                    cache::load_checked(&path, split, Some(config), sources.as_ref())
                        .map_err(anyhow::Error::from)
                })
                .collect()
        }
        None => {
            let sources = SourceSet::discover(&args.source.data)?;
            args.source
                .split
                .splits()
                .iter()
                .map(|&s| build_split(&sources, s, config))
                .collect()
        }
    }
}

fn stats_cmd(args: &StatsArgs) -> Result<ExitCode> {
    let config = window_config(&args.source)?;
    let datasets = load_datasets(args, &config)?;
    let splits: Vec<SplitStats> = datasets.iter().map(stats::split_stats).collect();
    let locations = stats::location_stats(&datasets.iter().collect::<Vec<_>>());
    let failing: Vec<&LocationStats> = locations
        .iter()
        .filter(|l| !l.passes_projection_check())
        .collect();
    if args.json {
        let json = serde_json::json!({ "data": args.source.data, "window_config": config, "splits": splits, "locations": locations, "projection_check_passed": failing.is_empty() });
        out!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        print_tables(&args.source.data, &config, &splits, &locations, &datasets);
    }
    if failing.is_empty() {
        Ok(ExitCode::SUCCESS)
    } else {
        for l in failing {
            eprintln!(
                "projection check failed: median lane distance {:.2} m ≥ {MAX_MEDIAN_LANE_DISTANCE_M} m at {}",
                l.median_lane_distance_m, l.location
            );
        }
        Ok(ExitCode::FAILURE)
    }
}

fn print_tables(
    data: &Path,
    config: &WindowConfig,
    splits: &[SplitStats],
    locations: &[LocationStats],
    datasets: &[Dataset],
) {
    out!("INTERACTION data in {}", data.display());
    out!(
        "windows: {} steps ({:.1} s), stride {}, agents present at step {} ({}..={}), map radius {} m, {} points per polyline",
        config.window_steps,
        config.window_steps as f64 * road_data::tracks::STEP_SECS,
        config.stride_steps,
        config.reference_step,
        config.min_agents,
        config.max_agents,
        config.map_radius_m,
        config.polyline_points
    );
    out!("");
    out!("| split | files | hours | windows | agents/window mean | p95 | max | position RMS (m) |");
    out!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for s in splits {
        out!(
            "| {} | {} | {:.2} | {} | {:.2} | {} | {} | {:.1} |",
            s.split,
            s.files,
            s.hours,
            s.windows,
            s.agents_mean,
            s.agents_p95,
            s.agents_max,
            s.position_rms_m
        );
    }
    out!("");
    for ds in datasets {
        report_skips(ds);
    }
    out!("");
    out!(
        "| location | files | hours | windows | polylines | track points | median lane distance (m) | check |"
    );
    out!("|---|---:|---:|---:|---:|---:|---:|---|");
    for l in locations {
        let ok = l.passes_projection_check();
        out!(
            "| {} | {} | {:.2} | {} | {} | {} | {:.2} | {} |",
            l.location,
            l.files,
            l.hours,
            l.windows,
            l.polylines,
            l.track_points,
            l.median_lane_distance_m,
            if ok { "ok" } else { "FAIL" }
        );
    }
}
