//! `CreateScene.populate`: a client that sends only a map and its ego gets model-driven
//! vehicles placed around it, on a Lanelet2 map built here (one the model never saw) and on a
//! procedural map without its scripted vehicles.

mod common;

use road_client::protocol::{AgentInfo, AgentInit, CreateScene, MapSource, Populate};

fn populate(vehicles: Option<u32>, per_100m: Option<f64>) -> Option<Populate> {
    Some(Populate {
        vehicles,
        vehicles_per_100m: per_100m,
        refine: true,
        initialiser: None,
    })
}

/// Every vehicle after the ego (the first agent) on the test map's lane at its last pose, and
/// more than `min_gap_m` from every other agent (centre to centre).
fn assert_on_the_lane_and_apart(agents: &[AgentInfo], min_gap_m: f64) {
    for a in &agents[1..] {
        let now = a.history.last().unwrap();
        assert!(
            (-0.5..=4.9).contains(&now.y_m) && (-1.0..=112.0).contains(&now.x_m),
            "vehicle {} starts off the lane: {now:?}",
            a.id
        );
        for b in agents.iter().filter(|b| b.id != a.id) {
            let other = b.history.last().unwrap();
            let gap = (now.x_m - other.x_m).hypot(now.y_m - other.y_m);
            assert!(
                gap > min_gap_m,
                "vehicles {} and {} {gap:.1} m apart",
                a.id,
                b.id
            );
        }
    }
}

/// Five ticks of the ego (id 7) replaying its history: four sane NPCs each.
fn run_five_ticks(scene: &mut road_client::Scene, ego: &AgentInit) {
    for t in 1..=5 {
        let npc = scene
            .step(t, vec![common::replay(&ego.history, 7, t)])
            .unwrap();
        assert_eq!(npc.npcs.len(), 4);
        common::assert_sane(&npc, 500.0);
    }
}

#[test]
fn a_map_and_an_ego_are_enough_for_a_populated_scene() {
    let dir = common::temp_dir("populate");
    let server = common::start(common::config(&dir));
    let c = common::client(&server, "populate");

    // The test's one-lanelet map (111 m along +x, 4.4 m wide), the ego near its start.
    let ego = common::straight_agent(7, 10.0, 2.2);
    let request = CreateScene {
        map: MapSource::Osm(common::osm(true)),
        agents: Some(vec![ego.clone()]),
        external: vec![7],
        populate: populate(Some(4), None),
        ..common::roundabout()
    };
    let mut scene = c.create(request).unwrap();
    let agents = scene.created().agents.clone();
    assert_eq!(agents.len(), 5, "{agents:?}");
    assert_eq!(agents[0].id, 7);
    assert!(agents[0].external && agents[1..].iter().all(|a| !a.external));
    // Ids after the ego's; every placed vehicle on the lane, 10 steps of history, clear of the
    // others.
    let ids: Vec<u32> = agents[1..].iter().map(|a| a.id).collect();
    assert_eq!(ids, vec![8, 9, 10, 11]);
    assert!(agents[1..].iter().all(|a| a.history.len() == 10));
    assert_on_the_lane_and_apart(&agents, 4.0);
    run_five_ticks(&mut scene, &ego);
    scene.close().unwrap();

    // A procedural map without its script: its ego (agent 1) and a density of vehicles.
    let request = CreateScene {
        populate: populate(None, Some(1.0)),
        ..common::roundabout()
    };
    let mut scene = c.create(request).unwrap();
    let created = scene.created().clone();
    assert_eq!(created.agents[0].id, 1);
    assert!(
        created.agents.len() >= 6,
        "1 vehicle per 100 m of the roundabout's lanes placed only {}",
        created.agents.len() - 1
    );
    let history = created.agents[0].history.clone();
    let npc = scene.step(1, vec![common::replay(&history, 1, 1)]).unwrap();
    assert_eq!(npc.npcs.len(), created.agents.len() - 1);
    scene.close().unwrap();
    drop(c);
    server.stop().unwrap();
}

/// `populate.initialiser`: the embedded road20-init (the server's default) draws the placed
/// vehicles anew around the ego on the test's map (one it never saw); every vehicle starts on
/// the lane, clear of the others, and the scene runs; `"none"` keeps the refined placement.
#[test]
fn the_initialiser_draws_the_placed_vehicles_around_the_ego() {
    let dir = common::temp_dir("populate-initialiser");
    let server = common::start(common::config(&dir));
    let c = common::client(&server, "populate-initialiser");
    let ego = common::straight_agent(7, 10.0, 2.2);
    let request = CreateScene {
        map: MapSource::Osm(common::osm(true)),
        agents: Some(vec![ego.clone()]),
        external: vec![7],
        populate: Some(Populate {
            initialiser: Some("road20-init".into()),
            ..populate(Some(4), None).unwrap()
        }),
        ..common::roundabout()
    };
    let mut scene = c.create(request.clone()).unwrap();
    let agents = scene.created().agents.clone();
    assert_eq!(agents.len(), 5, "{agents:?}");
    assert_eq!(agents[0].history, ego.history[ego.history.len() - 10..]);
    assert_on_the_lane_and_apart(&agents, 2.0);
    run_five_ticks(&mut scene, &ego);
    scene.close().unwrap();
    // The same request and seed draw the same vehicles; without the initialiser they are the
    // refined placement, which the draw moved (not every vehicle fell back to it).
    let again = c.create(request.clone()).unwrap();
    assert_eq!(again.created().agents, agents);
    again.close().unwrap();
    let refined_only = CreateScene {
        populate: Some(Populate {
            initialiser: Some("none".into()),
            ..populate(Some(4), None).unwrap()
        }),
        ..request.clone()
    };
    let refined = c.create(refined_only).unwrap();
    let placed = refined.created().agents.clone();
    refined.close().unwrap();
    let redrawn = agents[1..]
        .iter()
        .zip(&placed[1..])
        .filter(|(a, b)| a.history != b.history)
        .count();
    assert!(
        redrawn >= 1,
        "every drawn vehicle fell back to its placement"
    );
    // The server's default initialiser is road20-init: a request that names none gets the same.
    let by_default = CreateScene {
        populate: populate(Some(4), None),
        ..request
    };
    let default = c.create(by_default).unwrap();
    assert_eq!(default.created().agents, agents);
    default.close().unwrap();
    drop(c);
    server.stop().unwrap();
}

/// `inflow`: vehicles enter at the merge's two entry lanes while the scene runs, each
/// announced once in `NpcTick.entered` with a new id and then driven among the NPCs.
#[test]
fn vehicles_keep_entering_a_scene_with_inflow() {
    let dir = common::temp_dir("inflow");
    let server = common::start(common::config(&dir));
    let c = common::client(&server, "inflow");
    let request = CreateScene {
        inflow: Some(road_client::protocol::Inflow {
            vehicles_per_minute: 30.0,
            max_vehicles: Some(12),
        }),
        ..CreateScene::procedural("merge", vec![1], 4)
    };
    let mut scene = c.create(request).unwrap();
    let created = scene.created().clone();
    let mut known: Vec<u32> = created.agents.iter().map(|a| a.id).collect();
    let history = created.agents[0].history.clone();
    let mut entered = Vec::new();
    for t in 1..=80 {
        let npc = scene.step(t, vec![common::replay(&history, 1, t)]).unwrap();
        for a in &npc.entered {
            assert!(!known.contains(&a.id), "id {} reused", a.id);
            assert!(!a.external && a.history.len() == 10, "{a:?}");
            assert!(
                npc.npcs.iter().any(|s| s.id == a.id),
                "tick {t}: vehicle {} entered but is not among the NPCs",
                a.id
            );
            known.push(a.id);
            entered.push(a.id);
        }
        for s in &npc.npcs {
            assert!(known.contains(&s.id), "tick {t}: unknown NPC {}", s.id);
        }
        // The ego and at most 11 NPCs: the target of 12.
        assert!(npc.npcs.len() <= 11, "tick {t}: {} NPCs", npc.npcs.len());
        common::assert_sane(&npc, 1000.0);
    }
    // Two entries at 30 a minute for 8 s: about 8 arrivals, as many as have room.
    assert!(
        entered.len() >= 3,
        "{} vehicles entered: {entered:?}",
        entered.len()
    );
    scene.close().unwrap();
    drop(c);
    server.stop().unwrap();
}

/// A server whose default initialiser cannot draw vehicles refuses to start, naming it.
#[test]
fn a_default_initialiser_that_cannot_draw_is_refused_at_start() {
    let dir = common::temp_dir("populate-bad-initialiser");
    let mut config = common::config(&dir);
    config.default_initialiser = Some("road20-wide4".into());
    let endpoint = format!("tcp/127.0.0.1:{}", common::free_port());
    let zenoh = road_client::ZenohArgs::loopback(Some(&endpoint), None)
        .to_config()
        .unwrap();
    let e = match road_serve::Server::new(config, zenoh).start() {
        Ok(_) => panic!("the server started with road20-wide4 as its initialiser"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.contains("default initialiser \"road20-wide4\"") && e.contains("not trained"),
        "{e}"
    );
}
