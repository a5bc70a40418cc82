"""Models, complete: every FMI variable kind, parameters, events, terminate, time after skipped
releases, 20-sim build checks and parameters, and replay of a real-time run with live setpoints."""

from __future__ import annotations

import csv
import dataclasses
import shutil
import signal
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from jiwy_models import PAN_AXIS, JiwyPlant

import rtloop
from conftest import unique_name
from rtloop import App
from rtloop.models import FmuError, ModelError, load_model
from rtloop.runnable import TickInfo

TESTS = Path(__file__).parent
JIWY = TESTS.parent / "examples" / "jiwy"
needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None or shutil.which("g++") is None, reason="needs gcc/g++")


@pytest.fixture(scope="module")
def features_fmu(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed: cannot build the test FMU")
    from rtloop.models.fmu_build import build_fmu

    return build_fmu(TESTS / "fmus" / "features", tmp_path_factory.mktemp("features") / "Features.fmu")


def read_rows(path: Path, dicts: bool = False) -> list:
    with open(path, newline="") as file:
        return list(csv.DictReader(file) if dicts else csv.reader(file))


def started(fmu: Path, period_ns: int = 10_000_000, **options):
    runnable = load_model(f"fmu:{fmu}", **options)
    runnable.check_period(period_ns)
    runnable.prerun()
    return runnable


def test_integer_boolean_float32_and_array_outputs_arrive_as_float64(features_fmu: Path) -> None:
    r = started(features_fmu, inputs=["u"])
    assert r.output_names == ("x", "count", "positive", "half", "multiples[0]", "multiples[1]", "multiples[2]",
                              "events")
    assert list(r.initial_outputs) == [0.5, 0.0, 1.0, 0.25, 0.5, 1.0, 1.5, 0.0]
    u, y = np.array([-1.0]), np.zeros(r.n_outputs)
    for _ in range(3):
        r.step(u, y)
    x = 0.5 - 3 * 2.0 * 0.01  # gain 2 (its start value), h = the task period
    assert y[0] == pytest.approx(x) and y[1] == 3.0 and y[2] == 1.0
    assert y[3] == float(np.float32(y[0] / 2))  # a Float32, carried exactly
    assert list(y[4:7]) == [y[0], 2 * y[0], 3 * y[0]]
    r.postrun()


def test_an_event_runs_event_mode_and_parameters_are_set_by_name(features_fmu: Path) -> None:
    r = started(features_fmu, inputs=["u"], parameters={"event_at": 2, "x0": -1.0})
    assert r.initial_outputs[0] == -1.0 and r.initial_outputs[2] == 0.0  # x0 set; positive is False
    u, y = np.array([0.0]), np.zeros(r.n_outputs)
    r.step(u, y)
    assert y[7] == 0.0
    r.step(u, y)
    assert y[7] == 1.0, "the step that asked for event handling ran event mode"
    r.postrun()


def test_a_tunable_parameter_is_an_input_that_keeps_its_start_value(features_fmu: Path) -> None:
    r = started(features_fmu, inputs=["u", "gain"])
    assert r.input_start_values == (0.0, 2.0)
    u, y = np.array([1.0, 5.0]), np.zeros(r.n_outputs)
    r.step(u, y)
    assert y[0] == pytest.approx(0.5 + 5.0 * 0.01)  # the new gain applied at this step
    r.postrun()
    app = App(unique_name("tunable_fmu"))
    task = app.add_task("m", load_model(f"fmu:{features_fmu}", inputs=["u", "gain"]), period_ns=10_000_000)
    app.port("gain", to=task.u[1:2])
    from rtloop.runtime.layout import AppLayout

    layout = AppLayout.create(app)
    try:
        value = np.zeros(1)
        layout.input_ports["gain"].read_into(value)
        assert value[0] == 2.0, "a port into a tunable parameter starts at its start value, not 0"
    finally:
        layout.close()


def test_refusals_name_the_culprit_and_list_what_exists(features_fmu: Path) -> None:
    with pytest.raises(FmuError, match=r"'x0' is a fixed parameter.*parameters = "):
        load_model(f"fmu:{features_fmu}", inputs=["x0"])
    with pytest.raises(FmuError, match=r"parameters.nope: no such variable; parameters and inputs are: .*gain"):
        load_model(f"fmu:{features_fmu}", parameters={"nope": 1})
    with pytest.raises(FmuError, match="'label' is String"):
        load_model(f"fmu:{features_fmu}", outputs=["label"])
    with pytest.raises(FmuError, match=r"event_at is Int32: 2\.5 is not an integer"):
        load_model(f"fmu:{features_fmu}", parameters={"event_at": 2.5})


def test_terminate_simulation_stops_the_app_in_order_with_the_fmus_reason(features_fmu: Path, tmp_path: Path) -> None:
    app = App(unique_name("terminating_fmu"))
    task = app.add_task("m", load_model(f"fmu:{features_fmu}", parameters={"stop_at": 0.05}), period_ns=10_000_000)
    app.record(task.y)
    summary = rtloop.simulate(app, 1.0, tmp_path)
    assert "task m at cycle 4" in summary.stopped_by and "stop_at reached" in summary.stopped_by
    assert summary.failure is None
    rows = read_rows(tmp_path / "signals.csv")
    assert [r[0] for r in rows[1:]] == ["0.0", "0.01", "0.02", "0.03", "0.04"]  # the terminating step published nothing


def test_rtloop_equals_fmpy_with_parameters_set(features_fmu: Path, tmp_path: Path) -> None:
    from fmpy import simulate_fmu

    parameters = {"x0": 0.25, "gain": 3.0}
    app = App(unique_name("fmpy_equal"))
    task = app.add_task("m", load_model(f"fmu:{features_fmu}", inputs=["u"], parameters=parameters),
                        period_ns=10_000_000)
    app.port("u", to=task.u, initial=[0.7])
    app.record(task.y)
    rtloop.simulate(app, 0.2, tmp_path)
    rows = read_rows(tmp_path / "signals.csv", dicts=True)
    signal = np.array([(0.0, 0.7), (1.0, 0.7)], dtype=[("time", np.float64), ("u", np.float64)])
    reference = simulate_fmu(str(features_fmu), start_values=parameters, input=signal, stop_time=0.2,
                             output_interval=0.01, step_size=0.01, output=["x", "count", "half"])
    assert len(rows) == len(reference) == 21
    for row, ref in zip(rows, reference, strict=True):
        assert float(row["t_s"]) == pytest.approx(ref["time"], abs=1e-12)
        assert float(row["m.x"]) == ref["x"] and float(row["m.count"]) == ref["count"]  # bit for bit
        assert float(row["m.half"]) == float(ref["half"])


def test_a_missing_platform_binary_is_found_at_load(features_fmu: Path, tmp_path: Path) -> None:
    other = tmp_path / "Other.fmu"
    with zipfile.ZipFile(features_fmu) as source, zipfile.ZipFile(other, "w") as target:
        for item in source.namelist():
            name = item.replace("x86_64-linux", "plan9-risc").replace("aarch64-linux", "plan9-risc")
            target.writestr(name, source.read(item))
    with pytest.raises(FmuError, match=r"no binary for this machine: binaries/\S+/Features.so is missing.*"
                                        r"platforms present: plan9-risc"):
        load_model(f"fmu:{other}")


def test_a_failed_start_leaves_no_extracted_folder(features_fmu: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    broken = tmp_path / "Broken.fmu"
    with zipfile.ZipFile(features_fmu) as source, zipfile.ZipFile(broken, "w") as target:
        for item in source.namelist():
            data = source.read(item)
            target.writestr(item, data.replace(b"{rtloop-features-1}", b"{rtloop-features-X}")
                            if item == "modelDescription.xml" else data)
    runnable = load_model(f"fmu:{broken}")
    runnable.check_period(10_000_000)
    with pytest.raises(ModelError, match="failed to start"):
        runnable.prerun()
    assert [p.name for p in tmp_path.iterdir()] == ["Broken.fmu"]


def test_time_follows_the_release_timeline_after_skipped_releases(features_fmu: Path) -> None:
    r = started(features_fmu, inputs=["u"])
    r.tick = TickInfo(period_ns=10_000_000)
    u, y = np.array([1.0]), np.zeros(r.n_outputs)
    for cycle in (0, 1, 5):  # releases 2, 3 and 4 were skipped
        r.tick.cycle = cycle
        r.step(u, y)
    assert y[0] == pytest.approx(0.5 + 6 * 2.0 * 0.01), "x integrated over 6 periods, not 3"
    assert r.catch_up_steps == 3 and r.model.long_steps == 1  # a variable-step FMU: one longer step
    r.postrun()
    plant = JiwyPlant()
    plant.tick = TickInfo(period_ns=1_000_000)
    plant.prerun()
    for cycle in (0, 4):
        plant.tick.cycle = cycle
        plant.step(np.ones(2), np.zeros(2))
    assert plant.catch_up_steps == 1  # a fixed-step model catches up one extra step per cycle
    for cycle in (5, 6, 7):
        plant.tick.cycle = cycle
        plant.step(np.ones(2), np.zeros(2))
    assert plant.catch_up_steps == 3


@needs_gcc
def test_a_20sim_export_missing_a_common_file_fails_at_build_naming_symbol_and_file(tmp_path: Path) -> None:
    broken = tmp_path / "Broken"
    shutil.copytree(JIWY / "models" / "Plant", broken)
    (broken / "common" / "Euler.h").write_text("class Euler { public: Euler(); double Step(double s, double r, "
                                               "double h); };\n")
    source = broken / "Plant.cpp"
    text = source.read_text().replace('#include "Plant.h"', '#include "Plant.h"\n#include "common/Euler.h"')
    source.write_text(text.replace("m_s[i] = m_s[i] + m_R[i] * m_step_size;",
                                   "m_s[i] = Euler().Step(m_s[i], m_R[i], m_step_size);"))
    env = {"RTLOOP_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin",
           "PYTHONPATH": str(TESTS.parent / "src")}
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "model", "build", str(broken)],
                            capture_output=True, text=True, env=env)
    assert result.returncode == 2
    assert "undefined symbols: Euler::Euler()" in result.stderr and "common/Euler.cpp" in result.stderr
    assert "Traceback" not in result.stderr


def test_a_folder_with_several_exports_is_refused_with_their_list() -> None:
    with pytest.raises(ModelError, match=r"holds 3 20-sim exports \(Controller, Plant, PlantC\)"):
        load_model(f"20sim:{JIWY / 'models'}")


@needs_gcc
def test_20sim_parameters_by_name_change_the_model_like_the_python_twin(tmp_path: Path) -> None:
    from rtloop.models.twentysim import TwentySimModel

    def angles(runnable) -> np.ndarray:
        runnable.check_period(1_000_000)
        runnable.prerun()
        u, y, out = np.array([0.3, 0.2]), np.zeros(2), []
        for _ in range(300):
            runnable.step(u, y)
            out.append(y.copy())
        runnable.postrun()
        return np.array(out)

    from rtloop.models import ModelRunnable

    changed = {"pan\\r": 0.02, "pan.Dcam": 3e-4}
    plant = ModelRunnable(TwentySimModel(JIWY / "models" / "Plant", cache_dir=tmp_path, parameters=changed))
    twin = JiwyPlant(pan=dataclasses.replace(PAN_AXIS, r=0.02, d_cam=3e-4))
    assert np.max(np.abs(angles(plant) - angles(twin))) <= 1e-12
    assert np.max(np.abs(angles(JiwyPlant()) - angles(twin))) > 1e-6
    with pytest.raises(ModelError, match=r"unknown parameter 'nope'; parameters are: pan\\r, pan\\Jmot"):
        TwentySimModel(JIWY / "models" / "Plant", cache_dir=tmp_path, parameters={"nope": 1.0})


REPLAY_APP = """name = "{name}"
[tasks.controller]
runnable = "jiwy_models:JiwyController"
period_ns = {period_ns}
cpu = {cpu}
[tasks.plant]
runnable = "jiwy_models:JiwyPlant"
period_ns = {period_ns}
priority = 81
cpu = {cpu}
[[connect]]
from = "plant.y[0:2]"
to = "controller.u[0:2]"
[[connect]]
from = "controller.SteeringPan"
to = "plant.SteeringPan"
[[connect]]
from = "controller.y[1]"
to = "plant.u[1]"
[ports.setpoint]
to = "controller.u[2:4]"
[record]
signals = ["plant.y", "controller.y", "controller.u[2:4]"]
"""


@pytest.mark.rt
def test_replay_reproduces_a_real_time_run_with_live_port_writes(tmp_path: Path, rtloop_env) -> None:
    from conftest import other_cpu, scaled_ns, scaled_s, wait_for_app, wait_for_cycles

    cli = [sys.executable, "-m", "rtloop.cli"]
    name = unique_name("replay_t")
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(REPLAY_APP.format(name=name, cpu=other_cpu(), period_ns=scaled_ns(1_000_000)))
    run_dir = tmp_path / "run"
    # The run lasts until both writes are taken, then Ctrl-C ends it: each `rtloop port write` is a
    # Python start-up of its own, which a loaded machine stretched past a fixed 3 s run's end.
    process = subprocess.Popen([*cli, "run", str(app_file), "--duration", str(scaled_s(120)), "--out", str(run_dir),
                                "-q"], env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # each write once the task runs, and taken at a cycle of its own (however slow the start-up)
        app = wait_for_app(name, process, timeout_s=scaled_s(60))
        done = 0
        for values in (["0.5", "0.3"], ["-0.2", "0.1"]):
            done = wait_for_cycles(app, "controller", done + 100, process, timeout_s=scaled_s(30))
            write = subprocess.run([*cli, "port", "write", name, "setpoint", *values], env=rtloop_env,
                                   capture_output=True, text=True)
            assert write.returncode == 0, write.stderr
            done = wait_for_cycles(app, "controller", done + 100, process, timeout_s=scaled_s(30))
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=scaled_s(60))
    assert process.returncode == 0, stderr
    logged = read_rows(run_dir / "inputs.csv")
    assert logged[0] == ["task", "cycle", "port", "values"] and len(logged) == 3
    assert [row[3] for row in logged[1:]] == ["0.5 0.3", "-0.2 0.1"]
    # a loaded machine misses deadlines: the replay follows them, over the whole run
    result = subprocess.run([*cli, "replay", str(run_dir), "--out", str(tmp_path / "replay")],
                            env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "equal bit for bit over the whole run" in result.stdout
    replayed = read_rows(tmp_path / "replay" / "inputs.csv")
    assert replayed == logged, "the replay took the same values at the same cycles"
    assert read_rows(tmp_path / "replay" / "signals.csv") == read_rows(run_dir / "signals.csv")


def test_model_build_of_an_fmu_source_folder_never_writes_into_it(tmp_path: Path) -> None:
    source = tmp_path / "plant"
    shutil.copytree(JIWY / "models" / "fmu", source)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    env = {"RTLOOP_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin",
           "PYTHONPATH": str(TESTS.parent / "src")}
    info = subprocess.run([sys.executable, "-m", "rtloop.cli", "model", "info", str(source)],
                          capture_output=True, text=True, env=env)
    assert info.returncode == 2 and f"build it with `rtloop model build {source}`" in info.stderr
    built = subprocess.run([sys.executable, "-m", "rtloop.cli", "model", "build", str(source)],
                           capture_output=True, text=True, env=env)
    assert built.returncode == 0, built.stderr
    target = tmp_path / "cache" / "fmu" / "plant.fmu"
    assert target.is_file() and f'model = "fmu:{target}"' in built.stdout
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if "cache" not in p.parts) == before
    chosen = tmp_path / "chosen.fmu"
    assert subprocess.run([sys.executable, "-m", "rtloop.cli", "model", "build", str(source), "--out", str(chosen)],
                          capture_output=True, text=True, env=env).returncode == 0
    assert chosen.is_file()
    helped = "".join(subprocess.run([sys.executable, "-m", "rtloop.cli", *command, "--help"], capture_output=True,
                                    text=True, env=env).stdout for command in (["model"], ["model", "build"]))
    assert "FMU source folder" in helped and "20-sim" in helped


def test_the_jiwy_app_files_comment_names_files_that_exist_or_the_command_making_them() -> None:
    comment = (JIWY / "jiwy.toml").read_text()
    assert 'model = "20sim:models/Plant"' in comment and (JIWY / "models" / "Plant").is_dir()
    assert "rtloop model build examples/jiwy/models/fmu --out examples/jiwy/jiwy-plant.fmu" in comment
    assert 'model = "fmu:jiwy-plant.fmu"' in comment and (JIWY / "models" / "fmu" / "sources").is_dir()


def test_20sim_names_with_a_backslash_are_written_with_a_dot_in_an_app_file(tmp_path: Path) -> None:
    from rtloop.app.appfile import load_app

    app_file = tmp_path / "app.toml"
    app_file.write_text(f'name = "dotted"\n[tasks.plant]\nmodel = "20sim:{JIWY / "models" / "Plant"}"\n'
                        'parameters = { pan.r = 0.02, pan.Dcam = 3e-4 }   # pan\\r and pan\\Dcam, no escaping\n'
                        "period_ns = 1_000_000\n")
    model = load_app(app_file).tasks["plant"].runnable.model
    index = {name: i for name, i, _default in model.info.parameters}
    assert model.parameters == {index["pan\\r"]: 0.02, index["pan\\Dcam"]: 3e-4}  # by index, as the model keeps them


REFERENCE_FMUS_SKIP = ("the Modelica Reference FMUs' sources are not obtainable from the registries reachable here "
                       "(PyPI, Debian, npm carry no package of them): the FMUs this repository builds from source are "
                       "compared with FMPy instead (test_every_buildable_co_simulation_fmu_equals_fmpy)")


@pytest.mark.skip(reason=REFERENCE_FMUS_SKIP)
def test_the_modelica_reference_fmus_equal_fmpy() -> None:
    """Build every Reference FMU (FMI 2 and 3), compare each co-simulation one with FMPy's simulate_fmu."""


@pytest.mark.parametrize("folder", ["fmu", "fmu3"])
def test_every_buildable_co_simulation_fmu_equals_fmpy(folder: str, tmp_path: Path) -> None:
    """JIWY's plant as an FMI 2 and an FMI 3 co-simulation FMU: every output equals FMPy's, bit for bit."""
    from fmpy import read_model_description, simulate_fmu

    from rtloop.models.fmu_build import build_fmu

    fmu = build_fmu(JIWY / "models" / folder, tmp_path / f"{folder}.fmu")
    outputs = [v.name for v in read_model_description(str(fmu)).modelVariables if v.causality == "output"]
    app = App(f"fmpy_{folder}")
    task = app.add_task("plant", load_model(f"fmu:{fmu}"), period_ns=1_000_000)
    # A step of the steering at 0.1 s: the same inputs at every step for both (FMPy interpolates
    # between its rows, so its step is a ramp inside 0.0995–0.0996 s, between two steps).
    (tmp_path / "steering.csv").write_text("t_s,pan,tilt\n0,0,0\n0.1,0.3,-0.2\n")
    app.port("steering", to=task.u, feed=tmp_path / "steering.csv")
    app.record(task.y)
    rtloop.simulate(app, 0.3, tmp_path / "sim")
    rows = read_rows(tmp_path / "sim" / "signals.csv", dicts=True)
    inputs = [v.name for v in read_model_description(str(fmu)).modelVariables if v.causality == "input"]
    signal = np.array([(0.0, 0.0, 0.0), (0.0995, 0.0, 0.0), (0.0996, 0.3, -0.2), (1.0, 0.3, -0.2)],
                      dtype=[("time", np.float64), *((name, np.float64) for name in inputs)])
    reference = simulate_fmu(str(fmu), input=signal, stop_time=0.3, output_interval=0.001, step_size=0.001,
                             output=outputs)
    assert len(rows) == len(reference) == 301
    for row, ref in zip(rows, reference, strict=True):
        assert float(row["t_s"]) == pytest.approx(ref["time"], abs=1e-12)
        for name in outputs:
            assert float(row[f"plant.{name}"]) == float(ref[name]), (row["t_s"], name)  # exactly
    assert float(rows[-1][f"plant.{outputs[0]}"]) != 0.0  # the plant moved
