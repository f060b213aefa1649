//! The live view (`road serve --foxglove`): a Foxglove WebSocket client on loopback, beside a
//! zenoh ego client, sees each live scene's channels, gets its map and agent boxes as Message
//! Data frames, is answered with a `status` for bad ops, and sees a closed scene's channels
//! go. A client without the subprotocol is refused, and a client that never reads never holds
//! up publishing. Every wait is bounded; nothing is timed.

mod common;

use std::net::SocketAddr;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use road_serve::live::{self, ChannelSpec, LiveView};
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// Generous: a debug build on a busy 2-core machine, a scene's first tick is the warm-up.
const WAIT: Duration = Duration::from_secs(60);

const SCHEMA: &str = include_str!("../src/scene_update.schema.json");

/// A Foxglove client: a WebSocket with the subprotocol, on its own runtime.
struct Viewer {
    runtime: tokio::runtime::Runtime,
    ws: WebSocketStream<MaybeTlsStream<TcpStream>>,
}

/// A Message Data frame, owned.
#[derive(Debug)]
struct Frame {
    subscription: u32,
    log_time_ns: u64,
    payload: Value,
}

/// `future`, given [`WAIT`] at most (the timer is made inside the runtime).
async fn within<F: std::future::Future>(
    future: F,
) -> Result<F::Output, tokio::time::error::Elapsed> {
    tokio::time::timeout(WAIT, future).await
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

impl Viewer {
    fn connect(addr: SocketAddr) -> Self {
        let runtime = runtime();
        let mut request = format!("ws://{addr}").into_client_request().unwrap();
        request
            .headers_mut()
            .insert("Sec-WebSocket-Protocol", live::SUBPROTOCOL.parse().unwrap());
        let (ws, response) = runtime
            .block_on(within(tokio_tungstenite::connect_async(request)))
            .expect("the handshake timed out")
            .expect("the handshake failed");
        assert_eq!(
            response.headers()["Sec-WebSocket-Protocol"],
            live::SUBPROTOCOL
        );
        Self { runtime, ws }
    }

    fn send(&mut self, text: impl Into<String>) {
        self.runtime
            .block_on(self.ws.send(Message::Text(text.into())))
            .unwrap();
    }

    /// The next message, `None` when the connection ended.
    fn next(&mut self) -> Option<Message> {
        let next = self
            .runtime
            .block_on(within(self.ws.next()))
            .expect("nothing from the live view in time");
        match next {
            Some(Ok(Message::Close(_))) | None => None,
            Some(Ok(message)) => Some(message),
            Some(Err(e)) => panic!("reading the live view: {e}"),
        }
    }

    /// The next text message (an op), skipping frames.
    fn next_op(&mut self) -> Value {
        loop {
            match self.next().expect("the live view closed the connection") {
                Message::Text(text) => return serde_json::from_str(&text).unwrap(),
                Message::Binary(_) => continue,
                other => panic!("unexpected {other:?}"),
            }
        }
    }

    /// The next Message Data frame; ops in between must be none.
    fn next_frame(&mut self) -> Frame {
        match self.next().expect("the live view closed the connection") {
            Message::Binary(bytes) => {
                let data = live::parse_message_data(&bytes).expect("opcode 1 and a header");
                Frame {
                    subscription: data.subscription_id,
                    log_time_ns: data.log_time_ns,
                    payload: serde_json::from_slice(data.payload).expect("a JSON payload"),
                }
            }
            other => panic!("expected a Message Data frame, got {other:?}"),
        }
    }

    /// Reads `serverInfo` and the first `advertise`; the channels advertised.
    fn handshake_ops(&mut self) -> Vec<Value> {
        let info = self.next_op();
        assert_eq!(info["op"], "serverInfo", "{info}");
        assert_eq!(info["name"], "road serve");
        assert_eq!(info["capabilities"], json!([]));
        assert_eq!(info["supportedEncodings"], json!([]));
        assert!(info["sessionId"].is_string(), "{info}");
        let advertise = self.next_op();
        assert_eq!(advertise["op"], "advertise", "{advertise}");
        advertise["channels"].as_array().unwrap().clone()
    }

    /// Reads `advertise` ops until channels with both topics came; their ids (map, agents).
    fn scene_channels(&mut self, scene: u64, mut seen: Vec<Value>) -> (u32, u32) {
        let id_of = |seen: &[Value], topic: &str| {
            seen.iter()
                .find(|c| c["topic"] == topic)
                .map(|c| c["id"].as_u64().unwrap() as u32)
        };
        let (map, agents) = (
            format!("/scene/{scene}/map"),
            format!("/scene/{scene}/agents"),
        );
        loop {
            if let (Some(m), Some(a)) = (id_of(&seen, &map), id_of(&seen, &agents)) {
                for channel in seen
                    .iter()
                    .filter(|c| c["topic"] == map || c["topic"] == agents)
                {
                    assert_eq!(channel["encoding"], "json");
                    assert_eq!(channel["schemaName"], "foxglove.SceneUpdate");
                    assert_eq!(channel["schemaEncoding"], "jsonschema");
                    assert_eq!(channel["schema"], SCHEMA);
                }
                return (m, a);
            }
            let op = self.next_op();
            assert_eq!(op["op"], "advertise", "{op}");
            seen.extend(op["channels"].as_array().unwrap().iter().cloned());
        }
    }

    fn subscribe(&mut self, subscriptions: &[(u32, u32)]) {
        let subscriptions: Vec<Value> = subscriptions
            .iter()
            .map(|&(id, channel)| json!({ "id": id, "channelId": channel }))
            .collect();
        self.send(json!({ "op": "subscribe", "subscriptions": subscriptions }).to_string());
    }
}

/// A server with the live view on loopback port 0, and its recordings' folder (bind it as long
/// as the server runs).
fn start_server(name: &str) -> (common::TempFolder, road_serve::ServerHandle, SocketAddr) {
    let dir = common::temp_dir(name);
    let mut config = common::config(&dir);
    config.late_ego_deadline = Duration::ZERO; // a slow debug build must not turn ticks late
    config.foxglove_listen = Some("127.0.0.1:0".parse().unwrap());
    let server = common::start(config);
    let addr = server.foxglove_addr().expect("the live view runs");
    assert_ne!(addr.port(), 0, "the bound port is read back");
    (dir, server, addr)
}

/// The boxes of an agents update.
fn cubes(update: &Value) -> &Vec<Value> {
    assert_eq!(update["entities"][0]["id"], "agents", "{update}");
    update["entities"][0]["cubes"].as_array().unwrap()
}

#[test]
fn a_foxglove_client_watches_a_scene_tick_live() {
    let (_recordings, server, addr) = start_server("live");
    let mut viewer = Viewer::connect(addr);
    let before = viewer.handshake_ops();
    assert!(before.is_empty(), "no scene yet: {before:?}");

    let client = common::client(&server, "live-ego");
    let mut scene = client.create(common::roundabout()).unwrap();
    let agents = scene.created().agents.clone();
    let (map, boxes) = viewer.scene_channels(scene.id(), Vec::new());
    viewer.subscribe(&[(10, boxes), (11, map)]);
    // At once: the latest message of each channel, the map and the boxes at step 0.
    let mut first = [viewer.next_frame(), viewer.next_frame()];
    first.sort_by_key(|f| f.subscription);
    let [start, lanes] = first;
    assert_eq!(start.subscription, 10);
    assert_eq!(cubes(&start.payload).len(), agents.len());
    assert_eq!(lanes.subscription, 11);
    assert_eq!(lanes.payload["entities"][0]["id"], "lanes");
    assert!(
        !lanes.payload["entities"][0]["lines"]
            .as_array()
            .unwrap()
            .is_empty()
    );

    let history = agents[0].history.clone();
    let mut last_time = start.log_time_ns;
    for tick in 1..=3 {
        let npc = scene
            .step(tick, vec![common::replay(&history, 1, tick)])
            .unwrap();
        let frame = viewer.next_frame();
        assert_eq!(frame.subscription, 10, "tick {tick}");
        assert!(
            frame.log_time_ns > last_time,
            "tick {tick}: log times increase"
        );
        last_time = frame.log_time_ns;
        let cubes = cubes(&frame.payload);
        assert_eq!(cubes.len(), agents.len());
        // Each NPC's box is where the tick put it.
        for state in &npc.npcs {
            let k = agents.iter().position(|a| a.id == state.id).unwrap();
            let position = &cubes[k]["pose"]["position"];
            assert!((position["x"].as_f64().unwrap() - state.x_m).abs() < 1e-6);
            assert!((position["y"].as_f64().unwrap() - state.y_m).abs() < 1e-6);
            assert!((cubes[k]["size"]["x"].as_f64().unwrap() - agents[k].length_m).abs() < 1e-9);
        }
    }
    scene.close().unwrap();
    server.stop().unwrap();
}

#[test]
fn a_malformed_op_gets_a_status_and_the_scene_ticks_on() {
    let (_recordings, server, addr) = start_server("live-bad-op");
    let mut viewer = Viewer::connect(addr);
    viewer.handshake_ops();
    let client = common::client(&server, "bad-op-ego");
    let mut scene = client.create(common::roundabout()).unwrap();
    let history = scene.created().agents[0].history.clone();
    let (_, boxes) = viewer.scene_channels(scene.id(), Vec::new());
    scene.step(1, vec![common::replay(&history, 1, 1)]).unwrap();

    for (bad, named) in [
        ("{\"op\": \"subscribe\", ", "malformed JSON"),
        ("[1, 2]", "\"op\""),
        ("{\"op\": \"frobnicate\"}", "frobnicate"),
        ("{\"op\": \"subscribe\"}", "subscriptions"),
        (
            "{\"op\": \"unsubscribe\", \"subscriptionIds\": [\"x\"]}",
            "unsubscribe",
        ),
        (
            "{\"op\": \"getParameters\", \"parameterNames\": []}",
            "capability",
        ),
    ] {
        viewer.send(bad);
        let status = viewer.next_op();
        assert_eq!(status["op"], "status", "{bad}: {status}");
        assert_eq!(status["level"], 2, "{bad}: {status}");
        let message = status["message"].as_str().unwrap();
        assert!(message.contains(named), "{bad}: {message}");
    }
    // A channel that does not exist: a warning.
    viewer.subscribe(&[(1, 999_999)]);
    let status = viewer.next_op();
    assert_eq!(
        (status["op"].as_str(), status["level"].as_u64()),
        (Some("status"), Some(1))
    );

    // The connection and the scene carry on.
    viewer.subscribe(&[(2, boxes)]);
    let latest = viewer.next_frame();
    assert_eq!(latest.subscription, 2);
    // The same subscription id again is refused, the first one stays.
    viewer.subscribe(&[(2, boxes)]);
    assert_eq!(viewer.next_op()["level"], 2);
    for tick in 2..=3 {
        scene
            .step(tick, vec![common::replay(&history, 1, tick)])
            .unwrap();
        let frame = viewer.next_frame();
        assert_eq!(frame.subscription, 2);
        assert!(frame.log_time_ns > latest.log_time_ns);
    }
    // Another client, connected now, sees the scene's channels.
    let mut late = Viewer::connect(addr);
    let channels = late.handshake_ops();
    assert_eq!(channels.len(), 2, "{channels:?}");
    scene.close().unwrap();
    server.stop().unwrap();
}

#[test]
fn closing_a_scene_clears_and_unadvertises_its_channels() {
    let (_recordings, server, addr) = start_server("live-close");
    let client = common::client(&server, "close-ego");
    let mut scene = client.create(common::roundabout()).unwrap();
    let history = scene.created().agents[0].history.clone();
    scene.step(1, vec![common::replay(&history, 1, 1)]).unwrap();
    // A client that joins a running scene gets its channels with the others.
    let mut viewer = Viewer::connect(addr);
    let channels = viewer.handshake_ops();
    let (map, boxes) = viewer.scene_channels(scene.id(), channels);
    viewer.subscribe(&[(5, map), (6, boxes)]);
    let mut latest = [viewer.next_frame(), viewer.next_frame()];
    latest.sort_by_key(|f| f.subscription);
    assert_eq!(latest[0].payload["entities"][0]["id"], "lanes");
    assert_eq!(
        cubes(&latest[1].payload).len(),
        scene.created().agents.len()
    );

    scene.close().unwrap();
    // Both channels are cleared (every entity deleted), then withdrawn. (Tick 1's boxes may
    // come first: the core answers the client before it hands the boxes to the live view.)
    let mut cleared = Vec::new();
    while cleared.len() < 2 {
        let frame = viewer.next_frame();
        if frame.payload["deletions"].as_array().unwrap().is_empty() {
            assert_eq!(frame.subscription, 6, "only boxes before the clearing");
            continue;
        }
        assert_eq!(
            frame.payload["deletions"][0]["type"], 1,
            "{}",
            frame.payload
        );
        assert_eq!(frame.payload["entities"], json!([]));
        cleared.push(frame.subscription);
    }
    cleared.sort_unstable();
    assert_eq!(cleared, [5, 6]);
    let mut gone = Vec::new();
    while gone.len() < 2 {
        let op = viewer.next_op();
        assert_eq!(op["op"], "unadvertise", "{op}");
        gone.extend(
            op["channelIds"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_u64().unwrap()),
        );
    }
    gone.sort_unstable();
    let mut expected = vec![u64::from(map), u64::from(boxes)];
    expected.sort_unstable();
    assert_eq!(gone, expected);

    // A server that stops closes the connection.
    server.stop().unwrap();
    loop {
        match viewer.next() {
            None => break,
            Some(Message::Text(text)) => panic!("after the stop: {text}"),
            Some(_) => {}
        }
    }
}

#[test]
fn a_client_without_the_subprotocol_is_refused() {
    let view = LiveView::start("127.0.0.1:0".parse().unwrap()).unwrap();
    let addr = view.local_addr();
    let runtime = runtime();
    for offered in [None, Some("foxglove.websocket.v0, json")] {
        let mut request = format!("ws://{addr}").into_client_request().unwrap();
        if let Some(offered) = offered {
            request
                .headers_mut()
                .insert("Sec-WebSocket-Protocol", offered.parse().unwrap());
        }
        let refused = runtime
            .block_on(within(tokio_tungstenite::connect_async(request)))
            .expect("no answer in time");
        match refused {
            Err(tokio_tungstenite::tungstenite::Error::Http(response)) => {
                assert_eq!(response.status(), 400, "{offered:?}");
                let body = String::from_utf8(response.body().clone().unwrap()).unwrap();
                assert!(body.contains(live::SUBPROTOCOL), "{body}");
            }
            Err(e) => panic!("{offered:?}: refused, but not with an HTTP error: {e}"),
            Ok(_) => panic!("{offered:?}: accepted"),
        }
    }
    // The live view still serves a client that offers it (among others).
    let mut request = format!("ws://{addr}").into_client_request().unwrap();
    request.headers_mut().insert(
        "Sec-WebSocket-Protocol",
        // (tungstenite's client splits the list on bare commas; browsers send ", ")
        "foxglove.sdk.v1,foxglove.websocket.v1".parse().unwrap(),
    );
    let (_, response) = runtime
        .block_on(tokio_tungstenite::connect_async(request))
        .unwrap();
    assert_eq!(
        response.headers()["Sec-WebSocket-Protocol"],
        live::SUBPROTOCOL
    );
    view.stop();
}

#[test]
fn a_client_that_never_reads_never_holds_up_publishing() {
    let view = LiveView::start("127.0.0.1:0".parse().unwrap()).unwrap();
    let channel = view.advertise(ChannelSpec::scene_update("/scene/1/agents"));
    let mut stalled = Viewer::connect(view.local_addr());
    let channels = stalled.handshake_ops();
    assert_eq!(channels.len(), 1);
    stalled.subscribe(&[(1, channel.get())]);
    // The subscription is in place once a message comes back; then the client stops reading.
    let payload = br#"{"deletions":[],"entities":[]}"#;
    view.publish(channel, 1, &payload[..]);
    assert_eq!(stalled.next_frame().subscription, 1);

    // 256 MiB for a client that reads nothing: far more than its queue and its socket hold.
    let big: std::sync::Arc<[u8]> = vec![b' '; 64 << 10].into();
    let (done, published) = std::sync::mpsc::channel();
    std::thread::scope(|s| {
        s.spawn(|| {
            for k in 0..4096u64 {
                view.publish(channel, 2 + k, big.clone());
            }
            done.send(()).unwrap();
        });
        published
            .recv_timeout(WAIT)
            .expect("publishing waited on a client that does not read");
    });
    // Frames were dropped (oldest first), and counted.
    let deadline = std::time::Instant::now() + WAIT;
    loop {
        let stats = view.stats();
        if stats.dropped_for_clients + stats.dropped_in_core_queue > 0 {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "{stats:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
    // Another client is served meanwhile.
    let mut other = Viewer::connect(view.local_addr());
    assert_eq!(other.handshake_ops().len(), 1);
    assert_eq!(view.stats().clients, 2);
    // Stopping does not wait on the stalled client either.
    view.stop();
    drop(stalled);
}
