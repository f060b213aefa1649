//! A server on loopback for the tests: TCP on 127.0.0.1 port 0 (the real port read back),
//! scouting off, checkpoints from the repository's `models/`, recordings in a temp folder.

#![allow(dead_code)]

use std::path::PathBuf;
use std::time::Duration;

use road_client::protocol::{AgentInit, AgentState, CreateScene, Pose};
use road_client::{Client, ZenohArgs};
use road_serve::{ServeConfig, Server, ServerHandle};

/// The repository's models folder.
pub fn models_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models")
}

/// A fresh temp folder for recordings.
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("road-serve-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A config for tests: recordings under `dir`.
pub fn config(dir: &std::path::Path) -> ServeConfig {
    let mut config = ServeConfig::new(Some(models_dir()));
    config.record_dir = Some(dir.to_owned());
    config
}

/// A free loopback port. (Zenoh's API for a session's bound addresses is unstable and leaves
/// loopback out, so port 0 cannot be read back: take one the OS just handed out.)
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Starts a server listening on loopback.
pub fn start(config: ServeConfig) -> ServerHandle {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let zenoh = ZenohArgs::loopback(Some(&endpoint), None)
        .to_config()
        .unwrap();
    Server::new(config, zenoh).start().unwrap()
}

/// A client connected to `server` (its own session), with a 60 s timeout (debug builds, a
/// busy machine: a scene's first tick carries the model's warm-up).
pub fn client(server: &ServerHandle, id: &str) -> Client {
    let locator = server
        .listen_endpoints()
        .into_iter()
        .find(|l| l.starts_with("tcp/127.0.0.1"))
        .expect("the server listens on loopback");
    let args = ZenohArgs::loopback(None, Some(&locator));
    let mut client = Client::open(&args, road_client::protocol::DEFAULT_PREFIX, id).unwrap();
    client.set_timeout(Duration::from_secs(60));
    client
}

/// The procedural roundabout with its own vehicles, agent 1 external.
pub fn roundabout() -> CreateScene {
    CreateScene::procedural("roundabout", vec![1], 0)
}

/// Ten steps of a car driving east at 5 m/s from (x, y).
pub fn straight_agent(id: u32, x: f64, y: f64) -> AgentInit {
    AgentInit {
        id,
        length_m: 4.5,
        width_m: 1.8,
        history: (0..10)
            .map(|k| Pose {
                x_m: x + 0.5 * f64::from(k),
                y_m: y,
                heading_rad: 0.0,
            })
            .collect(),
    }
}

/// The pose of a constant-velocity ego at `tick` from its history.
pub fn replay(history: &[Pose], id: u32, tick: u64) -> AgentState {
    let (last, previous) = (history[history.len() - 1], history[history.len() - 2]);
    let k = tick as f64;
    AgentState {
        id,
        x_m: last.x_m + (last.x_m - previous.x_m) * k,
        y_m: last.y_m + (last.y_m - previous.y_m) * k,
        heading_rad: last.heading_rad,
    }
}

/// Every NPC state is finite and within `radius_m` of the origin of the map's frame.
pub fn assert_sane(npc: &road_client::protocol::NpcTick, radius_m: f64) {
    for a in &npc.npcs {
        assert!(
            a.x_m.is_finite() && a.y_m.is_finite() && a.heading_rad.is_finite(),
            "tick {}: {a:?}",
            npc.tick
        );
        assert!(
            a.x_m.hypot(a.y_m) < radius_m,
            "tick {}: {a:?} left the map",
            npc.tick
        );
    }
    // The reply's time split: compute and the wait for other scenes' rounds are parts of the
    // latency.
    assert!(
        npc.compute_ms >= 0.0
            && npc.queue_ms >= 0.0
            && npc.compute_ms + npc.queue_ms <= npc.latency_ms + 1e-6,
        "tick {}: latency {} ms, compute {} ms, queue {} ms",
        npc.tick,
        npc.latency_ms,
        npc.compute_ms,
        npc.queue_ms
    );
}
