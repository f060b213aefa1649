//! The live view: a WebSocket server speaking the Foxglove WebSocket protocol (subprotocol
//! `foxglove.websocket.v1`), so that Foxglove, connected to `ws://host:port`, shows every live
//! scene's map and agent boxes while the server runs (`road serve --foxglove ADDR`).
//!
//! Only the part of the protocol a viewer needs, by hand on `tokio-tungstenite` (the `foxglove`
//! crate would pull a second mcap, prost and a second WebSocket stack): `serverInfo` with no
//! capabilities, `advertise` / `unadvertise` of channels, the clients' `subscribe` and
//! `unsubscribe`, binary Message Data frames, and a `status` reply to anything else.
//!
//! Why a queue between the core and the sockets: the core thread must never wait on a viewer.
//! The core only pushes onto a bounded queue ([`LiveView::publish`] never blocks); a thread of
//! the live view, with its own tokio runtime, fans the messages out, and every client has its
//! own bounded queue. A full queue drops its **oldest** droppable message (an agents update is
//! superseded by the next one anyway), counts it ([`LiveView::stats`]) and warns; control
//! messages and reliable messages (the map, a closed scene's clearing) are never dropped, and
//! a client that falls so far behind that its queue holds [`CLIENT_QUEUE_RELIABLE`] of them is
//! disconnected.

use std::collections::{BTreeMap, VecDeque};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime};

use futures_util::{SinkExt, StreamExt};
use serde::Deserialize;
use serde_json::{Value, json};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;
use tokio::task::JoinSet;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode, header};
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;

use crate::{Error, Result};

/// The WebSocket subprotocol a client must offer (and the server answers with).
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";

/// The first byte of a binary Message Data frame.
pub const MESSAGE_DATA_OPCODE: u8 = 0x01;

/// Bytes before the payload in a Message Data frame: opcode, subscription id, log time.
pub const MESSAGE_DATA_HEADER_BYTES: usize = 1 + 4 + 8;

/// Droppable messages the core's queue holds at most (about 8 s of 16 scenes at 10 Hz).
pub const CORE_QUEUE_DROPPABLE: usize = 1024;

/// Droppable frames a client's queue holds at most.
pub const CLIENT_QUEUE_DROPPABLE: usize = 256;

/// Reliable messages (control, map) a client's queue may hold before the client is cut off:
/// a client this far behind will never catch up, and its queue must not grow without bound.
pub const CLIENT_QUEUE_RELIABLE: usize = 4096;

/// A client that has not finished the WebSocket handshake by then is dropped.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// On stop, clients get this long to receive what is queued and the close frame.
const STOP_GRACE: Duration = Duration::from_secs(1);

/// Clients only send small JSON ops: a larger message is refused by the WebSocket layer.
const MAX_CLIENT_MESSAGE_BYTES: usize = 1 << 20;

/// A channel's id, unique for the life of a [`LiveView`] (ids are not reused).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ChannelId(u32);

impl ChannelId {
    pub fn get(self) -> u32 {
        self.0
    }
}

/// What a channel carries, as advertised to clients.
#[derive(Debug, Clone)]
pub struct ChannelSpec {
    pub topic: String,
    /// The messages' encoding (`json`).
    pub encoding: &'static str,
    pub schema_name: &'static str,
    /// The schema's encoding (`jsonschema`).
    pub schema_encoding: &'static str,
    pub schema: &'static str,
}

impl ChannelSpec {
    /// A channel of `foxglove.SceneUpdate` messages in JSON, with the schema the recordings
    /// embed, which Foxglove's 3D panel shows without configuration.
    pub fn scene_update(topic: impl Into<String>) -> Self {
        Self {
            topic: topic.into(),
            encoding: "json",
            schema_name: "foxglove.SceneUpdate",
            schema_encoding: "jsonschema",
            schema: crate::record::SCENE_UPDATE_SCHEMA,
        }
    }

    fn advertisement(&self, id: ChannelId) -> Value {
        json!({
            "id": id.0,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.schema_name,
            "schemaEncoding": self.schema_encoding,
            "schema": self.schema,
        })
    }
}

/// How a queue treats a message once it holds its bound of droppable ones.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Delivery {
    /// Control messages and data a viewer cannot do without (the map): never dropped.
    Reliable,
    /// Superseded by the next message of its channel: the oldest goes first when full.
    Droppable,
}

/// What a push did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pushed {
    Queued,
    /// Queued, and the oldest droppable message was dropped to make room.
    DroppedOldest,
    /// The queue holds too many reliable messages: it is closed, the message not queued.
    Overflow,
    /// The queue was closed before.
    Closed,
}

/// A bounded queue from a synchronous or asynchronous producer to one asynchronous consumer.
/// Pushing never waits (the lock is held only to push or to take everything queued).
#[derive(Debug)]
struct Outbox<T> {
    state: Mutex<OutboxState<T>>,
    ready: Notify,
    droppable_bound: usize,
    reliable_bound: usize,
}

#[derive(Debug)]
struct OutboxState<T> {
    items: VecDeque<(Delivery, T)>,
    droppable: usize,
    reliable: usize,
    closed: bool,
}

/// Locks a mutex whose holder may have panicked (the data stays usable: every critical
/// section leaves it consistent).
fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl<T> Outbox<T> {
    fn new(droppable_bound: usize, reliable_bound: usize) -> Self {
        Self {
            state: Mutex::new(OutboxState {
                items: VecDeque::new(),
                droppable: 0,
                reliable: 0,
                closed: false,
            }),
            ready: Notify::new(),
            droppable_bound: droppable_bound.max(1),
            reliable_bound,
        }
    }

    fn push(&self, delivery: Delivery, item: T) -> Pushed {
        let mut state = lock(&self.state);
        if state.closed {
            return Pushed::Closed;
        }
        let mut pushed = Pushed::Queued;
        match delivery {
            Delivery::Reliable => {
                if state.reliable >= self.reliable_bound {
                    state.closed = true;
                    state.items.clear();
                    drop(state);
                    self.ready.notify_one();
                    return Pushed::Overflow;
                }
                state.reliable += 1;
            }
            Delivery::Droppable => {
                if state.droppable >= self.droppable_bound {
                    let oldest = state
                        .items
                        .iter()
                        .position(|(d, _)| *d == Delivery::Droppable)
                        .expect("the count says one is queued");
                    state.items.remove(oldest);
                    state.droppable -= 1;
                    pushed = Pushed::DroppedOldest;
                }
                state.droppable += 1;
            }
        }
        state.items.push_back((delivery, item));
        drop(state);
        self.ready.notify_one();
        pushed
    }

    /// No more pushes; the consumer still takes what is queued, then gets `None`.
    fn close(&self) {
        lock(&self.state).closed = true;
        self.ready.notify_one();
    }

    /// Everything queued, in order, once there is something; `None` once closed and empty.
    async fn take(&self) -> Option<VecDeque<(Delivery, T)>> {
        loop {
            {
                let mut state = lock(&self.state);
                if !state.items.is_empty() {
                    state.droppable = 0;
                    state.reliable = 0;
                    return Some(std::mem::take(&mut state.items));
                }
                if state.closed {
                    return None;
                }
            }
            self.ready.notified().await;
        }
    }
}

/// What the core asks of the live view's thread.
#[derive(Debug)]
enum Command {
    Advertise {
        id: ChannelId,
        spec: ChannelSpec,
    },
    Publish {
        id: ChannelId,
        log_time_ns: u64,
        payload: Arc<[u8]>,
    },
    Unadvertise {
        id: ChannelId,
    },
    Stop,
}

/// The live view's counters.
#[derive(Debug, Default)]
struct Counters {
    clients: AtomicUsize,
    dropped_in_core_queue: AtomicU64,
    dropped_for_clients: AtomicU64,
    clients_cut_off: AtomicU64,
}

/// Counts a drop and warns on the 1st, 2nd, 4th, 8th… (a bounded log for any rate).
fn count_drop(counter: &AtomicU64, what: &str) {
    let dropped = counter.fetch_add(1, Ordering::Relaxed) + 1;
    if dropped.is_power_of_two() {
        tracing::warn!(dropped, "live view: {what} dropped (oldest first)");
    }
}

/// The live view's counters at one moment.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LiveStats {
    /// Connected clients (past the handshake).
    pub clients: usize,
    /// Messages dropped because the live view's thread fell behind the core.
    pub dropped_in_core_queue: u64,
    /// Frames dropped because a client read too slowly (summed over clients).
    pub dropped_for_clients: u64,
    /// Clients disconnected for falling too far behind.
    pub clients_cut_off: u64,
}

/// A running live view: a WebSocket server on its own thread and tokio runtime. Dropping it
/// stops it (as [`LiveView::stop`]).
#[derive(Debug)]
pub struct LiveView {
    addr: SocketAddr,
    queue: Arc<Outbox<Command>>,
    next_channel: AtomicU32,
    counters: Arc<Counters>,
    thread: Option<JoinHandle<()>>,
}

impl LiveView {
    /// Binds `addr` (port 0: any free port, see [`Self::local_addr`]) and starts serving.
    pub fn start(addr: SocketAddr) -> Result<Self> {
        let failed = |source: std::io::Error| Error::LiveView { addr, source };
        let listener = std::net::TcpListener::bind(addr).map_err(failed)?;
        listener.set_nonblocking(true).map_err(failed)?;
        let bound = listener.local_addr().map_err(failed)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()
            .map_err(failed)?;
        let listener = {
            let _context = runtime.enter();
            TcpListener::from_std(listener).map_err(failed)?
        };
        let queue = Arc::new(Outbox::new(CORE_QUEUE_DROPPABLE, usize::MAX));
        let counters = Arc::new(Counters::default());
        let hub = Arc::new(Mutex::new(Hub::new(Arc::clone(&counters))));
        let thread_queue = Arc::clone(&queue);
        let thread = std::thread::Builder::new()
            .name("road-serve-live".into())
            .spawn(move || {
                // Should the thread end early (a panic), later pushes are refused, not queued.
                let _close_on_exit = CloseOnDrop(Arc::clone(&thread_queue));
                runtime.block_on(serve(listener, thread_queue, hub));
            })
            .map_err(failed)?;
        tracing::info!(addr = %bound, "Foxglove live view listening");
        Ok(Self {
            addr: bound,
            queue,
            next_channel: AtomicU32::new(1),
            counters,
            thread: Some(thread),
        })
    }

    /// The address the server is bound to.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Announces a channel to every client, now and as they connect.
    pub fn advertise(&self, spec: ChannelSpec) -> ChannelId {
        let id = ChannelId(self.next_channel.fetch_add(1, Ordering::Relaxed));
        self.queue
            .push(Delivery::Reliable, Command::Advertise { id, spec });
        id
    }

    /// Sends a message to the channel's subscribers and keeps it as the one a new subscriber
    /// gets first. Droppable: when the live view or a client is behind, the oldest droppable
    /// message goes (a newer one of the channel supersedes it).
    pub fn publish(&self, channel: ChannelId, log_time_ns: u64, payload: impl Into<Arc<[u8]>>) {
        self.push_publish(Delivery::Droppable, channel, log_time_ns, payload.into());
    }

    /// As [`Self::publish`], but never dropped (a client too far behind for it is cut off):
    /// for messages a viewer cannot do without, such as the map, sent once.
    pub fn publish_reliable(
        &self,
        channel: ChannelId,
        log_time_ns: u64,
        payload: impl Into<Arc<[u8]>>,
    ) {
        self.push_publish(Delivery::Reliable, channel, log_time_ns, payload.into());
    }

    fn push_publish(
        &self,
        delivery: Delivery,
        id: ChannelId,
        log_time_ns: u64,
        payload: Arc<[u8]>,
    ) {
        let command = Command::Publish {
            id,
            log_time_ns,
            payload,
        };
        if self.queue.push(delivery, command) == Pushed::DroppedOldest {
            count_drop(
                &self.counters.dropped_in_core_queue,
                "messages from the core",
            );
        }
    }

    /// Withdraws a channel: clients forget it and their subscriptions to it.
    pub fn unadvertise(&self, channel: ChannelId) {
        self.queue
            .push(Delivery::Reliable, Command::Unadvertise { id: channel });
    }

    pub fn stats(&self) -> LiveStats {
        let c = &self.counters;
        LiveStats {
            clients: c.clients.load(Ordering::Relaxed),
            dropped_in_core_queue: c.dropped_in_core_queue.load(Ordering::Relaxed),
            dropped_for_clients: c.dropped_for_clients.load(Ordering::Relaxed),
            clients_cut_off: c.clients_cut_off.load(Ordering::Relaxed),
        }
    }

    /// Closes every connection (each client gets what was queued for it, for at most a
    /// second) and ends the thread.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        let Some(thread) = self.thread.take() else {
            return;
        };
        self.queue.push(Delivery::Reliable, Command::Stop);
        self.queue.close();
        if thread.join().is_err() {
            tracing::error!("the live view's thread panicked");
        }
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// Closes a queue when dropped.
struct CloseOnDrop<T>(Arc<Outbox<T>>);

impl<T> Drop for CloseOnDrop<T> {
    fn drop(&mut self) {
        self.0.close();
    }
}

/// A Message Data frame: `[0x01][u32 LE subscription id][u64 LE log time ns][payload]`.
pub fn message_data(subscription_id: u32, log_time_ns: u64, payload: &[u8]) -> Vec<u8> {
    let mut frame = Vec::with_capacity(MESSAGE_DATA_HEADER_BYTES + payload.len());
    frame.push(MESSAGE_DATA_OPCODE);
    frame.extend_from_slice(&subscription_id.to_le_bytes());
    frame.extend_from_slice(&log_time_ns.to_le_bytes());
    frame.extend_from_slice(payload);
    frame
}

/// A Message Data frame read back (for clients and tests).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MessageData<'a> {
    pub subscription_id: u32,
    pub log_time_ns: u64,
    pub payload: &'a [u8],
}

/// Reads a Message Data frame; `None` for another opcode or a frame shorter than its header.
pub fn parse_message_data(frame: &[u8]) -> Option<MessageData<'_>> {
    if frame.len() < MESSAGE_DATA_HEADER_BYTES || frame[0] != MESSAGE_DATA_OPCODE {
        return None;
    }
    let subscription_id = u32::from_le_bytes(frame[1..5].try_into().ok()?);
    let log_time_ns = u64::from_le_bytes(frame[5..13].try_into().ok()?);
    Some(MessageData {
        subscription_id,
        log_time_ns,
        payload: &frame[MESSAGE_DATA_HEADER_BYTES..],
    })
}

/// The `level` of a `status` message.
#[derive(Debug, Clone, Copy)]
enum StatusLevel {
    Warning = 1,
    Error = 2,
}

fn status(level: StatusLevel, message: impl Into<String>) -> Message {
    let message: String = message.into();
    Message::Text(json!({ "op": "status", "level": level as u8, "message": message }).to_string())
}

/// Ops of the protocol this server does not offer (they need a capability it does not list).
const UNSUPPORTED_OPS: [&str; 9] = [
    "advertise",
    "unadvertise",
    "getParameters",
    "setParameters",
    "subscribeParameterUpdates",
    "unsubscribeParameterUpdates",
    "subscribeConnectionGraph",
    "unsubscribeConnectionGraph",
    "fetchAsset",
];

#[derive(Debug, Deserialize)]
struct SubscribeOp {
    subscriptions: Vec<SubscriptionRequest>,
}

#[derive(Debug, Deserialize)]
#[serde(rename_all = "camelCase")]
struct SubscriptionRequest {
    id: u32,
    channel_id: u32,
}

#[derive(Debug, Deserialize)]
#[serde(rename_all = "camelCase")]
struct UnsubscribeOp {
    subscription_ids: Vec<u32>,
}

/// A connected client's queue, and the signal that cuts it off.
#[derive(Debug)]
struct ClientLink {
    outbox: Outbox<Message>,
    cut_off: Notify,
}

#[derive(Debug)]
struct Client {
    peer: SocketAddr,
    link: Arc<ClientLink>,
    /// Subscription id (the client's choice) → channel.
    subscriptions: BTreeMap<u32, ChannelId>,
    /// Channel → subscription id (one subscription per channel and client).
    by_channel: BTreeMap<ChannelId, u32>,
}

#[derive(Debug)]
struct Channel {
    advertisement: Value,
    /// The last message, which a new subscriber gets at once (a late joiner sees the map and
    /// the boxes without waiting).
    latest: Option<(Delivery, u64, Arc<[u8]>)>,
}

/// The state the accepting task and every connection share: channels and clients. Only held
/// for synchronous work (no await under the lock).
#[derive(Debug)]
struct Hub {
    channels: BTreeMap<ChannelId, Channel>,
    clients: BTreeMap<u64, Client>,
    next_client: u64,
    server_info: String,
    counters: Arc<Counters>,
}

impl Hub {
    fn new(counters: Arc<Counters>) -> Self {
        let session = crate::record::unix_nanos(SystemTime::now());
        let server_info = json!({
            "op": "serverInfo",
            "name": "road serve",
            "capabilities": [],
            "supportedEncodings": [],
            "metadata": {},
            "sessionId": session.to_string(),
        })
        .to_string();
        Self {
            channels: BTreeMap::new(),
            clients: BTreeMap::new(),
            next_client: 1,
            server_info,
            counters,
        }
    }

    /// A new client: its queue starts with `serverInfo` and the advertisement of every channel.
    fn join(&mut self, peer: SocketAddr) -> (u64, Arc<ClientLink>) {
        let id = self.next_client;
        self.next_client += 1;
        let link = Arc::new(ClientLink {
            outbox: Outbox::new(CLIENT_QUEUE_DROPPABLE, CLIENT_QUEUE_RELIABLE),
            cut_off: Notify::new(),
        });
        let channels: Vec<&Value> = self.channels.values().map(|c| &c.advertisement).collect();
        let advertise = json!({ "op": "advertise", "channels": channels }).to_string();
        link.outbox
            .push(Delivery::Reliable, Message::Text(self.server_info.clone()));
        link.outbox
            .push(Delivery::Reliable, Message::Text(advertise));
        self.clients.insert(
            id,
            Client {
                peer,
                link: Arc::clone(&link),
                subscriptions: BTreeMap::new(),
                by_channel: BTreeMap::new(),
            },
        );
        self.counters
            .clients
            .store(self.clients.len(), Ordering::Relaxed);
        (id, link)
    }

    fn leave(&mut self, id: u64) {
        self.clients.remove(&id);
        self.counters
            .clients
            .store(self.clients.len(), Ordering::Relaxed);
    }

    /// Queues `message` for client `id`; cuts the client off when it is too far behind.
    fn send(&mut self, id: u64, delivery: Delivery, message: Message) {
        let Some(client) = self.clients.get(&id) else {
            return;
        };
        match client.link.outbox.push(delivery, message) {
            Pushed::Queued | Pushed::Closed => {}
            Pushed::DroppedOldest => count_drop(
                &self.counters.dropped_for_clients,
                "frames for a slow client",
            ),
            Pushed::Overflow => {
                tracing::warn!(
                    peer = %client.peer,
                    "live view: a client is {CLIENT_QUEUE_RELIABLE} control messages behind; disconnected"
                );
                client.link.cut_off.notify_one();
                self.counters
                    .clients_cut_off
                    .fetch_add(1, Ordering::Relaxed);
                self.leave(id);
            }
        }
    }

    fn broadcast(&mut self, message: &Message) {
        let ids: Vec<u64> = self.clients.keys().copied().collect();
        for id in ids {
            self.send(id, Delivery::Reliable, message.clone());
        }
    }

    /// Applies the core's commands in order; `false` once asked to stop.
    fn apply(&mut self, commands: VecDeque<(Delivery, Command)>) -> bool {
        for (delivery, command) in commands {
            match command {
                Command::Advertise { id, spec } => {
                    let advertisement = spec.advertisement(id);
                    let message = json!({ "op": "advertise", "channels": [&advertisement] });
                    self.broadcast(&Message::Text(message.to_string()));
                    self.channels.insert(
                        id,
                        Channel {
                            advertisement,
                            latest: None,
                        },
                    );
                }
                Command::Publish {
                    id,
                    log_time_ns,
                    payload,
                } => {
                    let Some(channel) = self.channels.get_mut(&id) else {
                        tracing::debug!(channel = id.0, "live view: publish on no channel");
                        continue;
                    };
                    channel.latest = Some((delivery, log_time_ns, Arc::clone(&payload)));
                    let subscribers: Vec<(u64, u32)> = self
                        .clients
                        .iter()
                        .filter_map(|(&c, client)| client.by_channel.get(&id).map(|&s| (c, s)))
                        .collect();
                    for (client, subscription) in subscribers {
                        let frame = message_data(subscription, log_time_ns, &payload);
                        self.send(client, delivery, Message::Binary(frame));
                    }
                }
                Command::Unadvertise { id } => {
                    if self.channels.remove(&id).is_none() {
                        continue;
                    }
                    for client in self.clients.values_mut() {
                        if let Some(subscription) = client.by_channel.remove(&id) {
                            client.subscriptions.remove(&subscription);
                        }
                    }
                    let message = json!({ "op": "unadvertise", "channelIds": [id.0] });
                    self.broadcast(&Message::Text(message.to_string()));
                }
                Command::Stop => return false,
            }
        }
        true
    }

    /// Handles a client's text message; anything but a valid `subscribe` or `unsubscribe` is
    /// answered with a `status` naming the problem.
    fn on_text(&mut self, client: u64, text: &str) {
        let value: Value = match serde_json::from_str(text) {
            Ok(v) => v,
            Err(e) => {
                return self.reply_status(
                    client,
                    StatusLevel::Error,
                    format!("malformed JSON: {e}"),
                );
            }
        };
        let Some(op) = value.get("op").and_then(Value::as_str).map(str::to_owned) else {
            return self.reply_status(
                client,
                StatusLevel::Error,
                "a text message must be a JSON object with a string field \"op\"",
            );
        };
        match op.as_str() {
            "subscribe" => match serde_json::from_value::<SubscribeOp>(value) {
                Ok(request) => self.subscribe(client, request),
                Err(e) => self.reply_status(client, StatusLevel::Error, format!("subscribe: {e}")),
            },
            "unsubscribe" => match serde_json::from_value::<UnsubscribeOp>(value) {
                Ok(request) => self.unsubscribe(client, request),
                Err(e) => {
                    self.reply_status(client, StatusLevel::Error, format!("unsubscribe: {e}"))
                }
            },
            op if UNSUPPORTED_OPS.contains(&op) => self.reply_status(
                client,
                StatusLevel::Error,
                format!("op {op:?} needs a capability this server does not offer (it has none)"),
            ),
            op => self.reply_status(
                client,
                StatusLevel::Error,
                format!("unknown op {op:?}: this server handles subscribe and unsubscribe"),
            ),
        }
    }

    fn reply_status(&mut self, client: u64, level: StatusLevel, message: impl Into<String>) {
        let message = message.into();
        tracing::debug!(client, "live view: status to a client: {message}");
        self.send(client, Delivery::Reliable, status(level, message));
    }

    fn subscribe(&mut self, id: u64, request: SubscribeOp) {
        for SubscriptionRequest {
            id: subscription,
            channel_id,
        } in request.subscriptions
        {
            let channel = ChannelId(channel_id);
            let Some(client) = self.clients.get_mut(&id) else {
                return;
            };
            let problem = if client.subscriptions.contains_key(&subscription) {
                Some((
                    StatusLevel::Error,
                    format!("subscription id {subscription} is in use; ignored"),
                ))
            } else if client.by_channel.contains_key(&channel) {
                Some((
                    StatusLevel::Error,
                    format!(
                        "channel {channel_id} is subscribed already (one subscription per channel); subscription {subscription} ignored"
                    ),
                ))
            } else if !self.channels.contains_key(&channel) {
                Some((
                    StatusLevel::Warning,
                    format!(
                        "channel {channel_id} is not advertised (its scene may have closed); subscription {subscription} ignored"
                    ),
                ))
            } else {
                None
            };
            if let Some((level, message)) = problem {
                self.reply_status(id, level, message);
                continue;
            }
            client.subscriptions.insert(subscription, channel);
            client.by_channel.insert(channel, subscription);
            let latest = self.channels.get(&channel).and_then(|c| c.latest.clone());
            if let Some((delivery, log_time_ns, payload)) = latest {
                let frame = message_data(subscription, log_time_ns, &payload);
                self.send(id, delivery, Message::Binary(frame));
            }
        }
    }

    fn unsubscribe(&mut self, id: u64, request: UnsubscribeOp) {
        for subscription in request.subscription_ids {
            let Some(client) = self.clients.get_mut(&id) else {
                return;
            };
            match client.subscriptions.remove(&subscription) {
                Some(channel) => {
                    client.by_channel.remove(&channel);
                }
                None => self.reply_status(
                    id,
                    StatusLevel::Warning,
                    format!("no subscription {subscription} to end"),
                ),
            }
        }
    }

    /// Stop: every client's queue closes (its connection ends once the queue is sent).
    fn close_all(&mut self) {
        for client in self.clients.values() {
            client.link.outbox.close();
        }
    }
}

/// The live view's thread: accepts connections and applies the core's commands until stopped.
async fn serve(listener: TcpListener, queue: Arc<Outbox<Command>>, hub: Arc<Mutex<Hub>>) {
    let mut connections = JoinSet::new();
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    connections.spawn(serve_client(stream, peer, Arc::clone(&hub)));
                }
                Err(e) => {
                    // Out of descriptors, say: wait a little instead of spinning.
                    tracing::warn!("live view: cannot accept a connection: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            },
            commands = queue.take() => {
                let go_on = commands.is_some_and(|commands| lock(&hub).apply(commands));
                if !go_on {
                    break;
                }
            }
            Some(_) = connections.join_next(), if !connections.is_empty() => {}
        }
    }
    lock(&hub).close_all();
    let drained = async { while connections.join_next().await.is_some() {} };
    if tokio::time::timeout(STOP_GRACE, drained).await.is_err() {
        tracing::debug!("live view: clients still connected at stop; closed");
    }
}

/// Accepts the WebSocket handshake only with the Foxglove subprotocol, and answers with it.
#[allow(
    clippy::result_large_err,
    reason = "tungstenite's handshake callback returns its HTTP response as the error"
)]
fn negotiate(
    peer: SocketAddr,
) -> impl FnOnce(&Request, Response) -> Result<Response, ErrorResponse> {
    move |request: &Request, mut response: Response| {
        let offered = request
            .headers()
            .get_all(header::SEC_WEBSOCKET_PROTOCOL)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(','))
            .any(|p| p.trim() == SUBPROTOCOL);
        if offered {
            response.headers_mut().insert(
                header::SEC_WEBSOCKET_PROTOCOL,
                HeaderValue::from_static(SUBPROTOCOL),
            );
            return Ok(response);
        }
        tracing::info!(%peer, "live view: refused a WebSocket client without subprotocol {SUBPROTOCOL}");
        let mut refusal = ErrorResponse::new(Some(format!(
            "this is a Foxglove WebSocket server (road serve's live view): offer the subprotocol {SUBPROTOCOL}\n"
        )));
        *refusal.status_mut() = StatusCode::BAD_REQUEST;
        refusal
            .headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static("text/plain"));
        Err(refusal)
    }
}

/// One client: the handshake, then its queue written out while its ops are read.
async fn serve_client(stream: TcpStream, peer: SocketAddr, hub: Arc<Mutex<Hub>>) {
    let _ = stream.set_nodelay(true);
    let config = WebSocketConfig {
        max_message_size: Some(MAX_CLIENT_MESSAGE_BYTES),
        max_frame_size: Some(MAX_CLIENT_MESSAGE_BYTES),
        ..WebSocketConfig::default()
    };
    let handshake =
        tokio_tungstenite::accept_hdr_async_with_config(stream, negotiate(peer), Some(config));
    let ws = match tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake).await {
        Ok(Ok(ws)) => ws,
        Ok(Err(e)) => {
            tracing::debug!(%peer, "live view: no WebSocket connection: {e}");
            return;
        }
        Err(_) => {
            tracing::debug!(%peer, "live view: no WebSocket handshake in {HANDSHAKE_TIMEOUT:?}");
            return;
        }
    };
    let (id, link) = lock(&hub).join(peer);
    tracing::info!(%peer, client = id, "live view: Foxglove client connected");
    let (mut sink, mut incoming) = ws.split();
    let writer = async {
        while let Some(batch) = link.outbox.take().await {
            for (_, message) in batch {
                sink.feed(message).await?;
            }
            sink.flush().await?;
        }
        sink.close().await
    };
    let reader = async {
        while let Some(message) = incoming.next().await {
            match message {
                Ok(Message::Text(text)) => lock(&hub).on_text(id, &text),
                Ok(Message::Binary(_)) => lock(&hub).reply_status(
                    id,
                    StatusLevel::Error,
                    "binary client messages are not supported (no clientPublish or services capability)",
                ),
                Ok(Message::Close(_)) => break,
                Ok(_) => {} // pings are answered by tungstenite
                Err(e) => {
                    tracing::debug!(%peer, "live view: reading from a client: {e}");
                    break;
                }
            }
        }
    };
    tokio::select! {
        written = writer => {
            if let Err(e) = written {
                tracing::debug!(%peer, "live view: writing to a client: {e}");
            }
        }
        () = reader => {}
        () = link.cut_off.notified() => {}
    }
    lock(&hub).leave(id);
    tracing::info!(%peer, client = id, "live view: Foxglove client disconnected");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_message_data_frame_is_opcode_subscription_time_payload_little_endian() {
        let frame = message_data(0x0403_0201, 0x0c0b_0a09_0807_0605, b"{}");
        assert_eq!(
            frame,
            [
                0x01, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09, 0x0a, 0x0b, 0x0c, b'{',
                b'}'
            ]
        );
        let read = parse_message_data(&frame).unwrap();
        assert_eq!(read.subscription_id, 0x0403_0201);
        assert_eq!(read.log_time_ns, 0x0c0b_0a09_0807_0605);
        assert_eq!(read.payload, b"{}");
    }

    #[test]
    fn frames_round_trip_and_short_or_foreign_frames_do_not_parse() {
        for (subscription, nanos, payload) in [
            (0u32, 0u64, &b""[..]),
            (u32::MAX, u64::MAX, &b"x"[..]),
            (7, 1_700_000_000_123_456_789, &[0u8; 300][..]),
        ] {
            let frame = message_data(subscription, nanos, payload);
            assert_eq!(frame.len(), MESSAGE_DATA_HEADER_BYTES + payload.len());
            let read = parse_message_data(&frame).unwrap();
            assert_eq!(
                (read.subscription_id, read.log_time_ns, read.payload),
                (subscription, nanos, payload)
            );
        }
        let frame = message_data(1, 2, b"abc");
        assert!(parse_message_data(&frame[..MESSAGE_DATA_HEADER_BYTES - 1]).is_none());
        let mut time_frame = frame.clone();
        time_frame[0] = 0x02;
        assert!(parse_message_data(&time_frame).is_none());
    }

    #[test]
    fn a_full_queue_drops_its_oldest_droppable_message_and_keeps_reliable_ones() {
        let outbox = Outbox::new(2, 3);
        assert_eq!(outbox.push(Delivery::Reliable, "map"), Pushed::Queued);
        assert_eq!(outbox.push(Delivery::Droppable, "t1"), Pushed::Queued);
        assert_eq!(outbox.push(Delivery::Droppable, "t2"), Pushed::Queued);
        assert_eq!(
            outbox.push(Delivery::Droppable, "t3"),
            Pushed::DroppedOldest
        );
        assert_eq!(outbox.push(Delivery::Reliable, "close"), Pushed::Queued);
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let taken: Vec<&str> = runtime
            .block_on(outbox.take())
            .unwrap()
            .into_iter()
            .map(|(_, m)| m)
            .collect();
        assert_eq!(taken, ["map", "t2", "t3", "close"]);
        // Too many reliable messages: the queue closes instead of growing.
        for _ in 0..3 {
            assert_eq!(outbox.push(Delivery::Reliable, "ad"), Pushed::Queued);
        }
        assert_eq!(outbox.push(Delivery::Reliable, "ad"), Pushed::Overflow);
        assert_eq!(outbox.push(Delivery::Droppable, "t4"), Pushed::Closed);
        assert!(runtime.block_on(outbox.take()).is_none());
    }

    #[test]
    fn a_new_client_gets_server_info_then_every_channel() {
        let mut hub = Hub::new(Arc::default());
        let ad = Command::Advertise {
            id: ChannelId(3),
            spec: ChannelSpec::scene_update("/scene/1/map"),
        };
        assert!(hub.apply(VecDeque::from([(Delivery::Reliable, ad)])));
        let (_, link) = hub.join("127.0.0.1:9".parse().unwrap());
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let texts: Vec<Value> = runtime
            .block_on(link.outbox.take())
            .unwrap()
            .into_iter()
            .map(|(_, m)| serde_json::from_str(m.to_text().unwrap()).unwrap())
            .collect();
        assert_eq!(texts[0]["op"], "serverInfo");
        assert_eq!(texts[0]["name"], "road serve");
        assert_eq!(texts[1]["op"], "advertise");
        let channel = &texts[1]["channels"][0];
        assert_eq!(channel["id"], 3);
        assert_eq!(channel["schemaName"], "foxglove.SceneUpdate");
        assert_eq!(channel["schemaEncoding"], "jsonschema");
        assert!(channel["schema"].as_str().unwrap().contains("SceneUpdate"));
    }
}
