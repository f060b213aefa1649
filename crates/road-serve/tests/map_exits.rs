//! Issue 39 (its first step): a served NPC that drives off the end of its lane, the map's edge,
//! leaves the scene: the tick says so (`NpcTick::left`), it is in no later tick, and leaving is
//! not counted as driving off road.

mod common;

use road_client::protocol::{AgentInit, CreateScene, MapSource, Pose};

/// A car's 10-step history along the lane's middle, ending at `x_end` at `speed_mps`.
fn driving(id: u32, x_end: f64, speed_mps: f64) -> AgentInit {
    AgentInit {
        id,
        length_m: 4.5,
        width_m: 1.8,
        history: (0..10)
            .map(|k| Pose {
                x_m: x_end - 0.1 * speed_mps * f64::from(9 - k),
                y_m: 2.2,
                heading_rad: 0.0,
            })
            .collect(),
    }
}

#[test]
fn an_npc_that_drives_off_the_map_leaves_the_scene() {
    let dir = common::temp_dir("map-exits");
    let mut config = common::config(&dir);
    config.late_ego_deadline = std::time::Duration::ZERO;
    let server = common::start(config);
    let c = common::client(&server, "exits");
    // The ego creeps along far behind; the NPC is 8 m from the lane's end at 10 m/s.
    let request = CreateScene {
        map: MapSource::Osm(common::osm(true)),
        agents: Some(vec![driving(1, 20.0, 1.0), driving(2, 103.0, 10.0)]),
        external: vec![1],
        ..common::roundabout()
    };
    let mut scene = c.create(request).unwrap();
    let ego = scene.created().agents[0].history.clone();
    let mut left_at = None;
    for t in 1..=40u64 {
        let npc = scene.step(t, vec![common::replay(&ego, 1, t)]).unwrap();
        assert!(
            !npc.off_road.contains(&2),
            "tick {t}: leaving counted off road"
        );
        match left_at {
            None if npc.left == [2] => {
                assert!(npc.npcs.iter().all(|a| a.id != 2), "tick {t}");
                left_at = Some(t);
            }
            None => {
                assert!(npc.left.is_empty(), "tick {t}: {:?}", npc.left);
                assert!(npc.npcs.iter().any(|a| a.id == 2), "tick {t}");
            }
            Some(_) => {
                assert!(npc.left.is_empty() && npc.npcs.is_empty(), "tick {t}");
            }
        }
    }
    let left_at = left_at.expect("the NPC never left the map in 40 ticks (4 s)");
    assert!(left_at <= 20, "it took {left_at} ticks");
    // The recording holds the tick that says so.
    let closed = scene.close().unwrap();
    let bytes = std::fs::read(closed.recording.unwrap()).unwrap();
    let said: usize = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.channel.topic == "/road/npc")
        .filter(|m| String::from_utf8_lossy(&m.data).contains("\"left\":[2]"))
        .count();
    assert_eq!(said, 1);
    server.stop().unwrap();
}
