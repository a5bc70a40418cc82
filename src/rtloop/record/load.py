"""``rtloop.load(RUN_DIR)``: a run directory as numpy arrays, for scripts, notebooks and the report.

    run = rtloop.load("runs/jiwy")
    run.signals["plant.AnglePan"]         # float64 array, one value per row of signals.csv
    run.signals.t_s                       # the time from which each row holds (decision 10)
    run.signals.units["plant.AnglePan"]   # "rad" where the model declares it
    run.timing["plant"].release_ns        # int64 arrays: cycle, release_ns, start_ns, end_ns
    run.inputs["setpoint"].values         # what entered through a live port, and when
    run.signals.to_pandas()               # a DataFrame indexed by t_s (pip install 'rtloop[pandas]')

Files are read in blocks of :data:`BLOCK_BYTES` and parsed by numpy, never one Python
object per row. A recording larger than ``memory_limit_bytes`` is parsed into an unnamed
temporary file and memory-mapped, so a day at 1 kHz loads with the memory of one block
(the figures are in BENCHMARKS.md). A run that was killed is loaded as far as it got: the
flight recorder's segments that were never joined are read in order, a last line cut in
half is left out and said so in :attr:`RunData.problems`.

Gaps stay gaps: an empty cell or ``nan`` is NaN, and rows that are missing altogether
(a pruned flight-recorder segment, signals the recorder had to drop) are listed in
:attr:`Signals.gaps` so plots break the line there instead of drawing across.
"""

from __future__ import annotations

import difflib
import math
import os
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from rtloop.errors import RtloopError
from rtloop.record.jsonfile import parse_json
from rtloop.stats.timing import TimingSamples
from rtloop.text import shorten

BLOCK_BYTES = 8 << 20
"""How much of a file is parsed at once."""
MEMORY_LIMIT_BYTES = 256 << 20
"""Files larger than this are parsed into a memory-mapped temporary file, not into memory."""
TIMING_HEADER = b"task,cycle,release_ns,start_ns,end_ns"
INPUTS_HEADER = b"task,cycle,port,values"
TIME_COLUMN = "t_s"
"""signals.csv's first column: the time from which each row holds."""
SIDECAR = "signals.json"
"""Units, model names and plot groups of signals.csv's columns (written beside it)."""
SEGMENTS_DIR = "segments"

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class LoadError(RtloopError, ValueError):
    """A run directory cannot be loaded (missing, or without a readable summary.json)."""


# --- the records ------------------------------------------------------------------------------
class Signals(Mapping[str, FloatArray]):
    """``signals.csv``: a mapping from column name to its values, with the row times beside.

    ``signals["plant.omega"]`` is a float64 array with one value per row; NaN where the
    signal has no value (not computed yet, or a gap in the recording). ``signals["t_s"]``, the
    file's first column, is :attr:`t_s` (it is not among the names: it is no signal).
    """

    def __init__(self, t_s: FloatArray, names: tuple[str, ...], table: FloatArray,
                 units: dict[str, str] | None = None, gaps: FloatArray | None = None,
                 plots: tuple[Plot, ...] = ()) -> None:
        self.t_s = t_s
        """Time from which each row holds, seconds since T0."""
        self.names = names
        """Column names in file order (``plant.omega``, ``pi.y[0]``, ...)."""
        self.table = table
        """All values as one rows × signals float64 array (memory-mapped for large runs)."""
        self.units = units or {}
        """Column name → unit (``rad/s``), for the signals whose model or runnable declares one."""
        self.gaps = gaps if gaps is not None else np.zeros((0, 2))
        """Rows missing from the recording: an n × 2 array of (last time before, first time after)."""
        self.plots = plots
        """Plot groups declared by the app (``[[plot]]``), by column name."""
        self._index = {name: i for i, name in enumerate(names)}

    def __getitem__(self, name: str) -> FloatArray:
        index = self._index.get(name)
        if index is None:
            if name == TIME_COLUMN:  # signals.csv's first column: the same array as the attribute
                return self.t_s
            close = difflib.get_close_matches(str(name), [*self.names, TIME_COLUMN], n=1, cutoff=0.5)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise KeyError(f"no signal {shorten(name)}; {hint}signals are {shorten(list(self.names), 400)}")
        return self.table[:, index]

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def rows(self) -> int:
        """Number of rows (times)."""
        return int(self.t_s.size)

    @property
    def columns(self) -> dict[str, FloatArray]:
        """Every column by name (views into :attr:`table`, no copies)."""
        return {name: self[name] for name in self.names}

    def unit(self, name: str) -> str:
        """The unit of ``name`` ('' when none is declared)."""
        return self.units.get(name, "")

    def to_pandas(self) -> Any:
        """A ``pandas.DataFrame`` indexed by ``t_s``, one column per signal (needs pandas)."""
        try:
            import pandas
        except ModuleNotFoundError:
            raise ModuleNotFoundError("Signals.to_pandas needs pandas: pip install 'rtloop[pandas]'",
                                      name="pandas") from None
        frame = pandas.DataFrame(np.asarray(self.table), columns=list(self.names),
                                 index=pandas.Index(np.asarray(self.t_s), name="t_s"))
        frame.attrs["units"] = dict(self.units)
        return frame

    def __repr__(self) -> str:
        return f"<Signals: {self.rows} rows × {len(self.names)} signals {list(self.names)[:6]}>"


@dataclass(frozen=True)
class Plot:
    """A plot the app declares: these signals on one axis (``[[plot]]`` / ``app.plot``)."""

    title: str
    """The plot's title (by default its signals, joined)."""
    signals: tuple[str, ...]
    """Column names of signals.csv, overlaid in this order."""
    setpoint: str | None = None
    """For a setpoint/measured pair: the setpoint's column (the other signal is what it sets)."""
    inferred: bool = False
    """Found from the app's wiring (a setpoint port beside a connection), not declared."""
    limits: bool = False
    """A device command: what it was sent (after its limits) beside what the controller asked for
    (``setpoint``); the report shades where the two differ (a limit acted)."""


@dataclass(frozen=True)
class PortInputs:
    """Values that entered through one live input port (``inputs.csv``), in the order taken."""

    task: str
    """The task the port feeds."""
    cycle: IntArray
    """The cycle of the task that took each value."""
    t_s: FloatArray
    """The release time of that cycle, seconds since T0 (where the value took effect)."""
    values: FloatArray
    """One row per value taken, one column per element of the port."""


class InputsByPort(dict[str, "PortInputs"]):
    """``run.inputs``: a dict of the ports that took live values; asked for another, it says why not."""

    def __init__(self, found: dict[str, PortInputs], ports: dict[str, Any]) -> None:
        super().__init__(found)
        self._ports = ports if isinstance(ports, dict) else {}

    def __missing__(self, name: str) -> PortInputs:
        port = self._ports.get(name)
        written = f"ports with live values in this run: {sorted(self)}" if self else "no port took a live value"
        if not isinstance(port, dict):
            inputs = sorted(n for n, p in self._ports.items() if isinstance(p, dict) and p.get("direction") == "in")
            raise KeyError(f"no input port {name!r} in this run (its input ports: {inputs}); {written}")
        if port.get("direction") != "in":
            raise KeyError(f"port {name!r} is an output port ({port.get('signal')}): it takes no values; {written}")
        feed = port.get("feed") if isinstance(port.get("feed"), dict) else None
        if feed is not None and not feed.get("nudge"):
            raise KeyError(f"port {name!r} was fed from {feed.get('file')}, not written live: its values are in "
                           f"run.signals ({port.get('signal')}); {written}")
        raise KeyError(f"port {name!r} took no live value in this run (rtloop port write, Python, ROS 2 or "
                       f"Foxglove write there); {written}")


@dataclass(frozen=True)
class RunData:
    """One run directory, loaded: what :func:`load` returns."""

    path: Path
    """The run directory."""
    summary: dict[str, Any]
    """``summary.json`` as parsed (see docs/architecture.md for its fields)."""
    signals: Signals | None
    """``signals.csv`` (None when the app recorded no signal)."""
    timing: dict[str, TimingSamples]
    """Per task: ``cycle``, ``release_ns``, ``start_ns``, ``end_ns`` of every recorded cycle (int64)."""
    inputs: dict[str, PortInputs]
    """Per input port that took live values: those values and when (``inputs.csv``); another port's
    name raises a KeyError saying why it has none (a profile fed it, nothing was written, no such port)."""
    problems: list[str] = field(default_factory=list)
    """What loading found wrong or incomplete (a cut last line, rows that disagree with the summary)."""

    @property
    def notes(self) -> list[str]:
        """The summary's notes, then :attr:`problems`."""
        return [str(n) for n in self.summary.get("notes") or []] + self.problems

    @property
    def failure(self) -> dict[str, Any] | None:
        """The failure that stopped the run, if any (task, cycle, phase, reason, traceback)."""
        return self.summary.get("failure")

    @property
    def mode(self) -> str:
        """``run`` or ``simulate``."""
        return str(self.summary.get("mode", "run"))

    @property
    def tasks(self) -> dict[str, dict[str, Any]]:
        """Per-task entries of ``summary.json``."""
        tasks: dict[str, dict[str, Any]] = self.summary.get("tasks", {})
        return tasks

    def __repr__(self) -> str:
        return (f"<RunData {self.path}: {self.mode}, tasks {list(self.tasks)}, "
                f"{self.signals.rows if self.signals is not None else 0} signal rows>")


# --- loading ----------------------------------------------------------------------------------
def load(run_dir: str | os.PathLike[str], *, memory_limit_bytes: int = MEMORY_LIMIT_BYTES) -> RunData:
    """Load the run directory ``run_dir`` (the ``--out`` of ``rtloop run``/``simulate``)."""
    path = Path(run_dir)
    if not path.is_dir():
        raise LoadError(f"{path}: no such run directory")
    summary_path = path / "summary.json"
    if not summary_path.is_file():
        raise LoadError(f"{path}: no summary.json (is this the --out directory of `rtloop run`?)")
    try:
        summary = parse_json(summary_path.read_text())
    except (OSError, ValueError) as error:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise LoadError(f"{summary_path}: unreadable: {error}") from None
    if not isinstance(summary, dict) or not isinstance(summary.get("tasks"), dict):
        raise LoadError(f"{summary_path}: no 'tasks' object; not an rtloop summary")
    problems: list[str] = []
    spill = _SpillPlace(path, memory_limit_bytes)
    if summary.get("running"):
        problems.append("summary.json is the one rewritten during the run: the run did not end normally "
                        "(killed, or still running); the files hold what was written until then")
    timing = _load_timing(_parts(path, "timing.csv", problems), list(summary["tasks"]), spill, problems)
    for name, task in summary["tasks"].items():
        recorded = len(timing[name]) if name in timing else 0
        counted = task.get("cycles") if isinstance(task, dict) else None
        if isinstance(counted, int) and recorded != counted and not summary.get("recording", {}).get("keep_s"):
            problems.append(f"task {name}: timing.csv has {recorded} rows but summary.json counts {counted} cycles")
    signals = _load_signals(path, summary, spill, problems)
    inputs = InputsByPort(_load_inputs(_parts(path, "inputs.csv", problems), summary, problems),
                          summary.get("ports") or {})
    return RunData(path, summary, signals, timing, inputs, problems)


class _SpillPlace:
    """Where large arrays go: an unnamed temporary file in the run directory (else the temp folder)."""

    def __init__(self, run_dir: Path, memory_limit_bytes: int) -> None:
        self.run_dir, self.limit = run_dir, memory_limit_bytes

    def wanted(self, parts: list[Path]) -> bool:
        return sum(p.stat().st_size for p in parts) > self.limit

    def file(self) -> IO[bytes]:
        # An unnamed file (O_TMPFILE where the file system has it): nothing is left behind,
        # and nothing another user planted in the folder is ever opened.
        for folder in (self.run_dir, None):
            try:
                return tempfile.TemporaryFile(dir=folder)
            except OSError:
                continue
        raise LoadError(f"{self.run_dir}: no room for a temporary file to load a large recording into")


class _Rows:
    """Collects parsed blocks of an n × width array: in memory, or appended to a spill file."""

    def __init__(self, width: int, dtype: type, spill: IO[bytes] | None) -> None:
        self.width, self.dtype, self.spill = width, np.dtype(dtype), spill
        self.blocks: list[np.ndarray] = []
        self.count = 0

    def add(self, block: np.ndarray) -> None:
        if not block.size:
            return
        self.count += block.shape[0]
        if self.spill is not None:
            self.spill.write(np.ascontiguousarray(block, dtype=self.dtype).tobytes())
        else:
            self.blocks.append(block)

    def array(self) -> np.ndarray:
        if self.spill is None:
            if not self.count:
                return np.zeros((0, self.width), dtype=self.dtype)
            return np.concatenate(self.blocks).astype(self.dtype, copy=False)
        with self.spill:  # the mapping outlives the file object; the file goes when both are gone
            if not self.count:
                return np.zeros((0, self.width), dtype=self.dtype)
            self.spill.flush()
            return np.memmap(self.spill, dtype=self.dtype, mode="r", shape=(self.count, self.width))


def _parts(path: Path, name: str, problems: list[str]) -> list[Path]:
    """``name`` and, after a run that was killed with ``--keep``, its segments not yet joined, in order."""
    parts = [path / name] if (path / name).is_file() else []
    segments = path / SEGMENTS_DIR
    if segments.is_dir():
        pieces = sorted(p for p in segments.iterdir() if p.name.endswith(f"-{name}") and p.is_file())
        if pieces:
            problems.append(f"{name}: read from {len(pieces)} flight-recorder segment(s) in {SEGMENTS_DIR}/ that "
                            "were never joined (the run was killed)")
        parts += pieces
    return parts


def _blocks(paths: list[Path], header: bytes | None, problems: list[str]) -> Iterator[tuple[str, int, bytes]]:
    """(file, number of the block's first line, whole lines) of each part, its header line skipped.

    A last line without its newline (a writer killed mid-line) is left out and reported.
    """
    for part in paths:
        with open(part, "rb") as file:
            first = file.readline()
            if not first:
                continue  # created, nothing written yet
            if header is not None and first.rstrip(b"\r\n") != header:
                problems.append(f"{part.name}: unexpected header {shorten(first)}; file skipped")
                continue
            line, rest = 2, b""
            while block := file.read(BLOCK_BYTES):
                block = rest + block
                cut = block.rfind(b"\n") + 1
                rest = block[cut:]
                if cut:
                    yield part.name, line, block[:cut]
                    line += block.count(b"\n", 0, cut)
            if rest.strip():
                problems.append(f"{part.name} line {line}: the last line is incomplete (the writer stopped "
                                "mid-line); left out")


def _parse_block(block: bytes, width: int, dtype: type, where: str, first_line: int,
                 problems: list[str]) -> np.ndarray:
    """Whole CSV lines of numbers → an n × width array; bad lines are left out and reported."""
    # Empty cells are values that are not there: NaN (ints never have them).
    text = block.replace(b"\r", b"")
    if dtype is np.float64 and (b",," in text or b",\n" in text or text.startswith(b",")):
        text = b"\n" + text
        for _ in range(2):  # ",,," needs two passes: the matches overlap
            text = text.replace(b",,", b",nan,")
        text = text.replace(b",\n", b",nan\n").replace(b"\n,", b"\nnan,")[1:]
    lines = text.count(b"\n")
    values = _numbers(text[:-1].replace(b"\n", b","), dtype)
    if values is not None and values.size == lines * width:
        return values.reshape(lines, width)
    good, bad = [], []
    for number, line in enumerate(text.split(b"\n")[:-1], start=first_line):  # the slow path: bad input only
        row = _numbers(line, dtype)
        if row is not None and row.size == width:
            good.append(row)
        else:
            bad.append((number, line))
    if bad:
        number, line = bad[0]
        more = f" and {len(bad) - 1} more line(s) of this block" if len(bad) > 1 else ""
        problems.append(f"{where} line {number}: not {width} numbers ({shorten(line, 60)}){more}; left out")
    return np.array(good, dtype=dtype).reshape(-1, width)


def _numbers(text: bytes, dtype: type) -> np.ndarray | None:
    if not text:
        return np.zeros(0, dtype=dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return np.fromstring(text, dtype=dtype, sep=",")
        except (ValueError, DeprecationWarning, OverflowError):
            return None


def _load_timing(parts: list[Path], tasks: list[str], spill: _SpillPlace,
                 problems: list[str]) -> dict[str, TimingSamples]:
    if not parts:
        problems.append("no timing.csv: no timing")
        return {}
    # Task names become their index in summary.json, so that each block is one numeric array.
    codes = [(b"\n" + name.encode() + b",", b"\n" + str(i).encode() + b",") for i, name in enumerate(tasks)]
    rows = [_Rows(4, np.int64, spill.file() if spill.wanted(parts) else None) for _ in tasks]
    # Checked block by block, so that a memory-mapped result is never read through here.
    last_cycle = [-1] * len(tasks)
    in_order = [True] * len(tasks)
    for where, line, block in _blocks(parts, TIMING_HEADER, problems):
        coded = b"\n" + block
        for named, code in codes:
            coded = coded.replace(named, code)
        table = _parse_block(coded[1:], 5, np.int64, where, line, problems)
        task_codes = table[:, 0]
        for i, task_rows in enumerate(rows):
            records = table[task_codes == i, 1:]
            if records.shape[0]:
                cycles = records[:, 0]
                in_order[i] &= bool(cycles[0] > last_cycle[i]) and not np.any(np.diff(cycles) <= 0)
                last_cycle[i] = int(cycles[-1])
            task_rows.add(records)
    out: dict[str, TimingSamples] = {}
    for i, (name, task_rows) in enumerate(zip(tasks, rows, strict=True)):
        records = task_rows.array()
        if not in_order[i]:  # a recording joined from segments in another order: sort (in memory)
            records = records[np.argsort(records[:, 0], kind="stable")]
        out[name] = TimingSamples(records[:, 0], records[:, 1], records[:, 2], records[:, 3])
    if not any(len(t) for t in out.values()):
        problems.append("timing.csv has no rows: the run recorded no cycle")
    return out


def _load_signals(path: Path, summary: dict[str, Any], spill: _SpillPlace, problems: list[str]) -> Signals | None:
    parts = _parts(path, "signals.csv", problems)
    if not parts:
        return None
    with open(parts[0], "rb") as file:
        header = file.readline().rstrip(b"\r\n").decode("utf-8", "replace").split(",")
    if header[0] != "t_s" or len(header) < 2:
        problems.append(f"signals.csv: unexpected header {shorten(','.join(header))}; signals not loaded")
        return None
    names = tuple(header[1:])
    rows = _Rows(len(header), np.float64, spill.file() if spill.wanted(parts) else None)
    gaps = _Gaps(summary)
    for where, line, block in _blocks(parts, ",".join(header).encode(), problems):
        table = _parse_block(block, len(header), np.float64, where, line, problems)
        gaps.add(table[:, 0])
        rows.add(table)
    table = rows.array()
    sidecar = _read_sidecar(path, names, problems)
    return Signals(table[:, 0], names, table[:, 1:], units=sidecar[0], gaps=gaps.array(), plots=sidecar[1])


class _Gaps:
    """Where rows are missing: consecutive rows further apart than the shortest period.

    Rows are the union of every recorded task's times, so without a gap no two rows are
    further apart than the shortest period. Found block by block, as the rows are parsed.
    """

    def __init__(self, summary: dict[str, Any]) -> None:
        declared = [t.get("period_ns") for t in summary.get("tasks", {}).values() if isinstance(t, dict)]
        periods = [p for p in declared if isinstance(p, int) and p > 0]
        self.limit_s = min(periods) / 1e9 * 1.5 if periods else math.inf
        self.last_s = math.nan
        self.found: list[np.ndarray] = []

    def add(self, t_s: FloatArray) -> None:
        if not t_s.size:
            return
        times = np.concatenate([[self.last_s], t_s]) if self.last_s == self.last_s else t_s
        where = np.flatnonzero(np.diff(times) > self.limit_s)
        if where.size:
            self.found.append(np.stack([times[where], times[where + 1]], axis=1))
        self.last_s = float(t_s[-1])

    def array(self) -> FloatArray:
        return np.concatenate(self.found) if self.found else np.zeros((0, 2))


def _read_sidecar(path: Path, names: tuple[str, ...],
                  problems: list[str]) -> tuple[dict[str, str], tuple[Plot, ...]]:
    """``signals.json``: units per column and the app's plot groups (absent before units existed)."""
    file = path / SIDECAR
    if not file.is_file():
        return {}, ()
    try:
        data = parse_json(file.read_text())
        columns = data.get("columns", {})
        units = {name: str(columns[name]["unit"]) for name in names
                 if isinstance(columns.get(name), dict) and columns[name].get("unit")}
        plots = tuple(Plot(str(p.get("title") or " vs ".join(p["signals"])),
                           tuple(str(s) for s in p["signals"] if s in names),
                           p["setpoint"] if p.get("setpoint") in names else None, bool(p.get("inferred")),
                           bool(p.get("limits")))
                      for p in data.get("plots", []))
    except (OSError, UnicodeDecodeError, ValueError, TypeError, KeyError, AttributeError) as error:
        problems.append(f"{SIDECAR}: unreadable ({type(error).__name__}); signals loaded without units")
        return {}, ()
    return units, tuple(p for p in plots if p.signals)


def _load_inputs(parts: list[Path], summary: dict[str, Any], problems: list[str]) -> dict[str, PortInputs]:
    """``inputs.csv`` (and its segments): one row per value a task took from a live port."""
    if not parts:
        return {}
    periods = {name: t.get("period_ns", 0) for name, t in summary.get("tasks", {}).items() if isinstance(t, dict)}
    collected: dict[str, tuple[str, list[int], list[FloatArray]]] = {}
    for where, line, block in _blocks(parts, INPUTS_HEADER, problems):
        for number, text in enumerate(block.decode("utf-8", "replace").splitlines(), start=line):
            task, cycle, port, values = [*text.split(","), "", "", ""][:4]
            row = _numbers(values.strip().replace(" ", ",").encode(), np.float64)
            if not cycle.isdigit() or row is None or task not in periods:
                problems.append(f"{where} line {number}: not task,cycle,port,values ({shorten(text, 60)}); left out")
                continue
            entry = collected.setdefault(port, (task, [], []))
            entry[1].append(int(cycle))
            entry[2].append(row)
    out: dict[str, PortInputs] = {}
    for port, (task, cycles, rows) in collected.items():
        width = max(r.size for r in rows)
        matrix = np.full((len(rows), width), math.nan)
        for i, r in enumerate(rows):
            matrix[i, : r.size] = r
        cycle_of_row = np.array(cycles, dtype=np.int64)
        out[port] = PortInputs(task, cycle_of_row, cycle_of_row * (periods.get(task) or 0) / 1e9, matrix)
    return out
