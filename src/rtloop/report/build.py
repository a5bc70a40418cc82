"""Figures and one self-contained HTML page of runs: the engine of ``rtloop report`` (``cli/report.py``)."""

from __future__ import annotations

import contextlib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from rtloop.newfile import write_new
from rtloop.owners import output_folder_problem
from rtloop.report import figures, html
from rtloop.report import signals as signal_figures
from rtloop.report.data import Histogram, ReportError, Run, load_run, run_labels, task_series

FIGURES_DIR = "report-figures"


@dataclass
class Report:
    """What :func:`build_report` produced."""

    runs: list[Run]
    """The runs, loaded."""
    pngs: list[Path] = field(default_factory=list)
    """Every figure written."""
    html: Path | None = None
    """The report page (None with ``html=False``)."""
    histograms: dict[tuple[str, str], dict[str, Histogram]] = field(default_factory=dict)
    """(run label, task) → the histograms drawn in that task's figure."""


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "run"


def build_report(paths: list[Path], out: Path | None = None, *, write_html: bool = True) -> Report:
    """Load every run, draw its figures into ``out``/report-figures and write ``out``/report.html.

    A folder that cannot be written (a full disk, another user's run) is a :class:`ReportError`
    naming the file and the reason, with the way out (``--out``); no half-written figure or page
    is left. The figures of an earlier report in ``out`` are removed first: none of them can sit
    beside the new ones as if it were one of them.
    """
    if not paths:
        raise ReportError("no run directory given")
    runs = [load_run(p, label) for p, label in zip(paths, run_labels(paths), strict=True)]
    out = Path(out) if out is not None else Path(paths[0])
    problem = output_folder_problem(out)
    if problem is not None:
        raise ReportError(f"cannot write the report into {out}/: {problem}; write it elsewhere with --out DIR")
    try:
        return _draw(runs, out, write_html)
    except OSError as error:
        where = f" ({error.filename})" if error.filename else ""
        raise ReportError(f"cannot write the report into {out}/: {error.strerror or error}{where}; "
                          "write it elsewhere with --out DIR") from None


def _remove_earlier_figures(fig_dir: Path) -> None:
    if fig_dir.is_dir() and not fig_dir.is_symlink():
        for old in fig_dir.glob("*.png"):
            old.unlink()


def _draw(runs: list[Run], out: Path, write_html: bool) -> Report:
    fig_dir = out / FIGURES_DIR
    if fig_dir.is_symlink():  # the figures go into a folder of the report's own, not where a link leads
        fig_dir.unlink()
    _remove_earlier_figures(fig_dir)
    report = Report(runs)
    run_figures: dict[str, list[html.FigureRef]] = {}
    for run in runs:
        refs = run_figures.setdefault(run.label, [])
        prefix = _slug(run.label) if len(runs) > 1 else "run"
        # a simulated clock has no timing: latency and jitter are zero by construction (html says so)
        series = {} if run.simulated else {name: task_series(run, name) for name in run.tasks}
        for name, s in series.items():
            fig, hists = figures.task_figure(name, s, run.label)
            report.histograms[(run.label, name)] = hists
            path = figures.save(fig, fig_dir / f"{prefix}-{_slug(name)}-timing.png")
            refs.append(html.FigureRef(path, f"Task {name}: wake-up latency, period jitter and execution time."))
        if series:
            path = figures.save(figures.latency_over_time_figure(run, series), fig_dir / f"{prefix}-latency-time.png")
            refs.append(html.FigureRef(path, "Wake-up latency of every cycle over time (grey: trimmed ends)."))
        if run.signals is not None:
            switches = run.summary.get("switches") or []
            path = figures.save(signal_figures.signals_figure(run.label, run.signals, run.data.inputs, switches),
                                fig_dir / f"{prefix}-signals.png")
            refs.append(html.FigureRef(path, "Recorded signals (signals.csv): one axis per declared plot, "
                                             "setpoint pair or unit; dotted lines: live port writes"
                                             + ("; solid purple: controller switches." if switches else ".")))
        report.pngs.extend(ref.path for ref in refs)
    comparison: list[html.FigureRef] = []
    if len(runs) > 1:
        for name in dict.fromkeys(n for run in runs for n in run.tasks):
            having = [(run.label, task_series(run, name)) for run in runs if name in run.tasks and not run.simulated]
            if not having:
                continue
            fig, _ = figures.comparison_figure(name, having)
            path = figures.save(fig, fig_dir / f"compare-{_slug(name)}.png")
            comparison.append(html.FigureRef(path, f"Task {name} in each run, on common bins."))
            report.pngs.append(path)
    with_signals = [(run.label, run.signals, run.data.inputs) for run in runs if run.signals is not None]
    if len(with_signals) > 1:
        first = next(run for run in runs if run.signals is not None)
        overlaid = signal_figures.comparison_figure(with_signals, first.summary.get("switches") or [])
        if overlaid is not None:
            path = figures.save(overlaid, fig_dir / "compare-signals.png")
            comparison.insert(0, html.FigureRef(path, f"The runs' signals overlaid, and each run's difference to "
                                                      f"{with_signals[0][0]} at the times both recorded."))
            report.pngs.append(path)
    if write_html:
        report.html = out / "report.html"
        _write_whole(report.html, html.page(runs, run_figures, comparison))
    return report


def _write_whole(path: Path, text: str) -> None:
    """Write ``path`` whole or not at all (a temporary name, then a rename)."""
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        write_new(temporary, text.encode())
        os.replace(temporary, path)
    except OSError:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise
