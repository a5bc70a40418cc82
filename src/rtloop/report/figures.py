"""Figures of a run, in the style of the thesis's chapter 6.

Histograms have log counts, the maximum marked by a red line (or, when it lies beyond
the plotted range, by an arrow and its value) and, for period jitter, the thesis's
criterion as dashed lines at ±3 % of the period. Everything is drawn on
:class:`matplotlib.figure.Figure` objects (Agg canvas, no pyplot state), so the
functions can run in any thread and never open a window.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.text import Text

from rtloop.newfile import open_new
from rtloop.report.data import Histogram, Run, TaskSeries, histogram
from rtloop.stats.timing import THESIS_JITTER_FRACTION

US = 1e3  # ns per µs
FIGURE_WIDTH_IN = 13.0
"""1300 px at 100 dpi: the report page reads at 1366 px without shrinking the figures."""
MAX_COLOR = "tab:red"
CRITERION_COLOR = "tab:orange"
RUN_COLORS = ("tab:blue", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:gray", "tab:olive", "tab:cyan")
PNG_COMPRESS_LEVEL = 3
"""zlib level of the figures: half the encoding time of the default 6 for files ~5 % larger."""
SUPTITLE_TOP_IN = 3 / 72
"""The figure title's distance from the top edge (where matplotlib's constrained layout puts it)."""
TITLE_Y = 1.0
"""An axis title right above its axis: where matplotlib puts it when nothing is drawn above the axis (as on a
log count axis, without an offset text); given, it spares matplotlib a pass over the y ticks to check that."""
TITLE_LINE_IN = 0.185
"""The height of one more line in an axis title (10 pt)."""
HISTOGRAM_MARGINS_IN = {"left_in": 0.6, "right_in": 0.1, "bottom_in": 0.48, "top_in": 0.49}
"""Around histogram and latency axes: log count ticks and a label left, a tick label's overhang right,
ticks and a label below, an axis title and the figure title above."""


def fixed_layout(fig: Figure, rows: int, columns: int, *, left_in: float, right_in: float, bottom_in: float,
                 top_in: float, wspace_in: float = 0.0, hspace_in: float = 0.0) -> None:
    """Place ``fig``'s grid of ``rows`` × ``columns`` axes with margins and gaps in inches.

    The margins are those matplotlib's constrained layout finds for these figures (their tick
    labels, titles and legends have known extents); set once, they spare its solve, which lays
    out every tick label of every axis twice before the figure is drawn and costs more than the
    drawing itself.
    """
    fig.set_layout_engine("none")  # whatever a matplotlibrc asks for: these margins are the layout
    width_in, height_in = fig.get_size_inches()
    axis_width_in = (width_in - left_in - right_in - (columns - 1) * wspace_in) / columns
    axis_height_in = (height_in - top_in - bottom_in - (rows - 1) * hspace_in) / rows
    fig.subplots_adjust(left=left_in / width_in, right=1 - right_in / width_in, bottom=bottom_in / height_in,
                        top=1 - top_in / height_in, wspace=wspace_in / axis_width_in,
                        hspace=hspace_in / axis_height_in)


def suptitle(fig: Figure, text: str) -> Text:
    """The figure's title, at the top edge (a fixed layout leaves the room for it)."""
    return fig.suptitle(text, fontsize=12, y=1 - SUPTITLE_TOP_IN / fig.get_size_inches()[1])


def literal(text: str) -> str:
    """``text`` drawn as written: matplotlib takes a pair of ``$`` for mathtext (a title
    "cost in $ per $m$" would fail to parse), an escaped ``\\$`` is a plain dollar sign."""
    return text.replace("$", r"\$")


def fmt_us(value_ns: float) -> str:
    """A duration in nanoseconds as readable microseconds (``1,234.5 µs``)."""
    if value_ns != value_ns:  # NaN
        return "–"
    if 0 < abs(value_ns) < 100:
        return f"{value_ns:g} ns"
    return f"{value_ns / US:,.1f} µs"


def period_text(period_ns: int) -> str:
    """``P = 1 ms (1000 Hz)``."""
    if not period_ns:
        return "P = ?"
    return f"P = {period_ns / 1e6:g} ms ({1e9 / period_ns:g} Hz)"


def _bars(ax: Axes, hist: Histogram, color: str, label: str | None = None, step: bool = False) -> None:
    """The histogram as one stepped artist on a log count axis (filled, or an outline to overlay
    runs): one path for all bins, where a bar per bin costs a patch each to lay out and draw."""
    ax.set_yscale("log", nonpositive="clip")
    ax.stairs(hist.counts, hist.edges_ns / US, fill=not step, color=color, label=label,
              linewidth=1.5 if step else 0.0, alpha=1.0 if step else 0.85)


def _mark_extreme(ax: Axes, hist: Histogram, which: str, color: str = MAX_COLOR) -> None:
    """Red line at the extreme if it is in range, else an arrow at the edge with its value."""
    value = hist.max_ns if which == "max" else hist.min_ns
    outside = hist.above if which == "max" else hist.below
    if not outside:
        ax.axvline(value / US, color=color, linewidth=1.2, label=f"{which} {fmt_us(value)}")
        return
    x, ha, arrow = (0.99, "right", "→") if which == "max" else (0.01, "left", "←")
    text = f"{which} {fmt_us(value)} {arrow}\n({outside} beyond the axis)" if which == "max" else \
        f"{arrow} {which} {fmt_us(value)}\n({outside} beyond the axis)"
    ax.text(x, 0.97, text, transform=ax.transAxes, ha=ha, va="top", color=color, fontsize=8,
            bbox={"facecolor": "white", "edgecolor": color, "alpha": 0.9, "boxstyle": "round,pad=0.3"})


def _headroom(ax: Axes, highest: int) -> None:
    """Log axis from below 1 to well above the highest bar: room for the legend and notes."""
    ax.set_ylim(0.5, max(highest, 1) * 40)


def _no_data(ax: Axes, title: str) -> None:
    ax.set_title(title)
    ax.text(0.5, 0.5, "no samples", transform=ax.transAxes, ha="center", va="center", color="gray")
    ax.set_xticks([])
    ax.set_yticks([])


def draw_histogram(
    ax: Axes,
    hist: Histogram,
    *,
    title: str,
    xlabel: str,
    period_ns: int = 0,
    criterion: bool = False,
    mark_min: bool = False,
) -> None:
    """One thesis-style histogram on ``ax``."""
    if hist.n == 0:
        _no_data(ax, title)
        return
    bin_ns = hist.edges_ns[1] - hist.edges_ns[0]
    _bars(ax, hist, "tab:blue", label=f"cycles ({hist.counts.size} bins of {fmt_us(bin_ns)})")
    if criterion and period_ns:
        limit_us = THESIS_JITTER_FRACTION * period_ns / US
        ax.axvline(limit_us, color=CRITERION_COLOR, linestyle="--", linewidth=1.2,
                   label=f"±3 % of P (±{limit_us:g} µs)")
        ax.axvline(-limit_us, color=CRITERION_COLOR, linestyle="--", linewidth=1.2)
    _mark_extreme(ax, hist, "max")
    if mark_min:
        _mark_extreme(ax, hist, "min", color="tab:purple")
    _headroom(ax, int(hist.counts.max()))
    ax.set_title(title, fontsize=10, y=TITLE_Y)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("cycles (log)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left" if not hist.below else "center left")


def task_histograms(series: TaskSeries) -> dict[str, Histogram]:
    """The histograms of one task's figure: ``latency``, ``jitter`` and ``exec``."""
    limit = THESIS_JITTER_FRACTION * series.period_ns
    return {
        "latency": histogram(series.latency_ns),
        "jitter": histogram(series.period_jitter_ns, include_ns=(-limit, limit) if limit else ()),
        "exec": histogram(series.exec_ns),
    }


def task_figure(task: str, series: TaskSeries, run_label: str) -> tuple[Figure, dict[str, Histogram]]:
    """Wake-up latency, period jitter and execution time of one task, side by side."""
    hists = task_histograms(series)
    fig = Figure(figsize=(FIGURE_WIDTH_IN, 4.4))
    axes = fig.subplots(1, 3)
    fixed_layout(fig, 1, 3, **HISTOGRAM_MARGINS_IN, wspace_in=0.7)
    jitter = series.period_jitter_ns
    over = int(np.count_nonzero(np.abs(jitter) > THESIS_JITTER_FRACTION * series.period_ns)) if jitter.size else 0
    draw_histogram(axes[0], hists["latency"], title=f"wake-up latency (start − release), n = {hists['latency'].n}",
                   xlabel="latency [µs]")
    draw_histogram(axes[1], hists["jitter"],
                   title=f"period jitter (Δstart − P), n = {hists['jitter'].n}, {over} beyond ±3 %",
                   xlabel="jitter [µs]", period_ns=series.period_ns, criterion=True, mark_min=True)
    draw_histogram(axes[2], hists["exec"], title=f"execution time (end − start), n = {hists['exec'].n}",
                   xlabel="execution time [µs]")
    suptitle(fig, f"{literal(run_label)} — task {task}, {period_text(series.period_ns)}, "
                  f"first and last {series.trim} cycles left out")
    return fig, hists


def latency_over_time_figure(run: Run, series: dict[str, TaskSeries]) -> Figure:
    """Wake-up latency of every cycle against time: periodic disturbances show as stripes."""
    names = list(series)
    fig = Figure(figsize=(FIGURE_WIDTH_IN, 2.6 + 2.2 * len(names)))
    axes = np.atleast_1d(fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0])
    fixed_layout(fig, len(names), 1, **HISTOGRAM_MARGINS_IN, hspace_in=0.33)
    for ax, name in zip(axes, names, strict=True):
        s = series[name]
        samples = s.all_samples
        if not len(samples):
            _no_data(ax, f"task {name}")
            continue
        t0 = samples.release_ns[0]
        t_s = (samples.release_ns - t0) / 1e9
        latency_us = (samples.start_ns - samples.release_ns) / US
        ax.plot(t_s, latency_us, ".", markersize=2, color="tab:blue", label="wake-up latency")
        _mark_misses(ax, run, name, samples, t_s, latency_us, s.period_ns)
        if s.trim and len(samples) > 2 * s.trim:
            ax.axvspan(t_s[0], t_s[s.trim - 1], color="gray", alpha=0.2, label="trimmed (not in statistics)")
            ax.axvspan(t_s[-s.trim], t_s[-1], color="gray", alpha=0.2)
        if latency_us.min() > 0:
            ax.set_yscale("log")
            ax.axhline(s.period_ns / US, color=MAX_COLOR, linestyle=":", linewidth=1,
                       label=f"one period ({s.period_ns / US:g} µs)")
        ax.set_ylabel("latency [µs]")
        ax.set_title(f"task {name}, {period_text(s.period_ns)}", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axes[-1].set_xlabel("time since first release [s]")
    suptitle(fig, f"{literal(run.label)} — wake-up latency over time")
    return fig


MISS_COLORS = {"step": "tab:red", "task": "tab:purple", "thread": "tab:orange", "machine": "tab:brown",
               "irq": "tab:pink", "run queue": "tab:olive", "page faults": "tab:cyan", "unexplained": "black"}
"""One colour per cause class of a miss (stats/miss_causes.py), in the latency-over-time figure."""


def _mark_misses(ax: Axes, run: Run, task: str, samples: Any, t_s: np.ndarray, latency_us: np.ndarray,
                 period_ns: int) -> None:
    """Each deadline miss as a cross, coloured by its cause where summary.json kept it in full."""
    missed = np.flatnonzero(samples.end_ns > samples.release_ns + period_ns)
    if not len(missed):
        return
    kept = {m["cycle"]: m["cause_class"] for m in (run.summary.get("misses") or {}).get("first", [])
            if m.get("task") == task}
    classes = [kept.get(int(samples.cycle[i]), "") for i in missed]
    for cls in dict.fromkeys(classes):
        at = missed[[c == cls for c in classes]]
        label = f"miss: {cls}" if cls else "miss (cause in summary.json counts)"
        ax.plot(t_s[at], np.maximum(latency_us[at], 1e-3), "x", markersize=6, color=MISS_COLORS.get(cls, "gray"),
                label=label)


def names_from_summary(summary: dict[str, Any]) -> dict[str, str]:
    """``{"plant.y[0]": "AnglePan", ...}`` from the task entries of summary.json."""
    names: dict[str, str] = {}
    for task, entry in summary.get("tasks", {}).items():
        for side, key in (("u", "input_names"), ("y", "output_names")):
            for index, name in enumerate(entry.get(key) or []):
                names[f"{task}.{side}[{index}]"] = name
    return names


def comparison_figure(task: str, runs: Sequence[tuple[str, TaskSeries]]) -> tuple[Figure, dict[str, list[Histogram]]]:
    """One task across several runs: latency and jitter histograms on common bins, overlaid."""
    period_ns = next((s.period_ns for _, s in runs if s.period_ns), 0)
    limit = THESIS_JITTER_FRACTION * period_ns
    fig = Figure(figsize=(FIGURE_WIDTH_IN, 4.8))
    axes = fig.subplots(1, 2)
    out: dict[str, list[Histogram]] = {"latency": [], "jitter": []}
    for ax, key, attr, xlabel in (
        (axes[0], "latency", "latency_ns", "wake-up latency [µs]"),
        (axes[1], "jitter", "period_jitter_ns", "period jitter [µs]"),
    ):
        pooled = histogram(np.concatenate([getattr(s, attr) for _, s in runs]),
                           include_ns=(-limit, limit) if key == "jitter" and limit else ())
        for i, (label, s) in enumerate(runs):
            values = getattr(s, attr).astype(np.float64)
            hist = _on_edges(values, pooled.edges_ns)
            out[key].append(hist)
            if hist.n == 0:
                continue
            color = RUN_COLORS[i % len(RUN_COLORS)]
            _bars(ax, hist, color, label=f"{literal(label)}: max {fmt_us(hist.max_ns)}", step=True)
            if not hist.above:
                ax.axvline(hist.max_ns / US, color=color, linestyle="-.", linewidth=1)
        if key == "jitter" and limit:
            ax.axvline(limit / US, color=CRITERION_COLOR, linestyle="--", label=f"±3 % of P (±{limit / US:g} µs)")
            ax.axvline(-limit / US, color=CRITERION_COLOR, linestyle="--")
        if pooled.n == 0:
            _no_data(ax, key)
            continue
        beyond = [f"{literal(label)}: {h.above} above" for (label, _), h in zip(runs, out[key], strict=True) if h.above]
        ax.set_title(f"{key} — dash-dot lines: each run's max" + (f"\n({', '.join(beyond)} the axis)"
                                                                  if beyond else ""), fontsize=10, y=TITLE_Y)
        _headroom(ax, max(int(h.counts.max()) if h.counts.size else 0 for h in out[key]))
        ax.set_xlabel(xlabel)
        ax.set_ylabel("cycles (log)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    title_lines = max(ax.get_title().count("\n") + 1 for ax in axes)
    fixed_layout(fig, 1, 2, **{**HISTOGRAM_MARGINS_IN, "top_in": HISTOGRAM_MARGINS_IN["top_in"]
                               + TITLE_LINE_IN * (title_lines - 1)}, wspace_in=0.68)
    suptitle(fig, f"task {task} across runs, {period_text(period_ns)}")
    return fig, out


def _on_edges(values: np.ndarray, edges_ns: np.ndarray) -> Histogram:
    if values.size == 0:
        return Histogram(np.zeros(len(edges_ns) - 1, np.int64), edges_ns, 0, 0, 0, float("nan"), float("nan"))
    counts, _ = np.histogram(values, bins=edges_ns)
    return Histogram(counts.astype(np.int64), edges_ns, int(np.count_nonzero(values < edges_ns[0])),
                     int(np.count_nonzero(values > edges_ns[-1])), int(values.size),
                     float(values.min()), float(values.max()))


def save(fig: Figure, path: Path) -> Path:
    """Write ``fig`` as a PNG and return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(open_new(path), "wb") as file:  # a new file: never through a link that has the name
            fig.savefig(file, dpi=100, format="png", pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    except BaseException:
        with contextlib.suppress(OSError):
            path.unlink()  # a full disk leaves no empty or half figure behind
        raise
    return path
