"""Plain-Python models: a :class:`PythonModel` is a :class:`~rtloop.models.base.Model`
and a :class:`~rtloop.Runnable` at once.

Subclass it, set the sizes, names and ``step_size_s``, and write ``initialize``,
``calculate`` and (optionally) ``terminate`` in the order 20-sim uses (see
:mod:`rtloop.models.base`). ``calculate`` runs every tick of a 1 kHz loop: use plain
floats and locals, no numpy temporaries.
"""

from __future__ import annotations

from typing import ClassVar

from rtloop.models.base import ModelRunnable
from rtloop.runnable import FloatVector


class PythonModel(ModelRunnable):
    """Base class of models written in Python; usable directly as a task's runnable."""

    kind = "python"
    step_size_s: float | None = None
    input_names: tuple[str, ...] | None = None
    output_names: tuple[str, ...] | None = None
    parameters: ClassVar[dict[str, float]] = {}
    """Declared parameters and their defaults; an app file sets them by name
    (``parameters = { gain = 2.0 }``), which calls :meth:`set_parameters`."""

    def __init__(self) -> None:
        super().__init__(model=None)
        self.parameters = dict(type(self).parameters)  # type: ignore[misc]  # each model owns a copy: set_parameters changes one model, not its class

    def set_parameters(self, values: dict[str, float]) -> None:
        """Take new parameter values (before the run); names are checked by the caller."""
        self.parameters.update(values)

    def initialize(self, u: FloatVector, y: FloatVector, t_s: float) -> None:
        """Set initial states at time ``t_s`` and write the initial outputs."""

    def calculate(self, u: FloatVector, y: FloatVector) -> None:  # pragma: no cover
        """One model step (override)."""
        raise NotImplementedError

    def terminate(self, u: FloatVector, y: FloatVector) -> None:
        """Release resources (nothing by default)."""

    def step(self, u: FloatVector, y: FloatVector) -> None:
        # Direct call, no adapter hop: this runs every tick.
        cycle = self.tick.cycle if hasattr(self, "tick") else self._next_cycle
        if cycle > self._next_cycle:  # releases were skipped: bring model time back (bounded per cycle)
            self._next_cycle += self.follow_timeline(cycle - self._next_cycle, u, y)
        self.calculate(u, y)
        self._next_cycle += 1
