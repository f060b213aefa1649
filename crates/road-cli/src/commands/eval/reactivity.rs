//! `road eval --suite reactivity` (math doc, "Evaluation"): one adversarial agent per scene
//! drives its logged path slowed to half; every other agent is the model's and must react.
//! 40 simulated steps after 10 observed, 3 samples per scene; collision rate with the
//! adversarial agent, off-road rate, time per sample and NFE per simulated step, next to the
//! non-reactive baselines (log replay, constant velocity).

use std::collections::BTreeSet;
use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use road_data::{Dataset, SceneWindow, SourceSet, Split, WindowConfig};
use road_sim::closed_loop::{
    ClosedLoop, Controller, NoExternal, SceneTick, SimScene, guard_actions, pick_adversary,
    simulate_scripted,
};

use road_sim::kinematics::{
    KinematicDivergence, Kinematics, REVERSING_MIN_SPEED_MPS, SHARP_TURN_MIN_DEG,
    SLIDING_MIN_ANGLE_DEG, StepCounts, YAW_MIN_SPEED_MPS,
};
use road_sim::metrics::{BOOTSTRAP_RESAMPLES, Estimate, bootstrap_ratio};

use super::common::{EvalArgs, SceneSelection, progress, select_scenes};
use crate::commands::engine::{EngineChoice, Engines};
use crate::plot::{
    ADVERSARY, LOGGED, PREDICTED, Ring, Stroke, figure_png, window_map_strokes,
    window_path_strokes, window_point_m,
};

/// Per-model totals over every simulated (scene, sample).
#[derive(Debug, Default, Clone, serde::Serialize)]
struct Totals {
    model: String,
    simulations: usize,
    /// Simulations in which the adversarial agent collides with anybody.
    adversary_collisions: usize,
    /// Simulations with any collision at all.
    any_collisions: usize,
    /// Agents driven by the model (or the baseline's controller), summed over simulations.
    driven_agents: usize,
    /// Of those, agents that left every lanelet at some tick (having started on one).
    off_road_agents: usize,
    /// Agent-ticks at which the collision guard braked a model-driven agent ahead of a
    /// predicted collision, and at which it stopped one short of an overlap (0 without a
    /// guard); out of `driven_agents` × simulated steps.
    guard_braked_agent_ticks: usize,
    guard_stopped_agent_ticks: usize,
    /// Agent-ticks at which the lane guard turned a model-driven agent's step back towards its
    /// lane, and at which it stopped one at the road's edge (0 without a lane guard).
    guard_steered_to_lane_agent_ticks: usize,
    /// Agent-ticks at which the lane guard nudged one towards its lane ahead of the road's edge
    /// (0 without its `anticipation`).
    guard_nudged_towards_lane_agent_ticks: usize,
    guard_stopped_at_road_edge_agent_ticks: usize,
    secs: f64,
    nfe_per_step: f64,
    expected_nfe_per_step: Option<f64>,
    /// Speed, acceleration, jerk and yaw of the driven agents that the log holds throughout.
    #[serde(skip)]
    kinematics: Kinematics,
    /// Against the logged paths of the same agents over the same steps.
    kinematic_divergence: Option<KinematicDivergence>,
    /// Per simulation: its scene and its counts.
    #[serde(skip)]
    per_simulation: Vec<(usize, SceneCounts)>,
    /// Per scene (filled in before the report; what `road compare` pairs on).
    per_scene: Vec<SceneCounts>,
    /// The rates with 95 % bootstrap intervals over scenes (filled in before the report).
    adversary_collision_rate: Option<Estimate>,
    any_collision_rate: Option<Estimate>,
    off_road_rate: Option<Estimate>,
    /// Share of the driven agents' simulated steps that go backwards along their heading
    /// (`road_sim::kinematics::reversing_steps`).
    reversing_rate: Option<Estimate>,
    /// Share of their steps at 2 m/s or more that move over 10° off their heading
    /// (`road_sim::kinematics::sliding_steps`).
    sliding_rate: Option<Estimate>,
    /// Share of their consecutive pairs of such steps whose course turns over 20°
    /// (`road_sim::kinematics::sharp_turns`).
    sharp_turn_rate: Option<Estimate>,
}

/// One scene's simulations, summed: its validation window and the counts of [`Totals`].
#[derive(Debug, Default, Clone, Copy, serde::Serialize)]
pub(crate) struct SceneCounts {
    window: usize,
    simulations: usize,
    adversary_collisions: usize,
    any_collisions: usize,
    driven_agents: usize,
    off_road_agents: usize,
    /// The driven agents' simulated steps, and those going backwards along the heading.
    driven_steps: usize,
    reversing_steps: usize,
    /// Their steps at 2 m/s or more, and those sliding sideways of the heading.
    moving_steps: usize,
    sliding_steps: usize,
    /// Their consecutive pairs of such steps, and those turning sharply.
    moving_pairs: usize,
    sharp_turns: usize,
}

/// A simulation's counts added to its scene's (the scene keeps its window).
impl std::ops::AddAssign<&SceneCounts> for SceneCounts {
    fn add_assign(&mut self, sim: &SceneCounts) {
        self.simulations += sim.simulations;
        self.adversary_collisions += sim.adversary_collisions;
        self.any_collisions += sim.any_collisions;
        self.driven_agents += sim.driven_agents;
        self.off_road_agents += sim.off_road_agents;
        self.driven_steps += sim.driven_steps;
        self.reversing_steps += sim.reversing_steps;
        self.moving_steps += sim.moving_steps;
        self.sliding_steps += sim.sliding_steps;
        self.moving_pairs += sim.moving_pairs;
        self.sharp_turns += sim.sharp_turns;
    }
}

impl Totals {
    /// `windows[k]`: the validation window of scene k.
    fn estimate(&mut self, logged: &Kinematics, windows: &[usize]) {
        let mut per_scene: Vec<SceneCounts> = windows
            .iter()
            .map(|&window| SceneCounts {
                window,
                ..SceneCounts::default()
            })
            .collect();
        for (k, sim) in &self.per_simulation {
            per_scene[*k] += sim;
        }
        per_scene.retain(|row| row.simulations > 0);
        let rate = |f: fn(&SceneCounts) -> (usize, usize)| {
            let pairs: Vec<(f64, f64)> = per_scene
                .iter()
                .map(|r| {
                    let (num, den) = f(r);
                    (num as f64, den as f64)
                })
                .collect();
            bootstrap_ratio(&pairs, 0x5eed)
        };
        self.adversary_collision_rate = Some(rate(|r| (r.adversary_collisions, r.simulations)));
        self.any_collision_rate = Some(rate(|r| (r.any_collisions, r.simulations)));
        self.off_road_rate = Some(rate(|r| (r.off_road_agents, r.driven_agents)));
        self.reversing_rate = Some(rate(|r| (r.reversing_steps, r.driven_steps)));
        self.sliding_rate = Some(rate(|r| (r.sliding_steps, r.moving_steps)));
        self.sharp_turn_rate = Some(rate(|r| (r.sharp_turns, r.moving_pairs)));
        self.per_scene = per_scene;
        self.kinematic_divergence = Some(self.kinematics.divergence_from(logged));
    }
}

/// Positions in metres, one per step.
type Path2d = Vec<[f64; 2]>;

/// Paths (metres, from the last observed step on) of the driven agents that the log holds at
/// every simulated step: the simulated ones and the logged ones, agent for agent.
fn kinematic_paths(
    w: &SceneWindow,
    ticks: &[SceneTick],
    adversary: usize,
    reference: usize,
) -> Vec<(Path2d, Path2d)> {
    let logged_at = |a: usize, t: usize| w.state(a, t).map(|s| w.frame.to_metres([s[0], s[1]]));
    (0..w.agents)
        .filter(|&a| a != adversary)
        .filter_map(|a| {
            let logged: Option<Vec<[f64; 2]>> = (reference..=reference + ticks.len())
                .map(|t| logged_at(a, t))
                .collect();
            let logged = logged?;
            let simulated = std::iter::once(logged[0])
                .chain(ticks.iter().map(|t| [t.poses[a].x_m, t.poses[a].y_m]))
                .collect();
            Some((simulated, logged))
        })
        .collect()
}

/// What one simulation did (`k`: the scene).
fn score(totals: &mut Totals, k: usize, ticks: &[SceneTick], adversary: usize, agents: usize) {
    totals.simulations += 1;
    let pairs: BTreeSet<(usize, usize)> = ticks
        .iter()
        .flat_map(|t| t.collisions.iter().copied())
        .collect();
    totals.any_collisions += usize::from(!pairs.is_empty());
    totals.adversary_collisions +=
        usize::from(pairs.iter().any(|&(i, j)| i == adversary || j == adversary));
    let off: BTreeSet<usize> = ticks
        .iter()
        .flat_map(|t| t.off_road.iter().copied())
        .filter(|&a| a != adversary)
        .collect();
    totals.driven_agents += agents - 1;
    totals.off_road_agents += off.len();
    let guards = guard_actions(ticks);
    totals.guard_braked_agent_ticks += guards.braked;
    totals.guard_stopped_agent_ticks += guards.stopped_short;
    totals.guard_steered_to_lane_agent_ticks += guards.steered_to_lane;
    totals.guard_nudged_towards_lane_agent_ticks += guards.nudged_towards_lane;
    totals.guard_stopped_at_road_edge_agent_ticks += guards.stopped_at_road_edge;
    let counts = StepCounts::of(ticks, (0..agents).filter(|&a| a != adversary));
    totals.per_simulation.push((
        k,
        SceneCounts {
            window: 0, // unused: added to the scene's row, which holds its window
            simulations: 1,
            adversary_collisions: usize::from(
                pairs.iter().any(|&(i, j)| i == adversary || j == adversary),
            ),
            any_collisions: usize::from(!pairs.is_empty()),
            driven_agents: agents - 1,
            off_road_agents: off.len(),
            driven_steps: counts.steps,
            reversing_steps: counts.reversing,
            moving_steps: counts.moving,
            sliding_steps: counts.sliding,
            moving_pairs: counts.moving_pairs,
            sharp_turns: counts.sharp_turns,
        },
    ));
}

pub fn run(args: EvalArgs) -> Result<ExitCode> {
    let samples = args.samples.unwrap_or(3).max(1);
    let observed = 10;
    let config = WindowConfig {
        window_steps: observed + args.sim_steps,
        reference_step: observed - 1,
        ..WindowConfig::default()
    };
    let reference = config.reference_step;
    let sources = SourceSet::discover(&args.data)
        .with_context(|| format!("the reactivity suite reads {}", args.data.display()))?;
    let started = Instant::now();
    let ds = Dataset::build(&sources, Split::Validation, &config).with_context(|| {
        format!(
            "cannot cut {}-step validation windows from {}",
            config.window_steps,
            args.data.display()
        )
    })?;
    tracing::info!(
        windows = ds.len(),
        secs = started.elapsed().as_secs_f32(),
        "validation windows cut"
    );
    // Eligible: enough agents, and an agent present throughout that moves (the adversary).
    let adversary_of = |i: usize| -> Option<usize> {
        ds.window(i)
            .ok()
            .and_then(|w| pick_adversary(&w, reference))
    };
    let SceneSelection { scenes, eligible } =
        select_scenes(&ds, &args, |i| adversary_of(i).is_some());
    anyhow::ensure!(
        !scenes.is_empty(),
        "no validation scene has {} agents or more and an agent that moves throughout",
        args.min_agents
    );
    let windows: Vec<SceneWindow> = scenes
        .iter()
        .map(|&i| ds.window(i))
        .collect::<Result<_, _>>()?;
    let adversaries: Vec<usize> = scenes
        .iter()
        .map(|&i| adversary_of(i).expect("selected scenes have one"))
        .collect();
    let maps: Vec<&road_data::LaneletMap> =
        scenes.iter().map(|&i| ds.map_of(&ds.windows[i])).collect();
    eprintln!(
        "reactivity suite: {} of {eligible} eligible scenes (top {} locations, ≥ {} agents at the last observed step, an agent present and moving through all {} steps: the adversary, the one with the longest path), {samples} samples each, {} simulated steps",
        windows.len(),
        args.top_locations,
        args.min_agents,
        config.window_steps,
        args.sim_steps
    );
    let controllers_with = |k: usize, others: Controller| -> Vec<Controller> {
        (0..windows[k].agents)
            .map(|a| {
                if a == adversaries[k] {
                    Controller::Adversarial
                } else {
                    others
                }
            })
            .collect()
    };
    if args.figure_scenes > 0 {
        std::fs::create_dir_all(&args.figures)
            .with_context(|| format!("cannot create {}", args.figures.display()))?;
    }

    let mut results = Vec::new();
    // The logged kinematics of the driven agents (filled once, with the log-replay baseline).
    let mut logged = Kinematics::default();
    // Non-reactive baselines: one deterministic sample each.
    for (name, others) in [
        ("log replay", Controller::Replay),
        ("constant velocity", Controller::ConstantVelocity),
    ] {
        let started = Instant::now();
        let mut totals = Totals {
            model: name.into(),
            ..Totals::default()
        };
        for (k, w) in windows.iter().enumerate() {
            let scene = SimScene {
                window: w.clone(),
                observed_steps: observed,
                controllers: controllers_with(k, others),
            };
            let ticks = simulate_scripted(&scene, Some(maps[k]), args.sim_steps)?;
            score(&mut totals, k, &ticks, adversaries[k], w.agents);
            for (simulated, logged_path) in kinematic_paths(w, &ticks, adversaries[k], reference) {
                totals.kinematics.add_path(&simulated);
                if name == "log replay" {
                    logged.add_path(&logged_path);
                }
            }
            if k < args.figure_scenes {
                draw(
                    &args.figures,
                    name,
                    k,
                    w,
                    adversaries[k],
                    &[ticks],
                    reference,
                )?;
            }
        }
        totals.secs = started.elapsed().as_secs_f64();
        results.push(totals);
    }

    let choice = EngineChoice::from(args.engine);
    let batch_scenes = args.batch_scenes.max(1);
    let mut skipped: Vec<String> = Vec::new();
    for dir in &args.checkpoints {
        let engines = Engines::load(dir, choice)
            .with_context(|| format!("cannot load checkpoint {}", dir.display()))?;
        let run =
            &crate::commands::engine::with_planner(&engines.cpu.meta.run, args.planner.as_deref())?;
        let n = run.planner.obs_slots;
        anyhow::ensure!(
            n <= observed,
            "{}: the planner observes {n} steps, the suite gives {observed}",
            dir.display()
        );
        if run.planner.kind == road_sched::PlannerKind::OneShot
            && run.planner.future_slots < args.sim_steps
        {
            // Open loop ends with the horizon: it cannot drive the whole simulation.
            eprintln!(
                "{}: a one-shot horizon of {} steps is shorter than the {} simulated steps: not run",
                run.name, run.planner.future_slots, args.sim_steps
            );
            skipped.push(format!(
                "{} (one-shot horizon {} < {} simulated steps)",
                run.name, run.planner.future_slots, args.sim_steps
            ));
            continue;
        }
        let mut totals = Totals {
            model: run.name.clone(),
            expected_nfe_per_step: Some(run.planner.expected_nfe_per_step(args.sim_steps as u64)),
            ..Totals::default()
        };
        let bar = indicatif::ProgressBar::new(windows.len() as u64);
        bar.set_message(run.name.clone());
        let mut nfe_sum = 0u64;
        let mut batches = 0u64;
        let started = Instant::now();
        let indices: Vec<usize> = (0..windows.len()).collect();
        for chunk in indices.chunks(batch_scenes) {
            let mut sims = Vec::with_capacity(chunk.len() * samples);
            let mut sim_maps = Vec::with_capacity(chunk.len() * samples);
            for &k in chunk {
                for _ in 0..samples {
                    sims.push(SimScene {
                        window: windows[k].clone(),
                        observed_steps: observed,
                        controllers: controllers_with(k, Controller::Model),
                    });
                    sim_maps.push(Some(maps[k]));
                }
            }
            // Each sample's noise stream is named by its scene in the dataset and its index, so
            // a scene samples the same futures whatever the chunking (`--batch-scenes`).
            let seeds: Vec<u64> = chunk
                .iter()
                .flat_map(|&k| {
                    let scene_stream = road_rollout::stream_seed(args.seed, scenes[k] as u64);
                    (0..samples).map(move |s| road_rollout::stream_seed(scene_stream, s as u64))
                })
                .collect();
            let mut engine = engines.engine()?;
            let mut sim = ClosedLoop::with_seeds(
                engine.as_dyn(),
                &run.model,
                &run.planner,
                sims,
                sim_maps,
                args.sim_steps,
                &seeds,
            )?;
            let mut per_sim: Vec<Vec<SceneTick>> =
                vec![Vec::with_capacity(args.sim_steps); chunk.len() * samples];
            let mut out = Vec::new();
            for _ in 0..args.sim_steps {
                sim.tick(engine.as_dyn(), &mut NoExternal, &mut out)?;
                for (i, t) in out.drain(..).enumerate() {
                    per_sim[i].push(t);
                }
            }
            nfe_sum += sim.nfe()?;
            batches += 1;
            for (j, &k) in chunk.iter().enumerate() {
                let ticks = &per_sim[j * samples..(j + 1) * samples];
                for t in ticks {
                    score(&mut totals, k, t, adversaries[k], windows[k].agents);
                    for (simulated, _) in kinematic_paths(&windows[k], t, adversaries[k], reference)
                    {
                        totals.kinematics.add_path(&simulated);
                    }
                }
                if k < args.figure_scenes {
                    draw(
                        &args.figures,
                        &run.name,
                        k,
                        &windows[k],
                        adversaries[k],
                        ticks,
                        reference,
                    )?;
                }
            }
            bar.inc(chunk.len() as u64);
            progress(&bar, &run.name, windows.len(), started);
        }
        bar.finish_and_clear();
        totals.secs = started.elapsed().as_secs_f64();
        totals.nfe_per_step = nfe_sum as f64 / batches.max(1) as f64 / args.sim_steps as f64;
        results.push(totals);
    }

    out!(
        "reactivity, INTERACTION validation: {} scenes × {samples} samples (baselines: 1), {} simulated steps after {observed} observed; engine {:?}",
        windows.len(),
        args.sim_steps,
        args.engine
    );
    out!(
        "| model | collision rate (adversary) [95 % CI] | any collision [95 % CI] | off-road rate [95 % CI] | JS speed | JS accel. | JS jerk | JS yaw rate | JS yaw accel. | reversing steps [95 % CI] | sliding steps [95 % CI] | sharp turns [95 % CI] | time per sample (s) | NFE per simulated step (expected) |"
    );
    out!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &mut results {
        r.estimate(&logged, &scenes);
        let sims = r.simulations.max(1) as f64;
        let nfe = match r.expected_nfe_per_step {
            Some(e) => format!("{:.1} ({e:.1})", r.nfe_per_step),
            None => "0 (scripted)".into(),
        };
        let show = |e: Option<Estimate>| e.map_or_else(String::new, |e| format!("{e:.3}"));
        let js = r.kinematic_divergence.expect("estimated above");
        out!(
            "| {} | {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {} | {} | {} | {:.3} | {nfe} |",
            r.model,
            show(r.adversary_collision_rate),
            show(r.any_collision_rate),
            show(r.off_road_rate),
            js.speed,
            js.acceleration,
            js.jerk,
            js.yaw_rate,
            js.yaw_acceleration,
            show(r.reversing_rate),
            show(r.sliding_rate),
            show(r.sharp_turn_rate),
            r.secs / sims,
        );
    }
    out!(
        "(intervals: 95 % percentile bootstrap over scenes, {BOOTSTRAP_RESAMPLES} resamples; JS: Jensen–Shannon divergence in bits of the driven agents' speed, acceleration, jerk, yaw rate and yaw acceleration histograms from the logged ones, agents the log holds throughout; yaw from the course of motion at ≥ 2 m/s; reversing steps: share of the driven agents' simulated steps going backwards along their heading faster than {REVERSING_MIN_SPEED_MPS} m/s; sliding steps: share of their steps at ≥ {YAW_MIN_SPEED_MPS} m/s moving over {SLIDING_MIN_ANGLE_DEG}° off their heading; sharp turns: share of their consecutive pairs of such steps whose course turns over {SHARP_TURN_MIN_DEG}°)"
    );
    for s in &skipped {
        out!("not run: {s}");
    }
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "suite": "reactivity",
            "not_run": skipped,
            "scenes": windows.len(),
            "eligible_scenes": eligible,
            "samples": samples,
            "sim_steps": args.sim_steps,
            "results": results,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(ExitCode::SUCCESS)
}

/// Paper style: map, logged trajectories grey, simulated agents orange (every sample), the
/// adversarial agent red, collisions circled.
fn draw(
    dir: &Path,
    model: &str,
    k: usize,
    w: &SceneWindow,
    adversary: usize,
    samples: &[Vec<SceneTick>],
    reference: usize,
) -> Result<()> {
    let mut strokes = window_map_strokes(w);
    strokes.extend(window_path_strokes(w, 0..w.steps, LOGGED, 2));
    let mut rings = Vec::new();
    for ticks in samples {
        for a in 0..w.agents {
            let start = w.state(a, reference).map(|s| window_point_m(w, s));
            strokes.push(Stroke {
                points: start
                    .into_iter()
                    .chain(ticks.iter().map(|t| (t.poses[a].x_m, t.poses[a].y_m)))
                    .collect(),
                color: if a == adversary { ADVERSARY } else { PREDICTED },
                width: if a == adversary { 3 } else { 1 },
            });
        }
        let mut seen = BTreeSet::new();
        for t in ticks {
            for &(i, j) in &t.collisions {
                if seen.insert((i, j)) {
                    rings.push(Ring {
                        centre: (
                            0.5 * (t.poses[i].x_m + t.poses[j].x_m),
                            0.5 * (t.poses[i].y_m + t.poses[j].y_m),
                        ),
                        radius_m: 3.0,
                        color: ADVERSARY,
                    });
                }
            }
        }
    }
    let file = format!(
        "reactivity-{}-{k:02}.png",
        model.replace(|c: char| !c.is_ascii_alphanumeric(), "-")
    );
    figure_png(
        &dir.join(file),
        &strokes,
        &[],
        &rings,
        700,
        (w.frame.origin_m[0], w.frame.origin_m[1]),
        45.0,
    )
}
