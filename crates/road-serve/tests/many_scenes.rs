//! Sixteen scenes at once over loopback, joining and leaving at different ticks, each driven
//! by its own client thread: every tick is answered in order, NPC states stay finite and on
//! the map, the core batches several scenes per round, and every scene's recording holds its
//! ticks. Then the late-ego policy: a client that stops sending gets model-driven, flagged
//! ticks, and its scene is closed when its liveliness token goes.

mod common;

use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use road_client::protocol::{MapSource, NpcTick};

#[test]
fn sixteen_scenes_join_and_leave() {
    let dir = common::temp_dir("many");
    let mut config = common::config(&dir);
    config.late_ego_deadline = Duration::ZERO; // a slow debug build must not turn ticks late
    let server = common::start(config);
    let scenes = 16u64;
    let start = Arc::new(Barrier::new(scenes as usize));
    let threads: Vec<_> = (0..scenes)
        .map(|i| {
            let client = common::client(&server, &format!("ego-{i}"));
            let start = Arc::clone(&start);
            std::thread::spawn(move || {
                start.wait();
                // Scenes join in waves and run for different lengths.
                std::thread::sleep(Duration::from_millis(150 * (i % 4)));
                let mut request = common::roundabout();
                request.seed = i;
                let mut scene = client.create(request).unwrap();
                let ego = scene.created().agents[0].clone();
                assert!(ego.external);
                let ticks = 3 + i % 5;
                let mut answered: Vec<NpcTick> = Vec::new();
                for t in 1..=ticks {
                    let npc = scene
                        .step(t, vec![common::replay(&ego.history, 1, t)])
                        .unwrap();
                    assert_eq!(npc.tick, t);
                    assert_eq!(npc.npcs.len(), 6);
                    assert!(npc.late_external.is_empty());
                    common::assert_sane(&npc, 300.0);
                    answered.push(npc);
                }
                let closed = scene.close().unwrap();
                assert_eq!(closed.ticks, ticks);
                (ticks, closed.recording.unwrap())
            })
        })
        .collect();
    let mut total = 0;
    for t in threads {
        let (ticks, recording) = t.join().expect("a client thread failed");
        total += ticks;
        let bytes = std::fs::read(&recording).unwrap();
        let npc = mcap::MessageStream::new(&bytes)
            .unwrap()
            .map(|m| m.unwrap())
            .filter(|m| m.channel.topic == "/road/npc")
            .count();
        assert_eq!(npc as u64, ticks, "{recording}");
    }
    let status = common::client(&server, "observer").status().unwrap();
    assert!(status.scenes.is_empty(), "{:?}", status.scenes);
    assert_eq!(status.tick_latency.count, total);
    assert_eq!(status.queue.count, total);
    assert!(status.max_batch > 1, "never more than one scene per round");
    server.stop().unwrap();
}

/// The intersection and the merge serve like the roundabout: their own vehicles, agent 1
/// external, every NPC state finite and on the map.
#[test]
fn every_procedural_map_serves_a_scene() {
    let dir = common::temp_dir("procedural");
    let server = common::start(common::config(&dir));
    let client = common::client(&server, "procedural-ego");
    for name in ["intersection", "merge"] {
        let mut request = common::roundabout();
        request.map = MapSource::Procedural(name.into());
        let mut scene = client.create(request).unwrap();
        let agents = scene.created().agents.clone();
        assert_eq!(agents.len(), 6, "{name}: its own six vehicles");
        let history = agents[0].history.clone();
        for tick in 1..=3 {
            let npc = scene
                .step(tick, vec![common::replay(&history, 1, tick)])
                .unwrap();
            assert_eq!(npc.npcs.len(), 5, "{name}: tick {tick}");
            common::assert_sane(&npc, 200.0);
        }
        scene.close().unwrap();
    }
    server.stop().unwrap();
}

#[test]
fn a_late_ego_is_driven_by_the_model_and_flagged() {
    let dir = common::temp_dir("late");
    let mut config = common::config(&dir);
    config.late_ego_deadline = Duration::from_millis(300);
    let server = common::start(config);
    let client = common::client(&server, "late-ego");
    let mut scene = client.create(common::roundabout()).unwrap();
    let history = scene.created().agents[0].history.clone();
    let on_time = scene.step(1, vec![common::replay(&history, 1, 1)]).unwrap();
    assert!(on_time.late_external.is_empty());
    // No ego for tick 2: after the deadline the model drives it, flagged.
    let late = scene.wait_tick(2).unwrap();
    assert_eq!(late.late_external.len(), 1);
    assert_eq!(late.late_external[0].id, 1);
    // Tick 2 is gone; the client goes on with tick 3 (or later, if more went late).
    let next = scene.last().unwrap().tick + 1;
    let npc = scene
        .step(next, vec![common::replay(&history, 1, next)])
        .unwrap();
    assert_eq!(npc.tick, next);

    // The client vanishes: its liveliness token goes, and so does its scene.
    let id = scene.id();
    drop(scene);
    drop(client);
    let observer = common::client(&server, "observer");
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let status = observer.status().unwrap();
        if status.scenes.iter().all(|s| s.scene != id) {
            break;
        }
        assert!(Instant::now() < deadline, "scene {id} outlived its client");
        std::thread::sleep(Duration::from_millis(100));
    }
    server.stop().unwrap();
}

/// `--engine gpu`: the same scenes served on the WGSL engine (lavapipe in CI) and on the fast
/// CPU engine, same seeds, answer the same NPC states to the engines' agreement, a second
/// scene joining the GPU's running batch included; the status names the engine.
#[test]
fn the_gpu_engine_serves_what_the_cpu_engine_serves() {
    let serve = |engine: road_serve::ServeEngine, name: &str| {
        let dir = common::temp_dir(name);
        let mut config = common::config(&dir);
        config.engine = engine;
        config.capacity = 2; // a small pool: lavapipe runs every slot of a round's batch
        config.late_ego_deadline = Duration::ZERO;
        let server = common::start(config);
        let client = common::client(&server, name);
        let status = client.status().unwrap();
        let mut first = client.create(common::roundabout()).unwrap();
        let first_history = first.created().agents[0].history.clone();
        let mut answered = vec![
            first
                .step(1, vec![common::replay(&first_history, 1, 1)])
                .unwrap(),
        ];
        // The second joins while the first's pool runs.
        let mut request = common::roundabout();
        request.seed = 5;
        request.map = MapSource::Procedural("merge".into());
        let mut second = client.create(request).unwrap();
        let second_history = second.created().agents[0].history.clone();
        for t in 2..=3 {
            answered.push(
                first
                    .step(t, vec![common::replay(&first_history, 1, t)])
                    .unwrap(),
            );
            answered.push(
                second
                    .step(t - 1, vec![common::replay(&second_history, 1, t - 1)])
                    .unwrap(),
            );
        }
        for npc in &answered {
            common::assert_sane(npc, 300.0);
        }
        first.close().unwrap();
        second.close().unwrap();
        server.stop().unwrap();
        (status.engine, answered)
    };
    let (gpu_engine, on_gpu) = serve(road_serve::ServeEngine::Gpu, "gpu-engine");
    let (cpu_engine, on_cpu) = serve(road_serve::ServeEngine::Cpu, "cpu-engine");
    assert!(gpu_engine.starts_with("WGSL engine on "), "{gpu_engine}");
    assert!(cpu_engine.starts_with("fast CPU engine"), "{cpu_engine}");
    assert_eq!(on_gpu.len(), 5);
    for (gpu, cpu) in on_gpu.iter().zip(&on_cpu) {
        assert_eq!((gpu.scene, gpu.tick), (cpu.scene, cpu.tick));
        assert_eq!(gpu.npcs.len(), cpu.npcs.len());
        for (g, c) in gpu.npcs.iter().zip(&cpu.npcs) {
            let apart = (g.x_m - c.x_m).hypot(g.y_m - c.y_m);
            assert!(
                apart < 0.05,
                "scene {} tick {}: agent {} {apart} m apart",
                gpu.scene,
                gpu.tick,
                g.id
            );
        }
    }
}
