"""A Python ego client of road's NPC server (``road serve``) over Eclipse Zenoh.

Create a scene, step it tick by tick with the ego's poses, close it::

    from road_client import Client, AgentState
    client = Client.open(connect=["tcp/127.0.0.1:7447"], client_id="my-ego")
    scene = client.create_scene({"procedural": "roundabout"}, external=[1])
    ego = scene.created.agents[0]
    npcs = scene.step(1, [AgentState(ego.id, ego.history[-1].x_m, ego.history[-1].y_m + 0.7,
                                     ego.history[-1].heading_rad)])
    scene.close()
    client.close()

Several servers under one root (``road serve --prefix road/a``, ``road/b``, behind a zenoh
router): find them and put the scene on the least-loaded one::

    from road_client import Client, open_session
    session = open_session(connect=["tcp/127.0.0.1:7447"])
    client, scene = Client.create_on_least_loaded(session, "road", "my-ego",
                                                  {"procedural": "roundabout"}, external=[1])
    ...  # keep ``client``: its liveliness token keeps the scene
    scene.close()
    client.close()
    session.close()

The messages are the JSON of ``docs/protocol.md``; poses are metres and radians in the map's
frame.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Optional

import zenoh

__all__ = [
    "AgentInfo",
    "AgentInit",
    "AgentPlan",
    "AgentState",
    "Client",
    "NpcTick",
    "Pose",
    "RoadError",
    "Scene",
    "SceneClosed",
    "SceneCreated",
    "ServerInfo",
    "discover",
    "least_loaded",
    "open_session",
]

DEFAULT_PREFIX = "road"


@dataclass
class Pose:
    x_m: float
    y_m: float
    heading_rad: float


@dataclass
class AgentInit:
    """An agent at creation: its box and its history, oldest first, 0.1 s apart."""

    id: int
    length_m: float
    width_m: float
    history: list[Pose]


@dataclass
class AgentState:
    id: int
    x_m: float
    y_m: float
    heading_rad: float


@dataclass
class AgentInfo:
    id: int
    length_m: float
    width_m: float
    external: bool
    history: list[Pose]


@dataclass
class SceneCreated:
    protocol: int
    scene: int
    agents: list[AgentInfo]
    planner: str
    checkpoint: str
    observed_steps: int
    step_secs: float
    max_ticks: int
    late_ego_deadline_ms: int
    ego_key: str
    npc_key: str
    error_key: str
    # The scene's secret: every tick and close of the scene carries it (protocol 4).
    token: str = ""
    recording: Optional[str] = None


@dataclass
class AgentPlan:
    """One NPC's plan: its poses at the ticks after the ``NpcTick`` that holds it, 0.1 s apart."""

    id: int
    poses: list[Pose]


@dataclass
class NpcTick:
    scene: int
    tick: int
    time_s: float
    npcs: list[AgentState]
    collisions: list[list[int]]
    off_road: list[int]
    latency_ms: float
    compute_ms: float
    # Of ``latency_ms``: the wait for other scenes' engine rounds (protocol 3).
    queue_ms: float = 0.0
    late_external: list[AgentState] = field(default_factory=list)
    # Each NPC's plan, when the scene was created with ``plans=True``.
    plans: list[AgentPlan] = field(default_factory=list)
    # NPCs that left this tick (drove off the map at a lane's end, or were taken out stuck):
    # gone from later ticks (protocol 4).
    left: list[int] = field(default_factory=list)
    # Those of ``left`` the server's stuck removal took out (a jam nothing undid).
    stuck: list[int] = field(default_factory=list)


@dataclass
class SceneClosed:
    scene: int
    ticks: int
    recording: Optional[str] = None


@dataclass
class ServerInfo:
    """A server found under a root: its key prefix and the ``Status`` it answered with (the
    JSON of ``docs/protocol.md``, kept as a dict so that new status fields need no client
    change)."""

    prefix: str
    status: dict

    @property
    def scenes(self) -> int:
        return len(self.status.get("scenes", []))

    @property
    def capacity(self) -> int:
        return int(self.status.get("capacity", 0))

    @property
    def load(self) -> float:
        """Live scenes over capacity: 0 when idle, 1 when full."""
        return self.scenes / max(self.capacity, 1)

    @property
    def has_room(self) -> bool:
        """Whether another scene fits."""
        return self.scenes < self.capacity


class RoadError(Exception):
    """The server refused a request or a tick (its error reply), or nothing came in time."""

    def __init__(self, code: str, message: str, field: Optional[str] = None, reply: Any = None):
        super().__init__(f"{code}: {message}" + (f" (field {field})" if field else ""))
        self.code = code
        self.field = field
        self.message = message
        self.reply = reply


def _reply(cls, d: dict):
    """``cls`` from a reply's JSON object, ignoring fields this client does not know: a newer
    server may add reply fields (protocol 3); requests stay strict on the server's side."""
    known = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in d.items() if k in known})


def _pose(d: dict) -> Pose:
    return _reply(Pose, d)


def _state(d: dict) -> AgentState:
    return _reply(AgentState, d)


def _created(d: dict) -> SceneCreated:
    d = dict(d)
    d["agents"] = [
        _reply(AgentInfo, {**a, "history": [_pose(p) for p in a["history"]]}) for a in d["agents"]
    ]
    return _reply(SceneCreated, d)


def _npc_tick(d: dict) -> NpcTick:
    d = dict(d)
    d["npcs"] = [_state(a) for a in d["npcs"]]
    d["late_external"] = [_state(a) for a in d.get("late_external", [])]
    d["plans"] = [AgentPlan(p["id"], [_pose(q) for q in p["poses"]]) for p in d.get("plans", [])]
    return _reply(NpcTick, d)


def _error(payload: bytes) -> RoadError:
    try:
        e = json.loads(payload)
        return RoadError(e.get("code", "unknown"), e.get("message", ""), e.get("field"), e)
    except (ValueError, AttributeError):
        return RoadError("unreadable", payload[:200].decode("utf-8", "replace"))


def _query(session: zenoh.Session, key: str, payload: bytes, timeout_s: float) -> dict:
    """The first reply of the queryable at ``key``; its error reply raised as ``RoadError``.
    A get that no queryable matches ends at once with no reply, reported as a timeout too."""
    start = time.monotonic()
    replies = session.get(key, payload=payload, timeout=timeout_s)
    for reply in replies:
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
        raise _error(reply.err.payload.to_bytes())
    waited = time.monotonic() - start
    if waited < 0.9 * timeout_s:
        raise RoadError("timeout", f"no reply on {key}: no queryable there answered "
                                   f"(after {waited:.1f} s of {timeout_s} s)")
    raise RoadError("timeout", f"no reply on {key} within {timeout_s} s")


def _server_prefix_of(key: str) -> Optional[str]:
    """The prefix of the server whose liveliness token is at ``key`` (``road/east/alive/server``
    -> ``road/east``), or None when ``key`` is not a server's token."""
    suffix = "/alive/server"
    if key.endswith(suffix) and len(key) > len(suffix):
        return key[: -len(suffix)]
    return None


def open_session(connect: Optional[list[str]] = None, listen: Optional[list[str]] = None,
                 mode: Optional[str] = None, multicast_scouting: bool = False,
                 config_file: Optional[str] = None,
                 overrides: Optional[list[tuple[str, str]]] = None) -> zenoh.Session:
    """Opens a zenoh session from a json5 config file and/or endpoints. ``mode`` is ``peer``
    (zenoh's default), ``client`` or ``router``; multicast scouting is off unless asked for, so
    that tests and containers find only the endpoints they name. ``overrides`` are
    ``(key, json5 value)`` pairs applied last, as ``road``'s ``--cfg KEY:VALUE`` (e.g. a
    router's user and password)."""
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if mode is not None:
        if mode not in ("peer", "client", "router"):
            raise ValueError(f"zenoh mode {mode!r}: expected peer, client or router")
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if not multicast_scouting:
        conf.insert_json5("scouting/multicast/enabled", "false")
    for key, value in overrides or []:
        conf.insert_json5(key, value)
    return zenoh.open(conf)


def discover(session: zenoh.Session, root: str = DEFAULT_PREFIX, timeout_s: float = 5.0
             ) -> tuple[list[ServerInfo], list[tuple[str, RoadError]]]:
    """Every server whose prefix is ``root`` or lies below it, with its status, sorted by
    prefix; and, so that none is dropped silently, the servers whose liveliness token is there
    but whose status did not come, each with its error.

    Every ``road serve`` holds a liveliness token at ``<prefix>/alive/server``, so one
    liveliness query on ``<root>/**/alive/server`` (``**`` matches zero chunks too) lists the
    servers the session reaches through its routers. ``timeout_s`` bounds the liveliness query
    and each status query (a busy server answers its status between two batched rounds)."""
    selector = f"{root.strip('/')}/**/alive/server"
    prefixes = set()
    # The handler's channel ends when every router has answered or the timeout has passed.
    for reply in session.liveliness().get(selector, timeout=timeout_s):
        if reply.ok is None:
            continue
        prefix = _server_prefix_of(str(reply.ok.key_expr))
        if prefix is not None:
            prefixes.add(prefix)
    servers: list[ServerInfo] = []
    unreachable: list[tuple[str, RoadError]] = []
    for prefix in sorted(prefixes):
        try:
            servers.append(ServerInfo(prefix, _query(session, f"{prefix}/status", b"",
                                                     timeout_s)))
        except RoadError as e:
            unreachable.append((prefix, e))
        except ValueError as e:
            unreachable.append((prefix, RoadError("unreadable", f"status of {prefix}: {e}")))
    return servers, unreachable


def least_loaded(servers: list[ServerInfo]) -> Optional[ServerInfo]:
    """The server with room whose load is lowest; ties go to fewer live scenes, then to the
    prefix (so that placement is deterministic). None when none has room."""
    with_room = [s for s in servers if s.has_room]
    return min(with_room, key=lambda s: (s.load, s.scenes, s.prefix), default=None)


def _scene_topic(key: str) -> Optional[tuple[int, str]]:
    """(scene id, "npc" or "error") of a key ending ``scene/<id>/npc`` or ``scene/<id>/error``."""
    chunks = key.split("/")
    if len(chunks) < 3 or chunks[-3] != "scene" or chunks[-1] not in ("npc", "error"):
        return None
    try:
        return int(chunks[-2]), chunks[-1]
    except ValueError:
        return None


class Client:
    """A session to a road server, announced by a liveliness token (while it lives, the server
    keeps the client's scenes).

    The client subscribes once to all its scenes' NPC states and errors
    (``<prefix>/client/<id>/scene/*/npc`` and ``…/error``), handing each sample to its scene,
    and once to the server's liveliness token: per-scene subscriptions would leave routing
    entries behind in zenoh for every scene (docs/experiments/bench-2026-11-24-soak.md)."""

    def __init__(self, session: zenoh.Session, client_id: str, prefix: str = DEFAULT_PREFIX,
                 timeout_s: float = 60.0, owns_session: bool = True):
        """``owns_session``: whether ``close()`` closes the session too (False when several
        clients, e.g. one per server, share it)."""
        self.session = session
        self.client_id = client_id
        self.prefix = prefix.strip("/")
        self.timeout_s = timeout_s
        self.owns_session = owns_session
        self._lock = threading.Lock()
        # scene id -> {"npc": queue, "error": queue}
        self._inboxes: dict[int, dict[str, queue.SimpleQueue]] = {}
        self._server_losses = 0
        self._closed = False
        base = f"{self.prefix}/client/{client_id}/scene"
        self._subscribers = [
            session.declare_subscriber(f"{base}/*/npc", self._deliver),
            session.declare_subscriber(f"{base}/*/error", self._deliver),
            # The server's liveliness token: when it goes (the server stopped, or the network
            # to it was cut) no tick will come, so a wait ends at once instead of at its timeout.
            session.liveliness().declare_subscriber(f"{self.prefix}/alive/server",
                                                    self._server_alive),
        ]
        self._token = session.liveliness().declare_token(f"{self.prefix}/alive/client/{client_id}")

    def _deliver(self, sample: zenoh.Sample) -> None:
        topic = _scene_topic(str(sample.key_expr))
        if topic is None:
            return
        scene, kind = topic
        with self._lock:
            inbox = self._inboxes.get(scene)
        # None: a scene this client closed; its late messages have no reader.
        if inbox is not None:
            inbox[kind].put(sample.payload.to_bytes())

    def _server_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            with self._lock:
                self._server_losses += 1

    def _open_inbox(self, scene: int) -> dict[str, queue.SimpleQueue]:
        inbox = {"npc": queue.SimpleQueue(), "error": queue.SimpleQueue()}
        with self._lock:
            self._inboxes[scene] = inbox
        return inbox

    def _close_inbox(self, scene: int) -> None:
        with self._lock:
            self._inboxes.pop(scene, None)

    @property
    def server_losses(self) -> int:
        """How many times the server's liveliness token went away since this client started."""
        with self._lock:
            return self._server_losses

    @classmethod
    def open(cls, connect: Optional[list[str]] = None, listen: Optional[list[str]] = None,
             client_id: str = "python-ego", prefix: str = DEFAULT_PREFIX,
             multicast_scouting: bool = False, config_file: Optional[str] = None,
             timeout_s: float = 60.0) -> "Client":
        """Opens a zenoh session (peer mode) from a json5 config file and/or endpoints."""
        session = open_session(connect=connect, listen=listen,
                               multicast_scouting=multicast_scouting, config_file=config_file)
        return cls(session, client_id, prefix, timeout_s)

    @classmethod
    def create_on_least_loaded(cls, session: zenoh.Session, root: str, client_id: str,
                               map: dict, agents: Optional[list[AgentInit]] = None,
                               external: Optional[list[int]] = None,
                               planner: Optional[str] = None, checkpoint: Optional[str] = None,
                               seed: int = 0, max_ticks: Optional[int] = None,
                               timeout_s: float = 60.0, discover_timeout_s: Optional[float] = None,
                               plans: bool = False) -> tuple["Client", "Scene"]:
        """Finds the servers under ``root`` (``discover``) and creates the scene (arguments as
        ``create_scene``) on the least-loaded one with room. Returns the client of that server,
        sharing ``session`` (its ``close()`` leaves the session open), and the scene: keep the
        client, its liveliness token keeps the scene. Raises ``RoadError`` with code
        ``no_server`` when no server has room, naming the servers that did not answer.
        ``discover_timeout_s`` (default ``timeout_s``) bounds the discovery's queries."""
        servers, unreachable = discover(
            session, root, timeout_s if discover_timeout_s is None else discover_timeout_s)
        server = least_loaded(servers)
        if server is None:
            why = "".join(f"; {prefix} did not answer: {e}" for prefix, e in unreachable)
            raise RoadError("no_server", f"no server under {root} has room for a scene "
                                         f"({len(servers)} found{why})")
        client = cls(session, client_id, server.prefix, timeout_s, owns_session=False)
        try:
            scene = client.create_scene(map, agents=agents, external=external, planner=planner,
                                        checkpoint=checkpoint, seed=seed, max_ticks=max_ticks,
                                        plans=plans)
        except BaseException:
            client.close()
            raise
        return client, scene

    def _query(self, key: str, payload: bytes) -> dict:
        return _query(self.session, key, payload, self.timeout_s)

    def create_scene(self, map: dict, agents: Optional[list[AgentInit]] = None,
                     external: Optional[list[int]] = None, planner: Optional[str] = None,
                     checkpoint: Optional[str] = None, seed: int = 0,
                     max_ticks: Optional[int] = None, plans: bool = False) -> "Scene":
        """Creates a scene. ``map`` is ``{"procedural": "roundabout"}``, ``{"osm": text}`` or
        ``{"file": name}``; ``agents`` may be omitted on a procedural map (its own vehicles).
        With ``plans`` every ``NpcTick`` also carries each NPC's plan (``NpcTick.plans``)."""
        request: dict[str, Any] = {"map": map, "external": list(external or []), "seed": seed,
                                   "client": self.client_id}
        if agents is not None:
            request["agents"] = [asdict(a) for a in agents]
        if planner is not None:
            request["planner"] = planner
        if checkpoint is not None:
            request["checkpoint"] = checkpoint
        if max_ticks is not None:
            request["max_ticks"] = max_ticks
        if plans:
            request["plans"] = True
        created = _created(self._query(f"{self.prefix}/scenes/create",
                                       json.dumps(request).encode()))
        return Scene(self, created)

    def status(self) -> dict:
        return self._query(f"{self.prefix}/status", b"")

    def close_scene(self, scene: int, token: str) -> SceneClosed:
        """Closes scene ``scene`` with its secret (``SceneCreated.token``; ``Scene.close``
        knows it)."""
        reply = self._query(f"{self.prefix}/scenes/close",
                            json.dumps({"scene": scene, "client": self.client_id,
                                        "token": token}).encode())
        return _reply(SceneClosed, reply)

    def close(self) -> None:
        # Its scenes' waits end with an error instead of running to their timeout.
        self._closed = True
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._token.undeclare()
        if self.owns_session:
            self.session.close()


class Scene:
    """A live scene: put the ego's poses, read the NPCs."""

    def __init__(self, client: Client, created: SceneCreated):
        self.client = client
        self.created = created
        self.last: Optional[NpcTick] = None
        self._inbox = client._open_inbox(created.scene)
        # Gone once the server's token went away after this scene began (sticky: a server back
        # under the same prefix does not know this scene).
        self._server_losses_before = client.server_losses

    @property
    def id(self) -> int:
        return self.created.scene

    def put(self, tick: int, agents: list[AgentState]) -> None:
        msg = {"tick": tick, "agents": [asdict(a) for a in agents],
               "client": self.client.client_id, "token": self.created.token}
        # Block, not zenoh's default Drop: a tick is never lost to a full queue.
        self.client.session.put(self.created.ego_key, json.dumps(msg).encode(),
                                congestion_control=zenoh.CongestionControl.BLOCK)

    def poll(self, tick: int) -> Optional[NpcTick]:
        """The NPCs of ``tick`` if they have come, else None, without waiting (to drive several
        scenes from one thread); raises the server's error for this scene (e.g. ``bad_tick``,
        ``scene_closed``), or ``server_gone`` when the server's liveliness token went."""
        try:
            raise _error(self._inbox["error"].get_nowait())
        except queue.Empty:
            pass
        while True:
            try:
                payload = self._inbox["npc"].get_nowait()
            except queue.Empty:
                break
            npc = _npc_tick(json.loads(payload))
            self.last = npc
            if npc.tick >= tick:
                return npc
        if self.client._closed:
            raise RoadError("client_closed", f"the client of scene {self.id} was closed: "
                                             f"tick {tick} will not be read")
        if self.client.server_losses > self._server_losses_before:
            raise RoadError("server_gone",
                            f"the server at {self.client.prefix} went away (its liveliness "
                            f"token is gone) before tick {tick} of scene {self.id}")
        return None

    def wait_tick(self, tick: int) -> NpcTick:
        """Waits for the NPCs of ``tick``; raises the server's error for this scene."""
        deadline = time.monotonic() + self.client.timeout_s
        while True:
            npc = self.poll(tick)
            if npc is not None:
                return npc
            if time.monotonic() > deadline:
                raise RoadError("timeout", f"no NPCs for tick {tick} of scene {self.id}")
            time.sleep(0.001)

    def step(self, tick: int, agents: list[AgentState]) -> NpcTick:
        """Puts the external agents' poses for ``tick`` and waits for that tick's NPCs."""
        self.put(tick, agents)
        return self.wait_tick(tick)

    def close(self) -> SceneClosed:
        self.client._close_inbox(self.id)
        return self.client.close_scene(self.id, self.created.token)
