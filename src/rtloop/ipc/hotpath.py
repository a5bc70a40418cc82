"""The framework's share of every cycle — sleep, read inputs, publish, record — in C or in Python.

A task's loop is ``while cycle.begin(): runnable.step(u, y); cycle.finish()``.
:class:`PythonCycle` below does that work in plain Python: it is the reference, read it
to see what happens in a cycle. ``_hotpath.Core`` (``_hotpath.c``) does exactly the same
over the same shared memory in two C calls, for a fraction of the cost. It is used when
it was built (pip builds it with the system compiler) unless ``RTLOOP_PURE_PYTHON=1``;
the tests run both and check they give the same signals (the pattern of CPython's
``bisect`` and ``_bisect``).
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Protocol

import numpy as np

from rtloop import build_check
from rtloop.errors import NonFiniteOutput
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import STOP_POLL_NS, ControlWord, StatusWord, constants
from rtloop.ipc.wiring import TaskWiring
from rtloop.linux.rt import AbsoluteSleeper, now_ns

SOURCES = ["_hotpath.c", "_schema.h"]
"""What the C hot path is built from (setup.py: HOTPATH_SOURCES)."""

_hotpath: ModuleType | None
try:
    _hotpath = importlib.import_module("rtloop.ipc._hotpath")  # by name: C, which mypy cannot read
except ImportError as error:  # no compiler when the package was installed
    _hotpath = None
    _NOT_BUILT = f"the C hot path rtloop.ipc._hotpath is not built ({error})"
else:
    _differ = sorted(name for name, value in constants().items() if getattr(_hotpath, "SCHEMA", {}).get(name) != value)
    # A stale build (an older schema.py) would read and write the wrong words: use Python instead.
    _NOT_BUILT = f"the C hot path was built from another schema (differs in {', '.join(_differ)}): rebuild it" \
        if _differ else ""
    # ... and one older than _hotpath.c would be called with arguments it does not take (where the
    # sources are here to tell: a checkout; an installed wheel was built in one go)
    _NOT_BUILT = _NOT_BUILT or build_check.stale_build(
        _hotpath, "the C hot path (rtloop.ipc._hotpath)",
        build_check.sources_digest(Path(__file__).resolve().parent, SOURCES), "ipc/_hotpath.c and ipc/_schema.h")

PURE_PYTHON_ENV = "RTLOOP_PURE_PYTHON"
SNAPSHOT_DUE = 2
"""What ``finish()`` returns when the supervisor asked for the task's state before the next release."""
CYCLE_LATE = 3
"""What ``finish()`` returns after a cycle that ended past its deadline (and the task goes on): the one
branch in which the loop reads the thread's own counters, for the miss's cause (runtime/evidence.py)."""
_announced = False


def c_built() -> bool:
    """Whether the C hot path was built (pip needs a compiler for it) from this schema."""
    return _hotpath is not None and not _NOT_BUILT


class Tick(Protocol):
    """What a cycle tells the runnable (``TickInfo``)."""

    cycle: int
    release_ns: int
    start_ns: int


class Words(Protocol):
    """A block of int64 words indexed by a schema enum (``status.WordBlock``)."""

    words: memoryview

    def __getitem__(self, word: int) -> int: ...
    def __setitem__(self, word: int, value: int) -> None: ...


class CycleWork(Protocol):
    """One task's per-cycle framework work: ``PythonCycle`` or ``_hotpath.Core``."""

    cycle: int
    """The cycle begin() runs next (or runs now)."""
    release_ns: int
    """Its release time."""

    @property
    def stale_reads(self) -> int: ...
    def start(self, t0_ns: int, end_ns: int, stale_reads: int) -> None: ...
    def begin(self) -> bool: ...
    def finish(self) -> bool | int: ...
    def begin_at(self, start_ns: int) -> bool: ...
    def finish_at(self, end_ns: int) -> bool | int: ...
    def read_inputs(self, release_ns: int, instead: dict[int, np.ndarray | None] | None = None) -> None: ...
    def publish_outputs(self, cycle: int, publish_ns: int) -> None: ...
    def close(self) -> None: ...


def why_python() -> str:
    """Why the Python hot path is in use here ("" when the C one is)."""
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return f"{PURE_PYTHON_ENV}={os.environ[PURE_PYTHON_ENV]}"
    return _NOT_BUILT


def hot_path() -> str:
    """``c`` or ``python``: which implementation a task started now would use."""
    return "python" if why_python() else "c"


def announce_once() -> None:
    """Say, once per process, that the slower Python path is in use and why."""
    global _announced
    reason = why_python()
    if reason and not _announced:
        _announced = True
        print(f"rtloop: per-cycle work runs in Python, not C: {reason}", file=sys.stderr)


class PythonCycle:
    """One task's per-cycle framework work, in Python (the reference for ``_hotpath.Core``)."""

    def __init__(self, tick: Tick, wiring: TaskWiring, control: Words, status: Words, timing: Int64Ring,
                 period_ns: int, catch_up: bool, max_misses: int | None = None) -> None:
        self.tick, self.wiring, self.control, self.status, self.timing = tick, wiring, control, status, timing
        self.period_ns, self.catch_up, self.max_misses = period_ns, catch_up, max_misses
        self.misses_in_a_row = 0
        self.snapshot_taken_ns = 0
        self.sleeper = AbsoluteSleeper()
        self.t0_ns = self.end_ns = self.cycle = self.release_ns = self.start_ns = self.last_end_ns = 0

    def start(self, t0_ns: int, end_ns: int, stale_reads: int) -> None:
        self.t0_ns, self.end_ns = t0_ns, end_ns
        self.cycle, self.release_ns = 0, t0_ns
        self.last_end_ns = now_ns()
        self.wiring.stale_reads = stale_reads

    @property
    def stale_reads(self) -> int:
        return self.wiring.stale_reads

    def begin(self) -> bool:
        """Sleep to the release, then read the inputs valid at it. False: time to stop."""
        if self.release_ns >= self.end_ns or self.control[ControlWord.STOP]:
            return False
        if not self.sleep_until_release(self.release_ns):
            return False
        return self._start_cycle(now_ns())

    def begin_at(self, start_ns: int) -> bool:
        """``begin()`` on a given clock, without sleeping: the seam the twins' tests drive."""
        if self.release_ns >= self.end_ns or self.control[ControlWord.STOP]:
            return False
        return self._start_cycle(start_ns)

    def _start_cycle(self, start_ns: int) -> bool:
        release_ns = self.release_ns
        self.start_ns = start_ns
        tick = self.tick
        tick.cycle, tick.release_ns, tick.start_ns = self.cycle, release_ns, self.start_ns
        self.wiring.read_inputs(release_ns, self.wiring.u)
        return True

    def sleep_until_release(self, release_ns: int) -> bool:
        """Sleep to the release (absolute time: no drift, unlike sleep(P - elapsed)); False: stop.

        A stop request is seen within STOP_POLL_NS however long the period (a long sleep
        wakes every STOP_POLL_NS before the release to look), and at once after a signal."""
        while True:
            wake_ns = release_ns
            if release_ns - self.last_end_ns > STOP_POLL_NS:  # a long sleep: cut it into slices
                left_ns = release_ns - now_ns()
                if left_ns > STOP_POLL_NS:
                    wake_ns = release_ns - (left_ns - 1) // STOP_POLL_NS * STOP_POLL_NS
            if self.sleeper.sleep_or_signal(wake_ns) and wake_ns == release_ns:
                return True
            if self.control[ControlWord.STOP]:
                return False

    def finish(self) -> bool | int:
        """Publish outputs valid from release + P, record the cycle, move to the next release.

        False: this was the ``max_misses``-th deadline miss in a row (the task should stop);
        ``SNAPSHOT_DUE``: the supervisor asked for the task's state before the next release;
        ``CYCLE_LATE``: this cycle missed its deadline; True: it was on time."""
        self._publish()
        return self._end_cycle(now_ns())

    def finish_at(self, end_ns: int) -> bool | int:
        """``finish()`` on a given clock: the seam the twins' tests drive."""
        self._publish()
        return self._end_cycle(end_ns)

    def _publish(self) -> None:
        self.wiring.publish_outputs(self.cycle, self.release_ns + self.period_ns, self.wiring.y)

    def _end_cycle(self, end_ns: int) -> bool | int:
        cycle, release_ns, start_ns, period_ns = self.cycle, self.release_ns, self.start_ns, self.period_ns
        self.last_end_ns = end_ns
        self.timing.push4(cycle, release_ns, start_ns, end_ns)
        status = self.status
        status[StatusWord.CYCLE] = cycle
        status[StatusWord.LATENCY_LAST_NS] = start_ns - release_ns
        status[StatusWord.EXEC_LAST_NS] = end_ns - start_ns
        cycle += 1
        release_ns += period_ns
        go_on: bool | int = True
        if end_ns > release_ns:  # overran into the next period
            status[StatusWord.DEADLINE_MISSES] += 1
            self.misses_in_a_row += 1
            if self.misses_in_a_row > status[StatusWord.MISSES_IN_A_ROW_MAX]:
                status[StatusWord.MISSES_IN_A_ROW_MAX] = self.misses_in_a_row
            go_on = self.max_misses is None or self.misses_in_a_row < self.max_misses
            skipped, first_missed_ns = 1, release_ns
            if not self.catch_up:  # skip the releases already missed
                next_cycle = (end_ns - self.t0_ns) // period_ns + 1
                skipped = next_cycle - cycle
                cycle, release_ns = next_cycle, self.t0_ns + next_cycle * period_ns
            left_ns = self.end_ns - first_missed_ns  # releases at or after the run's end are no overruns
            skipped = min(skipped, max(0, -(-left_ns // period_ns)))
            status[StatusWord.OVERRUNS] += skipped
            go_on = go_on and CYCLE_LATE
        else:
            self.misses_in_a_row = 0
        self.cycle, self.release_ns = cycle, release_ns
        wanted_ns = self.control[ControlWord.SNAPSHOT_NS]
        if go_on and wanted_ns > self.snapshot_taken_ns and release_ns >= wanted_ns:
            self.snapshot_taken_ns = wanted_ns
            return SNAPSHOT_DUE
        return go_on

    def close(self) -> None:
        """Nothing to let go of here (the C twin releases its hold on the shared memory)."""

    # --- the simulator's steps: no clock ---------------------------------------------------
    def read_inputs(self, release_ns: int, instead: dict[int, np.ndarray | None] | None = None) -> None:
        self.wiring.read_inputs(release_ns, self.wiring.u, instead)

    def publish_outputs(self, cycle: int, publish_ns: int) -> None:
        self.wiring.publish_outputs(cycle, publish_ns, self.wiring.y)


def _index_in(base: np.ndarray, view: np.ndarray) -> int:
    """Where the numpy view ``view`` starts inside ``base`` (in float64 elements)."""
    start: int = view.__array_interface__["data"][0] - base.__array_interface__["data"][0]
    return start // 8


def compiled_cycle(tick: Tick, wiring: TaskWiring, control: Words, status: Words, timing: Int64Ring,
                   period_ns: int, catch_up: bool, max_misses: int | None = None) -> CycleWork:
    """A ``_hotpath.Core`` over the same shared memory as ``wiring``."""
    if _hotpath is None or _NOT_BUILT:
        raise RuntimeError(_NOT_BUILT)
    u, y = wiring.u, wiring.y
    core = _hotpath.Core(tick, u, y, control.words, status.words, timing.memory, period_ns, catch_up,
                         max_misses or 0)
    for link in wiring.links:
        core.add_input(link.channel.words, link.period_ns, link.first, len(link.scratch), link.spans)
    for port, target, index in wiring.live_ports:
        if np.shares_memory(target, u):
            core.add_live_port(port.words, _index_in(u, target), len(target), port.last_seq_seen, index)
        else:  # a profile's live nudges: into their own buffer, which the profile adds or copies
            core.add_live_port(port.words, 0, len(target), port.last_seq_seen, index, target)
    if wiring.input_log is not None:
        core.set_input_log(wiring.input_log.words)
    if wiring.read_log is not None:
        core.set_read_log(wiring.read_log.memory)
    for reader in wiring.profiles:
        t_ns = np.ascontiguousarray(reader.profile.t_ns, dtype=np.int64)
        rows = np.ascontiguousarray(reader.profile.values, dtype=np.float64)
        core.add_profile(t_ns, rows, _index_in(u, reader.target), len(reader.target), reader.index,
                         reader.live_port, reader.mode)
    if wiring.output is not None:
        core.set_output(wiring.output.words)
    for queue, source in wiring.output_ports:
        core.add_output_port(queue.words, _index_in(y, source))
    if wiring.record is not None:
        core.set_record(wiring.record.words, wiring.sent)
    guards = wiring.guards
    if guards:
        core.set_input_guards(guards.indices, guards.low, guards.high, guards.step_max, guards.last, guards.clamped,
                              guards.rate_limited)
    if wiring.finite_checks:
        checks = wiring.finite_checks
        core.set_finite_check(tuple(c.index for c in checks), tuple(c.fault for c in checks),
                              tuple(c.label for c in checks), NonFiniteOutput)
    work: CycleWork = core
    return work


def cycle_work(tick: Tick, wiring: TaskWiring, control: Words, status: Words, timing: Int64Ring,
               period_ns: int, catch_up: bool, max_misses: int | None = None) -> CycleWork:
    """The per-cycle work of a task, built once before its loop: C when available, else Python."""
    kind: Callable[..., CycleWork] = compiled_cycle if hot_path() == "c" else PythonCycle
    return kind(tick, wiring, control, status, timing, period_ns, catch_up, max_misses)
