"""The module an app file names, loaded by its file path — the folder never goes on ``sys.path``.

An app file's ``runnable = "jiwy_models:JiwyPlant"`` may name a module that sits beside
the app file. Putting that folder first on ``sys.path`` (and having every task process
inherit it) would let any file in it shadow an installed or standard module: a
``numpy.py`` dropped there would run inside the real-time task as the app's user. So:

- only ``<folder>/<module>.py`` is loaded, by path, under the module's own name;
- a name that is also an installed or standard module is refused (no silent choice);
- the file must be owned by the caller or by root;
- task processes receive instances of its classes with a note to load that same file
  first (:func:`_reduce_by_file`), so unpickling works without touching ``sys.path``.

Modules beside the app file import each other as they would in a script
(``from motor import PiSpeed`` in ``faulty.py``): once a module of a folder is loaded,
:class:`SiblingFinder` serves that folder's other ``<name>.py`` files by the same rules —
it sits *last* among the import finders, so an installed or standard module of the
same name always wins, and the owner check applies to each file.
"""

from __future__ import annotations

import copyreg
import importlib.abc
import importlib.machinery
import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType
from typing import Any, ClassVar

from rtloop.errors import AppError
from rtloop.sudo import invoking_user


class ModuleRefused(AppError):
    """The module beside the app file cannot be used (shadows another, foreign owner, bad file)."""


def module_beside(folder: Path, module_name: str) -> Path | None:
    """``folder/module_name.py`` if the app file's folder holds the named (top-level) module."""
    if "." in module_name or not module_name.isidentifier():
        return None
    candidate = folder / f"{module_name}.py"
    return candidate if candidate.is_file() else None


def installed_origin(module_name: str) -> str | None:
    """Where ``import module_name`` finds the top-level module without the app's folder (None: nowhere)."""
    top = module_name.split(".")[0]
    if top in sys.builtin_module_names or importlib.machinery.FrozenImporter.find_spec(top) is not None:
        return f"built-in module {top!r}"
    spec = importlib.machinery.PathFinder.find_spec(top)
    if spec is None:
        return None
    return spec.origin or (list(spec.submodule_search_locations or [])[:1] or [top])[0]


def check_owner(path: Path) -> None:
    """Refuse a module file owned by someone other than the caller or root (under sudo, the
    user who ran sudo is the caller too: they could run anything as root already)."""
    owner = os.stat(path).st_uid
    if owner not in _trusted_uids():
        raise ModuleRefused(f"{path} is owned by uid {owner}, not by you (uid {os.geteuid()}) or root; "
                            "rtloop will not run it")


def _trusted_uids() -> set[int]:
    uids = {0, os.geteuid()}
    invoker = invoking_user()
    if invoker is not None:
        uids.add(invoker[0])
    return uids


def load_module_file(module_name: str, path: str | Path) -> ModuleType:
    """Load ``path`` as module ``module_name`` (once per process) and let its classes travel to task processes."""
    path = Path(path)
    loaded = sys.modules.get(module_name)
    if loaded is not None and getattr(loaded, "__file__", None) == str(path):
        return loaded
    check_owner(path)
    SiblingFinder.serve(path.parent)  # before it runs: its own imports may name its neighbours
    spec = importlib.util.spec_from_file_location(module_name, path)
    if spec is None or spec.loader is None:
        raise ModuleRefused(f"{path}: not a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[module_name]
        raise
    _send_classes_by_file(module)
    return module


def _send_classes_by_file(module: ModuleType) -> None:
    for value in vars(module).values():
        if isinstance(value, type) and value.__module__ == module.__name__:
            copyreg.pickle(value, _reduce_by_file)


class SiblingFinder(importlib.abc.MetaPathFinder):
    """Finds ``<folder>/<name>.py`` for a top-level import nothing installed answers.

    Appended to the end of ``sys.meta_path``: Python asks it only after the standard,
    built-in and installed modules said no, so a file here never shadows one of them.
    """

    folders: ClassVar[list[Path]] = []

    @classmethod
    def serve(cls, folder: Path) -> None:
        """Let the modules in ``folder`` import each other (once per folder and process)."""
        folder = folder.resolve()
        if folder not in cls.folders:
            cls.folders.append(folder)
        if not any(isinstance(finder, cls) for finder in sys.meta_path):
            sys.meta_path.append(cls())

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if path is not None or "." in fullname:
            return None  # submodules of packages are their package's business
        for folder in self.folders:
            candidate = module_beside(folder, fullname)
            if candidate is not None:
                check_owner(candidate)
                loader = _SiblingLoader(fullname, str(candidate))
                return importlib.util.spec_from_file_location(fullname, candidate, loader=loader)
        return None


class _SiblingLoader(importlib.machinery.SourceFileLoader):
    def exec_module(self, module: ModuleType) -> None:
        super().exec_module(module)
        _send_classes_by_file(module)  # its classes travel to task processes like the named module's


def _reduce_by_file(obj: Any) -> tuple[Any, ...]:
    """Pickle ``obj`` so that the receiving process loads its module by file first."""
    module = sys.modules[type(obj).__module__]
    rebuild, args, *rest = obj.__reduce_ex__(4)
    return (_rebuild, (_ModuleByFile(module.__name__, module.__file__), rebuild, args), *rest)


class _ModuleByFile:
    """Unpickles as 'load this file as that module' (it comes first, so later references resolve)."""

    def __init__(self, module_name: str, path: str) -> None:
        self.module_name, self.path = module_name, path

    def __reduce__(self) -> tuple[Any, ...]:
        return (load_module_file, (self.module_name, self.path))


def _rebuild(_module: ModuleType, rebuild: Any, args: tuple[Any, ...]) -> Any:
    return rebuild(*args)
