//! `road eval --suite procedural`: `road demo`'s closed loop counted over seeds, maps and
//! orientations. The procedural maps are not INTERACTION's, so this measures what a user sees
//! first: do the model's vehicles stay on the road and off each other on a map they never
//! saw, whichever way it is turned?

use std::collections::BTreeSet;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Result;
use anyhow::{Context, ensure};
use road_sim::closed_loop::{GuardCounts, SceneTick, guard_actions};
use road_sim::kinematics::{
    REVERSING_MIN_SPEED_MPS, SHARP_TURN_MIN_DEG, SLIDING_MIN_ANGLE_DEG, StepCounts,
    YAW_MIN_SPEED_MPS,
};
use road_sim::metrics::{BOOTSTRAP_RESAMPLES, Estimate, bootstrap_ratio};
use serde::Serialize;

use super::common::{EvalArgs, procedural_maps, progress};
use crate::commands::demo::{ProceduralRun, simulate_procedural};
use crate::commands::engine::{EngineChoice, Engines};

/// What went wrong in one run, each vehicle or pair once.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub(crate) struct RunInfractions {
    /// Model-driven vehicles that left every lanelet at some tick.
    pub off_road: BTreeSet<usize>,
    /// Pairs of model-driven vehicles that overlapped at some tick.
    pub model_pairs: BTreeSet<(usize, usize)>,
    /// Pairs of the ego (scripted, it does not yield) and a model-driven vehicle.
    pub ego_pairs: BTreeSet<(usize, usize)>,
    /// Model-driven vehicles that drove off the map through an open lane end (retired, as in
    /// a served scene; not an off-road event).
    pub left: BTreeSet<usize>,
}

impl RunInfractions {
    pub fn of(ticks: &[SceneTick], ego: usize) -> Self {
        let mut found = Self::default();
        for tick in ticks {
            found.left.extend(tick.left.iter().copied());
            found
                .off_road
                .extend(tick.off_road.iter().filter(|&&a| a != ego));
            for &(i, j) in &tick.collisions {
                if i == ego || j == ego {
                    found.ego_pairs.insert((i, j));
                } else {
                    found.model_pairs.insert((i, j));
                }
            }
        }
        found
    }

    fn clean(&self) -> bool {
        self.off_road.is_empty() && self.model_pairs.is_empty()
    }
}

#[derive(Debug, Serialize)]
struct RunRecord {
    map: &'static str,
    rotation_deg: f64,
    seed: u64,
    model_vehicles: usize,
    infractions: RunInfractions,
}

#[derive(Debug, Serialize)]
struct MapSummary {
    model: String,
    map: &'static str,
    runs: usize,
    model_vehicles: usize,
    off_road_vehicles: usize,
    /// Model-driven vehicles that left the map through an open lane end.
    left_vehicles: usize,
    /// Share of model-driven vehicles off road, bootstrap over runs.
    off_road_rate: Estimate,
    model_collision_pairs: usize,
    ego_collision_pairs: usize,
    /// Runs with no model-driven vehicle off road and no collision between two of them.
    clean_runs: usize,
    /// Off-road vehicles per rotation, in `--rotations-deg` order.
    off_road_by_rotation: Vec<usize>,
    /// What the planner's guards did, agent-ticks summed over runs (zeros without guards).
    guards: GuardCounts,
    /// The model-driven vehicles' simulated steps, and those going backwards along their
    /// heading (`road_sim::kinematics::reversing_steps`).
    model_vehicle_steps: usize,
    reversing_steps: usize,
    /// Their steps at 2 m/s or more, and those moving over 10° off the heading
    /// (`road_sim::kinematics::sliding_steps`).
    moving_steps: usize,
    sliding_steps: usize,
    /// Their consecutive pairs of such steps, and those whose course turns over 20°
    /// (`road_sim::kinematics::sharp_turns`).
    moving_pairs: usize,
    sharp_turns: usize,
    secs: f64,
}

pub fn run(args: EvalArgs) -> Result<ExitCode> {
    ensure!(args.seeds > 0, "--seeds must be at least 1");
    ensure!(
        args.procedural_steps > 0,
        "--procedural-steps must be at least 1"
    );
    ensure!(
        args.ego_speed_scale.is_finite() && args.ego_speed_scale >= 0.0,
        "--ego-speed-scale must be a finite share of the route's speed, 0 or more, got {}",
        args.ego_speed_scale
    );
    for &r in &args.rotations_deg {
        ensure!(
            r.is_finite(),
            "--rotations-deg: {r} is not a finite angle in degrees"
        );
    }
    let maps = procedural_maps(&args)?;
    let choice: EngineChoice = args.engine.into();
    eprintln!(
        "procedural suite: maps {}, {} seeds × rotations {:?}°, {} steps, the ego at {} × its route's speed",
        maps.iter().map(|m| m.name()).collect::<Vec<_>>().join(", "),
        args.seeds,
        args.rotations_deg,
        args.procedural_steps,
        args.ego_speed_scale
    );
    let initialiser = super::common::load_initialiser(&args)?;
    let mut summaries = Vec::new();
    let mut records = Vec::new();
    for dir in &args.checkpoints {
        let engines = Engines::load_or_embedded(dir, choice)?;
        let run =
            crate::commands::engine::with_planner(&engines.cpu.meta.run, args.planner.as_deref())?;
        let total = maps.len() * args.rotations_deg.len() * args.seeds as usize;
        let bar = indicatif::ProgressBar::new(total as u64);
        let started = Instant::now();
        for &map in &maps {
            let map_started = Instant::now();
            // (off-road vehicles, model-driven vehicles) of each run, for the bootstrap.
            let mut per_run = Vec::new();
            let mut by_rotation = vec![0; args.rotations_deg.len()];
            let (mut model_pairs, mut ego_pairs, mut clean_runs, mut left) = (0, 0, 0, 0);
            let mut guards = GuardCounts::default();
            let mut steps = StepCounts::default();
            for (r, &rotation_deg) in args.rotations_deg.iter().enumerate() {
                for seed in args.seed..args.seed + args.seeds {
                    let ProceduralRun { scene, ticks, .. } = simulate_procedural(
                        &engines,
                        &run,
                        map,
                        rotation_deg.to_radians(),
                        args.ego_speed_scale,
                        seed,
                        args.procedural_steps,
                        false,
                        args.populate,
                        args.populate_unrefined,
                        initialiser.as_ref(),
                    )
                    .with_context(|| {
                        format!(
                            "{}: procedural {} turned {rotation_deg}°, seed {seed}",
                            run.name,
                            map.name()
                        )
                    })?;
                    let found = RunInfractions::of(&ticks, scene.ego.agent);
                    guards += guard_actions(&ticks);
                    let vehicles = scene.window.agents - 1;
                    steps += StepCounts::of(
                        &ticks,
                        (0..scene.window.agents).filter(|&a| a != scene.ego.agent),
                    );
                    model_pairs += found.model_pairs.len();
                    ego_pairs += found.ego_pairs.len();
                    left += found.left.len();
                    clean_runs += usize::from(found.clean());
                    by_rotation[r] += found.off_road.len();
                    per_run.push((found.off_road.len() as f64, vehicles as f64));
                    records.push(RunRecord {
                        map: map.name(),
                        rotation_deg,
                        seed,
                        model_vehicles: vehicles,
                        infractions: found,
                    });
                    bar.inc(1);
                    progress(&bar, &run.name, total, started);
                }
            }
            summaries.push(MapSummary {
                model: run.name.clone(),
                map: map.name(),
                runs: per_run.len(),
                model_vehicles: per_run.iter().map(|&(_, n)| n as usize).sum(),
                off_road_vehicles: by_rotation.iter().sum(),
                left_vehicles: left,
                off_road_rate: bootstrap_ratio(&per_run, args.seed),
                model_collision_pairs: model_pairs,
                ego_collision_pairs: ego_pairs,
                clean_runs,
                off_road_by_rotation: by_rotation,
                guards,
                model_vehicle_steps: steps.steps,
                reversing_steps: steps.reversing,
                moving_steps: steps.moving,
                sliding_steps: steps.sliding,
                moving_pairs: steps.moving_pairs,
                sharp_turns: steps.sharp_turns,
                secs: map_started.elapsed().as_secs_f64(),
            });
        }
        bar.finish_and_clear();
    }

    out!(
        "procedural maps (road demo's closed loop: the scripted ego does not yield, every other vehicle the model's): {} seeds from {} × rotations {:?}°, {} steps; engine {:?}",
        args.seeds,
        args.seed,
        args.rotations_deg,
        args.procedural_steps,
        args.engine
    );
    out!(
        "| model | map | runs | model-driven vehicles off road | off-road rate [95 % CI] | off road by rotation | left the map | collisions between model-driven vehicles | collisions with the ego | clean runs | lane guard: nudged / steered / stopped at the edge | collision guard: braked / stopped short | reversing steps | sliding steps | sharp turns |"
    );
    out!("|---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for s in &summaries {
        let by_rotation = args
            .rotations_deg
            .iter()
            .zip(&s.off_road_by_rotation)
            .map(|(r, n)| format!("{r}°: {n}"))
            .collect::<Vec<_>>()
            .join(", ");
        out!(
            "| {} | {} | {} | {} of {} | {:.3} | {by_rotation} | {} | {} | {} | {} of {} | {} / {} / {} | {} / {} | {} of {} | {} of {} | {} of {} |",
            s.model,
            s.map,
            s.runs,
            s.off_road_vehicles,
            s.model_vehicles,
            s.off_road_rate,
            s.left_vehicles,
            s.model_collision_pairs,
            s.ego_collision_pairs,
            s.clean_runs,
            s.runs,
            s.guards.nudged_towards_lane,
            s.guards.steered_to_lane,
            s.guards.stopped_at_road_edge,
            s.guards.braked,
            s.guards.stopped_short,
            s.reversing_steps,
            s.model_vehicle_steps,
            s.sliding_steps,
            s.moving_steps,
            s.sharp_turns,
            s.moving_pairs
        );
    }
    out!(
        "(interval: 95 % percentile bootstrap over runs, {BOOTSTRAP_RESAMPLES} resamples; vehicles that drive off the map through an open lane end leave it, as in a served scene, and are not off road; a clean run has no model-driven vehicle off road and no collision between two of them; guards' actions in agent-ticks over all runs; reversing steps: the model-driven vehicles' steps going backwards along their heading faster than {REVERSING_MIN_SPEED_MPS} m/s; sliding steps: their steps at ≥ {YAW_MIN_SPEED_MPS} m/s moving over {SLIDING_MIN_ANGLE_DEG}° off their heading; sharp turns: their consecutive pairs of such steps whose course turns over {SHARP_TURN_MIN_DEG}°)"
    );
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "suite": "procedural",
            "seeds": args.seeds,
            "first_seed": args.seed,
            "rotations_deg": args.rotations_deg,
            "steps": args.procedural_steps,
            "ego_speed_scale": args.ego_speed_scale,
            "results": summaries,
            "runs": records,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use road_sim::Pose;

    fn tick(collisions: Vec<(usize, usize)>, off_road: Vec<usize>) -> SceneTick {
        SceneTick {
            poses: vec![
                Pose {
                    x_m: 0.0,
                    y_m: 0.0,
                    heading_rad: 0.0,
                };
                4
            ],
            collisions,
            off_road,
            guarded: Vec::new(),
            plans: Vec::new(),
            left: Vec::new(),
            stuck: Vec::new(),
        }
    }

    #[test]
    fn infractions_count_each_vehicle_and_pair_once_and_set_the_ego_apart() {
        let ticks = [
            tick(vec![(0, 2)], vec![3]),
            tick(vec![(0, 2), (1, 3)], vec![3, 1, 0]),
            tick(vec![(1, 3)], vec![]),
        ];
        let mut ticks = ticks.to_vec();
        ticks[2].left = vec![2];
        let found = RunInfractions::of(&ticks, 0);
        assert_eq!(found.off_road, BTreeSet::from([1, 3]));
        assert_eq!(found.left, BTreeSet::from([2]));
        assert_eq!(found.model_pairs, BTreeSet::from([(1, 3)]));
        assert_eq!(found.ego_pairs, BTreeSet::from([(0, 2)]));
        assert!(!found.clean());
        // The ego's own infractions do not make a run unclean.
        let ego_only = RunInfractions::of(&[tick(vec![(0, 1)], vec![0])], 0);
        assert!(ego_only.clean());
    }
}
