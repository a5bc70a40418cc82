"""20-sim generated C++ and ANSI-C code, compiled once and called through ctypes.

A 20-sim export is a folder of sources without a Makefile. :class:`TwentySimModel`
recognises the template (C++ class derived from ``Submodel20sim``, or the ANSI-C
``XXInitializeSubmodel`` functions with an optional prefix), reads the signal names
from the ``.info`` file, writes a small ``extern "C"`` shim, and compiles model + shim
into one shared library per model::

    g++ -O2 -fPIC -shared -include cstddef   (C++; some templates need <cstddef> for NULL)
    gcc -O2 -fPIC -shared                    (ANSI-C)

The library is cached under ``$RTLOOP_CACHE_DIR/models`` (default
``~/.cache/rtloop/models``), named by a hash of the sources, the shim, the compiler and
its flags, so a second run starts at once. It is loaded in the task process, in
``initialize`` (prerun); the constructor only parses and builds, so the model pickles.

The shim's C API (``rtloop_*``) takes an instance handle: C++ models may have several
instances in one process. ANSI-C models keep their state in globals; a second live
instance in the same process gets a private copy of the library.

A model's state can be saved and restored (a ``--keep`` run's window is replayed from it,
``runtime/snapshot.py``), through its state arrays, found in the sources (:class:`StateLayout`):

- C++: every ``XXDouble`` array the model's constructor allocates (``m_P = new XXDouble[n]``:
  parameters, variables, states, rates, ...) and every number member of the model class and
  of ``Submodel20sim`` (time, step size, the run state flags). The shim's ``rtloop_state``
  copies them out or in. If that copy does not compile for an export, the library is built
  without it and the state says why it cannot be saved.
- ANSI-C: every number the sources define at file scope (``xx_time``, ``xx_P[]``, ``xx_s[]``,
  ...): the whole model is in them. Their sizes come from the library's symbol table (``nm``).

A member or global rtloop cannot copy (a structure other than 20-sim's matrices, which point into
the arrays; a ``static`` number at file scope; an integration method that keeps a history)
makes the state refused, naming it: never saved half.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import re
import shutil
import stat
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.models.base import ModelBuildError, ModelError, StateNotCaptured
from rtloop.owners import untrusted_writer
from rtloop.runnable import FloatVector
from rtloop.sudo import trusted_uids, trusted_users_phrase

__all__ = ["TwentySimInfo", "TwentySimModel", "build_library", "default_cache_dir", "inspect"]

# -z defs: a symbol nothing defines (a missing common/*.cpp) fails the link, at build time.
# -ffp-contract=off: gcc fuses a*b+c into one FMA instruction where the CPU has one (aarch64,
# not baseline x86-64), which rounds once instead of twice; off, a model gives the same bits
# on both, and the same as the Python reference models.
CXX_FLAGS = ("-O2", "-ffp-contract=off", "-fPIC", "-shared", "-Wl,-z,defs", "-include", "cstddef")
C_FLAGS = ("-O2", "-ffp-contract=off", "-fPIC", "-shared", "-Wl,-z,defs")
SOURCE_SUFFIXES = {".c", ".cpp", ".cc", ".cxx", ".h", ".hpp"}

_CLASS_RE = re.compile(
    r"class\s+(\w+)\s*:\s*(?:virtual\s+)?public\s+(?:virtual\s+)?Submodel20sim\b"
)
_C_INIT_RE = re.compile(r"\b(\w*?)XXInitializeSubmodel\s*\(")
_MAIN_RE = re.compile(r"\bint\s+main\s*\(")
# "m_V[0] = u[0]; /* SteeringPan */" and "y[0] = m_V[14]; /* AnglePan */"
_SIGNAL_RE = re.compile(r"(?<![\w\]])([uy])\s*\[\s*(\d+)\s*\][^/\n]*/\*\s*(.*?)\s*\*/")
_PARAM_RE = re.compile(r"\b(?:m_P|\w*xx_P)\s*\[\s*(\d+)\s*\]\s*=\s*([^;]*);[ \t]*/\*\s*(.*?)\s*\*/")
_STEP_INFO_RE = re.compile(r"step\s*size\s*[:=]\s*([-+0-9.eE]+)", re.IGNORECASE)
_STEP_SRC_RE = re.compile(r"(?:m_step_size|xx_step_size)\s*=\s*([-+0-9.eE]+)\s*;")


@dataclass(frozen=True)
class TwentySimInfo:
    """What a 20-sim export folder contains, read without compiling it."""

    path: Path
    """The model folder."""
    name: str
    """Model name: C++ class name or folder name."""
    template: str
    """``"cpp"`` or ``"c"``."""
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    step_size_s: float | None
    """From the ``.info`` file, else from ``m_step_size = …`` / ``xx_step_size = …``."""
    sources: tuple[Path, ...]
    """Files compiled into the library (files with ``main`` left out)."""
    include_dirs: tuple[Path, ...]
    header: Path | None = None
    """C++: the header declaring the model class."""
    prefix: str = ""
    """ANSI-C: the function prefix (``%FUNCTIONPREFIX%``), may be empty."""
    parameters: tuple[tuple[str, int, float], ...] = ()
    """(name, index into the parameter array, default) from ``m_P[i] = value; /* name */`` lines."""

    def parameter_index(self, name: str) -> int | None:
        """Index of a parameter by its 20-sim name (``pan\\r``; ``pan.r`` also works)."""
        for known, index, _default in self.parameters:
            if name in (known, known.replace("\\", ".")):
                return index
        return None

    @property
    def kind(self) -> str:
        return "20sim-cpp" if self.template == "cpp" else "20sim-c"


def default_cache_dir() -> Path:
    """``$RTLOOP_CACHE_DIR/models``, or ``~/.cache/rtloop/models``."""
    root = os.environ.get("RTLOOP_CACHE_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "rtloop"
    return base / "models"


def inspect(path: str | os.PathLike[str]) -> TwentySimInfo:
    """Recognise a 20-sim export folder (or a file in it) and read its interface."""
    folder = Path(path).expanduser().resolve()
    if folder.is_file():
        folder = folder.parent
    if not folder.is_dir():
        raise ModelError(f"20-sim model folder {str(folder)!r} does not exist")
    files = sorted(p for p in folder.rglob("*") if p.suffix in SOURCE_SUFFIXES and p.is_file())
    texts = {p: p.read_text(errors="replace") for p in files}

    header, class_name = None, None
    for p, text in texts.items():
        m = _CLASS_RE.search(text) if p.suffix in {".h", ".hpp"} else None
        if m:
            header, class_name = p, m.group(1)
            break
    prefix = None
    if header is None:
        for text in texts.values():
            m = _C_INIT_RE.search(text)
            if m:
                prefix = m.group(1)
                break
    exports = _exports(folder, texts)
    if len(exports) > 1:
        listed = ", ".join(exports)
        raise ModelError(
            f"{str(folder)!r} holds {len(exports)} 20-sim exports ({listed}): name one of them, "
            f"e.g. 20sim:{folder / exports[0]}"
        )
    if header is None and prefix is None:
        raise ModelError(
            f"{str(folder)!r} is not a 20-sim export: no class derived from Submodel20sim "
            "(C++ template) and no XXInitializeSubmodel function (ANSI-C template)"
        )
    template = "cpp" if header is not None else "c"
    compiled = {".cpp", ".cc", ".cxx"} if template == "cpp" else {".c"}
    sources = tuple(
        p for p, text in texts.items() if p.suffix in compiled and not _MAIN_RE.search(text)
    )
    include_dirs = tuple(sorted({p.parent for p in files if p.suffix in {".h", ".hpp"}}))

    info_files = sorted(folder.glob("*.info"))
    info_text = "\n".join(p.read_text(errors="replace") for p in info_files)
    # Without a .info file, the copy-in/copy-out lines of the sources carry the names.
    signal_text = info_text or "\n".join(texts.values())
    inputs, outputs = _parse_signals(signal_text, folder)

    step_size_s = None
    m = _STEP_INFO_RE.search(info_text) or _STEP_SRC_RE.search("\n".join(texts.values()))
    if m:
        step_size_s = float(m.group(1))
    parameters: dict[str, tuple[int, float]] = {}

    def literal(text: str) -> float:
        """A number, or a quotient of two (``1.0 / 19.0``); NaN for anything else."""
        try:
            parts = [float(x) for x in text.split("/")]
        except ValueError:
            return float("nan")
        return parts[0] / parts[1] if len(parts) == 2 else parts[0] if len(parts) == 1 else float("nan")

    for text in texts.values():
        for index, value, name in _PARAM_RE.findall(text):
            parameters.setdefault(name, (int(index), literal(value)))
    return TwentySimInfo(
        path=folder,
        parameters=tuple((name, index, default) for name, (index, default) in parameters.items()),
        name=class_name or folder.name,
        template=template,
        input_names=inputs,
        output_names=outputs,
        step_size_s=step_size_s,
        sources=sources,
        include_dirs=include_dirs,
        header=header,
        prefix=prefix or "",
    )


_C_INIT_DEF_RE = re.compile(r"^\s*void\s+(\w*?)XXInitializeSubmodel\s*\([^;]*$", re.MULTILINE)


def _exports(folder: Path, texts: dict[Path, str]) -> list[str]:
    """Folders (relative to ``folder``) that each hold one export: a Submodel20sim class or an
    XXInitializeSubmodel definition."""
    found: set[Path] = set()
    for p, text in texts.items():
        is_class = p.suffix in {".h", ".hpp"} and _CLASS_RE.search(text)
        if is_class or (p.suffix == ".c" and _C_INIT_DEF_RE.search(text)):
            found.add(p.parent)
    return sorted(str(p.relative_to(folder)) or "." for p in found)


def _parse_signals(text: str, folder: Path) -> tuple[tuple[str, ...], tuple[str, ...]]:
    names: dict[str, dict[int, str]] = {"u": {}, "y": {}}
    for kind, index, name in _SIGNAL_RE.findall(text):
        names[kind].setdefault(int(index), name or f"{kind}{index}")
    result = []
    for kind in ("u", "y"):
        found = names[kind]
        n = max(found) + 1 if found else 0
        missing = [i for i in range(n) if i not in found]
        if missing:
            raise ModelError(f"{str(folder)!r}: no name for {kind}{missing} in the .info file")
        result.append(tuple(found[i] for i in range(n)))
    return result[0], result[1]


_NUMBER_TYPES = {"XXDouble", "XXBoolean", "XXInteger", "XXFloat", "bool", "int", "double", "float", "long", "short",
                 "char", "unsigned", "signed"}
_STRUCTURAL_TYPES = {"XXMatrix"}
"""20-sim's matrices: pointers into the arrays and their sizes, set when the model is built, never changed."""
_SINGLE_STEP_METHODS = {"Discrete", "Euler", "RungeKutta2", "RungeKutta4"}
"""20-sim's integration methods that keep nothing from one step to the next (scratch only)."""
_NEW_ARRAY_RE = re.compile(r"\b(\w+)\s*=\s*new\s+XXDouble\s*\[\s*([^\]]+?)\s*\]")
_SIZE_EXPR_RE = re.compile(r"^[\w\s+*()-]+$")
_MEMBER_RE = re.compile(r"^[ \t]*((?:unsigned\s+|signed\s+)?[A-Za-z_]\w*)[ \t]+([^;(){}\n]+);", re.MULTILINE)
_C_GLOBAL_RE = re.compile(r"^((?:static\s+)?(?:const\s+)?(?:unsigned\s+|signed\s+)?[A-Za-z_]\w*)\s+"
                          r"([A-Za-z_]\w*)\s*(\[[^\]]*\])?\s*(?:=[^;]*)?;", re.MULTILINE)


@dataclass(frozen=True)
class StateLayout:
    """What makes up a 20-sim model's state, read from its sources (see the module's docstring)."""

    arrays: tuple[tuple[str, str], ...] = ()
    """C++: (member, C++ expression of its length) of each ``new XXDouble[...]`` array."""
    members: tuple[str, ...] = ()
    """C++: number members (copied whole, ``sizeof``); ANSI-C: the globals."""
    refused: str = ""
    """Why the state cannot be saved ("" : it can)."""


def _class_body(text: str, name: str) -> str | None:
    """The text between the braces of ``class name ... {`` (None: not in ``text``)."""
    found = re.search(rf"\bclass\s+{re.escape(name)}\b[^;{{]*\{{", text)
    if found is None:
        return None
    depth, start = 1, found.end()
    for index in range(start, len(text)):
        depth += {"{": 1, "}": -1}.get(text[index], 0)
        if depth == 0:
            return text[start:index]
    return None


def _without_comments(text: str) -> str:
    return re.sub(r"//[^\n]*", "", re.sub(r"/\*.*?\*/", " ", text, flags=re.DOTALL))


def _without_bodies(text: str) -> str:
    """``text`` with every ``{...}`` (function bodies, initialisers) replaced by ``;``, innermost first."""
    while True:
        flat = re.sub(r"\{[^{}]*\}", ";", text)
        if flat == text:
            return flat
        text = flat


def state_layout(info: TwentySimInfo) -> StateLayout:
    """The arrays and numbers that hold ``info``'s state, or why rtloop cannot copy it."""
    texts = {p: _without_comments(p.read_text(errors="replace")) for p in sorted(info.path.rglob("*"))
             if p.suffix in SOURCE_SUFFIXES and p.is_file()}
    if info.template == "c":
        return _c_state_layout(info, texts)
    bodies = [body for text in texts.values() for name in (info.name, "Submodel20sim")
              if (body := _class_body(text, name)) is not None]
    enums = {name for body in bodies for name in re.findall(r"\benum\s+(\w+)", body)}
    pointers: set[str] = set()
    members: list[str] = []
    for body in bodies:
        body = re.sub(r"\benum\s+\w*\s*\{[^}]*\}\s*;", " ", body)  # the enum's own declaration
        body = _without_bodies(re.sub(r"\b(?:public|protected|private)\s*:", " ", body))
        for kind, names in _MEMBER_RE.findall(body):
            if kind in ("typedef", "friend", "return", "using", "static", "const", "virtual", "enum", "struct", "class",
                        "union"):
                continue
            for declared in names.split(","):
                declared = declared.strip()
                name = re.sub(r"\[.*", "", declared).lstrip("*& ").strip()
                if "*" in declared or "&" in declared:
                    pointers.add(name)
                elif kind in _NUMBER_TYPES or kind in enums:
                    members.append(name)
                elif kind in _STRUCTURAL_TYPES or kind in _SINGLE_STEP_METHODS:
                    continue
                else:
                    return StateLayout(refused=f"member {name} of type {kind} is not a number rtloop can copy")
    arrays: dict[str, str] = {}
    for path in info.sources:
        for name, size in _NEW_ARRAY_RE.findall(texts.get(path, "")):
            if name not in pointers:
                continue
            if not _SIZE_EXPR_RE.match(size):
                return StateLayout(refused=f"the length of array {name} ({size}) is not an expression rtloop reads")
            arrays.setdefault(name, size)
    if not arrays:
        return StateLayout(refused="no XXDouble array allocated by its constructor was found (m_s = new XXDouble[...])")
    return StateLayout(tuple(arrays.items()), tuple(dict.fromkeys(members)))


def _c_state_layout(info: TwentySimInfo, texts: dict[Path, str]) -> StateLayout:
    names = []
    for path in info.sources:
        for kind, name, _size in _C_GLOBAL_RE.findall(_without_bodies(texts.get(path, ""))):
            words = kind.split()
            base = words[-1]
            if "const" in words or base in ("return", "typedef", "extern", "struct", "void"):
                continue
            if base in _STRUCTURAL_TYPES:
                continue
            if base not in _NUMBER_TYPES:
                return StateLayout(refused=f"global {name} of type {base} is not a number rtloop can copy")
            if "static" in words:
                return StateLayout(refused=f"static {name} in {path.name} is not reachable from outside the library")
            names.append(name)
    if not names:
        return StateLayout(refused="no global number was found in its sources (xx_time, xx_s[], ...)")
    return StateLayout(members=tuple(dict.fromkeys(names)))


def _state_shim(info: TwentySimInfo, layout: StateLayout) -> tuple[str, str]:
    """(member function of RtloopModel, extern "C" entry point) that copy the state of a C++ model."""
    if layout.refused or info.template != "cpp":
        return "", ""
    copies = [f"RTLOOP_COPY({name}, sizeof(XXDouble) * (size_t)({size}))" for name, size in layout.arrays]
    copies += [f"RTLOOP_COPY(&{name}, sizeof({name}))" for name in layout.members]
    body = "\n        ".join(copies)
    member = f"""    /* the state (rtloop.models.twentysim): copied out (out != NULL) or in (in != NULL); its size */
    size_t rtloop_state(char *out, const char *in)
    {{
        size_t n = 0;
#define RTLOOP_COPY(p, bytes) {{ \\
    if (out) memcpy(out + n, (p), (bytes)); if (in) memcpy((p), in + n, (bytes)); n += (bytes); }}
        {body}
#undef RTLOOP_COPY
        return n;
    }}
"""
    entry = "size_t rtloop_state(void *m, char *out, const char *in) { return M(m)->rtloop_state(out, in); }\n"
    return member, entry


def _shim_source(info: TwentySimInfo, with_state: bool = True) -> str:
    """The generated ``extern "C"`` entry points (``rtloop_*``) for one model."""
    if info.template == "cpp":
        assert info.header is not None
        state_member, state_entry = _state_shim(info, state_layout(info)) if with_state else ("", "")
        return f"""/* generated by rtloop: C entry points for the 20-sim model {info.name} */
#include <cstring>
#include "{info.header.name}"

namespace {{
/* Derived only to read the protected step size. */
struct RtloopModel : public {info.name} {{
    XXDouble rtloop_step_size(void) {{ return m_step_size; }}
    void rtloop_set_parameter(int i, XXDouble v) {{ m_P[i] = v; }}
    /* after Initialize set new parameters: evaluate the equations again, as Initialize does */
    void rtloop_reevaluate(XXDouble *y)
    {{ CalculateStatic(); CalculateInput(); CalculateDynamic(); CalculateOutput(); CopyVariablesToOutputs(y); }}
{state_member}}};
inline RtloopModel *M(void *m) {{ return static_cast<RtloopModel *>(m); }}
}}

extern "C" {{
void *rtloop_new(void) {{ return new RtloopModel(); }}
void rtloop_delete(void *m) {{ delete M(m); }}
void rtloop_initialize(void *m, XXDouble *u, XXDouble *y, XXDouble t)
{{ M(m)->Initialize(u, y, t); }}
void rtloop_calculate(void *m, XXDouble *u, XXDouble *y) {{ M(m)->Calculate(u, y); }}
void rtloop_terminate(void *m, XXDouble *u, XXDouble *y) {{ M(m)->Terminate(u, y); }}
int rtloop_set_finish_time(void *m, XXDouble t) {{ return M(m)->SetFinishTime(t) ? 1 : 0; }}
int rtloop_is_finished(void *m) {{ return M(m)->IsFinished() ? 1 : 0; }}
void rtloop_reset(void *m, XXDouble t) {{ M(m)->Reset(t); }}
XXDouble rtloop_step_size(void *m) {{ return M(m)->rtloop_step_size(); }}
void rtloop_set_parameter(void *m, int i, XXDouble v) {{ M(m)->rtloop_set_parameter(i, v); }}
void rtloop_reevaluate(void *m, XXDouble *y) {{ M(m)->rtloop_reevaluate(y); }}
{state_entry}}}
"""
    p = info.prefix
    return f"""/* generated by rtloop: C entry points for the 20-sim ANSI-C model {info.name} */
/* 20-sim's XXDouble is double; the state is global, the handle is a dummy. */
extern double {p}xx_step_size;
extern double {p}xx_time;
extern double {p}xx_finish_time;
void {p}XXInitializeSubmodel(double *u, double *y, double t);
void {p}XXCalculateSubmodel(double *u, double *y, double t);
void {p}XXTerminateSubmodel(double *u, double *y, double t);

static int rtloop_instance;
void *rtloop_new(void) {{ return &rtloop_instance; }}
void rtloop_delete(void *m) {{ (void)m; }}
void rtloop_initialize(void *m, double *u, double *y, double t)
{{ (void)m; {p}XXInitializeSubmodel(u, y, t); }}
void rtloop_calculate(void *m, double *u, double *y)
{{ (void)m; {p}XXCalculateSubmodel(u, y, {p}xx_time); }}
void rtloop_terminate(void *m, double *u, double *y)
{{ (void)m; {p}XXTerminateSubmodel(u, y, {p}xx_time); }}
int rtloop_set_finish_time(void *m, double t) {{ (void)m; {p}xx_finish_time = t; return 1; }}
int rtloop_is_finished(void *m)
{{
    (void)m;
    return {p}xx_finish_time > 0.0 && {p}xx_time >= {p}xx_finish_time - 0.5 * {p}xx_step_size;
}}
void rtloop_reset(void *m, double t) {{ (void)m; {p}xx_time = t; }}
double rtloop_step_size(void *m) {{ (void)m; return {p}xx_step_size; }}
"""


def _compiler(info: TwentySimInfo) -> str:
    name = os.environ.get("CXX", "g++") if info.template == "cpp" else os.environ.get("CC", "gcc")
    found = shutil.which(name)
    if found is None:
        raise ModelError(
            f"cannot build 20-sim model {str(info.path)!r}: compiler {name!r} not found "
            "(Debian/Raspberry Pi OS: apt install build-essential)"
        )
    return found


def _build_key(info: TwentySimInfo, compiler: str, flags: tuple[str, ...], shim: str) -> str:
    digest = hashlib.sha256()
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True).stdout
    for part in (compiler, version, " ".join(flags), shim):
        digest.update(part.encode() + b"\0")
    for p in sorted(info.path.rglob("*")):
        if p.suffix in SOURCE_SUFFIXES and p.is_file():
            digest.update(str(p.relative_to(info.path)).encode() + b"\0")
            digest.update(p.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def build_library(
    info: TwentySimInfo,
    cache_dir: str | os.PathLike[str] | None = None,
    extra_flags: tuple[str, ...] = (),
) -> Path:
    """Compile the model and its shim into a shared library; return its path (cached).

    Raises :class:`~rtloop.models.base.ModelBuildError` with the compiler's output.
    """
    compiler = _compiler(info)
    base_flags = CXX_FLAGS if info.template == "cpp" else C_FLAGS
    flags = (*base_flags, *extra_flags)
    shim = _shim_source(info)
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    library = cache / f"{info.name}-{info.template}-{_build_key(info, compiler, flags, shim)}.so"
    if library.exists():
        foreign = _foreign_cache(library)
        if foreign:
            raise ModelError(f"{foreign}; rtloop will not load it (remove it, or point RTLOOP_CACHE_DIR at a "
                             "folder of your own)")
        return library
    cache.mkdir(parents=True, exist_ok=True)
    try:
        _compile(info, compiler, flags, shim, library)
    except ModelBuildError as error:
        plain = _shim_source(info, with_state=False)
        if plain == shim:
            raise
        # the state copy did not compile for this export: the model still runs, its state is not saved
        _compile(info, compiler, flags, plain, library)
        first = next((line for line in error.compiler_output.splitlines() if "error" in line), "")
        _state_note(library).write_text(f"the generated copy of its state did not compile ({first.strip()})")
    return library


def _foreign_cache(library: Path) -> str | None:
    """Why a cached library may be another user's (None: it is not): it, or its folder, is theirs or
    writable by them (a sticky folder aside). Its name is a hash anyone can compute."""
    trusted = trusted_uids()
    whom = trusted_users_phrase()
    for path, facts in ((library, os.lstat(library)), (library.parent, os.stat(library.parent))):
        if facts.st_uid not in trusted:
            return f"{path} is owned by uid {facts.st_uid}, not by {whom}"
        if stat.S_ISDIR(facts.st_mode) and facts.st_mode & stat.S_ISVTX:
            continue  # sticky: nobody replaces what is not theirs
        writer = untrusted_writer(facts, trusted, whom, path)  # a private group is fine
        if writer:
            return f"{path} is {writer}"
    return None


def _state_note(library: Path) -> Path:
    """Beside a library built without its state copy: why."""
    return library.with_name(library.name + ".no-state")


def _compile(info: TwentySimInfo, compiler: str, flags: tuple[str, ...], shim: str, library: Path) -> None:
    cache = library.parent
    with tempfile.TemporaryDirectory(dir=cache, prefix=".build-") as tmp:
        shim_path = Path(tmp) / ("rtloop_shim.cpp" if info.template == "cpp" else "rtloop_shim.c")
        shim_path.write_text(shim)
        output = Path(tmp) / library.name
        command = [
            compiler,
            *flags,
            *(f"-I{d}" for d in info.include_dirs),
            *(str(s) for s in info.sources),
            str(shim_path),
            "-o",
            str(output),
            "-lm",
        ]
        done = subprocess.run(command, capture_output=True, text=True, cwd=info.path)
        if done.returncode != 0:
            output_text = done.stdout + done.stderr
            raise ModelBuildError(str(info.path), command, _explain_undefined(info, output_text) + output_text)
        try:
            ctypes.CDLL(str(output))  # load it once here: what builds must also load
        except OSError as error:
            raise ModelBuildError(str(info.path), command, f"the library built but does not load: {error}\n") from None
        os.replace(output, library)  # atomic: concurrent builds of one model are harmless


_UNDEFINED_RE = re.compile(r"undefined reference to [`'‘]([^'’`]+)['’`]")


def _explain_undefined(info: TwentySimInfo, compiler_output: str) -> str:
    """A first line naming undefined symbols (demangled by the linker) and the file likely missing."""
    symbols = list(dict.fromkeys(_UNDEFINED_RE.findall(compiler_output)))
    if not symbols:
        return ""
    present = {p.stem for p in info.sources}
    missing = []
    for symbol in symbols:
        owner = symbol.split("::")[0].split("(")[0].strip()
        if owner and owner not in present and owner not in missing:
            missing.append(owner)
    suffix = ".cpp" if info.template == "cpp" else ".c"
    hint = (f"; the export seems to lack {', '.join(f'common/{m}{suffix}' for m in missing)}"
            " (copy it from 20-sim's code generation templates)" if missing else "")
    return f"undefined symbols: {', '.join(symbols[:5])}{hint}\n"


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
                note = _state_note(Path(library))
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
