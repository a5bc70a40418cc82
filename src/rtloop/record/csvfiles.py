"""``timing.csv`` and ``signals.csv``, written as data arrives (nothing waits for the end).

timing.csv  ``task,cycle,release_ns,start_ns,end_ns``, one row per cycle, appended and
            flushed at every drain, so a crash loses at most the last drain interval.
signals.csv ``t_s`` then one column per recorded signal. A row holds the values valid
            from its time on: outputs of the job released at t appear at t + P, the
            initial outputs at 0 (see :class:`SignalsCsv`); with several periods, rows are
            the union of those times and a slower task's columns hold their last value.
            Values are written with ``repr``: full precision, NaN as ``nan``, ±inf as ``inf``/``-inf``.
"""

from __future__ import annotations

import heapq
from pathlib import Path
from typing import TextIO

import numpy as np

from rtloop.app.builder import SignalRef


class TimingCsv:
    HEADER = "task,cycle,release_ns,start_ns,end_ns\n"

    def __init__(self, path: Path) -> None:
        self.file: TextIO = self._open(path)

    def _open(self, path: Path) -> TextIO:
        file = open(path, "w", buffering=1 << 16)  # noqa: SIM115
        file.write(self.HEADER)
        return file

    def switch_to(self, path: Path) -> None:
        """Go on in a new file (a recording segment), which starts with the header."""
        self.file.close()
        self.file = self._open(path)

    def append(self, task: str, records: np.ndarray) -> None:
        if len(records):
            lines = [f"{task},{c},{r},{s},{e}\n" for c, r, s, e in records.tolist()]
            self.file.writelines(lines)

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()


class InputsCsv:
    """``inputs.csv``: what entered the run from outside, and the cycle that took it.

    ``task,cycle,port,values`` — one row each time a task took a new value from a live
    input port (CLI, Python client, ROS 2 bridge); ``values`` are the port's values,
    space-separated with full precision. ``rtloop replay`` feeds them back at the same
    cycles.
    """

    HEADER = "task,cycle,port,values\n"

    def __init__(self, path: Path) -> None:
        self.file: TextIO = open(path, "w", buffering=1 << 14)  # noqa: SIM115
        self.file.write(self.HEADER)

    def append(self, task: str, period_ns: int, ports: list[tuple[str, int]], ticks: np.ndarray,
               rows: np.ndarray) -> None:
        """``ports[i]`` = (name, size) of the task's input port i; ``ticks`` are ns since T0."""
        for since_t0_ns, row in zip(ticks.tolist(), rows.tolist(), strict=True):
            name, size = ports[int(row[0])]
            values = " ".join(repr(v) for v in row[1 : 1 + size])
            self.file.write(f"{task},{since_t0_ns // period_ns},{name},{values}\n")

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def read_inputs_csv(path: Path) -> list[tuple[str, int, str, list[float]]]:
    """Rows of an ``inputs.csv``: (task, cycle, port, values)."""
    rows = []
    with open(path) as file:
        header = file.readline()
        if header != InputsCsv.HEADER:
            raise ValueError(f"{path}: not an inputs.csv (header {header.strip()!r})")
        for number, line in enumerate(file, start=2):
            parts = line.rstrip("\n").split(",")
            if len(parts) != 4:
                raise ValueError(f"{path}:{number}: expected task,cycle,port,values")
            rows.append((parts[0], int(parts[1]), parts[2], [float(v) for v in parts[3].split()]))
    return rows


NO_STAMP = -(2**62)
"""A read that found no sample at all (the read log's word for it; as in the channels)."""


class ReadsCsv:
    """``reads.csv``: each read of a connection that did not get the sample LET promised.

    ``task,cycle,writer,stamp_ns,due_ns`` — at ``cycle`` the task read ``writer``'s sample
    published with ``stamp_ns`` (ns since T0; empty: none at all, its inputs kept their
    values) instead of the one due at ``due_ns`` (a stale read: the writer was late). A
    clean cycle writes nothing; ``rtloop replay`` makes the task read the same samples.
    """

    HEADER = "task,cycle,writer,stamp_ns,due_ns\n"

    def __init__(self, path: Path) -> None:
        self.file: TextIO = self._open(path)

    def _open(self, path: Path) -> TextIO:
        file = open(path, "w", buffering=1 << 14)  # noqa: SIM115
        file.write(self.HEADER)
        return file

    def switch_to(self, path: Path) -> None:
        """Go on in a new file (a recording segment), which starts with the header."""
        self.file.close()
        self.file = self._open(path)

    def append(self, task: str, period_ns: int, writers: list[str], records: np.ndarray) -> None:
        """``records``: rows of ``[release, writer index, stamp got or NO_STAMP, stamp due]`` (ns since T0)."""
        lines = []
        for release_ns, writer, stamp_ns, due_ns in records.tolist():
            stamp = "" if stamp_ns == NO_STAMP else str(stamp_ns)
            lines.append(f"{task},{release_ns // period_ns},{writers[writer]},{stamp},{due_ns}\n")
        self.file.writelines(lines)

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def read_reads_csv(path: Path) -> list[tuple[str, int, str, int | None, int]]:
    """Rows of a ``reads.csv``: (task, cycle, writer, stamp_ns or None, due_ns)."""
    rows = []
    with open(path) as file:
        header = file.readline()
        if header != ReadsCsv.HEADER:
            raise ValueError(f"{path}: not a reads.csv (header {header.strip()!r})")
        for number, line in enumerate(file, start=2):
            parts = line.rstrip("\n").split(",")
            try:
                if len(parts) != 5:
                    raise ValueError
                task, cycle, writer, stamp, due = parts
                rows.append((task, int(cycle), writer, int(stamp) if stamp else None, int(due)))
            except ValueError:
                raise ValueError(f"{path}:{number}: expected task,cycle,writer,stamp_ns,due_ns") from None
    return rows


class SignalsCsv:
    """Collects record-queue rows per task and writes signals.csv rows in time order.

    Each row is labelled with the time from which its values hold (logical execution
    time): the outputs ``y`` computed by the job released at k·P hold from (k+1)·P, the
    inputs ``u`` it read hold from k·P, and a task's initial outputs (record tick −1)
    hold from 0. Columns are named by the model's variable names where the runnable
    gives them (``plant.AnglePan``), else by index (``plant.y[0]``).

    Rows are written once every recorded stream has delivered the values up to that
    time, so the file grows during the run.
    """

    def __init__(
        self,
        path: Path,
        recorded: list[SignalRef],
        periods_ns: dict[str, int],
        n_outputs: dict[str, int],
        signal_names: dict[str, tuple[tuple[str, ...] | None, tuple[str, ...] | None]] | None = None,
    ) -> None:
        self.path = path
        self.columns: list[tuple[tuple[str, str], int]] = []  # ((task, side), index into the record row)
        names: list[str] = []
        signal_names = signal_names or {}
        for ref in recorded:
            offset = 0 if ref.side == "y" else n_outputs[ref.task]
            labels = column_names(ref, *signal_names.get(ref.task, (None, None)))
            for i, name in zip(range(ref.start, ref.stop), labels, strict=True):
                self.columns.append(((ref.task, ref.side), offset + i))
                names.append(name)
        self.names = names
        self.streams = sorted({stream for stream, _ in self.columns})
        self.periods_ns = periods_ns
        self.pending: dict[tuple[str, str], list[tuple[int, np.ndarray]]] = {s: [] for s in self.streams}
        self.delivered_ns: dict[tuple[str, str], int] = dict.fromkeys(self.streams, -1)
        self.held: dict[tuple[str, str], np.ndarray | None] = dict.fromkeys(self.streams)
        self.gap: dict[tuple[str, str], bool] = dict.fromkeys(self.streams, False)
        """Whether a stream's newest value was lost (its cells are empty until the next one)."""
        self.last_tick: dict[str, int] = {}
        self.lost_marked: dict[str, int] = {}
        self.unexplained: dict[str, int] = {}
        """Per task, rows lost after its newest row (no later row has shown the gap yet)."""
        self.rows_written = 0
        self.file: TextIO = self._open(path)

    def _open(self, path: Path) -> TextIO:
        file = open(path, "w", buffering=1 << 16)  # noqa: SIM115
        file.write(",".join(["t_s", *self.names]) + "\n")
        return file

    def switch_to(self, path: Path) -> None:
        """Go on in a new file (a recording segment); the rows still pending go there."""
        self.file.close()
        self.path, self.file = path, self._open(path)

    def add(self, task: str, ticks: np.ndarray, rows: np.ndarray, lost_so_far: int = 0) -> None:
        """Rows of ``task``'s record queue; ``lost_so_far``: rows its queue has dropped in all (gaps)."""
        if not len(ticks):
            return
        gaps = self._gaps(task, ticks, lost_so_far)
        period = self.periods_ns[task]
        for side, shift in (("y", 1), ("u", 0)):  # y of tick k holds from (k+1)·P, u from k·P
            stream = (task, side)
            if stream not in self.pending:
                continue
            times = ((ticks + shift) * period).tolist()
            entries = [(t, row) for t, row in zip(times, rows, strict=True) if t >= 0]
            if gaps:
                entries += [((tick + shift) * period, None) for tick in gaps]
                entries.sort(key=lambda entry: entry[0])
            self.pending[stream].extend(entries)
            self.delivered_ns[stream] = max(self.delivered_ns[stream], times[-1])

    def _gaps(self, task: str, ticks: np.ndarray, lost_so_far: int) -> list[int]:
        """First ticks of the gaps lost rows left (a skipped release leaves a gap too: it is no loss).

        A gap is taken for lost rows while the queue's drop count is not yet explained by the
        gaps seen: drops are counted before the rows after them arrive, so the count is known
        when the gap shows.
        """
        previous = self.last_tick.get(task, -2)  # the first row is the initial outputs' (tick -1)
        self.last_tick[task] = int(ticks[-1])
        unexplained = lost_so_far - self.lost_marked.get(task, 0)
        if unexplained <= 0:
            return []
        joined = np.concatenate(([previous], ticks))
        firsts: list[int] = []
        for index in np.flatnonzero(np.diff(joined) > 1).tolist():
            if unexplained <= 0:
                break
            missing = int(joined[index + 1] - joined[index] - 1)
            firsts.append(int(joined[index]) + 1)
            unexplained -= missing
            self.lost_marked[task] = self.lost_marked.get(task, 0) + missing
        self.unexplained[task] = max(0, unexplained)
        return firsts

    def flush(self, final: bool = False) -> tuple[list[int], list[list[float | None]]]:
        """Write every row whose time all recorded streams have reached; return those rows.

        Returns (times since T0 in ns, values) of the rows written, NaN where a signal
        has no value yet, for other recorders (run.mcap) to take the same rows.
        """
        if not self.streams:
            return [], []
        if final:  # rows lost at the very end: no later row shows their gap, so mark it here
            for task, count in self.unexplained.items():
                if count > 0 and task in self.last_tick:
                    tick = self.last_tick[task] + 1
                    for side, shift in (("y", 1), ("u", 0)):
                        if (task, side) in self.pending:
                            self.pending[(task, side)].append(((tick + shift) * self.periods_ns[task], None))
            self.unexplained.clear()
        horizon = max(self.delivered_ns.values()) if final else min(self.delivered_ns.values())
        streams = [[(t, s, row) for t, row in self.pending[s] if t <= horizon] for s in self.streams]
        for s in self.streams:
            self.pending[s] = [(t, row) for t, row in self.pending[s] if t > horizon]
        times: list[int] = []
        rows: list[list[float | None]] = []
        current_t: int | None = None
        for t_ns, stream, row in heapq.merge(*streams, key=lambda item: item[0]):
            if current_t is not None and t_ns != current_t:
                times.append(current_t)
                rows.append(self._row())
            current_t = t_ns
            if row is None:
                self.gap[stream] = True
            else:
                self.held[stream], self.gap[stream] = row, False
        if current_t is not None:
            times.append(current_t)
            rows.append(self._row())
        self.file.writelines(_csv_line(t, row) for t, row in zip(times, rows, strict=True))
        self.rows_written += len(rows)
        self.file.flush()
        return times, rows

    def _row(self) -> list[float | None]:
        """The values valid now: None where they were lost (an empty cell), NaN where none came yet."""
        nan = float("nan")
        return [None if self.gap[stream] else nan if (held := self.held[stream]) is None else float(held[index])
                for stream, index in self.columns]

    def close(self) -> None:
        """Close the file; ``flush(final=True)`` first writes what is still pending."""
        self.file.close()


def column_names(ref: SignalRef, input_names: tuple[str, ...] | None,
                 output_names: tuple[str, ...] | None) -> list[str]:
    """``task.Name`` for each element of ``ref`` where the model names it uniquely, else ``task.y[i]``."""
    names = output_names if ref.side == "y" else input_names
    other = input_names if ref.side == "y" else output_names
    index_form = ref.names()
    if not names:
        return index_form
    taken = set(other or ())
    out = []
    for i, fallback in zip(range(ref.start, ref.stop), index_form, strict=True):
        name = names[i] if i < len(names) else ""
        usable = name and name not in taken and list(names).count(name) == 1
        out.append(f"{ref.task}.{name}" if usable else fallback)
    return out


def _csv_line(t_ns: int, row: list[float | None]) -> str:
    # NaN as nan, ±inf as inf/-inf, a lost value as an empty cell
    cells = [repr(t_ns / 1e9)] + ["" if value is None else repr(value) for value in row]
    return ",".join(cells) + "\n"
