"""The client's one subscription to all its scenes, without a server: each message reaches its
own scene by the key's scene id, and a closed client ends its scenes' waits at once."""

from __future__ import annotations

import json
import time

import pytest

from road_client import (Client, RoadError, Scene, SceneCreated, _created, _npc_tick,
                         _scene_topic, open_session)


def test_replies_with_fields_this_client_does_not_know_still_parse():
    # Protocol 3: a newer server may add reply fields; the client keeps what it knows.
    tick = _npc_tick({"scene": 1, "tick": 2, "time_s": 0.2, "npcs": [{"id": 3, "x_m": 1.0,
                      "y_m": 2.0, "heading_rad": 0.0, "new": 1}], "collisions": [],
                      "off_road": [], "latency_ms": 5.0, "compute_ms": 4.0, "queue_ms": 0.5,
                      "a_field_from_the_future": [1, 2]})
    assert (tick.scene, tick.tick, tick.queue_ms, tick.npcs[0].id) == (1, 2, 0.5, 3)
    created = _created({"protocol": 9, "scene": 4, "agents": [], "planner": "p",
                        "checkpoint": "c", "observed_steps": 10, "step_secs": 0.1,
                        "max_ticks": 5, "late_ego_deadline_ms": 0, "ego_key": "e",
                        "npc_key": "n", "error_key": "x", "something_new": {}})
    assert created.scene == 4


def test_scene_keys_name_their_scene_and_topic():
    assert _scene_topic("road/client/ego-1/scene/42/npc") == (42, "npc")
    assert _scene_topic("road/a/client/c/scene/7/error") == (7, "error")
    for key in ["road/client/c/scene/x/npc", "road/client/c/scene/1/ego",
                "road/client/c/scenes/1/npc", "npc", "1/npc"]:
        assert _scene_topic(key) is None, key


def created(scene: int) -> SceneCreated:
    base = f"road/client/me/scene/{scene}"
    return SceneCreated(protocol=3, scene=scene, agents=[], planner="road20", checkpoint="road20",
                        observed_steps=10, step_secs=0.1, max_ticks=10, late_ego_deadline_ms=0,
                        ego_key=f"{base}/ego", npc_key=f"{base}/npc", error_key=f"{base}/error")


def npc(scene: int, tick: int) -> bytes:
    return json.dumps({"scene": scene, "tick": tick, "time_s": 0.1 * tick, "npcs": [],
                       "collisions": [], "off_road": [], "latency_ms": 0.0,
                       "compute_ms": 0.0}).encode()


def wait(scene: Scene, tick: int):
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        got = scene.poll(tick)
        if got is not None:
            return got
        time.sleep(0.01)
    raise AssertionError(f"tick {tick} of scene {scene.id} never came")


def test_messages_reach_their_own_scene_and_a_closed_client_ends_the_wait():
    # One session both publishes (as the server would) and reads: zenoh delivers a session's
    # own puts to its own subscribers.
    session = open_session()
    client = Client(session, "me", timeout_s=5.0)
    try:
        one, two = Scene(client, created(1)), Scene(client, created(2))
        time.sleep(0.2)
        session.put(two.created.npc_key, npc(2, 1))
        session.put(one.created.npc_key, npc(1, 1))
        assert wait(one, 1).scene == 1
        assert wait(two, 1).scene == 2
        session.put(one.created.error_key, json.dumps(
            {"code": "bad_tick", "field": "tick", "message": "no", "scene": 1}).encode())
        with pytest.raises(RoadError) as e:
            wait(one, 2)
        assert e.value.code == "bad_tick"
        assert two.poll(2) is None
    finally:
        client.close()
        session.close()
    with pytest.raises(RoadError) as e:
        two.poll(2)
    assert e.value.code == "client_closed"
