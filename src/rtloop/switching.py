"""Several controllers in one task, one active: switch at a release, bumpless, or run one in shadow.

A :class:`Controllers` is itself a :class:`~rtloop.runnable.Runnable`: a task runs it like any
other, so run, simulate and replay treat it alike. What changes the active controller is an
*input* of the task (decision 22: a controller change is an input): three values after the
controllers' common inputs, written through the task's switch port (``rtloop switch``), logged
with the cycle at which they took effect, and replayed from that log bit for bit.

The three switch inputs (the port ``<task>_switch``)::

    controller        index of the controller asked to be active
    switch_at_cycle   the release from which the request holds (0: the next release)
    shadow            index of a controller to run in shadow, -1 for none
    code              id of edited code for ``controller`` (``rtloop reload``, :mod:`rtloop.code_reload`), 0: none

The outputs after the common ones say what happened::

    active_controller  index of the active controller (recorded: the switch cycles come from it)
    shadow_controller  index of the shadow controller, -1 for none
    switch_refusals    switches refused so far (``ready()`` said no, or reloaded code was not ready)
    active_code        id of the active controller's reloaded code, 0 while it runs the code it started with
    shadow_<output>    the shadow controller's outputs (recorded; they actuate nothing)

Bumpless transfer: before its first step the incoming controller's ``take_over(u, y_last)``
is called (``u``: its inputs now, ``y_last``: the outgoing controller's last outputs) when it
has one — a PI sets its integrator there so its first output equals ``y_last``. Without it,
the framework adds the difference between ``y_last`` and the incoming controller's first
output to its outputs and lets that offset decay to zero over ``blend_s`` (0: a plain switch,
the outputs may jump; the limits of devices and connections still hold).

Nothing in a switch imports or allocates: every controller is built and ``prerun`` before T0
(its module imported, its arrays made), and a switch only changes which one ``step`` calls.
"""

from __future__ import annotations

import copy
import inspect
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.code_reload import CodeReloader, code_file_name, code_id_of
from rtloop.errors import AppError
from rtloop.runnable import FloatVector, Runnable, TickInfo

CONTROLLER_NAME_MAX_CHARS = 64
"""A controller's name names its kept code in the run's folder (``code/<name>-<id>.py``): a name of
5000 letters passed the app file's check, then the run stopped with 'File name too long' after its
folder was begun."""
SWITCH_INPUTS = ("controller", "switch_at_cycle", "shadow", "code")
"""The task's switch inputs, in order, after the controllers' common inputs."""
STATUS_OUTPUTS = ("active_controller", "shadow_controller", "switch_refusals", "active_code")
"""Outputs after the common ones, before the shadow controller's copies of them."""
NO_SHADOW = -1
MAX_AT_CYCLE = float(2**53)
"""Largest cycle a switch may be asked for (a float holds every integer up to it exactly)."""


class Controllers(Runnable):
    """Alternative controllers for one task; ``active`` names the one that starts.

    ``controllers`` maps a name to a runnable; all have the same inputs and outputs (their own
    live parameters aside: each keeps its own, as inputs after the switch inputs, named
    ``<controller>_<parameter>``). ``blend_s``: how long the offset of a switch without
    ``take_over`` takes to decay (see the module doc)."""

    def __init__(self, controllers: Mapping[str, Runnable], active: str, *, blend_s: float = 0.5) -> None:
        if not isinstance(controllers, Mapping) or not controllers:
            raise AppError("controllers: give at least one, as {name: runnable}")
        for name, controller in controllers.items():
            if not isinstance(name, str) or not name.isidentifier():
                raise AppError(f"controllers: {name!r} is not a name (letters, digits, underscores)")
            if len(name) > CONTROLLER_NAME_MAX_CHARS:  # it names the kept code's files: the run failed midway
                raise AppError(f"controllers: {name[:24]}…: a name of {len(name)} characters; at most "
                               f"{CONTROLLER_NAME_MAX_CHARS}")
            if not isinstance(controller, Runnable) or isinstance(controller, Controllers):
                raise AppError(f"controllers.{name}: {controller!r} is not an rtloop.Runnable")
        if active not in controllers:
            raise AppError(f"controllers: active = {active!r} is not one of them; they are {sorted(controllers)}")
        if isinstance(blend_s, bool) or not isinstance(blend_s, int | float) or not 0 <= blend_s <= 3600:
            raise AppError(f"controllers: blend_s = {blend_s!r}; expected seconds from 0 to 3600")
        self.names = tuple(controllers)
        self.alternatives = list(controllers.values())
        self.blend_s = float(blend_s)
        self.start_index = self.names.index(active)
        for controller in self.alternatives:
            controller.add_parameter_inputs()  # each keeps its own live parameters
        first_name, first = self.names[0], self.alternatives[0]
        self.n_common_inputs = _declared_inputs(first)
        self.n_common_outputs = first.n_outputs
        for name, controller in zip(self.names[1:], self.alternatives[1:], strict=True):
            sizes = (_declared_inputs(controller), controller.n_outputs)
            if sizes != (self.n_common_inputs, self.n_common_outputs):
                raise AppError(f"controllers.{name}: {sizes[0]} inputs and {sizes[1]} outputs, but "
                               f"controllers.{first_name} has {self.n_common_inputs} and {self.n_common_outputs}: "
                               "the controllers of a task share its inputs and outputs")
        n_in, n_out = self.n_common_inputs, self.n_common_outputs
        self.switch_start = n_in
        parameter_names: list[str] = []
        parameter_starts: list[float] = []
        self.parameter_slices: list[slice] = []
        at = n_in + len(SWITCH_INPUTS)
        for name, controller in zip(self.names, self.alternatives, strict=True):
            own = controller.n_inputs - n_in
            self.parameter_slices.append(slice(at, at + own))
            parameter_names += [f"{name}_{parameter}" for parameter in controller.parameters][:own]
            starts = getattr(controller, "input_start_values", None)
            parameter_starts += list(starts[n_in:]) if starts is not None else [0.0] * own
            at += own
        self.n_inputs = at
        self.n_outputs = n_out + len(STATUS_OUTPUTS) + n_out
        common_in = _names(first.input_names, n_in, "u")
        common_out = _names(first.output_names, n_out, "y")
        self.input_names = (*common_in, *SWITCH_INPUTS, *parameter_names)
        self.output_names = (*common_out, *STATUS_OUTPUTS, *(f"shadow_{name}" for name in common_out))
        if first.input_units is not None:
            self.input_units = (*first.input_units[:n_in], *("",) * (self.n_inputs - n_in))
        if first.output_units is not None:
            units = tuple(first.output_units[:n_out])
            self.output_units = (*units, "", "", "", "", *units)
        first_starts = getattr(first, "input_start_values", None)
        common_starts = list(first_starts[:n_in]) if first_starts is not None else [0.0] * n_in
        self.input_start_values = (*common_starts, float(self.start_index), 0.0, float(NO_SHADOW), 0.0,
                                   *parameter_starts)
        self._tick = TickInfo()
        self._bound = False
        self.code_dir: Path | None = None
        """Where reloaded code is kept (the run's ``code/``); set by the run's session. None: no reloads."""
        self.wait_for_code = False
        """Wait at the release for reloaded code to be ready (simulate, replay); a real run never waits."""
        self._reloader: CodeReloader | None = None
        self.start_codes: dict[str, int] = {}
        """Per controller, the id of the kept code to start with (a replay: the code the run started
        with, whatever the module holds now); empty: the code as imported."""

    # --- what the app builder and `rtloop switch` need -------------------------------------
    @property
    def switch_slice(self) -> slice:
        """Where the switch inputs lie in the task's ``u``."""
        return slice(self.switch_start, self.switch_start + len(SWITCH_INPUTS))

    def switch_ranges(self) -> list[list[float]]:
        """What the switch port accepts, value by value."""
        last = float(len(self.names) - 1)
        return [[0.0, last], [0.0, MAX_AT_CYCLE], [float(NO_SHADOW), last], [0.0, MAX_AT_CYCLE]]

    def has_take_over(self, name: str) -> bool:
        return callable(getattr(self.alternatives[self.names.index(name)], "take_over", None))

    def check_period(self, period_ns: int) -> None:
        """Each controller is told its task's period (a model checks its step size, an FMU takes it)."""
        for controller in self.alternatives:
            check = getattr(controller, "check_period", None)
            if callable(check):
                check(period_ns)

    def own_inputs(self, index: int) -> FloatVector:
        """The input vector controller ``index`` steps with (the reloader binds new code to it)."""
        return self._own_u[index]

    # --- the task's side ------------------------------------------------------------------
    @property  # a property: each controller sees the task's tick
    def tick(self) -> TickInfo:
        return self._tick

    @tick.setter
    def tick(self, tick: TickInfo) -> None:
        self._tick = tick
        for controller in self.alternatives:
            controller.tick = tick

    def bind_inputs(self, u: FloatVector) -> None:
        self._bind(u)

    def _bind(self, u: FloatVector) -> None:
        """Each controller gets its own input vector (common inputs + its parameters) and its
        own output vector, made once: the loop copies into views, it never makes arrays."""
        n_in, n_out = self.n_common_inputs, self.n_common_outputs
        self._u = u
        self._own_u = [np.zeros(c.n_inputs) for c in self.alternatives]
        self._own_y = [np.zeros(n_out) for _ in self.alternatives]
        self._common_u = u[:n_in]
        self._own_common_u = [own[:n_in] for own in self._own_u]
        self._own_parameter_u = [own[n_in:] for own in self._own_u]
        self._parameter_u = [u[part] for part in self.parameter_slices]
        for controller, own, part in zip(self.alternatives, self._own_u, self._parameter_u, strict=True):
            own[n_in:] = part
            controller.bind_inputs(own)
        self._y_last = np.zeros(n_out)
        self._offset = np.zeros(n_out)
        self._scaled = np.zeros(n_out)
        self._bound = True

    def prerun(self) -> None:
        if self.code_dir is not None:  # each controller as built, before its prerun: a reload builds it so again
            self._reloader = CodeReloader(self, self.code_dir, [_state_copy(c) for c in self.alternatives],
                                          wait=self.wait_for_code)
            for name, code_id in self.start_codes.items():
                index = self.names.index(name)
                self.alternatives[index] = self._reloader.build_now(index, code_id)
        for controller in self.alternatives:
            controller.tick = self._tick
            controller.prerun()
        initial = getattr(self.alternatives[self.start_index], "initial_outputs", None)
        n_out = self.n_common_outputs
        y0 = np.zeros(self.n_outputs)
        if initial is not None:
            y0[:n_out] = initial
        y0[n_out] = self.start_index
        y0[n_out + 1] = NO_SHADOW
        y0[n_out + 4:] = math.nan  # no shadow yet
        self.initial_outputs = y0
        self.active = self.start_index
        self.shadow = NO_SHADOW
        self.refusals = 0
        self.blend_left = 0
        self.blend_cycles = 0
        self.codes = [0.0] * len(self.alternatives)
        """Per controller, the id of the reloaded code it runs (0: the code it started with)."""
        self._code_asked = 0.0
        self._index_asked = -1.0
        """The controller the reloader was last asked to build ``_code_asked`` for (one file may hold both)."""
        self.stepped_release_ns = 0
        """The release of the last step taken (set in place: the attribute exists before the loop)."""
        self._refused_index = self._refused_at = self._refused_code = math.nan
        self._y_last[:] = y0[:n_out]

    def postrun(self) -> None:
        if self._reloader is not None:
            self._reloader.close()
        errors: list[BaseException] = []
        for controller in self.alternatives:  # each one's postrun, whatever another's did
            try:
                controller.postrun()
            except Exception as error:
                errors.append(error)
        if errors:
            raise errors[0]

    def step(self, u: FloatVector, y: FloatVector) -> None:
        if not self._bound or u is not self._u:
            self._bind(u)  # a task that hands over another u (the simulator's, a test's)
        n_out = self.n_common_outputs
        at = self.switch_start
        requested, at_cycle, shadow, code = u[at], u[at + 1], u[at + 2], u[at + 3]
        if code != self._code_asked or (code and requested != self._index_asked):
            # new code asked for (or the same file for another controller): the reloader prepares it, outside the loop
            self._code_asked, self._index_asked = code, requested
            if code and self._reloader is not None and 0 <= requested < len(self.alternatives):
                self._reloader.ask(int(requested), int(code))
        new_code = bool(code) and 0 <= requested < len(self.alternatives) and code != self.codes[int(requested)]
        refused_before = (requested == self._refused_index and at_cycle == self._refused_at
                          and code == self._refused_code)
        if (requested != self.active or new_code) and self.tick.cycle >= at_cycle and not refused_before:
            self._switch_to(int(requested), at_cycle, code if new_code else 0.0)
        if shadow != self.shadow and NO_SHADOW <= shadow < len(self.alternatives):
            self.shadow = int(shadow) if shadow != self.active else NO_SHADOW
            if self.shadow != NO_SHADOW:
                self._resume(self.shadow)
        active = self.active
        self._step_one(active)
        own_y = self._own_y[active]
        if self.blend_left:
            self._blend(own_y)
        y[:n_out] = own_y
        self._y_last[:] = own_y
        y[n_out] = active
        y[n_out + 1] = self.shadow
        y[n_out + 2] = self.refusals
        y[n_out + 3] = self.codes[active]
        if self.shadow != NO_SHADOW:  # its step runs inside the task's: the task's execution time includes it
            self._step_one(self.shadow)
            y[n_out + 4:] = self._own_y[self.shadow]
        else:
            y[n_out + 4:] = math.nan  # no shadow: a gap in its signals, never a stale copy
        self.stepped_release_ns = self._tick.release_ns  # a reload's preparation waits for it (code_reload.SlackGate)

    def _step_one(self, index: int) -> None:
        np.copyto(self._own_common_u[index], self._common_u)
        np.copyto(self._own_parameter_u[index], self._parameter_u[index])
        self.alternatives[index].step(self._own_u[index], self._own_y[index])

    def _switch_to(self, index: int, at_cycle: float, code: float) -> None:
        incoming = self.alternatives[index] if 0 <= index < len(self.alternatives) else None
        reloader = self._reloader
        if code and incoming is not None:  # reloaded code takes the controller's place, if it is ready
            reloaded = reloader.take(int(code)) if reloader is not None else None
            if reloader is not None and reloaded is not None:
                reloader.retire(incoming)  # its postrun runs in the reloader's thread
                self.alternatives[index] = incoming = reloaded
                self.codes[index] = code
            else:
                incoming = None
        ready = getattr(incoming, "ready", None)
        if incoming is None or (callable(ready) and not ready()):
            self.refusals += 1
            self._refused_index, self._refused_at, self._refused_code = float(index), at_cycle, code
            return
        self._refused_index = self._refused_at = self._refused_code = math.nan
        take_over = getattr(incoming, "take_over", None)
        np.copyto(self._own_common_u[index], self._common_u)
        np.copyto(self._own_parameter_u[index], self._parameter_u[index])
        if self.shadow == index and not code:
            self.shadow = NO_SHADOW  # promoted: it is the active one now, its state warm
        else:
            self._resume(index)
            if self.shadow == index:
                self.shadow = NO_SHADOW
        self.active = index
        if callable(take_over):
            take_over(self._own_u[index], self._y_last)
            self.blend_left = 0
            return
        self.blend_cycles = round(self.blend_s * 1e9 / self.tick.period_ns) if self.tick.period_ns else 0
        self.blend_left = self.blend_cycles
        self._blend_first = True

    def _resume(self, index: int) -> None:
        """A controller that follows the timeline (a Python model) goes on from this release
        instead of catching up on the cycles it was not stepped."""
        resume_at = getattr(self.alternatives[index], "resume_at", None)
        if callable(resume_at):
            resume_at(self.tick.cycle)

    def _blend(self, own_y: FloatVector) -> None:
        if self._blend_first:  # the offset that makes this first output equal the last one
            np.subtract(self._y_last, own_y, out=self._offset)
            self._blend_first = False
        np.multiply(self._offset, self.blend_left / self.blend_cycles, out=self._scaled)
        np.add(own_y, self._scaled, out=own_y)
        self.blend_left -= 1


def switch_port_name(task: str) -> str:
    """The input port through which a task of several controllers is switched."""
    return f"{task}_switch"


def prepare_reloads(runnable: Runnable, code_dir: Path, *, wait: bool,
                    start_codes: dict[str, int] | None = None) -> None:
    """Tell a task of several controllers where its run keeps reloaded code (a replay has set the
    run's own folder already), whether to wait for it at the release (simulate and replay), and
    (a replay) which kept code each controller starts with."""
    if isinstance(runnable, Controllers):
        if runnable.code_dir is None:
            runnable.code_dir = code_dir
        runnable.wait_for_code = wait
        if start_codes is not None:
            runnable.start_codes = {name: int(code_id) for name, code_id in start_codes.items()
                                    if name in runnable.names and isinstance(code_id, int)}


START_CODES_FILE = "start.json"


def keep_start_code(tasks: Mapping[str, Runnable], code_dir: Path) -> None:
    """Keep the code each controller starts with in the run's folder (``code/``, and ``start.json``
    naming it per task and controller): a replay runs it even after the module has been edited
    (and reloaded) since."""
    starts: dict[str, dict[str, int]] = {}
    for task, runnable in tasks.items():
        if not isinstance(runnable, Controllers):
            continue
        for name, controller in zip(runnable.names, runnable.alternatives, strict=True):
            kept = runnable.start_codes.get(name)  # a replay starts with the run's kept code, not the module's
            source = _kept_source(runnable, name, kept) if kept is not None else _source_of(controller)
            if source is None:
                continue
            code_id = code_id_of(source)
            code_dir.mkdir(mode=0o700, exist_ok=True)
            path = code_dir / code_file_name(name, code_id)
            if not path.exists():
                path.write_bytes(source)
            starts.setdefault(task, {})[name] = code_id
    if starts:
        (code_dir / START_CODES_FILE).write_text(json.dumps(starts, indent=1) + "\n")


def start_codes_of(code_dir: Path) -> dict[str, dict[str, int]]:
    """What :func:`keep_start_code` kept (nothing for a run without controllers)."""
    try:
        starts = json.loads((code_dir / START_CODES_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return starts if isinstance(starts, dict) else {}


def _kept_source(runnable: Controllers, name: str, code_id: int) -> bytes | None:
    try:
        return (runnable.code_dir / code_file_name(name, code_id)).read_bytes() if runnable.code_dir else None
    except OSError:
        return None


def _source_of(runnable: Runnable) -> bytes | None:
    try:
        found = inspect.getsourcefile(type(runnable))
        return Path(found).read_bytes() if found else None
    except (TypeError, OSError):
        return None


def _state_copy(runnable: Runnable) -> Runnable | None:
    """A controller as built (a reload gives its state to the new code's class), None if it cannot be copied."""
    try:
        return copy.deepcopy(runnable)
    except Exception:
        return None


def _declared_inputs(runnable: Runnable) -> int:
    """A runnable's inputs without its live parameters (those come after them)."""
    return int(runnable.__dict__.get("_parameter_base", runnable.n_inputs))


def _names(names: tuple[str, ...] | None, count: int, side: str) -> tuple[str, ...]:
    given = tuple(names or ())[:count]
    return tuple(given[i] if i < len(given) and given[i] else f"{side}{i}" for i in range(count))


def switch_events(controller: Any, names: tuple[str, ...], period_ns: int) -> list[dict[str, Any]]:
    """The switches a recorded ``controller`` output shows: cycle, time, from and to (by name).

    ``controller`` holds the output as recorded, one value per cycle from cycle 0 (NaN where the
    recording has a gap: a gap is not a switch)."""
    values = np.asarray(controller, dtype=np.float64)
    events: list[dict[str, Any]] = []
    last = math.nan
    for cycle, value in enumerate(values.tolist()):
        if math.isnan(value):
            continue
        if not math.isnan(last) and value != last:
            events.append({"cycle": cycle, "t_s": cycle * period_ns / 1e9,
                           "from": _name_of(last, names), "to": _name_of(value, names)})
        last = value
    return events


def _name_of(index: float, names: tuple[str, ...]) -> str:
    return names[int(index)] if 0 <= index < len(names) else f"#{index:g}"
