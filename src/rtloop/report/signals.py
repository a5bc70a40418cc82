"""Figures of a run's signals: one axis per declared plot, setpoint pair or unit; runs overlaid.

Which signals share an axis: the app's plots first (``[[plot]]``, then the setpoint/measured
pairs inferred from its wiring), then the remaining signals one axis per unit, then those
without a unit one axis per task. Legends sit right of the axes, never over the traces.
Every value holds from its time on, so traces are drawn as steps; rows missing from the
recording break the line (a gap is never bridged). Live port writes are dotted vertical
lines, labelled on the first axis (overlaid: in each run's colour). Long runs are drawn as a min/max envelope of at most
:data:`ENVELOPE_BUCKETS` buckets, so a day at 1 kHz plots as fast as a minute.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

from rtloop.record.load import PortInputs, Signals
from rtloop.report.figures import SUPTITLE_TOP_IN, literal, suptitle

FIGURE_WIDTH_IN = 13.0
"""1300 px at the report's 100 dpi: the page reads at 1366 px without shrinking the figures."""
AXIS_HEIGHT_IN = 2.3
MAX_DRAWN_ROWS = 20_000
ENVELOPE_BUCKETS = 2_000
MAX_LABELLED_INPUTS = 12
MAX_SHADED_GAPS = 200
RUN_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
SETPOINT_STYLE = {"color": "black", "linestyle": "--", "linewidth": 1.1}
INPUT_STYLE: dict[str, Any] = {"color": "tab:gray", "linestyle": ":", "linewidth": 1.0}
SWITCH_STYLE: dict[str, Any] = {"color": "tab:purple", "linestyle": "-", "linewidth": 1.0, "alpha": 0.7}
TIME_LABEL = "t [s] (each value holds from t on)"
CODE_ID_OUTPUT = "active_code"
"""A task with controllers records which reloaded code runs (``switching.STATUS_OUTPUTS``): an id, not a
quantity, drawn on an axis of its own."""
PAD_IN = 3 / 72
"""Space between the figure's edge and what is drawn, and between two axes' labels."""


@dataclass(frozen=True)
class Group:
    """Signals on one axis."""

    title: str
    names: tuple[str, ...]
    setpoint: str | None
    """The setpoint's column in a setpoint/measured pair."""
    units: tuple[str, ...]
    """The distinct units of its signals ('' for none)."""
    limits: bool = False
    """What a device was sent beside what was asked for (``setpoint``): where they differ, a limit acted."""

    @property
    def ylabel(self) -> str:
        known = [u for u in self.units if u]
        if not known:
            return "value (no unit declared)"
        return f"[{', '.join(known)}]" + (" / no unit" if "" in self.units else "")


def groups_of(signals: Signals) -> list[Group]:
    """The axes of a signals figure, in order (declared plots, pairs, units, then tasks)."""
    out: list[Group] = []
    placed: set[str] = set()
    for plot in signals.plots:
        names = tuple(n for n in plot.signals if n in signals)
        if not names:
            continue
        title = plot.title
        if plot.inferred and plot.setpoint:
            measured = [n for n in names if n != plot.setpoint]
            title = f"{', '.join(measured)} and its setpoint {plot.setpoint}"
        out.append(Group(title, names, plot.setpoint, _units(signals, names), plot.limits))
        placed.update(names)
    by_unit: dict[str, list[str]] = {}
    by_task: dict[str, list[str]] = {}
    code_ids: list[str] = []
    for name in signals:
        if name in placed:
            continue
        unit = signals.unit(name)
        if unit:
            by_unit.setdefault(unit, []).append(name)
        elif name.rsplit(".", 1)[-1] == CODE_ID_OUTPUT:
            code_ids.append(name)  # a 48-bit id: on the task's axis it flattened every other trace to 0
        else:
            by_task.setdefault(name.split(".", 1)[0], []).append(name)
    out += [Group(f"signals in {unit}", tuple(names), None, (unit,)) for unit, names in by_unit.items()]
    out += [Group(f"task {task}", tuple(names), None, ("",)) for task, names in by_task.items()]
    out += [Group(f"{name}: the id of the reloaded code the active controller runs (0: the code it started with; "
                  "in hex on the switch lines)", (name,), None, ("",)) for name in code_ids]
    return out


def _units(signals: Signals, names: Sequence[str]) -> tuple[str, ...]:
    return tuple(dict.fromkeys(signals.unit(n) for n in names))


def drawable(t_s: np.ndarray, values: np.ndarray, gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(times, values, enveloped): what to draw for one signal, NaN where the line must break.

    Up to :data:`MAX_DRAWN_ROWS` rows every value is drawn, with a NaN put in at each gap.
    Beyond, each of :data:`ENVELOPE_BUCKETS` equal time buckets is drawn as its min and max
    (a bucket without rows, i.e. inside a gap, is NaN and breaks the line).
    """
    t_s = np.asarray(t_s)
    if t_s.size <= MAX_DRAWN_ROWS:
        values = np.asarray(values, dtype=np.float64)
        if len(gaps):
            at = np.searchsorted(t_s, np.asarray(gaps)[:, 1])
            return np.insert(t_s, at, np.asarray(gaps)[:, 0]), np.insert(values, at, np.nan), False
        return t_s, values, False
    first, last = float(t_s[0]), float(t_s[-1])
    width = (last - first) / ENVELOPE_BUCKETS or 1.0
    bucket = np.minimum(((t_s - first) / width).astype(np.int64), ENVELOPE_BUCKETS - 1)
    starts = np.searchsorted(bucket, np.arange(ENVELOPE_BUCKETS))
    counts = np.diff(np.append(starts, t_s.size))
    filled = counts > 0
    column = np.asarray(values, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        low = np.fmin.reduceat(column, starts[filled])
        high = np.fmax.reduceat(column, starts[filled])
    lows = np.full(ENVELOPE_BUCKETS, np.nan)
    highs = np.full(ENVELOPE_BUCKETS, np.nan)
    lows[filled], highs[filled] = low, high
    centers = first + (np.arange(ENVELOPE_BUCKETS) + 0.5) * width
    return np.repeat(centers, 2), np.stack([lows, highs], axis=1).ravel(), True


def _trace(ax: Axes, t_s: np.ndarray, values: np.ndarray, gaps: np.ndarray, **style: Any) -> None:
    x, y, enveloped = drawable(t_s, values, gaps)
    if enveloped:
        ax.plot(x, y, **style)
    else:
        ax.plot(x, y, drawstyle="steps-post", **style)


def _legend(ax: Axes) -> None:
    ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False, borderaxespad=0.0)


def _mark_inputs(axes: Sequence[Axes], inputs: dict[str, PortInputs], color: str | None = None,
                 labelled: set[tuple[float, str, tuple[float, ...]]] | None = None) -> int:
    """Dotted lines where live port writes took effect, labelled on the first axis. Returns how many.

    ``labelled``: writes already labelled by an earlier run of an overlay (a replay repeats its
    run's writes at the same times): those get their line in this run's colour, no second label.
    """
    events = sorted((float(t), port, tuple(float(v) for v in values)) for port, entry in inputs.items()
                    for t, values in zip(entry.t_s, entry.values, strict=True))
    if not axes:
        return len(events)
    style: dict[str, Any] = {**INPUT_STYLE, **({"color": color} if color else {})}
    for ax in axes:
        for t, _, _ in events:
            ax.axvline(t, **style)
    done = labelled if labelled is not None else set()
    fresh = [event for event in events if event not in done]
    if fresh and len(fresh) <= MAX_LABELLED_INPUTS:
        for t, port, values in fresh:
            text = literal(f"{port} ← {', '.join(f'{v:g}' for v in values if v == v)}")
            axes[0].annotate(text, (t, 1.0), xycoords=("data", "axes fraction"), xytext=(2, -2),
                             textcoords="offset points", rotation=90, va="top", ha="left", fontsize=7,
                             color=style["color"])
    done.update(fresh)
    return len(events)


def _mark_switches(axes: Sequence[Axes], switches: Sequence[dict[str, Any]]) -> int:
    """Solid lines where a task changed controller (or loaded new code), labelled on the first axis."""
    events = [s for s in switches if isinstance(s, dict) and isinstance(s.get("t_s"), int | float)]
    for ax in axes:
        for event in events:
            ax.axvline(float(event["t_s"]), **SWITCH_STYLE)
    if axes and len(events) <= MAX_LABELLED_INPUTS:
        for event in events:
            code = f" (code {event['code']})" if event.get("code") else ""
            text = literal(f"{event.get('task')}: {event.get('from')} → {event.get('to')}{code}")
            axes[0].annotate(text, (float(event["t_s"]), 0.0), xycoords=("data", "axes fraction"), xytext=(2, 2),
                             textcoords="offset points", rotation=90, va="bottom", ha="left", fontsize=7,
                             color=SWITCH_STYLE["color"])
    return len(events)


def without_switch_ports(inputs: dict[str, PortInputs], switches: Sequence[dict[str, Any]]) -> dict[str, PortInputs]:
    """The live writes to mark as port writes: a switch request is marked where it took effect instead."""
    tasks = {s.get("task") for s in switches if isinstance(s, dict)}
    return {port: entry for port, entry in inputs.items() if not any(port == f"{task}_switch" for task in tasks)}


def _shade_gaps(axes: Sequence[Axes], gaps: np.ndarray) -> None:
    """Grey where rows are missing (releases skipped, a pruned segment): nothing was recorded there."""
    for ax in axes:
        for i, (start, end) in enumerate(np.asarray(gaps)[:MAX_SHADED_GAPS]):
            ax.axvspan(start, end, color="tab:gray", alpha=0.15, linewidth=0,
                       label="not recorded" if i == 0 and ax is axes[0] else None)
    if len(gaps):
        _legend(axes[0])


def _shade_limits(ax: Axes, signals: Signals, group: Group) -> int:
    """Red where a device (or a guarded connection's reader) got something else than was asked for (its
    limits acted); how many stretches."""
    if not group.limits or group.setpoint is None or len(group.names) < 2:
        return 0
    sent = next(name for name in group.names if name != group.setpoint)
    differs = (signals[sent] != signals[group.setpoint]) & ~np.isnan(signals[sent])
    edges = np.flatnonzero(np.diff(np.concatenate(([False], differs, [False])).astype(np.int8)))
    stretches = edges.reshape(-1, 2)
    t_s = signals.t_s
    ends = np.append(t_s[1:], t_s[-1] if len(t_s) else 0.0)  # each value holds until the next row
    for i, (first, stop) in enumerate(stretches[:MAX_SHADED_GAPS]):
        ax.axvspan(t_s[first], ends[stop - 1], color="tab:red", alpha=0.12, linewidth=0,
                   label="limit acted" if i == 0 else None)
    if len(stretches):
        _legend(ax)
    return len(stretches)


def stack_axes(fig: Figure, axes: Sequence[Axes], heights: Sequence[float], title: Text) -> None:
    """Place ``axes`` one below the other across ``fig``, their heights in the ratios ``heights``,
    with room for what each draws outside itself (tick labels, titles, legends right of it).

    The room is measured once, from each axis as drawn at a first placement: a constrained
    layout measures every axis twice (and the figure draws once more before it is saved), which
    costs more than the drawing. The legends and labels are the same either way.
    """
    fig.set_layout_engine("none")  # whatever a matplotlibrc asks for: this is the layout
    width_in, height_in = fig.get_size_inches()
    renderer = FigureCanvasAgg(fig).get_renderer()  # type: ignore[no-untyped-call]  # untyped in matplotlib 3.11

    def place(left_in: float, right_in: float, top_in: float, gaps_in: Sequence[float], bottom_in: float) -> None:
        free_in = height_in - top_in - bottom_in - sum(gaps_in)
        y_in = height_in - top_in
        for ax, share, gap_in in zip(axes, heights, [0.0, *gaps_in], strict=True):
            y_in -= gap_in + free_in * share / sum(heights)
            ax.set_position((left_in / width_in, y_in / height_in, 1 - (left_in + right_in) / width_in,
                             free_in * share / sum(heights) / height_in))

    place(0.6, 2.0, 0.5, [0.35] * (len(axes) - 1), 0.5)  # near the final placement: the same ticks
    dpi = fig.dpi
    around = []  # (left, right, top, bottom) of each axis' labels and legend beyond it, in inches
    for ax in axes:
        box, inner = ax.get_tightbbox(renderer, for_layout_only=True), ax.get_window_extent(renderer)
        assert box is not None
        around.append(((inner.x0 - box.x0) / dpi, (box.x1 - inner.x1) / dpi, (box.y1 - inner.y1) / dpi,
                       (inner.y0 - box.y0) / dpi))
    title_in = title.get_window_extent(renderer).height / dpi
    place(max(a[0] for a in around) + PAD_IN, max(a[1] for a in around) + PAD_IN,
          SUPTITLE_TOP_IN + title_in + 2 * PAD_IN + around[0][2],
          [upper[3] + lower[2] + 2 * PAD_IN for upper, lower in itertools.pairwise(around)], around[-1][3] + PAD_IN)


def signals_figure(label: str, signals: Signals, inputs: dict[str, PortInputs] | None = None,
                   switches: Sequence[dict[str, Any]] = ()) -> Figure:
    """A run's recorded signals: one axis per group, legends outside, live inputs and switches marked."""
    groups = groups_of(signals)
    fig = Figure(figsize=(FIGURE_WIDTH_IN, 1.0 + AXIS_HEIGHT_IN * len(groups)))
    axes = fig.subplots(len(groups), 1, sharex=True, squeeze=False)[:, 0]
    for ax, group in zip(axes, groups, strict=True):
        color = iter(RUN_COLORS)
        for name in group.names:
            style = dict(SETPOINT_STYLE) if name == group.setpoint else {"color": next(color), "linewidth": 1.3}
            _trace(ax, signals.t_s, signals[name], signals.gaps, label=_label(signals, name, group), **style)
        _finish(ax, group)
    marked = _mark_inputs(list(axes), without_switch_ports(inputs or {}, switches))
    switched = _mark_switches(list(axes), switches)
    _shade_gaps(list(axes), signals.gaps)
    limited = sum(_shade_limits(ax, signals, group) for ax, group in zip(axes, groups, strict=True))
    axes[-1].set_xlabel(TIME_LABEL)
    note = f"; dotted: {marked} live port write(s)" if marked else ""
    note += f"; red: a limit acted ({limited} stretch(es))" if limited else ""
    note += f"; solid purple: {switched} controller switch(es)" if switched else ""
    gaps = f"; {len(signals.gaps)} gap(s) in the recording" if len(signals.gaps) else ""
    title = suptitle(fig, literal(f"{label} — recorded signals{note}{gaps}"))
    stack_axes(fig, list(axes), [AXIS_HEIGHT_IN] * len(groups), title)
    return fig


def comparison_figure(runs: Sequence[tuple[str, Signals, dict[str, PortInputs]]],
                      switches: Sequence[dict[str, Any]] = ()) -> Figure | None:
    """The runs' signals overlaid, each group with the differences to the first run below it.

    Runs are matched by column name and rows by time (a run and its simulation share
    their times t = k·P exactly). None when the runs share no signal.
    """
    reference_label, reference, _ = runs[0]
    groups = [g for g in groups_of(reference) if all(any(n in s for n in g.names) for _, s, _ in runs[1:])]
    if not groups:
        return None
    fig = Figure(figsize=(FIGURE_WIDTH_IN, 1.0 + (AXIS_HEIGHT_IN + 1.5) * len(groups)))
    axes = fig.subplots(2 * len(groups), 1, sharex=True, squeeze=False,
                        gridspec_kw={"height_ratios": [AXIS_HEIGHT_IN, 1.5] * len(groups)})[:, 0]
    limited = 0
    for i, group in enumerate(groups):
        ax, diff_ax = axes[2 * i], axes[2 * i + 1]
        for r, (label, signals, _) in enumerate(runs):
            for s, name in enumerate(n for n in group.names if n in signals):
                # the reference wide and pale beneath: where runs agree, both stay visible
                style = {"color": RUN_COLORS[r % len(RUN_COLORS)], "linewidth": 3.0 if r == 0 else 1.1,
                         "alpha": 0.45 if r == 0 else 1.0, "linestyle": ("-", "--", ":", "-.")[s % 4]}
                _trace(ax, signals.t_s, signals[name], signals.gaps, label=literal(f"{label}: {name}"), **style)
                if r == 0:
                    continue
                t_s, delta = difference(reference, signals, name)
                worst = float(np.nanmax(np.abs(delta))) if delta.size and np.isfinite(delta).any() else float("nan")
                _trace(diff_ax, t_s, delta, np.zeros((0, 2)), label=literal(f"{label} − {reference_label}: {name}"
                                                      f" (max |Δ| {worst:.3g})"), **style)
        _finish(ax, group)
        limited += _shade_limits(ax, reference, group)  # where the first run's limits acted
        diff_ax.axhline(0.0, color="black", linewidth=0.6)
        diff_ax.set_ylabel(literal("Δ " + group.ylabel), fontsize=9)
        diff_ax.grid(True, alpha=0.3)
        if diff_ax.get_legend_handles_labels()[0]:
            _legend(diff_ax)
    labelled: set[tuple[float, str, tuple[float, ...]]] = set()
    marked = [_mark_inputs(list(axes[::2]), without_switch_ports(inputs, switches), RUN_COLORS[r % len(RUN_COLORS)],
                           labelled)
              for r, (_, _, inputs) in enumerate(runs)]
    switched = _mark_switches(list(axes[::2]), switches)  # the first run's: a replay or a simulation repeats them
    axes[-1].set_xlabel(TIME_LABEL)
    writes = "; ".join(f"{label}: {count}" for (label, _, _), count in zip(runs, marked, strict=True) if count)
    note = f"; dotted, in each run's colour: live port writes ({writes})" if writes else ""
    note += f"; solid purple: {reference_label}'s {switched} controller switch(es)" if switched else ""
    note += f"; red: a limit acted in {reference_label} ({limited} stretch(es))" if limited else ""
    title = suptitle(fig, literal(f"signals of {', '.join(label for label, _, _ in runs)} overlaid; below each: the "
                         f"difference to {reference_label} at common times{note}"))
    stack_axes(fig, list(axes), [AXIS_HEIGHT_IN, 1.5] * len(groups), title)
    return fig


def difference(reference: Signals, other: Signals, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``other[name] − reference[name]`` at the times both recorded (rows matched exactly by time)."""
    if name not in reference or name not in other:
        return np.zeros(0), np.zeros(0)
    common, in_ref, in_other = np.intersect1d(np.asarray(reference.t_s), np.asarray(other.t_s),
                                              assume_unique=True, return_indices=True)
    return common, np.asarray(other[name])[in_other] - np.asarray(reference[name])[in_ref]


def _label(signals: Signals, name: str, group: Group) -> str:
    unit = signals.unit(name)
    role = (" (asked for)" if group.limits else " (setpoint)") if name == group.setpoint else ""
    return literal(f"{name}{role}" + (f" [{unit}]" if unit else ""))


def _finish(ax: Axes, group: Group) -> None:
    ax.set_title(literal(group.title), fontsize=10, loc="left")
    ax.set_ylabel(literal(group.ylabel))
    ax.grid(True, alpha=0.3)
    _legend(ax)
