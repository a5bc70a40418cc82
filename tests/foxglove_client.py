"""A run with a Foxglove live view, and a client's side of the Foxglove WebSocket protocol spoken by
hand with the ``websockets`` package (JSON ops; binary frames ``0x01 | u32 id | u64 log time | data``).

For the tests that watch or steer a run as Foxglove does (test_foxglove_live.py,
test_foxglove_parameters.py); they skip first where foxglove-sdk or websockets is missing.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest


def url_from(stderr_lines: queue.Queue[str], timeout_s: float) -> str:
    """The live view's URL, from the line ``rtloop run`` prints on stderr when its server is up."""
    deadline = time.monotonic() + timeout_s
    seen = []
    while time.monotonic() < deadline:
        try:
            line = stderr_lines.get(timeout=0.2)
        except queue.Empty:
            continue
        seen.append(line)
        if "Foxglove live view on " in line:
            return line.split("Foxglove live view on ", 1)[1].split()[0]
    pytest.fail(f"no live view URL printed within {timeout_s} s: {seen}")


@contextlib.contextmanager
def run_with_live_view(app_file: Path, out: Path, duration_s: float,
                       env: dict[str, str]) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``rtloop run APP --duration D --out OUT --quiet`` and its live view's URL. Leaving the block
    ends a run still going the way Ctrl-C does (killed if it takes over 60 s) and reaps it; the
    caller then asserts its return code. So D is a bound, not the test's time: a run's start (a
    Python that imports the live view's server) takes seconds of it on a loaded machine."""
    run = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", str(duration_s),
                            "--out", str(out), "--quiet"], env=env, stderr=subprocess.PIPE, text=True)
    assert run.stderr is not None
    stderr = run.stderr
    lines: queue.Queue[str] = queue.Queue()
    pump = threading.Thread(target=lambda: [lines.put(line) for line in stderr], daemon=True)
    pump.start()
    try:
        yield run, url_from(lines, 60)
    finally:
        if run.poll() is None:  # the test has seen what it came for
            run.send_signal(signal.SIGINT)
        try:
            run.wait(timeout=60)
        except subprocess.TimeoutExpired:
            run.kill()
            run.wait()
        pump.join(10)
        stderr.close()


def connect(url: str, subprotocol: str = "foxglove.websocket.v1") -> Any:
    """A client connection (a context manager) offering ``subprotocol``."""
    from websockets.sync.client import connect as websocket_connect

    # close_timeout: the server leaves the client's close frame unanswered while the run goes on
    # (websockets waits 10 s by default for the answer before it drops the connection)
    return websocket_connect(url, subprotocols=[subprotocol], open_timeout=20, close_timeout=1)


def handshake(client: Any, topics: set[str], timeout_s: float = 20.0) -> tuple[dict[str, Any], dict[str, int]]:
    """The server's ``serverInfo`` (its first message, as the protocol has it) and the channel id of
    every topic it advertises, once ``topics`` are among them."""
    info = json.loads(client.recv(timeout=timeout_s))
    assert info["op"] == "serverInfo", info
    channels: dict[str, int] = {}
    deadline = time.monotonic() + timeout_s
    while not topics <= channels.keys() and time.monotonic() < deadline:
        message = client.recv(timeout=timeout_s)
        if isinstance(message, str) and (op := json.loads(message))["op"] == "advertise":
            channels.update({channel["topic"]: channel["id"] for channel in op["channels"]})
    assert topics <= channels.keys(), channels
    return info, channels


def subscribe(client: Any, subscriptions: dict[int, int]) -> None:
    """Subscribe: subscription id → channel id; the channel's messages then come with the subscription's id."""
    client.send(json.dumps({"op": "subscribe", "subscriptions": [
        {"id": subscription, "channelId": channel} for subscription, channel in subscriptions.items()]}))
