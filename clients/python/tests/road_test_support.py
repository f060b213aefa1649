"""What the client tests share: the repository, the ``road`` binary under test, a free port."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

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
