"""Parameter sweeps: the same app simulated over a grid of parameter values, in parallel processes.

    result = sweep("examples/dcmotor/dcmotor.toml", {"pi.kp": grid("0.02:0.2:10")}, duration_s=1.0,
                   out="runs/sweep")
    result.rows[0]   # {"pi.kp": 0.02, "rise_time_s": ..., "overshoot_pct": ..., "run_dir": ...}

Each point is an ordinary :func:`rtloop.simulate` into ``out/NNN``, kept for
:func:`rtloop.load`; the table (``out/sweep.csv``) has one row per point: the parameter
values, then the step response of the declared signal (rise time 10–90 %, overshoot,
settling time to ±2 %, steady-state error over the last 10 % of the step). The step is the
first change of the setpoint paired with the signal (``signals.json``); a signal without a
setpoint is measured against its own final value.

Parameters are the declared parameters of a task's runnable (``parameters = {...}``), set
by name as an app file's ``parameters = { kp = ... }`` sets them.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import itertools
import math
import multiprocessing
import os
import pickle
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.app.specs import check_duration
from rtloop.errors import AppError, RtloopError
from rtloop.owners import output_folder_problem
from rtloop.record.disk_room import check_room
from rtloop.record.recorder import give_to_invoking_user
from rtloop.text import shorten

MAX_POINTS = 10_000
PROCESSES_PER_CPU = 4
METRICS = ("rise_time_s", "overshoot_pct", "settling_time_s", "steady_state_error")


@dataclass
class SweepResult:
    """What :func:`sweep` returns."""

    rows: list[dict[str, Any]]
    """One per point, in grid order: parameter values, the step metrics, ``run_dir`` and ``error``."""
    table: Path
    """``sweep.csv``: the rows as CSV."""
    signal: str
    """The signal whose step response was measured."""
    setpoint: str | None
    """Its setpoint ('' or None: measured against the signal's own final value)."""
    elapsed_s: float = 0.0
    """Wall-clock time of the whole sweep."""
    processes: int = 1
    """Worker processes used."""
    parameters: list[str] = field(default_factory=list)
    """The swept parameters, ``task.name``."""
    unit: str = ""
    """The measured signal's unit (that of the steady-state error); '' when it declares none."""


def grid(text: str) -> list[float]:
    """``0.1:1.0:10`` (10 values from 0.1 to 1.0) or ``0.1,0.2,0.5`` → the values."""
    number = 0
    try:
        if ":" in text:
            start, stop, count = text.split(":")
            number = int(count)
            ends = (float(start), float(stop))  # checked finite below before linspace multiplies them
            values = np.linspace(*ends, number).tolist() if 1 <= number <= MAX_POINTS and \
                all(math.isfinite(v) for v in ends) else []
        else:
            values = [float(v) for v in text.split(",")]
    except ValueError:
        raise AppError(f"sweep values {shorten(text, 60)}: expected START:STOP:COUNT (e.g. 0.1:1.0:10) "
                       "or a list (0.1,0.2,0.5)") from None
    if ":" in text and not 1 <= number <= MAX_POINTS:
        raise AppError(f"sweep values {shorten(text, 60)}: COUNT must be 1 to {MAX_POINTS}, got {number}")
    if not values or not all(math.isfinite(v) for v in values):
        raise AppError(f"sweep values {shorten(text, 60)}: need finite numbers")
    return values


def step_response(t_s: np.ndarray, measured: np.ndarray, setpoint: np.ndarray | None) -> dict[str, float]:
    """Rise time (10–90 %), overshoot [%], settling time (±2 %) and steady-state error of the first step.

    The step is the first change of ``setpoint`` (without one: the whole record, towards the
    signal's final value); the window runs to the next change or the end. NaN where a
    metric is not defined (no step, a signal that never rises).
    """
    nan = {name: math.nan for name in METRICS}
    t_s, measured = np.asarray(t_s, dtype=np.float64), np.asarray(measured, dtype=np.float64)
    if t_s.size < 3:
        return nan
    if setpoint is not None:
        sp = np.asarray(setpoint, dtype=np.float64)
        changes = np.flatnonzero(np.diff(sp) != 0) + 1
        if not changes.size:
            return nan
        begin = int(changes[0])
        end = int(changes[1]) if changes.size > 1 else t_s.size
        initial, target = float(measured[begin - 1]), float(sp[begin])
    else:
        begin, end = 0, t_s.size
        initial, target = float(measured[0]), float(measured[-1])
    t, y = t_s[begin:end] - t_s[begin], measured[begin:end]
    size = target - initial
    if size == 0 or y.size < 2 or not np.isfinite(y).any():
        return nan
    progress = (y - initial) / size  # 0 at the start, 1 at the target, whichever the direction
    reached_10 = np.flatnonzero(progress >= 0.1)
    reached_90 = np.flatnonzero(progress >= 0.9)
    rise = float(t[reached_90[0]] - t[reached_10[0]]) if reached_10.size and reached_90.size else math.nan
    overshoot = max(0.0, float(np.nanmax(progress)) - 1.0) * 100.0
    outside = np.flatnonzero(np.abs(progress - 1.0) > 0.02)
    settling = float(t[outside[-1] + 1]) if outside.size and outside[-1] + 1 < t.size else \
        (0.0 if not outside.size else math.nan)
    tail = y[int(0.9 * y.size):]
    error = float(target - np.nanmean(tail)) if setpoint is not None else math.nan
    return {"rise_time_s": rise, "overshoot_pct": overshoot, "settling_time_s": settling,
            "steady_state_error": error}


def parse_parameter(text: str) -> tuple[str, list[float]]:
    """``pi.kp=0.1:1.0:10`` → ("pi.kp", values)."""
    name, sep, values = text.partition("=")
    task, dot, parameter = name.strip().partition(".")
    if not sep or not dot or not task or not parameter.isidentifier():
        raise AppError(f"--param {shorten(text, 60)}: expected TASK.PARAMETER=START:STOP:COUNT, e.g. pi.kp=0.1:1.0:10")
    return f"{task}.{parameter}", grid(values)


def sweep(app: App | str | os.PathLike[str], parameters: dict[str, list[float]], *, duration_s: float,
          out: str | os.PathLike[str], signal: str | None = None, setpoint: str | None = None,
          processes: int | None = None, feeds: dict[str, str | os.PathLike[str]] | None = None,
          force: bool = False) -> SweepResult:
    """Simulate ``app`` at every point of the grid ``parameters`` (``{"pi.kp": [...], ...}``), in parallel.

    ``app`` is an :class:`~rtloop.App` (sent to the workers by pickling: its runnables'
    classes must be importable) or an app file, loaded again in each worker. ``signal``
    names the column whose step is measured (default: the first setpoint pair of
    signals.json); ``setpoint`` its setpoint (default: its pair's).
    """
    check_duration(duration_s)
    if not parameters:
        raise AppError("sweep: give at least one parameter to sweep (--param TASK.NAME=START:STOP:COUNT)")
    names = list(parameters)
    count = math.prod(len(parameters[n]) for n in names)  # counted before the grid exists: 1e12 points fit no memory
    if count > MAX_POINTS:
        raise AppError(f"sweep: {count} points; at most {MAX_POINTS}")
    check_processes(processes)
    points = list(itertools.product(*(parameters[n] for n in names)))
    source = _AppSource.of(app, feeds or {})
    probe = source.build()  # bad parameter names fail here, once, before any process starts
    for name in names:
        _set_parameter(probe, name, parameters[name][0])
    out = Path(out)
    check_room(probe, out, duration_s * len(points), what=f"{len(points)} simulations of {duration_s:.15g} s",
               remedy="sweep fewer points or give a shorter --duration")
    width = len(str(len(points) - 1))
    run_dirs = [out / f"{i:0{width}d}" for i in range(len(points))]
    _prepare_out(out, run_dirs, force)
    jobs = [(source, dict(zip(names, point, strict=True)), duration_s, str(run_dir), signal, setpoint, force)
            for run_dir, point in zip(run_dirs, points, strict=True)]
    workers = max(1, min(processes or os.cpu_count() or 1, len(jobs)))
    started = time.perf_counter()
    if workers == 1:
        rows = [_simulate_point(*job) for job in jobs]
    else:
        context = multiprocessing.get_context("spawn")  # no fork of a process that may hold threads
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            rows = list(pool.map(_simulate_point, *zip(*jobs, strict=True)))
    elapsed = time.perf_counter() - started
    measured = next((r["signal"] for r in rows if r.get("signal")), "")  # '': no point measured one
    paired = next((r["setpoint"] for r in rows if r.get("setpoint")), setpoint)
    unit = next((r["unit"] for r in rows if r.get("unit")), "")
    for row in rows:
        row.pop("signal", None)
        row.pop("setpoint", None)
        row.pop("unit", None)
    table = out / "sweep.csv"
    columns = [*names, *METRICS, "run_dir", "error"]
    with _out_errors(out, "the runs are there, the table was not written"):
        with open(table, "w", newline="") as file:
            writer = csv.DictWriter(file, columns)
            writer.writeheader()
            writer.writerows(rows)
        give_to_invoking_user(table)
    return SweepResult(rows, table, measured, paired, elapsed, workers, names, unit)


def max_processes() -> int:
    """Worker processes a sweep may start: a simulation keeps one CPU busy, so more than a few per
    CPU only share them (and each holds its own Python and app in memory)."""
    return PROCESSES_PER_CPU * len(os.sched_getaffinity(0))


def check_processes(processes: int | None) -> None:
    """Refuse a worker count that is not a whole number from 1 to :func:`max_processes`."""
    if processes is None:
        return
    most = max_processes()
    if isinstance(processes, bool) or not isinstance(processes, int) or not 1 <= processes <= most:
        raise AppError(f"sweep: processes {shorten(processes, 30)}: must be 1 to {most} "
                       f"({PROCESSES_PER_CPU} per CPU this process may use; more would only share them)")


def _prepare_out(out: Path, run_dirs: list[Path], force: bool) -> None:
    """Refuse an ``out`` that cannot take the sweep before anything runs; folders made here
    belong to the user who ran sudo (as a run's do), so they can sweep again without it."""
    table = out / "sweep.csv"
    if table.exists() and not force:
        raise AppError(f"--out {out} holds a sweep already (sweep.csv): choose another folder, "
                       "or --force to replace it (force=True in Python)")
    problem = output_folder_problem(out)
    if problem is not None:
        raise AppError(f"--out {out}: {problem}; nothing was run: choose a folder of yours")
    with _out_errors(out, "nothing was run"):
        missing = [folder for folder in (out, *out.parents) if not folder.exists()]
        out.mkdir(parents=True, exist_ok=True)
        for folder in reversed(missing):
            folder.chmod(folder.stat().st_mode & ~0o022)  # whatever the umask: nobody else writes in it
            give_to_invoking_user(folder)
        for path in (out, table, *run_dirs):
            if os.path.lexists(path) and not os.access(path, os.W_OK, follow_symlinks=False):
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))


@contextlib.contextmanager
def _out_errors(out: Path, consequence: str) -> Iterator[None]:
    try:
        yield
    except OSError as error:
        where = f" ({os.fsdecode(error.filename)})" if error.filename is not None else ""
        raise AppError(f"--out {out} cannot be used: {(error.strerror or str(error)).lower()}{where}; "
                       f"{consequence}: choose another --out") from None


@dataclass(frozen=True)
class _AppSource:
    """How a worker gets its own copy of the app: an app file to load, or a pickled App."""

    path: str | None
    pickled: bytes | None
    feeds: tuple[tuple[str, str], ...]

    @staticmethod
    def of(app: App | str | os.PathLike[str], feeds: dict[str, str | os.PathLike[str]]) -> _AppSource:
        pairs = tuple((port, str(Path(p).resolve())) for port, p in feeds.items())
        if isinstance(app, App):
            try:
                return _AppSource(None, pickle.dumps(app), pairs)
            except Exception as error:
                raise AppError(f"sweep: app {app.name!r} cannot be sent to worker processes ({error}); "
                               "define its runnables at module level, or sweep its app file") from None
        return _AppSource(str(Path(app).resolve()), None, pairs)

    def build(self) -> App:
        if self.pickled is not None:
            app: App = pickle.loads(self.pickled)
        else:
            from rtloop.app.appfile import load_app

            assert self.path is not None
            app = load_app(self.path)
        for port, path in self.feeds:
            app.feed(port, path)
        return app


def _set_parameter(app: App, name: str, value: float) -> None:
    from rtloop.models.base import apply_parameters

    task, _, parameter = name.partition(".")
    if task not in app.tasks:
        raise AppError(f"sweep {name}: no task {task!r}; tasks are {sorted(app.tasks)}")
    try:
        apply_parameters(app.tasks[task].runnable, {parameter: value}, f"sweep {name}")
    except RtloopError as error:
        raise AppError(str(error)) from None


def _simulate_point(source: _AppSource, values: dict[str, float], duration_s: float, out: str,
                    signal: str | None, setpoint: str | None, force: bool) -> dict[str, Any]:
    """One point of the grid, in a worker: build, set, simulate, measure."""
    from rtloop.record.load import load
    from rtloop.runtime.simulate import simulate

    row: dict[str, Any] = {**values, **dict.fromkeys(METRICS, math.nan), "run_dir": out, "error": ""}
    try:
        app = source.build()
        for name, value in values.items():
            _set_parameter(app, name, value)
        simulate(app, duration_s, out, force=force)
        run = load(out)
    except RtloopError as error:  # a point that fails (a model diverging to NaN, say) is a row, not the end
        row["error"] = str(error).splitlines()[0][:200]
        return row
    signals = run.signals
    if signals is None:
        row["error"] = "the app records no signal"
        return row
    if setpoint is not None and setpoint not in signals:
        row["error"] = f"no signal {setpoint!r} recorded (--setpoint)"
        return row
    measured, paired = _measured_signal(signals, signal, setpoint)
    if measured is None:
        row["error"] = f"no signal {signal!r} recorded" if signal else "no setpoint pair in signals.json: give --signal"
        return row
    row.update(step_response(signals.t_s, signals[measured], signals[paired] if paired else None))
    row["signal"], row["setpoint"], row["unit"] = measured, paired, signals.units.get(measured, "")
    return row


def _measured_signal(signals: Any, signal: str | None, setpoint: str | None) -> tuple[str | None, str | None]:
    pairs = [p for p in signals.plots if p.setpoint]
    if signal is None:
        if not pairs:
            return None, None
        pair = pairs[0]
        return next(n for n in pair.signals if n != pair.setpoint), setpoint or pair.setpoint
    if signal not in signals:
        return None, None
    if setpoint is None:
        setpoint = next((p.setpoint for p in pairs if signal in p.signals), None)
    return signal, setpoint if setpoint in signals else None


def format_table(result: SweepResult) -> str:
    """The sweep's table as aligned text."""
    error = f"ss error [{result.unit}]" if result.unit else "ss error"
    header = [*result.parameters, "rise [s]", "overshoot [%]", "settling [s]", error, "run"]
    lines = [header]
    for row in result.rows:
        cells = [f"{row[n]:.6g}" for n in result.parameters]
        cells += [f"{row[m]:.4g}" if row[m] == row[m] else "–" for m in METRICS]
        cells.append(row["error"] or Path(row["run_dir"]).name)
        lines.append(cells)
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join("  ".join(cell.rjust(w) for cell, w in zip(line, widths, strict=True)) for line in lines)
