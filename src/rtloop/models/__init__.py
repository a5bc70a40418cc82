"""Models as runnables: 20-sim generated code, FMUs and plain Python classes.

An app names a model by a spec string::

    "20sim:models/Plant"        a 20-sim C++ or ANSI-C export folder
    "fmu:models/JiwyPlant.fmu"  an FMI 2.0/3.0 co-simulation FMU
    "python:pkg.module:Class"   a Python class (a Runnable, or a Model to wrap)

:func:`load_model` turns a spec into a :class:`~rtloop.Runnable`;
:func:`model_info` and :func:`build` back ``rtloop model info`` / ``rtloop model build``.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import Any

from rtloop.models.base import FmuError as FmuError
from rtloop.models.base import Model as Model
from rtloop.models.base import ModelBuildError as ModelBuildError
from rtloop.models.base import ModelError as ModelError
from rtloop.models.base import ModelRunnable as ModelRunnable
from rtloop.models.base import StepSizeWarning as StepSizeWarning
from rtloop.models.python import PythonModel as PythonModel
from rtloop.runnable import Runnable

__all__ = [
    "FmuError",
    "Model",
    "ModelBuildError",
    "ModelError",
    "ModelRunnable",
    "PythonModel",
    "StepSizeWarning",
    "build",
    "cli_model_build",
    "cli_model_info",
    "load_model",
    "model_info",
    "model_path",
    "open_model",
]

SCHEMES = ("20sim", "fmu", "python")


def _split(spec: str | os.PathLike[str]) -> tuple[str, str]:
    """("20sim" | "fmu" | "python", rest); a bare path is classified by what it is."""
    text = os.fspath(spec)
    scheme, sep, rest = text.partition(":")
    if sep and scheme in SCHEMES:
        return scheme, rest
    path = Path(text)
    if path.suffix == ".fmu" or (path / "modelDescription.xml").is_file():
        return "fmu", text
    return "20sim", text


def _resolve(path: str, base_dir: str | os.PathLike[str] | None) -> Path:
    p = Path(path).expanduser()
    if not p.is_absolute() and base_dir is not None:
        p = Path(base_dir) / p
    return p


def model_path(spec: str | os.PathLike[str], base_dir: str | os.PathLike[str] | None = None) -> Path | None:
    """The file or folder a model spec loads code from (None for ``python:``, an installed module)."""
    scheme, rest = _split(spec)
    return None if scheme == "python" else _resolve(rest, base_dir)


def open_model(
    spec: str | os.PathLike[str], base_dir: str | os.PathLike[str] | None = None, **options: Any
) -> Model:
    """The :class:`Model` a spec names (not yet wrapped). ``options`` go to its constructor."""
    scheme, rest = _split(spec)
    if scheme == "python":
        module_name, _, attribute = rest.partition(":")
        if not attribute:
            raise ModelError(f"model spec {spec!r}: expected python:package.module:Class")
        cls = getattr(importlib.import_module(module_name), attribute)
        model: Model = cls(**options)
        return model
    path = _resolve(rest, base_dir)
    if scheme == "fmu":
        from rtloop.models.fmu import FmuModel

        return FmuModel(path, **options)
    from rtloop.models.twentysim import TwentySimModel

    return TwentySimModel(path, **options)


def load_model(
    spec: str | os.PathLike[str], base_dir: str | os.PathLike[str] | None = None, **options: Any
) -> Runnable:
    """A runnable for a model spec (``"20sim:…"``, ``"fmu:…"``, ``"python:mod:Class"``).

    Relative paths are taken from ``base_dir`` (the app file's folder) or the current
    directory. ``options`` go to the model's constructor (``finish_time_s=`` for 20-sim,
    ``inputs=``/``outputs=`` for FMUs). 20-sim code is compiled here, so compiler errors
    surface before any task starts. Call ``check_period(period_ns)`` on the result.
    """
    model = open_model(spec, base_dir, **options)
    if isinstance(model, Runnable):
        return model
    return ModelRunnable(model)


def model_info(
    spec: str | os.PathLike[str], base_dir: str | os.PathLike[str] | None = None
) -> dict[str, Any]:
    """Interface of a model without compiling or loading it.

    Returns ``{"path", "kind", "name", "inputs", "outputs", "step_size_s"}`` plus
    ``fmi_version`` for FMUs and ``template`` for 20-sim code.
    """
    scheme, rest = _split(spec)
    if scheme == "python":
        model = open_model(spec)
        return {
            "path": rest,
            "kind": getattr(model, "kind", "python"),
            "name": type(model).__name__,
            "inputs": list(model.input_names or ()),
            "outputs": list(model.output_names or ()),
            "step_size_s": getattr(model, "step_size_s", None),
        }
    path = _resolve(rest, base_dir)
    if scheme == "fmu":
        from rtloop.models.fmu import FmuModel

        fmu = FmuModel(path)
        return {
            "path": str(fmu.path),
            "kind": fmu.kind,
            "name": fmu.model_identifier,
            "inputs": list(fmu.input_names or ()),
            "outputs": list(fmu.output_names or ()),
            "step_size_s": fmu.step_size_s,
            "default_step_size_s": fmu.default_step_size_s,
            "fmi_version": fmu.fmi_version,
            "variables": fmu.describe_variables(),
        }
    from rtloop.models.twentysim import inspect

    info = inspect(path)
    return {
        "path": str(info.path),
        "kind": info.kind,
        "name": info.name,
        "inputs": list(info.input_names),
        "outputs": list(info.output_names),
        "step_size_s": info.step_size_s,
        "template": info.template,
        "sources": [str(s.relative_to(info.path)) for s in info.sources],
        "parameters": [{"name": n, "index": i, "default": d} for n, i, d in info.parameters],
    }


def build(
    spec: str | os.PathLike[str],
    base_dir: str | os.PathLike[str] | None = None,
    out_path: str | os.PathLike[str] | None = None,
) -> Path:
    """Compile a model; return what was built.

    A 20-sim folder → its cached shared library. An FMU source folder
    (``modelDescription.xml`` + ``sources/*.c``) → an ``.fmu`` at ``out_path`` (default:
    ``<cache>/fmu/<folder>.fmu``, the cache of 20-sim libraries — never the source tree).
    A ready ``.fmu`` has nothing to build.
    """
    scheme, rest = _split(spec)
    path = _resolve(rest, base_dir)
    if scheme == "fmu":
        if path.is_dir() and (path / "sources").is_dir():
            from rtloop.models.fmu_build import build_fmu
            from rtloop.models.twentysim import default_cache_dir

            default = default_cache_dir().parent / "fmu" / f"{path.resolve().name}.fmu"
            target = Path(out_path) if out_path else default
            target.parent.mkdir(parents=True, exist_ok=True)
            return build_fmu(path, target)
        raise ModelError(f"{str(path)!r} is an FMU: it is already built")
    if scheme == "python":
        raise ModelError(f"{spec!r} is a Python model: nothing to build")
    from rtloop.models.twentysim import build_library, inspect

    return build_library(inspect(path))


def cli_model_info(spec: str | os.PathLike[str]) -> str:
    """Text for ``rtloop model info PATH``."""
    info = model_info(spec)
    step = info["step_size_s"]
    default_step = info.get("default_step_size_s")
    if step:
        step_line = f"step size: {step * 1e3:g} ms"
    elif default_step:
        step_line = (f"step size: follows the task period (the FMU suggests {default_step * 1e3:g} ms, "
                     "used only without a task)")
    else:
        step_line = "step size: follows the task period"
    lines = [
        f"{info['name']}  ({info['kind']})  {info['path']}",
        step_line,
        f"inputs ({len(info['inputs'])}):",
        *(f"  u[{i}]  {name}" for i, name in enumerate(info["inputs"])),
        f"outputs ({len(info['outputs'])}):",
        *(f"  y[{i}]  {name}" for i, name in enumerate(info["outputs"])),
    ]
    if info.get("parameters"):
        lines.append(f"parameters ({len(info['parameters'])}), set with parameters = {{ name = value }}:")
        lines += [f"  {p['name']} = {p['default']!r}" for p in info["parameters"]]
    if info.get("variables"):
        lines.append("variables (name  type  causality/variability  start  unit  → mapped to; description):")
        for v in info["variables"]:
            shape = f"[{','.join(str(n) for n in v['shape'])}]" if v["shape"] else ""
            mapped = f"  → {', '.join(v['mapped'][:4])}{'…' if len(v['mapped']) > 4 else ''}" if v["mapped"] else ""
            lines.append(f"  {v['name']}{shape}  {v['type']}  {v['causality']}/{v['variability']}  "
                         f"start={v['start'] if v['start'] is not None else '-'}  unit={v['unit'] or '-'}"
                         f"{mapped}{'; ' + v['description'] if v['description'] else ''}")
    return "\n".join(lines)


def cli_model_build(spec: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None) -> str:
    """Text for ``rtloop model build PATH [--out FILE]`` (raises :class:`ModelBuildError` on failure)."""
    built = build(spec, out_path=out_path)
    text = f"built {os.fspath(spec)} → {built}"
    if built.suffix == ".fmu":
        text += f'\nuse it in an app file: model = "fmu:{built}"'
    return text
