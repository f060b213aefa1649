//! The stall release: a model-driven vehicle that stands still with free road ahead pulls
//! away after the planner's time, and one with a vehicle close ahead does not. The model is
//! replaced by an engine whose every plan stands still (each future slot the newest
//! observation), so that only the release moves anyone.

use rand::SeedableRng;
use rand::rngs::StdRng;
use road_data::WindowConfig;
use road_model::{ModelConfig, Result};
use road_planner::collision_guard::GuardAction;
use road_rollout::{ShiftEdit, ShiftShape, StepEngine, window_emitted, window_shift};
use road_sched::{PlannerSpec, StallRelease};
use road_sim::closed_loop::{ClosedLoop, Controller, NoExternal, SceneTick, SimScene};
use road_sim::populate::keep_agents;
use road_sim::procedural::{ProceduralMap, procedural};

/// Windows held as given; a step sets every future slot to the newest observation.
struct StandingEngine {
    w: usize,
    n: usize,
    agents: usize,
    windows: Vec<f32>,
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
            for slot in n..w {
                row[3 * slot..3 * slot + 3].copy_from_slice(&newest);
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

/// Vehicles 1 and 2 of the merge's script standing still for 10 s, under `release`.
fn run(release: Option<StallRelease>, keep: &[usize]) -> Vec<SceneTick> {
    let model = ModelConfig::default();
    let planner = PlannerSpec {
        stall_release: release,
        obs_noise: Some(0.0),
        ..PlannerSpec::default()
    };
    let scene = procedural(ProceduralMap::Merge, &WindowConfig::default(), 10).unwrap();
    let window = keep_agents(&scene.window, keep);
    let mut engine = StandingEngine {
        w: planner.window_slots(),
        n: planner.obs_slots,
        agents: 0,
        windows: Vec::new(),
    };
    let agents = window.agents;
    let mut sim = ClosedLoop::new(
        &mut engine,
        &model,
        &planner,
        vec![SimScene {
            window,
            observed_steps: 10,
            controllers: vec![Controller::Model; agents],
        }],
        vec![Some(&scene.map)],
        100,
        &mut StdRng::seed_from_u64(0),
    )
    .unwrap();
    let mut ticks = Vec::new();
    let mut out = Vec::new();
    for _ in 0..100 {
        sim.tick(&mut engine, &mut NoExternal, &mut out).unwrap();
        ticks.push(out[0].clone());
    }
    ticks
}

fn moved_m(ticks: &[SceneTick], agent: usize, from: usize) -> f64 {
    let (a, b) = (ticks[from].poses[agent], ticks.last().unwrap().poses[agent]);
    (b.x_m - a.x_m).hypot(b.y_m - a.y_m)
}

#[test]
fn a_vehicle_standing_with_free_road_ahead_pulls_away() {
    let release = StallRelease {
        after_secs: 3.0,
        acceleration_mps2: 1.5,
        release_speed_mps: 5.0,
    };
    // Vehicle 0 of the script alone on the main road.
    let still = run(None, &[0]);
    assert!(moved_m(&still, 0, 1) < 0.01, "the standing engine moved it");
    let released = run(Some(release), &[0]);
    // It stands from the first tick on (its history drove 9 m/s) and pulls away on the 30th
    // tick it has stood.
    let first = released
        .iter()
        .position(|t| t.guarded.contains(&(0, GuardAction::PulledAway)));
    assert_eq!(first, Some(30), "the first pull-away");
    let moved = moved_m(&released, 0, 1);
    assert!(moved > 5.0, "moved {moved:.2} m in 10 s");
    // On its lane, forwards (the main road runs along +x).
    let last = released.last().unwrap().poses[0];
    assert!(
        last.x_m > released[1].poses[0].x_m && last.y_m.abs() < 2.0,
        "{last:?}"
    );
}
