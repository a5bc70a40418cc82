"""The module an app file names, loaded by its file path — the folder never goes on ``sys.path``.

An app file's ``runnable = "jiwy_models:JiwyPlant"`` may name a module that sits beside
the app file. Putting that folder first on ``sys.path`` (and having every task process
inherit it) would let any file in it shadow an installed or standard module: a
``numpy.py`` dropped there would run inside the real-time task as the app's user. So:

- only ``<folder>/<module>.py`` is loaded, by path, under the module's own name;
- a name that is also an installed or standard module is refused (no silent choice);
- the file must be owned by the caller or by root (under sudo, the user who ran sudo too) and
  writable by no one else; so must its folder and every folder above it, or another user could
  swap the file between the check and the import;
- it is compiled from that checked source every time: bytecode in ``__pycache__`` is never read
  (another user may have written it) nor written (root's would litter a sudo user's folder);
- it is loaded once per process, until the file (or a module it loaded) is edited: the next app
  that names it then loads it anew, as a task process would (``app/sources.py`` keeps what each
  module was made of), so a notebook never runs yesterday's controller beside today's;
- task processes receive instances of its classes with a note to load that same file
  first (:func:`_reduce_by_file`), so unpickling works without touching ``sys.path``.

Modules beside the app file import each other as they would in a script
(``from motor import PiSpeed`` in ``faulty.py``): once a module of a folder is loaded,
:class:`SiblingFinder` serves that folder's other ``<name>.py`` files by the same rules —
it sits *last* among the import finders, so an installed or standard module of the
same name always wins, and the owner check applies to each file.
"""

from __future__ import annotations

import contextlib
import copyreg
import importlib.abc
import importlib.machinery
import importlib.util
import os
import stat
import sys
import weakref
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any, ClassVar

from rtloop.app import sources
from rtloop.errors import AppError
from rtloop.owners import folder_problem, untrusted_writer
from rtloop.sudo import trusted_uids, trusted_users_phrase

SOURCES_ATTRIBUTE = "__rtloop_sources__"
"""On a module loaded by file: the files it was made of (its own, and the modules it loaded), path → digest."""


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


def check_owner(path: Path, trusted: set[int] | None = None, whom: str | None = None) -> None:
    """Refuse a module file owned by someone other than the caller or root (under sudo, the
    user who ran sudo is the caller too: they could run anything as root already).
    ``trusted``/``whom``: check for other users than this process's (a service's, say)."""
    owner = os.stat(path).st_uid
    if owner not in (trusted or _trusted_uids()):
        raise ModuleRefused(f"{path} is owned by uid {owner}, not by {whom or _whom()}; rtloop will not run it")


def check_folders(folder: Path, trusted: set[int] | None = None, whom: str | None = None) -> None:
    """Refuse code from a folder that another user could change: one they own, or one they may
    write to (mode, or a group with them in it), or below such a folder (they could rename it
    away and put their own in its place). A sticky folder such as /tmp is fine: there nobody
    renames or removes what they do not own."""
    problem = folder_problem(folder, trusted or _trusted_uids(), whom or _whom(), sticky_is_enough=True)
    if problem is not None:
        path, what, chmod_fixes = problem
        raise ModuleRefused(f"{path} is {what}; rtloop will not run code from below it"
                            + (f" (chmod go-w {path})" if chmod_fixes else ""))


def check_model_files(path: Path) -> None:
    """A model (an FMU, a 20-sim export folder) is code that runs as the app's user: the same
    owner and writer rules as a module, for the file or every file of the folder, and the
    folders above."""
    path = path.resolve()
    if not path.exists():
        return  # the model's own loader says what is missing
    trusted = _trusted_uids()
    check_folders(path.parent)
    files = [path]
    if path.is_dir():
        check_folders(path)
        files = [child for child in sorted(path.rglob("*")) if not child.is_symlink()]
    for file in files:
        facts = os.stat(file)
        if facts.st_uid not in trusted:
            raise ModuleRefused(f"{file} is owned by uid {facts.st_uid}, not by {_whom()}; rtloop will not run it")
        writer = untrusted_writer(facts, trusted, _whom(), file)
        if writer and not (stat.S_ISDIR(facts.st_mode) and facts.st_mode & stat.S_ISVTX):
            raise ModuleRefused(f"{file} is {writer}; rtloop will not run it (chmod go-w {file})")
    digest = sources.file_digest(path)
    if digest is not None:
        sources.note({str(path): digest})


_TRUST_OVERRIDES: list[tuple[set[int], str]] = []
"""Set by :func:`trusting_only`: whose code to accept instead of this process's trusted users."""


@contextlib.contextmanager
def trusting_only(uid: int, whom: str) -> Iterator[None]:
    """Check code as a process of ``uid`` without sudo would (a service's user), not as this one."""
    _TRUST_OVERRIDES.append(({0, uid}, whom))
    try:
        yield
    finally:
        _TRUST_OVERRIDES.pop()


def read_checked_source(path: Path) -> bytes:
    """The bytes of module file ``path``, checked on the very file that is read (no swap between)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    try:
        facts = os.fstat(fd)
        if not stat.S_ISREG(facts.st_mode):
            raise ModuleRefused(f"{path}: not a regular file; rtloop will not run it")
        trusted = _trusted_uids()
        if facts.st_uid not in trusted:
            raise ModuleRefused(f"{path} is owned by uid {facts.st_uid}, not by {_whom()}; rtloop will not run it")
        writer = untrusted_writer(facts, trusted, _whom(), fd)
        if writer:
            raise ModuleRefused(f"{path} is {writer}; rtloop will not run it (chmod go-w {path})")
        with os.fdopen(os.dup(fd), "rb") as stream:
            return stream.read()
    finally:
        os.close(fd)


def _whom() -> str:
    return _TRUST_OVERRIDES[-1][1] if _TRUST_OVERRIDES else trusted_users_phrase()


def _trusted_uids() -> set[int]:
    return _TRUST_OVERRIDES[-1][0] if _TRUST_OVERRIDES else trusted_uids()


def load_module_file(module_name: str, path: str | Path) -> ModuleType:
    """Load ``path`` as module ``module_name`` (once per process) and let its classes travel to task processes."""
    path = Path(path)
    loaded = sys.modules.get(module_name)
    if loaded is not None and getattr(loaded, "__file__", None) == str(path):
        made_of = getattr(loaded, SOURCES_ATTRIBUTE, {})
        if not _changed(made_of):
            sources.note(made_of)  # what it was made of, for the app loading it now
            return loaded
        _forget_changed_modules()  # edited since: load today's file (a task process would), not the old code
    check_owner(path)
    check_folders(path.parent)
    SiblingFinder.serve(path.parent)  # before it runs: its own imports may name its neighbours
    spec = importlib.util.spec_from_file_location(module_name, path, loader=_SourceOnlyLoader(module_name, str(path)))
    if spec is None or spec.loader is None:
        raise ModuleRefused(f"{path}: not a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[module_name]
        raise
    return module


def _changed(made_of: dict[str, str]) -> bool:
    return any(sources.file_digest(file) != digest for file, digest in made_of.items())


def _forget_changed_modules() -> None:
    """Drop from ``sys.modules`` every module loaded by file that was edited since, or that loaded
    one that was: the next import loads the file as it is now."""
    for name, module in list(sys.modules.items()):
        made_of = getattr(module, SOURCES_ATTRIBUTE, None)
        if made_of and _changed(made_of):
            del sys.modules[name]


def _forget_other_folders_siblings(folder: Path) -> None:
    """Before a module of ``folder`` runs: drop the modules loaded by file from another folder under
    a name that ``folder`` has a file of (``helper.py`` in two apps' folders): its ``import helper``
    must get its own neighbour, not the other app's from ``sys.modules``."""
    for name, module in list(sys.modules.items()):
        if getattr(module, SOURCES_ATTRIBUTE, None) is None:
            continue
        if Path(module.__file__ or "").resolve().parent != folder and module_beside(folder, name) is not None:
            del sys.modules[name]


_FILE_OF_CLASS: weakref.WeakKeyDictionary[type, tuple[str, str]] = weakref.WeakKeyDictionary()
"""A class defined by a module loaded by file → (that module's name, its file): what the class came
from, even after another app's module of the same name took its place in ``sys.modules``."""


def _send_classes_by_file(module: ModuleType) -> None:
    for value in vars(module).values():
        if isinstance(value, type) and value.__module__ == module.__name__ and module.__file__:
            copyreg.pickle(value, _reduce_by_file)
            _FILE_OF_CLASS[value] = (module.__name__, module.__file__)


def replaced_class_by_file(cls: type) -> tuple[Any, ...] | None:
    """How to pickle ``cls`` when its module name now means another file's module (two apps of one
    process with ``controller.py`` each, the first one run again): load its own file by name, or
    None when pickling it by reference is right."""
    made = _FILE_OF_CLASS.get(cls)
    if made is None:
        return None
    current: Any = sys.modules.get(cls.__module__)
    for part in cls.__qualname__.split("."):
        current = getattr(current, part, None)
    if current is cls:
        return None
    return _class_from_file, (*made, cls.__qualname__)


def _class_from_file(module_name: str, path: str, qualname: str) -> Any:
    found: Any = load_module_file(module_name, path)
    for part in qualname.split("."):
        found = getattr(found, part)
    return found


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
        importing = _EXECUTING_FOLDERS[-1:]  # a module's own neighbours first (two apps may both have helper.py)
        for folder in importing + [f for f in self.folders if f not in importing]:
            candidate = module_beside(folder, fullname)
            if candidate is not None:
                candidate = candidate.resolve()  # a link to a module elsewhere: that file, in its folder
                check_owner(candidate)
                if candidate.parent != folder:
                    check_folders(candidate.parent)
                loader = _SourceOnlyLoader(fullname, str(candidate))
                return importlib.util.spec_from_file_location(fullname, candidate, loader=loader)
        return None


_EXECUTING_FOLDERS: list[Path] = []
"""The folders of the modules loaded by file that are running their top level now, innermost last."""


class _SourceOnlyLoader(importlib.machinery.SourceFileLoader):
    """Compiles the checked source every time, never touching ``__pycache__``: a user module is a
    few kB, compiled in a few milliseconds, and bytecode there could come from another user."""

    def get_code(self, fullname: str) -> Any:
        source = read_checked_source(Path(self.path))
        self.digest = sources.digest_of_bytes(source)  # of the very bytes compiled
        return self.source_to_code(source, self.path)

    def exec_module(self, module: ModuleType) -> None:
        folder = Path(self.path).parent.resolve()
        _forget_other_folders_siblings(folder)
        _EXECUTING_FOLDERS.append(folder)
        try:
            with sources.collecting() as loaded_by_it:  # the modules it loads in turn
                super().exec_module(module)
        finally:
            _EXECUTING_FOLDERS.pop()
        made_of = {self.path: self.digest, **loaded_by_it}
        setattr(module, SOURCES_ATTRIBUTE, made_of)
        sources.note(made_of)
        _send_classes_by_file(module)  # its classes travel to task processes, to be loaded by file there


def _reduce_by_file(obj: Any) -> tuple[Any, ...]:
    """Pickle ``obj`` so that the receiving process loads its module by file first."""
    made = _FILE_OF_CLASS.get(type(obj))  # its own module's file, whatever sys.modules holds now
    rebuild, args, *rest = obj.__reduce_ex__(4)
    if made is None:  # nothing to load by file: the receiver imports it by name
        return (rebuild, args, *rest)
    return (_rebuild, (_ModuleByFile(*made), rebuild, args), *rest)


class _ModuleByFile:
    """Unpickles as 'load this file as that module' (it comes first, so later references resolve)."""

    def __init__(self, module_name: str, path: str) -> None:
        self.module_name, self.path = module_name, path

    def __reduce__(self) -> tuple[Any, ...]:
        return (load_module_file, (self.module_name, self.path))

    def __deepcopy__(self, _memo: dict[int, Any]) -> _ModuleByFile:
        """``copy.deepcopy`` consults copyreg too, so without this an in-process copy of an instance loaded
        the module's file again: after an edit on disk it imported the edited file (compiling it, one C call
        of 7-10 ms holding the interpreter's lock in a task's reload thread: the loop, waking, waited as long)
        and put it in ``sys.modules``. A copy needs no module loaded: the class is copied by reference."""
        return self


def _rebuild(_module: ModuleType, rebuild: Any, args: tuple[Any, ...]) -> Any:
    return rebuild(*args)
