//! The zenoh front end and the core loop.
//!
//! Zenoh's callbacks (queryables for create, close and status; the subscriber of every scene's
//! ego key; the liveliness subscriber of clients) only stamp what arrived and hand it to one
//! core thread over a channel. The core thread owns every scene and the engine state: it
//! drains the channel, then runs one round over the scenes that are ready (their ego for the
//! next tick arrived, or their late-ego deadline passed) and publishes each one's NPCs as
//! soon as it is computed. A scene whose ego has not come is simply not in the round: it
//! never holds up another scene. Bad input is answered with an [`ErrorReply`] (the query's
//! error reply, or a message on the scene's error key) and changes nothing.
//!
//! Each scene's `foxglove.SceneUpdate` messages (the map at creation, the agents' boxes at
//! creation and after every tick) are built once and go to the recording and, when
//! [`ServeConfig::foxglove_listen`] is set, to the live view ([`crate::live`]). After
//! creation, recording and the live view's boxes are the scene writer's (`writer.rs`):
//! the core queues each published tick there and goes on with the next round.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use road_data::LaneletMap;
use road_gpu::{ContextOptions, GpuContext};
use road_protocol::{
    CloseScene, CreateScene, ErrorCode, ErrorReply, Keys, PROTOCOL_VERSION, Percentiles,
    SceneClosed, SceneCreated, SceneStatus, Status, parse, same_token,
};
use zenoh::Wait;
use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;
use zenoh::query::Query;
use zenoh::sample::SampleKind;

use crate::config::{ServeConfig, ServeEngine};
use crate::live::LiveView;
use crate::models::{Checkpoints, find_models_dir, planners};
use crate::pool::{Pool, PoolEngine, PoolKey};
use crate::record::{Recorder, agents_update, free_path, map_update, topics, unix_nanos};
use crate::scene::{LiveScene, SetupContext, setup};
use crate::writer::{LiveChannels, PublishedTick, SceneWriter};
use crate::{Error, Result};

/// Latency samples kept for the status percentiles.
const LATENCY_WINDOW: usize = 4096;

/// What the zenoh callbacks hand to the core thread.
enum Event {
    Create(Query, SystemTime),
    Close(Query),
    Status(Query),
    /// A put on `<prefix>/client/<client>/scene/<scene>/ego` (the key's chunks).
    Ego {
        client: String,
        scene: String,
        payload: Vec<u8>,
        /// The payload's size as received (the payload is dropped when over the limit).
        size: usize,
        received: Instant,
        at: SystemTime,
    },
    ClientGone(String),
    Stop,
}

/// A server about to start.
#[derive(Debug)]
pub struct Server {
    config: ServeConfig,
    zenoh: zenoh::Config,
}

/// A running server: its session (for the addresses it listens on) and its core thread.
pub struct ServerHandle {
    session: zenoh::Session,
    listen: Vec<String>,
    foxglove: Option<SocketAddr>,
    events: Sender<Event>,
    core: Option<JoinHandle<Result<()>>>,
    _token: LivelinessToken,
}

impl std::fmt::Debug for ServerHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServerHandle")
            .field("zid", &self.session.zid())
            .finish_non_exhaustive()
    }
}

impl Server {
    pub fn new(config: ServeConfig, zenoh: zenoh::Config) -> Self {
        Self { config, zenoh }
    }

    /// Checks the config, loads the default checkpoint and the map files, opens the zenoh
    /// session, declares the keys and starts the core thread.
    pub fn start(self) -> Result<ServerHandle> {
        let config = self.config;
        config.validate()?;
        // The recordings a killed predecessor left cut off, rewritten whole before any scene.
        if let Some(dir) = &config.record_dir {
            crate::recover::recover_folder(dir);
        }
        let models_dir = match &config.models_dir {
            Some(dir) => find_models_dir(Some(dir))?,
            None => None,
        };
        // The GPU engine's context lives as long as the server's pools (leaked once per server,
        // like the checkpoints they borrow); opening it first reports a missing adapter at start.
        let (mut checkpoints, engine) = match config.engine {
            ServeEngine::Cpu => (
                Checkpoints::new(models_dir),
                "fast CPU engine (continuous batching: one pool per checkpoint and planner)"
                    .to_owned(),
            ),
            ServeEngine::Gpu => {
                let options = ContextOptions {
                    precision: config.gpu_precision,
                    ..ContextOptions::default()
                };
                let ctx: &'static GpuContext = Box::leak(Box::new(GpuContext::new(&options)?));
                tracing::info!(adapter = %ctx.describe(), "serving on the GPU engine");
                let engine = format!(
                    "WGSL engine on {} (continuous batching: one pool per checkpoint and planner)",
                    ctx.describe()
                );
                (Checkpoints::with_gpu(models_dir, ctx), engine)
            }
        };
        let default = checkpoints.get(&config.default_checkpoint)?;
        // A checkpoint the kernels cannot run is refused now, not at the first scene.
        checkpoints.gpu_model(&config.default_checkpoint)?;
        tracing::info!(
            checkpoint = %config.default_checkpoint,
            planner = %default.meta.run.name,
            "default checkpoint loaded"
        );
        // The default initialiser too: one that does not load or cannot draw is refused now.
        if let Some(name) = &config.default_initialiser {
            let init = checkpoints.get(name)?;
            crate::scene::check_initialiser(init)
                .map_err(|why| Error::Config(format!("the default initialiser {name:?}: {why}")))?;
        }
        let mut map_files = BTreeMap::new();
        for (name, path) in &config.map_files {
            let map = LaneletMap::load(path, name)?;
            if map.lanelets.is_empty() {
                return Err(Error::Config(format!(
                    "map file {} ({name}) has no lanelets",
                    path.display()
                )));
            }
            map_files.insert(name.clone(), Arc::new(map));
        }
        let planners = planners()?;
        // Bound before the session opens: a taken port fails the start, not a later scene.
        let live_view = config
            .foxglove_listen
            .map(LiveView::start)
            .transpose()?
            .map(Arc::new);
        let foxglove = live_view.as_deref().map(LiveView::local_addr);
        let keys = Keys::new(&config.prefix);
        let listen = self
            .zenoh
            .get_json("listen/endpoints")
            .ok()
            .and_then(|json| serde_json::from_str::<Vec<String>>(&json).ok())
            .unwrap_or_default();
        let session =
            zenoh::open(bounded_messages(self.zenoh, config.max_payload_bytes)?).wait()?;
        let (tx, rx) = mpsc::channel::<Event>();

        let sender = tx.clone();
        session
            .declare_queryable(keys.create())
            .callback(move |q| {
                let _ = sender.send(Event::Create(q, SystemTime::now()));
            })
            .background()
            .wait()?;
        let sender = tx.clone();
        session
            .declare_queryable(keys.close())
            .callback(move |q| {
                let _ = sender.send(Event::Close(q));
            })
            .background()
            .wait()?;
        let sender = tx.clone();
        session
            .declare_queryable(keys.status())
            .callback(move |q| {
                let _ = sender.send(Event::Status(q));
            })
            .background()
            .wait()?;
        let sender = tx.clone();
        let max_payload = config.max_payload_bytes;
        let ego_keys = keys.clone();
        session
            .declare_subscriber(keys.ego_any())
            .callback(move |sample| {
                let received = Instant::now();
                let at = SystemTime::now();
                let key = sample.key_expr().as_str();
                // Every key the subscription matches has the two chunks.
                let Some((client, scene)) = ego_keys.ego_key_chunks(key) else {
                    tracing::warn!(key, "a put on a key that is not an ego key; ignored");
                    return;
                };
                let (client, scene) = (client.to_owned(), scene.to_owned());
                let payload = sample.payload();
                let size = payload.len();
                // Oversized payloads are not copied, only refused by their size.
                let payload = if size > max_payload {
                    Vec::new()
                } else {
                    payload.to_bytes().into_owned()
                };
                let _ = sender.send(Event::Ego {
                    client,
                    scene,
                    payload,
                    size,
                    received,
                    at,
                });
            })
            .background()
            .wait()?;
        let sender = tx.clone();
        session
            .liveliness()
            .declare_subscriber(keys.client_alive_any())
            .callback(move |sample| {
                if sample.kind() == SampleKind::Delete {
                    if let Some(client) = sample.key_expr().as_str().rsplit('/').next() {
                        let _ = sender.send(Event::ClientGone(client.to_owned()));
                    }
                }
            })
            .background()
            .wait()?;
        let token = session
            .liveliness()
            .declare_token(keys.server_alive())
            .wait()?;

        let writer = SceneWriter::start(live_view.clone(), config.flush_interval)?;
        let core = Core {
            engine,
            config,
            keys,
            session: session.clone(),
            checkpoints,
            planners,
            map_files,
            scenes: BTreeMap::new(),
            pools: BTreeMap::new(),
            closed: BTreeSet::new(),
            next_id: 1,
            stats: Stats::default(),
            writer,
            live_view,
        };
        let handle = std::thread::Builder::new()
            .name("road-serve-core".into())
            .spawn(move || core.run(rx))
            .map_err(|e| Error::Config(format!("cannot start the core thread: {e}")))?;
        Ok(ServerHandle {
            session,
            listen,
            foxglove,
            events: tx,
            core: Some(handle),
            _token: token,
        })
    }
}

impl ServerHandle {
    /// The endpoints the session was configured to listen on (as given: a port 0 stays 0;
    /// zenoh's API for the bound addresses is unstable and leaves loopback out).
    pub fn listen_endpoints(&self) -> Vec<String> {
        self.listen.clone()
    }

    /// Where the live view listens (the bound address: a port 0 is read back), when it runs.
    pub fn foxglove_addr(&self) -> Option<SocketAddr> {
        self.foxglove
    }

    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// Whether the core thread still runs.
    pub fn is_running(&self) -> bool {
        self.core.as_ref().is_some_and(|c| !c.is_finished())
    }

    /// Stops the core thread (finishing every recording) and closes the session.
    pub fn stop(mut self) -> Result<()> {
        self.shutdown()
    }

    /// Blocks until the core thread ends (it ends on [`Self::stop`] or an internal error).
    pub fn join(mut self) -> Result<()> {
        let result = match self.core.take() {
            Some(core) => core
                .join()
                .unwrap_or_else(|_| Err(Error::Config("the core thread panicked".into()))),
            None => Ok(()),
        };
        self.session.close().wait()?;
        result
    }

    fn shutdown(&mut self) -> Result<()> {
        let _ = self.events.send(Event::Stop);
        let result = match self.core.take() {
            Some(core) => core
                .join()
                .unwrap_or_else(|_| Err(Error::Config("the core thread panicked".into()))),
            None => Ok(()),
        };
        self.session.close().wait()?;
        result
    }
}

impl Drop for ServerHandle {
    fn drop(&mut self) {
        if self.core.is_some() {
            if let Err(e) = self.shutdown() {
                tracing::warn!("stopping the server: {e}");
            }
        }
    }
}

/// Round and latency statistics for the status.
#[derive(Debug, Default)]
struct Stats {
    rounds: u64,
    last_batch: usize,
    batch_sum: u64,
    max_batch: usize,
    latency_ms: VecDeque<f64>,
    compute_ms: VecDeque<f64>,
    queue_ms: VecDeque<f64>,
    /// The last engine rounds (start, end), newest last: what a tick's ego waited for.
    recent_rounds: VecDeque<(Instant, Instant)>,
}

/// Engine rounds remembered for the queue wait: a tick waits for at most one round per pool.
const RECENT_ROUNDS: usize = 256;

impl Stats {
    fn push(window: &mut VecDeque<f64>, v: f64) {
        if window.len() == LATENCY_WINDOW {
            window.pop_front();
        }
        window.push_back(v);
    }

    fn push_round(&mut self, started: Instant, ended: Instant) {
        if self.recent_rounds.len() == RECENT_ROUNDS {
            self.recent_rounds.pop_front();
        }
        self.recent_rounds.push_back((started, ended));
    }

    /// Seconds of engine rounds between `from` and `to` (the part of each round inside).
    fn engine_busy_secs(&self, from: Instant, to: Instant) -> f64 {
        self.recent_rounds
            .iter()
            .rev()
            .take_while(|&&(_, ended)| ended > from)
            .map(|&(started, ended)| {
                ended
                    .min(to)
                    .saturating_duration_since(started.max(from))
                    .as_secs_f64()
            })
            // Not `sum()`: an empty f64 sum is −0.0, which prints as "-0.00".
            .fold(0.0, |total, secs| total + secs)
    }
}

/// Percentiles (nearest rank) of a sample.
pub fn percentiles(sample: &[f64]) -> Percentiles {
    if sample.is_empty() {
        return Percentiles::default();
    }
    let mut sorted = sample.to_vec();
    sorted.sort_by(f64::total_cmp);
    let at = |q: f64| {
        let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
        sorted[rank - 1]
    };
    Percentiles {
        count: sorted.len() as u64,
        p50_ms: at(0.50),
        p90_ms: at(0.90),
        p99_ms: at(0.99),
        max_ms: sorted[sorted.len() - 1],
    }
}

struct SceneEntry {
    live: LiveScene,
    /// The scene is recorded (its recorder is the writer's).
    recorded: bool,
    /// The scene is in the live view (its channels are the writer's).
    viewed: bool,
    /// The scene's NPC key, declared once (undeclared when the entry drops): a session's put
    /// computes its route anew against every subscription the session knows, 70-100 µs a put
    /// beside 256 scenes' clients on the development VM against 5 through a publisher, and
    /// the core thread publishes every scene's tick in turn. `None` where the declaration
    /// failed: the session's put then.
    npc_publisher: Option<zenoh::pubsub::Publisher<'static>>,
}

/// The core thread's state: every scene, the checkpoints, the statistics.
struct Core {
    engine: String,
    config: ServeConfig,
    keys: Keys,
    session: zenoh::Session,
    checkpoints: Checkpoints,
    planners: BTreeMap<String, road_sched::PlannerSpec>,
    map_files: BTreeMap<String, Arc<LaneletMap>>,
    scenes: BTreeMap<u64, SceneEntry>,
    /// The engines: one pool of scenes per checkpoint and planner (continuous batching).
    pools: BTreeMap<PoolKey, Pool>,
    /// Ids of closed scenes, to tell "closed" from "never existed".
    closed: BTreeSet<u64>,
    next_id: u64,
    stats: Stats,
    /// The Foxglove live view, when `config.foxglove_listen` is set (shared with the writer).
    live_view: Option<Arc<LiveView>>,
    /// Records every scene and feeds the live view, on its own thread.
    writer: SceneWriter,
}

/// Zenoh's default reassembles messages of up to 1 GiB: a client could make the server buffer
/// that much before `max_payload_bytes` is checked. Unless the config sets its own limit, the
/// server's links refuse messages over twice `max_payload_bytes` (at least 1 MiB): payloads
/// between the two get the `payload_too_large` reply, larger ones are dropped by zenoh.
fn bounded_messages(mut zenoh: zenoh::Config, max_payload_bytes: usize) -> Result<zenoh::Config> {
    const KEY: &str = "transport/link/rx/max_message_size";
    const ZENOH_DEFAULT: u64 = 1 << 30;
    let current: Option<u64> = zenoh
        .get_json(KEY)
        .ok()
        .and_then(|v| serde_json::from_str(&v).ok());
    if current.is_none_or(|v| v == ZENOH_DEFAULT) {
        let limit = (2 * max_payload_bytes).max(1 << 20);
        zenoh
            .insert_json5(KEY, &limit.to_string())
            .map_err(|e| Error::ZenohConfig {
                input: format!("{KEY}: {limit}"),
                reason: e.to_string(),
            })?;
    }
    Ok(zenoh)
}

/// A query's payload in bytes, and the copy to read, which is made only when the payload is
/// within `max_bytes` (a refused payload costs no allocation of its size).
fn payload_of(query: &Query, max_bytes: usize) -> (usize, Vec<u8>) {
    let size = query.payload().map_or(0, |p| p.len());
    let bytes = query
        .payload()
        .filter(|_| size <= max_bytes)
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    (size, bytes)
}

/// One live scene's line of the status.
fn scene_status(e: &SceneEntry) -> SceneStatus {
    SceneStatus {
        scene: e.live.id,
        tick: e.live.tick,
        agents: e.live.agents.len(),
        client: Some(e.live.client.clone()),
        idle_s: e.live.last_heard.elapsed().as_secs_f64(),
        late_ticks: e.live.late_ticks,
        refused_puts: e.live.refused_puts,
    }
}

fn reply_ok<T: serde::Serialize>(query: &Query, value: &T) {
    let json = serde_json::to_vec(value).expect("replies serialise");
    if let Err(e) = query.reply(query.key_expr().clone(), json).wait() {
        tracing::warn!(key = %query.key_expr(), "cannot reply: {e}");
    }
}

fn cannot_record(e: &Error) -> ErrorReply {
    ErrorReply::new(
        ErrorCode::Internal,
        None,
        format!("cannot record the scene: {e}"),
    )
}

fn reply_err(query: &Query, error: &ErrorReply) {
    tracing::debug!(key = %query.key_expr(), "refused: {error}");
    let json = serde_json::to_vec(error).expect("errors serialise");
    if let Err(e) = query.reply_err(json).wait() {
        tracing::warn!(key = %query.key_expr(), "cannot reply: {e}");
    }
}

impl Core {
    fn run(mut self, events: Receiver<Event>) -> Result<()> {
        loop {
            let wait = self.next_wakeup();
            let mut stop = false;
            match events.recv_timeout(wait) {
                Ok(event) => stop |= !self.handle(event),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => stop = true,
            }
            // Everything that arrived meanwhile joins this round.
            while !stop {
                match events.try_recv() {
                    Ok(event) => stop |= !self.handle(event),
                    Err(_) => break,
                }
            }
            if stop {
                break;
            }
            self.round();
            self.housekeeping();
        }
        let ids: Vec<u64> = self.scenes.keys().copied().collect();
        for id in ids {
            self.close_notifying(id, ErrorCode::SceneClosed, "the server stops");
        }
        Ok(())
    }

    /// How long the core may sleep: until the nearest late-ego deadline, at most 100 ms (idle
    /// checks). Recordings flush on the writer's own clock.
    fn next_wakeup(&self) -> Duration {
        if self.pools.values().any(|p| p.ticks_in_progress() > 0) {
            // Ticks in flight: the next batched round is due now.
            return Duration::ZERO;
        }
        let now = Instant::now();
        let mut wait = Duration::from_millis(100);
        let deadline = self.config.late_ego_deadline;
        if !deadline.is_zero() {
            for entry in self.scenes.values() {
                let s = &entry.live;
                if s.pending.is_none() && s.in_flight.is_none() && s.tick < s.max_ticks {
                    wait = wait.min((s.waiting_since + deadline).saturating_duration_since(now));
                }
            }
        }
        wait
    }

    /// Handles one event; `false` to stop.
    fn handle(&mut self, event: Event) -> bool {
        match event {
            Event::Create(query, at) => self.on_create(&query, at),
            Event::Close(query) => self.on_close(&query),
            Event::Status(query) => self.on_status(&query),
            Event::Ego {
                client,
                scene,
                payload,
                size,
                received,
                at,
            } => self.on_ego(&client, &scene, payload, size, received, at),
            Event::ClientGone(client) => {
                let ids: Vec<u64> = self
                    .scenes
                    .iter()
                    .filter(|(_, e)| e.live.client == client)
                    .map(|(&id, _)| id)
                    .collect();
                for id in ids {
                    let why = format!("its client {client} went away");
                    self.close_notifying(id, ErrorCode::SceneClosed, &why);
                }
            }
            Event::Stop => return false,
        }
        true
    }

    fn too_large(&self, size: usize) -> Option<ErrorReply> {
        (size > self.config.max_payload_bytes).then(|| {
            ErrorReply::new(
                ErrorCode::PayloadTooLarge,
                None,
                format!(
                    "the payload has {size} bytes; the limit is {}",
                    self.config.max_payload_bytes
                ),
            )
        })
    }

    fn on_create(&mut self, query: &Query, at: SystemTime) {
        let (size, payload) = payload_of(query, self.config.max_payload_bytes);
        if let Some(e) = self.too_large(size) {
            return reply_err(query, &e);
        }
        let request: CreateScene = match parse(&payload) {
            Ok(r) => r,
            Err(e) => return reply_err(query, &e),
        };
        if self.scenes.len() >= self.config.capacity {
            return reply_err(
                query,
                &ErrorReply::new(
                    ErrorCode::Capacity,
                    None,
                    format!(
                        "the server holds {} live scenes, its capacity",
                        self.config.capacity
                    ),
                ),
            );
        }
        let mut ctx = SetupContext {
            config: &self.config,
            checkpoints: &mut self.checkpoints,
            planners: &self.planners,
            map_files: &self.map_files,
        };
        let scene_setup = match setup(&request, &mut ctx) {
            Ok(s) => s,
            Err(e) => return reply_err(query, &e),
        };
        let id = self.next_id;
        let map = scene_setup.map.clone();
        let key = PoolKey {
            checkpoint: scene_setup.checkpoint_name.clone(),
            planner: scene_setup.planner_name.clone(),
        };
        if !self.pools.contains_key(&key) {
            let pool = self
                .checkpoints
                .gpu_model(&key.checkpoint)
                .map_err(|e| format!("cannot put checkpoint {} on the GPU: {e}", key.checkpoint))
                .and_then(|gpu| {
                    let engine =
                        gpu.map_or(PoolEngine::Cpu, |(ctx, model)| PoolEngine::Gpu(ctx, model));
                    Pool::new(
                        scene_setup.model,
                        engine,
                        &scene_setup.planner,
                        self.config.capacity,
                        self.config.max_agents,
                    )
                    .map_err(|e| format!("cannot build the scene's engine: {e}"))
                });
            match pool {
                Ok(pool) => {
                    tracing::info!(checkpoint = %key.checkpoint, planner = %key.planner, "new pool");
                    self.pools.insert(key.clone(), pool);
                }
                Err(message) => {
                    return reply_err(query, &ErrorReply::new(ErrorCode::Internal, None, message));
                }
            }
        }
        let recording = match self.config.record_dir.as_deref().map(|d| free_path(d, id)) {
            Some(Ok(path)) => Some(path),
            Some(Err(e)) => return reply_err(query, &cannot_record(&e)),
            None => None,
        };
        let pool = self.pools.get_mut(&key).expect("inserted above");
        // The scene's secret: only this query's reply carries it (zenoh does not tell the
        // server who puts on a key, so a client id alone proves nothing).
        let token = format!("{:032x}", rand::random::<u128>());
        let live = match LiveScene::new(id, scene_setup, key, pool, token, Instant::now()) {
            Ok(l) => l,
            Err(e) => {
                return reply_err(
                    query,
                    &ErrorReply::new(
                        ErrorCode::Internal,
                        None,
                        format!("cannot build the scene: {e}"),
                    ),
                );
            }
        };
        self.next_id += 1;
        let created = SceneCreated {
            protocol: PROTOCOL_VERSION,
            scene: id,
            agents: live.agents.clone(),
            planner: live.planner_name.clone(),
            checkpoint: live.checkpoint_name.clone(),
            observed_steps: live.agents[0].history.len(),
            step_secs: road_sim::procedural::STEP_SECS,
            max_ticks: live.max_ticks,
            late_ego_deadline_ms: self.config.late_ego_deadline.as_millis() as u64,
            ego_key: self.keys.ego(&live.client, id),
            npc_key: self.keys.npc(&live.client, id),
            error_key: self.keys.error(&live.client, &id.to_string()),
            recording: recording.as_ref().map(|p| p.display().to_string()),
            token: live.token.clone(),
        };
        let created_json = serde_json::to_vec(&created).expect("replies serialise");
        // The scene's SceneUpdates, built once for the recording and the live view.
        let updates_wanted = recording.is_some() || self.live_view.is_some();
        let nanos = unix_nanos(at);
        let map_json = map
            .as_deref()
            .filter(|_| updates_wanted)
            .map(|m| map_update(m, nanos).to_string());
        let start_json = updates_wanted.then(|| {
            agents_update(&live.agents, live.poses(), None, &[], false, nanos).to_string()
        });
        let recorder = match &recording {
            Some(path) => {
                let map_bytes = map_json.as_deref().map(str::as_bytes);
                match Recorder::start_at(path, &payload, &created_json, map_bytes, at) {
                    Ok(mut r) => {
                        let start = start_json.as_deref().unwrap_or_default();
                        if let Err(e) = r.write(topics::AGENTS, start.as_bytes(), at) {
                            tracing::warn!(scene = id, "recording: {e}");
                        }
                        Some(r)
                    }
                    Err(e) => {
                        // The scene is in its pool already: give the slot back.
                        self.leave_pool(id, &live);
                        return reply_err(query, &cannot_record(&e));
                    }
                }
            }
            None => None,
        };
        tracing::info!(
            scene = id,
            client = %live.client,
            agents = live.agents.len(),
            planner = %live.planner_name,
            "scene created"
        );
        let channels = self.live_view.as_deref().map(|view| {
            let channels = LiveChannels::advertise(view, id);
            if let Some(json) = map_json {
                // Sent once: never dropped on the way to a viewer.
                view.publish_reliable(channels.map, nanos, json.into_bytes());
            }
            if let Some(json) = start_json {
                view.publish(channels.agents, nanos, json.into_bytes());
            }
            channels
        });
        let (recorded, viewed) = (recorder.is_some(), channels.is_some());
        if recorded || viewed {
            self.writer
                .start_scene(id, live.agents.clone(), recorder, channels);
        }
        let npc_publisher = match self
            .session
            .declare_publisher(self.keys.npc(&live.client, id))
            .congestion_control(CongestionControl::Block)
            .wait()
        {
            Ok(publisher) => Some(publisher),
            Err(e) => {
                tracing::warn!(
                    scene = id,
                    "cannot declare the NPC publisher ({e}): puts instead"
                );
                None
            }
        };
        let mut live = live;
        // The late-ego clock starts when the client has the reply, and so does its silence.
        live.waiting_since = Instant::now();
        live.awaiting_client_since = Some(live.waiting_since);
        self.scenes.insert(
            id,
            SceneEntry {
                live,
                recorded,
                viewed,
                npc_publisher,
            },
        );
        reply_ok(query, &created);
    }

    fn on_close(&mut self, query: &Query) {
        let (size, payload) = payload_of(query, self.config.max_payload_bytes);
        if let Some(e) = self.too_large(size) {
            return reply_err(query, &e);
        }
        let request: CloseScene = match parse(&payload) {
            Ok(r) => r,
            Err(e) => return reply_err(query, &e),
        };
        let Some(entry) = self.scenes.get(&request.scene) else {
            let message = if self.closed.contains(&request.scene) {
                format!("scene {} is already closed", request.scene)
            } else {
                format!("no scene {}", request.scene)
            };
            return reply_err(
                query,
                &ErrorReply {
                    scene: Some(request.scene),
                    ..ErrorReply::new(ErrorCode::UnknownScene, Some("scene"), message)
                },
            );
        };
        let not_owner = |field: &str, message: String| ErrorReply {
            scene: Some(request.scene),
            ..ErrorReply::new(ErrorCode::NotOwner, Some(field), message)
        };
        if request.client != entry.live.client {
            let message = format!(
                "scene {} is not client {}'s: close it under the id that created it",
                request.scene, request.client
            );
            return reply_err(query, &not_owner("client", message));
        }
        if !same_token(&request.token, &entry.live.token) {
            let message = format!(
                "the token is not scene {}'s: close it with the token its creation reply gave",
                request.scene
            );
            return reply_err(query, &not_owner("token", message));
        }
        let closed = self.close(request.scene, "the client closed it");
        match closed {
            Some(c) => reply_ok(query, &c),
            None => reply_err(
                query,
                &ErrorReply::new(ErrorCode::UnknownScene, Some("scene"), "no such scene"),
            ),
        }
    }

    /// Closes a scene its client did not ask to close, telling the client why on the scene's
    /// error key (`code`: `scene_closed` or `client_silent`), so that a client waiting for a
    /// tick hears of it.
    fn close_notifying(&mut self, id: u64, code: ErrorCode, why: &str) {
        let Some(live) = self.scenes.get(&id).map(|e| &e.live) else {
            return;
        };
        let (tick, client) = (Some(live.tick + 1), live.client.clone());
        let error = ErrorReply {
            scene: Some(id),
            tick,
            ..ErrorReply::new(code, None, format!("the server closed the scene: {why}"))
        };
        self.publish_error(&client, &id.to_string(), &error);
        self.close(id, why);
    }

    /// Gives scene `id`'s slot in its pool back.
    fn leave_pool(&mut self, id: u64, live: &LiveScene) {
        if let Some(pool) = self.pools.get_mut(&live.pool) {
            if let Err(e) = pool.remove(live.slot) {
                tracing::error!(scene = id, "cannot leave the pool: {e}");
            }
        }
    }

    /// Removes a scene and finishes its recording.
    fn close(&mut self, id: u64, why: &str) -> Option<SceneClosed> {
        let entry = self.scenes.remove(&id)?;
        self.closed.insert(id);
        self.leave_pool(id, &entry.live);
        // After everything queued for it: the file is complete when the reply names it.
        let recording = if entry.recorded || entry.viewed {
            self.writer.finish(id)
        } else {
            None
        };
        tracing::info!(scene = id, ticks = entry.live.tick, "scene closed: {why}");
        Some(SceneClosed {
            scene: id,
            ticks: entry.live.tick,
            recording,
        })
    }

    /// Publishes an error for a put on `<prefix>/client/<client>/scene/<chunk>/ego` on that
    /// client's error key (and records it when the chunk is a live scene).
    fn publish_error(&mut self, client: &str, chunk: &str, error: &ErrorReply) {
        tracing::debug!(client, scene = chunk, "refused: {error}");
        let json = serde_json::to_vec(error).expect("errors serialise");
        if let Ok(id) = chunk.parse::<u64>() {
            if self.scenes.get(&id).is_some_and(|e| e.recorded) {
                self.writer
                    .record(id, topics::ERROR, json.clone(), SystemTime::now());
            }
        }
        // A chunk that is not a key chunk (it came from a key, so it is one) cannot fail here.
        // Block, not zenoh's default Drop: a refusal is never lost to a full queue (a client
        // that does not read for 5 s has its link closed by zenoh instead, `docs/protocol.md`).
        if let Err(e) = self
            .session
            .put(self.keys.error(client, chunk), json)
            .congestion_control(CongestionControl::Block)
            .wait()
        {
            tracing::warn!(scene = chunk, "cannot publish an error: {e}");
        }
    }

    fn on_ego(
        &mut self,
        client: &str,
        chunk: &str,
        payload: Vec<u8>,
        size: usize,
        received: Instant,
        at: SystemTime,
    ) {
        let Ok(id) = chunk.parse::<u64>() else {
            return self.publish_error(
                client,
                chunk,
                &ErrorReply::new(
                    ErrorCode::UnknownScene,
                    Some("key"),
                    format!("{chunk:?} in the key is not a scene id"),
                ),
            );
        };
        if !self.scenes.contains_key(&id) {
            let message = if self.closed.contains(&id) {
                format!("scene {id} is closed")
            } else {
                format!("no scene {id}")
            };
            let error = self.too_large(size).unwrap_or_else(|| ErrorReply {
                scene: Some(id),
                tick: parse::<road_protocol::EgoTick>(&payload)
                    .ok()
                    .map(|m| m.tick),
                ..ErrorReply::new(ErrorCode::UnknownScene, Some("key"), message)
            });
            return self.publish_error(client, chunk, &error);
        }
        // Only a put that carries the scene's token is read on, and answered on the error key:
        // anyone can put on any key, and a message on the owner's error key ends the owner's
        // wait. Any other put is answered on the scene's `refused` key, recorded and counted.
        let too_large = self.too_large(size);
        let Some(entry) = self.scenes.get_mut(&id) else {
            return;
        };
        let refusal = if let Some(e) = too_large {
            Some(e)
        } else if road_protocol::token_of(&payload)
            .is_some_and(|token| same_token(&token, &entry.live.token))
        {
            None
        } else {
            Some(match parse::<road_protocol::EgoTick>(&payload) {
                Err(e) => e,
                Ok(_) => ErrorReply::new(
                    ErrorCode::NotOwner,
                    Some("token"),
                    format!(
                        "the tick lacks scene {id}'s token (the creation reply's `token`); it is not read"
                    ),
                ),
            })
        };
        if let Some(error) = refusal {
            entry.live.refused_puts += 1;
            let error = ErrorReply {
                scene: Some(id),
                ..error
            };
            tracing::debug!(scene = id, key_client = client, "refused: {error}");
            let json = serde_json::to_vec(&error).expect("errors serialise");
            if entry.recorded {
                self.writer.record(id, topics::ERROR, json.clone(), at);
            }
            if let Err(e) = self
                .session
                .put(self.keys.refused(client, chunk), json)
                .congestion_control(CongestionControl::Block)
                .wait()
            {
                tracing::warn!(scene = id, "cannot publish a refusal: {e}");
            }
            return;
        }
        let msg = match parse::<road_protocol::EgoTick>(&payload) {
            Ok(m) => m,
            Err(e) => {
                return self.publish_error(
                    client,
                    chunk,
                    &ErrorReply {
                        scene: Some(id),
                        ..e
                    },
                );
            }
        };
        let entry = self.scenes.get_mut(&id).expect("looked up above");
        match entry
            .live
            .check_ego(client, &msg, self.config.max_external_speed_mps, received)
        {
            Ok(pending) => {
                entry.live.pending = Some(pending);
                entry.live.last_heard = received;
                entry.live.awaiting_client_since = None;
                if entry.recorded {
                    // The payload goes to the recording as received, without a copy.
                    self.writer.record(id, topics::EGO, payload, at);
                }
            }
            Err(e) => self.publish_error(client, chunk, &e),
        }
    }

    /// One round: every scene whose ego arrived, or whose deadline passed, starts its tick;
    /// then every pool with ticks in progress runs one batched Heun round, and each scene
    /// whose tick finished publishes at once.
    fn round(&mut self) {
        let now = Instant::now();
        let deadline = self.config.late_ego_deadline;
        let ready: Vec<u64> = self
            .scenes
            .iter()
            .filter(|(_, e)| {
                let s = &e.live;
                s.in_flight.is_none()
                    && s.tick < s.max_ticks
                    && (s.pending.is_some()
                        || (!deadline.is_zero() && now >= s.waiting_since + deadline))
            })
            .map(|(&id, _)| id)
            .collect();
        let mut failed = Vec::new();
        for id in ready {
            let entry = self.scenes.get_mut(&id).expect("ready scenes are live");
            // Latency runs from the ego's arrival, or from the deadline for a late tick.
            let started = entry
                .live
                .pending
                .as_ref()
                .map(|p| p.received)
                .unwrap_or(entry.live.waiting_since + deadline);
            let pool = self
                .pools
                .get_mut(&entry.live.pool)
                .expect("a live scene's pool lives");
            // What the tick waited for: the rounds of other scenes that ran since its ego came.
            let queue_secs = self.stats.engine_busy_secs(started, now);
            if let Err(e) = entry.live.begin_tick(pool, started, queue_secs) {
                tracing::error!(scene = id, "tick failed: {e}");
                failed.push((id, e.to_string()));
            }
        }
        let mut finished = Vec::new();
        for (key, pool) in &mut self.pools {
            let batch = pool.ticks_in_progress();
            if batch == 0 {
                continue;
            }
            self.stats.rounds += 1;
            self.stats.last_batch = batch;
            self.stats.batch_sum += batch as u64;
            self.stats.max_batch = self.stats.max_batch.max(batch);
            let started = Instant::now();
            let result = pool.round();
            let ended = Instant::now();
            self.stats.push_round(started, ended);
            let secs = (ended - started).as_secs_f64();
            for entry in self.scenes.values_mut() {
                if let Some(flight) = entry.live.in_flight.as_mut() {
                    if entry.live.pool == *key {
                        flight.compute_secs += secs;
                    }
                }
            }
            match result {
                Ok(done) => finished.extend(done),
                Err(e) => {
                    // A failed round leaves its scenes' ticks undone: they close, the others
                    // (other pools) go on.
                    tracing::error!("batched round failed: {e}");
                    for (&id, entry) in &self.scenes {
                        if entry.live.in_flight.is_some() && entry.live.pool == *key {
                            failed.push((id, e.to_string()));
                        }
                    }
                }
            }
        }
        // Each finished scene publishes at once; its recording and live-view boxes go to the
        // writer's queue, so that no reply (and no next round) waits behind them.
        for (id, result) in finished {
            let Some(entry) = self.scenes.get_mut(&id) else {
                continue;
            };
            let out = match entry.live.finish_tick(&result) {
                Ok(out) => out,
                Err(e) => {
                    failed.push((id, e.to_string()));
                    continue;
                }
            };
            let json = serde_json::to_vec(&out.npc).expect("ticks serialise");
            let at = SystemTime::now();
            let wanted = entry.recorded || entry.viewed;
            // The writer's copy, when it wants one; the put takes the original.
            let kept = wanted.then(|| json.clone());
            let published = match &entry.npc_publisher {
                Some(publisher) => publisher.put(json).wait(),
                None => self
                    .session
                    .put(self.keys.npc(&entry.live.client, id), json)
                    .congestion_control(CongestionControl::Block)
                    .wait(),
            };
            if let Err(e) = published {
                tracing::warn!(scene = id, "cannot publish: {e}");
            }
            entry.live.waiting_since = Instant::now();
            // The client has something to answer from now on (its silence counts from here).
            if entry.live.awaiting_client_since.is_none() {
                entry.live.awaiting_client_since = Some(entry.live.waiting_since);
            }
            Stats::push(&mut self.stats.latency_ms, out.npc.latency_ms);
            Stats::push(&mut self.stats.compute_ms, out.compute_secs * 1e3);
            Stats::push(&mut self.stats.queue_ms, out.npc.queue_ms);
            if let Some(json) = kept {
                let late = !out.npc.late_external.is_empty();
                self.writer.tick(
                    id,
                    PublishedTick {
                        npc_json: json,
                        poses: out.poses,
                        present: out.present,
                        plans: out.npc.plans,
                        late,
                        at,
                        agents: out.agents,
                    },
                );
            }
        }
        for (id, message) in failed {
            let Some(client) = self.scenes.get(&id).map(|e| e.live.client.clone()) else {
                continue;
            };
            let error = ErrorReply {
                scene: Some(id),
                ..ErrorReply::new(
                    ErrorCode::Internal,
                    None,
                    format!("the tick failed and the scene is closed: {message}"),
                )
            };
            self.publish_error(&client, &id.to_string(), &error);
            self.close(id, "its tick failed");
        }
    }

    /// Closes the scenes whose client went quiet: nothing from it for the idle timeout since
    /// the server last gave it something to answer (ticks the model drove for want of its ego
    /// do not count as an answer), or more ticks in a row driven for want of its ego than the
    /// server allows.
    fn housekeeping(&mut self) {
        let timeout = self.config.idle_timeout;
        let max_late = self.config.max_consecutive_late_ticks;
        let silent: Vec<(u64, String)> = self
            .scenes
            .iter()
            .filter_map(|(&id, e)| {
                let live = &e.live;
                let quiet = live
                    .awaiting_client_since
                    .filter(|_| live.pending.is_none())
                    .map(|since| since.elapsed())
                    .filter(|&quiet| quiet > timeout);
                if let Some(quiet) = quiet {
                    Some((
                        id,
                        format!(
                            "client silent: nothing from client {} for {:.1} s (the idle timeout is {} s)",
                            live.client,
                            quiet.as_secs_f64(),
                            timeout.as_secs_f64()
                        ),
                    ))
                } else if live.consecutive_late_ticks >= max_late {
                    Some((
                        id,
                        format!(
                            "client silent: the model drove client {}'s agents {} ticks in a row for want of its ego (at most {max_late})",
                            live.client, live.consecutive_late_ticks
                        ),
                    ))
                } else {
                    None
                }
            })
            .collect();
        for (id, why) in silent {
            self.close_notifying(id, ErrorCode::ClientSilent, &why);
        }
    }

    /// The status query: the whole `Status`, or with `?scene=<id>` that live scene's
    /// `SceneStatus` alone (or `unknown_scene`): what a client waiting for a tick asks, one
    /// line whatever the server holds (the whole status has a line per scene, and at thousands
    /// of scenes every client waits at once).
    fn on_status(&self, query: &Query) {
        let Some(value) = query.parameters().get("scene") else {
            return reply_ok(query, &self.status());
        };
        let Ok(id) = value.parse::<u64>() else {
            return reply_err(
                query,
                &ErrorReply::new(
                    ErrorCode::InvalidField,
                    Some("scene"),
                    format!("status?scene={value}: a scene id is a whole number"),
                ),
            );
        };
        match self.scenes.get(&id) {
            Some(entry) => reply_ok(query, &scene_status(entry)),
            None => reply_err(
                query,
                &ErrorReply {
                    scene: Some(id),
                    ..ErrorReply::new(
                        ErrorCode::UnknownScene,
                        Some("scene"),
                        format!("no live scene {id}"),
                    )
                },
            ),
        }
    }

    fn status(&self) -> Status {
        let latency: Vec<f64> = self.stats.latency_ms.iter().copied().collect();
        let compute: Vec<f64> = self.stats.compute_ms.iter().copied().collect();
        let queue: Vec<f64> = self.stats.queue_ms.iter().copied().collect();
        Status {
            protocol: PROTOCOL_VERSION,
            engine: self.engine.clone(),
            checkpoint: self.config.default_checkpoint.clone(),
            capacity: self.config.capacity,
            scenes: self.scenes.values().map(scene_status).collect(),
            rounds: self.stats.rounds,
            last_batch: self.stats.last_batch,
            mean_batch: if self.stats.rounds == 0 {
                0.0
            } else {
                self.stats.batch_sum as f64 / self.stats.rounds as f64
            },
            max_batch: self.stats.max_batch,
            tick_latency: percentiles(&latency),
            compute: percentiles(&compute),
            queue: percentiles(&queue),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ticks_queue_wait_is_the_part_of_other_rounds_after_its_ego_came() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut stats = Stats::default();
        stats.push_round(at(0), at(10));
        stats.push_round(at(12), at(30));
        stats.push_round(at(31), at(40));
        let busy_ms =
            |stats: &Stats, from: u64, to: u64| stats.engine_busy_secs(at(from), at(to)) * 1e3;
        // The ego came during the second round: the rest of it, and all of the third.
        assert!((busy_ms(&stats, 20, 41) - 19.0).abs() < 1e-6);
        // It came between rounds and the next one was its own: no wait.
        assert_eq!(busy_ms(&stats, 41, 41), 0.0);
        assert!(busy_ms(&stats, 41, 41).is_sign_positive(), "0.0, not −0.0");
        // Rounds before the ego came do not count, whatever their number.
        for k in 0..RECENT_ROUNDS {
            stats.push_round(at(50 + 2 * k as u64), at(51 + 2 * k as u64));
        }
        let last_end = 51 + 2 * (RECENT_ROUNDS as u64 - 1);
        assert_eq!(busy_ms(&stats, last_end, last_end + 5), 0.0);
        assert!((busy_ms(&stats, last_end - 1, last_end + 5) - 1.0).abs() < 1e-6);
    }

    #[test]
    fn percentiles_by_nearest_rank() {
        let sample: Vec<f64> = (1..=100).map(f64::from).collect();
        let p = percentiles(&sample);
        assert_eq!(
            (p.p50_ms, p.p90_ms, p.p99_ms, p.max_ms),
            (50.0, 90.0, 99.0, 100.0)
        );
        assert_eq!(p.count, 100);
        assert_eq!(percentiles(&[]).count, 0);
    }
}
