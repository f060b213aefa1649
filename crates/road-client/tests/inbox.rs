//! The client's one subscription to all its scenes, without a server: each message reaches its
//! own scene by the key's scene id, and a dropped client ends its scenes' waits at once.

use std::time::Duration;

use road_client::protocol::{ErrorCode, NpcTick, PROTOCOL_VERSION, SceneCreated};
use road_client::{Client, Error, ZenohArgs};
use zenoh::Wait;

fn created(client: &Client, scene: u64) -> SceneCreated {
    let keys = client.keys();
    SceneCreated {
        protocol: PROTOCOL_VERSION,
        scene,
        agents: Vec::new(),
        planner: "road20".into(),
        checkpoint: "road20".into(),
        observed_steps: 10,
        step_secs: 0.1,
        max_ticks: 10,
        late_ego_deadline_ms: 0,
        ego_key: keys.ego(client.id(), scene),
        npc_key: keys.npc(client.id(), scene),
        error_key: keys.error(client.id(), &scene.to_string()),
        recording: None,
        token: "0".repeat(32),
    }
}

fn npc(scene: u64, tick: u64) -> Vec<u8> {
    serde_json::to_vec(&NpcTick {
        scene,
        tick,
        time_s: 0.1 * tick as f64,
        npcs: Vec::new(),
        collisions: Vec::new(),
        off_road: Vec::new(),
        late_external: Vec::new(),
        left: Vec::new(),
        stuck: Vec::new(),
        entered: Vec::new(),
        plans: Vec::new(),
        latency_ms: 0.0,
        compute_ms: 0.0,
        queue_ms: 0.0,
    })
    .unwrap()
}

#[test]
fn messages_reach_their_own_scene_and_a_dropped_client_ends_the_wait() {
    // One session both publishes (as the server would) and reads: zenoh delivers a session's
    // own puts to its own subscribers.
    let session = zenoh::open(ZenohArgs::loopback(None, None).to_config().unwrap())
        .wait()
        .unwrap();
    let client = Client::with_session(session.clone(), "road", "me").unwrap();
    let one = client.attach(created(&client, 1)).unwrap();
    let two = client.attach(created(&client, 2)).unwrap();
    session
        .put(&two.created().npc_key, npc(2, 1))
        .wait()
        .unwrap();
    session
        .put(&one.created().npc_key, npc(1, 1))
        .wait()
        .unwrap();
    let wait = Duration::from_secs(10);
    assert_eq!(one.try_npc(wait).unwrap().unwrap().scene, 1);
    assert_eq!(two.try_npc(wait).unwrap().unwrap().scene, 2);
    let refusal = br#"{"code":"bad_tick","field":"tick","message":"no","scene":1}"#;
    session
        .put(&one.created().error_key, refusal.to_vec())
        .wait()
        .unwrap();
    let e = one
        .wait_error(wait)
        .unwrap()
        .expect("the error reaches scene 1");
    assert_eq!(e.code, ErrorCode::BadTick);
    assert_eq!(two.try_error().unwrap(), None);
    // A message for a scene the client no longer holds goes nowhere.
    drop(one);
    session
        .put(&created(&client, 1).npc_key, npc(1, 2))
        .wait()
        .unwrap();
    drop(client);
    let err = two.try_npc(Duration::from_millis(100)).unwrap_err();
    assert!(matches!(err, Error::Zenoh(_)), "{err}");
    assert!(err.to_string().contains("subscription"), "{err}");
}
