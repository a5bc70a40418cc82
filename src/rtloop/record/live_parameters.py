"""Live parameters served to Foxglove and Lichtblick: the protocol's ``parameters`` capability.

A runnable's live parameters (``parameters = {"kp": 0.05}``) are inputs of its task; an input
port feeding them makes them writable while the app runs. Those whose port is listed in the
live view's ``inputs`` are served here by the name ``task.parameter``: ``getParameters`` reads
the port's value now (the shared memory the task reads, without touching its counters), and
``setParameters`` writes the whole port with the new value in its place, through
:meth:`RunningApp.write` — the checks of every port write (a number, finite, the port's
``range``) — so the task takes it at a release, logs it in inputs.csv, and a replay repeats it.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.errors import PortValueError, RtloopError
from rtloop.ipc.channels import LatestValue
from rtloop.ipc.ports import RunningApp
from rtloop.ipc.schema import PortWord
from rtloop.ipc.segments import Segment, fence

READ_TRIES = 100


class LiveParameters:
    """The live parameters a live view serves: ``task.name`` → (port, place in the port)."""

    def __init__(self, app: App, ports: tuple[str, ...] | list[str]) -> None:
        self.served: dict[str, tuple[str, int]] = {}
        for port_name in ports:
            port = app.ports.get(port_name)
            if port is None or port.direction != "in" or port.feed is not None:
                continue
            runnable = app.tasks[port.signal.task].runnable
            base = runnable.__dict__.get("_parameter_base")
            if base is None:
                continue
            names = list(runnable.parameters)
            for index in range(port.signal.start, port.signal.stop):
                if base <= index < base + len(names):
                    self.served[f"{port.signal.task}.{names[index - base]}"] = (port_name, index - port.signal.start)
        self.running: RunningApp | None = None
        self.channels: dict[str, tuple[Segment, LatestValue]] = {}
        self.lock = threading.Lock()  # the server calls back on threads of its own
        self.set_count = self.refused = 0
        self.warn: Any = None
        self.server: Any = None
        """The Foxglove server, once started: a refusal is also a status message to its clients."""

    def attach(self, running: RunningApp, warner: Any) -> None:
        self.running, self.warn = running, warner.warn
        for port in {port for port, _ in self.served.values()}:
            segment = running.segment(running.ports[port]["segment"])
            self.channels[port] = (segment, LatestValue(segment))

    def _values(self, port: str) -> np.ndarray:
        """The port's value now (seqlock read; the task's read counter is the task's alone)."""
        channel = self.channels[port][1]
        words = channel.words
        for _ in range(READ_TRIES):
            seq = words[PortWord.SEQ]
            if seq & 1:
                continue
            fence()
            values = np.array(channel.values, dtype=np.float64)
            fence()
            if words[PortWord.SEQ] == seq:
                return values
        raise PortValueError(f"port {port!r} changed on every read")

    def _parameter(self, name: str) -> Any:
        from foxglove.websocket import Parameter

        port, place = self.served[name]
        return Parameter(name, value=float(self._values(port)[place]))

    def get(self, names: list[str]) -> list[Any]:
        """The values of ``names`` (every served parameter when none is named); unknown names are left out."""
        with self.lock:
            return [self._parameter(name) for name in (names or sorted(self.served)) if name in self.served]

    def set(self, parameters: list[Any]) -> list[Any]:
        """Write each parameter's port; answer every parameter asked for with the value in force after it."""
        asked: list[str] = []
        running = self.running
        if running is None:  # not attached yet: nothing can be written
            return []
        with self.lock:
            for parameter in parameters:
                name = parameter.name
                if name not in self.served:
                    self._refuse(f"{name!r} is not a live parameter served here; served: {sorted(self.served)}")
                    continue
                asked.append(name)
                value = parameter.get_value() if parameter.value is not None else None
                if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                    self._refuse(f"parameter {name}: {value!r} is not a finite number; left as it was")
                    continue
                port, place = self.served[name]
                values = self._values(port)
                values[place] = float(value)
                try:
                    running.write(port, values)
                    self.set_count += 1
                except (PortValueError, RtloopError) as error:
                    self._refuse(f"parameter {name}: {error}; left as it was")
            return [self._parameter(name) for name in asked]

    def _refuse(self, text: str) -> None:
        self.refused += 1
        if self.warn is not None:
            self.warn(text, key="parameter")
        if self.server is not None:
            from foxglove.websocket import StatusLevel

            self.server.publish_status(text, StatusLevel.Warning)

    def counts(self) -> dict[str, Any]:
        """What summary.json says of them (under ``bridges.foxglove``)."""
        return {"parameters": sorted(self.served), "parameters_set": self.set_count,
                "parameters_refused": self.refused}

    def close(self) -> None:
        for segment, _channel in self.channels.values():
            segment.close()
        self.channels.clear()
