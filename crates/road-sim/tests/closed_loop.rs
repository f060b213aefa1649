//! The closed loop on the candle reference engine with a small untrained model: controllers
//! drive their agents exactly, the model's agents react to them, infractions are reported.

use candle_core::Device;
use rand::SeedableRng;
use rand::rngs::StdRng;
use road_cpu::CpuEngine;
use road_data::WindowConfig;
use road_model::ModelConfig;
use road_model::model::init_seeded;
use road_sched::{PlannerKind, PlannerSpec};
use road_sim::Pose;
use road_sim::closed_loop::{ClosedLoop, Controller, NoExternal, SceneTick, SimScene};
use road_sim::procedural::{ProceduralScene, roundabout};

fn small_model() -> road_model::Denoiser {
    let config = ModelConfig {
        hidden: 16,
        heads: 2,
        blocks: 1,
        window_slots: 14,
        ..ModelConfig::default()
    };
    init_seeded(&config, &Device::Cpu, 3).unwrap().1
}

fn planner() -> PlannerSpec {
    PlannerSpec {
        kind: PlannerKind::Rolling,
        obs_slots: 10,
        future_slots: 4,
        steps_per_diffusion: 8,
        ..PlannerSpec::default()
    }
}

fn scene() -> ProceduralScene {
    roundabout(&WindowConfig::default(), 10).unwrap()
}

/// The scene in a closed loop on `engine` with the test planner (`with_map`: off-road checks).
fn closed_loop<'m>(
    engine: &mut CpuEngine,
    model: &road_model::Denoiser,
    scene: &'m ProceduralScene,
    controllers: Vec<Controller>,
    with_map: bool,
    steps: usize,
    rng: &mut StdRng,
) -> road_sim::Result<ClosedLoop<'m>> {
    closed_loop_under(
        &planner(),
        engine,
        model,
        scene,
        controllers,
        with_map,
        steps,
        rng,
    )
}

/// [`closed_loop`] under `planner` (10 observed steps).
#[allow(clippy::too_many_arguments)]
fn closed_loop_under<'m>(
    planner: &PlannerSpec,
    engine: &mut CpuEngine,
    model: &road_model::Denoiser,
    scene: &'m ProceduralScene,
    controllers: Vec<Controller>,
    with_map: bool,
    steps: usize,
    rng: &mut StdRng,
) -> road_sim::Result<ClosedLoop<'m>> {
    ClosedLoop::new(
        engine,
        &model.config,
        planner,
        vec![SimScene {
            window: scene.window.clone(),
            observed_steps: 10,
            controllers,
        }],
        vec![with_map.then_some(&scene.map)],
        steps,
        rng,
    )
}

/// Runs `steps` ticks with the test planner; returns every tick's report.
fn simulate(
    model: &road_model::Denoiser,
    scene: &ProceduralScene,
    controllers: Vec<Controller>,
    external: &mut dyn road_sim::closed_loop::ExternalDriver,
    steps: usize,
    seed: u64,
) -> Vec<SceneTick> {
    simulate_under(&planner(), model, scene, controllers, external, steps, seed)
}

/// [`simulate`] under `planner`.
fn simulate_under(
    planner: &PlannerSpec,
    model: &road_model::Denoiser,
    scene: &ProceduralScene,
    controllers: Vec<Controller>,
    external: &mut dyn road_sim::closed_loop::ExternalDriver,
    steps: usize,
    seed: u64,
) -> Vec<SceneTick> {
    let mut engine = CpuEngine::new(model);
    let mut rng = StdRng::seed_from_u64(seed);
    let mut sim = closed_loop_under(
        planner,
        &mut engine,
        model,
        scene,
        controllers,
        true,
        steps,
        &mut rng,
    )
    .unwrap();
    let ticks = tick_reports(&mut sim, &mut engine, external, steps);
    assert_eq!(sim.ticks(), steps);
    // Rolling with K/F = 2 steps per tick after a K = 8 step warm-up, Heun (≤ 2 NFE a step).
    assert!(sim.nfe().unwrap() > 0);
    ticks
}

fn close(a: Pose, b: Pose) -> bool {
    (a.x_m - b.x_m).abs() < 1e-3 && (a.y_m - b.y_m).abs() < 1e-3
}

#[test]
fn the_external_agent_goes_exactly_where_its_driver_says() {
    let model = small_model();
    let scene = scene();
    let n = scene.window.agents;
    let mut controllers = vec![Controller::Model; n];
    controllers[0] = Controller::External;
    let mut ego = scene.ego.clone();
    let ticks = simulate(&model, &scene, controllers, &mut ego, 6, 1);
    let mut check = scene.ego.clone();
    for (t, tick) in ticks.iter().enumerate() {
        use road_sim::closed_loop::ExternalDriver;
        let want = check.pose(0, 0, t, &[]).unwrap();
        assert!(
            close(tick.poses[0], want),
            "tick {t}: {:?} vs {want:?}",
            tick.poses[0]
        );
        assert_eq!(tick.poses.len(), n);
    }
}

#[test]
fn model_agents_react_to_the_external_agent() {
    let model = small_model();
    let scene = scene();
    let n = scene.window.agents;
    let mut controllers = vec![Controller::Model; n];
    controllers[0] = Controller::External;
    let mut ego = scene.ego.clone();
    let a = simulate(&model, &scene, controllers.clone(), &mut ego, 5, 7);
    // The same noise, an ego that stops: the model's agents must come out differently.
    let mut stopped = scene.ego.clone();
    stopped.speed_mps = 0.0;
    let b = simulate(&model, &scene, controllers, &mut stopped, 5, 7);
    assert!(!close(a[4].poses[0], b[4].poses[0]));
    let moved = (1..n).any(|i| !close(a[4].poses[i], b[4].poses[i]));
    assert!(moved, "no model agent reacted to the ego");
}

#[test]
fn scripted_controllers_follow_their_scripts_and_collisions_are_reported() {
    let model = small_model();
    let scene = scene();
    let n = scene.window.agents;
    // Everybody at constant velocity: poses are the exact extrapolation.
    let ticks = simulate(
        &model,
        &scene,
        vec![Controller::ConstantVelocity; n],
        &mut NoExternal,
        4,
        2,
    );
    let w = &scene.window;
    for i in 0..n {
        let at = |t: usize| {
            let s = w.state(i, t).unwrap();
            w.frame.to_metres([s[0], s[1]])
        };
        let (p8, p9) = (at(8), at(9));
        let want = [p9[0] + 4.0 * (p9[0] - p8[0]), p9[1] + 4.0 * (p9[1] - p8[1])];
        let got = ticks[3].poses[i];
        assert!(
            (got.x_m - want[0]).abs() < 1e-3 && (got.y_m - want[1]).abs() < 1e-3,
            "agent {i}: {got:?} vs {want:?}"
        );
    }
    // Two external agents driven onto one spot collide; an agent sent into the centre island
    // is off road.
    struct Crash;
    impl road_sim::closed_loop::ExternalDriver for Crash {
        fn pose(
            &mut self,
            _: usize,
            agent: usize,
            tick: usize,
            world: &[Pose],
        ) -> road_sim::Result<Pose> {
            let spot = |x_m, y_m| Pose {
                x_m,
                y_m,
                heading_rad: 0.0,
            };
            Ok(match (agent, tick) {
                (0 | 1, 2..) => spot(60.0, 60.0),
                (2, 1..) => spot(0.0, 0.0),
                (a, _) => world[a],
            })
        }
    }
    let mut controllers = vec![Controller::Model; n];
    controllers[..3].fill(Controller::External);
    let ticks = simulate(&model, &scene, controllers, &mut Crash, 3, 4);
    assert!(!ticks[1].collisions.contains(&(0, 1)));
    assert!(
        ticks[2].collisions.contains(&(0, 1)),
        "{:?}",
        ticks[2].collisions
    );
    assert!(ticks[1].off_road.contains(&2), "{:?}", ticks[1].off_road);
    assert!(!ticks[0].off_road.contains(&2));
}

#[test]
fn an_external_agent_without_a_driver_is_an_error() {
    let model = small_model();
    let scene = scene();
    let mut engine = CpuEngine::new(&model);
    let mut rng = StdRng::seed_from_u64(0);
    let mut controllers = vec![Controller::Model; scene.window.agents];
    controllers[0] = Controller::External;
    let mut sim =
        closed_loop(&mut engine, &model, &scene, controllers, false, 2, &mut rng).unwrap();
    let err = sim
        .tick(&mut engine, &mut NoExternal, &mut Vec::new())
        .unwrap_err();
    assert!(err.to_string().contains("scene 0, agent 0"), "{err}");
    // A driver that reports a non-finite pose is refused with the scene and agent named.
    struct Broken;
    impl road_sim::closed_loop::ExternalDriver for Broken {
        fn pose(&mut self, _: usize, _: usize, _: usize, _: &[Pose]) -> road_sim::Result<Pose> {
            Ok(Pose {
                x_m: f64::NAN,
                y_m: 0.0,
                heading_rad: 0.0,
            })
        }
    }
    let err = sim
        .tick(&mut engine, &mut Broken, &mut Vec::new())
        .unwrap_err();
    assert!(
        err.to_string().contains("scene 0, agent 0") && err.to_string().contains("not finite"),
        "{err}"
    );
    // Controllers that do not match the agents are refused up front.
    let bad = closed_loop(
        &mut engine,
        &model,
        &scene,
        vec![Controller::Model],
        false,
        2,
        &mut rng,
    );
    assert!(
        bad.unwrap_err()
            .to_string()
            .contains("1 controllers for 7 agents")
    );
}

#[test]
fn scripted_baselines_match_the_closed_loop_with_the_same_controllers() {
    use road_sim::closed_loop::simulate_scripted;
    let model = small_model();
    let scene = scene();
    let n = scene.window.agents;
    let mut controllers = vec![Controller::ConstantVelocity; n];
    controllers[1] = Controller::Replay; // the log ends here: it carries on at constant velocity
    let looped = simulate(&model, &scene, controllers.clone(), &mut NoExternal, 5, 0);
    let sim_scene = SimScene {
        window: scene.window.clone(),
        observed_steps: 10,
        controllers,
    };
    let scripted = simulate_scripted(&sim_scene, Some(&scene.map), 5).unwrap();
    for (t, (a, b)) in looped.iter().zip(&scripted).enumerate() {
        for i in 0..n {
            assert!(close(a.poses[i], b.poses[i]), "tick {t} agent {i}");
        }
        assert_eq!(a.collisions, b.collisions);
        assert_eq!(a.off_road, b.off_road);
    }
    let mut with_model = sim_scene.clone();
    with_model.controllers[0] = Controller::Model;
    let err = simulate_scripted(&with_model, None, 5).unwrap_err();
    assert!(err.to_string().contains("agent 0 is not scripted"), "{err}");
}

#[test]
fn a_scene_switches_planner_between_ticks_on_the_same_checkpoint() {
    let model = small_model();
    let scene = scene();
    let n = scene.window.agents;
    let mut controllers = vec![Controller::Model; n];
    controllers[0] = Controller::External;
    let mut ego = scene.ego.clone();
    let mut engine = CpuEngine::new(&model);
    let mut rng = StdRng::seed_from_u64(5);
    let mut sim = closed_loop(&mut engine, &model, &scene, controllers, true, 6, &mut rng).unwrap();
    let mut out = Vec::new();
    for _ in 0..3 {
        sim.tick(&mut engine, &mut ego, &mut out).unwrap();
    }
    let rolling_nfe = sim.nfe().unwrap();
    // DJINN-4 MPC-1 on the same W = 14 checkpoint: a full K = 8 diffusion every tick.
    let mpc = PlannerSpec {
        kind: PlannerKind::Mpc,
        replan_every: Some(1),
        ..planner()
    };
    sim.switch_planner(&mpc).unwrap();
    assert_eq!(sim.planner(), &mpc);
    for _ in 0..3 {
        sim.tick(&mut engine, &mut ego, &mut out).unwrap();
    }
    assert_eq!(sim.ticks(), 6);
    // Heun: 2 NFE per step but 1 on the last (σ_next = 0 everywhere): 15 per MPC tick.
    assert_eq!(sim.nfe().unwrap() - rolling_nfe, 3 * 15);
    use road_sim::closed_loop::ExternalDriver;
    let want = scene.ego.clone().pose(0, 0, 5, &[]).unwrap();
    assert!(close(out[0].poses[0], want));
    // Another window length is another checkpoint: refused.
    let ar = PlannerSpec {
        kind: PlannerKind::Autoregressive,
        future_slots: 1,
        ..planner()
    };
    let err = sim.switch_planner(&ar).unwrap_err();
    assert!(err.to_string().contains("W = 11"), "{err}");
}

/// A scene that asks for plans gets, each tick, every agent's F − 1 planned poses (finite,
/// metres in the map frame, near the agent); asking again with `false` stops them.
#[test]
fn plans_come_on_request() {
    let model = small_model();
    let scene = scene();
    let agents = scene.window.agents;
    let mut engine = CpuEngine::new(&model);
    let mut rng = StdRng::seed_from_u64(5);
    let mut sim = closed_loop(
        &mut engine,
        &model,
        &scene,
        vec![Controller::Model; agents],
        false,
        4,
        &mut rng,
    )
    .unwrap();
    let mut out = Vec::new();
    sim.tick(&mut engine, &mut NoExternal, &mut out).unwrap();
    assert!(out[0].plans.is_empty(), "no plans unless asked");
    sim.request_plans(0, true).unwrap();
    for _ in 0..2 {
        sim.tick(&mut engine, &mut NoExternal, &mut out).unwrap();
        let tick = &out[0];
        assert_eq!(tick.plans.len(), agents);
        for (a, plan) in tick.plans.iter().enumerate() {
            // The test planner's F = 4: the 3 slots after the emitted one.
            assert_eq!(plan.len(), 3);
            for p in plan {
                assert!(p.x_m.is_finite() && p.y_m.is_finite() && p.heading_rad.is_finite());
                // An untrained model plans nonsense, but in the scene's frame: within the
                // normalisation's reach of the agent, not at the origin of another frame.
                let d = (p.x_m - tick.poses[a].x_m).hypot(p.y_m - tick.poses[a].y_m);
                assert!(
                    d < 1000.0,
                    "agent {a}: plan {p:?} far from {:?}",
                    tick.poses[a]
                );
            }
        }
    }
    sim.request_plans(0, false).unwrap();
    sim.tick(&mut engine, &mut NoExternal, &mut out).unwrap();
    assert!(out[0].plans.is_empty());
    assert!(sim.request_plans(3, true).is_err(), "no scene 3");
}

/// With the collision guard, a model-driven agent never ends a tick overlapping an agent it
/// did not overlap before the tick (the untrained model's steps are wild, so the guard has
/// work), and the guard says what it did.
#[test]
fn the_collision_guard_keeps_model_agents_out_of_each_other() {
    let model = small_model();
    let scene = scene();
    let agents = scene.window.agents;
    let guarded = PlannerSpec {
        collision_guard: Some(road_sched::CollisionGuard {
            horizon_steps: 10,
            brake_mps2: 6.0,
            yield_to_unreactive: false,
            release_deadlock_after_secs: None,
            regrow_cut_steps: false,
        }),
        ..planner()
    };
    let steps = 8;
    let mut engine = CpuEngine::new(&model);
    let mut rng = StdRng::seed_from_u64(11);
    let mut sim = ClosedLoop::new(
        &mut engine,
        &model.config,
        &guarded,
        vec![SimScene {
            window: scene.window.clone(),
            observed_steps: 10,
            controllers: vec![Controller::Model; agents],
        }],
        vec![None],
        steps,
        &mut rng,
    )
    .unwrap();
    let mut out = Vec::new();
    let mut before: Vec<(usize, usize)> = Vec::new();
    let mut acted = 0;
    for t in 0..steps {
        sim.tick(&mut engine, &mut NoExternal, &mut out).unwrap();
        let tick = &out[0];
        for pair in &tick.collisions {
            assert!(
                before.contains(pair),
                "tick {t}: {pair:?} overlap, and did not before the tick"
            );
        }
        before.clone_from(&tick.collisions);
        acted += tick.guarded.len();
    }
    assert!(
        acted > 0,
        "the untrained model's agents gave the guard nothing to do"
    );
}

/// The lane guard on the shipped default checkpoint driving the procedural roundabout (a map
/// unlike its training maps, where it leaves the road on its own): an agent the guard acts on
/// ends that tick on the road, the guard says what it did, and fewer model-driven agents leave
/// the road than without it; so do they with its nudges ahead of the edge and turned plans.
#[test]
fn the_lane_guard_keeps_model_agents_on_the_road() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/road20-wide4");
    let loaded = road_model::checkpoint::load(&dir, &Device::Cpu).unwrap();
    let model = &loaded.model;
    let own_planner = loaded.meta.run.planner.clone();
    let scene = roundabout(&WindowConfig::default(), own_planner.obs_slots).unwrap();
    let ego = scene.ego.agent;
    let mut controllers = vec![Controller::Model; scene.window.agents];
    controllers[ego] = Controller::ConstantVelocity;
    let steps = 40;
    let run = |planner: &PlannerSpec| {
        simulate_under(
            planner,
            model,
            &scene,
            controllers.clone(),
            &mut NoExternal,
            steps,
            0,
        )
    };
    let model_agents_off_road = |ticks: &[SceneTick]| {
        let mut off: Vec<usize> = ticks
            .iter()
            .flat_map(|t| t.off_road.iter().copied())
            .filter(|&a| a != ego)
            .collect();
        off.sort_unstable();
        off.dedup();
        off.len()
    };
    let unguarded = run(&PlannerSpec {
        lane_guard: None,
        ..own_planner.clone()
    });
    let guarded = run(&PlannerSpec {
        lane_guard: Some(road_sched::LaneGuard {
            lookahead_m: 6.0,
            turn_plan: false,
            anticipation: None,
            keep_off_opposing_lanes: false,
        }),
        ..own_planner.clone()
    });
    // The default's lane guard: nudges ahead of the edge, plans turned with every correction.
    let nudging = run(&PlannerSpec {
        lane_guard: Some(road_sched::LaneGuard {
            lookahead_m: 6.0,
            turn_plan: true,
            anticipation: Some(road_sched::LaneAnticipation {
                steps: 3,
                max_turn_rad_per_m: 0.1,
            }),
            keep_off_opposing_lanes: false,
        }),
        ..own_planner.clone()
    });
    let nudging_counts = road_sim::closed_loop::guard_actions(&nudging);
    assert!(
        nudging_counts.nudged_towards_lane > 0,
        "the lane guard nudges nobody: {nudging_counts:?}"
    );
    assert!(
        model_agents_off_road(&nudging) < model_agents_off_road(&unguarded),
        "model-driven agents off road: {} with the nudging lane guard, {} without a guard",
        model_agents_off_road(&nudging),
        model_agents_off_road(&unguarded)
    );
    for (t, tick) in guarded.iter().enumerate() {
        for (agent, action) in &tick.guarded {
            assert!(
                !tick.off_road.contains(agent),
                "tick {t}: agent {agent} off road after the guards' {action:?}"
            );
        }
    }
    let counts = road_sim::closed_loop::guard_actions(&guarded);
    assert!(
        counts.steered_to_lane + counts.stopped_at_road_edge > 0,
        "the lane guard reports no action: {counts:?}"
    );
    assert!(
        model_agents_off_road(&guarded) < model_agents_off_road(&unguarded),
        "model-driven agents off road: {} with the lane guard, {} without",
        model_agents_off_road(&guarded),
        model_agents_off_road(&unguarded)
    );
}

/// With `retire_on_exit`, vehicles that drive past the end of a lane with no successor (the
/// map's edge) leave the scene once (`SceneTick::left`), their pose held from then on, and are
/// never counted off road; without it the same vehicles drive on into the void, off road.
#[test]
fn vehicles_that_drive_off_the_map_leave_the_scene() {
    use road_sim::procedural::{ProceduralMap, procedural};
    let model = small_model();
    let scene = procedural(ProceduralMap::Merge, &WindowConfig::default(), 10).unwrap();
    let steps = 150;
    let run = |retire: bool| drive_at_constant_velocity(&model, &scene, retire, steps);
    let kept = run(false);
    let off_before: std::collections::BTreeSet<usize> =
        kept.iter().flat_map(|t| t.off_road.clone()).collect();
    assert!(kept.iter().all(|t| t.left.is_empty()));
    let retired = run(true);
    let mut left = std::collections::BTreeMap::new();
    for (t, tick) in retired.iter().enumerate() {
        for &a in &tick.left {
            assert!(left.insert(a, t).is_none(), "agent {a} left twice");
        }
    }
    assert!(
        !left.is_empty(),
        "no vehicle reached the map's end in {steps} ticks"
    );
    for (&a, &t) in &left {
        // Off road without retirement: that is what leaving the map used to count as.
        assert!(
            off_before.contains(&a),
            "agent {a} left without going off road before"
        );
        let held = retired[t].poses[a];
        for tick in &retired[t..] {
            assert!(
                !tick.off_road.contains(&a),
                "agent {a} off road after it left"
            );
            assert!(close(tick.poses[a], held), "agent {a} moved after it left");
            assert!(tick.collisions.iter().all(|&(i, j)| i != a && j != a));
        }
    }
}

/// Runs `steps` ticks of `scene` (the test planner, off-road checks on) with every vehicle at
/// constant velocity, retired where it leaves the map when `retire`; every tick's report.
fn drive_at_constant_velocity(
    model: &road_model::Denoiser,
    scene: &ProceduralScene,
    retire: bool,
    steps: usize,
) -> Vec<SceneTick> {
    let mut engine = CpuEngine::new(model);
    let mut rng = StdRng::seed_from_u64(0);
    let controllers = vec![Controller::ConstantVelocity; scene.window.agents];
    let mut sim = closed_loop(
        &mut engine,
        model,
        scene,
        controllers,
        true,
        steps,
        &mut rng,
    )
    .unwrap();
    sim.retire_on_exit(0, retire).unwrap();
    tick_reports(&mut sim, &mut engine, &mut NoExternal, steps)
}

/// Ticks `sim`'s one scene `steps` times; every tick's report.
fn tick_reports(
    sim: &mut ClosedLoop<'_>,
    engine: &mut CpuEngine,
    external: &mut dyn road_sim::closed_loop::ExternalDriver,
    steps: usize,
) -> Vec<SceneTick> {
    let mut out = Vec::new();
    (0..steps)
        .map(|_| {
            sim.tick(engine, external, &mut out).unwrap();
            out[0].clone()
        })
        .collect()
}

/// The merge's scene with its script's first `ends_m.len()` vehicles only, each observed
/// driving east at 9 m/s to its end point (x, y in metres).
fn merge_driving_east(ends_m: &[[f64; 2]]) -> ProceduralScene {
    use road_sim::populate::keep_agents;
    use road_sim::procedural::{ProceduralMap, procedural};
    let mut scene = procedural(ProceduralMap::Merge, &WindowConfig::default(), 10).unwrap();
    let agents: Vec<usize> = (0..ends_m.len()).collect();
    let mut window = keep_agents(&scene.window, &agents);
    for (agent, &[end_x_m, y_m]) in ends_m.iter().enumerate() {
        for t in 0..window.steps {
            let x_m = end_x_m - 0.9 * (window.steps - 1 - t) as f64;
            let xy = window.frame.to_norm([x_m, y_m]);
            let at = agent * window.steps + t;
            window.states[3 * at..3 * at + 3].copy_from_slice(&[xy[0], xy[1], 0.0]);
            window.valid[at] = true;
        }
    }
    scene.window = window;
    scene
}

/// A vehicle whose history ends a step before a lane's open end (a populated scene can place
/// one there) leaves on its first tick: it is retired, not driven on off road.
#[test]
fn a_vehicle_starting_at_the_map_s_end_leaves_on_its_first_step() {
    let model = small_model();
    // The script's vehicle 0 alone, at 9 m/s along the main road, 0.3 m before its end (x = 90).
    let scene = merge_driving_east(&[[89.7, 0.0]]);
    let first = &drive_at_constant_velocity(&model, &scene, true, 5)[0];
    assert_eq!(first.left, vec![0], "{:?}", first.poses[0]);
    assert!(first.off_road.is_empty());
}

/// A vehicle off every lanelet and more than 10 m from every lane (an INTERACTION scene's
/// vehicle can start off its crop's lanes) has left the map: it is retired on its first tick,
/// though it never had a lane end to leave through. One 6 m beside the road stays (the lane
/// guard and the stall release bring such a vehicle back).
#[test]
fn a_vehicle_far_from_every_lane_leaves_on_its_first_step() {
    let model = small_model();
    // The script's vehicles 0 and 1 at 9 m/s east, beside the main road after the merge (its
    // centre line y = 0, x in [0, 90]; the ramp lies south): 0 30 m north of it, 1 6 m.
    let scene = merge_driving_east(&[[40.0, 30.0], [40.0, 6.0]]);
    let ticks = drive_at_constant_velocity(&model, &scene, true, 10);
    assert_eq!(ticks[0].left, vec![0], "{:?}", ticks[0].poses[0]);
    for tick in &ticks[1..6] {
        assert!(tick.left.is_empty(), "{:?}", tick.poses[1]);
    }
}
