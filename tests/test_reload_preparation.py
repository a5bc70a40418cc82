"""What a reload's preparation does in the task process, proven without timing: it loads no file but the
kept code, and it records its own timeline (docs/switching.md, "What it costs")."""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rtloop.app.modules import load_module_file
from rtloop.code_reload import PHASES, CodeReloader, code_file_name, code_id_of, compiled_code, compiled_file_name
from rtloop.runnable import TickInfo
from rtloop.switching import Controllers

P = 1_000_000

MODULE = '''
from dataclasses import dataclass

from rtloop import Runnable


@dataclass(frozen=True)
class Gains:
    kp: float
    ki: float


class Pi(Runnable):
    n_inputs, n_outputs = 2, 1

    def __init__(self, gains=Gains(2.0, 5.0)):
        self.gains, self.integral = gains, 0.0

    def step(self, u, y):
        error = u[1] - u[0]
        self.integral += error * self.tick.period_ns * 1e-9
        y[0] = GAIN * self.gains.kp * error + self.gains.ki * self.integral


GAIN = {gain}
'''


@pytest.fixture
def module_by_file(tmp_path: Path):  # type: ignore[no-untyped-def]
    """A controller's module loaded by file, as an app file loads it (its classes then pickle by file)."""
    name = f"reload_prep_{tmp_path.name}"
    path = tmp_path / f"{name}.py"
    path.write_text(MODULE.format(gain=1.0))
    module = load_module_file(name, path)
    yield name, path, module
    sys.modules.pop(name, None)


def test_a_copy_of_an_instance_loads_no_file_even_after_its_module_was_edited(module_by_file) -> None:  # type: ignore[no-untyped-def]
    """copy.deepcopy consults the pickling hook of classes loaded by file: it loaded the module's file again,
    and after an edit it imported the edited file (a compilation of 7-10 ms holding the interpreter's lock in
    the task's reload thread, which built the new controller from a copy of the old one's state: the loop,
    waking, waited as long; benchmarks/bench_switch.py) and replaced the running module in sys.modules."""
    name, path, module = module_by_file
    controller = module.Pi()
    path.write_text(MODULE.format(gain=3.0))  # edited on disk while it runs
    copied = copy.deepcopy(controller)
    assert sys.modules[name] is module, "copying an instance imported the edited file"
    assert type(copied) is module.Pi and type(copied.gains) is module.Gains
    assert copied.gains == controller.gains and copied.gains is not controller.gains


def _prepared(module: Any, code_dir: Path, tick: TickInfo, *, wait_for_code: bool) -> Controllers:
    """The controllers ``{"pi": module.Pi()}`` with inputs bound, the run's code folder made and prerun
    done: ``wait_for_code``, a replay's (it waits for the kept code); without, a live run's reloader."""
    controllers = Controllers({"pi": module.Pi()}, "pi")
    controllers.bind_inputs(np.zeros(controllers.n_inputs))
    controllers.tick = tick
    code_dir.mkdir()
    controllers.code_dir = code_dir
    controllers.wait_for_code = wait_for_code
    controllers.prerun()
    return controllers

def test_a_reload_builds_the_new_code_from_the_kept_file_only_and_records_its_timeline(
        module_by_file, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    name, path, module = module_by_file
    code_dir = tmp_path / "code"
    controllers = _prepared(module, code_dir, TickInfo(cycle=3, period_ns=P), wait_for_code=True)
    new = MODULE.format(gain=3.0).encode()
    path.write_bytes(new)  # the module's own file edited, as `rtloop reload` finds it
    code_id = code_id_of(new)
    kept = code_dir / code_file_name("pi", code_id)
    kept.write_bytes(new)
    (code_dir / compiled_file_name("pi", code_id)).write_bytes(compiled_code(new, kept, code_id))
    compiled: list[str] = []
    real_compile = compile

    def compile_spy(source, filename, *rest, **named):  # type: ignore[no-untyped-def]
        compiled.append(str(filename))
        return real_compile(source, filename, *rest, **named)

    import builtins
    monkeypatch.setattr(builtins, "compile", compile_spy)
    reloader = controllers._reloader
    assert isinstance(reloader, CodeReloader)
    try:
        result = reloader._prepare(0, code_id)
    finally:
        monkeypatch.undo()
        controllers.postrun()
    assert result["accepted"], result
    assert str(path) not in compiled, "the reload compiled the module's own file, not only the kept code"
    assert sys.modules[name] is module
    timeline = reloader.timeline_ns
    assert all(timeline) and timeline == sorted(timeline), dict(zip(PHASES, timeline, strict=True))
    assert result["ready_ns"] == timeline[-1]


def test_simulate_and_replay_write_no_answer_over_the_runs_own(module_by_file, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """The answer file is for `rtloop reload` in a live run: a replay (as root, in the run's own folder)
    overwrote the run's answer, its readiness instant and timeline, with its own."""
    from rtloop.code_reload import result_file_name

    _name, _path, module = module_by_file
    controllers = _prepared(module, tmp_path / "code", TickInfo(cycle=3, period_ns=P), wait_for_code=True)
    new = MODULE.format(gain=3.0).encode()
    code_id = code_id_of(new)
    (controllers.code_dir / code_file_name("pi", code_id)).write_bytes(new)
    reloader = controllers._reloader
    assert isinstance(reloader, CodeReloader)
    try:
        reloader.ask(0, code_id)
        assert reloader.take(code_id) is not None
    finally:
        controllers.postrun()
    assert not (controllers.code_dir / result_file_name("pi", code_id)).exists()


class LogicalLoop:
    """A task's loop on a logical clock, for :class:`SlackGate`: releases T0 + k·P; at each one the loop takes
    the interpreter's lock if the reload thread does not hold it (else as soon as it lets go: ``waited``
    records by how long) and steps."""

    def __init__(self, t0_ns: int, period_ns: int) -> None:
        self.now_ns = t0_ns + 1
        self.tick = TickInfo(cycle=0, release_ns=t0_ns, period_ns=period_ns)
        self.stepped_release_ns = t0_ns
        self.waited_ns: list[int] = []
        self.free_at: list[int] = []

    def _next_release_ns(self) -> int:
        return self.tick.release_ns + self.tick.period_ns

    def _step_at(self, release_ns: int, woke_ns: int) -> None:
        self.tick.cycle += 1
        self.tick.release_ns = release_ns
        self.stepped_release_ns = release_ns
        self.waited_ns.append(woke_ns - release_ns)

    def clock(self) -> int:
        return self.now_ns

    def sleep_s(self, seconds: float) -> None:
        """The reload thread sleeps, its lock free: the loop steps at each release in between, on time."""
        until_ns = self.now_ns + round(seconds * 1e9)
        while self._next_release_ns() <= until_ns:
            release_ns = self._next_release_ns()
            self._step_at(release_ns, release_ns)
            self.free_at.append(release_ns)
        self.now_ns = until_ns

    def work(self, duration_ns: int) -> None:
        """The reload thread holds the lock for ``duration_ns`` (one C call): a release inside it waits."""
        self.now_ns += duration_ns
        while self._next_release_ns() <= self.now_ns:
            self._step_at(self._next_release_ns(), self.now_ns)


@pytest.mark.parametrize(("period_ns", "stretches_ns"), [
    (P, [7_000, 290_000, 45_000, 120_000, 3_000, 250_000, 80_000] * 60),
    (100_000, [7_000, 45_000, 20_000, 3_000, 50_000] * 200),  # 10 kHz: the margin is half the period
])
def test_the_gate_leaves_the_lock_free_at_every_release_when_each_stretch_of_work_is_within_the_margin(
        period_ns: int, stretches_ns: list[int]) -> None:
    from rtloop.code_reload import SlackGate

    loop = LogicalLoop(t0_ns=5_000_000_000, period_ns=period_ns)
    gate = SlackGate(loop, margin_ns=300_000, clock=loop.clock, sleep_s=loop.sleep_s)
    hook = gate.hook()
    for stretch_ns in stretches_ns:  # a preparation: a check (a call, a C call) before each stretch
        hook(None, "c_call", None)
        loop.work(stretch_ns)
    assert loop.tick.cycle > 20, "the preparation spanned too few releases to show anything"
    assert max(loop.waited_ns) == 0, f"the loop waited for the lock at a release: {max(loop.waited_ns)} ns"
    assert gate.waits == len(loop.free_at) == loop.tick.cycle
    assert gate.waited_ns < loop.tick.cycle * period_ns  # it waits for the releases, not longer


def test_a_stretch_longer_than_the_margin_delays_the_loop_by_what_it_lasts_beyond_it() -> None:
    from rtloop.code_reload import SlackGate

    loop = LogicalLoop(t0_ns=5_000_000_000, period_ns=P)
    gate = SlackGate(loop, margin_ns=300_000, clock=loop.clock, sleep_s=loop.sleep_s)
    hook = gate.hook()
    for stretch_ns in [649_999, 400_000, 100_000]:  # the long one begins 350 µs before the release
        hook(None, "c_call", None)
        loop.work(stretch_ns)
    assert loop.waited_ns == [50_000], "not late by what the stretch lasts beyond the release"
    for stretch_ns in [300_000, 400_000, 100_000]:  # now it would begin within the margin: the gate waits first
        hook(None, "c_call", None)
        loop.work(stretch_ns)
    assert loop.waited_ns[1:] == [0] * (len(loop.waited_ns) - 1)


def test_a_real_preparation_under_the_gate_yields_at_every_release_and_builds_the_same_controller(
        module_by_file, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """The gate as the reload thread installs it (its profile function), through a whole preparation of new
    code, on a logical clock that advances 2 µs at each of the gate's clock reads."""
    import time

    from rtloop import code_reload
    from rtloop.code_reload import SlackGate

    _name, _path, module = module_by_file
    loop = LogicalLoop(t0_ns=time.monotonic_ns(), period_ns=P)
    controllers = _prepared(module, tmp_path / "code", loop.tick, wait_for_code=False)  # installs the gate
    new = MODULE.format(gain=3.0).encode()
    code_id = code_id_of(new)
    kept = controllers.code_dir / code_file_name("pi", code_id)
    kept.write_bytes(new)
    (controllers.code_dir / compiled_file_name("pi", code_id)).write_bytes(compiled_code(new, kept, code_id))

    def clock() -> int:
        loop.work(2_000)  # the stretch since the last check
        controllers.stepped_release_ns = loop.stepped_release_ns
        return loop.clock()

    def sleep_s(seconds: float) -> None:
        loop.sleep_s(seconds)
        controllers.stepped_release_ns = loop.stepped_release_ns

    class LogicalGate(SlackGate):
        def __init__(self, owner: object) -> None:
            super().__init__(owner, clock=clock, sleep_s=sleep_s)

    reloader = controllers._reloader
    assert isinstance(reloader, CodeReloader)
    real_gate = code_reload.SlackGate
    code_reload.SlackGate = LogicalGate  # type: ignore[misc]
    try:
        reloader.ask(0, code_id)
        deadline = time.monotonic() + 30
        while code_id not in reloader.finished and time.monotonic() < deadline:
            time.sleep(0.01)
        ready = reloader.take(code_id)
    finally:
        code_reload.SlackGate = real_gate  # type: ignore[misc]
        controllers.postrun()
    assert ready is not None, reloader.failed_code
    assert reloader.gate is not None and reloader.gate.waits >= 2
    assert loop.tick.cycle >= 2 and max(loop.waited_ns) <= 2_000, "a release found the reload thread working"
    ready.bind_inputs(np.zeros(2))
    y = np.zeros(1)
    ready.step(np.array([0.0, 1.0]), y)
    assert y[0] == pytest.approx(3.0 * 2.0 + 5.0 * 1e-3)  # the new code (GAIN = 3), built from the old state


def test_the_replaced_controllers_postrun_runs_in_the_loops_slack_too(module_by_file, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """What the reload thread does after the swap (the old code's postrun) holds the same lock: under the
    gate and the reload switch interval, not the interpreter's 5 ms one."""
    import threading

    from rtloop import Runnable
    from rtloop.code_reload import RELOAD_SWITCH_INTERVAL_S

    _name, _path, module = module_by_file
    seen: list[tuple[object, float]] = []
    done = threading.Event()

    class Retired(Runnable):
        n_inputs, n_outputs = 2, 1

        def step(self, u, y):  # type: ignore[no-untyped-def]
            pass

        def postrun(self) -> None:
            seen.append((sys.getprofile(), sys.getswitchinterval()))
            done.set()

    controllers = _prepared(module, tmp_path / "code", TickInfo(cycle=3, release_ns=1, period_ns=P),
                            wait_for_code=False)
    reloader = controllers._reloader
    assert isinstance(reloader, CodeReloader)
    try:
        reloader.retire(Retired())
        assert done.wait(30)
    finally:
        controllers.postrun()
    [(profile, interval)] = seen
    assert profile is not None and interval == pytest.approx(RELOAD_SWITCH_INTERVAL_S)


SPINS_AT_IMPORT = MODULE.format(gain=1.0) + "\nwhile True:\n    pass\n"
SPINS_IN_STEP = MODULE.format(gain=1.0).replace("        error = u[1] - u[0]", "        while True:\n            pass")


@pytest.mark.parametrize("source", [SPINS_AT_IMPORT, SPINS_IN_STEP], ids=["at_import", "in_dry_step"])
def test_a_preparation_that_spins_is_stopped_at_its_deadline_refused_and_the_reloader_serves_on(
        module_by_file, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, source: str) -> None:  # type: ignore[no-untyped-def]
    """A module that spins at import, or whose dry step never returns, held the reload thread (SCHED_FIFO
    in a real-time task) for good: the kernel's RLIMIT_RTTIME then ended the whole run as 'the step is
    stuck in an endless loop' (a traceback), and no reload was answered again."""
    import json
    import time

    import rtloop.code_reload as code_reload
    from rtloop.code_reload import result_file_name

    monkeypatch.setattr(code_reload, "PREPARE_DEADLINE_S", 0.3, raising=False)
    _name, _path, module = module_by_file
    # as in a real run (no wait for kept code): the answer is written for `rtloop reload`
    controllers = _prepared(module, tmp_path / "code", TickInfo(cycle=3, period_ns=P), wait_for_code=False)
    reloader = controllers._reloader
    assert isinstance(reloader, CodeReloader)

    def answer_to(text: str) -> dict[str, object]:
        code = text.encode()
        code_id = code_id_of(code)
        (controllers.code_dir / code_file_name("pi", code_id)).write_bytes(code)
        reloader.ask(0, code_id)
        answer = controllers.code_dir / result_file_name("pi", code_id)
        deadline = time.monotonic() + 20
        while not answer.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert answer.exists(), "the reloader gave no answer"
        return json.loads(answer.read_text())

    try:
        refused = answer_to(source)
        assert refused["accepted"] is False
        assert "took more than 0.3 s: stopped there" in str(refused["reason"]), refused
        # The thread serves the next request: a good module, given the time a loaded machine may take to
        # prepare it (the deadline is read as each preparation is armed; a reload thread descheduled for
        # 0.3 s would have had this one refused too, and that is not what this test is about).
        reloader.deadline.limit_s = 30.0
        assert answer_to(MODULE.format(gain=4.0))["accepted"] is True
    finally:
        controllers.postrun()
