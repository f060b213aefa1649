"""The Python client against a real ``road serve`` on loopback: one scene on the procedural
roundabout with a log-replay ego (its history's velocity, held) for 100 ticks. Every tick is
answered, every NPC state is finite and on the map's frame (an NPC that drives off the map's
edge leaves, once), and the scene's MCAP recording
reads back with the ``mcap`` package holding the 100 ticks.

The server binary comes from ``$ROAD_BIN`` (``scripts/test.sh`` builds it), else
``target/debug/road`` of the repository."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from mcap.reader import make_reader

from road_client import AgentState, RoadError
from road_test_support import start_server

TICKS = 100


@pytest.fixture(scope="module")
def server():
    record = tempfile.mkdtemp(prefix="road-py-")
    log = open(Path(record) / "serve.log", "w+")
    proc, client = start_server(Path(record), "pytest", log)
    try:
        yield client, record
    finally:
        client.close()
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        shutil.rmtree(record, ignore_errors=True)


def test_log_replay_ego_for_100_ticks(server):
    client, record = server
    scene = client.create_scene({"procedural": "roundabout"}, external=[1], seed=1)
    ego = next(a for a in scene.created.agents if a.external)
    last, previous = ego.history[-1], ego.history[-2]
    vx, vy = last.x_m - previous.x_m, last.y_m - previous.y_m
    npc_ids = {a.id for a in scene.created.agents if not a.external}
    for t in range(1, TICKS + 1):
        npc = scene.step(t, [AgentState(ego.id, last.x_m + vx * t, last.y_m + vy * t,
                                        last.heading_rad)])
        assert npc.tick == t
        # An NPC that drove off the map's edge leaves once and is in no later tick.
        assert set(npc.left) <= npc_ids, (t, npc.left)
        # Those taken out stuck are among those that left.
        assert set(npc.stuck) <= set(npc.left), (t, npc.stuck, npc.left)
        npc_ids -= set(npc.left)
        assert {a.id for a in npc.npcs} == npc_ids
        assert not npc.late_external
        # Protocol 3: the wait for other scenes' rounds is a part of the latency, like compute.
        assert 0.0 <= npc.queue_ms and npc.compute_ms + npc.queue_ms <= npc.latency_ms + 1e-6
        for a in npc.npcs:
            assert all(math.isfinite(v) for v in (a.x_m, a.y_m, a.heading_rad)), a
            # The roundabout's frame: its arms end about 90 m from the centre.
            assert math.hypot(a.x_m, a.y_m) < 300.0, a
    closed = scene.close()
    assert closed.ticks == TICKS
    path = closed.recording
    assert path and path.startswith(record)
    with open(path, "rb") as f:
        reader = make_reader(f)
        counts: dict[str, int] = {}
        ticks = []
        for _schema, channel, message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/road/npc":
                ticks.append(json.loads(message.data)["tick"])
    assert ticks == list(range(1, TICKS + 1))
    assert counts["/road/ego"] == TICKS
    assert counts["/road/create"] == 1 and counts["/map"] == 1
    assert counts["/agents"] == TICKS + 1


def test_bad_input_is_refused_by_field(server):
    client, _ = server
    with pytest.raises(RoadError) as e:
        client.create_scene({"procedural": "nowhere"})
    assert e.value.code == "bad_map" and e.value.field == "map.procedural"
    scene = client.create_scene({"procedural": "roundabout"}, external=[1])
    ego = scene.created.agents[0]
    last = ego.history[-1]
    with pytest.raises(RoadError) as e:
        scene.step(2, [AgentState(ego.id, last.x_m, last.y_m, last.heading_rad)])
    assert e.value.code == "bad_tick" and e.value.field == "tick"
    # The scene goes on.
    npc = scene.step(1, [AgentState(ego.id, last.x_m, last.y_m + 0.5, last.heading_rad)])
    assert npc.tick == 1
    scene.close()


def test_plans_on_request(server):
    """A scene created with ``plans`` gets every NPC's plan each tick (the window's 9 steps
    after the emitted one for RoAD-20); the plan's first pose is where the NPC is heading."""
    client, _record = server
    scene = client.create_scene({"procedural": "roundabout"}, external=[1], seed=2, plans=True)
    ego = next(a for a in scene.created.agents if a.external)
    last = ego.history[-1]
    npc_ids = {a.id for a in scene.created.agents if not a.external}
    previous = None
    for t in range(1, 6):
        npc = scene.step(t, [AgentState(ego.id, last.x_m, last.y_m, last.heading_rad)])
        assert {p.id for p in npc.plans} == npc_ids
        for plan in npc.plans:
            assert len(plan.poses) == 9
            for p in plan.poses:
                assert all(math.isfinite(v) for v in (p.x_m, p.y_m, p.heading_rad)), p
        if previous is not None:
            # Last tick's plan for this tick against the state this tick emitted: the model
            # replans each tick, but not by more than a few metres in 0.1 s.
            now = {a.id: a for a in npc.npcs}
            for plan in previous.plans:
                first, state = plan.poses[0], now[plan.id]
                assert math.hypot(first.x_m - state.x_m, first.y_m - state.y_m) < 3.0, (plan.id, t)
        previous = npc
    scene.close()
    plain = client.create_scene({"procedural": "roundabout"}, external=[1], seed=2)
    npc = plain.step(1, [AgentState(ego.id, last.x_m, last.y_m, last.heading_rad)])
    assert npc.plans == []
    plain.close()
