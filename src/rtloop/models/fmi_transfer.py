"""The loop's side of an FMU's inputs and outputs: one :class:`Transfer` per FMI type, holding the
value references, a buffer of that type (or a pointer straight into ``u``/``y`` for float64 values
side by side) and the raw ctypes function that sets or gets them, all made once before the loop."""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from rtloop.models.fmi_variables import Element


class Transfer:
    """One FMI type's share of ``u`` or ``y``: value references, a buffer, and where each value goes."""

    def __init__(self, elements: list[Element], positions: list[int], fmi3: bool) -> None:
        self.elements = elements
        self.function_type = elements[0].function_type
        self.ctype = elements[0].ctype
        vrs: list[int] = []
        for e in elements:
            if not vrs or vrs[-1] != e.value_reference or e.offset == 0:
                vrs.append(e.value_reference)
        self.vrs = (ctypes.c_uint * len(vrs))(*vrs)
        self.n_vrs, self.n_values = len(vrs), len(elements)
        self.tail = (self.n_values,) if fmi3 else ()
        self.positions = np.array(positions, dtype=np.intp)
        contiguous = positions == list(range(positions[0], positions[0] + len(positions)))
        self.direct = self.ctype is ctypes.c_double and contiguous  # pass u/y itself, no copy
        self.buffer = (self.ctype * self.n_values)()
        self.view = np.ctypeslib.as_array(self.buffer)
        self.scratch = np.zeros(self.n_values)
        self.checked = any(e.low is not None for e in elements)
        self.pointer = ctypes.addressof(self.buffer)
        self.get: Any = None
        self.set: Any = None

    def bind(self, vector: np.ndarray) -> None:
        if self.direct:
            self.pointer = vector.ctypes.data + int(self.positions[0]) * 8

    def load_from(self, u: np.ndarray) -> None:
        """Fill the buffer from ``u`` (not needed for direct transfers), checking exactness."""
        np.take(u, self.positions, out=self.scratch)
        if self.checked:
            s = self.scratch
            if not np.all(np.isfinite(s)) or np.any(s != np.floor(s)):
                self._reject(s)
            for e, value in zip(self.elements, s, strict=True):
                if e.low is not None and e.high is not None and not e.low <= value <= e.high:
                    self._reject(s)
        if self.ctype is ctypes.c_bool:
            self.view[:] = self.scratch != 0.0
        else:
            self.view[:] = self.scratch

    def _reject(self, values: np.ndarray) -> None:
        for e, value in zip(self.elements, values.tolist(), strict=True):
            e.check(value)

    def store_to(self, y: np.ndarray) -> None:
        y[self.positions] = self.view


def raw_function(dll: ctypes.CDLL, name: str, argtypes: list[Any]) -> Any:
    """A fresh ctypes handle on an FMI function, with our own argtypes (no FMPy wrapper)."""
    function = getattr(dll, name)
    function = type(function)((name, dll))  # own object: FMPy's argtypes stay untouched
    function.argtypes = argtypes
    function.restype = ctypes.c_int
    return function


def _value_function(dll: ctypes.CDLL, verb: str, function_type: str, fmi_version: str) -> Any:
    prefix = "fmi3" if fmi_version == "3.0" else "fmi2"
    vr_ptr = ctypes.POINTER(ctypes.c_uint)
    args = [ctypes.c_void_p, vr_ptr, ctypes.c_size_t, ctypes.c_void_p]
    if fmi_version == "3.0":
        args.append(ctypes.c_size_t)  # nValues
    return raw_function(dll, f"{prefix}{verb}{function_type}", args)


def transfers(dll: ctypes.CDLL, elements: list[Element], verb: str, fmi_version: str) -> list[Transfer]:
    """The transfers that ``verb`` (``Set``: inputs, ``Get``: outputs) ``elements``, one per FMI type."""
    fmi3 = fmi_version == "3.0"
    groups: dict[str, tuple[list[Element], list[int]]] = {}
    for position, e in enumerate(elements):
        group = groups.setdefault(e.function_type, ([], []))
        group[0].append(e)
        group[1].append(position)
    made = []
    for function_type, (members, positions) in groups.items():
        transfer = Transfer(members, positions, fmi3)
        function = _value_function(dll, verb, function_type, fmi_version)
        if verb == "Set":
            transfer.set = function
        else:
            transfer.get = function
        made.append(transfer)
    return made
