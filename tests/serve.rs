//! End-to-end tests of `road serve` as a child process: it finds its checkpoints from anywhere,
//! says which paths it tried when it cannot, and its recordings survive a SIGKILL up to the
//! last flushed chunk (while its client's next tick fails with the reason).

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use road_client::protocol::{CreateScene, DEFAULT_PREFIX};
use road_client::{Client, ZenohArgs};

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("road-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Kills the child when the test ends, however it ends.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Connects a client, retrying while the server starts (it loads its checkpoint first).
fn connect(endpoint: &str, server: &mut Server) -> Client {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        if let Some(status) = server.0.try_wait().unwrap() {
            panic!("road serve exited early: {status}");
        }
        let args = ZenohArgs::loopback(None, Some(endpoint));
        if let Ok(mut client) = Client::open(&args, DEFAULT_PREFIX, "sigkill") {
            client.set_timeout(Duration::from_secs(5));
            if client.status().is_ok() {
                client.set_timeout(Duration::from_secs(60));
                return client;
            }
        }
        assert!(Instant::now() < deadline, "road serve did not come up");
        std::thread::sleep(Duration::from_millis(300));
    }
}

#[test]
fn a_killed_servers_recording_reads_back_to_its_last_chunk() {
    let cwd = temp_dir("sigkill");
    let record = cwd.join("rec");
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    // From a folder with no models/: the binary finds the repository's beside itself.
    let mut server = Server(
        Command::new(env!("CARGO_BIN_EXE_road"))
            .args(["serve", "--listen", &endpoint, "--no-multicast-scouting"])
            .args(["--late-ego-ms", "0", "--record"])
            .arg(&record)
            .current_dir(&cwd)
            .env("RUST_LOG", "warn")
            .env_remove("ROAD_MODELS")
            .stdout(Stdio::null())
            .spawn()
            .expect("road runs"),
    );
    let client = connect(&endpoint, &mut server);
    let mut scene = client
        .create(CreateScene::procedural("roundabout", vec![1], 0))
        .unwrap();
    let path = PathBuf::from(scene.created().recording.clone().unwrap());
    let ticks = 5u64;
    for t in 1..=ticks {
        let ego = scene.created().constant_velocity(1, t).unwrap();
        assert_eq!(scene.step(t, vec![ego]).unwrap().tick, t);
    }
    // Chunks are written out at least once a second.
    std::thread::sleep(Duration::from_millis(1500));
    // SIGKILL: no chance to finish the file.
    server.0.kill().unwrap();
    server.0.wait().unwrap();
    // The client's next tick fails at once with the reason instead of hanging.
    let ego = scene.created().constant_velocity(1, ticks + 1).unwrap();
    let err = scene.step(ticks + 1, vec![ego]).unwrap_err();
    assert!(
        matches!(err, road_client::Error::ServerGone { .. }),
        "{err}"
    );
    let bytes = std::fs::read(record.join(path.file_name().unwrap())).unwrap();
    let mut options = enumset::EnumSet::empty();
    options.insert(mcap::read::Options::IgnoreEndMagic);
    let mut npc_ticks = Vec::new();
    let mut topics = std::collections::BTreeSet::new();
    // The file ends mid-way (no summary, no end magic): read until the stream stops.
    for message in mcap::MessageStream::new_with_options(&bytes, options).unwrap() {
        let Ok(m) = message else { break };
        topics.insert(m.channel.topic.clone());
        if m.channel.topic == "/road/npc" {
            let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            npc_ticks.push(v["tick"].as_u64().unwrap());
        }
    }
    assert_eq!(npc_ticks, (1..=ticks).collect::<Vec<_>>());
    for t in ["/road/create", "/road/ego", "/map", "/agents"] {
        assert!(topics.contains(t), "{t} missing from {topics:?}");
    }
    // A finished file would have its summary; this one must not (it really was killed).
    assert!(
        mcap::MessageStream::new(&bytes)
            .unwrap()
            .any(|m| m.is_err())
    );
}

#[test]
fn serve_names_the_models_paths_it_tried() {
    let o = Command::new(env!("CARGO_BIN_EXE_road"))
        .args([
            "serve",
            "--models",
            "/nonexistent/models",
            "--no-multicast-scouting",
        ])
        .env("RUST_LOG", "warn")
        .output()
        .expect("road runs");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("/nonexistent/models"), "{err}");
    assert!(err.contains("ROAD_MODELS"), "{err}");
}
