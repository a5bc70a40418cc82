"""The supervisor: starts one process per task, watches them, stops them.

It runs in the ``rtloop run`` process (non-real-time), inside a
:class:`~rtloop.runtime.session.RunSession` that owns the shared memory, the recorder and
summary.json. The order of a run: spawn tasks → wait until every task has finished
``prerun`` → pick the common epoch T0 → drain (to a time budget) until the tasks end,
rewriting summary.json every few seconds and watching that every task makes progress →
join → the session writes the artifacts and removes shared memory. Ctrl-C, SIGTERM, a task
that raises, a task process that dies and a task the watchdog finds stuck all take the same
way out, so nothing recorded is lost. Without a duration the run goes on until Ctrl-C or
SIGTERM.

This module is the processes' lifecycle only. Beside it: ``task_messages.py`` reads what the
tasks say through their pipes, ``task_watch.py`` is the watchdog, ``run_view.py`` shows the run
(progress, notices, the Foxglove live view), ``run_summary.py`` builds the summary.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rtloop.app.builder import App
from rtloop.app.byvalue import children_without_main, dumps_runnable
from rtloop.errors import NotRealTimeWarning, TaskFailed
from rtloop.io.device import check_device
from rtloop.io.host import release_after_dead_task, safe_for_dead_task
from rtloop.ipc.hotpath import announce_once
from rtloop.ipc.status import ControlWord, StatusWord, TaskState, publish_epoch
from rtloop.linux import rt
from rtloop.linux.hygiene import (
    SUPERVISOR_PRIORITY,
    adopting_orphans,
    away_from_task_cpus,
    describe_exit,
    marked_environment,
    serving_below_real_time_tasks,
)
from rtloop.linux.lean import single_threaded_children
from rtloop.record.summary import (
    RunSummary,
    not_real_time_notes,
)
from rtloop.runtime.bridges import READY_WITHIN_S, Bridges
from rtloop.runtime.evidence import MissWatch
from rtloop.runtime.layout import AppLayout, device_wiring
from rtloop.runtime.memory_watch import MemoryWatch
from rtloop.runtime.run_summary import RunFacts, TaskFacts, build_summary
from rtloop.runtime.run_view import Progress, RunView
from rtloop.runtime.session import (
    DEFAULT_LIMITS,
    STARTUP_ALLOWANCE_ENV,
    Limits,
    RunSession,
    RunState,
    startup_allowance_s,
    stop_signals_handled,
)
from rtloop.runtime.snapshot import SnapshotRequests
from rtloop.runtime.task import STEP_STUCK, task_process_main
from rtloop.runtime.task_messages import TaskReports
from rtloop.runtime.task_start import child_start, task_context
from rtloop.runtime.task_watch import TaskProcess, Watchdog, phase_of

STOP_GRACE_S = DEFAULT_LIMITS.stop_grace_s  # what `rtloop service` sizes its stop timeout by
UNTIL_STOPPED_NS = 1 << 62  # the end time of a run without a duration: never


class Supervisor:
    def __init__(self, app: App, duration_s: float | None, out: Path, *, trim: int,
                 keep_s: float | None = None, force: bool = False, limits: Limits = DEFAULT_LIMITS,
                 on_progress: Callable[[Progress], None] | None = None, on_notice: Callable[[str], None] | None = None,
                 trace_misses: bool = False) -> None:
        allowance_s = startup_allowance_s(limits.startup_allowance_s)
        # Where the environment says start-up is slow (emulation, a small board), so is a task's way
        # from seeing T0 to its first release: T0's margin after the last READY grows in proportion.
        declared = STARTUP_ALLOWANCE_ENV in os.environ
        slower = max(1.0, allowance_s / DEFAULT_LIMITS.startup_allowance_s) if declared else 1.0
        limits = dataclasses.replace(limits, startup_allowance_s=allowance_s,
                                     start_margin_ns=round(limits.start_margin_ns * slower))
        self.session = RunSession(app, out, mode="run", duration_s=duration_s, keep_s=keep_s, trim=trim,
                                  force=force, limits=limits)
        for device in app.devices.values():  # a missing interface or permission: exit 2, nothing started
            check_device(device.device, app.source)
        self.notes: list[str] = []  # summary.json notes: the devices', the tasks', --trace-misses'
        self.held_for_dead_tasks: list[Any] = []  # devices the supervisor made safe for a killed task (GPIO lines held)
        self.app, self.duration_s, self.out, self.limits = app, duration_s, out, limits
        self.view = RunView(app, on_progress, on_notice)  # the console's progress and notices, the live view
        self.stop_detail = ""  # the StopRequested text (task, cycle, reason) when state is REQUESTED
        self.failure: TaskFailed | None = None
        self.t0_ns = 0
        self.end_ns = 0
        self.wall_t0_ns = 0
        self.runs: dict[str, TaskProcess] = {}
        self.memory = MemoryWatch()
        """Each task's resident size at the summary rewrites (a step leaking reference cycles)."""
        self.bridges: Bridges | None = None
        self.dma_latency_held = False
        self.snapshots = SnapshotRequests({}, [task.config.period_ns for task in app.tasks.values()])
        """--keep: the tasks' snapshots asked for and collected (runtime/snapshot.py)."""
        self.watchdog = Watchdog(app, limits)
        self.misses = MissWatch(app)
        """Every miss's cause, from evidence gathered between drains (runtime/evidence.py)."""
        self.trace_misses = trace_misses
        self.reports = TaskReports(self.misses, self.notes)
        """What the task processes said through their pipes (runtime/task_messages.py)."""

    @property
    def state(self) -> RunState:
        return self.session.state

    @state.setter
    def state(self, value: RunState) -> None:
        self.session.state = value

    # --- lifecycle -------------------------------------------------------------------------
    def run(self) -> RunSummary:
        self.view.check()  # a live view without foxglove-sdk stops the run before anything starts
        capabilities = rt.probe()
        announce_once()
        # The handlers are kept until the session has written everything.
        with stop_signals_handled(self._request_stop), self.session as session:
            session.summarise = lambda running: self._summary(capabilities, running=running)
            self._run_tasks(session, capabilities)
        if self.reports.refused is not None:
            raise self.reports.refused
        if self.failure is not None:
            raise self.failure
        assert self.session.summary is not None
        return self.session.summary

    def _run_tasks(self, session: RunSession, capabilities: rt.Capabilities) -> None:
        layout, recorder = session.layout, session.recorder
        recorder.listeners.append(self.misses)
        self.snapshots.task_segments = {name: handles.segments.task for name, handles in layout.tasks.items()}
        self.misses.after_drain(rt.now_ns())  # the first sample: misses of the first cycles have one before them
        if self.trace_misses:  # the kernel's scheduler and IRQ events on the tasks' CPUs, or one line why not
            self.notes += [f"--trace-misses: {why}" for why in [self.misses.start_tracing()] if why]
        self.bridges = Bridges(self.app)
        configs = [task.config for task in self.app.tasks.values()]
        above = all(c.policy == "deadline" or (c.policy in ("fifo", "rr") and c.priority > SUPERVISOR_PRIORITY)
                    for c in configs)
        # Whatever is opened here is closed on every way out, in the reverse order (trio's nursery).
        with contextlib.ExitStack() as resources:
            resources.callback(self._ended_by_duration_unless_said)
            resources.enter_context(adopting_orphans(layout.token))  # the strays of the tasks end with the run
            resources.enter_context(serving_below_real_time_tasks(above, capabilities.may_use_rt))
            resources.callback(release_after_dead_task, self.held_for_dead_tasks)
            resources.callback(self._end_processes, layout)
            self.dma_latency_held = resources.enter_context(rt.CpuDmaLatency()).held  # read now: for the summary
            resources.callback(self.view.close)
            resources.callback(self.bridges.stop)
            resources.callback(self.misses.close)
            resources.callback(self.snapshots.close)
            self.view.open_live_view(session)
            self._spawn(layout)
            assert layout.registry_path is not None
            self.bridges.start(layout.registry_path)  # while tasks prepare: bridges wait for T0 too
            # off the tasks' CPUs now that every child has started with the caller's CPUs (linux/hygiene.py)
            resources.enter_context(away_from_task_cpus(c.cpu for c in configs if c.cpu is not None))
            self._wait_until_ready(layout)
            if self.failure is None and self.state is RunState.RUNNING:
                self._start_epoch(layout, recorder)
                self.view.start(self.t0_ns, self.wall_t0_ns)
                self._drain_until_done(session)
            else:
                layout.control[ControlWord.STOP] = 1
            self._join(layout)
            session.drain_after_stop(self.limits.stop_drain_budget_s)
            self._keep_snapshots(layout, recorder)

    def _end_processes(self, layout: AppLayout) -> None:
        """Every task stopped, a process still alive killed (its devices made safe from here), each let go."""
        layout.control[ControlWord.STOP] = 1
        for task_run in self.runs.values():
            if task_run.process.is_alive():
                task_run.process.kill()
                task_run.process.join()
                self._devices_safe_after_death(task_run)
            task_run.process.join()
            _let_go_of_process(task_run)

    def _ended_by_duration_unless_said(self) -> None:
        if self.state is RunState.RUNNING:
            self.state = RunState.DURATION

    def _spawn(self, layout: AppLayout) -> None:
        """Start a process per task into ``self.runs`` (each one there as soon as it started,
        so the cleanup joins and closes it even when a later one fails to start)."""
        # Forked from the task server (single-threaded, the task's modules loaded), or spawned: never
        # forked from here (a forked child of a threaded parent can inherit held locks): runtime/task_start.py
        context, server = task_context()
        # Pickled here, unpickled by the task (a failure there is reported as "loading");
        # classes from a script, notebook or stdin travel by value (app/byvalue.py).
        runnables = {name: dumps_runnable(spec.runnable, name) for name, spec in self.app.tasks.items()}
        devices = {name: dumps_runnable(device_wiring(self.app, name), name) for name in self.app.tasks}
        for name, spec in self.app.tasks.items():
            reader, writer = context.Pipe(duplex=False)
            handles = layout.tasks[name]
            # no BLAS pool in an RT process; the mark lets the cleanup end what the task starts
            try:
                with single_threaded_children(), children_without_main(), marked_environment(layout.token):
                    process = context.Process(
                        target=task_process_main,
                        args=(spec.config, runnables[name], handles.plan, handles.segments, writer, devices[name],
                              self.watchdog.spin_limit_s(spec.config), child_start(server),
                              self.watchdog.orphan_limits_s(spec.config)),
                        name=f"rtloop-{self.app.name}-{name}",
                    )
                    process.start()
            except BaseException:
                reader.close()
                raise
            finally:
                writer.close()
            self.runs[name] = TaskProcess(name, process, reader)

    def _wait_until_ready(self, layout: AppLayout) -> None:
        """Wait for every prerun; bounded by a stop signal and by the run's duration (plus start-up)."""
        allowance_s = self.limits.startup_allowance_s
        limit_s = float("inf") if self.duration_s is None else self.duration_s + allowance_s
        deadline = time.monotonic() + limit_s
        bridges_until = time.monotonic() + READY_WITHIN_S
        while self.failure is None and self.state is RunState.RUNNING:
            self._poll(layout)
            slow = [n for n in self.runs if layout.tasks[n].status[StatusWord.STATE] != TaskState.READY]
            if not slow and not (  # and the bridges' DDS entities, for a while (runtime/bridges.py)
                    self.bridges and self.bridges.starting() and time.monotonic() < min(bridges_until, deadline)):
                return
            if time.monotonic() > deadline:
                reason = (f"prerun did not finish within the run's duration + {allowance_s:g} s "
                          f"of start-up ({limit_s:g} s)")
                self.failure = TaskFailed(slow[0], None, "prerun", reason)
                self.state = RunState.FAULT
                return
            time.sleep(0.005)

    def _start_epoch(self, layout: AppLayout, recorder: Any) -> None:
        margin_ns = self.limits.start_margin_ns
        wall_now_ns, now_ns = time.time_ns(), rt.now_ns()
        self.t0_ns = now_ns + margin_ns
        self.end_ns = UNTIL_STOPPED_NS if self.duration_s is None else self.t0_ns + round(self.duration_s * 1e9)
        self.wall_t0_ns = wall_now_ns + margin_ns
        publish_epoch(layout.control, self.t0_ns, self.end_ns)  # tasks start when they see T0
        # Only then open run.mcap: its first use imports mcap, which can take longer than the margin.
        recorder.start(self.t0_ns, self.wall_t0_ns)

    def _drain_until_done(self, session: RunSession) -> None:
        layout, recorder = session.layout, session.recorder
        give_up_ns = self.end_ns + round(self.limits.stop_grace_s * 1e9)
        stale_reads = dict.fromkeys(self.runs, 0)
        behind = False
        while not all(r.finished for r in self.runs.values()):
            if not behind:  # a supervisor that fell behind goes straight back to draining
                time.sleep(self.limits.drain_interval_s)
            self._poll(layout)
            if layout.control[ControlWord.STOP] and self.state is RunState.RUNNING:
                self.state = RunState.SIGNAL  # a task process was sent SIGTERM: it stops the app
            behind = session.drain(self.limits.drain_budget_s)
            self._poll(layout)
            self.misses.after_drain(rt.now_ns(), frozenset(r.process.pid for r in self.runs.values()))
            self._keep_snapshots(layout, recorder)
            self._watch(layout, recorder)
            assert self.bridges is not None
            self.bridges.poll()
            for name in self.runs:  # a stale read is an event the flight recorder keeps
                count = layout.tasks[name].status[StatusWord.STALE_READS]
                if count != stale_reads[name]:
                    stale_reads[name] = count
                    recorder.mark_event()
            self.view.after_drain(session)
            if self.failure is not None or self.state is not RunState.RUNNING:
                recorder.mark_event()
                layout.control[ControlWord.STOP] = 1
                break
            if rt.now_ns() > give_up_ns:
                layout.control[ControlWord.STOP] = 1
                break
            session.write_summary_if_due()
            self.view.show_progress(session, self.t0_ns, self.duration_s)

    def _keep_snapshots(self, layout: AppLayout, recorder: Any) -> None:
        """--keep: the snapshots the tasks wrote to the recorder; at a new recording segment, a new request."""
        self.snapshots.collect(recorder)
        self.snapshots.ask(layout.control, recorder, self.t0_ns)

    def _watch(self, layout: AppLayout, recorder: Any) -> None:
        """The watchdog (runtime/task_watch.py): a stuck task fails the run; its step is broken."""
        found = self.watchdog.find_stuck(self.runs, layout, recorder, self.t0_ns) if self.failure is None else None
        if found is None:
            return
        task_run, self.failure = found
        self.state = RunState.WATCHDOG
        layout.control[ControlWord.STOP] = 1  # the other tasks stop the orderly way
        with contextlib.suppress(ProcessLookupError):
            os.kill(task_run.process.pid, STEP_STUCK)  # breaks the step of a task with devices

    def _join(self, layout: AppLayout) -> None:
        stop_grace_s, watchdog_grace_s = self.limits.stop_grace_s, self.limits.watchdog_grace_s
        deadline = time.monotonic() + stop_grace_s + max(
            t.config.period_ns for t in self.app.tasks.values()
        ) / 1e9
        stuck_deadline = time.monotonic() + watchdog_grace_s
        for task_run in self.runs.values():
            task_run.process.join(max(0.0, (stuck_deadline if task_run.stuck else deadline) - time.monotonic()))
            if task_run.process.is_alive():
                task_run.process.kill()
                task_run.process.join()
                self._read_messages(task_run)  # a failure it reported before it hung (in postrun) is the one to say
                if task_run.stuck and self.failure is not None:
                    self.failure = TaskFailed(
                        task_run.name, self.failure.cycle, self.failure.phase,
                        f"{self.failure.reason}; its step did not return on the watchdog's signal; it was "
                        f"killed (SIGKILL) after {watchdog_grace_s:g} s, so its postrun did not run")
                if self.failure is None:
                    phase, cycle = phase_of(layout, self.app, task_run.name, self.t0_ns)
                    self.failure = TaskFailed(
                        task_run.name, cycle, phase,
                        f"did not stop within {stop_grace_s:g} s of the stop request; killed "
                        f"(is {phase}() blocking or looping?)",
                    )
                    self.state = RunState.FAULT
        self._poll(layout)

    # --- watching ----------------------------------------------------------------------------
    def _poll(self, layout: AppLayout) -> None:
        """Read task messages; notice failures and dead processes."""
        for task_run in self.runs.values():
            self._read_messages(task_run)
            process = task_run.process
            if process.exitcode is None or task_run.finished:
                continue
            # It exited: what it sent just before (its traceback) may have come after the read above.
            self._read_messages(task_run)
            task_run.finished = True
            if process.exitcode < 0:  # killed by a signal: its own way out, safe values first, never ran
                self._devices_safe_after_death(task_run)
            if task_run.failure is None and process.exitcode != 0:
                phase, cycle = phase_of(layout, self.app, task_run.name, self.t0_ns)
                task_run.failure = TaskFailed(
                    task_run.name, cycle, phase, f"task process died: {describe_exit(process.exitcode)}"
                )
            if task_run.failure is not None:
                self._fail(task_run.failure)

    def _fail(self, failure: TaskFailed) -> None:
        """The run failed (the first failure is the one reported): every task stops now."""
        if self.failure is None:
            self.failure = failure
            self.state = RunState.WATCHDOG if failure.reason.startswith("WatchdogExpired") else RunState.FAULT
        self.session.stop_tasks()

    def _devices_safe_after_death(self, task_run: TaskProcess) -> None:
        """Write the safe values of a killed task's devices from here, where their interface allows."""
        wirings = device_wiring(self.app, task_run.name)
        if wirings:
            why = f"was {describe_exit(task_run.process.exitcode)}"
            self.notes += safe_for_dead_task(task_run.name, wirings, why)
            self.held_for_dead_tasks += wirings

    def _read_messages(self, task_run: TaskProcess) -> None:
        """What the task said (runtime/task_messages.py): a failure stops every task now, not when its
        process exits (its postrun may hang); a stop it asked for ends the run unless something did first."""
        failure = self.reports.read(task_run)
        if failure is not None:
            self._fail(failure)
        if task_run.stop_request and self.state is RunState.RUNNING:
            self.state, self.stop_detail = RunState.REQUESTED, task_run.stop_request

    # --- signals ------------------------------------------------------------------------------
    def _request_stop(self, _signum: int) -> None:
        """Ctrl-C, SIGTERM, SIGHUP: the tasks are stopped from here, not at the control loop's next turn
        (tasks that keep the processors busy can delay that turn by seconds: it runs below them)."""
        if self.state is RunState.RUNNING:
            self.state = RunState.SIGNAL
        self.session.stop_tasks()

    # --- results --------------------------------------------------------------------------------
    def _stopped_by(self, running: bool) -> str:
        if running:
            return "running"
        if self.state is RunState.REQUESTED:
            return self.stop_detail
        return str((RunState.DURATION if self.state is RunState.RUNNING else self.state).value)

    def _summary(self, capabilities: rt.Capabilities, *, running: bool) -> RunSummary:
        recorder = self.session.recorder
        tasks: dict[str, TaskFacts] = {}
        for name in self.app.tasks:
            task_run = self.runs.get(name)
            if running and task_run is not None:
                self.memory.sample(name, task_run.process.pid, recorder.latest_ns)
            tasks[name] = TaskFacts(settings=task_run.settings if task_run else None,
                                    locked_bytes=task_run.locked_bytes if task_run else None,
                                    resident_bytes=self.memory.to_json(name),
                                    input_limits=self.reports.input_limits_of(self.app, name))
        bridges = self.bridges.summary() if self.bridges is not None else {}
        run = RunFacts(
            mode="run", started_wall_ns=self.wall_t0_ns or time.time_ns(), duration_s=self.duration_s,
            stopped_by=self._stopped_by(running), failure=self.failure.to_json() if self.failure else None,
            notes=[self.bridges.note if self.bridges is not None else "", *self.notes, *self.snapshots.problems],
            more_notes=self.memory.notes(), devices=self.reports.device_reads,
            bridges={**bridges, **self.view.summary()},
            machine={"cpu_dma_latency_held": self.dma_latency_held}, misses=self.misses.summary(final=not running))
        return build_summary(self.session, tasks, run, running=running)


def requested_policies(app: App) -> dict[str, str]:
    """Each task's scheduling policy as the app asks for it."""
    return {name: spec.config.policy for name, spec in app.tasks.items()}


def _let_go_of_process(task_run: TaskProcess) -> None:
    """Close what a joined task process holds open here (its pipe, its exit sentinel): a library's
    caller runs many apps in one process and must not run out of file descriptors."""
    task_run.pipe.close()
    with contextlib.suppress(ValueError):  # not started (a spawn that failed)
        task_run.process.close()


def run(app: App, duration_s: float | None, out: str | Path, *, trim: int = 20, keep_s: float | None = None,
        force: bool = False, limits: Limits = DEFAULT_LIMITS, on_progress: Callable[[Progress], None] | None = None,
        trace_misses: bool = False) -> RunSummary:
    """Run ``app`` in real time for ``duration_s`` (None: until SIGINT/SIGTERM); artifacts go into ``out``.

    ``keep_s``: keep only the last ``keep_s`` seconds of timing.csv, signals.csv and run.mcap,
    plus the cycles around every deadline miss, stale read or fault (None: keep everything).
    A folder that already holds a run is refused (:class:`~rtloop.runtime.session.RunDirectoryError`)
    unless ``force`` is true; then that run's files are removed first. ``on_progress`` is called
    with a :class:`Progress` at every drain (the CLI draws its progress line with it). ``trace_misses``:
    record the kernel's scheduler and IRQ events on the tasks' CPUs, to name who held a late cycle's CPU.
    """
    summary = Supervisor(app, duration_s, Path(out), trim=trim, keep_s=keep_s, force=force, limits=limits,
                         on_progress=on_progress, trace_misses=trace_misses).run()
    # a notebook sees it (the summary's notes say it too); rtloop run prints its own WARNING line
    for note in not_real_time_notes(summary.tasks, requested_policies(app)):
        warnings.warn(note, NotRealTimeWarning, stacklevel=2)
    return summary
