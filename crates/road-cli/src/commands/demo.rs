//! `road demo`: the main job on its embedded default. A procedurally built roundabout (or, with
//! `--map`, intersection or merge; no INTERACTION data: every byte redistributable) with a
//! scripted ego that does not yield and every other vehicle the model's. By default through
//! the product (`demo_zenoh`): `road serve` in this process, the ego a zenoh client on
//! loopback, the server's recording kept and animated. With `--in-process` the same closed
//! loop runs directly on an engine of choice, without server or network, and is drawn as one
//! figure (the evaluation notes use this path).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use rand::SeedableRng;
use road_model::checkpoint::LoadedModel;
use road_model::config::RunConfig;
use road_sim::closed_loop::{ClosedLoop, Controller, SceneTick, SimScene};
use road_sim::geometry::OrientedBox;
use road_sim::procedural::{ProceduralMap, ProceduralScene, STEP_SECS, procedural_turned};

use crate::commands::engine::{EngineChoice, Engines};
use crate::plot::{
    ADVERSARY, EGO, Footprint, HISTORY, PREDICTED, Ring, Stroke, figure_png, lanelet_strokes,
};

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Checkpoint folder; the default is the shipped default, RoAD-20 with agent maps, agent
    /// pairs and the constant-velocity residual at width 96 (`models/road20-wide4`,
    /// docs/results.md; embedded in the binary, so it runs without the folder too).
    #[arg(long, default_value = "models/road20-wide4")]
    pub checkpoint: PathBuf,
    /// Simulated steps (10 Hz); default 300 served (30 s: longer than the vehicles it starts
    /// with stay on the map), 60 with `--in-process`.
    #[arg(long)]
    pub steps: Option<usize>,
    /// The procedural map: `roundabout`, `intersection` or `merge`.
    #[arg(long, default_value = "roundabout", value_parser = parse_map)]
    pub map: ProceduralMap,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Run the closed loop in this process on `--engine`, without server or zenoh; draws
    /// `--out` and writes `--json` (the evaluation notes use this path).
    #[arg(long)]
    pub in_process: bool,
    /// With `--in-process`: `gpu` (WGSL kernels), `cpu` (the fast CPU engine), `candle` (the
    /// candle reference) or `auto` (default): a hardware GPU when wgpu finds one, else the fast
    /// CPU engine. Served (without `--in-process`): the server's engine, `cpu` (default, also
    /// for `auto`) or `gpu` (`road serve --engine gpu`).
    #[arg(long, value_enum)]
    pub engine: Option<EngineChoice>,
    /// With `--in-process`: drive under this planner of `configs/planners.toml` instead of the
    /// checkpoint's (e.g. `road20`, the paper's; `road20-calm-guarded`, the default before).
    #[arg(long, requires = "in_process")]
    pub planner: Option<String>,
    /// With `--in-process`: the figure (default `demo.png`): lanes grey, 1 s histories blue,
    /// the model's vehicles orange, the ego green, final footprints outlined, collisions
    /// circled red.
    #[arg(long, requires = "in_process")]
    pub out: Option<PathBuf>,
    /// With `--in-process`: also write every tick (poses, collisions, off-road agents) as JSON
    /// here.
    #[arg(long, requires = "in_process")]
    pub json: Option<PathBuf>,
    /// With `--in-process`: the whole scene (map, routes, histories) turned counter-clockwise by
    /// this many degrees: a model that reads the lanes drives it as it drives the unturned one
    /// (docs/experiments/2026-11-25-procedural-suite-rotation.md).
    #[arg(
        long,
        default_value_t = 0.0,
        requires = "in_process",
        allow_negative_numbers = true
    )]
    pub rotate_deg: f64,
    /// The scripted ego's speed as a share of its route's (0: it stops where its history
    /// ends; 0.5: it crawls), to see the model's vehicles around an ego that holds them up.
    #[arg(long, default_value_t = 1.0, requires = "in_process")]
    pub ego_speed_scale: f64,
    /// Instead of the map's scripted vehicles, this many placed on its lanes around the ego,
    /// refined by the model and redrawn by the initialiser (`--initialiser`;
    /// `CreateScene.populate`; `road_sim::populate` in process).
    /// Served, the default is 7 (`--scripted`: the map's script instead); in process the
    /// script is the default.
    #[arg(long)]
    pub populate: Option<usize>,
    /// Served: vehicles keep entering at each of the map's entry lanes at this rate a minute,
    /// up to the scene's vehicles at the start (`CreateScene.inflow`), so that a long demo keeps
    /// its traffic as vehicles leave at the map's ends; default 6 unless `--scripted`.
    #[arg(long, conflicts_with = "in_process")]
    pub inflow_per_minute: Option<f64>,
    /// The initialiser that draws the populated vehicles anew around the ego, as a served
    /// scene's are (`CreateScene.populate.initialiser`; default road20-init, the server's;
    /// `none`: the placement refined by the checkpoint only). Served: a checkpoint name. In
    /// process, with `--populate`: a checkpoint folder, or the embedded road20-init by name;
    /// the default is skipped, with a warning, where it does not fit `--checkpoint`.
    #[arg(long, conflicts_with = "scripted")]
    pub initialiser: Option<String>,
    /// Served: the map's scripted vehicles (the roundabout's six, with 1 s histories: the
    /// demo before issue 39) instead of vehicles the model places, and no inflow unless asked.
    #[arg(long, conflicts_with_all = ["in_process", "populate"])]
    pub scripted: bool,
    /// The served scene's MCAP recording (Foxglove shows `/map` and `/agents`; `road render`,
    /// `road replay`).
    #[arg(long, default_value = "demo.mcap", conflicts_with = "in_process")]
    pub mcap: PathBuf,
    /// The recording as an animated GIF (`road render`), one frame per tick.
    #[arg(long, default_value = "demo.gif", conflicts_with = "in_process")]
    pub gif: PathBuf,
    /// The served demo, once a flag of its own; now the default.
    #[arg(long, hide = true, conflicts_with = "in_process")]
    pub zenoh: bool,
}

/// One closed loop on a procedural map: its scene and every tick.
pub(crate) struct ProceduralRun {
    pub scene: ProceduralScene,
    pub ticks: Vec<SceneTick>,
    pub tick_ms: Vec<f64>,
    pub setup_secs: f64,
    /// Model evaluations over the run.
    pub nfe: u64,
}

/// `map` turned by `rotation_rad`, simulated for `steps` ticks with `run`'s model and planner
/// on `engines` (noise seeded by `seed`): the scripted ego that does not yield, at its
/// route's speed times `ego_speed_scale` (0: it stands where its history ends), every other
/// vehicle the model's. What `road demo --in-process` and `road eval --suite procedural` run.
#[allow(clippy::too_many_arguments)] // one run's map, orientation, ego, noise and length
pub(crate) fn simulate_procedural(
    engines: &Engines,
    run: &RunConfig,
    map: ProceduralMap,
    rotation_rad: f64,
    ego_speed_scale: f64,
    seed: u64,
    steps: usize,
    progress: bool,
    populate: Option<usize>,
    unrefined: bool,
    initialiser: Option<&LoadedModel>,
) -> Result<ProceduralRun> {
    let model = &run.model;
    let n = run.planner.obs_slots;
    let window_config = model.window_config();
    let mut scene = procedural_turned(map, &window_config, n, rotation_rad)?;
    let mut engine = engines.engine()?;
    if let Some(count) = populate {
        populate_scene(
            engine.as_dyn(),
            run,
            &mut scene,
            count,
            seed,
            !unrefined,
            initialiser,
        )?;
    }
    let agents = scene.window.agents;
    let mut controllers = vec![Controller::Model; agents];
    controllers[scene.ego.agent] = Controller::External;
    let mut ego = scene.ego.clone();
    ego.speed_mps *= ego_speed_scale;

    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let started = Instant::now();
    let mut sim = ClosedLoop::new(
        engine.as_dyn(),
        model,
        &run.planner,
        vec![SimScene {
            window: scene.window.clone(),
            observed_steps: n,
            controllers,
        }],
        vec![Some(&scene.map)],
        steps,
        &mut rng,
    )?;
    // As in a served scene, vehicles that drive off the map's lane ends leave it.
    sim.retire_on_exit(0, true)?;
    let setup_secs = started.elapsed().as_secs_f64();
    let mut ticks: Vec<SceneTick> = Vec::with_capacity(steps);
    let mut tick_ms: Vec<f64> = Vec::with_capacity(steps);
    let mut out = Vec::new();
    let bar = if progress {
        indicatif::ProgressBar::new(steps as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    for _ in 0..steps {
        let t0 = Instant::now();
        sim.tick(engine.as_dyn(), &mut ego, &mut out)?;
        tick_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        ticks.push(out[0].clone());
        bar.inc(1);
    }
    bar.finish_and_clear();
    let nfe = sim.nfe()?;
    drop(sim);
    Ok(ProceduralRun {
        scene,
        ticks,
        tick_ms,
        setup_secs,
        nfe,
    })
}

/// `scene`'s scripted vehicles replaced by `count` placed around its ego and refined by the
/// model on `engine` (`road_sim::populate`), then, with an `initialiser`, redrawn by it as a
/// served scene's are (`redraw_placement`); the ego becomes agent 0 and keeps the only route.
/// Placement, refinement and redraw draw from `seed`'s stream 1.
pub(crate) fn populate_scene(
    engine: &mut dyn road_rollout::StepEngine,
    run: &RunConfig,
    scene: &mut ProceduralScene,
    count: usize,
    seed: u64,
    refine: bool,
    initialiser: Option<&LoadedModel>,
) -> Result<()> {
    use road_sim::populate::{
        PlacementOptions, Refinement, footprints, keep_agents, place_vehicles, refine_histories,
        with_vehicles,
    };
    let n = run.planner.obs_slots;
    let ego_only = keep_agents(&scene.window, &[scene.ego.agent]);
    let mut rng = rand::rngs::StdRng::seed_from_u64(road_rollout::stream_seed(seed, 1));
    let placed = place_vehicles(
        &scene.map,
        &footprints(&ego_only),
        count,
        n,
        &PlacementOptions::default(),
        &mut rng,
    );
    let window = with_vehicles(&ego_only, &placed)?;
    // Only the ego keeps a scripted route: the placed vehicles have none.
    scene.routes = vec![scene.routes[scene.ego.agent].clone()];
    scene.ego.agent = 0;
    if !refine {
        scene.window = window;
        return Ok(());
    }
    let mut fixed = vec![false; window.agents];
    fixed[0] = true;
    scene.window = refine_histories(
        engine,
        &run.model,
        &run.planner.edm,
        &window,
        &fixed,
        Refinement::for_model(run.train.augmentation_ratio),
        &mut rng,
    )?;
    if let Some(init) = initialiser {
        (scene.window, _) = road_sim::populate::redraw_placement(
            &init.model,
            &init.meta.run.planner.edm,
            &scene.map,
            &window,
            &scene.window,
            &fixed,
            &mut rng,
        )?;
    }
    Ok(())
}

/// The in-process demo's initialiser (`--initialiser`): with `--populate`, a checkpoint folder
/// or the embedded one by name, road20-init unless named; `none` for the refinement alone.
/// One named that cannot draw, or does not fit the checkpoint `run`, is an error; the default
/// that does not fit is skipped with a warning, as `road serve` skips it.
fn in_process_initialiser(args: &DemoArgs, run: &RunConfig) -> Result<Option<LoadedModel>> {
    if args.populate.is_none() {
        anyhow::ensure!(
            args.initialiser.is_none(),
            "--initialiser redraws populated vehicles: with --in-process it needs --populate N"
        );
        return Ok(None);
    }
    let name = args
        .initialiser
        .as_deref()
        .unwrap_or(road_serve::config::DEFAULT_INITIALISER);
    if name == "none" {
        return Ok(None);
    }
    let folder = std::path::Path::new(name);
    let loaded = if folder.is_dir() {
        road_model::checkpoint::load(folder, &candle_core::Device::Cpu)
            .map_err(|e| anyhow::anyhow!("--initialiser {name}: {e}"))?
    } else if let Some(loaded) = road_serve::models::embedded::load(name) {
        loaded.map_err(|e| anyhow::anyhow!("--initialiser {name}: {e}"))?
    } else {
        anyhow::bail!(
            "--initialiser {name:?}: no checkpoint folder of that name and no embedded checkpoint ({}); `none` refines only",
            road_serve::config::DEFAULT_INITIALISER
        );
    };
    road_serve::scene::check_initialiser(&loaded)
        .map_err(|why| anyhow::anyhow!("--initialiser {name}: {why}"))?;
    if let Err(why) = road_serve::scene::fits(&loaded, &run.model, run.planner.obs_slots) {
        anyhow::ensure!(args.initialiser.is_none(), "--initialiser {name}: {why}");
        tracing::warn!(initialiser = name, %why, "the default initialiser is skipped: the placement is refined only");
        return Ok(None);
    }
    Ok(Some(loaded))
}

/// `--map`: a procedural map by name.
pub(crate) fn parse_map(name: &str) -> std::result::Result<ProceduralMap, String> {
    ProceduralMap::from_name(name).ok_or_else(|| {
        format!(
            "unknown procedural map {name:?}; known: {}",
            ProceduralMap::names()
        )
    })
}

/// The served demo's scene when no flag says otherwise: the roundabout populated by the model
/// around the ego, vehicles entering at 6 a minute per entry, for 30 s.
const SERVED_POPULATE: usize = 7;
const SERVED_INFLOW_PER_MINUTE: f64 = 6.0;
const SERVED_STEPS: usize = 300;
const IN_PROCESS_STEPS: usize = 60;

pub fn run(args: DemoArgs) -> Result<ExitCode> {
    let steps = args.steps.unwrap_or(if args.in_process {
        IN_PROCESS_STEPS
    } else {
        SERVED_STEPS
    });
    anyhow::ensure!(steps > 0, "--steps must be at least 1");
    if !args.in_process {
        let engine = match args.engine {
            None | Some(EngineChoice::Auto | EngineChoice::Cpu) => road_serve::ServeEngine::Cpu,
            Some(EngineChoice::Gpu) => road_serve::ServeEngine::Gpu,
            Some(EngineChoice::Candle) => anyhow::bail!(
                "--engine candle runs with --in-process only: the server serves on cpu or gpu"
            ),
        };
        let (populate, inflow_per_minute) = if args.scripted {
            (None, args.inflow_per_minute)
        } else {
            (
                Some(args.populate.unwrap_or(SERVED_POPULATE)),
                Some(args.inflow_per_minute.unwrap_or(SERVED_INFLOW_PER_MINUTE)),
            )
        };
        return crate::commands::demo_zenoh::run(
            &args.checkpoint,
            engine,
            args.map,
            steps,
            args.seed,
            &args.mcap,
            &args.gif,
            populate,
            args.initialiser.clone(),
            inflow_per_minute,
        );
    }
    let figure = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("demo.png"));
    let engine_choice = args.engine.unwrap_or(EngineChoice::Auto);
    let engines = Engines::load_or_embedded(&args.checkpoint, engine_choice)?;
    let run =
        &crate::commands::engine::with_planner(&engines.cpu.meta.run, args.planner.as_deref())?;
    anyhow::ensure!(
        args.ego_speed_scale.is_finite() && args.ego_speed_scale >= 0.0,
        "--ego-speed-scale must be a finite share of the route's speed, 0 or more, got {}",
        args.ego_speed_scale
    );
    anyhow::ensure!(
        args.rotate_deg.is_finite(),
        "--rotate-deg must be a finite angle in degrees, got {}",
        args.rotate_deg
    );
    let initialiser = in_process_initialiser(&args, run)?;
    let ProceduralRun {
        scene,
        ticks,
        tick_ms,
        setup_secs,
        nfe,
    } = simulate_procedural(
        &engines,
        run,
        args.map,
        args.rotate_deg.to_radians(),
        args.ego_speed_scale,
        args.seed,
        steps,
        true,
        args.populate,
        false,
        initialiser.as_ref(),
    )?;
    let agents = scene.window.agents;

    // What happened: each collision pair and off-road agent once, at its first tick.
    let name = |a: usize| {
        if a == scene.ego.agent {
            "the ego".to_owned()
        } else {
            format!("vehicle {a}")
        }
    };
    let mut seen_pairs = std::collections::BTreeSet::new();
    let mut seen_off = std::collections::BTreeSet::new();
    let mut events = Vec::new();
    for (t, tick) in ticks.iter().enumerate() {
        let secs = (t + 1) as f64 * STEP_SECS;
        for &(i, j) in &tick.collisions {
            if seen_pairs.insert((i, j)) {
                events.push(format!(
                    "tick {:>3} ({secs:4.1} s): collision of {} and {}",
                    t + 1,
                    name(i),
                    name(j)
                ));
            }
        }
        for &a in &tick.left {
            events.push(format!(
                "tick {:>3} ({secs:4.1} s): {} left the map",
                t + 1,
                name(a)
            ));
        }
        for &a in &tick.off_road {
            if seen_off.insert(a) {
                events.push(format!(
                    "tick {:>3} ({secs:4.1} s): {} off road",
                    t + 1,
                    name(a)
                ));
            }
        }
    }
    let mut sorted = tick_ms.clone();
    sorted.sort_by(f64::total_cmp);
    let mean_ms = tick_ms.iter().sum::<f64>() / tick_ms.len() as f64;
    out!(
        "road demo: procedural {}, {agents} vehicles (ego scripted, {} by {} on {}), {} ticks of {:.1} s",
        args.map.name(),
        agents - 1,
        run.name,
        engines.describe(),
        steps,
        STEP_SECS
    );
    out!(
        "time per tick: mean {mean_ms:.1} ms, median {:.1} ms, max {:.1} ms (first tick includes the {}-step warm-up); setup {:.0} ms; {:.1} NFE per simulated step",
        sorted[sorted.len() / 2],
        sorted[sorted.len() - 1],
        run.planner.steps_per_diffusion,
        setup_secs * 1e3,
        nfe as f64 / steps as f64
    );
    let guards = road_sim::closed_loop::guard_actions(&ticks);
    if run.planner.lane_guard.is_some() {
        out!(
            "lane guard (planner option): nudged a vehicle towards its lane {} time(s), steered one back to it {} time(s), stopped one at the road's edge {} time(s)",
            guards.nudged_towards_lane,
            guards.steered_to_lane,
            guards.stopped_at_road_edge
        );
    }
    if run.planner.collision_guard.is_some() {
        out!(
            "collision guard (planner option): braked a vehicle {} time(s), stopped one short of another {} time(s)",
            guards.braked,
            guards.stopped_short
        );
    }
    if seen_pairs.is_empty() && seen_off.is_empty() {
        out!("infractions: none (no collision, nobody off road)");
    } else {
        out!(
            "infractions: {} collision pair(s), {} vehicle(s) off road",
            seen_pairs.len(),
            seen_off.len()
        );
    }
    if !events.is_empty() {
        for e in &events {
            out!("  {e}");
        }
    }

    // The figure.
    let mut strokes = lanelet_strokes(&scene.map);
    let w = &scene.window;
    for a in 0..agents {
        let history: Vec<(f64, f64)> = (0..w.steps)
            .filter_map(|t| w.state(a, t))
            .map(|s| {
                let p = w.frame.to_metres([s[0], s[1]]);
                (p[0], p[1])
            })
            .collect();
        let start = *history.last().expect("agents are present at the last step");
        strokes.push(Stroke {
            points: std::iter::once(start)
                .chain(ticks.iter().map(|t| (t.poses[a].x_m, t.poses[a].y_m)))
                .collect(),
            color: if a == scene.ego.agent { EGO } else { PREDICTED },
            width: 2,
        });
        strokes.push(Stroke {
            points: history,
            color: HISTORY,
            width: 3,
        });
    }
    let last = ticks.last().expect("at least one tick");
    // Vehicles that left the map are not drawn where they left.
    let gone: std::collections::BTreeSet<usize> =
        ticks.iter().flat_map(|t| t.left.iter().copied()).collect();
    let footprints: Vec<Footprint> = (0..agents)
        .filter(|a| !gone.contains(a))
        .map(|a| Footprint {
            corners: OrientedBox {
                pose: last.poses[a],
                length_m: f64::from(w.length_m[a]),
                width_m: f64::from(w.width_m[a]),
            }
            .corners(),
            color: if a == scene.ego.agent { EGO } else { PREDICTED },
            fill: None,
        })
        .collect();
    let mut rings = Vec::new();
    for (t, tick) in ticks.iter().enumerate() {
        for &(i, j) in &tick.collisions {
            // Circle a pair where it first collides.
            if ticks[..t].iter().all(|e| !e.collisions.contains(&(i, j))) {
                let (p, q) = (tick.poses[i], tick.poses[j]);
                rings.push(Ring {
                    centre: (0.5 * (p.x_m + q.x_m), 0.5 * (p.y_m + q.y_m)),
                    radius_m: 4.0,
                    color: ADVERSARY,
                });
            }
        }
    }
    figure_png(
        &figure,
        &strokes,
        &footprints,
        &rings,
        900,
        (0.0, 0.0),
        60.0,
    )?;
    out!("figure: {}", figure.display());
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "scene": format!("procedural {}", args.map.name()),
            "checkpoint": args.checkpoint,
            "engine": engines.describe(),
            "step_secs": STEP_SECS,
            "ego_agent": scene.ego.agent,
            "tick_ms": tick_ms,
            "nfe": nfe,
            "ticks": ticks,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
        out!("ticks: {}", path.display());
    }
    Ok(ExitCode::SUCCESS)
}
