"""What the task processes tell the supervisor through their pipes, read and kept for the summary.

Each task process sends a dict per event (``runtime/task.py:_report``) through a one-way pipe:
the settings it applied, the memory it locked, a device refused at configure, its devices'
reads and problems, its guards' counts, a late cycle's counters, notes, a stop it asked for
(``finished``) and its failure. :class:`TaskReports` reads them and keeps what the summary
needs; what a failure or a stop request does to the run is the supervisor's to decide (it
stops every task at a failure message at once, not when the process exits).
"""

from __future__ import annotations

from typing import Any

from rtloop.app.builder import App
from rtloop.errors import DeviceError, DeviceMismatch, DeviceNotReady, TaskFailed
from rtloop.runtime.evidence import MissWatch
from rtloop.runtime.task_watch import TaskProcess
from rtloop.runtime.taskrun import postrun_failed_note


class TaskReports:
    """What every task process reported, gathered from their pipes."""

    def __init__(self, misses: MissWatch, notes: list[str]) -> None:
        self.misses = misses
        """The late cycles' counters go to the miss causes (runtime/evidence.py)."""
        self.notes = notes
        """The run's notes (summary.json ``notes``), which the tasks' notes and device problems join."""
        self.refused: DeviceError | None = None
        """A device that failed its configure (bad input: the run ends with exit 2)."""
        self.device_reads: dict[str, dict[str, Any]] = {}
        """Per device, what its task reported of its reads at the end (stale reads: summary.json ``devices``)."""
        self.input_limits: dict[str, dict[str, dict[str, int]]] = {}
        """Per task with guarded connections: how often each guard acted (reported when the task ends)."""

    def read(self, task_run: TaskProcess) -> TaskFailed | None:
        """Every message waiting in ``task_run``'s pipe, kept; the failure among them (also set on
        ``task_run``), else None. A pipe whose process is gone reads as empty."""
        failure = None
        try:
            while task_run.pipe.poll():
                failure = self._keep(task_run, task_run.pipe.recv()) or failure
        except (EOFError, OSError):
            pass
        return failure

    def _keep(self, task_run: TaskProcess, message: dict[str, Any]) -> TaskFailed | None:
        name, kind = task_run.name, message.get("kind")
        if kind == "settings":
            task_run.settings = message["settings"]
            self.misses.ran_realtime(name, bool(getattr(message["settings"], "rt", False)))
        elif kind == "locked":
            task_run.locked_bytes = message["bytes"]
        elif kind == "finished":
            task_run.stop_request = f"task {name} at cycle {message['cycle']}: {message['reason']}"
            if message.get("edge_ns"):  # an E-stop: when its edge came, when this task's devices were safe
                edge_ns, safe_ns = message["edge_ns"], message.get("safe_ns") or 0
                self.notes.append(
                    f"E-stop: edge at {edge_ns} ns (CLOCK_MONOTONIC, kernel timestamp); task {name}'s "
                    f"devices safe at {safe_ns} ns, {(safe_ns - edge_ns) / 1e3:.0f} µs after the edge")
        elif kind == "device_error":
            found = DeviceMismatch if message.get("mismatch") else DeviceError  # answered, not as declared
            self.refused = DeviceNotReady.of(found(message["device"], message["source"],
                                                   message["key"], message["problem"]))
        elif kind == "device_reads":
            self.device_reads.update({device: {"task": name, **report}
                                      for device, report in message["devices"].items()})
        elif kind == "input_limits":
            self.input_limits[name] = message["inputs"]
        elif kind == "device_problems":
            self.notes.extend(f"task {name}: {problem}" for problem in message["problems"])
        elif kind in ("late", "stopped"):  # counters after a late cycle; a model's extra steps
            self.misses.from_task(name, message)
        elif kind == "note":
            self.notes.append(f"task {name}: {message['text']}")
        elif kind == "postrun_failed":  # after the failure: its postrun raised too
            self.notes.append(postrun_failed_note(name, message["traceback"]))
        elif kind == "failed":
            task_run.failure = TaskFailed(name, message["cycle"], message["phase"], message["reason"],
                                          message["traceback"])
            return task_run.failure
        return None

    def input_limits_of(self, app: App, task: str) -> dict[str, dict[str, int]] | None:
        """How often the guards of ``task``'s connections acted (None: it has no guarded connection)."""
        if not any(c.guarded for c in app.connections if c.target.task == task):
            return None
        return self.input_limits.get(task, {})

