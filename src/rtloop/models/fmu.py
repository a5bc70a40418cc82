"""FMI 2.0 / 3.0 co-simulation FMUs through FMPy, with raw calls in the loop.

Outside the loop (``initialize``, ``terminate``) FMPy's convenience methods do the
work: extract, load, instantiate, set up, initialise. Inside the loop, ``calculate``
makes three raw ctypes calls — set inputs, ``DoStep``, get outputs — with value
reference arrays allocated once and the data pointers of the task's u and y arrays,
and checks their statuses together, once.

The communication step is the task period: the core calls
``ModelRunnable.check_period(period_ns)``, which calls :meth:`FmuModel.set_period_ns`.
Without it the FMU's ``DefaultExperiment stepSize`` is used.
"""

from __future__ import annotations

import ctypes
import os
import shutil
from pathlib import Path
from typing import Any

from rtloop.models.base import FmuError, ModelError
from rtloop.runnable import FloatVector

__all__ = ["FmuModel"]

_STATUS = ("OK", "Warning", "Discard", "Error", "Fatal", "Pending")
_REAL_TYPES = {"Real", "Float64"}


class FmuModel:
    """A co-simulation FMU as a :class:`~rtloop.models.base.Model`.

    Args:
        path: the ``.fmu`` file (or an extracted FMU folder).
        inputs: names of the real input variables that form ``u``, in order.
            Default: every real variable with causality ``input``, in file order.
        outputs: names of the real variables that form ``y`` (outputs, or any readable
            variable). Default: every real ``output``, in file order.
        instance_name: FMI instance name (default: the model identifier).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        inputs: list[str] | tuple[str, ...] | None = None,
        outputs: list[str] | tuple[str, ...] | None = None,
        instance_name: str | None = None,
    ) -> None:
        from fmpy import read_model_description

        self.path = Path(path).expanduser().resolve()
        if not self.path.exists():
            raise FmuError(f"FMU {str(self.path)!r} does not exist")
        try:
            md = read_model_description(str(self.path))
        except Exception as error:  # FMPy raises bare Exceptions and ValidationError
            raise FmuError(
                f"FMU {str(self.path)!r}: cannot read modelDescription.xml: {error}"
            ) from error
        self.fmi_version: str = md.fmiVersion
        if md.fmiVersion not in ("2.0", "3.0"):
            raise FmuError(
                f"FMU {str(self.path)!r} is FMI {md.fmiVersion}; rtloop runs FMI 2.0 and 3.0"
            )
        if md.coSimulation is None:
            raise FmuError(
                f"FMU {str(self.path)!r} supports only model exchange; rtloop needs a "
                "co-simulation FMU (the FMU brings its own solver). Re-export it with "
                "co-simulation enabled."
            )
        self.kind = "fmu3-cs" if self.fmi_version == "3.0" else "fmu2-cs"
        self.guid: str = md.guid
        self.model_identifier: str = md.coSimulation.modelIdentifier
        self.instance_name = instance_name or self.model_identifier

        variables = {v.name: v for v in md.modelVariables}
        real = [v for v in md.modelVariables if v.type in _REAL_TYPES]
        in_names = list(inputs) if inputs is not None else [
            v.name for v in real if v.causality == "input"
        ]
        out_names = list(outputs) if outputs is not None else [
            v.name for v in real if v.causality == "output"
        ]
        for name in in_names + out_names:
            v = variables.get(name)
            if v is None:
                known = ", ".join(v.name for v in real) or "none"
                raise FmuError(f"FMU {str(self.path)!r} has no variable {name!r} (reals: {known})")
            if v.type not in _REAL_TYPES:
                raise FmuError(f"FMU {str(self.path)!r}: {name!r} is {v.type}, not a real")
        for name in in_names:
            if variables[name].causality not in ("input", "parameter"):
                raise FmuError(
                    f"FMU {str(self.path)!r}: {name!r} has causality "
                    f"{variables[name].causality!r}; only inputs can be set while running"
                )
        self.input_names: tuple[str, ...] | None = tuple(in_names)
        self.output_names: tuple[str, ...] | None = tuple(out_names)
        self.n_inputs = len(in_names)
        self.n_outputs = len(out_names)
        self._in_vrs = [variables[n].valueReference for n in in_names]
        self._out_vrs = [variables[n].valueReference for n in out_names]

        experiment = md.defaultExperiment
        default_step = getattr(experiment, "stepSize", None) if experiment else None
        self.default_step_size_s = float(default_step) if default_step else None
        fixed = not md.coSimulation.canHandleVariableCommunicationStepSize
        self.step_size_s: float | None = self.default_step_size_s if fixed else None
        """Set only for FMUs that cannot change their communication step."""
        self.communication_step_s: float | None = self.default_step_size_s
        self._unload()

    def set_period_ns(self, period_ns: int) -> None:
        """Use the task period as communication step (called through ``check_period``)."""
        self.communication_step_s = period_ns * 1e-9

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update({key: None for key in self._RUNTIME})
        return state

    _RUNTIME = (
        "_fmu", "_unzip_dir", "_set", "_get", "_do_step", "_component", "_in_vr_array",
        "_out_vr_array", "_u_bound", "_y_bound", "_u_ptr", "_y_ptr", "_step_flags",
        "_step_tail", "_set_tail", "_get_tail",
    )  # fmt: skip

    def _unload(self) -> None:
        for key in self._RUNTIME:
            setattr(self, key, None)
        self._t0_s = 0.0
        self._k = 0

    # -- lifecycle ------------------------------------------------------------------

    def initialize(self, u: FloatVector, y: FloatVector, t_s: float) -> None:
        """Extract, load, instantiate and initialise with inputs ``u`` at ``t_s``."""
        from fmpy import extract

        if self.communication_step_s is None:
            raise FmuError(
                f"FMU {str(self.path)!r} has no default step size: give the task period "
                "with check_period / set_period_ns before prerun"
            )
        if self.path.is_dir():
            self._unzip_dir = None
            unzip_dir = str(self.path)
        else:
            unzip_dir = self._unzip_dir = extract(str(self.path))
        kwargs = dict(
            guid=self.guid,
            modelIdentifier=self.model_identifier,
            unzipDirectory=unzip_dir,
            instanceName=self.instance_name,
        )
        try:
            if self.fmi_version == "2.0":
                self._start_fmi2(kwargs, u, t_s)
            else:
                self._start_fmi3(kwargs, u, t_s)
        except ModelError:
            raise
        except Exception as error:  # FMPy raises bare Exception / FMICallException
            raise ModelError(f"FMU {str(self.path)!r} failed to start: {error}") from error
        self._t0_s = t_s
        self._k = 0
        self._bind(u, y)
        self._read_outputs()

    def _start_fmi2(self, kwargs: dict[str, Any], u: FloatVector, t_s: float) -> None:
        from fmpy.fmi2 import FMU2Slave

        fmu = self._fmu = FMU2Slave(**kwargs)
        fmu.instantiate()
        fmu.setupExperiment(startTime=t_s)
        fmu.enterInitializationMode()
        if self.n_inputs:
            fmu.setReal(self._in_vrs, [float(x) for x in u])
        fmu.exitInitializationMode()
        self._component = fmu.component
        dll = fmu.dll
        vr_ptr = ctypes.POINTER(ctypes.c_uint)
        self._set = _raw(dll, "fmi2SetReal", [ctypes.c_void_p, vr_ptr, ctypes.c_size_t,
                                               ctypes.c_void_p])
        self._get = _raw(dll, "fmi2GetReal", [ctypes.c_void_p, vr_ptr, ctypes.c_size_t,
                                               ctypes.c_void_p])
        self._do_step = _raw(dll, "fmi2DoStep", [ctypes.c_void_p, ctypes.c_double,
                                                  ctypes.c_double, ctypes.c_int])
        self._step_tail = (1,)  # noSetFMUStatePriorToCurrentPoint
        self._set_tail = self._get_tail = ()
        self._in_vr_array = (ctypes.c_uint * max(1, self.n_inputs))(*self._in_vrs)
        self._out_vr_array = (ctypes.c_uint * max(1, self.n_outputs))(*self._out_vrs)

    def _start_fmi3(self, kwargs: dict[str, Any], u: FloatVector, t_s: float) -> None:
        from fmpy.fmi3 import FMU3Slave

        fmu = self._fmu = FMU3Slave(**kwargs)
        fmu.instantiate()
        fmu.enterInitializationMode(startTime=t_s)
        if self.n_inputs:
            fmu.setFloat64(self._in_vrs, [float(x) for x in u])
        fmu.exitInitializationMode()
        self._component = fmu.component
        dll = fmu.dll
        vr_ptr = ctypes.POINTER(ctypes.c_uint)
        args = [ctypes.c_void_p, vr_ptr, ctypes.c_size_t, ctypes.c_void_p, ctypes.c_size_t]
        self._set = _raw(dll, "fmi3SetFloat64", args)
        self._get = _raw(dll, "fmi3GetFloat64", args)
        b = ctypes.POINTER(ctypes.c_bool)
        self._do_step = _raw(dll, "fmi3DoStep", [
            ctypes.c_void_p, ctypes.c_double, ctypes.c_double, ctypes.c_bool, b, b, b,
            ctypes.POINTER(ctypes.c_double),
        ])  # fmt: skip
        # eventHandlingNeeded, terminateSimulation, earlyReturn, lastSuccessfulTime
        flags = self._step_flags = (ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(),
                                    ctypes.c_double())
        self._step_tail = (True, *(ctypes.byref(f) for f in flags))
        n_in, n_out = self.n_inputs, self.n_outputs
        self._set_tail, self._get_tail = (n_in,), (n_out,)  # nValues
        self._in_vr_array = (ctypes.c_uint * max(1, n_in))(*self._in_vrs)
        self._out_vr_array = (ctypes.c_uint * max(1, n_out))(*self._out_vrs)

    def _bind(self, u: FloatVector, y: FloatVector) -> None:
        import numpy as np

        for name, a, n in (("u", u, self.n_inputs), ("y", y, self.n_outputs)):
            if a.dtype != np.float64 or not a.flags.c_contiguous or a.shape != (n,):
                raise ModelError(
                    f"FMU {str(self.path)!r}: {name} must be a contiguous float64 vector "
                    f"of length {n}, got {a.dtype} {a.shape}"
                )
        self._u_bound, self._y_bound = u, y
        self._u_ptr, self._y_ptr = u.ctypes.data, y.ctypes.data

    def _read_outputs(self) -> None:
        status = self._get(
            self._component, self._out_vr_array, self.n_outputs, self._y_ptr, *self._get_tail
        )
        if status > 1:
            self._fail("get outputs", status)

    def calculate(self, u: FloatVector, y: FloatVector) -> None:
        """Set ``u``, ``DoStep(t_k, P)``, get ``y``: three raw calls, one status check."""
        if u is not self._u_bound or y is not self._y_bound:
            self._bind(u, y)
        c = self._component
        h = self.communication_step_s
        t = self._t0_s + self._k * h  # type: ignore[operator]
        status = self._set(c, self._in_vr_array, self.n_inputs, self._u_ptr, *self._set_tail)
        status |= self._do_step(c, t, h, *self._step_tail)
        status |= self._get(c, self._out_vr_array, self.n_outputs, self._y_ptr, *self._get_tail)
        self._k += 1
        if status > 1:  # some call answered Discard, Error, Fatal or Pending
            self._fail(f"step at t = {t:.6f} s", status)

    def _fail(self, what: str, status: int) -> None:
        raise ModelError(
            f"FMU {str(self.path)!r}: {what} failed (status {status}: "
            f"{_STATUS[status] if 0 <= status < len(_STATUS) else '?'} or worse)"
        )

    def terminate(self, u: FloatVector, y: FloatVector) -> None:
        """Terminate, free the instance, unload and delete the extracted files."""
        fmu = self._fmu
        if fmu is None:
            return
        try:
            fmu.terminate()
            fmu.freeInstance()
        finally:
            if self._unzip_dir is not None:
                shutil.rmtree(self._unzip_dir, ignore_errors=True)
            self._unload()


def _raw(dll: ctypes.CDLL, name: str, argtypes: list[Any]) -> Any:
    """A fresh ctypes handle on an FMI function, with our own argtypes (no FMPy wrapper)."""
    function = getattr(dll, name)
    function = type(function)((name, dll))  # own object: FMPy's argtypes stay untouched
    function.argtypes = argtypes
    function.restype = ctypes.c_int
    return function
