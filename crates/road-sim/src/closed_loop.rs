//! The closed loop: scenes simulated tick by tick on an engine (the WGSL engine or the candle
//! reference, through [`StepEngine`]), each agent driven by its [`Controller`]. Agents the model
//! does not drive overwrite their emitted states every tick, so the model's agents react to them
//! (math doc: "In closed loop the ego agent's slots are overwritten by the states it reports").
//! Every tick reports poses in metres and infractions.

use rand::rngs::StdRng;
use road_data::{LaneletMap, SceneWindow, wrap_angle};
use road_model::batch::SceneInput;
use road_model::sample::{RolloutDriver, RolloutScene, StepEngine};
use road_model::{ModelConfig, Result as ModelResult};
use road_sched::PlannerSpec;

use crate::controllers::{constant_velocity, slowed_replay};
use crate::geometry::OrientedBox;
use crate::infractions::{collisions, off_road};
use crate::{Error, Pose, Result};

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

/// What one tick did in one scene.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SceneTick {
    /// Every agent's pose after the tick, metres and radians (heading wrapped to (−π, π]).
    pub poses: Vec<Pose>,
    /// Overlapping pairs `(i, j)`, `i < j`, not counting pairs that already overlapped at the
    /// last observed step (overlaps in the log itself, e.g. at standstill in a queue).
    pub collisions: Vec<(usize, usize)>,
    /// Agents whose centre is outside every lanelet but was inside one at the last observed
    /// step (agents that start off the map, in a parking lot say, are not counted).
    pub off_road: Vec<usize>,
}

struct SceneRuntime {
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
}

/// Simulates many scenes in lockstep with one planner on one engine.
pub struct ClosedLoop<'m> {
    driver: RolloutDriver,
    scenes: Vec<SceneRuntime>,
    maps: Vec<Option<&'m LaneletMap>>,
    heading_scale: f64,
    steps: usize,
}

impl std::fmt::Debug for ClosedLoop<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClosedLoop")
            .field("scenes", &self.scenes.len())
            .field("steps", &self.steps)
            .field("driver", &self.driver)
            .finish_non_exhaustive()
    }
}

fn pose_of(window: &SceneWindow, agent: usize, step: usize) -> Option<Pose> {
    window.state(agent, step).map(|s| {
        let p = window.frame.to_metres([s[0], s[1]]);
        Pose {
            x_m: p[0],
            y_m: p[1],
            heading_rad: f64::from(s[2]),
        }
    })
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
            pose_of(w, a, reference).ok_or_else(|| {
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
        for (i, scene) in scenes.into_iter().enumerate() {
            let poses = start_poses(&scene, n).map_err(|e| match e {
                Error::Config(m) => Error::Config(format!("scene {i}: {m}")),
                other => other,
            })?;
            let w = &scene.window;
            let reference = scene.observed_steps - 1;
            let scripted = (0..w.agents)
                .map(|a| script(w, a, reference, steps, scene.controllers[a]))
                .collect();
            let initial_boxes = boxes(w, &poses);
            let initially_on_road = match maps[i] {
                Some(map) => {
                    let off = off_road(&initial_boxes, map);
                    (0..w.agents).map(|a| !off.contains(&a)).collect()
                }
                None => vec![false; w.agents],
            };
            inputs.push(RolloutScene {
                history: SceneInput::from_window(w, scene.observed_steps - n, n, model),
            });
            runtimes.push(SceneRuntime {
                heading_unwrapped: poses.iter().map(|p| p.heading_rad).collect(),
                initial_overlaps: collisions(&initial_boxes),
                initially_on_road,
                overrides: vec![None; w.agents],
                poses,
                scripted,
                controllers: scene.controllers,
                window: scene.window,
            });
        }
        let driver = RolloutDriver::new(engine, planner, &inputs, steps, rng)?;
        Ok(Self {
            driver,
            scenes: runtimes,
            maps,
            heading_scale: model.heading_scale,
            steps,
        })
    }

    pub fn scenes(&self) -> usize {
        self.scenes.len()
    }

    /// Ticks done so far.
    pub fn ticks(&self) -> usize {
        self.driver.ticks()
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

    /// Poses after the last tick (the last observed step before the first), per agent.
    pub fn poses(&self, scene: usize) -> &[Pose] {
        &self.scenes[scene].poses
    }

    /// One simulated step of every scene; `out` receives one [`SceneTick`] per scene.
    pub fn tick(
        &mut self,
        engine: &mut dyn StepEngine,
        external: &mut dyn ExternalDriver,
        out: &mut Vec<SceneTick>,
    ) -> Result<()> {
        let tick = self.driver.ticks();
        if tick >= self.steps {
            return Err(Error::Config(format!(
                "the simulation was built for {} steps",
                self.steps
            )));
        }
        // Agents the model does not drive decide first: they react to the last tick's world.
        for (i, s) in self.scenes.iter_mut().enumerate() {
            for a in 0..s.controllers.len() {
                let pose = match s.controllers[a] {
                    Controller::Model => None,
                    Controller::External => {
                        let p = external.drive(i, a, tick, &s.poses)?;
                        if let Some(p) = p {
                            if !(p.x_m.is_finite()
                                && p.y_m.is_finite()
                                && p.heading_rad.is_finite())
                            {
                                return Err(Error::External {
                                    scene: i,
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
                    [xy[0], xy[1], (heading * self.heading_scale) as f32]
                });
            }
        }
        let scenes = &mut self.scenes;
        let heading_scale = self.heading_scale;
        self.driver.tick(engine, &mut |i: usize,
                                        emitted: &mut [f32]|
         -> ModelResult<()> {
            let s = &mut scenes[i];
            for (a, o) in s.overrides.iter().enumerate() {
                if let Some(state) = o {
                    emitted[3 * a..3 * a + 3].copy_from_slice(state);
                }
            }
            for a in 0..s.controllers.len() {
                let p = s
                    .window
                    .frame
                    .to_metres([emitted[3 * a], emitted[3 * a + 1]]);
                let heading = f64::from(emitted[3 * a + 2]) / heading_scale;
                s.heading_unwrapped[a] = heading;
                s.poses[a] = Pose {
                    x_m: p[0],
                    y_m: p[1],
                    heading_rad: f64::from(wrap_angle(heading as f32)),
                };
            }
            Ok(())
        })?;
        out.clear();
        for (s, map) in self.scenes.iter().zip(&self.maps) {
            let b = boxes(&s.window, &s.poses);
            let mut hits = collisions(&b);
            hits.retain(|pair| !s.initial_overlaps.contains(pair));
            let mut off = map.map(|m| off_road(&b, m)).unwrap_or_default();
            off.retain(|&a| s.initially_on_road[a]);
            out.push(SceneTick {
                poses: s.poses.clone(),
                collisions: hits,
                off_road: off,
            });
        }
        Ok(())
    }
}

/// Simulates a scene whose every agent is scripted (replay, adversarial, constant velocity):
/// the non-reactive baselines, with no model. Reports like [`ClosedLoop::tick`].
pub fn simulate_scripted(
    scene: &SimScene,
    map: Option<&LaneletMap>,
    steps: usize,
) -> Result<Vec<SceneTick>> {
    let start = start_poses(scene, 1)?;
    let w = &scene.window;
    let reference = scene.observed_steps - 1;
    if let Some(a) = scene
        .controllers
        .iter()
        .position(|c| matches!(c, Controller::Model | Controller::External))
    {
        return Err(Error::Config(format!(
            "{} {} frame {}: agent {a} is not scripted ({:?})",
            w.location, w.file, w.start_frame, scene.controllers[a]
        )));
    }
    let scripted: Vec<Vec<Pose>> = (0..w.agents)
        .map(|a| script(w, a, reference, steps, scene.controllers[a]))
        .collect();
    let initial_boxes = boxes(w, &start);
    let initial_overlaps = collisions(&initial_boxes);
    let initially_off = map.map(|m| off_road(&initial_boxes, m)).unwrap_or_default();
    Ok((0..steps)
        .map(|t| {
            let poses: Vec<Pose> = scripted
                .iter()
                .map(|p| Pose {
                    heading_rad: f64::from(wrap_angle(p[t].heading_rad as f32)),
                    ..p[t]
                })
                .collect();
            let b = boxes(w, &poses);
            let mut hits = collisions(&b);
            hits.retain(|pair| !initial_overlaps.contains(pair));
            let mut off = map.map(|m| off_road(&b, m)).unwrap_or_default();
            off.retain(|a| !initially_off.contains(a));
            SceneTick {
                poses,
                collisions: hits,
                off_road: off,
            }
        })
        .collect())
}

/// The scripted poses of agent `a` for ticks `0..steps` (pose after each tick); empty for the
/// model's and external agents.
fn script(
    w: &SceneWindow,
    a: usize,
    reference: usize,
    steps: usize,
    controller: Controller,
) -> Vec<Pose> {
    let last = pose_of(w, a, reference).expect("checked present at the reference step");
    let previous = reference
        .checked_sub(1)
        .and_then(|t| pose_of(w, a, t))
        .unwrap_or(last);
    match controller {
        Controller::Model | Controller::External => Vec::new(),
        Controller::ConstantVelocity => constant_velocity(previous, last, steps),
        Controller::Replay => {
            let mut out = Vec::with_capacity(steps);
            let (mut prev, mut cur) = (previous, last);
            for t in 1..=steps {
                let next = pose_of(w, a, reference + t).unwrap_or_else(|| {
                    // The log ends (or the agent left): carry on at constant velocity.
                    constant_velocity(prev, cur, 1)[0]
                });
                out.push(next);
                (prev, cur) = (cur, next);
            }
            out
        }
        Controller::Adversarial => {
            let logged: Vec<Pose> = (reference..w.steps)
                .map_while(|t| pose_of(w, a, t))
                .collect();
            slowed_replay(&logged, steps)
        }
    }
}

/// The reactivity test's adversarial agent: the one with the longest logged path over the
/// window's steps after `reference` (it must be present throughout), `None` when nobody moves.
pub fn pick_adversary(w: &SceneWindow, reference: usize) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for a in 0..w.agents {
        let path: Option<Vec<Pose>> = (reference..w.steps).map(|t| pose_of(w, a, t)).collect();
        let Some(path) = path else { continue };
        let length: f64 = path
            .windows(2)
            .map(|p| (p[1].x_m - p[0].x_m).hypot(p[1].y_m - p[0].y_m))
            .sum();
        if length > 1.0 && best.is_none_or(|(_, l)| length > l) {
            best = Some((a, length));
        }
    }
    best.map(|b| b.0)
}
