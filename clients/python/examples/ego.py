#!/usr/bin/env python3
"""A scripted ego client of ``road serve`` in Python, the counterpart of ``road ego``: it creates
scenes on a procedural map (on one server with ``--prefix``, or each on the least-loaded server
found under a root with ``--discover``), drives external agent 1 of every scene by holding its
history's last velocity (a log-replay ego: it does not yield), prints every tick's round trip,
then a summary per server, closes the scenes and prints where each was recorded.

Every tick of every scene is answered, or the run fails: exit status 1 with a line on stderr
naming the scene and its server. A deployment's smoke test (two servers behind a router)::

    python clients/python/examples/ego.py --connect tcp/router:7447 --discover road --scenes 4

Each scene has its own client id (``<client>-<i>``) and liveliness token on one shared zenoh
session; the scenes are driven side by side, each putting its next tick as soon as its last one
is answered, so that a slower server never makes another server's scenes late.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from typing import Optional

from road_client import AgentState, Client, RoadError, Scene, discover, open_session

EGO = 1
STEP_S = 0.1


@dataclass
class Driven:
    """One scene of the run, the client that keeps it (its liveliness token) and its ticks."""

    index: int
    client: Client
    scene: Scene
    start: AgentState
    velocity: tuple[float, float]
    tick: int = 0
    sent_at: float = 0.0
    rtt_ms: list[float] = field(default_factory=list)
    late: int = 0
    infractions: int = 0

    @property
    def server(self) -> str:
        return self.client.prefix

    def what(self) -> str:
        return f"scene {self.index} (id {self.scene.id}) on {self.server}"

    def pose(self, tick: int) -> AgentState:
        """The ego at ``tick``: its last observed pose moved on at its last velocity."""
        vx, vy = self.velocity
        return AgentState(EGO, self.start.x_m + vx * tick, self.start.y_m + vy * tick,
                          self.start.heading_rad)

    def send(self, tick: int) -> None:
        self.tick = tick
        self.sent_at = time.monotonic()
        self.scene.put(tick, [self.pose(tick)])


class Failure(Exception):
    """A scene failed: the message names it and its server."""


def percentile(sample: list[float], q: float) -> str:
    """Nearest rank, as the server's status computes its percentiles, in ms ("-" for none)."""
    if not sample:
        return "-"
    ordered = sorted(sample)
    rank = min(max(math.ceil(q * len(ordered)), 1), len(ordered))
    return f"{ordered[rank - 1]:.1f}"


def wait_for_servers(session, args) -> None:
    """Waits up to ``--wait-s`` for the servers to announce themselves (liveliness tokens): a
    deployment starts the ego beside its servers, which take a moment to come up."""
    deadline = time.monotonic() + max(args.wait_s, 0.0)
    while True:
        if args.discover is not None:
            servers, unreachable = discover(session, args.discover,
                                            min(args.timeout_s, 5.0))
            if len(servers) >= args.min_servers:
                return
            seen = ", ".join(s.prefix for s in servers) or "none"
            why = "".join(f"; {p} did not answer its status: {e}" for p, e in unreachable)
            problem = (f"{len(servers)} server(s) under {args.discover} ({seen}), "
                       f"{args.min_servers} wanted{why}")
        else:
            replies = session.liveliness().get(f"{args.prefix}/alive/server",
                                               timeout=min(args.timeout_s, 5.0))
            if any(r.ok is not None for r in replies):
                return
            problem = f"no server at {args.prefix} (no liveliness token {args.prefix}/alive/server)"
        if time.monotonic() >= deadline:
            raise Failure(f"{problem} after waiting {args.wait_s} s")
        time.sleep(0.25)


def create(session, args, i: int) -> Driven:
    client_id = f"{args.client}-{i}"
    map_ = {"procedural": args.map}
    # max_ticks: once its last tick is answered the scene waits for its close. Without it, the
    # server's late-ego policy would drive another tick when the close comes a second late
    # (scenes are closed one after another, after every scene's last tick).
    scene_args = {"external": [EGO], "seed": args.seed + i, "max_ticks": args.ticks}
    try:
        if args.discover is not None:
            client, scene = Client.create_on_least_loaded(
                session, args.discover, client_id, map_, timeout_s=args.timeout_s, **scene_args)
        else:
            client = Client(session, client_id, args.prefix, args.timeout_s, owns_session=False)
            try:
                scene = client.create_scene(map_, **scene_args)
            except BaseException:
                client.close()
                raise
    except RoadError as e:
        where = f"under {args.discover}" if args.discover is not None else f"on {args.prefix}"
        raise Failure(f"scene {i}: creation {where} failed: {e}") from e
    ego = next((a for a in scene.created.agents if a.id == EGO), None)
    if ego is None or len(ego.history) < 2:
        raise Failure(f"scene {i} (id {scene.id}) on {client.prefix}: no agent {EGO} with a "
                      f"history of two poses in the reply")
    last, previous = ego.history[-1], ego.history[-2]
    d = Driven(i, client, scene, AgentState(EGO, last.x_m, last.y_m, last.heading_rad),
               (last.x_m - previous.x_m, last.y_m - previous.y_m))
    print(f"scene {i}: id {scene.id} on {d.server} ({len(scene.created.agents)} agents, "
          f"ego {EGO} scripted)", flush=True)
    return d


def drive(driven: list[Driven], args) -> None:
    """Runs every scene to ``--ticks``, each putting its next tick as soon as its last came."""
    for d in driven:
        d.send(1)
    running = list(driven)
    while running:
        progressed = False
        for d in list(running):
            try:
                npc = d.scene.poll(d.tick)
            except RoadError as e:
                raise Failure(f"tick {d.tick}: {d.what()}: {e}") from e
            now = time.monotonic()
            if npc is None:
                if now - d.sent_at > args.timeout_s:
                    raise Failure(f"tick {d.tick}: {d.what()}: no NPCs within "
                                  f"{args.timeout_s} s")
                continue
            if npc.tick != d.tick:
                raise Failure(f"tick {d.tick}: {d.what()}: the server answered tick {npc.tick}")
            progressed = True
            d.rtt_ms.append((now - d.sent_at) * 1e3)
            d.late += bool(npc.late_external)
            d.infractions += len(npc.collisions) + len(npc.off_road)
            if not args.quiet:
                print(f"tick {d.tick:>4} ({d.tick * STEP_S:5.1f} s) scene {d.index} on "
                      f"{d.server}: round trip {d.rtt_ms[-1]:7.1f} ms, engine "
                      f"{npc.compute_ms:6.1f} ms, {len(npc.collisions)} collision(s), "
                      f"{len(npc.off_road)} off road" + (", late" if npc.late_external else ""),
                      flush=True)
            if d.tick == args.ticks:
                running.remove(d)
            else:
                d.send(d.tick + 1)
        if not progressed:
            time.sleep(0.001)


def summary(driven: list[Driven]) -> None:
    by_server: dict[str, list[Driven]] = {}
    for d in driven:
        by_server.setdefault(d.server, []).append(d)
    for server in sorted(by_server):
        scenes = by_server[server]
        answered = sum(len(d.rtt_ms) for d in scenes)
        # A scene's first tick holds the planner's warm-up: the percentiles leave it out.
        rtt = [ms for d in scenes for ms in d.rtt_ms[1:]]
        late = sum(d.late for d in scenes)
        print(f"{server}: {len(scenes)} scene(s), {answered} tick(s) answered, round trip "
              f"p50 {percentile(rtt, 0.5)} ms, p99 {percentile(rtt, 0.99)} ms "
              f"(ticks after the first); late {late}", flush=True)
    infractions = sum(d.infractions for d in driven)
    print(f"infractions (collisions and off-road agents, summed over ticks): {infractions}",
          flush=True)


def parse_args(argv: Optional[list[str]]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                        help="a zenoh endpoint to connect to (tcp/127.0.0.1:7447); repeatable")
    parser.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                        help="a zenoh endpoint to listen on; repeatable")
    parser.add_argument("-m", "--mode", choices=["peer", "client"], default=None,
                        help="zenoh mode (default: zenoh's, peer)")
    parser.add_argument("-c", "--config", help="a zenoh json5 config file")
    parser.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                        help="a zenoh config override, VALUE in json5 "
                             "('transport/auth/usrpwd/user:\"ego\"'); repeatable")
    parser.add_argument("--multicast-scouting", action="store_true",
                        help="turn zenoh's multicast scouting on (off by default)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--discover", metavar="ROOT",
                       help="find the servers under ROOT (road finds road and road/east) and "
                            "put each scene on the least-loaded one")
    where.add_argument("--prefix", default="road",
                       help="the one server's key prefix, without --discover (default road)")
    parser.add_argument("--min-servers", type=int, default=1, metavar="N",
                        help="with --discover, wait for N servers before creating (default 1)")
    parser.add_argument("--map", default="roundabout",
                        choices=["roundabout", "intersection", "merge"])
    parser.add_argument("--scenes", type=int, default=1, help="scenes side by side (default 1)")
    parser.add_argument("--ticks", type=int, default=60, help="ticks per scene (default 60)")
    parser.add_argument("--seed", type=int, default=0, help="seed of scene 0 (scene i: +i)")
    parser.add_argument("--client", default="python-ego",
                        help="client id; scene i's client is <client>-<i>")
    parser.add_argument("--timeout-s", type=float, default=120.0,
                        help="seconds a creation or a tick may take (a scene's first tick "
                             "holds the model's warm-up; default 120)")
    parser.add_argument("--wait-s", type=float, default=10.0,
                        help="seconds to wait for the servers to appear (default 10)")
    parser.add_argument("--quiet", action="store_true", help="print the summary only")
    args = parser.parse_args(argv)
    if args.scenes < 1:
        parser.error("--scenes must be at least 1")
    if args.ticks < 1:
        parser.error("--ticks must be at least 1")
    for item in args.cfg:
        if ":" not in item:
            parser.error(f"--cfg {item}: expected KEY:VALUE")
    if args.min_servers < 1:
        parser.error("--min-servers must be at least 1")
    if not (math.isfinite(args.timeout_s) and args.timeout_s > 0):
        parser.error(f"--timeout-s must be positive, got {args.timeout_s}")
    return args


def main(argv: Optional[list[str]] = None) -> int:
    args = parse_args(argv)
    try:
        session = open_session(connect=args.connect, listen=args.listen, mode=args.mode,
                               multicast_scouting=args.multicast_scouting,
                               config_file=args.config,
                               overrides=[tuple(item.split(":", 1)) for item in args.cfg])
    except Exception as e:
        print(f"error: cannot open the zenoh session: {e}", file=sys.stderr)
        return 1
    driven: list[Driven] = []
    try:
        wait_for_servers(session, args)
        for i in range(args.scenes):
            driven.append(create(session, args, i))
        try:
            drive(driven, args)
        finally:
            summary(driven)
        for d in driven:
            try:
                closed = d.scene.close()
            except RoadError as e:
                raise Failure(f"closing {d.what()}: {e}") from e
            if closed.ticks != args.ticks:
                raise Failure(f"{d.what()}: closed after {closed.ticks} tick(s), "
                              f"{args.ticks} driven")
            where = f"recorded at {closed.recording}" if closed.recording else "not recorded"
            print(f"scene {d.index}: id {d.scene.id} on {d.server}, {closed.ticks} ticks, "
                  f"{where}", flush=True)
        return 0
    except Failure as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        return 1
    finally:
        # The clients' tokens go with them: the server closes any scene still open.
        for d in driven:
            d.client.close()
        session.close()


if __name__ == "__main__":
    sys.exit(main())
