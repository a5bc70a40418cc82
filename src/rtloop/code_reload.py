"""Reloading a controller's edited code into a running task, outside its real-time loop.

``rtloop reload`` keeps the edited module in the run's folder (``code/<controller>-<id>.py``,
``id``: the first 48 bits of its SHA-256, in hex) and asks the task, through its switch port,
for that code at a release. In the task process a :class:`CodeReloader` thread, started before
T0 and parked on a pipe, does everything that imports and allocates: it reads the file (owned by
the run's user, not a link, its content matching its id), executes it as a fresh module, builds
the controller again with the state it was built with (its constructor's work, kept as a copy),
checks it (a Runnable, the same sizes, ``prerun``, a dry step on a copy with the current inputs:
finite outputs within the task's period) and hands the result back. The loop only swaps one
object for another at the release asked for, bumpless (:mod:`rtloop.switching`).

In a real-time task the thread runs under ``SCHED_FIFO`` at priority 1 (:data:`RELOAD_PRIORITY`), so
it runs only while the loop sleeps, and in a real run it works only in the loop's slack
(:class:`SlackGate`): near a release it lets the interpreter's lock go until the loop has stepped,
so the loop, waking, finds the lock free instead of waiting for the switch interval (50 µs here) and
for the thread's next check. docs/switching.md says what that costs, and what caused the misses it had.

In ``simulate`` and ``replay`` the loop waits for the reloader at the release (``wait = True``),
so the reloaded code acts at the same cycle as in the run; ``replay`` reads the code the run kept.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import hashlib
import importlib.util
import json
import marshal
import math
import os
import stat
import sys
import threading
import time
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.errors import RtloopError
from rtloop.runnable import Runnable, TickInfo

CODE_ID_HEX_DIGITS = 12
"""An id of 48 bits: a float holds it exactly, so it travels through a port as one value."""
RELOAD_SWITCH_INTERVAL_S = 50e-6
"""The interpreter's switch interval while a reload is prepared: how long the loop, waking, may
wait for the lock the reloader holds (CPython's default is 5 ms)."""
RELOAD_PRIORITY = 1
"""The reload thread's SCHED_FIFO priority in a real-time task: below every task (1 is the lowest), above
every SCHED_OTHER thread. Under SCHED_OTHER, the thread could be preempted by any busy process while it
held the interpreter's lock, and the loop, waking, waited for it as long (a priority inversion: up to
108 ms and 28 deadline misses at 1 kHz while a reload was prepared on a loaded machine,
benchmarks/bench_switch.py). At priority 1 it runs only while the loop sleeps, and gives the lock back
as soon as the loop asks for it."""
THREAD_STACK_BYTES = 512 * 1024
"""The reloader's stack (locked memory, as the task's is): not the default 8 MB."""
SLACK_MARGIN_NS = 500_000
"""How close to a release the reload thread stops and lets the interpreter's lock go (:class:`SlackGate`),
at most half the period. It is there for the single C calls a preparation makes, which no Python-level
check can cut: measured in reloads of examples/jiwy/jiwy_models.py beside a 1 kHz loop on this 2-core VM
(benchmarks/bench_switch.py with a kernel trace of the CPU, and a loop thread noting where the reloader
stood when it let go), the compilation of one method a ``@dataclass`` generates took 0.1-0.7 ms,
``marshal.loads`` of the module 0.1-0.5 ms. A C call begun just before the margin delays the loop's wake-up
by what it lasts beyond it (with 300 µs, one ran 0.5 ms past it: a wake-up 235 µs late); a wider margin
leaves the thread less of each period (it then takes longer to prepare, not the loop)."""
SLACK_POLL_S = 20e-6
"""While waiting for the loop's step after a release, how often the reload thread looks (it sleeps between)."""
PREPARE_DEADLINE_S = 5.0
"""How long a reload's preparation (executing the module, building, prerun, the dry step) may take
before it is stopped and refused (:class:`PreparationDeadline`). A module that spins at import or a
dry step that never returns held the reload thread at SCHED_FIFO for good: after 10 s the kernel's
RLIMIT_RTTIME (the task's spin watchdog, at least 10 s) ended the whole run as 'the step is stuck',
and a SCHED_OTHER task's reloader never answered again. Below that watchdog, above what a module's
import takes in the loop's slack (jiwy_models.py: 10 ms)."""
PHASES = ("asked", "read", "executed", "built", "dry_step", "prerun", "ready")
"""The reload's timeline, stamped (CLOCK_MONOTONIC ns) as each phase ends and kept in its result file:
``asked`` when the thread took the request, ``read`` the kept code, ``executed`` the module, ``built`` the
controller twice (the one that acts, and a copy for the dry step), ``dry_step`` the copy's step, ``prerun``
the new controller's, ``ready`` handed to the loop. benchmarks/bench_switch.py lines the loop's late
wake-ups up against it."""


def code_id_of(source: bytes) -> int:
    return int(hashlib.sha256(source).hexdigest()[:CODE_ID_HEX_DIGITS], 16)


def code_file_name(controller: str, code_id: int) -> str:
    return f"{controller}-{code_id:0{CODE_ID_HEX_DIGITS}x}.py"


def compiled_file_name(controller: str, code_id: int) -> str:
    return f"{controller}-{code_id:0{CODE_ID_HEX_DIGITS}x}.code"


def compiled_code(source: bytes, path: Path, code_id: int) -> bytes:
    """``source`` (kept at ``path``, named by ``code_id``) compiled, as ``rtloop reload`` keeps it beside
    the source: this interpreter's magic number, the id (8 bytes), then the marshalled code object.
    Compiling a module is one long C call that holds the interpreter's lock (9 ms for jiwy_models.py
    here): done in the command, the task's reload thread only loads it (75 µs), so the loop, waking,
    never waits for a compilation."""
    return importlib.util.MAGIC_NUMBER + code_id.to_bytes(8, "little") + marshal.dumps(
        compile(source, str(path), "exec"))


def result_file_name(controller: str, code_id: int) -> str:
    return f"{controller}-{code_id:0{CODE_ID_HEX_DIGITS}x}.result.json"


class CodeReloader:
    """The task's reload thread (see the module doc). ``owner`` is the task's ``Controllers``."""

    def __init__(self, owner: Any, code_dir: Path, pristine: list[Runnable | None], *, wait: bool) -> None:
        self.owner, self.code_dir, self.pristine, self.wait = owner, code_dir, pristine, wait
        self.request_index = -1
        self.request_code = 0
        self.ready_code = 0
        """The code id of :attr:`ready_runnable` once it is ready (0: nothing ready)."""
        self.ready_runnable: Runnable | None = None
        self.failed_code = 0
        self.done = threading.Event()
        self.finished: set[int] = set()
        """Code ids the thread has answered (ready or refused)."""
        self.retired: list[Runnable] = []
        self.gate: SlackGate | None = None
        """While a reload is prepared in a real run: what keeps the thread to the loop's slack."""
        self.timeline_ns = [0] * len(PHASES)
        """The last reload's timeline (:data:`PHASES`; 0: a phase not reached)."""
        self._wake_r, self._wake_w = os.pipe()
        previous = threading.stack_size(THREAD_STACK_BYTES)
        try:
            self.thread = threading.Thread(target=self._serve, name="rtloop-reload", daemon=True)
            self.thread.start()
            self.deadline = PreparationDeadline(self.thread, PREPARE_DEADLINE_S)
        finally:
            threading.stack_size(previous)

    # --- the loop's side: no import, no allocation beyond a one-byte write ----------------------
    def ask(self, index: int, code_id: int) -> None:
        self.request_index, self.request_code = index, code_id
        self.ready_code = 0
        self.finished.discard(code_id)  # the same file asked again for another controller: wait for this answer
        self.done.clear()
        os.write(self._wake_w, b"r")

    def take(self, code_id: int) -> Runnable | None:
        """The controller built from ``code_id`` if it is ready (in simulate: once it is)."""
        while self.wait and code_id not in self.finished:  # that code's answer, not an earlier request's
            self.done.wait(0.05)
            self.done.clear()
        if self.ready_code == code_id:
            runnable, self.ready_runnable, self.ready_code = self.ready_runnable, None, 0
            return runnable
        return None

    def build_now(self, index: int, code_id: int) -> Runnable:
        """Controller ``index`` built from kept code, before the run (a replay starts with the code the
        run started with). Its prerun is the caller's."""
        name = self.owner.names[index]
        source = self._read(code_file_name(name, code_id), code_id)
        return self._build(index, self._module(index, name, code_id, source))

    def retire(self, runnable: Runnable) -> None:
        """The replaced controller: its postrun runs in the reloader's thread, not in the loop."""
        self.retired.append(runnable)
        os.write(self._wake_w, b"p")

    def close(self) -> None:
        """After the loop: the retired controllers' postrun, then the thread ends."""
        os.write(self._wake_w, b"q")
        self.thread.join(timeout=10)
        self.deadline.close()
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)

    # --- the reloader's thread ----------------------------------------------------------------
    def _serve(self) -> None:
        try:  # this thread only (Linux: 0 is the calling thread): it inherited the loop's policy and priority
            os.sched_setscheduler(0, *reload_thread_policy(os.sched_getscheduler(0)))
        except (OSError, AttributeError):
            pass
        while True:
            what = os.read(self._wake_r, 1)
            if what == b"q" or not what:  # after the loop: no release to keep clear of
                self._postrun_retired()
                return
            with self._in_the_loops_slack():  # everything it does while the loop runs, the answer's file too
                if what == b"p":
                    self._postrun_retired()
                    continue
                index, code_id = self.request_index, self.request_code
                self.timeline_ns = [0] * len(PHASES)
                result = self._prepare_in_time(index, code_id)
                result["timeline_ns"] = dict(zip(PHASES, self.timeline_ns, strict=True))
                if self.gate is not None:
                    result["slack_waits"], result["slack_waited_ns"] = self.gate.waits, self.gate.waited_ns
                if not self.wait:  # the answer `rtloop reload` waits for; a replay must not overwrite the run's
                    self._write_result(index, code_id, result)
            self.finished.add(code_id)
            self.done.set()

    @contextlib.contextmanager
    def _in_the_loops_slack(self) -> Iterator[None]:
        """The reload switch interval and, in a real run, the :class:`SlackGate` (simulate and replay have none:
        their loop waits for the reloader)."""
        previous = sys.getswitchinterval()
        sys.setswitchinterval(RELOAD_SWITCH_INTERVAL_S)
        self.gate = None if self.wait else SlackGate(self.owner)
        if self.gate is not None:
            sys.setprofile(self.gate.hook())  # this thread's only
        try:
            yield
        finally:
            sys.setprofile(None)
            sys.setswitchinterval(previous)

    def _postrun_retired(self) -> None:
        while self.retired:
            try:
                self.retired.pop().postrun()
            except Exception:
                pass  # the code that replaced it runs on; a failing cleanup of old code stops nothing

    def _prepare_in_time(self, index: int, code_id: int) -> dict[str, Any]:
        """:meth:`_prepare` under the :class:`PreparationDeadline`: past it, refused."""
        self.deadline.arm()
        try:
            return self._prepare(index, code_id)
        except PreparationOverran as overran:  # delivered after the preparation's own handlers: still refused
            self.failed_code = code_id
            return {"accepted": False, "reason": str(overran)}
        finally:
            self.deadline.disarm()

    def _prepare(self, index: int, code_id: int) -> dict[str, Any]:
        owner = self.owner
        name = owner.names[index]
        stamp = self._stamp
        stamp("asked")
        try:
            source = self._read(code_file_name(name, code_id), code_id)
            stamp("read")
            module = self._module(index, name, code_id, source)
            stamp("executed")
            built = self._build(index, module)
            dry = self._build(index, module)
            stamp("built")
            dry_ns = self._dry_step(dry, index)
            stamp("dry_step")
            built.tick = owner.tick
            built.bind_inputs(owner.own_inputs(index))
            built.prerun()
            stamp("prerun")
            self.deadline.disarm()  # from here on nothing can stop it half-way: it is ready
        except ReloadRefused as refusal:
            self.failed_code = code_id
            return {"accepted": False, "reason": str(refusal)}
        except Exception as error:  # the user's new code failed: the old code keeps running
            self.failed_code = code_id
            where = _user_frame(error, str(self.code_dir))
            return {"accepted": False, "reason": f"{type(error).__name__}: {error}{where}"}
        self.ready_runnable = built
        self.ready_code = code_id
        stamp("ready")
        return {"accepted": True, "dry_step_ns": dry_ns, "ready_ns": self.timeline_ns[PHASES.index("ready")]}

    def _stamp(self, phase: str) -> None:
        self.timeline_ns[PHASES.index(phase)] = time.clock_gettime_ns(time.CLOCK_MONOTONIC)

    def _module(self, index: int, name: str, code_id: int, source: bytes) -> types.ModuleType:
        """The kept code executed as a fresh module (named as the controller's own, not registered)."""
        old = self.owner.alternatives[index]
        module_name = type(old).__module__
        if module_name == "__main__":
            raise ReloadRefused(f"{type(old).__name__} is defined in the script that started the app; "
                                "put it in a module of its own to reload it")
        module = types.ModuleType(module_name)
        module.__file__ = str(self.code_dir / code_file_name(name, code_id))
        code = self._compiled(name, code_id, module.__file__)
        if code is None:  # no compiled copy (simulate fed from a profile, another interpreter): compile it here
            code = compile(source, module.__file__, "exec")
        exec(code, module.__dict__)
        return module

    def _compiled(self, name: str, code_id: int, file_name: str) -> types.CodeType | None:
        """The code ``rtloop reload`` compiled (:func:`compiled_code`), if it is there, this run user's,
        for this interpreter and this code; else None."""
        try:
            data = self._read_own(self.code_dir / compiled_file_name(name, code_id))
        except ReloadRefused:
            return None
        head = importlib.util.MAGIC_NUMBER + code_id.to_bytes(8, "little")
        if not data.startswith(head):
            return None
        try:
            code = marshal.loads(data[len(head):])
        except (ValueError, EOFError, TypeError):
            return None
        return code if isinstance(code, types.CodeType) and code.co_filename == file_name else None

    def _read(self, file_name: str, code_id: int) -> bytes:
        path = self.code_dir / file_name
        source = self._read_own(path)
        if code_id_of(source) != code_id:
            raise ReloadRefused(f"{path}: its content does not match its name; not loaded")
        return source

    @staticmethod
    def _read_own(path: Path) -> bytes:
        """A file of the run's user (not a link), whole."""
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError as error:
            raise ReloadRefused(f"{path}: {error.strerror}") from None
        try:
            info = os.fstat(fd)
            if not stat.S_ISREG(info.st_mode) or info.st_uid != os.geteuid():
                raise ReloadRefused(f"{path} is not a file of this run's user; not loaded")
            data = b""
            while chunk := os.read(fd, 1 << 16):
                data += chunk
        finally:
            os.close(fd)
        return data

    def _build(self, index: int, module: types.ModuleType) -> Runnable:
        """The controller as it was built, of the new module's class (its constructor's state kept)."""
        old = self.owner.alternatives[index]
        cls = getattr(module, type(old).__qualname__, None)
        if not isinstance(cls, type) or not issubclass(cls, Runnable):
            raise ReloadRefused(f"the new code has no Runnable {type(old).__qualname__!r}")
        pristine = self.pristine[index]
        if pristine is None:
            raise ReloadRefused(f"{type(old).__name__}'s state could not be copied when the task started: "
                                "it cannot be built again")
        built = cls.__new__(cls)  # with what its constructor made, before any prerun (itself: the new object)
        built.__dict__.update(copy.deepcopy(vars(pristine), {id(pristine): built}))
        sizes = (built.n_inputs, built.n_outputs)
        if sizes != (old.n_inputs, old.n_outputs):
            raise ReloadRefused(f"the new code has {sizes[0]} inputs and {sizes[1]} outputs, the task "
                                f"{old.n_inputs} and {old.n_outputs}: a reload keeps the task's sizes")
        return built

    def _dry_step(self, dry: Runnable, index: int) -> int:
        """One step of a copy on the inputs of now: finite outputs, within the period (not in simulate)."""
        owner = self.owner
        tick = owner.tick
        dry.tick = TickInfo(tick.cycle, tick.release_ns, tick.start_ns, tick.period_ns)
        u = np.array(owner.own_inputs(index))
        y = np.zeros(dry.n_outputs)
        dry.bind_inputs(u)
        dry.prerun()
        gate = self.gate
        if gate is not None:  # timed without the gate's own cost, begun just after the loop's step
            sys.setprofile(None)
            gate.at_margin(whatever_is_left=True)
        try:
            started_ns = time.thread_time_ns()
            dry.step(u, y)
            took_ns = time.thread_time_ns() - started_ns
        finally:
            if gate is not None:
                sys.setprofile(gate.hook())
            dry.postrun()
        if not all(math.isfinite(value) for value in y.tolist()):
            raise ReloadRefused(f"its dry step on the current inputs gave {y.tolist()}: not finite")
        if not self.wait and tick.period_ns and took_ns > tick.period_ns:
            raise ReloadRefused(f"its dry step took {took_ns / 1e3:.0f} µs of CPU, more than the task's period "
                                f"({tick.period_ns / 1e3:.0f} µs)")
        return took_ns

    def _write_result(self, index: int, code_id: int, result: dict[str, Any]) -> None:
        path = self.code_dir / result_file_name(self.owner.names[index], code_id)
        try:
            temporary = path.with_suffix(".tmp")
            temporary.write_text(json.dumps(result) + "\n")
            os.replace(temporary, path)
        except OSError:
            pass  # the command then says it had no answer; the loop takes the code if it is ready


class SlackGate:
    """The reload thread works only in its loop's slack: a profile function of that thread alone
    (``sys.setprofile`` in it: called at each Python call and return and before each C call) that, once the
    next release (T0 + k·P, from the task's tick) is nearer than ``margin_ns``, sleeps until that release,
    then until the loop has stepped at it (``owner.stepped_release_ns``, or half a period at most), and only
    then lets the preparation go on. The interpreter's lock is then free at every release: the loop, waking,
    takes it at once instead of waiting for the switch interval and for the reloader's next check, unless
    one C call the reloader began before the margin is still running (SLACK_MARGIN_NS says how long they
    were). ``clock`` and ``sleep_s``: the thread's (a test gives its logical clock)."""

    def __init__(self, owner: Any, margin_ns: int = SLACK_MARGIN_NS, *, clock: Any = time.monotonic_ns,
                 sleep_s: Any = time.sleep) -> None:
        self.owner, self.margin_ns, self.clock, self.sleep_s = owner, margin_ns, clock, sleep_s
        self.work_until_ns = 0
        """Until when the thread may work without looking again (the next release less the margin)."""
        self.waits = 0
        self.waited_ns = 0

    def hook(self) -> Any:
        """The profile function: one clock read and a comparison, unless the margin has come."""
        clock, gate = self.clock, self

        def profile(_frame: Any, _event: str, _arg: Any) -> None:
            if clock() >= gate.work_until_ns:
                gate.at_margin()
        return profile

    def at_margin(self, *, whatever_is_left: bool = False) -> None:
        """Give the lock to the loop for the next release if it is within the margin (or, ``whatever_is_left``,
        however far it is: what comes next should start just after a step)."""
        tick = self.owner.tick
        period_ns, last_ns = tick.period_ns, tick.release_ns
        now_ns = self.clock()
        if period_ns <= 0 or last_ns <= 0:  # no timeline (yet): nothing to keep clear of
            self.work_until_ns = now_ns + self.margin_ns
            return
        margin_ns = min(self.margin_ns, period_ns // 2)
        release_ns = last_ns + ((now_ns - last_ns) // period_ns + 1) * period_ns
        if release_ns - now_ns > margin_ns and not whatever_is_left:
            self.work_until_ns = release_ns - margin_ns
            return
        # the lock is free: the loop takes it as it wakes (a moment after, so that a reload thread on another CPU,
        # waking too, does not take it first)
        self.sleep_s((release_ns - now_ns) / 1e9 + SLACK_POLL_S)
        give_up_ns = release_ns + period_ns // 2  # a skipped release: go on rather than wait a period
        while getattr(self.owner, "stepped_release_ns", release_ns) < release_ns and self.clock() < give_up_ns:
            self.sleep_s(SLACK_POLL_S)
        self.waits += 1
        done_ns = self.clock()
        self.waited_ns += done_ns - now_ns
        self.work_until_ns = release_ns + period_ns - margin_ns


class PreparationDeadline:
    """Stops a reload preparation that runs past ``limit_s``: a thread of its own, parked until a
    preparation is armed, that then raises :class:`PreparationOverran` in the reload thread
    (``PyThreadState_SetAsyncExc``: delivered at the thread's next bytecode, so a module spinning in
    Python is stopped; a C call that never returns, such as a sleep, is not, but it does not spin
    either), and again every ``limit_s`` while it stays armed (a cleanup that spins too). It runs one
    priority above the reload thread where that is SCHED_FIFO, so the spinning thread cannot starve
    it. The state both threads share is under a C lock (an exception raised asynchronously can land
    in Python code, never inside a C call: a ``threading.Condition`` held across one stayed held);
    a raise still pending when the reload thread disarms is let land in :meth:`disarm`, so none
    lands after it."""

    def __init__(self, target: threading.Thread, limit_s: float) -> None:
        self.target, self.limit_s = target, limit_s
        self.fired = 0
        self._lock = threading.Lock()  # a C lock: entered and left without a bytecode in between
        self._wake = threading.Event()  # waited on by the deadline's thread only
        self._until = 0.0  # CLOCK_MONOTONIC seconds; 0: nothing armed
        self._pending = False
        self._closing = False
        self.thread = threading.Thread(target=self._watch, name="rtloop-reload-deadline", daemon=True)
        self.thread.start()

    def arm(self) -> None:
        with self._lock:
            self._until = time.monotonic() + self.limit_s
        self._wake.set()

    def disarm(self) -> None:
        while True:
            try:
                with self._lock:
                    self._until = 0.0
                    pending, self._pending = self._pending, False
                if pending:  # raised, and perhaps not delivered yet: it lands here, at a backward jump
                    for _ in range(10_000):
                        pass
                return
            except PreparationOverran:  # delivered just now, after the preparation: it is over anyway
                continue

    def close(self) -> None:
        self._closing = True
        self._wake.set()
        self.thread.join(timeout=1)

    def _watch(self) -> None:
        try:
            if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RELOAD_PRIORITY + 1))
        except (OSError, AttributeError):
            pass
        while not self._closing:
            with self._lock:
                until = self._until
            self._wake.wait(None if not until else max(0.0, until - time.monotonic()))
            self._wake.clear()
            with self._lock:
                if self._closing or not self._until or time.monotonic() < self._until:
                    continue
                self._until = time.monotonic() + self.limit_s
                self._pending = True
                self.fired += 1
                _raise_in(self.target, PreparationOverran)


_set_async_exc = ctypes.pythonapi.PyThreadState_SetAsyncExc
_set_async_exc.argtypes = (ctypes.c_ulong, ctypes.py_object)
_set_async_exc.restype = ctypes.c_int


def _raise_in(thread: threading.Thread, exception: type[BaseException]) -> None:
    """``exception`` raised in ``thread`` at its next check of the interpreter's pending work. (Never
    withdrawn with NULL: CPython 3.11 then leaves that check on for every bytecode of every thread, and
    the reload thread crawled.)"""
    _set_async_exc(thread.ident or 0, exception)


def reload_thread_policy(inherited: int) -> tuple[int, os.sched_param]:
    """The reload thread's policy and priority: SCHED_FIFO at :data:`RELOAD_PRIORITY` in a real-time
    task (``inherited``: the loop's policy), else SCHED_OTHER, as the loop has."""
    if inherited in (os.SCHED_FIFO, os.SCHED_RR):
        return os.SCHED_FIFO, os.sched_param(RELOAD_PRIORITY)
    return os.SCHED_OTHER, os.sched_param(0)


class ReloadRefused(RtloopError):
    """The reason a reloaded module is not used (the old code keeps running)."""


class PreparationOverran(ReloadRefused):
    """Raised inside the reload thread (asynchronously, so without arguments) when its preparation
    passed :data:`PREPARE_DEADLINE_S`."""

    def __str__(self) -> str:
        return (f"its preparation (the module run, the controller built, prerun, the dry step) took more than "
                f"{PREPARE_DEADLINE_S:g} s: stopped there")


def _user_frame(error: BaseException, code_dir: str) -> str:
    """`` (line N)`` of the reloaded file where the error arose, if it did there."""
    line = None
    if isinstance(error, SyntaxError):
        line = error.lineno
    trace = error.__traceback__
    while trace is not None:
        if trace.tb_frame.f_code.co_filename.startswith(code_dir):
            line = trace.tb_lineno
        trace = trace.tb_next
    return f" (line {line} of the new code)" if line else ""
