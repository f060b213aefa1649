//! Scenes: a creation request checked field by field and turned into a closed-loop simulation
//! in its pool ([`setup`], [`LiveScene::new`]); a live scene's ego inputs checked
//! ([`LiveScene::check_ego`]) and its ticks ([`LiveScene::begin_tick`],
//! [`LiveScene::finish_tick`]) with the late-ego policy: when the ego of a tick does not come in
//! time the model drives the external agents for that tick, and the reply says so.

use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use glam::DVec2;
use rand::SeedableRng;
use rand::rngs::StdRng;
use road_data::geometry::{dist, resample};
use road_data::{AgentType, LaneletMap, SceneFrame, SceneWindow, WindowConfig, wrap_angle};
use road_model::checkpoint::LoadedModel;
use road_protocol::{
    AgentInfo, AgentInit, AgentPlan, AgentState, CreateScene, EgoTick, ErrorCode, ErrorReply,
    MapSource, NpcTick, Populate, Pose,
};
use road_sched::PlannerSpec;
use road_sim::Pose as SimPose;
use road_sim::closed_loop::{Controller, ExternalDriver, SceneTick, SimScene};
use road_sim::geometry::OrientedBox;
use road_sim::infractions::off_road;
use road_sim::populate::{
    Footprint, Inflow, PlacementOptions, Refinement, VehicleCount, place_vehicles,
    redraw_placement, refine_histories,
};
use road_sim::procedural::{ProceduralMap, STEP_SECS, procedural};

use crate::config::ServeConfig;
use crate::models::Checkpoints;
use crate::pool::{Pool, PoolKey};

/// Box sizes beyond these are refused as absurd (a semi-trailer is ≈ 25 m by 2.6 m).
const MAX_LENGTH_M: f64 = 30.0;
const MAX_WIDTH_M: f64 = 5.0;
/// How far outside its map's lanes (their bounding box) a position may be: room for parking
/// lots and driveways the map leaves out, and none for a number that is not a place.
pub const MAP_MARGIN_M: f64 = 500.0;
/// The largest heading magnitude taken (any number of turns up to it; the model unwraps).
pub const MAX_ABS_HEADING_RAD: f64 = 100.0;

/// Where positions may be: the bounding box of the map's lanelets grown by [`MAP_MARGIN_M`].
#[derive(Debug, Clone, Copy)]
pub struct Extent {
    min: DVec2,
    max: DVec2,
}

impl Extent {
    pub fn of(map: &LaneletMap) -> Option<Self> {
        let (min, max) =
            map.lanelets
                .iter()
                .fold((DVec2::INFINITY, DVec2::NEG_INFINITY), |(min, max), l| {
                    (
                        min.min(DVec2::from(l.bounds.min)),
                        max.max(DVec2::from(l.bounds.max)),
                    )
                });
        (min.is_finite() && max.is_finite()).then(|| Self {
            min: min - DVec2::splat(MAP_MARGIN_M),
            max: max + DVec2::splat(MAP_MARGIN_M),
        })
    }

    fn contains(&self, x_m: f64, y_m: f64) -> bool {
        (self.min.x..=self.max.x).contains(&x_m) && (self.min.y..=self.max.y).contains(&y_m)
    }

    fn describe(&self) -> String {
        format!(
            "x in [{:.3}, {:.3}] m, y in [{:.3}, {:.3}] m (the map's lanes and {MAP_MARGIN_M} m around them)",
            self.min.x, self.max.x, self.min.y, self.max.y
        )
    }
}

/// The first field of `p` that is not a usable number (not finite, outside `extent`, a
/// heading beyond ±[`MAX_ABS_HEADING_RAD`]), with what is wrong with it.
fn pose_fault(p: &Pose, extent: Option<&Extent>) -> Option<(&'static str, String)> {
    if let Some(f) = finite_pose(p) {
        return Some((f, format!("{f} is not finite")));
    }
    if p.heading_rad.abs() > MAX_ABS_HEADING_RAD {
        return Some((
            "heading_rad",
            format!(
                "heading_rad {} is beyond ±{MAX_ABS_HEADING_RAD} rad",
                p.heading_rad
            ),
        ));
    }
    if let Some(extent) = extent {
        if !extent.contains(p.x_m, p.y_m) {
            let field = if (extent.min.x..=extent.max.x).contains(&p.x_m) {
                "y_m"
            } else {
                "x_m"
            };
            return Some((
                field,
                format!(
                    "({}, {}) m is off the map: positions must lie within {}",
                    p.x_m,
                    p.y_m,
                    extent.describe()
                ),
            ));
        }
    }
    None
}

/// What [`setup`] needs besides the request.
#[derive(Debug)]
pub struct SetupContext<'a> {
    pub config: &'a ServeConfig,
    pub checkpoints: &'a mut Checkpoints,
    pub planners: &'a BTreeMap<String, PlannerSpec>,
    /// Maps the server was started with, by name.
    pub map_files: &'a BTreeMap<String, Arc<LaneletMap>>,
}

/// A checked request: everything a [`LiveScene`] is built from.
#[derive(Debug)]
pub struct SceneSetup {
    pub window: SceneWindow,
    pub map: Option<Arc<LaneletMap>>,
    pub agents: Vec<AgentInfo>,
    pub planner_name: String,
    pub planner: PlannerSpec,
    pub checkpoint_name: String,
    pub model: &'static LoadedModel,
    pub seed: u64,
    pub max_ticks: u64,
    /// The client's id: the scene's keys name it.
    pub client: String,
    /// Whether each tick's reply carries the NPCs' plans.
    pub plans: bool,
    /// Where the scene's positions may be (checked at creation, and on every ego tick).
    pub extent: Option<Extent>,
    /// Arrivals per minute at each entry lane and the target count, when vehicles keep
    /// entering.
    pub inflow: Option<(f64, Option<u32>)>,
}

fn invalid(field: impl Into<String>, message: impl Into<String>) -> ErrorReply {
    ErrorReply {
        field: Some(field.into()),
        ..ErrorReply::new(ErrorCode::InvalidField, None, message)
    }
}

fn refuse(code: ErrorCode, field: &str, message: impl Into<String>) -> ErrorReply {
    ErrorReply::new(code, Some(field), message)
}

fn finite_pose(p: &Pose) -> Option<&'static str> {
    if !p.x_m.is_finite() {
        Some("x_m")
    } else if !p.y_m.is_finite() {
        Some("y_m")
    } else if !p.heading_rad.is_finite() {
        Some("heading_rad")
    } else {
        None
    }
}

/// Checks `req` field by field (the first fault is reported, naming its field) and loads what
/// it names.
pub fn setup(req: &CreateScene, ctx: &mut SetupContext<'_>) -> Result<SceneSetup, ErrorReply> {
    let Some(client) = &req.client else {
        return Err(invalid(
            "client",
            "the client's id is required: the scene's keys name it (docs/protocol.md)",
        ));
    };
    if !road_protocol::valid_client_id(client) {
        return Err(invalid(
            "client",
            format!("client id {client:?}: expected 1 to 64 ASCII letters, digits, '-' or '_'"),
        ));
    }
    let max_ticks = match req.max_ticks {
        None => ctx.config.max_ticks,
        Some(0) => return Err(invalid("max_ticks", "max_ticks must be at least 1")),
        Some(t) if t > ctx.config.max_ticks => {
            return Err(invalid(
                "max_ticks",
                format!(
                    "max_ticks {t} exceeds the server's limit {}",
                    ctx.config.max_ticks
                ),
            ));
        }
        Some(t) => t,
    };

    if let Some(inflow) = &req.inflow {
        let v = inflow.vehicles_per_minute;
        if !(v.is_finite() && v > 0.0 && v <= MAX_INFLOW_PER_MINUTE) {
            return Err(invalid(
                "inflow.vehicles_per_minute",
                format!("{v} vehicles a minute per entry is not in (0, {MAX_INFLOW_PER_MINUTE}]"),
            ));
        }
        if let Some(m) = inflow.max_vehicles {
            if m == 0 || m as usize > ctx.config.max_agents {
                return Err(invalid(
                    "inflow.max_vehicles",
                    format!(
                        "a target of {m} vehicles is not in 1..={} (the server's agents a scene)",
                        ctx.config.max_agents
                    ),
                ));
            }
        }
    }

    // The model: checkpoint, then planner (n and W come from them).
    let checkpoint_name = req
        .checkpoint
        .clone()
        .unwrap_or_else(|| ctx.config.default_checkpoint.clone());
    if !ctx.checkpoints.exists(&checkpoint_name) {
        return Err(refuse(
            ErrorCode::BadModel,
            "checkpoint",
            format!(
                "unknown checkpoint {checkpoint_name:?} (no such folder with a config.toml in {})",
                ctx.checkpoints.describe()
            ),
        ));
    }
    let model = ctx.checkpoints.get(&checkpoint_name).map_err(|e| {
        refuse(
            ErrorCode::BadModel,
            "checkpoint",
            format!("checkpoint {checkpoint_name:?} does not load: {e}"),
        )
    })?;
    let (planner_name, planner) = match &req.planner {
        None => (model.meta.run.name.clone(), model.meta.run.planner.clone()),
        Some(name) => match ctx.planners.get(name) {
            Some(p) => (name.clone(), p.clone()),
            None => {
                return Err(refuse(
                    ErrorCode::BadModel,
                    "planner",
                    format!(
                        "unknown planner {name:?}; known: {}",
                        ctx.planners.keys().cloned().collect::<Vec<_>>().join(", ")
                    ),
                ));
            }
        },
    };
    let model_w = model.meta.run.model.window_slots;
    if planner.window_slots() != model_w || planner.obs_slots != model.meta.run.planner.obs_slots {
        return Err(refuse(
            ErrorCode::BadModel,
            "planner",
            format!(
                "planner {planner_name:?} has W = {} and n = {}; checkpoint {checkpoint_name:?} runs W = {model_w} and n = {}",
                planner.window_slots(),
                planner.obs_slots,
                model.meta.run.planner.obs_slots
            ),
        ));
    }
    let n = planner.obs_slots;
    let mc = &model.meta.run.model;
    let window_config = mc.window_config();

    // The map, and the procedural map's own vehicles.
    let (map, builtin): (Option<Arc<LaneletMap>>, Option<Vec<AgentInit>>) = match &req.map {
        MapSource::Procedural(name) => match ProceduralMap::from_name(name) {
            Some(kind) => {
                let scene = procedural(kind, &window_config, n)
                    .map_err(|e| refuse(ErrorCode::BadMap, "map.procedural", e.to_string()))?;
                let agents = window_agents(&scene.window);
                (Some(Arc::new(scene.map)), Some(agents))
            }
            None => {
                return Err(refuse(
                    ErrorCode::BadMap,
                    "map.procedural",
                    format!(
                        "unknown procedural map {name:?}; known: {}",
                        ProceduralMap::names()
                    ),
                ));
            }
        },
        MapSource::Osm(text) => {
            let map = LaneletMap::parse(text, Path::new("map.osm"), "request").map_err(|e| {
                refuse(
                    ErrorCode::BadMap,
                    "map.osm",
                    format!("the .osm does not parse: {e}"),
                )
            })?;
            if map.lanelets.is_empty() {
                return Err(refuse(
                    ErrorCode::BadMap,
                    "map.osm",
                    "the .osm has no lanelets (relations with type=lanelet and a left and right way)",
                ));
            }
            (Some(Arc::new(map)), None)
        }
        MapSource::File(name) => match ctx.map_files.get(name) {
            Some(map) => (Some(Arc::clone(map)), None),
            None => {
                return Err(refuse(
                    ErrorCode::BadMap,
                    "map.file",
                    format!(
                        "unknown map file {name:?}; the server was started with: {}",
                        if ctx.map_files.is_empty() {
                            "none".to_owned()
                        } else {
                            ctx.map_files.keys().cloned().collect::<Vec<_>>().join(", ")
                        }
                    ),
                ));
            }
        },
    };

    // The agents: the request's; else the procedural map's own (with `populate`, only its
    // ego, agent 0, the others placed).
    let given: Vec<AgentInit> = match (&req.agents, &builtin) {
        (Some(a), _) => a.clone(),
        (None, Some(b)) if req.populate.is_some() => b[..1].to_vec(),
        (None, Some(b)) => b.clone(),
        (None, None) if req.populate.is_some() => Vec::new(),
        (None, None) => {
            return Err(invalid(
                "agents",
                "agents are required unless the map is procedural or `populate` is given",
            ));
        }
    };
    let agents: &[AgentInit] = &given;
    if agents.is_empty() && req.populate.is_none() {
        return Err(invalid("agents", "a scene needs at least one agent"));
    }
    if agents.len() > ctx.config.max_agents {
        return Err(invalid(
            "agents",
            format!(
                "{} agents; the model takes at most {}",
                agents.len(),
                ctx.config.max_agents
            ),
        ));
    }
    let extent = map.as_deref().and_then(Extent::of);
    let mut seen = HashSet::new();
    for (i, a) in agents.iter().enumerate() {
        if !seen.insert(a.id) {
            return Err(invalid(
                format!("agents[{i}].id"),
                format!("agent id {} appears twice", a.id),
            ));
        }
        for (name, v, max) in [
            ("length_m", a.length_m, MAX_LENGTH_M),
            ("width_m", a.width_m, MAX_WIDTH_M),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= max) {
                return Err(invalid(
                    format!("agents[{i}].{name}"),
                    format!("{name} {v} of agent {} is not in (0, {max}]", a.id),
                ));
            }
        }
        if a.history.len() < n {
            return Err(invalid(
                format!("agents[{i}].history"),
                format!(
                    "agent {} has {} history steps; the planner observes {n}",
                    a.id,
                    a.history.len()
                ),
            ));
        }
        let max_step_m = ctx.config.max_external_speed_mps * STEP_SECS;
        for (k, p) in a.history.iter().enumerate() {
            if let Some((f, why)) = pose_fault(p, extent.as_ref()) {
                return Err(invalid(
                    format!("agents[{i}].history[{k}].{f}"),
                    format!("agent {} history step {k}: {why}", a.id),
                ));
            }
            if let Some(previous) = k.checked_sub(1).map(|j| &a.history[j]) {
                let moved_m = DVec2::new(p.x_m - previous.x_m, p.y_m - previous.y_m).length();
                if moved_m > max_step_m {
                    return Err(invalid(
                        format!("agents[{i}].history[{k}]"),
                        format!(
                            "agent {} moved {moved_m:.1} m from history step {} to {k}, one {STEP_SECS} s step; at most {max_step_m:.1} m ({} m/s)",
                            a.id,
                            k - 1,
                            ctx.config.max_external_speed_mps
                        ),
                    ));
                }
            }
        }
    }
    let mut external_seen = HashSet::new();
    for (j, id) in req.external.iter().enumerate() {
        if !seen.contains(id) {
            return Err(invalid(
                format!("external[{j}]"),
                format!("external agent {id} is not among the scene's agents"),
            ));
        }
        if !external_seen.insert(*id) {
            return Err(invalid(
                format!("external[{j}]"),
                format!("external agent {id} is listed twice"),
            ));
        }
    }

    let mut histories: Vec<Vec<Pose>> = agents
        .iter()
        .map(|a| a.history[a.history.len() - n..].to_vec())
        .collect();
    let mut all_agents = given.clone();
    // The initialiser, checked before anything is placed.
    let initialiser = match &req.populate {
        Some(populate) => initialiser(populate, ctx, &model.meta.run.model, n)?,
        None => None,
    };
    let placed = match (&req.populate, map.as_deref()) {
        (Some(populate), Some(map)) => {
            let vehicles = populated(populate, map, &histories, agents, n, ctx, req.seed)?;
            all_agents.extend(vehicles.iter().cloned());
            histories.extend(vehicles.into_iter().map(|v| v.history));
            all_agents.len() - agents.len()
        }
        _ => 0,
    };
    if all_agents.is_empty() {
        return Err(invalid(
            "populate",
            "the map had no room for a vehicle and the request gives no agent",
        ));
    }
    let agents: &[AgentInit] = &all_agents;
    let mut window = build_window(map.as_deref(), agents, &histories, &window_config, &req.map);
    if placed > 0 && req.populate.as_ref().is_some_and(|p| p.refine) {
        let mut fixed = vec![true; agents.len()];
        fixed[given.len()..].fill(false);
        let placement = window.clone();
        window = refined(model, &planner, &window, &fixed, req.seed).map_err(|e| {
            ErrorReply::new(
                ErrorCode::Internal,
                Some("populate"),
                format!("the model's refinement of the placed vehicles failed: {e}"),
            )
        })?;
        if let (Some(init), Some(map)) = (initialiser, map.as_deref()) {
            let kept;
            (window, kept) =
                drawn(init, map, &placement, &window, &fixed, req.seed).map_err(|e| {
                    ErrorReply::new(
                        ErrorCode::Internal,
                        Some("populate.initialiser"),
                        format!("the initialiser's draw of the placed vehicles failed: {e}"),
                    )
                })?;
            tracing::info!(
                drawn = kept.iter().filter(|&&k| k).count(),
                placed,
                "populate: vehicles the initialiser drew (the others keep their refined placement)"
            );
        }
        for (a, history) in histories.iter_mut().enumerate().skip(given.len()) {
            *history = window_history(&window, a);
        }
    }
    let infos = agents
        .iter()
        .zip(histories)
        .map(|(a, history)| AgentInfo {
            id: a.id,
            length_m: a.length_m,
            width_m: a.width_m,
            external: external_seen.contains(&a.id),
            history,
        })
        .collect();
    Ok(SceneSetup {
        window,
        map,
        agents: infos,
        planner_name,
        planner,
        checkpoint_name,
        model,
        seed: req.seed,
        max_ticks,
        plans: req.plans,
        client: client.clone(),
        extent,
        inflow: req
            .inflow
            .as_ref()
            .map(|i| (i.vehicles_per_minute, i.max_vehicles)),
    })
}

/// A window's agents as a request would give them (the procedural map's own vehicles).
fn window_agents(w: &SceneWindow) -> Vec<AgentInit> {
    (0..w.agents)
        .map(|a| AgentInit {
            id: w.track_ids[a],
            length_m: f64::from(w.length_m[a]),
            width_m: f64::from(w.width_m[a]),
            history: window_history(w, a),
        })
        .collect()
}

/// Simulation poses as the protocol's.
fn protocol_poses(poses: &[SimPose]) -> Vec<Pose> {
    poses
        .iter()
        .map(|p| Pose {
            x_m: p.x_m,
            y_m: p.y_m,
            heading_rad: p.heading_rad,
        })
        .collect()
}

/// Agent `a`'s states in `w`, in metres and radians.
fn window_history(w: &SceneWindow, a: usize) -> Vec<Pose> {
    (0..w.steps)
        .filter_map(|t| w.state(a, t))
        .map(|s| {
            let p = w.frame.to_metres([s[0], s[1]]);
            Pose {
                x_m: p[0],
                y_m: p[1],
                heading_rad: f64::from(wrap_angle(s[2])),
            }
        })
        .collect()
}

/// Arrivals `inflow.vehicles_per_minute` may ask for at each entry: one a second at most (a
/// vehicle needs its length and gap to clear the entry first anyway).
const MAX_INFLOW_PER_MINUTE: f64 = 60.0;
const INFLOW_STREAM: u64 = 0x0069_6e66_6c6f;

/// Densities `populate.vehicles_per_100m` may ask for: above 10 the lanes are full anyway.
const MAX_VEHICLES_PER_100M: f64 = 10.0;

/// The vehicles `populate` asks for on `map`, placed clear of the given agents (their
/// `histories`, n steps each), with ids after the largest given id; checked field by field.
fn populated(
    populate: &Populate,
    map: &LaneletMap,
    histories: &[Vec<Pose>],
    given: &[AgentInit],
    n: usize,
    ctx: &SetupContext<'_>,
    seed: u64,
) -> Result<Vec<AgentInit>, ErrorReply> {
    let room = ctx.config.max_agents.saturating_sub(given.len());
    let count = match (populate.vehicles, populate.vehicles_per_100m) {
        (Some(_), Some(_)) | (None, None) => {
            return Err(invalid(
                "populate",
                "give exactly one of `vehicles` and `vehicles_per_100m`",
            ));
        }
        (Some(v), None) => {
            if v as usize > room {
                return Err(invalid(
                    "populate.vehicles",
                    format!(
                        "{v} vehicles and {} given agents exceed the server's {} agents a scene",
                        given.len(),
                        ctx.config.max_agents
                    ),
                ));
            }
            v as usize
        }
        (None, Some(d)) => {
            if !(d.is_finite() && d > 0.0 && d <= MAX_VEHICLES_PER_100M) {
                return Err(invalid(
                    "populate.vehicles_per_100m",
                    format!("{d} vehicles per 100 m is not in (0, {MAX_VEHICLES_PER_100M}]"),
                ));
            }
            VehicleCount::PerHundredMetres(d).on(map).min(room)
        }
    };
    let occupied: Vec<Footprint> = given
        .iter()
        .zip(histories)
        .map(|(a, h)| {
            let p = h.last().expect("histories have n ≥ 1 steps");
            Footprint {
                pose: SimPose {
                    x_m: p.x_m,
                    y_m: p.y_m,
                    heading_rad: p.heading_rad,
                },
                length_m: a.length_m,
                width_m: a.width_m,
            }
        })
        .collect();
    // The placement's own stream: the same request and seed place the same vehicles.
    let mut rng = StdRng::seed_from_u64(road_rollout::stream_seed(seed, PLACEMENT_STREAM));
    let placed = place_vehicles(
        map,
        &occupied,
        count,
        n,
        &PlacementOptions::default(),
        &mut rng,
    );
    let mut next_id = given.iter().map(|a| a.id).max().map_or(1, |m| m + 1);
    Ok(placed
        .into_iter()
        .map(|v| {
            let id = next_id;
            next_id += 1;
            AgentInit {
                id,
                length_m: v.length_m,
                width_m: v.width_m,
                history: protocol_poses(&v.history),
            }
        })
        .collect())
}

/// Noise streams of a scene's setup, apart from its simulation's.
const PLACEMENT_STREAM: u64 = 0x0070_6c61_6365;
const REFINEMENT_STREAM: u64 = 0x7265_6669_6e65;
const INITIALISER_STREAM: u64 = 0x0064_7261_7773;

/// The initialiser of a `populate` request: the checkpoint `populate.initialiser` names,
/// loaded and checked (trained to draw whole vehicles, observing the scene's `n` steps on
/// windows cut as the scene's checkpoint (`scene_model`) cuts them; `refine: false` excludes
/// it); `"none"`: none; omitted: the server's default where it fits (else none, logged).
fn initialiser(
    populate: &Populate,
    ctx: &mut SetupContext<'_>,
    scene_model: &road_model::ModelConfig,
    n: usize,
) -> Result<Option<&'static LoadedModel>, ErrorReply> {
    let field = "populate.initialiser";
    let name = match populate.initialiser.as_deref() {
        Some("none") => return Ok(None),
        Some(name) => name.to_owned(),
        None => {
            let Some(name) = ctx.config.default_initialiser.clone() else {
                return Ok(None);
            };
            if !populate.refine {
                return Ok(None);
            }
            // Loaded and checked at the server's start; only its fit to this scene is left.
            let model = match ctx.checkpoints.get(&name) {
                Ok(model) => model,
                Err(e) => {
                    tracing::warn!(initialiser = %name, %e, "populate: placement refined only");
                    return Ok(None);
                }
            };
            return Ok(match fits(model, scene_model, n) {
                Ok(()) => Some(model),
                Err(why) => {
                    tracing::info!(initialiser = %name, why, "populate: placement refined only");
                    None
                }
            });
        }
    };
    if !populate.refine {
        return Err(invalid(
            field,
            "`refine: false` keeps the placement as it is and an initialiser draws it anew: give one of them",
        ));
    }
    if !ctx.checkpoints.exists(&name) {
        return Err(refuse(
            ErrorCode::BadModel,
            field,
            format!(
                "unknown checkpoint {name:?} (no such folder with a config.toml in {})",
                ctx.checkpoints.describe()
            ),
        ));
    }
    let model = ctx.checkpoints.get(&name).map_err(|e| {
        refuse(
            ErrorCode::BadModel,
            field,
            format!("checkpoint {name:?} does not load: {e}"),
        )
    })?;
    check_initialiser(model)
        .and_then(|()| fits(model, scene_model, n))
        .map_err(|why| {
            refuse(
                ErrorCode::BadModel,
                field,
                format!("checkpoint {name:?} {why}"),
            )
        })?;
    Ok(Some(model))
}

/// Whether `model` was trained to draw whole vehicles; why not.
pub fn check_initialiser(model: &LoadedModel) -> Result<(), String> {
    let trained = model
        .meta
        .run
        .model
        .agent_frame
        .as_ref()
        .is_some_and(|f| f.max_anchor_sigma.is_some());
    if trained {
        Ok(())
    } else {
        Err(format!(
            "was not trained to draw whole vehicles (no model.agent_frame.max_anchor_sigma; {} was)",
            crate::config::DEFAULT_INITIALISER
        ))
    }
}

/// Whether the initialiser `model` fits a scene of `scene_model` observing `n` steps; why not.
pub fn fits(
    model: &LoadedModel,
    scene_model: &road_model::ModelConfig,
    n: usize,
) -> Result<(), String> {
    let run = &model.meta.run;
    if run.model.window_config() != scene_model.window_config() {
        return Err(
            "cuts scene windows otherwise than the scene's checkpoint (position scale, polyline points)"
                .into(),
        );
    }
    if run.planner.obs_slots != n {
        return Err(format!(
            "observes {} steps; the scene's planner {n}",
            run.planner.obs_slots
        ));
    }
    Ok(())
}

/// `placement` redrawn by the initialiser `model` as a served scene starts
/// (`road_sim::populate::redraw_placement`; what `road eval --suite initialisation
/// --initialiser` measures), with its own noise stream; which agents kept the draw.
fn drawn(
    model: &LoadedModel,
    map: &LaneletMap,
    placement: &SceneWindow,
    refined: &SceneWindow,
    fixed: &[bool],
    seed: u64,
) -> road_sim::Result<(SceneWindow, Vec<bool>)> {
    let mut rng = StdRng::seed_from_u64(road_rollout::stream_seed(seed, INITIALISER_STREAM));
    redraw_placement(
        &model.model,
        &model.meta.run.planner.edm,
        map,
        placement,
        refined,
        fixed,
        &mut rng,
    )
}

/// `window` with the histories of the agents not `fixed` refined by the model (on a CPU
/// engine of its own: one scene, once; `road_sim::populate::refine_histories`).
fn refined(
    model: &LoadedModel,
    planner: &PlannerSpec,
    window: &SceneWindow,
    fixed: &[bool],
    seed: u64,
) -> road_sim::Result<SceneWindow> {
    let run = &model.meta.run;
    let mut engine = road_cpu::FastCpuEngine::new(&model.model)?;
    let mut rng = StdRng::seed_from_u64(road_rollout::stream_seed(seed, REFINEMENT_STREAM));
    refine_histories(
        &mut engine,
        &run.model,
        &planner.edm,
        window,
        fixed,
        Refinement::for_model(run.train.augmentation_ratio),
        &mut rng,
    )
}

/// A window of `histories` (each the last n steps of its agent), normalised around the agents'
/// mean position at step 0, with the map's lanes nearest to it as polylines, as the data
/// pipeline cuts INTERACTION windows.
fn build_window(
    map: Option<&LaneletMap>,
    agents: &[AgentInit],
    histories: &[Vec<Pose>],
    config: &WindowConfig,
    source: &MapSource,
) -> SceneWindow {
    let steps = histories[0].len();
    let count = histories.len() as f64;
    let centre = histories
        .iter()
        .map(|h| {
            let p = h.last().expect("histories have n ≥ 1 steps");
            DVec2::new(p.x_m, p.y_m)
        })
        .fold(DVec2::ZERO, |acc, p| acc + p / count);
    let frame = SceneFrame {
        origin_m: centre.to_array(),
        scale_m: config.position_scale_m,
    };
    let mut states = Vec::with_capacity(histories.len() * steps * 3);
    for h in histories {
        // Headings unwrapped along the history: the model's state is continuous.
        let mut previous: Option<f32> = None;
        for p in h {
            let xy = frame.to_norm([p.x_m, p.y_m]);
            let raw = p.heading_rad as f32;
            let heading = match previous {
                None => wrap_angle(raw),
                Some(prev) => prev + wrap_angle(raw - prev),
            };
            previous = Some(heading);
            states.extend([xy[0], xy[1], heading]);
        }
    }
    let mut polylines = Vec::new();
    let mut polyline_lanelet_ids = Vec::new();
    if let Some(map) = map {
        let origin = centre.to_array();
        let mut near: Vec<(f64, usize)> = map
            .lanelets
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let d = l
                    .centre_m
                    .iter()
                    .map(|&p| dist(p, origin))
                    .fold(f64::INFINITY, f64::min);
                (d, i)
            })
            .filter(|&(d, _)| d <= config.map_radius_m)
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        near.truncate(config.max_polylines);
        for &(_, i) in &near {
            let l = &map.lanelets[i];
            if l.centre_m.len() < 2 {
                continue;
            }
            for p in resample(&l.centre_m, config.polyline_points) {
                polylines.extend_from_slice(&frame.to_norm(p));
            }
            polyline_lanelet_ids.push(l.id);
        }
    }
    let location = match source {
        MapSource::Procedural(name) => format!("procedural_{name}"),
        MapSource::Osm(_) => "osm".into(),
        MapSource::File(name) => name.clone(),
    };
    SceneWindow {
        location,
        file: "request".into(),
        start_frame: 0,
        frame,
        agents: histories.len(),
        steps,
        states,
        valid: vec![true; histories.len() * steps],
        track_ids: agents.iter().map(|a| a.id).collect(),
        agent_types: vec![AgentType::Car; histories.len()],
        length_m: agents.iter().map(|a| a.length_m as f32).collect(),
        width_m: agents.iter().map(|a| a.width_m as f32).collect(),
        polyline_points: config.polyline_points,
        polylines,
        polyline_lanelet_ids,
    }
}

/// A tick's ego, checked and waiting for the scene's next round.
#[derive(Debug, Clone)]
pub struct PendingEgo {
    pub tick: u64,
    /// Per agent index: the external agents' poses.
    pub poses: Vec<Option<SimPose>>,
    pub received: Instant,
}

/// The external driver of one tick: the pending ego's poses, or none (late: the model
/// drives).
struct TickDriver<'a> {
    poses: Option<&'a [Option<SimPose>]>,
}

impl ExternalDriver for TickDriver<'_> {
    fn pose(
        &mut self,
        scene: usize,
        agent: usize,
        tick: usize,
        world: &[SimPose],
    ) -> road_sim::Result<SimPose> {
        self.drive(scene, agent, tick, world)?
            .ok_or_else(|| road_sim::Error::External {
                scene,
                agent,
                reason: format!("tick {tick}: no pose"),
            })
    }

    fn drive(
        &mut self,
        _scene: usize,
        agent: usize,
        _tick: usize,
        _world: &[SimPose],
    ) -> road_sim::Result<Option<SimPose>> {
        Ok(self.poses.and_then(|p| p[agent]))
    }
}

/// What one tick of a scene produced.
#[derive(Debug, Clone)]
pub struct TickOutput {
    pub npc: NpcTick,
    /// Every agent's pose after the tick, by agent index.
    pub poses: Vec<SimPose>,
    /// Which agents are still in the scene (not those that left the map), by agent index.
    pub present: Vec<bool>,
    pub compute_secs: f64,
    /// Every agent by index, when vehicles entered before this tick (for the recording).
    pub agents: Option<Vec<AgentInfo>>,
}

/// A scene being served: its place in its pool, its agents, and where it stands in the tick
/// sequence.
pub struct LiveScene {
    pub id: u64,
    pub client: String,
    pub agents: Vec<AgentInfo>,
    pub map: Option<Arc<LaneletMap>>,
    pub planner_name: String,
    pub checkpoint_name: String,
    /// The pool that simulates it, and its slot there.
    pub pool: PoolKey,
    pub slot: usize,
    /// Every agent's pose after the last tick, by agent index.
    poses: Vec<SimPose>,
    initially_on_road: Vec<bool>,
    index_of: BTreeMap<u32, usize>,
    /// Ticks simulated and published so far.
    pub tick: u64,
    pub max_ticks: u64,
    pub pending: Option<PendingEgo>,
    /// The tick being computed, if any.
    pub in_flight: Option<InFlight>,
    /// When the last tick was published (or the scene created): the late-ego clock.
    pub waiting_since: Instant,
    /// When the client was last heard from (creation, an ego put).
    pub last_heard: Instant,
    /// Since when the server has waited for its client: the first publication after the
    /// client's last word (`None` while the client has had nothing to answer, e.g. during a
    /// long warm-up). Ticks the model drives for want of the ego do not reset it.
    pub awaiting_client_since: Option<Instant>,
    pub late_ticks: u64,
    /// Late ticks since the last tick the client's ego came for.
    pub consecutive_late_ticks: u64,
    /// The scene's secret ([`road_protocol::SceneCreated::token`]).
    pub token: String,
    /// Puts on the scene's key refused for a missing or wrong token.
    pub refused_puts: u64,
    /// Where the scene's positions may be.
    extent: Option<Extent>,
    /// Agents that left the map (driven off a lane's end): no longer in the scene's ticks.
    retired: Vec<bool>,
    /// Vehicles entering at the map's entry lanes, when the scene was created with `inflow`.
    inflow: Option<Inflow>,
    /// The next id an entering vehicle gets (ids are never reused).
    next_id: u32,
    /// Vehicles that entered since the last published tick.
    entered: Vec<AgentInfo>,
    /// n: history steps an entering vehicle brings.
    observed: usize,
}

/// A tick in the pool's batches.
#[derive(Debug, Clone)]
pub struct InFlight {
    /// The tick being computed (one more than the last published).
    pub tick: u64,
    /// The model drives the external agents this tick: the ego did not come in time.
    pub late: bool,
    /// Where its latency runs from: the ego's arrival, or the deadline of a late tick.
    pub started: Instant,
    /// Engine time of the rounds this tick has taken part in (shared with the scenes batched
    /// beside it), seconds.
    pub compute_secs: f64,
    /// Engine time of other scenes' rounds between `started` and the tick's first round,
    /// seconds.
    pub queue_secs: f64,
}

impl std::fmt::Debug for LiveScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveScene")
            .field("id", &self.id)
            .field("client", &self.client)
            .field("tick", &self.tick)
            .field("agents", &self.agents.len())
            .finish_non_exhaustive()
    }
}

impl LiveScene {
    /// Adds the scene to `pool` (its first window, with the seed's noise).
    pub fn new(
        id: u64,
        setup: SceneSetup,
        pool_key: PoolKey,
        pool: &mut Pool,
        token: String,
        now: Instant,
    ) -> crate::Result<Self> {
        let controllers = setup
            .agents
            .iter()
            .map(|a| {
                if a.external {
                    Controller::External
                } else {
                    Controller::Model
                }
            })
            .collect();
        let observed = setup.window.steps;
        let steps = usize::try_from(setup.max_ticks).unwrap_or(usize::MAX);
        let slot = pool.add(
            id,
            SimScene {
                window: setup.window,
                observed_steps: observed,
                controllers,
            },
            &setup.planner,
            setup.map.clone(),
            steps,
            setup.seed,
        )?;
        if setup.plans {
            pool.request_plans(slot, true)?;
        }
        let start: Vec<SimPose> = pool.poses(slot).to_vec();
        let initially_on_road = match &setup.map {
            Some(map) => {
                let off = off_road(&boxes(&setup.agents, &start), map);
                (0..start.len()).map(|a| !off.contains(&a)).collect()
            }
            None => vec![false; start.len()],
        };
        let extent = setup.extent;
        let agent_count = setup.agents.len();
        let inflow = match (setup.inflow, &setup.map) {
            (Some((rate, max_vehicles)), Some(map)) => {
                let inflow = Inflow::new(
                    map,
                    rate,
                    road_rollout::stream_seed(setup.seed, INFLOW_STREAM),
                );
                Some(match max_vehicles {
                    Some(m) => inflow.with_max_vehicles(m as usize),
                    None => inflow,
                })
            }
            _ => None,
        };
        let next_id = setup.agents.iter().map(|a| a.id).max().map_or(1, |m| m + 1);
        Ok(Self {
            id,
            client: setup.client,
            index_of: setup
                .agents
                .iter()
                .enumerate()
                .map(|(i, a)| (a.id, i))
                .collect(),
            agents: setup.agents,
            map: setup.map,
            planner_name: setup.planner_name,
            checkpoint_name: setup.checkpoint_name,
            pool: pool_key,
            slot,
            poses: start,
            initially_on_road,
            tick: 0,
            max_ticks: setup.max_ticks,
            pending: None,
            in_flight: None,
            waiting_since: now,
            last_heard: now,
            awaiting_client_since: None,
            late_ticks: 0,
            consecutive_late_ticks: 0,
            token,
            refused_puts: 0,
            extent,
            retired: vec![false; agent_count],
            inflow,
            next_id,
            entered: Vec::new(),
            observed,
        })
    }

    /// Lets the vehicles in that arrive before the next tick (with `inflow`): each joins the
    /// pool's scene at a retired agent's index or a new one, with a new id. An arrival that
    /// finds the scene at its agent limit is dropped (logged).
    fn admit_arrivals(&mut self, pool: &mut Pool) -> crate::Result<()> {
        let Some(inflow) = self.inflow.as_mut() else {
            return Ok(());
        };
        let arrivals = inflow.arrivals(&pool.footprints(self.slot)?, self.observed);
        for vehicle in arrivals {
            let index = match pool.add_agent(self.slot, &vehicle) {
                Ok(index) => index,
                Err(e) => {
                    tracing::debug!(scene = self.id, "an entering vehicle is dropped: {e}");
                    continue;
                }
            };
            let info = AgentInfo {
                id: self.next_id,
                length_m: vehicle.length_m,
                width_m: vehicle.width_m,
                external: false,
                history: protocol_poses(&vehicle.history),
            };
            self.next_id += 1;
            let pose = *vehicle.history.last().expect("a history has a step");
            if index == self.agents.len() {
                self.agents.push(info.clone());
                self.poses.push(pose);
                self.initially_on_road.push(true);
                self.retired.push(false);
            } else {
                self.index_of.remove(&self.agents[index].id);
                self.agents[index] = info.clone();
                self.poses[index] = pose;
                self.initially_on_road[index] = true;
                self.retired[index] = false;
            }
            self.index_of.insert(info.id, index);
            self.entered.push(info);
        }
        Ok(())
    }

    /// Every agent's pose after the last tick, by agent index.
    pub fn poses(&self) -> &[SimPose] {
        &self.poses
    }

    /// Checks an ego input put on `key_client`'s ego key against the scene: owner, tick
    /// sequence, agents, values, motion.
    pub fn check_ego(
        &self,
        key_client: &str,
        msg: &EgoTick,
        max_speed_mps: f64,
        received: Instant,
    ) -> Result<PendingEgo, ErrorReply> {
        let bad = |code: ErrorCode, field: &str, message: String| ErrorReply {
            scene: Some(self.id),
            tick: Some(msg.tick),
            ..ErrorReply::new(code, Some(field), message)
        };
        let owner = &self.client;
        if key_client != owner {
            return Err(bad(
                ErrorCode::NotOwner,
                "key",
                format!(
                    "scene {} is not client {key_client}'s: this tick came on its ego key",
                    self.id
                ),
            ));
        }
        if msg.client != *owner {
            return Err(bad(
                ErrorCode::NotOwner,
                "client",
                format!(
                    "scene {} is not client {}'s: put ticks under the id that created it",
                    self.id, msg.client
                ),
            ));
        }
        let expected = self.tick + 1;
        if msg.tick <= self.tick {
            return Err(bad(
                ErrorCode::BadTick,
                "tick",
                format!(
                    "tick {} is in the past: the scene has simulated up to tick {}; send tick {expected}",
                    msg.tick, self.tick
                ),
            ));
        }
        if self.in_flight.as_ref().is_some_and(|f| f.tick == msg.tick) {
            return Err(bad(
                ErrorCode::BadTick,
                "tick",
                format!("tick {} was already sent; it is being computed", msg.tick),
            ));
        }
        if let Some(p) = &self.pending {
            if p.tick == msg.tick {
                return Err(bad(
                    ErrorCode::BadTick,
                    "tick",
                    format!(
                        "tick {} was already sent; it runs in the next round",
                        msg.tick
                    ),
                ));
            }
        }
        if msg.tick > expected {
            return Err(bad(
                ErrorCode::BadTick,
                "tick",
                format!("tick {} skips ahead: the next tick is {expected}", msg.tick),
            ));
        }
        if msg.tick > self.max_ticks {
            return Err(bad(
                ErrorCode::BadTick,
                "tick",
                format!(
                    "tick {} is beyond the scene's max_ticks {}",
                    msg.tick, self.max_ticks
                ),
            ));
        }
        let world = self.poses();
        let mut poses: Vec<Option<SimPose>> = vec![None; self.agents.len()];
        let max_step_m = max_speed_mps * STEP_SECS;
        for (i, a) in msg.agents.iter().enumerate() {
            let Some(&index) = self.index_of.get(&a.id) else {
                return Err(bad(
                    ErrorCode::BadTick,
                    &format!("agents[{i}].id"),
                    format!("scene {} has no agent {}", self.id, a.id),
                ));
            };
            if !self.agents[index].external {
                return Err(bad(
                    ErrorCode::BadTick,
                    &format!("agents[{i}].id"),
                    format!(
                        "agent {} is the model's, not external; only external agents are put",
                        a.id
                    ),
                ));
            }
            if poses[index].is_some() {
                return Err(bad(
                    ErrorCode::BadTick,
                    &format!("agents[{i}].id"),
                    format!("agent {} appears twice in the tick", a.id),
                ));
            }
            if let Some((f, why)) = pose_fault(&a.pose(), self.extent.as_ref()) {
                return Err(bad(
                    ErrorCode::InvalidField,
                    &format!("agents[{i}].{f}"),
                    format!("agent {}: {why}", a.id),
                ));
            }
            let from = DVec2::new(world[index].x_m, world[index].y_m);
            let moved_m = from.distance(DVec2::new(a.x_m, a.y_m));
            if moved_m > max_step_m {
                return Err(bad(
                    ErrorCode::InvalidField,
                    &format!("agents[{i}]"),
                    format!(
                        "agent {} moved {moved_m:.1} m in one {STEP_SECS} s step; at most {max_step_m:.1} m ({max_speed_mps} m/s)",
                        a.id
                    ),
                ));
            }
            poses[index] = Some(SimPose {
                x_m: a.x_m,
                y_m: a.y_m,
                heading_rad: a.heading_rad,
            });
        }
        if let Some(missing) = self
            .agents
            .iter()
            .enumerate()
            .find(|(i, a)| a.external && poses[*i].is_none())
        {
            return Err(bad(
                ErrorCode::BadTick,
                "agents",
                format!("the tick lacks external agent {}", missing.1.id),
            ));
        }
        Ok(PendingEgo {
            tick: msg.tick,
            poses,
            received,
        })
    }

    /// Starts the next tick in the pool with the pending ego, or (late: no ego by the
    /// deadline) with the model driving the external agents; `started` is where its latency
    /// runs from, `queue_secs` what it waited for other scenes' rounds since. Clears the
    /// pending ego.
    pub fn begin_tick(
        &mut self,
        pool: &mut Pool,
        started: Instant,
        queue_secs: f64,
    ) -> crate::Result<()> {
        self.admit_arrivals(pool)?;
        let pending = self.pending.take();
        let late = pending.is_none();
        let mut driver = TickDriver {
            poses: pending.as_ref().map(|p| p.poses.as_slice()),
        };
        pool.begin_tick(self.slot, &mut driver)?;
        self.in_flight = Some(InFlight {
            tick: self.tick + 1,
            late,
            started,
            compute_secs: 0.0,
            queue_secs,
        });
        Ok(())
    }

    /// The reply of the tick in flight, from what the pool's round made of it.
    pub fn finish_tick(&mut self, result: &SceneTick) -> crate::Result<TickOutput> {
        let flight = self.in_flight.take().ok_or_else(|| {
            crate::Error::Config(format!(
                "scene {}: a tick finished that was not begun",
                self.id
            ))
        })?;
        // A number the engine could not compute never reaches a client as `null`: the tick
        // fails and the scene closes with an `internal` error.
        let finite =
            |p: &SimPose| p.x_m.is_finite() && p.y_m.is_finite() && p.heading_rad.is_finite();
        if let Some(i) = result.poses.iter().position(|p| !finite(p)) {
            return Err(crate::Error::SceneFailed {
                scene: self.id,
                reason: format!(
                    "the engine computed a non-finite pose for agent {} at tick {}",
                    self.agents[i].id, flight.tick
                ),
            });
        }
        if let Some(i) = result
            .plans
            .iter()
            .position(|plan| !plan.iter().all(finite))
        {
            return Err(crate::Error::SceneFailed {
                scene: self.id,
                reason: format!(
                    "the engine computed a non-finite plan for agent {} at tick {}",
                    self.agents[i].id, flight.tick
                ),
            });
        }
        self.tick = flight.tick;
        self.poses.clone_from(&result.poses);
        let late = flight.late;
        if late {
            self.late_ticks += 1;
            self.consecutive_late_ticks += 1;
        } else {
            self.consecutive_late_ticks = 0;
        }
        let id_of = |i: usize| self.agents[i].id;
        let state = |i: usize| {
            let p = result.poses[i];
            AgentState {
                id: id_of(i),
                x_m: p.x_m,
                y_m: p.y_m,
                heading_rad: p.heading_rad,
            }
        };
        for &a in &result.left {
            self.retired[a] = true;
        }
        let off = match &self.map {
            Some(map) => {
                let mut present = boxes(&self.agents, &result.poses);
                for (a, b) in present.iter_mut().enumerate() {
                    if self.retired[a] {
                        *b = None;
                    }
                }
                let mut off = off_road(&present, map);
                off.retain(|&a| self.initially_on_road[a]);
                off
            }
            None => Vec::new(),
        };
        let npc = NpcTick {
            scene: self.id,
            tick: self.tick,
            time_s: self.tick as f64 * STEP_SECS,
            npcs: (0..self.agents.len())
                .filter(|&i| !self.agents[i].external && !self.retired[i])
                .map(state)
                .collect(),
            left: result.left.iter().map(|&i| id_of(i)).collect(),
            stuck: result.stuck.iter().map(|&i| id_of(i)).collect(),
            entered: std::mem::take(&mut self.entered),
            collisions: result
                .collisions
                .iter()
                .map(|&(i, j)| {
                    let (a, b) = (id_of(i), id_of(j));
                    [a.min(b), a.max(b)]
                })
                .collect(),
            off_road: off.into_iter().map(id_of).collect(),
            late_external: if late {
                (0..self.agents.len())
                    .filter(|&i| self.agents[i].external)
                    .map(state)
                    .collect()
            } else {
                Vec::new()
            },
            plans: result
                .plans
                .iter()
                .enumerate()
                .filter(|&(i, _)| !self.agents[i].external && !self.retired[i])
                .map(|(i, poses)| AgentPlan {
                    id: id_of(i),
                    poses: poses
                        .iter()
                        .map(|p| Pose {
                            x_m: p.x_m,
                            y_m: p.y_m,
                            heading_rad: p.heading_rad,
                        })
                        .collect(),
                })
                .collect(),
            latency_ms: flight.started.elapsed().as_secs_f64() * 1e3,
            compute_ms: flight.compute_secs * 1e3,
            queue_ms: flight.queue_secs * 1e3,
        };
        let agents = (!npc.entered.is_empty()).then(|| self.agents.clone());
        Ok(TickOutput {
            npc,
            poses: result.poses.clone(),
            present: self.retired.iter().map(|gone| !gone).collect(),
            compute_secs: flight.compute_secs,
            agents,
        })
    }
}

fn boxes(agents: &[AgentInfo], poses: &[SimPose]) -> Vec<Option<OrientedBox>> {
    agents
        .iter()
        .zip(poses)
        .map(|(a, &pose)| {
            Some(OrientedBox {
                pose,
                length_m: a.length_m,
                width_m: a.width_m,
            })
        })
        .collect()
}
