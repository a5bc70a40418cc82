"""Model adapters: Python JIWY models, 20-sim-shaped C++/ANSI-C code and an FMU agree.

The closed loop is run lock-step with rtloop's logical-execution-time wiring: at tick
k each task reads what the other published at tick k−1 (zeros at k = 0).
"""

from __future__ import annotations

import dataclasses
import pickle
import shutil
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from jiwy_models import PAN_AXIS, JiwyController, JiwyPlant

from rtloop import Runnable
from rtloop.models import (
    FmuError,
    ModelBuildError,
    ModelError,
    ModelRunnable,
    StepSizeWarning,
    build,
    cli_model_info,
    load_model,
    model_info,
)
from rtloop.models.twentysim import TwentySimModel, default_cache_dir, inspect

MODELS = Path(__file__).resolve().parents[1] / "examples" / "jiwy" / "models"
PERIOD_NS = 1_000_000
STEP_TIME_NS = 500_000_000
SETPOINT_RAD = (0.5, 0.3)

needs_gxx = pytest.mark.skipif(shutil.which("g++") is None, reason="g++ not installed")
needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("model-cache")


@pytest.fixture(scope="session")
def jiwy_fmu(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed: cannot build the JIWY FMU")
    from rtloop.models.fmu_build import build_fmu

    return build_fmu(MODELS / "fmu", tmp_path_factory.mktemp("fmu") / "JiwyPlant.fmu")


@pytest.fixture(scope="session")
def jiwy_fmu3(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed: cannot build the JIWY FMU")
    from rtloop.models.fmu_build import build_fmu

    return build_fmu(MODELS / "fmu3", tmp_path_factory.mktemp("fmu3") / "JiwyPlant3.fmu")


def twentysim(name: str, cache_dir: Path, **options: object) -> ModelRunnable:
    return ModelRunnable(TwentySimModel(MODELS / name, cache_dir=cache_dir, **options))


def closed_loop(controller: Runnable, plant: Runnable, duration_s: float = 3.0) -> np.ndarray:
    """Angles [pan, tilt] per tick for a setpoint step at 0.5 s."""
    for runnable in (controller, plant):
        check = getattr(runnable, "check_period", None)
        if check is not None:
            check(PERIOD_NS)
        runnable.prerun()
    n = round(duration_s * 1e9 / PERIOD_NS)
    u_ctrl, y_ctrl = np.zeros(4), np.zeros(2)
    u_plant, y_plant = np.zeros(2), np.zeros(2)
    published_ctrl, published_plant = np.zeros(2), np.zeros(2)
    angles = np.zeros((n, 2))
    for k in range(n):
        u_ctrl[0:2] = published_plant
        u_ctrl[2:4] = SETPOINT_RAD if k * PERIOD_NS >= STEP_TIME_NS else (0.0, 0.0)
        u_plant[:] = published_ctrl
        controller.step(u_ctrl, y_ctrl)
        plant.step(u_plant, y_plant)
        published_ctrl[:] = y_ctrl
        published_plant[:] = y_plant
        angles[k] = y_plant
    for runnable in (controller, plant):
        runnable.postrun()
    return angles


@pytest.fixture(scope="module")
def reference() -> np.ndarray:
    return closed_loop(JiwyController(), JiwyPlant())


# -- the Python models behave like a gimbal -------------------------------------------


def test_python_step_response_looks_like_a_gimbal(reference: np.ndarray) -> None:
    k_step = STEP_TIME_NS // PERIOD_NS
    assert np.all(reference[:k_step] == 0.0)
    for axis, setpoint in enumerate(SETPOINT_RAD):
        response = reference[k_step:, axis] / setpoint
        overshoot = response.max() - 1.0
        assert 0.05 < overshoot < 0.5, f"axis {axis}: overshoot {overshoot:.2%}"
        outside = np.nonzero(np.abs(response - 1.0) > 0.02)[0]
        settling_s = (outside[-1] + 1) * PERIOD_NS * 1e-9
        assert settling_s < 1.0, f"axis {axis}: settles in {settling_s:.3f} s"
        assert abs(response[-1] - 1.0) < 0.01


def test_comparison_detects_a_changed_parameter(reference: np.ndarray) -> None:
    # The 1e-9 agreement below means something: a 0.05 % change in one damping shows.
    pan = dataclasses.replace(PAN_AXIS, d_cam=PAN_AXIS.d_cam * 1.0005)
    changed = closed_loop(JiwyController(), JiwyPlant(pan=pan))
    assert np.max(np.abs(changed - reference)) > 1e-6


# -- generated code and FMU match the Python models -----------------------------------


@needs_gxx
def test_cpp_models_match_python(reference: np.ndarray, cache_dir: Path) -> None:
    angles = closed_loop(twentysim("Controller", cache_dir), twentysim("Plant", cache_dir))
    assert np.max(np.abs(angles - reference)) <= 1e-9


@needs_gcc
def test_ansi_c_plant_matches_python(reference: np.ndarray, cache_dir: Path) -> None:
    angles = closed_loop(JiwyController(), twentysim("PlantC", cache_dir))
    assert np.max(np.abs(angles - reference)) <= 1e-9


def test_fmu_plant_matches_python(reference: np.ndarray, jiwy_fmu: Path) -> None:
    angles = closed_loop(JiwyController(), load_model(f"fmu:{jiwy_fmu}"))
    assert np.max(np.abs(angles - reference)) <= 1e-9


def test_fmi3_plant_matches_python(reference: np.ndarray, jiwy_fmu3: Path) -> None:
    plant = load_model(f"fmu:{jiwy_fmu3}")
    assert plant.model.kind == "fmu3-cs"  # type: ignore[attr-defined]
    angles = closed_loop(JiwyController(), plant)
    assert np.max(np.abs(angles - reference)) <= 1e-9


@needs_gxx
def test_cpp_controller_with_fmu_plant(
    reference: np.ndarray, cache_dir: Path, jiwy_fmu: Path
) -> None:
    angles = closed_loop(twentysim("Controller", cache_dir), load_model(f"fmu:{jiwy_fmu}"))
    assert np.max(np.abs(angles - reference)) <= 1e-9


@needs_gcc
def test_two_ansi_c_instances_keep_separate_state(cache_dir: Path) -> None:
    a, b = twentysim("PlantC", cache_dir), twentysim("PlantC", cache_dir)
    a.prerun()
    b.prerun()
    y_a, y_b = np.zeros(2), np.zeros(2)
    for _ in range(100):
        a.step(np.array([1.0, 0.0]), y_a)
        b.step(np.array([0.0, 1.0]), y_b)
    a.postrun()
    b.postrun()
    assert y_a[0] > 0 and y_a[1] == 0.0
    assert y_b[0] == 0.0 and y_b[1] > 0


# -- 20-sim specifics ----------------------------------------------------------------


def test_info_names_are_parsed() -> None:
    plant = inspect(MODELS / "Plant")
    assert plant.template == "cpp" and plant.name == "Plant"
    assert plant.input_names == ("SteeringPan", "SteeringTilt")
    assert plant.output_names == ("AnglePan", "AngleTilt")
    assert plant.step_size_s == 0.001
    assert [s.name for s in plant.sources] == ["Plant.cpp"]  # test_Plant.cpp has main()
    controller = inspect(MODELS / "Controller")
    assert controller.input_names == (
        "MeasuredPan", "MeasuredTilt", "SetPointPan", "SetPointTilt",
    )  # fmt: skip
    c_plant = inspect(MODELS / "PlantC")
    assert (c_plant.template, c_plant.prefix) == ("c", "plant_")
    assert "xxmain.c" not in [s.name for s in c_plant.sources]


def test_info_lines_out_of_order_and_gaps(tmp_path: Path) -> None:
    folder = tmp_path / "M"
    shutil.copytree(MODELS / "Plant", folder)
    info = folder / "Plant.info"
    info.write_text(
        "Outputs:\n\ty[1] = m_V[15];\t/* AngleTilt */\n\ty[0] = m_V[14];\t/* AnglePan */\n"
        "Inputs:\n\tm_V[1] = u[1];\t/* B */\n\tm_V[0] = u[0];\t/* A */\n"
    )
    parsed = inspect(folder)
    assert parsed.input_names == ("A", "B")
    assert parsed.output_names == ("AnglePan", "AngleTilt")
    assert parsed.step_size_s == 0.001  # from m_step_size in Plant.cpp
    info.write_text("\tm_V[0] = u[0];\t/* A */\n\tm_V[2] = u[2];\t/* C */\n")
    with pytest.raises(ModelError, match=r"no name for u\[1\]"):
        inspect(folder)


@needs_gxx
def test_build_error_carries_compiler_output_and_path(tmp_path: Path, cache_dir: Path) -> None:
    folder = tmp_path / "Broken"
    shutil.copytree(MODELS / "Plant", folder)
    source = folder / "Plant.cpp"
    source.write_text(source.read_text().replace("m_R[3] = m_V[10];", "m_R[3] = m_V[10]"))
    with pytest.raises(ModelBuildError) as caught:
        TwentySimModel(folder, cache_dir=cache_dir)
    error = caught.value
    assert error.path == str(folder)
    assert "Plant.cpp" in error.compiler_output and "error" in error.compiler_output
    assert str(folder) in str(error) and error.compiler_output in str(error)
    assert isinstance(error, RuntimeError)


def test_not_a_twentysim_folder(tmp_path: Path) -> None:
    (tmp_path / "x.c").write_text("int f(void) { return 0; }\n")
    with pytest.raises(ModelError, match="not a 20-sim export"):
        inspect(tmp_path)


@needs_gxx
def test_finish_time(cache_dir: Path) -> None:
    runnable = twentysim("Plant", cache_dir, finish_time_s=0.05)
    runnable.prerun()
    y = np.zeros(2)
    u = np.array([0.1, 0.1])
    for _ in range(50):
        runnable.step(u, y)
    assert runnable.model.is_finished()  # type: ignore[attr-defined]
    frozen = y.copy()
    runnable.step(u, y)
    assert np.array_equal(y, frozen)
    runnable.postrun()


@needs_gxx
def test_runs_forever_by_default(cache_dir: Path) -> None:
    runnable = twentysim("Plant", cache_dir)
    runnable.prerun()
    y = np.zeros(2)
    u = np.array([0.1, 0.1])
    for _ in range(100_100):  # past the generated finish time of 100 s
        runnable.step(u, y)
    assert not runnable.model.is_finished()  # type: ignore[attr-defined]
    before = y.copy()
    runnable.step(u, y)
    assert y[0] > before[0]
    runnable.postrun()


@needs_gxx
def test_cache_is_reused_and_keyed_by_sources(tmp_path: Path, cache_dir: Path) -> None:
    first = TwentySimModel(MODELS / "Plant", cache_dir=cache_dir).library_path
    again = TwentySimModel(MODELS / "Plant", cache_dir=cache_dir).library_path
    assert first == again
    folder = tmp_path / "Plant"
    shutil.copytree(MODELS / "Plant", folder)
    (folder / "Plant.cpp").write_text((folder / "Plant.cpp").read_text() + "\n/* edit */\n")
    assert TwentySimModel(folder, cache_dir=cache_dir).library_path != first


def test_cache_dir_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("RTLOOP_CACHE_DIR", str(tmp_path))
    assert default_cache_dir() == tmp_path / "models"
    monkeypatch.delenv("RTLOOP_CACHE_DIR")
    assert default_cache_dir() == Path.home() / ".cache" / "rtloop" / "models"


# -- FMU specifics --------------------------------------------------------------------


def test_model_exchange_only_fmu_is_refused(tmp_path: Path) -> None:
    description = (MODELS / "fmu" / "modelDescription.xml").read_text()
    start = description.index("<CoSimulation")
    end = description.index("/>", start) + 2
    me_only = description[:start] + '<ModelExchange modelIdentifier="JiwyPlant"/>' + description[end:]
    fmu = tmp_path / "me_only.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        z.writestr("modelDescription.xml", me_only)
    with pytest.raises(FmuError, match=r"only model exchange.*co-simulation"):
        load_model(f"fmu:{fmu}")


def test_fmu_variables_by_name(jiwy_fmu: Path) -> None:
    runnable = load_model(f"fmu:{jiwy_fmu}", inputs=["SteeringTilt"], outputs=["AngleTilt", "pan.p"])
    assert (runnable.n_inputs, runnable.n_outputs) == (1, 2)
    assert runnable.output_names == ("AngleTilt", "pan.p")
    with pytest.raises(FmuError, match="no variable 'Nope'"):
        load_model(f"fmu:{jiwy_fmu}", outputs=["Nope"])
    with pytest.raises(FmuError, match="only inputs and tunable parameters can be set"):
        load_model(f"fmu:{jiwy_fmu}", inputs=["AnglePan"])


def test_fmu_info(jiwy_fmu: Path) -> None:
    info = model_info(jiwy_fmu)
    assert info["kind"] == "fmu2-cs" and info["fmi_version"] == "2.0"
    assert info["inputs"] == ["SteeringPan", "SteeringTilt"]
    # a variable-step FMU follows the task period; its default step is only a suggestion
    assert info["step_size_s"] is None and info["default_step_size_s"] == 0.001
    text = cli_model_info(f"fmu:{jiwy_fmu}")
    assert "y[1]  AngleTilt" in text and "follows the task period (the FMU suggests 1 ms" in text
    assert "AnglePan  Real  output/continuous" in text and "→ y[0]" in text


# -- adapter contract -----------------------------------------------------------------


@needs_gxx
def test_runnables_pickle_before_prerun(cache_dir: Path, jiwy_fmu: Path) -> None:
    runnables = [
        load_model("python:jiwy_models:JiwyPlant"),
        twentysim("Plant", cache_dir),
        twentysim("PlantC", cache_dir),
        load_model(f"fmu:{jiwy_fmu}"),
    ]
    for runnable in runnables:
        clone = pickle.loads(pickle.dumps(runnable))
        clone.prerun()  # what the task process does
        y = np.zeros(2)
        for _ in range(3):  # input → momentum → angle takes three Euler steps
            clone.step(np.array([0.1, 0.1]), y)
        assert y[0] > 0.0, type(runnable.model).__name__
        pickle.dumps(clone)  # still picklable, ctypes state left behind
        clone.postrun()


@needs_gxx
def test_step_size_warning(cache_dir: Path) -> None:
    runnable = twentysim("Plant", cache_dir)
    with pytest.warns(StepSizeWarning, match="step of 1 ms but its task runs every 2 ms"):
        assert runnable.check_period(2_000_000) is False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert runnable.check_period(1_000_000) is True
        assert JiwyPlant().check_period(1_000_000) is True


def test_fmu_takes_task_period_as_communication_step(jiwy_fmu: Path) -> None:
    runnable = load_model(f"fmu:{jiwy_fmu}")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # variable-step FMU: no warning
        runnable.check_period(2_000_000)
    assert runnable.model.communication_step_s == 0.002  # type: ignore[attr-defined]


def test_load_model_specs(tmp_path: Path) -> None:
    plant = load_model("python:jiwy_models:JiwyPlant")
    assert isinstance(plant, JiwyPlant)
    info = model_info("20sim:Plant", base_dir=MODELS)
    assert info["kind"] == "20sim-cpp" and info["outputs"] == ["AnglePan", "AngleTilt"]
    with pytest.raises(ModelError, match="does not exist"):
        load_model("20sim:NoSuchModel", base_dir=tmp_path)
    with pytest.raises(ModelError, match="nothing to build"):
        build("python:jiwy_models:JiwyPlant")
