"""What a reload's preparation does in the task process, proven without timing: it loads no file but the
kept code, and it records its own timeline (docs/switching.md, "What it costs")."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

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


def test_a_reload_builds_the_new_code_from_the_kept_file_only_and_records_its_timeline(
        module_by_file, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    name, path, module = module_by_file
    controllers = Controllers({"pi": module.Pi()}, "pi")
    u = np.zeros(controllers.n_inputs)
    controllers.bind_inputs(u)
    controllers.tick = TickInfo(cycle=3, period_ns=P)
    code_dir = tmp_path / "code"
    code_dir.mkdir()
    controllers.code_dir = code_dir
    controllers.wait_for_code = True
    controllers.prerun()
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
    controllers = Controllers({"pi": module.Pi()}, "pi")
    controllers.bind_inputs(np.zeros(controllers.n_inputs))
    controllers.tick = TickInfo(cycle=3, period_ns=P)
    controllers.code_dir = tmp_path / "code"
    controllers.code_dir.mkdir()
    controllers.wait_for_code = True
    controllers.prerun()
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
