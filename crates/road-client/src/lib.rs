//! A typed Rust client of road's NPC server (`road serve`): create a scene, step it tick by
//! tick with the ego's poses, close it. The messages are `road-protocol`'s (re-exported here);
//! `docs/protocol.md` documents the keys and the JSON.
//!
//! ```no_run
//! use road_client::{Client, ZenohArgs, protocol::*};
//! # fn main() -> Result<(), road_client::Error> {
//! let client = Client::open(&ZenohArgs::default(), DEFAULT_PREFIX, "my-ego")?;
//! let mut scene = client.create(CreateScene::procedural("roundabout", vec![1], 0))?;
//! // Agent 1 (ours) one step on at its last velocity.
//! let ego = scene.created().constant_velocity(1, 1).expect("agent 1 has a history");
//! let npcs = scene.step(1, vec![ego])?;
//! println!("{} NPCs at tick {}", npcs.npcs.len(), npcs.tick);
//! scene.close()?;
//! # Ok(()) }
//! ```

mod discovery;

pub use discovery::{Discovered, ServerInfo, discover};

mod inbox;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, TryRecvError};
use std::time::{Duration, Instant};

use zenoh::Wait;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};

use inbox::Inbox;

pub use road_protocol as protocol;
use road_protocol::{
    AgentState, CloseScene, CreateScene, EgoTick, ErrorCode, ErrorReply, Keys, NpcTick,
    SceneClosed, SceneCreated, SceneStatus, Status,
};

/// Errors of the client: the server refused (its [`ErrorReply`]), nothing came in time, or
/// zenoh failed.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("the server refused: {0}")]
    Refused(ErrorReply),
    #[error("no answer within {timeout:?} to {what}")]
    Timeout { what: String, timeout: Duration },
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("bad zenoh config: {reason} ({input})")]
    Config { input: String, reason: String },
    #[error(
        "the server at {prefix} went away (its liveliness token is gone: it stopped, or the \
         network between, e.g. a zenoh router, was cut); its scenes are closed"
    )]
    ServerGone { prefix: String },
    #[error(
        "scene {scene} is gone from the server at {prefix}: it closed the scene while this \
         client was cut off (e.g. a zenoh router restarted), so the tick will not come"
    )]
    SceneGone { scene: u64, prefix: String },
    #[error(
        "nobody answered the query on {key}: no server has that prefix, or zenoh's access \
         control refused this client (docs/deploy.md)"
    )]
    NoAnswer { key: String },
    #[error("no server under {root} has room for a scene{unreachable}")]
    NoServer { root: String, unreachable: String },
    #[error("unreadable reply on {key}: {reason}")]
    Reply { key: String, reason: String },
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl From<zenoh::Error> for Error {
    fn from(e: zenoh::Error) -> Self {
        Error::Zenoh(e.to_string())
    }
}

/// The zenoh session's config: a json5 file plus the overrides the zenoh examples take, with
/// the same flags.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ZenohArgs {
    /// A zenoh json5 config file.
    #[arg(short = 'c', long = "config")]
    pub config: Option<PathBuf>,
    /// Per-key overrides of the config, `KEY:VALUE` with VALUE in json5
    /// (`--cfg 'scouting/multicast/enabled:false'`).
    #[arg(long = "cfg")]
    pub cfg: Vec<String>,
    /// Endpoints to connect to (`tcp/127.0.0.1:7447`).
    #[arg(short = 'e', long = "connect")]
    pub connect: Vec<String>,
    /// Endpoints to listen on (`tcp/127.0.0.1:0` picks a free port).
    #[arg(short = 'l', long = "listen")]
    pub listen: Vec<String>,
    /// `peer`, `client` or `router`.
    #[arg(short = 'm', long = "mode")]
    pub mode: Option<String>,
    /// Turn multicast scouting off (tests, containers).
    #[arg(long = "no-multicast-scouting")]
    pub no_multicast_scouting: bool,
}

impl ZenohArgs {
    /// The zenoh config these arguments describe.
    pub fn to_config(&self) -> Result<zenoh::Config> {
        let bad = |input: &str, e: &dyn std::fmt::Display| Error::Config {
            input: input.to_owned(),
            reason: e.to_string(),
        };
        let mut config = match &self.config {
            Some(path) => zenoh::Config::from_file(path)
                .map_err(|e| bad(&format!("--config {}", path.display()), &e))?,
            None => zenoh::Config::default(),
        };
        if let Some(mode) = &self.mode {
            if !["peer", "client", "router"].contains(&mode.as_str()) {
                return Err(bad(
                    &format!("--mode {mode}"),
                    &"expected peer, client or router",
                ));
            }
            config
                .insert_json5("mode", &format!("\"{mode}\""))
                .map_err(|e| bad(&format!("--mode {mode}"), &e))?;
        }
        let list =
            |items: &[String]| serde_json::to_string(items).expect("a list of strings serialises");
        if !self.connect.is_empty() {
            config
                .insert_json5("connect/endpoints", &list(&self.connect))
                .map_err(|e| bad(&format!("--connect {}", self.connect.join(",")), &e))?;
        }
        if !self.listen.is_empty() {
            config
                .insert_json5("listen/endpoints", &list(&self.listen))
                .map_err(|e| bad(&format!("--listen {}", self.listen.join(",")), &e))?;
        }
        if self.no_multicast_scouting {
            config
                .insert_json5("scouting/multicast/enabled", "false")
                .map_err(|e| bad("--no-multicast-scouting", &e))?;
        }
        for item in &self.cfg {
            let (key, value) = item
                .split_once(':')
                .ok_or_else(|| bad(&format!("--cfg {item}"), &"expected KEY:VALUE"))?;
            config
                .insert_json5(key, value)
                .map_err(|e| bad(&format!("--cfg {item}"), &e))?;
        }
        Ok(config)
    }

    /// Loopback only: listen on `listen` (or nowhere), connect to `connect`, scouting off.
    pub fn loopback(listen: Option<&str>, connect: Option<&str>) -> Self {
        Self {
            listen: listen.map(str::to_owned).into_iter().collect(),
            connect: connect.map(str::to_owned).into_iter().collect(),
            mode: Some("peer".into()),
            no_multicast_scouting: true,
            ..Self::default()
        }
    }
}

/// A client of one server: its session, its id and its liveliness token (while the client
/// lives, the server keeps its scenes).
///
/// A client subscribes once, not once a scene: to its scenes' NPC states and errors (handed to
/// each [`Scene`] by scene id) and to the server's liveliness token. Per-scene subscriptions
/// leave a routing-table entry per scene behind in zenoh (in the server, in every router)
/// for as long as the client's session lives (`docs/experiments/bench-2026-11-24-soak.md`).
#[derive(Debug)]
pub struct Client {
    session: zenoh::Session,
    keys: Keys,
    id: String,
    timeout: Duration,
    inbox: Arc<Inbox>,
    /// How many times the server's liveliness token went away since this client started.
    server_losses: Arc<AtomicU64>,
    _token: LivelinessToken,
    _npc: Subscriber<()>,
    _errors: Subscriber<()>,
    _server_alive: Subscriber<()>,
}

impl Client {
    /// Opens a session from `args` (see [`ZenohArgs`]) and announces the client `id`.
    pub fn open(args: &ZenohArgs, prefix: &str, id: &str) -> Result<Self> {
        let session = zenoh::open(args.to_config()?).wait()?;
        Self::with_session(session, prefix, id)
    }

    /// A client on an open session.
    pub fn with_session(session: zenoh::Session, prefix: &str, id: &str) -> Result<Self> {
        if !road_protocol::valid_client_id(id) {
            return Err(Error::Config {
                input: format!("client id {id:?}"),
                reason: "expected 1 to 64 ASCII letters, digits, '-' or '_'".into(),
            });
        }
        let keys = Keys::new(prefix);
        let inbox = Arc::new(Inbox::default());
        let subscribe = |key: String| {
            let inbox = inbox.clone();
            session
                .declare_subscriber(key)
                .callback(move |sample| inbox.deliver(sample))
                .wait()
        };
        let npc = subscribe(keys.client_npc_any(id))?;
        let errors = subscribe(keys.client_error_any(id))?;
        let server_losses = Arc::new(AtomicU64::new(0));
        let server_alive = {
            let losses = server_losses.clone();
            session
                .liveliness()
                .declare_subscriber(keys.server_alive())
                .callback(move |sample| {
                    if sample.kind() == SampleKind::Delete {
                        losses.fetch_add(1, Ordering::SeqCst);
                    }
                })
                .wait()?
        };
        let token = session
            .liveliness()
            .declare_token(keys.client_alive(id))
            .wait()?;
        Ok(Self {
            session,
            keys,
            id: id.to_owned(),
            timeout: Duration::from_secs(30),
            inbox,
            server_losses,
            _token: token,
            _npc: npc,
            _errors: errors,
            _server_alive: server_alive,
        })
    }

    /// How long a request or a tick may take before [`Error::Timeout`] (30 s by default: a
    /// scene's first tick includes the model's warm-up).
    pub fn set_timeout(&mut self, timeout: Duration) {
        self.timeout = timeout;
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    pub fn keys(&self) -> &Keys {
        &self.keys
    }

    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// Sends `payload` to the queryable at `key`: its reply's bytes, or its error reply.
    pub fn query_raw(&self, key: &str, payload: Vec<u8>) -> Result<Result<Vec<u8>, ErrorReply>> {
        query_raw(&self.session, key, payload, self.timeout)
    }

    fn query<T: serde::de::DeserializeOwned>(&self, key: &str, payload: Vec<u8>) -> Result<T> {
        let bytes = self.query_raw(key, payload)?.map_err(Error::Refused)?;
        parse_reply(key, &bytes)
    }

    /// Creates a scene (the request's `client` is set to this client) and subscribes to its
    /// NPC states and errors.
    pub fn create(&self, mut request: CreateScene) -> Result<Scene> {
        request.client = Some(self.id.clone());
        let payload = serde_json::to_vec(&request).expect("requests serialise");
        let created: SceneCreated = self.query(&self.keys.create(), payload)?;
        self.attach(created)
    }

    /// A handle on a scene of this client's created elsewhere (its reply known). One handle a
    /// scene: attaching it again takes its messages away from the earlier handle.
    pub fn attach(&self, created: SceneCreated) -> Result<Scene> {
        let (npc, errors) = self.inbox.open(created.scene);
        Ok(Scene {
            session: self.session.clone(),
            keys: self.keys.clone(),
            client: self.id.clone(),
            timeout: self.timeout,
            created,
            inbox: self.inbox.clone(),
            npc,
            errors,
            server_losses: self.server_losses.clone(),
            server_losses_before: self.server_losses.load(Ordering::SeqCst),
            last: None,
        })
    }

    /// Finds the servers under `root` (see [`discover`]) and creates the scene on the
    /// least-loaded one with room: the client of that server (keep it: its liveliness token
    /// keeps the scene) and the scene.
    pub fn create_on_least_loaded(
        session: zenoh::Session,
        root: &str,
        id: &str,
        request: CreateScene,
        timeout: Duration,
    ) -> Result<(Client, Scene)> {
        let found = discover(&session, root, timeout)?;
        let Some(server) = found.least_loaded() else {
            let unreachable: String = found
                .unreachable
                .iter()
                .map(|(prefix, e)| format!("; {prefix} did not answer: {e}"))
                .collect();
            return Err(Error::NoServer {
                root: root.to_owned(),
                unreachable: format!(" ({} found{unreachable})", found.servers.len()),
            });
        };
        let mut client = Client::with_session(session, &server.prefix, id)?;
        client.set_timeout(timeout);
        let scene = client.create(request)?;
        Ok((client, scene))
    }

    /// The server's status.
    pub fn status(&self) -> Result<Status> {
        self.query(&self.keys.status(), Vec::new())
    }

    /// One live scene's line of the status (`status?scene=<id>`); [`Error::Refused`] with
    /// `unknown_scene` when the server holds no such scene.
    pub fn scene_status(&self, scene: u64) -> Result<SceneStatus> {
        self.query(&format!("{}?scene={scene}", self.keys.status()), Vec::new())
    }

    /// Closes a scene by id, with its secret (`SceneCreated::token`; [`Scene::close`] knows
    /// it).
    pub fn close_scene(&self, scene: u64, token: &str) -> Result<SceneClosed> {
        let payload = serde_json::to_vec(&CloseScene {
            scene,
            client: self.id.clone(),
            token: token.to_owned(),
        })
        .expect("requests serialise");
        self.query(&self.keys.close(), payload)
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        // Its scenes' waits end with an error instead of running to their timeout.
        self.inbox.close_all();
    }
}

/// How often a scene waiting for its tick asks the server whether it still holds the scene.
pub const PROBE_INTERVAL: Duration = Duration::from_secs(1);

/// One live scene: put the ego, read the NPCs.
#[derive(Debug)]
pub struct Scene {
    session: zenoh::Session,
    keys: Keys,
    client: String,
    timeout: Duration,
    created: SceneCreated,
    inbox: Arc<Inbox>,
    /// This scene's NPC ticks and errors, from the client's subscription.
    npc: Receiver<Sample>,
    errors: Receiver<Sample>,
    /// The server's liveliness token going away ends a wait at once ([`Error::ServerGone`]):
    /// the client's count of losses against its value when the scene was attached.
    server_losses: Arc<AtomicU64>,
    server_losses_before: u64,
    last: Option<NpcTick>,
}

impl Drop for Scene {
    fn drop(&mut self) {
        self.inbox.close(self.created.scene);
    }
}

impl Scene {
    /// The creation reply: scene id, agents, keys.
    pub fn created(&self) -> &SceneCreated {
        &self.created
    }

    pub fn id(&self) -> u64 {
        self.created.scene
    }

    /// The last NPC tick received.
    pub fn last(&self) -> Option<&NpcTick> {
        self.last.as_ref()
    }

    /// Puts the external agents' poses for `tick` without waiting.
    pub fn put(&self, tick: u64, agents: Vec<AgentState>) -> Result<()> {
        let msg = EgoTick {
            tick,
            agents,
            client: self.client.clone(),
            token: self.created.token.clone(),
        };
        self.put_raw(serde_json::to_vec(&msg).expect("ticks serialise"))
    }

    /// Puts any payload on the scene's ego key (tests of the server's input checks).
    pub fn put_raw(&self, payload: Vec<u8>) -> Result<()> {
        // Block, not zenoh's default Drop: a tick is never lost to a full queue.
        self.session
            .put(self.keys.ego(&self.client, self.created.scene), payload)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .wait()?;
        Ok(())
    }

    /// Puts the external agents' poses for `tick` and waits for the NPCs of that tick; an
    /// error the server publishes for this scene meanwhile is returned as
    /// [`Error::Refused`].
    pub fn step(&mut self, tick: u64, agents: Vec<AgentState>) -> Result<NpcTick> {
        self.put(tick, agents)?;
        self.wait_tick(tick)
    }

    /// Waits for the NPCs of `tick` (skipping older ticks). Fails with [`Error::ServerGone`]
    /// as soon as the server's liveliness token goes, and with [`Error::SceneGone`] when the
    /// server, asked every [`PROBE_INTERVAL`] of waiting, no longer lists the scene (it closed
    /// it while this client was cut off, and its error then never came), rather than at the
    /// timeout.
    pub fn wait_tick(&mut self, tick: u64) -> Result<NpcTick> {
        let deadline = Instant::now() + self.timeout;
        // Clients waiting in lockstep would ask together: each scene's probes are offset by
        // up to half an interval, by its id.
        let offset = PROBE_INTERVAL.mul_f64((self.created.scene % 64) as f64 / 128.0);
        let mut next_probe = Instant::now() + PROBE_INTERVAL + offset;
        loop {
            if Instant::now() >= next_probe {
                self.probe_scene()?;
                next_probe = Instant::now() + PROBE_INTERVAL;
            }
            if let Some(err) = self.try_error()? {
                return Err(Error::Refused(err));
            }
            self.check_server()?;
            let sample = received(self.npc.recv_timeout(Duration::from_millis(20)))?;
            if let Some(sample) = sample {
                let bytes = sample.payload().to_bytes();
                let npc: NpcTick = serde_json::from_slice(&bytes).map_err(|e| Error::Reply {
                    key: self.created.npc_key.clone(),
                    reason: e.to_string(),
                })?;
                let done = npc.tick >= tick;
                self.last = Some(npc);
                if done {
                    return Ok(self.last.clone().expect("just set"));
                }
            } else if Instant::now() > deadline {
                return Err(Error::Timeout {
                    what: format!("tick {tick} of scene {}", self.created.scene),
                    timeout: self.timeout,
                });
            }
        }
    }

    /// [`Error::SceneGone`] when the server says it holds no such scene; nothing when it does
    /// not answer (the wait goes on: a router may be coming back). It asks for this scene's
    /// status alone (`status?scene=<id>`): the whole status grows with the server's scenes,
    /// and every waiting client asks. A server before that query answers the whole status,
    /// which is read the old way.
    fn probe_scene(&self) -> Result<()> {
        let key = format!("{}?scene={}", self.keys.status(), self.created.scene);
        let gone = match query_raw(&self.session, &key, Vec::new(), PROBE_INTERVAL) {
            Ok(Ok(bytes)) => match parse_reply::<SceneStatus>(&key, &bytes) {
                Ok(_) => false,
                Err(_) => {
                    let status: Status = parse_reply(&key, &bytes)?;
                    !status.scenes.iter().any(|s| s.scene == self.created.scene)
                }
            },
            Ok(Err(refused)) => refused.code == ErrorCode::UnknownScene,
            Err(_) => false,
        };
        if !gone {
            return Ok(());
        }
        // The NPCs may have come (and the scene closed at its last tick) meanwhile.
        if let Some(err) = self.try_error()? {
            return Err(Error::Refused(err));
        }
        Err(Error::SceneGone {
            scene: self.created.scene,
            prefix: self.keys.prefix().to_owned(),
        })
    }

    /// [`Error::ServerGone`] once the server's liveliness token has gone.
    pub fn check_server(&self) -> Result<()> {
        if self.server_losses.load(Ordering::SeqCst) > self.server_losses_before {
            return Err(Error::ServerGone {
                prefix: self.keys.prefix().to_owned(),
            });
        }
        Ok(())
    }

    /// The next NPC tick of this scene, waiting up to `timeout` for it (`None` if none came).
    pub fn try_npc(&self, timeout: Duration) -> Result<Option<NpcTick>> {
        received(self.npc.recv_timeout(timeout))?
            .map(|sample| {
                serde_json::from_slice(&sample.payload().to_bytes()).map_err(|e| Error::Reply {
                    key: self.created.npc_key.clone(),
                    reason: e.to_string(),
                })
            })
            .transpose()
    }

    /// An error the server published for this scene, if one is waiting.
    pub fn try_error(&self) -> Result<Option<ErrorReply>> {
        let sample = match self.errors.try_recv() {
            Ok(sample) => Some(sample),
            Err(TryRecvError::Empty) => None,
            Err(TryRecvError::Disconnected) => return Err(closed_subscription()),
        };
        match sample {
            Some(sample) => {
                let bytes = sample.payload().to_bytes();
                serde_json::from_slice(&bytes)
                    .map(Some)
                    .map_err(|e| Error::Reply {
                        key: self.created.error_key.clone(),
                        reason: e.to_string(),
                    })
            }
            None => Ok(None),
        }
    }

    /// Waits up to `timeout` for an error on this scene's error key.
    pub fn wait_error(&self, timeout: Duration) -> Result<Option<ErrorReply>> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(e) = self.try_error()? {
                return Ok(Some(e));
            }
            if Instant::now() > deadline {
                return Ok(None);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Closes the scene.
    pub fn close(self) -> Result<SceneClosed> {
        let payload = serde_json::to_vec(&CloseScene {
            scene: self.created.scene,
            client: self.client.clone(),
            token: self.created.token.clone(),
        })
        .expect("requests serialise");
        let key = self.keys.close();
        let bytes =
            query_raw(&self.session, &key, payload, self.timeout)?.map_err(Error::Refused)?;
        parse_reply(&key, &bytes)
    }
}

/// A receive that timed out is `None`; the subscription's end (its client dropped) an error.
fn received(result: Result<Sample, RecvTimeoutError>) -> Result<Option<Sample>> {
    match result {
        Ok(sample) => Ok(Some(sample)),
        Err(RecvTimeoutError::Timeout) => Ok(None),
        Err(RecvTimeoutError::Disconnected) => Err(closed_subscription()),
    }
}

fn closed_subscription() -> Error {
    Error::Zenoh("the client's subscription to its scenes has ended".into())
}

fn parse_reply<T: serde::de::DeserializeOwned>(key: &str, bytes: &[u8]) -> Result<T> {
    serde_json::from_slice(bytes).map_err(|e| Error::Reply {
        key: key.to_owned(),
        reason: format!(
            "{e}: {}",
            String::from_utf8_lossy(bytes)
                .chars()
                .take(200)
                .collect::<String>()
        ),
    })
}

/// Sends `payload` to the queryable at `key` and waits for its one reply: the reply's bytes,
/// or the server's error reply.
fn query_raw(
    session: &zenoh::Session,
    key: &str,
    payload: Vec<u8>,
    timeout: Duration,
) -> Result<Result<Vec<u8>, ErrorReply>> {
    let replies = session.get(key).payload(payload).timeout(timeout).wait()?;
    // The channel closes without a reply when the query reached no queryable, or when
    // zenoh's access control dropped it on the way.
    let reply = replies
        .recv_timeout(timeout + Duration::from_secs(1))
        .map_err(|_| Error::NoAnswer {
            key: key.to_owned(),
        })?
        .ok_or_else(|| Error::Timeout {
            what: format!("the query on {key}"),
            timeout,
        })?;
    match reply.into_result() {
        Ok(sample) => Ok(Ok(sample.payload().to_bytes().into_owned())),
        Err(e) => Ok(Err(parse_reply(key, &e.payload().to_bytes())?)),
    }
}
