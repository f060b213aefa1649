//! The bad-input catalogue of `docs/protocol.md`, one test per row: each gets an error reply
//! naming the input (a query's error reply, or a message on the scene's error key), and the
//! scene it was aimed at still ticks afterwards.

mod common;

use std::sync::OnceLock;
use std::time::Duration;

use road_client::protocol::{
    AgentState, CreateScene, ErrorCode, ErrorReply, MapSource, NpcTick, Pose,
};
use road_client::{Client, Error, Scene};
use road_serve::ServerHandle;
use zenoh::Wait;

/// One server for the file; payloads over 64 KiB are refused; the late-ego deadline is off
/// so that slow debug ticks never turn late.
fn server() -> &'static ServerHandle {
    // Its recordings' folder lives as long (a static is never dropped: the folder stays, and
    // the next run sweeps it).
    static SERVER: OnceLock<(common::TempFolder, ServerHandle)> = OnceLock::new();
    &SERVER
        .get_or_init(|| {
            let dir = common::static_temp_dir("bad-input");
            let mut config = common::config(&dir);
            config.max_payload_bytes = 64 << 10;
            config.late_ego_deadline = Duration::ZERO;
            (dir, common::start(config))
        })
        .1
}

fn client(id: &str) -> Client {
    common::client(server(), id)
}

/// The error of a creation request given as raw bytes.
fn create_raw(client: &Client, payload: Vec<u8>) -> ErrorReply {
    client
        .query_raw(&client.keys().create(), payload)
        .unwrap()
        .expect_err("the request must be refused")
}

fn create_err(client: &Client, request: CreateScene) -> ErrorReply {
    match client.create(request) {
        Err(Error::Refused(e)) => e,
        other => panic!("expected a refusal, got {other:?}"),
    }
}

fn assert_refused(e: &ErrorReply, code: ErrorCode, field: Option<&str>) {
    assert_eq!(e.code, code, "{e}");
    assert_eq!(e.field.as_deref(), field, "{e}");
    assert!(!e.message.is_empty());
}

fn agents_request(agents: Vec<road_client::protocol::AgentInit>) -> CreateScene {
    CreateScene {
        map: MapSource::Osm(common::osm(true)),
        agents: Some(agents),
        external: vec![],
        ..common::roundabout()
    }
}

/// A live roundabout scene of `client` with its ego's history.
fn live_scene(client: &Client) -> (Scene, Vec<Pose>) {
    let scene = client.create(common::roundabout()).unwrap();
    let history = scene.created().agents[0].history.clone();
    (scene, history)
}

fn ego_at(history: &[Pose], tick: u64) -> AgentState {
    common::replay(history, 1, tick)
}

/// The error the server publishes for the scene after a put.
fn tick_err(scene: &Scene) -> ErrorReply {
    scene
        .wait_error(Duration::from_secs(30))
        .unwrap()
        .expect("the server must publish an error")
}

/// Puts `payload` on `scene`'s ego key and returns what the server answers on the scene's
/// `refused` key (puts without the scene's token are answered there, not on the error key).
fn refusal_of(c: &Client, scene: &Scene, payload: Vec<u8>) -> ErrorReply {
    let key = c.keys().refused(c.id(), &scene.id().to_string());
    let refused = c.session().declare_subscriber(key).wait().unwrap();
    scene.put_raw(payload).unwrap();
    let sample = refused
        .recv_timeout(Duration::from_secs(30))
        .unwrap()
        .expect("the server must answer on the refused key");
    serde_json::from_slice(&sample.payload().to_bytes()).unwrap()
}

/// A tick as JSON with the scene's client id and token, for raw edits.
fn tick_json(scene: &Scene, client: &str, history: &[Pose], tick: u64) -> serde_json::Value {
    serde_json::json!({
        "tick": tick, "client": client, "token": scene.created().token,
        "agents": [ego_at(history, tick)],
    })
}

/// The scene still ticks: tick `t` is answered.
fn still_ticks(scene: &mut Scene, history: &[Pose], t: u64) -> NpcTick {
    let npc = scene.step(t, vec![ego_at(history, t)]).unwrap();
    assert_eq!(npc.tick, t);
    npc
}

#[test]
fn malformed_json_is_refused() {
    let c = client("malformed");
    let e = create_raw(&c, b"{\"map\": {\"procedural\": \"roundabout\"".to_vec());
    assert_refused(&e, ErrorCode::MalformedJson, None);
}

#[test]
fn binary_garbage_is_refused_on_create_and_on_a_tick() {
    let c = client("garbage");
    let e = create_raw(&c, vec![0xff, 0x00, 0xfe, 0x13, 0x37]);
    assert_refused(&e, ErrorCode::MalformedJson, None);
    assert!(e.message.contains("UTF-8"), "{e}");
    let (mut scene, history) = live_scene(&c);
    // Garbage cannot carry the scene's token: it is answered on the refused key.
    let e = refusal_of(&c, &scene, vec![0xde, 0xad, 0xbe, 0xef]);
    assert_refused(&e, ErrorCode::MalformedJson, None);
    assert_eq!(scene.wait_error(Duration::from_millis(300)).unwrap(), None);
    still_ticks(&mut scene, &history, 1);
}

#[test]
fn an_oversized_payload_is_refused() {
    let c = client("oversized");
    let e = create_raw(&c, vec![b' '; 100 << 10]);
    assert_refused(&e, ErrorCode::PayloadTooLarge, None);
    let (mut scene, history) = live_scene(&c);
    // Refused unread (so its token cannot be known): answered on the refused key.
    let e = refusal_of(&c, &scene, vec![b' '; 100 << 10]);
    assert_refused(&e, ErrorCode::PayloadTooLarge, None);
    still_ticks(&mut scene, &history, 1);
}

#[test]
fn unknown_fields_are_refused() {
    let c = client("unknown-field");
    let e = create_raw(
        &c,
        br#"{"map":{"procedural":"roundabout"},"external":[1],"sede":3}"#.to_vec(),
    );
    assert_refused(&e, ErrorCode::UnknownField, Some("sede"));
}

#[test]
fn a_creation_without_a_client_id_is_refused() {
    let c = client("no-client-id");
    let e = create_raw(
        &c,
        br#"{"map": {"procedural": "roundabout"}, "external": [1]}"#.to_vec(),
    );
    assert_refused(&e, ErrorCode::InvalidField, Some("client"));
    assert!(e.message.contains("keys"), "{e}");
}

#[test]
fn a_missing_map_is_refused() {
    let c = client("missing-map");
    let e = create_raw(&c, br#"{"external":[]}"#.to_vec());
    assert_refused(&e, ErrorCode::MalformedJson, Some("map"));
}

#[test]
fn an_unknown_map_name_is_refused() {
    let c = client("unknown-map");
    let mut r = common::roundabout();
    r.map = MapSource::Procedural("atlantis".into());
    assert_refused(
        &create_err(&c, r),
        ErrorCode::BadMap,
        Some("map.procedural"),
    );
    let mut r = common::roundabout();
    r.map = MapSource::File("atlantis".into());
    assert_refused(&create_err(&c, r), ErrorCode::BadMap, Some("map.file"));
}

#[test]
fn an_osm_that_does_not_parse_is_refused() {
    let c = client("bad-osm");
    let mut r = agents_request(vec![common::straight_agent(1, 10.0, 2.0)]);
    r.map = MapSource::Osm("<osm><node id=\"1\"".into());
    assert_refused(&create_err(&c, r), ErrorCode::BadMap, Some("map.osm"));
}

#[test]
fn a_priority_rule_naming_no_lanelet_is_refused() {
    let c = client("bad-rule");
    let mut r = agents_request(vec![common::straight_agent(1, 10.0, 2.0)]);
    r.map = MapSource::Osm(common::osm(true).replace(
        "</osm>",
        "  <relation id=\"200\"><member type=\"relation\" ref=\"999\" role=\"yield\"/><tag k=\"type\" v=\"regulatory_element\"/><tag k=\"subtype\" v=\"all_way_stop\"/></relation>\n</osm>",
    ));
    let e = create_err(&c, r);
    assert_refused(&e, ErrorCode::BadMap, Some("map.osm"));
    assert!(
        e.message.contains("regulatory element 200") && e.message.contains("`999`"),
        "{e}"
    );
}

#[test]
fn a_map_with_no_lanelets_is_refused() {
    let c = client("no-lanelets");
    let mut r = agents_request(vec![common::straight_agent(1, 10.0, 2.0)]);
    r.map = MapSource::Osm(common::osm(false));
    let e = create_err(&c, r);
    assert_refused(&e, ErrorCode::BadMap, Some("map.osm"));
    assert!(e.message.contains("no lanelet"), "{e}");
}

#[test]
fn an_osm_map_by_value_runs() {
    let c = client("osm-ok");
    let mut r = agents_request(vec![
        common::straight_agent(1, 10.0, 2.0),
        common::straight_agent(2, 30.0, 2.0),
    ]);
    r.external = vec![1];
    let mut scene = c.create(r).unwrap();
    let history = scene.created().agents[0].history.clone();
    let npc = still_ticks(&mut scene, &history, 1);
    assert_eq!(npc.npcs.len(), 1);
    assert_eq!(npc.npcs[0].id, 2);
    scene.close().unwrap();
}

#[test]
fn zero_agents_are_refused() {
    let c = client("zero-agents");
    assert_refused(
        &create_err(&c, agents_request(vec![])),
        ErrorCode::InvalidField,
        Some("agents"),
    );
}

#[test]
fn more_agents_than_the_model_takes_are_refused() {
    let c = client("many-agents");
    let agents = (0..33)
        .map(|i| common::straight_agent(i, 5.0 * f64::from(i), 2.0))
        .collect();
    let e = create_err(&c, agents_request(agents));
    assert_refused(&e, ErrorCode::InvalidField, Some("agents"));
    assert!(e.message.contains("32"), "{e}");
}

#[test]
fn a_short_history_is_refused() {
    let c = client("short-history");
    let mut a = common::straight_agent(1, 10.0, 2.0);
    a.history.truncate(4);
    let e = create_err(&c, agents_request(vec![a]));
    assert_refused(&e, ErrorCode::InvalidField, Some("agents[0].history"));
}

#[test]
fn nan_or_infinite_history_values_are_refused() {
    let c = client("nan-history");
    // JSON has no NaN or infinity: such payloads are malformed JSON.
    let mut r = serde_json::to_value(agents_request(vec![common::straight_agent(1, 10.0, 2.0)]))
        .unwrap()
        .to_string();
    r = r.replacen("\"x_m\":10.0", "\"x_m\":NaN", 1);
    assert!(r.contains("NaN"));
    assert_refused(
        &create_raw(&c, r.into_bytes()),
        ErrorCode::MalformedJson,
        Some("agents[0].history[0].x_m"),
    );
    let r = serde_json::to_value(agents_request(vec![common::straight_agent(1, 10.0, 2.0)]))
        .unwrap()
        .to_string()
        .replacen("\"y_m\":2.0", "\"y_m\":1e999", 1);
    assert_refused(
        &create_raw(&c, r.into_bytes()),
        ErrorCode::MalformedJson,
        Some("agents[0].history[0].y_m"),
    );
}

/// The bound a refusal's message states: the numbers in "`axis` in [low, high] m".
fn bound_in(message: &str, axis: &str) -> (f64, f64) {
    let rest = message
        .split(&format!("{axis} in ["))
        .nth(1)
        .unwrap_or_else(|| panic!("no {axis} bound in {message}"));
    let (low, rest) = rest.split_once(", ").unwrap();
    let high = rest.split_once(']').unwrap().0;
    (low.parse().unwrap(), high.parse().unwrap())
}

/// Issue 41, finding 1: finite but absurd numbers (`1e300`) in a creation are refused by
/// field, each at and just past its bound; an NPC whose whole history sits at `1e300` too.
#[test]
fn absurd_finite_history_values_are_refused_at_their_bounds() {
    let c = client("absurd-history");
    let create = |edit: &dyn Fn(&mut road_client::protocol::AgentInit)| {
        let mut a = common::straight_agent(1, 10.0, 2.0);
        edit(&mut a);
        c.create(agents_request(vec![
            a,
            common::straight_agent(2, 30.0, 2.0),
        ]))
    };
    let refused = |edit: &dyn Fn(&mut road_client::protocol::AgentInit)| match create(edit) {
        Err(Error::Refused(e)) => e,
        other => panic!("expected a refusal, got {other:?}"),
    };
    let e = refused(&|a| a.history[3].x_m = 1e300);
    assert_refused(
        &e,
        ErrorCode::InvalidField,
        Some("agents[0].history[3].x_m"),
    );
    assert_refused(
        &refused(&|a| a.history[3].heading_rad = 1e300),
        ErrorCode::InvalidField,
        Some("agents[0].history[3].heading_rad"),
    );
    assert_refused(
        &refused(&|a| a.history.iter_mut().for_each(|p| p.y_m = -1e300)),
        ErrorCode::InvalidField,
        Some("agents[0].history[0].y_m"),
    );
    // The map's extent (its lanes and 500 m around them), read from the refusal (to the
    // millimetre): a history along its far edge is taken, one a centimetre past it is not.
    let (_, x_high) = bound_in(&e.message, "x");
    let x_high = x_high - 0.001;
    let along = |x_end: f64| {
        move |a: &mut road_client::protocol::AgentInit| {
            for (k, p) in a.history.iter_mut().enumerate() {
                p.x_m = x_end - 0.5 * (9 - k) as f64;
            }
        }
    };
    create(&along(x_high)).unwrap().close().unwrap();
    assert_refused(
        &refused(&along(x_high + 0.01)),
        ErrorCode::InvalidField,
        Some("agents[0].history[9].x_m"),
    );
    // Headings: any number of turns up to ±100 rad.
    create(&|a| a.history.iter_mut().for_each(|p| p.heading_rad = -100.0))
        .unwrap()
        .close()
        .unwrap();
    assert_refused(
        &refused(&|a| a.history[0].heading_rad = 100.001),
        ErrorCode::InvalidField,
        Some("agents[0].history[0].heading_rad"),
    );
    // Speeds: a history step longer than the server's speed bound (70 m/s: 7 m a step).
    assert_refused(
        &refused(&|a| a.history[5].x_m += 8.0),
        ErrorCode::InvalidField,
        Some("agents[0].history[5]"),
    );
}

/// Issue 41, finding 1: `1e300` as an ego tick's position or heading is refused by field
/// (it used to poison every later NPC pose into `null`, or blame the ego for moving `inf`
/// m); the scene goes on.
#[test]
fn absurd_finite_ego_values_are_refused() {
    let c = client("absurd-ego");
    let (mut scene, history) = live_scene(&c);
    for (field, value) in [("x_m", 1e300), ("y_m", -1e300), ("heading_rad", 1e300)] {
        let mut tick = tick_json(&scene, "absurd-ego", &history, 1);
        tick["agents"][0][field] = value.into();
        scene.put_raw(serde_json::to_vec(&tick).unwrap()).unwrap();
        let e = tick_err(&scene);
        assert_refused(
            &e,
            ErrorCode::InvalidField,
            Some(&format!("agents[0].{field}")),
        );
    }
    let npc = still_ticks(&mut scene, &history, 1);
    common::assert_sane(&npc, 500.0);
}

#[test]
fn non_positive_or_absurd_box_sizes_are_refused() {
    let c = client("box-sizes");
    for (length, width, field) in [
        (0.0, 1.8, "agents[0].length_m"),
        (-4.0, 1.8, "agents[0].length_m"),
        (400.0, 1.8, "agents[0].length_m"),
        (4.5, 0.0, "agents[0].width_m"),
        (4.5, 12.0, "agents[0].width_m"),
    ] {
        let mut a = common::straight_agent(1, 10.0, 2.0);
        a.length_m = length;
        a.width_m = width;
        let e = create_err(&c, agents_request(vec![a]));
        assert_refused(&e, ErrorCode::InvalidField, Some(field));
    }
}

#[test]
fn duplicate_agent_ids_are_refused() {
    let c = client("duplicate-ids");
    let e = create_err(
        &c,
        agents_request(vec![
            common::straight_agent(4, 10.0, 2.0),
            common::straight_agent(4, 30.0, 2.0),
        ]),
    );
    assert_refused(&e, ErrorCode::InvalidField, Some("agents[1].id"));
}

#[test]
fn an_external_agent_not_in_the_scene_is_refused() {
    let c = client("external-missing");
    let mut r = common::roundabout();
    r.external = vec![99];
    assert_refused(
        &create_err(&c, r),
        ErrorCode::InvalidField,
        Some("external[0]"),
    );
}

#[test]
fn an_unknown_planner_is_refused() {
    let c = client("unknown-planner");
    let mut r = common::roundabout();
    r.planner = Some("road99".into());
    assert_refused(&create_err(&c, r), ErrorCode::BadModel, Some("planner"));
}

#[test]
fn an_unknown_checkpoint_is_refused() {
    let c = client("unknown-checkpoint");
    for name in ["road99", "../models/road20"] {
        let mut r = common::roundabout();
        r.checkpoint = Some(name.into());
        assert_refused(&create_err(&c, r), ErrorCode::BadModel, Some("checkpoint"));
    }
}

#[test]
fn a_checkpoint_whose_window_does_not_fit_the_planner_is_refused() {
    let c = client("window-mismatch");
    let mut r = common::roundabout();
    r.planner = Some("road15".into()); // W = 15 on road20's W = 20
    let e = create_err(&c, r);
    assert_refused(&e, ErrorCode::BadModel, Some("planner"));
    assert!(e.message.contains("W = 15"), "{e}");
}

#[test]
fn more_scenes_than_the_capacity_are_refused() {
    // A server of its own with room for one scene.
    let dir = common::temp_dir("capacity");
    let mut config = common::config(&dir);
    config.capacity = 1;
    config.late_ego_deadline = Duration::ZERO;
    let small = common::start(config);
    let c = common::client(&small, "capacity");
    let (mut first, history) = live_scene(&c);
    let e = create_err(&c, common::roundabout());
    assert_refused(&e, ErrorCode::Capacity, None);
    still_ticks(&mut first, &history, 1);
    first.close().unwrap();
    // Room again.
    c.create(common::roundabout()).unwrap().close().unwrap();
    small.stop().unwrap();
}

#[test]
fn a_tick_for_an_unknown_scene_is_refused() {
    let c = client("unknown-scene");
    let (scene, _) = live_scene(&c);
    let ghost = road_client::protocol::SceneCreated {
        scene: 987_654,
        ego_key: c.keys().ego(c.id(), 987_654),
        npc_key: c.keys().npc(c.id(), 987_654),
        error_key: c.keys().error(c.id(), "987654"),
        ..scene.created().clone()
    };
    let ghost = c.attach(ghost).unwrap();
    ghost.put(1, vec![]).unwrap();
    let e = tick_err(&ghost);
    assert_refused(&e, ErrorCode::UnknownScene, Some("key"));
    assert_eq!(e.scene, Some(987_654));
}

#[test]
fn a_tick_for_a_closed_scene_is_refused() {
    let c = client("closed-scene");
    let (scene, history) = live_scene(&c);
    let created = scene.created().clone();
    scene.close().unwrap();
    let again = c.attach(created).unwrap();
    again.put(1, vec![ego_at(&history, 1)]).unwrap();
    let e = tick_err(&again);
    assert_refused(&e, ErrorCode::UnknownScene, Some("key"));
    assert!(e.message.contains("closed"), "{e}");
}

#[test]
fn a_tick_naming_a_non_external_agent_is_refused() {
    let c = client("not-external");
    let (mut scene, history) = live_scene(&c);
    let mut npc = ego_at(&history, 1);
    npc.id = 2;
    scene.put(1, vec![ego_at(&history, 1), npc]).unwrap();
    assert_refused(&tick_err(&scene), ErrorCode::BadTick, Some("agents[1].id"));
    still_ticks(&mut scene, &history, 1);
}

#[test]
fn a_tick_missing_an_external_agent_is_refused() {
    let c = client("missing-external");
    let mut r = common::roundabout();
    r.external = vec![1, 2];
    let mut scene = c.create(r).unwrap();
    let history = scene.created().agents[0].history.clone();
    scene.put(1, vec![ego_at(&history, 1)]).unwrap();
    let e = tick_err(&scene);
    assert_refused(&e, ErrorCode::BadTick, Some("agents"));
    assert!(e.message.contains('2'), "{e}");
    let second = scene.created().agents[1].history.clone();
    let npc = scene
        .step(1, vec![ego_at(&history, 1), common::replay(&second, 2, 1)])
        .unwrap();
    assert_eq!(npc.tick, 1);
}

#[test]
fn the_same_agent_twice_in_a_tick_is_refused() {
    let c = client("twice");
    let (mut scene, history) = live_scene(&c);
    scene
        .put(1, vec![ego_at(&history, 1), ego_at(&history, 1)])
        .unwrap();
    assert_refused(&tick_err(&scene), ErrorCode::BadTick, Some("agents[1].id"));
    still_ticks(&mut scene, &history, 1);
}

#[test]
fn a_nan_or_infinite_ego_state_is_refused() {
    let c = client("nan-ego");
    let (mut scene, history) = live_scene(&c);
    let good = serde_json::json!({
        "tick": 1, "client": "nan-ego", "token": scene.created().token,
        "agents": [{"id": 1, "x_m": 0.0, "y_m": 0.0, "heading_rad": 0.0}],
    })
    .to_string();
    // Not JSON, so not read for its token: answered on the refused key.
    for bad in ["NaN", "Infinity", "1e999"] {
        let payload = good.replace("\"x_m\":0.0", &format!("\"x_m\":{bad}"));
        assert_refused(
            &refusal_of(&c, &scene, payload.into_bytes()),
            ErrorCode::MalformedJson,
            Some("agents[0].x_m"),
        );
    }
    still_ticks(&mut scene, &history, 1);
}

#[test]
fn ticks_in_the_past_repeated_or_skipping_ahead_are_refused() {
    let c = client("tick-order");
    let (mut scene, history) = live_scene(&c);
    scene.put(2, vec![ego_at(&history, 2)]).unwrap();
    let e = tick_err(&scene);
    assert_refused(&e, ErrorCode::BadTick, Some("tick"));
    assert!(e.message.contains("skips ahead"), "{e}");
    still_ticks(&mut scene, &history, 1);
    scene.put(1, vec![ego_at(&history, 1)]).unwrap();
    let e = tick_err(&scene);
    assert_refused(&e, ErrorCode::BadTick, Some("tick"));
    assert!(e.message.contains("past"), "{e}");
    scene.put(0, vec![ego_at(&history, 0)]).unwrap();
    assert_refused(&tick_err(&scene), ErrorCode::BadTick, Some("tick"));
    still_ticks(&mut scene, &history, 2);
}

#[test]
fn an_ego_that_jumps_too_far_is_refused() {
    let c = client("jump");
    let (mut scene, history) = live_scene(&c);
    let mut far = ego_at(&history, 1);
    far.x_m += 50.0;
    scene.put(1, vec![far]).unwrap();
    let e = tick_err(&scene);
    assert_refused(&e, ErrorCode::InvalidField, Some("agents[0]"));
    assert!(e.message.contains("moved"), "{e}");
    still_ticks(&mut scene, &history, 1);
}

/// Issue 41, finding 2: ownership is the scene's token, not a name. Two real sessions: the
/// owner's and an intruder's, which knows the owner's id and scene id but not the token.
#[test]
fn a_second_client_claiming_the_ego_is_refused() {
    let owner = client("owner");
    let (mut scene, history) = live_scene(&owner);
    let intruder = client("intruder");
    // On its own key, with the owner's reply in hand (token included): not its scene.
    let theirs = intruder.attach(scene.created().clone()).unwrap();
    theirs.put(1, vec![ego_at(&history, 1)]).unwrap();
    let e = tick_err(&theirs);
    assert_refused(&e, ErrorCode::NotOwner, Some("key"));
    assert!(!e.message.contains("Some("), "{e}");
    // The refusal went to the intruder's own error key: the owner heard nothing.
    assert_eq!(scene.wait_error(Duration::from_millis(500)).unwrap(), None);
    // On the owner's key under the owner's name, without the token (no `client` field, and
    // the owner's id): refused on the refused key, never on the owner's error key.
    let forged_scene = road_client::protocol::SceneCreated {
        token: "0".repeat(32),
        ..scene.created().clone()
    };
    let spoof = client("owner-spoof");
    let key = owner.keys().ego("owner", scene.id());
    for payload in [
        serde_json::json!({"tick": 1, "agents": [ego_at(&history, 1)]}),
        serde_json::json!({"tick": 1, "agents": [ego_at(&history, 1)], "client": "owner",
                           "token": forged_scene.token}),
    ] {
        spoof
            .session()
            .put(key.as_str(), serde_json::to_vec(&payload).unwrap())
            .wait()
            .unwrap();
    }
    assert_eq!(scene.wait_error(Duration::from_millis(500)).unwrap(), None);
    let status = owner.status().unwrap();
    let mine = status
        .scenes
        .iter()
        .find(|s| s.scene == scene.id())
        .unwrap();
    assert_eq!(mine.refused_puts, 2, "{mine:?}");
    assert_eq!(mine.tick, 0, "no forged tick ran");
    // With the token but naming another client on the owner's key: refused by field.
    let mut named = tick_json(&scene, "intruder", &history, 1);
    named["client"] = "intruder".into();
    scene.put_raw(serde_json::to_vec(&named).unwrap()).unwrap();
    let e = tick_err(&scene);
    assert_refused(&e, ErrorCode::NotOwner, Some("client"));
    assert!(
        e.message.contains("intruder") && !e.message.contains("Some("),
        "{e}"
    );
    still_ticks(&mut scene, &history, 1);
    // A close under the intruder's own id, then under the owner's id without the token.
    let closing = |c: &Client, token: &str| match c.close_scene(scene.id(), token) {
        Err(Error::Refused(e)) => e,
        other => panic!("expected a refusal, got {other:?}"),
    };
    assert_refused(
        &closing(&intruder, &scene.created().token),
        ErrorCode::NotOwner,
        Some("client"),
    );
    let as_owner = {
        let request = serde_json::json!({"scene": scene.id(), "client": "owner",
                                         "token": "f".repeat(32)});
        intruder
            .query_raw(
                &intruder.keys().close(),
                serde_json::to_vec(&request).unwrap(),
            )
            .unwrap()
            .expect_err("a close without the token must be refused")
    };
    assert_refused(&as_owner, ErrorCode::NotOwner, Some("token"));
    // The owner was not told, and its scene goes on.
    assert_eq!(scene.wait_error(Duration::from_millis(500)).unwrap(), None);
    still_ticks(&mut scene, &history, 2);
}

#[test]
fn closing_an_unknown_scene_is_refused() {
    let c = client("close-unknown");
    let e = match c.close_scene(424_242, &"0".repeat(32)) {
        Err(Error::Refused(e)) => e,
        other => panic!("expected a refusal, got {other:?}"),
    };
    assert_refused(&e, ErrorCode::UnknownScene, Some("scene"));
}

#[test]
fn bad_input_loses_nothing_recorded() {
    let c = client("recorded");
    let (mut scene, history) = live_scene(&c);
    still_ticks(&mut scene, &history, 1);
    scene.put(5, vec![ego_at(&history, 5)]).unwrap();
    let _ = tick_err(&scene);
    still_ticks(&mut scene, &history, 2);
    let closed = scene.close().unwrap();
    let bytes = std::fs::read(closed.recording.unwrap()).unwrap();
    let topics: Vec<String> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(|m| m.unwrap().channel.topic.clone())
        .collect();
    let count = |t: &str| topics.iter().filter(|x| *x == t).count();
    assert_eq!(count("/road/ego"), 2);
    assert_eq!(count("/road/npc"), 2);
    assert_eq!(count("/road/error"), 1);
}

/// `populate` asks for vehicles by count or by density, exactly one of them, within limits.
#[test]
fn populate_requests_out_of_range_are_refused() {
    let c = client("populate-bad");
    let with = |vehicles: Option<u32>, vehicles_per_100m: Option<f64>| CreateScene {
        populate: Some(road_client::protocol::Populate {
            vehicles,
            vehicles_per_100m,
            refine: false,
            initialiser: None,
        }),
        ..agents_request(vec![common::straight_agent(1, 10.0, 2.0)])
    };
    for (request, field, says) in [
        (with(None, None), "populate", "exactly one"),
        (with(Some(2), Some(1.0)), "populate", "exactly one"),
        (with(Some(32), None), "populate.vehicles", "32"),
        (
            with(None, Some(0.0)),
            "populate.vehicles_per_100m",
            "(0, 10]",
        ),
        (
            with(None, Some(-1.0)),
            "populate.vehicles_per_100m",
            "(0, 10]",
        ),
        (
            with(None, Some(10.5)),
            "populate.vehicles_per_100m",
            "(0, 10]",
        ),
    ] {
        let e = create_err(&c, request);
        assert_refused(&e, ErrorCode::InvalidField, Some(field));
        assert!(e.message.contains(says), "{e}");
    }
    // An initialiser that is no checkpoint, one not trained to draw vehicles, or one beside
    // `refine: false`.
    for (initialiser, refine, code, says) in [
        (
            "no-such-model",
            true,
            ErrorCode::BadModel,
            "unknown checkpoint",
        ),
        (
            "road20-wide4",
            true,
            ErrorCode::BadModel,
            "not trained to draw",
        ),
        (
            "road20-init",
            false,
            ErrorCode::InvalidField,
            "refine: false",
        ),
    ] {
        let mut request = with(Some(2), None);
        if let Some(p) = request.populate.as_mut() {
            p.initialiser = Some(initialiser.into());
            p.refine = refine;
        }
        let e = create_err(&c, request);
        assert_refused(&e, code, Some("populate.initialiser"));
        assert!(e.message.contains(says), "{e}");
    }
    // A key `populate` does not have.
    let e = create_raw(
        &c,
        serde_json::to_vec(&serde_json::json!({
            "map": {"procedural": "roundabout"}, "client": "populate-bad",
            "external": [1], "populate": {"vehicle": 3},
        }))
        .unwrap(),
    );
    assert_eq!(e.code, ErrorCode::UnknownField, "{e}");
    assert!(e.message.contains("vehicle"), "{e}");
}

/// `inflow.vehicles_per_minute` lies in (0, 60], `inflow.max_vehicles` in 1..=32.
#[test]
fn inflow_rates_out_of_range_are_refused() {
    let c = client("inflow-bad");
    for rate in [0.0, -3.0, 60.5, 1e300] {
        let request = CreateScene {
            inflow: Some(road_client::protocol::Inflow {
                vehicles_per_minute: rate,
                max_vehicles: None,
            }),
            ..common::roundabout()
        };
        let e = create_err(&c, request);
        assert_refused(
            &e,
            ErrorCode::InvalidField,
            Some("inflow.vehicles_per_minute"),
        );
        assert!(e.message.contains("(0, 60]"), "{e}");
    }
    for target in [0, 33] {
        let request = CreateScene {
            inflow: Some(road_client::protocol::Inflow {
                vehicles_per_minute: 6.0,
                max_vehicles: Some(target),
            }),
            ..common::roundabout()
        };
        let e = create_err(&c, request);
        assert_refused(&e, ErrorCode::InvalidField, Some("inflow.max_vehicles"));
        assert!(e.message.contains("1..=32"), "{e}");
    }
}
