"""The controller switches of a run, read from what its tasks of several controllers record.

A task of several controllers (:class:`rtloop.switching.Controllers`) records which one is
active every cycle and which code it runs; a change there is a switch (or a reload: ``code``).
Decided from the recording, so run, simulate and replay list them alike. Bounded: the first
:data:`MAX_SWITCHES_LISTED` in full, then a count.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.switching import Controllers

MAX_SWITCHES_LISTED = 1000


class SwitchLog:
    def __init__(self, app: App) -> None:
        self.watched: dict[str, tuple[int, Controllers, int]] = {}
        """Per task of several controllers: where ``controller`` lies in its record rows, the
        controllers, the period."""
        for name, spec in app.tasks.items():
            runnable = spec.runnable
            if isinstance(runnable, Controllers):
                self.watched[name] = (runnable.n_common_outputs, runnable, spec.config.period_ns)
        self.last: dict[str, tuple[float, float]] = {name: (math.nan, math.nan) for name in self.watched}
        self.events: list[dict[str, Any]] = []
        self.not_listed = 0

    def add(self, task: str, ticks: np.ndarray, rows: np.ndarray) -> None:
        """Record-queue rows of ``task`` (the outputs of the job of each tick first)."""
        watched = self.watched.get(task)
        if watched is None or not len(ticks):
            return
        column, controllers, period_ns = watched
        table = np.asarray(rows)
        active, code = table[:, column], table[:, column + 3]  # active_controller, active_code
        last_active, last_code = self.last[task]
        before_active = np.concatenate(([last_active], active[:-1]))
        before_code = np.concatenate(([last_code], code[:-1]))
        changed = np.flatnonzero((active != before_active) | (code != before_code))
        for at in changed.tolist():
            if math.isnan(before_active[at]) or math.isnan(active[at]):
                continue  # the first row, or a gap: not a switch
            self._add_event(task, int(ticks[at]), period_ns, controllers, float(before_active[at]),
                            float(active[at]), float(code[at]) if code[at] != before_code[at] else 0.0)
        self.last[task] = (float(active[-1]), float(code[-1]))

    def _add_event(self, task: str, cycle: int, period_ns: int, controllers: Controllers,
                   before: float, now: float, code: float) -> None:
        if len(self.events) >= MAX_SWITCHES_LISTED:
            self.not_listed += 1
            return
        names = controllers.names
        to = names[int(now)] if 0 <= now < len(names) else f"#{now:g}"
        if 0 <= now < len(names) and controllers.has_take_over(to):
            transfer = "take_over"
        elif controllers.blend_s > 0:
            transfer = f"offset decaying over {controllers.blend_s:g} s"
        else:
            transfer = "direct"
        self.events.append({"task": task, "cycle": cycle, "t_s": cycle * period_ns / 1e9,
                            "from": names[int(before)] if 0 <= before < len(names) else f"#{before:g}",
                            "to": to, "transfer": transfer,
                            **({"code": f"{int(code):012x}"} if code else {})})

    def to_json(self) -> list[dict[str, Any]]:
        return list(self.events)
