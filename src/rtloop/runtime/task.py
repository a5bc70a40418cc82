"""The real-time task: one process, one runnable, one absolute timeline.

This is the file to read first. ``run_loop`` is the whole real-time part: everything
else in this module prepares it (scheduling, memory, the wait for the common epoch T0)
or cleans up after it. What the framework does in each cycle is in ``ipc/hotpath.py``.
"""

from __future__ import annotations

import gc
import multiprocessing
import multiprocessing.util
import os
import select
import signal
import time
import traceback
from typing import Any

from rtloop.app.byvalue import loads_runnable
from rtloop.app.specs import TaskConfig
from rtloop.errors import DeadlineMissesExceeded, DeviceError, DeviceMismatch, LibcError, StopRequested, WatchdogExpired
from rtloop.io.host import DeviceWiring, TaskDevices
from rtloop.ipc.hotpath import CYCLE_LATE, SNAPSHOT_DUE
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import CONTROL_WORDS, STATUS_WORDS, TASK_TIMING_OFFSET_BYTES
from rtloop.ipc.segments import Segment
from rtloop.ipc.status import ControlWord, StatusWord, TaskState, WordBlock, read_epoch
from rtloop.ipc.wiring import TaskSegments, TaskWiringPlan
from rtloop.linux import memory, rt
from rtloop.linux.cpustat import own_thread_counters
from rtloop.linux.lean import lock_what_the_loop_touches, lock_what_the_server_ran, unlock_what_the_loop_never_needs
from rtloop.runnable import Runnable
from rtloop.runtime.snapshot import snapshot_file_name, write_snapshot
from rtloop.runtime.task_start import ChildStart
from rtloop.runtime.taskrun import TaskRun  # its snapshot's imports too: none inside the loop
from rtloop.text import counted

T0_POLL_S = 0.001
LATE_READINGS_PER_RUN = 1000
"""Late cycles whose thread counters a task reads and sends (a few µs each): a run that misses every
cycle pays it for the first ones only."""
SUPERVISOR_GONE = signal.SIGRTMIN + 5
"""What the kernel sends a task when its supervisor dies (PR_SET_PDEATHSIG): a signal of rtloop's
own, so code that takes over SIGTERM (a library, a student's "clean exit") cannot keep the loop
running with no supervisor; it stops in order, as SIGTERM does."""
STEP_STUCK = signal.SIGRTMIN + 6
"""What the supervisor's watchdog sends a task whose cycles stand still: a task that owns devices
breaks its stuck step (its devices get their safe values on the way out). A signal of its own, not a
second SIGTERM: two SIGTERMs sent together may arrive as one."""
STOP_SIGNALS = (signal.SIGTERM, SUPERVISOR_GONE, STEP_STUCK)


class StopRequests:
    """The stop requests this task process received, counted (not read from the STOP flag, which the
    supervisor or another task may have set: a process-group SIGTERM racing the supervisor's is a
    first request, not a second). The first stops the app in order; a second one, or the watchdog's,
    breaks a step with devices that does not return, so the devices still get their safe values. The
    supervisor's death is one request however often the kernel says it (once per exiting thread).

    With the supervisor gone, its watchdog and its kill of a task that does not stop are gone too:
    the task sets kernel timers for both (``orphan_limits_s``: the watchdog's limit, None when it is
    off, and when to end the process), so a step stuck then is still broken (its devices made safe)
    and the process still ends."""

    def __init__(self, control: WordBlock, orphan_limits_s: tuple[float | None, float] | None = None) -> None:
        self.control = control
        self.orphan_limits_s = orphan_limits_s
        self.count = 0
        self.supervisor_gone = False
        self.task: RealtimeTask | None = None
        """Set once the task exists: whether it is in its loop and owns devices."""

    def __call__(self, signum: int, _frame: Any) -> None:
        if signum == SUPERVISOR_GONE:
            if self.supervisor_gone:
                return
            self.supervisor_gone = True
            self._watch_without_supervisor()
        if signum != STEP_STUCK:
            self.count += 1
        self.control[ControlWord.STOP] = 1
        task = self.task
        if task is None or not task.in_loop:
            return
        if signum == STEP_STUCK and self.supervisor_gone:  # (no watchdog breaks a device-less task's step then)
            raise TimeoutError("stopped by its own watchdog after its supervisor died, while its step did not "
                               "return" + (" (the devices were made safe)" if task.devices else ""))
        if (signum == STEP_STUCK or self.count > 1) and task.devices:
            who = "the watchdog" if signum == STEP_STUCK else "a second stop request"
            raise TimeoutError(f"stopped by {who} while its step did not return (the devices were made safe)")

    def _watch_without_supervisor(self) -> None:
        if self.orphan_limits_s is None:
            return
        stuck_after_s, end_after_s = self.orphan_limits_s
        try:
            if stuck_after_s is not None:
                rt.signal_self_after(STEP_STUCK, stuck_after_s)
            rt.signal_self_after(signal.SIGKILL, end_after_s)
        except LibcError:
            pass  # (no timer left in this process's limit) the stop goes on in order all the same




class RealtimeTask:
    """The task's real-time loop, in its own process, over its :class:`TaskRun` (runtime/taskrun.py)."""

    def __init__(self, run: TaskRun) -> None:
        self.run = run
        self.in_loop = False
        """True while the loop runs: a stuck step there may be broken (safe values on the way out)."""
        self.on_snapshot: Any = None
        """Called with (next cycle, T0) when the supervisor asked for this task's state."""
        self.on_late: Any = None
        """Called with (cycle, its counters) after a cycle that missed its deadline (runtime/evidence.py)."""
        self.late_readings_left = LATE_READINGS_PER_RUN

    @property
    def devices(self) -> TaskDevices:
        return self.run.devices

    @property
    def cycle(self) -> int:
        """The cycle being computed (or last computed; -1 before the first), for fault reports."""
        return self.run.tick.cycle

    def run_loop(self, t0_ns: int, end_ns: int) -> None:
        """Run releases T0, T0+P, T0+2P, ... until ``end_ns`` or the stop flag."""
        run = self.run
        job, tick, limit = run.job, run.tick, run.config.max_consecutive_misses
        self.in_loop = True
        try:
            # The framework's share of a cycle, in C or in its readable Python twin (ipc/hotpath.py).
            cycle = run.start(t0_ns, end_ns)
            # Read → step → publish: begin() sleeps to the absolute release T0 + k·P (no drift)
            # and reads the inputs valid at it; finish() publishes the outputs as valid from
            # release + P (logical execution time), so the result does not depend on how fast
            # this cycle ran, records its timing and moves to the next release (after an overrun,
            # as the overrun policy says). The job (devices, then step) is the task's: runtime/taskrun.py.
            while cycle.begin():
                job(tick.cycle)
                done = cycle.finish()
                if done is True:  # on time: nothing more to do
                    continue
                if done == CYCLE_LATE:  # late: the thread's own counters, for the miss's cause, and only here
                    if self.late_readings_left and self.on_late is not None:
                        self.late_readings_left -= 1
                        self.on_late(tick.cycle, own_thread_counters(rt.now_ns()))
                elif done == SNAPSHOT_DUE:  # a --keep run wants the state here, to replay a window from it
                    self.on_snapshot(cycle.cycle, t0_ns)
                elif not done:  # too many deadline misses in a row (max_consecutive_misses)
                    raise DeadlineMissesExceeded(f"{counted(limit or 0, 'deadline miss', 'deadline misses')} in a row "
                                                 f"(max_consecutive_misses = {limit})")
        except StopRequested:
            raise  # an orderly end, said by the caller
        except BaseException:
            # Said before the way out leaves SCHED_FIFO: the supervisor, waiting on this core, runs
            # at once then, and must not take a task that is failing (a spin the kernel ended) for one
            # that is stuck.
            run.status[StatusWord.STATE] = TaskState.FAILED
            run.control[ControlWord.STOP] = 1  # the other tasks stop now, not when this process has exited
            raise
        finally:
            self.in_loop = False
            run.stop()  # safe values first, on every way out of the loop
            rt.leave_realtime()  # teardown (gc, postrun, reports) must not delay tasks still in their loop


def _report(pipe: Any, **message: Any) -> None:
    try:
        pipe.send(message)
    except (BrokenPipeError, OSError):
        pass  # the supervisor is gone; nothing to tell


def _wait_for_epoch(control: WordBlock) -> tuple[int, int]:
    while not control[ControlWord.T0_NS]:
        if control[ControlWord.STOP]:
            return 0, 0
        time.sleep(T0_POLL_S)
    return read_epoch(control)


def task_process_main(
    config: TaskConfig,
    runnable_bytes: bytes,
    plan: TaskWiringPlan,
    segments: TaskSegments,
    pipe: Any,
    devices: tuple[DeviceWiring, ...] | bytes = (),
    spin_limit_s: tuple[float, float] | None = None,
    start: ChildStart | None = None,
    orphan_limits_s: tuple[float | None, float] | None = None,
) -> None:
    """Entry point of a task process (started by the supervisor, forked from its task server or
    spawned: runtime/task_start.py). ``spin_limit_s``: how long the loop may run at a real-time
    priority without sleeping before it fails, then is killed. ``start``: what it puts back first.
    ``orphan_limits_s``: once the supervisor died, when a step that has not returned is broken (None:
    the watchdog is off) and when the process ends (:class:`StopRequests`)."""
    if start is not None:  # forked: the supervisor's environment and CPUs, not the server's
        start.adopt()
    # Ctrl-C reaches the whole process group; the supervisor decides when tasks stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # a closing terminal too: it stops the app through the supervisor
    control_segment = Segment.attach(segments.control)
    task_segment = Segment.attach(segments.task)
    control = WordBlock(control_segment, 0, CONTROL_WORDS)
    # SIGTERM (from a user, or from the kernel when the supervisor dies) stops the whole
    # app the orderly way: the loop sees the stop flag and postrun still runs.
    stop_in_order = StopRequests(control, orphan_limits_s)
    for signum in STOP_SIGNALS:
        signal.signal(signum, stop_in_order)
    rt.die_with_parent(SUPERVISOR_GONE)  # the parent: the task server when forked, which ends with the supervisor
    try:
        rt.become_subreaper()  # whatever step() forks, however it detaches, ends with this task:
    except OSError:
        pass  # refused (an old kernel, qemu-user 7.2): its direct children still end here
    multiprocessing.util.Finalize(None, rt.end_strays, exitpriority=100)
    if _supervisor_gone(start):  # it died before we could ask
        return
    status = WordBlock(task_segment, 0, STATUS_WORDS)
    timing = Int64Ring(task_segment, TASK_TIMING_OFFSET_BYTES)
    status[StatusWord.PID] = os.getpid()
    try:  # the runnable's class and modules load here: a failure is "loading", not prerun
        runnable: Runnable = loads_runnable(runnable_bytes)
        if isinstance(devices, bytes):
            devices = tuple(loads_runnable(devices))
    except BaseException as error:
        status[StatusWord.STATE] = TaskState.FAILED
        _report(pipe, kind="failed", phase="loading", cycle=None, reason=f"{type(error).__name__}: {error}",
                traceback=traceback.format_exc())
        raise SystemExit(1) from None

    settings = rt.apply_realtime(config.cpu, config.policy, config.priority, config.period_ns)
    # mlockall (on fault): no guard gaps, no OpenBLAS work buffer unless asked; the rest before T0
    unlocked = unlock_what_the_loop_never_needs(config.lock_blas_buffer) if settings.memory_locked else None
    status[StatusWord.CPU] = config.cpu if config.cpu is not None else -1
    _report(pipe, kind="settings", settings=settings)

    run = TaskRun(config, runnable, plan, control, status, timing, devices)
    task = stop_in_order.task = RealtimeTask(run)

    snapshots_lost: list[str] = []

    def send_snapshot(next_cycle: int, t0_ns: int) -> None:
        # Inside the loop: into a file of shared memory, never through the pipe (a full pipe blocks
        # until the supervisor reads it, and a large state fills it).
        wanted_ns = control[ControlWord.SNAPSHOT_NS]
        at_ns = wanted_ns - t0_ns
        why_not = ""
        if run.tick.release_ns - t0_ns >= at_ns:  # the request came after the task had passed that instant
            why_not = f"it was asked after it had passed t = {at_ns / 1e9} s"
        try:
            write_snapshot(snapshot_file_name(segments.task, wanted_ns), run.snapshot(at_ns, next_cycle, why_not))
        except OSError as error:  # no room in /dev/shm: counted and said at the end, the loop goes on
            snapshots_lost.append(f"its snapshot at t = {at_ns / 1e9} s was not kept: {error}")

    task.on_snapshot = send_snapshot
    baseline = own_thread_counters(rt.now_ns())  # the first late cycle's counters count from here
    task.on_late = lambda cycle, counters: _report(pipe, kind="late", cycle=cycle, counters=counters,
                                                   baseline=baseline)
    try:
        run.prepare()  # devices configured (a DeviceError is bad input, exit 2), prerun, initial outputs
        for text in getattr(getattr(runnable, "model", None), "start_notes", ()):  # an FMU's Event Mode refused
            _report(pipe, kind="note", text=text)
        # Collect before READY, not after T0: T0 follows the last READY by a short margin
        # (start_margin_ns), and a full collection takes ~5 ms here, several times that on a
        # small board, ~20 times under emulation; tasks sharing a CPU would pay it one after another.
        gc.collect()
        gc.freeze()  # everything alive now is never scanned again
        gc.disable()  # and no collection pauses inside the loop
        _take_back_stop_signals(stop_in_order, pipe)  # the runnable's code may have taken them over
        if unlocked is not None:  # every page the loop may touch, faulted in and locked now, not in a cycle
            for failed in lock_what_the_loop_touches(unlocked).failed[:1]:  # the loop may fault there, once per page
                _report(pipe, kind="note", text=f"mlock refused a mapping its loop may touch ({failed})")
            if start is not None and start.forked:  # and the library code the server's imports ran (linux/lean.py)
                for failed in lock_what_the_server_ran(start.parent_pid).failed[:1]:
                    _report(pipe, kind="note", text=f"could not lock what the task server's imports ran ({failed})")
            _report(pipe, kind="locked", bytes=memory.locked_bytes())
        status[StatusWord.STATE] = TaskState.READY
        t0_ns, end_ns = _wait_for_epoch(control)
        status[StatusWord.STATE] = TaskState.RUNNING
        if t0_ns:  # (0: stopped before T0)
            if settings.rt and spin_limit_s:
                _end_a_spin_after(*spin_limit_s, task)
            try:
                task.run_loop(t0_ns, end_ns)
            except StopRequested as request:  # the runnable ended the run (a model's end): stop in order
                _report(pipe, kind="finished", cycle=task.cycle, reason=str(request), safe_ns=run.safe_ns,
                        edge_ns=getattr(request, "timestamp_ns", None))
                control[ControlWord.STOP] = 1
        gc.enable()
        run.finish(failed=False)  # postrun
    except BaseException as error:
        # A failed task stops the app at once: the others must not go on (driving their devices from
        # this task's last outputs) while this one makes its devices safe, reports and runs postrun.
        control[ControlWord.STOP] = 1
        run.stop()  # safe values before anything else
        _report_devices(pipe, run)
        status[StatusWord.STATE] = TaskState.FAILED
        if isinstance(error, DeviceError) and run.phase == "configure":
            _report(pipe, kind="device_error", device=error.device, source=error.source, key=error.key,
                    problem=error.problem, mismatch=isinstance(error, DeviceMismatch))
        _report(
            pipe,
            kind="failed",
            phase=getattr(error, "phase", None) or run.phase,  # a device's fault says where in the cycle
            cycle=task.cycle if run.phase == "step" else None,
            reason=f"{type(error).__name__}: {error}",
            traceback="" if isinstance(error, DeadlineMissesExceeded) else traceback.format_exc(),
        )
        postrun_problem = run.finish(failed=True)  # its chance to put hardware safe (unless it was postrun)
        if postrun_problem:
            _report(pipe, kind="postrun_failed", traceback=postrun_problem)
        raise SystemExit(1) from None
    for text in snapshots_lost:
        _report(pipe, kind="note", text=text)
    status[StatusWord.STATE] = TaskState.STOPPED
    run.stop()  # done already unless the stop came before T0
    _report_devices(pipe, run)
    _report(pipe, kind="stopped", cycles=task.cycle + 1, catch_up_steps=getattr(runnable, "catch_up_steps", 0))


def _supervisor_gone(start: ChildStart | None) -> bool:
    """Whether the supervisor (or the task server between us) is gone: then no parent-death signal comes."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return False
    expected = start.parent_pid if start is not None else parent.pid
    if os.getppid() != expected:
        return True
    # forked: the server is our parent; the supervisor's end of the data pipe says whether it lives
    return bool(start is not None and start.forked and select.select([parent.sentinel], [], [], 0)[0])


def _take_back_stop_signals(handler: Any, pipe: Any) -> None:
    """Put rtloop's handler back where loading or prerun replaced it (rclpy and other libraries
    install their own SIGTERM handler; SIG_IGN would leave a loop nobody can stop), and say so."""
    for signum in STOP_SIGNALS:
        if signal.getsignal(signum) is not handler:
            signal.signal(signum, handler)
            name = {signal.SIGTERM: "SIGTERM", SUPERVISOR_GONE: "the supervisor's death signal"}.get(
                signum, "the watchdog's signal")
            _report(pipe, kind="note", text=f"its code replaced rtloop's handler of {name} (in loading or "
                    "prerun); rtloop put its own back, so a stop, and the supervisor's death, still stop the "
                    "loop in order")


def _end_a_spin_after(fail_s: float, kill_s: float, task: RealtimeTask) -> None:
    """The kernel's watchdog for a step that spins: the supervisor's needs CPU time, which busy
    real-time tasks on every core never leave it. SIGXCPU fails the step (safe values written on
    the way out), SIGKILL follows if it cannot (a loop inside C code)."""
    def fail(_signum: int, _frame: Any) -> None:
        if task.in_loop:  # the loop marks the task failed on its way out, before it leaves SCHED_FIFO
            raise WatchdogExpired(f"watchdog: ran {fail_s:g} s at a real-time priority without sleeping "
                                  "(the kernel's RLIMIT_RTTIME); the step is stuck in an endless loop")

    signal.signal(signal.SIGXCPU, fail)
    rt.limit_realtime_cpu(fail_s, kill_s)


def _report_devices(pipe: Any, run: TaskRun) -> None:
    """What went wrong while stopping the devices, what they read stale and how often their limits
    acted, and how often the guards of the task's connections did (summary.json)."""
    devices, wiring = run.devices, run.wiring
    if wiring.guards:
        _report(pipe, kind="input_limits", inputs=wiring.guards.counts(devices.task, run.runnable.input_names))
    if devices.problems:
        _report(pipe, kind="device_problems", problems=devices.problems)
    for slot in devices.slots:  # (configured ones: stop() has let go of them)
        for text in slot.device.run_notes():
            _report(pipe, kind="note", text=f"devices.{slot.device.name}: {text}")
    if devices:
        _report(pipe, kind="device_reads", devices=devices.stale_report())
