"""The user's side of a task: what runs every period.

A :class:`Runnable` is the thesis's ``runnable`` (prerun/step/postrun). rtloop owns
the clock: the user writes :meth:`Runnable.step` and the framework calls it once per
period with preallocated input and output vectors.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

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
    """

    initial_outputs: FloatVector | None = None

    n_inputs: int = 0
    n_outputs: int = 0
    input_names: tuple[str, ...] | None = None
    output_names: tuple[str, ...] | None = None

    tick: TickInfo

    def prerun(self) -> None:
        """Prepare, in the task process, before real-time scheduling starts the loop."""

    @abstractmethod
    def step(self, u: FloatVector, y: FloatVector) -> None:
        """Compute one period: read ``u`` (length ``n_inputs``), fill ``y`` in place."""

    def postrun(self) -> None:
        """Clean up, in the task process, after the loop has stopped."""
