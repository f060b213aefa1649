//! Issue 41, finding 1 (inside the engines): a tick whose engine output holds a number that
//! is not finite never reaches a client as `null`: the tick fails, and the server closes the
//! scene with an `internal` error (the round's failure path, as for any failed tick).

mod common;

use std::collections::BTreeMap;
use std::time::Instant;

use road_client::protocol::CreateScene;
use road_serve::models::{Checkpoints, planners};
use road_serve::pool::{Pool, PoolEngine, PoolKey};
use road_serve::scene::{LiveScene, SetupContext, setup};
use road_sim::closed_loop::SceneTick;

#[test]
fn a_non_finite_engine_output_fails_the_tick() {
    let dir = common::temp_dir("engine-faults");
    let config = common::config(&dir);
    let mut checkpoints = Checkpoints::new(config.models_dir.clone());
    let planners = planners().unwrap();
    let request: CreateScene = CreateScene {
        client: Some("faults".into()),
        ..common::roundabout()
    };
    let build = |checkpoints: &mut Checkpoints| {
        let scene_setup = setup(
            &request,
            &mut SetupContext {
                config: &config,
                checkpoints,
                planners: &planners,
                map_files: &BTreeMap::new(),
            },
        )
        .unwrap();
        let key = PoolKey {
            checkpoint: scene_setup.checkpoint_name.clone(),
            planner: scene_setup.planner_name.clone(),
        };
        let mut pool = Pool::new(
            scene_setup.model,
            PoolEngine::Cpu,
            &scene_setup.planner,
            1,
            config.max_agents,
        )
        .unwrap();
        let live = LiveScene::new(
            1,
            scene_setup,
            key,
            &mut pool,
            "0".repeat(32),
            Instant::now(),
        )
        .unwrap();
        (pool, live)
    };
    for (agent, field) in [(0, "x"), (1, "heading")] {
        // A fresh scene each time: the failed tick leaves its pool's round unfinished.
        let (mut pool, mut live) = build(&mut checkpoints);
        live.begin_tick(&mut pool, Instant::now(), 0.0).unwrap();
        let mut poses = live.poses().to_vec();
        match field {
            "x" => poses[agent].x_m = f64::NAN,
            _ => poses[agent].heading_rad = f64::INFINITY,
        }
        let tick = SceneTick {
            poses,
            collisions: vec![],
            off_road: vec![],
            guarded: vec![],
            plans: vec![],
            left: Vec::new(),
            stuck: Vec::new(),
        };
        let e = live.finish_tick(&tick).unwrap_err().to_string();
        let id = live.agents[agent].id;
        assert!(
            e.contains("non-finite pose") && e.contains(&format!("agent {id}")),
            "{e}"
        );
        // Nothing of the failed tick was kept.
        assert_eq!(live.tick, 0);
        assert!(live.poses().iter().all(|p| p.x_m.is_finite()));
    }
}
