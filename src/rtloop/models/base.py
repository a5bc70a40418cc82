"""What every model adapter shares: the :class:`Model` protocol and :class:`ModelRunnable`.

A *model* is a block with a fixed step size and its own clock, the way 20-sim
generated code is: ``initialize`` once, then ``calculate`` once per step. rtloop runs
it inside a task through :class:`ModelRunnable`, which maps

==========  ======================================================
Runnable    Model
==========  ======================================================
prerun      ``initialize(u=0, y, t_s=0.0)`` — outputs from the initial states
step        ``calculate(u, y)`` — one model step
postrun     ``terminate(u, y)``
==========  ======================================================

This is the loop of 20-sim's generated ``main`` (``Initialize`` once, then
``Calculate`` until finished) and of the thesis's ``wrapper20``. Timing consequence,
which fits rtloop's logical execution time: the step of tick *k* (released at k·P)
integrates the states to (k+1)·h and answers the outputs there; rtloop publishes them
at (k+1)·P. With P = h the model and the task agree on time.

Order inside one ``calculate`` (20-sim, Euler): copy ``u`` in; integrate the states
with the rates of the *previous* evaluation (``s += h·R``); advance time by h;
evaluate the equations with the new states and the *current* inputs (new outputs and
rates); copy the outputs to ``y``.
"""

from __future__ import annotations

import math
import pickle
import warnings
from typing import Protocol, runtime_checkable

import numpy as np

from rtloop.errors import RtloopError
from rtloop.runnable import FloatVector, Runnable

__all__ = [
    "FmuError",
    "Model",
    "ModelBuildError",
    "ModelError",
    "ModelRunnable",
    "StateNotCaptured",
    "StepSizeWarning",
    "apply_parameters",
]


class ModelError(RtloopError, RuntimeError):
    """A model could not be found, read, loaded or run."""


class ModelBuildError(ModelError):
    """Generated model code did not compile.

    Attributes:
        path: the model folder.
        command: the compiler command line that failed.
        compiler_output: what the compiler printed, verbatim.
    """

    def __init__(self, path: str, command: list[str], compiler_output: str) -> None:
        self.path = str(path)
        self.command = list(command)
        self.compiler_output = compiler_output
        super().__init__(
            f"20-sim model {self.path} did not compile:\n"
            f"$ {' '.join(self.command)}\n{compiler_output}"
        )


class FmuError(ModelError, ValueError):
    """An FMU cannot be used by rtloop (wrong kind, unknown variable, ...)."""


NOT_STATE = ("tick", "model", "_parameter_live")
"""Attributes a saved state leaves out: the framework's tick, the model itself, views of ``u``."""


class StateNotCaptured(ModelError):
    """A task's state cannot be saved (a ``--keep`` window starting there cannot be replayed)."""


class StepSizeWarning(UserWarning):
    """The task period differs from the step size the model was generated for."""


@runtime_checkable
class Model(Protocol):
    """A fixed-step block with its own clock (20-sim generated code, an FMU, a Python class).

    ``u`` and ``y`` are float64 vectors of length ``n_inputs`` / ``n_outputs``.
    """

    n_inputs: int
    n_outputs: int
    input_names: tuple[str, ...] | None
    output_names: tuple[str, ...] | None
    step_size_s: float | None
    """The step the model was generated for; ``None`` if it follows the task period."""
    kind: str
    """``"python"``, ``"20sim-cpp"``, ``"20sim-c"``, ``"fmu2-cs"`` or ``"fmu3-cs"``."""

    def initialize(self, u: FloatVector, y: FloatVector, t_s: float) -> None:
        """Set the initial states and time ``t_s``; write the initial outputs to ``y``."""

    def calculate(self, u: FloatVector, y: FloatVector) -> None:
        """Advance one step with inputs ``u``; write the outputs to ``y``."""

    def terminate(self, u: FloatVector, y: FloatVector) -> None:
        """Finish: release what ``initialize`` acquired."""


def check_step_size(model: Model, period_ns: int) -> bool:
    """Warn (:class:`StepSizeWarning`) if ``period_ns`` is not the model's step size.

    Returns True when they agree (or the model has no fixed step).
    """
    step_s = model.step_size_s
    if step_s is None:
        return True
    step_ns = round(step_s * 1e9)
    if step_ns == int(period_ns):
        return True
    warnings.warn(
        f"{model.kind} model {describe(model)} was generated for a step of "
        f"{step_s * 1e3:g} ms but its task runs every {period_ns / 1e6:g} ms: each "
        "calculate still advances the model by its own step, so the model runs "
        f"{step_ns / period_ns:.4g}× real time and its dynamics change",
        StepSizeWarning,
        stacklevel=3,
    )
    return False


def describe(model: object) -> str:
    """Short name of a model for messages (its path if it has one)."""
    path = getattr(model, "path", None)
    return repr(str(path)) if path is not None else type(model).__name__


MAX_CATCH_UP_STEPS_PER_CYCLE = 1
"""Extra model steps a cycle takes after skipped releases: a cycle costs at most twice a step."""


class ModelRunnable(Runnable):
    """Runs any :class:`Model` as a :class:`Runnable` in a task.

    Picklable until :meth:`prerun`: adapters load shared libraries and FMUs in
    ``initialize``, which runs in :meth:`prerun`, inside the task process.

    The core calls :meth:`check_period` with the task period before spawning the task.

    Time follows the release timeline: when the task skipped releases (an overrun
    under the ``skip`` policy) the model is brought back to it — in one call by a
    variable-step FMU (one longer step), else by extra steps with the inputs held, at
    most :data:`MAX_CATCH_UP_STEPS_PER_CYCLE` per cycle: ten skipped releases caught up
    in one cycle would make that cycle overrun again, the spiral skipping exists to stop.
    Until it has caught up, the model is that many steps behind the releases. Counted in
    :attr:`catch_up_steps`.
    """

    parameters_are_inputs = False  # a model's parameters are set before the run (set_parameters)

    def __init__(self, model: Model | None = None) -> None:
        self.model: Model = self if model is None else model  # type: ignore[assignment]  # a Python model is its own model (a subclass of both)
        self.n_inputs = self.model.n_inputs
        self.n_outputs = self.model.n_outputs
        self.input_names = self.model.input_names
        self.output_names = self.model.output_names
        self.input_units = getattr(self.model, "input_units", None)
        self.output_units = getattr(self.model, "output_units", None)
        starts = getattr(self.model, "input_start_values", None)
        self.input_start_values: tuple[float, ...] | None = tuple(starts) if starts is not None else None
        """What each input holds until something writes it (an FMU's start values)."""
        self.initial_outputs: FloatVector | None = None
        """What ``initialize`` answered (outputs at t = 0), kept for inspection."""
        self.catch_up_steps = 0
        """Extra model steps taken to follow the timeline after skipped releases."""
        self._next_cycle = 0

    def check_period(self, period_ns: int) -> bool:
        """Tell the model its task period; warn if it is not the model's step size.

        Called by the core once, before the task starts. Models whose step follows
        the task (FMUs: communication step) take it from here through an optional
        ``set_period_ns(period_ns)`` method. Returns False if a
        :class:`StepSizeWarning` was issued.
        """
        agrees = check_step_size(self.model, period_ns)
        set_period = getattr(self.model, "set_period_ns", None)
        if set_period is not None:
            set_period(period_ns)
        return agrees

    def prerun(self) -> None:
        """Initialize the model at t = 0 with the inputs' start values (zeros if none)."""
        u0 = np.zeros(self.n_inputs)
        if self.input_start_values is not None:
            u0[:] = self.input_start_values
        y0 = np.zeros(self.n_outputs)
        self.model.initialize(u0, y0, 0.0)
        self.initial_outputs = y0.copy()
        self._u_final = u0
        self._y_final = y0
        self._next_cycle = 0

    def step(self, u: FloatVector, y: FloatVector) -> None:
        """One model step: ``calculate(u, y)``, after catching up with skipped releases."""
        tick = getattr(self, "tick", None)
        if tick is not None and tick.cycle > self._next_cycle:
            self._next_cycle += self.follow_timeline(tick.cycle - self._next_cycle, u, y)
        self.model.calculate(u, y)
        self._next_cycle += 1

    def resume_at(self, cycle: int) -> None:
        """Go on from ``cycle`` without catching up: the model did not run in between on purpose
        (a controller that was not the active one, see :mod:`rtloop.switching`)."""
        self._next_cycle = cycle

    def follow_timeline(self, behind: int, u: FloatVector, y: FloatVector) -> int:
        """Bring the model forward by up to ``behind`` periods (releases the task did not run).

        Returns the periods it moved: all of them for a variable-step FMU (one longer
        step), at most :data:`MAX_CATCH_UP_STEPS_PER_CYCLE` otherwise."""
        skip = getattr(self.model, "skip_releases", None)
        steps = behind if getattr(self.model, "variable_step", False) else min(behind, MAX_CATCH_UP_STEPS_PER_CYCLE)
        if skip is not None:
            skip(steps)
        else:
            for _ in range(steps):
                self.model.calculate(u, y)
        self.catch_up_steps += steps
        return steps

    def save_state(self) -> bytes:
        """Everything the next steps depend on, after a step (a ``--keep`` window is replayed from it).

        The model's own ``save_state`` where it has one (an FMU: FMI's serialised FMU state), a
        Python model's attributes by pickling; compiled code that keeps its state to itself
        raises :class:`StateNotCaptured` saying so.
        """
        model = self.model
        own = {key: value for key, value in vars(self).items() if key not in NOT_STATE}
        if model is self:  # type: ignore[comparison-overlap]  # a Python model is its own model (a subclass of both)
            model_state = None
        elif (save := getattr(model, "save_state", None)) is not None:
            model_state = save()
        elif model.kind == "python":
            model_state = pickle.dumps(vars(model))
        else:
            raise StateNotCaptured(f"{model.kind} model {describe(model)} keeps its state in compiled code "
                                   "that rtloop cannot read out")
        try:
            return pickle.dumps({"runnable": own, "model": model_state})
        except Exception as error:  # whatever the user's attributes hold
            raise StateNotCaptured(f"{type(self).__name__}'s attributes do not pickle ({error})") from None

    def restore_state(self, saved: bytes) -> None:
        """Take back a state from :meth:`save_state` (after ``prerun``, which loaded the model)."""
        state = pickle.loads(saved)
        vars(self).update(state["runnable"])
        model = self.model
        if state["model"] is None:
            return
        restore = getattr(model, "restore_state", None)
        if restore is not None:
            restore(state["model"])
        else:
            vars(model).update(pickle.loads(state["model"]))

    def postrun(self) -> None:
        """``terminate`` the model (zero inputs; the outputs it writes are not published)."""
        self.model.terminate(self._u_final, self._y_final)
        # The extra steps (catch_up_steps) are said by the supervisor, once per run, with the task's
        # name and the true cause of the skipped releases (runtime/evidence.py), not guessed here.


def apply_parameters(runnable: object, parameters: dict[str, object], where: str) -> None:
    """Set declared parameters of a Python model by name (``parameters = {…}`` in an app file)."""
    declared = getattr(runnable, "parameters", None)
    if not isinstance(declared, dict) or not declared:
        example = ", ".join(f'"{name}": 0.0' for name in list(parameters)[:3] if isinstance(name, str))
        raise ModelError(f"{where}: {type(runnable).__name__} declares no parameters; declare them in its class "
                         f"with their defaults, in one line: parameters = {{{example}}} (then self.NAME in step)")
    numbers: dict[str, float] = {}
    for name, value in parameters.items():
        if name not in declared:
            raise ModelError(f"{where}: unknown parameter {name!r}; parameters are {sorted(declared)}")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ModelError(f"{where}: parameter {name!r} = {value!r} is not a number")
        if not math.isfinite(value):
            raise ModelError(f"{where}: parameter {name!r} = {value!r} is not a finite number")
        numbers[name] = float(value)
    setter = getattr(runnable, "set_parameters", None)
    if setter is None:
        raise ModelError(f"{where}: {type(runnable).__name__} has no set_parameters method")
    setter(numbers)
