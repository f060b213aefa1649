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

/// A fresh temp folder for recordings, removed when dropped unless the test is failing (its
/// recordings are then kept to look at).
pub fn temp_dir(name: &str) -> TempFolder {
    let dir = std::env::temp_dir().join(format!("road-serve-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    TempFolder(dir)
}

/// A temp folder for a server held in a `static`, which is never dropped, so its folder outlives
/// the process: the folders of earlier runs (the same name, any other process, last written
/// over an hour ago) are swept first, so that repeated test runs do not pile up in the temp folder.
pub fn static_temp_dir(name: &str) -> TempFolder {
    const STALE_AFTER: Duration = Duration::from_secs(3600);
    let prefix = format!("road-serve-{name}-");
    let own = format!("{prefix}{}", std::process::id());
    if let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) {
        for entry in entries.flatten() {
            let file_name = entry.file_name();
            let file_name = file_name.to_string_lossy();
            let earlier_run = file_name
                .strip_prefix(&prefix)
                .is_some_and(|pid| pid.bytes().all(|b| b.is_ascii_digit()))
                && *file_name != own;
            let stale = entry
                .metadata()
                .and_then(|m| m.modified())
                .ok()
                .and_then(|t| t.elapsed().ok())
                .is_some_and(|age| age > STALE_AFTER);
            if earlier_run && stale {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
    }
    temp_dir(name)
}

/// A folder [`temp_dir`] made; bind it for as long as the server writes there.
pub struct TempFolder(PathBuf);

impl std::ops::Deref for TempFolder {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        &self.0
    }
}

impl AsRef<std::path::Path> for TempFolder {
    fn as_ref(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempFolder {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
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

/// A Lanelet2 map of one straight lanelet along +x, 111 m long and 4.4 m wide from lat/lon
/// (0, 0) (`lanelets: false`: its two ways and no lanelet).
pub fn osm(lanelets: bool) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<osm version=\"0.6\">\n");
    for (id, lat, lon) in [
        (1, 0.0, 0.0),
        (2, 0.0, 0.001),
        (3, 0.00004, 0.0),
        (4, 0.00004, 0.001),
    ] {
        s += &format!("  <node id=\"{id}\" lat=\"{lat}\" lon=\"{lon}\"/>\n");
    }
    s += "  <way id=\"10\"><nd ref=\"3\"/><nd ref=\"4\"/></way>\n";
    s += "  <way id=\"11\"><nd ref=\"1\"/><nd ref=\"2\"/></way>\n";
    if lanelets {
        s += "  <relation id=\"100\"><member type=\"way\" ref=\"10\" role=\"left\"/><member type=\"way\" ref=\"11\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/><tag k=\"subtype\" v=\"road\"/></relation>\n";
    }
    s += "</osm>\n";
    s
}
