//! What the evaluation suites share: their command-line arguments, the choice of scenes and
//! progress for logs.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use clap::Args;
use road_data::Dataset;
use road_sim::procedural::ProceduralMap;

use crate::commands::sample::Engine;

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Suite: `forecasting` (10 observed steps, 30 predicted, joint samples per scene),
    /// `reactivity` (an adversarial agent per scene, 40 simulated steps after 10 observed) or
    /// `procedural` (`road demo`'s closed loop on the procedural maps over seeds and rotations:
    /// vehicles off road and collisions; no INTERACTION data needed) or `long` (sessions of
    /// `--minutes` on the procedural maps and INTERACTION locations with inflow, every vehicle
    /// the model's: counts per vehicle-minute) or `initialisation` (validation scenes
    /// repopulated around one fixed vehicle by the heuristic placement, by the model's
    /// refinement of it and, with `--initialiser`, drawn by a model trained to, against the
    /// log: Jensen–Shannon distances of speed, lane offset, heading offset and gap ahead).
    #[arg(long, default_value = "forecasting")]
    pub suite: String,
    /// Checkpoints to evaluate; a constant-velocity baseline is always added.
    #[arg(long, num_args = 1.., default_values = ["models/road20-wide4"])]
    pub checkpoints: Vec<PathBuf>,
    /// Run every checkpoint under this planner of `configs/planners.toml` instead of its own
    /// (rows named `checkpoint [planner]`); it must fit the checkpoint's window.
    #[arg(long)]
    pub planner: Option<String>,
    /// Joint samples per scene (default: 6 for forecasting, 3 for reactivity).
    #[arg(long)]
    pub samples: Option<usize>,
    /// Scenes evaluated (spread evenly over the eligible ones); 0 = all.
    #[arg(long, default_value_t = 60)]
    pub limit: usize,
    /// Locations kept: the ones with the most eligible scenes.
    #[arg(long, default_value_t = 6)]
    pub top_locations: usize,
    /// Scenes with fewer agents present at the last observed step are left out.
    #[arg(long, default_value_t = 4)]
    pub min_agents: usize,
    /// Miss threshold (metres) on the final displacement.
    #[arg(long, default_value_t = 2.0)]
    pub miss_threshold_m: f64,
    /// Scenes per batched rollout (each repeated `samples` times in the batch).
    #[arg(long, default_value_t = 8)]
    pub batch_scenes: usize,
    #[arg(long, value_enum, default_value_t = Engine::Cpu)]
    pub engine: Engine,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value = ".road-cache")]
    pub cache: PathBuf,
    /// Also write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Reactivity: the INTERACTION data folder (its windows are cut 50 steps long, longer than
    /// the training caches' 40).
    #[arg(long, env = "ROAD_DATA", default_value = "../shared/data/interaction")]
    pub data: PathBuf,
    /// Reactivity: simulated steps after the observations.
    #[arg(long, default_value_t = 40)]
    pub sim_steps: usize,
    /// Draw the first this many scenes of every model (paper style) into `--figures` (both suites).
    #[arg(long, default_value_t = 0)]
    pub figure_scenes: usize,
    /// Folder for the figures.
    #[arg(long, default_value = "eval-figures")]
    pub figures: PathBuf,
    /// Procedural: runs per map and rotation, noise seeds `--seed`, `--seed` + 1, ….
    #[arg(long, default_value_t = 5)]
    pub seeds: u64,
    /// Procedural: each map turned counter-clockwise by each of these angles (degrees).
    #[arg(long, num_args = 1.., default_values_t = [0.0], allow_negative_numbers = true)]
    pub rotations_deg: Vec<f64>,
    /// Procedural and long: the maps (`roundabout`, `intersection`, `merge`; long also takes
    /// INTERACTION locations, e.g. `DR_USA_Roundabout_FT`); default the three procedural ones.
    #[arg(long, num_args = 1..)]
    pub maps: Vec<String>,
    /// Procedural: simulated steps per run (`road demo`'s 60 by default).
    #[arg(long, default_value_t = 60)]
    pub procedural_steps: usize,
    /// Procedural: the scripted ego's speed as a share of its route's (0: it stops where its
    /// history ends, holding up the vehicles behind it and those that must pass it).
    #[arg(long, default_value_t = 1.0)]
    pub ego_speed_scale: f64,
    /// Procedural: the map's scripted vehicles replaced by this many placed around the ego and
    /// refined by the model (`road demo --populate`).
    #[arg(long)]
    pub populate: Option<usize>,
    /// With `--populate`: the placement as it is, without the model's refinement.
    #[arg(long, requires = "populate")]
    pub populate_unrefined: bool,
    /// Initialisation: also draw the scene's vehicles with this checkpoint (one trained with the
    /// initialisation task, e.g. `models/road20-init`), from each of `--initialiser-sigmas`.
    /// Procedural and long, with `--populate`: the placed vehicles redrawn by it as a served
    /// scene's are (from σ = 0.1, draws off the lanes or onto another keeping the refinement).
    #[arg(long, conflicts_with = "populate_unrefined")]
    pub initialiser: Option<PathBuf>,
    /// Initialisation: the σ (scene units, 40 m each) the initialiser's vehicles start at:
    /// σ_max (80) draws them from noise alone, a lower σ around the heuristic's placement.
    #[arg(long, num_args = 1.., default_values_t = [80.0, 0.25])]
    pub initialiser_sigmas: Vec<f64>,
    /// Initialisation: Heun steps of the initialiser from its σ down to σ_min.
    #[arg(long, default_value_t = 32)]
    pub initialiser_steps: usize,
    /// Long: minutes per session.
    #[arg(long, default_value_t = 10.0)]
    pub minutes: f64,
    /// Long: vehicles entering per minute at each of the map's entry lanes.
    #[arg(long, default_value_t = 6.0)]
    pub inflow_per_minute: f64,
    /// Long: write each session's ticks to this folder, one JSON line a tick
    /// (`<map>-seed<seed>.jsonl`: the poses, guard actions, collisions, off-road agents, and
    /// which agents entered, with their sizes, and left), and its map and starting vehicles'
    /// sizes beside them (`<map>-seed<seed>.map.json`).
    #[arg(long)]
    pub trace: Option<PathBuf>,
}

/// The checkpoint of `--initialiser`, loaded and checked: trained to draw whole vehicles.
pub(crate) fn load_initialiser(
    args: &EvalArgs,
) -> anyhow::Result<Option<road_model::checkpoint::LoadedModel>> {
    let Some(dir) = &args.initialiser else {
        return Ok(None);
    };
    let loaded = road_model::checkpoint::load(dir, &candle_core::Device::Cpu)
        .map_err(|e| anyhow::anyhow!("--initialiser {}: {e}", dir.display()))?;
    road_serve::scene::check_initialiser(&loaded)
        .map_err(|why| anyhow::anyhow!("--initialiser {}: {why}", dir.display()))?;
    Ok(Some(loaded))
}

/// The procedural maps of `--maps` (all of them when none is named).
pub(crate) fn procedural_maps(args: &EvalArgs) -> anyhow::Result<Vec<ProceduralMap>> {
    if args.maps.is_empty() {
        return Ok(ProceduralMap::ALL.to_vec());
    }
    args.maps
        .iter()
        .map(|name| {
            crate::commands::demo::parse_map(name).map_err(|e| anyhow::anyhow!("--maps: {e}"))
        })
        .collect()
}

/// The scenes a suite evaluates.
pub(crate) struct SceneSelection {
    /// Window indices evaluated: spread evenly over the eligible ones, at most `limit`.
    pub scenes: Vec<usize>,
    /// Eligible windows of the kept locations (what `--limit 0` evaluates).
    pub eligible: usize,
}

/// Scenes of the suite: eligible windows (enough agents, and `extra`) of the top locations,
/// spread evenly up to `limit`.
pub(crate) fn select_scenes(
    ds: &Dataset,
    args: &EvalArgs,
    extra: impl Fn(usize) -> bool,
) -> SceneSelection {
    let eligible: Vec<usize> = (0..ds.len())
        .filter(|&i| ds.windows[i].agents.len() >= args.min_agents && extra(i))
        .collect();
    let mut per_location: BTreeMap<&str, usize> = BTreeMap::new();
    for &i in &eligible {
        *per_location
            .entry(
                ds.recordings[ds.windows[i].recording as usize]
                    .location
                    .as_str(),
            )
            .or_default() += 1;
    }
    let mut ranked: Vec<(&str, usize)> = per_location.into_iter().collect();
    ranked.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
    let keep: Vec<&str> = ranked
        .iter()
        .take(args.top_locations)
        .map(|r| r.0)
        .collect();
    let kept: Vec<usize> = eligible
        .into_iter()
        .filter(|&i| {
            keep.contains(
                &ds.recordings[ds.windows[i].recording as usize]
                    .location
                    .as_str(),
            )
        })
        .collect();
    let eligible = kept.len();
    if args.limit == 0 || kept.len() <= args.limit {
        return SceneSelection {
            scenes: kept,
            eligible,
        };
    }
    let scenes = (0..args.limit)
        .map(|k| kept[k * kept.len() / args.limit])
        .collect();
    SceneSelection { scenes, eligible }
}

/// Progress for logs, where the bar is hidden (stderr not a terminal): scenes done, elapsed
/// and expected seconds.
pub(crate) fn progress(bar: &indicatif::ProgressBar, model: &str, scenes: usize, started: Instant) {
    if !bar.is_hidden() {
        return;
    }
    let done = bar.position() as usize;
    let secs = started.elapsed().as_secs_f64();
    tracing::info!(
        model,
        done,
        scenes,
        elapsed_secs = secs.round(),
        remaining_secs = (secs / done.max(1) as f64 * scenes.saturating_sub(done) as f64).round(),
        "evaluating"
    );
}

/// `w` cut to its first `steps` steps.
pub(crate) fn first_steps(w: &road_data::SceneWindow, steps: usize) -> road_data::SceneWindow {
    let mut out = w.clone();
    out.steps = steps;
    out.states = (0..w.agents)
        .flat_map(|a| w.states[3 * a * w.steps..][..3 * steps].iter().copied())
        .collect();
    out.valid = (0..w.agents)
        .flat_map(|a| w.valid[a * w.steps..][..steps].iter().copied())
        .collect();
    out
}
