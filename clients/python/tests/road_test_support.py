"""What the client tests share: the repository, the ``road`` binary under test, a free port, a
server started and answering."""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path
from typing import IO

import pytest

from road_client import Client

REPO = Path(__file__).resolve().parents[3]


def road_bin() -> str:
    """``$ROAD_BIN`` (``scripts/test.sh`` builds it), else ``target/debug/road``."""
    path = os.environ.get("ROAD_BIN") or str(REPO / "target" / "debug" / "road")
    if not Path(path).is_file():
        pytest.fail(f"no road binary at {path}: build it (cargo build -p road-cli) or set ROAD_BIN")
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(record: Path, client_id: str, log: IO[str]) -> tuple[subprocess.Popen, Client]:
    """``road serve`` on a free loopback port recording into ``record``, its log to ``log`` (a
    pipe nobody reads would fill and stall it), and a client ``client_id`` connected once the
    server answers its status (with a 120 s timeout: a debug server's first tick is slow). The
    caller closes the client and stops the process."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(
        [road_bin(), "serve", "--listen", endpoint, "--no-multicast-scouting",
         "--models", str(REPO / "models"), "--record", str(record), "--late-ego-ms", "0"],
        stderr=log, text=True)
    deadline = time.monotonic() + 120
    while True:
        if proc.poll() is not None:
            log.seek(0)
            pytest.fail(f"road serve exited with {proc.returncode}: {log.read()}")
        client = None
        try:
            client = Client.open(connect=[endpoint], client_id=client_id, timeout_s=5.0)
            client.status()
            client.timeout_s = 120.0
            return proc, client
        except Exception:
            if client is not None:
                client.close()
            if time.monotonic() > deadline:
                proc.kill()
                raise
            time.sleep(0.5)
