"""Two servers behind a zenoh router on loopback, as ``docker/compose.yaml`` deploys them (there
``router`` is the router's host name): ``road router``, two ``road serve --mode client`` under the
prefixes ``road/a`` and ``road/b``, each recording to its own folder. The scripted Python ego
(``clients/python/examples/ego.py``) finds them under ``road`` and splits 4 scenes 2/2 between
them; every tick is answered and every scene's recording reads back. Discovery and least-loaded
placement are also checked directly, including a server whose status does not answer.

The binary comes from ``$ROAD_BIN``, else ``target/debug/road`` of the repository."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import pytest
from mcap.reader import make_reader

from road_client import Client, RoadError, ServerInfo, discover, least_loaded, open_session
from road_test_support import REPO, free_port, road_bin

EGO = REPO / "clients" / "python" / "examples" / "ego.py"
SCENES = 4
TICKS = 20
# Debug-build servers take seconds over a scene's first tick (the model's warm-up) and share
# the machine with everything else: generous bounds, which a passing run never comes near.
START_S = 120.0
EGO_S = 900.0


def tail(path: Path, lines: int = 40) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError as e:
        return f"({e})"


class Deployment:
    """The router and the two servers: their processes, logs and record folders."""

    def __init__(self, root: Path):
        self.root = root
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.record = {"road/a": root / "a", "road/b": root / "b"}
        self.procs: dict[str, subprocess.Popen] = {}
        self.session = None

    def start(self, name: str, args: list[str]) -> None:
        # Logs go to files, not pipes: a pipe nobody reads fills up and stalls the process.
        with open(self.root / f"{name}.log", "wb") as log:
            self.procs[name] = subprocess.Popen([road_bin(), *args], stdout=log,
                                                stderr=subprocess.STDOUT, cwd=REPO)

    def check_running(self) -> None:
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                pytest.fail(f"{name} exited with {proc.returncode}\n{self.logs()}")

    def logs(self) -> str:
        return "\n".join(f"--- {name} (last lines of {self.root / (name + '.log')}):\n"
                         f"{tail(self.root / (name + '.log'))}" for name in self.procs)

    @contextmanager
    def shown_on_failure(self):
        """Prints the processes' logs when the block fails (pytest shows them with the
        failure)."""
        try:
            yield
        except BaseException:
            print(self.logs())
            raise

    def stop(self) -> None:
        if self.session is not None:
            self.session.close()
        # The servers first (they close their scenes and finish their recordings), the router
        # last.
        for name in sorted(self.procs, key=lambda n: n == "router"):
            proc = self.procs[name]
            if proc.poll() is None:
                proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    dep = Deployment(tmp_path_factory.mktemp("deploy"))
    try:
        dep.start("router", ["router", "--listen", dep.endpoint, "--no-multicast-scouting"])
        # A client-mode session opens only once the router listens; the servers (client mode
        # too) would fail at once before that.
        deadline = time.monotonic() + START_S
        while dep.session is None:
            dep.check_running()
            try:
                dep.session = open_session(connect=[dep.endpoint], mode="client")
            except Exception:
                if time.monotonic() > deadline:
                    pytest.fail(f"the router never listened on {dep.endpoint}\n{dep.logs()}")
                time.sleep(0.2)
        for prefix, record in dep.record.items():
            dep.start(f"serve-{prefix[-1]}",
                      ["serve", "--mode", "client", "--connect", dep.endpoint,
                       "--no-multicast-scouting", "--prefix", prefix, "--record", str(record)])
        while True:
            dep.check_running()
            servers, _ = discover(dep.session, "road", 5.0)
            if [s.prefix for s in servers] == ["road/a", "road/b"]:
                break
            if time.monotonic() > deadline:
                pytest.fail(f"the servers never appeared under road (found "
                            f"{[s.prefix for s in servers]})\n{dep.logs()}")
            time.sleep(0.2)
        yield dep
    finally:
        dep.stop()


def recordings(folder: Path) -> set[Path]:
    return set(folder.glob("*.mcap")) if folder.is_dir() else set()


def test_ego_splits_scenes_between_two_servers(deployment):
    dep = deployment
    before = {prefix: recordings(folder) for prefix, folder in dep.record.items()}
    env = dict(os.environ)
    # The client under test is this checkout's, installed or not.
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO / "clients" / "python"), *filter(None, [env.get("PYTHONPATH")])])
    cmd = [sys.executable, str(EGO), "--connect", dep.endpoint, "--discover", "road",
           "--scenes", str(SCENES), "--ticks", str(TICKS), "--min-servers", "2"]
    with dep.shown_on_failure():
        ego = subprocess.run(cmd, capture_output=True, text=True, timeout=EGO_S, cwd=REPO,
                             env=env)
        report = f"ego exited with {ego.returncode}\nstdout:\n{ego.stdout}\nstderr:\n{ego.stderr}"
        assert ego.returncode == 0, report
        dep.check_running()

        # Where each scene went, as the ego says.
        placed = dict(re.findall(r"^scene (\d+): id \d+ on (\S+) \(", ego.stdout, re.M))
        assert len(placed) == SCENES, report
        assert Counter(placed.values()) == {"road/a": 2, "road/b": 2}, report
        # Least-loaded with ties to the prefix: a, b, a, b.
        assert [placed[str(i)] for i in range(SCENES)] == ["road/a", "road/b"] * 2, report
        # Every tick of every scene answered, per server.
        for prefix in ("road/a", "road/b"):
            assert re.search(rf"^{prefix}: 2 scene\(s\), {2 * TICKS} tick\(s\) answered",
                             ego.stdout, re.M), report
        ticks = re.findall(r"^tick +(\d+) .* scene (\d+) on (\S+):", ego.stdout, re.M)
        assert sorted((int(s), int(t)) for t, s, _ in ticks) == [
            (s, t) for s in range(SCENES) for t in range(1, TICKS + 1)], report

        # The recordings: each server recorded its 2 scenes, every tick in them.
        printed = re.findall(r"^scene (\d+): id \d+ on (\S+), (\d+) ticks, recorded at (.+)$",
                             ego.stdout, re.M)
        assert len(printed) == SCENES, report
        for index, prefix, closed_ticks, path in printed:
            assert int(closed_ticks) == TICKS, report
            assert prefix == placed[index], report
            assert Path(path).parent == dep.record[prefix], report
        for prefix, folder in dep.record.items():
            new = recordings(folder) - before[prefix]
            assert new == {Path(p) for _, pr, _, p in printed if pr == prefix}, report
            assert len(new) == 2, report
            for path in new:
                npc_ticks = []
                with open(path, "rb") as f:
                    for _schema, channel, message in make_reader(f).iter_messages():
                        if channel.topic == "/road/npc":
                            npc_ticks.append(json.loads(message.data)["tick"])
                assert npc_ticks == list(range(1, TICKS + 1)), path

        # Closed: neither server holds a scene any more.
        servers, unreachable = discover(dep.session, "road", 30.0)
        assert not unreachable
        assert {s.prefix: s.scenes for s in servers} == {"road/a": 0, "road/b": 0}


def test_discover_and_least_loaded(deployment):
    dep = deployment
    session = dep.session
    clients: list[Client] = []
    with dep.shown_on_failure():
        servers, unreachable = discover(session, "road", 30.0)
        assert [s.prefix for s in servers] == ["road/a", "road/b"]
        assert unreachable == []
        assert all(s.load == 0.0 and s.has_room and s.capacity == 256 for s in servers)
        assert least_loaded(servers).prefix == "road/a"  # the tie goes to the prefix
        # A root below the servers' finds only its own; one beside them, none.
        assert [s.prefix for s in discover(session, "road/b", 30.0)[0]] == ["road/b"]
        assert discover(session, "elsewhere", 30.0) == ([], [])

        try:
            # One scene on road/a: road/b becomes the least loaded, and takes the next scene.
            a = Client(session, "pytest-a", "road/a", timeout_s=120.0, owns_session=False)
            clients.append(a)
            scene_a = a.create_scene({"procedural": "roundabout"}, external=[1])
            servers, _ = discover(session, "road", 30.0)
            loads = {s.prefix: s.load for s in servers}
            assert loads == {"road/a": 1 / 256, "road/b": 0.0}
            assert least_loaded(servers).prefix == "road/b"
            b, scene_b = Client.create_on_least_loaded(
                session, "road", "pytest-b", {"procedural": "roundabout"}, external=[1],
                timeout_s=120.0, discover_timeout_s=30.0)
            clients.append(b)
            assert b.prefix == "road/b" and not b.owns_session
            assert scene_b.created.ego_key.startswith("road/b/")
            servers, _ = discover(session, "road", 30.0)
            assert {s.prefix: s.scenes for s in servers} == {"road/a": 1, "road/b": 1}

            # A server whose token is there but whose status does not answer is reported,
            # not dropped, and never chosen.
            ghost = session.liveliness().declare_token("road/ghost/alive/server")
            try:
                servers, unreachable = discover(session, "road", 5.0)
            finally:
                ghost.undeclare()
            assert [s.prefix for s in servers] == ["road/a", "road/b"]
            assert [p for p, _ in unreachable] == ["road/ghost"]
            assert isinstance(unreachable[0][1], RoadError)

            assert scene_a.close().scene == scene_a.id
            assert scene_b.close().scene == scene_b.id
        finally:
            for client in clients:
                client.close()
        # The session is still open: the clients did not own it.
        assert [s.scenes for s in discover(session, "road", 30.0)[0]] == [0, 0]


def test_least_loaded_prefers_room_then_load_then_scenes_then_prefix():
    def server(prefix: str, scenes: int, capacity: int) -> ServerInfo:
        return ServerInfo(prefix, {"capacity": capacity, "scenes": [{}] * scenes})

    assert least_loaded([]) is None
    assert least_loaded([server("road/full", 2, 2)]) is None
    assert server("road/x", 1, 4).load == 0.25
    assert server("road/x", 0, 0).load == 0.0 and not server("road/x", 0, 0).has_room
    # Room first, then the lowest load.
    assert least_loaded([server("road/a", 4, 4), server("road/b", 3, 4)]).prefix == "road/b"
    assert least_loaded([server("road/a", 2, 4), server("road/b", 3, 16)]).prefix == "road/b"
    # Equal loads: fewer scenes, then the prefix.
    assert least_loaded([server("road/a", 2, 8), server("road/b", 1, 4)]).prefix == "road/b"
    assert least_loaded([server("road/b", 1, 4), server("road/a", 1, 4)]).prefix == "road/a"
