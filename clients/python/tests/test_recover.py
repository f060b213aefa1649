"""A killed server's recording, recovered: ``road serve`` runs a scene for a few ticks and is
killed (SIGKILL); its recording then has no summary, and the ``mcap`` package's default reader
(``make_reader(f).iter_messages()``) fails on it. ``road recover`` rewrites it whole, and the
default reader then reads every NPC tick.

The server binary comes from ``$ROAD_BIN`` (``scripts/test.sh`` builds it), else
``target/debug/road`` of the repository."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader

from road_client import AgentState, RoadError
from road_test_support import road_bin, start_server

TICKS = 5


def npc_ticks(path: Path) -> list[int]:
    """The NPC ticks of a recording, read by the ``mcap`` package's default reader."""
    with open(path, "rb") as f:
        return [json.loads(message.data)["tick"]
                for _schema, channel, message in make_reader(f).iter_messages()
                if channel.topic == "/road/npc"]


def test_recover_makes_a_killed_servers_recording_readable(tmp_path):
    record = tmp_path / "rec"
    log = open(tmp_path / "serve.log", "w+")
    proc, client = start_server(record, "pyrecover", log)
    try:
        scene = client.create_scene({"procedural": "roundabout"}, external=[1], seed=3)
        path = Path(scene.created.recording)
        ego = next(a for a in scene.created.agents if a.external)
        last = ego.history[-1]
        for t in range(1, TICKS + 1):
            state = AgentState(ego.id, last.x_m, last.y_m, last.heading_rad)
            assert scene.step(t, [state]).tick == t
        # The server writes its chunks out at least once a second.
        time.sleep(1.5)
        proc.kill()  # SIGKILL: no chance to finish the file
        proc.wait(timeout=30)
        # The client hears of it from the server's liveliness token, not from a timeout.
        with pytest.raises(RoadError) as e:
            scene.step(TICKS + 1, [state])
        assert e.value.code == "server_gone"
    finally:
        client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()

    assert path.parent == record and path.is_file()
    # What the issue found: the default reader, which starts from the summary, fails
    # (`RecordLengthLimitExceeded` when the file ends in the chunk being filled).
    with pytest.raises(McapError):
        npc_ticks(path)

    out = subprocess.run([road_bin(), "recover", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert f"{path}: recovered " in out.stdout, out.stdout
    assert npc_ticks(path) == list(range(1, TICKS + 1))
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.chunk_indexes
    topics = {c.topic for c in summary.channels.values()}
    assert {"/road/create", "/road/ego", "/road/npc", "/map", "/agents"} <= topics

    again = subprocess.run([road_bin(), "recover", str(path)], capture_output=True, text=True,
                           timeout=60)
    assert again.returncode == 0 and "already complete" in again.stdout, again
