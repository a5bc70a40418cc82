"""A built 20-sim export as a :class:`~rtloop.models.base.Model`: the library loaded in the task
process, its shim's functions called through ctypes on the task's arrays, its state saved and
restored."""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.models.base import ModelError, StateNotCaptured
from rtloop.models.twentysim.build import build_library, state_note
from rtloop.models.twentysim.export import inspect, state_layout
from rtloop.runnable import FloatVector

# ANSI-C libraries in use in this process (their globals are the model state).
_C_LIBRARIES_IN_USE: set[str] = set()
_VOIDP = ctypes.c_void_p
_DOUBLE = ctypes.c_double
_SIGNATURES = {
    "rtloop_new": ([], _VOIDP),
    "rtloop_delete": ([_VOIDP], None),
    "rtloop_initialize": ([_VOIDP, _VOIDP, _VOIDP, _DOUBLE], None),
    "rtloop_calculate": ([_VOIDP, _VOIDP, _VOIDP], None),
    "rtloop_terminate": ([_VOIDP, _VOIDP, _VOIDP], None),
    "rtloop_set_finish_time": ([_VOIDP, _DOUBLE], ctypes.c_int),
    "rtloop_is_finished": ([_VOIDP], ctypes.c_int),
    "rtloop_reset": ([_VOIDP, _DOUBLE], None),
    "rtloop_step_size": ([_VOIDP], _DOUBLE),
}
_CPP_SIGNATURES = {
    "rtloop_set_parameter": ([_VOIDP, ctypes.c_int, _DOUBLE], None),
    "rtloop_reevaluate": ([_VOIDP, _VOIDP], None),
}
_STATE_SIGNATURE = ([_VOIDP, _VOIDP, _VOIDP], ctypes.c_size_t)


def _exported_sizes(library: str) -> dict[str, int]:
    """Bytes of each data symbol the library exports (``nm -D -S``), by name."""
    nm = shutil.which("nm")
    if nm is None:
        raise StateNotCaptured("nm (binutils) is not installed: the sizes of the model's globals are unknown")
    listing = subprocess.run([nm, "-D", "-S", "--defined-only", library], capture_output=True, text=True)
    sizes = {}
    for line in listing.stdout.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[2] in "BDGSbdgs":
            sizes[parts[3]] = int(parts[1], 16)
    return sizes


class TwentySimModel:
    """A 20-sim C++ or ANSI-C export as a :class:`~rtloop.models.base.Model`.

    Args:
        path: the model folder (``Plant/`` with ``Plant.h``, ``Plant.cpp``, ``Plant.info``).
        finish_time_s: passed to ``SetFinishTime`` after ``Initialize``; 0.0 (default)
            runs forever. The generated default of 100 s would freeze the outputs of a
            real-time run after 100 s.
        cache_dir: where compiled libraries are kept (default :func:`default_cache_dir`).
        build: compile now (default), so compiler errors surface before any task starts.
        extra_flags: more compiler flags (part of the cache key).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        finish_time_s: float = 0.0,
        cache_dir: str | os.PathLike[str] | None = None,
        build: bool = True,
        extra_flags: tuple[str, ...] = (),
        parameters: dict[str, float] | None = None,
    ) -> None:
        self.info = inspect(path)
        self.parameters = self._check_parameters(dict(parameters or {}))
        self.path = self.info.path
        self.kind = self.info.kind
        self.n_inputs = len(self.info.input_names)
        self.n_outputs = len(self.info.output_names)
        self.input_names: tuple[str, ...] | None = self.info.input_names
        self.output_names: tuple[str, ...] | None = self.info.output_names
        self.step_size_s: float | None = self.info.step_size_s
        self.finish_time_s = finish_time_s
        self.cache_dir = cache_dir
        self.extra_flags = tuple(extra_flags)
        self.state_layout = state_layout(self.info)
        """What holds the model's state, or why it cannot be saved (``save_state``)."""
        self.library_path: Path | None = self.build() if build else None
        self._unload()

    def _check_parameters(self, parameters: dict[str, float]) -> dict[int, float]:
        where = f"20-sim model {str(self.info.path)!r}"
        if parameters and self.info.template != "cpp":
            raise ModelError(f"{where}: parameters are supported for C++ exports only (this is ANSI-C)")
        checked: dict[int, float] = {}
        for name, value in parameters.items():
            index = self.info.parameter_index(name)
            if index is None:
                known = ", ".join(n for n, _i, _d in self.info.parameters) or "none named in the sources"
                raise ModelError(f"{where}: unknown parameter {name!r}; parameters are: {known}")
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ModelError(f"{where}: parameter {name!r} = {value!r} is not a number")
            checked[index] = float(value)
        return checked

    def build(self) -> Path:
        """Compile (or find in the cache) the shared library; return its path."""
        self.library_path = build_library(self.info, self.cache_dir, self.extra_flags)
        return self.library_path

    # -- pickling: ctypes objects stay behind, the task process loads its own --------

    def __getstate__(self) -> dict[str, object]:
        state = self.__dict__.copy()
        for key in ("_lib", "_handle", "_calculate", "_u_bound", "_y_bound", "_private_copy", "_state"):
            state[key] = None
        state["_u_ptr"] = state["_y_ptr"] = None
        return state

    def _unload(self) -> None:
        self._lib: ctypes.CDLL | None = None
        self._handle: int | None = None
        self._calculate: Any = None  # rtloop_calculate, a ctypes function once loaded
        self._u_bound: FloatVector | None = None
        self._y_bound: FloatVector | None = None
        self._u_ptr: int | None = None
        self._y_ptr: int | None = None
        self._private_copy: str | None = None
        self._state: Any = None
        """C++: the shim's rtloop_state; ANSI-C: a view of each global; or why the state cannot be saved."""

    def _load(self) -> None:
        library = str(self.library_path or self.build())
        if self.info.template == "c":
            if library in _C_LIBRARIES_IN_USE:
                # dlopen would hand back the same globals: load a private copy instead.
                fd, copy = tempfile.mkstemp(suffix=".so", prefix=f"rtloop-{self.info.name}-")
                os.close(fd)
                shutil.copyfile(library, copy)
                self._private_copy = copy
                library = copy
            else:
                _C_LIBRARIES_IN_USE.add(library)
        lib = ctypes.CDLL(library)
        signatures = {**_SIGNATURES, **(_CPP_SIGNATURES if self.info.template == "cpp" else {})}
        for name, (argtypes, restype) in signatures.items():
            function = getattr(lib, name)
            function.argtypes = argtypes
            function.restype = restype
        self._lib = lib
        self._calculate = lib.rtloop_calculate
        self._handle = lib.rtloop_new()
        self._state = self._state_access(lib, library)

    def _state_access(self, lib: ctypes.CDLL, library: str) -> Any:
        """How to reach the state in this loaded library (found at prerun, not at a snapshot), or why not."""
        if self.state_layout.refused:
            return self.state_layout.refused
        if self.info.template == "cpp":
            function = getattr(lib, "rtloop_state", None)
            if function is None:
                note = state_note(Path(library))
                return note.read_text() if note.is_file() else "its library was built without the state copy"
            function.argtypes, function.restype = _STATE_SIGNATURE
            return function
        try:
            sizes = _exported_sizes(library)
        except StateNotCaptured as error:
            return str(error)
        missing = [name for name in self.state_layout.members if not sizes.get(name)]
        if missing:
            return f"global {missing[0]} is not exported by its library"
        return [(ctypes.c_char * sizes[name]).in_dll(lib, name) for name in self.state_layout.members]

    def save_state(self) -> bytes:
        """The model's state (see the module's docstring); :class:`StateNotCaptured` says why not."""
        state = self._state
        if state is None:
            raise StateNotCaptured(f"{self.kind} model {str(self.path)!r} is not loaded (initialize first)")
        if isinstance(state, str):
            raise StateNotCaptured(f"{self.kind} model {str(self.path)!r}: {state}")
        if isinstance(state, list):
            data = b"".join(bytes(view) for view in state)
        else:
            size = state(self._handle, None, None)
            buffer = ctypes.create_string_buffer(size)
            state(self._handle, buffer, None)
            data = buffer.raw
        return Path(str(self.library_path)).name.encode() + b"\0" + data

    def restore_state(self, saved: bytes) -> None:
        """Take back a state from :meth:`save_state` of the same build of this model (after ``initialize``)."""
        name, _, data = saved.partition(b"\0")
        if name.decode(errors="replace") != Path(str(self.library_path)).name:
            raise ModelError(f"{self.kind} model {str(self.path)!r}: the saved state is of another build "
                             f"({name.decode(errors='replace')}, not {Path(str(self.library_path)).name})")
        state = self._state
        if state is None or isinstance(state, str):
            raise StateNotCaptured(f"{self.kind} model {str(self.path)!r}: {state or 'not loaded'}")
        if isinstance(state, list):
            if len(data) != sum(len(view) for view in state):
                raise ModelError(f"{self.kind} model {str(self.path)!r}: the saved state has {len(data)} bytes")
            offset = 0
            for view in state:
                ctypes.memmove(view, data[offset:], len(view))
                offset += len(view)
            return
        if len(data) != state(self._handle, None, None):
            raise ModelError(f"{self.kind} model {str(self.path)!r}: the saved state has {len(data)} bytes")
        state(self._handle, None, data)

    def _bind(self, u: FloatVector, y: FloatVector) -> None:
        """Remember the data pointers of the task's (fixed) u and y arrays."""
        for name, a, n in (("u", u, self.n_inputs), ("y", y, self.n_outputs)):
            if a.dtype != np.float64 or not a.flags.c_contiguous or a.shape != (n,):
                raise ModelError(
                    f"{self.kind} model {str(self.path)!r}: {name} must be a contiguous "
                    f"float64 vector of length {n}, got {a.dtype} {a.shape}"
                )
        if not y.flags.writeable:
            raise ModelError(f"{self.kind} model {str(self.path)!r}: y is read-only")
        self._u_bound, self._y_bound = u, y
        self._u_ptr, self._y_ptr = u.ctypes.data, y.ctypes.data

    def initialize(self, u: FloatVector, y: FloatVector, t_s: float) -> None:
        """Load the library, create the instance, ``Initialize`` and ``SetFinishTime``."""
        if self._lib is None:
            self._load()
        assert self._lib is not None
        self._bind(u, y)
        self._lib.rtloop_initialize(self._handle, self._u_ptr, self._y_ptr, t_s)
        if self.parameters:  # Initialize set the defaults; ours replace them, then the equations run again
            for index, value in self.parameters.items():
                self._lib.rtloop_set_parameter(self._handle, index, value)
            self._lib.rtloop_reevaluate(self._handle, self._y_ptr)
        if not self._lib.rtloop_set_finish_time(self._handle, self.finish_time_s):
            raise ModelError(
                f"{str(self.path)!r}: SetFinishTime({self.finish_time_s}) refused "
                "(a finish time must lie after the start time)"
            )
        built_step_s = self._lib.rtloop_step_size(self._handle)
        if self.step_size_s is None or abs(built_step_s - self.step_size_s) > 1e-15:
            self.step_size_s = built_step_s  # the compiled code is the authority

    def calculate(self, u: FloatVector, y: FloatVector) -> None:
        """One ``Calculate(u, y)`` call (pointers are cached per array)."""
        if u is not self._u_bound or y is not self._y_bound:
            self._bind(u, y)
        self._calculate(self._handle, self._u_ptr, self._y_ptr)

    def is_finished(self) -> bool:
        """``IsFinished()``: True once the finish time has passed (outputs then hold)."""
        assert self._lib is not None, "initialize first"
        return bool(self._lib.rtloop_is_finished(self._handle))

    def terminate(self, u: FloatVector, y: FloatVector) -> None:
        """``Terminate(u, y)``, delete the instance and release the library."""
        if self._lib is None:
            return
        self._bind(u, y)
        self._lib.rtloop_terminate(self._handle, self._u_ptr, self._y_ptr)
        self._lib.rtloop_delete(self._handle)
        if self._private_copy is not None:
            os.unlink(self._private_copy)  # the mapping stays valid until exit
        else:
            _C_LIBRARIES_IN_USE.discard(str(self.library_path))
        self._unload()
