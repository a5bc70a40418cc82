"""One task's lifecycle, the same object under the real-time clock and under the simulator's.

A :class:`TaskRun` owns what a task is while it runs: its inputs ``u`` and outputs ``y``, its
tick, its wiring to the other tasks, its devices and the per-cycle work of the hot path. Two
drivers use it and add only what is theirs:

- the task process (``runtime/task.py``) adds a process's concerns (signals, the supervisor's
  death, real-time settings, the garbage collector, pipe messages) and the real-time loop:
  ``while cycle.begin(): run.job(cycle); cycle.finish()``;
- the simulator (``runtime/simulate.py``) adds a logical clock: it releases every task's jobs in
  time order, reads the inputs and publishes the outputs with the same cycle work, without sleeping.

"Run equals simulate" holds because both call these methods, not two copies kept in step::

    prepare()          configure the devices, prerun, publish the initial outputs
    start(t0, end)     T0 known: the initial outputs stamped, the devices active, the cycle work built
    job(cycle)         devices at the release, the runnable's step, devices after the step
    stop()             the devices' safe values, the cycle work let go (every way out of the loop)
    finish(failed)     postrun: always, exactly once, whatever happened before
"""

from __future__ import annotations

import traceback
from collections.abc import Sequence

import numpy as np

from rtloop.app.specs import TaskConfig
from rtloop.io.host import DeviceWiring, TaskDevices
from rtloop.ipc.hotpath import CycleWork, Words, cycle_work
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.status import StatusWord, TaskState
from rtloop.ipc.wiring import TaskWiring, TaskWiringPlan
from rtloop.linux import rt
from rtloop.runnable import Runnable, TickInfo
from rtloop.runtime.snapshot import TaskSnapshot, take


class TaskRun:
    """A task from its prerun to its postrun (see the module's docstring for the order of calls)."""

    def __init__(self, config: TaskConfig, runnable: Runnable, plan: TaskWiringPlan, control: Words,
                 status: Words, timing: Int64Ring, devices: Sequence[DeviceWiring] = ()) -> None:
        self.config = config
        self.name = config.name
        self.period_ns = config.period_ns
        self.runnable = runnable
        self.control, self.status, self.timing = control, status, timing
        self.u = initial_inputs(runnable)
        self.y = np.zeros(runnable.n_outputs)
        self.tick = TickInfo(cycle=-1, period_ns=config.period_ns)
        runnable.tick = self.tick
        self.wiring = TaskWiring(plan, self.u, self.y, status)  # type: ignore[arg-type]  # a WordBlock or a dict
        self.devices = TaskDevices(config.name, config.period_ns, devices, self.u, self.y, self.wiring.sent)
        self._devices = self.devices or None  # None: a task without devices pays one test of None per job
        self.cycle: CycleWork | None = None
        """The hot path's per-cycle work (C or Python), built by :meth:`start`."""
        self.phase = "configure"
        """Where the task is, for a failure's report: configure, prerun, step, postrun."""
        self.safe_ns = 0
        """When the devices' safe values were written (CLOCK_MONOTONIC; 0: no devices, or not yet)."""
        self._prepare_begun = False
        self._finished = False

    def prepare(self) -> None:
        """Before T0: open and check the devices (a DeviceError is bad input), prerun, and publish
        the initial outputs (stamped at :meth:`start`, when T0 is known)."""
        self._prepare_begun = True
        self.phase = "configure"
        self.devices.configure()
        self.phase = "prerun"
        self.runnable.prerun()
        self.wiring.publish_initial(initial_outputs(self.runnable, self.y))

    def start(self, t0_ns: int, end_ns: int, *, stamped: bool = False) -> CycleWork:
        """T0 known: stamp the initial outputs (unless the caller did: a replay resuming from a snapshot),
        activate the devices and build the cycle work for releases T0 + k·P before ``end_ns``."""
        self.phase = "step"
        if not stamped:
            self.wiring.stamp_initial(t0_ns)
        config = self.config
        cycle = self.cycle = cycle_work(self.tick, self.wiring, self.control, self.status, self.timing,
                                        config.period_ns, catch_up=config.overrun == "catch_up",
                                        max_misses=config.max_consecutive_misses)
        cycle.start(t0_ns, end_ns, self.wiring.stale_reads)
        self.devices.activate(t0_ns, config.period_ns)
        return cycle

    def job(self, cycle: int) -> None:
        """The job released at ``cycle``, between the hot path's read of the inputs and its publish.

        Devices follow LET too (docs/devices.md): at the release they are written with the commands
        that hold from it (those of the job before) and read; then the runnable steps; then devices
        with ``io = "immediate"`` write at once.
        """
        devices = self._devices
        if devices:
            devices.at_release(cycle)
        self.runnable.step(self.u, self.y)  # the runnable's step: the one call of user code in a cycle
        if devices:
            devices.after_step(cycle)

    def stop(self) -> None:
        """The devices' safe values first, then let go of the cycle work (before the shared memory
        it views is unmapped). Safe to call more than once, and before :meth:`start`."""
        self.devices.stop()
        if self._devices is not None and not self.safe_ns:
            self.safe_ns = rt.now_ns()  # when they were written (an E-stop's report says it)
        if self.cycle is not None:
            self.cycle.close()

    def finish(self, failed: bool) -> str:
        """postrun, always and exactly once for a task whose :meth:`prepare` began: after a fault too,
        a chance to put hardware in a safe state (an FMU is terminated, its folder removed).

        ``failed``: the run failed already, so an exception of postrun is returned as its traceback
        ('' when none) rather than raised; otherwise it is raised (phase ``postrun``).
        """
        if self._finished or not self._prepare_begun:
            return ""
        self._finished = True
        if not failed:
            self.phase = "postrun"
            self.status[StatusWord.STATE] = TaskState.POSTRUN
            self.runnable.postrun()
            return ""
        try:
            self.runnable.postrun()
        except BaseException:
            return traceback.format_exc()
        return ""

    def close(self) -> None:
        """Let go of every view of shared memory (a simulator's process goes on after the run)."""
        if self.cycle is not None:
            self.cycle.close()
        self.wiring.close()

    def snapshot(self, at_ns: int, next_cycle: int, why_not: str = "") -> TaskSnapshot:
        """The task's state at ``at_ns`` (ns since T0) for a --keep window's replay: the runnable's saved
        state, ``u``, ``y``, the nudges its profiles hold and the samples still in its channel."""
        if not why_not and self.devices:
            why_not = "its devices' state is not saved"
        return take(self.name, self.runnable, at_ns, next_cycle, self.tick.cycle, self.u, self.y, why_not,
                    self.wiring.held_nudges(), self.wiring.recent_outputs())


def postrun_failed_note(task: str, traceback_text: str) -> str:
    """summary.json's note for a postrun that raised after the task had failed already (the first
    failure is the run's; this one would otherwise be lost): the exception's own line."""
    lines = [line for line in traceback_text.strip().splitlines() if line.strip()]
    return f"task {task}: its postrun failed too, after the failure: {lines[-1] if lines else '(no traceback)'}"


def initial_inputs(runnable: Runnable) -> np.ndarray:
    """The task's ``u`` before anything writes it: the model's input start values, or zeros."""
    u = np.zeros(runnable.n_inputs)
    starts = getattr(runnable, "input_start_values", None)
    if starts is not None:
        u[:] = starts
    runnable.bind_inputs(u)  # live parameters (self.kp) read their slots of u
    return u


def initial_outputs(runnable: Runnable, y: np.ndarray) -> np.ndarray:
    """The outputs a task shows before its first step: ``runnable.initial_outputs`` or zeros."""
    initial = getattr(runnable, "initial_outputs", None)
    if initial is not None:
        y[:] = initial
    return y
