"""Units of signals and the plots an app asks for: declared, or inferred from its wiring.

Units come from the runnable (``input_units``/``output_units``, one line in a Python
runnable; an FMU's ``unit`` attributes), overridden by the app (``app.set_units`` or
``units = { ... }`` in a task's table). Plots are declared (``app.plot(...)``, ``[[plot]]``)
or inferred: an input port whose name says it is a setpoint (``setpoint``, ``reference``,
``target``, ...) next to a connection of the same size into the same task (from another task
or from a device's readings) is drawn over what that connection carries, element by element:
setpoint and measured on one axis.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from rtloop.errors import AppError

# The builder imports this module, so the app and its signals are typed loosely here.
App = Any
SignalRef = Any

Element = tuple[str, str, int]
"""(task, side, index): one value of a task's input (``u``) or output (``y``) vector."""

SETPOINT_WORDS = re.compile(r"setpoint|set_point|reference|(^|_)ref($|_)|target|desired|demand|(^|_)sp($|_)",
                            re.IGNORECASE)
MAX_UNIT_LENGTH = 32


@dataclass(frozen=True, slots=True)
class PlotSpec:
    """Signals drawn on one axis."""

    title: str
    """The plot's title ('' : named after its signals)."""
    signals: tuple[SignalRef, ...]
    """What is drawn, in this order."""
    setpoint: Element | None = None
    """For a setpoint/measured pair: the setpoint element (the other is the measured one)."""
    inferred: bool = False
    """Found from the wiring, not declared."""


def check_unit(where: str, unit: object) -> str:
    """A unit is a short printable string (``rad/s``, ``N·m``); '' for none."""
    if not isinstance(unit, str) or len(unit) > MAX_UNIT_LENGTH or not unit.isprintable() or "," in unit:
        raise AppError(f"{where}: unit {unit!r} must be text of at most {MAX_UNIT_LENGTH} characters, no commas")
    return unit.strip()


def runnable_units(runnable: object, side: str, count: int) -> list[str]:
    """The units a runnable declares for ``u`` or ``y`` ('' where it declares none)."""
    declared = getattr(runnable, "input_units" if side == "u" else "output_units", None) or ()
    units = [str(u) if u is not None else "" for u in list(declared)[:count]]
    return units + [""] * (count - len(units))


def element_units(app: App) -> dict[Element, str]:
    """Every element's unit: the app's declaration, else the runnable's ('' when neither has one)."""
    units: dict[Element, str] = {}
    for name, spec in app.tasks.items():
        for side, count in (("u", spec.runnable.n_inputs), ("y", spec.runnable.n_outputs)):
            for index, unit in enumerate(runnable_units(spec.runnable, side, count)):
                units[(name, side, index)] = unit
    units.update(app.unit_overrides)
    return units


def elements(ref: SignalRef) -> list[Element]:
    return [(ref.task, ref.side, i) for i in range(ref.start, ref.stop)]


def inferred_plots(app: App) -> list[PlotSpec]:
    """Setpoint over measured, for each setpoint port beside a connection of its size into the same task."""
    units = element_units(app)
    plots = []
    for port in app.ports.values():
        if port.direction != "in":
            continue
        target = port.signal
        names = _element_names(app, target)
        names_say_so = any(names) and all(SETPOINT_WORDS.search(n) for n in names)
        if not (SETPOINT_WORDS.search(port.name) or names_say_so):
            continue
        # what is measured comes from another task, or from a device (a reading the task takes in)
        links = [c for c in [*app.connections, *app.device_links]
                 if c.target.task == target.task and c.target.size == target.size]
        if len(links) != 1:
            continue  # none, or ambiguous: leave it to a declared [[plot]]
        measured = links[0]
        from_device = measured.source.task not in app.tasks
        for i in range(target.size):
            setpoint = app.tasks[target.task].u[target.start + i]
            if from_device:  # recorded as the task's input it feeds
                source = app.tasks[target.task].u[measured.target.start + i]
            else:
                source = app.tasks[measured.source.task].y[measured.source.start + i]
            unit_sp, unit_m = units.get(elements(setpoint)[0], ""), units.get(elements(source)[0], "")
            if unit_sp and unit_m and unit_sp != unit_m:
                continue
            plots.append(PlotSpec("", (source, setpoint), setpoint=elements(setpoint)[0], inferred=True))
    return plots


def _element_names(app: App, ref: SignalRef) -> list[str]:
    runnable = app.tasks[ref.task].runnable
    names = list(getattr(runnable, "input_names" if ref.side == "u" else "output_names", None) or ())
    return [names[i] if i < len(names) else "" for i in range(ref.start, ref.stop)]
