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

The messages are the JSON of ``docs/protocol.md``; poses are metres and radians in the map's
frame.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Optional

import zenoh

__all__ = [
    "AgentInfo",
    "AgentInit",
    "AgentState",
    "Client",
    "NpcTick",
    "Pose",
    "RoadError",
    "Scene",
    "SceneClosed",
    "SceneCreated",
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
    recording: Optional[str] = None


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
    late_external: list[AgentState] = field(default_factory=list)


@dataclass
class SceneClosed:
    scene: int
    ticks: int
    recording: Optional[str] = None


class RoadError(Exception):
    """The server refused a request or a tick (its error reply), or nothing came in time."""

    def __init__(self, code: str, message: str, field: Optional[str] = None, reply: Any = None):
        super().__init__(f"{code}: {message}" + (f" (field {field})" if field else ""))
        self.code = code
        self.field = field
        self.message = message
        self.reply = reply


def _pose(d: dict) -> Pose:
    return Pose(**d)


def _state(d: dict) -> AgentState:
    return AgentState(**d)


def _created(d: dict) -> SceneCreated:
    d = dict(d)
    d["agents"] = [
        AgentInfo(**{**a, "history": [_pose(p) for p in a["history"]]}) for a in d["agents"]
    ]
    return SceneCreated(**d)


def _npc_tick(d: dict) -> NpcTick:
    d = dict(d)
    d["npcs"] = [_state(a) for a in d["npcs"]]
    d["late_external"] = [_state(a) for a in d.get("late_external", [])]
    return NpcTick(**d)


def _error(payload: bytes) -> RoadError:
    try:
        e = json.loads(payload)
        return RoadError(e.get("code", "unknown"), e.get("message", ""), e.get("field"), e)
    except (ValueError, AttributeError):
        return RoadError("unreadable", payload[:200].decode("utf-8", "replace"))


class Client:
    """A session to a road server, announced by a liveliness token (while it lives, the server
    keeps the client's scenes)."""

    def __init__(self, session: zenoh.Session, client_id: str, prefix: str = DEFAULT_PREFIX,
                 timeout_s: float = 60.0):
        self.session = session
        self.client_id = client_id
        self.prefix = prefix.strip("/")
        self.timeout_s = timeout_s
        self._token = session.liveliness().declare_token(f"{self.prefix}/alive/client/{client_id}")

    @classmethod
    def open(cls, connect: Optional[list[str]] = None, listen: Optional[list[str]] = None,
             client_id: str = "python-ego", prefix: str = DEFAULT_PREFIX,
             multicast_scouting: bool = False, config_file: Optional[str] = None,
             timeout_s: float = 60.0) -> "Client":
        """Opens a zenoh session (peer mode) from a json5 config file and/or endpoints."""
        conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(connect))
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        if not multicast_scouting:
            conf.insert_json5("scouting/multicast/enabled", "false")
        return cls(zenoh.open(conf), client_id, prefix, timeout_s)

    def _query(self, key: str, payload: bytes) -> dict:
        replies = self.session.get(key, payload=payload, timeout=self.timeout_s)
        for reply in replies:
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
            raise _error(reply.err.payload.to_bytes())
        raise RoadError("timeout", f"no reply on {key} within {self.timeout_s} s")

    def create_scene(self, map: dict, agents: Optional[list[AgentInit]] = None,
                     external: Optional[list[int]] = None, planner: Optional[str] = None,
                     checkpoint: Optional[str] = None, seed: int = 0,
                     max_ticks: Optional[int] = None) -> "Scene":
        """Creates a scene. ``map`` is ``{"procedural": "roundabout"}``, ``{"osm": text}`` or
        ``{"file": name}``; ``agents`` may be omitted on a procedural map (its own vehicles)."""
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
        created = _created(self._query(f"{self.prefix}/scenes/create",
                                       json.dumps(request).encode()))
        return Scene(self, created)

    def status(self) -> dict:
        return self._query(f"{self.prefix}/status", b"")

    def close_scene(self, scene: int) -> SceneClosed:
        reply = self._query(f"{self.prefix}/scenes/close",
                            json.dumps({"scene": scene, "client": self.client_id}).encode())
        return SceneClosed(**reply)

    def close(self) -> None:
        self._token.undeclare()
        self.session.close()


class Scene:
    """A live scene: put the ego's poses, read the NPCs."""

    def __init__(self, client: Client, created: SceneCreated):
        self.client = client
        self.created = created
        self.last: Optional[NpcTick] = None
        self._npc = client.session.declare_subscriber(created.npc_key)
        self._errors = client.session.declare_subscriber(created.error_key)

    @property
    def id(self) -> int:
        return self.created.scene

    def put(self, tick: int, agents: list[AgentState]) -> None:
        msg = {"tick": tick, "agents": [asdict(a) for a in agents],
               "client": self.client.client_id}
        self.client.session.put(self.created.ego_key, json.dumps(msg).encode())

    def wait_tick(self, tick: int) -> NpcTick:
        """Waits for the NPCs of ``tick``; raises the server's error for this scene."""
        deadline = time.monotonic() + self.client.timeout_s
        while True:
            err = self._errors.try_recv()
            if err is not None:
                raise _error(err.payload.to_bytes())
            sample = self._npc.try_recv()
            if sample is not None:
                npc = _npc_tick(json.loads(sample.payload.to_bytes()))
                self.last = npc
                if npc.tick >= tick:
                    return npc
                continue
            if time.monotonic() > deadline:
                raise RoadError("timeout", f"no NPCs for tick {tick} of scene {self.id}")
            time.sleep(0.001)

    def step(self, tick: int, agents: list[AgentState]) -> NpcTick:
        """Puts the external agents' poses for ``tick`` and waits for that tick's NPCs."""
        self.put(tick, agents)
        return self.wait_tick(tick)

    def close(self) -> SceneClosed:
        self._npc.undeclare()
        self._errors.undeclare()
        return self.client.close_scene(self.id)
