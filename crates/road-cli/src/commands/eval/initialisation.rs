//! `road eval --suite initialisation`: scenes populated from a map and one fixed vehicle,
//! against the recordings (issue 39). Per validation scene: the log's first vehicle stays
//! (its 1 s history), the others are removed and as many are placed on the scene's lanes
//! (within the log's vehicles' reach of the scene's centre) by the heuristic
//! (`road_sim::populate::place_vehicles`), then refined by the model from the same placement
//! (`refine_histories`) and, with `--initialiser`, drawn by a checkpoint trained with the
//! initialisation task (`initialise_histories`) from each `--initialiser-sigmas` (σ_max: from
//! noise alone; lower: around the same placement). The vehicles' speed, lane offset, heading
//! against the lane and gap to the vehicle ahead compare with the log's by Jensen–Shannon
//! distance; overlapping and off-road shares beside; for each σ also what a served scene
//! starts from (`sound_or`: a draw off the lanes or onto another agent keeps the refined
//! placement). Intervals: bootstrap over scenes; the refinement against the heuristic and
//! every initialiser row against the refinement, paired on the same scenes and placements.

use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use road_data::{AgentType, SceneWindow, Split, WindowConfig};
use road_sim::initialisation::{
    Bins, GAP_BINS, HEADING_OFFSET_BINS, InitFeatures, InitialVehicle, LANE_OFFSET_BINS,
    SPEED_BINS, js_distance,
};
use road_sim::metrics::{BOOTSTRAP_RESAMPLES, Estimate};
use road_sim::populate::{
    Initialisation, PlacementOptions, Refinement, footprints, initialise_histories, keep_agents,
    place_vehicles, refine_histories, sound_or, with_vehicles,
};
use serde::Serialize;

use super::common::{EvalArgs, SceneSelection, first_steps, load_initialiser, select_scenes};
use crate::commands::engine::{EngineChoice, Engines};
use crate::commands::load_cache;

/// One scene's vehicles by source: the log, the heuristic's placement, the model's refinement,
/// then the initialiser's draws (one per σ), in `sources`' order.
struct SceneVehicles {
    /// The dataset's window index.
    window: usize,
    by_source: Vec<Vec<InitialVehicle>>,
}

/// The source indices of the log, the heuristic placement and its refinement.
const LOG: usize = 0;
const HEURISTIC: usize = 1;
const REFINED: usize = 2;

/// A model row's JS distances minus another's, paired on the same scenes.
#[derive(Debug, Serialize)]
struct PairedRow {
    source: String,
    minus: String,
    /// Speed, lane offset, heading offset, gap ahead.
    difference: Vec<Estimate>,
}

#[derive(Debug, Serialize)]
struct Row {
    source: String,
    js_speed: Estimate,
    js_lane_offset: Estimate,
    js_heading_offset: Estimate,
    js_gap_ahead: Estimate,
    vehicles: usize,
    overlapping_share: f64,
    off_road_share: f64,
}

/// Every vehicle of `w` at step `step` (and the step before), cars and trucks present at both.
fn vehicles_at(w: &SceneWindow, step: usize) -> Vec<(usize, InitialVehicle)> {
    (0..w.agents)
        .filter(|&a| matches!(w.agent_types[a], AgentType::Car | AgentType::Truck))
        .filter_map(|a| {
            let pose = |t: usize| road_sim::window_pose(w, a, t);
            Some((
                a,
                InitialVehicle {
                    before: pose(step.checked_sub(1)?)?,
                    now: pose(step)?,
                    length_m: f64::from(w.length_m[a]),
                    width_m: f64::from(w.width_m[a]),
                },
            ))
        })
        .collect()
}

pub fn run(args: EvalArgs) -> Result<ExitCode> {
    let window_config = WindowConfig::default();
    let ds = load_cache(&args.cache, Split::Validation)?;
    let n = window_config.reference_step + 1;
    let SceneSelection { scenes, eligible } = select_scenes(&ds, &args, |_| true);
    anyhow::ensure!(
        !scenes.is_empty(),
        "no validation scene has {} agents or more",
        args.min_agents
    );
    let dir = args
        .checkpoints
        .first()
        .context("--checkpoints names no checkpoint")?;
    let choice: EngineChoice = args.engine.into();
    let engines = Engines::load_or_embedded(dir, choice)?;
    let run =
        crate::commands::engine::with_planner(&engines.cpu.meta.run, args.planner.as_deref())?;
    anyhow::ensure!(
        run.planner.obs_slots == n,
        "{} observes {} steps; the validation windows give {n}",
        run.name,
        run.planner.obs_slots
    );
    eprintln!(
        "initialisation suite: {} of {eligible} eligible scenes (top {} locations, ≥ {} agents), {} refining",
        scenes.len(),
        args.top_locations,
        args.min_agents,
        run.name
    );
    let initialiser = match load_initialiser(&args)? {
        Some(loaded) => {
            for &sigma in &args.initialiser_sigmas {
                let edm = &loaded.meta.run.planner.edm;
                anyhow::ensure!(
                    sigma > edm.sigma_min && sigma <= edm.sigma_max,
                    "--initialiser-sigmas: {sigma} is not in (σ_min, σ_max] = ({}, {}]",
                    edm.sigma_min,
                    edm.sigma_max
                );
            }
            Some(loaded)
        }
        None => None,
    };
    let mut sources: Vec<String> = vec![
        "log".into(),
        "heuristic placement".into(),
        "placement refined by the model".into(),
    ];
    if let Some(init) = &initialiser {
        for &sigma in &args.initialiser_sigmas {
            let drawn = if sigma >= init.meta.run.planner.edm.sigma_max {
                format!("drawn by {} from noise", init.meta.run.name)
            } else {
                format!(
                    "placement redrawn by {} from σ = {sigma} ({:.0} m)",
                    init.meta.run.name,
                    sigma * init.meta.run.model.position_scale_m
                )
            };
            // Then what a served scene starts from (`populate.initialiser`).
            let served = format!("{drawn}, draws off the lanes or onto another refined placement");
            sources.extend([drawn, served]);
        }
    }
    let started = Instant::now();
    let mut engine = engines.engine()?;
    let mut per_scene = Vec::with_capacity(scenes.len());
    for &i in &scenes {
        let full = ds.window(i)?;
        let map = ds.map_of(&ds.windows[i]);
        let observed = first_steps(&full, n);
        let log = vehicles_at(&observed, n - 1);
        let Some(&(ego, _)) = log.first() else {
            continue;
        };
        // Placement within the log's vehicles' reach of the scene's centre.
        let centre = observed.frame.origin_m;
        let reach_m = log
            .iter()
            .map(|(_, v)| (v.now.x_m - centre[0]).hypot(v.now.y_m - centre[1]))
            .fold(10.0, f64::max)
            + 5.0;
        let given = keep_agents(&observed, &[ego]);
        let mut rng = StdRng::seed_from_u64(road_rollout::stream_seed(args.seed, i as u64));
        let options = PlacementOptions {
            region: Some((observed.frame.origin_m, reach_m)),
            ..PlacementOptions::default()
        };
        let placed = place_vehicles(
            map,
            &footprints(&given),
            log.len() - 1,
            n,
            &options,
            &mut rng,
        );
        let placed_window = with_vehicles(&given, &placed)?;
        let mut fixed = vec![false; placed_window.agents];
        fixed[0] = true;
        let refined_window = refine_histories(
            engine.as_dyn(),
            &run.model,
            &run.planner.edm,
            &placed_window,
            &fixed,
            Refinement::for_model(run.train.augmentation_ratio),
            &mut rng,
        )?;
        let all = |w: &SceneWindow| {
            vehicles_at(w, n - 1)
                .into_iter()
                .map(|(_, v)| v)
                .collect::<Vec<_>>()
        };
        let mut by_source = vec![
            log.iter().map(|&(_, v)| v).collect(),
            all(&placed_window),
            all(&refined_window),
        ];
        if let Some(init) = &initialiser {
            for &sigma in &args.initialiser_sigmas {
                let drawn = initialise_histories(
                    &init.model,
                    &init.meta.run.planner.edm,
                    &placed_window,
                    &fixed,
                    Initialisation {
                        sigma_start: sigma,
                        steps: args.initialiser_steps,
                    },
                    &mut rng,
                )?;
                let (sound, _) = sound_or(map, &drawn, &refined_window, &fixed)?;
                by_source.push(all(&drawn));
                by_source.push(all(&sound));
            }
        }
        per_scene.push(SceneVehicles {
            window: i,
            by_source,
        });
    }
    let secs = started.elapsed().as_secs_f64();
    // Features pooled over a set of scenes (indices into `per_scene`); the first vehicle of
    // each (the fixed one) is left out of the per-vehicle features.
    let pooled = |which: &[usize], source: usize| {
        let mut f = InitFeatures::default();
        for &k in which {
            let s = &per_scene[k];
            let vehicles = &s.by_source[source];
            let mut counted = vec![true; vehicles.len()];
            counted[0] = false;
            f.add_scene(ds.map_of(&ds.windows[s.window]), vehicles, &counted);
        }
        f
    };
    let all: Vec<usize> = (0..per_scene.len()).collect();
    let features: Vec<InitFeatures> = (0..sources.len()).map(|s| pooled(&all, s)).collect();
    let js_all = |f: &InitFeatures, log: &InitFeatures| -> [f64; 4] {
        [
            js_distance(&f.speed_mps, &log.speed_mps, SPEED_BINS),
            js_distance(&f.lane_offset_m, &log.lane_offset_m, LANE_OFFSET_BINS),
            js_distance(
                &f.heading_offset_rad,
                &log.heading_offset_rad,
                HEADING_OFFSET_BINS,
            ),
            js_distance(&f.gap_ahead_m, &log.gap_ahead_m, GAP_BINS),
        ]
    };
    // Bootstrap over scenes: every source resampled on the same scenes.
    let mut rng = StdRng::seed_from_u64(args.seed);
    // [resample][source][feature]
    let mut draws: Vec<Vec<[f64; 4]>> = Vec::with_capacity(BOOTSTRAP_RESAMPLES);
    for _ in 0..BOOTSTRAP_RESAMPLES {
        let sample: Vec<usize> = (0..all.len())
            .map(|_| rng.random_range(0..all.len()))
            .collect();
        let f: Vec<InitFeatures> = (0..sources.len()).map(|s| pooled(&sample, s)).collect();
        draws.push(f.iter().map(|source| js_all(source, &f[LOG])).collect());
    }
    let estimate = |value: f64, mut xs: Vec<f64>| {
        xs.retain(|x| x.is_finite());
        xs.sort_by(f64::total_cmp);
        let at = |q: f64| {
            xs.get(((xs.len() as f64 - 1.0) * q).round() as usize)
                .copied()
        };
        Estimate {
            value,
            ci_low: at(0.025).unwrap_or(f64::NAN),
            ci_high: at(0.975).unwrap_or(f64::NAN),
        }
    };
    let mut rows = Vec::new();
    for (s, name) in sources.iter().enumerate().skip(1) {
        let point = js_all(&features[s], &features[LOG]);
        let column = |k: usize| estimate(point[k], draws.iter().map(|d| d[s][k]).collect());
        rows.push(Row {
            source: name.clone(),
            js_speed: column(0),
            js_lane_offset: column(1),
            js_heading_offset: column(2),
            js_gap_ahead: column(3),
            vehicles: features[s].vehicles,
            overlapping_share: features[s].overlapping_share(),
            off_road_share: features[s].off_road_share(),
        });
    }
    // The refinement minus the heuristic and every initialiser row minus the refinement (the
    // default before it), paired on the same resampled scenes.
    let paired: Vec<PairedRow> = (REFINED..sources.len())
        .map(|s| {
            let base = if s == REFINED { HEURISTIC } else { REFINED };
            let (point, reference) = (
                js_all(&features[s], &features[LOG]),
                js_all(&features[base], &features[LOG]),
            );
            PairedRow {
                source: sources[s].clone(),
                minus: sources[base].clone(),
                difference: (0..4)
                    .map(|k| {
                        estimate(
                            point[k] - reference[k],
                            draws.iter().map(|d| d[s][k] - d[base][k]).collect(),
                        )
                    })
                    .collect(),
            }
        })
        .collect();
    out!(
        "initialisation: {} validation scenes (of {eligible} eligible, top {} locations), the log's first vehicle fixed, the others placed anew ({} vehicles); {} refining on {}; {:.0} s",
        per_scene.len(),
        args.top_locations,
        features[0].vehicles,
        run.name,
        engines.describe(),
        secs
    );
    out!(
        "| initial states | JS speed | JS lane offset | JS heading offset | JS gap ahead | vehicles | overlapping | off road |"
    );
    out!("|---|---:|---:|---:|---:|---:|---:|---:|");
    out!(
        "| log | 0 | 0 | 0 | 0 | {} | {:.3} | {:.3} |",
        features[0].vehicles,
        features[0].overlapping_share(),
        features[0].off_road_share()
    );
    for r in &rows {
        out!(
            "| {} | {:.3} | {:.3} | {:.3} | {:.3} | {} | {:.3} | {:.3} |",
            r.source,
            r.js_speed,
            r.js_lane_offset,
            r.js_heading_offset,
            r.js_gap_ahead,
            r.vehicles,
            r.overlapping_share,
            r.off_road_share
        );
    }
    for p in &paired {
        let d = &p.difference;
        out!(
            "| {} − {} (paired) | {:.3} | {:.3} | {:.3} | {:.3} | | | |",
            p.source,
            p.minus,
            d[0],
            d[1],
            d[2],
            d[3]
        );
    }
    out!(
        "(Jensen–Shannon distance to the log's distribution, base 2, 0 = the same; bins: speed {}, lane offset {}, heading offset {}, gap {}; [95 % CI]: {BOOTSTRAP_RESAMPLES} bootstrap resamples of the scenes)",
        describe(SPEED_BINS, "m/s"),
        describe(LANE_OFFSET_BINS, "m"),
        describe(HEADING_OFFSET_BINS, "rad"),
        describe(GAP_BINS, "m")
    );
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "suite": "initialisation", "scenes": per_scene.len(), "eligible_scenes": eligible,
            "checkpoint": run.name, "log": {"vehicles": features[0].vehicles,
            "overlapping_share": features[0].overlapping_share(),
            "off_road_share": features[0].off_road_share()},
            "initialiser": initialiser.as_ref().map(|i| &i.meta.run.name),
            "initialiser_steps": args.initialiser_steps,
            "rows": rows, "paired": paired,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(ExitCode::SUCCESS)
}

fn describe(bins: Bins, unit: &str) -> String {
    format!(
        "{} × {:.3} {unit} from {}",
        bins.count,
        (bins.high - bins.low) / bins.count as f64,
        bins.low
    )
}
