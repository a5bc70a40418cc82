"""Runnables used by the tests (importable by spawned task processes)."""

from __future__ import annotations

import os
import time
from pathlib import Path

from rtloop import Runnable


def busy_until(end_ns: int) -> None:
    """Spin on the CPU (no sleep: the task keeps its CPU) until CLOCK_MONOTONIC reaches ``end_ns``."""
    while time.monotonic_ns() < end_ns:
        pass


class Noop(Runnable):
    n_inputs = 0
    n_outputs = 0

    def step(self, u, y) -> None:
        pass


class Counter(Runnable):
    """y[0] = number of steps so far; y[1] = the tick's logical time in seconds."""

    n_inputs = 0
    n_outputs = 2

    def __init__(self) -> None:
        self.count = 0

    def step(self, u, y) -> None:
        self.count += 1
        y[0] = self.count
        y[1] = self.tick.time_s


class RaiseAt(Runnable):
    """Raises ZeroDivisionError in step at the first cycle at or after a given one (a real run on a
    loaded machine may skip that release; simulate never does)."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, cycle: int) -> None:
        self.fail_cycle = cycle

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.tick.cycle >= self.fail_cycle:
            1 / 0  # noqa: B018


class RaiseAtThenInPostrun(RaiseAt):
    """RaiseAt whose postrun raises too (a cleanup that trips over the state the fault left)."""

    def postrun(self) -> None:
        raise OSError("postrun could not close the port")


class RaiseFrom(RaiseAt):
    """Raises ZeroDivisionError in the first step at or after a given cycle (a late task may skip it)."""

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.tick.cycle >= self.fail_cycle:
            1 / 0  # noqa: B018


class ReportSettings(Runnable):
    """Outputs what the kernel says about this process: policy, priority, CPUs, locked kB."""

    n_inputs = 0
    n_outputs = 4

    def prerun(self) -> None:
        locked_kb = 0
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmLck:"):
                locked_kb = int(line.split()[1])
        cpus = sorted(os.sched_getaffinity(0))
        self.values = (
            float(os.sched_getscheduler(0)),
            float(os.sched_getparam(0).sched_priority),
            float(cpus[0] if len(cpus) == 1 else -1),
            float(locked_kb),
        )

    def step(self, u, y) -> None:
        y[:] = self.values


class Gain(Runnable):
    """y = gain · u + offset, over n values."""

    def __init__(self, n: int = 2, gain: float = 1.0, offset: float = 0.0) -> None:
        self.n_inputs = self.n_outputs = n
        self.gain, self.offset = gain, offset

    def step(self, u, y) -> None:
        y[:] = self.gain * u + self.offset


class SlowToStop(Runnable):
    """Does nothing each cycle; its postrun takes ``hold_s`` (a task that keeps a run's end waiting)."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle

    def postrun(self) -> None:
        time.sleep(self.hold_s)


class Integrator(Runnable):
    """Discrete plant: x += h·(u − x)·gain, y = x (per element); reacts one tick late."""

    def __init__(self, n: int = 2, gain: float = 3.0) -> None:
        self.n_inputs = self.n_outputs = n
        self.gain = gain
        self.x = [0.0] * n

    def step(self, u, y) -> None:
        h = self.tick.period_ns * 1e-9
        for i in range(self.n_outputs):
            self.x[i] += h * self.gain * (u[i] - self.x[i])
            y[i] = self.x[i]


class PiController(Runnable):
    """u = [measured (n), setpoint (n)], y = kp·e + ki·∫e."""

    def __init__(self, n: int = 2, kp: float = 2.0, ki: float = 5.0) -> None:
        self.n_inputs, self.n_outputs = 2 * n, n
        self.kp, self.ki = kp, ki
        self.integral = [0.0] * n

    def step(self, u, y) -> None:
        h = self.tick.period_ns * 1e-9
        n = self.n_outputs
        for i in range(n):
            error = u[n + i] - u[i]
            self.integral[i] += h * error
            y[i] = self.kp * error + self.ki * self.integral[i]


class Sleepy(Runnable):
    """Sleeps for a while in the first step at or after every ``every``-th release (to provoke
    overruns); y[0] counts the sleeps. "At or after": a loaded machine may skip that release."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, sleep_s: float, every: int = 1) -> None:
        self.sleep_s, self.every = sleep_s, every
        self.next_sleep = 0

    def step(self, u, y) -> None:
        if self.tick.cycle >= self.next_sleep:
            self.next_sleep = (self.tick.cycle // self.every + 1) * self.every
            time.sleep(self.sleep_s)
            y[0] += 1


class BadPrerun(Noop):
    def prerun(self) -> None:
        raise RuntimeError("sensor not found on /dev/ttyUSB0")


class SegfaultAt(Runnable):
    """Dereferences a null pointer at the first cycle at or after a given one (a loaded machine may
    skip that release): the task process dies with SIGSEGV."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, cycle: int) -> None:
        self.fail_cycle = cycle

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.tick.cycle >= self.fail_cycle:
            import ctypes

            ctypes.string_at(0)


class Fault(Runnable):
    """Misbehaves in one phase: raise, exit, segfault, fork (a detached process left running) or hang.

    In ``step`` it waits for ``at_cycle``; a forked process writes its pid to ``pid_file``.
    """

    n_inputs = 0
    n_outputs = 1

    def __init__(self, phase: str, kind: str, at_cycle: int = 3, pid_file: str = "") -> None:
        self.phase, self.kind, self.at_cycle, self.pid_file = phase, kind, at_cycle, pid_file

    def _misbehave(self) -> None:
        if self.kind == "raise":
            raise RuntimeError(f"injected in {self.phase}")
        if self.kind == "exit":
            os._exit(3)
        if self.kind == "segfault":
            import ctypes

            ctypes.string_at(0)
        if self.kind == "fork":
            if os.fork() == 0:  # detach: a new session, then the grandchild lives on alone
                os.setsid()
                if os.fork() == 0:  # written whole, then renamed: a reader never sees it empty
                    partial = Path(f"{self.pid_file}.partial")
                    partial.write_text(str(os.getpid()))
                    partial.rename(self.pid_file)
                    while True:
                        time.sleep(1)
                os._exit(0)
            os.wait()
            while not Path(self.pid_file).exists():
                time.sleep(0.01)
        if self.kind == "hang":
            while True:
                time.sleep(0.1)

    def prerun(self) -> None:
        if self.phase == "prerun":
            self._misbehave()

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.phase == "step" and self.tick.cycle == self.at_cycle:
            self._misbehave()

    def postrun(self) -> None:
        if self.phase == "postrun":
            self._misbehave()


class SpinFrom(Runnable):
    """From a given cycle on, never returns from step (an endless loop, as a bug would make);
    first writes the cycle it got stuck in to ``path``."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, cycle: int, path: str) -> None:
        self.stuck_cycle, self.path = cycle, path

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.tick.cycle >= self.stuck_cycle:
            Path(self.path).write_text(str(self.tick.cycle))
            while True:
                pass


class LateFrom(Runnable):
    """From a given cycle on, every step takes 1.5 periods: a deadline miss every cycle."""

    n_inputs = 0
    n_outputs = 0

    def __init__(self, cycle: int) -> None:
        self.late_cycle = cycle

    def step(self, u, y) -> None:
        if self.tick.cycle >= self.late_cycle:
            busy_until(self.tick.release_ns + self.tick.period_ns * 3 // 2)


class LateOnce(Runnable):
    """The first step from a given cycle on ends 3 periods after its release (a deadline miss)."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, cycle: int) -> None:
        self.late_cycle = cycle
        self.done = False

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.tick.cycle >= self.late_cycle and not self.done:
            self.done = True
            busy_until(self.tick.release_ns + self.tick.period_ns * 3)


class MatrixProduct(Runnable):
    """Multiplies two 3×3 matrices each step; y[0] = minor page faults the product took."""

    n_inputs = 0
    n_outputs = 1

    def prerun(self) -> None:
        import numpy as np

        self.a = np.arange(9.0).reshape(3, 3)
        self.b = np.eye(3)

    def step(self, u, y) -> None:
        import resource

        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        self.a @ self.b
        y[0] = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


class PolicyAfterLoop(Runnable):
    """Writes the scheduling policy its postrun runs under (``os.SCHED_*``) to ``path``."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, path: str) -> None:
        self.path = path

    def step(self, u, y) -> None:
        y[0] = os.sched_getscheduler(0)

    def postrun(self) -> None:
        Path(self.path).write_text(str(os.sched_getscheduler(0)))


class SlowIntegrator(Integrator):
    """An :class:`Integrator` whose step takes ``slow_s`` longer every ``every`` cycles (overruns on purpose)."""

    def __init__(self, n: int = 2, gain: float = 3.0, slow_s: float = 0.0025, every: int = 100) -> None:
        super().__init__(n, gain)
        self.slow_s, self.every = slow_s, every

    def step(self, u, y) -> None:
        super().step(u, y)
        if self.tick.cycle % self.every == self.every // 2:
            time.sleep(self.slow_s)


class StopAt(Counter):
    """Ends the run in order (StopRequested) at the first cycle at or after a given one."""

    def __init__(self, cycle: int) -> None:
        super().__init__()
        self.stop_cycle = cycle

    def step(self, u, y) -> None:
        super().step(u, y)
        if self.tick.cycle >= self.stop_cycle:
            from rtloop import StopRequested

            raise StopRequested(f"cycle {self.tick.cycle} reached")


class FailsWithSlowPostrun(Runnable):
    """Raises in step at ``fail_cycle`` (its message says when, in CLOCK_MONOTONIC ns: ``at NNN ns``),
    then takes ``postrun_s`` in postrun (None: hangs there until killed)."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, fail_cycle: int, postrun_s: float | None) -> None:
        self.fail_cycle, self.postrun_s = fail_cycle, postrun_s

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        if self.tick.cycle >= self.fail_cycle:
            raise RuntimeError(f"failed at {time.clock_gettime_ns(time.CLOCK_MONOTONIC)} ns")

    def postrun(self) -> None:
        if self.postrun_s is not None:
            time.sleep(self.postrun_s)
            return
        while True:  # a postrun that never returns (a device that does not answer)
            time.sleep(1)


class SpinFor(Runnable):
    """Every step busy-waits ``spin_ns`` from its start (a step longer than its period overruns)."""

    n_inputs = 0
    n_outputs = 0

    def __init__(self, spin_ns: int) -> None:
        self.spin_ns = spin_ns

    def step(self, u, y) -> None:
        busy_until(time.monotonic_ns() + self.spin_ns)


class TunedGain(Runnable):
    """y[0] = k, a live parameter (its only input): what a Parameters panel tunes."""

    n_inputs, n_outputs = 0, 1
    parameters = {"k": 2.0}  # noqa: RUF012 — live parameters are declared so

    def step(self, u, y) -> None:
        y[0] = self.k


class BigState(Counter):
    """A Counter with a large state (``n`` floats): its --keep snapshot is far above a pipe's 64 KiB."""

    def __init__(self, n: int = 40_000) -> None:
        super().__init__()
        import numpy

        self.big = numpy.arange(float(n))


class ThreadPageFaults(Runnable):
    """y[0] = page faults (minor + major) of the task's thread since prerun, read each step."""

    n_inputs = 0
    n_outputs = 1

    def prerun(self) -> None:
        import resource

        self.getrusage, self.who = resource.getrusage, resource.RUSAGE_THREAD
        usage = self.getrusage(self.who)
        self.before = usage.ru_minflt + usage.ru_majflt

    def step(self, u, y) -> None:
        usage = self.getrusage(self.who)
        y[0] = usage.ru_minflt + usage.ru_majflt - self.before
