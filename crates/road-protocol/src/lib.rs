//! The messages of road's zenoh protocol, shared by the server (`road-serve`) and its clients
//! (`road-client`, the Python package in `clients/python/`). Every payload is UTF-8 JSON;
//! `docs/protocol.md` lists the key expressions, the JSON schemas and the error table.
//!
//! Poses are metres and radians in the map's frame (for a Lanelet2 `.osm`, `road-data`'s
//! projection: UTM zone 31 minus the projection of (0, 0)). Step `0` is the last step of the
//! histories given at creation; step `t ≥ 1` is `t · step_secs` later.
//!
//! Requests refuse unknown fields (`#[serde(deny_unknown_fields)]`): a misspelt optional field
//! would otherwise be silently ignored. Replies (server to client) ignore them, so that a
//! server may add a reply field without breaking the clients already deployed (protocol 3).

use serde::{Deserialize, Serialize};

/// Version of this protocol, in the status and creation replies.
///
/// 2: a scene's ego, NPC and error keys name its client (`<prefix>/client/<id>/scene/<n>/…`),
/// and a scene must have a client.
/// 3: `NpcTick::queue_ms`; clients ignore reply fields they do not know.
/// 4: a scene's secret ([`SceneCreated::token`]) and its client id are required on every ego
/// tick and close; `client_silent` closes a scene whose client went quiet.
pub const PROTOCOL_VERSION: u32 = 4;

/// The key prefix a server uses unless configured otherwise.
pub const DEFAULT_PREFIX: &str = "road";

/// The key expressions of one server, under its prefix.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    prefix: String,
}

impl Keys {
    /// Keys under `prefix` (no leading or trailing `/`).
    pub fn new(prefix: &str) -> Self {
        Self {
            prefix: prefix.trim_matches('/').to_owned(),
        }
    }

    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// Queryable: [`CreateScene`] → [`SceneCreated`] or [`ErrorReply`].
    pub fn create(&self) -> String {
        format!("{}/scenes/create", self.prefix)
    }

    /// Queryable: [`CloseScene`] → [`SceneClosed`] or [`ErrorReply`].
    pub fn close(&self) -> String {
        format!("{}/scenes/close", self.prefix)
    }

    /// Queryable: no payload → [`Status`].
    pub fn status(&self) -> String {
        format!("{}/status", self.prefix)
    }

    /// The client puts [`EgoTick`] here for its scene `scene`.
    ///
    /// A scene's keys name its client: a client subscribes once to all its scenes
    /// ([`Keys::client_npc_any`], [`Keys::client_error_any`]) instead of once a scene, which
    /// would leave routing entries behind in zenoh for every scene; and a router's access
    /// control can give each client its own `<prefix>/client/<id>/**`.
    pub fn ego(&self, client: &str, scene: u64) -> String {
        format!("{}/client/{client}/scene/{scene}/ego", self.prefix)
    }

    /// Every scene's ego key (the server's subscription).
    pub fn ego_any(&self) -> String {
        format!("{}/client/*/scene/*/ego", self.prefix)
    }

    /// The server publishes [`NpcTick`] here for `client`'s scene `scene`.
    pub fn npc(&self, client: &str, scene: u64) -> String {
        format!("{}/client/{client}/scene/{scene}/npc", self.prefix)
    }

    /// The server publishes [`ErrorReply`] here for puts it refused (ticks have no reply of
    /// their own). `client` and `scene` are the key chunks the bad put used, even when they
    /// name no client or scene of this server.
    pub fn error(&self, client: &str, scene: &str) -> String {
        format!("{}/client/{client}/scene/{scene}/error", self.prefix)
    }

    /// Where the server answers a put on `client`'s ego key of scene `scene` that lacks the
    /// scene's token ([`SceneCreated::token`]): not on the error key, whose messages end the
    /// owner's wait, since anyone may put on any key. A client writer debugging its puts
    /// subscribes here.
    pub fn refused(&self, client: &str, scene: &str) -> String {
        format!("{}/client/{client}/scene/{scene}/refused", self.prefix)
    }

    /// The NPC keys of all of `client`'s scenes (the client's one subscription to them).
    pub fn client_npc_any(&self, client: &str) -> String {
        format!("{}/client/{client}/scene/*/npc", self.prefix)
    }

    /// The error keys of all of `client`'s scenes.
    pub fn client_error_any(&self, client: &str) -> String {
        format!("{}/client/{client}/scene/*/error", self.prefix)
    }

    /// The client and scene chunks of an ego key (`<prefix>/client/<client>/scene/<scene>/ego`),
    /// or `None` when `key` is not one under this prefix.
    pub fn ego_key_chunks<'k>(&self, key: &'k str) -> Option<(&'k str, &'k str)> {
        let rest = key.strip_prefix(&self.prefix)?.strip_prefix("/client/")?;
        let (client, rest) = rest.split_once("/scene/")?;
        let scene = rest.strip_suffix("/ego")?;
        let single_chunks = !client.is_empty()
            && !scene.is_empty()
            && !client.contains('/')
            && !scene.contains('/');
        single_chunks.then_some((client, scene))
    }

    /// The server's liveliness token.
    pub fn server_alive(&self) -> String {
        format!("{}/alive/server", self.prefix)
    }

    /// A client's liveliness token: when it goes, the server closes the client's scenes.
    pub fn client_alive(&self, client: &str) -> String {
        format!("{}/alive/client/{client}", self.prefix)
    }

    /// Every client's liveliness token (the server's liveliness subscription).
    pub fn client_alive_any(&self) -> String {
        format!("{}/alive/client/*", self.prefix)
    }
}

/// The key expression that matches the liveliness token of every server whose prefix is
/// `root` or lies below it (`road/**/alive/server` matches `road/alive/server` and
/// `road/east/alive/server`): what a client queries to find servers.
pub fn servers_alive_under(root: &str) -> String {
    format!("{}/**/alive/server", root.trim_matches('/'))
}

/// The prefix of the server whose liveliness token is at `key` (`road/east/alive/server` →
/// `road/east`), or `None` when `key` is not a server's token.
pub fn server_prefix_of(key: &str) -> Option<&str> {
    key.strip_suffix("/alive/server")
        .filter(|prefix| !prefix.is_empty())
}

/// The `token` field of a JSON payload, if it has one as a string: what a put is checked
/// against before anything else of it is read (a payload that does not parse still names its
/// token when it has one).
pub fn token_of(payload: &[u8]) -> Option<String> {
    let value: serde_json::Value = serde_json::from_slice(payload).ok()?;
    value.get("token")?.as_str().map(str::to_owned)
}

/// Compares two tokens in time independent of where they differ.
pub fn same_token(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// Whether `id` can be a client id: one key chunk of 1 to 64 ASCII letters, digits, `-` or
/// `_`.
pub fn valid_client_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 64
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
}

/// A pose: metres and radians in the map's frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Pose {
    pub x_m: f64,
    pub y_m: f64,
    pub heading_rad: f64,
}

/// Where a scene's map comes from (exactly one key).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum MapSource {
    /// A map built from code, by name: `"roundabout"`, `"intersection"` or `"merge"`.
    Procedural(String),
    /// A Lanelet2 `.osm` document, by value.
    Osm(String),
    /// A map file the server was started with (`--map NAME=FILE`), by name.
    File(String),
}

/// One agent at creation: its box and its observed history, oldest first, `step_secs`
/// apart, the last entry at step 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentInit {
    pub id: u32,
    pub length_m: f64,
    pub width_m: f64,
    pub history: Vec<Pose>,
}

/// Creates a scene (the `create` queryable's payload).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateScene {
    pub map: MapSource,
    /// The agents and their histories (at least the planner's `n` observed steps each).
    /// Omitted: the procedural map's own vehicles (only for `map.procedural`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agents: Option<Vec<AgentInit>>,
    /// Ids of the agents the client drives (its ego stack's); the model drives the others.
    #[serde(default)]
    pub external: Vec<u32>,
    /// A planner of `configs/planners.toml`; omitted: the checkpoint's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub planner: Option<String>,
    /// A checkpoint folder name under the server's models folder; omitted: the server's
    /// default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub checkpoint: Option<String>,
    /// Seeds the scene's noise: same request, seed and ego puts, the same NPCs to within about
    /// 2 mm, bit for bit for a scene served alone on the CPU engine (`docs/protocol.md`).
    #[serde(default)]
    pub seed: u64,
    /// The client's id (see [`valid_client_id`]); required (the server refuses a request
    /// without it): the scene's keys name it, and the scene is closed when the client's
    /// liveliness token goes. `road_client::Client::create` fills it in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client: Option<String>,
    /// Ticks after which the scene refuses more; omitted: the server's limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_ticks: Option<u64>,
    /// Every [`NpcTick`] also carries each NPC's plan ([`NpcTick::plans`]); default false
    /// (it costs one more readback per tick).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub plans: bool,
    /// Vehicles the server puts on the map around `agents` (which may then be just the ego,
    /// or omitted): see [`Populate`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub populate: Option<Populate>,
    /// Vehicles keep entering at the map's entry lanes (lanelets without a predecessor) while
    /// the scene runs: see [`Inflow`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inflow: Option<Inflow>,
}

/// Model-driven vehicles entering a scene at each of its map's entry lanes (lanelets no other
/// lanelet leads into), as a Poisson process; arrivals queue beyond the map (up to 4 an entry)
/// until their entry has room, and one that finds the scene at the server's agent limit is
/// dropped. Each enters with a 1 s
/// history from beyond the map along the lane and a new id, announced in
/// [`NpcTick::entered`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inflow {
    /// Arrivals per minute at each entry lane, in (0, 60].
    pub vehicles_per_minute: f64,
    /// A target count: arrivals wait while the scene holds this many agents or more (the
    /// ego included), so that vehicles come in as others leave; at most the server's agent
    /// limit. Omitted: the limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_vehicles: Option<u32>,
}

/// How many model-driven vehicles the server puts on the map at creation, besides the given
/// agents: exactly one of `vehicles` and `vehicles_per_100m`. They are placed on lane centres
/// with room around them, their 1 s histories along their lanes, then refined by the model
/// around the given agents (`docs/protocol.md`, "Populating a map"). [`SceneCreated::agents`]
/// lists them (ids after the largest given id).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Populate {
    /// This many vehicles (fewer when the map has no more room; at most the server's agent
    /// limit with the given agents).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicles: Option<u32>,
    /// So many vehicles per 100 m of the map's lane centre lines, in (0, 10]; capped at the
    /// server's agent limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicles_per_100m: Option<f64>,
    /// Whether the model refines the placed histories (default true); false: the placement
    /// as it is (constant speed on the lane centre).
    #[serde(default = "default_true")]
    pub refine: bool,
    /// A checkpoint trained to draw whole vehicles (`road20-init`, embedded in the server)
    /// draws the placed vehicles anew around the given agents, from their placement under
    /// about 4 m of noise (`docs/protocol.md`, "Populating a map"); a vehicle it draws
    /// off the lanes or onto another keeps its refined placement. `"none"`: the
    /// placement refined by the scene's checkpoint only. Omitted: the server's default
    /// initialiser (`road serve --initialiser`, road20-init) where it fits the scene's
    /// checkpoint (the same observed steps and window cut), else none; with `refine: false`
    /// none (the placement as it is).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub initialiser: Option<String>,
}

fn default_true() -> bool {
    true
}

impl CreateScene {
    /// A scene on the procedural map `map` (`roundabout`, `intersection`, `merge`) with the
    /// map's own vehicles, `external` driven by the client; the rest as the server defaults.
    pub fn procedural(map: &str, external: Vec<u32>, seed: u64) -> Self {
        Self {
            map: MapSource::Procedural(map.into()),
            agents: None,
            external,
            planner: None,
            checkpoint: None,
            seed,
            client: None,
            max_ticks: None,
            plans: false,
            populate: None,
            inflow: None,
        }
    }
}

/// What the server made of an agent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgentInfo {
    pub id: u32,
    pub length_m: f64,
    pub width_m: f64,
    pub external: bool,
    /// The history the scene starts from, oldest first, the last entry at step 0.
    pub history: Vec<Pose>,
}

/// The `create` queryable's reply.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneCreated {
    pub protocol: u32,
    pub scene: u64,
    pub agents: Vec<AgentInfo>,
    pub planner: String,
    pub checkpoint: String,
    /// History steps the model observes (n).
    pub observed_steps: usize,
    pub step_secs: f64,
    pub max_ticks: u64,
    /// How long after publishing tick t − 1 the server waits for tick t's ego before the
    /// model drives the external agents for that tick; 0: it waits forever.
    pub late_ego_deadline_ms: u64,
    /// Where to put ticks, where NPC states and errors come.
    pub ego_key: String,
    pub npc_key: String,
    pub error_key: String,
    /// The MCAP file recording the scene, on the server's machine.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recording: Option<String>,
    /// The scene's secret (32 hex digits, drawn at random for this scene): every [`EgoTick`]
    /// and [`CloseScene`] of the scene must carry it. Zenoh does not tell a server who sent a
    /// put, so a client id alone can be faked by anyone who can read or guess it; the token
    /// reaches only the creating query's reply.
    pub token: String,
}

impl SceneCreated {
    /// Agent `id` at step `tick`, driven on from step 0 at its last observed velocity and
    /// heading (a scripted ego's simplest drive); `None` without that agent or without two
    /// history poses.
    pub fn constant_velocity(&self, id: u32, tick: u64) -> Option<AgentState> {
        let history = &self.agents.iter().find(|a| a.id == id)?.history;
        let [.., previous, last] = history.as_slice() else {
            return None;
        };
        let k = tick as f64;
        Some(AgentState {
            id,
            x_m: last.x_m + (last.x_m - previous.x_m) * k,
            y_m: last.y_m + (last.y_m - previous.y_m) * k,
            heading_rad: last.heading_rad,
        })
    }
}

/// An agent's state at one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentState {
    pub id: u32,
    pub x_m: f64,
    pub y_m: f64,
    pub heading_rad: f64,
}

impl AgentState {
    pub fn pose(&self) -> Pose {
        Pose {
            x_m: self.x_m,
            y_m: self.y_m,
            heading_rad: self.heading_rad,
        }
    }
}

/// The client's external agents at step `tick` (put on the scene's ego key).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EgoTick {
    /// The step these poses are at: one more than the last tick the server published.
    pub tick: u64,
    /// Every external agent of the scene, once each.
    pub agents: Vec<AgentState>,
    /// The scene's client id: the one its ego key names.
    pub client: String,
    /// The scene's secret, [`SceneCreated::token`].
    pub token: String,
}

/// Every NPC at step `tick` (published on the scene's npc key), with the step's
/// infractions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NpcTick {
    pub scene: u64,
    pub tick: u64,
    pub time_s: f64,
    /// The model's agents.
    pub npcs: Vec<AgentState>,
    /// Pairs of agent ids (smaller first) whose boxes overlap at this step (pairs that
    /// overlapped at step 0 are not counted).
    pub collisions: Vec<[u32; 2]>,
    /// Agents whose centre is off every lane at this step (agents off-road at step 0 are not
    /// counted). Empty on maps without lanes.
    pub off_road: Vec<u32>,
    /// The tick's ego came after the deadline (or not at all): the model drove the external
    /// agents this step; their poses are here.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub late_external: Vec<AgentState>,
    /// NPCs that left the scene this tick: they drove off the map through an open lane end (the
    /// end of a lane with no successor, or the start of one with no predecessor), or the
    /// planner's stuck removal took them out (listed in [`Self::stuck`] too); they are in no
    /// later tick (protocol 4).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub left: Vec<u32>,
    /// Those of [`Self::left`] taken out by the planner's stuck removal: they stood stuck in a
    /// jam for its time, or across or against their lanes for its shorter time, far from the
    /// client's agents (`stuck_removal` in `configs/planners.toml`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub stuck: Vec<u32>,
    /// NPCs that entered the scene before this tick (a scene created with `inflow`), as
    /// [`SceneCreated::agents`] lists agents: id (new, never reused), size, the history it
    /// came with; their states are in `npcs` from this tick on.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub entered: Vec<AgentInfo>,
    /// When the scene was created with `plans`: each NPC's plan, the model's estimate of its
    /// poses at the steps after this one (its window's later slots; the far ones the least
    /// certain). The NPCs' next states may differ: the model replans every tick.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub plans: Vec<AgentPlan>,
    /// Milliseconds from the ego's arrival (or the deadline) to this publication.
    pub latency_ms: f64,
    /// Milliseconds of engine compute for this tick (part of `latency_ms`).
    pub compute_ms: f64,
    /// Milliseconds of `latency_ms` spent waiting for engine rounds of other scenes that were
    /// already running when the ego arrived (continuous batching: a tick joins the next
    /// round). `latency_ms − compute_ms − queue_ms` is the server's own time.
    #[serde(default)]
    pub queue_ms: f64,
}

/// One NPC's plan: its poses at ticks `tick + 1`, `tick + 2`, … of the [`NpcTick`] that holds
/// it, 0.1 s apart.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgentPlan {
    pub id: u32,
    pub poses: Vec<Pose>,
}

/// Closes a scene (the `close` queryable's payload).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CloseScene {
    pub scene: u64,
    /// The scene's client id.
    pub client: String,
    /// The scene's secret, [`SceneCreated::token`].
    pub token: String,
}

/// The `close` queryable's reply.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneClosed {
    pub scene: u64,
    pub ticks: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recording: Option<String>,
}

/// Percentiles of a latency sample, milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Percentiles {
    pub count: u64,
    pub p50_ms: f64,
    pub p90_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
}

/// One live scene in the status.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneStatus {
    pub scene: u64,
    pub tick: u64,
    pub agents: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client: Option<String>,
    /// Seconds since the scene last heard from its client.
    pub idle_s: f64,
    pub late_ticks: u64,
    /// Puts on the scene's ego key refused for a missing or wrong token (not answered: the
    /// sender cannot be told apart from the owner on that key).
    #[serde(default)]
    pub refused_puts: u64,
}

/// The `status` queryable's reply.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub protocol: u32,
    pub engine: String,
    pub checkpoint: String,
    pub capacity: usize,
    pub scenes: Vec<SceneStatus>,
    /// Engine rounds so far, and how many scenes ticked in each (last, mean, max).
    pub rounds: u64,
    pub last_batch: usize,
    pub mean_batch: f64,
    pub max_batch: usize,
    /// Ego arrival to NPC publication, over the last 4096 scene-ticks.
    pub tick_latency: Percentiles,
    /// Engine compute per scene-tick, over the same ticks.
    pub compute: Percentiles,
    /// Wait for other scenes' running rounds per scene-tick (`NpcTick::queue_ms`), over the
    /// same ticks.
    #[serde(default)]
    pub queue: Percentiles,
}

/// What went wrong, by kind; `docs/protocol.md` has one row per kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// The payload is not UTF-8 JSON of the expected shape (garbage, a missing or mistyped
    /// field).
    MalformedJson,
    /// A field the message does not have.
    UnknownField,
    /// The payload is larger than the server's limit.
    PayloadTooLarge,
    /// A value out of range or inconsistent (NaN, sizes, counts, duplicate ids, ...).
    InvalidField,
    /// The map cannot be used (unknown name, unparsable `.osm`, no lanelets).
    BadMap,
    /// An unknown planner or checkpoint, or one that does not fit the other.
    BadModel,
    /// The server holds as many scenes as it may.
    Capacity,
    /// No scene has this id (never had, or closed).
    UnknownScene,
    /// The tick does not fit the scene's sequence or its agents.
    BadTick,
    /// A client other than the scene's owner.
    NotOwner,
    /// The server failed; the scene is closed.
    Internal,
    /// The server closed the scene without its client asking: the client's liveliness token
    /// went, the server stops (the message says which).
    SceneClosed,
    /// The server closed the scene because its client went quiet: nothing from it for the
    /// idle timeout, or too many ticks in a row that the model drove for want of its ego.
    ClientSilent,
}

/// An error reply (a query's error reply, or a message on a scene's error key).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorReply {
    pub code: ErrorCode,
    /// The input at fault, as a JSON path (`agents[2].history[0].x_m`, `map.osm`, `tick`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    pub message: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tick: Option<u64>,
}

impl ErrorReply {
    pub fn new(code: ErrorCode, field: Option<&str>, message: impl Into<String>) -> Self {
        Self {
            code,
            field: field.map(str::to_owned),
            message: message.into(),
            scene: None,
            tick: None,
        }
    }
}

impl std::fmt::Display for ErrorReply {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:?}: {}", self.code, self.message)?;
        if let Some(field) = &self.field {
            write!(f, " (field {field})")?;
        }
        if let Some(scene) = self.scene {
            write!(f, " (scene {scene})")?;
        }
        if let Some(tick) = self.tick {
            write!(f, " (tick {tick})")?;
        }
        Ok(())
    }
}

impl std::error::Error for ErrorReply {}

/// Parses a JSON payload into `T`, mapping serde's complaint to an [`ErrorReply`] that names
/// the field where serde knows it.
pub fn parse<T: serde::de::DeserializeOwned>(payload: &[u8]) -> Result<T, ErrorReply> {
    let text = std::str::from_utf8(payload).map_err(|e| {
        ErrorReply::new(
            ErrorCode::MalformedJson,
            None,
            format!("the payload is not UTF-8 text: {e}"),
        )
    })?;
    let mut deserializer = serde_json::Deserializer::from_str(text);
    let value = serde_path_to_error::deserialize(&mut deserializer).map_err(|e| {
        // Where serde was in the document: `agents[2].history[0]`, or `.` at the top.
        let path = e.path().to_string();
        let inner = e.into_inner();
        // A document that ends early names no field (its message gives where it ended).
        let data_fault = inner.classify() != serde_json::error::Category::Eof;
        let message = inner.to_string();
        let at = |name: Option<&str>| -> Option<String> {
            let within = (path != ".").then_some(path.as_str());
            match (within, name) {
                (Some(p), Some(n)) => Some(format!("{p}.{n}")),
                (Some(p), None) => Some(p.to_owned()),
                (None, Some(n)) => Some(n.to_owned()),
                (None, None) => None,
            }
        };
        // serde_json words these `unknown field `x`, expected ...` and `missing field `x``.
        let quoted = message.split('`').nth(1);
        // The path of an unknown field already ends in its name; an unknown variant's is
        // the enum's.
        if message.starts_with("unknown field") {
            ErrorReply {
                field: at(None),
                ..ErrorReply::new(ErrorCode::UnknownField, None, message)
            }
        } else if message.starts_with("unknown variant") {
            ErrorReply {
                field: at(quoted),
                ..ErrorReply::new(ErrorCode::UnknownField, None, message)
            }
        } else if message.starts_with("missing field") {
            ErrorReply {
                field: at(quoted),
                ..ErrorReply::new(ErrorCode::MalformedJson, None, message)
            }
        } else {
            ErrorReply {
                field: data_fault.then(|| at(None)).flatten(),
                ..ErrorReply::new(ErrorCode::MalformedJson, None, message)
            }
        }
    })?;
    // Trailing characters after the document.
    deserializer
        .end()
        .map_err(|e| ErrorReply::new(ErrorCode::MalformedJson, None, e.to_string()))?;
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_server_token_names_its_prefix() {
        assert_eq!(servers_alive_under("/road/"), "road/**/alive/server");
        let east = Keys::new("road/east");
        assert_eq!(server_prefix_of(&east.server_alive()), Some("road/east"));
        assert_eq!(
            server_prefix_of(&Keys::new(DEFAULT_PREFIX).server_alive()),
            Some("road")
        );
        assert_eq!(server_prefix_of(&east.client_alive("ego")), None);
        assert_eq!(server_prefix_of("/alive/server"), None);
    }

    #[test]
    fn requests_round_trip() {
        let create = CreateScene {
            map: MapSource::Procedural("roundabout".into()),
            agents: Some(vec![AgentInit {
                id: 7,
                length_m: 4.5,
                width_m: 1.8,
                history: vec![Pose {
                    x_m: 1.0,
                    y_m: 2.0,
                    heading_rad: 0.5,
                }],
            }]),
            external: vec![7],
            planner: None,
            checkpoint: Some("road20".into()),
            seed: 3,
            client: Some("ego-1".into()),
            max_ticks: None,
            plans: true,
            populate: Some(Populate {
                vehicles: None,
                vehicles_per_100m: Some(1.5),
                refine: true,
                initialiser: Some("road20-init".into()),
            }),
            inflow: Some(Inflow {
                vehicles_per_minute: 6.0,
                max_vehicles: Some(12),
            }),
        };
        let json = serde_json::to_vec(&create).unwrap();
        assert_eq!(parse::<CreateScene>(&json).unwrap(), create);
        let text = String::from_utf8(json).unwrap();
        assert!(
            text.contains(r#""map":{"procedural":"roundabout"}"#),
            "{text}"
        );
    }

    #[test]
    fn parse_errors_name_the_field() {
        let e = parse::<CreateScene>(br#"{"map":{"procedural":"x"},"sede":1}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::UnknownField);
        assert_eq!(e.field.as_deref(), Some("sede"));
        let e = parse::<CreateScene>(br#"{"external":[]}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::MalformedJson);
        assert_eq!(e.field.as_deref(), Some("map"));
        let e = parse::<EgoTick>(&[0xff, 0xfe, 0x00]).unwrap_err();
        assert_eq!(e.code, ErrorCode::MalformedJson);
        assert!(e.message.contains("UTF-8"), "{e}");
        // Deeper faults name their path (issue 41: `map: {}` named nothing).
        let e = parse::<CreateScene>(br#"{"map":{},"client":"c"}"#).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("map"), "{e}");
        let e = parse::<CreateScene>(br#"{"map":{"atlantis":"x"},"client":"c"}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::UnknownField);
        assert_eq!(e.field.as_deref(), Some("map.atlantis"), "{e}");
        let e = parse::<CreateScene>(
            br#"{"map":{"procedural":"merge"},"client":"c","agents":[
                {"id":1,"length_m":4,"width_m":2,"history":[{"x_m":0,"y_m":"north","heading_rad":0}]}]}"#,
        )
        .unwrap_err();
        assert_eq!(e.code, ErrorCode::MalformedJson);
        assert_eq!(e.field.as_deref(), Some("agents[0].history[0].y_m"), "{e}");
        let e = parse::<EgoTick>(br#"{"tick":1,"agents":[{"id":1}],"client":"c","token":"t"}"#)
            .unwrap_err();
        assert_eq!(e.field.as_deref(), Some("agents[0].x_m"), "{e}");
        let e =
            parse::<EgoTick>(br#"{"tick":1,"agents":[],"client":"c","token":"t"} x"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::MalformedJson);
    }

    #[test]
    fn replies_ignore_fields_they_do_not_know_and_requests_refuse_them() {
        // A newer server's reply field must not break a deployed client (protocol 3) …
        let tick: NpcTick = serde_json::from_str(
            r#"{"scene":1,"tick":2,"time_s":0.2,"npcs":[],"collisions":[],"off_road":[],
                "latency_ms":5.0,"compute_ms":4.0,"a_field_from_the_future":[1,2]}"#,
        )
        .unwrap();
        assert_eq!((tick.scene, tick.tick, tick.queue_ms), (1, 2, 0.0));
        let closed: SceneClosed =
            serde_json::from_str(r#"{"scene":3,"ticks":9,"new":true}"#).unwrap();
        assert_eq!((closed.scene, closed.ticks), (3, 9));
        // … while a misspelt request field is still refused by name.
        let e = parse::<EgoTick>(br#"{"tick":1,"agents":[],"tik":2}"#).unwrap_err();
        assert_eq!(e.code, ErrorCode::UnknownField);
        assert_eq!(e.field.as_deref(), Some("tik"));
    }

    #[test]
    fn a_constant_velocity_ego_goes_on_from_its_last_step() {
        let pose = |x_m: f64| Pose {
            x_m,
            y_m: 1.0,
            heading_rad: 0.0,
        };
        let created = SceneCreated {
            protocol: PROTOCOL_VERSION,
            scene: 1,
            agents: vec![AgentInfo {
                id: 4,
                length_m: 4.5,
                width_m: 1.8,
                external: true,
                history: vec![pose(0.0), pose(1.0), pose(1.5)],
            }],
            planner: "road20".into(),
            checkpoint: "road20".into(),
            observed_steps: 3,
            step_secs: 0.1,
            max_ticks: 10,
            late_ego_deadline_ms: 0,
            ego_key: String::new(),
            npc_key: String::new(),
            error_key: String::new(),
            recording: None,
            token: String::new(),
        };
        let at = created.constant_velocity(4, 2).unwrap();
        assert_eq!((at.id, at.x_m, at.y_m), (4, 2.5, 1.0));
        assert_eq!(created.constant_velocity(5, 1), None);
        assert_eq!(
            CreateScene::procedural("merge", vec![1], 3).map,
            MapSource::Procedural("merge".into())
        );
    }

    #[test]
    fn tokens_are_read_from_any_json_and_compared_whole() {
        assert_eq!(
            token_of(br#"{"tick": 1, "token": "ab12"}"#).as_deref(),
            Some("ab12")
        );
        // Read before the rest of the message is checked: unknown fields do not hide it.
        assert_eq!(
            token_of(br#"{"nonsense": [1, 2], "token": "ab12"}"#).as_deref(),
            Some("ab12")
        );
        for payload in [&b"{\"token\": 7}"[..], b"[]", b"not json", b"{\"tick\": 1}"] {
            assert_eq!(token_of(payload), None);
        }
        assert!(same_token("ab12", "ab12"));
        assert!(!same_token("ab12", "ab13") && !same_token("ab12", "ab1") && !same_token("", "a"));
    }

    #[test]
    fn ego_keys_name_client_and_scene() {
        let keys = Keys::new("road/east");
        assert_eq!(
            keys.ego_key_chunks(&keys.ego("ego-1", 42)),
            Some(("ego-1", "42"))
        );
        assert_eq!(
            keys.ego_key_chunks("road/east/client/c/scene/x/ego"),
            Some(("c", "x"))
        );
        for key in [
            "road/client/c/scene/1/ego",
            "road/east/client/c/scene/1/npc",
            "road/east/client//scene/1/ego",
            "road/east/client/a/b/scene/1/ego",
            "road/east/client/c/scene/1/2/ego",
        ] {
            assert_eq!(keys.ego_key_chunks(key), None, "{key}");
        }
        assert_eq!(
            keys.npc("c", 3),
            "road/east/client/c/scene/3/npc",
            "the client's npc subscription {} matches it",
            keys.client_npc_any("c")
        );
        assert_eq!(keys.error("c", "3"), "road/east/client/c/scene/3/error");
    }

    #[test]
    fn client_ids_are_single_key_chunks() {
        assert!(valid_client_id("ego-1_a"));
        for bad in ["", "a/b", "*", "a$", &"x".repeat(65)] {
            assert!(!valid_client_id(bad), "{bad}");
        }
    }
}
