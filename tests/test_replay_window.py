"""--keep windows of tasks whose state lives in 20-sim generated code, fed by profiles nudged live.

A ``--keep`` window is replayed from the snapshot taken at its start: each task's state, and the
live values its nudged profile ports hold (they are not in ``u``: an offset is added to the
profile's row at every release, an override holds until the next row). A 20-sim model's state
is read out of its state arrays (C++: the arrays its constructor allocates and the model's number
members, through the generated shim; ANSI-C: its globals).
"""

from __future__ import annotations

import csv
import dataclasses
import os
import pickle
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import other_cpu
from rtloop import App
from rtloop.runnable import TickInfo

P = 1_000_000
MODELS = Path(__file__).resolve().parents[1] / "examples" / "jiwy" / "models"
needs_compilers = pytest.mark.skipif(shutil.which("g++") is None or shutil.which("gcc") is None,
                                     reason="g++ and gcc are needed to build the 20-sim models")


@pytest.fixture(scope="module")
def model_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("model-cache")


def _steps(runnable, n: int, u: np.ndarray, first_cycle: int = 0) -> list[float]:
    y = np.zeros(runnable.n_outputs)
    out = []
    for k in range(first_cycle, first_cycle + n):
        runnable.tick = TickInfo(cycle=k, period_ns=P)
        runnable.step(u, y)
        out += y.tolist()
    return out


@needs_compilers
@pytest.mark.parametrize("model", ["Plant", "PlantC", "Controller"])
def test_a_20sim_models_state_is_saved_from_its_arrays_and_restored(model: str, model_cache: Path) -> None:
    from rtloop.models import ModelRunnable
    from rtloop.models.twentysim import TwentySimModel
    from rtloop.runtime.snapshot import restore_state, save_state

    runnables = [ModelRunnable(TwentySimModel(MODELS / model, cache_dir=model_cache)) for _ in range(3)]
    first, second, fresh = runnables
    for runnable in runnables:  # three live instances: an ANSI-C model's globals are private to each
        runnable.check_period(P)
        runnable.prerun()
    u = np.array([0.1, -0.2, 0.3, 0.05][: first.n_inputs])
    _steps(first, 50, u)
    state, reason = save_state(first)
    assert state is not None, reason
    expected = _steps(first, 30, u, 50)
    restore_state(second, state)
    assert _steps(second, 30, u, 50) == expected, "restored, it goes on exactly as the original"
    assert _steps(fresh, 30, u, 50) != expected, "without the state it would not (the test can fail)"
    for runnable in runnables:
        runnable.postrun()


def _copy_model(tmp_path: Path, edit_header: tuple[str, str] = ("", ""), edit_source: tuple[str, str] = ("", "")
                ) -> Path:
    folder = tmp_path / "Plant"
    shutil.copytree(MODELS / "Plant", folder)
    for name, (old, new) in (("Plant.h", edit_header), ("Plant.cpp", edit_source)):
        if old:
            text = (folder / name).read_text()
            assert old in text
            (folder / name).write_text(text.replace(old, new))
    return folder


@needs_compilers
def test_a_20sim_export_whose_state_copy_does_not_compile_still_runs_and_says_why(tmp_path: Path) -> None:
    from rtloop.models import ModelRunnable
    from rtloop.models.twentysim import TwentySimModel
    from rtloop.runtime.snapshot import save_state

    # an array length through a constructor's local variable: the shim cannot name it
    folder = _copy_model(tmp_path, edit_source=("m_P = new XXDouble[m_number_parameters + 1];",
                                                "int parameters = m_number_parameters;\n"
                                                "\tm_P = new XXDouble[parameters + 1];"))
    runnable = ModelRunnable(TwentySimModel(folder, cache_dir=tmp_path / "cache"))
    runnable.check_period(P)
    runnable.prerun()
    assert len(_steps(runnable, 5, np.array([0.1, 0.2]))) == 10, "the model runs"
    state, reason = save_state(runnable)
    assert state is None and reason.startswith("StateNotCaptured: 20sim-cpp model ")
    assert "the generated copy of its state did not compile" in reason and "parameters" in reason
    runnable.postrun()
    again = ModelRunnable(TwentySimModel(folder, cache_dir=tmp_path / "cache"))  # from the cache: the same
    again.prerun()
    assert save_state(again) == (None, reason)
    again.postrun()


@needs_compilers
def test_a_20sim_member_rtloop_cannot_copy_refuses_the_state_naming_it(tmp_path: Path) -> None:
    from rtloop.models import ModelRunnable
    from rtloop.models.twentysim import TwentySimModel
    from rtloop.runtime.snapshot import save_state

    folder = _copy_model(tmp_path, edit_header=("\tXXDouble *m_R;\t/* rates */",
                                                "\tXXDouble *m_R;\t/* rates */\n\tstruct History { double h[3]; };\n"
                                                "\tHistory m_history;"))
    runnable = ModelRunnable(TwentySimModel(folder, cache_dir=tmp_path / "cache"))
    runnable.prerun()
    state, reason = save_state(runnable)
    assert state is None
    assert reason.endswith("member m_history of type History is not a number rtloop can copy"), reason
    runnable.postrun()


# --- a --keep run's window: a 20-sim plant, profiles nudged live ----------------------------------


def _window_app(name: str, pan: Path, tilt: Path) -> App:
    from rt_test_runnables import PiController
    from rtloop.models import ModelRunnable
    from rtloop.models.twentysim import TwentySimModel

    app = App(name)
    controller = app.add_task("controller", PiController(2, kp=0.05, ki=0.02), period_ns=P, cpu=other_cpu())
    plant = app.add_task("plant", ModelRunnable(TwentySimModel(MODELS / "Plant")), period_ns=P, priority=81,
                         cpu=other_cpu())
    app.connect(plant.y, controller.u[0:2])
    app.connect(controller.y, plant.u)
    app.port("pan", to=controller.u[2:3], feed=pan, nudge="override")
    app.port("tilt", to=controller.u[3:4], feed=tilt, nudge="offset")
    app.port("angles", source=plant.y)  # the test's clock: the plant's cycles as they run
    app.record(plant.y, controller.y, controller.u)
    return app


def _input_cycles(run: Path) -> list[tuple[str, int]]:
    with open(run / "inputs.csv", newline="") as file:
        return [(row["port"], int(row["cycle"])) for row in csv.DictReader(file)]


def _drop_timing_before(run: Path, next_cycles: dict[str, int]) -> None:
    """What the flight recorder does to the segments before the window: their cycles are gone."""
    with open(run / "timing.csv", newline="") as file:
        rows = list(csv.reader(file))
    kept = [rows[0]] + [row for row in rows[1:] if int(row[1]) >= next_cycles[row[0]]]
    (run / "timing.csv").write_text("".join(",".join(row) + "\n" for row in kept))


@needs_compilers
@pytest.mark.rt
@pytest.mark.timeout(300)
def test_a_keep_window_with_a_20sim_plant_and_nudged_profiles_replays_from_its_snapshot(tmp_path: Path) -> None:
    from rtloop.ipc.ports import connect_app
    from rtloop.runtime.replay import replay
    from rtloop.runtime.snapshot import SNAPSHOTS_DIR, read_snapshots

    pan, tilt = tmp_path / "pan.csv", tmp_path / "tilt.csv"
    pan.write_text("t_s,pan\n0,0.2\n0.3,0.1\n")
    tilt.write_text("t_s,tilt\n0,-0.1\n1.5,0.05\n")
    name = f"replay_window_{os.getpid()}"
    done = threading.Event()
    seen_at_write: list[int] = []  # the plant's newest cycle when each nudge was written

    def nudge() -> None:  # two nudges early (held through the window's start), one inside it
        app = connect_app(name, timeout_s=60)
        newest = -1
        with app.reader("angles") as angles:
            for at_cycle, port, value in ((600, "pan", 0.35), (600, "tilt", 0.02), (2800, "pan", -0.15)):
                while not done.is_set() and newest < at_cycle:
                    ticks, _rows = angles.read()
                    newest = int(ticks[-1]) if len(ticks) else newest
                    time.sleep(0.01)
                app.write(port, [value])
                seen_at_write.append(newest)

    writer = threading.Thread(target=nudge, daemon=True)
    writer.start()
    try:
        rtloop.run(_window_app(name, pan, tilt), 4.0, tmp_path / "run", keep_s=1.0)
    finally:
        done.set()
        writer.join(10)
    run = tmp_path / "run"
    taken = sorted(_input_cycles(run), key=lambda entry: entry[1])
    # inputs.csv rotates with the window: the late nudge is in it; the early ones only if an event
    # pinned their segment (the window's replay takes them from the snapshot)
    assert len(seen_at_write) == 3 and len(taken) in (1, 3) and taken[-1][0] == "pan", (seen_at_write, taken)
    assert len(taken) == 1 or {port for port, _cycle in taken[:2]} == {"pan", "tilt"}
    early = taken[1][1] if len(taken) == 3 else seen_at_write[1]  # taken at the first release after the write
    late_write = taken[-1][1]
    found: dict[int, dict] = {}
    for path in sorted((run / SNAPSHOTS_DIR).glob("*.pkl")):
        for snapshot in read_snapshots(path):
            found.setdefault(snapshot.at_ns, {})[snapshot.task] = snapshot
    later = [at for at in sorted(found) if at > (early + 100) * P and len(found[at]) == 2]
    usable = [at for at in later if late_write * P > at]
    if not usable:
        pytest.skip(f"no snapshot between the early nudges (cycle {early}) and the late one ({late_write}) "
                    f"on this machine: {sorted(found)}")
    at_ns = usable[0]
    snapshots = found[at_ns]
    assert all(s.state is not None for s in snapshots.values()), [s.reason for s in snapshots.values()]
    assert dict(snapshots["controller"].nudges) == {"pan": (0.35,), "tilt": (0.02,)}
    _drop_timing_before(run, {task: s.next_cycle for task, s in snapshots.items()})

    result = replay(run, tmp_path / "replay", app=_window_app(name, pan, tilt))
    assert result.cannot is None and result.divergence is None, (
        result.cannot, result.divergence and result.divergence.describe())
    assert result.equal and result.from_s == at_ns / 1e9 and result.port_inputs == 1
    assert result.rows_compared == result.rows_in_run > 500

    # the nudges held are what made it equal: without them the window's replay differs
    for path in sorted((run / SNAPSHOTS_DIR).glob("*.pkl")):
        bare = [dataclasses.replace(snapshot, nudges=()) for snapshot in read_snapshots(path)]
        path.write_bytes(pickle.dumps(bare))
    without = replay(run, tmp_path / "without", app=_window_app(name, pan, tilt))
    assert not without.equal and without.divergence is not None and without.divergence.task == "controller"
