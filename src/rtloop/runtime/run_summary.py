"""The run summary, made in one place for ``run``, ``simulate`` and ``replay``.

Each driver knows a few facts of its own about a task (the real-time settings its process
applied, or that it was simulated; what a step cost on the host; the process's memory); the
rest comes from the same shared memory and the same recording in every mode. :func:`build_summary`
turns both into :class:`~rtloop.record.summary.RunSummary`, so a simulation's summary.json and a
run's cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from dataclasses import dataclass, field
from typing import Any

from rtloop.ipc.hotpath import hot_path
from rtloop.ipc.status import StatusWord
from rtloop.ipc.wiring import nonfinite_fields
from rtloop.linux import rt
from rtloop.record.summary import (
    PortSummary,
    RunSummary,
    TaskSummary,
    limit_notes,
    nonfinite_notes,
    not_real_time_notes,
    signal_names,
    slow_step_notes,
    stale_device_notes,
)
from rtloop.runtime.layout import AppLayout
from rtloop.runtime.session import RunSession

SIMULATED_REASON = "offline simulation: logical time, no real-time scheduling"


@dataclass
class TaskFacts:
    """What a driver knows of one task beyond its shared memory and its recording."""

    settings: rt.AppliedSettings | None = None
    """The real-time settings its process applied (None: it never got that far, or ``simulated``)."""
    simulated: bool = False
    """Run by the simulator: logical time, no scheduling."""
    host_exec_ns: dict[str, float] | None = None
    """Simulation: what its steps cost on the host."""
    resident_bytes: dict[str, int] | None = None
    """Run: the task process's resident memory at the supervisor's samples."""
    locked_bytes: int | None = None
    """Run: the memory its process holds locked, measured by itself before T0 (linux/memory.locked_bytes)."""
    input_limits: dict[str, Any] | None = None
    """How often the guards of its connections acted."""


@dataclass
class RunFacts:
    """What a driver knows of the whole run."""

    mode: str
    started_wall_ns: int
    duration_s: float | None
    stopped_by: str
    failure: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    """The driver's own notes (device problems, a bridge's), said after the recording's."""
    more_notes: list[str] = field(default_factory=list)
    """Notes said last (the memory watch's)."""
    devices: dict[str, Any] = field(default_factory=dict)
    bridges: dict[str, Any] = field(default_factory=dict)
    machine: dict[str, Any] = field(default_factory=dict)
    misses: dict[str, Any] = field(default_factory=dict)


def task_summary(session: RunSession, name: str, facts: TaskFacts) -> TaskSummary:
    """One task's summary from its status words, its recorded timing and the driver's facts."""
    app, layout, recorder = session.app, session.layout, session.recorder
    spec, handles = app.tasks[name], layout.tasks[name]
    status = handles.status
    timing = recorder.timing_of(name)
    if spec.config.overrun == "skip" and not facts.simulated:
        # The task's own count of the releases it skipped is the true one: timing.csv's gaps miss
        # those after its last cycle (an overrun running into the run's end) and count lost records
        # as if they were skips.
        timing = dataclasses.replace(timing, overruns=status[StatusWord.OVERRUNS])
    settings = facts.settings
    if facts.simulated:
        policy, reason, cpu = "simulated", SIMULATED_REASON, None
    elif settings is None:
        policy, reason, cpu = "not started", "the task never started", spec.config.cpu
    else:
        policy, reason, cpu = settings.policy, "; ".join(settings.reasons), spec.config.cpu
    return TaskSummary(
        period_ns=spec.config.period_ns,
        priority=settings.priority if settings else 0,
        cpu=cpu,
        policy=policy,
        rt=settings.rt if settings else False,
        rt_reason=reason,
        memory_locked=settings.memory_locked if settings else False,
        timing=timing,
        stale_reads=status[StatusWord.STALE_READS],
        misses_in_a_row_max=status[StatusWord.MISSES_IN_A_ROW_MAX],
        timing_samples_dropped=handles.timing.dropped,
        host_exec_ns=facts.host_exec_ns,
        **signal_names(spec.runnable),
        **nonfinite_fields(status, handles.plan),
        resident_bytes=facts.resident_bytes,
        locked_bytes=facts.locked_bytes,
        input_limits=facts.input_limits,
    )


def build_summary(session: RunSession, tasks: dict[str, TaskFacts], run: RunFacts, *, running: bool) -> RunSummary:
    """The run's summary (``running``: the progress one, rewritten while it goes on)."""
    app, layout, recorder = session.app, session.layout, session.recorder
    summaries = {name: task_summary(session, name, tasks.get(name, TaskFacts())) for name in app.tasks}
    requested = {name: spec.config.policy for name, spec in app.tasks.items()  # what a simulation never is
                 if not tasks.get(name, TaskFacts()).simulated}
    capabilities = rt.probe()
    return RunSummary(
        app=app.name,
        mode=run.mode,
        hot_path=hot_path(),
        started=dt.datetime.fromtimestamp(run.started_wall_ns / 1e9, tz=dt.UTC).isoformat(timespec="milliseconds"),
        duration_s=run.duration_s,
        rt_capable=capabilities.may_use_rt,
        tasks=summaries,
        ports=port_summaries(layout, recorder.latest_ns),
        stopped_by="running" if running else run.stopped_by,
        failure=run.failure,
        machine={**machine_facts(capabilities), **run.machine},
        notes=[*not_real_time_notes(summaries, requested), *slow_step_notes(summaries), *session.notes(*run.notes),
               *nonfinite_notes(summaries), *stale_device_notes(run.devices), *limit_notes(summaries, run.devices),
               *run.more_notes],
        devices=run.devices,
        bridges=run.bridges,
        elapsed_s=recorder.latest_ns / 1e9,
        running=running,
        recording={**recorder.to_json(), **session.losses.to_json()},
        switches=recorder.switches.to_json(),
        misses=run.misses,
    )


def port_summaries(layout: AppLayout, last_release_ns: int = 0) -> dict[str, PortSummary]:
    """Traffic of every port; what a profile delivered counts its rows up to ``last_release_ns`` (since T0)."""
    ports: dict[str, PortSummary] = {}
    for name, spec in layout.app.ports.items():
        if spec.direction == "in":
            value = layout.input_ports[name]
            ports[name] = PortSummary("in", str(spec.signal), value.writes, value.reads,
                                      max(0, value.writes - value.reads), _feed_summary(layout, name, last_release_ns))
        else:
            queue = layout.output_ports[name]
            ports[name] = PortSummary("out", str(spec.signal), queue.sent + queue.dropped,
                                      queue.received, queue.dropped)
    return ports


def _feed_summary(layout: AppLayout, port: str, last_release_ns: int) -> dict[str, Any] | None:
    """What a port's profile delivered: its rows whose time came by the last release recorded."""
    spec = layout.app.ports[port]
    link = next((link for link in layout.tasks[spec.signal.task].plan.input_ports if link.name == port), None)
    if spec.feed is None or link is None or link.profile is None:
        return None
    delivered = sum(1 for t_ns in link.profile.t_ns if t_ns <= last_release_ns)
    return {"file": str(spec.feed), "rows": len(link.profile.t_ns), "rows_delivered": delivered,
            "nudge": link.nudge}


def machine_facts(capabilities: rt.Capabilities) -> dict[str, Any]:
    return {
        "kernel": capabilities.kernel,
        "preemption": capabilities.preemption_model,
        "cpus": list(capabilities.cpus),
        "isolated_cpus": list(capabilities.isolated_cpus),
        "rt_permission": capabilities.rt_reason,
    }
