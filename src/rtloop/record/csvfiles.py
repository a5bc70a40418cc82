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

import itertools
from pathlib import Path
from typing import TextIO

import numpy as np

from rtloop.app.specs import SentName, SignalRef
from rtloop.ipc.schema import NO_STAMP  # a read that found no sample at all
from rtloop.seconds import seconds_text


class AppendOnlyCsv:
    """A CSV file written in order and never rewritten: a header, then rows appended as they come,
    flushed at every drain (a crash loses at most the last drain interval), and, for a ``--keep``
    run's window, continued in a new segment file that starts with the header again. Every file of
    a run's recording is one (each says its header and how it formats its rows)."""

    BUFFER_BYTES = 1 << 14

    def __init__(self, path: Path) -> None:
        self.path = path
        self.file: TextIO = self._open(path)

    def header(self) -> str:
        """The first line of every segment."""
        raise NotImplementedError

    def _open(self, path: Path) -> TextIO:
        file = open(path, "w", buffering=self.BUFFER_BYTES)  # noqa: SIM115 (open for the recording's life)
        file.write(self.header())
        return file

    def switch_to(self, path: Path) -> None:
        """Go on in a new file (a recording segment), which starts with the header."""
        self.file.close()
        self.path, self.file = path, self._open(path)

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()


class TimingCsv(AppendOnlyCsv):
    HEADER = "task,cycle,release_ns,start_ns,end_ns\n"

    BUFFER_BYTES = 1 << 16

    def header(self) -> str:
        return self.HEADER

    def append(self, task: str, records: np.ndarray) -> None:
        if len(records):  # one % formatting call per block: the text is built in C
            line = task.replace("%", "%%") + ",%d,%d,%d,%d\n"
            self.file.write((line * len(records)) % tuple(records.ravel().tolist()))


class InputsCsv(AppendOnlyCsv):
    """``inputs.csv``: what entered the run from outside, and the cycle that took it.

    ``task,cycle,port,values`` — one row each time a task took a new value from a live
    input port (CLI, Python client, ROS 2 bridge); ``values`` are the port's values,
    space-separated with full precision. ``rtloop replay`` feeds them back at the same
    cycles.
    """

    HEADER = "task,cycle,port,values\n"

    def header(self) -> str:
        return self.HEADER

    def append(self, task: str, period_ns: int, ports: list[tuple[str, int]], ticks: np.ndarray,
               rows: np.ndarray) -> None:
        """``ports[i]`` = (name, size) of the task's input port i; ``ticks`` are ns since T0."""
        for since_t0_ns, row in zip(ticks.tolist(), rows.tolist(), strict=True):
            name, size = ports[int(row[0])]
            values = " ".join(repr(v) for v in row[1 : 1 + size])
            self.file.write(f"{task},{since_t0_ns // period_ns},{name},{values}\n")


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


class ReadsCsv(AppendOnlyCsv):
    """``reads.csv``: each read of a connection that did not get the sample LET promised.

    ``task,cycle,writer,stamp_ns,due_ns`` — at ``cycle`` the task read ``writer``'s sample
    published with ``stamp_ns`` (ns since T0; empty: none at all, its inputs kept their
    values) instead of the one due at ``due_ns`` (a stale read: the writer was late). A
    clean cycle writes nothing; ``rtloop replay`` makes the task read the same samples.
    """

    HEADER = "task,cycle,writer,stamp_ns,due_ns\n"

    def header(self) -> str:
        return self.HEADER

    def append(self, task: str, period_ns: int, writers: list[str], records: np.ndarray) -> None:
        """``records``: rows of ``[release, writer index, stamp got or NO_STAMP, stamp due]`` (ns since T0)."""
        lines = []
        for release_ns, writer, stamp_ns, due_ns in records.tolist():
            stamp = "" if stamp_ns == NO_STAMP else str(stamp_ns)
            lines.append(f"{task},{release_ns // period_ns},{writers[writer]},{stamp},{due_ns}\n")
        self.file.writelines(lines)


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


MAX_PENDING_VALUES = 1 << 23
"""Values signals.csv holds back at most (64 MiB of float64): past it, a task's record queue is not
drained (:meth:`SignalsCsv.room`), so its rows wait in shared memory and what overflows there is
counted lost and shows as a gap, never as memory that grows with the run."""


class SignalsCsv(AppendOnlyCsv):
    """Collects record-queue rows per task and writes signals.csv rows in time order.

    Each row is labelled with the time from which its values hold (logical execution
    time): the outputs ``y`` computed by the job released at k·P hold from (k+1)·P, the
    inputs ``u`` it read hold from k·P, and a task's initial outputs (record tick −1)
    hold from 0. Columns are named by the model's variable names where the runnable
    gives them (``plant.AnglePan``), else by index (``plant.y[0]``).

    Rows are written once every recorded stream's values are known up to that time (a
    stream's next row comes a period after its newest at the earliest), so the file grows
    during the run and a slow task holds back only the rows of its cycle in progress. The
    work is done on numpy blocks: the union
    of the streams' times, then for each stream the index of its value valid at each
    time (``searchsorted``), and one ``%`` formatting call per block for the text
    (``%r``: the shortest text that reads back as the same float).

    Lost rows (a record queue that was full) are gaps: from the first lost row's time on,
    the stream's cells are empty until its next recorded row.
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
        # Per stream: which record-row elements it takes, and where they go in a signals.csv row.
        self.takes = {s: np.array([i for st, i in self.columns if st == s], dtype=np.intp) for s in self.streams}
        self.places = {s: np.array([c for c, (st, _) in enumerate(self.columns) if st == s], dtype=np.intp)
                       for s in self.streams}
        self.periods_ns = periods_ns
        self.pending: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {
            s: [] for s in self.streams}
        """Per stream, blocks of (times ns, values, lost?) not written yet, in time order."""
        self.known_through_ns: dict[tuple[str, str], int] = dict.fromkeys(self.streams, -1)
        """Per stream, the time up to which its values are known: a stream's next row comes one period
        after its newest at the earliest, so a slow task holds back only the rows of its own cycle in
        progress, never a whole period's worth of a fast one's (a 1-hour task beside a 1 kHz one held
        3.6 M rows when the rows waited for the slow task's next row)."""
        self.held = {s: np.full(len(self.takes[s]), np.nan) for s in self.streams}
        """Per stream, the values valid at the last row written (NaN: none yet)."""
        self.gap: dict[tuple[str, str], bool] = dict.fromkeys(self.streams, False)
        """Whether a stream's newest value was lost (its cells are empty until the next one)."""
        self.last_tick: dict[str, int] = {}
        self.lost_marked: dict[str, int] = {}
        self.unexplained: dict[str, int] = {}
        """Per task, rows lost after its newest row (no later row has shown the gap yet)."""
        self.rows_written = 0
        super().__init__(path)

    BUFFER_BYTES = 1 << 16

    def header(self) -> str:
        return ",".join(["t_s", *self.names]) + "\n"

    # switch_to: the rows still pending go to the new segment

    def add(self, task: str, ticks: np.ndarray, rows: np.ndarray, lost_so_far: int = 0) -> None:
        """Rows of ``task``'s record queue; ``lost_so_far``: rows its queue has dropped in all (gaps)."""
        if not len(ticks):
            return
        ticks = np.asarray(ticks, dtype=np.int64)
        gaps = np.array(self._gaps(task, ticks, lost_so_far), dtype=np.int64)
        period = self.periods_ns[task]
        for side, shift in (("y", 1), ("u", 0)):  # y of tick k holds from (k+1)·P, u from k·P
            stream = (task, side)
            if stream not in self.pending:
                continue
            times = (ticks + shift) * period
            kept = times >= 0
            block_times, values = times[kept], rows[kept][:, self.takes[stream]]
            lost = np.zeros(len(block_times), dtype=bool)
            if gaps.size:
                block_times = np.concatenate((block_times, (gaps + shift) * period))
                values = np.concatenate((values, np.full((gaps.size, values.shape[1]), np.nan)))
                lost = np.concatenate((lost, np.ones(gaps.size, dtype=bool)))
                order = np.argsort(block_times, kind="stable")
                block_times, values, lost = block_times[order], values[order], lost[order]
            if block_times.size:
                self.pending[stream].append((block_times, values, lost))
            self.known_through_ns[stream] = max(self.known_through_ns[stream], int(times[-1]) + period - 1)

    def room(self, task: str) -> int:
        """How many more rows of ``task`` may be held back now. Each recorded task has an equal share of
        :data:`MAX_PENDING_VALUES`, so the task the others wait for always has room for its rows."""
        own = [stream for stream in self.streams if stream[0] == task]
        width = sum(len(self.takes[stream]) for stream in own)
        if not width:
            return MAX_PENDING_VALUES  # nothing of it is recorded: its rows are not kept
        share = MAX_PENDING_VALUES // len({stream[0] for stream in self.streams})
        held = sum(block[1].size for stream in own for block in self.pending[stream])
        return max(0, (share - held) // width)

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

    def lost_after_newest(self, task: str, count: int) -> None:
        """``count`` rows of ``task`` after its newest one are lost for good (the run ended without
        them): the final flush marks the gap from the tick after the newest row."""
        self.unexplained[task] = self.unexplained.get(task, 0) + count

    def flush(self, final: bool = False) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[override]  # writes the rows every stream reached, then the file; returns them for run.mcap
        """Write every row whose time all recorded streams have reached; return those rows.

        Returns (times since T0 in ns, values) of the rows written, NaN where a signal
        has no value yet or was lost, for other recorders (run.mcap) to take the same rows.
        """
        empty = np.empty(0, dtype=np.int64), np.empty((0, len(self.columns)))
        if not self.streams:
            return empty
        if final:  # rows lost at the very end: no later row shows their gap, so mark it here
            for task, count in self.unexplained.items():
                if count > 0 and task in self.last_tick:
                    tick = self.last_tick[task] + 1
                    for side, shift in (("y", 1), ("u", 0)):
                        stream = (task, side)
                        if stream in self.pending:
                            width = len(self.takes[stream])
                            self.pending[stream].append((np.array([(tick + shift) * self.periods_ns[task]]),
                                                         np.full((1, width), np.nan), np.ones(1, dtype=bool)))
            self.unexplained.clear()
        # at the end everything pending is written, the marks of rows lost at the very end included
        horizon = np.iinfo(np.int64).max if final else min(self.known_through_ns.values())
        ready: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for stream in self.streams:
            blocks = self.pending[stream]
            if not blocks:
                continue
            times = np.concatenate([b[0] for b in blocks]) if len(blocks) > 1 else blocks[0][0]
            values = np.concatenate([b[1] for b in blocks]) if len(blocks) > 1 else blocks[0][1]
            lost = np.concatenate([b[2] for b in blocks]) if len(blocks) > 1 else blocks[0][2]
            cut = int(np.searchsorted(times, horizon, side="right"))
            ready[stream] = times[:cut], values[:cut], lost[:cut]
            self.pending[stream] = [(times[cut:], values[cut:], lost[cut:])] if cut < times.size else []
        if not ready:
            return empty
        union = np.unique(np.concatenate([r[0] for r in ready.values()]))
        if not union.size:
            return empty
        table = np.empty((union.size, len(self.columns)))
        lost_cells = np.zeros((union.size, len(self.columns)), dtype=bool)
        for stream in self.streams:
            places = self.places[stream]
            if stream not in ready or not ready[stream][0].size:
                table[:, places] = self.held[stream]
                lost_cells[:, places] = self.gap[stream]
                continue
            times, values, lost = ready[stream]
            index = np.searchsorted(times, union, side="right") - 1
            before = index < 0  # rows before this stream's first new value hold its previous one
            taken = np.maximum(index, 0)
            table[:, places] = np.where(before[:, None], self.held[stream], values[taken])
            lost_cells[:, places] = np.where(before, self.gap[stream], lost[taken])[:, None]
            self.gap[stream] = bool(lost[-1])
            if not lost[-1]:
                self.held[stream] = values[-1]
        self.file.write(_csv_block(union, table, lost_cells))
        self.rows_written += int(union.size)
        self.file.flush()
        table[lost_cells] = np.nan
        return union, table

    def close(self) -> None:
        """Close the file; ``flush(final=True)`` first writes what is still pending."""
        super().close()


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
        if isinstance(name, SentName):  # what a device of the task was sent: named after the device
            out.append(str(name))
            continue
        usable = name and name not in taken and list(names).count(name) == 1
        out.append(f"{ref.task}.{name}" if usable else fallback)
    return out


def _csv_block(t_ns: np.ndarray, table: np.ndarray, lost_cells: np.ndarray) -> str:
    """signals.csv lines: ``t_s`` exactly (:func:`rtloop.seconds.seconds_text`: it reads back to the
    nanosecond), then ``repr`` of every value (NaN as nan, ±inf as inf/-inf), a lost value as an empty cell.

    One ``%`` formatting call for the rows without a lost cell: Python's ``%r`` of a float
    is its ``repr``, the shortest text that reads back as the same float.
    """
    width = table.shape[1]
    times = [seconds_text(t) for t in t_ns.tolist()]
    if not lost_cells.any():
        line = ",".join(["%s", *["%r"] * width]) + "\n"
        cells = itertools.chain.from_iterable((t, *row) for t, row in zip(times, table.tolist(), strict=True))
        return (line * len(times)) % tuple(cells)
    lines = []
    for t, row, lost in zip(times, table.tolist(), lost_cells.tolist(), strict=True):
        lines.append(",".join([t] + ["" if gone else repr(v) for v, gone in zip(row, lost, strict=True)]) + "\n")
    return "".join(lines)
