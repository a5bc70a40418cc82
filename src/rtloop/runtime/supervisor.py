"""The supervisor: starts one process per task, drains what they record, stops them.

It runs in the ``rtloop run`` process (non-real-time). The order of a run:
create shared memory → spawn tasks → wait until every task has finished ``prerun`` →
pick the common epoch T0 → drain timing and recordings until the tasks end (rewriting
summary.json every few seconds, watching that every task makes progress) → write the
artifacts → remove shared memory. Ctrl-C, SIGTERM, a task that raises, a task process that
dies and a task the watchdog finds stuck all take the same way out, so nothing recorded is
lost. Without a duration the run goes on until Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import datetime as dt
import multiprocessing
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rtloop import rt
from rtloop.app.builder import WATCHDOG_MIN_S, App, check_duration
from rtloop.app.byvalue import children_without_main, dumps_runnable
from rtloop.errors import AppError, DeviceError, TaskFailed
from rtloop.io.device import check_device
from rtloop.ipc.hotpath import announce_once, hot_path
from rtloop.ipc.status import ControlWord, StatusWord, TaskState, publish_epoch
from rtloop.lean import single_threaded_children
from rtloop.record.recorder import Recorder
from rtloop.record.summary import PortSummary, RunSummary, SummaryFile, TaskSummary, signal_names, slow_step_notes
from rtloop.runtime.bridges import Bridges
from rtloop.runtime.layout import AppLayout
from rtloop.runtime.task import task_process_main

DRAIN_INTERVAL_S = 0.05
DRAIN_BATCH_RECORDS = 2048
START_MARGIN_NS = 100_000_000
STOP_GRACE_S = 5.0
STARTUP_ALLOWANCE_S = 30.0
"""Time to start a task process (Python, numpy, the runnable's imports) on top of the run's duration."""
WATCHDOG_GRACE_S = 2.0  # between SIGTERM and SIGKILL of a task the watchdog found stuck
SUMMARY_INTERVAL_S = 2.0
UNTIL_STOPPED_NS = 1 << 62  # the end time of a run without a duration: never


@dataclass
class _TaskRun:
    name: str
    process: Any
    pipe: Any
    settings: rt.AppliedSettings | None = None
    failure: TaskFailed | None = None
    finished: bool = False
    stop_request: str | None = None
    progress_cycle: int = -1  # the CYCLE status word when the watchdog last saw it change
    progress_ns: int = 0  # and when that was
    stuck: bool = False  # the watchdog gave up on it: SIGTERM sent, SIGKILL follows


class Supervisor:
    def __init__(self, app: App, duration_s: float | None, out: Path, *, progress: bool, trim: int,
                 keep_s: float | None = None) -> None:
        app.validate()
        if duration_s is not None:
            check_duration(duration_s)
        if keep_s is not None and not keep_s > 0:
            raise AppError(f"--keep must be > 0 seconds, got {keep_s}")
        for device in app.devices.values():  # a missing interface or permission: exit 2, nothing started
            check_device(device.device, app.source)
        self.refused: DeviceError | None = None  # a device that failed its configure (bad input, exit 2)
        self.device_problems: list[str] = []
        self.app, self.duration_s, self.out = app, duration_s, out
        self.keep_s = keep_s
        self.progress, self.trim = progress, trim
        self.stop_reason = "duration"
        self.failure: TaskFailed | None = None
        self.t0_ns = 0
        self.end_ns = 0

    # --- lifecycle -------------------------------------------------------------------------
    def run(self) -> RunSummary:
        if self.app.live_view is not None:  # a missing foxglove-sdk stops the run before anything starts
            from rtloop.ros.live import import_foxglove

            import_foxglove()
        self.out.mkdir(parents=True, exist_ok=True)
        capabilities = rt.probe()
        announce_once()
        summary_file = SummaryFile(self.out)  # reserves its disk space first
        layout = AppLayout.create(self.app, summary_file.path)
        runs: dict[str, _TaskRun] = {}
        self.live: Any = None
        try:
            recorder = Recorder(self.app, self.out, keep_s=self.keep_s, trim=self.trim)
            recorder.write_replay_info(self.duration_s)
            self.bridges = Bridges(self.app)
            previous_handlers = self._install_signal_handlers()
            self.dma_latency = rt.CpuDmaLatency().__enter__()
            self.dma_latency_held = self.dma_latency.held  # read now: the summary is written after it is let go
            children_before = _adopt_orphans()
            try:
                self._open_live_view(recorder, layout)
                runs = self._spawn(layout)
                assert layout.registry_path is not None
                self.bridges.start(layout.registry_path)  # while tasks prepare: bridges wait for T0 too
                self._wait_until_ready(layout, runs)
                if self.failure is None and self.stop_reason == "duration":
                    self._start_epoch(layout, recorder)
                    if self.live is not None:
                        self.live.start(self.t0_ns, self.wall_t0_ns)
                    self._drain_until_done(layout, runs, recorder, capabilities, summary_file)
                else:
                    layout.control[ControlWord.STOP] = 1
                self._join(layout, runs)
                self._drain(layout, recorder)
            finally:
                self.bridges.stop()
                if self.live is not None:
                    self.live.close()
                self.dma_latency.__exit__()
                self._restore_signal_handlers(previous_handlers)
                layout.control[ControlWord.STOP] = 1
                for task_run in runs.values():
                    if task_run.process.is_alive():
                        task_run.process.kill()
                    task_run.process.join()
                rt.end_strays(keep=children_before | _resource_tracker())  # whatever the tasks left running
                try:
                    recorder.close()
                except Exception as error:
                    recorder.stopped = recorder.stopped or f"recording not closed: {error}"
                summary = self._summary(layout, runs, capabilities, recorder, running=False)
                summary_file.write(summary)
                summary_file.close()
        finally:
            layout.close()  # whatever happened above: no shared memory is left behind
            summary_file.close()
        if summary_file.problem:
            sys.stderr.write(f"rtloop: {summary_file.problem}\n")
        if self.refused is not None:
            raise self.refused
        if self.failure is not None:
            raise self.failure
        return summary

    def _open_live_view(self, recorder: Recorder, layout: AppLayout) -> None:
        """Start the Foxglove server if the app asks for one (in this non-real-time process)."""
        if self.app.live_view is None:
            return
        from rtloop.ros.live import LiveView

        names = recorder.signals.names if recorder.signals is not None else []
        assert layout.registry_path is not None
        self.live = LiveView(self.app, self.app.live_view, names, layout.registry_path)
        recorder.live = self.live
        print(f"rtloop: Foxglove live view on {self.live.url} (Foxglove: Open connection → Foxglove WebSocket)",
              file=sys.stderr, flush=True)

    def _spawn(self, layout: AppLayout) -> dict[str, _TaskRun]:
        # spawn, not fork: a forked child of a threaded parent can inherit held locks.
        context = multiprocessing.get_context("spawn")
        runs: dict[str, _TaskRun] = {}
        # Pickled here, unpickled by the task (a failure there is reported as "loading");
        # classes from a script, notebook or stdin travel by value (app/byvalue.py).
        runnables = {name: dumps_runnable(spec.runnable, name) for name, spec in self.app.tasks.items()}
        devices = {name: dumps_runnable(self.app.device_wiring(name), name) for name in self.app.tasks}
        for name, spec in self.app.tasks.items():
            reader, writer = context.Pipe(duplex=False)
            handles = layout.tasks[name]
            process = context.Process(
                target=task_process_main,
                args=(spec.config, runnables[name], handles.plan, handles.segments, writer, devices[name]),
                name=f"rtloop-{self.app.name}-{name}",
            )
            with single_threaded_children(), children_without_main():  # no BLAS pool in an RT process
                process.start()
            writer.close()
            runs[name] = _TaskRun(name, process, reader)
        return runs

    def _wait_until_ready(self, layout: AppLayout, runs: dict[str, _TaskRun]) -> None:
        """Wait for every prerun; bounded by a stop signal and by the run's duration (plus start-up)."""
        limit_s = float("inf") if self.duration_s is None else self.duration_s + STARTUP_ALLOWANCE_S
        deadline = time.monotonic() + limit_s
        while self.failure is None and self.stop_reason == "duration":
            self._poll(layout, runs)
            states = [layout.tasks[name].status[StatusWord.STATE] for name in runs]
            if all(state == TaskState.READY for state in states):
                return
            if time.monotonic() > deadline:
                slow = [n for n, s in zip(runs, states, strict=True) if s != TaskState.READY]
                reason = (f"prerun did not finish within the run's duration + {STARTUP_ALLOWANCE_S:g} s "
                          f"of start-up ({limit_s:g} s)")
                self.failure = TaskFailed(slow[0], None, "prerun", reason)
                self.stop_reason = "fault"
                return
            time.sleep(0.005)

    def _start_epoch(self, layout: AppLayout, recorder: Recorder) -> None:
        wall_now_ns, now_ns = time.time_ns(), rt.now_ns()
        self.t0_ns = now_ns + START_MARGIN_NS
        self.end_ns = UNTIL_STOPPED_NS if self.duration_s is None else self.t0_ns + round(self.duration_s * 1e9)
        self.wall_t0 = (wall_now_ns + START_MARGIN_NS) / 1e9
        self.wall_t0_ns = wall_now_ns + START_MARGIN_NS
        recorder.start(self.t0_ns, wall_now_ns + START_MARGIN_NS)
        publish_epoch(layout.control, self.t0_ns, self.end_ns)  # tasks start when they see T0

    def _drain_until_done(self, layout: AppLayout, runs: dict[str, _TaskRun], recorder: Recorder,
                          capabilities: rt.Capabilities, summary_file: SummaryFile) -> None:
        give_up_ns = self.end_ns + round(STOP_GRACE_S * 1e9)
        next_summary_s = time.monotonic()
        stale_reads = dict.fromkeys(runs, 0)
        recording_stopped = ""
        while not all(r.finished for r in runs.values()):
            time.sleep(DRAIN_INTERVAL_S)
            self._poll(layout, runs)
            if layout.control[ControlWord.STOP] and self.stop_reason == "duration":
                self.stop_reason = "signal"  # a task process was sent SIGTERM: it stops the app
            self._drain(layout, recorder)
            self._poll(layout, runs)
            self._watch(layout, runs, recorder)
            self.bridges.poll()
            for name in runs:  # a stale read is an event the flight recorder keeps
                count = layout.tasks[name].status[StatusWord.STALE_READS]
                if count != stale_reads[name]:
                    stale_reads[name] = count
                    recorder.mark_event()
            if recorder.stopped != recording_stopped:
                recording_stopped = recorder.stopped
                sys.stderr.write(f"\nrtloop: {recording_stopped}\n")
            if self.failure is not None or self.stop_reason != "duration":
                recorder.mark_event()
                layout.control[ControlWord.STOP] = 1
                break
            if rt.now_ns() > give_up_ns:
                layout.control[ControlWord.STOP] = 1
                break
            if time.monotonic() >= next_summary_s:
                next_summary_s = time.monotonic() + SUMMARY_INTERVAL_S
                summary_file.write(self._summary(layout, runs, capabilities, recorder, running=True))
            if self.progress:
                self._show_progress(layout, recorder)
        if self.progress:
            sys.stderr.write("\n")

    def _watch(self, layout: AppLayout, runs: dict[str, _TaskRun], recorder: Recorder) -> None:
        """The watchdog: a running task whose cycle count stands still too long is stuck."""
        now_ns = rt.now_ns()
        for task_run in runs.values():
            status = layout.tasks[task_run.name].status
            if task_run.finished or task_run.stuck or status[StatusWord.STATE] != TaskState.RUNNING:
                continue
            cycle = status[StatusWord.CYCLE]
            if cycle != task_run.progress_cycle:
                task_run.progress_cycle, task_run.progress_ns = cycle, now_ns
                continue
            config = self.app.tasks[task_run.name].config
            if not config.watchdog_periods:
                continue
            limit_ns = max(config.watchdog_periods * config.period_ns, round(WATCHDOG_MIN_S * 1e9))
            quiet_ns = now_ns - max(task_run.progress_ns, self.t0_ns)
            if quiet_ns <= limit_ns or self.failure is not None:
                continue
            task_run.stuck = True
            self.failure = TaskFailed(
                task_run.name, self._cycle_after(task_run.name, recorder), "step",
                f"watchdog: no cycle finished for {quiet_ns / 1e9:.1f} s ({config.watchdog_periods} periods); "
                "the step is stuck (a blocking call or an endless loop)",
            )
            self.stop_reason = "watchdog"
            layout.control[ControlWord.STOP] = 1  # the other tasks stop the orderly way
            try:
                os.kill(task_run.process.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass

    def _cycle_after(self, name: str, recorder: Recorder) -> int:
        """The cycle a task works on: the one after its newest timing record."""
        last = recorder.last_record[name]
        if last is None:
            return 0
        cycle, release_ns, _start_ns, end_ns = last
        config = self.app.tasks[name].config
        if end_ns <= release_ns + config.period_ns or config.overrun == "catch_up":
            return cycle + 1
        return (end_ns - self.t0_ns) // config.period_ns + 1  # skip: the next release after it ended

    def _join(self, layout: AppLayout, runs: dict[str, _TaskRun]) -> None:
        deadline = time.monotonic() + STOP_GRACE_S + max(
            t.config.period_ns for t in self.app.tasks.values()
        ) / 1e9
        stuck_deadline = time.monotonic() + WATCHDOG_GRACE_S
        for task_run in runs.values():
            task_run.process.join(max(0.0, (stuck_deadline if task_run.stuck else deadline) - time.monotonic()))
            if task_run.process.is_alive():
                task_run.process.kill()
                task_run.process.join()
                if task_run.stuck and self.failure is not None:
                    self.failure = TaskFailed(
                        task_run.name, self.failure.cycle, self.failure.phase,
                        f"{self.failure.reason}; it ignored SIGTERM and was killed (SIGKILL) after "
                        f"{WATCHDOG_GRACE_S:.0f} s, so its postrun did not run")
                if self.failure is None:
                    phase, cycle = self._phase_of(layout, task_run.name)
                    self.failure = TaskFailed(
                        task_run.name, cycle, phase,
                        f"did not stop within {STOP_GRACE_S:.0f} s of the stop request; killed "
                        f"(is {phase}() blocking or looping?)",
                    )
                    self.stop_reason = "fault"
        self._poll(layout, runs)

    # --- draining and watching ---------------------------------------------------------------
    @staticmethod
    def _drain(layout: AppLayout, recorder: Recorder) -> None:
        """Hand what the tasks recorded to the recorder, in bounded batches: a supervisor that fell
        behind catches up without a burst of memory (which Python would keep afterwards)."""
        more = True
        while more:
            more = False
            for name, handles in layout.tasks.items():
                records = handles.timing.drain(DRAIN_BATCH_RECORDS)
                recorder.add_timing(name, records)
                more |= len(records) == DRAIN_BATCH_RECORDS
                if handles.input_log is not None:
                    recorder.add_inputs(name, *handles.input_log.drain())
                if handles.read_log is not None:
                    recorder.add_reads(name, handles.read_log.drain(), handles.read_log.dropped)
                if handles.record is not None:
                    ticks, rows = handles.record.drain(DRAIN_BATCH_RECORDS)
                    recorder.add_signals(name, ticks, rows)
                    more |= len(ticks) == DRAIN_BATCH_RECORDS
            recorder.flush()

    def _poll(self, layout: AppLayout, runs: dict[str, _TaskRun]) -> None:
        """Read task messages; notice failures and dead processes."""
        for task_run in runs.values():
            self._read_messages(task_run)
            process = task_run.process
            if process.exitcode is None or task_run.finished:
                continue
            task_run.finished = True
            if task_run.failure is None and process.exitcode != 0:
                phase, cycle = self._phase_of(layout, task_run.name)
                task_run.failure = TaskFailed(
                    task_run.name, cycle, phase, f"task process died: {_describe_exit(process.exitcode)}"
                )
            if task_run.failure is not None and self.failure is None:
                self.failure = task_run.failure
                self.stop_reason = "fault"
                layout.control[ControlWord.STOP] = 1

    def _phase_of(self, layout: AppLayout, name: str) -> tuple[str, int | None]:
        """What a task was doing when it died or hung: its phase and, in step, the cycle in progress."""
        handles = layout.tasks[name]
        state = handles.status[StatusWord.STATE]
        if state in (TaskState.STARTING, TaskState.READY):
            return "prerun", None
        if state == TaskState.POSTRUN:
            return "postrun", None
        if state == TaskState.STOPPED:
            return "process", None
        return "step", cycle_in_progress(handles, self.t0_ns, self.app.tasks[name].config)

    def _read_messages(self, task_run: _TaskRun) -> None:
        try:
            while task_run.pipe.poll():
                message = task_run.pipe.recv()
                kind = message.get("kind")
                if kind == "settings":
                    task_run.settings = message["settings"]
                elif kind == "finished":
                    task_run.stop_request = f"task {task_run.name} at cycle {message['cycle']}: {message['reason']}"
                    if message.get("edge_ns"):  # an E-stop: when its edge came, when this task's devices were safe
                        edge_ns, safe_ns = message["edge_ns"], message.get("safe_ns") or 0
                        self.device_problems.append(
                            f"E-stop: edge at {edge_ns} ns (CLOCK_MONOTONIC, kernel timestamp); task {task_run.name}'s "
                            f"devices safe at {safe_ns} ns, {(safe_ns - edge_ns) / 1e3:.0f} µs after the edge")
                elif kind == "device_error":
                    self.refused = DeviceError(message["device"], message["source"], message["key"],
                                               message["problem"])
                elif kind == "device_problems":
                    self.device_problems += [f"task {task_run.name}: {p}" for p in message["problems"]]
                elif kind == "failed":
                    task_run.failure = TaskFailed(
                        task_run.name, message["cycle"], message["phase"], message["reason"],
                        message["traceback"],
                    )
        except (EOFError, OSError):
            pass
        if task_run.stop_request and self.stop_reason == "duration":
            self.stop_reason = task_run.stop_request

    def _show_progress(self, layout: AppLayout, recorder: Recorder) -> None:
        elapsed_s = max(0.0, (rt.now_ns() - self.t0_ns) / 1e9)
        misses = sum(h.status[StatusWord.DEADLINE_MISSES] for h in layout.tasks.values())
        worst_us = max(h.status[StatusWord.LATENCY_LAST_NS] for h in layout.tasks.values()) / 1e3
        until = "  (Ctrl-C stops)" if self.duration_s is None else f" / {self.duration_s:.1f} s"
        if self.duration_s is not None:
            elapsed_s = min(elapsed_s, self.duration_s)
        recording = "   RECORDING STOPPED" if recorder.stopped else ""
        sys.stderr.write(
            f"\r  {elapsed_s:7.1f} s{until}   deadline misses {misses}   latency now {worst_us:7.1f} µs{recording}  "
        )
        sys.stderr.flush()

    # --- signals ------------------------------------------------------------------------------
    def _install_signal_handlers(self) -> dict[int, Any]:
        if threading.current_thread() is not threading.main_thread():
            return {}

        def request_stop(signum: int, _frame: object) -> None:
            self.stop_reason = "signal"

        return {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}

    @staticmethod
    def _restore_signal_handlers(previous: dict[int, Any]) -> None:
        for signum, handler in previous.items():
            signal.signal(signum, handler)

    # --- results --------------------------------------------------------------------------------
    def _summary(self, layout: AppLayout, runs: dict[str, _TaskRun], capabilities: rt.Capabilities,
                 recorder: Recorder, *, running: bool) -> RunSummary:
        tasks: dict[str, TaskSummary] = {}
        for name, spec in self.app.tasks.items():
            task_run = runs.get(name)
            status = layout.tasks[name].status
            settings = task_run.settings if task_run else None
            tasks[name] = TaskSummary(
                period_ns=spec.config.period_ns,
                priority=settings.priority if settings else 0,
                cpu=spec.config.cpu,
                policy=settings.policy if settings else "not started",
                rt=settings.rt if settings else False,
                rt_reason="; ".join(settings.reasons) if settings else "the task never started",
                memory_locked=settings.memory_locked if settings else False,
                timing=recorder.timing_of(name),
                stale_reads=status[StatusWord.STALE_READS],
                misses_in_a_row_max=status[StatusWord.MISSES_IN_A_ROW_MAX],
                timing_samples_dropped=layout.tasks[name].timing.dropped,
                **signal_names(spec.runnable),
            )
        return RunSummary(
            app=self.app.name,
            mode="run",
            hot_path=hot_path(),
            started=_iso(getattr(self, "wall_t0", time.time())),
            duration_s=self.duration_s,
            rt_capable=capabilities.may_use_rt,
            tasks=tasks,
            ports=port_summaries(layout, recorder.latest_ns),
            stopped_by="running" if running else self.stop_reason,
            failure=self.failure.to_json() if self.failure else None,
            machine={**machine_facts(capabilities), "cpu_dma_latency_held": self.dma_latency_held},
            notes=[*slow_step_notes(tasks),
                   *(note for note in (recorder.mcap_note, self.bridges.note, recorder.stopped) if note),
                   *self.device_problems],
            bridges={**self.bridges.summary(), **(self.live.summary() if self.live is not None else {})},
            elapsed_s=recorder.latest_ns / 1e9,
            running=running,
            recording=recorder.to_json(),
        )


def cycle_in_progress(handles: Any, t0_ns: int, config: Any) -> int:
    """The cycle a running task was in: the one after its last completed cycle (the status
    block holds the last completed one), or after the releases an overrun skipped."""
    status = handles.status
    if handles.timing.written_total == 0:
        return 0
    last = status[StatusWord.CYCLE]
    period_ns = config.period_ns
    last_end_ns = t0_ns + last * period_ns + status[StatusWord.LATENCY_LAST_NS] + status[StatusWord.EXEC_LAST_NS]
    following = last + 1
    if config.overrun == "skip" and t0_ns and last_end_ns > t0_ns + following * period_ns:
        following = (last_end_ns - t0_ns) // period_ns + 1
    return following


def _adopt_orphans() -> set[int]:
    """Become the subreaper of what the tasks start; returns the children that existed before."""
    try:
        rt.become_subreaper()
    except OSError:
        pass  # an old kernel: task processes still end their own strays
    return rt.child_pids()


def _resource_tracker() -> set[int]:
    """multiprocessing's helper process (a child of ours, started with the first task)."""
    from multiprocessing import resource_tracker

    pid = getattr(resource_tracker._resource_tracker, "_pid", None)
    return {pid} if pid else set()


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


def _iso(wall_s: float) -> str:
    return dt.datetime.fromtimestamp(wall_s, tz=dt.UTC).isoformat(timespec="milliseconds")


def _describe_exit(exitcode: int) -> str:
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def run(app: App, duration_s: float | None, out: str | Path, *, progress: bool = False, trim: int = 20,
        keep_s: float | None = None) -> RunSummary:
    """Run ``app`` in real time for ``duration_s`` (None: until SIGINT/SIGTERM); artifacts go into ``out``.

    ``keep_s``: keep only the last ``keep_s`` seconds of timing.csv, signals.csv and run.mcap,
    plus the cycles around every deadline miss, stale read or fault (None: keep everything).
    """
    return Supervisor(app, duration_s, Path(out), progress=progress, trim=trim, keep_s=keep_s).run()
