//! The closed loop: scenes simulated tick by tick on an engine (the WGSL engine or the candle
//! reference, through [`StepEngine`]), each agent driven by its [`Controller`]. Agents the model
//! does not drive overwrite their emitted states every tick, so the model's agents react to them
//! (math doc: "In closed loop the ego agent's slots are overwritten by the states it reports").
//! Every tick reports poses in metres and infractions.

use std::sync::Arc;

use glam::DVec2;
use rand::rngs::StdRng;
use road_data::tracks::STEP_SECS;
use road_data::{LaneletMap, SceneWindow, wrap_angle};
use road_model::batch::SceneInput;
use road_model::{ModelConfig, Result as ModelResult};
use road_rollout::{RolloutDriver, RolloutScene, StepEngine};
use road_sched::{CollisionGuard, GiveWay, LaneGuard, PlannerSpec, StallRelease, StuckRemoval};

use crate::geometry::OrientedBox;
use crate::infractions::{collisions, off_road};
use crate::{Error, Pose, Result};
use road_planner::collision_guard::GuardAction;
use road_planner::lane_guard::{LaneAction, keep_on_road, nudge_towards_lane};

mod exits;
mod give_way;
mod releases;
mod scripted;

pub use exits::EXIT_LATERAL_MARGIN_M;
use releases::HeldMemory;
use scripted::script;
pub use scripted::{pick_adversary, simulate_scripted};

/// Who drives an agent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Controller {
    /// The model: a reactive NPC.
    Model,
    /// Its logged future step by step; constant velocity where the log ends.
    Replay,
    /// The paper's adversarial agent: its logged path slowed so that it covers only half of it
    /// by the last simulated step.
    Adversarial,
    /// Constant velocity from its last two observed poses.
    ConstantVelocity,
    /// Driven by the caller through [`ExternalDriver`] (an ego stack; the server).
    External,
}

/// One scene to simulate: a window whose first `observed_steps` steps are the history (the last
/// `n` of them the model's observations) and whose later steps are the log, which replayed and
/// adversarial agents follow.
#[derive(Debug, Clone)]
pub struct SimScene {
    pub window: SceneWindow,
    pub observed_steps: usize,
    /// One per agent of the window.
    pub controllers: Vec<Controller>,
}

/// Poses of externally driven agents, asked once per tick before the model steps: the pose the
/// agent will have after the tick. `world` holds every agent's pose after the previous tick.
pub trait ExternalDriver {
    fn pose(&mut self, scene: usize, agent: usize, tick: usize, world: &[Pose]) -> Result<Pose>;

    /// Like [`Self::pose`], but the driver may decline for this tick (`None`): the model then
    /// drives the agent this tick (a server's late ego). The default never declines.
    fn drive(
        &mut self,
        scene: usize,
        agent: usize,
        tick: usize,
        world: &[Pose],
    ) -> Result<Option<Pose>> {
        self.pose(scene, agent, tick, world).map(Some)
    }
}

/// An [`ExternalDriver`] for simulations without external agents: asking it is an error.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoExternal;

impl ExternalDriver for NoExternal {
    fn pose(&mut self, scene: usize, agent: usize, _tick: usize, _world: &[Pose]) -> Result<Pose> {
        Err(Error::External {
            scene,
            agent,
            reason: "the agent is external but the simulation has no external driver".into(),
        })
    }
}

/// A scene's map in a closed loop: borrowed (the evaluation suites and the demo share one map
/// between scenes) or shared (the server's scenes hold their maps by `Arc`, which a pool that
/// lives as long as the server cannot borrow).
#[derive(Debug, Clone)]
pub enum SceneMap<'m> {
    Borrowed(&'m LaneletMap),
    Shared(Arc<LaneletMap>),
}

impl SceneMap<'_> {
    pub fn get(&self) -> &LaneletMap {
        match self {
            SceneMap::Borrowed(map) => map,
            SceneMap::Shared(map) => map,
        }
    }
}

/// How often the guards acted over some ticks, in agent-ticks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct GuardCounts {
    /// The collision guard braked an agent ahead of a predicted collision.
    pub braked: usize,
    /// The collision guard stopped an agent short of an overlap.
    pub stopped_short: usize,
    /// The lane guard turned an agent's step back towards its lane.
    pub steered_to_lane: usize,
    /// The lane guard nudged an agent towards its lane ahead of the road's edge.
    pub nudged_towards_lane: usize,
    /// The lane guard stopped an agent at the road's edge.
    pub stopped_at_road_edge: usize,
    /// The stall release pulled a vehicle away (agent-ticks).
    pub pulled_away: usize,
    /// The deadlock release backed a vehicle off (agent-ticks).
    pub backed_off: usize,
    /// The give-way rule held a vehicle short of its stop line (agent-ticks).
    pub gave_way: usize,
}

impl std::ops::AddAssign for GuardCounts {
    fn add_assign(&mut self, other: Self) {
        self.braked += other.braked;
        self.stopped_short += other.stopped_short;
        self.steered_to_lane += other.steered_to_lane;
        self.nudged_towards_lane += other.nudged_towards_lane;
        self.stopped_at_road_edge += other.stopped_at_road_edge;
        self.pulled_away += other.pulled_away;
        self.backed_off += other.backed_off;
        self.gave_way += other.gave_way;
    }
}

/// How often the guards acted over `ticks`.
pub fn guard_actions(ticks: &[SceneTick]) -> GuardCounts {
    let mut counts = GuardCounts::default();
    for (_, action) in ticks.iter().flat_map(|t| &t.guarded) {
        match action {
            GuardAction::Braked => counts.braked += 1,
            GuardAction::StoppedShort => counts.stopped_short += 1,
            GuardAction::SteeredToLane => counts.steered_to_lane += 1,
            GuardAction::NudgedTowardsLane => counts.nudged_towards_lane += 1,
            GuardAction::StoppedAtRoadEdge => counts.stopped_at_road_edge += 1,
            GuardAction::PulledAway => counts.pulled_away += 1,
            GuardAction::BackedOff => counts.backed_off += 1,
            GuardAction::GaveWay => counts.gave_way += 1,
        }
    }
    counts
}

/// What one tick did in one scene.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct SceneTick {
    /// Every agent's pose after the tick, metres and radians (heading wrapped to (−π, π]).
    pub poses: Vec<Pose>,
    /// Overlapping pairs `(i, j)`, `i < j`, not counting pairs that already overlapped at the
    /// last observed step (overlaps in the log itself, e.g. at standstill in a queue).
    pub collisions: Vec<(usize, usize)>,
    /// Agents whose centre is outside every lanelet but was inside one at the last observed
    /// step (agents that start off the map, in a parking lot say, are not counted).
    pub off_road: Vec<usize>,
    /// Model-driven agents whose step the lane guard, then the collision guard, changed this
    /// tick (empty when the planner has neither).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub guarded: Vec<(usize, GuardAction)>,
    /// When requested ([`ClosedLoop::request_plans`]): every agent's plan, the model's
    /// estimate of its poses at the steps after this one (metres, radians), one list per agent.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub plans: Vec<Vec<Pose>>,
    /// With [`ClosedLoop::retire_on_exit`]: agents that drove off the map through an open lane
    /// end this tick (the end of a lane with no successor, or the start of one with no
    /// predecessor: the map's edge). They are retired: from now on
    /// their pose is held, they count in no collision or off-road check, and the model no
    /// longer simulates them. Leaving the map is not an off-road event.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub left: Vec<usize>,
    /// Those of [`Self::left`] taken out of the scene by the planner's stuck removal
    /// (`road_sched::StuckRemoval`): they stood stuck, not at the map's end.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stuck: Vec<usize>,
}

struct SceneRuntime<'m> {
    window: SceneWindow,
    controllers: Vec<Controller>,
    /// Scripted poses (replay, adversarial, constant velocity) `[agent][tick]`; empty for model
    /// and external agents.
    scripted: Vec<Vec<Pose>>,
    /// Poses after the last tick, one per agent.
    poses: Vec<Pose>,
    /// Unwrapped heading of every agent after the last tick (model units need continuity).
    heading_unwrapped: Vec<f64>,
    /// Overrides of this tick, model units, `None` = the model's state stands.
    overrides: Vec<Option<[f32; 3]>>,
    initial_overlaps: Vec<(usize, usize)>,
    initially_on_road: Vec<bool>,
    /// What the lane and collision guards did in the last tick.
    guarded: Vec<(usize, GuardAction)>,
    map: Option<SceneMap<'m>>,
    /// Ticks the scene was built for (its scripts' length).
    steps: usize,
    /// Whether agents that drive off the map's lane ends are retired (see [`SceneTick::left`]).
    retire_on_exit: bool,
    /// Agents retired so far, and those retired this tick.
    retired: Vec<bool>,
    left: Vec<usize>,
    /// Those of `left` taken out stuck this tick.
    stuck: Vec<usize>,
    /// The lanelet each agent was last on (a map exit is the end of a lanelet without
    /// successors).
    last_lanelet: Vec<Option<usize>>,
    /// What the stall release and the deadlock release remember of each agent.
    held: Vec<HeldMemory>,
    /// Each agent's speed over the last tick (m/s).
    speed_mps: Vec<f64>,
    /// Whether this tick's planner keeps vehicles on the road (a lane guard, with a map): only
    /// then does a back-off over the road's edge make no room.
    keeps_on_road: bool,
}

/// Simulates many scenes on one engine: in lockstep with one planner ([`ClosedLoop::new`],
/// [`ClosedLoop::tick`]), or as a pool that scenes join and leave, each ticking when its
/// caller asks, one batched round at a time ([`ClosedLoop::pool`], [`ClosedLoop::add_scene`],
/// [`ClosedLoop::begin_tick`], [`ClosedLoop::round`]).
pub struct ClosedLoop<'m> {
    driver: RolloutDriver,
    /// One per driver slot; `None`: a free slot of a pool.
    scenes: Vec<Option<SceneRuntime<'m>>>,
    model: ModelConfig,
    heading_scale: f64,
    /// Per scene slot, its planner's guards (scratch of [`Self::round`]).
    guards: Vec<Layers>,
}

/// A planner's closed-loop layers after the model, each off when absent.
#[derive(Debug, Clone, Copy, Default)]
struct Layers {
    lane_guard: Option<LaneGuard>,
    collision_guard: Option<CollisionGuard>,
    stall_release: Option<StallRelease>,
    stuck_removal: Option<StuckRemoval>,
    give_way: Option<GiveWay>,
}

impl std::fmt::Debug for ClosedLoop<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClosedLoop")
            .field("scenes", &self.scenes.len())
            .field("driver", &self.driver)
            .finish_non_exhaustive()
    }
}

fn boxes(window: &SceneWindow, poses: &[Pose]) -> Vec<Option<OrientedBox>> {
    poses
        .iter()
        .enumerate()
        .map(|(a, &pose)| {
            Some(OrientedBox {
                pose,
                length_m: f64::from(window.length_m[a]),
                width_m: f64::from(window.width_m[a]),
            })
        })
        .collect()
}

/// Checks a scene against its window (one controller per agent, `min_observed` ≤ observed
/// steps ≤ window steps, every agent present at the last observed step) and returns the poses
/// at that step. Errors name the scene by its recording and frame.
fn start_poses(scene: &SimScene, min_observed: usize) -> Result<Vec<Pose>> {
    let w = &scene.window;
    let label = || format!("{} {} frame {}", w.location, w.file, w.start_frame);
    if scene.controllers.len() != w.agents {
        return Err(Error::Config(format!(
            "{}: {} controllers for {} agents",
            label(),
            scene.controllers.len(),
            w.agents
        )));
    }
    if scene.observed_steps < min_observed.max(1) || scene.observed_steps > w.steps {
        return Err(Error::Config(format!(
            "{}: {} observed steps; at least {} needed and the window has {}",
            label(),
            scene.observed_steps,
            min_observed.max(1),
            w.steps
        )));
    }
    let reference = scene.observed_steps - 1;
    (0..w.agents)
        .map(|a| {
            crate::window_pose(w, a, reference).ok_or_else(|| {
                Error::Config(format!(
                    "{}: agent {a} (track {}) is absent at the last observed step",
                    label(),
                    w.track_ids[a]
                ))
            })
        })
        .collect()
}

impl<'m> ClosedLoop<'m> {
    /// Builds the first windows of every scene on `engine` (`rng` seeds the scenes' noise). `maps[i]` (when given) is scene
    /// `i`'s lanelet map for the off-road check. Every agent must be present at the last
    /// observed step.
    pub fn new(
        engine: &mut dyn StepEngine,
        model: &ModelConfig,
        planner: &PlannerSpec,
        scenes: Vec<SimScene>,
        maps: Vec<Option<&'m LaneletMap>>,
        steps: usize,
        rng: &mut StdRng,
    ) -> Result<Self> {
        let seeds = road_rollout::batch_seeds(rng, scenes.len());
        Self::with_seeds(engine, model, planner, scenes, maps, steps, &seeds)
    }

    /// [`Self::new`] with scene `i`'s noise stream seeded by `seeds[i]`
    /// (`road_rollout::stream_seed` names streams independently of the batch).
    pub fn with_seeds(
        engine: &mut dyn StepEngine,
        model: &ModelConfig,
        planner: &PlannerSpec,
        scenes: Vec<SimScene>,
        maps: Vec<Option<&'m LaneletMap>>,
        steps: usize,
        seeds: &[u64],
    ) -> Result<Self> {
        if maps.len() != scenes.len() {
            return Err(Error::Config(format!(
                "{} maps for {} scenes",
                maps.len(),
                scenes.len()
            )));
        }
        let n = planner.obs_slots;
        let mut inputs = Vec::with_capacity(scenes.len());
        let mut runtimes = Vec::with_capacity(scenes.len());
        for (i, (scene, map)) in scenes.into_iter().zip(maps).enumerate() {
            let (input, runtime) =
                SceneRuntime::new(scene, map.map(SceneMap::Borrowed), model, n, steps).map_err(
                    |e| match e {
                        Error::Config(m) => Error::Config(format!("scene {i}: {m}")),
                        other => other,
                    },
                )?;
            inputs.push(input);
            runtimes.push(Some(runtime));
        }
        let driver = RolloutDriver::with_seeds(engine, planner, &inputs, seeds, steps)?;
        Ok(Self {
            driver,
            scenes: runtimes,
            model: model.clone(),
            heading_scale: model.heading_scale,
            guards: Vec::new(),
        })
    }

    /// An empty pool of `capacity` scenes of at most `agents` agents on `engine`, for scenes
    /// under planners with `planner`'s window, observations and noise (see
    /// [`RolloutDriver::with_capacity`]); the map room is the model's.
    pub fn pool(
        engine: &mut dyn StepEngine,
        model: &ModelConfig,
        planner: &PlannerSpec,
        capacity: usize,
        agents: usize,
    ) -> Result<Self> {
        let driver = RolloutDriver::with_capacity(
            engine,
            planner,
            capacity,
            agents,
            model.map_polylines,
            model.polyline_points,
        )?;
        Ok(Self {
            driver,
            scenes: (0..capacity).map(|_| None).collect(),
            model: model.clone(),
            heading_scale: model.heading_scale,
            guards: Vec::new(),
        })
    }

    /// Adds `scene` to a pool for `steps` ticks under `planner`, its noise seeded with `seed`
    /// (its samples do not depend on the other scenes of the pool); `map` for the off-road
    /// check and the lane guard. Returns its index. Its first tick takes the planner's warm-up.
    pub fn add_scene(
        &mut self,
        engine: &mut dyn StepEngine,
        scene: SimScene,
        planner: &PlannerSpec,
        map: Option<SceneMap<'m>>,
        steps: usize,
        seed: u64,
    ) -> Result<usize> {
        let (input, runtime) =
            SceneRuntime::new(scene, map, &self.model, planner.obs_slots, steps)?;
        let index = self.driver.add_scene(engine, &input, planner, seed)?;
        self.scenes[index] = Some(runtime);
        Ok(index)
    }

    /// Removes scene `scene` from a pool (a tick in progress is dropped).
    pub fn remove_scene(&mut self, scene: usize) -> Result<()> {
        self.driver.remove_scene(scene)?;
        self.scenes[scene] = None;
        Ok(())
    }

    /// Scene slots; in a pool, free ones included.
    pub fn scenes(&self) -> usize {
        self.scenes.len()
    }

    /// Scenes simulated now.
    pub fn live_scenes(&self) -> usize {
        self.driver.live_scenes()
    }

    /// Ticks done so far (scene 0's: every scene's in lockstep).
    pub fn ticks(&self) -> usize {
        self.driver.ticks()
    }

    /// Ticks scene `scene` has done so far.
    pub fn scene_ticks(&self, scene: usize) -> usize {
        self.driver.scene_ticks(scene)
    }

    /// Model evaluations per scene so far.
    pub fn nfe(&self) -> Result<u64> {
        Ok(self.driver.nfe()?)
    }

    /// Switches every scene to another planner on the same checkpoint (same W and n), from the
    /// next tick on; see [`RolloutDriver::switch_planner`].
    pub fn switch_planner(&mut self, planner: &PlannerSpec) -> Result<()> {
        Ok(self.driver.switch_planner(planner)?)
    }

    /// The planner the next tick uses.
    pub fn planner(&self) -> &PlannerSpec {
        self.driver.planner()
    }

    /// Scene `scene`'s runtime, borrowed from `scenes` alone (the driver stays free to use).
    fn runtime_mut<'s>(
        scenes: &'s mut [Option<SceneRuntime<'m>>],
        scene: usize,
    ) -> Result<&'s mut SceneRuntime<'m>> {
        scenes
            .get_mut(scene)
            .and_then(Option::as_mut)
            .ok_or_else(|| Error::Config(format!("no scene {scene} in the simulation")))
    }

    fn runtime(&self, scene: usize) -> Result<&SceneRuntime<'m>> {
        self.scenes
            .get(scene)
            .and_then(Option::as_ref)
            .ok_or_else(|| Error::Config(format!("no scene {scene} in the simulation")))
    }

    /// Poses after the last tick (the last observed step before the first), per agent.
    pub fn poses(&self, scene: usize) -> &[Pose] {
        &self.runtime(scene).expect("a live scene").poses
    }

    /// Starts scene `scene`'s next tick: agents the model does not drive decide first (they
    /// react to the last tick's world; `external` gives the external ones), then the model's
    /// part is computed by [`Self::round`].
    pub fn begin_tick(&mut self, scene: usize, external: &mut dyn ExternalDriver) -> Result<()> {
        let tick = self.driver.scene_ticks(scene);
        let heading_scale = self.heading_scale;
        let s = Self::runtime_mut(&mut self.scenes, scene)?;
        if tick >= s.steps {
            return Err(Error::Config(format!(
                "scene {scene}: the simulation was built for {} steps",
                s.steps
            )));
        }
        for a in 0..s.controllers.len() {
            let pose = match s.controllers[a] {
                Controller::Model => None,
                Controller::External => {
                    let p = external.drive(scene, a, tick, &s.poses)?;
                    if let Some(p) = p {
                        if !(p.x_m.is_finite() && p.y_m.is_finite() && p.heading_rad.is_finite()) {
                            return Err(Error::External {
                                scene,
                                agent: a,
                                reason: format!("tick {tick}: pose {p:?} is not finite"),
                            });
                        }
                    }
                    p
                }
                _ => Some(s.scripted[a][tick]),
            };
            s.overrides[a] = pose.map(|p| {
                let heading = s.heading_unwrapped[a]
                    + f64::from(wrap_angle((p.heading_rad - s.heading_unwrapped[a]) as f32));
                let xy = s.window.frame.to_norm([p.x_m, p.y_m]);
                [xy[0], xy[1], (heading * heading_scale) as f32]
            });
        }
        Ok(self.driver.request_tick(scene)?)
    }

    /// Scenes with a tick begun and not yet finished.
    pub fn ticks_in_progress(&self) -> usize {
        self.driver.ticks_in_progress()
    }

    /// One batched round of every tick in progress (one engine step); `out` receives the
    /// scenes whose tick finished, with what it did.
    pub fn round(
        &mut self,
        engine: &mut dyn StepEngine,
        out: &mut Vec<(usize, SceneTick)>,
    ) -> Result<()> {
        out.clear();
        // Each scene's guard, read before the driver is borrowed for the round.
        self.guards.clear();
        self.guards.extend((0..self.scenes.len()).map(|i| {
            self.driver
                .scene_planner(i)
                .map_or(Layers::default(), |p| Layers {
                    lane_guard: p.lane_guard,
                    collision_guard: p.collision_guard,
                    stall_release: p.stall_release,
                    stuck_removal: p.stuck_removal,
                    give_way: p.give_way,
                })
        }));
        let (scenes, guards) = (&mut self.scenes, &self.guards);
        let heading_scale = self.heading_scale;
        let done = self.driver.round(engine, &mut |i: usize,
                                                    emitted: &mut [f32],
                                                    plan_turns: &mut [f32]|
         -> ModelResult<()> {
            let s = scenes[i].as_mut().expect("the driver ticks live scenes");
            s.apply(emitted, plan_turns, heading_scale, guards[i]);
            Ok(())
        })?;
        for i in done {
            let s = self.scenes[i]
                .as_ref()
                .expect("the driver ticks live scenes");
            let mut report = s.report();
            for &a in &report.left {
                self.driver.retire_agent(i, a)?;
            }
            if let Some((steps, plan)) = self.driver.plan(i) {
                report.plans = s.plan_poses(steps, plan, heading_scale);
            }
            out.push((i, report));
        }
        Ok(())
    }

    /// Whether agents of scene `scene` that drive off the map through the end of a lane leave
    /// the scene ([`SceneTick::left`]) instead of driving on into the void (off by default:
    /// the paper's suites keep every agent for their 4 s).
    pub fn retire_on_exit(&mut self, scene: usize, on: bool) -> Result<()> {
        self.scenes
            .get_mut(scene)
            .and_then(Option::as_mut)
            .ok_or_else(|| Error::Config(format!("no scene {scene}")))?
            .retire_on_exit = on;
        Ok(())
    }

    /// A model-driven vehicle joins scene `scene` between its ticks (inflow at an entry lane;
    /// [`crate::populate`]): `vehicle`'s history, in metres, becomes its observations. It takes
    /// a retired agent's index when there is one, else a new one while the batch has room
    /// ([`RolloutDriver::admit_agent`]: the scene's next tick takes the warm-up). Returns its
    /// index.
    pub fn add_agent(
        &mut self,
        engine: &mut dyn StepEngine,
        scene: usize,
        vehicle: &crate::populate::PlacedVehicle,
    ) -> Result<usize> {
        let heading_scale = self.heading_scale;
        let s = Self::runtime_mut(&mut self.scenes, scene)?;
        let mut previous: Option<f64> = None;
        let history: Vec<[f32; 3]> = vehicle
            .history
            .iter()
            .map(|p| {
                let heading = match previous {
                    None => f64::from(wrap_angle(p.heading_rad as f32)),
                    Some(prev) => prev + f64::from(wrap_angle((p.heading_rad - prev) as f32)),
                };
                previous = Some(heading);
                let xy = s.window.frame.to_norm([p.x_m, p.y_m]);
                [xy[0], xy[1], (heading * heading_scale) as f32]
            })
            .collect();
        let features = road_model::batch::agent_features(
            &[vehicle.length_m as f32],
            &[vehicle.width_m as f32],
            &[road_data::AgentType::Car],
        );
        let agent = self
            .driver
            .admit_agent(engine, scene, &history, &features)?;
        let pose = *vehicle.history.last().expect("a history has a step");
        let lanelet = s
            .map
            .as_ref()
            .and_then(|m| m.get().lanelet_at([pose.x_m, pose.y_m]));
        let w = &mut s.window;
        let track_id = w.track_ids.iter().copied().max().map_or(1, |m| m + 1);
        if agent == w.agents {
            w.agents += 1;
            w.states.extend(std::iter::repeat_n(0.0, 3 * w.steps));
            w.valid.extend(std::iter::repeat_n(false, w.steps));
            w.track_ids.push(track_id);
            w.agent_types.push(road_data::AgentType::Car);
            w.length_m.push(vehicle.length_m as f32);
            w.width_m.push(vehicle.width_m as f32);
            s.controllers.push(Controller::Model);
            s.scripted.push(Vec::new());
            s.poses.push(pose);
            s.heading_unwrapped
                .push(previous.unwrap_or(pose.heading_rad));
            s.overrides.push(None);
            s.initially_on_road.push(true);
            s.retired.push(false);
            s.last_lanelet.push(lanelet);
            s.held.push(HeldMemory::default());
            s.speed_mps.push(vehicle.speed_mps);
        } else {
            // A retired agent's place: its log is not this vehicle's.
            w.states[3 * agent * w.steps..3 * (agent + 1) * w.steps].fill(0.0);
            w.valid[agent * w.steps..(agent + 1) * w.steps].fill(false);
            w.track_ids[agent] = track_id;
            w.agent_types[agent] = road_data::AgentType::Car;
            w.length_m[agent] = vehicle.length_m as f32;
            w.width_m[agent] = vehicle.width_m as f32;
            s.controllers[agent] = Controller::Model;
            s.scripted[agent] = Vec::new();
            s.poses[agent] = pose;
            s.heading_unwrapped[agent] = previous.unwrap_or(pose.heading_rad);
            s.overrides[agent] = None;
            s.initially_on_road[agent] = true;
            s.retired[agent] = false;
            s.last_lanelet[agent] = lanelet;
            s.held[agent] = HeldMemory::default();
            s.speed_mps[agent] = vehicle.speed_mps;
        }
        Ok(agent)
    }

    /// Where the present (not retired) agents of scene `scene` are now, with their sizes:
    /// what an entering vehicle keeps clear of.
    pub fn footprints(&self, scene: usize) -> Result<Vec<crate::populate::Footprint>> {
        let s = self.runtime(scene)?;
        Ok((0..s.poses.len())
            .filter(|&a| !s.retired[a])
            .map(|a| crate::populate::Footprint {
                pose: s.poses[a],
                length_m: f64::from(s.window.length_m[a]),
                width_m: f64::from(s.window.width_m[a]),
            })
            .collect())
    }

    /// Agents of scene `scene` present now (not retired).
    pub fn present_agents(&self, scene: usize) -> Result<usize> {
        Ok(self.runtime(scene)?.retired.iter().filter(|&&r| !r).count())
    }

    /// Whether scene `scene`'s ticks report every agent's plan ([`SceneTick::plans`]): one
    /// more readback per tick, of that scene's window estimate. Off when a scene joins.
    pub fn request_plans(&mut self, scene: usize, on: bool) -> Result<()> {
        self.runtime(scene)?;
        Ok(self.driver.request_plans(scene, on)?)
    }

    /// One simulated step of every scene; `out` receives one [`SceneTick`] per scene, in scene
    /// order.
    pub fn tick(
        &mut self,
        engine: &mut dyn StepEngine,
        external: &mut dyn ExternalDriver,
        out: &mut Vec<SceneTick>,
    ) -> Result<()> {
        let live: Vec<usize> = (0..self.scenes.len())
            .filter(|&i| self.scenes[i].is_some())
            .collect();
        for &i in &live {
            self.begin_tick(i, external)?;
        }
        let mut finished: Vec<Option<SceneTick>> = vec![None; self.scenes.len()];
        let mut round = Vec::new();
        let mut waiting = live.len();
        while waiting > 0 {
            self.round(engine, &mut round)?;
            if round.is_empty() && self.driver.ticks_in_progress() == 0 {
                return Err(Error::Config(format!(
                    "{waiting} scenes did not finish their tick"
                )));
            }
            for (i, t) in round.drain(..) {
                finished[i] = Some(t);
                waiting -= 1;
            }
        }
        out.clear();
        out.extend(live.into_iter().filter_map(|i| finished[i].take()));
        Ok(())
    }
}

impl<'m> SceneRuntime<'m> {
    /// The runtime of `scene` and the model's input, checked (see [`start_poses`]).
    fn new(
        scene: SimScene,
        map: Option<SceneMap<'m>>,
        model: &ModelConfig,
        n: usize,
        steps: usize,
    ) -> Result<(RolloutScene, Self)> {
        let poses = start_poses(&scene, n)?;
        let w = &scene.window;
        let reference = scene.observed_steps - 1;
        let scripted = (0..w.agents)
            .map(|a| script(w, a, reference, steps, scene.controllers[a]))
            .collect();
        let initial_boxes = boxes(w, &poses);
        let initially_on_road = match &map {
            Some(map) => {
                let off = off_road(&initial_boxes, map.get());
                (0..w.agents).map(|a| !off.contains(&a)).collect()
            }
            None => vec![false; w.agents],
        };
        let input = RolloutScene {
            history: SceneInput::from_window(w, scene.observed_steps - n, n, model),
        };
        let agents = w.agents;
        // Where each agent starts: one placed a step before a lane's open end leaves the map on
        // its first step (a populated scene's vehicle drove on off road for good).
        let last_lanelet = match &map {
            Some(map) => poses
                .iter()
                .map(|p| map.get().lanelet_at([p.x_m, p.y_m]))
                .collect(),
            None => vec![None; agents],
        };
        // Each agent's speed over its last observed step.
        let speed_mps = (0..agents)
            .map(|a| {
                match (
                    crate::window_pose(w, a, reference.saturating_sub(1)),
                    reference,
                ) {
                    (Some(p), 1..) => (poses[a].position_m() - p.position_m()).length() / STEP_SECS,
                    _ => 0.0,
                }
            })
            .collect();
        Ok((
            input,
            Self {
                heading_unwrapped: poses.iter().map(|p| p.heading_rad).collect(),
                initial_overlaps: collisions(&initial_boxes),
                initially_on_road,
                guarded: Vec::new(),
                overrides: vec![None; w.agents],
                poses,
                scripted,
                controllers: scene.controllers,
                window: scene.window,
                retire_on_exit: false,
                retired: vec![false; agents],
                left: Vec::new(),
                stuck: Vec::new(),
                last_lanelet,
                held: vec![HeldMemory::default(); agents],
                speed_mps,
                map,
                steps,
                keeps_on_road: false,
            },
        ))
    }

    /// The model's emitted states `[agents·3]` (model units) with this tick's overrides put
    /// in, then the lane guard's and the collision guard's changes to model-driven agents
    /// (when the planner has them; the collision guard last, so that nobody steers into
    /// another); the poses after the tick follow from them. The lane guard's steers and nudges
    /// turn the agents' plans where it says so (`plan_turns [agents·4]`, the driver's).
    fn apply(
        &mut self,
        emitted: &mut [f32],
        plan_turns: &mut [f32],
        heading_scale: f64,
        layers: Layers,
    ) {
        let Layers {
            lane_guard,
            collision_guard,
            stall_release,
            stuck_removal,
            give_way,
        } = layers;
        for (a, o) in self.overrides.iter().enumerate() {
            if let Some(state) = o {
                emitted[3 * a..3 * a + 3].copy_from_slice(state);
            }
        }
        // A retired agent stays where it left: the model's states for it are padding.
        for a in (0..self.retired.len()).filter(|&a| self.retired[a]) {
            let xy = self
                .window
                .frame
                .to_norm([self.poses[a].x_m, self.poses[a].y_m]);
            let heading = (self.heading_unwrapped[a] * heading_scale) as f32;
            emitted[3 * a..3 * a + 3].copy_from_slice(&[xy[0], xy[1], heading]);
        }
        self.guarded.clear();
        self.left.clear();
        self.stuck.clear();
        self.keeps_on_road = lane_guard.is_some() && self.map.is_some();
        if let Some(release) = stall_release {
            self.release_stalls(emitted, heading_scale, release);
        }
        self.back_off(emitted, heading_scale, stall_release.is_some());
        if let (Some(guard), Some(map)) = (lane_guard, self.map.clone()) {
            self.keep_on_road(emitted, plan_turns, heading_scale, guard, map.get());
        }
        if let (Some(rule), Some(map)) = (give_way, self.map.clone()) {
            self.give_way(emitted, heading_scale, rule, map.get());
        }
        if let Some(guard) = collision_guard {
            self.guard(emitted, heading_scale, guard);
        }
        for a in 0..self.controllers.len() {
            let p = self
                .window
                .frame
                .to_metres([emitted[3 * a], emitted[3 * a + 1]]);
            self.speed_mps[a] = (DVec2::from(p) - self.poses[a].position_m()).length() / STEP_SECS;
            let heading = f64::from(emitted[3 * a + 2]) / heading_scale;
            self.heading_unwrapped[a] = heading;
            self.poses[a] = Pose {
                x_m: p[0],
                y_m: p[1],
                heading_rad: f64::from(wrap_angle(heading as f32)),
            };
        }
        self.track_still();
        if self.retire_on_exit {
            if let Some(removal) = stuck_removal {
                self.remove_stuck(removal);
            }
            if let Some(map) = self.map.clone() {
                self.retire_exits(map.get());
            }
        }
    }

    /// Runs the lane guard on this tick's states (model units, overrides in) of the model-driven
    /// agents: poses before the tick are `self.poses` (headings unwrapped), after it `emitted`.
    /// With `guard.anticipation` it nudges agents bound to leave the road; with
    /// `guard.turn_plan`, a steered or nudged agent's plan turns about its position before the
    /// tick by the angle its step turned (`plan_turns`).
    fn keep_on_road(
        &mut self,
        emitted: &mut [f32],
        plan_turns: &mut [f32],
        heading_scale: f64,
        guard: LaneGuard,
        map: &LaneletMap,
    ) {
        let frame = &self.window.frame;
        for a in 0..self.controllers.len() {
            if self.controllers[a] != Controller::Model
                || self.overrides[a].is_some()
                || self.retired[a]
            {
                continue;
            }
            let before = Pose {
                heading_rad: self.heading_unwrapped[a],
                ..self.poses[a]
            };
            let p = frame.to_metres([emitted[3 * a], emitted[3 * a + 1]]);
            let mut proposed = Pose {
                x_m: p[0],
                y_m: p[1],
                heading_rad: f64::from(emitted[3 * a + 2]) / heading_scale,
            };
            let model_step = DVec2::new(proposed.x_m - before.x_m, proposed.y_m - before.y_m);
            let action = match keep_on_road(
                map,
                before,
                &mut proposed,
                guard.lookahead_m,
                guard.keep_off_opposing_lanes,
            ) {
                Some(LaneAction::Steered) => GuardAction::SteeredToLane,
                Some(LaneAction::StoppedAtEdge) => GuardAction::StoppedAtRoadEdge,
                None => match guard.anticipation {
                    Some(anticipation)
                        if nudge_towards_lane(
                            map,
                            before,
                            &mut proposed,
                            guard.lookahead_m,
                            anticipation,
                            guard.keep_off_opposing_lanes,
                        ) =>
                    {
                        GuardAction::NudgedTowardsLane
                    }
                    _ => continue,
                },
            };
            if guard.turn_plan
                && matches!(
                    action,
                    GuardAction::SteeredToLane | GuardAction::NudgedTowardsLane
                )
            {
                let steered_step = DVec2::new(proposed.x_m - before.x_m, proposed.y_m - before.y_m);
                let angle_rad = model_step.angle_to(steered_step);
                let pivot = frame.to_norm([before.x_m, before.y_m]);
                plan_turns[4 * a..4 * a + 4].copy_from_slice(&[
                    pivot[0],
                    pivot[1],
                    angle_rad as f32,
                    (angle_rad * heading_scale) as f32,
                ]);
            }
            self.guarded.push((a, action));
            set_emitted(
                emitted,
                a,
                frame,
                proposed.position_m(),
                proposed.heading_rad,
                heading_scale,
            );
            // A stop at the edge lands within micrometres of it, and the model's f32 units can
            // round it over (issue 39's long sessions counted such off-road events): it stays
            // where it stood instead.
            if action == GuardAction::StoppedAtRoadEdge
                && map
                    .lanelet_at(frame.to_metres([emitted[3 * a], emitted[3 * a + 1]]))
                    .is_none()
            {
                set_emitted(
                    emitted,
                    a,
                    frame,
                    before.position_m(),
                    proposed.heading_rad,
                    heading_scale,
                );
            }
        }
    }

    /// A plan `[agents, steps, 3]` in model units as poses per agent (headings continue
    /// from the agent's pose after the tick, then wrap).
    fn plan_poses(&self, steps: usize, plan: &[f32], heading_scale: f64) -> Vec<Vec<Pose>> {
        (0..self.controllers.len())
            .map(|a| {
                (0..steps)
                    .map(|t| {
                        let k = 3 * (a * steps + t);
                        let p = self.window.frame.to_metres([plan[k], plan[k + 1]]);
                        Pose {
                            x_m: p[0],
                            y_m: p[1],
                            heading_rad: f64::from(wrap_angle(
                                (f64::from(plan[k + 2]) / heading_scale) as f32,
                            )),
                        }
                    })
                    .collect()
            })
            .collect()
    }

    /// The poses after the tick and its infractions.
    fn report(&self) -> SceneTick {
        let mut b = boxes(&self.window, &self.poses);
        for (a, gone) in self.retired.iter().enumerate() {
            if *gone {
                b[a] = None;
            }
        }
        let mut hits = collisions(&b);
        hits.retain(|pair| !self.initial_overlaps.contains(pair));
        let mut off = self
            .map
            .as_ref()
            .map(|m| off_road(&b, m.get()))
            .unwrap_or_default();
        off.retain(|&a| self.initially_on_road[a]);
        SceneTick {
            poses: self.poses.clone(),
            collisions: hits,
            off_road: off,
            guarded: self.guarded.clone(),
            plans: Vec::new(),
            left: self.left.clone(),
            stuck: self.stuck.clone(),
        }
    }
}

/// Agent `a`'s emitted state (model units, `[agents·3]`) set to `at` (metres) and `heading_rad`
/// (unwrapped).
fn set_emitted(
    emitted: &mut [f32],
    a: usize,
    frame: &road_data::SceneFrame,
    at: DVec2,
    heading_rad: f64,
    heading_scale: f64,
) {
    let xy = frame.to_norm(at.into());
    emitted[3 * a..3 * a + 3].copy_from_slice(&[
        xy[0],
        xy[1],
        (heading_rad * heading_scale) as f32,
    ]);
}
