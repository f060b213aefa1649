//! Putting vehicles on a map that has none yet (a client that sends only a map and its ego) and
//! keeping them coming (inflow at the map's entry lanes).
//!
//! Two stages, each usable alone:
//! - [`place_vehicles`] and [`spawn_at_entry`]: where a vehicle starts (a lane drawn by length,
//!   a place on its centre line with room around it) and its observed history (constant speed
//!   along the lane, back through the lane's predecessors). This is also the heuristic
//!   baseline of `road eval --suite initialisation`.
//! - [`initialise_histories`]: a denoiser trained with the initialisation task draws the new
//!   vehicles' histories whole (from noise, or around a placement from a σ of the caller's).
//! - [`refine_histories`]: the denoiser moves those histories towards what it learnt of real
//!   traffic, jointly over every vehicle and conditioned on the map and on the agents the caller
//!   fixes (the ego): each new vehicle's observed slots start at the noise level of the model's
//!   conditioning augmentation around the placed history and are denoised to σ_min, the fixed
//!   agents' slots written back at every level (replacement inpainting), the future slots held
//!   at pure noise. The model was trained on observations at that noise (the paper's
//!   conditioning augmentation), not on whole agents generated from σ_max: it corrects lane
//!   offsets, headings and speeds within about the augmentation's noise (0.7 m for
//!   road20-wide4), while the lane and place come from the placement.
//!
//! All positions are metres in the map frame; headings radians.

mod initialise;

pub use initialise::{
    Initialisation, REDRAW_SIGMA, REDRAW_STEPS, initialise_histories, redraw_placement, sound_or,
};

use glam::DVec2;
use rand::Rng;
use rand::rngs::StdRng;
use road_data::geometry::{Point, dist};
use road_data::tracks::STEP_SECS;
use road_data::{LaneletMap, SceneWindow};
use road_model::ModelConfig;
use road_model::batch::{SceneInput, normal_vec};
use road_rollout::StepEngine;
use road_rollout::heun::heun_update;
use road_sched::edm::EdmSchedule;

use crate::geometry::OrientedBox;
use crate::route::Route;
use crate::{Error, Pose, Result};

/// How many vehicles to put on a map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum VehicleCount {
    /// This many.
    Vehicles(usize),
    /// So many per 100 m of the map's lanes (centre-line length; connectors that cross count
    /// each).
    PerHundredMetres(f64),
}

impl VehicleCount {
    /// The count on `map`.
    pub fn on(self, map: &LaneletMap) -> usize {
        match self {
            VehicleCount::Vehicles(n) => n,
            VehicleCount::PerHundredMetres(d) => (d * lane_length_m(map) / 100.0).round() as usize,
        }
    }
}

/// What placed vehicles look like and how much room they keep.
#[derive(Debug, Clone, PartialEq)]
pub struct PlacementOptions {
    /// Speeds drawn uniformly from this range (m/s): INTERACTION's moving vehicles mostly drive
    /// 3–10 m/s.
    pub speed_mps: (f64, f64),
    /// Room kept ahead of and behind each vehicle to any other (metres, bumper to bumper);
    /// sideways half a metre, so that vehicles sit side by side on parallel lanes.
    pub min_gap_m: f64,
    pub length_m: (f64, f64),
    pub width_m: (f64, f64),
    /// Tries per vehicle before the map counts as full.
    pub tries: usize,
    /// Only within this distance (metres) of this point (map frame): a scene's area on a
    /// large map. None: the whole map.
    pub region: Option<([f64; 2], f64)>,
}

impl Default for PlacementOptions {
    fn default() -> Self {
        Self {
            speed_mps: (4.0, 9.0),
            min_gap_m: 6.0,
            length_m: (4.2, 5.0),
            width_m: (1.75, 1.95),
            tries: 200,
            region: None,
        }
    }
}

/// Where a vehicle is and how big it is: what placement keeps clear of.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Footprint {
    pub pose: Pose,
    pub length_m: f64,
    pub width_m: f64,
}

/// A vehicle put on the map: its observed history, oldest first, the last entry now.
#[derive(Debug, Clone, PartialEq)]
pub struct PlacedVehicle {
    pub history: Vec<Pose>,
    pub length_m: f64,
    pub width_m: f64,
    /// The lanelet (index into the map's) it was placed on.
    pub lanelet: usize,
    pub speed_mps: f64,
}

impl PlacedVehicle {
    pub fn footprint(&self) -> Footprint {
        Footprint {
            pose: *self.history.last().expect("a history has a step"),
            length_m: self.length_m,
            width_m: self.width_m,
        }
    }
}

/// The centre-line length of every lanelet of `map`, summed (metres).
pub fn lane_length_m(map: &LaneletMap) -> f64 {
    map.lanelets
        .iter()
        .map(|l| polyline_length_m(&l.centre_m))
        .sum()
}

fn polyline_length_m(points: &[Point]) -> f64 {
    points.windows(2).map(|p| dist(p[0], p[1])).sum()
}

/// Each lanelet's predecessors (the lanelets listing it as a successor).
pub fn predecessors(map: &LaneletMap) -> Vec<Vec<usize>> {
    let mut out = vec![Vec::new(); map.lanelets.len()];
    for (i, l) in map.lanelets.iter().enumerate() {
        for &s in &l.successors {
            if let Some(p) = out.get_mut(s as usize) {
                p.push(i);
            }
        }
    }
    out
}

/// The lanelets where traffic enters the map: no predecessor, and a successor or some length
/// (a lone lanelet with neither is not a road).
pub fn entry_lanelets(map: &LaneletMap) -> Vec<usize> {
    let preds = predecessors(map);
    (0..map.lanelets.len())
        .filter(|&i| preds[i].is_empty() && polyline_length_m(&map.lanelets[i].centre_m) > 5.0)
        .collect()
}

/// Whether a vehicle of `length_m` × `width_m` at `pose` keeps `min_gap_m` to every one of
/// `others` (boxes grown by the gap along their length and half a metre across).
fn has_room(pose: Pose, length_m: f64, width_m: f64, others: &[Footprint], min_gap_m: f64) -> bool {
    let grown = |pose: Pose, l: f64, w: f64| OrientedBox {
        pose,
        length_m: l + min_gap_m,
        width_m: w + 0.5,
    };
    let me = grown(pose, length_m, width_m);
    others.iter().all(|o| {
        // Far apart: no need for the box test.
        let d = DVec2::new(o.pose.x_m - pose.x_m, o.pose.y_m - pose.y_m).length();
        d > 0.5 * (length_m + o.length_m) + min_gap_m + width_m + o.width_m
            || !me.overlaps(&grown(o.pose, o.length_m, o.width_m))
    })
}

/// The route a vehicle on lanelet `lane` drove to get there: back through the first
/// predecessors (at most 60 m), then straight back from where the chain starts (traffic comes
/// from beyond the map), then the lane itself. Returns it with the arc length of `lane`'s start.
fn route_into(map: &LaneletMap, preds: &[Vec<usize>], lane: usize) -> (Route, f64) {
    let mut chain = vec![lane];
    let mut back_m = 0.0;
    let mut at = lane;
    while back_m < 60.0 {
        let Some(&p) = preds[at].first() else { break };
        if chain.contains(&p) {
            break; // a ring
        }
        back_m += polyline_length_m(&map.lanelets[p].centre_m);
        chain.push(p);
        at = p;
    }
    chain.reverse();
    let mut points: Vec<Point> = Vec::new();
    let first = &map.lanelets[chain[0]].centre_m;
    if first.len() >= 2 {
        let (a, b) = (DVec2::from(first[0]), DVec2::from(first[1]));
        let back = (a - b).normalize_or_zero();
        points.push((a + back * 80.0).into());
    }
    let mut lane_start_m = 0.0;
    for &l in &chain {
        if l == lane {
            let mut route = points.clone();
            route.push(map.lanelets[l].centre_m[0]);
            lane_start_m = Route::new(route).length_m();
        }
        points.extend(&map.lanelets[l].centre_m);
    }
    (Route::new(points), lane_start_m)
}

/// The observed history of a vehicle at arc length `at_m` of `route` driving `speed_mps`:
/// `steps` poses 0.1 s apart, oldest first.
fn history_along(route: &Route, at_m: f64, speed_mps: f64, steps: usize) -> Vec<Pose> {
    (0..steps)
        .map(|t| route.pose_at(at_m - speed_mps * STEP_SECS * (steps - 1 - t) as f64))
        .collect()
}

fn draw(rng: &mut StdRng, (lo, hi): (f64, f64)) -> f64 {
    if hi > lo {
        rng.random_range(lo..hi)
    } else {
        lo
    }
}

/// Puts up to `count` vehicles on `map`'s lane centres, clear of `occupied` and of each other:
/// lanelets drawn by length, places uniformly along them, speeds from `options`, histories of
/// `steps` poses along the lane ([`PlacedVehicle`]). Fewer come back when the map has no more
/// room (`options.tries` failed draws in a row).
pub fn place_vehicles(
    map: &LaneletMap,
    occupied: &[Footprint],
    count: usize,
    steps: usize,
    options: &PlacementOptions,
    rng: &mut StdRng,
) -> Vec<PlacedVehicle> {
    let in_region = |p: Point| {
        options
            .region
            .is_none_or(|(centre, radius_m)| dist(p, centre) <= radius_m)
    };
    // Lanelets outside the region weigh nothing.
    let lengths: Vec<f64> = map
        .lanelets
        .iter()
        .map(|l| {
            if l.centre_m.iter().any(|&p| in_region(p)) {
                polyline_length_m(&l.centre_m)
            } else {
                0.0
            }
        })
        .collect();
    let total: f64 = lengths.iter().sum();
    let mut placed: Vec<PlacedVehicle> = Vec::with_capacity(count);
    if total <= 0.0 || steps == 0 {
        return placed;
    }
    let preds = predecessors(map);
    let mut others: Vec<Footprint> = occupied.to_vec();
    let mut failures = 0;
    while placed.len() < count && failures < options.tries {
        let mut pick = rng.random_range(0.0..total);
        let mut lane = 0;
        while lane + 1 < lengths.len() && pick >= lengths[lane] {
            pick -= lengths[lane];
            lane += 1;
        }
        let (route, lane_start_m) = route_into(map, &preds, lane);
        let at_m = lane_start_m + pick.min(lengths[lane]);
        let (length_m, width_m) = (draw(rng, options.length_m), draw(rng, options.width_m));
        let pose = route.pose_at(at_m);
        if !in_region([pose.x_m, pose.y_m])
            || !has_room(pose, length_m, width_m, &others, options.min_gap_m)
        {
            failures += 1;
            continue;
        }
        failures = 0;
        let speed_mps = draw(rng, options.speed_mps);
        let vehicle = PlacedVehicle {
            history: history_along(&route, at_m, speed_mps, steps),
            length_m,
            width_m,
            lanelet: lane,
            speed_mps,
        };
        others.push(vehicle.footprint());
        placed.push(vehicle);
    }
    placed
}

/// A vehicle entering the map at the start of lanelet `lane` (an entry lane), or `None` when
/// the start has no room (`occupied`, with `options.min_gap_m`): its history comes from beyond
/// the map straight along the lane's first direction. Its speed is `options`', or the
/// nearest vehicle's ahead on the same lanelet when that one is slower.
pub fn spawn_at_entry(
    map: &LaneletMap,
    lane: usize,
    occupied: &[Footprint],
    steps: usize,
    options: &PlacementOptions,
    rng: &mut StdRng,
) -> Option<PlacedVehicle> {
    let centre = &map.lanelets.get(lane)?.centre_m;
    if centre.len() < 2 || steps == 0 {
        return None;
    }
    let (route, lane_start_m) = route_into(map, &predecessors(map), lane);
    spawn_on(&route, lane_start_m, lane, occupied, steps, options, rng)
}

/// [`spawn_at_entry`] on lane `lane`'s route into the map (`route`, the lane starting at
/// `lane_start_m` along it).
fn spawn_on(
    route: &Route,
    lane_start_m: f64,
    lane: usize,
    occupied: &[Footprint],
    steps: usize,
    options: &PlacementOptions,
    rng: &mut StdRng,
) -> Option<PlacedVehicle> {
    let (length_m, width_m) = (draw(rng, options.length_m), draw(rng, options.width_m));
    // The front bumper at the lane's start.
    let at_m = lane_start_m + 0.5 * length_m;
    let pose = route.pose_at(at_m);
    if !has_room(pose, length_m, width_m, occupied, options.min_gap_m) {
        return None;
    }
    let speed_mps = draw(rng, options.speed_mps);
    Some(PlacedVehicle {
        history: history_along(route, at_m, speed_mps, steps),
        length_m,
        width_m,
        lanelet: lane,
        speed_mps,
    })
}

/// `window` with only the agents `keep` (in that order): a scene's given agents before the
/// placed vehicles join ([`with_vehicles`]).
pub fn keep_agents(window: &SceneWindow, keep: &[usize]) -> SceneWindow {
    let steps = window.steps;
    let mut out = window.clone();
    out.agents = keep.len();
    out.states = keep
        .iter()
        .flat_map(|&a| {
            window.states[3 * a * steps..3 * (a + 1) * steps]
                .iter()
                .copied()
        })
        .collect();
    out.valid = keep
        .iter()
        .flat_map(|&a| window.valid[a * steps..(a + 1) * steps].iter().copied())
        .collect();
    out.track_ids = keep.iter().map(|&a| window.track_ids[a]).collect();
    out.agent_types = keep.iter().map(|&a| window.agent_types[a]).collect();
    out.length_m = keep.iter().map(|&a| window.length_m[a]).collect();
    out.width_m = keep.iter().map(|&a| window.width_m[a]).collect();
    out
}

/// `window` (its frame and map kept) with `vehicles` added after its agents, as cars with track
/// ids after the window's largest. Each history must have the window's steps.
pub fn with_vehicles(window: &SceneWindow, vehicles: &[PlacedVehicle]) -> Result<SceneWindow> {
    let mut out = window.clone();
    let first_id = window.track_ids.iter().copied().max().map_or(1, |m| m + 1);
    for (next_id, (i, v)) in (first_id..).zip(vehicles.iter().enumerate()) {
        if v.history.len() != window.steps {
            return Err(Error::Config(format!(
                "vehicle {i}: {} history steps for a window of {}",
                v.history.len(),
                window.steps
            )));
        }
        let mut previous: Option<f32> = None;
        for p in &v.history {
            let xy = window.frame.to_norm([p.x_m, p.y_m]);
            let raw = p.heading_rad as f32;
            let heading = match previous {
                None => road_data::wrap_angle(raw),
                Some(prev) => prev + road_data::wrap_angle(raw - prev),
            };
            previous = Some(heading);
            out.states.extend([xy[0], xy[1], heading]);
            out.valid.push(true);
        }
        out.agents += 1;
        out.track_ids.push(next_id);
        out.agent_types.push(road_data::AgentType::Car);
        out.length_m.push(v.length_m as f32);
        out.width_m.push(v.width_m as f32);
    }
    Ok(out)
}

/// The last observed pose and size of every agent of `window`: what placement keeps clear of.
pub fn footprints(window: &SceneWindow) -> Vec<Footprint> {
    (0..window.agents)
        .filter_map(|a| {
            Some(Footprint {
                pose: crate::window_pose(window, a, window.steps - 1)?,
                length_m: f64::from(window.length_m[a]),
                width_m: f64::from(window.width_m[a]),
            })
        })
        .collect()
}

/// Vehicles entering a map at its entry lanes ([`entry_lanelets`]) as a Poisson process of
/// `vehicles_per_minute` per entry: each tick an entry gets an arrival with probability
/// rate × 0.1 s. Arrivals queue beyond the map (at most [`MAX_WAITING_PER_ENTRY`] an entry;
/// more are dropped) until the entry has room ([`spawn_at_entry`]) and, with a target count
/// ([`Inflow::with_max_vehicles`]), until the scene has fewer vehicles than that; one enters
/// an entry a tick.
/// The most arrivals an entry queues beyond the map ([`Inflow`]): with a target count, a
/// vehicle that leaves is replaced at once by one that queued while the scene was full (with
/// one waiting an entry, the merge's six fell to four for 17 s: issue 39).
pub const MAX_WAITING_PER_ENTRY: u32 = 4;

#[derive(Debug, Clone)]
pub struct Inflow {
    per_tick: f64,
    entries: Vec<usize>,
    /// Each entry's route into the map and where its lane starts along it (made once).
    routes: Vec<(Route, f64)>,
    /// Arrivals queued at each entry.
    waiting: Vec<u32>,
    options: PlacementOptions,
    rng: StdRng,
    max_vehicles: Option<usize>,
}

impl Inflow {
    /// Inflow on `map`'s entries, its own random stream seeded by `seed`.
    pub fn new(map: &LaneletMap, vehicles_per_minute: f64, seed: u64) -> Self {
        use rand::SeedableRng;
        let entries = entry_lanelets(map);
        let preds = predecessors(map);
        Self {
            per_tick: (vehicles_per_minute * STEP_SECS / 60.0).clamp(0.0, 1.0),
            waiting: vec![0; entries.len()],
            routes: entries
                .iter()
                .map(|&lane| route_into(map, &preds, lane))
                .collect(),
            entries,
            options: PlacementOptions::default(),
            rng: StdRng::seed_from_u64(seed),
            max_vehicles: None,
        }
    }

    /// Arrivals wait while the scene holds `max_vehicles` or more (a target count: vehicles
    /// come in as others leave).
    pub fn with_max_vehicles(mut self, max_vehicles: usize) -> Self {
        self.max_vehicles = Some(max_vehicles);
        self
    }

    /// The map's entry lanelets this inflow feeds.
    pub fn entries(&self) -> &[usize] {
        &self.entries
    }

    /// The vehicles entering this tick, clear of `occupied` and of each other, with histories
    /// of `steps` poses (≥ 1).
    pub fn arrivals(&mut self, occupied: &[Footprint], steps: usize) -> Vec<PlacedVehicle> {
        let mut others = occupied.to_vec();
        let mut out = Vec::new();
        if steps == 0 {
            return out;
        }
        for (k, &lane) in self.entries.iter().enumerate() {
            if self.rng.random_bool(self.per_tick) {
                self.waiting[k] = (self.waiting[k] + 1).min(MAX_WAITING_PER_ENTRY);
            }
            if self.waiting[k] == 0 || self.max_vehicles.is_some_and(|m| others.len() >= m) {
                continue;
            }
            let (route, lane_start_m) = &self.routes[k];
            let spawned = spawn_on(
                route,
                *lane_start_m,
                lane,
                &others,
                steps,
                &self.options,
                &mut self.rng,
            );
            if let Some(v) = spawned {
                self.waiting[k] -= 1;
                others.push(v.footprint());
                out.push(v);
            }
        }
        out
    }
}

/// How [`refine_histories`] denoises.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refinement {
    /// Local diffusion time the histories start at: at most the model's conditioning
    /// augmentation ratio r (the highest observation noise it was trained on).
    pub u_start: f64,
    /// Heun steps from there to σ_min.
    pub steps: usize,
}

impl Refinement {
    /// The model's own limit: from its training's augmentation ratio, in 8 steps.
    pub fn for_model(augmentation_ratio: f64) -> Self {
        Self {
            u_start: augmentation_ratio,
            steps: 8,
        }
    }
}

/// The denoiser's version of `window`'s observed histories (every step of the window observed;
/// positions, headings) for the agents not `fixed`; see the module's documentation. `engine`
/// is prepared here for this one scene (its earlier contents are lost); `edm` the planner's
/// schedule, `model` the checkpoint's configuration. Returns the window with the refined
/// states; the fixed agents' states are as given.
pub fn refine_histories(
    engine: &mut dyn StepEngine,
    model: &ModelConfig,
    edm: &EdmSchedule,
    window: &SceneWindow,
    fixed: &[bool],
    refinement: Refinement,
    rng: &mut StdRng,
) -> Result<SceneWindow> {
    let (a, n, w) = (window.agents, window.steps, engine.window_slots());
    check_histories(window, fixed, w)?;
    if !(0.0..=1.0).contains(&refinement.u_start) || refinement.steps == 0 {
        return Err(Error::Config(format!(
            "refinement from u = {} in {} steps: u lies in [0, 1], steps ≥ 1",
            refinement.u_start, refinement.steps
        )));
    }
    let input = SceneInput::from_window(window, 0, n, model);
    let (polylines, map, map_valid) = padded_map(&input);
    engine.prepare(1, a, &input.agent_features, polylines, &map, &map_valid)?;

    // Window [A, W, 3]: history slots, then pure-noise future slots the model sees as such.
    let sigma_max = edm.sigma_max as f32;
    let sigma_start = edm.sigma(refinement.u_start).max(edm.sigma_min) as f32;
    let valid = vec![1.0f32; a * w];
    let truth = |agent: usize, slot: usize| &input.states[3 * (agent * n + slot)..][..3];
    let noise = normal_vec(rng, a * w * 3);
    let mut x = vec![0.0f32; a * w * 3];
    for agent in 0..a {
        for slot in 0..w {
            let k = 3 * (agent * w + slot);
            for d in 0..3 {
                x[k + d] = if slot < n {
                    truth(agent, slot)[d] + sigma_start * noise[k + d]
                } else {
                    sigma_max * noise[k + d]
                };
            }
        }
    }
    engine.load(&x, &valid)?;
    // ρ-spaced levels from σ_start down to σ_min.
    let levels: Vec<f32> = (0..=refinement.steps)
        .map(|i| {
            let u = refinement.u_start * (1.0 - i as f64 / refinement.steps as f64);
            edm.sigma(u).max(edm.sigma_min) as f32
        })
        .collect();
    let mut denoised = vec![0.0f32; a * w * 3];
    for pair in levels.windows(2) {
        let (cur, next) = (pair[0], pair[1]);
        if cur == next {
            continue;
        }
        let row = |level: f32| -> Vec<f32> {
            (0..w)
                .map(|slot| if slot < n { level } else { sigma_max })
                .collect()
        };
        let (sigma_cur, sigma_next) = (row(cur), row(next));
        let (stepped, _) = heun_update(&x, a, w, &sigma_cur, &sigma_next, true, |xs, sigma| {
            engine.load_scene(0, xs, &valid)?;
            // Any move makes the engine evaluate the scene; its own update is not used.
            let moved: Vec<f32> = sigma.iter().map(|s| 0.5 * s).collect();
            engine.step(sigma, &moved, false)?;
            engine.read_denoised(&[0], &mut denoised)?;
            Ok(denoised.clone())
        })?;
        x = stepped;
        // The fixed agents as they are, at the next level's noise.
        let redraw = normal_vec(rng, a * n * 3);
        for agent in (0..a).filter(|&agent| fixed[agent]) {
            for slot in 0..n {
                for d in 0..3 {
                    x[3 * (agent * w + slot) + d] =
                        truth(agent, slot)[d] + next * redraw[3 * (agent * n + slot) + d];
                }
            }
        }
    }
    with_drawn_histories(window, fixed, &x, w, model.heading_scale, "refinement")
}

/// Checks a window of observed histories and its `fixed` flags against a model's `slots`.
fn check_histories(window: &SceneWindow, fixed: &[bool], slots: usize) -> Result<()> {
    let (a, n) = (window.agents, window.steps);
    if fixed.len() != a {
        return Err(Error::Config(format!(
            "{} fixed flags for {a} agents",
            fixed.len()
        )));
    }
    if n == 0 || n >= slots {
        return Err(Error::Config(format!(
            "{n} history steps; the model's window has {slots} slots"
        )));
    }
    Ok(())
}

/// One scene's map as a model takes it: (polylines, at least one; `[P, Q, 2]` points, padded;
/// `[P]` flags).
fn padded_map(input: &SceneInput) -> (usize, Vec<f32>, Vec<f32>) {
    let polylines = input.polylines.max(1);
    let mut map = vec![0.0f32; polylines * input.points * 2];
    map[..input.map.len()].copy_from_slice(&input.map);
    let mut map_valid = vec![0.0f32; polylines];
    map_valid[..input.polylines].fill(1.0);
    (polylines, map, map_valid)
}

/// `window` with the observed steps of its agents not `fixed` taken from sampled states
/// `x [A, slots, 3]` (model units: headings times `heading_scale`); `what` names the sampler in
/// the error a non-finite state gives.
fn with_drawn_histories(
    window: &SceneWindow,
    fixed: &[bool],
    x: &[f32],
    slots: usize,
    heading_scale: f64,
    what: &str,
) -> Result<SceneWindow> {
    let n = window.steps;
    let mut out = window.clone();
    for agent in (0..window.agents).filter(|&agent| !fixed[agent]) {
        for slot in 0..n {
            let k = 3 * (agent * slots + slot);
            let state = [x[k], x[k + 1], x[k + 2] / heading_scale as f32];
            if state.iter().any(|v| !v.is_finite()) {
                return Err(Error::Config(format!(
                    "{what}: agent {agent} step {slot} is not finite ({state:?})"
                )));
            }
            let o = 3 * (agent * n + slot);
            out.states[o..o + 3].copy_from_slice(&state);
            out.valid[agent * n + slot] = true;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural::{ProceduralMap, procedural};
    use rand::SeedableRng;
    use road_data::WindowConfig;

    fn on_lanes(map: &LaneletMap, p: &Pose) -> bool {
        map.lanelet_at([p.x_m, p.y_m]).is_some()
    }

    #[test]
    fn placed_vehicles_sit_on_lanes_apart_and_move_along_them() {
        for kind in ProceduralMap::ALL {
            let scene = procedural(kind, &WindowConfig::default(), 10).unwrap();
            let mut rng = StdRng::seed_from_u64(7);
            let options = PlacementOptions::default();
            let placed = place_vehicles(&scene.map, &[], 12, 10, &options, &mut rng);
            let name = kind.name();
            assert_eq!(placed.len(), 12, "{name}");
            for (i, v) in placed.iter().enumerate() {
                let now = v.history.last().unwrap();
                assert!(on_lanes(&scene.map, now), "{name}: vehicle {i} at {now:?}");
                // Constant speed along the lane: each step moves speed × 0.1 s.
                let step = v.history[9].position_m() - v.history[8].position_m();
                assert!((step.length() - v.speed_mps * 0.1).abs() < 0.05, "{name}");
                for (j, u) in placed.iter().enumerate().take(i) {
                    let others = [u.footprint()];
                    assert!(
                        has_room(now.to_owned(), v.length_m, v.width_m, &others, 0.0),
                        "{name}: vehicles {j} and {i} overlap"
                    );
                }
            }
        }
    }

    #[test]
    fn a_full_map_gives_fewer_vehicles_and_a_density_counts_lane_metres() {
        let scene = procedural(ProceduralMap::Merge, &WindowConfig::default(), 10).unwrap();
        let mut rng = StdRng::seed_from_u64(1);
        let placed = place_vehicles(
            &scene.map,
            &[],
            10_000,
            10,
            &PlacementOptions::default(),
            &mut rng,
        );
        let metres = lane_length_m(&scene.map);
        // At least a vehicle per 11 m + gaps cannot fit, and some do.
        assert!(placed.len() > 5 && (placed.len() as f64) < metres / 10.0);
        assert_eq!(
            VehicleCount::PerHundredMetres(2.0).on(&scene.map),
            (2.0 * metres / 100.0).round() as usize
        );
    }

    #[test]
    fn entries_spawn_only_with_room() {
        let scene = procedural(ProceduralMap::Intersection, &WindowConfig::default(), 10).unwrap();
        let entries = entry_lanelets(&scene.map);
        assert_eq!(entries.len(), 4, "one entry per arm");
        let mut rng = StdRng::seed_from_u64(3);
        let options = PlacementOptions::default();
        let v = spawn_at_entry(&scene.map, entries[0], &[], 10, &options, &mut rng).unwrap();
        assert!(on_lanes(&scene.map, v.history.last().unwrap()));
        // Its history comes from beyond the map's edge.
        assert!(!on_lanes(&scene.map, &v.history[0]) || v.speed_mps * 0.9 < v.length_m);
        // A vehicle standing at the entry blocks it.
        let blocked = spawn_at_entry(
            &scene.map,
            entries[0],
            &[v.footprint()],
            10,
            &options,
            &mut rng,
        );
        assert!(blocked.is_none());
    }

    #[test]
    fn arrivals_queue_while_the_scene_is_full_and_refill_it_at_once() {
        let scene = procedural(ProceduralMap::Merge, &WindowConfig::default(), 10).unwrap();
        let mut inflow = Inflow::new(&scene.map, 6.0, 5).with_max_vehicles(3);
        assert_eq!(inflow.entries().len(), 2, "the main road and the ramp");
        // Full for two minutes (three vehicles far from the entries): nobody enters, and about
        // twelve arrivals an entry queue, up to the queue's bound.
        let far = |x_m: f64| Footprint {
            pose: Pose::at(DVec2::new(x_m, 0.0), 0.0),
            length_m: 4.5,
            width_m: 1.8,
        };
        let full = [far(60.0), far(70.0), far(80.0)];
        for _ in 0..1200 {
            assert!(inflow.arrivals(&full, 10).is_empty(), "the scene is full");
        }
        // All three leave; each tick the entered ones have driven off (not in `occupied`).
        // One a tick at each entry, from the queue, without waiting for new arrivals.
        let entered: Vec<usize> = (0..4).map(|_| inflow.arrivals(&[], 10).len()).collect();
        assert_eq!(entered, [2, 2, 2, 2], "two entries, four queued at each");
        let after: usize = (0..4).map(|_| inflow.arrivals(&[], 10).len()).sum();
        assert!(after <= 1, "the queues are empty: {after} entered");
    }
}
