"""``signals.json``: what signals.csv's columns are (task, side, index, unit) and how to plot them.

signals.csv stays a plain CSV that any tool reads; this small file beside it carries what a
CSV header cannot: each column's unit and the app's plots (declared with ``[[plot]]`` or
inferred setpoint/measured pairs), by column name::

    {"version": 1,
     "columns": {"plant.omega": {"task": "plant", "side": "y", "index": 0, "unit": "rad/s"}, ...},
     "plots": [{"title": "speed", "signals": ["pi.setpoint", "plant.omega"],
                "setpoint": "pi.setpoint", "inferred": true}, ...]}

The same units go into run.mcap's ``rtloop`` metadata record (key ``units``, JSON).
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any

from rtloop.app.builder import App
from rtloop.app.guards import recorded_input_names, sent_signal
from rtloop.app.plots import Element, element_units, elements, inferred_plots
from rtloop.newfile import write_new
from rtloop.record.csvfiles import column_names

SIDECAR = "signals.json"
VERSION = 1


def recorded_columns(app: App) -> dict[Element, str]:
    """Each recorded element → its signals.csv column name (the order of the file)."""
    columns: dict[Element, str] = {}
    for ref in app.recorded:
        runnable = app.tasks[ref.task].runnable
        names = column_names(ref, recorded_input_names(app, ref.task), runnable.output_names)
        for element, name in zip(elements(ref), names, strict=True):
            columns.setdefault(element, name)
    return columns


def sidecar_content(app: App) -> dict[str, Any]:
    """The JSON of ``signals.json`` for ``app``'s recording."""
    columns = recorded_columns(app)
    units = element_units(app)
    for link in app.device_links:  # what a device was sent has the unit of the output that asked for it
        if link.target.task in app.devices:
            sent = sent_signal(app, link.target.task, link.target.start, link.target.stop)
            for source, element in zip(elements(link.source), elements(sent), strict=True):
                units.setdefault(element, units.get(source, ""))
    carried_by = _mirrors(app)
    out_columns = {name: {"task": task, "side": side, "index": index, "unit": units.get((task, side, index), "")}
                   for (task, side, index), name in columns.items()}
    plots = []
    for spec in [*app.plots, *inferred_plots(app)]:
        names = []
        for ref in spec.signals:
            for element in elements(ref):
                column = columns.get(element) or next((columns[e] for e in carried_by.get(element, ()) if e in columns),
                                                      None)
                if column is not None and column not in names:
                    names.append(column)
        setpoint = columns.get(spec.setpoint) if spec.setpoint is not None else None
        if not names or (spec.inferred and (setpoint is None or len(names) < 2)):
            continue  # an inferred pair is drawn only when both of its signals were recorded
        plots.append({"title": spec.title or " vs ".join(names), "signals": names, "setpoint": setpoint,
                      "inferred": spec.inferred})
    return {"version": VERSION, "columns": out_columns, "plots": [*plots, *_sent_plots(app, columns)]}


def _sent_plots(app: App, columns: dict[Element, str]) -> list[dict[str, Any]]:
    """A plot per device command recorded: what the device was sent (its limits applied) over what the
    controller asked for (drawn as its reference; the report shades where they differ); the same for
    each guarded connection whose two ends are recorded (of one period: a row is the same instant)."""
    plots = []
    recorded = set(columns.values())
    for link in app.device_links:
        spec = app.devices.get(link.target.task)
        if spec is None:
            continue
        names = spec.device.command_names()
        for source, index in zip(elements(link.source), range(link.target.start, link.target.stop), strict=True):
            sent = f"{spec.name}.{names[index]}"
            asked = columns.get(source)
            if sent in recorded:
                plots.append({"title": f"{sent}: what device {spec.name} was sent (after its limits)"
                              + (f" and what {asked} asked for" if asked else ""),
                              "signals": [asked, sent] if asked else [sent], "setpoint": asked, "inferred": False,
                              "limits": True})
    for connection in app.connections:  # a guarded connection of equal periods: the same rows compare
        periods = {app.tasks[end.task].config.period_ns for end in (connection.source, connection.target)}
        if not connection.guarded or len(periods) != 1:
            continue
        for source, target in zip(elements(connection.source), elements(connection.target), strict=True):
            asked, got = columns.get(source), columns.get(target)
            if asked and got:
                plots.append({"title": f"{got}: what it got through its connection's guard and what {asked} asked for",
                              "signals": [asked, got], "setpoint": asked, "inferred": False, "limits": True})
    return plots


def _mirrors(app: App) -> dict[Element, list[Element]]:
    """An output element → the inputs that read it through a connection (the same values, a period on)."""
    mirrors: dict[Element, list[Element]] = {}
    for connection in app.connections:
        for source, target in zip(elements(connection.source), elements(connection.target), strict=True):
            mirrors.setdefault(source, []).append(target)
    return mirrors


def units_by_column(content: dict[str, Any]) -> dict[str, str]:
    """Column → unit, for the columns that have one."""
    return {name: column["unit"] for name, column in content["columns"].items() if column["unit"]}


def write_sidecar(out: Path, content: dict[str, Any]) -> None:
    """Write ``signals.json`` whole or not at all (a temporary name, then a rename)."""
    temporary = out / f".{SIDECAR}.tmp"
    try:
        write_new(temporary, (json.dumps(content, indent=1) + "\n").encode())
        os.replace(temporary, out / SIDECAR)
    except OSError:
        with contextlib.suppress(OSError):
            temporary.unlink()  # a full disk leaves no half-written temporary behind
        raise
