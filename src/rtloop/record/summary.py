"""The run summary: frozen records whose JSON form is ``summary.json``."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rtloop.timing import TaskTiming


@dataclass(frozen=True, slots=True)
class TaskSummary:
    """How one task ran: where, with which scheduling, and how well it kept time."""

    period_ns: int
    """Nominal period."""
    priority: int
    """Real-time priority in force while it ran (0 if not real-time)."""
    cpu: int | None
    """CPU it was pinned to (None: not pinned)."""
    policy: str
    """Scheduling policy in force (fifo, rr, deadline or other)."""
    rt: bool
    """Whether a real-time policy was in force."""
    rt_reason: str
    """Why not real-time, or what could not be applied ('' when everything was)."""
    memory_locked: bool
    """Whether mlockall succeeded."""
    timing: TaskTiming
    """Timing statistics."""
    stale_reads: int
    """Connection reads that found an older value than the tick was entitled to."""
    timing_samples_dropped: int
    """Timing samples lost because the supervisor did not drain fast enough."""
    input_names: tuple[str, ...] | None = None
    """Names of u[0], u[1], ... if the runnable gives them (a model's .info file, say)."""
    output_names: tuple[str, ...] | None = None
    """Names of y[0], y[1], ... if the runnable gives them."""
    host_exec_ns: dict[str, float] | None = None
    """Simulation only: what ``step`` cost on the host (count, mean, max), not real time."""

    def to_json(self) -> dict[str, Any]:
        timing = self.timing.to_json()
        return {
            "period_ns": self.period_ns,
            "priority": self.priority,
            "cpu": self.cpu,
            "policy": self.policy,
            "rt": self.rt,
            "rt_reason": self.rt_reason,
            "memory_locked": self.memory_locked,
            **{k: v for k, v in timing.items() if k != "period_ns"},
            "stale_reads": self.stale_reads,
            "timing_samples_dropped": self.timing_samples_dropped,
            "input_names": list(self.input_names) if self.input_names else None,
            "output_names": list(self.output_names) if self.output_names else None,
            **({"host_exec_ns": self.host_exec_ns} if self.host_exec_ns is not None else {}),
        }


def signal_names(runnable: object) -> dict[str, tuple[str, ...] | None]:
    """``input_names``/``output_names`` of a runnable, as TaskSummary fields (None if absent)."""
    out: dict[str, tuple[str, ...] | None] = {}
    for key in ("input_names", "output_names"):
        names = getattr(runnable, key, None)
        out[key] = tuple(str(n) for n in names) if names else None
    return out


@dataclass(frozen=True, slots=True)
class PortSummary:
    """Traffic through one port."""

    direction: str
    """``in`` (non-RT → task) or ``out`` (task → non-RT)."""
    signal: str
    """The task signal it is attached to."""
    sent: int
    """Values offered: writes by clients (in) or ticks pushed by the task (out)."""
    received: int
    """Values taken: new values read by the task (in) or rows read by a client (out)."""
    dropped: int
    """Values lost: overwritten before the task read them (in) or rejected by a full queue (out)."""

    def to_json(self) -> dict[str, Any]:
        return {"direction": self.direction, "signal": self.signal, "sent": self.sent,
                "received": self.received, "dropped": self.dropped}


@dataclass(frozen=True, slots=True)
class RunSummary:
    """Everything ``summary.json`` says about a run."""

    app: str
    """App name."""
    mode: str
    """``run`` (real time) or ``simulate`` (lock-step, offline)."""
    started: str
    """ISO 8601 wall-clock time of T0."""
    duration_s: float
    """Requested duration."""
    rt_capable: bool
    """Whether the supervisor's probe found real-time scheduling allowed."""
    tasks: dict[str, TaskSummary]
    """Per-task results."""
    ports: dict[str, PortSummary] = field(default_factory=dict)
    """Per-port traffic."""
    stopped_by: str = "duration"
    """``duration``, ``signal`` (Ctrl-C/SIGTERM) or ``fault``."""
    failure: dict[str, Any] | None = None
    """The task failure that stopped the run, if any (task, cycle, phase, reason, traceback)."""
    machine: dict[str, Any] = field(default_factory=dict)
    """Kernel, preemption model, CPUs: what the numbers were measured on."""
    notes: list[str] = field(default_factory=list)
    """Anything the reader should know that has no field of its own."""
    bridges: dict[str, Any] = field(default_factory=dict)
    """ROS 2 bridge processes: state, messages passed, messages rejected (and why)."""
    hot_path: str = ""
    """Where the per-cycle framework work ran: ``c`` (compiled) or ``python`` (the fallback)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "app": self.app,
            "mode": self.mode,
            "started": self.started,
            "duration_s": self.duration_s,
            "rt_capable": self.rt_capable,
            "stopped_by": self.stopped_by,
            "failure": self.failure,
            "machine": self.machine,
            "notes": self.notes,
            "tasks": {name: task.to_json() for name, task in self.tasks.items()},
            "ports": {name: port.to_json() for name, port in self.ports.items()},
            "bridges": self.bridges,
            "hot_path": self.hot_path,
        }

    def write(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")
