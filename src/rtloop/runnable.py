"""The user's side of a task: what runs every period.

A :class:`Runnable` is the thesis's ``runnable`` (prerun/step/postrun). rtloop owns
the clock: the user writes :meth:`Runnable.step` and the framework calls it once per
period with preallocated input and output vectors.
"""

from __future__ import annotations

import keyword
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

FloatVector = npt.NDArray[np.float64]


@dataclass(slots=True)
class TickInfo:
    """Timing of the tick being computed (like rclpy's ``TimerInfo``).

    Updated in place by the task before each :meth:`Runnable.step`; read it, do not keep it.
    """

    cycle: int = 0
    """Index k of this tick, counted from 0 at the app's epoch T0."""
    release_ns: int = 0
    """When this tick was due: T0 + k·P, CLOCK_MONOTONIC nanoseconds."""
    start_ns: int = 0
    """When the task actually woke up for it (CLOCK_MONOTONIC nanoseconds)."""
    period_ns: int = 0
    """The task's period."""

    @property
    def time_s(self) -> float:
        """Logical time of this tick in seconds since T0 (k·P)."""
        return self.cycle * self.period_ns * 1e-9


class Runnable(ABC):
    """Code that runs periodically in a real-time task.

    Subclasses set ``n_inputs`` and ``n_outputs`` (class attributes or in ``__init__``)
    and implement :meth:`step`. ``prerun`` and ``postrun`` run in the task process,
    outside the timed loop: allocate, open files and warm up there, never in ``step``.

    ``self.tick`` holds the current :class:`TickInfo` while the task runs.

    A runnable whose outputs at t = 0 are not zero (a model's initial conditions) sets
    ``initial_outputs`` in ``prerun``: other tasks then read those values at T0.
    A runnable with a ``check_period(period_ns)`` method is told its task's period when
    it is added to an app (models warn if it differs from their step size).

    Live parameters are declared in one line, with their defaults::

        parameters = {"kp": 0.05, "ki": 2.0}

    ``step`` reads them as ``self.kp`` and ``self.ki``. An app sets them before the run
    (``parameters = { kp = 0.08 }`` in an app file) and, while it runs, through a port:
    each parameter is also an input of the task, after the declared ones, named after it
    (``[ports.gains] to = "pi.kp"``; ``rtloop port write APP gains 0.08``). Being inputs,
    they are recorded with ``u``, logged for replay, and take effect at a release.
    """

    parameters: ClassVar[dict[str, float]] = {}
    """Live parameters and their defaults (see the class docstring); each reads as ``self.<name>``."""
    parameters_are_inputs: ClassVar[bool] = True
    """Models keep their own parameter mechanism (``set_parameters`` before the run) and set this False."""

    initial_outputs: FloatVector | None = None

    n_inputs: int = 0
    n_outputs: int = 0
    input_names: tuple[str, ...] | None = None
    output_names: tuple[str, ...] | None = None
    input_units: tuple[str, ...] | None = None
    """Unit of each input, for plots and recordings (``("rad/s", "V")``; '' for none)."""
    output_units: tuple[str, ...] | None = None
    """Unit of each output."""
    input_start_values: tuple[float, ...] | None = None
    """What each input holds until something writes it (None: zeros)."""

    tick: TickInfo

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        own = cls.__dict__.get("parameters")
        if not cls.parameters_are_inputs or own is None:
            return
        if not isinstance(own, dict):
            raise TypeError(f"{cls.__name__}.parameters must be a dict such as {{'kp': 0.5}}, got {own!r}")
        inherited: dict[str, Any] = next(
            (base.__dict__["parameters"] for base in cls.__mro__[1:] if "parameters" in base.__dict__), {})
        merged = {**inherited, **own}  # a subclass adds to its base's parameters; the base's keep their place
        for index, (name, default) in enumerate(merged.items()):
            if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name) \
                    or name.startswith("_") or name in _RESERVED_NAMES:
                raise TypeError(f"{cls.__name__}.parameters: {name!r} cannot be a parameter name "
                                "(a Python identifier, not starting with _ nor one of Runnable's own attributes)")
            if isinstance(default, bool) or not isinstance(default, int | float) or not math.isfinite(default):
                raise TypeError(f"{cls.__name__}.parameters: {name} = {default!r} is not a finite number")
            setattr(cls, name, LiveParameter(name, index))
        cls.parameters = {name: float(value) for name, value in merged.items()}

    def set_parameters(self, values: dict[str, float]) -> None:
        """New values of declared parameters, before the run (names checked by the caller)."""
        for name, value in values.items():
            setattr(self, name, float(value))

    def add_parameter_inputs(self) -> None:
        """Append the declared parameters to the inputs (called once, when added to an app)."""
        names = tuple(self.parameters) if self.parameters_are_inputs else ()
        if not names or "_parameter_base" in self.__dict__:
            return
        base = self.n_inputs
        starts = getattr(self, "input_start_values", None)
        own_names = tuple(self.input_names or ())[:base]
        self._parameter_base = base
        self.n_inputs = base + len(names)
        self.input_names = (*own_names, *("",) * (base - len(own_names)), *names)  # "": named by index
        self.input_start_values = (*(starts if starts is not None else (0.0,) * base), *self._parameter_starts())

    def bind_inputs(self, u: FloatVector) -> None:
        """Read live parameters from their slots of the task's ``u`` from now on (task side)."""
        base = self.__dict__.get("_parameter_base")
        if base is not None:
            self._parameter_live = u[base:]

    def _parameter_starts(self) -> list[float]:
        """The values parameters start a run with (this runnable's own copy of the defaults)."""
        starts = self.__dict__.get("_parameter_start")
        if starts is None:
            starts = self.__dict__["_parameter_start"] = list(self.parameters.values())
        return starts

    def prerun(self) -> None:
        """Prepare, in the task process, before real-time scheduling starts the loop."""

    @abstractmethod
    def step(self, u: FloatVector, y: FloatVector) -> None:
        """Compute one period: read ``u`` (length ``n_inputs``), fill ``y`` in place."""

    def postrun(self) -> None:
        """Clean up, in the task process, after the loop has stopped."""


class LiveParameter:
    """``self.kp`` of a runnable that declares ``parameters = {"kp": ...}``.

    In a running task (after :meth:`Runnable.bind_inputs`) it reads the parameter's slot of
    the task's ``u``, where ports write; before that, the value the run will start with.
    """

    __slots__ = ("index", "name")

    def __init__(self, name: str, index: int) -> None:
        self.name, self.index = name, index

    def __get__(self, runnable: Runnable | None, owner: type | None = None) -> Any:
        if runnable is None:
            return self
        live = runnable.__dict__.get("_parameter_live")
        return float(live[self.index] if live is not None else runnable._parameter_starts()[self.index])

    def __set__(self, runnable: Runnable, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError(f"parameter {self.name} = {value!r} is not a number")
        runnable._parameter_starts()[self.index] = float(value)
        live = runnable.__dict__.get("_parameter_live")
        if live is not None:
            live[self.index] = float(value)
        base = runnable.__dict__.get("_parameter_base")
        if base is not None:  # added to an app already: the task starts from the new value
            starts = list(runnable.input_start_values or ())
            starts[base + self.index] = float(value)
            runnable.input_start_values = tuple(starts)


_RESERVED_NAMES = frozenset(dir(Runnable)) | {"tick", "n_inputs", "n_outputs"}
