//! Rollouts of a small trained denoiser on the candle reference engine: every planner through
//! the scheduler, scenes at different phases in one batch, seeded noise streams, turned plans.

#[path = "../../road-model/tests/common/mod.rs"]
mod common;

use candle_core::Device;
use rand::{SeedableRng, rngs::StdRng};
use road_data::Split;
use road_model::batch::SceneInput;
use road_model::model;
use road_model::train::Trainer;
use road_model::{RunConfig, TrainConfig};

use common::{dataset, identity, run_config, temp_dir};

/// Reference sampling: every planner that fits the window runs through the scheduler with the
/// NFE of the math doc's table, deterministically for a seed; a trained model follows the
/// logged futures far better than an untrained one.
#[test]
fn reference_sampling_runs_every_planner_and_learns_the_lanes() {
    use road_cpu::rollout;
    use road_rollout::RolloutScene;
    use road_sched::{PlannerKind, PlannerSpec};
    let run = RunConfig {
        train: TrainConfig {
            steps: 300,
            ema_decay: 0.9,
            ..run_config().train
        },
        ..run_config()
    };
    let ds = dataset(Split::Train);
    let mut trainer = Trainer::new(run.clone(), &ds, identity(), None).unwrap();
    let untrained = trainer.ema_model().unwrap();
    let dir = temp_dir("sampling");
    trainer.run_until(&ds, &dir, 300, "test", |_| {}).unwrap();
    let trained = trainer.ema_model().unwrap();
    std::fs::remove_dir_all(&dir).ok();

    let window = ds.window(3).unwrap();
    let n = 10;
    let history = SceneInput::from_window(&window, 0, n, &run.model);
    let scenes = vec![RolloutScene { history }; 3];
    let steps = 10;
    let planner = |kind, x| PlannerSpec {
        kind,
        steps_per_diffusion: 10,
        replan_every: x,
        ..PlannerSpec::default()
    };
    for (spec, nfe) in [
        (planner(PlannerKind::Rolling, None), 20 + 9 * 2),
        (planner(PlannerKind::Mpc, Some(5)), 2 * 19),
        (planner(PlannerKind::OneShot, None), 19),
    ] {
        let a = rollout(
            &trained,
            &spec,
            &scenes,
            steps,
            &mut StdRng::seed_from_u64(1),
        )
        .unwrap();
        let b = rollout(
            &trained,
            &spec,
            &scenes,
            steps,
            &mut StdRng::seed_from_u64(1),
        )
        .unwrap();
        assert_eq!(a, b, "{:?}: same seed, same samples", spec.kind);
        assert_eq!(a.nfe, nfe, "{:?}", spec.kind);
        assert_eq!(a.states.len(), 3);
        assert_eq!(a.states[0].len(), window.agents * steps * 3);
        assert!(a.states.iter().flatten().all(|v| v.is_finite()));
        assert_ne!(a.states[0], a.states[1], "each scene has its own noise");
    }
    // Average displacement from the logged future (normalised units).
    let ade = |m: &road_model::Denoiser| {
        let r = rollout(
            m,
            &planner(PlannerKind::Rolling, None),
            &scenes,
            steps,
            &mut StdRng::seed_from_u64(2),
        )
        .unwrap();
        let (mut sum, mut count) = (0.0f32, 0);
        for sample in &r.states {
            for a in 0..window.agents {
                for t in 0..steps {
                    if let Some(truth) = window.state(a, n + t) {
                        let k = 3 * (a * steps + t);
                        sum += ((sample[k] - truth[0]).powi(2)
                            + (sample[k + 1] - truth[1]).powi(2))
                        .sqrt();
                        count += 1;
                    }
                }
            }
        }
        sum / count as f32
    };
    let (trained_ade, untrained_ade) = (ade(&trained), ade(&untrained));
    assert!(
        trained_ade < 0.5 * untrained_ade,
        "ADE trained {trained_ade} vs untrained {untrained_ade}"
    );
}

/// The scheduler batches scenes at different phases and under different planners: a scene's
/// samples are the same whether it runs alone or shares every batch with a scene that is in its
/// warm-up while it rolls (each scene has its own σ rows and its own noise stream).
#[test]
fn scenes_at_different_phases_share_batches_without_changing_each_other() {
    use road_cpu::CpuEngine;
    use road_rollout::{RolloutDriver, RolloutScene};
    use road_sched::{PlannerKind, PlannerSpec};
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 11).unwrap();
    let n = 10;
    let scene = |i: usize| RolloutScene {
        history: SceneInput::from_window(&ds.window(i).unwrap(), 0, n, &run.model),
    };
    let rolling = PlannerSpec {
        steps_per_diffusion: 10,
        ..PlannerSpec::default()
    };
    let mpc = PlannerSpec {
        kind: PlannerKind::Mpc,
        replan_every: Some(2),
        ..rolling.clone()
    };
    let emitted = |driver: &mut RolloutDriver, engine: &mut CpuEngine, which: &[usize]| {
        let mut out: Vec<Vec<f32>> = vec![Vec::new(); driver.scenes()];
        driver
            .tick_scenes(engine, which, &mut |i, e, _| {
                out[i] = e.to_vec();
                Ok(())
            })
            .unwrap();
        out
    };
    // Alone: scene 0 rolls for 6 ticks.
    let mut engine = CpuEngine::new(&model);
    let mut alone = RolloutDriver::new(
        &mut engine,
        &rolling,
        &[scene(0)],
        6,
        &mut StdRng::seed_from_u64(3),
    )
    .unwrap();
    let alone_out: Vec<Vec<f32>> = (0..6)
        .map(|_| emitted(&mut alone, &mut engine, &[0]).swap_remove(0))
        .collect();
    // Together with scene 1, which switches to MPC at tick 2 (a full diffusion while scene 0
    // is in its rolling stages) and skips tick 4.
    let mut engine = CpuEngine::new(&model);
    let mut both = RolloutDriver::new(
        &mut engine,
        &rolling,
        &[scene(0), scene(1)],
        6,
        &mut StdRng::seed_from_u64(3),
    )
    .unwrap();
    for (t, alone_tick) in alone_out.iter().enumerate() {
        if t == 2 {
            both.switch_scene_planner(1, &mpc).unwrap();
        }
        let which: &[usize] = if t == 4 { &[0] } else { &[0, 1] };
        let out = emitted(&mut both, &mut engine, which);
        for (x, y) in out[0].iter().zip(alone_tick) {
            assert!(
                (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                "tick {t}: {x} vs {y}"
            );
        }
    }
    assert_eq!(both.scene_ticks(0), 6);
    assert_eq!(both.scene_ticks(1), 5);
    // Scene 1: the rolling warm-up (20) and one rolling stage (2), then MPC-2 replans at its
    // ticks 2 and 4 (19 each; its tick 3 executes the plan).
    assert_eq!(both.scene_nfe(1).unwrap(), 20 + 2 + 19 + 19);
    assert!(
        both.into_rollout().is_err(),
        "unequal ticks have no common rollout"
    );
}

/// Noise streams named by the caller (`RolloutDriver::with_seeds`, `stream_seed`): a scene
/// samples the same futures alone, first in a batch or second, so that an evaluation's figures
/// do not depend on how its scenes are chunked.
#[test]
fn a_seeded_scene_samples_the_same_wherever_it_sits_in_the_batch() {
    use road_cpu::CpuEngine;
    use road_rollout::{RolloutScene, rollout_seeded, stream_seed};
    use road_sched::PlannerSpec;
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 11).unwrap();
    let scene = |i: usize| RolloutScene {
        history: SceneInput::from_window(&ds.window(i).unwrap(), 0, 10, &run.model),
    };
    let planner = PlannerSpec {
        steps_per_diffusion: 10,
        ..PlannerSpec::default()
    };
    let (seed_a, seed_b) = (stream_seed(5, 0), stream_seed(5, 1));
    assert_ne!(seed_a, seed_b);
    let run_with = |scenes: &[RolloutScene], seeds: &[u64]| {
        rollout_seeded(&mut CpuEngine::new(&model), &planner, scenes, 4, seeds).unwrap()
    };
    let alone = run_with(&[scene(0)], &[seed_a]);
    let first = run_with(&[scene(0), scene(1)], &[seed_a, seed_b]);
    let second = run_with(&[scene(1), scene(0)], &[seed_b, seed_a]);
    for (name, states) in [("first", &first.states[0]), ("second", &second.states[1])] {
        assert_eq!(states.len(), alone.states[0].len());
        for (x, y) in states.iter().zip(&alone.states[0]) {
            assert!(
                (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                "{name}: {x} vs {y}"
            );
        }
    }
    // Another seed samples another future.
    let other = run_with(&[scene(0)], &[seed_b]);
    assert!(
        other.states[0]
            .iter()
            .zip(&alone.states[0])
            .any(|(x, y)| (x - y).abs() > 1e-3),
        "two seeds gave the same samples"
    );
    // One seed per scene.
    assert!(
        rollout_seeded(
            &mut CpuEngine::new(&model),
            &planner,
            &[scene(0)],
            4,
            &[1, 2]
        )
        .is_err()
    );
}

/// A hook that turns an agent's plan at an emission (`plan_turns` of
/// `road_rollout::Overrides`) turns that agent's future slots n … W − 2 of the window and
/// of the multistep sampler's kept estimate by `turn_plan`, and nothing else: the other agents,
/// the observed slots and the fresh slot are as without the turn.
#[test]
fn a_turned_plan_turns_only_that_agent_s_future_slots() {
    use road_cpu::CpuEngine;
    use road_rollout::{RolloutDriver, RolloutScene, StepEngine, turn_plan};
    use road_sched::{PlannerSpec, Sampler};
    let run = run_config();
    let ds = dataset(Split::Train);
    let (_, model) = model::init_seeded(&run.model, &Device::Cpu, 11).unwrap();
    let n = 10;
    let history = SceneInput::from_window(&ds.window(0).unwrap(), 0, n, &run.model);
    let agents = history.agents;
    assert!(agents >= 2, "the test needs two agents");
    let scenes = [RolloutScene { history }];
    let planner = PlannerSpec {
        steps_per_diffusion: 10,
        sampler: Sampler::Multistep,
        ..PlannerSpec::default()
    };
    let turn = [0.3f32, -0.2, 0.5, 0.25];
    let turned_agent = 1;
    // Windows [A, W, 3] and estimates after 3 ticks, the last one turning `turned_agent`'s
    // plan when `turned`.
    let windows_after = |turned: bool| {
        let mut engine = CpuEngine::new(&model);
        let mut driver = RolloutDriver::new(
            &mut engine,
            &planner,
            &scenes,
            3,
            &mut StdRng::seed_from_u64(5),
        )
        .unwrap();
        for t in 0..3 {
            driver
                .tick(&mut engine, &mut |_, _, plan_turns| {
                    if turned && t == 2 {
                        plan_turns[4 * turned_agent..][..4].copy_from_slice(&turn);
                    }
                    Ok(())
                })
                .unwrap();
        }
        let w = engine.window_slots();
        let mut window = vec![0.0f32; agents * w * 3];
        let mut slot = vec![0.0f32; agents * 3];
        for k in 0..w {
            engine.read_emitted(&[Some(k)], &mut slot).unwrap();
            for a in 0..agents {
                window[3 * (a * w + k)..][..3].copy_from_slice(&slot[3 * a..][..3]);
            }
        }
        let mut estimate = vec![0.0f32; agents * w * 3];
        engine.read_denoised(&[0], &mut estimate).unwrap();
        (w, window, estimate)
    };
    let (w, plain_window, plain_estimate) = windows_after(false);
    let (_, turned_window, turned_estimate) = windows_after(true);
    for (what, plain, turned) in [
        ("window", &plain_window, &turned_window),
        ("estimate", &plain_estimate, &turned_estimate),
    ] {
        for a in 0..agents {
            for k in 0..w {
                let mut expected = plain[3 * (a * w + k)..][..3].to_vec();
                if a == turned_agent && (n..w - 1).contains(&k) {
                    turn_plan(&mut expected, &turn);
                    assert_ne!(expected, plain[3 * (a * w + k)..][..3], "{what} slot {k}");
                }
                assert_eq!(
                    turned[3 * (a * w + k)..][..3],
                    expected[..],
                    "{what}: agent {a}, slot {k}"
                );
            }
        }
    }
}
