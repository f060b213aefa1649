//! What the closed loop's tests share: an engine whose every plan stands still or drives on
//! at a set speed (each future slot the newest observation, moved on along its heading), so
//! that only the rules under test move anyone, and a procedural scene run on it.

// Each test binary uses its own part.
#![allow(dead_code)]

use rand::SeedableRng;
use rand::rngs::StdRng;
use road_data::{LaneletMap, WindowConfig};
use road_model::{ModelConfig, Result};
use road_rollout::{ShiftEdit, ShiftShape, StepEngine, window_emitted, window_shift};
use road_sched::PlannerSpec;
use road_sim::Pose;
use road_sim::closed_loop::{ClosedLoop, Controller, ExternalDriver, SceneTick, SimScene};
use road_sim::populate::keep_agents;
use road_sim::procedural::{ProceduralMap, procedural};

/// Windows held as given; a step sets every future slot to the newest observation, moved on
/// along its heading by `forward` (model position units per slot; 0: standing), turning by
/// `turn_rad` a slot; with `rocking`, the first future slot goes back where the last step went
/// forwards and forwards where it went back (a model rocking every vehicle in place); with
/// `stuttering`, a step after one of over half `forward` is a tenth of it (a model crawling
/// every vehicle on, some ticks faster than others). Model units: headings `heading_scale` per
/// radian.
pub struct StandingEngine {
    w: usize,
    n: usize,
    agents: usize,
    windows: Vec<f32>,
    forward: f32,
    turn_rad: f32,
    rocking: bool,
    stuttering: bool,
    heading_scale: f32,
}

impl StepEngine for StandingEngine {
    fn window_slots(&self) -> usize {
        self.w
    }
    fn prepare(
        &mut self,
        b: usize,
        a: usize,
        _: &[f32],
        _: usize,
        _: &[f32],
        _: &[f32],
    ) -> Result<()> {
        self.agents = a;
        self.windows = vec![0.0; b * a * self.w * 3];
        Ok(())
    }
    fn prepare_scene(&mut self, _: usize, _: &[f32], _: &[f32], _: &[f32]) -> Result<()> {
        Ok(())
    }
    fn load(&mut self, windows: &[f32], _: &[f32]) -> Result<()> {
        self.windows = windows.to_vec();
        Ok(())
    }
    fn load_scene(&mut self, scene: usize, window: &[f32], _: &[f32]) -> Result<()> {
        let len = self.agents * self.w * 3;
        self.windows[scene * len..(scene + 1) * len].copy_from_slice(window);
        Ok(())
    }
    fn step(&mut self, _: &[f32], _: &[f32], _: bool) -> Result<()> {
        let (w, n) = (self.w, self.n);
        for row in self.windows.chunks_exact_mut(w * 3) {
            let newest: [f32; 3] = row[3 * (n - 1)..3 * n].try_into().unwrap();
            let heading = newest[2] / self.heading_scale;
            let (mut x, mut y) = (newest[0], newest[1]);
            let went_forwards = (newest[0] - row[3 * (n - 2)]) * heading.cos()
                + (newest[1] - row[3 * (n - 2) + 1]) * heading.sin()
                > 0.0;
            let last_step = (newest[0] - row[3 * (n - 2)]).hypot(newest[1] - row[3 * (n - 2) + 1]);
            let forward = if self.rocking && went_forwards {
                -self.forward
            } else if self.stuttering && last_step > 0.5 * self.forward {
                0.1 * self.forward
            } else {
                self.forward
            };
            for slot in n..w {
                if self.turn_rad == 0.0 {
                    let k = (slot + 1 - n) as f32 * forward;
                    row[3 * slot..3 * slot + 3].copy_from_slice(&[
                        newest[0] + k * heading.cos(),
                        newest[1] + k * heading.sin(),
                        newest[2],
                    ]);
                    continue;
                }
                let turned = heading + (slot + 1 - n) as f32 * self.turn_rad;
                x += self.forward * turned.cos();
                y += self.forward * turned.sin();
                row[3 * slot..3 * slot + 3].copy_from_slice(&[x, y, turned * self.heading_scale]);
            }
        }
        Ok(())
    }
    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()> {
        window_emitted(&self.windows, self.agents, self.w, slots, out);
        Ok(())
    }
    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()> {
        let len = self.agents * self.w * 3;
        for edit in edits {
            let window = &mut self.windows[edit.scene * len..(edit.scene + 1) * len];
            window_shift(window, self.w, edit, shape);
        }
        Ok(())
    }
}

/// An external driver holding every external agent where it stood at the start.
pub struct StandingEgo(Option<Pose>);

impl ExternalDriver for StandingEgo {
    fn pose(&mut self, _: usize, agent: usize, _: usize, world: &[Pose]) -> road_sim::Result<Pose> {
        Ok(*self.0.get_or_insert(world[agent]))
    }
}

/// `map`'s procedural scene, its vehicles `keep` (`stands`: index among the kept, x, y (m)
/// and heading (rad), standing there over their whole history) driven by `planner` for
/// `ticks`, the plans driving on at `speed_mps` and turning by `turn_rad` a slot (positive:
/// left); `external`: the kept vehicle a client drives, standing where it starts.
#[allow(clippy::too_many_arguments)]
pub fn run_turning(
    map: ProceduralMap,
    planner: &PlannerSpec,
    keep: &[usize],
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
    speed_mps: f64,
    turn_rad: f64,
    external: Option<usize>,
) -> Vec<SceneTick> {
    let motion = Motion {
        turn_rad,
        ..Motion::straight(speed_mps)
    };
    run_on(map, None, planner, keep, stands, ticks, motion, external)
}

/// As [`run_turning`] on the merge (no turns, no client), every vehicle rocked in place by the
/// engine at `speed_mps`.
pub fn run_rocking(
    planner: &PlannerSpec,
    keep: &[usize],
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
    speed_mps: f64,
) -> Vec<SceneTick> {
    let motion = Motion {
        rocking: true,
        ..Motion::straight(speed_mps)
    };
    run_on_merge(planner, keep, stands, ticks, motion)
}

/// As [`run_turning`] on the merge (no turns, no client), every vehicle crawled on by the
/// engine, one step at `speed_mps` and the next at a tenth of it.
pub fn run_stuttering(
    planner: &PlannerSpec,
    keep: &[usize],
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
    speed_mps: f64,
) -> Vec<SceneTick> {
    let motion = Motion {
        stuttering: true,
        ..Motion::straight(speed_mps)
    };
    run_on_merge(planner, keep, stands, ticks, motion)
}

/// The merge's scene without a client, its vehicles moved by the engine's plans as `motion`.
fn run_on_merge(
    planner: &PlannerSpec,
    keep: &[usize],
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
    motion: Motion,
) -> Vec<SceneTick> {
    run_on(
        ProceduralMap::Merge,
        None,
        planner,
        keep,
        stands,
        ticks,
        motion,
        None,
    )
}

/// How the engine's plans move every vehicle.
#[derive(Clone, Copy)]
struct Motion {
    speed_mps: f64,
    turn_rad: f64,
    rocking: bool,
    stuttering: bool,
}

impl Motion {
    /// Straight on at `speed_mps`, every step alike.
    fn straight(speed_mps: f64) -> Self {
        Self {
            speed_mps,
            turn_rad: 0.0,
            rocking: false,
            stuttering: false,
        }
    }
}

/// As [`run_turning`] (no turns, no client) with the vehicles on `lanes` instead of the
/// procedural map's lanes (its scene's window, placed by `stands`, still frames them).
pub fn run_on_lanes(
    lanes: &LaneletMap,
    planner: &PlannerSpec,
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
    speed_mps: f64,
) -> Vec<SceneTick> {
    let keep: Vec<usize> = (0..stands.len()).collect();
    let motion = Motion::straight(speed_mps);
    run_on(
        ProceduralMap::Merge,
        Some(lanes),
        planner,
        &keep,
        stands,
        ticks,
        motion,
        None,
    )
}

/// As [`run_on_lanes`] with `map`'s script's vehicles `keep` (their sizes) placed by `stands`
/// (index among the kept) on `lanes`.
pub fn run_kept_on_lanes(
    map: ProceduralMap,
    lanes: &LaneletMap,
    planner: &PlannerSpec,
    keep: &[usize],
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
) -> Vec<SceneTick> {
    let motion = Motion::straight(0.0);
    run_on(map, Some(lanes), planner, keep, stands, ticks, motion, None)
}

#[allow(clippy::too_many_arguments)]
fn run_on(
    map: ProceduralMap,
    lanes: Option<&LaneletMap>,
    planner: &PlannerSpec,
    keep: &[usize],
    stands: &[(usize, f64, f64, f64)],
    ticks: usize,
    motion: Motion,
    external: Option<usize>,
) -> Vec<SceneTick> {
    let Motion {
        speed_mps,
        turn_rad,
        rocking,
        stuttering,
    } = motion;
    let model = ModelConfig::default();
    let scene = procedural(map, &WindowConfig::default(), 10).unwrap();
    let mut window = keep_agents(&scene.window, keep);
    for &(a, x_m, y_m, heading_rad) in stands {
        let xy = window.frame.to_norm([x_m, y_m]);
        for t in 0..window.steps {
            let i = a * window.steps + t;
            window.states[3 * i..3 * i + 3].copy_from_slice(&[xy[0], xy[1], heading_rad as f32]);
            window.valid[i] = true;
        }
    }
    let mut engine = StandingEngine {
        w: planner.window_slots(),
        n: planner.obs_slots,
        agents: 0,
        windows: Vec::new(),
        forward: (speed_mps * 0.1 / window.frame.scale_m) as f32,
        turn_rad: turn_rad as f32,
        rocking,
        stuttering,
        heading_scale: model.heading_scale as f32,
    };
    let agents = window.agents;
    let mut sim = ClosedLoop::new(
        &mut engine,
        &model,
        planner,
        vec![SimScene {
            window,
            observed_steps: 10,
            controllers: (0..agents)
                .map(|a| {
                    if Some(a) == external {
                        Controller::External
                    } else {
                        Controller::Model
                    }
                })
                .collect(),
        }],
        vec![Some(lanes.unwrap_or(&scene.map))],
        ticks,
        &mut StdRng::seed_from_u64(0),
    )
    .unwrap();
    // As served scenes: vehicles leave through the map's open lane ends.
    sim.retire_on_exit(0, true).unwrap();
    let mut out_ticks = Vec::new();
    let mut out = Vec::new();
    let mut ego = StandingEgo(None);
    for _ in 0..ticks {
        sim.tick(&mut engine, &mut ego, &mut out).unwrap();
        out_ticks.push(out[0].clone());
    }
    out_ticks
}

pub fn moved_m(ticks: &[SceneTick], agent: usize, from: usize) -> f64 {
    let (a, b) = (ticks[from].poses[agent], ticks.last().unwrap().poses[agent]);
    (b.x_m - a.x_m).hypot(b.y_m - a.y_m)
}
