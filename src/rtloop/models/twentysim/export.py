"""Reading a 20-sim export without compiling it: which template (C++ class derived from
``Submodel20sim``, or ANSI-C ``XXInitializeSubmodel`` functions with an optional prefix), the signal
names of the ``.info`` file, the parameters, the step size, and where the model keeps its state
(:class:`StateLayout`)."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from rtloop.models.base import ModelError

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
