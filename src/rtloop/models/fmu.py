"""FMI 2.0 / 3.0 co-simulation FMUs through FMPy, with raw calls in the loop.

Outside the loop (``initialize``, ``terminate``) FMPy's convenience methods do the
work: extract, load, instantiate, set parameters, initialise. Inside the loop,
``calculate`` makes raw ctypes calls — set inputs, ``DoStep``, get outputs — with value
reference arrays and value buffers allocated once. Float64 variables that sit side by
side in ``u``/``y`` are passed by pointer straight into the task's arrays; other types
(integers, booleans, enumerations, Float32, FMI 3 arrays) go through a buffer of their
own type and are converted exactly (see :mod:`rtloop.models.fmi_variables`).

Each call's status is compared on its own: Warning is counted (and the FMU's message
kept for the end of the run), Discard/Error/Fatal stop the task with the call named.
FMI 3 ``eventHandlingNeeded`` runs event mode to the end, ``earlyReturn`` finishes the
step, and ``terminateSimulation`` (FMI 2: ``fmi2Terminated`` after a Discard) stops the
app in order with the FMU's own reason (:class:`~rtloop.errors.StopRequested`).

The communication step is the task period (``check_period`` → :meth:`set_period_ns`).
Time follows the release timeline: the step of the job released at k·P starts at k·P;
after skipped releases an FMU that can change its step does one longer step, others
catch up step by step (counted).
"""

from __future__ import annotations

import collections
import ctypes
import pickle
import shutil
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.errors import StopRequested
from rtloop.models.base import FmuError, ModelError, StateNotCaptured
from rtloop.models.fmi3_start import instantiate, said
from rtloop.models.fmi_transfer import raw_function, transfers
from rtloop.models.fmi_variables import UNSUPPORTED, Element, carried, elements_of
from rtloop.runnable import FloatVector

__all__ = ["FmuModel"]

_STATUS = ("OK", "Warning", "Discard", "Error", "Fatal", "Pending")
_FLOAT_TYPES = {"Real", "Float64"}
WARNINGS_KEPT = 20
EARLY_RETURN_LIMIT = 1000


class FmuModel:
    """A co-simulation FMU as a :class:`~rtloop.models.base.Model`.

    Args:
        path: the ``.fmu`` file (or an extracted FMU folder).
        inputs: names of the variables that form ``u``, in order: inputs, or tunable
            parameters (changed live through a port). Default: every ``input``.
        outputs: names of the variables that form ``y`` (outputs, or any readable
            variable). Default: every ``output``. Arrays (FMI 3) take one element each.
        parameters: start values by name, set before initialisation (parameters,
            inputs' start values, structural parameters).
        instance_name: FMI instance name (default: the model identifier).
    """

    def __init__(
        self,
        path: str | Any,
        inputs: list[str] | tuple[str, ...] | None = None,
        outputs: list[str] | tuple[str, ...] | None = None,
        parameters: dict[str, Any] | None = None,
        instance_name: str | None = None,
    ) -> None:
        from fmpy import read_model_description

        self.path = Path(path).expanduser().resolve()
        where = f"FMU {str(self.path)!r}"
        if not self.path.exists():
            raise FmuError(f"{where} does not exist")
        try:
            md = read_model_description(str(self.path))
        except Exception as error:  # FMPy raises bare Exceptions and ValidationError
            raise FmuError(f"{where}: cannot read modelDescription.xml: {error}") from error
        self.fmi_version: str = md.fmiVersion
        if md.fmiVersion not in ("2.0", "3.0"):
            raise FmuError(f"{where} is FMI {md.fmiVersion}; rtloop runs FMI 2.0 and 3.0")
        if md.coSimulation is None:
            if getattr(md, "scheduledExecution", None) is not None:
                raise FmuError(
                    f"{where} supports only scheduled execution (FMI 3: the importer activates "
                    "its clocked partitions); rtloop runs co-simulation FMUs. Re-export it with "
                    "co-simulation enabled."
                )
            raise FmuError(
                f"{where} supports only model exchange; rtloop needs a co-simulation FMU (the FMU "
                "brings its own solver). Re-export it with co-simulation enabled."
            )
        self.kind = "fmu3-cs" if self.fmi_version == "3.0" else "fmu2-cs"
        self.guid: str = md.guid
        self.model_identifier: str = md.coSimulation.modelIdentifier
        self.instance_name = instance_name or self.model_identifier
        self.has_event_mode = bool(getattr(md.coSimulation, "hasEventMode", False))
        self.variable_step = bool(md.coSimulation.canHandleVariableCommunicationStepSize)
        self.can_save_state = bool(getattr(md.coSimulation, "canGetAndSetFMUstate", False)
                                   and getattr(md.coSimulation, "canSerializeFMUstate", False))
        """The FMU can hand out its state as bytes and take it back (FMI getFMUstate + serialize)."""
        self._check_binary(md)

        self.variables = {v.name: v for v in md.modelVariables}
        usable = [v for v in md.modelVariables if carried(v, self.fmi_version)]
        in_names = list(inputs) if inputs is not None else [v.name for v in usable if v.causality == "input"]
        out_names = list(outputs) if outputs is not None else [v.name for v in usable if v.causality == "output"]
        self._in_elements = self._elements(in_names, "inputs", settable=True)
        self._out_elements = self._elements(out_names, "outputs", settable=False)
        self.input_names: tuple[str, ...] | None = tuple(e.name for e in self._in_elements)
        self.output_names: tuple[str, ...] | None = tuple(e.name for e in self._out_elements)
        self.input_units: tuple[str, ...] | None = tuple(self._unit_of(e.variable) for e in self._in_elements)
        self.output_units: tuple[str, ...] | None = tuple(self._unit_of(e.variable) for e in self._out_elements)
        self.n_inputs = len(self._in_elements)
        self.n_outputs = len(self._out_elements)
        self.parameters = self._check_parameters(dict(parameters or {}))
        self.input_start_values: tuple[float, ...] = tuple(
            self._start_of(e) for e in self._in_elements
        )
        """What each input holds until something writes it: its start value (or parameter)."""

        experiment = md.defaultExperiment
        default_step = getattr(experiment, "stepSize", None) if experiment else None
        self.default_step_size_s = float(default_step) if default_step else None
        self.step_size_s: float | None = None if self.variable_step else self.default_step_size_s
        """Set only for FMUs that cannot change their communication step."""
        self.communication_step_s: float | None = self.default_step_size_s
        self.catch_up_steps = 0
        """Extra steps taken after skipped releases (FMUs with a fixed communication step)."""
        self.long_steps = 0
        """Steps stretched over skipped releases (FMUs with a variable communication step)."""
        self.events = 0
        """Event-mode iterations run after a step asked for them (FMI 3)."""
        self.warnings = 0
        """Calls answered with status Warning."""
        self.messages: collections.deque[str] = collections.deque(maxlen=WARNINGS_KEPT)
        self.start_notes: list[str] = []
        """What the run's summary notes say of how the FMU was started (a refused Event Mode)."""
        self._unload()

    # -- the interface, checked when the app is built ------------------------------------

    def _check_binary(self, md: Any) -> None:
        """The platform binary must be there now, not at prerun in a temporary folder."""
        from fmpy import platform, platform_tuple

        key = platform_tuple if self.fmi_version == "3.0" else platform
        wanted = f"binaries/{key}/{self.model_identifier}.so"
        if self.path.is_dir():
            names = [p.relative_to(self.path).as_posix() for p in self.path.rglob("*") if p.is_file()]
        else:
            try:
                with zipfile.ZipFile(self.path) as archive:
                    names = archive.namelist()
            except zipfile.BadZipFile as error:
                raise FmuError(f"FMU {str(self.path)!r} is not a zip archive: {error}") from None
        if wanted in names:
            return
        present = sorted({n.split("/")[1] for n in names if n.startswith("binaries/") and n.count("/") >= 2})
        if self.path.is_dir() and (self.path / "sources").is_dir():
            raise FmuError(f"{str(self.path)!r} is the source folder of an FMU, not a built one: build it with "
                           f"`rtloop model build {self.path}` (add --out FILE.fmu to choose where), then name "
                           "the .fmu it prints")
        raise FmuError(
            f"FMU {str(self.path)!r} has no binary for this machine: {wanted} is missing "
            f"(platform key {key!r}; platforms present: {', '.join(present) or 'none'}). "
            "Export it for this platform, or with its sources and build it here."
        )

    def _elements(self, names: list[str], role: str, settable: bool) -> list[Element]:
        where = f"FMU {str(self.path)!r}"
        out: list[Element] = []
        for name in names:
            v = self.variables.get(name)
            if v is None:
                known = ", ".join(n for n, w in self.variables.items() if carried(w, self.fmi_version)) or "none"
                raise FmuError(f"{where}: {role}: no variable {name!r} (variables: {known})")
            if v.type in UNSUPPORTED:
                raise FmuError(f"{where}: {role}: {name!r} is {v.type}; rtloop carries numbers and booleans only")
            if settable:
                causality, variability = v.causality, v.variability
                if causality == "parameter" and variability == "fixed":
                    raise FmuError(
                        f"{where}: {role}: {name!r} is a fixed parameter: it cannot change while the FMU "
                        f"runs; set it before the start with parameters = {{ {name} = … }}"
                    )
                if causality not in ("input", "parameter"):
                    raise FmuError(
                        f"{where}: {role}: {name!r} has causality {causality!r}; only inputs and "
                        "tunable parameters can be set while running"
                    )
            try:
                out.extend(elements_of(v, self.fmi_version))
            except FmuError as error:
                raise FmuError(f"{where}: {role}: {error}") from None
        return out

    def _check_parameters(self, parameters: dict[str, Any]) -> dict[str, list[float]]:
        where = f"FMU {str(self.path)!r}"
        checked: dict[str, list[float]] = {}
        settable = ("parameter", "structuralParameter", "input")
        for name, value in parameters.items():
            v = self.variables.get(name)
            if v is None or v.causality not in settable or not carried(v, self.fmi_version):
                known = ", ".join(n for n, w in self.variables.items()
                                  if w.causality in settable and carried(w, self.fmi_version)) or "none"
                reason = "no such variable" if v is None else f"causality {v.causality!r}, type {v.type}"
                raise FmuError(f"{where}: parameters.{name}: {reason}; parameters and inputs are: {known}")
            elements = elements_of(v, self.fmi_version)
            values = list(value) if isinstance(value, list | tuple) else [value]
            if len(values) != len(elements):
                raise FmuError(f"{where}: parameters.{name}: expected {len(elements)} values, got {len(values)}")
            floats = []
            for e, x in zip(elements, values, strict=True):
                if isinstance(x, bool):
                    x = float(x)
                if not isinstance(x, int | float):
                    raise FmuError(f"{where}: parameters.{name}: {x!r} is not a number")
                try:
                    e.check(float(x))
                except FmuError as error:
                    raise FmuError(f"{where}: parameters.{name}: {error}") from None
                floats.append(float(x))
            checked[name] = floats
        return checked

    def _start_of(self, element: Element) -> float:
        given = self.parameters.get(element.variable)
        if given is not None:
            return given[element.offset]
        return element.start if element.start is not None else 0.0

    def _unit_of(self, name: str) -> str:
        """The variable's unit, or its declared type's ('' when the FMU gives none)."""
        variable = self.variables.get(name)
        if variable is None:
            return ""
        declared = getattr(variable, "declaredType", None)
        return str(getattr(variable, "unit", None) or (getattr(declared, "unit", None) if declared else None) or "")

    def describe_variables(self) -> list[dict[str, Any]]:
        """Every model variable: type, causality, variability, start, unit, description, and where rtloop maps it."""
        where: dict[str, list[str]] = {}
        for side, elements in (("u", self._in_elements), ("y", self._out_elements)):
            for i, e in enumerate(elements):
                where.setdefault(e.variable, []).append(f"{side}[{i}]")
        rows = []
        for v in self.variables.values():
            unit = v.unit or (v.declaredType.unit if getattr(v, "declaredType", None) is not None else None)
            shape = None
            if self.fmi_version == "3.0" and getattr(v, "dimensions", None):
                try:
                    from rtloop.models.fmi_variables import shape_of

                    shape = list(shape_of(v))
                except FmuError:
                    shape = None
            rows.append({
                "name": v.name, "type": v.type, "causality": v.causality, "variability": v.variability,
                "start": v.start, "unit": unit, "description": v.description, "shape": shape,
                "mapped": where.get(v.name, []),
            })
        return rows

    def set_period_ns(self, period_ns: int) -> None:
        """Use the task period as communication step (called through ``check_period``)."""
        self.communication_step_s = period_ns / 1e9  # correctly rounded: 10 ms is 0.01 exactly

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update({key: None for key in self._RUNTIME})
        return state

    _RUNTIME = (
        "_fmu", "_unzip_dir", "_do_step", "_component", "_u_bound", "_y_bound", "_inputs", "_outputs",
        "_step_flags", "_step_tail", "_callbacks", "_logger",
    )  # fmt: skip

    def _unload(self) -> None:
        for key in self._RUNTIME:
            setattr(self, key, None)
        self._t0_s = 0.0
        self._k = 0

    # -- lifecycle ------------------------------------------------------------------

    def initialize(self, u: FloatVector, y: FloatVector, t_s: float) -> None:
        """Extract, load, instantiate, set parameters, initialise with inputs ``u`` at ``t_s``."""
        from fmpy import extract

        if self.communication_step_s is None:
            raise FmuError(
                f"FMU {str(self.path)!r} has no default step size: give the task period "
                "with check_period / set_period_ns before prerun"
            )
        try:
            if self.path.is_dir():
                self._unzip_dir = None
                unzip_dir = str(self.path)
            else:
                unzip_dir = self._unzip_dir = extract(str(self.path))
            kwargs = dict(guid=self.guid, modelIdentifier=self.model_identifier,
                          unzipDirectory=unzip_dir, instanceName=self.instance_name)
            if self.fmi_version == "2.0":
                self._start_fmi2(kwargs, u, t_s)
            else:
                self._start_fmi3(kwargs, u, t_s)
            self._t0_s = t_s
            self._k = 0
            self._bind(u, y)
            self._read_outputs(y)
        except BaseException as error:
            self._abandon()  # nothing left behind: instance freed, extracted folder removed
            if isinstance(error, ModelError):
                raise
            if isinstance(error, Exception):  # FMPy raises bare Exception / FMICallException
                raise ModelError(f"FMU {str(self.path)!r} failed to start: {error}{said(self.messages)}") from error
            raise

    def _abandon(self) -> None:
        fmu = self._fmu
        if fmu is not None and getattr(fmu, "component", None):
            try:
                fmu.freeInstance()
            except Exception:
                pass
        if self._unzip_dir is not None:
            shutil.rmtree(self._unzip_dir, ignore_errors=True)
        self._unload()

    def _log(self, status: int, category: bytes | None, message: bytes | None) -> None:
        label = _STATUS[status] if 0 <= status < len(_STATUS) else str(status)
        self.messages.append(f"[{label}] {(message or b'').decode(errors='replace')}")  # bounded: last few

    def _set_start_values(self, fmu: Any, u: FloatVector) -> None:
        """Parameters and the inputs' start values, set before initialisation, each in its own type."""
        values: list[tuple[Element, float]] = []
        for name, given in self.parameters.items():
            values.extend(zip(elements_of(self.variables[name], self.fmi_version), given, strict=True))
        values.extend(zip(self._in_elements, (float(x) for x in u), strict=True))
        for element, value in values:
            transfer = transfers(fmu.dll, [element], "Set", self.fmi_version)[0]
            transfer.load_from(np.array([value]))
            self._check(transfer.set(fmu.component, transfer.vrs, transfer.n_vrs, transfer.pointer,
                                     *transfer.tail), f"set {element.name} = {value!r}")

    def _start_fmi2(self, kwargs: dict[str, Any], u: FloatVector, t_s: float) -> None:
        from fmpy import calloc, free
        from fmpy.fmi2 import (
            FMU2Slave,
            fmi2CallbackAllocateMemoryTYPE,
            fmi2CallbackFreeMemoryTYPE,
            fmi2CallbackFunctions,
            fmi2CallbackLoggerTYPE,
        )

        fmu = self._fmu = FMU2Slave(**kwargs)
        callbacks = self._callbacks = fmi2CallbackFunctions()
        self._logger = fmi2CallbackLoggerTYPE(lambda _env, _name, status, category, message:
                                              self._log(status, category, message))
        callbacks.logger = self._logger
        callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        try:
            from fmpy.logging import addLoggerProxy

            addLoggerProxy(ctypes.byref(callbacks))  # formats the variadic message in C
        except Exception:
            pass
        fmu.instantiate(callbacks=callbacks)
        fmu.setupExperiment(startTime=t_s)
        self._set_start_values(fmu, u)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        self._component = fmu.component
        self._do_step = raw_function(fmu.dll, "fmi2DoStep", [ctypes.c_void_p, ctypes.c_double, ctypes.c_double,
                                                     ctypes.c_int])
        self._step_tail: tuple[object, ...] = (1,)  # noSetFMUStatePriorToCurrentPoint
        self._make_transfers(fmu.dll)

    def _start_fmi3(self, kwargs: dict[str, Any], u: FloatVector, t_s: float) -> None:
        from fmpy.fmi3 import FMU3Slave

        fmu = self._fmu = FMU3Slave(**kwargs)
        if instantiate(fmu, self.has_event_mode, self._log) != self.has_event_mode:  # refused: runs without
            self.has_event_mode = False
            self.start_notes.append(f"FMU {self.model_identifier} ({self.path.name}) declares Event Mode but refused "
                                    f"it at instantiate{said(self.messages)}: it runs without Event Mode, handling "
                                    "its events inside each step (FMI 3.0 allows it)")
        self._set_start_values(fmu, u)
        fmu.enterInitializationMode(startTime=t_s)
        fmu.exitInitializationMode()
        if self.has_event_mode:  # instantiated with eventModeUsed: initialisation ends in Event Mode
            self._event_iteration(fmu, enter=False)
        self._component = fmu.component
        b = ctypes.POINTER(ctypes.c_bool)
        self._do_step = raw_function(fmu.dll, "fmi3DoStep", [
            ctypes.c_void_p, ctypes.c_double, ctypes.c_double, ctypes.c_bool, b, b, b,
            ctypes.POINTER(ctypes.c_double),
        ])  # fmt: skip
        # eventHandlingNeeded, terminateSimulation, earlyReturn, lastSuccessfulTime
        flags = self._step_flags = (ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(), ctypes.c_double())
        self._step_tail = (True, *(ctypes.byref(f) for f in flags))
        self._make_transfers(fmu.dll)

    def _make_transfers(self, dll: ctypes.CDLL) -> None:
        self._inputs = transfers(dll, self._in_elements, "Set", self.fmi_version)
        self._outputs = transfers(dll, self._out_elements, "Get", self.fmi_version)

    def _bind(self, u: FloatVector, y: FloatVector) -> None:
        for name, a, n in (("u", u, self.n_inputs), ("y", y, self.n_outputs)):
            if a.dtype != np.float64 or not a.flags.c_contiguous or a.shape != (n,):
                raise ModelError(
                    f"FMU {str(self.path)!r}: {name} must be a contiguous float64 vector "
                    f"of length {n}, got {a.dtype} {a.shape}"
                )
        for transfer in self._inputs:
            transfer.bind(u)
        for transfer in self._outputs:
            transfer.bind(y)
        self._u_bound, self._y_bound = u, y

    def _read_outputs(self, y: FloatVector) -> None:
        c = self._component
        for transfer in self._outputs:
            status = transfer.get(c, transfer.vrs, transfer.n_vrs, transfer.pointer, *transfer.tail)
            if status:
                self._check(status, "get outputs")
            if not transfer.direct:
                transfer.store_to(y)

    def calculate(self, u: FloatVector, y: FloatVector) -> None:
        """Set ``u``, ``DoStep(t_k, h)``, get ``y``: raw calls, each status checked."""
        if u is not self._u_bound or y is not self._y_bound:
            self._bind(u, y)
        c = self._component
        h = self.communication_step_s
        assert h is not None  # check_period set it before the run
        t = self._t0_s + self._k * h
        for transfer in self._inputs:
            if not transfer.direct:
                transfer.load_from(u)
            status = transfer.set(c, transfer.vrs, transfer.n_vrs, transfer.pointer, *transfer.tail)
            if status:
                self._check(status, f"set inputs at t = {t:.6f} s")
        # Communication points on the timeline t0 + k·h, the step between them (as FMPy's own loop does)
        self._step(t, self._t0_s + (self._k + 1) * h - t)
        self._k += 1
        self._read_outputs(y)

    def _step(self, t: float, h: float) -> None:
        status = self._do_step(self._component, t, h, *self._step_tail)
        if self._step_flags is None:  # FMI 2
            if status == 2 and self._fmi2_terminated():
                raise StopRequested(self._reason(f"FMU {self.model_identifier} ended the simulation at t = {t:.6f} s"))
            if status:
                self._check(status, f"step at t = {t:.6f} s")
            return
        if status:
            self._check(status, f"step at t = {t:.6f} s")
        event, terminate, early, last_time = self._step_flags
        if terminate.value:
            raise StopRequested(self._reason(f"FMU {self.model_identifier} ended the simulation at t = {t:.6f} s"))
        if event.value and self.has_event_mode:
            self._event_iteration(self._fmu)
        repeats = 0
        while early.value and last_time.value < t + h and repeats < EARLY_RETURN_LIMIT:
            # Returned before the end of the step (an event inside it): finish the step from there.
            repeats += 1
            start = last_time.value
            status = self._do_step(self._component, start, t + h - start, *self._step_tail)
            if status:
                self._check(status, f"step at t = {start:.6f} s")
            if terminate.value:
                raise StopRequested(self._reason(f"FMU {self.model_identifier} ended the simulation"))
            if event.value and self.has_event_mode:
                self._event_iteration(self._fmu)

    def _event_iteration(self, fmu: Any, enter: bool = True) -> None:
        """FMI 3 event mode: update discrete states until they settle, then back to step mode.

        ``enter=False`` right after initialisation: an FMU instantiated with ``eventModeUsed``
        is in Event Mode already when ``fmi3ExitInitializationMode`` returns, and entering it
        again is an error (FMI 3.0, co-simulation state machine).
        """
        if enter:
            self.events += 1
            fmu.enterEventMode()
        need, terminate = ctypes.c_bool(True), ctypes.c_bool(False)
        nominals, values, defined, next_time = ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(), ctypes.c_double()
        rounds = 0
        while need.value:
            rounds += 1
            fmu.fmi3UpdateDiscreteStates(fmu.component, ctypes.byref(need), ctypes.byref(terminate),
                                         ctypes.byref(nominals), ctypes.byref(values), ctypes.byref(defined),
                                         ctypes.byref(next_time))
            if terminate.value:
                raise StopRequested(self._reason(f"FMU {self.model_identifier} ended the simulation in event mode"))
            if rounds > EARLY_RETURN_LIMIT:
                raise ModelError(f"FMU {str(self.path)!r}: event iteration did not settle")
        fmu.enterStepMode()

    def _fmi2_terminated(self) -> bool:
        value = ctypes.c_int()
        function = raw_function(self._fmu.dll, "fmi2GetBooleanStatus", [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p])
        status = function(self._component, 3, ctypes.byref(value))  # fmi2Terminated
        return status == 0 and bool(value.value)

    def _reason(self, what: str) -> str:
        last = f": {self.messages[-1]}" if self.messages else ""
        return what + last

    def _check(self, status: int, what: str) -> None:
        if status == 0:
            return
        if status == 1:  # Warning: the call did its work; count it, keep the message for later
            self.warnings += 1
            return
        label = _STATUS[status] if 0 <= status < len(_STATUS) else "?"
        last = f"; the FMU said: {self.messages[-1]}" if self.messages else ""
        raise ModelError(f"FMU {str(self.path)!r}: {what} failed (status {status}: {label}){last}")

    def skip_releases(self, skipped: int) -> None:
        """The task skipped ``skipped`` releases: bring the FMU's time back onto the timeline.

        A variable-step FMU does its next step over the whole elapsed interval; a fixed-step
        FMU catches up with extra steps (inputs held), counted in :attr:`catch_up_steps`.
        """
        if skipped <= 0 or self._component is None:
            return
        h = self.communication_step_s
        assert h is not None  # check_period set it before the run
        t = self._t0_s + self._k * h
        k, t0 = self._k, self._t0_s
        if self.variable_step:
            self._step(t, t0 + (k + skipped) * h - t)
            self.long_steps += 1
        else:
            for i in range(skipped):
                start = t0 + (k + i) * h
                self._step(start, t0 + (k + i + 1) * h - start)
            self.catch_up_steps += skipped
        self._k += skipped

    def save_state(self) -> bytes:
        """The FMU's serialised state and our place on its timeline (``--keep`` windows are replayed from it)."""
        fmu = self._fmu
        if not self.can_save_state:
            raise StateNotCaptured(f"FMU {str(self.path)!r} cannot serialise its state "
                                   "(canGetAndSetFMUstate and canSerializeFMUstate are not both true)")
        if fmu is None:
            raise StateNotCaptured(f"FMU {str(self.path)!r} is not instantiated")
        fmi2 = self.fmi_version == "2.0"
        state = fmu.getFMUstate() if fmi2 else fmu.getFMUState()
        try:
            data = fmu.serializeFMUstate(state) if fmi2 else fmu.serializeFMUState(state)
        finally:
            fmu.freeFMUstate(state) if fmi2 else fmu.freeFMUState(state)
        return pickle.dumps({"fmu": bytes(data), "k": self._k, "t0_s": self._t0_s,
                             "communication_step_s": self.communication_step_s})

    def restore_state(self, saved: bytes) -> None:
        """Take back a state from :meth:`save_state` (the FMU instantiated by ``initialize``)."""
        values = pickle.loads(saved)
        fmu = self._fmu
        if fmu is None:
            raise ModelError(f"FMU {str(self.path)!r}: restore_state before initialize")
        fmi2 = self.fmi_version == "2.0"
        state = fmu.deSerializeFMUstate(values["fmu"]) if fmi2 else fmu.deserializeFMUState(values["fmu"])
        try:
            fmu.setFMUstate(state) if fmi2 else fmu.setFMUState(state)
        finally:
            fmu.freeFMUstate(state) if fmi2 else fmu.freeFMUState(state)
        self._k, self._t0_s = values["k"], values["t0_s"]
        self.communication_step_s = values["communication_step_s"]

    def terminate(self, u: FloatVector, y: FloatVector) -> None:
        """Terminate, free the instance, unload and delete the extracted files."""
        fmu = self._fmu
        if fmu is None:
            return
        try:
            try:
                fmu.terminate()
            except Exception:
                pass  # after terminateSimulation an FMU may refuse; freeing it is what matters
            fmu.freeInstance()
        finally:
            if self._unzip_dir is not None:
                shutil.rmtree(self._unzip_dir, ignore_errors=True)
            self._unload()
            if self.warnings:
                last = f"; last: {self.messages[-1]}" if self.messages else ""
                print(f"rtloop: FMU {self.model_identifier}: {self.warnings} calls answered Warning{last}",
                      file=sys.stderr)
