//! End-to-end tests of `road serve` as a child process: it finds its checkpoints from anywhere,
//! says which paths it tried when it cannot, and its recordings survive a SIGKILL up to the
//! last flushed chunk (while its client's next tick fails with the reason): `road recover`
//! rewrites such a file whole for the default readers, and so does the next server at start.

use std::path::{Path, PathBuf};
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

/// `road serve` on loopback from `cwd` (a folder with no models/: the binary finds the
/// repository's beside itself), recording to `record`, its log in `log`.
fn serve(cwd: &Path, record: &Path, endpoint: &str, log: &Path) -> Server {
    Server(
        Command::new(env!("CARGO_BIN_EXE_road"))
            .args(["serve", "--listen", endpoint, "--no-multicast-scouting"])
            .args(["--late-ego-ms", "0", "--record"])
            .arg(record)
            .current_dir(cwd)
            .env("RUST_LOG", "warn")
            .env_remove("ROAD_MODELS")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .expect("road runs"),
    )
}

/// A server recording to `record` runs one scene for `ticks` ticks and is killed (SIGKILL)
/// after its last flush; the client's next tick fails at once with the reason. Returns the
/// scene's recording, as the killed server left it.
fn killed_servers_recording(cwd: &Path, record: &Path, ticks: u64) -> PathBuf {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let mut server = serve(cwd, record, &endpoint, &cwd.join("killed.log"));
    let client = connect(&endpoint, &mut server);
    let mut scene = client
        .create(CreateScene::procedural("roundabout", vec![1], 0))
        .unwrap();
    let path = PathBuf::from(scene.created().recording.clone().unwrap());
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
    record.join(path.file_name().unwrap())
}

/// The NPC ticks of a whole recording, read as the default readers read: from its summary,
/// then every message without an error.
fn npc_ticks_of_a_whole_file(bytes: &[u8]) -> (Vec<u64>, usize) {
    let summary = mcap::Summary::read(bytes).unwrap().expect("a summary");
    assert!(!summary.chunk_indexes.is_empty());
    let messages: Vec<mcap::Message> = mcap::MessageStream::new(bytes)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let ticks = messages
        .iter()
        .filter(|m| m.channel.topic == "/road/npc")
        .map(|m| {
            serde_json::from_slice::<serde_json::Value>(&m.data).unwrap()["tick"]
                .as_u64()
                .unwrap()
        })
        .collect();
    (ticks, messages.len())
}

/// `road recover FILE…`: its exit status, stdout and stderr.
fn road_recover(files: &[&Path]) -> (bool, String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_road"))
        .arg("recover")
        .args(files)
        .env("RUST_LOG", "warn")
        .output()
        .expect("road runs");
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn a_killed_servers_recording_reads_back_to_its_last_chunk() {
    let cwd = temp_dir("sigkill");
    let record = cwd.join("rec");
    let ticks = 5u64;
    let file = killed_servers_recording(&cwd, &record, ticks);
    let bytes = std::fs::read(&file).unwrap();
    let mut options = enumset::EnumSet::empty();
    options.insert(mcap::read::Options::IgnoreEndMagic);
    let mut npc_ticks = Vec::new();
    let mut topics = std::collections::BTreeSet::new();
    let mut streamed = 0;
    // The file ends mid-way (no summary, no end magic): read until the stream stops.
    for message in mcap::MessageStream::new_with_options(&bytes, options).unwrap() {
        let Ok(m) = message else { break };
        streamed += 1;
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
    // A finished file would have its summary; this one must not (it really was killed), and
    // the default readers, which start from the summary, cannot read it.
    assert!(
        mcap::MessageStream::new(&bytes)
            .unwrap()
            .any(|m| m.is_err())
    );
    assert!(!matches!(mcap::Summary::read(&bytes), Ok(Some(_))));

    // `road recover` rewrites it whole: the default readers read every message streamed.
    let (ok, stdout, stderr) = road_recover(&[&file]);
    assert!(ok, "{stdout}{stderr}");
    assert!(
        stdout.contains(&format!(
            "{}: recovered {streamed} messages",
            file.display()
        )),
        "{stdout}"
    );
    let recovered = std::fs::read(&file).unwrap();
    let (ticks_read, messages) = npc_ticks_of_a_whole_file(&recovered);
    assert_eq!(ticks_read, npc_ticks);
    assert_eq!(messages, streamed);
    let mut recovering = file.file_name().unwrap().to_owned();
    recovering.push(".recovering");
    assert!(!file.with_file_name(recovering).exists());
    // Once more: nothing to do, nothing touched.
    let (ok, stdout, stderr) = road_recover(&[&file]);
    assert!(ok, "{stdout}{stderr}");
    assert!(stdout.contains("already complete"), "{stdout}");
    assert_eq!(std::fs::read(&file).unwrap(), recovered);
    // A file that is not MCAP: an error naming it, the other files still done.
    let text = cwd.join("notes.mcap");
    std::fs::write(&text, "not a recording").unwrap();
    let (ok, stdout, stderr) = road_recover(&[&text, &file]);
    assert!(!ok);
    assert!(stderr.contains(&text.display().to_string()), "{stderr}");
    assert!(stdout.contains("already complete"), "{stdout}");
    std::fs::remove_dir_all(&cwd).ok();
}

#[test]
fn a_restarted_server_recovers_the_recordings_its_killed_predecessor_left() {
    let cwd = temp_dir("restart");
    let record = cwd.join("rec");
    let ticks = 4u64;
    let file = killed_servers_recording(&cwd, &record, ticks);
    let cut = std::fs::read(&file).unwrap();
    assert!(!matches!(mcap::Summary::read(&cut), Ok(Some(_))));
    // A file of the same folder that is not the server's own: left as it is.
    let other = record.join("kept.mcap");
    std::fs::write(&other, &cut).unwrap();

    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let log = cwd.join("restarted.log");
    let mut server = serve(&cwd, &record, &endpoint, &log);
    // The server answers once it has started, and it recovers before it declares any key.
    let client = connect(&endpoint, &mut server);
    let (npc_ticks, _) = npc_ticks_of_a_whole_file(&std::fs::read(&file).unwrap());
    assert_eq!(npc_ticks, (1..=ticks).collect::<Vec<_>>());
    assert_eq!(std::fs::read(&other).unwrap(), cut);
    let log_text = std::fs::read_to_string(&log).unwrap();
    assert!(
        log_text.contains("recovered a recording cut off by a killed server")
            && log_text.contains(&file.display().to_string()),
        "{log_text}"
    );

    // The new server's own scene takes a new name, and `road recover` leaves its file alone
    // while the server writes it.
    let mut scene = client
        .create(CreateScene::procedural("roundabout", vec![1], 0))
        .unwrap();
    let live = PathBuf::from(scene.created().recording.clone().unwrap());
    assert_ne!(live.file_name(), file.file_name());
    let ego = scene.created().constant_velocity(1, 1).unwrap();
    assert_eq!(scene.step(1, vec![ego]).unwrap().tick, 1);
    let (ok, stdout, stderr) = road_recover(&[&live]);
    assert!(!ok, "{stdout}");
    assert!(
        stderr.contains("being written by a running server"),
        "{stderr}"
    );
    scene.close().unwrap();
    drop(server);
    std::fs::remove_dir_all(&cwd).ok();
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
