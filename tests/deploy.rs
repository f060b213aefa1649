//! Deployment and faults on loopback, with `road` as child processes: two servers behind a
//! zenoh router share the scenes of a client that places them on the least-loaded one; zenoh's
//! access control lets only listed clients create scenes; a TLS router takes encrypted links
//! only; a client killed mid-scene has its
//! scene reclaimed and its recording finished; a router restarted between two ticks ends the
//! scene with a clear error and the client goes on with a new one; 16 clients sending ticks as
//! fast as they can get every one answered or refused. `docs/deploy.md` describes the setup.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use road_client::protocol::{
    AgentState, CreateScene, DEFAULT_PREFIX, ErrorCode, ErrorReply, NpcTick,
};
use road_client::{Client, Error, Scene, ZenohArgs};
use zenoh::Wait;

const REPO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../..");

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("road-deploy-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn free_endpoint() -> String {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    format!("tcp/127.0.0.1:{port}")
}

/// A `road` child process, killed when the test ends however it ends.
struct Proc {
    child: Child,
    name: &'static str,
}

impl Proc {
    fn spawn(name: &'static str, args: &[&str]) -> Self {
        let child = Command::new(env!("CARGO_BIN_EXE_road"))
            .args(args)
            .current_dir(REPO)
            // ROAD_TEST_LOG: the children's log filter when debugging a test (default warn).
            .env(
                "RUST_LOG",
                std::env::var("ROAD_TEST_LOG").unwrap_or_else(|_| "warn".into()),
            )
            .stdout(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("{name}: road does not run: {e}"));
        Self { child, name }
    }

    fn assert_running(&mut self) {
        if let Some(status) = self.child.try_wait().unwrap() {
            panic!("{} exited early: {status}", self.name);
        }
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// `road router` listening at `endpoint`, once its port takes connections (servers in client
/// mode give up when their router is not there yet).
fn router(endpoint: &str, extra: &[&str]) -> Proc {
    let mut args = vec!["router", "--listen", endpoint, "--no-multicast-scouting"];
    args.extend_from_slice(extra);
    let mut router = Proc::spawn("road router", &args);
    wait_for_port(&mut router, endpoint.trim_start_matches("tcp/"));
    router
}

/// Waits until `address` takes TCP connections (the router listens).
fn wait_for_port(router: &mut Proc, address: &str) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::net::TcpStream::connect(address).is_err() {
        router.assert_running();
        assert!(
            Instant::now() < deadline,
            "road router never listened on {address}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// `road serve` in client mode behind the router at `endpoint`.
fn server_behind(endpoint: &str, prefix: &str, record: &Path, extra: &[&str]) -> Proc {
    let record = record.to_str().unwrap();
    let mut args = vec![
        "serve",
        "--mode",
        "client",
        "--connect",
        endpoint,
        "--no-multicast-scouting",
        "--prefix",
        prefix,
        "--record",
        record,
    ];
    args.extend_from_slice(extra);
    Proc::spawn("road serve", &args)
}

fn client_args(endpoint: &str, cfg: &[String]) -> ZenohArgs {
    ZenohArgs {
        mode: Some("client".into()),
        connect: vec![endpoint.to_owned()],
        no_multicast_scouting: true,
        cfg: cfg.to_vec(),
        ..ZenohArgs::default()
    }
}

/// Opens a client of the server at `prefix`, retrying while the processes start.
fn connect(args: &ZenohArgs, prefix: &str, id: &str, procs: &mut [&mut Proc]) -> Client {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        for p in procs.iter_mut() {
            p.assert_running();
        }
        if let Ok(mut client) = Client::open(args, prefix, id) {
            client.set_timeout(Duration::from_secs(5));
            if client.status().is_ok() {
                client.set_timeout(Duration::from_secs(120));
                return client;
            }
        }
        assert!(Instant::now() < deadline, "{prefix} did not come up");
        std::thread::sleep(Duration::from_millis(300));
    }
}

fn roundabout(seed: u64) -> CreateScene {
    CreateScene::procedural("roundabout", vec![1], seed)
}

/// The ego's pose at `tick`: its history's last velocity, held.
fn ego_at(scene: &Scene, tick: u64) -> AgentState {
    scene.created().constant_velocity(1, tick).unwrap()
}

/// Creates a roundabout scene, ticks it once and closes it.
fn one_tick_scene(client: &Client, seed: u64) {
    let mut scene = client.create(roundabout(seed)).unwrap();
    assert_eq!(scene.step(1, vec![ego_at(&scene, 1)]).unwrap().tick, 1);
    scene.close().unwrap();
}

/// The NPC ticks of a recording, reading past a missing end (a killed writer).
fn recorded_npc_ticks(path: &Path) -> (Vec<u64>, bool) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let finished = mcap::MessageStream::new(&bytes)
        .map(|stream| stream.into_iter().all(|m| m.is_ok()))
        .unwrap_or(false);
    let mut options = enumset::EnumSet::empty();
    options.insert(mcap::read::Options::IgnoreEndMagic);
    let mut ticks = Vec::new();
    for message in mcap::MessageStream::new_with_options(&bytes, options).unwrap() {
        let Ok(m) = message else { break };
        if m.channel.topic == "/road/npc" {
            let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            ticks.push(v["tick"].as_u64().unwrap());
        }
    }
    (ticks, finished)
}

#[test]
fn two_servers_behind_a_router_share_the_scenes() {
    let dir = temp_dir("two");
    let endpoint = free_endpoint();
    let mut router = router(&endpoint, &[]);
    let mut east = server_behind(&endpoint, "road/east", &dir.join("east"), &[]);
    let mut west = server_behind(&endpoint, "road/west", &dir.join("west"), &[]);
    let args = client_args(&endpoint, &[]);
    // Both up: each answers its status through the router.
    let _east = connect(
        &args,
        "road/east",
        "probe-east",
        &mut [&mut router, &mut east],
    );
    let _west = connect(
        &args,
        "road/west",
        "probe-west",
        &mut [&mut router, &mut west],
    );

    let session = zenoh::open(args.to_config().unwrap()).wait().unwrap();
    let found = road_client::discover(&session, "road", Duration::from_secs(5)).unwrap();
    let prefixes: Vec<&str> = found.servers.iter().map(|s| s.prefix.as_str()).collect();
    assert_eq!(prefixes, ["road/east", "road/west"]);
    assert!(found.unreachable.is_empty(), "{:?}", found.unreachable);

    let mut placed = Vec::new();
    for i in 0..4 {
        let (client, scene) = Client::create_on_least_loaded(
            session.clone(),
            "road",
            &format!("ego-{i}"),
            roundabout(i),
            Duration::from_secs(120),
        )
        .unwrap();
        placed.push((client, scene));
    }
    let on = |prefix: &str| {
        placed
            .iter()
            .filter(|(c, _)| c.keys().prefix() == prefix)
            .count()
    };
    assert_eq!((on("road/east"), on("road/west")), (2, 2));
    // Each server ticks its own scenes.
    for (_, scene) in &placed {
        scene.put(1, vec![ego_at(scene, 1)]).unwrap();
    }
    for (client, scene) in &mut placed {
        let npc = scene.wait_tick(1).unwrap();
        assert_eq!(npc.tick, 1, "{}", client.keys().prefix());
        assert!(!npc.npcs.is_empty());
    }
    for (client, scene) in placed {
        let closed = scene.close().unwrap();
        assert_eq!(closed.ticks, 1);
        let recording = PathBuf::from(closed.recording.unwrap());
        assert!(
            recording.starts_with(dir.join(client.keys().prefix().trim_start_matches("road/"))),
            "{} recorded by {}",
            recording.display(),
            client.keys().prefix()
        );
    }
    // A root with nothing under it finds nothing, and placement there says so.
    let none = road_client::discover(&session, "elsewhere", Duration::from_secs(2)).unwrap();
    assert!(none.servers.is_empty());
    let err = Client::create_on_least_loaded(
        session.clone(),
        "elsewhere",
        "ego-x",
        roundabout(0),
        Duration::from_secs(2),
    )
    .unwrap_err();
    assert!(matches!(err, Error::NoServer { .. }), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_unlisted_client_cannot_create_scenes() {
    let dir = temp_dir("acl");
    let endpoint = free_endpoint();
    let users = format!(
        "transport/auth/usrpwd/dictionary_file:{:?}",
        Path::new(REPO)
            .join("configs/zenoh/users.txt")
            .to_str()
            .unwrap()
    );
    let mut router = router(
        &endpoint,
        &[
            "--config",
            "configs/zenoh/router-acl.json5",
            "--cfg",
            &users,
        ],
    );
    let login = |user: &str, password: &str| {
        vec![
            format!("transport/auth/usrpwd/user:{user:?}"),
            format!("transport/auth/usrpwd/password:{password:?}"),
        ]
    };
    let server_login = login("road-server", "change-me-server");
    // No late-ego deadline: a scene waits for its own client's tick however long it takes.
    let mut server_args: Vec<&str> = vec!["--late-ego-ms", "0"];
    for item in &server_login {
        server_args.extend(["--cfg", item]);
    }
    let mut server = server_behind(&endpoint, DEFAULT_PREFIX, &dir.join("rec"), &server_args);

    // A listed client creates, ticks and closes a scene.
    let listed = client_args(&endpoint, &login("ego-a", "change-me-ego-a"));
    let client = connect(
        &listed,
        DEFAULT_PREFIX,
        "ego-a",
        &mut [&mut router, &mut server],
    );
    one_tick_scene(&client, 0);

    // Each listed client reaches only its own scenes' keys. ego-b, listed, posing as ego-a on
    // ego-a's live scene: its tick never reaches the server (no late-ego deadline here, so
    // the scene waits), and it hears none of the scene.
    let mut scene = client.create(roundabout(2)).unwrap();
    let ego_b = client_args(&endpoint, &login("ego-b", "change-me-ego-b"));
    let impostor = Client::open(&ego_b, DEFAULT_PREFIX, "ego-a").unwrap();
    let stolen = impostor.attach(scene.created().clone()).unwrap();
    stolen.put(1, vec![ego_at(&scene, 1)]).unwrap();
    std::thread::sleep(Duration::from_secs(1));
    // Had the server taken the impostor's tick 1, ego-a's own would be refused as sent.
    assert_eq!(scene.step(1, vec![ego_at(&scene, 1)]).unwrap().tick, 1);
    assert_eq!(stolen.try_npc(Duration::from_secs(1)).unwrap(), None);
    scene.close().unwrap();
    drop(stolen);
    drop(impostor);
    // As itself, ego-b drives scenes of its own.
    one_tick_scene(
        &connect(&ego_b, DEFAULT_PREFIX, "ego-b", &mut [&mut router]),
        3,
    );

    // A client that logs in but is not listed: its creation reaches no server.
    let guest = Client::open(
        &client_args(&endpoint, &login("guest", "change-me-guest")),
        DEFAULT_PREFIX,
        "guest",
    )
    .unwrap();
    let err = guest.create(roundabout(1)).unwrap_err();
    assert!(matches!(err, Error::NoAnswer { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains("road/scenes/create") && text.contains("access control"),
        "{text}"
    );
    // Nor was anything created behind its back.
    assert!(client.status().unwrap().scenes.is_empty());

    // Without a login (or with a wrong password) the router does not even open the link.
    let anonymous = Client::open(&client_args(&endpoint, &[]), DEFAULT_PREFIX, "anon");
    assert!(anonymous.is_err(), "an anonymous client connected");
    let wrong = Client::open(
        &client_args(&endpoint, &login("ego-a", "wrong")),
        DEFAULT_PREFIX,
        "wrong",
    );
    assert!(wrong.is_err(), "a wrong password connected");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A CA and a certificate for "localhost" signed by it, made with the openssl command.
fn localhost_certificates(dir: &Path) {
    let run = |args: &[&str]| {
        let o = Command::new("openssl")
            .args(args)
            .current_dir(dir)
            .output()
            .expect("openssl runs (scripts/install-test-deps.sh installs it)");
        assert!(
            o.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    run(&[
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca-key.pem",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=road-test-ca",
    ]);
    run(&[
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "router-key.pem",
        "-out",
        "router.csr",
        "-subj",
        "/CN=localhost",
    ]);
    std::fs::write(dir.join("san.cnf"), "subjectAltName=DNS:localhost\n").unwrap();
    run(&[
        "x509",
        "-req",
        "-in",
        "router.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca-key.pem",
        "-CAcreateserial",
        "-out",
        "router.pem",
        "-days",
        "2",
        "-extfile",
        "san.cnf",
    ]);
}

#[test]
fn a_tls_router_takes_encrypted_links_only() {
    let dir = temp_dir("tls");
    localhost_certificates(&dir);
    let path = |name: &str| dir.join(name).to_str().unwrap().to_owned();
    let port = free_endpoint()
        .trim_start_matches("tcp/127.0.0.1:")
        .to_owned();
    let endpoint = format!("tls/localhost:{port}");
    let cert = format!(
        "transport/link/tls/listen_certificate:{:?}",
        path("router.pem")
    );
    let key = format!(
        "transport/link/tls/listen_private_key:{:?}",
        path("router-key.pem")
    );
    let ca = format!(
        "transport/link/tls/root_ca_certificate:{:?}",
        path("ca.pem")
    );
    let mut router = Proc::spawn(
        "road router",
        &[
            "router",
            "--config",
            "configs/zenoh/router-tls.json5",
            "--listen",
            &endpoint,
            "--cfg",
            &cert,
            "--cfg",
            &key,
            "--cfg",
            &ca,
        ],
    );
    wait_for_port(&mut router, &format!("localhost:{port}"));
    let mut server = server_behind(&endpoint, DEFAULT_PREFIX, &dir.join("rec"), &["--cfg", &ca]);
    let client = connect(
        &client_args(&endpoint, std::slice::from_ref(&ca)),
        DEFAULT_PREFIX,
        "tls-ego",
        &mut [&mut router, &mut server],
    );
    one_tick_scene(&client, 0);
    // Plain TCP to the TLS port is not a zenoh link.
    let plain = Client::open(
        &client_args(&format!("tcp/127.0.0.1:{port}"), &[]),
        DEFAULT_PREFIX,
        "plain",
    );
    assert!(
        plain.is_err(),
        "a plain TCP client connected to the TLS router"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_killed_clients_scene_is_reclaimed_and_its_recording_finished() {
    let dir = temp_dir("killed-client");
    let endpoint = free_endpoint();
    let record = dir.join("rec");
    let mut server = Proc::spawn(
        "road serve",
        &[
            "serve",
            "--listen",
            &endpoint,
            "--no-multicast-scouting",
            "--idle-timeout-s",
            "3",
            "--record",
            record.to_str().unwrap(),
        ],
    );
    let observer = connect(
        &ZenohArgs::loopback(None, Some(&endpoint)),
        DEFAULT_PREFIX,
        "observer",
        &mut [&mut server],
    );
    let mut ego = Proc::spawn(
        "road ego",
        &[
            "ego",
            "--connect",
            &endpoint,
            "--no-multicast-scouting",
            "--ticks",
            "5000",
            "--quiet",
        ],
    );
    // Let it drive a few ticks, then kill it without warning.
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        ego.assert_running();
        let status = observer.status().unwrap();
        if status.scenes.first().is_some_and(|s| s.tick >= 3) {
            break;
        }
        assert!(Instant::now() < deadline, "the ego never got to tick 3");
        std::thread::sleep(Duration::from_millis(200));
    }
    ego.kill();
    // Reclaimed: its liveliness token goes with its link, or the idle timeout passes.
    let deadline = Instant::now() + Duration::from_secs(60);
    while !observer.status().unwrap().scenes.is_empty() {
        assert!(
            Instant::now() < deadline,
            "the killed client's scene was never closed"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    let recording = record.join("scene-1.mcap");
    let (ticks, finished) = recorded_npc_ticks(&recording);
    assert!(finished, "the reclaimed scene's recording was not finished");
    assert!(ticks.len() >= 3, "{ticks:?}");
    assert_eq!(ticks, (1..=ticks.len() as u64).collect::<Vec<_>>());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_router_restart_between_ticks_ends_the_scene_with_a_clear_error() {
    let dir = temp_dir("router-restart");
    let endpoint = free_endpoint();
    let mut first_router = router(&endpoint, &[]);
    let mut server = server_behind(&endpoint, DEFAULT_PREFIX, &dir.join("rec"), &[]);
    let args = client_args(&endpoint, &[]);
    let client = connect(
        &args,
        DEFAULT_PREFIX,
        "ego",
        &mut [&mut first_router, &mut server],
    );
    let mut scene = client.create(roundabout(0)).unwrap();
    for t in 1..=2 {
        assert_eq!(scene.step(t, vec![ego_at(&scene, t)]).unwrap().tick, t);
    }
    first_router.kill();
    let mut router = router(&endpoint, &[]);
    // The policy (docs/deploy.md): the server saw its client go and closed the scene; the
    // client's next tick fails with an error that says so, instead of hanging.
    let err = scene.step(3, vec![ego_at(&scene, 3)]).unwrap_err();
    // (The put, held back while the link was down, may reach the server after it: then the
    // server itself refuses it for a closed scene.)
    let refused_as_closed = matches!(&err, Error::Refused(e) if e.code == ErrorCode::UnknownScene);
    assert!(
        refused_as_closed || matches!(err, Error::SceneGone { .. } | Error::ServerGone { .. }),
        "{err}"
    );
    // Both ends reconnected by themselves: a new scene runs.
    router.assert_running();
    server.assert_running();
    one_tick_scene(&client, 1);
    let (ticks, finished) = recorded_npc_ticks(&dir.join("rec/scene-1.mcap"));
    assert_eq!(ticks, [1, 2]);
    assert!(finished);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// What came back for one client's burst: NPC ticks and errors, by tick.
#[derive(Default)]
struct Outcomes {
    answered: Vec<u64>,
    refused: Vec<(u64, ErrorCode)>,
}

#[test]
fn sixteen_clients_sending_ticks_as_fast_as_they_can_lose_none() {
    const CLIENTS: usize = 16;
    const TICKS: u64 = 1000;
    let endpoint = free_endpoint();
    let mut server = Proc::spawn(
        "road serve",
        &[
            "serve",
            "--listen",
            &endpoint,
            "--no-multicast-scouting",
            "--no-record",
            "--late-ego-ms",
            "0",
        ],
    );
    let observer = connect(
        &ZenohArgs::loopback(None, Some(&endpoint)),
        DEFAULT_PREFIX,
        "observer",
        &mut [&mut server],
    );
    drop(observer);
    let outcomes: Vec<Outcomes> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..CLIENTS)
            .map(|i| {
                let endpoint = endpoint.clone();
                s.spawn(move || {
                    let mut client = Client::open(
                        &ZenohArgs::loopback(None, Some(&endpoint)),
                        DEFAULT_PREFIX,
                        &format!("burst-{i}"),
                    )
                    .unwrap();
                    client.set_timeout(Duration::from_secs(300));
                    let scene = client.create(roundabout(i as u64)).unwrap();
                    // Every tick 1..=TICKS at once, without waiting: tick 1 is the next one,
                    // the others skip ahead of it.
                    for t in 1..=TICKS {
                        scene.put(t, vec![ego_at(&scene, t)]).unwrap();
                    }
                    let mut out = Outcomes::default();
                    let deadline = Instant::now() + Duration::from_secs(600);
                    while (out.answered.len() + out.refused.len()) < TICKS as usize {
                        assert!(
                            Instant::now() < deadline,
                            "client {i}: {} answered, {} refused of {TICKS}",
                            out.answered.len(),
                            out.refused.len()
                        );
                        while let Some(e) = scene.try_error().unwrap() {
                            let ErrorReply { tick, code, .. } = e;
                            out.refused
                                .push((tick.expect("a tick's error names it"), code));
                        }
                        if let Some(npc) = scene_npc(&scene) {
                            out.answered.push(npc.tick);
                        }
                    }
                    scene.close().unwrap();
                    out
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for (i, out) in outcomes.iter().enumerate() {
        // Tick 1 is answered (and the next ones, had they come after its NPCs: a run of
        // ticks from 1); every other tick is refused once; none is missing or doubled.
        let k = out.answered.len() as u64;
        assert!(k >= 1, "client {i}: tick 1 was not answered");
        assert_eq!(out.answered, (1..=k).collect::<Vec<_>>(), "client {i}");
        let mut refused: Vec<u64> = out.refused.iter().map(|(t, _)| *t).collect();
        refused.sort_unstable();
        assert_eq!(refused, (k + 1..=TICKS).collect::<Vec<_>>(), "client {i}");
        assert!(
            out.refused.iter().all(|(_, c)| *c == ErrorCode::BadTick),
            "client {i}"
        );
    }
}

/// One NPC tick of the scene if one is waiting (a short wait).
fn scene_npc(scene: &Scene) -> Option<NpcTick> {
    scene.try_npc(Duration::from_millis(20)).unwrap()
}
