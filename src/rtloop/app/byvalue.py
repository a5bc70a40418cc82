"""Runnables defined in a script, a notebook or ``python -`` travel to task processes by value.

A task process is *spawned*: it starts a fresh interpreter and unpickles its runnable.
Pickle sends a class by reference (``module.Class``), which the new interpreter cannot
resolve when the class lives in ``__main__`` (a notebook cell, ``python -``, a script's
``if __name__ == "__main__"`` block) or inside a function. Such classes and functions are
sent here by value instead: their code objects (``marshal``: parent and child run the
same interpreter), the globals they use, their defaults and closures. Everything else
(rtloop's own classes, numpy, modules beside an app file) still goes by reference.

:func:`dumps_runnable` pickles one runnable this way; :func:`loads_runnable` is plain
``pickle.loads``: the reconstruction functions below are found by name in the child.
"""

from __future__ import annotations

import abc
import builtins
import importlib
import io
import marshal
import multiprocessing.spawn
import pickle
import sys
import types
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from rtloop.errors import AppError
from rtloop.text import clip

__all__ = ["RunnableNotSendable", "children_without_main", "dumps_runnable", "loads_runnable"]

_SKIPPED_CLASS_KEYS = frozenset({"__dict__", "__weakref__", "_abc_impl", "__abstractmethods__"})
_NAMESPACES: dict[str, dict[str, Any]] = {}
"""Child side: one globals dict per original module, shared by its functions (as a module's is)."""


class RunnableNotSendable(AppError):
    """A runnable could not be pickled for its task process."""


def dumps_runnable(runnable: object, task: str) -> bytes:
    """The runnable as bytes for a spawned task process; one clear line if it cannot be."""
    buffer = io.BytesIO()
    try:
        _ByValuePickler(buffer, protocol=5).dump(runnable)
    except RecursionError:
        raise RunnableNotSendable(f"task {task!r}: its runnable refers to itself too deeply to be sent to the "
                                  "task process; define its class in a module file and import it") from None
    except Exception as error:  # whatever pickle raises for an attribute it cannot send
        raise RunnableNotSendable(
            f"task {task!r}: {type(runnable).__name__} cannot be sent to its task process "
            f"({type(error).__name__}: {clip(str(error), 160)}); keep only numbers, arrays and plain objects in its "
            "attributes before prerun (open files, devices and libraries in prerun)") from None
    return buffer.getvalue()


def loads_runnable(data: bytes) -> Any:
    """Rebuild a runnable from :func:`dumps_runnable`'s bytes (in the task process)."""
    return pickle.loads(data)


@contextmanager
def children_without_main() -> Iterator[None]:
    """Processes spawned inside do not re-run ``__main__`` (the user's script, a notebook, stdin).

    multiprocessing's spawn re-imports the parent's main module in each child so that
    classes pickled by reference to ``__main__`` resolve: that fails for ``python -``
    (``FileNotFoundError: '<stdin>'``) and runs a script's unguarded top level again.
    Here what the child needs from ``__main__`` travels by value, so it is left out.
    """
    original = multiprocessing.spawn.get_preparation_data

    def without_main(name: str) -> dict[str, Any]:
        data = original(name)
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    multiprocessing.spawn.get_preparation_data = without_main
    try:
        yield
    finally:
        multiprocessing.spawn.get_preparation_data = original


def sent_by_value(obj: Any) -> bool:
    """True for classes and functions a fresh interpreter cannot import by name."""
    module = getattr(obj, "__module__", None)
    return module in ("__main__", "__mp_main__") or "<locals>" in getattr(obj, "__qualname__", "")


class _ByValuePickler(pickle.Pickler):
    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, type) and sent_by_value(obj):
            return _reduce_class(obj)
        if isinstance(obj, type) and (by_file := _replaced_class_by_file(obj)) is not None:
            return by_file
        if isinstance(obj, types.FunctionType) and sent_by_value(obj):
            return _reduce_function(obj)
        if isinstance(obj, types.ModuleType) and obj.__name__ not in ("__main__", "__mp_main__"):
            return importlib.import_module, (obj.__name__,)
        if isinstance(obj, staticmethod | classmethod):
            return type(obj), (obj.__func__,)
        if isinstance(obj, property):
            return property, (obj.fget, obj.fset, obj.fdel, obj.__doc__)
        return NotImplemented


def _replaced_class_by_file(cls: type) -> tuple[Any, ...] | None:
    """``modules.replaced_class_by_file`` where modules were loaded by file at all (a task process,
    which only unpickles, never imports the loader and what it needs: hashlib, tempfile, ...)."""
    modules = sys.modules.get("rtloop.app.modules")
    return None if modules is None else modules.replaced_class_by_file(cls)


# --- classes -------------------------------------------------------------------------------
def _reduce_class(cls: type) -> tuple[Any, ...]:
    slots = cls.__dict__.get("__slots__", ())
    slots = (slots,) if isinstance(slots, str) else tuple(slots)
    attributes = {
        key: value for key, value in cls.__dict__.items()
        if key not in _SKIPPED_CLASS_KEYS and key not in slots
    }
    skeleton = (type(cls), cls.__name__, cls.__bases__, {"__slots__": slots} if slots else {}, cls.__module__)
    # The attributes go in the state, set after the skeleton is memoised: methods whose
    # closure holds the class itself (``super()``'s ``__class__`` cell) then resolve to it.
    return _make_class, skeleton, attributes, None, None, _set_class_attributes


def _make_class(metaclass: type, name: str, bases: tuple[type, ...], namespace: dict[str, Any],
                module: str) -> type:
    cls: type = metaclass(name, bases, {**namespace, "__module__": module})
    return cls


def _set_class_attributes(cls: type, attributes: dict[str, Any]) -> None:
    for key, value in attributes.items():
        if key not in ("__module__", "__slots__"):
            setattr(cls, key, value)
    abc.update_abstractmethods(cls)  # step() arrived after the class was made: it is concrete now


# --- functions -----------------------------------------------------------------------------
def _reduce_function(function: types.FunctionType) -> tuple[Any, ...]:
    code = function.__code__
    used = {name: function.__globals__[name] for name in _global_names(code) if name in function.__globals__}
    closure = tuple(cell.cell_contents if _cell_is_set(cell) else _EMPTY for cell in function.__closure__ or ())
    state = {
        "globals": used, "defaults": function.__defaults__, "kwdefaults": function.__kwdefaults__,
        "closure": closure, "dict": function.__dict__, "qualname": function.__qualname__,
        "module": function.__module__, "doc": function.__doc__, "annotations": function.__annotations__,
    }
    skeleton = (marshal.dumps(code), function.__name__, function.__module__, len(closure))
    return _make_function, skeleton, state, None, None, _set_function_state


def _global_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _global_names(constant)
    return names


def _cell_is_set(cell: types.CellType) -> bool:
    try:
        cell.cell_contents  # noqa: B018 — reading it is the test
    except ValueError:
        return False
    return True


class _Empty:
    """An unset closure cell (a variable assigned after the function was made)."""

    def __reduce__(self) -> str:
        return "_EMPTY"


_EMPTY = _Empty()


def _make_function(code_bytes: bytes, name: str, module: str, n_cells: int) -> types.FunctionType:
    namespace = _NAMESPACES.setdefault(module, {"__builtins__": builtins, "__name__": module})
    cells = tuple(types.CellType() for _ in range(n_cells))
    return types.FunctionType(marshal.loads(code_bytes), namespace, name, None, cells or None)


def _set_function_state(function: types.FunctionType, state: dict[str, Any]) -> None:
    function.__globals__.update(state["globals"])
    function.__defaults__ = state["defaults"]
    function.__kwdefaults__ = state["kwdefaults"]
    function.__dict__.update(state["dict"])
    function.__qualname__ = state["qualname"]
    function.__module__ = state["module"]
    function.__doc__ = state["doc"]
    function.__annotations__ = state["annotations"]
    for cell, value in zip(function.__closure__ or (), state["closure"], strict=True):
        if value is not _EMPTY:
            cell.cell_contents = value

