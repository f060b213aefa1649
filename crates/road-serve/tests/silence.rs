//! Issue 41, finding 3: a scene whose client goes quiet is closed as `client_silent`, however
//! many ticks the late-ego policy drove for it meanwhile; and so is one whose ego has been
//! missing for too many ticks in a row. And the status of one scene, by which a waiting client
//! finds its scene gone.

mod common;

use std::time::{Duration, Instant};

use road_client::protocol::ErrorCode;

/// A client that creates a scene and then says nothing (no liveliness token is needed for
/// this: its client stays connected) sees it closed within the idle timeout, while the
/// model drives its ego every late-ego deadline.
#[test]
fn a_silent_clients_scene_is_closed_despite_late_ticks() {
    let dir = common::temp_dir("silence");
    let mut config = common::config(&dir);
    config.late_ego_deadline = Duration::from_millis(100);
    config.idle_timeout = Duration::from_secs(2);
    let server = common::start(config);
    let c = common::client(&server, "quiet");
    let scene = c.create(common::roundabout()).unwrap();
    let started = Instant::now();
    let e = scene
        .wait_error(Duration::from_secs(60))
        .unwrap()
        .expect("the server must close the silent scene");
    assert_eq!(e.code, ErrorCode::ClientSilent, "{e}");
    assert!(e.message.contains("quiet"), "{e}");
    assert!(
        started.elapsed() >= Duration::from_secs(2),
        "closed too early"
    );
    // Ticks the model drove on the late-ego deadline came meanwhile; none of them kept it.
    assert!(scene.last().is_none() || scene.last().unwrap().tick >= 1);
    let status = c.status().unwrap();
    assert!(status.scenes.iter().all(|s| s.scene != scene.id()));
    server.stop().unwrap();
}

/// The cap on consecutive late ticks closes a scene long before the idle timeout.
#[test]
fn too_many_late_ticks_in_a_row_close_the_scene() {
    let dir = common::temp_dir("late-cap");
    let mut config = common::config(&dir);
    config.late_ego_deadline = Duration::from_millis(50);
    config.idle_timeout = Duration::from_secs(600);
    config.max_consecutive_late_ticks = 5;
    let server = common::start(config);
    let c = common::client(&server, "late");
    let scene = c.create(common::roundabout()).unwrap();
    let e = scene
        .wait_error(Duration::from_secs(120))
        .unwrap()
        .expect("the server must close the scene");
    assert_eq!(e.code, ErrorCode::ClientSilent, "{e}");
    assert!(e.message.contains("5 ticks in a row"), "{e}");
    server.stop().unwrap();
}

/// A client that answers every tick keeps its scene past the idle timeout, however slow the
/// server's first tick (its warm-up is the server's silence, not the client's).
#[test]
fn a_client_that_answers_keeps_its_scene() {
    let dir = common::temp_dir("answering");
    let mut config = common::config(&dir);
    config.late_ego_deadline = Duration::ZERO;
    config.idle_timeout = Duration::from_secs(1);
    let server = common::start(config);
    let c = common::client(&server, "talker");
    let mut scene = c.create(common::roundabout()).unwrap();
    let history = scene.created().agents[0].history.clone();
    let until = Instant::now() + Duration::from_secs(3);
    let mut t = 1;
    while Instant::now() < until {
        let npc = scene.step(t, vec![common::replay(&history, 1, t)]).unwrap();
        assert_eq!(npc.tick, t);
        t += 1;
    }
    scene.close().unwrap();
    server.stop().unwrap();
}

/// `status?scene=<id>` (what a waiting client probes): that live scene's line alone; for an id
/// the server does not hold, `unknown_scene` naming it; for one that is no number,
/// `invalid_field` naming the parameter. The whole status is unchanged beside it.
#[test]
fn a_scenes_own_status_is_its_line_alone_and_bad_ids_are_named() {
    let dir = common::temp_dir("scene-status");
    let server = common::start(common::config(&dir));
    let c = common::client(&server, "asker");
    let scene = c.create(common::roundabout()).unwrap();
    let own = c.scene_status(scene.id()).unwrap();
    assert_eq!(own.scene, scene.id());
    assert_eq!(own.client.as_deref(), Some("asker"));
    let missing = scene.id() + 1000;
    match c.scene_status(missing).unwrap_err() {
        road_client::Error::Refused(e) => {
            assert_eq!(e.code, ErrorCode::UnknownScene, "{e}");
            assert_eq!(e.scene, Some(missing), "{e}");
        }
        other => panic!("expected unknown_scene, got {other}"),
    }
    let key = format!("{}?scene=first", c.keys().status());
    let refused = c.query_raw(&key, Vec::new()).unwrap().unwrap_err();
    assert_eq!(refused.code, ErrorCode::InvalidField, "{refused}");
    assert_eq!(refused.field.as_deref(), Some("scene"), "{refused}");
    assert!(refused.message.contains("scene=first"), "{refused}");
    let status = c.status().unwrap();
    assert!(status.scenes.iter().any(|s| s.scene == scene.id()));
    server.stop().unwrap();
}
