"""Reaching a running app from non-real-time code: by app name, then by port name.

    from rtloop.ipc.ports import connect_app
    app = connect_app("jiwy")
    app.write("setpoint", [0.5, 0.3])          # validated here; the task never sees a bad value
    ticks, rows = app.read("log")              # every tick since the last read (one reader at a time)

A running supervisor describes its ports in a registry file next to its shared memory;
``rtloop port write/read/list`` are thin wrappers over this module.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.errors import PortValueError, RtloopError
from rtloop.ipc.channels import LatestValue, SampleQueue
from rtloop.ipc.segments import SHM_DIR, Segment, pid_alive
from rtloop.ipc.status import STATUS_WORDS, WordBlock


class AppNotRunning(RtloopError, LookupError):
    """No running app of that name was found."""


@dataclass(frozen=True)
class RunningApp:
    """A live app found through its registry file."""

    name: str
    pid: int
    registry: dict[str, Any]
    path: Path

    @property
    def ports(self) -> dict[str, dict[str, Any]]:
        return self.registry["ports"]

    def _port(self, name: str, direction: str) -> dict[str, Any]:
        info = self.ports.get(name)
        if info is None:
            raise PortValueError(f"app {self.name!r} has no port {name!r}; its ports are {sorted(self.ports)}")
        if info["direction"] != direction:
            verb = "written" if direction == "in" else "read"
            raise PortValueError(f"port {name!r} of app {self.name!r} goes {info['direction']}; it cannot be {verb}")
        return info

    def write(self, port: str, values: list[float] | np.ndarray) -> None:
        """Post values to an input port; rejects wrong lengths and NaN/inf (unless allowed)."""
        info = self._port(port, "in")
        array = validate_values(values, info["size"], allow_nonfinite=info["allow_nonfinite"],
                                where=f"port {port!r} ({info['signal']})")
        segment = Segment.attach(info["segment"])
        channel = LatestValue(segment)
        if channel.fed_by_profile:
            raise PortValueError(f"port {port!r} is fed from a profile in this run; live writes are refused")
        with open(segment.path, "rb") as lock:  # writers serialise; the RT reader never waits
            fcntl.flock(lock, fcntl.LOCK_EX)
            channel.write(array)

    def reader(self, port: str) -> PortReader:
        """The single reader of an output port (held until closed)."""
        return PortReader(self, port, self._port(port, "out"))

    def alive(self) -> bool:
        """Whether the app's supervisor is still running."""
        return pid_alive(self.pid) and self.path.exists()

    def task_pids(self) -> dict[str, int]:
        """PID of each task process (0 until it has started)."""
        pids: dict[str, int] = {}
        for task, segment_name in self.registry["tasks"].items():
            segment = Segment.attach(segment_name)
            pids[task] = WordBlock(segment, 0, STATUS_WORDS)[1]
        return pids


class PortReader:
    """Reads every tick an output port sends. One reader per port at a time (flock)."""

    def __init__(self, app: RunningApp, name: str, info: dict[str, Any]) -> None:
        self.name = name
        self.segment = Segment.attach(info["segment"])
        self._lock = open(self.segment.path, "rb")  # noqa: SIM115
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock.close()
            raise PortValueError(f"port {name!r} of app {app.name!r} already has a reader") from None
        self.queue = SampleQueue(self.segment)
        self.period_ns = int(info["period_ns"])

    def read(self, max_rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(ticks, rows) sent since the last read; never blocks."""
        return self.queue.drain(max_rows)

    def close(self) -> None:
        self._lock.close()

    def __enter__(self) -> PortReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def validate_values(values: Any, size: int, *, allow_nonfinite: bool = False, where: str = "value") -> np.ndarray:
    """Check a value for a port: right length, numbers, finite unless allowed."""
    try:
        array = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise PortValueError(f"{where}: {values!r} are not numbers") from None
    if array.size != size:
        raise PortValueError(f"{where}: takes {size} values, got {array.size}")
    if not allow_nonfinite and not np.all(np.isfinite(array)):
        bad = [i for i, v in enumerate(array) if not math.isfinite(v)]
        raise PortValueError(f"{where}: NaN or infinite value at index {bad} of {array.tolist()}")
    return array


def app_from_registry(path: Path) -> RunningApp:
    """The app described by one registry file."""
    registry = json.loads(path.read_text())
    return RunningApp(registry["app"], int(registry["pid"]), registry, path)


def running_apps(shm_dir: Path = SHM_DIR) -> list[RunningApp]:
    """Every app whose supervisor is alive, newest first."""
    found: list[RunningApp] = []
    for path in shm_dir.glob("rtloop-*-registry.json"):
        try:
            app = app_from_registry(path)
        except (OSError, ValueError, KeyError, TypeError):
            continue  # being written or removed right now, or not ours
        if pid_alive(app.pid):
            found.append(app)
    found.sort(key=lambda app: app.path.stat().st_mtime if app.path.exists() else 0, reverse=True)
    return found


def connect_app(name: str, timeout_s: float = 0.0) -> RunningApp:
    """The running app called ``name`` (an app file's path works too); waits up to ``timeout_s``."""
    if name.endswith(".toml") and os.path.exists(name):
        import tomllib

        name = tomllib.loads(Path(name).read_text()).get("name", name)
    deadline = time.monotonic() + timeout_s
    while True:
        matches = [app for app in running_apps() if app.name == name]
        if matches:
            return matches[0]
        if time.monotonic() >= deadline:
            running = sorted({app.name for app in running_apps()})
            raise AppNotRunning(f"no running app named {name!r}; running: {running or 'none'}")
        time.sleep(0.05)
