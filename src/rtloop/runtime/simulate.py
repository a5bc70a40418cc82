"""Offline simulation: the same app, lock-step in one process, as fast as it can go.

Time here is logical: every task is released at T0 + k·P exactly, and tasks released
at the same instant run one after the other. Because tasks communicate with logical
execution time (an output computed at release t becomes valid at t + P), the order in
which they run within an instant does not matter, and a real-time run that misses no
deadline reproduces this simulation value for value.
"""

from __future__ import annotations

import heapq
import time
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.errors import AppError, DeviceError, StopRequested, TaskFailed
from rtloop.ipc.hotpath import announce_once
from rtloop.ipc.wiring import TaskWiring
from rtloop.record.summary import (
    RunSummary,
)
from rtloop.runtime.layout import READ_LOG_CAPACITY, RECORD_QUEUE_CAPACITY, AppLayout, device_wiring
from rtloop.runtime.run_summary import RunFacts, TaskFacts, build_summary
from rtloop.runtime.session import DEFAULT_LIMITS, Limits, RunSession
from rtloop.runtime.taskrun import TaskRun, postrun_failed_note

SIMULATION_T0_NS = 1_000_000_000  # any positive epoch works; stamps are relative to it


class HostExecution:
    """Streaming count/mean/max of how long ``step`` took on the host (no list that grows)."""

    def __init__(self) -> None:
        self.count, self.total_ns, self.max_ns = 0, 0, 0

    def add(self, exec_ns: int) -> None:
        self.count += 1
        self.total_ns += exec_ns
        self.max_ns = max(self.max_ns, exec_ns)

    def to_json(self) -> dict[str, float]:
        mean = self.total_ns / self.count if self.count else float("nan")
        return {"count": self.count, "mean": mean, "max": float(self.max_ns)}


PortWrites = dict[tuple[str, int], list[tuple[str, list[float]]]]
"""(task, cycle) → the (port, values) a run's task took at that cycle (its inputs.csv)."""


class LetTimeline:
    """The logical timeline: every task runs every release from cycle 0 and reads what LET promises.

    A replay (:mod:`rtloop.runtime.replay`) follows a run's real timeline instead: the cycles
    it ran and skipped, and the older samples its late reads got.
    """

    def start(self, task: Any, layout: AppLayout, t0_ns: int) -> None:
        """Before the first release: ``task`` (a simulated task) publishes its initial outputs at T0."""
        task.wiring.stamp_initial(t0_ns)

    def first_cycle(self, task: str) -> int | None:
        """The first cycle ``task`` runs (None: it runs none)."""
        return 0

    def next_cycle(self, task: str, cycle: int) -> int | None:
        """The cycle ``task`` runs after ``cycle`` (None: no more)."""
        return cycle + 1

    def read_inputs(self, task: str, cycle: int, release_ns: int, io: Any, wiring: TaskWiring) -> None:
        """Read ``task``'s inputs for the release of ``cycle`` into ``wiring.u`` (the hot path's read)."""
        io.read_inputs(release_ns)

    def published(self, task: str, cycle: int, y: np.ndarray) -> None:
        """``task`` published ``y`` as the outputs of ``cycle`` (-1: its initial outputs)."""


def simulate(app: App, duration_s: float, out: str | Path, *, trim: int = 20,
             port_writes: PortWrites | None = None, keep_s: float | None = None,
             timeline: LetTimeline | None = None, force: bool = False, protect: tuple[Path, ...] = (),
             limits: Limits = DEFAULT_LIMITS) -> RunSummary:
    """Run ``app`` lock-step in this process, as fast as possible; same artifacts as :func:`rtloop.run`,
    and as a run does, ``summary.json`` rewritten every ``limits.summary_interval_s`` of wall time
    while it goes on (``"running": true``), so a long simulation shows its progress.

    ``port_writes`` replays what entered a real run from outside: each value is written
    to its port just before the task's release that took it in the run. ``timeline`` says
    which cycles run and what they read (default: :class:`LetTimeline`). A folder that
    already holds a run is refused unless ``force`` is true (as :func:`rtloop.run`);
    ``protect``: folders ``out`` may not be nor be inside (the run a replay reads).
    """
    if duration_s is None:
        raise AppError("a simulation needs a duration (--duration S): logical time cannot be stopped by Ctrl-C")
    for name in app.tasks:  # every device needs a twin: found before anything is written
        device_wiring(app, name, twins=True)
    session = RunSession(app, out, mode="simulate", duration_s=duration_s, keep_s=keep_s, trim=trim, force=force,
                         protect=protect, registry=False, limits=limits,
                         check_disk=timeline is None)  # a replay checks the span it records itself
    announce_once()
    tasks: dict[str, TaskRun] = {}
    outcome = _Outcome()
    with session:
        session.summarise = lambda running: _summary(app, session, duration_s, outcome, tasks, running=running)
        session.before_close.append(lambda: _let_go(tasks))
        _simulate(session, duration_s, port_writes or {}, timeline or LetTimeline(), tasks, outcome)
    if outcome.failure is not None:
        raise outcome.failure
    assert session.summary is not None
    return session.summary


class _Outcome:
    """How the simulation ended: a failure, or what stopped it."""

    def __init__(self) -> None:
        self.failure: TaskFailed | None = None
        self.stopped_by = "duration"
        self.started_ns = time.time_ns()
        """Wall time the simulation started (``started`` in summary.json: its logical T0)."""
        self.host_exec: dict[str, HostExecution] = {}
        """Per task, what its jobs cost on this host (never taken for timing)."""
        self.records: dict[str, list[tuple[int, int, int, int]]] = {}
        """Per task, its timing records since the last drain."""
        self.notes: list[str] = []
        """summary.json notes from the way out (a postrun that failed after the failure)."""


def _let_go(tasks: dict[str, TaskRun]) -> None:
    """Let go of the shared memory before it is removed: the cycle work's hold first, then the
    tasks (their views of the layout), then each task's own mappings."""
    wirings = [task.wiring for task in tasks.values()]
    for task in tasks.values():
        if task.cycle is not None:
            task.cycle.close()
    tasks.clear()
    for wiring in wirings:
        wiring.close()


def _simulate(session: RunSession, duration_s: float, port_writes: PortWrites, timeline: LetTimeline,
              tasks: dict[str, TaskRun], outcome: _Outcome) -> None:
    """The logical clock over the tasks' lifecycles (runtime/taskrun.py): prepare each, start each at
    T0, release their jobs in time order until the end, then stop and finish each (postrun always)."""
    app, layout, recorder = session.app, session.layout, session.recorder
    t0_ns = SIMULATION_T0_NS
    recorder.start(t0_ns, time.time_ns())
    end_ns = t0_ns + round(duration_s * 1e9)
    current, cycle = "", -1
    try:
        for name, spec in app.tasks.items():
            current = name
            handles = layout.tasks[name]
            wirings = device_wiring(app, name, twins=True)  # each device's twin in its place
            tasks[name] = task = TaskRun(spec.config, spec.runnable, handles.plan, layout.control, handles.status,
                                         handles.timing, wirings)
            for wiring in wirings:
                wiring.device.twin.tick = task.tick  # type: ignore[attr-defined]  # twins=True: a TwinDevice
            outcome.host_exec[name], outcome.records[name] = HostExecution(), []
            task.prepare()
            timeline.published(name, -1, task.y)
        for task in tasks.values():
            timeline.start(task, layout, t0_ns)  # the initial outputs stamped (or a snapshot restored)
            task.start(t0_ns, end_ns, stamped=True)
        # (release time, task order, cycle, name): a heap of the next release of each task
        order = {name: i for i, name in enumerate(tasks)}
        firsts = {name: timeline.first_cycle(name) for name in tasks}
        releases = [(t0_ns + first * tasks[name].period_ns, order[name], first, name)
                    for name, first in firsts.items() if first is not None]
        heapq.heapify(releases)
        steps = 0
        summary_interval_s = session.limits.summary_interval_s
        summary_due_s = time.monotonic() + summary_interval_s
        while releases and releases[0][0] < end_ns:
            release_ns, rank, cycle, current = heapq.heappop(releases)
            for port, values in port_writes.get((current, cycle), ()):
                layout.input_ports[port].write(np.asarray(values, dtype=np.float64))
            try:
                _release(tasks[current], cycle, release_ns, timeline, outcome)
            except StopRequested as request:  # a model ended the run: stop every task, in order
                outcome.stopped_by = f"task {current} at cycle {cycle}: {request}"
                break
            following = timeline.next_cycle(current, cycle)
            if following is not None:
                heapq.heappush(releases, (t0_ns + following * tasks[current].period_ns, rank, following, current))
            steps += 1
            now_s = time.monotonic()  # checked every step: one step may take seconds
            if steps % (min(RECORD_QUEUE_CAPACITY, READ_LOG_CAPACITY) // 2) == 0 or now_s >= summary_due_s:
                _drain(outcome, session)
            if now_s >= summary_due_s:  # the progress summary.json, as a run writes one
                session.write_summary_if_due()
                summary_due_s = now_s + summary_interval_s
        for task in tasks.values():  # safe values first, as in a real run
            task.stop()
        for name, task in tasks.items():
            current = name
            task.finish(failed=False)
    except DeviceError:  # a twin that does not configure: bad input, like a device in a real run
        raise
    except Exception as error:  # the user's code raised: report it like a real run does
        import traceback

        phase = tasks[current].phase if current in tasks else "prerun"
        where = getattr(error, "phase", None) or phase  # a device's fault says where in the cycle
        outcome.failure = TaskFailed(current, cycle if phase == "step" else None, where,
                                     f"{type(error).__name__}: {error}", traceback.format_exc())
        outcome.stopped_by = "fault"
    finally:
        for task in tasks.values():
            task.stop()  # the twins see the safe values on every way out too
        for name, task in tasks.items():  # postrun after a fault too (an FMU terminated), never twice
            problem = task.finish(failed=True)
            if problem:
                outcome.notes.append(postrun_failed_note(name, problem))
        _drain(outcome, session)


def _release(task: TaskRun, cycle: int, release_ns: int, timeline: LetTimeline, outcome: _Outcome) -> None:
    """The job of ``task`` at ``cycle`` on the logical clock: the inputs LET promises (or the run's
    timeline says), the job, the outputs published as valid from release + P."""
    tick, work = task.tick, task.cycle
    assert work is not None
    tick.cycle, tick.release_ns, tick.start_ns = cycle, release_ns, release_ns
    timeline.read_inputs(task.name, cycle, release_ns, work, task.wiring)
    started = time.perf_counter_ns()
    task.job(cycle)
    outcome.host_exec[task.name].add(time.perf_counter_ns() - started)
    work.publish_outputs(cycle, release_ns + task.period_ns)
    timeline.published(task.name, cycle, task.y)
    # Logical time: the job starts and ends at its release, so it cannot miss a deadline.
    # What it cost on this host is kept apart (host_exec_ns), never taken for timing.
    outcome.records[task.name].append((cycle, release_ns, release_ns, release_ns))


def _drain(outcome: _Outcome, session: RunSession) -> None:
    """Hand what the tasks recorded since the last drain to the recorder."""
    recorder = session.recorder
    for name, records in outcome.records.items():
        recorder.add_timing(name, np.array(records, dtype=np.int64).reshape(-1, 4))
        records.clear()
    session.drain()  # the signal and input queues, as in a real run


def _summary(app: App, session: RunSession, duration_s: float, outcome: _Outcome,
             sim_tasks: dict[str, TaskRun], *, running: bool) -> RunSummary:
    tasks = {name: TaskFacts(simulated=True,
                             host_exec_ns=outcome.host_exec[name].to_json() if name in outcome.host_exec else None,
                             input_limits=task.wiring.guards.counts(name, task.runnable.input_names)
                             if task.wiring.guards else None)
             for name, task in sim_tasks.items()}
    devices = {device: {"task": name, **report} for name, task in sim_tasks.items() if task.devices
               for device, report in task.devices.stale_report().items()}
    started = [f"task {name}: {text}" for name, task in sim_tasks.items()  # an FMU's Event Mode refused
               for text in getattr(getattr(task.runnable, "model", None), "start_notes", ())]
    run = RunFacts(mode="simulate", started_wall_ns=outcome.started_ns, duration_s=duration_s,
                   stopped_by=outcome.stopped_by, failure=outcome.failure.to_json() if outcome.failure else None,
                   notes=[*started, *outcome.notes], devices=devices)
    return build_summary(session, {name: tasks.get(name, TaskFacts(simulated=True)) for name in app.tasks}, run,
                         running=running)
