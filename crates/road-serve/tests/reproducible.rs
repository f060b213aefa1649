//! Issue 41, finding 6: a scene served alone repeats bit for bit for the same request, seed and
//! ego puts, even on a machine busy with other work (the CPU engine used to fall back to one
//! thread when its workers waited for cores, and one worker rounds the default checkpoint's
//! products differently from two).

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use road_client::protocol::AgentState;

/// Every NPC state of 60 ticks of the roundabout with its scripted ego replayed, seed 3.
fn run(name: &str) -> Vec<Vec<AgentState>> {
    let dir = common::temp_dir(name);
    let mut config = common::config(&dir);
    // No late ticks: the model never drives the ego, whatever the machine's load.
    config.late_ego_deadline = std::time::Duration::ZERO;
    let server = common::start(config);
    let c = common::client(&server, name);
    let mut request = common::roundabout();
    request.seed = 3;
    let mut scene = c.create(request).unwrap();
    let ego = scene.created().agents[0].history.clone();
    let states = (1..=60u64)
        .map(|t| {
            scene
                .step(t, vec![common::replay(&ego, 1, t)])
                .unwrap()
                .npcs
        })
        .collect();
    scene.close().unwrap();
    drop(c);
    server.stop().unwrap();
    states
}

#[test]
fn a_scene_served_alone_repeats_bit_for_bit_on_a_busy_machine() {
    // Threads that keep every core busy, so that the engine's workers wait for one.
    let stop = Arc::new(AtomicBool::new(false));
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
    let hogs: Vec<_> = (0..cores)
        .map(|_| {
            let stop = Arc::clone(&stop);
            std::thread::spawn(move || {
                let mut x = 0u64;
                while !stop.load(Ordering::Relaxed) {
                    x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
                }
            })
        })
        .collect();
    let (first, second) = (run("repeat-a"), run("repeat-b"));
    stop.store(true, Ordering::Relaxed);
    for hog in hogs {
        hog.join().unwrap();
    }
    assert_eq!(first.len(), second.len());
    for (t, (a, b)) in first.iter().zip(&second).enumerate() {
        assert_eq!(a, b, "tick {}: the NPCs differ", t + 1);
    }
}
