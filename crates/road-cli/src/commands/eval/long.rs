//! `road eval --suite long`: sessions of `--minutes` on the procedural maps and INTERACTION
//! locations (`--maps`), every vehicle the model's, vehicles retired where they drive off the
//! map and entering at its entry lanes (`--inflow-per-minute` each, while the scene holds fewer
//! than it started with: the start's count is the target): does traffic last? Counted per
//! vehicle-minute (`road_sim::session`): off-road events, collisions, stops with free road
//! ahead, ring laps, and the vehicle count against its start (issue 39's "long sessions stay
//! sane").
//!
//! An INTERACTION location's session starts from one of its validation scenes (the seed's own:
//! [`scene_of_seed`]), its vehicles' logged second of history, on the
//! crop of the location's map that the scene's window holds (the lanes the model sees): the
//! crop's open lane ends are where vehicles leave and enter.

use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result, ensure};
use road_data::{AgentType, LaneletMap, SceneWindow, Split};
use road_sim::closed_loop::{ClosedLoop, Controller, NoExternal, SceneMap, SimScene};
use road_sim::metrics::{Estimate, bootstrap_ratio};
use road_sim::populate::Inflow;
use road_sim::procedural::{ProceduralMap, procedural};
use road_sim::session::{LONG_STOP_SECS, STOP_LENGTH_EDGES_TICKS, SessionStats};
use serde::Serialize;

use super::common::{EvalArgs, first_steps};
use crate::commands::demo::populate_scene;
use crate::commands::engine::{EngineChoice, Engines};

/// Agents a session's scene may hold (the server's limit).
const SESSION_AGENTS: usize = 32;
/// The vehicle count is judged against its start from this minute on (the first fills up).
const SETTLED_AFTER_SECS: usize = 60;
/// Which of `STOP_LENGTH_EDGES_TICKS` the per-100-vehicle-minutes rate counts: 5 s.
const AT_LEAST_5_S: usize = 1;
const _: () = assert!(STOP_LENGTH_EDGES_TICKS[AT_LEAST_5_S] == 50);

#[derive(Debug, Serialize)]
struct SessionRecord {
    map: String,
    seed: u64,
    /// Vehicles at the start: the count the session should keep.
    target: usize,
    stats: SessionStats,
    secs: f64,
}

#[derive(Debug, Serialize)]
struct MapSummary {
    model: String,
    map: String,
    sessions: usize,
    vehicle_minutes: f64,
    off_road_per_vehicle_minute: Estimate,
    collisions_per_vehicle_minute: Estimate,
    /// Stops of `LONG_STOP_SECS` or more with free road ahead or in a gridlock, and of those
    /// in a gridlock (`SessionStats`).
    long_free_stops: u64,
    long_gridlock_stops: u64,
    longest_free_stop_secs: f64,
    /// Such stops by length, at least each of `STOP_LENGTH_EDGES_TICKS` (3, 5, 7, 10 s), and of
    /// them those in a gridlock; the stops of 5 s or more per 100 vehicle-minutes: a count
    /// many times the 10 s one's, so that two builds' difference stands out of the sessions'
    /// chance (`SessionStats::free_stops_at_least`).
    free_stops_at_least: [u64; 4],
    gridlock_stops_at_least: [u64; 4],
    stops_5s_per_100_vehicle_minutes: Estimate,
    /// Stands of `LONG_STOP_SECS` or more whatever was ahead (queues behind a jam too), the
    /// longest, and the share of vehicle time spent in them, percent (`SessionStats`).
    long_stands: u64,
    longest_stand_secs: f64,
    long_stand_percent: Estimate,
    ring_laps: u64,
    /// Of the ticks vehicles moved, the share driven forwards against the lanes under them
    /// (`SessionStats::wrong_way_ticks`), percent.
    wrong_way_percent: Estimate,
    /// Ticks stood with free road ahead, by what held the vehicle: the collision guard, the
    /// lane guard at the road's edge, neither (`SessionStats`).
    free_stop_ticks_collision_guard: u64,
    free_stop_ticks_lane_guard: u64,
    free_stop_ticks_model: u64,
    entered: u64,
    left: u64,
    /// Of those that left, vehicles the stuck removal took out (`SessionStats::removed_stuck`).
    removed_stuck: u64,
    /// Over the 10 s samples after the first minute: fewest and most vehicles as a share of
    /// the start, and the share of samples within ±30 % of it.
    fewest_share: f64,
    most_share: f64,
    within_30_percent: f64,
}

pub fn run(args: EvalArgs) -> Result<ExitCode> {
    ensure!(args.seeds > 0, "--seeds must be at least 1");
    ensure!(
        args.minutes.is_finite() && args.minutes > 0.0,
        "--minutes must be positive, got {}",
        args.minutes
    );
    ensure!(
        args.inflow_per_minute.is_finite() && args.inflow_per_minute >= 0.0,
        "--inflow-per-minute must be 0 or more, got {}",
        args.inflow_per_minute
    );
    let maps = long_maps(&args)?;
    let dataset = if maps.iter().any(|m| matches!(m, LongMap::Interaction(_))) {
        Some(crate::commands::load_cache(&args.cache, Split::Validation)?)
    } else {
        None
    };
    if let Some(ds) = &dataset {
        for map in &maps {
            if let LongMap::Interaction(location) = map {
                ensure!(
                    !location_scenes(ds, location, args.min_agents).is_empty(),
                    "--maps: {location:?} is no procedural map ({}) and no validation scene of such a location has {} vehicles or more; locations: {}",
                    ProceduralMap::names(),
                    args.min_agents,
                    locations(ds).join(", ")
                );
            }
        }
    }
    let ticks = (args.minutes * 600.0).round() as usize;
    let choice: EngineChoice = args.engine.into();
    eprintln!(
        "long suite: maps {}, {} seeds, {} min each, inflow {} a minute per entry",
        maps.iter()
            .map(LongMap::name)
            .collect::<Vec<_>>()
            .join(", "),
        args.seeds,
        args.minutes,
        args.inflow_per_minute
    );
    let initialiser = super::common::load_initialiser(&args)?;
    let mut summaries = Vec::new();
    let mut totals = Vec::new();
    let mut records = Vec::new();
    for dir in &args.checkpoints {
        let model_from = records.len();
        let engines = Engines::load_or_embedded(dir, choice)?;
        let run =
            crate::commands::engine::with_planner(&engines.cpu.meta.run, args.planner.as_deref())?;
        for map in &maps {
            let mut sessions = Vec::new();
            for seed in args.seed..args.seed + args.seeds {
                let started = Instant::now();
                let start = session_start(
                    &engines,
                    &run,
                    map,
                    dataset.as_ref(),
                    seed,
                    &args,
                    initialiser.as_ref(),
                )
                .with_context(|| format!("{}: {} seed {seed}", run.name, map.name()))?;
                let stats = session(&engines, &run, map.name(), start, seed, ticks, &args)
                    .with_context(|| format!("{}: {} seed {seed}", run.name, map.name()))?;
                let target = stats.0;
                tracing::info!(
                    model = run.name,
                    map = map.name(),
                    seed,
                    secs = started.elapsed().as_secs_f64().round(),
                    "session done"
                );
                sessions.push(SessionRecord {
                    map: map.name().to_owned(),
                    seed,
                    target,
                    stats: stats.1,
                    secs: started.elapsed().as_secs_f64(),
                });
            }
            summaries.push(summarise(&run.name, map.name(), &sessions, args.seed));
            records.extend(sessions);
        }
        totals.push(summarise(
            &run.name,
            "all maps",
            &records[model_from..],
            args.seed,
        ));
    }
    out!(
        "long sessions: {} seeds from {} × {} min, every vehicle the model's, inflow {} a minute per entry, vehicles retired at the map's ends; engine {:?}",
        args.seeds,
        args.seed,
        args.minutes,
        args.inflow_per_minute,
        args.engine
    );
    out!(
        "| model | map | sessions | vehicle-minutes | off-road events per vehicle-minute [95 % CI] | collisions per vehicle-minute [95 % CI] | stops ≥ {LONG_STOP_SECS} s with free road (in a gridlock) | longest (s) | stands ≥ {LONG_STOP_SECS} s, queues too (longest s) | time in them (% of vehicle time) [95 % CI] | held by: collision guard / lane guard / model (ticks) | ring laps | wrong way (% of moving time) [95 % CI] | entered / left (of them removed stuck) | vehicles after 1 min, fewest / most (× start) | samples within ±30 % |"
    );
    out!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for s in &summaries {
        out!(
            "| {} | {} | {} | {:.0} | {:.4} | {:.4} | {} ({}) | {:.0} | {} ({:.0}) | {:.2} | {} / {} / {} | {} | {:.2} | {} / {} ({}) | {:.2} / {:.2} | {:.2} |",
            s.model,
            s.map,
            s.sessions,
            s.vehicle_minutes,
            s.off_road_per_vehicle_minute,
            s.collisions_per_vehicle_minute,
            s.long_free_stops,
            s.long_gridlock_stops,
            s.longest_free_stop_secs,
            s.long_stands,
            s.longest_stand_secs,
            s.long_stand_percent,
            s.free_stop_ticks_collision_guard,
            s.free_stop_ticks_lane_guard,
            s.free_stop_ticks_model,
            s.ring_laps,
            s.wrong_way_percent,
            s.entered,
            s.left,
            s.removed_stuck,
            s.fewest_share,
            s.most_share,
            s.within_30_percent
        );
    }
    out!(
        "(intervals: 95 % percentile bootstrap over sessions; off-road event: a present vehicle leaving every lanelet, leaving at a map's end is not one; collision: a pair of vehicles starting to overlap; a stop with free road: slower than 0.3 m/s over the last tick or on average over the last 2 s, no vehicle's box in its path (its width and 0.3 m each side, 15 m ahead of its centre) and no vehicle's centre within 15 m ahead and 3 m of its axis (one coming towards it, more than 135° off its heading, only with its box in the path), or in a gridlock (on a cycle of standing vehicles, each in the path of the one before); a stand: standing so, whatever is ahead; a ring lap: a vehicle turning over 1¼ turns in total; wrong way: a tick moving forwards (≥ 1 m/s) whose course runs more than 135° off a lanelet under the vehicle and within 90° of none)"
    );
    let edges_secs: Vec<String> = STOP_LENGTH_EDGES_TICKS
        .iter()
        .map(|&t| format!("{}", f64::from(t) / 10.0))
        .collect();
    out!(
        "| model | map | stops with free road (in a gridlock) ≥ {} s | ≥ 5 s per 100 vehicle-minutes [95 % CI] |",
        edges_secs.join(" / ")
    );
    out!("|---|---|---|---:|");
    for s in summaries.iter().chain(&totals) {
        let by_length: Vec<String> = s
            .free_stops_at_least
            .iter()
            .zip(&s.gridlock_stops_at_least)
            .map(|(all, gridlock)| format!("{all} ({gridlock})"))
            .collect();
        out!(
            "| {} | {} | {} | {:.2} |",
            s.model,
            s.map,
            by_length.join(" / "),
            s.stops_5s_per_100_vehicle_minutes
        );
    }
    out!(
        "(the stops of the first table by length: the releases act after 1 s in a gridlock and 3 s on free road; a stop of 10 s is rare, one a build's rule can move by chance alone, the shorter ones many times as many)"
    );
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "suite": "long", "minutes": args.minutes,
            "inflow_per_minute": args.inflow_per_minute, "seeds": args.seeds,
            "summaries": summaries, "totals": totals, "sessions": records,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(ExitCode::SUCCESS)
}

/// A long session's map: a procedural one, or an INTERACTION location.
enum LongMap {
    Procedural(ProceduralMap),
    Interaction(String),
}

impl LongMap {
    fn name(&self) -> &str {
        match self {
            LongMap::Procedural(map) => map.name(),
            LongMap::Interaction(location) => location,
        }
    }
}

/// The maps of `--maps`: procedural names and INTERACTION locations (checked against the
/// validation cache once it is loaded); all procedural maps when none is named.
fn long_maps(args: &EvalArgs) -> Result<Vec<LongMap>> {
    if args.maps.is_empty() {
        return Ok(ProceduralMap::ALL.map(LongMap::Procedural).into());
    }
    Ok(args
        .maps
        .iter()
        .map(|name| match ProceduralMap::from_name(name) {
            Some(map) => LongMap::Procedural(map),
            None => LongMap::Interaction(name.clone()),
        })
        .collect())
}

/// The validation cache's locations, sorted.
fn locations(ds: &road_data::Dataset) -> Vec<String> {
    let mut names: Vec<String> = ds.recordings.iter().map(|r| r.location.clone()).collect();
    names.sort();
    names.dedup();
    names
}

/// The validation windows of `location` with at least `min_agents` agents, in order.
fn location_scenes(ds: &road_data::Dataset, location: &str, min_agents: usize) -> Vec<usize> {
    (0..ds.len())
        .filter(|&i| {
            let w = &ds.windows[i];
            ds.recordings[w.recording as usize].location == location && w.agents.len() >= min_agents
        })
        .collect()
}

/// Which of a location's `scenes` eligible scenes seed `seed` starts from: the seed's base-2
/// radical inverse (0, ½, ¼, ¾, ⅛, …) of the way along them, so that the seeds from 0 on spread
/// over the location however many are run, and a seed starts from the same scene in every run
/// (`--seed 7 --seeds 1` replays seed 7 of `--seeds 10`, to trace it).
fn scene_of_seed(seed: u64, scenes: usize) -> usize {
    let fraction = seed.reverse_bits() as f64 / 2f64.powi(64);
    ((fraction * scenes as f64) as usize).min(scenes.saturating_sub(1))
}

/// Where a session starts: the scene's window (its observed steps) and the map it runs on.
struct SessionStart {
    window: SceneWindow,
    map: LaneletMap,
}

/// The start of `map`'s session for `seed`: a procedural map's scene (its script's vehicles, or
/// `--populate` placed ones); for an INTERACTION location, one of its validation scenes (the
/// seed's own, [`scene_of_seed`]), its cars and trucks with the logged second of
/// history, on the crop of the location's map that the scene's window holds.
fn session_start(
    engines: &Engines,
    run: &road_model::config::RunConfig,
    map: &LongMap,
    dataset: Option<&road_data::Dataset>,
    seed: u64,
    args: &EvalArgs,
    initialiser: Option<&road_model::checkpoint::LoadedModel>,
) -> Result<SessionStart> {
    let n = run.planner.obs_slots;
    match map {
        LongMap::Procedural(kind) => {
            let mut scene = procedural(*kind, &run.model.window_config(), n)?;
            if let Some(count) = args.populate {
                let mut engine = engines.engine()?;
                populate_scene(
                    engine.as_dyn(),
                    run,
                    &mut scene,
                    count,
                    seed,
                    !args.populate_unrefined,
                    initialiser,
                )?;
            }
            Ok(SessionStart {
                window: scene.window,
                map: scene.map,
            })
        }
        LongMap::Interaction(location) => {
            ensure!(
                args.populate.is_none(),
                "--populate places vehicles on the procedural maps only; {location} starts from its recordings"
            );
            let ds = dataset.context("the validation cache is loaded for INTERACTION maps")?;
            let scenes = location_scenes(ds, location, args.min_agents);
            let index = scenes[scene_of_seed(seed, scenes.len())];
            let full = ds.window(index)?;
            ensure!(
                full.steps >= n,
                "{location}: window {index} has {} steps; {} observes {n}",
                full.steps,
                run.name
            );
            let observed = first_steps(&full, n);
            let vehicles: Vec<usize> = (0..observed.agents)
                .filter(|&a| matches!(observed.agent_types[a], AgentType::Car | AgentType::Truck))
                .filter(|&a| (0..n).all(|t| observed.valid[a * n + t]))
                .collect();
            ensure!(
                !vehicles.is_empty(),
                "{location}: window {index} has no vehicle observed over its first {n} steps"
            );
            let window = road_sim::populate::keep_agents(&observed, &vehicles);
            let ids: std::collections::BTreeSet<i64> =
                window.polyline_lanelet_ids.iter().copied().collect();
            let map = ds.map_of(&ds.windows[index]).crop(|l| ids.contains(&l.id));
            Ok(SessionStart { window, map })
        }
    }
}

/// One session from `start`, every vehicle the model's, for `ticks`. Returns the vehicles at
/// the start and the counts.
fn session(
    engines: &Engines,
    run: &road_model::config::RunConfig,
    map_name: &str,
    start: SessionStart,
    seed: u64,
    ticks: usize,
    args: &EvalArgs,
) -> Result<(usize, SessionStats)> {
    let model = &run.model;
    let n = run.planner.obs_slots;
    let SessionStart { window, map } = start;
    let mut engine = engines.engine()?;
    let agents = window.agents;
    let size_m: Vec<[f32; 2]> = (0..agents)
        .map(|a| [window.length_m[a], window.width_m[a]])
        .collect();
    ensure!(
        agents <= SESSION_AGENTS,
        "{agents} vehicles; a session holds at most {SESSION_AGENTS}"
    );
    let mut sim = ClosedLoop::pool(engine.as_dyn(), model, &run.planner, 1, SESSION_AGENTS)?;
    let id = sim.add_scene(
        engine.as_dyn(),
        SimScene {
            window,
            observed_steps: n,
            controllers: vec![Controller::Model; agents],
        },
        &run.planner,
        Some(SceneMap::Borrowed(&map)),
        ticks,
        road_rollout::stream_seed(seed, 0),
    )?;
    sim.retire_on_exit(id, true)?;
    // The start's count is the target: arrivals wait while the scene holds as many.
    let mut inflow = (args.inflow_per_minute > 0.0).then(|| {
        Inflow::new(
            &map,
            args.inflow_per_minute,
            road_rollout::stream_seed(seed, 2),
        )
        .with_max_vehicles(agents)
    });
    let size_f64 = |[length_m, width_m]: [f32; 2]| [f64::from(length_m), f64::from(width_m)];
    let mut stats = SessionStats::new(
        &size_m.iter().copied().map(size_f64).collect::<Vec<_>>(),
        &[],
    );
    let mut trace = args
        .trace
        .as_deref()
        .map(|dir| -> Result<_> {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("--trace: cannot create {}", dir.display()))?;
            // The session's map and its vehicles' sizes beside the ticks, so that a trace can be
            // drawn on its own.
            let map_path = dir.join(format!("{map_name}-seed{seed}.map.json"));
            let sidecar = serde_json::json!({ "map": &map, "size_m": &size_m });
            std::fs::write(&map_path, sidecar.to_string())
                .with_context(|| format!("--trace: cannot write {}", map_path.display()))?;
            let path = dir.join(format!("{map_name}-seed{seed}.jsonl"));
            let file = std::fs::File::create(&path)
                .with_context(|| format!("--trace: cannot create {}", path.display()))?;
            Ok((path, std::io::BufWriter::new(file)))
        })
        .transpose()?;
    let mut out = Vec::new();
    for tick in 0..ticks {
        let mut entered = Vec::new();
        let mut entered_size_m = Vec::new();
        if let Some(inflow) = inflow.as_mut() {
            let footprints = sim.footprints(id)?;
            for vehicle in inflow.arrivals(&footprints, n) {
                // A full scene drops the arrival, as a served one does.
                if let Ok(agent) = sim.add_agent(engine.as_dyn(), id, &vehicle) {
                    stats.entered(agent, [vehicle.length_m, vehicle.width_m]);
                    entered.push(agent);
                    entered_size_m.push([vehicle.length_m, vehicle.width_m]);
                }
            }
        }
        sim.tick(engine.as_dyn(), &mut NoExternal, &mut out)?;
        stats.tick(&out[0], Some(&map));
        if let Some((path, writer)) = trace.as_mut() {
            use std::io::Write;
            let line = serde_json::json!({
                "tick": tick, "entered": entered, "entered_size_m": entered_size_m, "scene": &out[0]
            });
            writeln!(writer, "{line}")
                .with_context(|| format!("--trace: cannot write {}", path.display()))?;
        }
    }
    if let Some((path, mut writer)) = trace {
        use std::io::Write;
        writer
            .flush()
            .with_context(|| format!("--trace: cannot write {}", path.display()))?;
    }
    stats.finish();
    Ok((agents, stats))
}

fn summarise(model: &str, map: &str, sessions: &[SessionRecord], seed: u64) -> MapSummary {
    let per = |count: fn(&SessionStats) -> u64| -> Vec<(f64, f64)> {
        sessions
            .iter()
            .map(|s| (count(&s.stats) as f64, s.stats.vehicle_minutes()))
            .collect()
    };
    let settled_from = SETTLED_AFTER_SECS / 10;
    let shares: Vec<f64> = sessions
        .iter()
        .flat_map(|s| {
            s.stats
                .vehicles_every_10s
                .iter()
                .skip(settled_from)
                .map(move |&v| v as f64 / s.target.max(1) as f64)
        })
        .collect();
    let within = shares.iter().filter(|&&x| (0.7..=1.3).contains(&x)).count();
    MapSummary {
        model: model.to_owned(),
        map: map.to_owned(),
        sessions: sessions.len(),
        vehicle_minutes: sessions.iter().map(|s| s.stats.vehicle_minutes()).sum(),
        off_road_per_vehicle_minute: bootstrap_ratio(&per(|s| s.off_road_events), seed),
        collisions_per_vehicle_minute: bootstrap_ratio(&per(|s| s.collision_events), seed),
        long_free_stops: sessions.iter().map(|s| s.stats.long_free_stops).sum(),
        long_gridlock_stops: sessions.iter().map(|s| s.stats.long_gridlock_stops).sum(),
        longest_free_stop_secs: sessions
            .iter()
            .map(|s| s.stats.longest_free_stop_secs)
            .fold(0.0, f64::max),
        free_stops_at_least: sum_by_length(sessions, |s| s.free_stops_at_least),
        gridlock_stops_at_least: sum_by_length(sessions, |s| s.gridlock_stops_at_least),
        stops_5s_per_100_vehicle_minutes: bootstrap_ratio(
            &sessions
                .iter()
                .map(|s| {
                    let at_least_5s = s.stats.free_stops_at_least[AT_LEAST_5_S];
                    (100.0 * at_least_5s as f64, s.stats.vehicle_minutes())
                })
                .collect::<Vec<_>>(),
            seed,
        ),
        long_stands: sessions.iter().map(|s| s.stats.long_stands).sum(),
        longest_stand_secs: sessions
            .iter()
            .map(|s| s.stats.longest_stand_secs)
            .fold(0.0, f64::max),
        long_stand_percent: percent_over_sessions(sessions, seed, |s| {
            (s.long_stand_ticks, s.vehicle_ticks)
        }),
        ring_laps: sessions.iter().map(|s| s.stats.ring_laps).sum(),
        wrong_way_percent: percent_over_sessions(sessions, seed, |s| {
            (s.wrong_way_ticks, s.moving_ticks)
        }),
        free_stop_ticks_collision_guard: sessions
            .iter()
            .map(|s| s.stats.free_stop_ticks_collision_guard)
            .sum(),
        free_stop_ticks_lane_guard: sessions
            .iter()
            .map(|s| s.stats.free_stop_ticks_lane_guard)
            .sum(),
        free_stop_ticks_model: sessions.iter().map(|s| s.stats.free_stop_ticks_model).sum(),
        entered: sessions.iter().map(|s| s.stats.entered).sum(),
        left: sessions.iter().map(|s| s.stats.left).sum(),
        removed_stuck: sessions.iter().map(|s| s.stats.removed_stuck).sum(),
        // No sample after the first minute (a shorter session): nothing to judge.
        fewest_share: if shares.is_empty() {
            f64::NAN
        } else {
            shares.iter().copied().fold(f64::INFINITY, f64::min)
        },
        most_share: if shares.is_empty() {
            f64::NAN
        } else {
            shares.iter().copied().fold(0.0, f64::max)
        },
        within_30_percent: if shares.is_empty() {
            f64::NAN
        } else {
            within as f64 / shares.len() as f64
        },
    }
}

/// `count`'s four lengths summed over the sessions.
fn sum_by_length(sessions: &[SessionRecord], count: fn(&SessionStats) -> [u64; 4]) -> [u64; 4] {
    sessions.iter().fold([0; 4], |mut sum, s| {
        for (total, n) in sum.iter_mut().zip(count(&s.stats)) {
            *total += n;
        }
        sum
    })
}

/// The share `part / whole` of `count` (ticks) over the sessions, percent, with its bootstrap
/// interval over sessions.
fn percent_over_sessions(
    sessions: &[SessionRecord],
    seed: u64,
    count: fn(&SessionStats) -> (u64, u64),
) -> Estimate {
    let per_session: Vec<(f64, f64)> = sessions
        .iter()
        .map(|s| {
            let (part, whole) = count(&s.stats);
            (100.0 * part as f64, whole as f64)
        })
        .collect();
    bootstrap_ratio(&per_session, seed)
}

#[cfg(test)]
mod tests {
    use super::scene_of_seed;

    #[test]
    fn a_seed_starts_from_its_own_scene_and_the_first_seeds_spread() {
        let firsts: Vec<usize> = (0..5).map(|seed| scene_of_seed(seed, 80)).collect();
        assert_eq!(firsts, vec![0, 40, 20, 60, 10]);
        // Sixteen seeds over sixteen scenes take each once.
        let mut all: Vec<usize> = (0..16).map(|seed| scene_of_seed(seed, 16)).collect();
        all.sort_unstable();
        assert_eq!(all, (0..16).collect::<Vec<_>>());
        assert_eq!(scene_of_seed(u64::MAX, 7), 6, "never past the last");
        assert_eq!(scene_of_seed(3, 1), 0);
    }
}
